import json
import math
import os
import subprocess
import sys
import textwrap
from importlib.metadata import EntryPoint, EntryPoints
from pathlib import Path

import numpy as np
import pytest
import torch

from psmini import (
    CalibrationError,
    DataFormatError,
    DirectionalLights,
    InputError,
    LEDLights,
    LightField,
    LightModel,
    PointLights,
    ShapeError,
    as_batched_lights,
    check_spans_3d,
    light_model_class,
    lights_from_dict,
    lights_to_dict,
    ring_lights,
)
from psmini.lights import LIGHT_MODELS_GROUP
from tests.conftest import BaseTester
from tests.user_light_models import GaussianBeamLEDs, TabulatedBeamLEDs

REPO = Path(__file__).resolve().parents[1]


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

    def test_count_and_angles_raise(self):
        # 2.5 lights silently made 3 at the wrong spacing; a NaN zenith, NaN directions
        with pytest.raises(InputError, match="count must be an integer .* got 2.5"):
            ring_lights(2.5, 55.0)
        with pytest.raises(InputError, match="count must be an integer .* got tensor\\(4.\\)"):
            ring_lights(torch.tensor(4.0), 55.0)  # a float tensor failed as a bare TypeError of operator.index
        with pytest.raises(InputError, match="zenith_deg must be a finite number .* got nan"):
            ring_lights(8, float("nan"))
        with pytest.raises(InputError, match="azimuth_offset_deg must be a finite number .* got None"):
            ring_lights(8, 55.0, None)
        assert ring_lights(np.int64(4), np.float32(55.0)).shape == (4, 3)


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


class TestAsBatchedLights(BaseTester):
    def test_gradcheck(self):
        lights = ring_lights(4, 45.0, dtype=torch.float64).requires_grad_()
        reference = torch.zeros(1, dtype=torch.float64)
        self.gradcheck(lambda lit: as_batched_lights(lit, 2, reference), (lights,))
        batched = torch.rand(2, 4, 3, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda lit: as_batched_lights(lit, 2, reference), (batched,))


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

    def test_gradcheck_point_lights(self):
        positions = (ring_lights(3, 50.0, dtype=torch.float64) * 10).requires_grad_()
        intensities = torch.tensor([1.0, 1.5, 2.0], dtype=torch.float64, requires_grad=True)
        points = torch.rand(1, 3, 2, 2, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda pos, i, pts: PointLights(pos, i)(pts), (positions, intensities, points))

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

    def test_gradcheck(self):
        directions = (ring_lights(4, 45.0, dtype=torch.float64) * 1.5).requires_grad_()  # normalised on the way
        intensities = torch.linspace(0.5, 2.0, 4, dtype=torch.float64).requires_grad_()
        points = torch.rand(1, 3, 2, 2, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda d, i, pts: DirectionalLights(d, i)(pts), (directions, intensities, points))
        self.gradcheck(lambda d, i: DirectionalLights(d, i).scaled_directions(), (directions, intensities))


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

    def test_builtin_json_is_unchanged(self):
        """Lights files and manifests written before the fields became public read and write the same."""
        ring = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [-1.0, 0.0, 1.0]], dtype=torch.float64)
        led = LEDLights(ring * 10, -ring, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64),
                        torch.tensor([0.5, 1.0, 1.5], dtype=torch.float64))
        data = lights_to_dict(led)
        assert list(data) == ["model", "positions_mm", "principal_directions", "intensities", "mu"]
        assert data["model"] == "led" and data["positions_mm"][0] == [10.0, 0.0, 10.0]
        assert data["principal_directions"][0] == pytest.approx([-1 / math.sqrt(2), 0.0, -1 / math.sqrt(2)])
        assert data["intensities"] == [1.0, 2.0, 3.0] and data["mu"] == [0.5, 1.0, 1.5]
        assert list(lights_to_dict(PointLights(ring))) == ["model", "positions_mm", "intensities"]
        assert list(lights_to_dict(DirectionalLights(ring))) == ["model", "directions", "intensities"]
        assert {k: v.describe() for k, v in LEDLights.fields.items()} == {
            "positions_mm": "(K, 3)", "principal_directions": "(K, 3)", "intensities": "(K,)", "mu": "(K,)"}

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


# ------------------------------------------------------------------------------------------------ user models


def _leds() -> LEDLights:
    ring = ring_lights(8, 58.0, dtype=torch.float64)
    return LEDLights(ring * 18.6, -ring, torch.linspace(0.8, 1.2, 8, dtype=torch.float64),
                     torch.full((8,), 1.0, dtype=torch.float64))


def _points(dtype=torch.float64, device="cpu") -> torch.Tensor:
    gen = torch.Generator().manual_seed(4)
    xy = torch.rand(2, 2, 3, 4, generator=gen, dtype=torch.float64) * 10 - 5
    return torch.cat([xy, torch.rand(2, 1, 3, 4, generator=gen, dtype=torch.float64)], 1).to(device, dtype)


class TestUserModels(BaseTester):
    """A tabulated radial beam and a Gaussian-beam subclass of LEDLights, written outside psmini."""

    def test_tabulated_beam_interpolates_its_table(self):
        position = torch.tensor([[0.0, 0.0, 10.0]], dtype=torch.float64)
        axis = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        beam = torch.tensor([[2.0, 1.5, 0.5, 0.25]], dtype=torch.float64)  # at 0, 10, 20, 30 degrees
        model = TabulatedBeamLEDs(position, axis, torch.tensor([10.0], dtype=torch.float64), beam)
        angles = torch.tensor([0.0, 10.0, 15.0, 27.0, 35.0], dtype=torch.float64)
        x = 10 * torch.deg2rad(angles).tan()  # points on the card, these angles off the LED's axis
        points = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)])[None, :, None, :]
        directions, irradiance = model(points)
        r2 = 100 + x.square()
        expected = torch.tensor([2.0, 1.5, 1.0, 0.5 - 0.7 * 0.25, 0.0], dtype=torch.float64) / r2
        self.assert_close(irradiance[0, 0, 0, 0], expected)
        self.assert_close(directions[0, 0, :, 0], torch.stack([-x, torch.zeros_like(x), torch.full_like(x, 10.0)])
                          / r2.sqrt())

    def test_tabulated_table_of_an_led_is_the_led(self):
        leds = _leds()
        model = TabulatedBeamLEDs.from_leds(leds, samples=1201, step_deg=0.05)  # linear between 0.05° samples
        points = _points()
        for got, want in zip(model(points), leds(points), strict=True):
            torch.testing.assert_close(got, want, rtol=1e-6, atol=0)

    def test_gaussian_beam_formula(self):
        position = torch.tensor([[3.0, -2.0, 9.0]], dtype=torch.float64)
        axis = torch.tensor([[-0.2, 0.1, -1.0]], dtype=torch.float64)
        model = GaussianBeamLEDs(position, axis, torch.tensor([2.5], dtype=torch.float64),
                                 torch.tensor([0.4], dtype=torch.float64))
        point = torch.tensor([0.4, 0.3, 0.5], dtype=torch.float64)
        v = position[0] - point
        r = float(v.norm())
        cosine = float(-(axis[0] / axis[0].norm()) @ v) / r
        _, irradiance = model(point.view(1, 3, 1, 1))
        assert float(irradiance) == pytest.approx(2.5 * math.exp(-(1 - cosine) / 0.16) / r**2, rel=1e-12)

    def test_devices_and_dtypes(self, device, dtype):
        """float64 parameters on the CPU, points of any dtype on any device: results follow the points."""
        for model in (TabulatedBeamLEDs.from_leds(_leds()), GaussianBeamLEDs(_leds().positions_mm,
                                                                          _leds().principal_directions)):
            directions, irradiance = model(_points(dtype, device))
            assert directions.dtype == irradiance.dtype == dtype and directions.device.type == device.type
            assert directions.shape == (2, 8, 3, 3, 4) and irradiance.shape == (2, 8, 1, 3, 4)
            self.assert_close(directions.square().sum(2), torch.ones_like(irradiance[:, :, 0]))

    def test_gradcheck_tabulated(self):
        start = TabulatedBeamLEDs.from_leds(_leds(), samples=13, step_deg=2.5)
        points = _points()[:1, :, :2, :2].clone().requires_grad_()

        def forward(positions, axes, beam, pts):
            return TabulatedBeamLEDs(positions, axes, start.step_deg, beam)(pts)

        inputs = (start.positions_mm, start.principal_directions + 0.01, start.beam * 1.1)
        self.gradcheck(forward, (*(t.clone().requires_grad_() for t in inputs), points))

    def test_gradcheck_gaussian(self):
        leds = _leds()
        points = _points()[:1, :, :2, :2].clone().requires_grad_()

        def forward(positions, axes, intensities, width, pts):
            return GaussianBeamLEDs(positions, axes, intensities, width)(pts)

        inputs = (leds.positions_mm, leds.principal_directions, leds.intensities, torch.full((8,), 0.5,
                                                                                             dtype=torch.float64))
        self.gradcheck(forward, (*(t.clone().requires_grad_() for t in inputs), points))

    def test_json_round_trip_in_process(self):
        models = [TabulatedBeamLEDs.from_leds(_leds()),
                  GaussianBeamLEDs(_leds().positions_mm, _leds().principal_directions, None,
                                   torch.linspace(0.3, 0.6, 8, dtype=torch.float64))]
        for model in models:
            data = json.loads(json.dumps(lights_to_dict(model)))
            back = lights_from_dict(data, dtype=torch.float64)
            assert type(back) is type(model) and back.count == 8
            for got, want in zip(back(_points()), model(_points()), strict=True):
                torch.testing.assert_close(got, want)
        assert models[0].kind == "tests.user_light_models:TabulatedBeamLEDs"  # no kind: the import path
        assert lights_to_dict(models[1])["model"] == "gaussian_beam_leds" and "mu" not in lights_to_dict(models[1])
        assert len(lights_to_dict(models[0])["beam"][0]) == 13  # the (K, N) table, N = 13

    def test_from_dict_on_a_subclass(self):
        data = lights_to_dict(_leds())
        assert type(LEDLights.from_dict(data)) is LEDLights and type(PointLights.from_dict(data)) is LEDLights
        with pytest.raises(DataFormatError, match="is a DirectionalLights, not a LEDLights"):
            LEDLights.from_dict({"model": "directional", "directions": [[0, 0, 1]] * 3})

    def test_table_of_the_wrong_shape(self):
        good = lights_to_dict(TabulatedBeamLEDs.from_leds(_leds()))
        for beam, message in [([1.0] * 8, r"'beam' must be a list of K rows, shape \(K, N\), got shape \(8,\)"),
                              ([[1.0, 0.5]] * 7 + [[1.0]], "must hold numbers of shape"),  # ragged
                              ([[1.0, 0.5]] * 7, "'beam' has 7 lights but 'positions_mm' has 8"),
                              ([[]] * 8, "is empty"),
                              ([["a", "b"]] * 8, "must hold numbers")]:
            with pytest.raises(DataFormatError, match=message):
                lights_from_dict({**good, "beam": beam})
        with pytest.raises(DataFormatError, match=r"'step_deg' must be a list of numbers, shape \(K,\)"):
            lights_from_dict({**good, "step_deg": [[2.5]] * 8})
        with pytest.raises(DataFormatError, match="lacks 'beam'"):
            lights_from_dict({k: v for k, v in good.items() if k != "beam"})

    def test_fields_declare_shapes(self):
        assert LightField((3,)).describe() == "(K, 3)" and LightField((None, 2)).describe() == "(K, N, 2)"
        for bad in ((0,), (-1,), ("3",), (True,), 3):
            with pytest.raises(InputError, match="shape"):
                LightField(bad)
        assert TabulatedBeamLEDs.fields["beam"] == LightField((None,))

    def test_tuple_shorthand_and_count(self):
        class Pair(LightModel):
            fields = {"positions_mm": (3,)}  # a bare shape: a required field

            def __init__(self, positions_mm):
                super().__init__()
                self.positions_mm = positions_mm

            def forward(self, points):
                return PointLights(self.positions_mm)(points)

        assert Pair.fields == {"positions_mm": LightField((3,))} and Pair(torch.ones(2, 3)).count == 2

        class NoFields(LightModel):
            def forward(self, points):
                return points, points

        with pytest.raises(InputError, match="declares no fields"):
            _ = NoFields().count

    def test_project(self):
        leds = LEDLights(torch.rand(3, 3) + torch.tensor([0, 0, 5.0]), torch.tensor([[0.0, 0.0, -2.0]] * 3),
                         learnable=True)
        with torch.no_grad():
            leds.mu.copy_(torch.tensor([-0.5, 0.5, 1.0]))
            leds.intensities.copy_(torch.tensor([-1.0, 1.0, 2.0]))
            leds.principal_directions.mul_(3)
        leds.project_()
        assert leds.mu.tolist() == [0.0, 0.5, 1.0] and float(leds.intensities.detach()[0]) > 0
        self.assert_close(leds.principal_directions.detach().norm(dim=-1), torch.ones(3))
        plain = torch.tensor([[0.0, 0.0, 2.0]] * 3)
        DirectionalLights(plain).project_()  # plain tensors (not learnable) are the caller's: left alone
        assert plain[0, 2] == 2.0


class TestKindResolution:
    """Where a "model" name is looked for: built-ins and imported classes, entry points, import paths."""

    @pytest.fixture(autouse=True)
    def _fresh_aliases(self, monkeypatch):
        monkeypatch.setattr(LightModel, "_ALIASES", {})

    def test_builtins_and_imported(self):
        assert light_model_class("led") is LEDLights
        assert light_model_class("gaussian_beam_leds") is GaussianBeamLEDs  # defined (imported) above
        assert light_model_class("tests.user_light_models:TabulatedBeamLEDs") is TabulatedBeamLEDs

    def test_entry_point(self, monkeypatch):
        points = EntryPoints([EntryPoint("tabbeam", "tests.user_light_models:TabulatedBeamLEDs", LIGHT_MODELS_GROUP)])
        monkeypatch.setattr("importlib.metadata.entry_points", lambda group=None: points if group ==
                            LIGHT_MODELS_GROUP else EntryPoints([]))
        data = {**lights_to_dict(TabulatedBeamLEDs.from_leds(_leds())), "model": "tabbeam"}
        assert type(lights_from_dict(data)) is TabulatedBeamLEDs
        assert light_model_class("tabbeam") is TabulatedBeamLEDs

    def test_entry_point_errors(self, monkeypatch):
        points = EntryPoints([EntryPoint("broken", "no_such_package_xyz.beams:Beam", LIGHT_MODELS_GROUP),
                              EntryPoint("notamodel", "collections:OrderedDict", LIGHT_MODELS_GROUP)])
        monkeypatch.setattr("importlib.metadata.entry_points", lambda group=None: points)
        with pytest.raises(DataFormatError, match="loading the entry point broken = 'no_such_package_xyz.beams:Beam' "
                                                  "of group 'psmini.light_models' failed: ModuleNotFoundError"):
            light_model_class("broken")
        with pytest.raises(DataFormatError, match="entry point notamodel .* not a subclass of psmini.lights"):
            light_model_class("notamodel")
        with pytest.raises(DataFormatError, match=r"of group 'psmini.light_models' \(broken, notamodel\)"):
            light_model_class("laser")

    def test_unknown_kind_says_where_it_looked_and_how_to_register(self):
        with pytest.raises(DataFormatError) as error:
            lights_from_dict({"model": "fresnel", "positions_mm": [[0, 0, 10]] * 3})
        message = str(error.value)
        for part in ("the built-ins ['directional', 'led', 'point']", "gaussian_beam_leds",
                     "an entry point of group 'psmini.light_models'", 'an import path "package.module:Class"',
                     "got 'fresnel'", '[project.entry-points."psmini.light_models"] name = "package.module:Class"'):
            assert part in message, (part, message)

    def test_import_path_errors(self):
        cases = [
            ("no_such_package_xyz.beams:Beam", "no module named 'no_such_package_xyz'.*PYTHONPATH"),
            ("tests.user_light_models:Nope", "module 'tests.user_light_models' has no 'Nope'"),
            ("collections:OrderedDict", "is <class 'collections.OrderedDict'>, not a subclass of psmini.lights"),
            ("tests.user_light_models:_unit", "not a subclass"),
            ("__main__:Beam", "defined in a script run as __main__.*top level of a module"),
            ("tests.user_light_models:f.<locals>.Beam", "not an import path"),
            ("tests.user_light_models:", "not an import path"),
            ("1bad.module:Beam", "not an import path"),
        ]
        for kind, message in cases:
            with pytest.raises(DataFormatError, match=message):
                light_model_class(kind)
        for kind in (None, 3, ["led"], ""):
            with pytest.raises(DataFormatError, match="must be one of"):
                light_model_class(kind)

    def test_abstract_and_constructor_errors(self, tmp_path, monkeypatch):
        (tmp_path / "odd_models.py").write_text(textwrap.dedent("""
            import torch
            from psmini.lights import LightField, LightModel

            class NoForward(LightModel):
                fields = {"positions_mm": LightField((3,))}

            class OtherArguments(LightModel):
                fields = {"positions_mm": LightField((3,))}

                def __init__(self, where):
                    super().__init__()

                def forward(self, points):
                    return points, points

            class Failing(LightModel):
                fields = {"positions_mm": LightField((3,))}

                def __init__(self, positions_mm):
                    raise RuntimeError("a bug in the user's constructor")

                def forward(self, points):
                    return points, points
        """))
        monkeypatch.syspath_prepend(str(tmp_path))
        with pytest.raises(DataFormatError, match="NoForward .* defines no forward"):
            light_model_class("odd_models:NoForward")
        with pytest.raises(DataFormatError, match=r"OtherArguments\(positions_mm=...\) failed.*as a keyword"):
            lights_from_dict({"model": "odd_models:OtherArguments", "positions_mm": [[0, 0, 1]]})
        with pytest.raises(RuntimeError, match="a bug in the user's constructor"):  # not hidden behind a format error
            lights_from_dict({"model": "odd_models:Failing", "positions_mm": [[0, 0, 1]]})
        (tmp_path / "broken_module.py").write_text("raise ValueError('half-written module')\n")
        with pytest.raises(DataFormatError, match="importing 'broken_module' failed: ValueError: half-written"):
            light_model_class("broken_module:Beam")

    def test_builtin_kind_cannot_be_taken(self):
        with pytest.raises(InputError, match="'led' is psmini's built-in LEDLights"):
            class Impostor(LEDLights):  # noqa: F841 (refused at definition)
                kind = "led"

    def test_redefinition_replaces_and_another_module_warns(self):
        source = "class Beam(GaussianBeamLEDs):\n    kind = 'twice_defined_beam'\n"
        first: dict = {"GaussianBeamLEDs": GaussianBeamLEDs, "__name__": "notebook_cell"}
        exec(source, first)
        exec(source, dict(first))  # the same cell run again: no warning
        with pytest.warns(UserWarning, match="'twice_defined_beam' of other_module:Beam replaces"):
            exec(source, {"GaussianBeamLEDs": GaussianBeamLEDs, "__name__": "other_module"})

    @pytest.mark.slow
    def test_entry_point_of_an_installed_distribution_in_a_fresh_process(self, tmp_path):
        """A package with a dist-info that registers the Gaussian beam under its kind: a fresh process reads it."""
        (tmp_path / "beams_pkg.py").write_text((REPO / "tests" / "user_light_models.py").read_text())
        dist = tmp_path / "beams_pkg-0.1.dist-info"
        dist.mkdir()
        (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: beams-pkg\nVersion: 0.1\n")
        (dist / "entry_points.txt").write_text(
            f"[{LIGHT_MODELS_GROUP}]\ngaussian_beam_leds = beams_pkg:GaussianBeamLEDs\n")
        data = lights_to_dict(GaussianBeamLEDs(_leds().positions_mm, _leds().principal_directions))
        code = ("import json, sys; from psmini.lights import lights_from_dict; "
                "m = lights_from_dict(json.loads(sys.argv[1])); print(type(m).__module__, type(m).__name__, m.count)")
        env = {**os.environ, "PYTHONPATH": str(tmp_path)}
        run = subprocess.run([sys.executable, "-c", code, json.dumps(data)], capture_output=True, text=True, env=env,
                             cwd=tmp_path, check=False)
        assert run.returncode == 0, run.stderr
        assert run.stdout.split() == ["beams_pkg", "GaussianBeamLEDs", "8"]


def test_the_guides_model(tmp_path, monkeypatch):
    """docs/guides/light-models.md's beams.py works as the guide says: it is the model of tests/user_light_models.py,
    and its JSON names it by its import path."""
    guide = (REPO / "docs" / "guides" / "light-models.md").read_text(encoding="utf-8")
    block = guide.split("<!-- beams.py -->", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    (tmp_path / "beams.py").write_text(block)
    monkeypatch.syspath_prepend(str(tmp_path))
    from beams import TabulatedBeamLEDs as GuideBeam  # noqa: I001 (written just above)

    reference = TabulatedBeamLEDs.from_leds(_leds())
    model = GuideBeam(reference.positions_mm, reference.principal_directions, reference.step_deg, reference.beam)
    for got, want in zip(model(_points()), reference(_points()), strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    data = json.loads(json.dumps(lights_to_dict(model)))
    assert data["model"] == "beams:TabulatedBeamLEDs" and set(data) == {"model", *GuideBeam.fields}
    assert type(lights_from_dict(data)) is GuideBeam
