"""Normal integration: analytic surfaces integrated back, gradients, error paths."""

from __future__ import annotations

import math

import pytest
import torch

from psmini.errors import CalibrationError, InputError, ShapeError
from psmini.integrate import (
    DCTPoisson,
    FrankotChellappa,
    MaskedLeastSquares,
    dct_poisson,
    frankot_chellappa,
    integrate,
    integrate_normals,
    masked_least_squares,
    perspective_log_gradients,
)
from tests.conftest import BaseTester


def bumps_surface(height, width, pitch, device, dtype, tilt=(0.3, -0.2), batch=2):
    """A tilted plane plus Gaussian bumps (vanishing at the border) and its exact gradients (p, q), mm."""
    row = torch.arange(height, device=device, dtype=dtype).view(-1, 1)
    col = torch.arange(width, device=device, dtype=dtype).view(1, -1)
    x, y = (col - (width - 1) / 2) * pitch, -(row - (height - 1) / 2) * pitch
    z = tilt[0] * x + tilt[1] * y
    p = torch.full_like(z, tilt[0]) + 0 * y
    q = torch.full_like(z, tilt[1]) + 0 * x
    size = min(height, width) * pitch
    for cx, cy, amp, sig in [(-0.15, 0.1, 0.08, 0.09), (0.2, -0.12, -0.05, 0.07), (0.0, 0.05, 0.06, 0.06)]:
        cx, cy, amp, sig = cx * size, cy * size, amp * size, sig * size
        g = amp * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sig**2))
        z = z + g
        p = p - g * (x - cx) / sig**2
        q = q - g * (y - cy) / sig**2
    scale = torch.linspace(1.0, 0.5, batch, device=device, dtype=dtype).view(-1, 1, 1, 1)
    return z * scale, p * scale, q * scale


def relative_rmse(z, z_gt, mask=None):
    """RMSE after removing the mean difference, divided by the depth range (per batch, the worst)."""
    if mask is None:
        mask = torch.ones_like(z_gt, dtype=torch.bool)
    errs = []
    for b in range(z.shape[0]):
        m = mask[b].bool()
        d = (z[b] - z_gt[b])[m]
        d = d - d.mean()
        errs.append(float(d.pow(2).mean().sqrt() / (z_gt[b][m].max() - z_gt[b][m].min())))
    return max(errs)


class TestFrankotChellappa(BaseTester):
    @pytest.mark.parametrize("boundary", ["mirror", "periodic"])
    def test_plane_and_bumps(self, device, dtype, boundary):
        z, p, q = bumps_surface(64, 80, 0.025, device, dtype)
        est = frankot_chellappa(p, q, pixel_pitch_mm=0.025, boundary=boundary)
        assert est.shape == z.shape and est.dtype == dtype and est.device.type == device.type
        assert relative_rmse(est, z) < 1e-3
        assert abs(float(est.mean())) < 1e-5 * float(z.abs().max())

    def test_tilted_plane_is_exact(self, device, dtype):
        z, p, q = bumps_surface(32, 48, 1.0, device, dtype, tilt=(0.7, 0.4))
        plane_p, plane_q = torch.full_like(p, 0.7), torch.full_like(q, 0.4)
        est = frankot_chellappa(plane_p, plane_q, boundary="periodic")
        col = torch.arange(48, device=device, dtype=dtype) - 23.5
        row = torch.arange(32, device=device, dtype=dtype).view(-1, 1) - 15.5
        self.assert_close(est[0, 0], 0.7 * col - 0.4 * row, rtol=1e-4, atol=1e-4)

    def test_mask_sets_mean_slope_and_offset(self, device, dtype):
        z, p, q = bumps_surface(40, 40, 0.1, device, dtype, tilt=(0.5, 0.0), batch=1)
        mask = torch.zeros_like(z, dtype=torch.bool)
        mask[..., 5:35, 5:35] = True
        p_noisy = torch.where(mask, p, torch.full_like(p, 9.0))  # garbage outside the mask is ignored
        est = frankot_chellappa(p_noisy, q, pixel_pitch_mm=0.1, mask=mask)
        assert abs(float(est[mask].mean())) < 1e-5
        assert relative_rmse(est, z, mask) < 0.05

    def test_module_matches_functional(self, device, dtype):
        _, p, q = bumps_surface(16, 16, 0.5, device, dtype)
        self.assert_close(FrankotChellappa(0.5, "periodic")(p, q), frankot_chellappa(p, q, 0.5, "periodic"))

    def test_integrate_dispatches(self, device, dtype):
        _, p, q = bumps_surface(16, 16, 0.5, device, dtype)
        self.assert_close(integrate(p, q, method="fc", pixel_pitch_mm=0.5), frankot_chellappa(p, q, 0.5))

    @pytest.mark.parametrize("boundary", ["mirror", "periodic"])
    def test_gradcheck(self, boundary):
        p = torch.rand(1, 1, 5, 6, dtype=torch.float64, requires_grad=True)
        q = torch.rand(1, 1, 5, 6, dtype=torch.float64, requires_grad=True)
        mask = torch.rand(1, 1, 5, 6) > 0.3
        mask[..., 0, 0] = True
        self.gradcheck(lambda a, b: frankot_chellappa(a, b, 0.3, boundary, mask), (p, q))

    def test_errors(self):
        p = torch.zeros(1, 1, 8, 8)
        with pytest.raises(ShapeError, match="same shape"):
            frankot_chellappa(p, torch.zeros(1, 1, 8, 7))
        with pytest.raises(ShapeError, match=r"\(B, 1, H, W\)"):
            frankot_chellappa(torch.zeros(8, 8), torch.zeros(8, 8))
        with pytest.raises(InputError, match="finite"):
            frankot_chellappa(p, torch.full((1, 1, 8, 8), math.nan))
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            frankot_chellappa(p, p, pixel_pitch_mm=0.0)
        with pytest.raises(InputError, match="boundary"):
            frankot_chellappa(p, p, boundary="reflect")
        with pytest.raises(ShapeError, match="mask"):
            frankot_chellappa(p, p, mask=torch.ones(1, 1, 4, 4, dtype=torch.bool))
        with pytest.raises(ShapeError, match="empty"):
            frankot_chellappa(p, p, mask=torch.zeros(1, 1, 8, 8, dtype=torch.bool))
        with pytest.raises(InputError, match="fc"):
            integrate(p, p, method="poisson")
        with pytest.raises(InputError, match="unknown"):
            integrate(p, p, method="fc", tolerance=1.0)


def doubled_grid_fc(p, q, pitch):
    """Mirrored Frankot–Chellappa as it was first written: the FFT of the (2H, 2W) mirrored gradients, in NumPy.

    An independent reference for the N-point cosine-transform solver (float64, one image ``(H, W)``).
    """
    import numpy as np

    height, width = p.shape
    p0, q0 = p.mean(), q.mean()
    gu, gv = (p - p0) * pitch, -(q - q0) * pitch
    gu = np.concatenate([gu, -gu[:, ::-1]], 1)
    gv = np.concatenate([gv, gv[:, ::-1]], 1)
    gu, gv = np.concatenate([gu, gu[::-1]], 0), np.concatenate([gv, -gv[::-1]], 0)
    wu = 2 * np.pi * np.fft.rfftfreq(2 * width)[None, :]
    wv = 2 * np.pi * np.fft.fftfreq(2 * height)[:, None]
    denom = wu**2 + wv**2
    denom[0, 0] = 1
    spectrum = (-1j * wu * np.fft.rfft2(gu) - 1j * wv * np.fft.rfft2(gv)) / denom
    z = np.fft.irfft2(spectrum, s=gu.shape)[:height, :width]
    v, u = np.meshgrid(np.arange(height) - (height - 1) / 2, np.arange(width) - (width - 1) / 2, indexing="ij")
    z = z + (p0 * u - q0 * v) * pitch
    return z - z.mean()


class TestCosineTransforms(BaseTester):
    """The N-point DCT-II of :mod:`psmini.integrate._dct` against SciPy, and FC on it against the doubled grid."""

    @pytest.mark.parametrize("shape", [(6, 9), (7, 5), (16, 16), (33, 20), (1, 4), (3, 1), (2, 2), (1, 1)])
    def test_matches_scipy(self, device, dtype, shape):
        scipy_fft = pytest.importorskip("scipy.fft")
        from psmini.integrate._dct import dct2, idct2

        x = torch.randn(2, 3, *shape, device=device, dtype=dtype)
        expected = torch.from_numpy(scipy_fft.dctn(x.double().cpu().numpy(), type=2, axes=(-2, -1)))
        inverse = torch.from_numpy(scipy_fft.idctn(x.double().cpu().numpy(), type=2, axes=(-2, -1)))
        rtol, atol = self.tolerance(dtype)
        scale = float(expected.abs().max())
        self.assert_close(dct2(x).double().cpu() / scale, expected / scale, rtol, atol)
        self.assert_close(idct2(x).double().cpu(), inverse, rtol, atol)
        self.assert_close(idct2(dct2(x)), x)

    def test_gradcheck(self):
        from psmini.integrate._dct import dct2, idct2

        x = torch.rand(2, 5, 6, dtype=torch.float64, requires_grad=True)
        self.gradcheck(dct2, (x,))
        self.gradcheck(idct2, (x,))

    @pytest.mark.parametrize("shape", [(5, 6), (4, 7)])
    def test_fc_gradcheck_without_mask(self, shape):
        p = torch.rand(2, 1, *shape, dtype=torch.float64, requires_grad=True)
        q = torch.rand(2, 1, *shape, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda a, b: frankot_chellappa(a, b, 0.3), (p, q))
        self.gradcheck(lambda a, b: frankot_chellappa(a, b, 0.3, mask=torch.ones_like(a, dtype=torch.bool)), (p, q))

    @pytest.mark.parametrize("shape", [(6, 9), (7, 5), (2, 2), (3, 8), (64, 48)])
    def test_mirror_fc_equals_doubled_grid(self, shape):
        torch.manual_seed(0)
        p, q = torch.randn(2, 1, *shape, dtype=torch.float64), torch.randn(2, 1, *shape, dtype=torch.float64)
        z = frankot_chellappa(p, q, pixel_pitch_mm=0.025)
        for b in range(2):
            expected = torch.from_numpy(doubled_grid_fc(p[b, 0].numpy(), q[b, 0].numpy(), 0.025))
            assert float((z[b, 0] - expected).abs().max() / expected.abs().max()) < 1e-12

    @pytest.mark.parametrize("shape", [(6, 9), (7, 5), (2, 2), (3, 8), (16, 11), (2, 7)])
    def test_spectral_map_equals_reference_steps(self, shape):
        """The mirrored FC's per-frequency map, probed from the reference steps between its two FFTs, gives those
        steps' result on any spectrum, not only on the probes: the steps are local in frequency (k_v with -k_v)."""
        from psmini.integrate.fourier import _mirror_plan, _mirror_reference, _reference_solution, _solution_spectrum

        height, width = shape
        torch.manual_seed(3)
        spectrum = torch.randn(3, 2, height, width // 2 + 1, dtype=torch.complex128)
        plan = _mirror_plan(height, width, 0.3, torch.device("cpu"), torch.float64)
        expected = _reference_solution(spectrum, _mirror_reference(height, width))
        self.assert_close(_solution_spectrum(spectrum, plan), expected, 1e-12, 1e-12 * float(expected.abs().max()))

    def test_first_row_and_column_stay_in_place(self):
        """The mean slopes are added in the spectrum on its row k_v = 0 and column k_u = 0 alone: the inverse
        DCT's steps map a coefficient row 0 (column 0) onto the spectrum's row 0 (column 0) and nowhere else."""
        from psmini.integrate._dct import inverse_spectrum
        from psmini.integrate._dct import plan as dct_plan

        coefficients = torch.zeros(2, 7, 6, dtype=torch.float64)
        coefficients[0, 0], coefficients[1, :, 0] = torch.rand(6) + 0.5, torch.rand(7) + 0.5
        spectrum = inverse_spectrum(coefficients, dct_plan(7, 6, torch.device("cpu"), torch.float64))
        assert float(spectrum[0, 1:].abs().max()) == 0 and float(spectrum[1, :, 1:].abs().max()) == 0
        assert float(spectrum[0, 0].abs().min()) > 0 and float(spectrum[1, :, 0].abs().min()) > 0

    @pytest.mark.parametrize("weights", ["bool", "float"])
    def test_masked_mirror_fc_equals_doubled_grid(self, weights):
        """A mask (or float weights m) replaces the gradients by m g + (1 - m) mean: the doubled grid on those
        gradients, less the depth's masked mean. Fractional weights are weights, not an all-true mask."""
        torch.manual_seed(2)
        p, q = torch.randn(3, 1, 23, 31, dtype=torch.float64), torch.randn(3, 1, 23, 31, dtype=torch.float64)
        if weights == "bool":
            mask = torch.rand(3, 1, 23, 31) > 0.3
            weight = mask.double()
        else:
            mask = weight = 0.05 + 0.95 * torch.rand(3, 1, 23, 31, dtype=torch.float64)
        z = frankot_chellappa(p, q, pixel_pitch_mm=0.025, mask=mask)
        for b in range(3):
            w = weight[b, 0].numpy()
            p0, q0 = (p[b, 0].numpy() * w).sum() / w.sum(), (q[b, 0].numpy() * w).sum() / w.sum()
            filled_p, filled_q = p0 + w * (p[b, 0].numpy() - p0), q0 + w * (q[b, 0].numpy() - q0)
            expected = doubled_grid_fc(filled_p, filled_q, 0.025)
            expected = expected - (expected * w).sum() / w.sum()
            assert float((z[b, 0].numpy() - expected).__abs__().max() / abs(expected).max()) < 1e-12

    @pytest.mark.parametrize("masked", [False, True])
    def test_mirror_fc_without_gradient_equals_recorded_path(self, masked):
        """Without a gradient to record, the CPU batch gathers the slopes straight into the transform's order and
        writes each item's depth into the batch's; with one, it concatenates. Both give the same numbers."""
        torch.manual_seed(4)
        p, q = torch.randn(3, 1, 17, 12, dtype=torch.float64), torch.randn(3, 1, 17, 12, dtype=torch.float64)
        mask = torch.rand(3, 1, 17, 12) > 0.3 if masked else None
        fast = frankot_chellappa(p, q, pixel_pitch_mm=0.025, mask=mask)
        recorded = frankot_chellappa(p.clone().requires_grad_(), q, pixel_pitch_mm=0.025, mask=mask)
        assert recorded.requires_grad and not fast.requires_grad
        assert torch.equal(fast, recorded.detach())
        items = torch.cat([frankot_chellappa(p[i : i + 1], q[i : i + 1], 0.025, mask=None if mask is None
                                             else mask[i : i + 1]) for i in range(3)])
        assert torch.equal(fast, items)

    def test_masked_gradcheck_float_weights(self):
        p = torch.rand(2, 1, 5, 6, dtype=torch.float64, requires_grad=True)
        q = torch.rand(2, 1, 5, 6, dtype=torch.float64, requires_grad=True)
        weights = (0.1 + torch.rand(2, 1, 5, 6, dtype=torch.float64)).requires_grad_()
        self.gradcheck(lambda a, b, w: frankot_chellappa(a, b, 0.3, mask=w), (p, q, weights))

    def test_mirror_fc_float32_within_1e6(self):
        """Rig-sized float32 input: the N-point solve agrees with the doubled-grid one within 1e-6 relative."""
        torch.manual_seed(1)
        _, p, q = bumps_surface(400, 400, 0.025, "cpu", torch.float32, batch=1)
        p, q = p + 0.05 * torch.randn_like(p), q + 0.05 * torch.randn_like(q)
        z = frankot_chellappa(p, q, pixel_pitch_mm=0.025)
        expected = torch.from_numpy(doubled_grid_fc(p[0, 0].double().numpy(), q[0, 0].double().numpy(), 0.025))
        assert float((z[0, 0].double() - expected).abs().max() / expected.abs().max()) < 1e-6

    def test_cuda_matches_cpu(self, cuda_device):
        _, p, q = bumps_surface(40, 56, 0.05, "cpu", torch.float64)
        expected = frankot_chellappa(p, q, 0.05)
        self.assert_close(frankot_chellappa(p.to(cuda_device), q.to(cuda_device), 0.05).cpu(), expected)
        self.assert_close(dct_poisson(p.to(cuda_device), q.to(cuda_device), 0.05).cpu(), dct_poisson(p, q, 0.05))


def smooth_surface(height, width, pitch, device, dtype):
    """A smooth, non-periodic surface (no symmetry at the border) and its exact gradients, shape (1, 1, H, W)."""
    row = torch.arange(height, device=device, dtype=dtype).view(-1, 1)
    col = torch.arange(width, device=device, dtype=dtype).view(1, -1)
    size = max(height, width) * pitch
    x, y = (col - (width - 1) / 2) * pitch / size, -(row - (height - 1) / 2) * pitch / size  # in [-0.5, 0.5]
    z = torch.sin(2 * x + 1) * torch.cos(3 * y) + 0.5 * x * y + x**2
    p = 2 * torch.cos(2 * x + 1) * torch.cos(3 * y) + 0.5 * y + 2 * x
    q = -3 * torch.sin(2 * x + 1) * torch.sin(3 * y) + 0.5 * x
    return (size * z).expand(1, 1, height, width), p.expand(1, 1, height, width), q.expand(1, 1, height, width)


def vase_mask(height, width, device):
    """A vase-like outline: a width varying with the row, narrow neck, a hole-free non-rectangular domain."""
    row = torch.arange(height, device=device, dtype=torch.float64).view(-1, 1) / (height - 1)
    col = torch.arange(width, device=device, dtype=torch.float64).view(1, -1) / (width - 1) - 0.5
    half = 0.18 + 0.2 * torch.sin(math.pi * row) ** 2 - 0.1 * torch.exp(-((row - 0.2) ** 2) / 0.005)
    return ((col.abs() < half) & (row > 0.05) & (row < 0.95)).view(1, 1, height, width)


class TestDCTPoisson(BaseTester):
    def test_non_periodic_surface(self, device, dtype):
        z, p, q = smooth_surface(96, 112, 0.05, device, dtype)
        est = dct_poisson(p, q, pixel_pitch_mm=0.05)
        assert est.dtype == dtype and est.device.type == device.type
        assert relative_rmse(est, z) < 1e-4

    def test_module_and_dispatch(self, device, dtype):
        _, p, q = bumps_surface(16, 20, 0.5, device, dtype)
        self.assert_close(DCTPoisson(0.5)(p, q), dct_poisson(p, q, 0.5))
        self.assert_close(integrate(p, q, "dct", 0.5), dct_poisson(p, q, 0.5))

    def test_gradcheck(self):
        p = torch.rand(1, 1, 5, 6, dtype=torch.float64, requires_grad=True)
        q = torch.rand(1, 1, 5, 6, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda a, b: dct_poisson(a, b, 0.3), (p, q))

    def test_errors(self):
        with pytest.raises(ShapeError, match="same shape"):
            dct_poisson(torch.zeros(1, 1, 8, 8), torch.zeros(2, 1, 8, 8))
        with pytest.raises(InputError, match="finite"):
            dct_poisson(torch.full((1, 1, 8, 8), math.inf), torch.zeros(1, 1, 8, 8))


class TestMaskedLeastSquares(BaseTester):
    def test_vase_domain(self, device, dtype):
        z, p, q = smooth_surface(96, 80, 0.1, device, dtype)
        mask = vase_mask(96, 80, device)
        # Gradients outside the domain are garbage; the solve must not see them.
        p = torch.where(mask, p, torch.full_like(p, 50.0))
        est = masked_least_squares(p, q, pixel_pitch_mm=0.1, mask=mask)
        assert relative_rmse(est, z, mask) < 1e-3
        assert float(est[~mask].abs().max()) == 0.0
        assert abs(float(est[mask].mean())) < 1e-4 * float(z.abs().max())
        # The rectangle solvers are far off on the same domain (the reason for this method).
        assert relative_rmse(dct_poisson(p, q, 0.1, mask), z, mask) > 10 * relative_rmse(est, z, mask)

    def test_batch_and_weights(self, device, dtype):
        z, p, q = bumps_surface(40, 48, 0.1, device, dtype)
        mask = torch.ones_like(z, dtype=torch.bool)
        mask[0, :, :10, :10] = False
        est = masked_least_squares(p, q, 0.1, mask, weights=torch.rand_like(z) + 0.5)
        assert relative_rmse(est, z, mask) < 1e-3

    def test_module_and_dispatch(self, device, dtype):
        _, p, q = bumps_surface(16, 20, 0.5, device, dtype)
        expected = masked_least_squares(p, q, 0.5)
        self.assert_close(MaskedLeastSquares(0.5)(p, q), expected, rtol=1e-3, atol=1e-4)
        self.assert_close(integrate(p, q, "masked", 0.5, tol=1e-6), expected, rtol=1e-3, atol=1e-4)

    def test_gradcheck(self):
        p = torch.rand(1, 1, 4, 5, dtype=torch.float64, requires_grad=True)
        q = torch.rand(1, 1, 4, 5, dtype=torch.float64, requires_grad=True)
        w = (torch.rand(1, 1, 4, 5, dtype=torch.float64) + 0.5).requires_grad_()
        mask = torch.ones(1, 1, 4, 5, dtype=torch.bool)
        mask[..., 0, :2] = False
        self.gradcheck(lambda a, b, c: masked_least_squares(a, b, 0.3, mask, c, tol=1e-12), (p, q, w))

    def test_stencil_and_transfers_equal_their_padded_definitions(self):
        """The multigrid's operator, Jacobi sweep, restriction and prolongation (border terms left out rather than
        read from zero-padded copies, 2 x 2 sums by strided views) equal their definitions on padded arrays, to
        the bit, on a masked grid of odd size."""
        import torch.nn.functional as F

        from psmini.integrate.poisson import _JACOBI_OMEGA, _Level

        gen = torch.Generator().manual_seed(0)
        wu, wv = torch.rand(2, 1, 9, 6, generator=gen), torch.rand(2, 1, 8, 7, generator=gen)
        inside = (torch.rand(2, 1, 9, 7, generator=gen) > 0.2).float()
        level = _Level.build(wu, wv, inside)
        z, r = torch.randn(2, 1, 9, 7, generator=gen), torch.randn(2, 1, 9, 7, generator=gen)
        padded = F.pad(z, (1, 1, 1, 1))
        shifted = (padded[..., 1:-1, :-2], padded[..., 1:-1, 2:], padded[..., :-2, 1:-1], padded[..., 2:, 1:-1])
        applied = level.diag * z
        for weight, neighbour in zip(level.neighbours, shifted, strict=True):
            applied.addcmul_(weight, neighbour, value=-1)
        assert torch.equal(level.apply(z), applied)
        scale, weights = level.jacobi
        swept = torch.add(r * scale, z, alpha=1 - _JACOBI_OMEGA)
        for weight, neighbour in zip(weights, shifted, strict=True):
            swept.addcmul_(weight, neighbour)
        assert torch.equal(level.smooth(z, r, 1), swept)
        zeroed = torch.where(level.active, r, torch.zeros_like(r))
        assert torch.equal(level.restrict(r), 4 * F.avg_pool2d(F.pad(zeroed, (0, 1, 0, 1)), 2))
        coarse = torch.randn(2, 1, 5, 4, generator=gen)
        fine = coarse.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)[..., :9, :7]
        assert torch.equal(level.prolong(coarse), torch.where(level.active, fine, torch.zeros_like(fine)))

    def test_errors(self):
        p = torch.zeros(1, 1, 8, 8)
        with pytest.raises(ShapeError, match="weights"):
            masked_least_squares(p, p, weights=torch.ones(1, 1, 4, 4))
        with pytest.raises(InputError, match="non-negative"):
            masked_least_squares(p, p, weights=-torch.ones(1, 1, 8, 8))
        with pytest.raises(ShapeError, match="empty"):
            masked_least_squares(p, p, mask=torch.zeros(1, 1, 8, 8, dtype=torch.bool))


class TestWeightedPoissonErrors:
    """The grid solver under masked_least_squares and near light, and its operators, called directly."""

    def system(self, height=6, width=7):
        gen = torch.Generator().manual_seed(0)
        wu, wv = torch.ones(1, 1, height, width - 1), torch.ones(1, 1, height - 1, width)
        tu = torch.rand(1, 1, height, width - 1, generator=gen)
        tv = torch.rand(1, 1, height - 1, width, generator=gen)
        return wu, wv, tu, tv, torch.ones(1, 1, height, width)

    def test_solver_misuse_raise(self):
        from psmini.integrate.poisson import solve_weighted_poisson

        wu, wv, tu, tv, mask = self.system()
        # the column edges' targets for the row edges' failed as a bare RuntimeError of broadcasting
        with pytest.raises(ShapeError, match="tu must be a \\(B, 1, 6, 6\\) tensor, got \\(1, 1, 5, 7\\)"):
            solve_weighted_poisson(wu, wv, tv, tu, mask)
        with pytest.raises(ShapeError, match="mask must be a \\(B, 1, H, W\\) tensor, got \\(6, 7\\)"):
            solve_weighted_poisson(wu, wv, tu, tv, mask[0, 0])  # was a bare IndexError
        with pytest.raises(ShapeError, match="x0 must be a \\(B, 1, 6, 7\\) tensor, got \\(1, 1, 4, 4\\)"):
            solve_weighted_poisson(wu, wv, tu, tv, mask, x0=torch.zeros(1, 1, 4, 4))
        with pytest.raises(ShapeError, match="wu must be .* got list"):
            solve_weighted_poisson(wu.tolist(), wv, tu, tv, mask)
        # an empty mask failed as a bare RuntimeError of min()
        with pytest.raises(ShapeError, match="mask must select at least one pixel, got an empty mask of 6x7"):
            solve_weighted_poisson(wu, wv, tu, tv, torch.zeros_like(mask))
        # a NaN target gave zeros after maxiter iterations; a NaN weight dropped its pixels silently
        bad = tu.clone()
        bad[0, 0, 2, 3] = math.nan
        with pytest.raises(InputError, match="tu must be finite, got 1 NaN"):
            solve_weighted_poisson(wu, wv, bad, tv, mask)
        with pytest.raises(InputError, match="wv must be finite"):
            solve_weighted_poisson(wu, torch.full_like(wv, math.inf), tu, tv, mask)
        # outside the mask's bounding box a NaN is never read, as before
        inner = torch.zeros_like(mask)
        inner[..., :, :4] = 1
        outside = tu.clone()
        outside[..., 5] = math.nan
        torch.testing.assert_close(solve_weighted_poisson(wu, wv, outside, tv, inner),
                                   solve_weighted_poisson(wu, wv, tu, tv, inner))
        assert solve_weighted_poisson(wu, wv, tu, tv, mask.bool()).shape == (1, 1, 6, 7)  # a bool mask works

    def test_operators_misuse_raise(self):
        from psmini.integrate.poisson import edge_mask, grid_differences

        # a 1-D tensor failed as a bare IndexError, a list as a TypeError, a bool map as a RuntimeError
        with pytest.raises(ShapeError, match="z must have shape \\(B, 1, H, W\\), got \\(5,\\)"):
            grid_differences(torch.ones(5))
        with pytest.raises(InputError, match="z must be a torch.Tensor, got list"):
            grid_differences([[1.0]])
        with pytest.raises(InputError, match="z must be a floating-point tensor .* got torch.bool"):
            grid_differences(torch.ones(1, 1, 4, 4, dtype=torch.bool))
        with pytest.raises(ShapeError, match="mask must be a \\(B, 1, H, W\\) tensor, got \\(5,\\)"):
            edge_mask(torch.ones(5))
        with pytest.raises(ShapeError, match="mask must be .* got list"):
            edge_mask([[1.0]])
        mu, mv = edge_mask(torch.ones(2, 1, 4, 5, dtype=torch.bool))  # a bool mask gives bool edges, as before
        assert mu.shape == (2, 1, 4, 4) and mv.shape == (2, 1, 3, 5) and mu.dtype == torch.bool


def perspective_plane(height, width, device, dtype):
    """A tilted plane seen by a pinhole camera: intrinsics, psmini normals and the true depth (mm)."""
    k = torch.tensor([[300.0, 0, width / 2 - 3], [0, 320.0, height / 2 + 2], [0, 0, 1]], device=device, dtype=dtype)
    m = torch.tensor([0.3, -0.2, -1.0], device=device, dtype=dtype)  # OpenCV-frame normal facing the camera
    m = m / m.norm()
    u = torch.arange(width, device=device, dtype=dtype).view(1, -1)
    v = torch.arange(height, device=device, dtype=dtype).view(-1, 1)
    ray_dot = m[0] * (u - k[0, 2]) / k[0, 0] + m[1] * (v - k[1, 2]) / k[1, 1] + m[2]
    depth = -500.0 / ray_dot  # plane m . P = -500 mm
    normals = torch.stack([m[0], -m[1], -m[2]]).view(1, 3, 1, 1).expand(1, 3, height, width)
    return k, normals, depth.view(1, 1, height, width)


class TestIntegrateNormals(BaseTester):
    @pytest.mark.parametrize("method", ["masked", "dct", "fc"])
    def test_perspective_plane(self, device, dtype, method):
        k, normals, depth = perspective_plane(40, 50, device, dtype)
        est = integrate_normals(normals, method, intrinsics=k)
        assert bool((est > 0).all())
        ratio = est / depth
        assert float(ratio.std() / ratio.mean()) < 1e-3  # depth up to one global scale

    def test_orthographic_matches_gradients(self, device, dtype):
        z, p, q = bumps_surface(24, 28, 0.2, device, dtype)
        normals = torch.cat([-p, -q, torch.ones_like(p)], dim=1)
        normals = normals / normals.norm(dim=1, keepdim=True)
        self.assert_close(integrate_normals(normals, "dct", pixel_pitch_mm=0.2), dct_poisson(p, q, 0.2))

    def test_log_gradients_sign(self, device, dtype):
        k, normals, depth = perspective_plane(20, 30, device, dtype)
        gu, gv, scale = perspective_log_gradients(normals, k)
        log_depth = depth.log()
        self.assert_close(
            (gu / scale)[..., 1:-1, 5], ((log_depth[..., 6] - log_depth[..., 4]) / 2)[..., 1:-1], rtol=1e-3, atol=1e-6
        )
        self.assert_close(
            (gv / scale)[..., 5, 1:-1],
            ((log_depth[..., 6, :] - log_depth[..., 4, :]) / 2)[..., 1:-1],
            rtol=1e-3,
            atol=1e-6,
        )

    def test_gradcheck(self):
        k, normals, _ = perspective_plane(5, 6, "cpu", torch.float64)
        normals = (normals + 0.05 * torch.rand_like(normals)).requires_grad_()
        self.gradcheck(lambda n: integrate_normals(n, "dct", intrinsics=k), (normals,))

    def test_gradcheck_orthographic_and_log_gradients(self):
        k, normals, _ = perspective_plane(4, 5, "cpu", torch.float64)
        normals = (normals + 0.05 * torch.rand_like(normals)).requires_grad_()
        self.gradcheck(lambda n: perspective_log_gradients(n, k), (normals,))
        self.gradcheck(lambda n: integrate_normals(n, "fc", pixel_pitch_mm=0.3), (normals,))

    def test_errors(self):
        n = torch.zeros(1, 3, 8, 8)
        n[:, 2] = 1
        with pytest.raises(ShapeError, match="normals"):
            integrate_normals(torch.zeros(1, 2, 8, 8))
        with pytest.raises(ShapeError, match="intrinsics"):
            integrate_normals(n, intrinsics=torch.eye(2))
        with pytest.raises(CalibrationError, match="focal"):
            integrate_normals(n, intrinsics=torch.diag(torch.tensor([0.0, 1.0, 1.0])))
        with pytest.raises(InputError, match="masked"):
            integrate_normals(n, method="nope")

    def test_log_gradients_errors(self):
        k = torch.tensor([[500.0, 0, 4], [0, 500.0, 4], [0, 0, 1]])
        n = torch.zeros(1, 3, 8, 8)
        n[:, 2] = 1
        # two channels gave empty gradients, a (3, H, W) map gradients of a batch of 3, a NaN normal NaN gradients
        with pytest.raises(ShapeError, match="normals must have shape \\(B, 3, H, W\\), got \\(1, 2, 8, 8\\)"):
            perspective_log_gradients(n[:, :2], k)
        with pytest.raises(ShapeError, match="got \\(3, 8, 8\\)"):
            perspective_log_gradients(n[0], k)
        with pytest.raises(InputError, match="normals must be a torch.Tensor, got list"):
            perspective_log_gradients(n.tolist(), k)
        bad = n.clone()
        bad[0, :, 3, 3] = math.nan
        with pytest.raises(InputError, match="normals must be finite, got 3 NaN"):
            perspective_log_gradients(bad, k)
        with pytest.raises(ShapeError, match="intrinsics"):
            perspective_log_gradients(n, torch.eye(2))
        with pytest.raises(CalibrationError, match="focal"):
            perspective_log_gradients(n, -k)


class TestDispatchAndModules(BaseTester):
    @pytest.mark.parametrize("method", ["fc", "dct", "masked"])
    def test_gradcheck_integrate(self, method):
        generator = torch.Generator().manual_seed(0)
        p, q = (torch.rand(2, 1, 1, 4, 5, generator=generator, dtype=torch.float64) - 0.5).requires_grad_()
        mask = torch.ones(1, 1, 4, 5, dtype=torch.bool)
        mask[..., 0, :2] = False
        self.gradcheck(lambda a, b: integrate(a, b, method, 0.3, mask), (p, q))

    @pytest.mark.parametrize("module", [FrankotChellappa(0.3), DCTPoisson(0.3), MaskedLeastSquares(0.3)], ids=repr)
    def test_gradcheck_module(self, module):
        generator = torch.Generator().manual_seed(0)
        p, q = (torch.rand(2, 1, 1, 4, 5, generator=generator, dtype=torch.float64) - 0.5).requires_grad_()
        self.gradcheck(module, (p, q))


def test_package_is_callable():
    import psmini

    p = torch.zeros(1, 1, 6, 6)
    assert psmini.integrate(p, p).shape == p.shape
    assert psmini.integrate.integrate is integrate


class TestUndoEdgeAveraging(BaseTester):
    """The trapezoidal rule of the masked least-squares integrator scales a relief of angular frequency w per
    pixel by a = (w/2) / tan(w/2); the correction on the rectangle restores it (uniform weights: exactly)."""

    @pytest.mark.parametrize("period_px", [2.4, 3.0, 5.0, 12.0])
    def test_restores_a_fine_relief(self, period_px):
        from psmini.integrate.least_squares import _undo_edge_averaging

        height, width, pitch = 8, 96, 0.025
        k = round(2 * width / period_px)  # a DCT-II basis function along u: even about both edges
        w = math.pi * k / width
        u = torch.arange(width, dtype=torch.float64) + 0.5
        z = (0.01 * torch.cos(w * u)).expand(1, 1, height, width)
        p = (-0.01 * w * torch.sin(w * u) / pitch).expand(1, 1, height, width)  # exact slopes, mm per mm
        q = torch.zeros_like(p)
        solved = integrate(p, q, "masked", pixel_pitch_mm=pitch, mask=torch.ones_like(p, dtype=torch.bool),
                           tol=1e-13, maxiter=5000)
        flattened = float((solved - solved.mean()).abs().max() / z.abs().max())
        assert flattened == pytest.approx((w / 2) / math.tan(w / 2), rel=1e-6)  # the rule's response
        self.assert_close(_undo_edge_averaging(solved - solved.mean()), z, rtol=1e-6, atol=1e-9)

    def test_cap_and_mean(self):
        from psmini.integrate.least_squares import _MAX_SHARPENING, _undo_edge_averaging

        u = torch.arange(10, dtype=torch.float64) + 0.5
        finest = torch.cos(math.pi * 9 * u / 10).expand(1, 1, 6, 10)  # response 0.03: the gain stops at the cap
        out = _undo_edge_averaging(0.5 + finest)
        self.assert_close(out, 0.5 + _MAX_SHARPENING * finest)  # and the mean is kept

    def test_gradcheck(self):
        from psmini.integrate.least_squares import _undo_edge_averaging

        self.gradcheck(_undo_edge_averaging, (torch.rand(2, 1, 5, 7, dtype=torch.float64, requires_grad=True),))
