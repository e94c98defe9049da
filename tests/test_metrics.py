import math

import pytest
import torch

from psmini import InputError, ShapeError
from psmini.metrics import angular_error_deg, depth_error, mean_angular_error, median_angular_error
from tests.conftest import BaseTester


def _tilted(angle_deg: float, shape=(1, 3, 4, 4)):
    a = math.radians(angle_deg)
    return torch.tensor([math.sin(a), 0.0, math.cos(a)]).view(1, 3, 1, 1).expand(*shape).clone()


class TestAngular(BaseTester):
    def test_known_angles(self, device, dtype):
        reference = _tilted(0).to(device, dtype)
        for angle in (0.01, 1.0, 30.0, 90.0, 150.0):
            error = angular_error_deg(_tilted(angle).to(device, dtype), reference)
            self.assert_close(error, torch.full_like(error, angle), rtol=1e-4, atol=1e-4)

    def test_mean_median_masked(self, device, dtype):
        normals = _tilted(0).to(device, dtype)
        normals[..., 0, :] = _tilted(10)[..., 0, :].to(device, dtype)
        mask = torch.ones(1, 1, 4, 4, dtype=torch.bool, device=device)
        mask[..., 3, :] = False
        reference = _tilted(0).to(device, dtype)
        self.assert_close(
            mean_angular_error(normals, reference, mask),
            torch.tensor([10 / 3], device=device, dtype=dtype),
            rtol=1e-4,
            atol=1e-4,
        )
        self.assert_close(
            median_angular_error(normals, reference), torch.tensor([0.0], device=device, dtype=dtype), rtol=0, atol=1e-3
        )

    def test_empty_mask_raise(self):
        with pytest.raises(InputError, match="selects no pixel"):
            mean_angular_error(_tilted(1), _tilted(0), torch.zeros(1, 1, 4, 4, dtype=torch.bool))

    def test_shape_mismatch_raise(self):
        with pytest.raises(ShapeError, match="does not match"):
            angular_error_deg(_tilted(1), _tilted(0, shape=(1, 3, 4, 5)))

    def test_nan_estimate_raise(self):
        # NaN estimates on half the pixels were left out of the average: the 45° half alone scored 0°
        normals, reference = _tilted(0), _tilted(0)
        reference[..., :2, :] = _tilted(45)[..., :2, :]
        normals[..., :2, :] = float("nan")
        for score in (mean_angular_error, median_angular_error):
            with pytest.raises(InputError, match="normals is NaN or infinite at 8 scored pixel"):
                score(normals, reference)
        outside = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        outside[..., :2, :] = False
        assert float(mean_angular_error(normals, reference, outside)) < 1e-3  # NaN outside the mask: not scored
        reference[..., :2, :] = float("nan")
        assert float(mean_angular_error(normals, reference)) < 1e-3  # nor where the ground truth is NaN


    def test_gradcheck(self):
        # seeded: distinct angles (the median picks one of them) and no pair of equal normals (|a x b| has a kink at 0)
        gen = torch.Generator().manual_seed(0)
        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
        a = (torch.rand(1, 3, 2, 3, generator=gen, dtype=torch.float64) - 0.5 + up).requires_grad_()
        b = (torch.rand(1, 3, 2, 3, generator=gen, dtype=torch.float64) - 0.5 + up).requires_grad_()
        mask = torch.ones(1, 1, 2, 3, dtype=torch.bool)
        mask[..., 0, 0] = False
        self.gradcheck(angular_error_deg, (a, b))
        self.gradcheck(lambda x, y: mean_angular_error(x, y, mask), (a, b))
        self.gradcheck(lambda x, y: median_angular_error(x, y, mask), (a, b))


class TestDepthError(BaseTester):
    def test_offset_and_scale(self, device, dtype):
        gt = torch.rand(2, 1, 8, 8, device=device, dtype=dtype) + 1.0
        gt[0, 0, 0, 0] = float("nan")  # NaN in the ground truth counts as outside
        noise = torch.zeros_like(gt)
        noise[..., 4, 4] = 0.64
        result = depth_error(gt + 2.0 + noise, gt, align="offset")
        expected_rmse = torch.tensor([0.64 * math.sqrt(62) / 63, 0.64 * math.sqrt(63) / 64], device=device, dtype=dtype)
        self.assert_close(result["rmse"], expected_rmse, rtol=1e-3, atol=1e-4)
        scaled = depth_error(gt * 3.0, gt, align="scale")
        self.assert_close(scaled["mae"], torch.zeros(2, device=device, dtype=dtype), rtol=0, atol=1e-5)

    def test_nan_estimate_raise(self):
        gt = torch.rand(1, 1, 4, 4)
        depth = gt + torch.randn(1, 1, 4, 4)
        depth[..., 0, :] = float("nan")
        with pytest.raises(InputError, match="depth is NaN or infinite at 4 scored pixel"):
            depth_error(depth, gt)
        gt[..., 0, :] = float("nan")
        assert torch.isfinite(depth_error(depth, gt)["rmse"]).all()  # where the ground truth is NaN too: outside

    @pytest.mark.parametrize("align", ["offset", "scale", "none"])
    def test_gradcheck(self, align):
        gen = torch.Generator().manual_seed(0)  # distinct ratios: the median of "scale" picks one of them
        depth = (torch.rand(1, 1, 3, 3, generator=gen, dtype=torch.float64) + 1.0).requires_grad_()
        gt = (torch.rand(1, 1, 3, 3, generator=gen, dtype=torch.float64) + 1.0).requires_grad_()
        mask = torch.ones(1, 1, 3, 3, dtype=torch.bool)
        mask[..., 1, 1] = False
        self.gradcheck(lambda d, g: tuple(depth_error(d, g, mask, align).values()), (depth, gt))

    def test_bad_align_raise(self):
        with pytest.raises(InputError, match="align"):
            depth_error(torch.rand(1, 1, 2, 2), torch.rand(1, 1, 2, 2), align="median")
