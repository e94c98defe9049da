"""Bilateral (discontinuity-preserving) normal integration: analytic surfaces, gradients, errors, real data."""

from __future__ import annotations

import math

import pytest
import torch

from psmini.errors import InputError, ShapeError
from psmini.integrate import (
    BilateralIntegration,
    bilateral_integration,
    integrate,
    integrate_normals,
)
from tests.conftest import BaseTester, shared_data
from tests.test_integrate import bumps_surface, relative_rmse


class TestBilateral(BaseTester):
    def test_plane_and_bumps(self, device, dtype):
        z, p, q = bumps_surface(48, 56, 0.05, device, dtype)
        assert relative_rmse(bilateral_integration(p, q, 0.05), z) < 1e-3

    def test_masked_bumps_and_batch(self, device, dtype):
        z, p, q = bumps_surface(40, 48, 0.05, device, dtype)
        mask = torch.ones_like(z, dtype=torch.bool)
        mask[..., :6, :10] = False
        mask[1, ..., 30:, 40:] = False
        out = bilateral_integration(p, q, 0.05, mask)
        assert relative_rmse(out, z, mask) < 1e-3
        assert bool((out[~mask] == 0).all())
        single = bilateral_integration(p[1:], q[1:], 0.05, mask[1:])
        self.assert_close(out[1:], single, rtol=1e-3, atol=1e-4 * float(z.abs().max()))

    def test_module_and_dispatch(self, device, dtype):
        z, p, q = bumps_surface(24, 28, 0.1, device, dtype, batch=1)
        expected = bilateral_integration(p, q, 0.1, k=1.0)
        self.assert_close(BilateralIntegration(0.1, k=1.0)(p, q), expected)
        self.assert_close(integrate(p, q, "bilateral", 0.1, k=1.0), expected)

    def test_perspective_plane(self, device, dtype):
        # A fronto-parallel plane seen in perspective has constant depth: the normalised depth is 1 everywhere.
        normals = torch.zeros(1, 3, 20, 24, device=device, dtype=dtype)
        normals[:, 2] = 1
        k = torch.tensor([[600.0, 0, 12], [0, 600.0, 10], [0, 0, 1]])
        depth = integrate_normals(normals, "bilateral", intrinsics=k)
        self.assert_close(depth, torch.ones_like(depth), rtol=1e-4, atol=1e-4)

    @pytest.mark.slow
    def test_gradcheck(self):
        torch.manual_seed(0)
        z, p, q = bumps_surface(6, 6, 0.5, "cpu", torch.float64, batch=1)
        p = (p + 0.5 * torch.rand_like(p)).requires_grad_()
        q = (q + 0.5 * torch.rand_like(q)).requires_grad_()
        weights = (0.5 + torch.rand_like(p)).requires_grad_()
        mask = torch.ones(1, 1, 6, 6, dtype=torch.bool)
        mask[..., 0, :2] = False
        # cg_tol small: the output is the energy's fixed point, whose derivative the backward computes
        self.gradcheck(
            lambda a, b, w: bilateral_integration(
                a, b, 0.5, mask, k=1.0, max_iterations=300, tol=0.0, cg_tol=1e-12, weights=w
            ),
            (p, q, weights),
        )

    def test_gradcheck_module_default_weights(self):
        """The module and the default normal-form weights 1 / (1 + p² + q²), which depend on p and q too."""
        generator = torch.Generator().manual_seed(0)
        p, q = (torch.rand(2, 1, 1, 5, 5, generator=generator, dtype=torch.float64) - 0.5).requires_grad_()
        # cg_tol small: the output is the energy's fixed point, whose derivative the backward computes
        module = BilateralIntegration(0.5, k=1.0, max_iterations=300, tol=0.0, cg_tol=1e-12)
        self.gradcheck(module, (p, q))

    def test_errors(self):
        p = torch.zeros(1, 1, 8, 8)
        with pytest.raises(ShapeError, match="same shape"):
            bilateral_integration(p, torch.zeros(1, 1, 8, 7))
        with pytest.raises(ShapeError, match=r"\(B, 1, H, W\)"):
            bilateral_integration(torch.zeros(8, 8), torch.zeros(8, 8))
        with pytest.raises(ShapeError, match="empty"):
            bilateral_integration(p, p, mask=torch.zeros(1, 1, 8, 8, dtype=torch.bool))
        with pytest.raises(InputError, match="finite"):
            bilateral_integration(p, torch.full((1, 1, 8, 8), math.nan))
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            bilateral_integration(p, p, pixel_pitch_mm=-1.0)
        for bad in (0.0, -2.0, math.inf, math.nan, True, "2"):
            with pytest.raises(InputError, match="k must"):
                bilateral_integration(p, p, k=bad)
        for bad in (0, 1.5, -3, True):
            with pytest.raises(InputError, match="max_iterations"):
                bilateral_integration(p, p, max_iterations=bad)
        for bad in (-1e-3, 1.0, math.nan):
            with pytest.raises(InputError, match="tol"):
                bilateral_integration(p, p, tol=bad)
        for bad in (0.0, 1.0, -1e-3, math.nan, True):
            with pytest.raises(InputError, match="cg_tol"):
                bilateral_integration(p, p, cg_tol=bad)
        with pytest.raises(InputError, match="non-negative"):
            bilateral_integration(p, p, weights=-torch.ones_like(p))
        with pytest.raises(ShapeError, match="weights"):
            bilateral_integration(p, p, weights=torch.ones(1, 1, 8, 7))
        with pytest.raises(InputError, match="unknown"):
            integrate(p, p, "bilateral", boundary="mirror")

    def test_cuda_matches_cpu(self, cuda_device):
        z, p, q = bumps_surface(32, 36, 0.1, "cpu", torch.float64)
        expected = bilateral_integration(p, q)
        on_cuda = bilateral_integration(p.to(cuda_device), q.to(cuda_device)).cpu()
        self.assert_close(on_cuda, expected, rtol=1e-6, atol=1e-6)


def test_diligent_cat():
    """Ground-truth normals of DiLiGenT cat, perspective: within 10% of the authors' 0.074 mm (measured 0.075 mm;
    masked least squares 0.398 mm; the same energy solved exactly at every iteration 0.101 mm)."""
    from benchmarks.integration import REFERENCE_BILATERAL, aligned_error, load

    normals, mask, k, depth_gt = load(shared_data("DiLiGenT_depth", "cat"))
    depth = integrate_normals(normals, "bilateral", mask, intrinsics=k)
    error = aligned_error(depth[0, 0].double().numpy(), depth_gt, mask[0, 0].numpy())
    assert error < 1.1 * REFERENCE_BILATERAL["cat"]
    assert bool(torch.isfinite(depth[mask]).all()) and bool((depth[mask] > 0).all())


def test_perspective_weights_are_the_normal_against_the_ray():
    """integrate_normals hands bilateral the paper's perspective confidence (n . r)^2, r = ((u-cx)/fx, (v-cy)/fy, 1)."""
    torch.manual_seed(0)
    normals = torch.randn(1, 3, 9, 11, dtype=torch.float64)
    normals[:, 2] = normals[:, 2].abs() + 2
    normals = normals / normals.norm(dim=1, keepdim=True)
    k = torch.tensor([[300.0, 0, 4.5], [0, 280.0, 3.0], [0, 0, 1]], dtype=torch.float64)
    u = torch.arange(11, dtype=torch.float64).view(1, -1)
    v = torch.arange(9, dtype=torch.float64).view(-1, 1)
    # psmini's normal (y up, z toward the camera) against the OpenCV ray (y down, z forward)
    expected = (normals[0, 0] * (u - 4.5) / 300 - normals[0, 1] * (v - 3.0) / 280 - normals[0, 2]) ** 2
    explicit = integrate_normals(normals, "bilateral", intrinsics=k, weights=expected.view(1, 1, 9, 11), cg_tol=1e-12)
    implicit = integrate_normals(normals, "bilateral", intrinsics=k, cg_tol=1e-12)
    torch.testing.assert_close(implicit, explicit, rtol=1e-12, atol=1e-12)
    other = integrate_normals(normals, "bilateral", intrinsics=k, weights=torch.ones(1, 1, 9, 11), cg_tol=1e-12)
    assert float((other - explicit).abs().max()) > 1e-9
