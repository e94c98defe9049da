r"""Discontinuity-preserving integration: bilateral normal integration (Cao et al., ECCV 2022).

Implemented from the published maths of X. Cao, H. Santo, B. Shi, F. Okura and Y. Matsushita, "Bilateral Normal
Integration", ECCV 2022 (no code of theirs was read). The surface is assumed *semi-smooth*: one-sided
differentiable everywhere along rows and columns. Each pixel ``i`` has a forward and a backward equation per axis
(written along columns; rows alike), in the normal form that weighs a pixel by how squarely it faces the camera,

.. math::
    E(z) = \sum_i c_i \big[ s_i (z_{i+1} - z_i - g_i)^2 + (1 - s_i)(z_i - z_{i-1} - g_i)^2 \big],
    \qquad s_i = \sigma\!\big(k\, c_i\, [(z_i - z_{i-1})^2 - (z_{i+1} - z_i)^2]\big),

with :math:`\sigma` the logistic function and :math:`c_i = 1/(1 + |g_i|^2)` (:math:`n_z^2` orthographically; close
to the paper's perspective factor :math:`(n\cdot\text{ray})^2` for the log-depth gradients of
:func:`psmini.integrate.perspective_log_gradients`, which are scaled to read as slopes). A pixel next to a jump
puts its weight on the side without the jump, so the two sides of a discontinuity stop pulling on each other.
The paper minimises :math:`E` by iteratively re-weighted least squares: solve the weighted problem with the
shares :math:`s` fixed, recompute :math:`s` from the new depth, stop when the energy changes by less than a
relative ``tol``. Each weighted problem is the edge system of
:func:`psmini.integrate.poisson.solve_weighted_poisson` (its multigrid-preconditioned CG, warm-started from the
previous depth and solved loosely until the last one). The unknown is in pixel steps, so ``k`` is in
1/pixel² whatever the pitch.

Gradients (the choice and why). The result is the fixed point :math:`z^\ast` of :math:`G(z, g) = \nabla_z E(z;
s(z, g), g) = 0`; the path the iterations took to it does not matter, so the gradient is taken at the fixed point
by the implicit function theorem rather than by unrolling tens of solves (whose memory grows with every
iteration and whose derivative would depend on the inner tolerances). The adjoint :math:`(\partial G/\partial
z)^\top \mu = \bar z` is non-symmetric (the shares depend on :math:`z`); it is solved by Richardson iterations
preconditioned with the forward's weighted Laplacian solve, which converge exactly when the re-weighting
converges locally, and :math:`\bar g = -(\partial G/\partial g)^\top \mu` follows by automatic differentiation of
:math:`G`. The gradient is exact to the extent the forward reached its fixed point (``tol``).
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini.errors import InputError
from psmini.integrate._common import check_gradients
from psmini.integrate.least_squares import _edge_system
from psmini.integrate.poisson import _Hierarchy, _pcg, divergence, edge_mask, grid_differences

logger = logging.getLogger(__name__)

__all__ = ["bilateral_integration", "BilateralIntegration"]

# Relative CG residual of the intermediate weighted solves: the shares are re-estimated right after, so solving
# them further is wasted; the last solve goes to the usual tolerance.
_INNER_TOL = 1e-3
_CG_MAXITER = 500


def _confidence(gu: Tensor, gv: Tensor) -> Tensor:
    """Normal-form weight :math:`1/(1 + |g|^2)` per pixel (:math:`n_z^2` for orthographic gradients)."""
    return 1 / (1 + gu**2 + gv**2)


class _Grid:
    """Which one-sided equations exist on a mask (edges with both ends inside)."""

    def __init__(self, mask: Tensor) -> None:
        self.mask = mask
        self.mu, self.mv = edge_mask(mask)
        mu, mv = self.mu > 0, self.mv > 0
        self.forward_u, self.backward_u = F.pad(mu, (0, 1)), F.pad(mu, (1, 0))
        self.forward_v, self.backward_v = F.pad(mv, (0, 0, 0, 1)), F.pad(mv, (0, 0, 1, 0))

    @staticmethod
    def _one_sided(share: Tensor, forward: Tensor, backward: Tensor) -> Tensor:
        # A pixel with one equation along an axis (at the outline) keeps it at full weight.
        return torch.where(backward, torch.where(forward, share, torch.zeros_like(share)), torch.ones_like(share))

    def half(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """The first shares: both sides alike (plain least squares)."""
        half = torch.full_like(like, 0.5)
        return (self._one_sided(half, self.forward_u, self.backward_u),
                self._one_sided(half, self.forward_v, self.backward_v))

    def shares(self, z: Tensor, conf: Tensor, k: float) -> tuple[Tensor, Tensor]:
        """Weight of each pixel's forward equation, from the one-sided depth differences (the bilateral weights)."""
        du, dv = grid_differences(z)
        du, dv = du * self.mu, dv * self.mv
        su = torch.sigmoid(k * conf * (F.pad(du, (1, 0)) ** 2 - F.pad(du, (0, 1)) ** 2))
        sv = torch.sigmoid(k * conf * (F.pad(dv, (0, 0, 1, 0)) ** 2 - F.pad(dv, (0, 0, 0, 1)) ** 2))
        return (self._one_sided(su, self.forward_u, self.backward_u),
                self._one_sided(sv, self.forward_v, self.backward_v))

    def system(self, gu: Tensor, gv: Tensor, conf: Tensor, su: Tensor, sv: Tensor) -> tuple[Tensor, ...]:
        """Edge weights and targets of the weighted least squares with the shares fixed."""
        wu, wv, tu, tv = _edge_system(gu, gv, conf, su, sv)
        return wu * self.mu, wv * self.mv, tu, tv

    def energy(self, z: Tensor, gu: Tensor, gv: Tensor, conf: Tensor, su: Tensor, sv: Tensor) -> Tensor:
        """Bilateral energy per batch item, shape ``(B,)``."""
        du, dv = grid_differences(z)
        eu = conf[..., :, :-1] * su[..., :, :-1] * (du - gu[..., :, :-1]) ** 2
        eu = eu + conf[..., :, 1:] * (1 - su[..., :, 1:]) * (du - gu[..., :, 1:]) ** 2
        ev = conf[..., :-1, :] * sv[..., :-1, :] * (dv - gv[..., :-1, :]) ** 2
        ev = ev + conf[..., 1:, :] * (1 - sv[..., 1:, :]) * (dv - gv[..., 1:, :]) ** 2
        return (eu * self.mu).sum(dim=(1, 2, 3)) + (ev * self.mv).sum(dim=(1, 2, 3))

    def stationarity(self, z: Tensor, gu: Tensor, gv: Tensor, k: float) -> Tensor:
        r""":math:`G(z, g)`: the energy's gradient in :math:`z` with the shares evaluated at :math:`z` (0 at the
        result)."""
        conf = _confidence(gu, gv)
        wu, wv, tu, tv = self.system(gu, gv, conf, *self.shares(z, conf, k))
        du, dv = grid_differences(z)
        return divergence(wu * (du - tu), wv * (dv - tv))


def _solve(system: tuple[Tensor, ...], grid: _Grid, x0: Tensor, tol: float) -> tuple[Tensor, _Hierarchy]:
    """One weighted least-squares solve, warm-started; returns the solution and its preconditioner."""
    wu, wv, tu, tv = system
    hierarchy = _Hierarchy(wu, wv, grid.mask)
    active = hierarchy.fine.active
    b = torch.where(active, divergence(wu * tu, wv * tv), torch.zeros_like(x0))
    return _pcg(hierarchy, b, torch.where(active, x0, torch.zeros_like(x0)), tol, _CG_MAXITER), hierarchy


def _irls(gu: Tensor, gv: Tensor, grid: _Grid, k: float, max_iterations: int, tol: float, cg_tol: float):
    """Re-weighted least squares to the bilateral fixed point; returns the depth and the last preconditioner."""
    conf = _confidence(gu, gv)
    su, sv = grid.half(gu)
    z = torch.zeros_like(gu)
    # Energy changes below rounding of the data's own energy count as converged (exact data has energy ~0).
    floor = torch.finfo(gu.dtype).eps * grid.energy(torch.zeros_like(gu), gu, gv, conf, su, sv)
    previous = None
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        z, _ = _solve(grid.system(gu, gv, conf, su, sv), grid, z, max(cg_tol, _INNER_TOL))
        energy = grid.energy(z, gu, gv, conf, su, sv)
        if previous is not None and bool(((previous - energy).abs() <= tol * previous + floor).all()):
            break
        previous = energy
        su, sv = grid.shares(z, conf, k)
    else:
        logger.info("bilateral integration: %d iterations without reaching tol=%.1e", max_iterations, tol)
    logger.debug("bilateral integration: %d re-weighting iterations", iterations)
    return _solve(grid.system(gu, gv, conf, su, sv), grid, z, cg_tol)


class _Bilateral(torch.autograd.Function):
    """Forward: re-weighted least squares. Backward: implicit differentiation at the fixed point."""

    @staticmethod
    def forward(ctx, gu, gv, mask, k, max_iterations, tol, cg_tol):
        grid = _Grid(mask)
        z, hierarchy = _irls(gu, gv, grid, k, max_iterations, tol, cg_tol)
        ctx.grid, ctx.hierarchy, ctx.k, ctx.max_iterations, ctx.cg_tol = grid, hierarchy, k, max_iterations, cg_tol
        ctx.save_for_backward(gu, gv, z)
        return z

    @staticmethod
    def backward(ctx, grad_z):
        gu, gv, z = ctx.saved_tensors
        grid, hierarchy, k = ctx.grid, ctx.hierarchy, ctx.k
        active = hierarchy.fine.active
        rhs = torch.where(active, grad_z, torch.zeros_like(grad_z))
        with torch.enable_grad():
            zz = z.detach().requires_grad_()
            g_z = grid.stationarity(zz, gu.detach(), gv.detach(), k)
            # Richardson on (dG/dz)^T mu = rhs, preconditioned by the forward's weighted Laplacian solve.
            mu = torch.zeros_like(rhs)
            residual = rhs
            threshold = ctx.cg_tol * rhs.flatten(1).norm(dim=1).max()
            for _ in range(ctx.max_iterations):
                mu = mu + _pcg(hierarchy, residual, torch.zeros_like(rhs), ctx.cg_tol, _CG_MAXITER)
                (jt_mu,) = torch.autograd.grad(g_z, zz, mu, retain_graph=True)
                residual = torch.where(active, rhs - jt_mu, torch.zeros_like(rhs))
                if bool(residual.flatten(1).norm(dim=1).max() <= threshold):
                    break
            else:
                logger.warning("bilateral integration: the adjoint solve did not converge; gradients are approximate")
            gu_, gv_ = gu.detach().requires_grad_(), gv.detach().requires_grad_()
            grad_gu, grad_gv = torch.autograd.grad(grid.stationarity(z.detach(), gu_, gv_, k), (gu_, gv_), mu)
        return -grad_gu, -grad_gv, None, None, None, None, None


def _check_options(k: float, max_iterations: int, tol: float) -> None:
    if not (isinstance(k, (int, float)) and not isinstance(k, bool) and 0 < k < float("inf")):
        raise InputError(f"k must be a positive finite number, got {k!r}")
    if not (isinstance(max_iterations, int) and not isinstance(max_iterations, bool) and max_iterations >= 1):
        raise InputError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    if not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and 0 <= tol < 1):
        raise InputError(f"tol must be a number in [0, 1), got {tol!r}")


def bilateral_integration(
    p: Tensor,
    q: Tensor,
    pixel_pitch_mm: float = 1.0,
    mask: Tensor | None = None,
    k: float = 2.0,
    max_iterations: int = 100,
    tol: float = 1e-4,
) -> Tensor:
    r"""Discontinuity-preserving integration on a mask: bilateral normal integration (Cao et al., ECCV 2022).

    Minimises the bilaterally weighted energy of the module docstring by re-weighted least squares, so depth
    jumps (occlusion boundaries, steps, folds seen edge-on) stay jumps instead of being smeared into slopes, and
    steep pixels near an outline weigh less (normal form). With ``integrate_normals(..., intrinsics=K)`` it works
    on log-depth, as in the paper's perspective case.

    Args:
        p: :math:`\partial z/\partial x`, shape :math:`(B, 1, H, W)` (x right).
        q: :math:`\partial z/\partial y`, shape :math:`(B, 1, H, W)` (y up).
        pixel_pitch_mm: size of one pixel on the surface in mm.
        mask: pixels to integrate :math:`(B, 1, H, W)` (default: all).
        k: sharpness of the logistic weights, in 1/pixel² (the paper's default 2; larger splits at smaller jumps).
        max_iterations: most re-weighting iterations.
        tol: relative change of the energy between iterations at which the re-weighting stops (0: run all).

    Returns:
        height toward the camera in mm, :math:`(B, 1, H, W)`, zero mean over the mask and 0 outside it; pieces
        separated by a discontinuity keep the offset the weak coupling across it gives them. Differentiable with
        respect to ``p`` and ``q`` (implicit differentiation at the fixed point, see the module docstring).

    Raises:
        ShapeError: when shapes disagree or the mask is empty.
        InputError: when inputs hold NaN/inf, the pitch or ``k`` is not positive, ``max_iterations`` is not an
            integer >= 1 or ``tol`` is outside [0, 1).

    Example:
        >>> mask = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
        >>> mask[..., 2:14, 4:12] = True
        >>> z = bilateral_integration(torch.full((1, 1, 16, 16), 0.5), torch.zeros(1, 1, 16, 16), 0.1, mask)
        >>> round(float(z[0, 0, 5, 7] - z[0, 0, 5, 6]), 4)
        0.05
    """
    mask, pitch = check_gradients(p, q, mask, pixel_pitch_mm)
    _check_options(k, max_iterations, tol)
    mask = torch.ones_like(p) if mask is None else mask
    height, width = mask.shape[-2:]
    rows, cols = (mask > 0).any(dim=0).any(dim=0).any(dim=1), (mask > 0).any(dim=0).any(dim=0).any(dim=0)
    r0, r1 = int(rows.nonzero().min()), int(rows.nonzero().max()) + 1
    c0, c1 = int(cols.nonzero().min()), int(cols.nonzero().max()) + 1
    box = (..., slice(r0, r1), slice(c0, c1))  # work on the mask's bounding box only
    cg_tol = 1e-6 if p.dtype == torch.float32 else 1e-10
    z = _Bilateral.apply(p[box], -q[box], mask[box], float(k), max_iterations, float(tol), cg_tol)
    inside = mask[box]
    z = (z - (z * inside).sum(dim=(-2, -1), keepdim=True) / inside.sum(dim=(-2, -1), keepdim=True)) * inside
    return pitch * F.pad(z, (c0, width - c1, r0, height - r1))


class BilateralIntegration(nn.Module):
    """Module form of :func:`bilateral_integration` holding the pixel pitch and the re-weighting settings.

    Example:
        >>> BilateralIntegration(0.025)(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8)).shape
        torch.Size([1, 1, 8, 8])
    """

    def __init__(self, pixel_pitch_mm: float = 1.0, k: float = 2.0, max_iterations: int = 100,
                 tol: float = 1e-4) -> None:
        super().__init__()
        self.pixel_pitch_mm, self.k, self.max_iterations, self.tol = pixel_pitch_mm, k, max_iterations, tol

    def forward(self, p: Tensor, q: Tensor, mask: Tensor | None = None) -> Tensor:
        return bilateral_integration(p, q, self.pixel_pitch_mm, mask, self.k, self.max_iterations, self.tol)
