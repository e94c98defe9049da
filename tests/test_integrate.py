"""Normal integration: analytic surfaces integrated back, gradients, error paths."""

from __future__ import annotations

import math

import pytest
import torch

from psmini.errors import InputError, ShapeError
from psmini.integrate import FrankotChellappa, frankot_chellappa, integrate
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
