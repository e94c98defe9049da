import math

import numpy as np
import pytest
import torch

from psmini import InputError, LEDLights, PointLights, ShapeError, _chunks, ring_lights
from psmini.config import ReconstructionConfig
from psmini.flatfield import flatfield
from psmini.geometry import depth_to_points
from psmini.integrate import integrate
from psmini.metrics import angular_error_deg
from psmini.nearlight import (
    NearLightOptions,
    NearLightResult,
    RefineOptions,
    _adjugate,
    _candidates,
    _confidence,
    _integrate,
    _noise_model,
    estimate_height_offset,
    near_light_vectors,
    refine_depth,
    robust_near_light_normals,
    solve_near_light,
)
from psmini.normals import albedo_normals, normals_to_gradients
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


def _capture(size=48, offset_mm=0.5, device=None, dtype=torch.float32):
    leds = _rig(device, dtype)
    height = _bumps(size, offset_mm, device, dtype)
    normals = normals_from_height(height, PITCH)
    albedo = torch.full_like(height, 0.6)
    images = render(depth_to_points(height, PITCH), normals, albedo, leds)
    card = render(
        depth_to_points(torch.zeros_like(height), PITCH),
        normals_from_height(torch.zeros_like(height), PITCH),
        torch.full_like(height, 0.8),
        leds,
    )
    return leds, height, normals, images, card


def _glinting_tapes(seed: int):
    """The float64 capture of :func:`_capture` with metallic tapes every 15 rows (glints under some LEDs) and 1%
    noise: its images (1, K, 48, 48), light vectors and the tapes' mask."""
    leds, height, normals, _, _ = _capture(dtype=torch.float64)
    rows = torch.arange(48).view(1, 1, 48, 1).expand(1, 1, 48, 48)
    metal = (rows // 5) % 3 == 0
    images = render(depth_to_points(height, PITCH), normals, torch.where(metal, 0.25, 0.6).to(height), leds,
                    specular=torch.where(metal, 0.9, 0.0).to(height), shininess=40.0)
    noise = torch.randn(images.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    images = (images + 0.01 * images.mean() * noise).clamp_min(0)
    return images, near_light_vectors(leds, height, PITCH), metal


class TestNearLightVectors(BaseTester):
    def test_flat_card_reads_its_albedo(self, device, dtype):
        """On the card plane, flat-fielded vectors have z = 1: a flat patch of albedo ρ reads ρ under every LED."""
        vectors = near_light_vectors(
            _rig(device, dtype), torch.zeros(1, 1, 6, 6, device=device, dtype=dtype), PITCH, 0.0
        )
        self.assert_close(vectors[:, :, 2], torch.ones(1, 8, 6, 6, device=device, dtype=dtype))

    def test_raw_vectors_follow_inverse_square(self, device, dtype):
        light = PointLights(
            torch.tensor([[0.0, 0.0, 10.0]], device=device, dtype=dtype),
            torch.tensor([50.0], device=device, dtype=dtype),
        )
        vectors = near_light_vectors(light, torch.full((1, 1, 1, 1), 2.0, device=device, dtype=dtype), PITCH)
        self.assert_close(vectors[0, 0, :, 0, 0], torch.tensor([0.0, 0.0, 50.0 / 64.0], device=device, dtype=dtype))

    def test_light_below_card_raise(self):
        light = PointLights(torch.tensor([[0.0, 0.0, -5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 5.0]]))
        with pytest.raises(InputError, match="above the card"):
            near_light_vectors(light, torch.zeros(1, 1, 2, 2), PITCH, card_height_mm=0.0)

    def test_gradcheck(self):
        leds = _rig(dtype=torch.float64)
        depth = (torch.rand(1, 1, 3, 3, dtype=torch.float64) * 0.2).requires_grad_()
        positions = leds.positions_mm.clone().requires_grad_()

        def vectors(d, pos):
            return near_light_vectors(LEDLights(pos, -leds.positions_mm, leds.intensities), d, PITCH, 0.0)

        self.gradcheck(vectors, (depth, positions))

        def every_parameter(d, pos, axes, intensities, mu):  # the terms the field updates in place among them
            return near_light_vectors(LEDLights(pos, axes, intensities, mu), d, PITCH, 0.0)

        parameters = (-leds.positions_mm, leds.intensities * 1.1, torch.full_like(leds.intensities, 1.3))
        self.gradcheck(every_parameter, (depth, positions, *(t.clone().requires_grad_() for t in parameters)))


class TestRobustNormals(BaseTester):
    def test_per_pixel_lights_exact(self, device, dtype):
        leds, height, normals, images, _ = _capture(device=device, dtype=dtype)
        vectors = near_light_vectors(leds, height, PITCH)
        albedo, estimate, weights = robust_near_light_normals(images, vectors)
        self.assert_close(estimate, normals, rtol=1e-3, atol=1e-3)
        self.assert_close(albedo, torch.full_like(albedo, 0.6), rtol=1e-3, atol=1e-3)

    def test_cast_shadows_and_highlights_are_dropped(self, device, dtype):
        leds, height, normals, images, _ = _capture(device=device, dtype=dtype)
        corrupted = images.clone()
        corrupted[:, 2, 10:20, 10:20] = 0.0  # a cast shadow of LED 2
        corrupted[:, 5, 30:40, 5:15] *= 3.0  # a highlight under LED 5
        vectors = near_light_vectors(leds, height, PITCH)
        _, plain = albedo_normals(corrupted, vectors)
        _, robust, weights = robust_near_light_normals(corrupted, vectors)
        assert float(angular_error_deg(plain, normals).max()) > 5.0
        assert float(angular_error_deg(robust, normals).max()) < 0.05
        assert not bool(weights[:, 2, 10:20, 10:20].any()) and not bool(weights[:, 5, 30:40, 5:15].any())

    def test_specular_threads_are_dropped(self, device, dtype):
        """Metallic tapes (a Blinn–Phong lobe, as data_synth's lurex) on every third band: the leave-one-out test
        finds the glinting observations that a plain residual test keeps (the glint tilts the fit until the good
        observations look like the outliers); matte pixels keep all their observations."""
        leds, height, normals, _, _ = _capture(device=device, dtype=dtype)
        rows = torch.arange(48, device=device).view(1, 1, 48, 1).expand(1, 1, 48, 48)
        metal = (rows // 4) % 3 == 0
        specular = torch.where(metal, 0.9, 0.0).to(height)
        albedo = torch.where(metal, 0.25, 0.6).to(height)
        images = render(depth_to_points(height, PITCH), normals, albedo, leds, specular=specular, shininess=40.0)
        vectors = near_light_vectors(leds, height, PITCH)
        _, plain, _ = robust_near_light_normals(images, vectors, options=NearLightOptions(highlight_fraction=None))
        _, robust, weights = robust_near_light_normals(images, vectors)
        assert float(angular_error_deg(plain, normals)[metal].mean()) > 5.0
        assert float(angular_error_deg(robust, normals)[metal].mean()) < 0.6
        assert bool((weights.sum(dim=1) >= 4).all())  # a pixel keeps an overdetermined fit
        assert bool(weights.permute(0, 2, 3, 1)[~metal[:, 0]].all())

    def test_noise_is_not_a_highlight(self, device):
        """On noisy Lambertian images the threshold follows the image's noise: next to nothing is dropped."""
        leds, height, normals, images, _ = _capture(device=device, dtype=torch.float64)
        gen = torch.Generator().manual_seed(0)
        noisy = images + 0.01 * images.mean() * torch.randn(images.shape, generator=gen, dtype=images.dtype).to(device)
        vectors = near_light_vectors(leds, height, PITCH)
        _, _, without = robust_near_light_normals(noisy, vectors, options=NearLightOptions(highlight_fraction=None))
        _, _, weights = robust_near_light_normals(noisy, vectors)
        assert float((without & ~weights).sum()) < 0.002 * float(without.sum())

    def test_gain_scales_the_noise(self, device):
        """Flat-fielding by a card that two LEDs light six times more dimly multiplies the camera's noise under
        them sixfold: with the gain the noise model follows it and keeps their good observations, which a noise
        level common to every observation takes for highlights and shadows."""
        leds, height, normals, images, _ = _capture(device=device, dtype=torch.float64)
        gain = torch.ones(1, 8, 1, 1, dtype=torch.float64, device=device)
        gain[:, :2] = 6.0
        gen = torch.Generator().manual_seed(1)
        noise = torch.randn(images.shape, generator=gen, dtype=images.dtype).to(device)
        noisy = (images + 0.004 * gain * noise).clamp_min(0)
        gain = gain.expand(1, 8, 48, 48)
        vectors = near_light_vectors(leds, height, PITCH)
        options = NearLightOptions(highlight_fraction=1e-6)  # the noise alone sets the threshold
        _, _, plain = robust_near_light_normals(noisy, vectors, options=options)
        _, with_gain, weights = robust_near_light_normals(noisy, vectors, options=options, gain=gain)
        lost = lambda w: float((~w).sum()) / w.numel()  # noqa: E731  (every observation is lit and valid)
        assert lost(weights) < 0.002 and lost(plain) > 3 * lost(weights)
        assert float(angular_error_deg(with_gain, normals).mean()) < 1.0

    def test_cast_shadow_does_not_make_a_highlight(self, device):
        """A cast shadow of one LED over a noisy matte patch: the fit that keeps it is pulled below the lit
        observations, and its brightest observation would look like a highlight. The shadowed observation, the
        farther beyond its threshold, leaves instead; the brightest stays."""
        leds, height, normals, images, _ = _capture(device=device, dtype=torch.float64)
        gen = torch.Generator().manual_seed(0)
        noisy = images + 0.01 * images.mean() * torch.randn(images.shape, generator=gen, dtype=images.dtype).to(device)
        noisy[:, 3, 8:40, 8:40] = 0.02 * noisy[:, 3, 8:40, 8:40]  # LED 3 shadowed by a neighbouring yarn
        vectors = near_light_vectors(leds, height, PITCH)
        _, estimate, weights = robust_near_light_normals(noisy, vectors)
        patch = weights[:, :, 8:40, 8:40]
        assert not bool(patch[:, 3].any())
        others = torch.cat([patch[:, :3], patch[:, 4:]], dim=1)
        assert float(others.float().mean()) > 0.995
        assert float(angular_error_deg(estimate, normals)[..., 8:40, 8:40].max()) < 1.0

    def test_bands_of_rows_give_the_whole_image_selection(self, monkeypatch):
        """On the CPU the selection's rounds run in bands of rows; with bands of 8 rows (six of them, on an image
        with noise, glinting tapes and a cast shadow that cross them) the weights are the whole image's and the
        normals equal to float64 rounding."""
        import psmini.nearlight as nearlight

        images, vectors, metal = _glinting_tapes(seed=2)
        images[:, 3, 5:30, 20:44] *= 0.02  # a cast shadow over several bands
        whole = robust_near_light_normals(images, vectors)
        monkeypatch.setattr(nearlight, "_BAND_ELEMENTS", 1)  # every band _MIN_BAND_ROWS = 8 rows
        assert len(nearlight._row_bands(images)) == 6
        banded = robust_near_light_normals(images, vectors)
        assert torch.equal(banded[2], whole[2]) and not bool(whole[2][:, 3, 5:30, 20:44].any())
        assert bool((~whole[2][:, :, metal[0, 0]]).any())  # glints were dropped
        self.assert_close(banded[1], whole[1], rtol=0, atol=1e-12)
        self.assert_close(banded[0], whole[0], rtol=0, atol=1e-12)

    def test_packed_rounds_give_the_selection_of_re_solving_every_pixel(self, monkeypatch):
        """After the first update of a phase only the pixels that changed are updated and re-solved, packed: the
        weights and fits equal those of the plain loop that updates and re-solves every pixel in every round (on
        the image of glinting tapes, noise and a cast shadow), and the packing itself is lossless."""
        import psmini.nearlight as nearlight

        def every_pixel(rejection, images, vectors, used, fit, albedo, normals, mask, updates, highlight_rounds=None):
            def phase(state, rounds, highlights_only):
                used, fit, albedo, normals = state
                for _ in range(rounds):
                    new = rejection.update(vectors, fit, albedo, used, highlights_only)
                    if torch.equal(new, used):
                        break
                    used, fit, albedo, normals = nearlight._solve_selection(images, vectors, mask, new)
                return used, fit, albedo, normals

            rejection.settle_relative_noise(vectors, used, mask)
            state = phase((used, fit, albedo, normals), images.shape[1] - 3, True)
            rejection.settle_noise_model(vectors, state[1], state[2], state[0], mask)
            state = nearlight._solve_selection(images, vectors, mask, rejection.settle(state[0]))
            return phase(state, updates, False)

        images, vectors, _ = _glinting_tapes(seed=3)
        images[:, 2, 10:40, 4:30] *= 0.03  # a cast shadow
        packed = robust_near_light_normals(images, vectors, rounds=3)
        monkeypatch.setattr(nearlight, "_select", every_pixel)
        plain = robust_near_light_normals(images, vectors, rounds=3)
        assert torch.equal(packed[2], plain[2]) and bool((~plain[2][:, 2, 10:40, 4:30]).any())
        self.assert_close(packed[1], plain[1], rtol=0, atol=1e-12)
        self.assert_close(packed[0], plain[0], rtol=0, atol=1e-12)
        where = torch.rand(2, 1, 5, 6, generator=torch.Generator().manual_seed(0)) < 0.3
        pixels = nearlight._Pixels(where)
        grid = torch.randn(2, 4, 5, 6, dtype=torch.float64)
        column = pixels.take(grid)
        assert column.shape == (1, 4, 1, int(where.sum()))
        restored = torch.zeros_like(grid)
        pixels.put(restored, column)
        assert torch.equal(restored, grid * where)
        per_item = pixels.take(torch.tensor([1.0, 2.0]).view(2, 1, 1, 1)).flatten()  # a level per batch item
        assert per_item.tolist() == [1.0] * int(where[0].sum()) + [2.0] * int(where[1].sum())

    def test_candidates_match_a_count_over_the_lights(self):
        """The candidates (running top three, no count over the lights) equal the plain definition: brighter than
        the level times the brightest where three or more are, else the three brightest valid ones (ties all
        count) when the third is not zero; checked on quantised random images with ties, zeros and invalid
        observations, for 2-12 lights and a scalar or per-pixel level."""
        gen = torch.Generator().manual_seed(0)
        for count in (2, 3, 4, 8, 12):
            images = torch.round(5 * (torch.rand(2, count, 30, 30, generator=gen) - 0.3).clamp_min(0)) / 5
            valid = torch.rand(2, count, 30, 30, generator=gen) > 0.2
            for level in (0.0, 0.1, 0.5, torch.rand(2, 1, 30, 30, generator=gen)):
                ranked = images.masked_fill(~valid, -torch.inf)
                bright = valid & (images > level * ranked.amax(dim=1, keepdim=True))
                top = min(3, count)
                third = ranked.topk(top, dim=1).values[:, top - 1 : top]
                nonzero = (valid & (images > 0)).sum(dim=1, keepdim=True) >= 3
                expected = torch.where(bright.sum(dim=1, keepdim=True) >= 3, bright,
                                       valid & (ranked >= third) & nonzero)
                assert torch.equal(_candidates(images, valid, level), expected)

    def test_counts_and_box_means_equal_their_plain_definitions(self):
        """The byte counts over the lights equal a sum of the booleans (also past 255 lights, summed plainly), the
        logical choice equals torch.where on booleans, and the fill's box mean equals avg_pool2d's two 1-D passes
        to the bit, on images smaller than the window too."""
        import torch.nn.functional as F

        import psmini.nearlight as nearlight

        gen = torch.Generator().manual_seed(0)
        for count in (3, 8, 300):
            selection = torch.rand(2, count, 7, 5, generator=gen) < 0.4
            assert torch.equal(nearlight._count(selection).long(), selection.sum(dim=1, keepdim=True))
            assert nearlight._count(selection, torch.float64).dtype == torch.float64
        a, b = torch.rand(2, 8, 7, 5, generator=gen) < 0.5, torch.rand(2, 8, 7, 5, generator=gen) < 0.5
        condition = torch.rand(2, 1, 7, 5, generator=gen) < 0.5
        assert torch.equal(nearlight._choose(condition, a, b), torch.where(condition, a, b))
        k = nearlight._FILL_SIZE
        for shape in ((1, 1, 64, 48), (2, 2, 5, 3)):
            x = torch.randn(shape, generator=gen)
            plain = F.avg_pool2d(F.avg_pool2d(x, (k, 1), 1, (k // 2, 0)), (1, k), 1, (0, k // 2))
            assert torch.equal(nearlight._box(x), plain)

    def test_read_noise_ignores_lit_observations_among_the_dark(self):
        """The read noise comes from observations that the fit puts in attached shadow; lit ones among them (2%
        here, reading 0.06, as a glint-bent fit predicts) are clipped away: the estimate stays within 10% of the
        true sigma0^2 where their mean square would make it six times larger."""
        gen = torch.Generator().manual_seed(0)
        images = (0.005 * torch.randn(1, 8, 64, 64, generator=gen, dtype=torch.float64)).clamp_min(0)
        images[:, 1:][torch.rand(1, 7, 64, 64, generator=gen, dtype=torch.float64) < 0.02] = 0.06
        images[:, 0] = 1.0
        pred = torch.full_like(images, -1.0)
        pred[:, 0] = 1.0
        ones = torch.ones(1, 1, 64, 64, dtype=torch.float64)
        valid = torch.ones_like(images, dtype=torch.bool)
        floor_sq, _ = _noise_model(images, pred, valid, valid, ones, ones, None)
        assert abs(float(floor_sq) / 0.005**2 - 1) < 0.1

    def test_bad_gain_raise(self):
        images, vectors = torch.rand(1, 4, 2, 2) + 0.5, torch.rand(1, 4, 3, 2, 2)
        with pytest.raises(ShapeError, match="gain must broadcast"):
            robust_near_light_normals(images, vectors, gain=torch.ones(1, 3, 2, 2))
        with pytest.raises(InputError, match="gain must be >= 0"):
            robust_near_light_normals(images, vectors, gain=-torch.ones(1, 4, 2, 2))
        with pytest.raises(InputError, match="gain"):
            robust_near_light_normals(images, vectors, gain=torch.full((1, 1, 2, 2), float("nan")))
        with pytest.raises(ShapeError, match="gain must broadcast"):
            solve_near_light(torch.rand(1, 8, 2, 2) + 0.5, _rig(), PITCH, 0.0, gain=torch.ones(2, 8, 2))

    def test_bad_options_raise(self):
        with pytest.raises(InputError, match="outlier_fraction"):
            NearLightOptions(outlier_fraction=0.0)
        with pytest.raises(InputError, match="highlight_fraction"):
            NearLightOptions(highlight_fraction=0.0)
        with pytest.raises(InputError, match="rounds"):
            robust_near_light_normals(torch.rand(1, 4, 2, 2), torch.rand(1, 4, 3, 2, 2), rounds=-1)
        with pytest.raises(ShapeError, match="light_vectors"):
            robust_near_light_normals(torch.rand(1, 4, 2, 2), torch.rand(1, 5, 3, 2, 2))

    def test_per_pixel_shape_mismatch_raise(self):
        with pytest.raises(ShapeError, match="per-pixel lights"):
            albedo_normals(torch.rand(1, 4, 2, 2), torch.rand(1, 4, 3, 2, 3))

    def test_gradcheck_per_pixel_solve(self):
        vectors = (
            torch.rand(1, 5, 3, 2, 2, dtype=torch.float64)
            + torch.tensor([0, 0, 1.0], dtype=torch.float64).view(1, 1, 3, 1, 1)
        ).requires_grad_()
        images = (torch.rand(1, 5, 2, 2, dtype=torch.float64) + 0.5).requires_grad_()
        self.gradcheck(lambda i, v: albedo_normals(i, v), (images, vectors))


def _flat(images, card):
    return flatfield(images, card, card_albedo=0.8)


class TestNearLightOptions:
    def test_defaults_validate_and_serialise(self):
        options = NearLightOptions()
        assert NearLightOptions(**options.to_dict()) == options
        assert options.replace(max_iterations=3).max_iterations == 3

    @pytest.mark.parametrize("bad", [dict(max_iterations=0), dict(tolerance_deg=0.0), dict(change_percentile=1.5),
                                     dict(search_mm=(1.0, -1.0)), dict(shadow_fraction=1.0), dict(integrator="nope"),
                                     dict(estimate_offset=1), dict(estimate_tilt="yes"),
                                     dict(initial_height_mm=float("nan"))])
    def test_bad_values_raise(self, bad):
        with pytest.raises(InputError, match="NearLightOptions"):
            NearLightOptions(**bad)

    def test_unknown_name_raise(self):
        with pytest.raises(InputError, match="unknown near-light options"):
            NearLightOptions().replace(iterations=3)


class TestSolveNearLight(BaseTester):
    @pytest.mark.parametrize("offset_mm", [0.0, 1.0])
    def test_recovers_normals_and_height(self, device, offset_mm):
        leds, height, normals, images, card = _capture(offset_mm=offset_mm, device=device, dtype=torch.float64)
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        errors = angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2]  # borders: one-sided differences
        assert float(errors.mean()) < 0.05
        assert abs(float(result.offset_mm[0]) - float(height.mean())) < 0.01  # absolute height found, mm
        assert float((result.depth - height).abs().max()) < 0.02
        assert result.converged and 2 <= result.iterations <= NearLightOptions().max_iterations * 2

    def test_masked_integrator_agrees(self):
        leds, height, normals, images, card = _capture(offset_mm=0.5, dtype=torch.float64)
        flat = _flat(images, card)
        result = solve_near_light(
            flat.images, leds, PITCH, 0.0, flat.valid, options=NearLightOptions(integrator="masked")
        )
        assert float(angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2].mean()) < 0.05
        assert float((result.depth - height).abs().max()) < 0.02

    def test_batch_equals_items(self):
        """Each batch item gets its own offset and the same answer as alone."""
        a = _capture(size=32, offset_mm=0.2, dtype=torch.float64)
        b = _capture(size=32, offset_mm=0.8, dtype=torch.float64)
        flat = _flat(torch.cat([a[3], b[3]]), a[4])
        both = solve_near_light(flat.images, a[0], PITCH, 0.0, flat.valid)
        for item in (0, 1):  # converged items leave the batch: each ends where it ends alone
            alone = solve_near_light(flat.images[item : item + 1], a[0], PITCH, 0.0, flat.valid[item : item + 1])
            self.assert_close(both.depth[item : item + 1], alone.depth, rtol=0, atol=1e-5)
            self.assert_close(both.normals[item : item + 1], alone.normals, rtol=0, atol=1e-6)
        assert abs(float(both.offset_mm[0]) - 0.2) < 0.02 and abs(float(both.offset_mm[1]) - 0.8) < 0.02

    def test_items_leave_the_batch_when_they_converge(self):
        """A clean and a noisy capture converge after different numbers of alternations: in one batch each still
        ends exactly where it ends alone (the clean one stopped, not dragged along by the noisy one)."""
        leds, _, _, images, card = _capture(size=32, offset_mm=0.8, dtype=torch.float64)
        noise = 0.01 * images.amax() * torch.randn(images.shape, generator=torch.Generator().manual_seed(0),
                                                   dtype=torch.float64)
        flat = _flat(torch.cat([images, (images + noise).clamp_min(0)]), card)
        options = NearLightOptions(tolerance_deg=0.001)
        both = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid, options=options)
        alone = [solve_near_light(flat.images[i : i + 1], leds, PITCH, 0.0, flat.valid[i : i + 1], options=options)
                 for i in (0, 1)]
        assert alone[0].iterations < alone[1].iterations == both.iterations and both.converged
        for item in (0, 1):
            self.assert_close(both.depth[item : item + 1], alone[item].depth, rtol=0, atol=1e-9)
            self.assert_close(both.normals[item : item + 1], alone[item].normals, rtol=0, atol=1e-9)

    def test_cpu_chunks_give_the_batch_answer(self, monkeypatch):

        a = _capture(size=32, offset_mm=0.2, dtype=torch.float64)
        b = _capture(size=32, offset_mm=0.8, dtype=torch.float64)
        flat = _flat(torch.cat([a[3], b[3], a[3]]), a[4])
        whole = solve_near_light(flat.images, a[0], PITCH, 0.0, flat.valid)
        monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 2 * flat.images[0].numel())  # chunks of 2 and 1
        chunked = solve_near_light(flat.images, a[0], PITCH, 0.0, flat.valid)
        for name in ("depth", "normals", "albedo", "offset_mm"):
            self.assert_close(getattr(chunked, name), getattr(whole, name), rtol=0, atol=1e-9)
        assert torch.equal(chunked.weights, whole.weights) and torch.equal(chunked.mask, whole.mask)
        assert (chunked.iterations, chunked.converged) == (whole.iterations, whole.converged)
        assert len(chunked.changes_deg) == len(whole.changes_deg)

    def test_distant_assumption_is_much_worse(self):
        """The reason the module exists: least squares with the lights seen from the centre errs by degrees."""
        leds, height, normals, images, card = _capture(offset_mm=1.0)
        far = PhotometricStereo(leds, PITCH, ReconstructionConfig(solver="distant"))(images, card, card_albedo=0.8)
        near = PhotometricStereo(leds, PITCH, ReconstructionConfig(solver="near"))(images, card, card_albedo=0.8)
        far_error = float(angular_error_deg(far.normals, normals).mean())
        near_error = float(angular_error_deg(near.normals, normals).mean())
        assert far_error > 10 * near_error and far_error > 0.5

    def test_raw_images_without_card(self):
        """Without a card the height is weakly observable (inverse-square variation only): tens of µm, 0.1°."""
        leds, height, normals, images, _ = _capture(offset_mm=0.3, dtype=torch.float64)
        result = solve_near_light(images * 0.7, leds, PITCH, None)  # unknown camera gain
        far = PhotometricStereo(leds, PITCH, ReconstructionConfig(solver="distant"))(images * 0.7)
        near_error = float(angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2].mean())
        assert near_error < 0.2
        assert float(angular_error_deg(far.normals, normals).mean()) > 20 * near_error
        assert abs(float(result.offset_mm[0]) - 0.3) < 0.1

    def test_fixed_offset_keeps_initial_height(self):
        leds, height, normals, images, card = _capture(offset_mm=0.4, dtype=torch.float64)
        flat = _flat(images, card)
        options = NearLightOptions(initial_height_mm=float(height.mean()), estimate_offset=False)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid, options=options)
        assert abs(float(result.depth.mean() - height.mean())) < 1e-9

    def test_unsolved_pits_are_no_spikes(self):
        """Pixels no light reaches (zero in every image) stay unsolved, and their depth is filled from their rims:
        never the solver's 0 plus the offset, a spike of the cloth's whole height."""
        leds, height, normals, images, card = _capture(offset_mm=1.0, dtype=torch.float64)
        images = images.clone()
        images[..., 20:23, 20:23] = 0.0
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        assert not bool(result.mask[..., 20:23, 20:23].any())
        assert float((result.depth - height)[..., 18:25, 18:25].abs().max()) < 0.05

    def test_a_fit_facing_away_is_no_spike(self):
        """A pixel whose three usable observations fit a normal facing away from the camera (n_z < 0, an albedo six
        times the cloth's: what a knit's crevices give), beside an unsolved one: its capped slope (1/min_nz) gets
        no confidence, so the depth around it stays on the surface (it stood 0.4 mm off, its unsolved neighbour
        2.1 mm, while the even power of n_z in the confidence weighted it as a well-seen facet)."""
        leds, height, normals, images, card = _capture(offset_mm=0.5, dtype=torch.float64)
        flat = _flat(images, card)
        row, col = 24, 24
        lights = near_light_vectors(leds, height, PITCH, 0.0)[0, :, :, row, col]  # (K, 3), flat-fielded
        reading = lights @ torch.tensor([0.0, 3.0, -2.0], dtype=torch.float64)  # rho n with n_z = -0.55
        assert int((reading > 0).sum()) == 3
        doctored = flat.images.clone()
        doctored[0, :, row, col] = reading.clamp_min(0)
        doctored[0, :, row + 1, col : col + 2] = 0.0  # a crevice no LED reaches
        result = solve_near_light(doctored, leds, PITCH, 0.0, flat.valid)
        assert bool(result.mask[0, 0, row, col]) and float(result.normals[0, 2, row, col]) < 0
        assert float((result.depth - height)[..., row - 3 : row + 4, col - 3 : col + 4].abs().max()) < 0.05

    def test_lost_steps_are_found_as_a_tilt(self):
        """Courses that rise gently and drop by a cliff (a purl's rows of loops): the cliffs' steep slopes have
        little confidence, so integration loses every drop and the drops add up to a tilt across the field. The
        images' near-light cue finds that tilt (estimate_tilt): the height is right again, and the tilt found is the
        plane of the error made without it."""
        dtype = torch.float64
        leds = _rig(dtype=dtype)
        coords = (torch.arange(48, dtype=dtype) - 23.5) * PITCH
        y, x = torch.meshgrid(-coords, coords, indexing="ij")
        height = (0.2 * torch.remainder(y, 0.8) / 0.8 + 0.5 + 0.03 * torch.sin(2 * math.pi * x / 1.3))[None, None]
        images = render(depth_to_points(height, PITCH), normals_from_height(height, PITCH),
                        torch.full_like(height, 0.6), leds)
        flat_card = torch.zeros_like(height)
        card = render(depth_to_points(flat_card, PITCH), normals_from_height(flat_card, PITCH),
                      torch.full_like(height, 0.8), leds)
        flat = _flat(images, card)
        plain = solve_near_light(
            flat.images, leds, PITCH, 0.0, flat.valid, options=NearLightOptions(estimate_tilt=False)
        )
        found = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)

        def error(result):
            difference = (result.depth - height)[0, 0]
            return difference - difference.mean()

        design = torch.stack([torch.ones_like(x), x, y], dim=-1).view(-1, 3)
        plane = torch.linalg.lstsq(design, error(plain).reshape(-1, 1)).solution[1:, 0]  # mm per mm
        assert float(plain.tilt.abs().max()) == 0.0 and float(plane[1]) > 0.03  # the lost drops: > 30 µm/mm
        assert float((found.tilt[0] + plane).abs().max()) < 0.15 * float(plane.abs().max())
        rmse = [float(error(r).square().mean().sqrt()) for r in (plain, found)]
        assert rmse[1] < 0.3 * rmse[0]

    def test_no_tilt_from_noise(self):
        """A smooth surface loses no step: on noisy 64-pixel captures (1% noise, where the tilt's standard error is
        20-40 µm/mm) the tilt stays 0 and the depth is the one without the estimate, seed after seed."""
        leds, height, normals, images, card = _capture(size=64, offset_mm=0.5, dtype=torch.float64)
        for seed in range(4):
            noise = 0.01 * images.amax() * torch.randn(images.shape, generator=torch.Generator().manual_seed(seed),
                                                       dtype=torch.float64)
            flat = _flat((images + noise).clamp_min(0), card)
            result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
            plain = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid,
                                     options=NearLightOptions(estimate_tilt=False))
            assert torch.equal(result.tilt, torch.zeros_like(result.tilt)), seed
            self.assert_close(result.depth, plain.depth, rtol=0, atol=1e-12)

    def test_steep_unconfident_slopes_do_not_tilt_the_surface(self):
        """A plateau with a few pixels whose slopes are wildly wrong but barely determined (seen by three grazing
        lights): inverse-variance confidence keeps them from bending the integrated surface."""
        height = torch.zeros(1, 1, 40, 40, dtype=torch.float64)
        normals = normals_from_height(height, PITCH)
        p, q = normals_to_gradients(normals)
        wrong = torch.zeros_like(height, dtype=torch.bool)
        wrong[..., 5:35:6, 10] = True
        p = torch.where(wrong, torch.full_like(p, 3.0), p)  # 3 mm/mm slopes where the plateau is flat
        confidence = torch.where(wrong, torch.full_like(p, 1e-3), torch.ones_like(p))
        domain = torch.ones_like(wrong)
        for method in ("fill", "masked"):
            z = _integrate(p, q, confidence, domain, method, PITCH, None, False)
            assert float(z.max() - z.min()) < 0.005, method  # mm; unweighted the wrong slopes step by 0.3 mm
        plain = integrate(p, q, method="masked", pixel_pitch_mm=PITCH)
        assert float(plain.max() - plain.min()) > 0.05

    def test_confidence_of_a_flat_patch(self):
        """Four symmetric lights on a flat patch: every pixel equally confident (1), rims of a gap capped."""
        vectors = torch.tensor([[1.0, 0, 1], [-1.0, 0, 1], [0, 1.0, 1], [0, -1.0, 1]])[None, :, :, None, None]
        vectors = vectors.expand(1, 4, 3, 6, 6)
        lx, ly, lz = vectors.unbind(2)
        solved = torch.ones(1, 1, 6, 6, dtype=torch.bool)
        solved[..., 2, 2] = False
        normals = torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1).expand(1, 3, 6, 6)
        used = torch.ones(1, 4, 6, 6, dtype=torch.bool)
        matrix = _adjugate(lx, ly, lz, used)
        conf, noisy = _confidence((torch.ones(1, 1, 6, 6), normals, solved), matrix, used, torch.ones_like(solved))
        assert noisy.sum() == 1 and bool(noisy[0, 0, 2, 2])  # without a noise model only the unsolved pixel
        assert float(conf[0, 0, 5, 5]) == 1.0 and float(conf[0, 0, 2, 2]) == 0.0
        assert float(conf[0, 0, 2, 3]) == pytest.approx(0.01)

    def test_confidence_of_a_normal_facing_away(self):
        """n_z <= 0 has no usable slope: confidence 0 and noisy (filled), where the mirrored normal keeps its own."""
        vectors = torch.tensor([[1.0, 0, 1], [-1.0, 0, 1], [0, 1.0, 1], [0, -1.0, 1]])[None, :, :, None, None]
        lx, ly, lz = vectors.expand(1, 4, 3, 1, 2).unbind(2)
        normals = torch.tensor([[0.0, 0.6], [0.0, 0.6], [0.8, -0.8]]).view(1, 3, 1, 2)  # n_z = +0.8 and -0.8
        used = torch.ones(1, 4, 1, 2, dtype=torch.bool)
        solved = torch.ones(1, 1, 1, 2, dtype=torch.bool)
        conf, noisy = _confidence((torch.ones(1, 1, 1, 2), normals, solved), _adjugate(lx, ly, lz, used), used,
                                  torch.ones_like(solved), torch.tensor(1e-6).view(1, 1, 1, 1))
        assert float(conf[0, 0, 0, 0]) > 0.5 and float(conf[0, 0, 0, 1]) == 0.0
        assert not bool(noisy[0, 0, 0, 0]) and bool(noisy[0, 0, 0, 1])

    def test_iterations_reported_and_capped(self):
        leds, _, _, images, card = _capture(size=24)
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid, options=NearLightOptions(max_iterations=1))
        assert result.iterations == 1 and not result.converged and result.changes_deg == ()

    def test_module_equals_stage(self):
        leds, _, _, images, card = _capture(size=24)
        # LEDs: near
        module = PhotometricStereo(leds, PITCH, ReconstructionConfig(near=NearLightOptions(max_iterations=2)))
        a = module(images, card, card_albedo=0.8)
        flat = _flat(images, card)
        b = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid, options=NearLightOptions(max_iterations=2))
        self.assert_close(a.normals, b.normals, rtol=1e-3, atol=1e-3)  # float32 rounding of a different path
        self.assert_close(a.depth, b.depth, rtol=1e-3, atol=1e-4)

    def test_module_bad_option_raise_before_work(self):
        with pytest.raises(InputError, match="iterations"):
            PhotometricStereo(_rig(), PITCH, ReconstructionConfig(near={"iterations": 2}))
        with pytest.raises(InputError, match="near solver weights its own"):
            PhotometricStereo(
                _rig(), PITCH, ReconstructionConfig(integrator="fc", integrator_options={"boundary": "mirror"})
            )

    def test_gradcheck(self):
        """Through the last solve: intensities and the LEDs' positions (float64, a small case). The depth that
        the alternation found is not differentiated (a search); its effect on the normals is second order, about
        1e-4 of the first-order terms here, hence the tolerance."""
        leds, _, _, images, card = _capture(size=8, dtype=torch.float64)
        flat = _flat(images, card)
        options = NearLightOptions(max_iterations=1, estimate_offset=False, initial_height_mm=0.5)
        directions, intensities = leds.principal_directions.detach(), leds.intensities.detach()

        def normals(i, positions):
            lights = LEDLights(positions, directions, intensities)
            return solve_near_light(i, lights, PITCH, 0.0, options=options).normals

        self.gradcheck(
            normals,
            (flat.images.clone().requires_grad_(), leds.positions_mm.detach().clone().requires_grad_()),
            atol=1e-4,
            rtol=1e-3,
            fast_mode=True,
        )
        # the positions alone, every derivative (fast mode's projections missed a gradient that never reached them)
        self.gradcheck(lambda positions: normals(flat.images, positions),
                       (leds.positions_mm.detach().clone().requires_grad_(),), atol=1e-4, rtol=1e-3)

    def test_learnable_led_model_gets_gradients(self):
        """Every parameter of a learnable LED model, mu at 1 included, receives the gradient of its central
        difference through the last solve (the alternations run without gradients)."""
        leds, _, _, images, card = _capture(size=8, dtype=torch.float64)
        flat = _flat(images, card)
        options = NearLightOptions(max_iterations=1, estimate_offset=False, initial_height_mm=0.5)
        model = LEDLights(leds.positions_mm.detach(), leds.principal_directions.detach(), leds.intensities.detach(),
                          learnable=True).double()

        def loss() -> torch.Tensor:
            return solve_near_light(flat.images, model, PITCH, 0.0, options=options).normals[:, 0].sum()

        loss().backward()
        with torch.no_grad():
            for name, parameter in model.named_parameters():
                index, step = (0,) * parameter.ndim, 1e-6
                parameter[index] += step
                up = loss()
                parameter[index] -= 2 * step
                down = loss()
                parameter[index] += step
                numerical = float((up - down) / (2 * step))
                assert parameter.grad is not None, name
                assert float(parameter.grad[index]) == pytest.approx(numerical, rel=0.02, abs=1e-5), name

    def test_count_mismatch_raise(self):
        with pytest.raises(ShapeError, match="8 lights"):
            solve_near_light(torch.rand(1, 6, 8, 8), _rig(), PITCH, 0.0)

    def test_nan_raise(self):
        images = torch.rand(1, 8, 8, 8)
        images[0, 1, 2, 3] = float("nan")
        with pytest.raises(InputError, match="finite"):
            solve_near_light(images, _rig(), PITCH, 0.0)

    def test_bad_inputs_raise(self):
        with pytest.raises(InputError, match="point or LED"):
            solve_near_light(torch.rand(1, 8, 8, 8), ring_lights(8, 55.0), PITCH, 0.0)
        with pytest.raises(InputError, match="options"):
            solve_near_light(torch.rand(1, 8, 8, 8), _rig(), PITCH, 0.0, options=dict(max_iterations=2))
        with pytest.raises(ShapeError, match="valid"):
            solve_near_light(torch.rand(1, 8, 8, 8), _rig(), PITCH, 0.0, valid=torch.ones(1, 8, 4, 4, dtype=torch.bool))
        with pytest.raises(InputError, match="card_height_mm"):
            solve_near_light(torch.rand(1, 8, 8, 8), _rig(), PITCH, float("inf"))
        with pytest.raises(InputError, match="search_mm"):
            estimate_height_offset(torch.rand(1, 8, 8, 8), _rig(), torch.zeros(1, 1, 8, 8), PITCH,
                                   torch.ones(1, 8, 8, 8, dtype=torch.bool), search_mm=(1.0, -1.0))


class TestKeptGainTerms:
    """The gain's noise scales and 2 x 2 average are kept while its data live unchanged (psmini.nearlight._kept)."""

    def test_kept_equal_fresh_and_follow_changes(self):
        from psmini import nearlight

        gain = torch.rand(1, 8, 16, 16) + 0.5
        gain[0, 3, :2] = 0  # untrusted card pixels
        images = torch.rand(1, 8, 16, 16)
        first = nearlight._noise_scales(gain, images)
        assert torch.equal(first, nearlight._relative_gain(gain, images))
        assert nearlight._noise_scales(gain, images) is first  # kept
        pooled = nearlight._pooled_gain(gain, images)
        assert torch.equal(pooled, torch.nn.functional.avg_pool2d(gain, 2))
        assert nearlight._pooled_gain(gain, images) is pooled
        gain[0, 5] *= 3  # an in-place change: computed again
        changed = nearlight._noise_scales(gain, images)
        assert changed is not first and torch.equal(changed, nearlight._relative_gain(gain, images))
        assert not torch.equal(changed, first)

    def test_freed_gain_is_forgotten(self):
        from psmini import nearlight

        gain = torch.rand(1, 8, 16, 16) + 0.5
        nearlight._noise_scales(gain, torch.rand(1, 8, 16, 16))
        count = len(nearlight._kept_gains)
        del gain
        assert len(nearlight._kept_gains) == count - 1

    def test_eviction_frees_derived_terms_without_deadlock(self):
        """Dropping the oldest gain frees its pooled gain, whose own entry's weak reference callback then takes
        the (re-entrant) lock while it is held."""
        import threading

        from psmini import nearlight

        images = torch.rand(1, 8, 16, 16)

        def fill():
            for _ in range(3 * nearlight._KEPT_GAINS):
                gain = torch.rand(1, 8, 16, 16) + 0.5
                nearlight._noise_scales(nearlight._pooled_gain(gain, images), images[..., ::2, ::2])
                del gain

        worker = threading.Thread(target=fill, daemon=True)
        worker.start()
        worker.join(timeout=30)
        assert not worker.is_alive()
        assert len(nearlight._kept_gains) <= nearlight._KEPT_GAINS

    def test_gain_that_needs_a_gradient_is_not_kept(self):
        from psmini import nearlight

        gain = (torch.rand(1, 8, 16, 16) + 0.5).requires_grad_()
        images = torch.rand(1, 8, 16, 16)
        assert nearlight._noise_scales(gain, images) is not nearlight._noise_scales(gain, images)


class TestKeptLightFields:
    """Light fields are kept by the light model's values (psmini.nearlight._light_field)."""

    def test_same_values_share_a_field_and_equal_a_fresh_one(self):
        from psmini import nearlight

        like = torch.zeros(1, 8, 24, 20)
        first = nearlight._light_field(_rig(), 24, 20, PITCH, 0.0, like, 2)
        again = nearlight._light_field(_rig(), 24, 20, PITCH, 0.0, like, 2)  # another model object, same values
        assert again is first
        depth = torch.full((1, 1, 12, 10), 0.4)
        fresh = nearlight._LightField(_rig(), 24, 20, PITCH, 0.0, like, 2)
        for kept, expected in zip(first(depth), fresh(depth), strict=True):
            assert torch.equal(kept, expected)

    def test_every_nth_pixel_equals_the_field_at_that_stride(self):
        """The offset scan's field (every second pixel of a stride-2 field: views of its terms) equals the field
        built at stride 4, for an LED model (card scale and lobe) and for a model evaluated through its forward;
        the noise statistics' sampling reads every second row and column only from 4 x 2^15 pixels on."""
        from psmini import nearlight
        like = torch.zeros(1, 8, 24, 20)
        depth = torch.rand(1, 1, 6, 5, generator=torch.Generator().manual_seed(0))
        class Wrapped(torch.nn.Module):  # not a point model: the field evaluates its forward on its grid's points
            def __init__(self, inner):
                super().__init__()
                self.inner, self.count = inner, inner.count

            def forward(self, points):
                return self.inner(points)

        for model in (_rig(), PointLights(_rig().positions_mm), Wrapped(_rig())):
            sub = nearlight._LightField(model, 24, 20, PITCH, 0.0, like, 2).every(2)
            direct = nearlight._LightField(model, 24, 20, PITCH, 0.0, like, 4)
            assert sub.shape == direct.shape and sub.stride == 4
            for a, b in zip(sub(depth), direct(depth), strict=True):
                assert torch.equal(a, b)
        assert nearlight._noise_sample(torch.zeros(1, 8, 362, 362))(like) is like  # 131,044 pixels: all
        assert nearlight._noise_sample(torch.zeros(1, 8, 400, 400))(like).shape == (1, 8, 12, 10)
        assert nearlight._noise_sample(like)(1.0) == 1.0 and nearlight._noise_sample(like)(None) is None

    def test_other_values_or_grids_get_their_own(self):
        from psmini import nearlight

        like = torch.zeros(1, 8, 24, 20)
        first = nearlight._light_field(_rig(), 24, 20, PITCH, 0.0, like)
        moved = _rig()
        moved.positions_mm[0, 0] += 0.5
        assert nearlight._light_field(moved, 24, 20, PITCH, 0.0, like) is not first
        assert nearlight._light_field(_rig(), 24, 20, PITCH, 0.5, like) is not first  # card height
        assert nearlight._light_field(_rig(), 24, 20, PITCH, 0.0, like.double()) is not first

    def test_models_that_need_gradients_and_large_fields_are_not_kept(self, monkeypatch):
        from psmini import nearlight

        like = torch.zeros(1, 8, 24, 20)
        ring = _rig()
        learnable = LEDLights(ring.positions_mm, ring.principal_directions, ring.intensities, learnable=True)
        assert nearlight._light_field(learnable, 24, 20, PITCH, 0.0, like) is not \
            nearlight._light_field(learnable, 24, 20, PITCH, 0.0, like)
        monkeypatch.setattr(nearlight, "_KEPT_FIELD_BYTES", 1000)
        nearlight._kept_fields.clear()
        nearlight._light_field(_rig(), 24, 20, PITCH, 0.0, like)
        assert not nearlight._kept_fields


class TestSimulatedKnit:
    def test_depth_has_no_spikes(self, tmp_path):
        """`psmini synth knit` reconstructed as `psmini reconstruct` does (noisy 10-bit capture, its card, near
        light): no solved pixel more than 0.3 mm from the simulator's height (there were 105, up to 1.7 mm, beside
        unsolved crevices, while fitted normals facing away from the camera had weight), and the describe step's
        kurtosis is that of a relief, not of spikes (it read 1237)."""
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
        assert int((error.abs() > 0.3).sum()) == 0, float(error.abs().max())
        assert describe(result.depth, sample.pixel_pitch_mm, result.mask)[0]["iso25178"]["Sku"] < 10


class TestNoiseFloorFits:
    def test_flags_the_fits_to_a_shadow(self, tmp_path):
        """`psmini synth net` (200 px, noisy 10-bit): the solved pixels fitted to three observations with one at the
        noise floor are flagged; they are exactly three-observation fits, and their normals err tens of degrees
        where the others err about one (35 against 1.1 deg when written)."""
        from data_synth.rig import write_synthetic_capture
        from psmini import reconstruct
        from psmini.io import load_sample

        sample_dir, _ = write_synthetic_capture(tmp_path, "net", seed=0, size=200)
        sample = load_sample(sample_dir)
        result = reconstruct(sample)
        flagged, solved = result.at_noise_floor[0, 0], result.mask[0, 0]
        error = angular_error_deg(result.normals, sample.normals_gt[None])[0, 0]
        assert int(flagged.sum()) > 100 and bool((flagged <= solved).all())
        assert bool((result.weights[0].sum(0)[flagged] == 3).all())
        assert float(error[flagged].mean()) > 10 * float(error[solved & ~flagged].mean())
        from psmini.evaluation import evaluation_mask, score_reconstruction

        scores, scored = score_reconstruction(result, sample), evaluation_mask(sample, error.device)[0, 0]
        assert scores["noise_floor_pixels"] == int((flagged & scored).sum()) > 0
        assert scores["noise_floor_error_deg"] == pytest.approx(float(error[flagged & scored].mean()), rel=1e-4)
        distant = reconstruct(sample, ReconstructionConfig(solver="distant"))
        assert "noise_floor_pixels" not in score_reconstruction(distant, sample)

    def test_none_where_every_light_reaches(self):
        leds, _, _, images, card = _capture(size=24)
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        assert result.at_noise_floor.shape == (1, 1, 24, 24) and not bool(result.at_noise_floor.any())
        both = NearLightResult.concatenate([result, result])
        assert both.at_noise_floor.shape == (2, 1, 24, 24)

    def test_moves_to_a_device_whole(self):
        """``to`` keeps a near-light result's type and its diagnostics (it failed on the iteration count)."""
        leds, _, _, images, card = _capture(size=24)
        flat = _flat(images, card)
        result = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        moved = result.to("cpu")
        assert isinstance(moved, NearLightResult) and moved.iterations == result.iterations > 0
        assert moved.converged == result.converged and torch.equal(moved.at_noise_floor, result.at_noise_floor)
        assert torch.equal(moved.weights, result.weights) and torch.equal(moved.depth, result.depth)

    def test_item_of_a_batch_keeps_the_diagnostics(self):
        """``item`` (what ``psmini.batch`` hands each sample) keeps a near-light result's type and its flags."""
        leds, _, _, images, card = _capture(size=24)
        flat = _flat(images, card)
        single = solve_near_light(flat.images, leds, PITCH, 0.0, flat.valid)
        both = NearLightResult.concatenate([single, single.to("cpu")])
        second = both.item(-1)
        assert isinstance(second, NearLightResult) and second.iterations == single.iterations
        for name in ("albedo", "normals", "depth", "mask", "weights", "offset_mm", "tilt", "at_noise_floor"):
            assert torch.equal(getattr(second, name), getattr(single, name)), name
        with pytest.raises(InputError, match="index 2 is outside the batch of 2"):
            both.item(2)


class TestRefineDepth(BaseTester):
    def test_reduces_smooth_depth_error(self):
        leds, height, normals, images, card = _capture(offset_mm=0.5, dtype=torch.float64)
        flat = images / card * 0.8
        coords = torch.linspace(-1, 1, 48, dtype=torch.float64)
        y, x = torch.meshgrid(coords, coords, indexing="ij")
        start = height + 0.3 * (1 - x**2 - y**2)[None, None]  # a 0.3 mm dome, the distant-light artefact
        depth, albedo, losses = refine_depth(
            flat, leds, start, PITCH, card_height_mm=0.0, options=RefineOptions(steps=40)
        )
        before, after = start - height, depth - height

        def rms(depth):
            return float((depth - depth.mean()).square().mean().sqrt())

        assert rms(after) < 0.05 * rms(before)
        assert abs(float(after.mean())) < 0.01  # the absolute height too, mm
        self.assert_close(albedo[..., 2:-2, 2:-2], torch.full_like(albedo[..., 2:-2, 2:-2], 0.6), rtol=0, atol=0.02)

    def test_bad_scales_raise(self):
        with pytest.raises(InputError, match="scales"):
            RefineOptions(scales=(0,))
        with pytest.raises(InputError, match="RefineOptions"):
            refine_depth(torch.rand(1, 8, 8, 8), _rig(), torch.zeros(1, 1, 8, 8), PITCH, options=dict(steps=3))
