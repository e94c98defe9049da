r"""Non-Lambertian normals: a Lambertian body plus a Blinn–Phong lobe, fitted per pixel by robust LM.

Glossy threads (Lurex, satin) and the varnish of DiLiGenT's objects add a specular lobe to the diffuse reading,
and the robust Lambertian estimators of :mod:`psmini.robust` can only down-weight it. Here each pixel gets the
reflectance model of :func:`psmini.render.render` with its own parameters: with light vector
:math:`l_k = E_k u_k` (unit direction :math:`u_k`, irradiance :math:`E_k`), orthographic view :math:`v = (0, 0, 1)`
and half vector :math:`h_k = (u_k + v) / \lVert u_k + v \rVert`,

.. math::
    I_k = E_k \left( \rho \max(n \cdot u_k, 0) + s \, [n \cdot u_k > 0] \max(n \cdot h_k, 0)^{\alpha} \right)

with diffuse albedo :math:`\rho`, specular albedo :math:`s \ge 0` and shininess :math:`\alpha \ge 1` per pixel (the
lobe of Blinn, "Models of light reflection for computer synthesized pictures", SIGGRAPH 1977). Fitting a parametric
specular model per pixel is the approach of Georghiades ("Incorporating the Torrance and Sparrow model of reflectance
in uncalibrated photometric stereo", ICCV 2003) and Goldman et al. ("Shape and spatially-varying BRDFs from
photometric stereo", ICCV 2005, with Ward's lobe); the bi-polynomial model of Shi et al. (TPAMI 2014) and the
bivariate regression of Ikehata & Aizawa (CVPR 2014) fit low-dimensional isotropic BRDFs instead.

The fit minimises the Cauchy loss :math:`\sum_k \log(1 + (r_k / \sigma)^2)` of the residuals, with :math:`\sigma` a
fraction (``scale``) of the pixel's median reading, over the pixel's usable readings: readings darker than
``shadow`` times the pixel's brightest are dropped first, since a cast shadow reads about 0 where the model predicts
light and an attached one carries no information on the lobe; so are the readings that the start explains as
shadows (a prediction :math:`p_k = l_k \cdot \rho n \le 0`, or a reading below :math:`p_k / 2`, the cast-shadow
rule of :mod:`psmini.robust`), which inter-reflection lifts above any threshold and which a lobe would otherwise
fit. It starts from the robust Lambertian estimate
(:func:`psmini.robust.robust_normals`, or weighted least squares for per-pixel lights) with a faint lobe, raced for a
few iterations against a start sized on the data (albedos by linear least squares, the normal possibly moved to the
half vector of the brightest reading; see :func:`_starts`), and runs a fixed number of
Levenberg–Marquardt iterations (Levenberg 1944, Marquardt 1963) on the iteratively reweighted normal equations
(Cauchy weights :math:`1 / (1 + (r/\sigma)^2)`, Holland & Welsch 1977), with a damping factor and an accept/reject
decision per pixel. The five unknowns are two tangent-plane steps of the normal, :math:`\rho`, :math:`s` and
:math:`\log \alpha`.

A pixel keeps the fit only when its lobe passes a likelihood-ratio test against the start (the robust Lambertian
estimate, the nested model with :math:`s = 0`): the drop of the residual sum of squares, in units of the noise
variance, must exceed the :math:`1 - \alpha` quantile of :math:`\chi^2_2` (``significance`` :math:`\alpha`,
1e-6 by default: an image of N matte pixels keeps about :math:`\alpha N` false lobes, fewer than one up to a
megapixel, where the former 1% kept 210 on the matte satin's 40,000 pixels and cost it 0.001°; the lobes of glossy
pixels pass at any level, so ball, cat and lurex moved by at most 0.01°), with the noise a fraction of the
pixel's median reading estimated once per image as the median over its pixels of the fit's residual variance
(see :func:`_keep_lobe`). Otherwise it keeps the start, lobe 0. With the rig's 8 lights a lobe can fit the noise
of a matte pixel; judged on each pixel's own residual alone (3 degrees of freedom left), it did so on 23% of the
matte satin's pixels and lost 0.05° to its start, where the pooled test keeps the start on 99% of them. The test
uses the pooled noise level, so it also decides pixels with too few readings to estimate their own (a glossy
thread seen under 5 lights).

The readings must also locate the lobe: its peak must lie within the cone of the lights' half vectors, or the lobe
be at most half that cone wide (see :func:`_peak_observed`). Beyond the half vectors the readings see only a lobe's
tail, which for a broad lobe has the shape of the diffuse term and of inter-reflection; on concave scenes (the
V-grooves and folds of ``data_synth.stress``, where two bounces add 10–25% to the lit readings) such fits moved the
normals by more than the lobe explained and made them worse than the robust start (grooves 13.7° against 9.7°).

All pixels are solved at once as the rows of :math:`N \times K` matrices (blocks of :data:`_CHUNK` that stay in
the CPU caches, each pixel's readings contiguous); the normal equations of all pixels are one batched product and
the 5×5 systems one batched solve. The fixed iteration count keeps the result differentiable.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor, nn

from psmini._checks import check_finite, check_mask, check_shape, check_tensor
from psmini.errors import InputError, ShapeError
from psmini.lights import as_batched_lights
from psmini.normals import _check_lights, _check_weights, albedo_normals
from psmini.robust import (
    RobustOptions,
    _float_mask,
    _median,
    _median_padding,
    _scatter,
    _tracked,
    robust_normals,
    threshold_weights,
)

__all__ = ["BlinnPhongFit", "NonLambertianNormals", "NonLambertianOptions", "blinn_phong_images", "fit_blinn_phong",
           "nonlambertian_normals"]

# Pixels solved together: the (chunk, K) arrays of one iteration stay in cache (the normal equations ran ~5x faster
# in blocks of 4096 pixels than over DiLiGenT cat's 45,200 at once, one CPU thread).
_CHUNK = 4096
_PARAMETERS = 5  # two tangent-plane steps of the normal, rho, s, log(alpha)
_FAINT_LOBE, _FAINT_SHININESS = 0.01, 30.0
# iterations both starts run before each pixel keeps the better one
_RACE = 6
# largest lobe peak s E, in units of the pixel's brightest usable reading
_PEAK_RATIO = 4.0


@dataclass(frozen=True)
class NonLambertianOptions:
    r"""Options of :func:`fit_blinn_phong`; the defaults are the ones ``benchmarks/robust_stress.py`` measures.

    Attributes:
        iterations: Levenberg–Marquardt iterations (fixed, so the result is differentiable).
        shadow: readings below this fraction of the pixel's brightest usable one are dropped as shadow, in [0, 1).
        scale: Cauchy scale :math:`\sigma` as a fraction of the pixel's median usable reading (> 0).
        saturation: readings at or above this level are dropped; ``None`` keeps all.
        shininess: starting exponents :math:`\alpha` tried per pixel (each in [1, ``max_shininess``]): for each,
            the albedos by linear least squares; the pixel starts from the one of least Cauchy cost, or from the
            Lambertian start (no lobe) when that is lower.
        max_shininess: largest exponent allowed.
        significance: level :math:`\alpha` of the per-pixel likelihood-ratio test the lobe must pass against the
            Lambertian start, in (0, 1): smaller keeps the start on more pixels (see :func:`fit_blinn_phong`).

    Raises:
        InputError: naming the field, what it must be and what came.

    Example:
        >>> NonLambertianOptions(iterations=5).to_dict()["iterations"]
        5
    """

    iterations: int = 20
    shadow: float = 0.05
    scale: float = 0.1
    saturation: float | None = None
    shininess: tuple[float, ...] = (4.0, 16.0, 64.0, 256.0)
    max_shininess: float = 2000.0
    significance: float = 1e-6

    def __post_init__(self) -> None:
        if isinstance(self.iterations, bool) or int(self.iterations) != self.iterations or self.iterations < 0:
            raise InputError(f"NonLambertianOptions.iterations must be a non-negative integer, got {self.iterations!r}")
        if not 0.0 <= self.shadow < 1.0:
            raise InputError("NonLambertianOptions.shadow must lie in [0, 1) (a fraction of the brightest reading), "
                             f"got {self.shadow}")
        if not self.scale > 0:
            raise InputError(f"NonLambertianOptions.scale must be positive, got {self.scale}")
        if self.saturation is not None and not self.saturation > 0:
            raise InputError(f"NonLambertianOptions.saturation must be positive or None, got {self.saturation}")
        if not self.max_shininess >= 1.0:
            raise InputError(f"NonLambertianOptions.max_shininess must be at least 1, got {self.max_shininess}")
        if not 0.0 < self.significance < 1.0:
            raise InputError("NonLambertianOptions.significance must lie in (0, 1) (a test level), "
                             f"got {self.significance}")
        exponents = tuple(float(e) for e in self.shininess)
        if not exponents or not all(1.0 <= e <= self.max_shininess for e in exponents):
            raise InputError("NonLambertianOptions.shininess (starting exponents) must be non-empty, each in "
                             f"[1, max_shininess={self.max_shininess}], got {self.shininess}")
        object.__setattr__(self, "shininess", exponents)

    def to_dict(self) -> dict:
        """The options as a plain dict (JSON-ready)."""
        return asdict(self)


class BlinnPhongFit(NamedTuple):
    """Per-pixel reflectance of :func:`fit_blinn_phong`: maps :math:`(B, 1, H, W)`, normals :math:`(B, 3, H, W)`.

    Attributes:
        albedo: diffuse albedo :math:`\\rho` (0 where not solved).
        normals: unit normals ((0, 0, 1) where not solved).
        specular: specular albedo :math:`s \\ge 0`.
        shininess: Blinn–Phong exponent :math:`\\alpha \\ge 1`.
    """

    albedo: Tensor
    normals: Tensor
    specular: Tensor
    shininess: Tensor


def _split_lights(lights: Tensor) -> tuple[Tensor, Tensor]:
    """Irradiance |l| and the half vectors between the unit directions and the view (0, 0, 1).

    ``lights`` is (K, 3) or per pixel row (N, K, 3) (the last dim holds xyz); returns irradiance as a (1, K) row or
    (N, K), and half vectors of the shape of ``lights``.
    """
    tiny = torch.finfo(lights.dtype).tiny
    energy = lights.norm(dim=-1, keepdim=True).clamp_min(tiny)
    half = lights / energy
    half[..., 2] += 1
    half = half / half.norm(dim=-1, keepdim=True).clamp_min(tiny)
    return (energy.T if lights.ndim == 2 else energy.squeeze(-1)), half


def _dot(vectors: Tensor, normals: Tensor) -> Tensor:
    """Dot products of K vectors (K, 3) or per-pixel vectors (N, K, 3) with pixel rows of vectors (N, 3): (N, K)."""
    if vectors.ndim == 2:
        return normals @ vectors.T
    return (vectors * normals.unsqueeze(1)).sum(dim=-1)


def _shade(normals: Tensor, albedo: Tensor, specular: Tensor, shininess: Tensor, lights: Tensor, energy: Tensor,
           half: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The model on pixel rows: normals (N, 3), maps (N, 1).

    Returns cosine E(n·u), where it is positive (0/1 floats), lit lobe E g^α, g = n·h, log g and the images, each
    (N, K).
    """
    cosine = _dot(lights, normals)  # E (n · u): lights carry their irradiance
    tiny = torch.finfo(normals.dtype).tiny
    # g is clamped to a tiny positive value: g**α has an infinite gradient at 0 for α < 1, and log(g) is needed
    g = _dot(half, normals).clamp_min(tiny)
    log_g = torch.log(g)
    if _tracked(normals, albedo, specular, shininess, lights, energy, half):
        lit = cosine > 0
        # where, not a product with the mask: the unlit branch's gradient can be infinite, and 0 * inf is NaN
        lobe = torch.where(lit, energy * torch.exp(shininess * log_g), 0.0)
        lit = _float_mask(lit, cosine.dtype)
    else:  # the same values as a product with a 0/1 float mask, in place: 2.4x cheaper than the bool where
        lit = torch.gt(cosine, 0, out=torch.empty_like(cosine))
        lobe = torch.exp(shininess * log_g).mul_(energy).mul_(lit)
    return cosine, lit, lobe, g, log_g, albedo * cosine.clamp_min(0) + specular * lobe


def blinn_phong_images(normals: Tensor, albedo: Tensor, specular: Tensor, shininess: Tensor, lights: Tensor) -> Tensor:
    r"""Images of a Lambertian body with a Blinn–Phong lobe, per-pixel parameters (the model of this module).

    :math:`I_k = E_k (\rho \max(n \cdot u_k, 0) + s [n \cdot u_k > 0] \max(n \cdot h_k, 0)^{\alpha})`; with a
    constant shininess it equals :func:`psmini.render.render` with ``specular=s``.

    Args:
        normals: unit normals, shape :math:`(B, 3, H, W)`.
        albedo: diffuse albedo :math:`\rho`, shape :math:`(B, 1, H, W)`.
        specular: specular albedo :math:`s`, shape :math:`(B, 1, H, W)`.
        shininess: exponent :math:`\alpha` (> 0), shape :math:`(B, 1, H, W)`.
        lights: light directions scaled by irradiance, :math:`(K, 3)`, :math:`(B, K, 3)` (distant) or per pixel
            :math:`(B, K, 3, H, W)` (near lights, as :func:`psmini.normals.albedo_normals` takes them).

    Returns:
        images, shape :math:`(B, K, H, W)`.

    Raises:
        ShapeError: when the shapes do not fit.
        InputError: when an input is not a floating-point tensor or the shininess is not positive.

    Example:
        >>> from psmini.lights import ring_lights
        >>> up = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> ones = torch.ones(1, 1, 1, 1)
        >>> images = blinn_phong_images(up, 0.5 * ones, ones, 10 * ones, ring_lights(8, 60.0))
        >>> round(float(images[0, 0, 0, 0]), 4)                    # 0.5 cos 60° + cos(30°)^10
        0.4873
    """
    sizes = check_shape(normals, ["B", "3", "H", "W"], "normals")
    for name, value in (("albedo", albedo), ("specular", specular), ("shininess", shininess)):
        check_tensor(value, name)
        if value.shape != (sizes["B"], 1, sizes["H"], sizes["W"]):
            raise ShapeError(f"{name} must have shape ({sizes['B']}, 1, {sizes['H']}, {sizes['W']}), got "
                             f"{tuple(value.shape)}")
    if bool((shininess <= 0).any()):
        raise InputError("shininess must be positive")
    check_tensor(lights, "lights")
    if lights.ndim == 5:
        lights = _check_lights(lights, {"B": sizes["B"], "K": lights.shape[1], "H": sizes["H"], "W": sizes["W"]})
    else:
        lights = as_batched_lights(lights, sizes["B"], normals)
    images = []
    for b in range(sizes["B"]):  # a loop over images, not pixels
        rows = lights[b].to(normals).flatten(2).permute(2, 0, 1) if lights.ndim == 5 else lights[b]
        energy, half = _split_lights(rows)
        maps = [x[b].flatten(1).T for x in (albedo, specular, shininess)]
        images.append(_shade(normals[b].flatten(1).T, maps[0], maps[1], maps[2], rows, energy, half)[-1].T)
    return torch.stack(images).view(sizes["B"], -1, sizes["H"], sizes["W"])


def _tangents(normals: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors (N, 3) orthogonal to unit normals (N, 3) and to each other."""
    # cross with z unless the normal is near z; then with x
    axis = torch.zeros_like(normals)
    near_z = normals[:, 2].abs() > 0.9
    axis[:, 0] = near_z.to(normals.dtype)
    axis[:, 2] = (~near_z).to(normals.dtype)
    first = torch.linalg.cross(normals, axis, dim=1)
    first = first / first.norm(dim=1, keepdim=True)
    return first, torch.linalg.cross(normals, first, dim=1)


def _cauchy_cost(residuals: Tensor, usable: Tensor, sigma: Tensor) -> Tensor:
    """Cauchy cost (N, 1) of residuals (N, K) over the usable readings, scale sigma (N, 1).

    Without autograd the residuals (a temporary of the caller's) are overwritten: one (N, K) array instead of
    five fresh ones, each a few MB that the allocator maps anew.
    """
    if _tracked(residuals, usable, sigma):
        return (usable * torch.log1p((residuals / sigma).square())).sum(dim=1, keepdim=True)
    return residuals.div_(sigma).square_().log1p_().mul_(usable).sum(dim=1, keepdim=True)


def _brightest_half(values: Tensor, usable: Tensor, half: Tensor) -> Tensor:
    """Half vector (N, 3) of each pixel's brightest usable reading: the normal if that reading is a highlight peak."""
    brightest = torch.where(usable > 0, values, torch.full_like(values, -math.inf)).argmax(dim=1)  # (N,)
    if half.ndim == 2:
        return half[brightest]
    return half.gather(1, brightest.view(-1, 1, 1).expand(-1, 1, 3))[:, 0]


def _starts(values: Tensor, usable: Tensor, albedo: Tensor, normals: Tensor, lights: Tensor, energy: Tensor,
            half: Tensor, sigma: Tensor, options: NonLambertianOptions) -> tuple[list[Tensor], list[Tensor]]:
    """Two starting states [normals (N, 3), albedo, specular albedo, log shininess (each (N, 1))].

    The first is the given start with a faint lobe (specular 1% of the albedo, exponent 30): the robust loss then
    sees a highlight as an outlier at first and grows the lobe only as far as the data support it. The second is the
    candidate of least Cauchy cost among, for each starting normal (the given one, the half vector of the brightest
    reading, and their bisector) and each exponent of ``options.shininess``, albedo and specular albedo by linear
    least squares on the usable readings (a 2×2 system per pixel, the specular albedo clamped at 0): a lobe of the
    size and at the place of a strong highlight, which the first start can miss when the robust start is far off.
    """
    tiny = torch.finfo(values.dtype).tiny
    most = _PEAK_RATIO * (usable * values / energy).amax(dim=1, keepdim=True)
    faint = [normals, albedo, _FAINT_LOBE * albedo, torch.full_like(albedo, math.log(_FAINT_SHININESS))]
    best: list[Tensor] | None = None
    best_cost = torch.zeros_like(albedo)
    peak = _brightest_half(values, usable, half)
    bisector = normals + peak
    bisector = bisector / bisector.norm(dim=1, keepdim=True).clamp_min(tiny)
    for start_normals in (normals, peak, bisector):
        for exponent in options.shininess:
            log_alpha = torch.full_like(albedo, math.log(exponent))
            cosine, _, lobe, _, _, _ = _shade(start_normals, albedo, albedo, log_alpha.exp(), lights, energy, half)
            diffuse = cosine.clamp_min(0)
            a, b, d, r1, r2 = [(usable * x * y).sum(dim=1, keepdim=True) for x, y in (
                (diffuse, diffuse), (diffuse, lobe), (lobe, lobe), (diffuse, values), (lobe, values))]
            specular = ((a * r2 - b * r1) / (a * d - b * b).clamp_min(tiny)).clamp_min(0).minimum(most)
            rho = ((r1 - b * specular) / a.clamp_min(tiny)).clamp_min(0)
            candidate = [start_normals, rho, specular, log_alpha]
            cost = _cauchy_cost(values - rho * diffuse - specular * lobe, usable, sigma)
            if best is None:
                best, best_cost = candidate, cost
                continue
            better = cost < best_cost
            best = [torch.where(better, new, old) for new, old in zip(candidate, best, strict=True)]
            best_cost = torch.where(better, cost, best_cost)
    assert best is not None  # options.shininess is never empty
    return faint, best


def _normal_equations(jacobian: list[Tensor], residuals: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """J^T W J (N, 5, 5) and J^T W r (N, 5) of the weighted Gauss–Newton step, each pixel's rows (N, K).

    One batched product of the stacked (N, 6, K) matrix [J | r] with its weighted transpose gives both: measured
    3x faster than the 20 products and sums of the separate entries.
    """
    design = torch.stack(jacobian + [residuals], dim=1)
    normal = torch.bmm(design * weights.unsqueeze(1), design.transpose(1, 2))
    return normal[:, :_PARAMETERS, :_PARAMETERS], normal[:, :_PARAMETERS, _PARAMETERS]


def _iterate(values: Tensor, usable: Tensor, sigma: Tensor, lights: Tensor, energy: Tensor, half: Tensor,
             state: list[Tensor], damping: Tensor, iterations: int, top: float) -> tuple[list[Tensor], Tensor, Tensor]:
    """Levenberg–Marquardt iterations on the Cauchy cost; returns the state, its cost and the damping (N, 1)."""
    tiny = torch.finfo(values.dtype).tiny
    normals, albedo, specular, log_alpha = state
    # the lobe's peak stays within a few times the brightest reading: a huge, narrow lobe far from every light
    # would otherwise fit a tail of readings (the peak between lights is unobserved, not unbounded)
    most = _PEAK_RATIO * (usable * values / energy).amax(dim=1, keepdim=True)
    cost = _cauchy_cost(values - _shade(normals, albedo, specular, log_alpha.exp(), lights, energy, half)[-1],
                        usable, sigma)
    for _ in range(iterations):
        alpha = log_alpha.exp()
        cosine, lit, lobe, g, log_g, model = _shade(normals, albedo, specular, alpha, lights, energy, half)
        residuals = values - model
        # IRLS weights of the Cauchy loss
        if _tracked(residuals, usable, sigma):
            weights = usable / (1 + (residuals / sigma).square())
        else:
            scaled = (residuals / sigma).square_().add_(1)
            weights = torch.div(usable, scaled, out=scaled)
        first, second = _tangents(normals)
        diffuse = albedo * lit  # d model / d (n · l)
        glossy = specular * alpha * lobe / g  # d model / d (n · h)
        jacobian = [diffuse * _dot(lights, first) + glossy * _dot(half, first),
                    diffuse * _dot(lights, second) + glossy * _dot(half, second),
                    cosine.clamp_min(0), lobe, specular * alpha * lobe * log_g]
        gram, rhs = _normal_equations(jacobian, residuals, weights)
        diagonal = gram.diagonal(dim1=1, dim2=2)
        # Marquardt's scaled damping, plus a floor so that a parameter without effect (s = 0) keeps the system regular
        floor = 1e-9 * diagonal.sum(dim=1, keepdim=True) + tiny
        step, info = torch.linalg.solve_ex(gram + torch.diag_embed(damping * diagonal + floor), rhs)
        step = torch.where((info == 0)[:, None], step, torch.zeros_like(step))  # (N, 5)
        trial_normals = normals + step[:, 0:1] * first + step[:, 1:2] * second
        trial_normals = trial_normals / trial_normals.norm(dim=1, keepdim=True)
        trial = [trial_normals, (albedo + step[:, 2:3]).clamp_min(0),
                 torch.minimum((specular + step[:, 3:4]).clamp_min(0), most),
                 (log_alpha + step[:, 4:5]).clamp(0.0, top)]
        trial_cost = _cauchy_cost(values - _shade(trial[0], trial[1], trial[2], trial[3].exp(), lights, energy,
                                                  half)[-1], usable, sigma)
        better = trial_cost < cost  # per pixel: accept and trust the model more, or reject and damp
        normals, albedo, specular, log_alpha = [torch.where(better, new, old) for new, old in
                                                zip(trial, (normals, albedo, specular, log_alpha), strict=True)]
        cost = torch.where(better, trial_cost, cost)
        damping = torch.where(better, damping / 3, damping * 4).clamp(1e-7, 1e7)
    return [normals, albedo, specular, log_alpha], cost, damping


def _fit_rows(values: Tensor, lights: Tensor, usable: Tensor, albedo: Tensor, normals: Tensor,
              options: NonLambertianOptions) -> list[Tensor]:
    """Robust LM fit on pixel rows; returns the fit's albedo (N, 1), normals (N, 3), specular albedo and shininess
    (N, 1), the start's albedo and normals, and the statistics (N, 4) of :func:`_keep_lobe`.

    values and usable (N, K), lights (K, 3) or (N, K, 3), starting albedo (N, 1) and normals (N, 3). Both starts of
    :func:`_starts` run side by side (as 2N rows) for the first :data:`_RACE` iterations; each pixel goes on from
    the one of lower cost.
    """
    energy, half = _split_lights(lights)
    tiny = torch.finfo(values.dtype).tiny
    # the Cauchy scale: a fraction of the pixel's median usable reading
    padding = _median_padding(usable > 0, values.dtype)
    median = _median(values, padding)[:, None]
    sigma = (options.scale * median).clamp_min(1e-6 * (usable * values).abs().amax(dim=1, keepdim=True) + tiny)
    top = math.log(options.max_shininess)
    faint, strong = _starts(values, usable, albedo, normals, lights, energy, half, sigma, options)
    race = min(_RACE, options.iterations)
    both = [torch.cat(pair) for pair in ((values, values), (usable, usable), (sigma, sigma))]
    per_row = [x if lights.ndim == 2 else torch.cat([x, x]) for x in (lights, energy, half)]
    state = [torch.cat(pair) for pair in zip(faint, strong, strict=True)]
    damping = torch.full_like(state[1], 1e-2)
    state, cost, damping = _iterate(both[0], both[1], both[2], per_row[0], per_row[1], per_row[2], state, damping,
                                    race, top)
    count = values.shape[0]
    first = cost[:count] <= cost[count:]
    state = [torch.where(first, x[:count], x[count:]) for x in state]
    damping = torch.where(first, damping[:count], damping[count:])
    state, _, _ = _iterate(values, usable, sigma, lights, energy, half, state, damping,
                           options.iterations - race, top)
    start = [normals, albedo, torch.zeros_like(albedo), torch.zeros_like(albedo)]
    # the residual sums of squares of both models on the usable readings, for the test of :func:`_keep_lobe`
    squares = [(usable * (values - _shade(x[0], x[1], x[2], x[3].exp(), lights, energy, half)[-1]).square())
               .sum(dim=1, keepdim=True) for x in (state, start)]
    fitted = [state[1], state[0], state[2], state[3].exp()]
    statistics = torch.cat(squares + [median, usable.sum(dim=1, keepdim=True)], dim=1)  # (N, 4)
    return fitted + [albedo, normals, statistics, _peak_observed(state[0], state[3].exp(), half)]


def _peak_observed(normals: Tensor, shininess: Tensor, half: Tensor) -> Tensor:
    r"""Whether each fitted lobe (normals (N, 3), exponents (N, 1)) is located by the readings, bool (N, 1).

    A Blinn–Phong lobe peaks where the half vector :math:`h_k` meets the normal. When the normal lies within the cone
    of the lights' half vectors (about their mean, out to the widest one: radius :math:`\Theta`), the readings sample
    the lobe about its peak. Beyond them they see only its tail: a narrow lobe's tail is confined to the cone's edge
    and still locates it, but a tail broad enough to reach across the cone has the shape of the diffuse term
    (:math:`\cos^2(\theta/2)` is affine in :math:`\cos\theta`) and of inter-reflection, and a fit there
    extrapolates the normal from a confusion of the two. So a lobe whose peak lies outside the cone must be at most
    half the cone wide: its half width at half maximum :math:`\arccos 2^{-1/\alpha} \le \Theta / 2` (for
    DiLiGenT's lights :math:`\Theta` = 21.6°, :math:`\alpha \ge 39`; for the rig's, 28.8° and 21). ``half``
    (K, 3), or per pixel (N, K, 3).
    """
    axis = half.mean(dim=-2)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(half.dtype).tiny)
    if half.ndim == 2:
        widest, facing = (half @ axis).amin(), normals @ axis
    else:
        widest, facing = (half * axis[:, None]).sum(dim=-1).amin(dim=1), (normals * axis).sum(dim=-1)
    radius = torch.acos(widest.clamp(-1, 1))
    half_width = torch.acos(torch.exp2(-1 / shininess[:, 0]))
    return ((facing >= widest) | (half_width <= radius / 2))[:, None]


def _wilson_hilferty_median(degrees: Tensor) -> Tensor:
    r"""Median of a :math:`\chi^2` variable with ``degrees`` degrees of freedom, :math:`d (1 - 2 / (9 d))^3`
    (Wilson & Hilferty, "The distribution of chi-square", PNAS 1931; within 3.5% of the exact median for d = 1, 1%
    from d = 3)."""
    return degrees * (1 - 2 / (9 * degrees)) ** 3


def _keep_lobe(statistics: Tensor, significance: float) -> Tensor:
    r"""Per pixel, whether the fitted lobe passes the likelihood-ratio test against the Lambertian start, bool (N,).

    ``statistics`` (N, 4): residual sums of squares of the fit :math:`S_5` and of the start :math:`S_3`, the pixel's
    median usable reading :math:`\mu` and its count of usable readings :math:`K`. The noise is taken as a fraction
    :math:`\tau` of the median reading (the scale the Cauchy loss uses), one :math:`\tau` per image, estimated from
    the pixels whose fit leaves residual degrees of freedom (:math:`K > 5`): :math:`\tau^2 = \mathrm{median}(S_5 /
    (\mu^2 m_{K-5}))` with :math:`m_d` the median of :math:`\chi^2_d` (:func:`_wilson_hilferty_median`), a median
    over pixels so that glints and cast shadows on some pixels do not inflate it. The lobe is kept where the drop
    :math:`(S_3 - S_5) / (\tau \mu)^2` exceeds the :math:`1 - \alpha` quantile of :math:`\chi^2_2` (two extra
    parameters), :math:`-2 \ln \alpha`. With 8 lights a lobe fitted to noise lowers the residual by about
    :math:`\chi^2_2` and fails; a highlight lowers it by far more. A pixel with 3 readings has :math:`S_3 = 0` and
    never passes; an image without any pixel of more than 5 readings gives no noise level and keeps every start.
    """
    fit_squares, start_squares, median, count = statistics.detach().unbind(dim=1)
    free = count > _PARAMETERS
    if not bool(free.any()):
        return torch.zeros_like(free)
    degrees = (count - _PARAMETERS).clamp_min(1)
    noise = (fit_squares / (median.square() * _wilson_hilferty_median(degrees)))[free].median()
    tiny = torch.finfo(statistics.dtype).tiny
    drop = (start_squares - fit_squares) / (noise * median.square()).clamp_min(tiny)
    return drop > -2 * math.log(significance)


def _fit_chunked(values: Tensor, lights: Tensor, usable: Tensor, albedo: Tensor, normals: Tensor,
                 options: NonLambertianOptions) -> list[Tensor]:
    """:func:`_fit_rows` on blocks of :data:`_CHUNK` pixels, each turned into contiguous pixel rows.

    values and usable (K, N), lights (K, 3) or (K, 3, N), albedo (1, N), normals (3, N); returns albedo, normals,
    specular and shininess as (C, N): the fit where its lobe passes :func:`_keep_lobe`, else the start (no lobe).
    """
    parts = []
    for start in range(0, values.shape[1], _CHUNK):
        block = slice(start, start + _CHUNK)
        block_lights = lights if lights.ndim == 2 else lights[..., block].permute(2, 0, 1).contiguous()
        rows = [x[:, block].T.contiguous() for x in (values, usable, albedo, normals)]
        parts.append(_fit_rows(rows[0], block_lights, rows[1], rows[2], rows[3], options))
    if not parts:
        return [albedo, normals, albedo, albedo]
    # the test of the lobe takes one noise level for the whole image: all blocks first, then the choice
    albedo_fit, normals_fit, specular, shininess, albedo_start, normals_start, statistics, observed = [
        torch.cat(x) for x in zip(*parts, strict=True)]
    lobe = _keep_lobe(statistics, options.significance)[:, None] & observed
    maps = [torch.where(lobe, albedo_fit, albedo_start), torch.where(lobe, normals_fit, normals_start),
            torch.where(lobe, specular, torch.zeros_like(specular)),
            torch.where(lobe, shininess, torch.ones_like(shininess))]
    return [x.T for x in maps]


def fit_blinn_phong(
    intensities: Tensor,
    lights: Tensor,
    mask: Tensor | None = None,
    weights: Tensor | None = None,
    options: NonLambertianOptions | None = None,
    init: tuple[Tensor, Tensor] | None = None,
) -> BlinnPhongFit:
    r"""Fit the Lambertian + Blinn–Phong model per pixel by robust Levenberg–Marquardt (see the module docstring).

    Args:
        intensities: readings, shape :math:`(B, K, H, W)` (flat-fielded, or divided by the light intensities).
        lights: light directions scaled by irradiance: distant :math:`(K, 3)` / :math:`(B, K, 3)`, or per pixel
            :math:`(B, K, 3, H, W)` (near lights).
        mask: optional pixels to solve, bool :math:`(B, 1, H, W)`; only those are computed.
        weights: optional usable observations :math:`(B, K, H, W)` (e.g. the flat-field's ``valid``).
        options: a :class:`NonLambertianOptions` (``None``: the defaults).
        init: starting albedo :math:`(B, 1, H, W)` and normals :math:`(B, 3, H, W)`; ``None``: the recommended robust
            estimator of :func:`psmini.robust.robust_normals` for distant lights, least squares on the readings above
            the ``shadow`` threshold for per-pixel lights.

    Returns:
        a :class:`BlinnPhongFit`; pixels outside the mask, or that the start leaves unsolved (fewer than three usable
        lights), get albedo 0, normal (0, 0, 1), specular 0 and shininess 1.

    Raises:
        InputError: for NaN input or options that are not a :class:`NonLambertianOptions`.
        ShapeError: when shapes do not fit.
        CalibrationError: when distant lights do not span 3D.

    Example:
        >>> from psmini.lights import ring_lights
        >>> images = torch.rand(1, 8, 4, 4) + 0.1
        >>> fit = fit_blinn_phong(images, ring_lights(8, 55.0), options=NonLambertianOptions(iterations=3))
        >>> fit.shininess.shape
        torch.Size([1, 1, 4, 4])
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_finite(intensities, "intensities")
    check_tensor(lights, "lights")
    lights = _check_lights(lights, sizes)
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    base = _check_weights(weights, intensities.shape)
    options = _check_options(options)
    usable = threshold_weights(intensities, options.shadow, options.saturation, base)
    if init is None:
        if lights.ndim == 5:
            init = albedo_normals(intensities, lights, mask, usable)
        else:
            start = replace(RobustOptions(), shadow=options.shadow, saturation=options.saturation)
            init = robust_normals(intensities, lights, "robust", mask, base, start)
    start_albedo, start_normals = _check_init(init, sizes)
    lights = lights.to(intensities) if lights.ndim == 5 else as_batched_lights(lights, sizes["B"], intensities)

    maps = []
    for b in range(sizes["B"]):  # a loop over images, not pixels: each image's pixels are one set of columns
        solved = start_albedo[b, 0].flatten() > 0
        if mask is not None:
            solved = solved & mask[b, 0].flatten().bool()
        columns_lights = lights[b].flatten(2)[..., solved] if lights.ndim == 5 else lights[b]
        values = intensities[b].flatten(1)[:, solved]
        columns_albedo, columns_normals = start_albedo[b].flatten(1)[:, solved], start_normals[b].flatten(1)[:, solved]
        # the readings the start explains as shadows (a prediction p <= 0, or a reading below p / 2: the cast shadows
        # of psmini.robust) are left out: visibility, not reflectance, accounts for them, and a lobe fitted to them
        # moves the normal (the bottom of a crevice, where most readings are cast shadows lifted by inter-reflection)
        lit = _lit_by(values, columns_lights, (columns_albedo * columns_normals).detach())
        fitted = _fit_chunked(values, columns_lights, (usable[b].flatten(1)[:, solved] & lit).to(intensities.dtype),
                              columns_albedo, columns_normals, options)
        total = solved.numel()
        up = torch.zeros(3, total, device=intensities.device, dtype=intensities.dtype)
        up[2] = 1
        normals = torch.where(solved[None], _scatter(fitted[1], solved, total), up)
        ones = torch.ones(1, total, device=intensities.device, dtype=intensities.dtype)
        shininess_map = torch.where(solved[None], _scatter(fitted[3], solved, total), ones)
        maps.append([_scatter(fitted[0], solved, total), normals, _scatter(fitted[2], solved, total), shininess_map])
    albedo, normals, specular_map, shininess_map = (torch.stack(parts).view(sizes["B"], -1, sizes["H"], sizes["W"])
                                                    for parts in zip(*maps, strict=True))
    return BlinnPhongFit(albedo, normals, specular_map, shininess_map)


def _lit_by(values: Tensor, lights: Tensor, m: Tensor) -> Tensor:
    r"""Readings (K, N) that the Lambertian estimate m = albedo × normal (3, N) explains as lit:
    :math:`|I_k - p_k| < I_k` with :math:`p_k = l_k \cdot m` (a positive prediction and a reading of more than half of
    it; :func:`psmini.robust._lit`). ``values`` (K, N), ``lights`` (K, 3) or per pixel (K, 3, N)."""
    predicted = lights @ m if lights.ndim == 2 else (lights * m[None]).sum(dim=1)
    readings = values.detach()
    return (readings - predicted).abs() < readings


def _check_options(options: NonLambertianOptions | None) -> NonLambertianOptions:
    options = NonLambertianOptions() if options is None else options
    if not isinstance(options, NonLambertianOptions):
        raise InputError(f"options must be a NonLambertianOptions, got {type(options).__name__}")
    return options


def _check_init(init: tuple[Tensor, Tensor], sizes: dict[str, int]) -> tuple[Tensor, Tensor]:
    if not isinstance(init, (tuple, list)) or len(init) != 2:
        raise InputError("init must be a pair (albedo (B, 1, H, W), normals (B, 3, H, W))")
    albedo, normals = init
    check_tensor(albedo, "init albedo")
    check_tensor(normals, "init normals")
    expected = (sizes["B"], 1, sizes["H"], sizes["W"])
    if albedo.shape != expected or normals.shape != (sizes["B"], 3, sizes["H"], sizes["W"]):
        raise ShapeError(f"init must be albedo {expected} and normals ({sizes['B']}, 3, {sizes['H']}, {sizes['W']}), "
                         f"got {tuple(albedo.shape)} and {tuple(normals.shape)}")
    check_finite(albedo, "init albedo")
    check_finite(normals, "init normals")
    return albedo, normals


def nonlambertian_normals(
    intensities: Tensor,
    lights: Tensor,
    mask: Tensor | None = None,
    weights: Tensor | None = None,
    options: NonLambertianOptions | None = None,
    init: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    r"""Albedo and normals of the Lambertian + Blinn–Phong fit (:func:`fit_blinn_phong`); the CLI's ``nonlambertian``.

    Args:
        intensities: readings, shape :math:`(B, K, H, W)`.
        lights: scaled light directions, :math:`(K, 3)` / :math:`(B, K, 3)` or per pixel :math:`(B, K, 3, H, W)`.
        mask: optional pixels to solve, bool :math:`(B, 1, H, W)`.
        weights: optional usable observations :math:`(B, K, H, W)`.
        options: a :class:`NonLambertianOptions` (``None``: the defaults).
        init: starting albedo and normals, as :func:`fit_blinn_phong` takes them.

    Returns:
        diffuse albedo :math:`(B, 1, H, W)` and unit normals :math:`(B, 3, H, W)`.

    Raises:
        InputError, ShapeError, CalibrationError: as :func:`fit_blinn_phong`.

    Example:
        >>> from psmini.lights import ring_lights
        >>> albedo, normals = nonlambertian_normals(torch.rand(1, 8, 4, 4) + 0.1, ring_lights(8, 55.0))
        >>> normals.shape
        torch.Size([1, 3, 4, 4])
    """
    fit = fit_blinn_phong(intensities, lights, mask, weights, options, init)
    return fit.albedo, fit.normals


class NonLambertianNormals(nn.Module):
    """Non-Lambertian albedo and normals with stored distant lights and options; see :func:`nonlambertian_normals`.

    Args:
        lights: scaled light directions, shape :math:`(K, 3)`.
        options: a :class:`NonLambertianOptions` (``None``: the defaults).

    Raises:
        InputError: for options that are not a :class:`NonLambertianOptions`.
        ShapeError: for lights that are not (K, 3).

    Example:
        >>> from psmini.lights import ring_lights
        >>> solver = NonLambertianNormals(ring_lights(8, 55.0), NonLambertianOptions(iterations=5))
        >>> albedo, normals = solver(torch.rand(1, 8, 4, 4) + 0.1)
        >>> normals.shape
        torch.Size([1, 3, 4, 4])
    """

    def __init__(self, lights: Tensor, options: NonLambertianOptions | None = None) -> None:
        super().__init__()
        options = _check_options(options)
        check_tensor(lights, "lights")
        if lights.ndim != 2 or lights.shape[-1] != 3:
            raise ShapeError(f"lights must have shape (K, 3), got {tuple(lights.shape)}")
        self.register_buffer("lights", lights.clone())
        self.options = options

    def forward(
        self, intensities: Tensor, mask: Tensor | None = None, weights: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Albedo :math:`(B, 1, H, W)` and normals :math:`(B, 3, H, W)` of ``intensities`` :math:`(B, K, H, W)`."""
        lights: Tensor = self.lights  # type: ignore[assignment]  # a registered buffer
        return nonlambertian_normals(intensities, lights, mask, weights, self.options)
