import math
import sys

import numpy as np
import pytest
import torch

from psmini import InputError, LEDLights, PointLights, ShapeError, _chunks, ring_lights
from psmini._compile import compile_blocker
from psmini.config import ReconstructionConfig
from psmini.flatfield import flatfield
from psmini.geometry import depth_to_points
from psmini.lights import LightModel
from psmini.metrics import angular_error_deg
from psmini.nearlight import (
    NearLightOptions,
    NearLightResult,
    _Data,
    _fit_noise,
    _initial_fit,
    _line_minimum,
    _Penalty,
    _plane_basis,
    _robust_step,
    _Steps,
    near_light_energy,
    near_light_vectors,
    solve_near_light,
)
from psmini.normals import albedo_normals
from psmini.pipeline import PhotometricStereo
from psmini.render import normals_from_height, render
from tests.conftest import BaseTester

PITCH = 0.1  # mm: a 48-pixel test field covers 4.8 mm, at the rig's scale of LED distances


def _rig(device=None, dtype=torch.float32) -> LEDLights:
    """Eight LEDs on a 31.6 mm ring 10 mm above the card, pointing at the field centre (the psmini rig)."""
    ring = ring_lights(8, 90.0, device=device, dtype=dtype) * 15.8
    positions = ring + torch.tensor([0.0, 0.0, 10.0], device=device, dtype=dtype)
    intensities = torch.linspace(0.9, 1.1, 8, device=device, dtype=dtype) * 300.0
    return LEDLights(positions, -positions, intensities)


def _bumps(size: int, offset_mm: float, device=None, dtype=torch.float32) -> torch.Tensor:
    """A smooth cloth-like height field (mm), lifted by offset_mm above the card plane."""
    coords = (torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2) * PITCH
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    height = 0.08 * torch.sin(2 * math.pi * x / 1.2) * torch.cos(2 * math.pi * y / 1.5) + 0.02 * x
    return (height + offset_mm)[None, None]


def _capture(size=48, offset_mm=0.5, device=None, dtype=torch.float32, lights=None):
    leds = _rig(device, dtype) if lights is None else lights
    height = _bumps(size, offset_mm, device, dtype)
    normals = normals_from_height(height, PITCH)
    albedo = torch.full_like(height, 0.6)
    images = render(depth_to_points(height, PITCH), normals, albedo, leds)
    flat = torch.zeros_like(height)
    card = render(depth_to_points(flat, PITCH), normals_from_height(flat, PITCH), torch.full_like(height, 0.8), leds)
    return leds, height, normals, images, card


def _flat(images, card):
    return flatfield(images, card, card_albedo=0.8)


def _cliffs(across: str):
    """Courses 0.8 mm apart along ``across`` ("y": rows; "|x|": outward from the middle column) that rise 0.2 mm
    gently and drop by a cliff whose foot lies in its own shadow (readings there 0), with a faint wave the other
    way, 0.5 mm above the card, float64: (leds, height (1, 1, 48, 48), flat-fielded capture)."""
    dtype = torch.float64
    leds = _rig(dtype=dtype)
    coords = (torch.arange(48, dtype=dtype) - 23.5) * PITCH
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    along, other = (y, x) if across == "y" else (x.abs(), y)
    phase = torch.remainder(along, 0.8)
    height = (0.2 * phase / 0.8 + 0.5 + 0.03 * torch.sin(2 * math.pi * other / 1.3))[None, None]
    images = render(depth_to_points(height, PITCH), normals_from_height(height, PITCH),
                    torch.full_like(height, 0.6), leds)
    images = torch.where(((phase < 0.15) | (phase > 0.75))[None, None], torch.zeros_like(images), images)
    card = render(depth_to_points(torch.zeros_like(height), PITCH),
                  normals_from_height(torch.zeros_like(height), PITCH), torch.full_like(height, 0.8), leds)
    return leds, height, _flat(images, card)


def _relief_rmse(result, height) -> float:
    """RMS depth error after the mean, mm."""
    difference = (result.depth - height)[0, 0]
    return float((difference - difference.mean()).square().mean().sqrt())


def _noisy(images, seed, level=0.01):
    noise = torch.randn(images.shape, generator=torch.Generator().manual_seed(seed), dtype=images.dtype)
    return (images + level * images.amax() * noise).clamp_min(0)


class TestNearLightVectors(BaseTester):
    def test_flat_card_reads_its_albedo(self, device, dtype):
        """On the card plane, flat-fielded vectors have z = 1: a flat patch of albedo ρ reads ρ under every LED."""
        flat = torch.zeros(1, 1, 6, 6, device=device, dtype=dtype)
        vectors = near_light_vectors(_rig(device, dtype), flat, PITCH, 0.0)
        self.assert_close(vectors[:, :, 2], torch.ones(1, 8, 6, 6, device=device, dtype=dtype))

    def test_raw_vectors_follow_inverse_square(self, device, dtype):
        light = PointLights(torch.tensor([[0.0, 0.0, 10.0]], device=device, dtype=dtype),
                            torch.tensor([50.0], device=device, dtype=dtype))
        vectors = near_light_vectors(light, torch.full((1, 1, 1, 1), 2.0, device=device, dtype=dtype), PITCH)
        self.assert_close(vectors[0, 0, :, 0, 0], torch.tensor([0.0, 0.0, 50.0 / 64.0], device=device, dtype=dtype))

    def test_light_below_card_raise(self):
        light = PointLights(torch.tensor([[0.0, 0.0, -5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 5.0]]))
        with pytest.raises(InputError, match="above the card"):
            near_light_vectors(light, torch.zeros(1, 1, 2, 2), PITCH, card_height_mm=0.0)
        with pytest.raises(InputError, match="LightModel"):
            near_light_vectors(torch.nn.Identity(), torch.zeros(1, 1, 2, 2), PITCH)

    def test_gradcheck(self):
        leds = _rig(dtype=torch.float64)
        depth = (torch.rand(1, 1, 3, 3, dtype=torch.float64) * 0.2).requires_grad_()

        def every_parameter(d, pos, axes, intensities, mu):
            return near_light_vectors(LEDLights(pos, axes, intensities, mu), d, PITCH, 0.0)

        parameters = (leds.positions_mm, -leds.positions_mm, leds.intensities * 1.1,
                      torch.full_like(leds.intensities, 1.3))
        self.gradcheck(every_parameter, (depth, *(t.clone().requires_grad_() for t in parameters)))


class TestEnergyTerms(BaseTester):
    """The pieces of the energy: the penalties' constants, the noise model, the robust fit at fixed lights."""

    @pytest.mark.parametrize("name, scale", [("welsch", 2.9846), ("cauchy", 2.3849)])
    def test_penalty_constants_match_their_integrals(self, name, scale):
        """95% Gaussian efficiency at the default scales, and the consistency factor, against numpy quadrature."""
        penalty = _Penalty(name, scale)
        r = np.linspace(-30, 30, 600001)
        density = np.exp(-0.5 * r**2) / math.sqrt(2 * math.pi) * (r[1] - r[0])
        weight = 1 / (1 + r**2 / scale**2) if name == "cauchy" else np.exp(-(r**2) / scale**2)
        psi = r * weight
        dpsi = np.gradient(psi, r)
        efficiency = (dpsi * density).sum() ** 2 / (psi**2 * density).sum()
        assert efficiency == pytest.approx(0.95, abs=2e-4)
        assert penalty.consistency == pytest.approx((r**2 * weight * density).sum() / (weight * density).sum(), 1e-5)
        assert penalty.covariance_factor == pytest.approx(
            (psi**2 * density).sum() * (weight * density).sum() / (dpsi * density).sum() ** 2, rel=1e-4)
        values = penalty.value(torch.tensor([0.0, 1.0, 1e6], dtype=torch.float64))
        assert float(values[0]) == 0 and 0 < float(values[1]) < 0.5 and (
            float(values[2]) == pytest.approx(scale**2 / 2) if name == "welsch" else float(values[2]) > scale**2)

    def test_noise_model_recovers_read_and_shot_noise(self):
        """Readings of a known model with read noise α and shot noise β (through a varying flat-field gain, a tenth
        of them in attached shadow): the fit at the true lights recovers the variance of lit readings within 10% and
        the read noise within 25% (α and β trade off along the readings' levels)."""
        torch.manual_seed(0)
        leds = _rig(dtype=torch.float64)
        lights = near_light_vectors(leds, torch.full((1, 1, 64, 64), 0.3, dtype=torch.float64), PITCH, 0.0)
        normals = torch.nn.functional.normalize(torch.randn(1, 3, 64, 64, dtype=torch.float64) * 0.4
                                                + torch.tensor([0, 0, 1.0], dtype=torch.float64).view(1, 3, 1, 1),
                                                dim=1)
        albedo = 0.5 + 0.3 * torch.rand(1, 1, 64, 64, dtype=torch.float64)
        clean = albedo * (lights * normals.unsqueeze(1)).sum(2).clamp_min(0)
        gain = 1 + 2 * torch.rand(1, 8, 64, 64, dtype=torch.float64)
        alpha, beta = 1e-5, 1e-4
        raw = clean / gain
        images = (raw + (alpha + beta * raw).sqrt() * torch.randn_like(raw)).clamp_min(0) * gain
        valid = torch.ones_like(images)
        data = _Data(images, valid, gain, torch.tensor([1e-12, 0.0, 1e-6], dtype=torch.float64).view(1, 3, 1, 1),
                     _Steps(False, images.device))
        penalty = _Penalty("welsch", 2.9846)
        prior = images.amax(1, keepdim=True) * normals
        data.set_noise(_fit_noise(data, lights, _initial_fit(data, lights, prior), penalty, 6))
        m = _initial_fit(data, lights, prior).m
        for _ in range(3):
            fit = _robust_step(data, lights, m, prior, penalty)
            m = fit.m
        noise = _fit_noise(data, lights, fit, penalty, 6)
        for level in (0.0, 0.1, 0.3, 0.6):  # the variance of a raw reading at the levels of the capture
            tolerance = 0.25 if level == 0 else 0.1  # a dark reading's variance is the read noise alone
            assert float(noise[0, 0] + noise[0, 1] * level) == pytest.approx(alpha + beta * level, rel=tolerance)

    def test_cast_shadows_and_highlights_leave_the_fit(self):
        """A cast shadow of one LED and a glint (three times the reading) under another: at the true lights the
        robust fit keeps to the truth where least squares errs by degrees, and gives both readings no weight."""
        leds, height, normals, images, _ = _capture(dtype=torch.float64)
        corrupted = images.clone()
        corrupted[:, 2, 10:20, 10:20] = 0.0  # a cast shadow of LED 2
        corrupted[:, 5, 30:40, 5:15] *= 3.0  # a highlight under LED 5
        corrupted = _noisy(corrupted, seed=1, level=0.002)
        lights = near_light_vectors(leds, height, PITCH)
        noise = torch.tensor([1e-12, 0.0, 1e-6], dtype=torch.float64).view(1, 3, 1, 1)
        data = _Data(corrupted, torch.ones_like(corrupted), torch.ones_like(corrupted[:1, :1]), noise,
                     _Steps(False, corrupted.device))
        penalty = _Penalty("welsch", 2.9846)
        prior = corrupted.amax(1, keepdim=True) * torch.tensor([0, 0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
        data.set_noise(_fit_noise(data, lights, _initial_fit(data, lights, prior), penalty, 6))
        # the solver's start: the lit-weighted least squares, then a step of Cauchy's penalty
        start = _initial_fit(data, lights, prior).m
        m = _robust_step(data, lights, start, prior, _Penalty("cauchy", penalty.scale)).m
        for _ in range(3):
            fit = _robust_step(data, lights, m, prior, penalty)
            m = fit.m
        robust = angular_error_deg(torch.nn.functional.normalize(m, dim=1), normals)
        plain = angular_error_deg(albedo_normals(corrupted, lights)[1], normals)
        assert float(plain.max()) > 5.0 and float(robust.max()) < 1.0 and float(robust.mean()) < 0.3
        assert float(fit.share[:, 2, 10:20, 10:20].max()) < 1e-3 and float(fit.share[:, 5, 30:40, 5:15].max()) < 1e-3
        assert float(fit.share[:, :, 25:28, 25:28].min()) > 0.5  # a clean pixel keeps every reading


class TestNearLightOptions:
    def test_defaults_validate_and_serialise(self):
        options = NearLightOptions()
        assert NearLightOptions(**options.to_dict()) == options
        assert options.replace(max_iterations=5).max_iterations == 5
        assert options.penalty_function().scale == pytest.approx(2.9846)
        assert NearLightOptions(penalty="cauchy", robust_scale=2.0).penalty_function() == _Penalty("cauchy", 2.0)

    @pytest.mark.parametrize("bad", [{"max_iterations": 0}, {"irls_steps": True}, {"tolerance_deg": -1.0},
                                     {"robust_scale": 0.0}, {"penalty": "huber"}, {"estimate_tilt": 1},
                                     {"estimate_bend": "yes"}, {"initial_height_mm": math.nan},
                                     {"search_mm": (1.0, -1.0)}, {"integrator": "fill"}, {"compile": "yes"}])
    def test_bad_values_raise(self, bad):
        with pytest.raises(InputError, match=next(iter(bad))):
            NearLightOptions(**bad)

    def test_unknown_name_raise(self):
        with pytest.raises(InputError, match="unknown near-light options"):
            NearLightOptions().replace(shadow_fraction=0.1)


class TestSolveNearLight(BaseTester):
    @pytest.mark.parametrize("offset_mm", [0.0, 1.0])
    def test_recovers_normals_and_height(self, device, offset_mm):
        leds, height, normals, images, card = _capture(offset_mm=offset_mm, device=device, dtype=torch.float64)
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        errors = angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2]  # borders: one-sided differences
        assert float(errors.mean()) < 0.05
        assert abs(float(result.offset_mm[0]) - float(height.mean())) < 0.01  # the absolute height, mm
        assert float((result.depth - height).abs().max()) < 0.02
        assert bool(result.mask.all()) and float(result.normal_std.max()) < 1.0

    def test_batch_equals_items(self):
        """Each batch item gets its own height and the answer it gets alone."""
        a = _capture(size=32, offset_mm=0.2, dtype=torch.float64)
        b = _capture(size=32, offset_mm=0.8, dtype=torch.float64)
        flat = _flat(torch.cat([a[3], _noisy(b[3], 0)]), a[4])
        both = solve_near_light(flat.images, a[0], PITCH, 0.0, flat.valid)
        for item in (0, 1):
            alone = solve_near_light(flat.images[item : item + 1], a[0], PITCH, 0.0, flat.valid[item : item + 1])
            self.assert_close(both.depth[item : item + 1], alone.depth, rtol=0, atol=1e-8)
            self.assert_close(both.normals[item : item + 1], alone.normals, rtol=0, atol=1e-8)
        assert abs(float(both.offset_mm[0]) - 0.2) < 0.02 and abs(float(both.offset_mm[1]) - 0.8) < 0.05

    def test_cpu_chunks_give_the_batch_answer(self, monkeypatch):
        a = _capture(size=32, offset_mm=0.2, dtype=torch.float64)
        b = _capture(size=32, offset_mm=0.8, dtype=torch.float64)
        flat = _flat(torch.cat([a[3], b[3], a[3]]), a[4])
        whole = solve_near_light(flat.images, a[0], PITCH, 0.0, flat.valid)
        monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 2 * flat.images[0].numel())  # chunks of 2 and 1
        chunked = solve_near_light(flat.images, a[0], PITCH, 0.0, flat.valid)
        for name in ("depth", "normals", "albedo", "offset_mm", "normal_std", "weights"):
            self.assert_close(getattr(chunked, name), getattr(whole, name), rtol=0, atol=1e-8)
        assert (chunked.iterations, chunked.converged) == (whole.iterations, whole.converged)

    def test_distant_assumption_is_much_worse(self):
        """The reason the module exists: least squares with the lights seen from the centre errs by degrees."""
        leds, height, normals, images, card = _capture(offset_mm=1.0)
        far = PhotometricStereo(leds, PITCH, ReconstructionConfig(solver="distant", card_smoothing_px=None))(
            images, card, card_albedo=0.8)
        near = PhotometricStereo(leds, PITCH, ReconstructionConfig(solver="near", card_smoothing_px=None))(
            images, card, card_albedo=0.8)
        far_error = float(angular_error_deg(far.normals, normals).mean())
        near_error = float(angular_error_deg(near.normals, normals).mean())
        assert far_error > 10 * near_error and far_error > 0.5

    def test_raw_images_without_card(self):
        """Without a card the height shows only through the inverse-square law, and the fit still holds."""
        leds, height, normals, images, _ = _capture(offset_mm=0.3, dtype=torch.float64)
        result = solve_near_light(images * 0.7, leds, PITCH, None)  # an unknown camera gain
        far = PhotometricStereo(leds, PITCH, ReconstructionConfig(solver="distant"))(images * 0.7)
        near_error = float(angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2].mean())
        assert near_error < 0.2
        assert float(angular_error_deg(far.normals, normals).mean()) > 20 * near_error
        assert abs(float(result.offset_mm[0]) - 0.3) < 0.1

    def test_fixed_offset_keeps_initial_height(self):
        leds, height, normals, images, card = _capture(offset_mm=0.4, dtype=torch.float64)
        flat = _flat(images, card)
        options = NearLightOptions(initial_height_mm=float(height.mean()), estimate_offset=False,
                                   estimate_tilt=False, estimate_bend=False)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid, options=options)
        assert abs(float(result.depth.mean() - height.mean())) < 1e-9

    def test_unlit_pits_are_unsolved_and_no_spikes(self):
        """Pixels no light reaches (zero in every image) are unsolved (their predicted error is the prior's), and
        their depth comes from their rims: never a spike."""
        leds, height, normals, images, card = _capture(offset_mm=1.0, dtype=torch.float64)
        images = images.clone()
        images[..., 20:23, 20:23] = 0.0
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        assert not bool(result.mask[..., 20:23, 20:23].any()) and bool(result.mask[..., 5:15, 5:15].all())
        assert float(result.normal_std[..., 20:23, 20:23].min()) > 30
        assert float((result.depth - height)[..., 18:25, 18:25].abs().max()) < 0.05

    def test_lost_steps_are_found_as_a_tilt(self):
        """Courses that rise gently and drop by a cliff (a purl's rows of loops) whose foot lies in its own shadow:
        integration cannot see the drops, and they add up to a tilt across the field (0.25 mm/mm), which the
        images' near-light cue finds (estimate_tilt)."""
        leds, height, flat = _cliffs("y")
        plain = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid,
                                 options=NearLightOptions(estimate_tilt=False))
        found = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        assert float(plain.tilt.abs().max()) == 0.0 and float(found.tilt[0, 1]) < -0.1
        assert _relief_rmse(found, height) < 0.25 * _relief_rmse(plain, height)

    def test_lost_steps_are_found_as_a_bend(self):
        """Courses that rise gently away from the middle and drop outward by a cliff whose foot lies in its own
        shadow: integration loses the drops on both sides, which add up to a V (0.25 mm/mm either way) that the
        images' near-light cue finds as a bend (estimate_bend), a negative d²z/dx²."""
        leds, height, flat = _cliffs("|x|")
        plain = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid,
                                 options=NearLightOptions(estimate_bend=False))
        found = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        assert float(plain.bend.abs().max()) == 0.0 and float(found.bend[0, 0]) < -0.05
        assert _relief_rmse(found, height) < 0.5 * _relief_rmse(plain, height)

    def test_creases_keep_their_depth(self, monkeypatch):
        """V grooves 0.3 mm deep every 0.8 mm (flanks at 37°, creases at every valley and ridge): the final
        integration's one-sided equations take each crease's edges from its flanks, where the trapezoidal rule
        (k = 0) averages the two flanks' slopes into a flat crease: 13.8 µm RMS error against 8.8 µm."""
        leds = _rig(dtype=torch.float64)
        coords = (torch.arange(48, dtype=torch.float64) - 23.5) * PITCH
        y, x = torch.meshgrid(-coords, coords, indexing="ij")
        phase = torch.remainder(x + 0.05, 0.8) / 0.8
        height = (0.5 + 0.15 * (1 - 2 * (2 * phase - 1).abs()) + 0.02 * torch.sin(2 * math.pi * y / 1.3))[None, None]
        images = render(depth_to_points(height, PITCH), normals_from_height(height, PITCH),
                        torch.full_like(height, 0.6), leds)
        flat_height = torch.zeros_like(height)
        card = render(depth_to_points(flat_height, PITCH), normals_from_height(flat_height, PITCH),
                      torch.full_like(height, 0.8), leds)
        flat = _flat(images, card)
        one_sided = _relief_rmse(solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid), height)
        monkeypatch.setattr(sys.modules["psmini.nearlight"], "_ONE_SIDED_K", 0.0)
        trapezoid = _relief_rmse(solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid), height)
        assert one_sided < 0.011 < trapezoid
        assert one_sided < 0.75 * trapezoid

    def test_line_search_goes_to_the_parabolas_minimum(self):
        """The placement's line search on energies sampled at 0, 1/2 and 1 of a step: the minimum of a parabola
        (0.3, and 1 or 0 beyond the step's ends, or where the energies curve down), and a fraction that moves by a
        rounding's size when the energies do, where two nearly equal energies made the least of three flip."""
        t = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
        energies = torch.stack([5 + 2 * (t - centre).square() for centre in (0.3, 1.7, -0.4)])
        concave = torch.stack([5 - (t - 0.2).square(), 5 - (t - 0.8).square()])
        torch.testing.assert_close(_line_minimum(torch.cat([energies, concave])),
                                   torch.tensor([0.3, 1.0, 0.0, 1.0, 0.0], dtype=torch.float64))
        tie = torch.tensor([[11455.69, 11403.752, 11403.748]], dtype=torch.float64)
        moved = _line_minimum(tie * torch.tensor([1.0, 1 + 1e-7, 1 - 1e-7], dtype=torch.float64))
        assert abs(float(moved - _line_minimum(tie))) < 1e-4 and 0.7 < float(_line_minimum(tie)) < 0.8

    def test_placement_shapes_keep_the_mean(self):
        """On a mask off the field's centre each shape of the placement but the offset has zero mean over the mask,
        each on its own (so that the offset is the mean height, whatever the tilt and bend are shrunk to)."""
        x, y = torch.meshgrid(torch.linspace(-2, 2, 20), torch.linspace(-2, 2, 20), indexing="xy")
        domain = torch.zeros(1, 1, 20, 20, dtype=torch.bool)
        domain[..., 2:9, 11:19] = True
        basis = _plane_basis(torch.stack([x, y])[None], domain)
        means = basis[:, :, domain[0, 0]].mean(dim=2)
        torch.testing.assert_close(means, torch.tensor([[1.0, 0, 0, 0, 0, 0]]), atol=1e-6, rtol=0)

    def test_no_tilt_or_bend_from_noise(self):
        """A smooth surface loses no step: on noisy captures the tilt and bend that noise makes are shrunk away
        (below 5e-4 /mm and /mm², a fraction of a µm over the field; the share q / (q + 3²) kept 1.4e-3 to 5.8e-3 of
        them here)."""
        leds, height, normals, images, card = _capture(size=64, offset_mm=0.5, dtype=torch.float64)
        for seed in range(4):
            flat = _flat(_noisy(images, seed), card)
            result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
            assert float(result.tilt.abs().max()) < 5e-4, seed
            assert float(result.bend.abs().max()) < 5e-4, seed

    def test_predicted_errors_hold(self):
        """On noisy captures (Gaussian noise of 1% of the brightest reading) the normals' errors are as predicted:
        about 63% below the predicted RMS error (a 2-D Gaussian's 1 - 1/e) and error² / predicted² about 1."""
        leds, height, normals, images, card = _capture(size=64, offset_mm=0.5, dtype=torch.float64)
        within, ratio = [], []
        for seed in range(3):
            flat = _flat(_noisy(images, seed), card)
            result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
            error = angular_error_deg(result.normals, normals)[..., 4:-4, 4:-4]
            predicted = result.normal_std[..., 4:-4, 4:-4]
            within.append(float((error < predicted).double().mean()))
            ratio.append(float((error / predicted).square().mean()))
        assert 0.55 < float(np.mean(within)) < 0.71 and 0.75 < float(np.mean(ratio)) < 1.3, (within, ratio)

    def test_predicted_errors_hold_where_the_model_misfits(self):
        """Readings in the left half off the Lambertian model by 6% each (a sheen the model lacks, six times the
        noise): the fit's covariance alone would understate the errors there (error² / predicted² about 2, 39%
        below); scaled by the local misfit (the a posteriori variance factor) they are as predicted again."""
        leds, height, normals, images, card = _capture(size=64, offset_mm=0.5, dtype=torch.float64)
        within, ratio = [], []
        for seed in range(3):
            sheen = torch.ones_like(images)
            sheen[..., :32] += 0.06 * torch.randn(sheen[..., :32].shape, dtype=images.dtype,
                                                  generator=torch.Generator().manual_seed(100 + seed))
            flat = _flat(_noisy(images * sheen, seed), card)
            result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
            error = angular_error_deg(result.normals, normals)[..., 4:-4, 4:24]
            predicted = result.normal_std[..., 4:-4, 4:24]
            within.append(float((error < predicted).double().mean()))
            ratio.append(float((error / predicted).square().mean()))
        assert 0.55 < float(np.mean(within)) < 0.71 and 0.75 < float(np.mean(ratio)) < 1.3, (within, ratio)

    def test_stable_under_rounding_changes(self):
        """A card changed by one part in 10^7, float32 against float64, a batch of four against one: the normals
        move by rounding's size, never by a selection's flip (the energy is smooth in its input)."""
        leds, height, normals, images, card = _capture(size=64, offset_mm=0.5, dtype=torch.float64)
        noisy = _noisy(images, 0)
        base = _flat(noisy, card)
        reference = solve_near_light(base.images, leds, PITCH, 0.0, base.valid)
        scaled = _flat(noisy, card * (1 + 1e-7))
        moved = [solve_near_light(scaled.images, leds, PITCH, 0.0, scaled.valid).normals]
        single = solve_near_light(base.images.float(), _rig(dtype=torch.float32), PITCH, 0.0, base.valid)
        batch = solve_near_light(base.images.float().expand(4, -1, -1, -1).contiguous(), _rig(dtype=torch.float32),
                                 PITCH, 0.0, base.valid.expand(4, -1, -1, -1))
        moved += [single.normals.double(), batch.normals[2:3].double()]
        for other in moved:
            change = angular_error_deg(reference.normals, other)
            assert float(change.mean()) < 0.005 and float(change.max()) < 1.0

    @pytest.mark.skipif(compile_blocker(torch.device("cpu")) is not None,
                        reason=f"torch.compile cannot run here: {compile_blocker(torch.device('cpu'))}")
    def test_compiled_equals_eager(self):
        """NearLightOptions(compile=True) fuses the per-pixel steps: the same result within 1e-5 (normals' mean angle
        in radians, the relief in mm, albedo relative) on a noisy capture at two sizes (one compiled graph for both);
        the absolute height within 0.5 µm, what a change of the card by one part in 10^7 moves the eager one by
        (its line search's parabola through float32 energies: 0.06-0.29 µm here)."""
        for size in (48, 64):
            leds, _, _, images, card = _capture(size=size, offset_mm=0.5)
            flat = _flat(_noisy(images, 0), card)
            eager = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
            compiled = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid,
                                        options=NearLightOptions(compile=True))
            angle = angular_error_deg(eager.normals.double(), compiled.normals.double()) * math.pi / 180
            assert float(angle.mean()) < 1e-5, float(angle.mean())
            offset = compiled.offset_mm - eager.offset_mm
            assert float(offset.abs().max()) < 5e-4
            assert float((eager.depth - compiled.depth + offset.view(-1, 1, 1, 1)).abs().max()) < 1e-5
            assert float(((eager.albedo - compiled.albedo) / eager.albedo).abs().max()) < 1e-5

    def test_without_a_compiler_it_runs_eagerly(self, monkeypatch):
        """Without a C++ compiler, compile=True warns and runs the eager steps: the eager result, bit for bit."""
        monkeypatch.setenv("CXX", "no-such-compiler-for-psmini")
        leds, _, _, images, card = _capture(size=32)
        flat = _flat(images, card)
        eager = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler 'no-such-compiler-for-psmini' on the PATH"):
            fallback = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid,
                                        options=NearLightOptions(compile=True))
        assert torch.equal(eager.normals, fallback.normals) and torch.equal(eager.depth, fallback.depth)

    def test_gradcheck_through_the_whole_solve(self):
        """Gradients of the depth and the normals with respect to the images and the LEDs' positions, through every
        alternation, the noise model and the placement (float64, a 12-pixel capture)."""
        leds, _, _, images, card = _capture(size=12, dtype=torch.float64)
        flat = _flat(_noisy(images, 3, 0.002), card)
        options = NearLightOptions(max_iterations=2, search_mm=(-1.0, 1.0))
        directions, intensities = leds.principal_directions.detach(), leds.intensities.detach()

        def solve(i, positions):
            result = solve_near_light(i, LEDLights(positions, directions, intensities), PITCH, 0.0, options=options)
            return result.depth, result.normals

        self.gradcheck(solve, (flat.images.clone().requires_grad_(), leds.positions_mm.detach().clone()
                               .requires_grad_()), atol=1e-5, rtol=1e-3, fast_mode=True)

    def test_a_learnable_model_gets_gradients(self):
        """Every parameter of a learnable LED model receives the gradient of its central difference through the
        whole solve."""
        leds, _, _, images, card = _capture(size=12, dtype=torch.float64)
        flat = _flat(images, card)
        options = NearLightOptions(max_iterations=2, search_mm=(-1.0, 1.0))
        model = LEDLights(leds.positions_mm.detach(), leds.principal_directions.detach(), leds.intensities.detach(),
                          learnable=True).double()

        def loss() -> torch.Tensor:
            result = solve_near_light(flat.images, model, PITCH, 0.0, options=options)
            return result.normals[:, 0].sum() + result.depth.sum()

        loss().backward()
        with torch.no_grad():
            for name, parameter in model.named_parameters():
                index, step = (1,) * parameter.ndim, 1e-6
                parameter[index] += step
                up = loss()
                parameter[index] -= 2 * step
                down = loss()
                parameter[index] += step
                numerical = float((up - down) / (2 * step))
                assert parameter.grad is not None, name
                # (the intensities cancel in flat-fielded images: their gradient is 0, their difference rounding's)
                assert float(parameter.grad[index]) == pytest.approx(numerical, rel=0.02, abs=1e-5), name

    def test_a_model_of_the_users_own(self):
        """The solver asks a light model for nothing but ``model(points)``: a user's subclass of ``LEDLights`` that
        overrides ``forward`` (a Gaussian beam) is solved with its own lights, as accurately as the built-in LED."""

        class GaussianBeam(LEDLights):
            def forward(self, points):
                directions, irradiance = super().forward(points)
                axis = torch.nn.functional.normalize(self.principal_directions, dim=-1).to(points)
                cosine = -(directions * axis[None, :, :, None, None]).sum(2, keepdim=True)
                return directions, irradiance * torch.exp(-((1 - cosine) / 0.05))

        base = _rig(dtype=torch.float64)
        beam = GaussianBeam(base.positions_mm, base.principal_directions, base.intensities)
        leds, height, normals, images, card = _capture(offset_mm=0.5, dtype=torch.float64, lights=beam)
        flat = _flat(images, card)
        own = solve_near_light(flat.images, beam, PITCH, 0.0, flat.valid)
        assert float(angular_error_deg(own.normals, normals)[..., 2:-2, 2:-2].mean()) < 0.05
        wrong = solve_near_light(flat.images, base, PITCH, 0.0, flat.valid)  # the beam ignored: the error shows
        assert float(angular_error_deg(wrong.normals, normals)[..., 2:-2, 2:-2].mean()) > 0.2

    def test_energy_is_lowest_at_the_truth(self):
        """The public energy: nothing left at the true depth, albedo and normals; more when the LEDs move."""
        from psmini.result import Reconstruction

        leds, height, normals, images, card = _capture(size=16, dtype=torch.float64)
        flat = _flat(images, card)
        noise = torch.tensor(0.005, dtype=torch.float64)
        truth = Reconstruction(torch.full_like(height, 0.6), normals, height, height, height, height > 0)
        assert float(near_light_energy(flat.images, leds, truth, PITCH, 0.0, noise)) < 1e-6
        moved = LEDLights(leds.positions_mm + 0.5, leds.principal_directions, leds.intensities)
        assert float(near_light_energy(flat.images, moved, truth, PITCH, 0.0, noise)) > 1.0
        wrong = Reconstruction(truth.albedo, normals[:, :2], height, height, height, truth.mask)
        with pytest.raises(ShapeError, match="normals"):
            near_light_energy(flat.images, leds, wrong, PITCH, 0.0, noise)

    def test_energy_gradcheck(self):
        """The energy is differentiable in the readings, the reconstruction, the noise and every LED parameter."""
        from psmini.result import Reconstruction

        gen = torch.Generator().manual_seed(0)
        leds = _rig(dtype=torch.float64)
        count = leds.count

        def rand(*shape):
            return torch.rand(*shape, generator=gen, dtype=torch.float64)

        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
        normals = torch.nn.functional.normalize(up + 0.2 * (rand(1, 3, 3, 3) - 0.5), dim=1)
        images, depth, albedo = rand(1, count, 3, 3) * 0.4 + 0.2, rand(1, 1, 3, 3) * 0.2, rand(1, 1, 3, 3) + 0.3

        def energy(i, d, a, n, noise, *parameters):
            result = Reconstruction(a, n, torch.zeros_like(d), torch.zeros_like(d), d, d > -1)
            return near_light_energy(i, LEDLights(*parameters), result, PITCH, 0.0, noise)

        parameters = (leds.positions_mm, leds.principal_directions, leds.intensities, torch.full((count,), 1.3,
                                                                                                   dtype=torch.float64))
        inputs = (images, depth, albedo, normals, torch.tensor(0.05, dtype=torch.float64), *parameters)
        self.gradcheck(energy, tuple(t.clone().requires_grad_() for t in inputs))

    def test_module_equals_stage(self):
        leds, _, _, images, card = _capture(size=24)
        config = ReconstructionConfig(card_smoothing_px=None)
        result = PhotometricStereo(leds, PITCH, config)(images, card, card_albedo=0.8)
        flat = _flat(images, card)
        stage = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid, gain=flat.gain,
                                 options=config.near_options(False))
        self.assert_close(result.depth, stage.depth)
        assert isinstance(result, NearLightResult)

    def test_result_moves_and_splits_whole(self):
        leds, _, _, images, card = _capture(size=24)
        flat = _flat(images, card)
        single = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        both = NearLightResult.concatenate([single, single.to("cpu")])
        second = both.item(-1)
        assert isinstance(second, NearLightResult) and second.iterations == single.iterations
        for name in ("albedo", "normals", "depth", "mask", "weights", "offset_mm", "tilt", "bend", "normal_std",
                     "noise"):
            assert torch.equal(getattr(second, name), getattr(single, name)), name
        with pytest.raises(InputError, match="index 2 is outside the batch of 2"):
            both.item(2)

    def test_count_mismatch_raise(self):
        with pytest.raises(ShapeError, match="8 lights"):
            solve_near_light(torch.rand(1, 6, 8, 8), _rig(), PITCH, 0.0)

    def test_nan_raise(self):
        images = torch.rand(1, 8, 8, 8)
        images[0, 1, 2, 3] = float("nan")
        with pytest.raises(InputError, match="finite"):
            solve_near_light(images, _rig(), PITCH, 0.0)

    def test_bad_inputs_raise(self):
        images = torch.rand(1, 8, 8, 8)
        with pytest.raises(InputError, match="LightModel"):
            solve_near_light(images, ring_lights(8, 55.0), PITCH, 0.0)
        with pytest.raises(InputError, match="options"):
            solve_near_light(images, _rig(), PITCH, 0.0, options=dict(max_iterations=2))
        with pytest.raises(ShapeError, match="valid"):
            solve_near_light(images, _rig(), PITCH, 0.0, valid=torch.ones(1, 8, 4, 4, dtype=torch.bool))
        with pytest.raises(InputError, match="card_height_mm"):
            solve_near_light(images, _rig(), PITCH, float("inf"))
        with pytest.raises(InputError, match="gain must be >= 0"):
            solve_near_light(images, _rig(), PITCH, 0.0, gain=-torch.ones(1, 8, 8, 8))
        # an all-dark sample beside a lit one: its noise model of 0 made NaN of everything ("p must be finite")
        with pytest.raises(InputError, match="all <= 0 or not valid: no light to solve for"):
            solve_near_light(torch.cat([images, torch.zeros_like(images)]), _rig(), PITCH, 0.0)
        with pytest.raises(ShapeError, match="gain"):
            solve_near_light(images, _rig(), PITCH, 0.0, gain=torch.ones(1, 8, 4, 4))
        assert isinstance(_rig(), LightModel)


@pytest.mark.slow
class TestSimulatedFabrics:
    def test_knit_depth_has_no_spikes(self, tmp_path):
        """`psmini synth knit` reconstructed as `psmini reconstruct` does (noisy 10-bit capture, its card): no solved
        pixel far from the simulator's height, and the describe step's kurtosis is a relief's, not spikes'."""
        from data_synth.rig import write_synthetic_capture
        from psmini import reconstruct
        from psmini.fabric import describe
        from psmini.io import load_sample

        sample_dir, _ = write_synthetic_capture(tmp_path, "knit", seed=0)
        sample = load_sample(sample_dir)
        result = reconstruct(sample)
        truth = torch.from_numpy(np.load(sample_dir / "gt" / "depth.npy"))[None, None].to(result.depth)
        error = (result.depth - truth)[result.mask]
        error = error - error.median()
        assert float(error.abs().quantile(0.999)) < 0.3
        assert describe(result.depth, sample.pixel_pitch_mm, result.mask)[0]["iso25178"]["Sku"] < 10

    def test_predicted_errors_cover_a_metallic_fabrics_glints(self):
        """Lurex's metal tapes glint: where the robust fit keeps the wrong three readings of a glinting pixel, its
        residuals fit that wrong normal to the noise and neither the covariance nor the misfit sees it (error² /
        predicted² 5.3-5.4 on these captures without the rejections' part). With it (the share of the pixel's light
        the fit rejects times the angle to the lit readings' least squares, squared) 1.8-1.9; with the unexplained
        light's factor as well (the kept readings taken to carry the share of light rejected above its prediction)
        1.29, the share below the prediction 65%."""
        from data_synth import make_fabric
        from data_synth.rig import RigConfig, render_capture, render_card

        config = RigConfig(size=200, pixel_pitch_mm=0.05, noise=True, bit_depth=8, intensity_spread=0.05)
        card = render_card(config, 0.8)
        capture = render_capture(make_fabric("lurex", size=200, pixel_pitch_mm=0.05, seed=0), config,
                                 height_offset_mm=0.5)
        result = PhotometricStereo(capture.lights, 0.05)(capture.images[None], card.images[None],
                                                         capture.dark[None], card.dark[None], card_albedo=0.8,
                                                         saturation_level=1.0)
        flat = flatfield(capture.images[None], card.images[None], capture.dark[None], card.dark[None], 0.8,
                         saturation_level=1.0)
        scored = (((capture.lit & flat.valid[0]).sum(0) >= 3) & capture.mask[0].bool())
        error = angular_error_deg(result.normals, capture.normals[None])[0, 0][scored]
        predicted = result.normal_std[0, 0][scored]
        ratio, within = float((error / predicted).square().mean()), float((error < predicted).double().mean())
        assert ratio < 1.45 and 0.55 < within < 0.71, (ratio, within)

    @pytest.mark.parametrize("name", ["knit", "purl"])
    def test_stable_under_rounding_changes_of_a_capture(self, name):
        """Issue 45's stability on the fabrics where hard selections flipped most (knit, purl: 0.32° and 0.46° mean,
        140° and 166° at single pixels), on the benchmark's 400-px captures (at 128 or 256 px no pixel sits where a
        narrower hinge let 1.1-1.3° through): the card scaled by 1 + 1e-7, float64 against float32 and another
        thread count (its own order of summation) each move the mean normal by at most 0.005° and no pixel by more
        than 1° (a batch: test_stable_under_rounding_changes). Before e901adc and ec80e03 purl's normals moved
        0.0069° on average between one thread and two (the coarse preconditioner's float32 pseudo-inverse, the
        line search's choice between equal energies)."""
        from data_synth import make_fabric
        from data_synth.rig import RigConfig, render_capture, render_card

        config = RigConfig(size=400, pixel_pitch_mm=0.025, noise=True, bit_depth=8, intensity_spread=0.05)
        card = render_card(config, 0.8)
        capture = render_capture(make_fabric(name, size=400, pixel_pitch_mm=0.025, seed=0), config,
                                 height_offset_mm=0.5)

        def solve(reference, dtype=torch.float32):
            model = PhotometricStereo(capture.lights.to(dtype=dtype), 0.025)
            return model(capture.images[None].to(dtype), reference.to(dtype), capture.dark[None].to(dtype),
                         card.dark[None].to(dtype), card_albedo=0.8, saturation_level=1.0).normals.double()

        alone = solve(card.images[None])
        others = {"card": solve(card.images[None] * (1 + 1e-7)), "float64": solve(card.images[None], torch.float64)}
        threads = torch.get_num_threads()
        torch.set_num_threads(2 if threads == 1 else 1)
        try:
            others["threads"] = solve(card.images[None])
        finally:
            torch.set_num_threads(threads)
        for change_of, normals in others.items():
            change = angular_error_deg(alone, normals)
            assert float(change.mean()) <= 0.005 and float(change.max()) <= 1.0, (change_of, change)
