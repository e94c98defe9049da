r"""Discontinuity-preserving integration: bilateral normal integration (Cao et al., ECCV 2022).

Implemented from the published maths of X. Cao, H. Santo, B. Shi, F. Okura and Y. Matsushita, "Bilateral Normal
Integration", ECCV 2022 (no code of theirs was read). The surface is assumed *semi-smooth*: one-sided
differentiable everywhere along rows and columns. Each pixel ``i`` has a forward and a backward equation per axis
(written along columns; rows alike) in the paper's normal form,

.. math::
    E(z) = \sum_i c_i \big[ w_i (z_{i+1} - z_i - g_i)^2 + (1 - w_i)(z_i - z_{i-1} - g_i)^2 \big],
    \qquad w_i = \sigma\!\big(k\, c_i\, [(z_i - z_{i-1})^2 - (z_{i+1} - z_i)^2]\big),

:math:`\sigma` the logistic function. The confidence :math:`c_i` is the square of the normal's component that
multiplies the depth derivative: :math:`n_z^2 = 1/(1 + p^2 + q^2)` orthographically, and in the perspective case
(log-depth, :func:`psmini.integrate.integrate_normals`) the paper's :math:`\tilde n_z^2 \propto (n\cdot r)^2`, the
normal against the pixel's ray, which ``integrate_normals`` passes as ``weights``. The weight is the sigmoid of
the difference between the two one-sided differences' squares, each taken in the equations' own form
(:math:`c_i` times the squared difference): a pixel next to a jump puts its weight on the side without it, so
the two sides of a discontinuity stop pulling on each other. A pixel at the mask's outline has one equation
along that axis; the missing side counts as a zero difference in its weight, as in the paper's discretisation
(its difference operator has a zero row there), so an outline pixel whose remaining difference is steep leans
on it less (:math:`w \le 1/2`).

The paper minimises :math:`E` by iteratively re-weighted least squares, and so does this module, with the
paper's algorithm and defaults: start from :math:`z = 0` and :math:`w = 1/2`; solve the weighted least squares
by conjugate gradients preconditioned with the matrix's diagonal (Jacobi), warm-started from the previous depth,
to a relative residual of ``cg_tol`` = 1e-3; recompute the weights from the new depth and the energy with them;
stop when the energy changes by less than a relative ``tol`` = 1e-4 (or after ``max_iterations`` = 100).

The inner tolerance is part of the method, not a detail of it. When a discontinuity splits the mask into
pieces joined by weak weights, the pieces' relative offsets are the weighted Laplacian's slowest modes; a loose
Jacobi-preconditioned solve barely moves them, so they stay where the earlier, more evenly weighted iterations
put them, while the shape within each piece follows the sharpening weights. Solving every weighted problem
exactly instead lets those offsets follow the few weak links left across each jump. On the ground-truth normals
of DiLiGenT_depth (perspective, median-ratio aligned mean absolute error, mm; ``benchmarks/integration.py``) the
defaults give buddha 1.08, cat 0.075, cow 0.058, goblet 9.23, pot1 0.637, pot2 0.220, within 2.4% of the authors'
figures (1.098, 0.074, 0.058, 9.018, 0.635, 0.220) on each. The same energy solved to 1e-7 at every
iteration (by multigrid) gives 0.671, 0.104, 0.073, 8.51, 0.627, 0.212: better on the four objects with large
pieces, 40% and 25% worse on the smooth cat and cow (their heads and paws drift); a loose solve preconditioned by
multigrid, which moves the slow modes too, 0.091 on cat. With ``cg_tol`` small the output is the energy's fixed
point (what the gradients below assume), at the price of many more Jacobi-preconditioned iterations.

Gradients (the choice and why). The energy's stationary point :math:`z^\ast` solves :math:`G(z, g, c) =
\nabla_z E(z; w(z, g, c), g, c) = 0`; its gradient is taken by the implicit function theorem rather than by
unrolling tens of solves (whose memory grows with every iteration and whose derivative would depend on the
inner iterations' stopping points). The adjoint :math:`(\partial G/\partial z)^\top \mu = \bar z` is
non-symmetric (the weights depend on :math:`z`); it is solved by Richardson iterations preconditioned with a
multigrid solve of the last weighted Laplacian, which converge exactly when the re-weighting converges locally,
and :math:`\bar g, \bar c = -(\partial G/\partial (g, c))^\top \mu` follow by automatic differentiation of
:math:`G`. The gradient is exact at the fixed point; with the default loose inner solves the output stops short
of it (see above), and the gradient is that of the fixed point near it.
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini.errors import InputError
from psmini.integrate._common import check_gradients
from psmini.integrate.least_squares import _check_weights, _edge_system
from psmini.integrate.poisson import _Hierarchy, _Level, _pcg, divergence, edge_mask, grid_differences

logger = logging.getLogger(__name__)

__all__ = ["bilateral_integration", "BilateralIntegration"]

_CG_MAXITER = 5000  # most Jacobi-preconditioned CG iterations of one weighted solve
_ADJOINT_MAXITER = 500  # most multigrid-preconditioned CG iterations of one adjoint step


def _confidence(gu: Tensor, gv: Tensor) -> Tensor:
    """Normal-form weight :math:`1/(1 + |g|^2)` per pixel (:math:`n_z^2` for orthographic gradients)."""
    return 1 / (1 + gu**2 + gv**2)


class _Grid:
    """Which one-sided equations exist on a mask (edges with both ends inside)."""

    def __init__(self, mask: Tensor) -> None:
        self.mask = mask
        self.mu, self.mv = edge_mask(mask)

    def shares(self, z: Tensor, conf: Tensor, k: float) -> tuple[Tensor, Tensor]:
        """Weight of each pixel's forward equation, from the one-sided depth differences (the bilateral weights).

        A difference leaving the mask counts as 0 (the paper's zero row), so it needs no special case.
        """
        du, dv = grid_differences(z)
        du, dv = du * self.mu, dv * self.mv
        su = torch.sigmoid(k * conf * (F.pad(du, (1, 0)) ** 2 - F.pad(du, (0, 1)) ** 2))
        sv = torch.sigmoid(k * conf * (F.pad(dv, (0, 0, 1, 0)) ** 2 - F.pad(dv, (0, 0, 0, 1)) ** 2))
        return su, sv

    def system(self, gu: Tensor, gv: Tensor, conf: Tensor, su: Tensor, sv: Tensor) -> tuple[Tensor, ...]:
        """Edge weights and targets of the weighted least squares with the shares fixed."""
        wu, wv, tu, tv = _edge_system(gu, gv, conf, su, sv)
        return wu * self.mu, wv * self.mv, tu, tv

    def energy(self, z: Tensor, gu: Tensor, gv: Tensor, conf: Tensor, su: Tensor, sv: Tensor) -> Tensor:
        """Bilateral energy over the equations inside the mask, per batch item, shape ``(B,)``."""
        du, dv = grid_differences(z)
        eu = conf[..., :, :-1] * su[..., :, :-1] * (du - gu[..., :, :-1]) ** 2
        eu = eu + conf[..., :, 1:] * (1 - su[..., :, 1:]) * (du - gu[..., :, 1:]) ** 2
        ev = conf[..., :-1, :] * sv[..., :-1, :] * (dv - gv[..., :-1, :]) ** 2
        ev = ev + conf[..., 1:, :] * (1 - sv[..., 1:, :]) * (dv - gv[..., 1:, :]) ** 2
        return (eu * self.mu).sum(dim=(1, 2, 3)) + (ev * self.mv).sum(dim=(1, 2, 3))

    def stationarity(self, z: Tensor, gu: Tensor, gv: Tensor, conf: Tensor, k: float) -> Tensor:
        r""":math:`G(z, g, c)`: the energy's gradient in :math:`z` with the shares evaluated at :math:`z` (0 at the
        fixed point)."""
        wu, wv, tu, tv = self.system(gu, gv, conf, *self.shares(z, conf, k))
        du, dv = grid_differences(z)
        return divergence(wu * (du - tu), wv * (dv - tv))


def _batched_dot(a: Tensor, b: Tensor) -> Tensor:
    """Per batch item dot product of contiguous ``(B, 1, H, W)`` tensors, ``(B, 1, 1, 1)`` (one BLAS call)."""
    batch = a.shape[0]
    return torch.bmm(a.view(batch, 1, -1), b.view(batch, -1, 1)).view(batch, 1, 1, 1)


def _jacobi_cg(level: _Level, b: Tensor, x: Tensor, tol: float, maxiter: int) -> Tensor:
    """Conjugate gradients preconditioned with the diagonal, per batch item to ``|r| <= tol |b|``, from ``x``.

    Rows outside the active pixels are identities with ``b = x = 0`` there, so they stay 0 without masking. In a
    batch, an item that has converged is frozen (its steps are 0), so each item gets the iterates it gets alone.
    ``x`` is updated in place. The loop is dispatch-bound on the CPU at these sizes, so every buffer is written in
    place and the stencil's shifted views are taken once (the products of :meth:`_Level.apply`, in its order).
    """
    batched = b.shape[0] > 1
    inverse_diagonal = level.inside / level.diag
    r = b - level.apply(x)
    y = r * inverse_diagonal
    d = y.clone()
    product = torch.empty_like(d)
    left, right, up, down = level.neighbours
    stencil = (
        (product[..., :, 1:], left[..., :, 1:], d[..., :, :-1]),
        (product[..., :, :-1], right[..., :, :-1], d[..., :, 1:]),
        (product[..., 1:, :], up[..., 1:, :], d[..., :-1, :]),
        (product[..., :-1, :], down[..., :-1, :], d[..., 1:, :]),
    )
    rz = _batched_dot(r, y)
    threshold = tol**2 * _batched_dot(b, b)
    iteration = 0
    while iteration < maxiter:
        live = _batched_dot(r, r) > threshold
        if not bool(live.any()):
            break
        torch.mul(level.diag, d, out=product)
        for target, weight, source in stencil:
            target.addcmul_(weight, source, value=-1)
        alpha = rz / _batched_dot(d, product)
        alpha = torch.where(live, alpha, 0) if batched else alpha
        x.addcmul_(alpha, d)
        r.addcmul_(alpha, product, value=-1)
        torch.mul(r, inverse_diagonal, out=y)
        rz_new = _batched_dot(r, y)
        beta = rz_new / rz
        torch.addcmul(y, torch.where(live, beta, 0) if batched else beta, d, out=d)
        rz = rz_new
        iteration += 1
    else:
        logger.info("bilateral integration: a weighted solve stopped at %d CG iterations above tol=%.1e", maxiter, tol)
    logger.debug("bilateral integration: %d CG iterations", iteration)
    return x


def _solve(system: tuple[Tensor, ...], grid: _Grid, x0: Tensor, cg_tol: float) -> Tensor:
    """One weighted least-squares solve, warm-started from ``x0``."""
    wu, wv, tu, tv = system
    level = _Level.build(wu, wv, grid.mask)
    b = divergence(wu * tu, wv * tv) * level.inside
    return _jacobi_cg(level, b, x0 * level.inside, cg_tol, _CG_MAXITER)


def _irls(gu: Tensor, gv: Tensor, conf: Tensor, grid: _Grid, k: float, max_iterations: int, tol: float,
          cg_tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """Re-weighted least squares (the paper's loop); returns the depth and the shares it was solved with."""
    su = sv = torch.full_like(gu, 0.5)
    z = torch.zeros_like(gu)
    # Energy changes below rounding of the data's own energy count as converged (exact data has energy ~0).
    floor = torch.finfo(gu.dtype).eps * grid.energy(z, gu, gv, conf, su, sv)
    previous = None
    running = torch.ones(gu.shape[0], 1, 1, 1, dtype=torch.bool, device=gu.device)
    iteration = 0
    while iteration < max_iterations:
        iteration += 1
        z = torch.where(running, _solve(grid.system(gu, gv, conf, su, sv), grid, z, cg_tol), z)
        su_new, sv_new = grid.shares(z, conf, k)
        energy = grid.energy(z, gu, gv, conf, su_new, sv_new)
        if previous is not None:
            running = running & ((previous - energy).abs() > tol * previous + floor).view(-1, 1, 1, 1)
            if not bool(running.any()):
                break
        previous = energy
        su, sv = torch.where(running, su_new, su), torch.where(running, sv_new, sv)
    else:
        logger.info("bilateral integration: %d iterations without reaching tol=%.1e", max_iterations, tol)
    logger.debug("bilateral integration: %d re-weighting iterations", iteration)
    return z, su, sv


class _Bilateral(torch.autograd.Function):
    """Forward: re-weighted least squares. Backward: implicit differentiation at the fixed point."""

    @staticmethod
    def forward(ctx, gu, gv, conf, mask, k, max_iterations, tol, cg_tol):
        grid = _Grid(mask)
        z, su, sv = _irls(gu, gv, conf, grid, k, max_iterations, tol, cg_tol)
        ctx.grid, ctx.k, ctx.max_iterations = grid, k, max_iterations
        ctx.save_for_backward(gu, gv, conf, z, su, sv)
        return z

    @staticmethod
    def backward(ctx, grad_z):
        gu, gv, conf, z, su, sv = ctx.saved_tensors
        grid, k = ctx.grid, ctx.k
        wu, wv, _, _ = grid.system(gu, gv, conf, su, sv)
        hierarchy = _Hierarchy(wu, wv, grid.mask)
        active = hierarchy.fine.active
        inner_tol = 1e-6 if grad_z.dtype == torch.float32 else 1e-10
        rhs = torch.where(active, grad_z, torch.zeros_like(grad_z))
        with torch.enable_grad():
            zz = z.detach().requires_grad_()
            g_z = grid.stationarity(zz, gu.detach(), gv.detach(), conf.detach(), k)
            # Richardson on (dG/dz)^T mu = rhs, preconditioned by a solve of the last weighted Laplacian.
            mu = torch.zeros_like(rhs)
            residual = rhs
            threshold = inner_tol * rhs.flatten(1).norm(dim=1).max()
            for _ in range(ctx.max_iterations):
                mu = mu + _pcg(hierarchy, residual, torch.zeros_like(rhs), inner_tol, _ADJOINT_MAXITER)
                (jt_mu,) = torch.autograd.grad(g_z, zz, mu, retain_graph=True)
                residual = torch.where(active, rhs - jt_mu, torch.zeros_like(rhs))
                if bool(residual.flatten(1).norm(dim=1).max() <= threshold):
                    break
            else:
                logger.warning("bilateral integration: the adjoint solve did not converge; gradients are approximate")
            gu_, gv_, conf_ = (t.detach().requires_grad_() for t in (gu, gv, conf))
            grads = torch.autograd.grad(grid.stationarity(z.detach(), gu_, gv_, conf_, k), (gu_, gv_, conf_), mu)
        return -grads[0], -grads[1], -grads[2], None, None, None, None, None


def _check_options(k: float, max_iterations: int, tol: float, cg_tol: float) -> None:
    def number(x: object) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    if not (number(k) and 0 < k < float("inf")):
        raise InputError(f"k must be a positive finite number, got {k!r}")
    if not (isinstance(max_iterations, int) and not isinstance(max_iterations, bool) and max_iterations >= 1):
        raise InputError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    if not (number(tol) and 0 <= tol < 1):
        raise InputError(f"tol must be a number in [0, 1), got {tol!r}")
    if not (number(cg_tol) and 0 < cg_tol < 1):
        raise InputError(f"cg_tol must be a number in (0, 1), got {cg_tol!r}")


def bilateral_integration(
    p: Tensor,
    q: Tensor,
    pixel_pitch_mm: float = 1.0,
    mask: Tensor | None = None,
    k: float = 2.0,
    max_iterations: int = 100,
    tol: float = 1e-4,
    cg_tol: float = 1e-3,
    weights: Tensor | None = None,
) -> Tensor:
    r"""Discontinuity-preserving integration on a mask: bilateral normal integration (Cao et al., ECCV 2022).

    Minimises the bilaterally weighted energy of the module docstring by the paper's re-weighted least squares,
    so depth jumps (occlusion boundaries, steps, folds seen edge-on) stay jumps instead of being smeared into
    slopes, and steep pixels near an outline weigh less (normal form). With ``integrate_normals(...,
    intrinsics=K)`` it works on log-depth with the paper's perspective confidence.

    Args:
        p: :math:`\partial z/\partial x`, shape :math:`(B, 1, H, W)` (x right).
        q: :math:`\partial z/\partial y`, shape :math:`(B, 1, H, W)` (y up).
        pixel_pitch_mm: size of one pixel on the surface in mm.
        mask: pixels to integrate :math:`(B, 1, H, W)` (default: all).
        k: sharpness of the logistic weights, in 1/pixel² (the paper's default 2; larger splits at smaller jumps).
        max_iterations: most re-weighting iterations.
        tol: relative change of the energy between iterations at which the re-weighting stops (0: run all).
        cg_tol: relative residual at which each weighted solve (Jacobi-preconditioned CG) stops: the paper's 1e-3
            by default; small values (1e-10) give the energy's fixed point (see the module docstring).
        weights: optional confidence of each pixel's equations :math:`(B, 1, H, W)`, non-negative (default the
            normal form :math:`1/(1 + p^2 + q^2)`, which is :math:`n_z^2`).

    Returns:
        height toward the camera in mm, :math:`(B, 1, H, W)`, zero mean over the mask and 0 outside it; pieces
        separated by a discontinuity keep the offset the weak coupling across it gives them. Differentiable with
        respect to ``p``, ``q`` and ``weights`` (implicit differentiation at the fixed point, see the module
        docstring).

    Raises:
        ShapeError: when shapes disagree or the mask is empty.
        InputError: when inputs hold NaN/inf, the pitch or ``k`` is not positive, ``max_iterations`` is not an
            integer >= 1, ``tol`` is outside [0, 1), ``cg_tol`` outside (0, 1) or weights are negative.

    Example:
        >>> mask = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
        >>> mask[..., 2:14, 4:12] = True
        >>> z = bilateral_integration(torch.full((1, 1, 16, 16), 0.5), torch.zeros(1, 1, 16, 16), 0.1, mask)
        >>> round(float(z[0, 0, 5, 7] - z[0, 0, 5, 6]), 4)
        0.05
    """
    mask, pitch = check_gradients(p, q, mask, pixel_pitch_mm)
    _check_options(k, max_iterations, tol, cg_tol)
    conf = _confidence(p, q) if weights is None else _check_weights(weights, p)
    mask = torch.ones_like(p) if mask is None else mask
    height, width = mask.shape[-2:]
    rows, cols = (mask > 0).any(dim=0).any(dim=0).any(dim=1), (mask > 0).any(dim=0).any(dim=0).any(dim=0)
    r0, r1 = int(rows.nonzero().min()), int(rows.nonzero().max()) + 1
    c0, c1 = int(cols.nonzero().min()), int(cols.nonzero().max()) + 1
    box = (..., slice(r0, r1), slice(c0, c1))  # work on the mask's bounding box only
    z = _Bilateral.apply(p[box], -q[box], conf[box], mask[box], float(k), max_iterations, float(tol), float(cg_tol))
    inside = mask[box]
    z = (z - (z * inside).sum(dim=(-2, -1), keepdim=True) / inside.sum(dim=(-2, -1), keepdim=True)) * inside
    return pitch * F.pad(z, (c0, width - c1, r0, height - r1))


class BilateralIntegration(nn.Module):
    """Module form of :func:`bilateral_integration` holding the pixel pitch and the re-weighting settings.

    Example:
        >>> BilateralIntegration(0.025)(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8)).shape
        torch.Size([1, 1, 8, 8])
    """

    def __init__(
        self, pixel_pitch_mm: float = 1.0, k: float = 2.0, max_iterations: int = 100, tol: float = 1e-4,
        cg_tol: float = 1e-3,
    ) -> None:
        super().__init__()
        self.pixel_pitch_mm, self.k, self.max_iterations = pixel_pitch_mm, k, max_iterations
        self.tol, self.cg_tol = tol, cg_tol

    def forward(self, p: Tensor, q: Tensor, mask: Tensor | None = None, weights: Tensor | None = None) -> Tensor:
        return bilateral_integration(
            p, q, self.pixel_pitch_mm, mask, self.k, self.max_iterations, self.tol, self.cg_tol, weights
        )
