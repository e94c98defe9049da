r"""Lambertian least-squares albedo and normals, and surface gradients from normals.

Woodham, "Photometric method for determining surface orientation from multiple images", Optical Engineering
19(1), 1980: under K distant lights with scaled directions :math:`L \in \mathbb{R}^{K \times 3}`, a Lambertian
pixel reads :math:`I = \rho L n`; least squares gives :math:`m = L^{+} I`, albedo :math:`\rho = \lVert m \rVert` and
normal :math:`n = m / \lVert m \rVert`. With per-observation weights :math:`w_k` (0 for shadowed or saturated
observations) the normal equations :math:`(L^T W L) m = L^T W I` are solved per pixel instead.
"""

from __future__ import annotations

from typing import overload

import torch
from torch import Tensor, nn

from psmini._checks import (
    all_true,
    any_true,
    check_finite,
    check_mask,
    check_out,
    check_same_size,
    check_shape,
    check_tensor,
)
from psmini.errors import CalibrationError, InputError, ShapeError
from psmini.lights import as_batched_lights, check_spans_3d

__all__ = ["albedo_normals", "LeastSquaresNormals", "normals_to_gradients", "solve_normal_equations"]

# Per-pixel normal matrices whose determinant falls below this fraction of (trace / 3)^3 are taken as
# rank-deficient (fewer than three usable lights, or coplanar ones): the pixel is then left out. The ratio is at
# most the ratio of the smallest to the largest eigenvalue.
_RANK_RATIO = 1e-6


def _unit_and_length(m: Tensor, solved: Tensor | None,
                     out: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Split m (B, 3, H, W) into albedo |m| and unit normal; (0, 0, 1) and albedo 0 where not solved.

    ``solved`` (B, 1, H, W) marks well-posed pixels; ``None`` means all. Pixels with |m| = 0 count as not solved.
    ``out`` (albedo, normals), checked by :func:`psmini._checks.check_out`, receives the results; only then are
    the length's clamp and fills done in place (out of place, autograd records them).
    """
    # the squared length as one product and two multiply-adds, which read each component once and write one plane
    # (m.square().sum(dim=1) writes and reads back a three-plane temporary: 0.60 against 0.28 ms with the test
    # below on 400^2; vector_norm over the 3-long dim 1 measured 10x slower still on the CPU)
    x, y, z = m[:, 0:1], m[:, 1:2], m[:, 2:3]
    tiny = torch.finfo(m.dtype).tiny  # no NaN gradient at 0
    if out is None:
        length = (x * x).addcmul_(y, y).addcmul_(z, z).clamp_min(tiny).sqrt_()
    else:
        length = torch.mul(x, x, out=out[0]).addcmul_(y, y).addcmul_(z, z).clamp_min_(tiny).sqrt_()
    normals = None if out is None else out[1]
    eps = torch.finfo(m.dtype).eps
    if solved is None and bool(length.amin() > eps):  # the usual case: one reduction, no boolean plane, no where
        return length, torch.div(m, length, out=normals)
    nonzero = length > eps
    solved = nonzero if solved is None else solved & nonzero
    if all_true(solved):  # no masked_fill, no where, one division
        return length, torch.div(m, length, out=normals)
    # an infinite length zeroes the unsolved pixels' normals in the division, and their n_z is then set to 1: two
    # passes over one plane each instead of a where over the three (and a gradient of 0 there, as where's)
    unsolved = ~solved
    normals = torch.div(m, length.masked_fill(unsolved, torch.inf), out=normals)
    normals[:, 2:3].masked_fill_(unsolved, 1.0)
    if out is None:
        return length.masked_fill(unsolved, 0), normals
    return length.masked_fill_(unsolved, 0), normals


def _project(intensities: Tensor, pinv: Tensor) -> Tensor:
    """m = L^+ I per pixel: ``pinv`` (B|1, 3, K) or (3, K) times ``intensities`` (B, K, H, W), as (B, 3, H, W)."""
    batch, _, height, width = intensities.shape
    return torch.matmul(pinv, intensities.flatten(2)).view(batch, 3, height, width)


def _solve_with_pinv(intensities: Tensor, pinv: Tensor, mask: Tensor | None = None,
                    out: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """:func:`albedo_normals` without weights, from the light matrix's pseudo-inverse ``pinv`` (3, K), for
    callers that have checked everything: the pipeline, whose flat-fielded images are finite by construction
    and whose light matrix is the same for every chunk of a batch (its SVD and the scan of the solution for NaN
    were 0.1 and 0.12 ms per 8 x 400^2 capture on one thread of the 2-core Xeon). ``mask`` is bool or ``None``;
    ``out`` is checked as :func:`albedo_normals` checks it."""
    if out is not None:
        _check_results_out(out, intensities, pinv)
    return _unit_and_length(_project(intensities, pinv), mask, out)


def _check_results_out(out, intensities: Tensor, *inputs: Tensor | None) -> None:
    """:func:`~psmini._checks.check_out` for ``(albedo, normals)`` of ``intensities`` (B, K, H, W)."""
    batch, _, height, width = intensities.shape
    check_out(out, ((batch, 1, height, width), (batch, 3, height, width)), ("albedo", "normals"),
              (intensities, *inputs))


@overload
def _check_weights(weights: Tensor, shape: torch.Size) -> Tensor: ...
@overload
def _check_weights(weights: None, shape: torch.Size) -> None: ...
def _check_weights(weights: Tensor | None, shape: torch.Size) -> Tensor | None:
    if weights is None:
        return None
    if not isinstance(weights, Tensor) or not (weights.dtype == torch.bool or weights.is_floating_point()):
        raise InputError("weights must be a bool or floating-point tensor, "
                         f"got {getattr(weights, 'dtype', type(weights))}")
    if weights.shape != shape:
        raise ShapeError(f"weights must have the shape of the intensities {tuple(shape)}, got {tuple(weights.shape)}")
    if weights.dtype != torch.bool:
        check_finite(weights, "weights")
        if bool((weights < 0).any()):
            raise InputError("weights must be non-negative")
    return weights


# indices of the six distinct entries of a symmetric 3×3 matrix: (0,0) (0,1) (0,2) (1,1) (1,2) (2,2)
_ROWS, _COLS = (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)


def _symmetric_adjugate(a: Tensor, b: Tensor, c: Tensor, d: Tensor, e: Tensor,
                       f: Tensor) -> tuple[tuple[Tensor, ...], Tensor, Tensor]:
    """Adjugate and determinant of symmetric 3×3 matrices given element-wise by their entries (00, 01, 02, 11, 12,
    22), and where each is well posed: its determinant at least ``_RANK_RATIO`` times (trace / 3)³ (1 for a
    multiple of the identity, 0 for a singular matrix), which holds when three usable, non-coplanar lights remain.

    Returns the adjugate's six distinct entries (00, 01, 02, 11, 12, 22), the determinant and the bool test, each of
    the entries' shape. Shared by :func:`solve_normal_equations` and the near-light fit, which reuses the adjugate.
    """
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    scale = ((a + d + f).detach() / 3).pow(3).clamp_min(torch.finfo(a.dtype).tiny)
    return (c00, c01, c02, c11, c12, c22), det, det.detach() > _RANK_RATIO * scale


def solve_normal_equations(gram: Tensor, rhs: Tensor, dim: int = 1) -> tuple[Tensor, Tensor]:
    """Solve many symmetric 3×3 systems in closed form (adjugate over determinant), element-wise.

    Batched LAPACK calls on millions of 3×3 systems cost far more than these few products, and the closed form
    is differentiable.

    Args:
        gram: the six distinct entries (00, 01, 02, 11, 12, 22) along ``dim``, any other shape.
        rhs: the three right-hand sides along ``dim``, the same other shape.
        dim: the dimension holding the entries.

    Returns:
        solutions (three along ``dim``; 0 where not well posed) and where the system is well posed (``dim``
        kept with size 1): its determinant is at least ``_RANK_RATIO`` times (trace / 3)³, which holds when three
        usable, non-coplanar lights remain.

    Raises:
        InputError: ``gram`` or ``rhs`` not a floating-point tensor. ShapeError: ``gram`` without six entries or
            ``rhs`` without three along ``dim``, a ``dim`` out of range, or other sizes that differ.
    """
    # other counts failed as bare TypeErrors and ValueErrors of unpacking, other shapes as RuntimeErrors; python
    # checks only (no sync: the solvers call this once per chunk)
    check_tensor(gram, "gram")
    check_tensor(rhs, "rhs")
    ndim = gram.ndim
    if not (isinstance(dim, int) and -ndim <= dim < ndim) or rhs.ndim != ndim:
        raise ShapeError(f"gram and rhs must have the same number of dimensions and dim must index one, got gram "
                         f"{tuple(gram.shape)}, rhs {tuple(rhs.shape)}, dim {dim!r}")
    axis = dim % ndim
    others = [[size for i, size in enumerate(x.shape) if i != axis] for x in (gram, rhs)]
    if (gram.shape[axis], rhs.shape[axis]) != (6, 3) or others[0] != others[1]:
        raise ShapeError(f"gram must hold 6 entries and rhs 3 along dim {dim}, with the same other sizes, got gram "
                         f"{tuple(gram.shape)} and rhs {tuple(rhs.shape)}")
    r0, r1, r2 = rhs.unbind(dim)
    (c00, c01, c02, c11, c12, c22), det, well_posed = _symmetric_adjugate(*gram.unbind(dim))
    well_posed = well_posed.unsqueeze(dim)
    safe_det = torch.where(well_posed, det.unsqueeze(dim), torch.ones_like(well_posed, dtype=det.dtype))
    m = torch.stack(
        [c00 * r0 + c01 * r1 + c02 * r2, c01 * r0 + c11 * r1 + c12 * r2, c02 * r0 + c12 * r1 + c22 * r2], dim=dim
    ) / safe_det
    return torch.where(well_posed, m, torch.zeros_like(m)), well_posed


def _weighted_solve(intensities: Tensor, lights: Tensor, weights: Tensor | None) -> tuple[Tensor, Tensor]:
    """Per-pixel weighted least squares with lights (B, K, 3) or per-pixel (B, K, 3, H, W).

    Returns m (B, 3, H, W) and where the system is well posed (B, 1, H, W).
    """
    used = torch.ones_like(intensities) if weights is None else weights.to(intensities)
    signal = intensities if weights is None else intensities * used
    if lights.ndim == 3:
        # lights shared by the pixels: the normal matrix is one small matmul over the K observations
        products = lights[..., _ROWS] * lights[..., _COLS]  # (B, K, 6)
        gram = torch.einsum("bkp,bkhw->bphw", products, used)
        rhs = torch.einsum("bki,bkhw->bihw", lights, signal)
    else:
        products = lights[:, :, _ROWS] * lights[:, :, _COLS]  # (B, K, 6, H, W)
        gram = (products * used.unsqueeze(2)).sum(1)
        rhs = (lights * signal.unsqueeze(2)).sum(1)
    return solve_normal_equations(gram, rhs, dim=1)


def _partially_weighted_solve(intensities: Tensor, lights: Tensor, weights: Tensor) -> tuple[Tensor, Tensor | None]:
    """:func:`_weighted_solve` for lights ``(B, K, 3)``, with the pseudo-inverse where every weight is 1.

    Usually only a few pixels lose an observation (a dark card corner, a saturated highlight): the normal
    equations (about 40 element-wise passes) are then formed for those pixels alone, and the others take the
    pseudo-inverse's solution (one product), which is theirs with unit weights. The N pixels' observations are
    gathered as (K, N) rows and their normal equations kept as (6, N) rows: every pass of the closed-form solve
    then reads contiguous memory (the (N, K) gather by advanced indexing and an (N, 6) solve cost 1.3 ms more on a
    capture with 30,000 such pixels).
    """
    # all(dim=1) over the K observations of a bool tensor measured 10x slower than a uint8 amin over the same dim
    ones = weights if weights.dtype == torch.bool else weights == 1
    full = ones.view(torch.uint8).amin(dim=1, keepdim=True).bool()
    if not any_true(full):
        return _weighted_solve(intensities, lights, weights)
    batch, count, height, width = intensities.shape
    m = torch.matmul(torch.linalg.pinv(lights), intensities.flatten(2)).view(batch, 3, height, width)
    if all_true(full):
        return m, None
    plane = height * width
    pixels = (~full).view(-1).nonzero()[:, 0]  # flat (b, y, x) of the pixels with a weight other than 1
    sample, pixel = pixels // plane, pixels % plane
    # where observation k of each such pixel lies in the (B, K, H, W) stack: (K, N)
    where = (sample * (count * plane) + pixel) + (torch.arange(count, device=pixels.device) * plane)[:, None]
    used = weights.take(where).to(intensities.dtype)
    signal = intensities.take(where) * used
    products = lights[..., _ROWS] * lights[..., _COLS]  # (B, K, 6)
    if lights.shape[0] == 1 or lights.stride(0) == 0:
        # one light matrix for the batch: the normal equations of all N pixels are two small matrix products
        # (per-pixel light tensors made them N tiny batched products: 130 ms for 65k pixels, now ~2 ms)
        gram, rhs = products[0].T @ used, lights[0].T @ signal
    else:
        gram = (products[sample].permute(2, 1, 0) * used).sum(1)  # (6, K, N) summed over K
        rhs = (lights[sample].permute(2, 1, 0) * signal).sum(1)
    part, well_posed = solve_normal_equations(gram, rhs, dim=0)
    m.view(batch, 3, plane)[sample, :, pixel] = part.T  # in place: m is this function's own product
    full.view(-1)[pixels] = well_posed[0]
    return m, full


def _check_lights(lights: Tensor, sizes: dict[str, int]) -> Tensor:
    """Lights (K, 3), (B, K, 3) or per-pixel (B, K, 3, H, W), matching the intensities; returned batched."""
    if isinstance(lights, Tensor) and lights.ndim == 5:
        check_shape(lights, ["B", "K", "3", "H", "W"], "lights")
        check_finite(lights, "lights")
        if lights.shape[0] not in (1, sizes["B"]) or tuple(lights.shape[3:]) != (sizes["H"], sizes["W"]):
            raise ShapeError(
                f"per-pixel lights must have shape ({sizes['B']}, K, 3, {sizes['H']}, {sizes['W']}), "
                f"got {tuple(lights.shape)}"
            )
        check_same_size(lights.shape[1], sizes["K"], "the number of lights", "lights", "intensities")
        if sizes["K"] < 3:
            raise CalibrationError(f"photometric stereo needs at least 3 lights spanning 3D, got {sizes['K']}")
        return lights.expand(sizes["B"], -1, -1, -1, -1)
    check_spans_3d(lights)
    check_same_size(lights.shape[-2], sizes["K"], "the number of lights", "lights", "intensities")
    return lights


def albedo_normals(
    intensities: Tensor, lights: Tensor, mask: Tensor | None = None, weights: Tensor | None = None, *,
    out: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Lambertian least-squares albedo and normals (Woodham 1980).

    Solves :math:`I = \rho L n` per pixel with the pseudo-inverse of the light matrix, or, with ``weights``, by
    weighted least squares per pixel (weights 0 drop shadowed or saturated observations).

    Args:
        intensities: flat-fielded images, shape :math:`(B, K, H, W)`.
        lights: light directions scaled by their intensities, shape :math:`(B, K, 3)` or :math:`(K, 3)`, camera
            frame (x right, y up, z toward the camera); or per-pixel light vectors :math:`(B, K, 3, H, W)` (near
            lights), solved pixel by pixel.
        mask: optional pixels to solve, shape :math:`(B, 1, H, W)` (bool); others get albedo 0 and normal
            (0, 0, 1).
        weights: optional per-observation weights, shape :math:`(B, K, H, W)`, bool or non-negative float.
            Pixels left with fewer than three usable lights get albedo 0 and normal (0, 0, 1).
        out: optional ``(albedo, normals)`` tensors of the results' shapes, dtype and device that receive them
            (the pipeline writes each chunk of a batch straight into the batch's tensors this way, without a
            copy). Not differentiable: refused when an input requires grad with grad enabled.

    Returns:
        albedo :math:`(B, 1, H, W)` and unit normals :math:`(B, 3, H, W)`: the ``out`` tensors when given.

    Raises:
        ShapeError: when K differs between ``intensities`` and ``lights``, or a mask, weights or ``out`` do not fit.
        CalibrationError: when the lights do not span 3D (fewer than 3, or coplanar).
        InputError: when an input holds NaN or infinite values, or ``out`` cannot take the results (see above, or
            tensors that share memory).

    Example:
        >>> from psmini.lights import ring_lights
        >>> albedo, normals = albedo_normals(torch.rand(2, 8, 4, 4), ring_lights(8, zenith_deg=55.0))
        >>> normals.shape
        torch.Size([2, 3, 4, 4])
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    lights = _check_lights(lights, sizes)
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    weights = _check_weights(weights, intensities.shape)
    if out is not None:
        _check_results_out(out, intensities, lights, weights)
    solved: Tensor | None  # pixels solved; None: all of them
    if lights.ndim == 5:
        check_finite(intensities, "intensities")
        m, solved = _weighted_solve(intensities, lights.to(intensities), weights)
    elif weights is None:
        # one product with the pseudo-inverse: a NaN or infinite reading reaches its pixel's m (0 * NaN and
        # 0 * inf are NaN), so the K-image stack is scanned only when m is not finite (on DiLiGenT cat the scan
        # of the 96 images was a quarter of the solve's time)
        pinv = torch.linalg.pinv(as_batched_lights(lights, sizes["B"], intensities))  # (B, 3, K)
        m = _project(intensities, pinv)
        if not bool(torch.isfinite(m.detach().sum())):
            check_finite(intensities, "intensities")
        return _unit_and_length(m, None if mask is None else mask.bool(), out)
    else:
        check_finite(intensities, "intensities")
        m, solved = _partially_weighted_solve(intensities, as_batched_lights(lights, sizes["B"], intensities), weights)
    if mask is not None:
        solved = mask.bool() if solved is None else solved & mask.bool()
    return _unit_and_length(m, solved, out)


class LeastSquaresNormals(nn.Module):
    """Least-squares albedo and normals with stored light directions; see :func:`albedo_normals`.

    Args:
        lights: scaled light directions, shape :math:`(K, 3)`; checked to span 3D once, here.

    Example:
        >>> from psmini.lights import ring_lights
        >>> solver = LeastSquaresNormals(ring_lights(8, 55.0))
        >>> albedo, normals = solver(torch.rand(1, 8, 4, 4))
        >>> albedo.shape
        torch.Size([1, 1, 4, 4])
    """

    lights: Tensor  # a buffer

    def __init__(self, lights: Tensor) -> None:
        super().__init__()
        self.register_buffer("lights", check_spans_3d(lights).clone())

    def forward(
        self, intensities: Tensor, mask: Tensor | None = None, weights: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Albedo :math:`(B, 1, H, W)` and normals :math:`(B, 3, H, W)` of ``intensities`` :math:`(B, K, H, W)`."""
        return albedo_normals(intensities, self.lights, mask, weights)


def normals_to_gradients(normals: Tensor, min_nz: float = 1e-2, *, out: Tensor | None = None) -> tuple[Tensor, Tensor]:
    r"""Surface gradients :math:`p = \partial z / \partial x = -n_x / n_z` and
    :math:`q = \partial z / \partial y = -n_y / n_z`.

    x points right and y up (so along image rows, downward, the height changes by :math:`-q` per pixel step).
    A normal with :math:`n_z \le` ``min_nz`` (grazing, or facing away from the camera, which a surface seen by the
    camera cannot have) would give huge or sign-flipped slopes: its :math:`n_z` is clamped to ``min_nz``, capping
    the slope at :math:`1/\text{min\_nz}` (about 89.4° for the default) with the normal's own azimuth.

    Args:
        normals: unit normals, shape :math:`(B, 3, H, W)`.
        min_nz: smallest :math:`n_z` used in the division, in (0, 1).
        out: optional :math:`(B, 2, H, W)` tensor of the normals' dtype and device that receives p and q (channels
            0 and 1). Not differentiable: refused when ``normals`` requires grad with grad enabled.

    Returns:
        p and q, each :math:`(B, 1, H, W)`, dimensionless (height per unit of x or y): views of ``out`` when given.

    Raises:
        ShapeError: when ``normals`` is not :math:`(B, 3, H, W)`, or ``out`` does not fit.
        InputError: for NaN input, ``min_nz`` outside (0, 1), or an ``out`` that cannot take the result.

    Example:
        >>> n = torch.tensor([0.6, 0.0, 0.8]).view(1, 3, 1, 1)
        >>> p, q = normals_to_gradients(n)
        >>> float(p), float(q)
        (-0.75, -0.0)
    """
    check_shape(normals, ["B", "3", "H", "W"], "normals")
    check_finite(normals, "normals")
    if not 0.0 < min_nz < 1.0:
        raise InputError(f"min_nz must lie in (0, 1), got {min_nz}")
    if out is not None:
        check_out((out,), ((normals.shape[0], 2, *normals.shape[2:]),), ("slopes",), (normals,))
    return _slopes_of(normals, min_nz, out)


def _slopes_of(normals: Tensor, min_nz: float = 1e-2, out: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:func:`normals_to_gradients` without its checks, for the pipeline's normals (unit and finite by
    construction, their scan for NaN 0.12 ms per 400^2 capture; the integrator still checks the slopes) and an
    ``out`` of the caller's own making (not checked)."""
    # one division of both slopes by -n_z; p and q are views of one (B, 2, H, W) tensor
    slopes = torch.div(normals[:, 0:2], normals[:, 2:3].clamp_min(min_nz).neg_(), out=out)
    return slopes[:, 0:1], slopes[:, 1:2]
