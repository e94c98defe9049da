import pytest
import torch

from psmini import CalibrationError, InputError, ShapeError, ring_lights
from psmini.normals import LeastSquaresNormals, albedo_normals, normals_to_gradients
from tests._analytic import analytic_sphere, render
from tests.conftest import BaseTester


def _lit_everywhere(normals, lights):
    """Pixels where every light has a positive cosine (no attached shadow): least squares is exact there."""
    return (torch.einsum("kc,bchw->bkhw", lights.to(normals), normals) > 1e-3).all(dim=1, keepdim=True)


class TestAlbedoNormals(BaseTester):
    def test_recovers_sphere(self, device, dtype):
        normals, inside, albedo = analytic_sphere(48, device=device, dtype=dtype)
        lights = (
            ring_lights(8, 35.0, device=device, dtype=dtype)
            * torch.linspace(0.8, 1.2, 8, device=device, dtype=dtype)[:, None]
        )
        images = render(normals, albedo, lights)
        est_albedo, est_normals = albedo_normals(images, lights)
        region = inside & _lit_everywhere(normals, lights)
        assert int(region.sum()) > 500
        self.assert_close(est_normals * region, normals * region, rtol=1e-4, atol=1e-4)
        self.assert_close(est_albedo * region, albedo * region, rtol=1e-4, atol=1e-4)

    def test_weights_drop_shadowed_observations(self, device, dtype):
        normals, inside, albedo = analytic_sphere(48, device=device, dtype=dtype)
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = render(normals, albedo, lights)
        lit = torch.einsum("kc,bchw->bkhw", lights, normals) > 1e-3
        _, plain = albedo_normals(images, lights)
        _, weighted = albedo_normals(images, lights, mask=inside, weights=lit)
        enough = inside & (lit.sum(1, keepdim=True) >= 3)
        shadowed = enough & ~lit.all(1, keepdim=True)
        # with shadows ignored the solution is exact wherever three lights remain; plain least squares is not
        self.assert_close(weighted * enough, normals * enough, rtol=1e-4, atol=1e-4)
        assert float(((plain - normals).norm(dim=1, keepdim=True) * shadowed).max()) > 0.05

    def test_rank_deficient_pixels_get_default(self, device, dtype):
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = torch.rand(1, 8, 2, 2, device=device, dtype=dtype)
        weights = torch.ones_like(images)
        weights[0, 2:, 0, 0] = 0  # two lights left at pixel (0, 0)
        albedo, normals = albedo_normals(images, lights, weights=weights)
        assert float(albedo[0, 0, 0, 0]) == 0.0
        assert normals[0, :, 0, 0].tolist() == [0.0, 0.0, 1.0]
        assert bool((albedo[0, 0].flatten()[1:] > 0).all())

    def test_mask(self, device, dtype):
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        mask = torch.zeros(1, 1, 3, 3, dtype=torch.bool, device=device)
        mask[..., 1, 1] = True
        albedo, normals = albedo_normals(torch.rand(1, 8, 3, 3, device=device, dtype=dtype) + 0.1, lights, mask)
        assert int((albedo > 0).sum()) == 1 and normals[0, 2, 0, 0] == 1

    def test_batched_lights(self, device, dtype):
        lights = torch.stack(
            [ring_lights(8, 45.0, device=device, dtype=dtype), ring_lights(8, 30.0, device=device, dtype=dtype)]
        )
        normals, _, albedo = analytic_sphere(16, device=device, dtype=dtype)
        images = torch.cat([render(normals, albedo, lights[0]), render(normals, albedo, lights[1])])
        _, est = albedo_normals(images, lights)
        region = _lit_everywhere(normals, lights[0]) & _lit_everywhere(normals, lights[1])
        self.assert_close(est * region, normals.expand(2, -1, -1, -1) * region, rtol=1e-4, atol=1e-4)

    def test_module_equals_functional(self, device, dtype):
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = torch.rand(2, 8, 5, 5, device=device, dtype=dtype)
        for a, b in zip(LeastSquaresNormals(lights)(images), albedo_normals(images, lights), strict=True):
            self.assert_close(a, b)

    @pytest.mark.parametrize("case", ["plain", "masked", "weighted", "zero pixel"])
    def test_out_equals_new_tensors(self, device, dtype, case):
        """Results written into ``out`` are the new tensors' values on every path (the all-solved one, masked
        pixels, per-pixel weights, a pixel of zero intensity), and the out tensors themselves are returned."""
        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = torch.rand(2, 8, 6, 5, device=device, dtype=dtype) + 0.1
        mask = weights = None
        if case == "masked":
            mask = torch.rand(2, 1, 6, 5, device=device) > 0.3
        if case == "weighted":
            weights = torch.rand(2, 8, 6, 5, device=device) > 0.2
        if case == "zero pixel":
            images[1, :, 2, 3] = 0.0
        expected = albedo_normals(images, lights, mask, weights)
        out = (torch.full((2, 1, 6, 5), torch.nan, device=device, dtype=dtype),
               torch.full((2, 3, 6, 5), torch.nan, device=device, dtype=dtype))
        got = albedo_normals(images, lights, mask, weights, out=out)
        assert got[0] is out[0] and got[1] is out[1]
        self.assert_close(got[0], expected[0], rtol=0, atol=0)
        self.assert_close(got[1], expected[1], rtol=0, atol=0)

    def test_pipeline_kernel_equals_albedo_normals(self, device, dtype):
        """The pipeline's unchecked kernel (one pseudo-inverse per batch) gives albedo_normals' values."""
        from psmini.normals import _solve_with_pinv

        lights = ring_lights(8, 55.0, device=device, dtype=dtype)
        images = torch.rand(2, 8, 6, 5, device=device, dtype=dtype) + 0.1
        mask = torch.rand(2, 1, 6, 5, device=device) > 0.3
        for m in (None, mask):
            for got, expected in zip(_solve_with_pinv(images, torch.linalg.pinv(lights), m),
                                     albedo_normals(images, lights, m), strict=True):
                self.assert_close(got, expected, rtol=1e-6 if dtype == torch.float32 else 1e-12, atol=1e-7)

    def test_bad_out_raise(self):
        lights, images = ring_lights(8, 55.0), torch.rand(1, 8, 4, 4)
        albedo, normals = torch.empty(1, 1, 4, 4), torch.empty(1, 3, 4, 4)
        with pytest.raises(InputError, match="tuple of 2 tensors"):
            albedo_normals(images, lights, out=albedo)
        with pytest.raises(ShapeError, match=r"out normals .*\(1, 3, 4, 4\).*\(1, 3, 4, 3\)"):
            albedo_normals(images, lights, out=(albedo, torch.empty(1, 3, 4, 3)))
        with pytest.raises(ShapeError, match="float64"):
            albedo_normals(images, lights, out=(albedo, normals.double()))
        with pytest.raises(InputError, match="share memory"):
            albedo_normals(images, lights, out=(normals[:, :1], normals))
        with pytest.raises(InputError, match="requires grad"):
            albedo_normals(images.requires_grad_(), lights, out=(albedo, normals))
        with pytest.raises(InputError, match="out albedo requires grad"):
            albedo_normals(images.detach(), lights, out=(albedo.requires_grad_(), normals))

    def test_count_mismatch_raise(self):
        with pytest.raises(ShapeError, match=r"number of lights.*\(8\).*\(7\)"):
            albedo_normals(torch.rand(1, 7, 4, 4), ring_lights(8, 55.0))

    def test_coplanar_raise(self):
        with pytest.raises(CalibrationError, match="coplanar"):
            albedo_normals(torch.rand(1, 4, 8, 8), ring_lights(4, zenith_deg=90.0))

    def test_two_lights_raise(self):
        with pytest.raises(CalibrationError, match="got 2"):
            albedo_normals(torch.rand(1, 2, 8, 8), ring_lights(2, 45.0))

    @pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
    def test_nan_raise(self, bad):
        """NaN or inf anywhere raises, whether found in the solution (the pseudo-inverse path scans the images only
        then) or in the images (the weighted and per-pixel paths), masked out or not, with a light component 0."""
        images = torch.rand(1, 8, 4, 4)
        images[0, 3, 1, 1] = bad
        lights = ring_lights(8, 55.0)
        lights[3, 0] = 0.0  # a zero in the light matrix: 0 * inf and 0 * NaN are NaN all the same
        outside = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        outside[0, 0, 1, 1] = False
        for kwargs in ({}, {"mask": outside}, {"weights": torch.ones(1, 8, 4, 4)},
                       {"weights": torch.ones(1, 8, 4, 4).index_fill_(1, torch.tensor([3]), 0.0)}):
            with pytest.raises(InputError, match="intensities must be finite"):
                albedo_normals(images, lights, **kwargs)
        per_pixel = lights[None, :, :, None, None].expand(1, 8, 3, 4, 4)
        with pytest.raises(InputError, match="intensities must be finite"):
            albedo_normals(images, per_pixel)

    def test_wrong_shape_raise(self):
        with pytest.raises(ShapeError, match=r"\(B, K, H, W\)"):
            albedo_normals(torch.rand(8, 4, 4), ring_lights(8, 55.0))
        with pytest.raises(ShapeError, match="weights"):
            albedo_normals(torch.rand(1, 8, 4, 4), ring_lights(8, 55.0), weights=torch.ones(1, 8, 4, 3))

    def test_integer_images_raise(self):
        with pytest.raises(InputError, match="floating-point"):
            albedo_normals(torch.zeros(1, 8, 4, 4, dtype=torch.uint8), ring_lights(8, 55.0))

    def test_gradcheck(self):
        lights = ring_lights(8, 55.0, dtype=torch.float64)
        images = (torch.rand(1, 8, 3, 3, dtype=torch.float64) + 0.5).requires_grad_()
        self.gradcheck(lambda i: albedo_normals(i, lights), (images,))
        weights = torch.rand(1, 8, 3, 3, dtype=torch.float64) + 0.1
        self.gradcheck(lambda i: albedo_normals(i, lights, weights=weights), (images,))

    def test_gradcheck_lights(self):
        lights = ring_lights(8, 55.0, dtype=torch.float64).requires_grad_()
        images = torch.rand(1, 8, 2, 2, dtype=torch.float64) + 0.5
        self.gradcheck(lambda light: albedo_normals(images, light), (lights,))

    def test_gradcheck_module(self):
        solver = LeastSquaresNormals(ring_lights(8, 55.0, dtype=torch.float64))
        images = (torch.rand(1, 8, 2, 3, dtype=torch.float64) + 0.5).requires_grad_()
        self.gradcheck(solver, (images,))


class TestGradients(BaseTester):
    def test_plane(self, device, dtype):
        # plane z = 0.3 x - 0.2 y has normal (-0.3, 0.2, 1) / norm
        normal = torch.tensor([-0.3, 0.2, 1.0], device=device, dtype=dtype)
        normals = (normal / normal.norm()).view(1, 3, 1, 1).expand(2, 3, 4, 4)
        p, q = normals_to_gradients(normals)
        self.assert_close(p, torch.full_like(p, 0.3))
        self.assert_close(q, torch.full_like(q, -0.2))

    def test_grazing_normal_is_capped(self):
        normals = torch.tensor([1.0, 0.0, -0.1]).view(1, 3, 1, 1)
        p, _ = normals_to_gradients(normals, min_nz=0.05)
        assert float(p) == pytest.approx(-20.0)

    def test_bad_min_nz_raise(self):
        with pytest.raises(InputError, match="min_nz"):
            normals_to_gradients(torch.rand(1, 3, 2, 2), min_nz=0.0)

    def test_out(self, device, dtype):
        normals = torch.nn.functional.normalize(torch.rand(2, 3, 4, 5, device=device, dtype=dtype) - 0.3, dim=1)
        out = torch.full((2, 2, 4, 5), torch.nan, device=device, dtype=dtype)
        p, q = normals_to_gradients(normals, out=out)
        expected = normals_to_gradients(normals)
        assert p.data_ptr() == out.data_ptr()
        self.assert_close(out, torch.cat(expected, 1), rtol=0, atol=0)
        with pytest.raises(ShapeError, match=r"\(2, 2, 4, 5\)"):
            normals_to_gradients(normals, out=out[:, :1])
        with pytest.raises(InputError, match="requires grad"):
            normals_to_gradients(normals.clone().requires_grad_(), out=out)

    def test_gradcheck(self):
        normals = torch.nn.functional.normalize(
            torch.rand(1, 3, 3, 3, dtype=torch.float64) + 0.3, dim=1
        ).requires_grad_()
        self.gradcheck(normals_to_gradients, (normals,))


class TestSolveNormalEquations(BaseTester):
    def test_matches_linalg_solve(self, device, dtype):
        from psmini.normals import solve_normal_equations

        a = torch.randn(50, 3, 3, device=device, dtype=dtype)
        spd = a @ a.transpose(1, 2) + 0.1 * torch.eye(3, device=device, dtype=dtype)
        rhs = torch.randn(50, 3, device=device, dtype=dtype)
        rows, cols = (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)
        m, well_posed = solve_normal_equations(spd[:, rows, cols], rhs, dim=1)
        assert bool(well_posed.all())
        self.assert_close(m, torch.linalg.solve(spd, rhs), rtol=1e-3, atol=1e-3)

    def test_singular_is_flagged(self):
        from psmini.normals import solve_normal_equations

        gram = torch.tensor([[1.0, 0.0, 0.0, 1.0, 0.0, 0.0]])  # rank 2: no light along z
        m, well_posed = solve_normal_equations(gram, torch.ones(1, 3), dim=1)
        assert not bool(well_posed.any()) and m.abs().sum() == 0

    def test_misuse_raise(self):
        from psmini.normals import solve_normal_equations

        gram, rhs = torch.rand(5, 6), torch.rand(5, 3)
        # five entries failed as a bare TypeError of _symmetric_adjugate, four right-hand sides as a ValueError of
        # unpacking, another count of systems as a RuntimeError, dim=2 as an IndexError, a list as an AttributeError
        with pytest.raises(ShapeError, match="gram must hold 6 entries and rhs 3 along dim 1, .* got gram \\(5, 5\\)"):
            solve_normal_equations(gram[:, :5], rhs)
        with pytest.raises(ShapeError, match="rhs \\(5, 4\\)"):
            solve_normal_equations(gram, torch.rand(5, 4))
        with pytest.raises(ShapeError, match="with the same other sizes, got gram \\(5, 6\\) and rhs \\(4, 3\\)"):
            solve_normal_equations(gram, rhs[:4])
        with pytest.raises(ShapeError, match="dim must index one, .* dim 2"):
            solve_normal_equations(gram, rhs, dim=2)
        with pytest.raises(InputError, match="gram must be a torch.Tensor, got list"):
            solve_normal_equations(gram.tolist(), rhs)
        with pytest.raises(InputError, match="rhs must be a floating-point tensor"):
            solve_normal_equations(gram, torch.ones(5, 3, dtype=torch.int64))
        m, _ = solve_normal_equations(gram.T, rhs.T, dim=-2)  # a negative dim, as before
        assert m.shape == (3, 5)

    def test_weighted_matches_lstsq_per_pixel(self):
        lights = ring_lights(8, 50.0, dtype=torch.float64)
        images = torch.rand(1, 8, 3, 3, dtype=torch.float64)
        weights = torch.rand(1, 8, 3, 3, dtype=torch.float64)
        albedo, normals = albedo_normals(images, lights, weights=weights)
        for r in range(3):
            for c in range(3):
                w = weights[0, :, r, c].sqrt()
                m = torch.linalg.lstsq(lights * w[:, None], (images[0, :, r, c] * w)[:, None]).solution[:, 0]
                self.assert_close(normals[0, :, r, c] * albedo[0, 0, r, c], m)


class TestPartiallyWeightedSolve(BaseTester):
    """Pixels whose weights are all 1 take the pseudo-inverse, the others the normal equations: the same numbers."""

    @pytest.mark.parametrize("kind", ["bool", "float"])
    def test_equals_full_weighted_solve(self, device, kind):
        from psmini.lights import as_batched_lights
        from psmini.normals import _unit_and_length, _weighted_solve

        torch.manual_seed(0)
        lights = ring_lights(8, 55.0, dtype=torch.float64).to(device)
        intensities = torch.rand(3, 8, 12, 14, dtype=torch.float64, device=device)
        weights = torch.rand(3, 8, 12, 14, device=device) > 0.1
        weights[0, 1:7, 2, 3] = False  # two lights left: unsolved
        weights[2] = True  # a batch item with every weight 1
        if kind == "float":
            weights = weights.double() * torch.where(torch.rand_like(intensities) > 0.5, 1.0, 0.7)
        albedo, normals = albedo_normals(intensities, lights, None, weights)
        m, solved = _weighted_solve(intensities, as_batched_lights(lights, 3, intensities), weights)
        expected_albedo, expected_normals = _unit_and_length(m, solved)
        self.assert_close(albedo, expected_albedo)
        self.assert_close(normals, expected_normals)
        assert float(albedo[0, 0, 2, 3]) == 0.0

    def test_strided_stack_equals_contiguous(self, device):
        # the partial pixels' observations are gathered by position in the row-major stack: a transposed view
        # (and its transposed weights) must give the contiguous stack's numbers
        torch.manual_seed(2)
        lights = ring_lights(8, 55.0, dtype=torch.float64).to(device)
        intensities = torch.rand(2, 8, 9, 11, dtype=torch.float64, device=device).transpose(-1, -2)
        weights = (torch.rand(2, 8, 9, 11, device=device) > 0.15).transpose(-1, -2)
        albedo, normals = albedo_normals(intensities, lights, None, weights)
        expected = albedo_normals(intensities.contiguous(), lights, None, weights.contiguous())
        self.assert_close(albedo, expected[0])
        self.assert_close(normals, expected[1])

    def test_per_sample_lights_equal_full_weighted_solve(self, device):
        # lights (B, K, 3) that differ per sample take the gathered branch, one matrix for all the shared one
        from psmini.normals import _unit_and_length, _weighted_solve

        torch.manual_seed(1)
        lights = torch.stack([ring_lights(8, zenith, dtype=torch.float64) for zenith in (40.0, 55.0, 70.0)]).to(device)
        intensities = torch.rand(3, 8, 10, 9, dtype=torch.float64, device=device)
        weights = torch.rand(3, 8, 10, 9, device=device) > 0.2
        albedo, normals = albedo_normals(intensities, lights, None, weights)
        expected = _unit_and_length(*_weighted_solve(intensities, lights, weights))
        self.assert_close(albedo, expected[0])
        self.assert_close(normals, expected[1])

    def test_gradcheck(self):
        lights = ring_lights(6, 50.0, dtype=torch.float64)
        intensities = (torch.rand(1, 6, 3, 4, dtype=torch.float64) + 0.2).requires_grad_()
        weights = torch.ones(1, 6, 3, 4, dtype=torch.bool)
        weights[0, 0, 1, 1] = False
        self.gradcheck(lambda i: albedo_normals(i, lights, None, weights)[1], (intensities,))
