"""Depth from a normal map, orthographic (pixel pitch) or perspective (camera intrinsics, log-depth)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from psmini._checks import check_finite, check_mask, check_positive, check_shape
from psmini.errors import CalibrationError, ShapeError
from psmini.integrate.api import integrate

__all__ = ["integrate_normals", "perspective_log_gradients"]

# Normals are clamped this far from grazing (|n . ray| >= this fraction of |ray|) before dividing.
_MIN_FACING = 1e-3


def _check_intrinsics(intrinsics: Tensor, like: Tensor) -> Tensor:
    """``(3, 3)`` or ``(B, 3, 3)`` pinhole matrix → ``(B, 3, 3)`` on ``like``'s device and dtype."""
    if not isinstance(intrinsics, Tensor) or intrinsics.shape[-2:] != (3, 3) or intrinsics.ndim not in (2, 3):
        got = tuple(intrinsics.shape) if isinstance(intrinsics, Tensor) else type(intrinsics).__name__
        raise ShapeError(f"intrinsics must have shape (3, 3) or (B, 3, 3), got {got}")
    k = intrinsics.to(device=like.device, dtype=like.dtype)
    k = k.expand(like.shape[0], 3, 3) if k.ndim == 2 else k
    if k.shape[0] != like.shape[0]:
        raise ShapeError(f"intrinsics batch ({k.shape[0]}) must match the normals' batch ({like.shape[0]})")
    check_finite(k, "intrinsics")
    if not bool(((k[:, 0, 0] > 0) & (k[:, 1, 1] > 0)).all()):
        raise CalibrationError("intrinsics must have positive focal lengths fx = K[0, 0] and fy = K[1, 1]")
    return k


def perspective_log_gradients(normals: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""Gradients of the log-depth along image columns and rows from normals seen by a pinhole camera.

    A point at depth :math:`d` along the optical axis on the ray :math:`r = ((u - c_x)/f_x, (v - c_y)/f_y, 1)`
    (OpenCV frame: x right, y down, z forward) is :math:`P = d\,r`; its tangents are orthogonal to the normal
    :math:`m`, which gives :math:`\partial_u \log d = -m_x/(f_x\, m\cdot r)` and
    :math:`\partial_v \log d = -m_y/(f_y\, m\cdot r)` (Durou and Courteille, "Integration of a normal field without
    boundary condition", 2007; Quéau, Durou and Aujol, JMIV 2018). The psmini normal :math:`(n_x, n_y, n_z)`
    (y up, z toward the camera) is :math:`m = (n_x, -n_y, -n_z)`. Normals closer than 1e-3 to grazing are
    clamped there.

    Args:
        normals: unit normals :math:`(B, 3, H, W)`, psmini's camera frame.
        intrinsics: pinhole matrix :math:`(3, 3)` or :math:`(B, 3, 3)`, pixels, ``u`` = column, ``v`` = row.

    Returns:
        ``(gu, gv, scale)``: :math:`\partial_u\log d` and :math:`\partial_v\log d` scaled by ``scale`` (the
        mean focal length, so they read as slopes), each :math:`(B, 1, H, W)`, and ``scale`` :math:`(B, 1, 1, 1)`.

    Raises:
        ShapeError: when ``normals`` is not :math:`(B, 3, H, W)` or the intrinsics do not fit.
        CalibrationError: when the intrinsics have non-positive focal lengths.
        InputError: when the normals hold NaN/inf or are not a floating-point tensor.

    Example:
        >>> k = torch.tensor([[500.0, 0, 8], [0, 500.0, 8], [0, 0, 1]])
        >>> n = torch.zeros(1, 3, 16, 16); n[:, 2] = 1
        >>> gu, gv, scale = perspective_log_gradients(n, k)
        >>> float(gu.abs().max()), float(scale)
        (0.0, 500.0)
    """
    # normals of 2 channels gave empty gradients, a (3, H, W) map a batch of 3, a NaN normal NaN gradients
    check_shape(normals, ["B", "3", "H", "W"], "normals")
    check_finite(normals, "normals")
    gu, gv, scale, _ = _perspective_terms(normals, _check_intrinsics(intrinsics, normals))
    return gu, gv, scale


def _perspective_terms(normals: Tensor, k: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    r""":func:`perspective_log_gradients`' results and the normal's component along the pixel's ray
    :math:`-m\cdot r` (clamped away from grazing), the factor of the depth derivatives in the normal-form
    equations (Cao et al.'s :math:`\tilde n_z` over the focal length)."""
    height, width = normals.shape[-2:]
    fx, fy = k[:, 0, 0].view(-1, 1, 1, 1), k[:, 1, 1].view(-1, 1, 1, 1)
    cx, cy = k[:, 0, 2].view(-1, 1, 1, 1), k[:, 1, 2].view(-1, 1, 1, 1)
    u = torch.arange(width, device=normals.device, dtype=normals.dtype).view(1, 1, 1, -1)
    v = torch.arange(height, device=normals.device, dtype=normals.dtype).view(1, 1, -1, 1)
    rx, ry = (u - cx) / fx, (v - cy) / fy
    mx, my, mz = normals[:, 0:1], -normals[:, 1:2], -normals[:, 2:3]
    facing = mx * rx + my * ry + mz  # negative for a surface facing the camera
    limit = _MIN_FACING * torch.sqrt(1 + rx**2 + ry**2)
    facing = torch.minimum(facing, -limit)
    scale = (fx + fy) / 2
    return -scale * mx / (fx * facing), -scale * my / (fy * facing), scale, -facing


def integrate_normals(
    normals: Tensor,
    method: str = "masked",
    mask: Tensor | None = None,
    intrinsics: Tensor | None = None,
    pixel_pitch_mm: float = 1.0,
    **options: Any,
) -> Tensor:
    r"""Depth from a normal map: orthographic height, or perspective depth with camera intrinsics.

    Without ``intrinsics`` the normals become :math:`p = -n_x/n_z`, :math:`q = -n_y/n_z` (``n_z`` clamped at
    1e-3) and are integrated at ``pixel_pitch_mm``. With ``intrinsics`` the log-depth gradients of
    :func:`perspective_log_gradients` are integrated (in units of the mean focal length, so the same methods and
    options apply) and exponentiated: the result is the depth along the optical axis up to one global scale.
    ``"bilateral"`` gets the paper's perspective confidence :math:`(n\cdot r)^2` (normal against the pixel's ray
    :math:`r = ((u - c_x)/f_x, (v - c_y)/f_y, 1)`) as its ``weights`` unless the caller passes its own.

    Args:
        normals: unit normals :math:`(B, 3, H, W)` (x right, y up, z toward the camera).
        method: any name of :data:`psmini.integrate.METHODS` (default ``"masked"``).
        mask: optional pixels to integrate :math:`(B, 1, H, W)`.
        intrinsics: optional pinhole matrix :math:`(3, 3)` or :math:`(B, 3, 3)` in pixels; switches to perspective.
        pixel_pitch_mm: orthographic pixel size on the surface in mm (ignored with ``intrinsics``).
        **options: passed to the method.

    Returns:
        :math:`(B, 1, H, W)`: without intrinsics the height toward the camera in mm with the method's offset
        convention (zero mean over the mask); with intrinsics the positive depth along the optical axis, scaled
        so that its geometric mean over the mask is 1 (multiply by a known depth to fix the scale).
        Differentiable with respect to ``normals`` as the method is.

    Raises:
        ShapeError: when ``normals`` is not :math:`(B, 3, H, W)` or the mask or intrinsics do not fit.
        CalibrationError: when the intrinsics have non-positive focal lengths.
        InputError: when the normals hold NaN/inf, the pitch is not positive, or the method is unknown.

    Example:
        >>> n = torch.zeros(1, 3, 16, 16); n[:, 2] = 1
        >>> k = torch.tensor([[500.0, 0, 8], [0, 500.0, 8], [0, 0, 1]])
        >>> depth = integrate_normals(n, "dct", intrinsics=k)
        >>> round(float(depth.mean()), 4)
        1.0
    """
    sizes = check_shape(normals, ["B", "3", "H", "W"], "normals")
    check_finite(normals, "normals")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    if intrinsics is None:
        pitch = check_positive(pixel_pitch_mm, "pixel_pitch_mm")
        nz = normals[:, 2:3].clamp_min(_MIN_FACING)
        return integrate(-normals[:, 0:1] / nz, -normals[:, 1:2] / nz, method, pitch, mask, **options)
    gu, gv, scale, facing = _perspective_terms(normals, _check_intrinsics(intrinsics, normals))
    if method == "bilateral" and "weights" not in options:
        options["weights"] = facing.square()  # the paper's perspective normal form (normal against the ray)
    log_depth = integrate(gu, -gv, method, 1.0, mask, **options) / scale
    depth = torch.exp(log_depth)
    return depth if mask is None else torch.where(mask.bool(), depth, torch.zeros_like(depth))
