"""LED calibration from card images: recovery on rendered cards, vignetting, error paths, gradients, MAT files, CLI."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch

from data_synth.rig import RigConfig, render_card, rig_lights
from psmini.commands._calibrate_leds import register_leds
from psmini.errors import CalibrationError, DataFormatError, InputError, ShapeError
from psmini.io import (
    lights_from_dict,
    load_rig_calibration_mat,
    read_lights_file,
    read_mat,
    write_capture,
    write_lights_file,
)
from psmini.ledcal import (
    LEDFit,
    LEDFitOptions,
    LightFitOptions,
    card_loss,
    card_shading,
    eliminate_gain,
    fit_leds,
    fit_lights,
    nominal_leds,
)
from psmini.lights import DirectionalLights, LEDLights
from tests.conftest import BaseTester, shared_data
from tests.user_light_models import GaussianBeamLEDs, TabulatedBeamLEDs

HEIGHTS = (0.0, 1.0)


def _cards(config: RigConfig) -> tuple[torch.Tensor, torch.Tensor]:
    cards = [render_card(config, height_mm=h, seed=1 + i) for i, h in enumerate(HEIGHTS)]
    return torch.stack([c.images for c in cards]), torch.stack([c.dark for c in cards])


def _perturbed_start(config: RigConfig) -> LEDLights:
    """The nominal rig with every LED moved by about 1 mm and mu 1.5 instead of 1."""
    nominal = rig_lights(config.replace(intensity_spread=0.0), dtype=torch.float64)
    offsets = torch.randn(config.led_count, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    offsets = offsets / offsets.norm(dim=-1, keepdim=True)  # 1 mm each
    return LEDLights(nominal.positions_mm + offsets, nominal.principal_directions, None,
                     torch.full((config.led_count,), 1.5, dtype=torch.float64))


def _errors(fit: LEDFit, truth: LEDLights) -> tuple[float, float, float]:
    position = float((fit.positions_mm.double() - truth.positions_mm.double()).norm(dim=-1).max())
    relative = truth.intensities.double() / truth.intensities.double().mean()
    intensity = float((fit.intensities.double() / relative - 1).abs().max())
    mu = float((fit.mu.double() - truth.mu.double()).abs().max())
    return position, intensity, mu


# Noise-free 16-bit cards covering the 10 mm field at 64x64, with 3x the default vignetting (0.45 lost at the
# corners): the gain is eliminated per pixel, so it must not bias the fit.
CLEAN = RigConfig(size=64, pixel_pitch_mm=10.0 / 64, noise=False, bit_depth=16, intensity_spread=0.1, vignetting=0.45)
# The simulator's default sensor (shot and read noise) quantised to 8 bits, full 400x400 crop.
NOISY = RigConfig(bit_depth=8, intensity_spread=0.1)


@pytest.fixture(scope="module")
def clean_fit() -> tuple[LEDFit, LEDLights]:
    images, dark = _cards(CLEAN)
    fit = fit_leds(images, HEIGHTS, CLEAN.pixel_pitch_mm, _perturbed_start(CLEAN), dark=dark, saturation_level=1.0)
    return fit, rig_lights(CLEAN, dtype=torch.float64)


class TestFitLeds(BaseTester):
    @pytest.mark.slow
    def test_recovers_noise_free_cards(self, clean_fit):
        fit, truth = clean_fit
        position, intensity, mu = _errors(fit, truth)
        assert position < 0.05
        assert intensity < 0.005
        # mu trades off against the LED's distance along a very flat valley (a change of 0.05 in mu, with the
        # positions following it, changes the cards by ~1e-5 of their level); FIELD_NOTES: mu 10 vs 1 costs 0.2°.
        assert mu < 0.05
        assert fit.residual_rms < 1e-4
        directions = fit.principal_directions.double()
        assert torch.allclose(directions.norm(dim=-1), torch.ones(8, dtype=torch.float64), atol=1e-6)
        assert float(fit.intensities.mean()) == pytest.approx(1.0, abs=1e-6)

    def test_gain_map_is_the_vignetting(self, clean_fit):
        fit, _ = clean_fit
        gain = fit.gain[0, 0]
        # the simulated lens loses `vignetting` at the corners relative to the centre
        centre = gain[gain.shape[0] // 2 - 1 : gain.shape[0] // 2 + 1, gain.shape[1] // 2 - 1 : gain.shape[1] // 2 + 1]
        corner_ratio = float(gain[0, 0] / centre.mean())
        assert corner_ratio == pytest.approx(1 - CLEAN.vignetting, abs=0.03)

    @pytest.mark.slow
    def test_recovers_cards_with_default_noise(self):
        images, dark = _cards(NOISY)
        fit = fit_leds(list(images), list(HEIGHTS), NOISY.pixel_pitch_mm, _perturbed_start(NOISY), dark=list(dark),
                       saturation_level=1.0)
        position, intensity, _ = _errors(fit, rig_lights(NOISY, dtype=torch.float64))
        assert position < 0.25  # the target
        assert intensity < 0.02
        assert fit.residual_rms_per_led.shape == (8,) and fit.residual_rms_per_height.shape == (2,)

    def test_vignetting_leaves_loss_and_gradient_at_truth(self):
        config = CLEAN.replace(size=24, pixel_pitch_mm=10.0 / 24, vignetting=0.0, exposure=0.3)  # nothing saturates
        images, dark = _cards(config)
        truth = rig_lights(config, dtype=torch.float64)
        signal = (images - dark).double()
        x = torch.linspace(-1, 1, 24, dtype=torch.float64)
        vignette = (1 - 0.6 * (x[None] ** 2 + x[:, None] ** 2) / 2) * (1 + 0.2 * x[None])  # also not symmetric
        points = torch.cat([_grid(config), torch.tensor(HEIGHTS, dtype=torch.float64)[:, None, None, None]
                            .expand(2, 1, 24, 24)], dim=1)
        shifted = truth.positions_mm + torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)
        for scale in (torch.ones_like(vignette), vignette):
            images = signal * scale / signal.mean()
            positions = truth.positions_mm.clone().requires_grad_()
            loss = card_loss(LEDLights(positions, truth.principal_directions, truth.intensities, truth.mu), images,
                             points)
            loss.backward()
            # at the truth only the 16-bit quantisation is left (relative RMS ~1e-5) ...
            assert float(loss.detach()) < 1e-9
            assert float(positions.grad.abs().max()) < 1e-7
            # ... while 0.1 mm off costs orders of magnitude more, vignetted or not
            off = card_loss(LEDLights(shifted, truth.principal_directions, truth.intensities, truth.mu), images, points)
            assert float(off) > 100 * float(loss.detach())

    def test_directional_start_places_leds_at_the_nominal_distance(self):
        images, dark = _cards(CLEAN.replace(size=16, pixel_pitch_mm=10.0 / 16))
        directions = torch.tensor([[math.cos(a), math.sin(a), 1.0] for a in torch.arange(8) * math.pi / 4])
        fit = fit_leds(images - dark, HEIGHTS, 10.0 / 16, DirectionalLights(directions),
                       options=LEDFitOptions(iterations=(0, 0), nominal_distance_mm=20.0))
        expected = directions / directions.norm(dim=-1, keepdim=True) * 20.0
        self.assert_close(fit.start.positions_mm, expected, atol=1e-5, rtol=0)
        self.assert_close(fit.start.principal_directions, -expected / 20.0, atol=1e-6, rtol=0)

    def test_to_dict_is_a_lights_file(self, clean_fit):
        fit, _ = clean_fit
        data = json.loads(json.dumps(fit.to_dict()))
        assert data["model"] == "led" and set(data["residuals"]) >= {"rms", "per_led"}
        lights = lights_from_dict(data, dtype=torch.float64)
        self.assert_close(lights.positions_mm, fit.positions_mm.double(), atol=1e-6, rtol=0)

    def test_cuda(self, cuda_device):
        images, dark = _cards(CLEAN.replace(size=16, pixel_pitch_mm=10.0 / 16))
        fit = fit_leds(
            images.to(cuda_device) - dark.to(cuda_device), HEIGHTS, 10.0 / 16, options=LEDFitOptions(iterations=(5, 5))
        )
        assert fit.positions_mm.device.type == "cuda" and fit.gain.device.type == "cuda"


def _grid(config: RigConfig) -> torch.Tensor:
    from psmini.geometry import pixel_grid_mm

    x, y = pixel_grid_mm(config.size, config.size, config.pixel_pitch_mm, dtype=torch.float64)
    return torch.stack([x, y])[None].expand(2, -1, -1, -1)


class TestErrors:
    def setup_method(self) -> None:
        self.images = torch.rand(2, 8, 8, 8) * 0.5 + 0.25

    def test_led_count_mismatch(self):
        with pytest.raises(ShapeError, match="6 lights but the card images have K=8"):
            fit_leds(self.images, HEIGHTS, 1.0, nominal_leds(6))

    def test_nan(self):
        images = self.images.clone()
        images[1, 3, 2, 2] = float("nan")
        with pytest.raises(InputError, match="finite"):
            fit_leds(images, HEIGHTS, 1.0)

    def test_no_heights(self):
        with pytest.raises(InputError, match="at least one card height"):
            fit_leds([], [], 1.0)

    def test_heights_do_not_match(self):
        with pytest.raises(ShapeError, match="one value per card height"):
            fit_leds(self.images, [0.0, 1.0, 2.0], 1.0)
        # one height in a list for several cards was stretched to all of them; a plain number still is
        with pytest.raises(ShapeError, match=r"one value per card height \(2\), got 1"):
            fit_leds(self.images, [0.0], 1.0)

    def test_black_card_image(self):
        images = self.images.clone()
        images[0, 5] = 0.01
        with pytest.raises(CalibrationError, match="LED 5 at height index 0 has no signal"):
            fit_leds(images, HEIGHTS, 1.0, dark=torch.full((1, 1, 8, 8), 0.01))

    def test_wrong_shapes_and_options(self):
        with pytest.raises(ShapeError):
            fit_leds(self.images[0], HEIGHTS, 1.0)
        with pytest.raises(ShapeError, match="dark"):
            fit_leds(self.images, HEIGHTS, 1.0, dark=torch.zeros(3, 1, 8, 8))
        with pytest.raises(InputError, match="optimizer"):
            fit_leds(self.images, HEIGHTS, 1.0, options=LEDFitOptions(optimizer="sgd"))
        with pytest.raises(CalibrationError, match="above the card plane"):
            fit_leds(self.images, HEIGHTS, 1.0, LEDLights(-nominal_leds(8).positions_mm, nominal_leds(8).positions_mm))
        with pytest.raises(InputError, match="init must be"):
            fit_leds(self.images, HEIGHTS, 1.0, init="sphere")


class TestModel(BaseTester):
    def test_card_shading_matches_the_formula(self):
        s = torch.tensor([[3.0, -2.0, 9.0]], dtype=torch.float64)
        d = torch.tensor([[-0.2, 0.1, -1.0]], dtype=torch.float64)
        leds = LEDLights(s, d, torch.tensor([2.5], dtype=torch.float64), torch.tensor([1.7], dtype=torch.float64))
        point = torch.tensor([0.4, 0.3, 0.5], dtype=torch.float64)
        v = s[0] - point
        r = float(v.norm())
        expected = 2.5 * (float(-(d[0] / d[0].norm()) @ v) / r) ** 1.7 / r**2 * (float(v[2]) / r)
        shading = card_shading(leds, point.view(1, 3, 1, 1))
        assert float(shading) == pytest.approx(expected, rel=1e-12)

    def test_eliminate_gain_is_per_pixel_least_squares(self):
        gen = torch.Generator().manual_seed(3)
        images = torch.rand(2, 4, 3, 3, generator=gen, dtype=torch.float64)
        shading = torch.rand(2, 4, 3, 3, generator=gen, dtype=torch.float64) + 0.1
        weights = (torch.rand(2, 4, 3, 3, generator=gen, dtype=torch.float64) > 0.2).double()
        residuals, gain = eliminate_gain(images, shading, weights)
        a = (shading * weights.sqrt()).permute(2, 3, 0, 1).reshape(9, 8, 1).numpy()
        b = (images * weights.sqrt()).permute(2, 3, 0, 1).reshape(9, 8).numpy()
        expected = np.array([np.linalg.lstsq(a[i], b[i], rcond=None)[0][0] for i in range(9)]).reshape(3, 3)
        np.testing.assert_allclose(gain[0, 0].numpy(), expected, rtol=1e-12)
        self.assert_close(residuals, images - gain * shading)

    def test_card_loss_misuse_raise(self):
        points = torch.zeros(1, 3, 3, 3)
        leds = nominal_leds(4)
        images = card_shading(leds, points)
        # a tensor of directions failed as a bare TypeError ('Tensor' object is not callable)
        with pytest.raises(InputError, match="lights must be a light model .* got Tensor of shape \\(4, 3\\)"):
            card_loss(leds.positions_mm, images, points)
        # weights of another size failed as a bare RuntimeError of broadcasting
        with pytest.raises(ShapeError, match="weights must have the images' shape \\(1, 4, 3, 3\\), got \\(1, 4, 2,"):
            card_loss(leds, images, points, torch.ones(1, 4, 2, 2))
        # a delta of 0 failed as a bare RuntimeError of huber_loss
        with pytest.raises(InputError, match="huber_delta must be a positive finite number, got 0.0"):
            card_loss(leds, images, points, huber_delta=0.0)
        with pytest.raises(ShapeError, match="shading must have the images' shape \\(1, 6, 3, 3\\)"):
            card_loss(leds, torch.rand(1, 6, 3, 3), points)  # 6 images for 4 lights

    def test_eliminate_gain_shape_error(self):
        with pytest.raises(ShapeError, match="shading"):
            eliminate_gain(torch.rand(1, 2, 3, 3), torch.rand(1, 3, 3, 3))

    def test_gradcheck(self):
        gen = torch.Generator().manual_seed(1)
        leds = nominal_leds(3, dtype=torch.float64)
        points = torch.cat([torch.rand(2, 2, 3, 3, generator=gen, dtype=torch.float64) * 4 - 2,
                            torch.tensor([0.0, 1.0], dtype=torch.float64).view(2, 1, 1, 1).expand(2, 1, 3, 3)], 1)
        images = card_shading(leds, points) * (1 + 0.1 * torch.rand(2, 3, 3, 3, generator=gen, dtype=torch.float64))
        images = images / images.mean()

        def loss(positions, directions, intensities, mu):
            # a small threshold puts residuals on both sides of the Huber knee
            return card_loss(LEDLights(positions, directions, intensities, mu), images, points, huber_delta=0.02)

        inputs = (leds.positions_mm + 0.3, leds.principal_directions, leds.intensities * 1.1, leds.mu * 1.2)
        self.gradcheck(loss, tuple(t.clone().requires_grad_() for t in inputs))


class TestRigCalibrationMat:
    def test_real_file(self):
        path = shared_data("near_ps_rig", "light.mat")
        leds = load_rig_calibration_mat(path)
        raw = read_mat(path)
        assert leds.count == 8
        positions, directions = leds.positions_mm.double(), leds.principal_directions.double()
        np.testing.assert_allclose(positions.numpy(), raw["S"] * [1, -1, -1], rtol=1e-6)
        assert torch.allclose(directions.norm(dim=-1), torch.ones(8, dtype=torch.float64), atol=1e-6)
        # the scene lies beyond the LEDs along the optical axis: in psmini's frame, below them (smaller z) ...
        assert bool((directions[:, 2] < 0).all())
        # ... and the beams lean toward the optical axis
        assert bool(((directions[:, :2] * -positions[:, :2]).sum(-1) > 0).all())
        # with the scene plane at 600 mm from the camera as the reference, every LED lies above it
        lifted = load_rig_calibration_mat(path, reference_depth_mm=600.0)
        assert bool((lifted.positions_mm[:, 2] > 0).all())
        gray = raw["Phi"] @ np.array([0.2989, 0.5870, 0.1140])
        np.testing.assert_allclose(leds.intensities.double().numpy(), gray, rtol=1e-6)
        np.testing.assert_allclose(leds.mu.double().numpy(), raw["mu"][:, 0])

    def test_missing_file_and_variables(self, tmp_path):
        with pytest.raises(DataFormatError, match="does not exist"):
            load_rig_calibration_mat(tmp_path / "absent.mat")
        scipy_io = pytest.importorskip("scipy.io")
        scipy_io.savemat(tmp_path / "partial.mat", {"S": np.ones((8, 3)), "Dir": np.ones((8, 3))})
        with pytest.raises(DataFormatError, match="missing"):
            load_rig_calibration_mat(tmp_path / "partial.mat")


class TestCommand:
    @staticmethod
    def _parser() -> argparse.ArgumentParser:
        parser = argparse.ArgumentParser(prog="psmini calibrate")
        register_leds(parser.add_subparsers(dest="target"))
        return parser

    @pytest.mark.slow
    def test_fits_card_captures(self, tmp_path, capsys):
        config = CLEAN.replace(size=32, pixel_pitch_mm=10.0 / 32)
        folders = []
        for index, height in enumerate(HEIGHTS):
            card = render_card(config, height_mm=height, seed=index)
            folders.append(str(write_capture(
                tmp_path / f"card{index}", card.images, card.lights, pixel_pitch_mm=config.pixel_pitch_mm,
                kind="flatfield", bit_depth=16, dark=card.dark, card_albedo=0.8,
                metadata={"card_height_mm": height})))
        out = tmp_path / "leds.json"
        args = self._parser().parse_args(["leds", *folders, "--out", str(out), "--json"])
        assert args.run(args) == 0
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert set(summary) >= {"positions_mm", "principal_directions", "intensities", "mu", "residual_rms"}
        lights_file = read_lights_file(out)
        assert len(lights_file.leds) == 8 and "residuals" in lights_file.provenance
        fitted = lights_file.lights
        truth = rig_lights(config, dtype=torch.float64)
        assert float((fitted.positions_mm.double() - truth.positions_mm).norm(dim=-1).max()) < 0.1
        np.testing.assert_allclose(summary["positions_mm"], fitted.positions_mm.numpy(), atol=1e-6)

    def test_refuses_sample_captures_and_bad_heights(self, tmp_path):
        config = CLEAN.replace(size=16, pixel_pitch_mm=10.0 / 16)
        card = render_card(config)
        folder = write_capture(tmp_path / "s", card.images, card.lights, pixel_pitch_mm=config.pixel_pitch_mm,
                               kind="sample", bit_depth=16)
        args = self._parser().parse_args(["leds", str(folder), "--out", str(tmp_path / "x.json")])
        with pytest.raises(InputError, match="flatfield"):
            args.run(args)
        args = self._parser().parse_args(["leds", str(folder), "--out", str(tmp_path / "x.json"),
                                          "--heights-mm", "0", "1"])
        with pytest.raises(InputError, match="one height per DIR"):
            args.run(args)


# ------------------------------------------------------------------------------------------------ fit_lights


def _user_cards(truth, size: int = 16) -> tuple[RigConfig, torch.Tensor, torch.Tensor]:
    """Noise-free 16-bit cards at 0 and 1 mm rendered with ``truth`` (any light model) in place of the rig's LEDs, at
    a size the fit takes without pooling (a model evaluated at a block's centre is not the block's mean: 0.6 mm blocks
    move the fitted LEDs by ~0.05 mm)."""
    config = CLEAN.replace(size=size, pixel_pitch_mm=10.0 / size)
    cards = [render_card(config, 0.8, seed=1 + i, height_mm=h, lights=truth) for i, h in enumerate(HEIGHTS)]
    return config, torch.stack([c.images for c in cards]), torch.stack([c.dark for c in cards])


def _offsets(scale: float) -> torch.Tensor:
    offsets = torch.randn(8, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return offsets / offsets.norm(dim=-1, keepdim=True) * scale


class TestFitLights(BaseTester):
    def test_recovers_a_tabulated_beam(self):
        truth = TabulatedBeamLEDs.from_leds(rig_lights(CLEAN, dtype=torch.float64))
        angles = torch.arange(13, dtype=torch.float64) * 2.5
        truth.beam = truth.beam * (1 - 0.2 * (angles / 20) ** 2)  # narrower than the LEDs' cos beam
        config, images, dark = _user_cards(truth)
        start = TabulatedBeamLEDs.from_leds(rig_lights(CLEAN.replace(intensity_spread=0.0), dtype=torch.float64),
                                            learnable=True)
        with torch.no_grad():
            start.positions_mm.add_(_offsets(0.5))
        fit = fit_lights(start, images, HEIGHTS, config.pixel_pitch_mm, card_albedo=0.8, dark=dark,
                         saturation_level=1.0, options=LightFitOptions(parameters=("positions_mm", "beam")))
        assert isinstance(fit.lights, TabulatedBeamLEDs) and fit.parameters == ("positions_mm", "beam")
        position = (fit.lights.positions_mm.detach() - truth.positions_mm).norm(dim=-1)
        assert float(position.max()) < 0.01
        # the cards see the beams out to ~16° off axis: the samples at 0-15° come back, up to the common scale
        ratio = (fit.lights.beam.detach() / truth.beam)[:, :7]
        assert float((ratio / ratio.mean() - 1).abs().max()) < 1e-3
        assert fit.residual_rms < 1e-4 and fit.stages[-1]["optimizer"] == "lm" and fit.stages[-1]["iterations"] < 20
        # held parameters and the start are left alone; the model given is not changed
        self.assert_close(fit.lights.principal_directions, start.principal_directions.detach())
        assert float((start.positions_mm.detach() - fit.start.positions_mm.detach()).abs().max()) == 0
        assert start.positions_mm.requires_grad and fit.lights.positions_mm.requires_grad

    def test_recovers_perturbed_leds_in_their_own_units(self):
        truth = rig_lights(CLEAN, dtype=torch.float64)
        config, images, dark = _user_cards(truth)
        nominal = rig_lights(CLEAN.replace(intensity_spread=0.0), dtype=torch.float64)
        start = LEDLights(nominal.positions_mm + _offsets(1.0), nominal.principal_directions, None,
                          torch.full((8,), 1.5, dtype=torch.float64), learnable=True)
        fit = fit_lights(start, images, HEIGHTS, config.pixel_pitch_mm, card_albedo=0.8, dark=dark,
                         saturation_level=1.0, options=LightFitOptions())
        lights = fit.lights
        assert float((lights.positions_mm.detach() - truth.positions_mm).norm(dim=-1).max()) < 0.01
        relative = lights.intensities.detach() / lights.intensities.detach().mean()
        assert float((relative / (truth.intensities / truth.intensities.mean()) - 1).abs().max()) < 1e-3
        assert float((lights.mu.detach() - truth.mu).abs().max()) < 0.01
        # L-BFGS on the same raw parameters (mm, relative intensities, mu) does not get there: the reason for LM
        slow = fit_lights(start, images, HEIGHTS, config.pixel_pitch_mm, card_albedo=0.8, dark=dark,
                          saturation_level=1.0, options=LightFitOptions(optimizer="lbfgs"))
        assert float((slow.lights.positions_mm.detach() - truth.positions_mm).norm(dim=-1).max()) > 0.1

    def test_recovers_a_gaussian_beam(self):
        leds = rig_lights(CLEAN, dtype=torch.float64)
        truth = GaussianBeamLEDs(leds.positions_mm, leds.principal_directions, leds.intensities,
                                 torch.full((8,), 0.5, dtype=torch.float64))
        config, images, dark = _user_cards(truth)
        start = GaussianBeamLEDs(leds.positions_mm + _offsets(0.5), leds.principal_directions, None,
                                 torch.full((8,), 0.7, dtype=torch.float64), learnable=True)
        fit = fit_lights(start, images, HEIGHTS, config.pixel_pitch_mm, card_albedo=0.8, dark=dark,
                         saturation_level=1.0, options=LightFitOptions())
        assert float((fit.lights.positions_mm.detach() - truth.positions_mm).norm(dim=-1).max()) < 0.02
        assert float((fit.lights.width.detach() - truth.width).abs().max()) < 1e-3

    def test_adam_and_lbfgs_projection_and_records(self):
        truth = rig_lights(CLEAN, dtype=torch.float64)
        config, images, dark = _user_cards(truth)
        calls = []

        class Counted(LEDLights):
            def project_(self):
                calls.append(1)
                super().project_()

        start = Counted(truth.positions_mm + 0.2, truth.principal_directions * 2, truth.intensities, truth.mu,
                        learnable=True)
        fit = fit_lights(start, images - dark, HEIGHTS, config.pixel_pitch_mm,
                         options=LightFitOptions(adam_iterations=5, optimizer="lbfgs", iterations=40))
        assert [(r["optimizer"], r["iterations"]) for r in fit.stages] == [("adam", 5), ("lbfgs", 40)]
        assert len(calls) == 5 + 2 and len(fit.losses) == 7  # after every Adam step, every 20 L-BFGS iterations
        self.assert_close(fit.lights.principal_directions.detach().norm(dim=-1), torch.ones(8, dtype=torch.float64))
        assert fit.losses[-1] < fit.losses[0] and fit.loss == fit.stages[-1]["loss"]
        assert fit.residual_rms_per_light.shape == (8,) and fit.residual_rms_per_height.shape == (2,)
        assert fit.gain.shape == (1, 1, 16, 16) and fit.gain.dtype == images.dtype
        assert fit.lights.positions_mm.dtype == torch.float64  # the model's dtype, not the images'

    def test_to_dict_is_a_lights_file(self, tmp_path):
        truth = TabulatedBeamLEDs.from_leds(rig_lights(CLEAN, dtype=torch.float64))
        config, images, dark = _user_cards(truth)
        start = TabulatedBeamLEDs.from_leds(rig_lights(CLEAN, dtype=torch.float64), learnable=True)
        fit = fit_lights(start, images - dark, HEIGHTS, config.pixel_pitch_mm,
                         options=LightFitOptions(parameters=("beam",), iterations=2))
        data = fit.to_dict()
        assert data["model"] == "tests.user_light_models:TabulatedBeamLEDs"
        assert data["calibration"]["parameters"] == ["beam"] and len(data["residuals"]["per_led"]) == 8
        path = write_lights_file(tmp_path / "beam.json", data)
        back = read_lights_file(path).lights
        assert isinstance(back, TabulatedBeamLEDs)
        self.assert_close(back.beam.double(), fit.lights.beam.detach(), rtol=1e-6, atol=1e-9)

    def test_model_without_forward_mode_needs_lbfgs(self):
        class Opaque(torch.autograd.Function):  # a custom operation with a backward but no forward-mode rule
            @staticmethod
            def forward(ctx, x):
                ctx.save_for_backward(x)
                return x.clone()

            @staticmethod
            def backward(ctx, grad):
                return grad

        class OpaqueLEDs(LEDLights):
            def forward(self, points):
                directions, irradiance = super().forward(points)
                return directions, Opaque.apply(irradiance)

        truth = rig_lights(CLEAN, dtype=torch.float64)
        config, images, dark = _user_cards(truth)
        start = OpaqueLEDs(truth.positions_mm + 0.1, truth.principal_directions, learnable=True)
        with pytest.raises(InputError, match="forward mode.*optimizer='lbfgs'"):
            fit_lights(start, images - dark, HEIGHTS, config.pixel_pitch_mm)
        fit = fit_lights(start, images - dark, HEIGHTS, config.pixel_pitch_mm,
                         options=LightFitOptions(optimizer="lbfgs", iterations=20))
        assert fit.stages[0]["iterations"] == 20

    def test_cuda(self, cuda_device):
        """Images on the GPU, the model on the CPU: the fit (Levenberg–Marquardt's forward-mode Jacobian included)
        runs on the GPU and the fitted copy lives there."""
        truth = TabulatedBeamLEDs.from_leds(rig_lights(CLEAN, dtype=torch.float64))
        config, images, dark = _user_cards(truth)
        start = TabulatedBeamLEDs.from_leds(rig_lights(CLEAN, dtype=torch.float64), learnable=True)
        with torch.no_grad():
            start.positions_mm.add_(_offsets(0.3))
        fit = fit_lights(start, images.to(cuda_device), HEIGHTS, config.pixel_pitch_mm, card_albedo=0.8,
                         dark=dark.to(cuda_device), saturation_level=1.0,
                         options=LightFitOptions(parameters=("positions_mm", "beam")))
        assert fit.lights.positions_mm.device.type == "cuda" and fit.gain.device.type == "cuda"
        assert float((fit.lights.positions_mm.detach().cpu() - truth.positions_mm).norm(dim=-1).max()) < 0.01
        assert start.positions_mm.device.type == "cpu"

    def test_errors(self):
        images = torch.rand(2, 8, 8, 8) * 0.5 + 0.25
        with pytest.raises(InputError, match="must be a psmini.lights.LightModel, got Linear"):
            fit_lights(torch.nn.Linear(2, 2), images, HEIGHTS, 1.0)
        with pytest.raises(InputError, match="no nn.Parameter to fit: build it with learnable=True"):
            fit_lights(nominal_leds(8), images, HEIGHTS, 1.0)
        leds = LEDLights(nominal_leds(8).positions_mm, nominal_leds(8).principal_directions, learnable=True)
        with pytest.raises(InputError, match="no parameter 'position'; its parameters are"):
            fit_lights(leds, images, HEIGHTS, 1.0, options=LightFitOptions(parameters=("position",)))
        with pytest.raises(ShapeError, match="the model has 8 lights but the card images have K=6"):
            fit_lights(leds, images[:, :6], HEIGHTS, 1.0)
        with pytest.raises(ShapeError, match="one value per card height"):
            fit_lights(leds, images, [0.0, 1.0, 2.0], 1.0)
        with pytest.raises(InputError, match="options must be a LightFitOptions"):
            fit_lights(leds, images, HEIGHTS, 1.0, options=LEDFitOptions())
        step = torch.full((8,), 1.0, requires_grad=True) * 2.5  # a plain attribute that is no leaf: cannot be copied
        table = TabulatedBeamLEDs(nominal_leds(8).positions_mm, nominal_leds(8).principal_directions, step,
                                  torch.ones(8, 5), learnable=True)
        with pytest.raises(InputError, match="cannot be copied for the fit"):
            fit_lights(table, images, HEIGHTS, 1.0)
        frozen = LEDLights(nominal_leds(8).positions_mm, nominal_leds(8).principal_directions, learnable=True)
        frozen.requires_grad_(False)
        with pytest.raises(InputError, match="every one has requires_grad=False"):
            fit_lights(frozen, images, HEIGHTS, 1.0)
        for bad, message in [({"optimizer": "adam"}, "optimizer must be 'lm' or 'lbfgs'"),
                             ({"iterations": -1}, "iterations must be an integer >= 0"),
                             ({"adam_iterations": 1.5}, "adam_iterations must be an integer"),
                             ({"parameters": "positions_mm"}, "tuple of parameter names"),
                             ({"max_size": 1}, "max_size"), ({"huber_delta": 0.0}, "huber_delta"),
                             ({"learning_rate": -1.0}, "learning_rate"), ({"tolerance": -1.0}, "tolerance")]:
            with pytest.raises(InputError, match=message):
                LightFitOptions(**bad)
        assert LightFitOptions().iterations == 50 and LightFitOptions(optimizer="lbfgs").iterations == 400
