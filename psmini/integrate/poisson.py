r"""Weighted least-squares integration on a pixel grid: operators, a multigrid-preconditioned CG, gradients.

Every integrator beyond the Fourier ones reduces to one problem on the 4-connected pixel grid:

.. math::
    \min_z \sum_{(i,j)} w^u_{ij} (z_{i,j+1} - z_{ij} - t^u_{ij})^2
        + \sum_{(i,j)} w^v_{ij} (z_{i+1,j} - z_{ij} - t^v_{ij})^2

with edge weights ``w`` (zero on edges leaving the mask) and edge targets ``t``. Its normal equations
:math:`L z = D^\top W t` hold a weighted graph Laplacian :math:`L = D^\top W D`, solved here by conjugate gradients
preconditioned with a V-cycle of aggregation multigrid (2×2 aggregates, Galerkin coarse operators, damped
Jacobi smoothing). Pixels outside the mask are identity rows held at 0.

Gradients are implicit (no differentiation through the CG iterations): with :math:`\lambda = L^{-1}\bar z`,
:math:`\partial/\partial t = W D\lambda` and :math:`\partial/\partial w = (t - Dz)\odot D\lambda` (one more solve
in the backward pass).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from psmini._checks import check_finite, check_shape
from psmini.errors import ShapeError

logger = logging.getLogger(__name__)

__all__ = ["solve_weighted_poisson", "edge_mask", "grid_differences"]

_COARSEST = 12  # stop coarsening when a side is at most this many pixels; solve densely there
_JACOBI_OMEGA = 0.8
_SWEEPS = 2
_CHECK_EVERY = 5  # iterations between convergence checks (each check syncs with the device)
_STAGNATION = 20  # iterations without a better residual before giving up


def _check_grid(x: object, name: str, size: tuple[int, int] | None = None) -> None:
    """Raise :class:`ShapeError` unless ``x`` is a ``(B, 1, H, W)`` tensor (any dtype: a bool mask works), of
    ``size`` (H, W) when given."""
    if (not isinstance(x, Tensor) or x.ndim != 4 or x.shape[1] != 1
            or (size is not None and tuple(x.shape[2:]) != size)):
        expected = "(B, 1, H, W)" if size is None else f"(B, 1, {size[0]}, {size[1]})"
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ShapeError(f"{name} must be a {expected} tensor, got {got}")


def grid_differences(z: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences of ``z`` ``(B, 1, H, W)`` along columns ``(B, 1, H, W-1)`` and rows ``(B, 1, H-1, W)``.

    Raises:
        ShapeError: a ``z`` that is not :math:`(B, 1, H, W)`. InputError: one that is not a floating-point tensor.
    """
    check_shape(z, ["B", "1", "H", "W"], "z")  # a 1-D z failed as a bare IndexError, a bool one as a RuntimeError
    return z[..., :, 1:] - z[..., :, :-1], z[..., 1:, :] - z[..., :-1, :]


def divergence(fu: Tensor, fv: Tensor) -> Tensor:
    r""":math:`D^\top` of edge fields ``fu`` ``(B,1,H,W-1)``, ``fv`` ``(B,1,H-1,W)``, shape ``(B,1,H,W)``."""
    return F.pad(fu, (1, 0)) - F.pad(fu, (0, 1)) + F.pad(fv, (0, 0, 1, 0)) - F.pad(fv, (0, 0, 0, 1))


def edge_mask(mask: Tensor) -> tuple[Tensor, Tensor]:
    """Edges with both ends inside ``mask`` (float ``(B,1,H,W)``): shapes ``(B,1,H,W-1)`` and ``(B,1,H-1,W)``.

    Raises:
        ShapeError: a mask that is not a :math:`(B, 1, H, W)` tensor.
    """
    _check_grid(mask, "mask")  # a 1-D mask failed as a bare IndexError, a list as a TypeError
    return mask[..., :, 1:] * mask[..., :, :-1], mask[..., 1:, :] * mask[..., :-1, :]


def _add_neighbours(out: Tensor, weights, x: Tensor, value: float) -> Tensor:
    """``out`` plus ``value`` times each neighbour weight (left, right, up, down) times that neighbour of ``x``, in
    place, in that order. A weight toward a pixel beyond the border is 0 (:meth:`_Level.build`), so those pixels'
    terms are left out rather than read from a zero-padded copy (one copy of ``x`` fewer per pass; the same
    value: the left-out terms were products with zero)."""
    left, right, up, down = weights
    out[..., :, 1:].addcmul_(left[..., :, 1:], x[..., :, :-1], value=value)
    out[..., :, :-1].addcmul_(right[..., :, :-1], x[..., :, 1:], value=value)
    out[..., 1:, :].addcmul_(up[..., 1:, :], x[..., :-1, :], value=value)
    out[..., :-1, :].addcmul_(down[..., :-1, :], x[..., 1:, :], value=value)
    return out


@dataclass
class _Level:
    """One grid of the multigrid hierarchy as a 5-point stencil.

    ``left``, ``right``, ``up``, ``down`` hold each pixel's weight to that neighbour; active rows are inside
    pixels with at least one edge; every other row is the identity (zero neighbour weights, diagonal 1).
    """

    wu: Tensor
    wv: Tensor
    active: Tensor
    neighbours: Tensor  # (4, B, 1, H, W): left, right, up, down
    diag: Tensor

    @classmethod
    def build(cls, wu: Tensor, wv: Tensor, inside: Tensor) -> _Level:
        left, right = F.pad(wu, (1, 0)), F.pad(wu, (0, 1))
        up, down = F.pad(wv, (0, 0, 1, 0)), F.pad(wv, (0, 0, 0, 1))
        total = left + right + up + down
        active = (inside > 0) & (total > 0)
        zero = torch.zeros_like(total)
        neighbours = torch.stack([torch.where(active, w, zero) for w in (left, right, up, down)])
        return cls(wu, wv, active, neighbours, torch.where(active, total, torch.ones_like(total)))

    def apply(self, z: Tensor) -> Tensor:
        # one pass per neighbour (the products accumulated in place): the hierarchy's tensors outgrow the cache
        # and every pass reads them from memory
        return _add_neighbours(self.diag * z, self.neighbours, z, -1)

    @functools.cached_property
    def jacobi(self) -> tuple[Tensor, Tensor]:
        r"""The damped Jacobi sweep's constants: :math:`\omega / d` and the neighbour weights times it (4, ...)."""
        scale = _JACOBI_OMEGA / self.diag
        return scale, self.neighbours * scale

    def smooth(self, x: Tensor | None, r: Tensor, sweeps: int) -> Tensor:
        r"""``sweeps`` damped Jacobi sweeps :math:`x \leftarrow x + \omega D^{-1}(r - A x)` from ``x`` (zero when
        ``None``), each computed as :math:`(1 - \omega) x + \omega D^{-1} r + \omega D^{-1} N x` (:math:`N` the
        neighbour weights, :math:`A = D - N`): one pass per neighbour, and the first sweep from zero is
        :math:`\omega D^{-1} r` alone."""
        if sweeps == 0:
            return torch.zeros_like(r) if x is None else x
        scale, weights = self.jacobi
        start = r * scale
        if x is None:  # the first sweep from zero
            x, sweeps = start, sweeps - 1
        for _ in range(sweeps):
            x = _add_neighbours(torch.add(start, x, alpha=1 - _JACOBI_OMEGA), weights, x, 1)
        return x

    @functools.cached_property
    def inside(self) -> Tensor:
        """The active rows as 1.0, the others 0.0 (a product with it is ``where(active, x, 0)``'s value, on the
        CPU in a third of the time)."""
        return self.active.to(self.diag.dtype)

    def restrict(self, r: Tensor) -> Tensor:
        """The sums over 2 x 2 aggregates of the active rows' residuals, added in ``4 * avg_pool2d``'s order (its
        value; a quarter of its time on the CPU)."""
        r = r * self.inside
        height, width = r.shape[-2:]
        r = F.pad(r, (0, width % 2, 0, height % 2))
        return r[..., 0::2, 0::2] + r[..., 0::2, 1::2] + r[..., 1::2, 0::2] + r[..., 1::2, 1::2]

    def prolong(self, xc: Tensor) -> Tensor:
        height, width = self.active.shape[-2:]
        x = xc.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)[..., :height, :width]
        return x * self.inside

    def coarsen(self) -> _Level:
        height, width = self.active.shape[-2:]
        ph, pw = height % 2, width % 2
        wu, wv = F.pad(self.wu, (0, pw, 0, ph)), F.pad(self.wv, (0, pw, 0, ph))
        # Galerkin operator of piecewise-constant aggregation: the fine edges between 2x2 aggregates (column edges
        # at odd columns summed over the aggregate's two rows, row edges at odd rows). Scaling it down (as a
        # rediscretisation would) made the V-cycle indefinite on random data; the Galerkin sum stays SPD.
        wu_c = wu[..., :, 1::2].unflatten(-2, (-1, 2)).sum(-2)
        wv_c = wv[..., 1::2, :].unflatten(-1, (-1, 2)).sum(-1)
        inside_c = F.max_pool2d(F.pad(self.active.to(wu.dtype), (0, pw, 0, ph)), 2)
        return _Level.build(wu_c, wv_c, inside_c)


class _Hierarchy:
    """Multigrid V-cycle used as a symmetric preconditioner; a dense pseudo-inverse on the coarsest grid."""

    def __init__(self, wu: Tensor, wv: Tensor, inside: Tensor) -> None:
        self.levels = [_Level.build(wu, wv, inside)]
        while min(self.levels[-1].active.shape[-2:]) > _COARSEST:
            self.levels.append(self.levels[-1].coarsen())
        # the coarsest grid's dense inverse in float64 whatever the dtype, damped smoothly below float32's resolution
        # (Tikhonov's λ / (λ² + τ²) on each eigenvalue, τ = n ε₃₂ λ_max): its null space (a constant per connected
        # region) and the modes whose gain float32 cannot apply go to 0 without a cutoff to flip. float32's own
        # pseudo-inverse rounded those modes, and the preconditioner with them, differently from float64's and from one
        # thread count to another; a solve stopped at a loose tolerance then differed by micrometres (near light's
        # normals by 0.007° on a purl, float32 against float64)
        coarsest = _Level.build(self.levels[-1].wu.double(), self.levels[-1].wv.double(), self.levels[-1].inside)
        batch, _, height, width = coarsest.active.shape
        n = height * width
        basis = torch.eye(n, device=wu.device, dtype=torch.float64).view(1, n, 1, height, width)
        basis = basis.expand(batch, -1, -1, -1, -1)
        expand = lambda t: t.unsqueeze(1).expand(-1, n, -1, -1, -1).reshape(batch * n, *t.shape[1:])  # noqa: E731
        level = _Level(
            coarsest.wu, coarsest.wv, expand(coarsest.active), torch.stack([expand(w) for w in coarsest.neighbours]),
            expand(coarsest.diag)
        )
        dense = level.apply(basis.reshape(batch * n, 1, height, width)).view(batch, n, n)
        values, vectors = torch.linalg.eigh(dense)
        damping = n * torch.finfo(torch.float32).eps * values.abs().amax(dim=-1, keepdim=True)
        gains = values / (values.square() + damping.square())
        self.coarse_inverse = ((vectors * gains.unsqueeze(-2)) @ vectors.transpose(-1, -2)).to(wu.dtype)

    @property
    def fine(self) -> _Level:
        return self.levels[0]

    def precondition(self, r: Tensor, index: int = 0) -> Tensor:
        level = self.levels[index]
        if index == len(self.levels) - 1:
            return (self.coarse_inverse @ r.flatten(1).unsqueeze(-1)).view_as(r)
        x = level.smooth(None, r, _SWEEPS)
        x = x + level.prolong(self.precondition(level.restrict(r - level.apply(x)), index + 1))
        return level.smooth(x, r, _SWEEPS)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(dim=(1, 2, 3), keepdim=True)


def _pcg(hierarchy: _Hierarchy, b: Tensor, x0: Tensor, tol: float, maxiter: int) -> Tensor:
    """Preconditioned conjugate gradients on every batch item at once, to ``|r| <= tol |b|`` per item.

    The residual is kept free of the constant mode (the Laplacian's null space on a connected mask), which
    rounding would otherwise feed; the best iterate is returned if the residual stagnates above ``tol``
    (float32 reaches about 1e-6), instead of letting lost orthogonality take the iterates away.
    """
    op = hierarchy.fine
    active = op.active.to(b.dtype)
    count = active.sum(dim=(1, 2, 3), keepdim=True).clamp_min(1)

    def project(r: Tensor) -> Tensor:
        return (r - _dot(r, active) / count) * active

    tiny = torch.finfo(b.dtype).tiny
    x = x0.clone()
    r = project(b - op.apply(x))
    z = hierarchy.precondition(r)
    d = z.clone()
    rz = _dot(r, z)
    threshold = (tol * b.flatten(1).norm(dim=1)).clamp_min(tiny).view(-1, 1, 1, 1)
    best_x, best_res = x, r.flatten(1).norm(dim=1).view(-1, 1, 1, 1)
    since_best, iteration = 0, 0
    for iteration in range(1, maxiter + 1):
        ad = op.apply(d)
        alpha = rz / _dot(d, ad).clamp_min(tiny)
        x = x + alpha * d
        r = project(r - alpha * ad)
        res = r.flatten(1).norm(dim=1).view(-1, 1, 1, 1)
        improved = res < best_res
        best_x, best_res = torch.where(improved, x, best_x), torch.where(improved, res, best_res)
        if iteration % _CHECK_EVERY == 0:
            if bool((best_res <= threshold).all()):
                break
            since_best = 0 if bool(improved.any()) else since_best + _CHECK_EVERY
            if since_best >= _STAGNATION:
                logger.info(
                    "conjugate gradients stagnated at relative residual %.2e (tol %.1e) after %d iterations",
                    float((best_res / threshold).max()) * tol, tol, iteration,
                )
                break
        z = hierarchy.precondition(r)
        rz_new = _dot(r, z)
        d = z + (rz_new / rz.clamp_min(tiny)) * d
        rz = rz_new
    else:
        logger.warning(
            "conjugate gradients stopped at maxiter=%d with relative residual %.2e > tol=%.1e",
            maxiter, float((best_res / threshold).max()) * tol, tol,
        )
    logger.debug("conjugate gradients: %d iterations", iteration)
    return best_x


class _WeightedPoisson(torch.autograd.Function):
    """Solve the weighted edge least squares; backward by implicit differentiation (one more solve)."""

    @staticmethod
    def forward(ctx, wu, wv, tu, tv, inside, x0, tol, maxiter):
        hierarchy = _Hierarchy(wu, wv, inside)
        b = torch.where(hierarchy.fine.active, divergence(wu * tu, wv * tv), torch.zeros_like(x0))
        z = _pcg(hierarchy, b, torch.where(hierarchy.fine.active, x0, torch.zeros_like(x0)), tol, maxiter)
        ctx.hierarchy, ctx.tol, ctx.maxiter = hierarchy, tol, maxiter
        ctx.save_for_backward(wu, wv, tu, tv, z)
        return z

    @staticmethod
    def backward(ctx, grad_z):
        wu, wv, tu, tv, z = ctx.saved_tensors
        active = ctx.hierarchy.fine.active
        rhs = torch.where(active, grad_z, torch.zeros_like(grad_z))
        lam = _pcg(ctx.hierarchy, rhs, torch.zeros_like(rhs), ctx.tol, ctx.maxiter)
        lu, lv = grid_differences(lam)
        zu, zv = grid_differences(z)
        return (tu - zu) * lu, (tv - zv) * lv, wu * lu, wv * lv, None, None, None, None


def solve_weighted_poisson(
    wu: Tensor,
    wv: Tensor,
    tu: Tensor,
    tv: Tensor,
    mask: Tensor,
    x0: Tensor | None = None,
    tol: float | None = None,
    maxiter: int = 500,
) -> Tensor:
    r"""Minimise :math:`\sum w^u (D_u z - t^u)^2 + \sum w^v (D_v z - t^v)^2` over the pixels of ``mask``.

    Args:
        wu, tu: weights and targets of the column edges, shape :math:`(B, 1, H, W-1)`.
        wv, tv: weights and targets of the row edges, shape :math:`(B, 1, H-1, W)`.
        mask: float mask :math:`(B, 1, H, W)`; edges leaving it are dropped.
        x0: optional initial guess :math:`(B, 1, H, W)` (warm start).
        tol: relative residual at which CG stops (default 1e-6 in float32, 1e-10 in float64).
        maxiter: most CG iterations.

    Returns:
        :math:`z` of shape :math:`(B, 1, H, W)`, zero mean over the mask, 0 outside it. Several disconnected
        regions each get their own arbitrary offset. Differentiable in the weights and the targets.

    Raises:
        ShapeError: a tensor of another shape (targets of the column edges for the row edges', a 2-D mask), or a
            mask that selects no pixel.
        InputError: NaN or infinite weights, targets or ``x0`` within the mask's bounding box.
    """
    # shapes that do not fit failed as bare RuntimeErrors of broadcasting or IndexErrors, an empty mask as a
    # RuntimeError of min(); NaN targets gave zeros after maxiter, NaN weights dropped their pixels silently
    _check_grid(mask, "mask")
    height, width = mask.shape[-2:]
    for name, x in (("wu", wu), ("tu", tu)):
        _check_grid(x, name, (height, width - 1))
    for name, x in (("wv", wv), ("tv", tv)):
        _check_grid(x, name, (height - 1, width))
    if x0 is not None:
        _check_grid(x0, "x0", (height, width))
    inside = (mask > 0).any(dim=0).any(dim=0)  # (H, W): inside for some sample
    rows, cols = inside.any(dim=1).nonzero().flatten(), inside.any(dim=0).nonzero().flatten()  # ascending
    if rows.numel() == 0:
        raise ShapeError(f"mask must select at least one pixel, got an empty mask of {height}x{width}")
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    if (r1 - r0, c1 - c0) != (height, width):  # solve on the mask's bounding box only
        z = solve_weighted_poisson(
            wu[..., r0:r1, c0 : c1 - 1], wv[..., r0 : r1 - 1, c0:c1], tu[..., r0:r1, c0 : c1 - 1],
            tv[..., r0 : r1 - 1, c0:c1], mask[..., r0:r1, c0:c1], None if x0 is None else x0[..., r0:r1, c0:c1],
            tol, maxiter,
        )
        return F.pad(z, (c0, width - c1, r0, height - r1))
    for name, given in (("wu", wu), ("wv", wv), ("tu", tu), ("tv", tv), ("x0", x0)):  # over the bounding box only
        if given is not None:
            check_finite(given, name)
    mu, mv = edge_mask(mask)
    wu, wv = wu * mu, wv * mv
    if tol is None:
        tol = 1e-6 if wu.dtype == torch.float32 else 1e-10
    if x0 is None:
        x0 = torch.zeros_like(mask)
    z = _WeightedPoisson.apply(wu, wv, tu, tv, mask, x0.detach(), tol, maxiter)
    z = z - (z * mask).sum(dim=(-2, -1), keepdim=True) / mask.sum(dim=(-2, -1), keepdim=True)
    return z * mask
