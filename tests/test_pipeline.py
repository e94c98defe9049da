import math

import pytest
import torch

from psmini import CalibrationError, DirectionalLights, InputError, LEDLights, ShapeError, _chunks, ring_lights
from psmini.config import ReconstructionConfig
from psmini.flatfield import flatfield
from psmini.integrate import frankot_chellappa, masked_least_squares
from psmini.normals import albedo_normals, normals_to_gradients
from psmini.pipeline import NORMAL_ESTIMATORS, PhotometricStereo, distant_light_matrix, reconstruct
from tests._analytic import analytic_sphere, render
from tests.conftest import BaseTester


def _bumpy_plane(size: int, pitch: float, device=None, dtype=torch.float32):
    """Height (1, 1, H, W) mm of a tilted plane plus Gaussian bumps, and its analytic normals."""
    coords = (torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2) * pitch
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    sigma = 8 * pitch
    z, zx, zy = 0.05 * x - 0.03 * y, torch.full_like(x, 0.05), torch.full_like(x, -0.03)
    for cx, cy, amp in ((0.1, 0.2, 0.08), (-0.3, -0.1, -0.05), (0.25, -0.3, 0.06)):
        g = amp * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))
        z, zx, zy = z + g, zx - g * (x - cx) / sigma**2, zy - g * (y - cy) / sigma**2
    normals = torch.stack([-zx, -zy, torch.ones_like(z)])
    return z[None, None], (normals / normals.norm(dim=0)).unsqueeze(0)


class TestPhotometricStereo(BaseTester):
    def test_bumpy_plane_end_to_end(self, device, dtype):
        """Render a tilted bumpy plane under a card-normalised ring, recover normals and the surface."""
        pitch = 0.025
        height, normals = _bumpy_plane(64, pitch, device, dtype)
        lights = ring_lights(8, 45.0, device=device, dtype=dtype)
        # each LED's smooth beam times the camera's per-pixel gain, common to the LEDs: the card cancels both (the
        # card's smoothing keeps the gain and fits the beams exactly, being linear here)
        u = torch.linspace(-1, 1, 64, device=device, dtype=dtype)
        beams = 1 + 0.2 * torch.cos(torch.arange(8, device=device, dtype=dtype)).view(1, 8, 1, 1) * u.view(1, 1, 1, 64)
        falloff = beams * (torch.rand(1, 1, 64, 64, device=device, dtype=dtype) * 0.5 + 0.5)
        albedo = torch.full_like(height, 0.6)
        images = render(normals, albedo, lights / lights[:, 2:3]) * lights[:, 2].view(1, 8, 1, 1) * falloff + 0.02
        reference = 0.8 * falloff * lights[:, 2].view(1, 8, 1, 1) + 0.02
        dark = torch.full((1, 1, 64, 64), 0.02, device=device, dtype=dtype)
        result = PhotometricStereo(lights, pixel_pitch_mm=pitch)(images, reference, dark, card_albedo=0.8)
        self.assert_close(result.normals, normals, rtol=1e-3, atol=1e-3)
        self.assert_close(result.albedo, albedo, rtol=1e-3, atol=1e-3)
        expected = height - height.mean()
        rmse = (result.depth - expected).square().mean().sqrt() / (expected.max() - expected.min())
        assert float(rmse) < 2e-3

    def test_functional_equals_module(self, device, dtype):
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = torch.rand(2, 8, 16, 16, device=device, dtype=dtype) + 0.1
        result = PhotometricStereo(lights, pixel_pitch_mm=0.5)(images)
        albedo, normals = albedo_normals(flatfield(images).images, lights)
        p, q = normals_to_gradients(normals)
        self.assert_close(result.normals, normals)
        self.assert_close(result.depth, frankot_chellappa(p, q, 0.5, mask=albedo > 0))

    def test_led_model_uses_centre_directions(self, device, dtype):
        ring = ring_lights(8, 55.0, device=device, dtype=dtype)
        positions = ring * 12.0
        leds = LEDLights(positions, -ring)
        matrix = distant_light_matrix(leds, flatfielded=True, reference=positions)
        self.assert_close(matrix, ring / ring[:, 2:3])
        unflat = distant_light_matrix(leds, flatfielded=False, reference=positions)
        self.assert_close(unflat.norm(dim=-1), torch.full((8,), 1 / 144.0, device=device, dtype=dtype))

    def test_mask_and_shadows(self, device, dtype):
        normals, inside, albedo = analytic_sphere(32, device=device, dtype=dtype)
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = render(normals, albedo, lights)
        result = PhotometricStereo(lights, pixel_pitch_mm=None)(images, mask=inside)
        assert not bool(result.mask[~inside].any())
        assert torch.isfinite(result.depth).all()

    def test_wrong_count_raise(self):
        with pytest.raises(ShapeError, match="number of lights"):
            PhotometricStereo(ring_lights(8, 55.0), None)(torch.rand(1, 6, 8, 8))

    def test_coplanar_raise(self):
        with pytest.raises(CalibrationError, match="coplanar"):
            PhotometricStereo(ring_lights(8, 90.0), None)(torch.rand(1, 8, 8, 8))

    @pytest.mark.parametrize("estimator", ["lstsq", "rpca"])
    def test_dark_images_raise(self, estimator):
        # all-zero images failed in the integrator as "mask must select at least one pixel ..., got an empty mask"
        model = PhotometricStereo(ring_lights(8, 55.0), 0.1, ReconstructionConfig(estimator=estimator))
        images = torch.rand(2, 8, 4, 4) + 0.1
        images[1] = 0
        with pytest.raises(InputError, match=r"no pixel could be solved in batch item\(s\) \[1\]: .*dark"):
            model(images)
        mask = torch.zeros(2, 1, 4, 4, dtype=torch.bool)
        mask[..., :2] = True
        images[0, :, :, :2] = 0
        with pytest.raises(InputError, match=r"no pixel could be solved inside the mask in batch item\(s\) \[0, 1\]"):
            model(images, mask=mask)

    def test_nan_raise(self):
        images = torch.rand(1, 8, 8, 8)
        images[0, 0, 0, 0] = math.nan
        with pytest.raises(InputError, match="finite"):
            PhotometricStereo(ring_lights(8, 55.0), None)(images)

    def test_bad_lights_raise(self):
        with pytest.raises(InputError, match="light model"):
            PhotometricStereo("ring", None)

    def test_distant_light_matrix_of_a_tensor_raise(self):
        # a tensor of directions failed as a bare TypeError ("'Tensor' object is not callable")
        with pytest.raises(InputError, match="lights must be a light model .* got Tensor of shape \\(8, 3\\); wrap "
                                             ".* DirectionalLights"):
            distant_light_matrix(ring_lights(8, 55.0), True, torch.zeros(1))
        with pytest.raises(InputError, match="reference must be a tensor .* got float"):
            distant_light_matrix(DirectionalLights(ring_lights(8, 55.0)), True, 0.0)

    def test_reconstruct_tensor_raise(self):
        # a tensor of images for a sample failed as a bare AttributeError ('Tensor' has no attribute 'images')
        with pytest.raises(InputError, match="needs a loaded sample .* got Tensor; .*PhotometricStereo"):
            reconstruct(torch.rand(8, 8, 8))

    def test_solver_choice(self):
        ring = ring_lights(8, 58.0)
        leds = LEDLights(ring * 18.6, -ring)
        assert PhotometricStereo(leds, 0.025).solver == "near" and PhotometricStereo(ring, None).solver == "distant"
        assert PhotometricStereo(leds, 0.025, ReconstructionConfig(solver="distant")).solver == "distant"
        with pytest.raises(InputError, match="solver must be"):
            ReconstructionConfig(solver="far")
        with pytest.raises(InputError, match="point or LED model"):
            PhotometricStereo(ring, None, ReconstructionConfig(solver="near"))
        with pytest.raises(InputError, match="pixel pitch"):
            PhotometricStereo(leds, pixel_pitch_mm=None)
        with pytest.raises(InputError, match="ReconstructionConfig"):
            PhotometricStereo(ring, None, {"solver": "distant"})

    def test_pixel_pitch_has_no_default(self):
        with pytest.raises(TypeError, match="pixel_pitch_mm"):
            PhotometricStereo(ring_lights(8, 55.0))
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            PhotometricStereo(ring_lights(8, 55.0), -0.1)

    def test_mask_makes_auto_integrate_over_it(self, device, dtype):
        """With an outline (DiLiGenT), auto integrates over the outline only: the result equals masked least
        squares over the solved pixels, and the background does not move the object's relief."""
        normals, inside, albedo = analytic_sphere(32, device=device, dtype=dtype)
        lights = ring_lights(8, 30.0, device=device, dtype=dtype)
        images = render(normals, albedo, lights)
        result = PhotometricStereo(lights, None)(images, mask=inside)
        p, q = normals_to_gradients(result.normals)
        self.assert_close(result.depth, masked_least_squares(p, q, 1.0, mask=result.mask))
        forced = PhotometricStereo(lights, None, ReconstructionConfig(integrator="fc"))(images, mask=inside)
        assert not torch.allclose(forced.depth, result.depth)

    def test_estimator_registry(self, device, dtype):
        normals, inside, albedo = analytic_sphere(24, device=device, dtype=dtype)
        lights = ring_lights(12, 40.0, device=device, dtype=dtype)
        images = render(normals, albedo, lights)
        for name in NORMAL_ESTIMATORS:
            result = PhotometricStereo(lights, None, ReconstructionConfig(estimator=name))(images, mask=inside)
            lit = inside & (result.mask)
            error = torch.rad2deg(torch.acos((result.normals * normals).sum(1, keepdim=True).clamp(-1, 1)))[lit]
            assert float(error.median()) < 1.0, name

    def test_light_below_card_raise(self):
        lights = DirectionalLights(torch.tensor([[0.5, 0, 0.8], [-0.5, 0, 0.8], [0, 0.5, -0.8]]))
        with pytest.raises(InputError, match="above the card"):
            PhotometricStereo(lights, None)(torch.rand(1, 3, 4, 4), reference=torch.ones(3, 4, 4))

    @pytest.mark.parametrize("with_mask", [True, False], ids=["mask", "no mask"])
    @pytest.mark.parametrize("chunked", [False, True], ids=["whole", "chunked"])
    @pytest.mark.parametrize("integrator", ["auto", "masked"])
    def test_batch_equals_items(self, device, dtype, integrator, chunked, with_mask, monkeypatch):
        """A batch gives each item what it gets alone: no estimator or integrator couples the items, and solving a
        CPU batch in chunks (of two items and one, here) changes nothing, also where a chunk's least squares
        writes straight into the batch's tensors (the unsaturated last chunk, with a mask and without)."""
        if chunked:
            monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 2 * 8 * 24 * 20)
        lights = ring_lights(8, 50.0, device=device, dtype=dtype)
        images = torch.rand(3, 8, 24, 20, device=device, dtype=dtype) * 0.6 + 0.2
        images[1, 2, :4, :5] = 1.0  # saturated: fewer observations there
        reference = torch.rand(1, 8, 24, 20, device=device, dtype=dtype) * 0.4 + 0.5
        dark = torch.rand(3, 1, 24, 20, device=device, dtype=dtype) * 0.01
        mask = torch.rand(3, 1, 24, 20, device=device) > 0.1 if with_mask else None
        model = PhotometricStereo(lights, 0.025, ReconstructionConfig(integrator=integrator))
        batch = model(images, reference, dark, dark[:1], mask, 0.8, 0.99)
        for i in range(3):
            item_mask = None if mask is None else mask[i : i + 1]
            item = model(images[i : i + 1], reference, dark[i : i + 1], dark[:1], item_mask, 0.8, 0.99)
            self.assert_close(batch.albedo[i : i + 1], item.albedo)
            self.assert_close(batch.normals[i : i + 1], item.normals)
            assert torch.equal(batch.mask[i : i + 1], item.mask)
            self.assert_close(batch.depth[i : i + 1], item.depth, rtol=1e-4, atol=1e-5)

    @pytest.mark.parametrize("chunked", [False, True], ids=["whole", "chunked"])
    def test_frame_of_another_batch_raise(self, chunked, monkeypatch):
        if chunked:
            monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 8 * 8 * 8)
        with pytest.raises(ShapeError, match=r"\(3, 8, 8, 8\)"):
            PhotometricStereo(ring_lights(8, 55.0), None)(torch.rand(3, 8, 8, 8), dark=torch.rand(2, 1, 8, 8))

    def test_near_light_batch_in_chunks_equals_whole(self, monkeypatch):
        """The near solver through the pipeline, a CPU batch of three in chunks of one: each item as in the whole."""
        ring = ring_lights(8, 58.0, dtype=torch.float64)
        model = PhotometricStereo(LEDLights(ring * 18.6, -ring), 0.025)
        images = torch.rand(3, 8, 16, 16, dtype=torch.float64) * 0.5 + 0.3
        whole = model(images, torch.full((8, 16, 16), 0.6, dtype=torch.float64), card_albedo=0.8)
        monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 8 * 16 * 16)
        chunked = model(images, torch.full((8, 16, 16), 0.6, dtype=torch.float64), card_albedo=0.8)
        for name in ("albedo", "normals", "depth", "offset_mm"):
            self.assert_close(getattr(chunked, name), getattr(whole, name), rtol=0, atol=1e-9)
        self.assert_close(chunked.weights, whole.weights, rtol=0, atol=1e-9)
        assert chunked.iterations == whole.iterations

    def test_gradcheck_batch(self):
        """Gradients of a batch through flat-field, normals and the item-by-item Frankot–Chellappa."""
        lights = ring_lights(8, 45.0, dtype=torch.float64)
        model = PhotometricStereo(lights, pixel_pitch_mm=0.1)
        images = (torch.rand(2, 8, 4, 5, dtype=torch.float64) * 0.5 + 0.5).requires_grad_()
        self.gradcheck(lambda x: model(x).depth, (images,))

    def test_gradcheck_batch_in_chunks(self, monkeypatch):
        """Gradients through the CPU chunks (flat-field and normals one item at a time, then concatenated)."""
        monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 8 * 4 * 5)
        lights = ring_lights(8, 45.0, dtype=torch.float64)
        model = PhotometricStereo(lights, pixel_pitch_mm=0.1)
        reference = torch.rand(1, 8, 4, 5, dtype=torch.float64) + 0.5
        images = (torch.rand(2, 8, 4, 5, dtype=torch.float64) * 0.5 + 0.5).requires_grad_()
        self.gradcheck(lambda x: model(x, reference, card_albedo=0.8).depth, (images,))

    def test_gradcheck_whole_pipeline(self):
        lights = ring_lights(8, 45.0, dtype=torch.float64)
        reference = torch.rand(1, 8, 4, 4, dtype=torch.float64) + 0.5
        model = PhotometricStereo(lights, pixel_pitch_mm=0.1)

        def run(images, ref):
            result = model(images, ref, card_albedo=0.8)
            return result.albedo, result.normals, result.depth

        images = (torch.rand(1, 8, 4, 4, dtype=torch.float64) * 0.5 + 0.5).requires_grad_()
        self.gradcheck(run, (images, reference.requires_grad_()))

    @pytest.mark.parametrize("flatfielded", [False, True])
    def test_gradcheck_distant_light_matrix(self, flatfielded):
        """Gradients reach every parameter of the light model through the matrix seen from the field centre."""
        reference = torch.zeros(1, dtype=torch.float64)
        ring = ring_lights(4, 50.0, dtype=torch.float64)
        directions, intensities = ring.clone().requires_grad_(), torch.linspace(0.5, 2, 4, dtype=torch.float64)
        self.gradcheck(lambda d, i: distant_light_matrix(DirectionalLights(d, i), flatfielded, reference),
                       (directions, intensities.requires_grad_()))
        ones = torch.ones(4, dtype=torch.float64)
        leds = (ring * 18.6, -ring, 1.2 * ones, 1.5 * ones)
        self.gradcheck(lambda *t: distant_light_matrix(LEDLights(*t), flatfielded, reference),
                       tuple(t.clone().requires_grad_() for t in leds))

    def test_gradcheck_reconstruct(self):
        from psmini.io import Sample

        lights = DirectionalLights(ring_lights(8, 45.0, dtype=torch.float64))
        config = ReconstructionConfig(dtype="float64")

        def run(images):
            result = reconstruct(Sample(name="grad", images=images, lights=lights, pixel_pitch_mm=0.1), config)
            return result.normals, result.depth

        self.gradcheck(run, ((torch.rand(8, 3, 4, dtype=torch.float64) * 0.5 + 0.5).requires_grad_(),))


def test_card_smoothing_lowers_the_noise_of_near_light_normals():
    """A noisy 8-bit card: dividing by its smoothed images (config.card_smoothing_px) gives near light's normals
    less noise; on a noise-free card it changes nothing measurable."""
    from data_synth import make_fabric
    from data_synth.rig import RigConfig, render_capture, render_card
    from psmini.config import ReconstructionConfig
    from psmini.metrics import angular_error_deg

    size, pitch = 160, 0.0625
    noisy = RigConfig(size=size, pixel_pitch_mm=pitch, noise=True, bit_depth=8)
    fabric = make_fabric("cotton", size=size, pixel_pitch_mm=pitch, seed=0)
    for config, expect_gain in ((noisy, True), (noisy.replace(noise=False, bit_depth=16), False)):
        card = render_card(config, 0.8)
        capture = render_capture(fabric, config, height_offset_mm=0.5)
        region = capture.mask.bool() & (capture.lit.sum(0, keepdim=True) >= 3)
        errors = []
        for smoothing in (None, 3.0):
            result = PhotometricStereo(capture.lights, pitch, ReconstructionConfig(card_smoothing_px=smoothing))(
                capture.images[None], card.images[None], capture.dark[None], card.dark[None], card_albedo=0.8,
                saturation_level=1.0)
            errors.append(float(angular_error_deg(result.normals, capture.normals[None])[0][region].mean()))
        if expect_gain:
            assert errors[1] < 0.9 * errors[0], errors
        else:
            assert abs(errors[1] - errors[0]) < 0.005, errors


def test_near_light_predicts_the_cards_saturated_readings():
    """A card bright enough to saturate under the LEDs nearest its corners: near light predicts those readings from
    its light model (flatfield's card_shading) instead of dropping every reading divided by them, and reads the
    cloth as it does with a dimmer card that nothing saturates (noise-free renders, so that only the card's clip
    differs)."""
    from data_synth import make_fabric
    from data_synth.rig import RigConfig, render_capture, render_card
    from psmini.metrics import angular_error_deg

    size, pitch = 160, 0.0625
    config = RigConfig(size=size, pixel_pitch_mm=pitch, noise=False, bit_depth=16)
    capture = render_capture(make_fabric("knit", size=size, pixel_pitch_mm=pitch, seed=0), config,
                             height_offset_mm=0.5)
    region = capture.mask.bool() & (capture.lit.sum(0, keepdim=True) >= 3)
    results = {}
    for albedo in (1.0, 0.5):
        card = render_card(config, albedo)
        results[albedo] = PhotometricStereo(capture.lights, pitch, ReconstructionConfig(solver="near"))(
            capture.images[None], card.images[None], capture.dark[None], card.dark[None], card_albedo=albedo,
            saturation_level=1.0)
        if albedo == 1.0:
            assert float((card.images >= 1.0).float().mean()) > 0.01  # the precondition: it saturates
    bright, dim = (angular_error_deg(results[a].normals, capture.normals[None])[0][region] for a in (1.0, 0.5))
    assert abs(float(bright.mean()) - float(dim.mean())) < 0.01, (float(bright.mean()), float(dim.mean()))
    depth = (results[1.0].depth - results[0.5].depth)[0, 0][region[0]]
    assert float((depth - depth.mean()).abs().max()) < 0.005  # mm

