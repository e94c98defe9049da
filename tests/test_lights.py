import json
import math

import pytest
import torch

from psmini import (
    CalibrationError,
    DataFormatError,
    DirectionalLights,
    InputError,
    LEDLights,
    LightModel,
    PointLights,
    ShapeError,
    check_spans_3d,
    lights_from_dict,
    lights_to_dict,
    ring_lights,
)
from tests.conftest import BaseTester


class TestRingLights(BaseTester):
    def test_zenith_and_azimuth(self, device, dtype):
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        self.assert_close(lights.norm(dim=-1), torch.ones(8, device=device, dtype=dtype))
        zenith = torch.rad2deg(torch.acos(lights[:, 2]))
        self.assert_close(zenith, torch.full_like(zenith, 55.0), rtol=1e-4, atol=1e-3)
        azimuth = torch.rad2deg(torch.atan2(lights[:, 1], lights[:, 0])) % 360
        self.assert_close(azimuth, torch.arange(8, device=device, dtype=dtype) * 45.0, rtol=1e-4, atol=1e-3)

    def test_count_zero_raises(self):
        with pytest.raises(CalibrationError, match="at least one"):
            ring_lights(0, 55.0)


class TestSpans3d:
    def test_two_lights_raise(self):
        with pytest.raises(CalibrationError, match="at least 3 lights.*got 2"):
            check_spans_3d(ring_lights(2, 45.0))

    def test_coplanar_raise(self):
        with pytest.raises(CalibrationError, match="coplanar"):
            check_spans_3d(ring_lights(6, 90.0))

    def test_nan_raise(self):
        lights = ring_lights(4, 45.0)
        lights[1, 0] = float("nan")
        with pytest.raises(Exception, match="finite"):
            check_spans_3d(lights)

    def test_bad_shape_raise(self):
        with pytest.raises(ShapeError, match=r"\(K, 3\)"):
            check_spans_3d(torch.rand(4, 2))


class TestPointAndLED(BaseTester):
    def test_point_inverse_square(self, device, dtype):
        lights = PointLights(
            torch.tensor([[0.0, 0.0, 10.0]], device=device, dtype=dtype),
            torch.tensor([2.0], device=device, dtype=dtype),
        )
        points = torch.zeros(1, 3, 1, 2, device=device, dtype=dtype)
        points[0, 0, 0, 1] = 10.0  # second point at x = 10 mm
        dirs, irradiance = lights(points)
        self.assert_close(irradiance[0, 0, 0, 0, 0], torch.tensor(2.0 / 100, device=device, dtype=dtype))
        self.assert_close(irradiance[0, 0, 0, 0, 1], torch.tensor(2.0 / 200, device=device, dtype=dtype))
        expected = torch.tensor([-1.0, 0.0, 1.0], device=device, dtype=dtype) / math.sqrt(2)
        self.assert_close(dirs[0, 0, :, 0, 1], expected)

    def test_led_cosine_power(self, device, dtype):
        position = torch.tensor([[0.0, 0.0, 10.0]], device=device, dtype=dtype)
        down = torch.tensor([[0.0, 0.0, -1.0]], device=device, dtype=dtype)
        leds = LEDLights(
            position,
            down,
            torch.tensor([1.0], device=device, dtype=dtype),
            torch.tensor([3.0], device=device, dtype=dtype),
        )
        points = torch.zeros(1, 3, 1, 1, device=device, dtype=dtype)
        points[0, 0] = 10.0
        _, irradiance = leds(points)
        cosine = 1 / math.sqrt(2)
        self.assert_close(irradiance[0, 0, 0, 0, 0], torch.tensor(cosine**3 / 200, device=device, dtype=dtype))

    def test_led_behind_is_dark(self):
        leds = LEDLights(torch.tensor([[0.0, 0.0, 10.0]]), torch.tensor([[0.0, 0.0, 1.0]]))
        _, irradiance = leds(torch.zeros(1, 3, 1, 1))
        assert float(irradiance) < 1e-30

    def test_mismatched_counts_raise(self):
        with pytest.raises(ShapeError, match="same lights"):
            PointLights(torch.rand(3, 3), torch.ones(2))
        with pytest.raises(ShapeError, match="same lights"):
            LEDLights(torch.rand(3, 3), torch.rand(2, 3))

    def test_negative_mu_raise(self):
        with pytest.raises(CalibrationError, match="mu"):
            LEDLights(torch.rand(3, 3), -torch.ones(3, 3).abs(), mu=torch.tensor([1.0, -1.0, 1.0]))

    def test_gradcheck(self):
        positions = (
            torch.rand(3, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)
        ).requires_grad_()
        points = torch.rand(1, 3, 2, 2, dtype=torch.float64, requires_grad=True)
        down = torch.tensor([[0.0, 0.1, -1.0]], dtype=torch.float64).expand(3, 3)

        def irradiance(pos, pts):
            dirs, irr = LEDLights(pos, down, mu=torch.full((3,), 1.5, dtype=torch.float64), learnable=False)(pts)
            return dirs, irr

        self.gradcheck(irradiance, (positions, points))

    def test_learnable_parameters(self):
        leds = LEDLights(torch.rand(3, 3), torch.rand(3, 3) - torch.tensor([0, 0, 2.0]), learnable=True)
        names = {name for name, _ in leds.named_parameters()}
        assert names == {"positions_mm", "intensities", "principal_directions", "mu"}


class TestDirectional(BaseTester):
    def test_forward_broadcasts(self, device, dtype):
        lights = DirectionalLights(
            ring_lights(8, 55.0, device=device, dtype=dtype), torch.linspace(1, 2, 8, device=device, dtype=dtype)
        )
        dirs, irradiance = lights(torch.zeros(2, 3, 4, 5, device=device, dtype=dtype))
        assert dirs.shape == (2, 8, 3, 4, 5) and irradiance.shape == (2, 8, 1, 4, 5)
        self.assert_close(irradiance[1, :, 0, 3, 4], torch.linspace(1, 2, 8, device=device, dtype=dtype))
        self.assert_close(lights.scaled_directions().norm(dim=-1), torch.linspace(1, 2, 8, device=device, dtype=dtype))

    def test_zero_direction_raise(self):
        with pytest.raises(CalibrationError, match="non-zero"):
            DirectionalLights(torch.zeros(3, 3))

    def test_bad_points_raise(self):
        with pytest.raises(ShapeError, match="points"):
            DirectionalLights(ring_lights(4, 45.0))(torch.zeros(1, 2, 4, 4))


class TestLightModel:
    """The one light-model type: what the pipeline asks (count, is_near) and the JSON form."""

    def models(self):
        ring = ring_lights(8, 58.0, dtype=torch.float64)
        return [
            DirectionalLights(ring, torch.linspace(0.8, 1.2, 8, dtype=torch.float64)),
            PointLights(ring * 18.6, torch.linspace(0.8, 1.2, 8, dtype=torch.float64)),
            LEDLights(ring * 18.6, -ring, torch.linspace(0.8, 1.2, 8, dtype=torch.float64),
                      torch.linspace(0.5, 2.0, 8, dtype=torch.float64)),
        ]

    def test_kinds_and_nearness(self):
        kinds = [(m.kind, m.is_near, m.count) for m in self.models()]
        assert kinds == [("directional", False, 8), ("point", True, 8), ("led", True, 8)]
        assert all(isinstance(m, LightModel) for m in self.models())

    def test_json_round_trip_renders_the_same(self):
        points = torch.randn(1, 3, 4, 5, dtype=torch.float64) * 2 - torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1)
        for model in self.models():
            back = lights_from_dict(json.loads(json.dumps(lights_to_dict(model))), dtype=torch.float64)
            assert type(back) is type(model)
            for got, want in zip(back(points), model(points), strict=True):
                torch.testing.assert_close(got, want)

    def test_bad_json_raises(self):
        with pytest.raises(DataFormatError, match="must be one of"):
            lights_from_dict({"model": "laser", "directions": [[0, 0, 1]]})
        with pytest.raises(DataFormatError, match="lacks 'principal_directions'"):
            lights_from_dict({"model": "led", "positions_mm": [[0, 0, 10]] * 3})
        # a model name that is not a string (a JSON list or object) is refused as unknown, not by a TypeError of
        # the lookup in the kinds' dict (unhashable)
        for model in (["led"], {"kind": "led"}):
            with pytest.raises(DataFormatError, match="must be one of"):
                lights_from_dict({"model": model, "positions_mm": [[0, 0, 10]] * 3})
        with pytest.raises(InputError, match="got Linear"):
            lights_to_dict(torch.nn.Linear(2, 2))
