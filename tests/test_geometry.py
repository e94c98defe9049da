import numpy as np
import pytest
import torch

from psmini import InputError, ShapeError
from psmini.geometry import depth_to_points, pixel_grid_mm, point_cloud
from tests.conftest import BaseTester


class TestGeometry(BaseTester):
    def test_grid_axes(self, device, dtype):
        x, y = pixel_grid_mm(4, 6, 0.025, device=device, dtype=dtype)
        self.assert_close(x[0, 1] - x[0, 0], torch.tensor(0.025, device=device, dtype=dtype))
        self.assert_close(y[1, 0] - y[0, 0], torch.tensor(-0.025, device=device, dtype=dtype))  # rows go down, y up
        self.assert_close(x.mean(), torch.tensor(0.0, device=device, dtype=dtype))
        self.assert_close(y.mean(), torch.tensor(0.0, device=device, dtype=dtype))

    def test_points_and_cloud(self, device, dtype):
        depth = torch.arange(6, device=device, dtype=dtype).view(1, 1, 2, 3).expand(2, 1, 2, 3)
        points = depth_to_points(depth, 2.0)
        assert points.shape == (2, 3, 2, 3)
        self.assert_close(points[0, :, 1, 2], torch.tensor([2.0, -1.0, 5.0], device=device, dtype=dtype))
        cloud = point_cloud(depth, 2.0)
        assert cloud.shape == (2, 6, 3)
        self.assert_close(cloud[1, 5], points[1, :, 1, 2])

    def test_bad_pitch_raise(self):
        with pytest.raises(InputError, match="pixel_pitch_mm"):
            depth_to_points(torch.zeros(1, 1, 2, 2), -1.0)

    def test_bad_grid_size_raise(self):
        # a negative size failed as torch's RuntimeError of arange; 6.5 rows silently made 7
        with pytest.raises(InputError, match="height must be a positive integer .* got -1"):
            pixel_grid_mm(-1, 3, 0.5)
        with pytest.raises(InputError, match="width must be a positive integer .* got 6.5"):
            pixel_grid_mm(3, 6.5, 0.5)
        with pytest.raises(InputError, match="height must be a positive integer .* got tensor\\(3.\\)"):
            pixel_grid_mm(torch.tensor(3.0), 3, 0.5)  # a float tensor failed as a bare TypeError of operator.index
        x, _ = pixel_grid_mm(np.int64(2), np.int64(3), 0.5)  # integers of numpy are sizes too
        assert x[0].tolist() == [-0.5, 0.0, 0.5]

    def test_bad_shape_raise(self):
        with pytest.raises(ShapeError, match="depth"):
            depth_to_points(torch.zeros(1, 2, 2, 2), 1.0)

    def test_point_cloud_misuse_raise(self):
        with pytest.raises(ShapeError, match="depth must have shape \\(B, 1, H, W\\), got \\(4, 5\\)"):
            point_cloud(torch.zeros(4, 5), 0.025)
        with pytest.raises(InputError, match="pixel_pitch_mm must be a positive finite number, got nan"):
            point_cloud(torch.zeros(1, 1, 4, 5), float("nan"))
        with pytest.raises(InputError, match="floating-point"):
            point_cloud(torch.zeros(1, 1, 4, 5, dtype=torch.int64), 0.025)

    def test_gradcheck(self):
        depth = torch.rand(1, 1, 3, 3, dtype=torch.float64, requires_grad=True)
        self.gradcheck(lambda d: point_cloud(d, 0.5), (depth,))
