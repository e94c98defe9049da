"""Scoring a reconstruction of a loaded sample against its ground truth (used by ``psmini evaluate`` and benchmarks)."""

from __future__ import annotations

import torch

from psmini.metrics import depth_error, mean_angular_error, median_angular_error
from psmini.pipeline import Reconstruction, reconstruct

__all__ = ["evaluate_sample", "score_reconstruction"]


def score_reconstruction(result: Reconstruction, sample) -> dict[str, float | int | str]:
    """Angular and depth errors of ``result`` against ``sample``'s ground truth, over its mask.

    The evaluation mask is the sample's mask (all pixels when it has none) intersected with the ground truth's
    own validity; pixels the solver left out still count (with the default normal), as in the DiLiGenT protocol.

    Args:
        result: a batch-1 :class:`~psmini.pipeline.Reconstruction`.
        sample: the :class:`psmini.io.Sample` it was reconstructed from, with ``normals_gt``.

    Returns:
        dict with ``name``, ``pixels``, ``mean_angular_error_deg``, ``median_angular_error_deg`` and, when the
        sample has ground-truth depth, ``depth_rmse_mm`` and ``depth_mae_mm`` (after removing the mean offset).

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
    device, dtype = result.normals.device, result.normals.dtype
    normals_gt = sample.normals_gt.to(device=device, dtype=dtype).unsqueeze(0)
    mask = torch.isfinite(normals_gt).all(dim=1, keepdim=True)
    if sample.mask is not None:
        mask = mask & sample.mask.to(device).unsqueeze(0).bool()
    normals_gt = torch.nan_to_num(normals_gt)
    scores: dict[str, float | int | str] = {
        "name": sample.name,
        "pixels": int(mask.sum()),
        "mean_angular_error_deg": float(mean_angular_error(result.normals, normals_gt, mask)[0]),
        "median_angular_error_deg": float(median_angular_error(result.normals, normals_gt, mask)[0]),
    }
    if sample.depth_gt is not None:
        errors = depth_error(result.depth, sample.depth_gt.to(device=device, dtype=dtype).unsqueeze(0), mask)
        scores["depth_rmse_mm"] = float(errors["rmse"][0])
        scores["depth_mae_mm"] = float(errors["mae"][0])
    return scores


def evaluate_sample(
    sample,
    *,
    device: torch.device | str = "cpu",
    integrator: str | None = None,
    light_model: str = "distant",
    method: str = "lstsq",
) -> dict[str, float | int | str]:
    """Reconstruct ``sample`` (:func:`psmini.pipeline.reconstruct`, with its ``method``) and score it; see
    :func:`score_reconstruction`.

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
    result = reconstruct(sample, device=device, integrator=integrator, light_model=light_model, method=method)
    return score_reconstruction(result, sample)
