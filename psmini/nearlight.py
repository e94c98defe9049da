r"""Near-light photometric stereo as one robust, smooth energy.

With a light model :math:`L_k(x)` (:mod:`psmini.lights`: unit direction times irradiance at the surface point
:math:`x`), a Lambertian pixel reads :math:`I_k = \rho \max(n \cdot L_k(x), 0)`. Near light minimises, over the
albedo :math:`\rho`, the normals :math:`n`, the depth :math:`z`, the cloth's absolute height, its tilt and its bend:

.. math::
    E = \sum_{\text{pixels}} \sum_k \lambda_k\, \psi(r_k), \qquad
    r_k = \frac{I_k - \rho \max(n \cdot L_k(x(z)), 0)}{\sigma_k}, \qquad
    \lambda_k = \frac{I_k^2}{I_k^2 + 9\sigma_k^2}

with :math:`\psi` Welsch's robust penalty by default (Dennis and Welsch 1978) or Cauchy's (Quéau, Durix, Wu, Cremers,
Lauze and Durou, "LED-based photometric stereo: modeling, calibration and numerical solution", JMIV 60, 2018, Section
4, compare robust estimators of this kind), and :math:`\sigma_k` each reading's noise level, fitted to the capture.
It alternates (Quéau et al. 2018; Logothetis et al. 2017 use the same fixed point), coarse to fine: per pixel
re-weighted Gauss–Newton steps on :math:`m = \rho n` at the current depth's lights; the normals integrated to depth;
the height, tilt and bend by Gauss–Newton with the normals projected out (variable projection, Golub and Pereyra
1973). ``torch.autograd`` differentiates the whole solve in the images and the light model's parameters. The
near-light guide, ``docs/guides/near-light.md``, says why this form, how each step works and what it measures up to.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import check_finite, check_mask, check_positive, check_shape
from psmini._chunks import batch_part, chunks
from psmini._compile import _eager, compiler
from psmini._tensor import box_sum, masked_mean, masked_median, non_negative_solve, vector_length
from psmini.errors import InputError, ShapeError
from psmini.flatfield import _check_frame
from psmini.geometry import pixel_grid_mm
from psmini.integrate import METHODS as INTEGRATORS
from psmini.integrate import dct_poisson, integrate
from psmini.integrate.bilateral import _Grid
from psmini.integrate.least_squares import _edge_system, _undo_edge_averaging
from psmini.integrate.poisson import solve_weighted_poisson
from psmini.lights import LightModel
from psmini.metrics import angular_error_deg
from psmini.normals import _slopes_of, _symmetric_adjugate
from psmini.render import normals_from_height
from psmini.result import Reconstruction
from psmini.robust import _EFFICIENT_SCALES, _Penalty

__all__ = ["NearLightOptions", "NearLightResult", "near_light_vectors", "near_light_energy", "solve_near_light"]

logger = logging.getLogger(__name__)

# The model's relative accuracy (the light model's and the flat-field's), a floor under every reading's noise level:
# a thousandth, finer than any LED calibration, so that a render without noise is fitted to its model error rather
# than to the rounding of 16 bits (which would make every model error an outlier).
_MODEL_ERROR = 1e-3
# A reading counts by I² / (I² + (this × σ)²): within three noise levels of zero it is not known to be lit.
_LIT_SIGMAS = 3.0
# The max's Jacobian: the chance Φ(m·L / σ) that a reading predicted at m·L, noise σ, is lit, as a logistic of scale
# 1/1.702 (Φ to 1%). A narrower one (0.25) let rounding move single pixels by 1.3°; a step would flip weights.
_HINGE_WIDTH = 1 / 1.702
# The first fit weighs each reading by I² / (I² + (this × the pixel's brightest)² + (3σ)²): a penumbra is no light.
_INIT_SHARE = 0.1
# A pixel's prior toward the current surface's normal (times its albedo): a Gaussian of this fraction of its length (23°
# a direction, 32° RMS: alone, unsolved), firm enough that shadows' faint weights cannot swing it (0.5: 2° by rounding).
_PRIOR_SPREAD = 0.4
# A normal whose noise predicts worse than this (degrees) is unsolved: its readings add little to the prior's 32°.
_SOLVED_BELOW_DEG = 30.0
# Slopes are weighted by 1 / (their variance + this²), relative to the typical pixel's and at most 1: the error of a
# measured slope against the forward difference the integration compares it with, about a 1° tilt.
_SLOPE_FLOOR = 0.02
# A normal whose predicted error exceeds this (degrees) has its slopes blended into its neighbourhood's ...
_FILL_ABOVE_DEG = 10.0
# ... and so does a slope whose standard error exceeds this (a rise per run known to worse than ±1: a normal too near
# the horizontal for its rise to be measured, a wall's 80° normal whose slope of 6 would make a spike) ...
_FILL_SLOPE_STD = 1.0
# ... a window of this many pixels on a side (a yarn's width at the rig's 25 µm).
_FILL_SIZE = 9
# Least weight of a slope in the integration: a filled slope still holds its pixel to its neighbours.
_WEIGHT_FLOOR = 1e-2
# Sharpness (1/pixel²) of the final integration's choice of an edge's one-sided slope: bilateral normal integration's
# k (Cao et al. 2022); one-sided depth differences whose squares differ by one pixel² share the edge 0.88 to 0.12.
_ONE_SIDED_K = 2.0
# Relative residual at which the weighted integration stops (warm-started: within micrometres of converged).
_CG_TOLERANCE = 1e-2
# Most a placement's Gauss–Newton step moves any pixel; the light field's forward difference in the height (mm).
_MAX_STEP_MM, _HEIGHT_STEP_MM = 0.5, 0.01
# The noise model is fitted on every _NOISE_STRIDE-th pixel in each direction (two parameters), the placement on
# the stride that leaves about _PLACE_PIXELS of them (six parameters, on a sixteenth of the rig's 400² frame).
_NOISE_STRIDE, _PLACE_PIXELS = 4, 10_000
# Heights tried by a scan: at most this many, an eighth of a millimetre apart at least.
_SCAN_POINTS = 13
# Interval (mm) scanned around the coarse level's height by the first full-resolution alternation: pooling mixes a
# thread's top with the hole beside it, which biases the coarse height.
_FINE_SEARCH_MM = (-0.5, 0.5)
# Images at least this large (and of even size) run this many alternations at half resolution first (a coarse level
# of fewer than 32² pixels is too few to find the height on).
_MIN_COARSE_SIZE, _COARSE_ITERATIONS = 64, 2
# A tilt (or a bend) is kept in the share r⁴ / (1 + r⁴), r = q / this², q its squared Mahalanobis length: a soft test
# at 4 standard errors, not 3 (smooth cloth's false tilts and bends stood 1.6 times further out than the Hessian says).
_TILT_SIGMAS = 4.0


@dataclass(frozen=True)
class NearLightOptions:
    """Options of the near-light solver (:func:`solve_near_light`); the defaults are what ``benchmarks/nearlight.py``
    measures.

    Attributes:
        max_iterations: most alternations (lights → normals → depth) at full resolution (after two at half
            resolution, for images of at least 64² pixels).
        tolerance_deg: a sample's alternations stop when its normals moved less than this on average since the
            previous alternation, degrees.
        penalty: the robust penalty of each reading's standardised residual: ``"welsch"`` (the default, Dennis and
            Welsch 1978, :math:`\\tfrac{c^2}{2}(1 - e^{-r^2/c^2})`: bounded, so that a pixel whose readings are
            mostly cast shadows is fitted to its lit ones) or ``"cauchy"`` (:math:`\\tfrac{c^2}{2}\\log(1 + r^2/c^2)`,
            whose outliers keep a pull that grows with their number).
        robust_scale: the penalty's scale :math:`c`, in noise levels; ``None``: the value with 95% of least squares'
            efficiency on Gaussian noise (2.985 for Welsch, 2.385 for Cauchy).
        irls_steps: re-weighted Gauss–Newton steps of the per-pixel fit in each alternation.
        estimate_offset: find the absolute height from the images (the light field is not uniform); otherwise the
            mean height stays ``initial_height_mm``.
        estimate_tilt: find the plane of the height from the images as well (the steps that integration loses).
        estimate_bend: find the height's quadric (its second derivatives) from the images as well (the steps that
            integration loses where the LEDs light their walls unevenly across the field).
        initial_height_mm: starting height of the cloth above the card plane's origin, mm.
        search_mm: interval of heights scanned around ``initial_height_mm`` before the first alternation, mm.
        integrator: the final integration of the normals: ``"masked"`` (weighted least squares on the mask, slopes
            weighted by their inverse variance, an edge's from the side where the depth runs smoother, the finest
            relief restored on the whole rectangle) or another method of :func:`psmini.integrate.integrate`.
        compile: compile the per-pixel steps with ``torch.compile``, for many captures: 1.8 times faster warm on a
            CPU at 400², after a first call of 25–60 s; the same result up to rounding (the near-light guide's "What
            it costs"). Without a C++ compiler (CPU) or Triton (CUDA) the solve runs eagerly, with a warning.

    Raises:
        InputError: for values out of range.

    Example:
        >>> NearLightOptions(max_iterations=3).to_dict()["max_iterations"]
        3
    """

    max_iterations: int = 2
    tolerance_deg: float = 0.005
    penalty: str = "welsch"
    robust_scale: float | None = None
    irls_steps: int = 1
    estimate_offset: bool = True
    estimate_tilt: bool = True
    estimate_bend: bool = True
    initial_height_mm: float = 0.0
    search_mm: tuple[float, float] = (-3.0, 3.0)
    integrator: str = "masked"
    compile: bool = False

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> InputError:
            return InputError(f"NearLightOptions.{name} must be {expected}, got {getattr(self, name)!r}")

        for name in ("max_iterations", "irls_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise bad(name, "an integer >= 1")
        for name in ("tolerance_deg", "robust_scale"):
            value = getattr(self, name)
            if (value is not None or name == "tolerance_deg") and (
                    isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf):
                raise bad(name, "a positive number" + (" or None" if name == "robust_scale" else ""))
        if self.penalty not in _EFFICIENT_SCALES:
            raise bad("penalty", f"one of {', '.join(sorted(_EFFICIENT_SCALES))}")
        for name in ("estimate_offset", "estimate_tilt", "estimate_bend", "compile"):
            if not isinstance(getattr(self, name), bool):
                raise bad(name, "a bool")
        if not (isinstance(self.initial_height_mm, (int, float)) and math.isfinite(self.initial_height_mm)):
            raise bad("initial_height_mm", "a finite number")
        search = self.search_mm
        if not (isinstance(search, (tuple, list)) and len(search) == 2
                and all(isinstance(s, (int, float)) and math.isfinite(s) for s in search) and search[0] < search[1]):
            raise bad("search_mm", "an increasing pair of finite numbers")
        object.__setattr__(self, "search_mm", (float(search[0]), float(search[1])))
        if self.integrator not in INTEGRATORS:
            raise bad("integrator", f"one of {', '.join(sorted(INTEGRATORS))}")

    def penalty_function(self) -> _Penalty:
        """The robust penalty these options name, at its scale."""
        scale = _EFFICIENT_SCALES[self.penalty] if self.robust_scale is None else float(self.robust_scale)
        return _Penalty(self.penalty, scale)

    def to_dict(self) -> dict:
        """The options as a JSON-serialisable dict (``NearLightOptions(**d)`` rebuilds them)."""
        return dataclasses.asdict(self) | {"search_mm": list(self.search_mm)}

    def replace(self, **changes) -> NearLightOptions:
        """A copy with some fields changed (validated again).

        Raises:
            InputError: for a name that is no option, or a value out of range.
        """
        names = [f.name for f in dataclasses.fields(self)]
        if unknown := set(changes) - set(names):
            raise InputError(f"unknown near-light options {sorted(unknown)}; expected some of {names}")
        return dataclasses.replace(self, **changes)


@dataclass
class NearLightResult(Reconstruction):
    """A :class:`~psmini.result.Reconstruction` with the near-light solver's diagnostics.

    Attributes:
        normal_std: predicted root-mean-square angular error of each normal, :math:`(B, 1, H, W)`, degrees: from the
            fit's covariance under the fitted noise model, scaled up where the readings fit worse than their noise
            (an unmodelled reflection) and by the light the fit rejected or could not explain; ``mask``: where the
            noise's part is under 30°.
        weights: each observation's weight in the last fit, :math:`(B, K, H, W)` in [0, 1]: the robust penalty's
            (near 0 for a cast shadow, a highlight or an attached shadow), 0 where not valid.
        offset_mm: mean height of the cloth above the card plane, :math:`(B,)`, mm.
        tilt: the plane found from the images, :math:`(B, 2)`: its slopes dz/dx and dz/dy (x right, y up).
        bend: the quadric found from the images, :math:`(B, 3)`: its second derivatives d²z/dx², d²z/dxdy and
            d²z/dy², 1/mm.
        noise: the fitted noise model :math:`(\\alpha, \\beta, \\gamma)` of each sample, :math:`(B, 3)`: a reading's
            variance is :math:`s^2\\alpha + s\\beta I + \\gamma I^2` (read noise and shot noise of the raw reading,
            :math:`s` the flat-field's gain, and the model's relative error).
        iterations: alternations run, at both resolutions (the first ones on 2 × 2-averaged images).
        changes_deg: the mean change of the normals in each alternation after the first at each resolution (the
            largest over the batch), degrees.
        converged: whether the change fell below the tolerance before ``max_iterations``.
    """

    normal_std: Tensor | None = None
    weights: Tensor | None = None
    offset_mm: Tensor | None = None
    tilt: Tensor | None = None
    bend: Tensor | None = None
    noise: Tensor | None = None
    iterations: int = 0
    changes_deg: tuple[float, ...] = ()
    converged: bool = False

    @classmethod
    def concatenate(cls, parts: list[NearLightResult]) -> NearLightResult:
        """A batch's chunks' results as one: tensors concatenated, counts and changes the largest, converged if all."""
        tensors = {f.name: torch.cat([getattr(part, f.name) for part in parts]) for f in dataclasses.fields(cls)
                   if isinstance(getattr(parts[0], f.name), Tensor)}
        longest = max(len(part.changes_deg) for part in parts)
        changes = tuple(max(part.changes_deg[i] for part in parts if i < len(part.changes_deg))
                        for i in range(longest))
        return cls(**tensors, iterations=max(part.iterations for part in parts), changes_deg=changes,
                   converged=all(part.converged for part in parts))


# --- The light field: a light model evaluated on the pixel grid at a height map ---------------------------------


class _LightField:
    """Light vectors :math:`L_k` of a model on a pixel grid (every ``stride``-th pixel), relative to the card's
    reading when the images were flat-fielded by a card at ``card_height``: the card reads
    :math:`\\rho_c E_k(x_c)\\,l_{k,z}(x_c)`, so a flat-fielded pixel reads :math:`\\rho\\, n \\cdot L_k(x) /
    (E_k(x_c)\\,l_{k,z}(x_c))`, the camera's gain, vignetting and the LEDs' intensities cancelled."""

    def __init__(self, model: nn.Module, size: tuple[int, int], pitch: float, card_height: float | None,
                 like: Tensor, steps: _Steps, stride: int = 1) -> None:
        x, y = pixel_grid_mm(*size, pitch, device=like.device, dtype=like.dtype)
        self.model, self.xy = model, torch.stack([x[::stride, ::stride], y[::stride, ::stride]])[None]  # (1, 2, h, w)
        self.steps, self.card_scale = steps, None
        if card_height is not None:
            card = steps.light_vectors(model, self.xy, torch.full_like(self.xy[:, :1], card_height), None)[:, :, 2:3]
            if bool((card.detach() <= 0).any()):
                raise InputError("flat-fielding needs every light above the card plane, lighting it, at every pixel")
            self.card_scale = 1 / card  # (1, K, 1, h, w)

    def __call__(self, depth: Tensor) -> Tensor:
        """Light vectors at the heights ``depth`` :math:`(B, 1, h, w)` (mm): :math:`(B, K, 3, h, w)`."""
        return self.steps.light_vectors(self.model, self.xy, depth, self.card_scale)


def _light_vectors(model: nn.Module, xy: Tensor, depth: Tensor, card_scale: Tensor | None) -> Tensor:
    """The model's light vectors at the points ``xy`` (1, 2, h, w), ``depth`` (B, 1, h, w), times ``card_scale``."""
    directions, irradiance = model(torch.cat([xy.expand(depth.shape[0], -1, -1, -1), depth], dim=1))
    return directions * (irradiance if card_scale is None else irradiance * card_scale)


def near_light_vectors(light_model: nn.Module, depth: Tensor, pixel_pitch_mm: float,
                       card_height_mm: float | None = None) -> Tensor:
    r"""Per-pixel light vectors :math:`L_k(x)` of a light model on a height map.

    Args:
        light_model: a :class:`~psmini.lights.LightModel`.
        depth: height toward the camera, shape :math:`(B, 1, H, W)`, mm (same frame as the light positions).
        pixel_pitch_mm: pixel size on the cloth, mm (orthographic camera, :mod:`psmini.geometry`).
        card_height_mm: for flat-fielded images, the height of the card they were divided by: the vectors are then
            divided by the card's irradiance times :math:`l_z` at the same pixel. ``None`` for raw images.

    Returns:
        light vectors :math:`(B, K, 3, H, W)`: unit direction times irradiance (relative to the card's when
        ``card_height_mm`` is given).

    Raises:
        ShapeError: when ``depth`` is not :math:`(B, 1, H, W)`.
        InputError: for a light at or below the card plane with ``card_height_mm``, or a model that is no
            :class:`~psmini.lights.LightModel`.

    Example:
        >>> from psmini.lights import PointLights
        >>> lights = PointLights(torch.tensor([[10.0, 0, 10], [-10.0, 0, 10], [0, 10.0, 10]]))
        >>> vectors = near_light_vectors(lights, torch.zeros(1, 1, 4, 4), 0.025, card_height_mm=0.0)
        >>> torch.allclose(vectors[:, :, 2], torch.ones(1, 3, 4, 4))   # on the card itself l_z / l_z = 1
        True
    """
    sizes = check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    _check_light_model(light_model)
    return _LightField(light_model, (sizes["H"], sizes["W"]), pixel_pitch_mm, card_height_mm, depth,
                       _Steps(False, depth.device))(depth)


# --- The robust per-pixel fit at fixed lights -------------------------------------------------------------------


class _Data:
    """One level's images :math:`(B, K, h, w)`, their validity (float 0/1), the flat-field's gain (broadcastable; 1 for
    raw images), the noise model :math:`(\\alpha, \\beta, \\gamma)` (B, 3, 1, 1), each :math:`\\lambda_k` and the
    steps that compute on them."""

    def __init__(self, images: Tensor, valid: Tensor, gain: Tensor, noise: Tensor, steps: _Steps) -> None:
        self.images, self.valid, self.gain, self.noise, self.steps = images, valid, gain, noise, steps
        self.read, self.shot, self.reliability = steps.reading_terms(images, valid, gain, noise)

    def variance(self, predicted: Tensor) -> Tensor:
        """:math:`s^2\\alpha + s\\beta\\hat I + \\gamma\\hat I^2` at the predicted readings."""
        return _variance(self.read, self.shot, self.noise, predicted)

    def set_noise(self, noise: Tensor) -> None:
        """Replace the noise model (and the readings' weights that follow from it)."""
        self.__init__(self.images, self.valid, self.gain, noise, self.steps)  # type: ignore[misc]

    def every(self, stride: int) -> _Data:
        """The same data on every ``stride``-th pixel in each direction."""
        return _Data(_stride(self.images, stride), _stride(self.valid, stride), _stride(self.gain, stride), self.noise,
                     self.steps)


class _Steps:
    """The per-pixel steps of the solve (chains of elementwise passes over the K readings, bound by memory): the
    functions themselves, or with ``NearLightOptions.compile`` each compiled by ``torch.compile``, which fuses a chain
    into a few loops (where it can run: :func:`psmini._compile.compiler`)."""

    def __init__(self, compile: bool, device: torch.device) -> None:
        wrap = compiler(device) if compile else _eager
        self.robust_step, self.initial_fit, self.energy = wrap(_robust_step), wrap(_initial_fit), wrap(_energy)
        self.normal_std, self.predicted_std, self.fit_noise = wrap(_normal_std), wrap(_predicted_std), wrap(_fit_noise)
        self.light_vectors, self.reading_terms = wrap(_light_vectors), wrap(_reading_terms)
        self.height_terms, self.blended_slopes = wrap(_height_terms), wrap(_blended_slopes)


def _variance(read: Tensor, shot: Tensor, noise: Tensor, predicted: Tensor) -> Tensor:
    reading = predicted.clamp_min(0)
    return read + (shot + noise[:, 2:3] * reading) * reading


def _reading_terms(images: Tensor, valid: Tensor, gain: Tensor, noise: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The variance's terms in the flat-fielded units, :math:`s^2\\alpha` (1 where not valid: an untrusted card has a
    gain of 0, and the weight there is 0 whatever the variance) and :math:`s\\beta`, and each :math:`\\lambda_k`."""
    read = torch.where(valid > 0, gain.square() * noise[:, 0:1], torch.ones_like(valid))
    shot = gain * noise[:, 1:2] * valid
    reading = images.clamp_min(0)
    # a reading within its noise of zero is as likely a cast shadow as an attached one: it says little about the
    # normal, and a bounded penalty would otherwise rather turn a normal away from the LEDs of cast shadows
    variance = _variance(read, shot, noise, reading)
    return read, shot, valid * reading.square() / (reading.square() + _LIT_SIGMAS**2 * variance
                                                   + torch.finfo(reading.dtype).tiny)


class _Fit:
    """A per-pixel weighted least-squares fit of :math:`m = \\rho n` with a Gaussian prior: the inverse of its normal
    matrix, the weights that made it (with the noise: ``weights``; without: ``share``, in [0, 1]) and the solution.
    The 3 × 3 algebra (adjugates: batched LAPACK on millions of 3 × 3 systems costs far more) runs in float64: where
    two LEDs light a pixel its third direction is held by the faint prior alone, beyond float32's seven digits."""

    def __init__(self, lights: Tensor, images: Tensor, weights: Tensor, prior: Tensor,
                 share: Tensor | None = None) -> None:
        self.weights, self.share, self.dtype = weights, share, images.dtype
        lx, ly, lz = lights.unbind(2)
        wx, wy, wz = weights * lx, weights * ly, weights * lz
        gram = [(wx * lx).sum(1), (wx * ly).sum(1), (wx * lz).sum(1), (wy * ly).sum(1), (wy * lz).sum(1),
                (wz * lz).sum(1)]  # each (B, h, w): entries 00 01 02 11 12 22
        rhs = [(wx * images).sum(1), (wy * images).sum(1), (wz * images).sum(1)]
        # the prior m ~ N(prior, (τ |prior|)² I), its information in the readings' units (the weights are 1 / σ²)
        magnitude = prior.square().sum(1)
        floor = 1e-6 * magnitude.mean(dim=(-2, -1), keepdim=True) + torch.finfo(magnitude.dtype).tiny
        prior_weight = 1 / (_PRIOR_SPREAD**2 * (magnitude + floor))
        gram = [g.double() + (prior_weight.double() if i in (0, 3, 5) else 0) for i, g in enumerate(gram)]
        cofactors, det, _ = _symmetric_adjugate(*gram)
        self.inverse = tuple(c / det for c in cofactors)
        self.m = self.solve([r + prior_weight * prior[:, j] for j, r in enumerate(rhs)])

    def every(self, stride: int) -> _Fit:
        """The same fit on every ``stride``-th pixel in each direction (copies: passes over strided views are slow)."""
        part = copy.copy(self)
        part.inverse = tuple(_stride(c, stride) for c in self.inverse)
        part.weights, part.m = _stride(self.weights, stride), _stride(self.m, stride)
        return part

    def solve(self, rhs: list[Tensor]) -> Tensor:
        """:math:`(A + \\lambda I)^{-1} b` per pixel for three right-hand sides (B, h, w) → (B, 3, h, w)."""
        i00, i01, i02, i11, i12, i22 = self.inverse
        r0, r1, r2 = (r.double() for r in rhs)
        return torch.stack([i00 * r0 + i01 * r1 + i02 * r2, i01 * r0 + i11 * r1 + i12 * r2,
                            i02 * r0 + i12 * r1 + i22 * r2], dim=1).to(self.dtype)

    def quadratic(self, vectors: Tensor) -> Tensor:
        """:math:`v^\\top (A + \\lambda I)^{-1} v` of vectors along dim -3 (..., 3, h, w) → (..., h, w)."""
        i00, i01, i02, i11, i12, i22 = (c.view(c.shape[0], *([1] * (vectors.dim() - 4)), *c.shape[1:])
                                        for c in self.inverse)
        x, y, z = (component.double() for component in vectors.unbind(-3))
        form = i00 * x.square() + i11 * y.square() + i22 * z.square() + 2 * (i01 * x * y + i02 * x * z + i12 * y * z)
        return form.to(self.dtype)


def _predict(m: Tensor, lights: Tensor) -> Tensor:
    """:math:`m \\cdot L_k` per light, :math:`(B, K, h, w)` (before the clamp at 0)."""
    return (lights * m.unsqueeze(1)).sum(2)


def _initial_fit(data: _Data, lights: Tensor, prior: Tensor) -> _Fit:
    """Least squares with every reading weighted by how clearly it is lit, :math:`I^2 / (I^2 + (0.1 I_{max})^2 +
    (3\\sigma)^2)`: shadows, penumbras and readings within the noise of zero barely count, so the robust steps start
    near the lit readings' solution (a pixel without any, near the prior, of the pixel's own brightness)."""
    images = data.images * data.valid
    variance = data.variance(images)
    floor = (_INIT_SHARE * images.amax(dim=1, keepdim=True)).square() + _LIT_SIGMAS**2 * variance
    lit = images.square() / (images.square() + floor + torch.finfo(images.dtype).tiny)
    return _Fit(lights, images, data.valid * lit / variance, prior)


def _robust_step(data: _Data, lights: Tensor, m: Tensor, prior: Tensor, penalty: _Penalty) -> _Fit:
    """One re-weighted Gauss–Newton step of the energy at fixed lights from ``m``: the penalty's weights of its
    residuals times :math:`\\lambda_k`, the :math:`\\max`'s Jacobian (readings predicted in attached shadow leave,
    smoothly: :data:`_HINGE_WIDTH`)."""
    predicted = _predict(m, lights)
    variance = data.variance(predicted)
    share = _lit(data, predicted, variance) * penalty.weight((data.images - predicted.clamp_min(0)).square() / variance)
    return _Fit(lights, data.images, share / variance, prior, share)


def _lit(data: _Data, predicted: Tensor, variance: Tensor) -> Tensor:
    """Each reading's weight before the penalty's: its reliability times the max's Jacobian (the chance it is lit)."""
    return data.reliability * torch.sigmoid(predicted / (_HINGE_WIDTH * variance.sqrt()))


def _fit_noise(data: _Data, lights: Tensor, fit: _Fit, penalty: _Penalty, rounds: int = 3) -> Tensor:
    r"""The noise model :math:`(\alpha, \beta, \gamma)` (B, 3, 1, 1) from the residuals of ``fit``.

    In the raw readings' units (divided by the gain :math:`s`), each reading's squared residual over :math:`1 - h_k`
    (its leverage) estimates :math:`\alpha + \beta\hat R + \gamma\hat R^2`, :math:`\hat R = \hat I / s`: read noise,
    shot noise and the model's relative error (:math:`\gamma` = :data:`_MODEL_ERROR`², fixed). :math:`\alpha, \beta
    \ge 0` come from their regression with inverse-variance weights, the penalty's weights (cast shadows and
    highlights do not count) and its consistency factor, started at their median (read noise alone). Readings in
    attached shadow measure :math:`\alpha`, but not one of exactly 0, clamped there by the dark subtraction (a
    shadow's others are the positive half of its noise, whose mean square is its variance). The model's accuracy at
    the readings' RMS level bounds :math:`\alpha` below."""
    predicted = _predict(fit.m, lights).clamp_min(0)
    counted = data.valid * (data.images > 0)
    gain = torch.where(counted > 0, data.gain, torch.ones_like(data.gain))
    leverage = (fit.weights * fit.quadratic(lights)).clamp(0, 0.99)
    target = torch.where(counted > 0, (data.images - predicted).square() / (1 - leverage) / gain.square(),
                         torch.zeros_like(predicted))
    level = predicted / gain
    model = _MODEL_ERROR**2 * level.square()
    floor = _MODEL_ERROR**2 * masked_mean(level.square(), counted) + torch.finfo(level.dtype).tiny
    alpha = torch.maximum(masked_median(target, counted > 0) / 0.4549, floor)  # 0.4549: χ²₁'s median
    beta = torch.zeros_like(floor)
    features = torch.stack([torch.ones_like(level), level], dim=1)
    for _ in range(rounds):
        variance = (alpha + beta * level + model).clamp_min(torch.finfo(level.dtype).tiny)
        weight = counted * penalty.weight(target / variance) / variance.square()
        weight = (weight / weight.amax(dim=(1, 2, 3), keepdim=True).clamp_min(torch.finfo(level.dtype).tiny))
        normal = torch.einsum("bikhw,bjkhw->bij", features * weight.unsqueeze(1), features)
        rhs = (features * (weight * (target / penalty.consistency - model)).unsqueeze(1)).sum(dim=(2, 3, 4))
        solution = non_negative_solve(normal, rhs)
        alpha, beta = solution[:, 0].view(-1, 1, 1, 1).clamp_min(floor), solution[:, 1].view(-1, 1, 1, 1)
    return torch.cat([alpha, beta, torch.full_like(alpha, _MODEL_ERROR**2)], dim=1)


def _normal_std(data: _Data, lights: Tensor, fit: _Fit, prior: Tensor, penalty: _Penalty) -> Tensor:
    r"""Predicted RMS angular error (degrees) of each normal from the noise, :math:`(B, 1, h, w)`: the fit's covariance
    :math:`C = c\,(A + \lambda I)^{-1}` (:math:`c` the penalty's covariance factor) across the normal,
    :math:`\sqrt{\operatorname{tr}((I - nn^\top) C (I - nn^\top))} / \rho`, at most 180°, where a reading predicted
    within a few noise levels of zero, not known to be lit (the :math:`\max` makes its constraint one-sided), counts by
    :math:`z^2 / (z^2 + 3^2)`, :math:`z` its prediction in noise levels (a pixel lit by two LEDs that leans on a dark
    reading is not well measured)."""
    predicted = _predict(fit.m, lights)
    snr_sq = predicted.clamp_min(0).square() / data.variance(predicted)
    information = _Fit(lights, data.images, fit.weights * snr_sq / (snr_sq + _LIT_SIGMAS**2), prior)
    albedo, normals = _split(fit.m)
    i00, _, _, i11, _, i22 = information.inverse
    across = (i00 + i11 + i22).to(normals.dtype) - information.quadratic(normals.unsqueeze(1))[:, 0]
    albedo = albedo.squeeze(1).clamp_min(torch.finfo(albedo.dtype).eps)
    radians = (across.clamp_min(0) * penalty.covariance_factor).sqrt() / albedo
    return (radians.unsqueeze(1) * (180 / math.pi)).clamp(max=180.0)


def _predicted_std(data: _Data, lights: Tensor, fit: _Fit, least_squares: Tensor, normal_std: Tensor,
                   penalty: _Penalty) -> Tensor:
    r"""The result's predicted RMS angular error (degrees), :math:`(B, 1, h, w)`: :func:`_normal_std` times the factors
    of the misfit and of the unexplained light, plus the rejections' part. The misfit's: least-squares adjustment's a
    posteriori variance factor, at least 1, over each pixel's :data:`_FILL_SIZE`² window: the weighted squared
    standardised residuals over what noise alone leaves, the penalty's consistency times the weights less their
    leverages, :math:`\sum_k s_k h_k = \operatorname{tr}(A^{-1} \sum_k s_k w_k L_k L_k^\top)`. The unexplained light's:
    the penalty rejected a share :math:`u` of the pixel's light above its prediction among readings taken as lit (a
    glint, a sheen); each kept reading taken to carry that share unexplained, independently, is noise of :math:`u I_k`
    beside its :math:`\sigma_k`, which adds :math:`u^2 \overline{(I_k/\sigma_k)^2}` (over the kept readings) to the
    factor. The rejections: a fit that rejects a share :math:`q` of the pixel's light (a glint, or the right readings)
    errs by :math:`d`, the angle to the lit readings' least squares, with chance :math:`q`."""
    assert fit.share is not None
    predicted = _predict(fit.m, lights)
    variance = data.variance(predicted)
    weighted, pairs = (fit.share * fit.weights).unsqueeze(2) * lights, ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    leverage = torch.stack([(2 - (i == j)) * c * (weighted[:, :, i] * lights[:, :, j]).sum(1).double()
                            for c, (i, j) in zip(fit.inverse, pairs, strict=True)]).sum(0)  # _Fit.inverse's order
    freedom = box_sum((fit.share.sum(1) - leverage.to(variance.dtype)).clamp_min(0).unsqueeze(1), _FILL_SIZE)
    residual_sq = (fit.share * (data.images - predicted.clamp_min(0)).square() / variance).sum(1, keepdim=True)
    misfit = (box_sum(residual_sq, _FILL_SIZE) / (freedom * penalty.consistency).clamp_min(1)).clamp_min(1)
    light, tiny = (data.images * data.valid).clamp_min(0), torch.finfo(variance.dtype).tiny
    total_light = light.sum(1, keepdim=True).clamp_min(tiny)
    rejected = ((1 - fit.share) * light).sum(1, keepdim=True) / total_light
    above = (_lit(data, predicted, variance) - fit.share).clamp_min(0) * (light - predicted.clamp_min(0)).clamp_min(0)
    snr_sq = (fit.weights * light.square()).sum(1, keepdim=True) / fit.share.sum(1, keepdim=True).clamp_min(tiny)
    unexplained = (above.sum(1, keepdim=True) / total_light).square() * snr_sq
    apart = angular_error_deg(_split(least_squares)[1], _split(fit.m)[1])
    total = normal_std.square() * (misfit + unexplained) + rejected * apart.square()
    return total.clamp_min(tiny).sqrt().clamp(max=180.0)


def _split(m: Tensor) -> tuple[Tensor, Tensor]:
    """Albedo :math:`|m|` and unit normal :math:`m / |m|` ((0, 0, 1) where :math:`m = 0`: no reading and no prior)."""
    albedo = vector_length(m, dim=1)
    return albedo, torch.where(albedo > torch.finfo(m.dtype).tiny, m / albedo, _up(albedo))


def _up(like: Tensor) -> Tensor:
    """The flat normal (0, 0, 1), :math:`(B, 3, h, w)` for ``like`` :math:`(B, 1, h, w)`."""
    return torch.cat([torch.zeros_like(like), torch.zeros_like(like), torch.ones_like(like)], dim=1)


# --- Depth: integration of the normals, the height, the tilt and the bend ---------------------------------------


def _integrate(steps: _Steps, normals: Tensor, normal_std: Tensor, domain: Tensor, pitch: float, method: str,
               warm: Tensor | None = None, one_sided: bool = False) -> Tensor:
    """Relative depth (mm, zero mean over ``domain``) of the normals: ``"masked"``, weighted least squares from
    ``warm`` (or the Neumann (DCT) solve); ``"fill"``, that Neumann solve alone; another method of
    :func:`psmini.integrate.integrate`, unweighted. Each slope weighs its inverse variance, relative to the typical
    pixel's and at most 1 (a flat facet is not worth a hundred walls). A normal the readings hardly decide (a crevice)
    or a slope they do not (a wall's normal near the horizontal) is blended into its neighbourhood's, so that it can
    never make a spike, and its neighbours weigh as little (a rim's normal sees the crevice's wall, which the next
    pixel's depth does not: the many crevices of a knit add up to a dome otherwise). An edge's slope is its pixels'
    mean, or with ``one_sided`` and ``warm`` mostly the slope of the pixel on whose side the warm depth runs smoother
    (Cao et al., "Bilateral normal integration", ECCV 2022): where two flanks meet (a crevice between yarns, a ridge)
    their mean is neither's, and the crevice comes out shallow. A filled slope, or its neighbour's, keeps the mean."""
    p, q, support, settled = steps.blended_slopes(normals, normal_std, domain)
    if method not in ("masked", "fill"):
        return integrate(p, q, method, pitch, domain)
    start = dct_poisson(p, q, pitch) if method == "fill" or warm is None else warm
    if method == "fill":
        return start
    forward_u = forward_v = torch.full_like(p, 0.5)
    if one_sided and warm is not None:
        forward_u, forward_v = _Grid(domain.to(p.dtype)).shares(warm / pitch, settled, _ONE_SIDED_K)
    wu, wv, tu, tv = _edge_system(p * pitch, -q * pitch, support + _WEIGHT_FLOOR, forward_u, forward_v)
    # a solve that is differentiated is solved to the dtype's precision: its implicit gradient is that of the exact
    # solution, so the one computed must be it
    tolerance = None if torch.is_grad_enabled() and wu.requires_grad else _CG_TOLERANCE
    return solve_weighted_poisson(wu, wv, tu, tv, domain.to(p.dtype), x0=start, tol=tolerance)


def _blended_slopes(normals: Tensor, normal_std: Tensor, domain: Tensor) -> tuple[Tensor, ...]:
    """:func:`_integrate`'s slopes p, q, each blended into its neighbourhood's as far as it is not decided, their
    weights and where the pixel and its neighbours are decided, each (B, 1, h, w)."""
    p, q = _slopes_of(normals)
    slope_variance = (normal_std * (math.pi / 180)).square() / normals[:, 2:3].clamp_min(0.05).pow(4)
    confidence = 1 / (slope_variance + _SLOPE_FLOOR**2)
    confidence = (confidence / masked_median(confidence, domain)).clamp(max=1) * domain
    decided = 1 / (1 + (normal_std / _FILL_ABOVE_DEG).pow(4) + slope_variance.square() / _FILL_SLOPE_STD**8)
    settled = -F.max_pool2d(-decided, 3, stride=1, padding=1)  # decided, and so are its eight neighbours
    support = confidence * settled
    local = box_sum(support, _FILL_SIZE).clamp_min(torch.finfo(p.dtype).tiny)
    p, q = (decided * g + (1 - decided) * box_sum(support * g, _FILL_SIZE) / local for g in (p, q))
    return p, q, support, settled


def _placed(relative: Tensor, basis: Tensor, theta: Tensor) -> Tensor:
    """``relative`` placed by ``theta`` (B, 6): plus its offset, tilt and bend over ``basis`` (:func:`_plane_basis`)."""
    return relative + (basis * theta[:, :, None, None]).sum(1, keepdim=True)


def _plane_basis(xy: Tensor, domain: Tensor) -> Tensor:
    """The placement's shapes, (B, 6, h, w): 1, the coordinates x, y (mm) centred on the domain, and the quadric's
    x²/2, xy, y²/2 of those, less their mean: the offset is the domain's mean height whatever the tilt and bend."""
    xy = xy.expand(domain.shape[0], -1, -1, -1)
    xy = xy - masked_mean(xy, domain, dim=(2, 3))
    x, y = xy.unbind(1)
    quadric = torch.stack([x.square() / 2, x * y, y.square() / 2], dim=1)
    return torch.cat([torch.ones_like(x[:, None]), xy, quadric - masked_mean(quadric, domain, dim=(2, 3))], dim=1)


def _energy(data: _Data, predicted: Tensor, penalty: _Penalty, domain: Tensor) -> Tensor:
    """The energy of each sample (B,) at the predicted readings (before their clamp at 0), over ``domain``."""
    residual_sq = (data.images - predicted.clamp_min(0)).square() / data.variance(predicted)
    return (penalty.value(residual_sq) * data.reliability * domain).sum(dim=(1, 2, 3), dtype=torch.float64)


def _line_minimum(energies: Tensor) -> Tensor:
    """The step's fraction in [0, 1] at the minimum of the parabola through the energies (B, 3) at 0, 1/2 and 1, the
    lower end where they curve down (Nocedal and Wright 2006, 3.5): continuous, where the least of three flipped."""
    first, half, full = energies.unbind(1)
    curvature = first - 2 * half + full
    fraction = (0.25 * (3 * first - 4 * half + full) / curvature.clamp_min(torch.finfo(first.dtype).tiny)).clamp(0, 1)
    return torch.where(curvature > 0, fraction, (full < first).to(fraction))


def _place(data: _Data, field: _LightField, relative: Tensor, m: Tensor, domain: Tensor, theta: Tensor, free: Tensor,
           penalty: _Penalty, steps: int, line_search: bool = True) -> Tensor:
    r"""Gauss–Newton steps of the energy in the placement ``theta`` (its entries that ``free`` names) on the grid of
    ``field`` (a stride of the image); returns the new ``theta``. The normals are projected out (variable projection,
    Golub and Pereyra 1973): the derivative of each prediction in the height, :math:`g_k = m \cdot \partial L_k /
    \partial z`, loses its part that a change of :math:`m` would absorb, :math:`g - L A^{-1} \sum_k w_k L_k g_k`, so
    the step follows the energy with the normals re-fitted at each height. The penalty is not convex: a step goes as
    far as the energies at its half and its end say (:func:`_line_minimum`; without ``line_search``, all of it, for a
    start in its basin), no pixel moving more than :data:`_MAX_STEP_MM`. The tilt and the bend then pass
    :data:`_TILT_SIGMAS`' soft test, their squared lengths in standard errors from the inverse Hessian's block."""
    if not bool(free.any()):
        return theta
    chosen, basis = free.to(relative.dtype), _plane_basis(field.xy, domain)
    features = basis * chosen[None, :, None, None]
    hessian = torch.eye(6, dtype=theta.dtype, device=theta.device).expand(theta.shape[0], 6, 6)
    for _ in range(steps):
        depth = _placed(relative, basis, theta)
        lights = field(depth)
        fit = data.steps.robust_step(data, lights, m, m, penalty)  # the normals at this height, one step from the last
        m = fit.m
        curvature, gradient, predicted = data.steps.height_terms(data, fit, lights, field(depth + _HEIGHT_STEP_MM),
                                                                 domain)
        hessian = torch.einsum("bihw,bjhw,bhw->bij", features, features, curvature) + torch.diag(1 - chosen)
        # a ridge of a rounding's size: far from the height every reading is an outlier and the curvature vanishes
        ridge = torch.finfo(theta.dtype).eps * hessian.diagonal(dim1=1, dim2=2).amax(1) + torch.finfo(theta.dtype).tiny
        step = torch.linalg.solve(hessian + ridge.view(-1, 1, 1) * torch.eye(6).to(theta),
                                  (features * gradient).sum(dim=(2, 3)))
        # a trust region: no pixel moves by more than half a millimetre in one step
        largest = ((basis * step[:, :, None, None]).sum(1, keepdim=True).abs() * domain).amax(dim=(1, 2, 3))
        step = step * (_MAX_STEP_MM / largest.clamp_min(_MAX_STEP_MM)).unsqueeze(1)
        if line_search:
            energies = [data.steps.energy(data, predicted, penalty, domain)]
            for fraction in (0.5, 1.0):
                trial_lights = field(_placed(relative, basis, theta + fraction * step))
                trial = data.steps.robust_step(data, trial_lights, m, m, penalty).m
                energies.append(data.steps.energy(data, _predict(trial, trial_lights), penalty, domain))
            step = step * _line_minimum(torch.stack(energies, dim=1)).to(step.dtype).unsqueeze(1)
        theta = theta + step
    covariance = torch.linalg.inv(hessian)
    for block in (slice(1, 3), slice(3, 6)):
        if bool(free[block].all()):
            shape = theta[:, block]
            q = shape.unsqueeze(1) @ torch.linalg.solve(covariance[:, block, block], shape.unsqueeze(2))
            clear = (q.view(-1, 1) / _TILT_SIGMAS**2).pow(4)
            theta = torch.cat([theta[:, :block.start], shape * clear / (1 + clear), theta[:, block.stop:]], dim=1)
    return theta


def _height_terms(data: _Data, fit: _Fit, lights: Tensor, raised: Tensor, domain: Tensor) -> tuple[Tensor, ...]:
    """Each pixel's curvature (B, h, w) and gradient (B, 1, h, w) of the energy in its height, the normals projected
    out, from the lights a forward difference ``raised`` above, and the predicted readings."""
    along = _predict(fit.m, (raised - lights) / _HEIGHT_STEP_MM)  # (B, K, h, w)
    across = along - _predict(fit.solve([(fit.weights * along * lights[:, :, j]).sum(1) for j in range(3)]), lights)
    predicted = _predict(fit.m, lights)
    residual = data.images - predicted.clamp_min(0)
    curvature = (fit.weights * across.square()).sum(1) * domain[:, 0]
    return curvature, (fit.weights * across * residual).sum(1, keepdim=True) * domain, predicted


def _scan_offset(data: _Data, field: _LightField, relative: Tensor, domain: Tensor, theta: Tensor,
                 search: tuple[float, float], penalty: _Penalty) -> Tensor:
    """The offset of least energy among heights in ``search`` (mm, around the current one; at most :data:`_SCAN_POINTS`,
    an eighth of a millimetre apart at least), each with its normals fitted afresh (the lit-weighted least squares and a
    robust step): the start of the Gauss–Newton steps, whose basin is narrower than the search."""
    points = min(_SCAN_POINTS, round((search[1] - search[0]) * 8) + 1)
    offsets = torch.linspace(*search, points, device=relative.device, dtype=relative.dtype)
    # every height at once, as a batch of each sample repeated for each height, with ``field``'s steps
    repeat, steps = functools.partial(torch.repeat_interleave, repeats=points, dim=0), field.steps
    trials = _Data(repeat(data.images), repeat(data.valid), repeat(data.gain) if len(data.gain) > 1 else data.gain,
                   repeat(data.noise), steps)
    shifted = (theta.unsqueeze(1) + F.pad(offsets.unsqueeze(1), (0, 5))).flatten(0, 1)
    lights = field(_placed(repeat(relative), repeat(_plane_basis(field.xy, domain)), shifted))
    prior = (trials.images * trials.valid).amax(dim=1, keepdim=True) * _up(repeat(relative))
    m = steps.robust_step(trials, lights, steps.initial_fit(trials, lights, prior).m, prior, penalty).m
    energies = steps.energy(trials, _predict(m, lights), penalty, repeat(domain)).view(-1, points)
    return theta + F.pad(offsets[energies.argmin(dim=1)].unsqueeze(1), (0, 5))


def near_light_energy(intensities: Tensor, light_model: nn.Module, result: Reconstruction, pixel_pitch_mm: float,
                      card_height_mm: float | None, noise_std: Tensor, valid: Tensor | None = None,
                      options: NearLightOptions | None = None) -> Tensor:
    r"""The energy near light minimises, per sample, at a reconstruction (:math:`\sum_k \lambda_k \psi(r_k)` over the
    valid readings): a self-calibration's loss, differentiable in every argument and the light model's parameters.

    Args:
        intensities: images :math:`(B, K, H, W)` (flat-fielded when ``card_height_mm`` is given).
        light_model: a :class:`~psmini.lights.LightModel`.
        result: the reconstruction whose ``depth`` (mm), ``albedo`` and unit ``normals`` are scored, each
            :math:`(B, \cdot, H, W)` (a :class:`NearLightResult` or any :class:`~psmini.result.Reconstruction`).
        pixel_pitch_mm: pixel size on the cloth, mm.
        card_height_mm: see :func:`near_light_vectors`.
        noise_std: the readings' noise levels :math:`\sigma_k`, broadcastable to :math:`(B, K, H, W)`. Hold them
            fixed while the lights change: re-fitted to each light model (``result.noise``), they grow with its
            misfit, and the energy then falls as the lights leave the truth.
        valid: readings to count, :math:`(B, K, H, W)`; all when omitted.
        options: the :class:`NearLightOptions` whose penalty to use; defaults when omitted.

    Returns:
        the energy of each sample, :math:`(B,)`.

    Raises:
        ShapeError: when the shapes do not agree.

    Example:
        >>> from psmini.lights import PointLights
        >>> lights = PointLights(torch.tensor([[10.0, 0, 10], [-10.0, 0, 10], [0, 10.0, 10]]))
        >>> up = torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1).expand(1, 3, 4, 4)
        >>> flat = torch.zeros(1, 1, 4, 4)
        >>> card = Reconstruction(flat + 0.5, up, flat, flat, flat, flat > -1)  # albedo 0.5 on the card plane
        >>> energy = near_light_energy(torch.full((1, 3, 4, 4), 0.5), lights, card, 0.025, 0.0, torch.tensor(0.01))
        >>> energy.shape, bool(energy < 1e-6)   # the images are exactly the model's: nothing left to penalise
        (torch.Size([1]), True)
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    for name, channels in (("depth", "1"), ("albedo", "1"), ("normals", "3")):
        check_shape(getattr(result, name), [str(sizes["B"]), channels, str(sizes["H"]), str(sizes["W"])], name)
    lights = near_light_vectors(light_model, result.depth, pixel_pitch_mm, card_height_mm)
    residual_sq = ((intensities - result.albedo * _predict(result.normals, lights).clamp_min(0)) / noise_std).square()
    reading = intensities.clamp_min(0).square()
    weight = reading / (reading + (_LIT_SIGMAS * noise_std).square() + torch.finfo(reading.dtype).tiny)
    weight = weight if valid is None else weight * valid.to(weight)
    return (_check_options(options).penalty_function().value(residual_sq) * weight).sum(dim=(1, 2, 3))


# --- The solver -------------------------------------------------------------------------------------------------


def _check_light_model(light_model: object) -> None:
    if not isinstance(light_model, LightModel):
        raise InputError("the near-light solver needs a psmini.lights.LightModel (its count, and forward(points) → "
                         f"unit directions and irradiance at the points), got {type(light_model).__name__}")


def _check_options(options: NearLightOptions | None) -> NearLightOptions:
    if options is not None and not isinstance(options, NearLightOptions):
        raise InputError(f"options must be a NearLightOptions, got {type(options).__name__}")
    return NearLightOptions() if options is None else options


def solve_near_light(intensities: Tensor, light_model: nn.Module, pixel_pitch_mm: float, card_height_mm: float | None,
                     valid: Tensor | None = None, mask: Tensor | None = None, options: NearLightOptions | None = None,
                     gain: Tensor | None = None) -> NearLightResult:
    r"""The near-light stage: images → albedo, normals, absolute depth and each normal's predicted error, by
    minimising the robust energy of the module's docstring.

    Differentiable with respect to the intensities and the light model's parameters through the whole solve. On the
    CPU a batch is solved in chunks of one 8 × 400 × 400 capture's size; each sample's alternations stop on their own
    test, so a sample gets the answer it gets alone up to the rounding of batched operations, which the energy's
    continuity keeps at rounding size.

    Args:
        intensities: flat-fielded images :math:`(B, K, H, W)` (divided by the card under the same LEDs and
            multiplied by its albedo), or dark-subtracted raw images when ``card_height_mm`` is ``None``.
        light_model: a :class:`~psmini.lights.LightModel` whose lights vary over the field (positions in mm, origin
            on the optical axis at the card plane): the solver calls nothing but ``light_model(points)``.
        pixel_pitch_mm: pixel size on the cloth, mm.
        card_height_mm: height of the card the images were divided by, mm; ``None`` for raw images (the height is
            then observable only through the inverse-square law).
        valid: readings to use at all, :math:`(B, K, H, W)` bool (the flat-field's validity: saturation, untrusted
            card); all when omitted.
        mask: pixels to solve and integrate, :math:`(B, 1, H, W)`; all when omitted.
        options: :class:`NearLightOptions`; defaults when omitted.
        gain: the flat-field's gain (:attr:`psmini.flatfield.FlatFieldResult.gain`), broadcastable to
            :math:`(B, K, H, W)`: the factor each raw reading was multiplied by, which scales its noise. ``None``:
            raw images (a gain of 1).

    Returns:
        :class:`NearLightResult`; ``depth`` is the absolute height above the card plane's origin, mm, ``mask`` the
        pixels whose normal the readings decide (error predicted from the noise under 30°), ``normal_std`` each
        normal's predicted RMS error, degrees (from the noise, the fit's misfit and the light it rejected).

    Raises:
        ShapeError: when the shapes do not match (K of the images vs the light model, mask, valid, gain).
        InputError: for NaN input, a sample without light, a negative gain, a model that is no
            :class:`~psmini.lights.LightModel`, bad options or a light below the card.

    Example:
        >>> from psmini.lights import LEDLights, ring_lights
        >>> ring = ring_lights(8, 58.0)
        >>> leds = LEDLights(ring * 18.6, -ring)
        >>> result = solve_near_light(torch.rand(1, 8, 16, 16) + 0.5, leds, 0.025, 0.0,
        ...                           options=NearLightOptions(max_iterations=2))
        >>> result.depth.shape, result.normal_std.shape
        (torch.Size([1, 1, 16, 16]), torch.Size([1, 1, 16, 16]))
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_finite(intensities, "intensities")
    check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    _check_light_model(light_model)
    if light_model.count != sizes["K"]:
        raise ShapeError(f"the light model has {light_model.count} lights but intensities has K={sizes['K']}")
    if card_height_mm is not None and not (isinstance(card_height_mm, (int, float)) and math.isfinite(card_height_mm)):
        raise InputError(f"card_height_mm must be a finite number or None, got {card_height_mm!r}")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    if valid is not None and (not isinstance(valid, Tensor) or valid.shape != intensities.shape):
        got = tuple(valid.shape) if isinstance(valid, Tensor) else type(valid).__name__
        raise ShapeError(f"valid must have the images' shape {tuple(intensities.shape)}, got {got}")
    valid = torch.ones_like(intensities, dtype=torch.bool) if valid is None else valid.bool()
    if not bool(((intensities > 0) & valid).flatten(1).any(1).all()):  # a noise model of 0 made NaN of everything
        raise InputError("a sample's readings are all <= 0 or not valid: no light to solve for (an all-dark capture?)")
    gain = _check_frame(gain, sizes["B"], sizes["K"], sizes["H"], sizes["W"], "gain")
    if gain is not None and bool((gain < 0).any()):
        raise InputError(f"gain must be >= 0 (the flat-field's factor per reading), got one of {float(gain.min()):.3g}")
    options = _check_options(options)
    parts = [_solve(intensities[part], valid[part], batch_part(mask, intensities, part, "mask"), light_model,
                    pixel_pitch_mm, card_height_mm, options, batch_part(gain, intensities, part, "gain"))
             for part in chunks(intensities)]
    return parts[0] if len(parts) == 1 else NearLightResult.concatenate(parts)


@dataclass
class _State:
    """What the alternations carry from one to the next, and from the coarse level to the fine one."""

    relative: Tensor  # the integrated depth, zero mean over the domain
    theta: Tensor  # the placement (B, 6): offset (mm), tilt (dz/dx, dz/dy) and bend (second derivatives, 1/mm)
    free: Tensor  # which of theta the images decide, (6,) bool
    basis: Tensor = dataclasses.field(init=False)  # theta's shapes on the level's grid, set by _alternate
    m: Tensor | None = None
    normal_std: Tensor | None = None
    weights: Tensor | None = None  # each reading's weight in [0, 1] in the last fit
    predicted_std: Tensor | None = None  # normal_std with the misfit, the unexplained light and the rejections
    iterations: int = 0
    changes: list[float] = dataclasses.field(default_factory=list)
    converged: bool = False


def _solve(images: Tensor, valid: Tensor, mask: Tensor | None, model: nn.Module, pitch: float,
           card_height: float | None, options: NearLightOptions, gain: Tensor | None) -> NearLightResult:
    """:func:`solve_near_light` on one chunk: alternations at half resolution, at full resolution, the final depth."""
    batch, _, height, width = images.shape
    domain = torch.ones_like(images[:, :1], dtype=torch.bool) if mask is None else mask.bool()
    gain = torch.ones_like(images[:1, :1, :1, :1]) if gain is None else gain.to(images)
    # a start of a thousandth of the raw readings' RMS, below any camera's noise: the first fit follows its readings,
    # whose residuals then give the noise model
    raw = images / gain.clamp_min(torch.finfo(images.dtype).tiny)
    alpha = (1e-6 * masked_mean(raw.square(), valid)).clamp_min(torch.finfo(images.dtype).tiny)
    data = _Data(images, valid.to(images.dtype), gain,
                 torch.cat([alpha, torch.zeros_like(alpha), torch.full_like(alpha, _MODEL_ERROR**2)], dim=1),
                 _Steps(options.compile, images.device))
    start = F.pad(torch.tensor([options.initial_height_mm], device=images.device, dtype=images.dtype), (0, 5))
    free = torch.tensor([options.estimate_offset] + [options.estimate_tilt] * 2 + [options.estimate_bend] * 3,
                        device=images.device)
    state = _State(torch.zeros_like(images[:, :1]), start.expand(batch, 6), free)
    scan = options.search_mm if options.estimate_offset else None
    if height % 2 == 0 and width % 2 == 0 and min(height, width) >= _MIN_COARSE_SIZE:
        small_domain = F.avg_pool2d(domain.to(images.dtype), 2) > 0.5
        small = _Data(F.avg_pool2d(images, 2), (F.avg_pool2d(data.valid, 2) > 0.999).to(images.dtype),
                      F.avg_pool2d(gain, 2) if gain.shape[-1] > 1 else gain, data.noise, data.steps)
        coarse = _State(F.avg_pool2d(state.relative, 2), state.theta, free)
        _alternate(small, small_domain, model, 2 * pitch, card_height, options, coarse, scan, _COARSE_ITERATIONS,
                   final=False)
        assert coarse.m is not None
        upsample = functools.partial(F.interpolate, size=(height, width), mode="bilinear", align_corners=False)
        state = _State(upsample(coarse.relative), coarse.theta, free, m=upsample(coarse.m),
                       iterations=coarse.iterations, changes=coarse.changes)
        scan = _FINE_SEARCH_MM if options.estimate_offset else None
    field = _alternate(data, domain, model, pitch, card_height, options, state, scan, options.max_iterations,
                       final=True)
    return _finish(data, field, state, domain, mask is None, pitch, options)


def _alternate(data: _Data, domain: Tensor, model: nn.Module, pitch: float, card_height: float | None,
               options: NearLightOptions, state: _State, scan: tuple[float, float] | None, iterations: int,
               final: bool) -> _LightField:
    """Alternations at one resolution, updating ``state`` and ``data``'s noise model; returns the level's light field.
    The coarse level's depth only places the lights (a full rectangle's Neumann solve, no tilt or bend). A sample whose
    normals moved less than the tolerance stops there; the last alternation at full resolution ends with its fit."""
    size = (data.images.shape[-2], data.images.shape[-1])
    stride = max(1, int((size[0] * size[1] / _PLACE_PIXELS) ** 0.5))
    steps = data.steps
    field = _LightField(model, size, pitch, card_height, data.images, steps)
    sub_field = _LightField(model, size, pitch, card_height, data.images, steps, stride)
    state.basis = _plane_basis(field.xy, domain)
    penalty = options.penalty_function()
    cauchy = _Penalty("cauchy", penalty.scale)
    free = state.free & torch.tensor([True] + [final] * 5, device=domain.device)
    method = "masked" if final or not bool(domain.all()) else "fill"
    done = torch.zeros(data.images.shape[0], dtype=torch.bool, device=data.images.device)
    before: Tensor | None = None
    for iteration in range(iterations):
        state.iterations += 1
        depth = _placed(state.relative, state.basis, state.theta)
        lights = field(depth)
        # every alternation starts afresh from the lit readings (a fit remembers no rejection made at other lights),
        # with the current surface's normal as the prior (at first the coarse level's, or the flat surface's)
        if state.m is None:
            prior = (data.images * data.valid).amax(dim=1, keepdim=True) * _up(state.relative)
        else:
            prior = vector_length(state.m, dim=1) * normals_from_height(depth, pitch)
        sample_lights = _stride(lights, _NOISE_STRIDE)
        if state.weights is None:  # the level's first fit: a noise model from the lit readings' least squares
            sample = data.every(_NOISE_STRIDE)
            first = steps.initial_fit(sample, sample_lights, _stride(prior, _NOISE_STRIDE))
            data.set_noise(steps.fit_noise(sample, sample_lights, first, penalty, 6))
        # first a step of Cauchy's penalty: it pulls the fit back from a glint the least squares followed (graduated
        # non-convexity, Blake and Zisserman 1987), before Welsch's steps reject it
        least_squares = steps.initial_fit(data, lights, prior).m
        m = steps.robust_step(data, lights, least_squares, prior, cauchy).m
        for _ in range(options.irls_steps):
            fit = steps.robust_step(data, lights, m, prior, penalty)
            m = fit.m
        data.set_noise(steps.fit_noise(data.every(_NOISE_STRIDE), sample_lights, fit.every(_NOISE_STRIDE), penalty, 2))
        normal_std = steps.normal_std(data, lights, fit, prior, penalty)
        normals = _split(m)[1]
        converging = torch.zeros_like(done)
        if before is not None:  # the mean angle between the normals and the last alternation's, degrees
            change = masked_mean(angular_error_deg(normals, before), domain).view(-1)
            state.changes.append(float(change.detach().max()))
            logger.info("near-light alternation %d at %d x %d: normals moved %.2e deg on average",
                        state.iterations, *size, state.changes[-1])
            converging = ~done & (change < options.tolerance_deg)
        before = normals
        # the samples done in an earlier alternation keep its state; this one is the last of those converging now
        state.m, state.normal_std = _keep(done, state.m, m), _keep(done, state.normal_std, normal_std)
        state.weights = _keep(done, state.weights, fit.share if fit.share is not None else fit.weights)
        if final and (iteration == iterations - 1 or bool(converging.any())):  # the result's (only it needs them)
            state.predicted_std = _keep(done, state.predicted_std,
                                        steps.predicted_std(data, lights, fit, least_squares, normal_std, penalty))
        done = done | converging
        state.converged = bool(done.all())
        if state.converged or final and 0 < iteration == iterations - 1:
            break
        warm = state.relative if iteration else None
        relative = _integrate(steps, normals, normal_std, domain, pitch, method, warm)
        theta = state.theta
        if scan is not None and iteration == 0:  # on a quarter of the placement's pixels: only a start
            every = max(1, int((size[0] * size[1] / _PLACE_PIXELS * 4) ** 0.5))
            # eagerly: the scan's batch of 13 would be another compiled graph of every step, for a start
            coarse_field = _LightField(model, size, pitch, card_height, data.images, _Steps(False, domain.device),
                                       every)
            theta = _scan_offset(data.every(every), coarse_field, _stride(relative, every), _stride(domain, every),
                                 theta, scan, penalty)
        theta = _place(data.every(stride), sub_field, _stride(relative, stride), _stride(m, stride),
                       _stride(domain, stride), theta, free, penalty, steps=2 if iteration == 0 else 1)
        state.relative, state.theta = _keep(done, state.relative, relative), _keep(done, state.theta, theta)
    return field


def _stride(x: Tensor, stride: int) -> Tensor:
    return x[..., ::stride, ::stride].contiguous()


def _keep(done: Tensor, old: Tensor | None, new: Tensor) -> Tensor:
    """``new``, except for the samples that are ``done``, which keep ``old``."""
    return new if old is None or not bool(done.any()) else torch.where(done.view(-1, *[1] * (new.dim() - 1)), old, new)


def _finish(data: _Data, field: _LightField, state: _State, domain: Tensor, full: bool, pitch: float,
            options: NearLightOptions) -> NearLightResult:
    """The final depth and the result: the last normals integrated by ``options.integrator`` and placed by one
    Gauss–Newton step on every pixel (on a sixteenth of them a knit's or a net's bend does not stand clear of its
    noise), without a line search (in the step's basin a half step is a bias): the guide's step 3."""
    assert state.m is not None and state.normal_std is not None and state.weights is not None
    assert state.predicted_std is not None
    albedo, normals = _split(state.m)
    relative = _integrate(data.steps, normals, state.normal_std, domain, pitch, options.integrator, state.relative,
                          one_sided=True)
    if options.integrator == "masked" and full:
        # the edges' trapezoidal rule flattens the finest relief (a silk's threads to a third): undone on the rectangle
        relative = _undo_edge_averaging(relative)
    theta = _place(data, field, relative, state.m, domain, state.theta, state.free, options.penalty_function(), 1,
                   line_search=False)
    depth = _placed(relative, state.basis, theta)
    inside = domain.to(albedo.dtype)
    normals = torch.where(domain, normals, _up(albedo))
    p, q = _slopes_of(normals)
    return NearLightResult(albedo * inside, normals, p, q, depth, domain & (state.normal_std < _SOLVED_BELOW_DEG),
                           normal_std=state.predicted_std, weights=state.weights * inside, noise=data.noise.view(-1, 3),
                           offset_mm=masked_mean(depth, domain).view(-1), tilt=theta[:, 1:3], bend=theta[:, 3:],
                           iterations=state.iterations, changes_deg=tuple(state.changes), converged=state.converged)
