"""Guards and conversions shared by the integrators. Internal.

Every integrator works on *pixel-grid gradients*: ``gu`` the derivative of the unknown along image columns
(left to right) and ``gv`` along image rows (top to bottom), both per pixel step. The camera-frame gradients
``p = dz/dx``, ``q = dz/dy`` (x right, y up, millimetres) become ``gu = p`` and ``gv = -q`` for an unknown
measured in pixel steps (``z / pixel_pitch_mm``); the row axis points down, hence the sign.
"""

from __future__ import annotations

import torch
from torch import Tensor

from psmini import _tensor
from psmini._checks import check_finite, check_mask, check_positive, check_shape
from psmini.errors import ShapeError


def check_gradients(p: Tensor, q: Tensor, mask: Tensor | None, pixel_pitch_mm: float) -> tuple[Tensor | None, float]:
    """Check ``p``, ``q`` (both ``(B, 1, H, W)``, finite), the optional mask and the pitch.

    Returns the mask as a float tensor of ``p``'s dtype (``None`` when absent) and the pitch as a float.
    """
    sizes = check_shape(p, ["B", "1", "H", "W"], "p")
    check_shape(q, ["B", "1", "H", "W"], "q")
    if q.shape != p.shape:
        raise ShapeError(f"p and q must have the same shape, got p {tuple(p.shape)} and q {tuple(q.shape)}")
    if q.dtype != p.dtype or q.device != p.device:
        raise ShapeError(f"p and q must share dtype and device, got {p.dtype}/{p.device} and {q.dtype}/{q.device}")
    if sizes["H"] < 2 or sizes["W"] < 2:
        raise ShapeError(f"p and q must be at least 2x2 pixels to integrate, got {tuple(p.shape[2:])}")
    pitch = check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    check_finite(p, "p")
    check_finite(q, "q")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    if mask is not None:
        mask = mask.to(device=p.device, dtype=p.dtype)
        if not bool((mask.flatten(1).sum(1) > 0).all()):
            raise ShapeError("mask must select at least one pixel in every batch item, got an empty mask")
    return mask, pitch


def masked_mean(x: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of ``x`` ``(B, C, H, W)`` over the mask (or every pixel) per channel, shape ``(B, C, 1, 1)``."""
    if mask is None:
        return x.mean(dim=(-2, -1), keepdim=True)
    return _tensor.masked_mean(x, mask, dim=(-2, -1))


def centred_grid(height: int, width: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates ``(u, v)`` centred on the image, shapes ``(1, 1, 1, W)`` and ``(1, 1, H, 1)``.

    ``u`` grows along columns (right), ``v`` along rows (down), in pixel steps.
    """
    u = torch.arange(width, device=like.device, dtype=like.dtype) - (width - 1) / 2
    v = torch.arange(height, device=like.device, dtype=like.dtype) - (height - 1) / 2
    return u.view(1, 1, 1, width), v.view(1, 1, height, 1)
