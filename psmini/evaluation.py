"""Scoring a reconstruction of a loaded sample against its ground truth: the one rule of every entry point.

``psmini evaluate``, ``psmini demo``, ``psmini batch``, the notebooks and the benchmarks all score through
:func:`score_reconstruction`, so the same folder gives the same number everywhere.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from psmini._checks import check_shape
from psmini.config import ReconstructionConfig
from psmini.errors import InputError, ShapeError
from psmini.metrics import angular_error_deg, depth_error, mean_angular_error, median_angular_error
from psmini.pipeline import Reconstruction, reconstruct

__all__ = ["evaluate_sample", "score_reconstruction", "evaluation_mask"]


def evaluation_mask(sample, device: torch.device | str = "cpu") -> Tensor:
    """The pixels every score counts: where the ground truth is valid, :math:`(1, 1, H, W)` bool.

    That is where the ground-truth normals are finite, within the ground truth's own mask (``gt_mask``: the cloth
    of a synthetic capture, without the gaps between yarns) and the sample's mask (DiLiGenT's object outline).

    Args:
        sample: a :class:`psmini.io.Sample` with ``normals_gt`` :math:`(3, H, W)`.
        device: where to make the mask.

    Returns:
        the mask, :math:`(1, 1, H, W)` bool.

    Raises:
        InputError: when the sample has no ground-truth normals.
        ShapeError: when ``normals_gt`` is not :math:`(3, H, W)` or a mask is not of its size.

    Example:
        >>> from psmini.io import Sample
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> normals = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).repeat(1, 4, 4)
        >>> normals[:, 0, 0] = float("nan")
        >>> sample = Sample("s", torch.rand(8, 4, 4), DirectionalLights(ring_lights(8, 45.0)), normals_gt=normals)
        >>> int(evaluation_mask(sample).sum())
        15
    """
    if getattr(sample, "normals_gt", None) is None:
        raise InputError(f"sample {getattr(sample, 'name', sample)!r} has no ground-truth normals (normals_gt): "
                         "there is nothing to score against")
    sizes = check_shape(sample.normals_gt, ["3", "H", "W"], "normals_gt")
    mask = torch.isfinite(sample.normals_gt.to(device)).all(dim=0, keepdim=True)
    for name in ("gt_mask", "mask"):
        extra = getattr(sample, name)
        if extra is not None:
            if tuple(extra.shape) != (1, sizes["H"], sizes["W"]):
                raise ShapeError(f"{name} must be (1, {sizes['H']}, {sizes['W']}) like normals_gt, got "
                                 f"{tuple(extra.shape)}")
            mask = mask & extra.to(device).bool()
    return mask.unsqueeze(0)


def score_reconstruction(result: Reconstruction, sample) -> dict[str, float | int | str]:
    """Angular and depth errors of ``result`` against ``sample``'s ground truth: the one scoring rule.

    Every pixel of :func:`evaluation_mask` counts, solved or not: a pixel the solver left out (fewer than three
    usable lights) counts with its default normal (0, 0, 1), as in the DiLiGenT protocol, and how many there were
    is reported beside the error (``unsolved_pixels``, ``unsolved_share``) rather than hidden by leaving them out.

    Args:
        result: a batch-1 :class:`~psmini.pipeline.Reconstruction`.
        sample: the :class:`psmini.io.Sample` it was reconstructed from, with ``normals_gt``.

    Returns:
        dict with ``name``, ``pixels`` (scored), ``unsolved_pixels`` and ``unsolved_share`` (of the scored ones),
        ``mean_angular_error_deg``, ``median_angular_error_deg``; for near light, over the scored solved pixels, the
        median predicted error (:attr:`~psmini.nearlight.NearLightResult.normal_std`, ``normal_std_median_deg``),
        the share of errors below their prediction (``within_normal_std_share``: 0.63 for 2-D Gaussian errors
        predicted right) and the mean of error² / predicted² (``error_to_normal_std_ratio``: 1 when right); and, when
        the sample has
        ground-truth depth, ``depth_rmse_mm`` and ``depth_mae_mm`` (after removing the mean offset).

    Raises:
        InputError: when ``result`` is no reconstruction, the sample has no ground-truth normals, or none of its
            pixels has valid ground truth.
        ShapeError: when ``result`` is not a batch of one of the sample's size.

    Example:
        >>> from psmini.io import Sample
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> lights = ring_lights(8, 45.0)
        >>> flat = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 8, 8)
        >>> images = (lights @ flat.reshape(3, -1)).reshape(8, 8, 8) * 0.5
        >>> sample = Sample(name="plane", images=images, lights=DirectionalLights(lights), normals_gt=flat)
        >>> round(score_reconstruction(reconstruct(sample), sample)["mean_angular_error_deg"], 3)
        0.0
    """
    if not isinstance(result, Reconstruction):
        raise InputError(f"score_reconstruction needs a psmini Reconstruction, got {type(result).__name__}")
    mask = evaluation_mask(sample, result.normals.device)
    height, width = mask.shape[-2:]
    if tuple(result.normals.shape) != (1, 3, height, width):
        raise ShapeError(f"score_reconstruction needs a reconstruction of one sample of {sample.name!r}'s size, "
                         f"normals (1, 3, {height}, {width}); got {tuple(result.normals.shape)} (score each sample "
                         "of a batch apart)")
    if not bool(mask.any()):
        raise InputError(f"sample {sample.name!r} has no pixel with valid ground truth (finite normals_gt inside its "
                         "masks): there is nothing to score")
    device, dtype = result.normals.device, result.normals.dtype
    normals_gt = torch.nan_to_num(sample.normals_gt.to(device=device, dtype=dtype).unsqueeze(0))
    pixels = int(mask.sum())
    unsolved = int((mask & ~result.mask.bool()).sum())
    scores: dict[str, float | int | str] = {
        "name": sample.name,
        "pixels": pixels,
        "unsolved_pixels": unsolved,
        "unsolved_share": unsolved / max(pixels, 1),
        "mean_angular_error_deg": float(mean_angular_error(result.normals, normals_gt, mask)[0]),
        "median_angular_error_deg": float(median_angular_error(result.normals, normals_gt, mask)[0]),
    }
    normal_std = getattr(result, "normal_std", None)
    solved = mask & result.mask.bool()
    if normal_std is not None and bool(solved.any()):  # near light: how well its predicted errors held
        predicted = normal_std.to(device=device, dtype=dtype)[solved].clamp_min(torch.finfo(dtype).tiny)
        error = angular_error_deg(result.normals, normals_gt)[solved]
        scores["normal_std_median_deg"] = float(predicted.median())
        scores["within_normal_std_share"] = float((error < predicted).to(dtype).mean())
        scores["error_to_normal_std_ratio"] = float((error / predicted).square().mean())
    if sample.depth_gt is not None:
        errors = depth_error(result.depth, sample.depth_gt.to(device=device, dtype=dtype).unsqueeze(0), mask)
        scores["depth_rmse_mm"] = float(errors["rmse"][0])
        scores["depth_mae_mm"] = float(errors["mae"][0])
    return scores


def evaluate_sample(sample, config: ReconstructionConfig | None = None) -> dict[str, Any]:
    """Reconstruct ``sample`` with ``config`` (:func:`psmini.pipeline.reconstruct`) and score it
    (:func:`score_reconstruction`); the result also says which solver, estimator and integrator ran (``config``:
    the resolved :meth:`~psmini.config.ReconstructionConfig.to_dict`).

    Example:
        >>> from psmini.io import Sample
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> lights = ring_lights(8, 45.0)
        >>> flat = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 8, 8)
        >>> images = (lights @ flat.reshape(3, -1)).reshape(8, 8, 8) * 0.5
        >>> sample = Sample(name="plane", images=images, lights=DirectionalLights(lights), normals_gt=flat)
        >>> evaluate_sample(sample)["pixels"]
        64
    """
    config = ReconstructionConfig() if config is None else config
    scores: dict[str, Any] = score_reconstruction(reconstruct(sample, config), sample)
    scores["config"] = config.resolved(sample.lights, sample.mask is not None).to_dict()
    return scores
