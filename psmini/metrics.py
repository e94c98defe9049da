"""Accuracy metrics: angular error of normals, depth error after alignment.

The angular error follows the DiLiGenT protocol (Shi et al., CVPR 2016 / TPAMI 2019): the angle between the
estimated and the true unit normal, in degrees, averaged over the mask.
"""

from __future__ import annotations

import torch
from torch import Tensor

from psmini._checks import any_true, check_mask, check_shape
from psmini._tensor import vector_length
from psmini.errors import InputError, ShapeError

__all__ = ["angular_error_deg", "mean_angular_error", "median_angular_error", "depth_error"]


def _masked(values: Tensor, mask: Tensor | None) -> Tensor:
    """(B, 1, H, W) bool mask of where to measure: the given mask and finite values."""
    keep = torch.isfinite(values)
    if mask is not None:
        keep = keep & mask.bool()
    if bool((keep.flatten(1).sum(1) == 0).any()):
        raise InputError("the mask selects no pixel with a finite value in at least one batch item")
    return keep


def _check_scored_finite(estimate: Tensor, reference: Tensor, mask: Tensor | None, name: str,
                         reference_name: str) -> None:
    """Raise :class:`InputError` where ``estimate`` is NaN or infinite at a pixel that is scored: inside ``mask``
    with a finite ``reference``. A non-finite reference marks a pixel as outside; a non-finite estimate at a scored
    pixel was left out of the average just as silently, flattering the score (NaN on half its pixels: 0°)."""
    if not estimate.numel() or bool(torch.isfinite(estimate.detach().sum())):  # one sum: the common, finite case
        return
    bad = ~torch.isfinite(estimate).all(dim=1, keepdim=True) & torch.isfinite(reference).all(dim=1, keepdim=True)
    if mask is not None:
        bad = bad & mask.bool()
    if any_true(bad):
        raise InputError(f"{name} is NaN or infinite at {int(bad.sum())} scored pixel(s) (inside the mask, where "
                         f"{reference_name} is finite): they would be left out of the score; fill them, or leave "
                         "them out of the mask")


def angular_error_deg(normals: Tensor, normals_gt: Tensor) -> Tensor:
    """Per-pixel angle between two normal maps, degrees.

    Computed as ``atan2(|a × b|, a · b)`` after normalising both, which stays accurate near 0° where ``acos``
    loses precision.

    Args:
        normals: estimated normals, shape :math:`(B, 3, H, W)`.
        normals_gt: reference normals, same shape (or batch 1).

    Returns:
        angles :math:`(B, 1, H, W)` in degrees, in [0, 180].

    Example:
        >>> a = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> b = torch.tensor([1.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> round(float(angular_error_deg(a, b)), 6)
        45.0
    """
    sizes = check_shape(normals, ["B", "3", "H", "W"], "normals")
    check_shape(normals_gt, ["B", "3", "H", "W"], "normals_gt")
    if normals_gt.shape[0] not in (1, sizes["B"]) or normals_gt.shape[2:] != normals.shape[2:]:
        raise ShapeError(f"normals_gt {tuple(normals_gt.shape)} does not match normals {tuple(normals.shape)}")
    # normalised by vector_length: F.normalize along dim 1 runs fifty times slower on the CPU (15 ms on 400²)
    a, b = normals, normals_gt.to(normals)
    a, b = a / vector_length(a, dim=1), b / vector_length(b, dim=1)
    cross = vector_length(torch.linalg.cross(a, b.expand_as(a), dim=1), dim=1)
    dot = (a * b).sum(dim=1, keepdim=True)
    return torch.rad2deg(torch.atan2(cross, dot))


def mean_angular_error(normals: Tensor, normals_gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean angular error over a mask, degrees; one value per batch item.

    Args:
        normals: estimated normals, shape :math:`(B, 3, H, W)`.
        normals_gt: reference normals, same shape.
        mask: pixels to average over, shape :math:`(B, 1, H, W)`; all pixels when omitted.

    Returns:
        mean error :math:`(B,)`, degrees.

    Raises:
        ShapeError: when a tensor or the mask has another shape.
        InputError: when ``normals`` is NaN or infinite at a scored pixel (inside the mask, with finite
            ``normals_gt``: a non-finite ground truth counts as outside), or the mask selects no pixel.

    Example:
        >>> n = torch.nn.functional.normalize(torch.rand(2, 3, 8, 8), dim=1)
        >>> mean_angular_error(n, n).abs().max() < 1e-3
        tensor(True)
    """
    errors = angular_error_deg(normals, normals_gt)
    mask = check_mask(mask, *(errors.shape[0], errors.shape[2], errors.shape[3]))
    _check_scored_finite(normals, normals_gt, mask, "normals", "normals_gt")
    keep = _masked(errors, mask)
    return torch.where(keep, errors, torch.zeros_like(errors)).flatten(1).sum(1) / keep.flatten(1).sum(1)


def median_angular_error(normals: Tensor, normals_gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Median angular error over a mask, degrees; one value per batch item (see :func:`mean_angular_error`).

    Raises:
        ShapeError, InputError: as :func:`mean_angular_error` (NaN ``normals`` at a scored pixel included).

    Example:
        >>> n = torch.nn.functional.normalize(torch.rand(1, 3, 8, 8), dim=1)
        >>> float(median_angular_error(n, n)) < 1e-3
        True
    """
    errors = angular_error_deg(normals, normals_gt)
    mask = check_mask(mask, *(errors.shape[0], errors.shape[2], errors.shape[3]))
    _check_scored_finite(normals, normals_gt, mask, "normals", "normals_gt")
    keep = _masked(errors, mask)
    return torch.stack([e[k].median() for e, k in zip(errors, keep, strict=True)])


def depth_error(depth: Tensor, depth_gt: Tensor, mask: Tensor | None = None,
                align: str = "offset") -> dict[str, Tensor]:
    """Depth error after alignment, over a mask; NaN in ``depth_gt`` counts as outside the mask (NaN in ``depth``
    inside it, where ``depth_gt`` is finite, is refused rather than left out of the score).

    Args:
        depth: estimated depth or height, shape :math:`(B, 1, H, W)`, mm.
        depth_gt: reference, same shape, mm.
        mask: pixels to compare, shape :math:`(B, 1, H, W)`.
        align: ``"offset"`` (heights up to a constant: subtract the mean difference; orthographic integration),
            ``"scale"`` (depth up to a factor: multiply by the median ratio, the protocol of Cao et al. 2022 for
            perspective integration) or ``"none"``.

    Returns:
        dict of ``mae`` and ``rmse`` (each :math:`(B,)`, mm) and ``aligned`` depth :math:`(B, 1, H, W)`.

    Raises:
        ShapeError: when ``depth``, ``depth_gt`` or the mask has another shape.
        InputError: when ``depth`` is NaN or infinite at a scored pixel (inside the mask, with finite
            ``depth_gt``), the mask selects no pixel, or ``align`` is unknown.

    Example:
        >>> gt = torch.rand(1, 1, 8, 8)
        >>> float(depth_error(gt + 3.0, gt)["rmse"]) < 1e-6
        True
    """
    sizes = check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_shape(depth_gt, ["B", "1", "H", "W"], "depth_gt")
    if depth_gt.shape != depth.shape:
        raise ShapeError(f"depth_gt {tuple(depth_gt.shape)} does not match depth {tuple(depth.shape)}")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    _check_scored_finite(depth, depth_gt, mask, "depth", "depth_gt")
    keep = _masked(depth_gt + depth, mask)
    count = keep.flatten(1).sum(1).view(-1, 1, 1, 1)

    def masked_mean(x: Tensor) -> Tensor:
        return torch.where(keep, x, torch.zeros_like(x)).flatten(1).sum(1).view(-1, 1, 1, 1) / count

    if align == "offset":
        aligned = depth + masked_mean(depth_gt - depth)
    elif align == "scale":
        ratios = [(g[k] / d[k]).median() for d, g, k in zip(depth, depth_gt, keep, strict=True)]
        aligned = depth * torch.stack(ratios).view(-1, 1, 1, 1)
    elif align == "none":
        aligned = depth
    else:
        raise InputError(f"align must be 'offset', 'scale' or 'none', got {align!r}")
    difference = aligned - depth_gt
    return {
        "mae": masked_mean(difference.abs()).flatten(),
        "rmse": masked_mean(difference.square()).sqrt().flatten(),
        "aligned": aligned,
    }
