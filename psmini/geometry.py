"""Geometry of the orthographic camera: pixel grid in millimetres, depth to 3D points and point clouds.

The rig's macro camera sees about 10 mm of cloth from a working distance much larger than the cloth's relief,
so psmini's default camera is orthographic with a pixel pitch (mm per pixel on the cloth). The origin lies on the
optical axis, at the centre of the image, x right, y up, z toward the camera.
"""

from __future__ import annotations

import torch
from torch import Tensor

from psmini._checks import as_index, check_positive, check_shape
from psmini.errors import InputError

__all__ = ["pixel_grid_mm", "depth_to_points", "point_cloud"]


def pixel_grid_mm(
    height: int,
    width: int,
    pixel_pitch_mm: float,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Coordinates of the pixel centres in millimetres.

    :math:`x = (c - (W-1)/2)\,\text{pitch}` and :math:`y = -(r - (H-1)/2)\,\text{pitch}` for row r and column c.

    Args:
        height: H, rows.
        width: W, columns.
        pixel_pitch_mm: size of one pixel on the object, mm.
        device: device of the result.
        dtype: floating dtype of the result.

    Returns:
        x and y, each :math:`(H, W)`, mm.

    Raises:
        InputError: for a size that is not a positive integer, or a pitch that is not positive.

    Example:
        >>> x, y = pixel_grid_mm(3, 3, 0.5)
        >>> x[0].tolist(), y[:, 0].tolist()
        ([-0.5, 0.0, 0.5], [0.5, 0.0, -0.5])
    """
    for name, size in (("height", height), ("width", width)):
        index = as_index(size)
        if index is None or index < 1:
            raise InputError(f"pixel_grid_mm's {name} must be a positive integer (pixels), got {size!r}")
    pitch = check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    dtype = dtype or torch.get_default_dtype()
    cols = (torch.arange(width, device=device, dtype=dtype) - (width - 1) / 2) * pitch
    up = ((height - 1) / 2 - torch.arange(height, device=device, dtype=dtype)) * pitch  # rows grow downward
    y, x = torch.meshgrid(up, cols, indexing="ij")
    return x, y


def depth_to_points(depth: Tensor, pixel_pitch_mm: float) -> Tensor:
    """3D points of a height map seen by the orthographic camera.

    Args:
        depth: height toward the camera, shape :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: size of one pixel on the object, mm.

    Returns:
        points :math:`(B, 3, H, W)`, mm, camera frame (x right, y up, z toward the camera).

    Example:
        >>> depth_to_points(torch.zeros(1, 1, 2, 2), 1.0)[0, :, 0, 0].tolist()
        [-0.5, 0.5, 0.0]
    """
    sizes = check_shape(depth, ["B", "1", "H", "W"], "depth")
    x, y = pixel_grid_mm(sizes["H"], sizes["W"], pixel_pitch_mm, device=depth.device, dtype=depth.dtype)
    xy = torch.stack([x, y]).unsqueeze(0).expand(sizes["B"], -1, -1, -1)
    return torch.cat([xy, depth], dim=1)


def point_cloud(depth: Tensor, pixel_pitch_mm: float) -> Tensor:
    """Depth to a point cloud in row-major pixel order.

    Args:
        depth: height toward the camera, shape :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: size of one pixel on the object, mm.

    Returns:
        points :math:`(B, H \\cdot W, 3)`, mm.

    Raises:
        ShapeError: a depth that is not :math:`(B, 1, H, W)`. InputError: a pitch that is not a positive number, a
            depth that is not a floating-point tensor (as :func:`depth_to_points`).

    Example:
        >>> point_cloud(torch.zeros(2, 1, 4, 5), 0.025).shape
        torch.Size([2, 20, 3])
    """
    return depth_to_points(depth, pixel_pitch_mm).flatten(2).transpose(1, 2)
