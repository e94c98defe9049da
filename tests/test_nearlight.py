import math

import pytest
import torch

from psmini import InputError, LEDLights, PointLights, ShapeError, ring_lights
from psmini.geometry import depth_to_points
from psmini.integrate import integrate
from psmini.nearlight import (
    _integrate_solved,
    estimate_height_offset,
    near_light_photometric_stereo,
    near_light_vectors,
    refine_depth,
    robust_near_light_normals,
)
from psmini.metrics import angular_error_deg
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
    card = render(depth_to_points(torch.zeros_like(height), PITCH), normals_from_height(torch.zeros_like(height), PITCH),
                  torch.full_like(height, 0.8), leds)
    return leds, height, normals, images, card


class TestNearLightVectors(BaseTester):
    def test_flat_card_reads_its_albedo(self, device, dtype):
        """On the card plane, flat-fielded vectors have z = 1: a flat patch of albedo ρ reads ρ under every LED."""
        vectors = near_light_vectors(_rig(device, dtype), torch.zeros(1, 1, 6, 6, device=device, dtype=dtype), PITCH, 0.0)
        self.assert_close(vectors[:, :, 2], torch.ones(1, 8, 6, 6, device=device, dtype=dtype))

    def test_raw_vectors_follow_inverse_square(self, device, dtype):
        light = PointLights(torch.tensor([[0.0, 0.0, 10.0]], device=device, dtype=dtype), torch.tensor([50.0], device=device, dtype=dtype))
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
        _, plain, _ = robust_near_light_normals(images, vectors, highlight_fraction=None)
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
        _, _, without = robust_near_light_normals(noisy, vectors, highlight_fraction=None)
        _, _, weights = robust_near_light_normals(noisy, vectors)
        assert float((without & ~weights).sum()) < 0.002 * float(without.sum())

    def test_bad_options_raise(self):
        with pytest.raises(InputError, match="outlier_fraction"):
            robust_near_light_normals(torch.rand(1, 4, 2, 2), torch.rand(1, 4, 3, 2, 2), outlier_fraction=0.0)
        with pytest.raises(InputError, match="highlight_fraction"):
            robust_near_light_normals(torch.rand(1, 4, 2, 2), torch.rand(1, 4, 3, 2, 2), highlight_fraction=0.0)

    def test_per_pixel_shape_mismatch_raise(self):
        with pytest.raises(ShapeError, match="per-pixel lights"):
            albedo_normals(torch.rand(1, 4, 2, 2), torch.rand(1, 4, 3, 2, 3))

    def test_gradcheck_per_pixel_solve(self):
        vectors = (torch.rand(1, 5, 3, 2, 2, dtype=torch.float64) + torch.tensor([0, 0, 1.0], dtype=torch.float64).view(1, 1, 3, 1, 1)).requires_grad_()
        images = (torch.rand(1, 5, 2, 2, dtype=torch.float64) + 0.5).requires_grad_()
        self.gradcheck(lambda i, v: albedo_normals(i, v), (images, vectors))


class TestNearLightPhotometricStereo(BaseTester):
    @pytest.mark.parametrize("offset_mm", [0.0, 1.0])
    def test_recovers_normals_and_height(self, device, offset_mm):
        leds, height, normals, images, card = _capture(offset_mm=offset_mm, device=device, dtype=torch.float64)
        result = near_light_photometric_stereo(images, leds, PITCH, reference=card, card_albedo=0.8)
        errors = angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2]  # borders: one-sided differences
        assert float(errors.mean()) < 0.05
        assert abs(float(result.offset_mm[0]) - float(height.mean())) < 0.01  # absolute height found, mm
        assert float((result.depth - height).abs().max()) < 0.02

    def test_distant_assumption_is_much_worse(self):
        """The reason the module exists: least squares with the lights seen from the centre errs by degrees."""
        leds, height, normals, images, card = _capture(offset_mm=1.0)
        far = PhotometricStereo(leds, pixel_pitch_mm=PITCH, solver="distant")(images, card, card_albedo=0.8)
        near = near_light_photometric_stereo(images, leds, PITCH, reference=card, card_albedo=0.8)
        far_error = float(angular_error_deg(far.normals, normals).mean())
        near_error = float(angular_error_deg(near.normals, normals).mean())
        assert far_error > 10 * near_error and far_error > 0.5

    def test_raw_images_without_card(self):
        """Without a card the height is weakly observable (inverse-square variation only): tens of µm, 0.1°."""
        leds, height, normals, images, _ = _capture(offset_mm=0.3, dtype=torch.float64)
        result = near_light_photometric_stereo(images * 0.7, leds, PITCH)  # unknown camera gain
        far = PhotometricStereo(leds, pixel_pitch_mm=PITCH, solver="distant")(images * 0.7)
        near_error = float(angular_error_deg(result.normals, normals)[..., 2:-2, 2:-2].mean())
        assert near_error < 0.2
        assert float(angular_error_deg(far.normals, normals).mean()) > 20 * near_error
        assert abs(float(result.offset_mm[0]) - 0.3) < 0.1

    def test_fixed_offset_keeps_initial_height(self):
        leds, height, normals, images, card = _capture(offset_mm=0.4, dtype=torch.float64)
        result = near_light_photometric_stereo(images, leds, PITCH, reference=card, card_albedo=0.8,
                                               initial_depth=float(height.mean()), estimate_offset=False)
        assert abs(float(result.depth.mean() - height.mean())) < 1e-9

    def test_rims_of_unsolved_pits_do_not_bend_the_surface(self, device):
        """A flat plateau with deep pits: the pits are unsolved, and the rim pixels' central-difference normals see
        the pit's wall. Integrated with full confidence they pull the plateau down around each pit; beside-the-gap
        confidence leaves it flat to a micrometre."""
        height = torch.full((1, 1, 40, 40), 0.2, device=device, dtype=torch.float64)
        pits = torch.zeros_like(height, dtype=torch.bool)
        for row in range(4, 40, 9):
            for col in range(4, 40, 9):
                pits[..., row : row + 3, col : col + 3] = True
        height = height.masked_fill(pits, 0.0)
        normals = normals_from_height(height, PITCH)
        plateau = ~pits
        weighted = _integrate_solved(normals, plateau, "masked", PITCH)
        p, q = normals_to_gradients(normals)
        plain = integrate(p, q, method="masked", pixel_pitch_mm=PITCH, mask=plateau)
        spread = lambda z: float(z[plateau].max() - z[plateau].min())  # noqa: E731
        assert spread(plain) > 0.01  # mm: tens of µm of bending
        assert spread(weighted) < 0.002  # the rims keep 1 % of their slope: a micrometre, no bending

    def test_integrator_without_weights(self):
        """Integrators without per-pixel weights (Frankot–Chellappa) get the plain mask."""
        leds, _, _, images, card = _capture(size=24)
        result = near_light_photometric_stereo(images, leds, PITCH, reference=card, card_albedo=0.8, integrator="fc",
                                               max_iterations=2)
        assert result.depth.shape == (1, 1, 24, 24)

    def test_module_equals_functional(self):
        leds, _, _, images, card = _capture(size=24)
        module = PhotometricStereo(leds, pixel_pitch_mm=PITCH, max_iterations=2)  # LEDs: the near solver
        a = module(images, card, card_albedo=0.8)
        b = near_light_photometric_stereo(images, leds, PITCH, reference=card, card_albedo=0.8, max_iterations=2)
        self.assert_close(a.normals, b.normals)
        self.assert_close(a.depth, b.depth)

    def test_count_mismatch_raise(self):
        with pytest.raises(ShapeError, match="8 lights"):
            near_light_photometric_stereo(torch.rand(1, 6, 8, 8), _rig(), PITCH)

    def test_nan_raise(self):
        images = torch.rand(1, 8, 8, 8)
        images[0, 1, 2, 3] = float("nan")
        with pytest.raises(InputError, match="finite"):
            near_light_photometric_stereo(images, _rig(), PITCH)

    def test_bad_options_raise(self):
        with pytest.raises(InputError, match="max_iterations"):
            near_light_photometric_stereo(torch.rand(1, 8, 8, 8), _rig(), PITCH, max_iterations=0)
        with pytest.raises(ShapeError, match="initial_depth"):
            near_light_photometric_stereo(torch.rand(1, 8, 8, 8), _rig(), PITCH, initial_depth=torch.zeros(1, 1, 4, 4))
        with pytest.raises(InputError, match="light_model"):
            near_light_photometric_stereo(torch.rand(1, 8, 8, 8), ring_lights(8, 55.0), PITCH)
        with pytest.raises(InputError, match="search_mm"):
            estimate_height_offset(torch.rand(1, 8, 8, 8), _rig(), torch.zeros(1, 1, 8, 8), PITCH,
                                   torch.ones(1, 8, 8, 8, dtype=torch.bool), search_mm=(1.0, -1.0))


class TestRefineDepth(BaseTester):
    def test_reduces_smooth_depth_error(self):
        leds, height, normals, images, card = _capture(offset_mm=0.5, dtype=torch.float64)
        flat = images / card * 0.8
        coords = torch.linspace(-1, 1, 48, dtype=torch.float64)
        y, x = torch.meshgrid(coords, coords, indexing="ij")
        start = height + 0.3 * (1 - x**2 - y**2)[None, None]  # a 0.3 mm dome, the distant-light artefact
        depth, albedo, losses = refine_depth(flat, leds, start, PITCH, card_height_mm=0.0, scales=(4, 2, 1), steps=40)
        before, after = start - height, depth - height
        assert float((after - after.mean()).square().mean().sqrt()) < 0.05 * float((before - before.mean()).square().mean().sqrt())
        assert abs(float(after.mean())) < 0.01  # the absolute height too, mm
        self.assert_close(albedo[..., 2:-2, 2:-2], torch.full_like(albedo[..., 2:-2, 2:-2], 0.6), rtol=0, atol=0.02)

    def test_bad_scales_raise(self):
        with pytest.raises(InputError, match="scales"):
            refine_depth(torch.rand(1, 8, 8, 8), _rig(), torch.zeros(1, 1, 8, 8), PITCH, scales=(0,))
