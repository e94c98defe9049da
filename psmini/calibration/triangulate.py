r"""LED positions from two or more sphere placements: the least-squares intersection of the reflected rays.

A sphere measures the direction to an LED from its own highlight, not the LED's position. With the sphere
at P ≥ 2 places, LED k lies near every ray ``o_kp + t d_kp`` (reflection point and direction of placement
p). The point nearest all rays in the least-squares sense minimises
``Σ_p |(I - d_kp d_kpᵀ)(s - o_kp)|²``, a 3×3 linear system per LED:

.. math:: \Big(\sum_p (I - d_p d_p^\top)\Big)\, s = \sum_p (I - d_p d_p^\top)\, o_p

(e.g. Hartley & Zisserman, "Multiple View Geometry", 2nd ed., §12 for the triangulation problem; this is
its midpoint form for many rays). The residual of an LED is the root-mean-square distance of its point
from its rays. The system is singular when the rays are parallel (placements along one ray), which is
reported rather than solved.
"""

from __future__ import annotations

import torch
from torch import Tensor

from psmini._checks import check_finite, check_shape
from psmini.errors import CalibrationError, ShapeError

__all__ = ["triangulate_rays"]

# Smallest/largest eigenvalue of the normal matrix below which the rays are taken as parallel: rays that
# meet at less than ~0.5° leave the position along them undetermined.
_PARALLEL_RATIO = 1e-4


def triangulate_rays(origins: Tensor, directions: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    r"""The least-squares intersection of each LED's rays, and its residual.

    Args:
        origins: points on the rays, shape :math:`(K, P, 3)` (K LEDs, P placements), mm.
        directions: ray directions, shape :math:`(K, P, 3)` (normalised here).
        weights: optional non-negative weight of each ray, shape :math:`(K, P)`.

    Returns:
        positions :math:`(K, 3)` mm and residuals :math:`(K,)` mm (root-mean-square distance from the rays).
        Differentiable in the origins and directions.

    Raises:
        ShapeError: for shapes that differ or are not (K, P, 3).
        CalibrationError: for fewer than 2 rays per LED, or rays (nearly) parallel, naming the LED.

    Example:
        >>> origins = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0]]])
        >>> directions = torch.tensor([[[1.0, 0, 1], [-1.0, 0, 1]]])
        >>> positions, residuals = triangulate_rays(origins, directions)
        >>> [round(v, 4) for v in positions[0].tolist()], round(float(residuals[0]), 4)
        ([1.0, 0.0, 1.0], 0.0)
    """
    sizes = check_shape(origins, ["K", "P", "3"], "origins")
    check_shape(directions, ["K", "P", "3"], "directions")
    if directions.shape != origins.shape:
        raise ShapeError(f"directions {tuple(directions.shape)} and origins {tuple(origins.shape)} must have one shape")
    check_finite(origins, "origins")
    check_finite(directions, "directions")
    if sizes["P"] < 2:
        raise CalibrationError(f"LED positions need rays from at least 2 sphere placements, got {sizes['P']}")
    if weights is None:
        weights = torch.ones(origins.shape[:2], device=origins.device, dtype=origins.dtype)
    elif tuple(weights.shape) != tuple(origins.shape[:2]):
        raise ShapeError(f"weights must have shape {tuple(origins.shape[:2])}, got {tuple(weights.shape)}")
    unit = directions / directions.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, device=origins.device, dtype=origins.dtype)
    projector = (eye - unit.unsqueeze(-1) * unit.unsqueeze(-2)) * weights.to(origins)[..., None, None]  # (K, P, 3, 3)
    normal = projector.sum(dim=1)  # (K, 3, 3)
    right = (projector @ origins.unsqueeze(-1)).sum(dim=1)  # (K, 3, 1)
    eigen = torch.linalg.eigvalsh(normal.detach())
    parallel = eigen[:, 0] <= _PARALLEL_RATIO * eigen[:, -1]
    if bool(parallel.any()):
        leds = torch.nonzero(parallel).flatten().tolist()
        raise CalibrationError(
            f"LED(s) {leds}: the reflected rays of the sphere placements are (nearly) parallel, so the LED's distance "
            "along them is undetermined; place the sphere farther apart (across the field)"
        )
    positions = torch.linalg.solve(normal, right)[..., 0]
    offsets = positions.unsqueeze(1) - origins  # (K, P, 3)
    perpendicular = offsets - (offsets * unit).sum(-1, keepdim=True) * unit
    w = weights.to(origins)
    residuals = ((perpendicular.square().sum(-1) * w).sum(1) / w.sum(1)).sqrt()
    return positions, residuals
