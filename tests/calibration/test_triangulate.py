import pytest
import torch

from psmini.calibration.triangulate import triangulate_rays
from psmini.errors import CalibrationError, ShapeError
from tests.conftest import BaseTester


def _rays(leds: torch.Tensor, origins: torch.Tensor) -> torch.Tensor:
    return leds[:, None, :] - origins


class TestTriangulate(BaseTester):
    def test_exact(self, device, dtype):
        leds = torch.tensor([[15.8, 0.0, 10.0], [0.0, -15.8, 10.0]], device=device, dtype=dtype)
        origins = torch.tensor([[[0.0, 0.0, 1.5], [3.0, 3.0, 1.5], [-3.0, 3.0, 1.2]]], device=device, dtype=dtype)
        origins = origins.expand(2, -1, -1)
        positions, residuals = triangulate_rays(origins, _rays(leds, origins))
        self.assert_close(positions, leds, rtol=1e-4, atol=1e-4)
        assert float(residuals.max()) < 1e-3

    def test_residual_is_the_rms_distance(self):
        # two rays along x at y = ±d: the point lies midway, at distance d from each
        origins = torch.tensor([[[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 5.0]]], dtype=torch.float64)
        directions = torch.tensor([[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
        positions, residuals = triangulate_rays(origins, directions)
        self.assert_close(positions, torch.zeros(1, 3, dtype=torch.float64))
        self.assert_close(residuals, torch.tensor([(2 / 3) ** 0.5], dtype=torch.float64))

    def test_errors(self):
        origins = torch.zeros(1, 2, 3)
        with pytest.raises(CalibrationError, match="at least 2"):
            triangulate_rays(torch.zeros(1, 1, 3), torch.ones(1, 1, 3))
        with pytest.raises(CalibrationError, match=r"LED\(s\) \[0\].*parallel"):
            triangulate_rays(torch.tensor([[[0.0, 0, 0], [0.0, 0, 1]]]), torch.tensor([[[0.0, 0, 1], [0.0, 0, 1]]]))
        with pytest.raises(ShapeError):
            triangulate_rays(origins, torch.ones(1, 3, 3))
        with pytest.raises(ShapeError, match="weights"):
            triangulate_rays(origins, torch.ones(1, 2, 3), weights=torch.ones(2))

    def test_gradcheck(self):
        origins = torch.randn(3, 3, 3, dtype=torch.float64, requires_grad=True)
        directions = (torch.randn(3, 3, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
        self.gradcheck(triangulate_rays, (origins, directions.requires_grad_()))
