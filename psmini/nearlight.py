r"""Near-light photometric stereo: per-pixel LED lighting that depends on the surface it lights.

At the rig's geometry (LEDs about 10 mm above a 10 mm field) the distant-light assumption is badly wrong: the
direction and the irradiance of each LED change across the field and with the height of the cloth. With a light
model of :mod:`psmini.lights` (points or LEDs, Quéau et al., JMIV 2018) the light vector at a surface point
:math:`x` is :math:`L_k(x) = E_k(x)\,l_k(x)` and a Lambertian pixel reads :math:`I_k = \rho\,\max(n \cdot L_k, 0)`.
The lights depend on the unknown depth, so the solver alternates (Quéau et al. 2018, Section 4; Logothetis et al.
2017 use the same fixed point): lights at the current depth → per-pixel least-squares normals → integrated depth.

Flat-fielded images (divided by the card image under the same LED, see :mod:`psmini.flatfield`) are supported
exactly: the card at height :math:`h_c` reads :math:`\rho_c E_k(x_c)\,(e_z \cdot l_k(x_c))`, so a flat-fielded pixel
reads :math:`\rho\,n \cdot L_k(x) / (E_k(x_c)\,l_{k,z}(x_c))`, with :math:`x_c` the point of the card seen by the same
pixel. The camera's gain and vignetting cancel, and so do the LEDs' intensities; what remains is the geometry.

The absolute height of the cloth is observable because the light field is not uniform: the per-pixel least-squares
residual is zero only at the true height (noise-free, Lambertian). The solver finds the height offset by a scan of that
residual on a coarse pixel grid in the first alternation, then refines it by parabolic (Newton) steps in later ones, a
few batched evaluations of the light model on every fourth pixel. With a card it is sharp (about a micrometre on
noise-free renders of the rig); on raw images the height shows only through the inverse-square law's variation across
the field and is found to tens of micrometres.

Near light is a stage of the pipeline (:func:`solve_near_light`): it takes images that are already flat-fielded
(:func:`psmini.flatfield.flatfield`) with their validity, and returns albedo, normals, depth and the solved mask.
Its options travel as one frozen :class:`NearLightOptions`.

Two departures from plain least squares keep textiles within the Lambertian model's reach. Metallic threads add a
specular lobe that only brightens, and a yarn's cast shadow only darkens: each pixel's brightest and darkest
observations are tested against the fit of the others (leave-one-out residuals, from the hat matrix), and the one
farther from it in noise levels leaves when beyond its threshold, one observation per update; the noise model
follows the flat-field's gain, which amplifies the camera's noise where an LED lights the card dimly. Crevices
lit by fewer than three LEDs stay unsolved; the pixels on their rims, whose normals see the crevice's wall, get
little weight in the integration (the many crevices of a knit would otherwise add up to a dome), and the unsolved
pixels themselves are filled smoothly from their rims, so they can never stand out as depth spikes.

A second, joint refinement (:func:`refine_depth`) minimises a robust (Huber) re-rendering loss over the depth
map by gradient descent, coarse to fine, with the albedo solved in closed form at each step.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import logging
import math
import threading
import weakref
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import check_finite, check_mask, check_positive, check_shape
from psmini._chunks import batch_part, chunks
from psmini.errors import InputError, ShapeError
from psmini.flatfield import _check_frame, _data_of
from psmini.geometry import pixel_grid_mm
from psmini.integrate import METHODS as INTEGRATORS
from psmini.integrate import dct_poisson, integrate
from psmini.integrate.least_squares import _edge_system, _undo_edge_averaging
from psmini.integrate.poisson import solve_weighted_poisson
from psmini.lights import LEDLights, PointLights
from psmini.normals import _COLS, _ROWS, _symmetric_adjugate, _unit_and_length, normals_to_gradients
from psmini.render import normals_from_height
from psmini.result import Reconstruction

__all__ = [
    "NearLightOptions",
    "NearLightResult",
    "RefineOptions",
    "near_light_vectors",
    "robust_near_light_normals",
    "estimate_height_offset",
    "solve_near_light",
    "refine_depth",
]

logger = logging.getLogger(__name__)

# Light vectors within this cosine of the tangent plane count as attached shadows (grazing light).
_GRAZING_COSINE = 0.02
# Stride of the pixel grid on which the height offset is searched (the residual is smooth across pixels).
_OFFSET_STRIDE = 4
# Offsets tried by the first, coarse scan of the height offset, over the search interval.
_SCAN_POINTS = 25
# The scan reads every _SCAN_STRIDE-th pixel of the search's grid in each direction: it only picks the start of the
# parabolic steps, which read the whole grid (a 100 x 100 grid's scan took 38 of a 0.8 s solve).
_SCAN_STRIDE = 2
# Half-width (mm) of the first parabolic step that refines the offset in later alternations.
_NEWTON_STEP_MM = 0.1
# ... and the width (mm) at which a search stops refining.
_OFFSET_TOLERANCE_MM = 1e-3
# Most parabolic steps of one search (a cost without a minimum, e.g. images that do not depend on the height,
# would otherwise walk downhill for ever).
_MAX_OFFSET_STEPS = 12
# Observations whose leave-one-out residual exceeds this many noise levels are highlights, when the noise makes
# that larger than ``highlight_fraction``.
_HIGHLIGHT_SIGMAS = 4.0
# ... in the rounds before the noise model (whose noise level is cruder): only gross glints.
_FIRST_HIGHLIGHT_SIGMAS = 8.0
# A pixel is tested for a highlight only with at least this many observations: the fit of the others then stays
# overdetermined (an exactly determined fit of three turns noise into false highlights where light is scarce).
_HIGHLIGHT_MIN_OBS = 5
# The read noise is estimated from observations in attached shadows, those beyond this many of its noise levels
# left out (they are lit), in at most this many rounds.
_NOISE_CLIP_SIGMAS = 4.0
_NOISE_CLIP_ROUNDS = 10
# Observations within this many zero-signal noise levels of zero are shadows, not light.
_SHADOW_SIGMAS = 3.5
# Observations near zero within this many noise levels of a prediction near zero are used (grazing light).
_GRAZING_SIGMAS = 3.0
_GRAZING_LOW = 1.0
# Residuals within this many noise levels are never outliers.
_OUTLIER_SIGMAS = 6.0
# Pixels next to an unsolved one get this confidence in the integration (see solve_near_light).
_EDGE_CONFIDENCE = 0.01
# Images at least this large (and of even size) run their first alternations at half resolution.
_MIN_COARSE_SIZE = 32
# Interval (mm) scanned around the half-resolution offset by the first full-resolution alternation.
_FINE_SEARCH_MM = (-0.5, 0.5)
# ... with this many offsets (0.125 mm apart) before the parabolic steps.
_FINE_SCAN_POINTS = 9
# Updates of the observations' selection in one alternation at full resolution (after three highlight rounds);
# later alternations keep it.
_SELECTION_UPDATES = 2
_FINE_HIGHLIGHT_ROUNDS = 1
# The half-resolution alternations stop at this many times the tolerance (their depth only places the lights).
_COARSE_TOLERANCE_FACTOR = 10.0
# Relative residual at which the final integration stops. It starts from the Neumann solve of the same filled
# slopes, which is right at high frequencies: the weighted solve corrects the long waves, within a few micrometres
# of its converged depth at 1% (about ten iterations; the slopes' noise makes tens of micrometres).
_FINAL_CG_TOLERANCE = 1e-2
# Least weight of a slope in the final integration: unconfident and unsolved pixels keep their filled slope (the
# confidence-weighted mean around them) at this weight, so no region of the mask floats on its own and the
# conjugate gradients meet a weight range of 100 rather than 1000 (knit and net: depth within 30 µm, not 100).
_CONFIDENCE_FLOOR = 1e-2
# Slopes are replaced by that filled slope when their confidence is below this (a variance ten times the median)...
_FILL_BELOW = 0.1
# ... and their standard deviation (from the images' noise model) exceeds this, in slope units (about a degree):
# exact slopes (noise-free renders) are never replaced, however few lights determine them.
_SLOPE_NOISE = 0.02
# Pixels fitted to exactly three observations get this share of their confidence (nothing checks their fit).
_THREE_OBSERVATIONS_CONFIDENCE = 0.1
# Side (pixels) of the window from which unconfident slopes are filled.
_FILL_SIZE = 9
# Step (mm) of the forward difference of each pixel's residuals in its height, for the tilt's Gauss-Newton step.
_TILT_STEP_MM = 0.02
# The tilt's standard error is read from the spread of its estimates on _TILT_PHASES² interleaved pixel lattices
# (every _TILT_PHASES-th pixel in each direction from each phase): their noise is independent.
_TILT_PHASES = 4
# Stride of the pixel grid on which the tilt is estimated (half the standard error of the offset's stride).
_TILT_STRIDE = 2
# A slope of the tilt is kept only where it stands this many standard errors clear of zero (a two-sided test at
# 0.3%).
_TILT_SIGMAS = 3.0


@dataclass(frozen=True)
class NearLightOptions:
    """Options of the near-light solver (:func:`solve_near_light`); the defaults are what
    ``benchmarks/nearlight.py`` measures.

    Attributes:
        max_iterations: most alternations (lights → normals → depth).
        tolerance_deg: the solver stops when ``change_percentile`` of the solved pixels' normals moved less than
            this since the previous alternation, degrees (the depth is then consistent with its normals).
        change_percentile: the share of solved pixels whose normal change must fall below ``tolerance_deg``: a few
            oscillating pixels (rims of crevices) cannot hold the iteration hostage.
        estimate_offset: find the absolute height from the images (the light field is not uniform); otherwise
            the mean height stays ``initial_height_mm``.
        estimate_tilt: find the plane of the height from the images as well (the same cue as the offset):
            integration cannot see a step, and where a surface steps down the same way again and again (a purl's
            courses, a knit's loops) the lost steps add up to a tilt, 20 µm/mm on the benchmark's purl. A slope
            is kept only where it stands three standard errors clear of zero (the error read from the spread of the
            estimate over interleaved lattices of pixels); otherwise, and without ``estimate_tilt``, the integrated
            plane stays.
        initial_height_mm: starting height of the cloth above the card plane's origin, mm (kept as the mean
            height without ``estimate_offset``).
        search_mm: interval of height offsets scanned in the first alternation, mm, around ``initial_height_mm``.
        shadow_fraction: observations darker than this fraction of the pixel's brightest are shadows (raised to
            three noise levels on noisy images, at most 0.1).
        highlight_fraction: excess of an observation over the fit of the others, relative to the pixel's scale,
            above which the brightest is a highlight (or four noise levels when larger); ``None`` keeps every
            observation (purely Lambertian cloth).
        outlier_fraction: shortfall of the darkest observation below the fit of the others, relative to the
            pixel's scale, above which it is a cast shadow missed by the shadow test (or six noise levels when
            larger).
        integrator: the final integration: ``"masked"`` (the default: unconfident slopes filled from their
            surroundings, then weighted least squares on the mask, slopes weighted by their inverse variance, by
            conjugate gradients warm-started from the fill's depth; without a mask, the finest relief that the
            edge equations' trapezoidal rule flattens is then restored: a silk's 2.4-pixel threads from a third of
            their height), ``"fill"`` (the filled slopes by a Neumann
            DCT solve alone: faster, depth errors about twice as large on the benchmark's jute) or another
            method of :func:`psmini.integrate.integrate` (unweighted, on the solved pixels). The alternations always
            use ``"fill"``.

    Raises:
        InputError: for values out of range.

    Example:
        >>> NearLightOptions(max_iterations=3).to_dict()["max_iterations"]
        3
    """

    max_iterations: int = 8
    tolerance_deg: float = 0.02
    change_percentile: float = 0.99
    estimate_offset: bool = True
    estimate_tilt: bool = True
    initial_height_mm: float = 0.0
    search_mm: tuple[float, float] = (-3.0, 3.0)
    shadow_fraction: float = 0.02
    highlight_fraction: float | None = 0.02
    outlier_fraction: float = 0.15
    integrator: str = "masked"

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> InputError:
            return InputError(f"NearLightOptions.{name} must be {expected}, got {getattr(self, name)!r}")

        if not (isinstance(self.max_iterations, int) and not isinstance(self.max_iterations, bool)
                and self.max_iterations >= 1):
            raise bad("max_iterations", "an integer >= 1")
        if not (isinstance(self.tolerance_deg, (int, float)) and 0 < self.tolerance_deg < math.inf):
            raise bad("tolerance_deg", "a positive number")
        if not (isinstance(self.change_percentile, (int, float)) and 0 < self.change_percentile <= 1):
            raise bad("change_percentile", "in (0, 1]")
        if not isinstance(self.estimate_offset, bool):
            raise bad("estimate_offset", "a bool")
        if not isinstance(self.estimate_tilt, bool):
            raise bad("estimate_tilt", "a bool")
        if not (isinstance(self.initial_height_mm, (int, float)) and math.isfinite(self.initial_height_mm)):
            raise bad("initial_height_mm", "a finite number")
        search = self.search_mm
        if not (isinstance(search, (tuple, list)) and len(search) == 2
                and all(isinstance(s, (int, float)) and math.isfinite(s) for s in search) and search[0] < search[1]):
            raise bad("search_mm", "an increasing pair of finite numbers")
        object.__setattr__(self, "search_mm", (float(search[0]), float(search[1])))
        if not (isinstance(self.shadow_fraction, (int, float)) and 0 <= self.shadow_fraction < 1):
            raise bad("shadow_fraction", "in [0, 1)")
        if self.highlight_fraction is not None and not (
                isinstance(self.highlight_fraction, (int, float)) and self.highlight_fraction > 0):
            raise bad("highlight_fraction", "a positive number or None")
        if not (isinstance(self.outlier_fraction, (int, float)) and self.outlier_fraction > 0):
            raise bad("outlier_fraction", "a positive number")
        if self.integrator != "fill" and self.integrator not in INTEGRATORS:
            raise bad("integrator", f"'fill' or one of {', '.join(sorted(INTEGRATORS))}")

    def to_dict(self) -> dict:
        """The options as a JSON-serialisable dict (``NearLightOptions(**d)`` rebuilds them)."""
        values = dataclasses.asdict(self)
        values["search_mm"] = list(self.search_mm)
        return values

    def replace(self, **changes) -> NearLightOptions:
        """A copy with some fields changed (validated again).

        Raises:
            InputError: for a name that is no option, or a value out of range.
        """
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise InputError(f"unknown near-light options {sorted(unknown)}; expected some of "
                             f"{[f.name for f in dataclasses.fields(self)]}")
        return dataclasses.replace(self, **changes)


@dataclass
class NearLightResult(Reconstruction):
    """A :class:`~psmini.result.Reconstruction` with the near-light solver's diagnostics.

    Attributes:
        weights: observations used in the last solve, :math:`(B, K, H, W)` bool (False: shadow, outlier, invalid).
        offset_mm: mean height of the cloth above the card plane, :math:`(B,)`, mm.
        tilt: the plane added to the integrated height, :math:`(B, 2)`: its slopes dz/dx and dz/dy (mm per mm,
            x right, y up; 0 without ``estimate_tilt``).
        iterations: alternations run, at both resolutions (the first ones run on 2 × 2-averaged images).
        changes_deg: the ``change_percentile`` quantile of the normals' change of each alternation after the first
            at each resolution (over the batch, the largest), degrees.
        converged: whether the change fell below the tolerance before ``max_iterations``.
        at_noise_floor: solved pixels fitted to exactly three observations of which one reads below the shadow
            level (3.5 read-noise levels), :math:`(B, 1, H, W)` bool: with no fourth observation to check it,
            nothing tells a grazing light from a shadow there, and the normal is as likely wrong as right (on the
            simulator's net, knit and jute, 1-12% of the field, 35-57° off on average against 1-5° for the other
            solved pixels; within a few degrees where that reading is a grazing light). Mask them out where a
            normal must be trusted.
    """

    weights: Tensor | None = None
    offset_mm: Tensor | None = None
    tilt: Tensor | None = None
    iterations: int = 0
    changes_deg: tuple[float, ...] = ()
    converged: bool = False
    at_noise_floor: Tensor | None = None

    @classmethod
    def concatenate(cls, parts: list[NearLightResult]) -> NearLightResult:
        """One result from those of consecutive chunks of a batch: tensors concatenated, the alternations' counts
        and changes the largest over the chunks, converged when every chunk converged."""
        tensors = {name: torch.cat([getattr(part, name) for part in parts])
                   for name in ("albedo", "normals", "p", "q", "depth", "mask", "weights", "offset_mm", "tilt")}
        floors = [part.at_noise_floor for part in parts if part.at_noise_floor is not None]
        at_noise_floor = torch.cat(floors) if len(floors) == len(parts) else None
        longest = max(len(part.changes_deg) for part in parts)
        changes = tuple(max(part.changes_deg[i] for part in parts if i < len(part.changes_deg))
                        for i in range(longest))
        return cls(**tensors, at_noise_floor=at_noise_floor, iterations=max(part.iterations for part in parts),
                   changes_deg=changes, converged=all(part.converged for part in parts))


# ----------------------------------------------------------------------------------------------------------------
# Light field: per-pixel light vectors at a height map, the depth-independent parts computed once
# ----------------------------------------------------------------------------------------------------------------


class _LightField:
    """Light vectors of a light model on the pixel grid, as three (B, K, H, W) components and their length.

    For point and LED models the parts that do not depend on the height (the in-plane offsets to each light, their
    squared length, the LED axis' in-plane product, the card's irradiance for flat-fielded images) are computed
    once; each evaluation is then a handful of element-wise operations (one fused pass, no norms over a
    component dimension). Other models go through their ``forward``. Differentiable in the height and in the
    light model's parameters.
    """

    def __init__(self, model: nn.Module, height: int, width: int, pitch: float, card_height: float | None,
                 like: Tensor, stride: int = 1) -> None:
        self.model, self.pitch, self.stride = model, pitch, stride
        x, y = pixel_grid_mm(height, width, pitch, device=like.device, dtype=like.dtype)
        x, y = x[::stride, ::stride], y[::stride, ::stride]
        self.x, self.y = x, y  # mm, x right and y up (the plane of the tilt)
        self.shape = x.shape
        self.fast = isinstance(model, PointLights)
        if isinstance(model, PointLights):
            positions = model.positions_mm.to(like)
            self.ox = positions[:, 0, None, None] - x  # (K, h, w)
            self.oy = positions[:, 1, None, None] - y
            self.pz = positions[:, 2, None, None]
            self.rxy2 = self.ox.square() + self.oy.square()
            self.phi = model.intensities.to(like)[:, None, None]
            self.led = isinstance(model, LEDLights)
            if isinstance(model, LEDLights):
                axis = model.principal_directions.to(like)
                axis = axis / axis.norm(dim=-1, keepdim=True)
                self.axy = self.ox * axis[:, 0, None, None] + self.oy * axis[:, 1, None, None]
                self.az = axis[:, 2, None, None]
                self.mu = model.mu.to(like)[:, None, None]
                # (a learnable mu of 1 still needs the power: its derivative, cos^mu ln cos, is not 0)
                self.unit_mu = not self.mu.requires_grad and bool((self.mu.detach() == 1).all())
        else:
            self.points_xy = torch.stack([x, y])[None]
        self.card_scale = None
        if card_height is not None:
            card = torch.full((1, 1, *self.shape), float(card_height), device=like.device, dtype=like.dtype)
            lx, ly, lz, _ = self._raw(card)
            if bool((lz.detach() <= 0).any()):
                raise InputError("flat-fielding needs every light above the card plane at every pixel")
            # the card reads E_k l_kz: flat-fielded vectors are L_k / (E_k(x_c) l_kz(x_c)), with l_kz = lz / E_k
            self.card_scale = 1 / lz[0]

    def _raw(self, depth: Tensor, factor: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Vectors (x, y, z components) and their lengths, each (B, K, h, w), times ``factor`` (the card's
        scale) when given."""
        if not self.fast:
            points = torch.cat([self.points_xy.expand(depth.shape[0], -1, -1, -1), depth], dim=1)
            directions, irradiance = self.model(points)
            vectors = directions * irradiance
            lx, ly, lz = vectors.unbind(dim=2)
            length = irradiance[:, :, 0]
            return (lx, ly, lz, length) if factor is None else (lx * factor, ly * factor, lz * factor,
                                                                 length * factor)
        # each operation is a pass over (B, K, h, w): fused multiply-adds where two would do, and the card's scale
        # applied once, to the length, before it scales the three offsets
        # (fresh results updated in place where autograd keeps no copy of them: the same values, fewer buffers)
        oz = self.pz - depth  # (B, K, h, w) by broadcasting (B, 1, h, w)
        inverse = torch.addcmul(self.rxy2, oz, oz).rsqrt_()
        length = inverse.square().mul_(self.phi)  # irradiance φ / r²
        if self.led:
            cosine = (torch.addcmul(self.axy, oz, self.az) * inverse).neg_().clamp_min_(torch.finfo(oz.dtype).tiny)
            length = length.mul_(cosine if self.unit_mu else cosine.pow(self.mu))
        if factor is not None:
            length = length.mul_(factor)
        scale = length * inverse  # irradiance / r: the offsets become unit directions times irradiance
        # (oz is kept for the backward of its products above, when one is recorded)
        z = oz * scale if torch.is_grad_enabled() else oz.mul_(scale)
        return self.ox * scale, self.oy * scale, z, length

    def every(self, n: int) -> _LightField:
        """The same field on every ``n``-th pixel of its grid in each direction (views of its terms)."""
        if n == 1:
            return self
        part = copy.copy(self)
        for name, value in vars(self).items():
            if isinstance(value, Tensor) and value.dim() >= 2 and tuple(value.shape[-2:]) == tuple(self.shape):
                setattr(part, name, value[..., ::n, ::n])
        part.shape, part.stride = part.x.shape, self.stride * n
        return part

    def nbytes(self) -> int:
        """Bytes of the tensors this field holds."""
        return sum(value.nbytes for value in vars(self).values() if isinstance(value, Tensor))

    def __call__(self, depth: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self._raw(depth, self.card_scale)


#: Bytes of light fields kept for the next solves (:func:`_light_field`): a 400 x 400 rig's fields at both levels
#: take about 42 MB; larger images' fields are built afresh.
_KEPT_FIELD_BYTES = 64 * 2**20
_kept_fields: collections.OrderedDict[tuple, _LightField] = collections.OrderedDict()
# guards the kept fields and gains (solves in several threads; re-entrant: freeing a kept gain runs the weak
# reference callback of what was derived from it); what is kept is computed outside it
_kept_lock = threading.RLock()


def _light_field(model: nn.Module, height: int, width: int, pitch: float, card_height: float | None, like: Tensor,
                 stride: int = 1) -> _LightField:
    """:class:`_LightField` ``(model, height, width, pitch, card_height, like, stride)``, kept for the next solves
    with the same values of a point or LED model, grid, card height, dtype and device.

    Its terms that do not depend on the height (the offsets to each LED, their squared lengths, the LEDs' axes, the
    card's irradiance) took 19 ms of a 0.8 s solve of one 8 x 400 x 400 capture, in every solve. The model's values
    decide, not the object: a batch run builds a model for each group of samples. A model that needs a gradient,
    or that is not a point or LED model (whose field evaluates the model itself), is not kept; the kept fields are
    the most recently used, within :data:`_KEPT_FIELD_BYTES`.
    """
    if not isinstance(model, PointLights) or _needs_gradient(model):
        return _LightField(model, height, width, pitch, card_height, like, stride)
    values = tuple((name, tuple(value.shape), value.dtype, value.detach().cpu().numpy().tobytes())
                   for name, value in _model_tensors(model))
    key = (type(model), values, height, width, float(pitch), card_height, stride, like.dtype, like.device)
    with _kept_lock:
        field = _kept_fields.get(key)
        if field is not None:
            _kept_fields.move_to_end(key)
            return field
    field = _LightField(model, height, width, pitch, card_height, like, stride)
    if field.nbytes() <= _KEPT_FIELD_BYTES:
        with _kept_lock:
            _kept_fields[key] = field
            while sum(kept.nbytes() for kept in _kept_fields.values()) > _KEPT_FIELD_BYTES:
                _kept_fields.popitem(last=False)
    return field


def _model_tensors(model: nn.Module) -> list[tuple[str, Tensor]]:
    """A light model's tensors by name: its parameters, buffers and tensor attributes (a model that is not
    learnable keeps its tensors as plain attributes)."""
    attributes = sorted((name, value) for name, value in vars(model).items() if isinstance(value, Tensor))
    return attributes + list(model.named_buffers()) + list(model.named_parameters())


def _needs_gradient(model: nn.Module) -> bool:
    """Whether any of a light model's tensors (:func:`_model_tensors`) needs a gradient."""
    return any(value.requires_grad for _, value in _model_tensors(model))


def near_light_vectors(
    light_model: nn.Module, depth: Tensor, pixel_pitch_mm: float, card_height_mm: float | None = None
) -> Tensor:
    r"""Per-pixel light vectors :math:`L_k(x)` of a light model on a height map.

    Args:
        light_model: a module of :mod:`psmini.lights`.
        depth: height toward the camera, shape :math:`(B, 1, H, W)`, mm (same frame as the light positions).
        pixel_pitch_mm: pixel size on the cloth, mm (orthographic camera, :mod:`psmini.geometry`).
        card_height_mm: for flat-fielded images, the height of the card they were divided by: the vectors are then
            divided by the card's irradiance times :math:`l_z` at the same pixel. ``None`` for raw images.

    Returns:
        light vectors :math:`(B, K, 3, H, W)`: unit direction times irradiance (relative to the card's when
        ``card_height_mm`` is given).

    Raises:
        ShapeError: when ``depth`` is not :math:`(B, 1, H, W)`.
        InputError: for a light at or below the card plane with ``card_height_mm``, or a non-module light model.

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
    field = _LightField(light_model, sizes["H"], sizes["W"], pixel_pitch_mm, card_height_mm, depth)
    lx, ly, lz, _ = field(depth)
    return torch.stack([lx, ly, lz], dim=2)


# ----------------------------------------------------------------------------------------------------------------
# Per-pixel weighted least squares on component tensors (unchecked kernels)
# ----------------------------------------------------------------------------------------------------------------


def _fit(intensities: Tensor, lx: Tensor, ly: Tensor, lz: Tensor, used: Tensor) -> tuple[Tensor, Tensor, tuple]:
    """Weighted per-pixel least squares m = ρ n, by the adjugate of each pixel's normal matrix (element-wise
    products: batched LAPACK on millions of 3 × 3 systems costs far more). Returns m (B, 3, H, W) (0 where not
    well posed), where it is well posed (B, 1, H, W), and the normal matrix's adjugate and determinant
    (:func:`_adjugate`), which the leverage and the confidence reuse."""
    used = used.to(lx.dtype)  # once: a boolean factor costs twice a float one in every product
    matrix = _adjugate(lx, ly, lz, used)
    (c00, c01, c02, c11, c12, c22), det = matrix
    signal = (used * intensities).unbind(1)
    r0, r1, r2 = (_sum_of_products(signal, component.unbind(1)) for component in (lx, ly, lz))
    m = torch.cat([c00 * r0 + c01 * r1 + c02 * r2, c01 * r0 + c11 * r1 + c12 * r2,
                   c02 * r0 + c12 * r1 + c22 * r2], dim=1) / det
    return m, torch.isfinite(det), matrix


def _sum_of_products(a: tuple[Tensor, ...], b: tuple[Tensor, ...]) -> Tensor:
    r""":math:`\sum_k a_k b_k` over the lights, (B, 1, H, W), from the planes of each light (``unbind(1)`` of a
    (B, K, H, W) tensor): one product per light accumulated in place, which reads each operand
    once (a product and then a sum writes and reads back a (B, K, H, W) temporary: 1.1 against 0.5 ms on
    8 × 400²; planes sliced afresh for every sum cost 30% more than these)."""
    total = a[0] * b[0]
    for x, y in zip(a[1:], b[1:], strict=True):
        total.addcmul_(x, y)
    return total.unsqueeze(1)


def _split(m: Tensor, well_posed: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """Albedo |m| and unit normal; albedo 0 and normal (0, 0, 1) where not solved."""
    return _unit_and_length(m, well_posed if mask is None else well_posed & mask.bool())


def _predict(m: Tensor, lx: Tensor, ly: Tensor, lz: Tensor) -> Tensor:
    """Unclamped Lambertian prediction m·L_k = ρ n·L_k, (B, K, H, W)."""
    # the products added in place: the sum's value to the bit, two temporaries fewer (addcmul_ fuses a multiply-add,
    # which rounds otherwise)
    return (m[:, 0:1] * lx).add_(m[:, 1:2] * ly).add_(m[:, 2:3] * lz)


def _adjugate(lx: Tensor, ly: Tensor, lz: Tensor, used: Tensor) -> tuple[tuple[Tensor, ...], Tensor]:
    """The six entries of the adjugate of each pixel's normal matrix and its determinant, each (B, 1, H, W);
    the determinant is +inf where the matrix is not well posed (its inverse is then 0)."""
    used = used.to(lx.dtype)
    x, y, z = (component.unbind(1) for component in (lx, ly, lz))
    wx, wy, wz = ((used * component).unbind(1) for component in (lx, ly, lz))
    a, b, c = _sum_of_products(wx, x), _sum_of_products(wx, y), _sum_of_products(wx, z)
    d, e, f = _sum_of_products(wy, y), _sum_of_products(wy, z), _sum_of_products(wz, z)
    adjugate, det, well_posed = _symmetric_adjugate(a, b, c, d, e, f)
    return adjugate, torch.where(well_posed, det, torch.full_like(det, torch.inf))


def _leverage(lx: Tensor, ly: Tensor, lz: Tensor, matrix: tuple) -> Tensor:
    r"""Leverage :math:`L_k^T (\sum_{j} w_j L_j L_j^T)^{-1} L_k` of every light, (B, K, H, W), from the adjugate
    and determinant of the fit's normal matrix (:func:`_fit`)."""
    (c00, c01, c02, c11, c12, c22), det = matrix
    # c00 lx lx + c11 ly ly + c22 lz lz + 2 (c01 lx ly + c02 lx lz + c12 ly lz), grouped as written and computed in
    # place (the same values, six fresh buffers where there were seventeen)
    quadratic = (c00 * lx).mul_(lx).add_((c11 * ly).mul_(ly)).add_((c22 * lz).mul_(lz))
    mixed = (c01 * lx).mul_(ly).add_((c02 * lx).mul_(lz)).add_((c12 * ly).mul_(lz))
    return quadratic.add_(mixed.mul_(2)).div_(det)


def _candidates(intensities: Tensor, valid: Tensor, level: Tensor | float) -> Tensor:
    """Observations that may be lit: brighter than ``level`` times the pixel's brightest.

    Where fewer than three pass, a grazing light may still be real (0.01 next to 0.8 is lit, not shadowed): such
    pixels take their three brightest valid observations, provided the third is not zero. A pixel with fewer than
    three non-zero observations cannot be solved and gets none (it is left unsolved rather than fitted to shadows).
    An observation is among the three brightest when it is at least the third largest (ties all count).
    """
    ranked = intensities.masked_fill(~valid, -torch.inf)
    first, third = _first_and_third(ranked)
    # (three or more pass a bar exactly where the third largest does: no count over the lights)
    bar = level * first
    bright = ranked > bar
    brightest_three = (ranked >= third) & (third > 0)  # the third above zero: three valid non-zero observations
    return _choose(third > bar, bright, brightest_three)


def _count(selection: Tensor, dtype: torch.dtype | None = None) -> Tensor:
    """How many of each pixel's observations the boolean ``selection`` (B, K, H, W) holds, (B, 1, H, W), as bytes
    (or ``dtype``): on the CPU a sum of booleans over the lights took 2.0 ms on 8 x 400^2, of their bytes 0.03 ms."""
    if selection.shape[1] > torch.iinfo(torch.uint8).max:
        count = selection.sum(dim=1, keepdim=True)
    else:
        count = selection.view(torch.uint8).sum(dim=1, keepdim=True, dtype=torch.uint8)
    return count if dtype is None else count.to(dtype)


def _choose(condition: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``torch.where(condition, a, b)`` for boolean tensors, by logic: on the CPU ``where`` on booleans took 6.6
    against 0.5 ms on 8 x 400^2."""
    return (a & condition) | (b & ~condition)


def _first_and_third(x: Tensor) -> tuple[Tensor, Tensor]:
    """The largest and the third largest of ``x`` (B, K, H, W) over dimension 1 (ties counted), each (B, 1, H, W);
    -inf for the third when K < 3. A running top three, each light inserted by five element-wise passes over a
    plane: ``topk`` over the lights' dimension took 13 ms on 8 x 400^2, this 2.9 ms."""
    first = x[:, 0:1].clone()
    second, third = torch.full_like(first, -torch.inf), torch.full_like(first, -torch.inf)
    for k in range(1, x.shape[1]):
        value = x[:, k : k + 1]
        torch.maximum(third, torch.minimum(second, value), out=third)
        torch.maximum(second, torch.minimum(first, value), out=second)
        torch.maximum(first, value, out=first)
    return first, third


def _median(values: Tensor, usable: Tensor) -> Tensor:
    """Median of ``values`` over the ``usable`` pixels of each batch item, (B, 1, 1, 1); 0 where none."""
    medians = [v.masked_select(u).median() if bool(u.any()) else v.new_zeros(())
               for v, u in zip(values, usable, strict=True)]
    return torch.stack(medians).view(-1, 1, 1, 1)


def _noise_scales(gain: Tensor | None, images: Tensor) -> Tensor | float:
    """The flat-field's ``gain`` (B|1, K|1, H, W) relative to its median over the trusted card of each of its items,
    (B|1, K, H, W) (1 where the gain is 0: observations that are not valid anyway); 1.0 without a gain. Kept for
    the last gains (:func:`_kept`)."""
    if gain is None:
        return 1.0
    return _kept(gain, ("noise scales", tuple(images.shape[1:]), images.dtype, images.device),
                 lambda: _relative_gain(gain, images))


def _pooled_gain(gain: Tensor | None, like: Tensor) -> Tensor | None:
    """``gain`` averaged over 2 x 2 pixels in ``like``'s dtype (the coarse alternations'), kept (:func:`_kept`)."""
    if gain is None:
        return None
    return _kept(gain, ("pooled", like.dtype), lambda: F.avg_pool2d(gain.to(like), 2))


def _relative_gain(gain: Tensor, images: Tensor) -> Tensor:
    """:func:`_noise_scales` computed afresh."""
    gain = gain.to(images).expand(gain.shape[0], *images.shape[1:])
    trusted = gain > 0
    median = _median(gain, trusted).clamp_min(torch.finfo(gain.dtype).tiny)
    return torch.where(trusted, gain / median, torch.ones_like(gain))


class _Kept(NamedTuple):
    key: tuple
    owner: weakref.ref
    results: dict


#: What was derived from the last few gains (newest last), see :func:`_kept`.
_kept_gains: list[_Kept] = []
_KEPT_GAINS = 4


def _kept(source: Tensor, what: tuple, compute):
    """``compute()``, a function of ``source`` alone named by ``what``, kept while ``source``'s data live unchanged.

    The flat-field keeps one card's terms for a batch run, so every chunk and every call gets the same gain
    tensor; its noise scales (a median over the card's K x H x W values) and its 2 x 2 average cost 21 and 10 ms
    of a 0.9 s solve of one 8 x 400 x 400 capture, each time. A gain that needs a gradient is not kept. The key is
    where the data lie and their version (:func:`psmini.flatfield._data_of`), checked against a weak reference to
    the tensor that owns them, as the flat-field does for its card.
    """
    if source.requires_grad:
        return compute()
    owner, where = _data_of(source)
    key = (where, source.dtype, source.device)
    with _kept_lock:
        entry = next((entry for entry in _kept_gains if entry.key == key and entry.owner() is owner), None)
        if entry is not None and what in entry.results:
            return entry.results[what]
    result = compute()
    with _kept_lock:
        if entry is None:
            if len(_kept_gains) >= _KEPT_GAINS:
                del _kept_gains[0]
            entry = _Kept(key, weakref.ref(owner, lambda _: _forget_gain(key)), {})
            _kept_gains.append(entry)
        entry.results[what] = result
    return result


def _forget_gain(key: tuple) -> None:
    """Drop what was kept for a gain once the tensor that owns its data is freed."""
    with _kept_lock:
        _kept_gains[:] = [entry for entry in _kept_gains if entry.key != key]


#: Pixels the noise statistics (:meth:`_Rejection.settle_noise_model`, :meth:`_Rejection.settle_relative_noise`:
#: a mean and medians over the image) read at least: an image of more reads every n-th row and column, the largest
#: n that leaves this many (a 400 x 400 capture's statistics took 74 ms of a 0.8 s solve over all its pixels).
_NOISE_SAMPLE_PIXELS = 2**15


def _noise_sample(images: Tensor):
    """The sampling of :data:`_NOISE_SAMPLE_PIXELS` for ``images``' grid: a function of a per-pixel tensor (or a
    tuple of them; anything else is returned as it is) to its every n-th row and column."""
    height, width = images.shape[-2:]
    n = max(1, math.isqrt(height * width // _NOISE_SAMPLE_PIXELS))

    def sample(x):
        if isinstance(x, tuple):
            return tuple(sample(item) for item in x)
        return x[..., ::n, ::n] if isinstance(x, Tensor) and n > 1 else x

    return sample


def _twice_mean(values: Tensor, chosen: Tensor) -> Tensor:
    """Twice the mean of ``values`` over the ``chosen`` entries of each batch item, (B, 1, 1, 1) (0 where none)."""
    total = (values * chosen.to(values.dtype)).sum(dim=(1, 2, 3), keepdim=True)
    return 2 * total / _count(chosen).sum(dim=(1, 2, 3), keepdim=True).clamp_min(1)


def _noise_model(images: Tensor, pred: Tensor, used: Tensor, valid: Tensor, albedo: Tensor, scale: Tensor,
                 mask: Tensor | None, noise_scale: Tensor | float = 1.0) -> tuple[Tensor, Tensor]:
    r"""The images' noise as :math:`\sigma_k^2 = s_k^2 \sigma_0^2 + s_k\,g\,\max(\hat I_k, 0)` (read noise and
    quantisation, then shot noise, which grows with the signal), :math:`\sigma_0^2` and :math:`g` each
    (B, 1, 1, 1), in the images' units; :math:`s_k` is the observation's ``noise_scale`` (:func:`_noise_scales`):
    flat-fielding multiplied the raw reading, and its noise, by the card's gain, so a raw noise
    :math:`a + b\,I_{raw}` becomes :math:`s^2 a + s\,b\,I` (on the rig's card the gain varies six times across the
    field under one LED: against the simulator's noise a model without it was off by 0.5-3.2 times across the
    card's levels, with it by 1.1-1.7 times).

    :math:`\sigma_0` comes from the observations that the fit puts well inside an attached shadow: they read noise
    alone, clipped at zero by the dark subtraction, whose 75th percentile is :math:`0.674\,\sigma_0`. :math:`g`
    is the median over pixels with at least five observations of (residual variance per degree of freedom minus
    the read noise) over the mean of :math:`s_k \hat I_k`.
    """
    usable = albedo > 0
    if mask is not None:
        usable = usable & mask.bool()
    # (and that read little next to the pixel's brightest: a fit bent by a glint puts lit observations there too)
    dark = valid & usable & (pred < -0.1 * scale) & (images < 0.1 * images.amax(dim=1, keepdim=True))
    # noise clipped at zero: twice the mean square is sigma0^2 (quantisation included: at 8 bits most of these
    # read 0, and a percentile would too); lit observations among them (a fit bent by a glint predicts them dark)
    # are clipped away, 4 sigma0 at a time, until none is left (a noise-free lurex otherwise read 0.014 of noise)
    squares = (images / noise_scale).square()
    floor_sq = _twice_mean(squares, dark)
    for _ in range(_NOISE_CLIP_ROUNDS):
        kept = dark & (squares <= _NOISE_CLIP_SIGMAS**2 * floor_sq)
        if bool((kept == dark).all()):
            break
        dark = kept
        floor_sq = _twice_mean(squares, dark)
    weight = used.to(images.dtype)  # once: a boolean factor costs twice a float one in every product
    n = _count(used, images.dtype)
    variance = ((images - pred).square() * weight).sum(dim=1, keepdim=True) / (n - 3).clamp_min(1)
    read = floor_sq * (weight * noise_scale**2).sum(dim=1, keepdim=True) / n.clamp_min(1)
    level = ((pred.clamp_min(0) * noise_scale * weight).sum(dim=1, keepdim=True) / n.clamp_min(1)).clamp_min(1e-12)
    gain = _median((variance - read) / level, usable & (n >= _HIGHLIGHT_MIN_OBS)).clamp_min(0)
    return floor_sq, gain


class _Rejection:
    r"""Which observations a pixel's fit uses: decided once, then updated once per alternation.

    Shadows: observations darker than the shadow level (``shadow_fraction`` of the pixel's brightest, raised to
    3.5 read-noise levels once the noise model is known, :meth:`settle_noise_model`, before any residual is
    judged).
    Highlights: per update, the brightest observation relative to its light (:math:`I_k / |L_k|`) is dropped when
    the fit of the others misses it by more than the larger of ``highlight_fraction`` and four noise levels times
    :math:`1/\sqrt{1 - h_k}` (relative to the pixel's scale; :math:`r_k / (1 - h_k)` is the leave-one-out residual
    from the full fit, :math:`h_k` the hat matrix's diagonal, Cook and Weisberg, "Residuals and influence in
    regression", 1982); a specular lobe only adds light, so only positive excesses count, and only pixels with
    :data:`_HIGHLIGHT_MIN_OBS` observations are tested. Cast shadows: the darkest observation is dropped when the
    fit of the others predicts it brighter by more than the larger of ``outlier_fraction`` and six noise levels.
    Of the two suspects only the one with the larger studentised residual (in noise levels) may leave in one
    update: each bends the fit toward itself, so that the other looks like an outlier too. Attached shadows
    (:math:`n \cdot L_k \le 0.02\,|L_k|`) leave the fit; each update starts from all candidates, so an early drop
    of a shadow can be undone, and a pixel keeps its previous observations rather than fall below three. The noise
    of each observation scales with the flat-field's gain (:func:`_noise_model`).
    """

    def __init__(self, intensities: Tensor, valid: Tensor, options: NearLightOptions,
                 gain: Tensor | None = None) -> None:
        self.intensities, self.valid, self.options = intensities, valid, options
        self.noise_scale = _noise_scales(gain, intensities)
        self.candidates = _candidates(intensities, valid, options.shadow_fraction)
        self.highlights = torch.zeros_like(valid)
        self.shadows = torch.zeros_like(valid)
        self.noise: tuple[Tensor, Tensor] | None = None
        self.relative_noise: Tensor | None = None

    _PER_PIXEL = ("intensities", "valid", "noise_scale", "candidates", "highlights", "shadows")

    def band(self, rows: slice) -> _Rejection:
        """The same rejection on the image rows ``rows``: its per-pixel tensors are views of this one's, the noise
        model (per batch item) is shared. :meth:`update` replaces a band's highlight and shadow maps; :meth:`absorb`
        writes them back."""
        band = copy.copy(self)
        for name in self._PER_PIXEL:
            setattr(band, name, _rows_of(getattr(self, name), rows))
        return band

    def absorb(self, band: _Rejection, rows: slice) -> None:
        """Write the highlight and shadow maps of ``band`` (:meth:`band` of ``rows``) back into this one's."""
        self.highlights[..., rows, :] = band.highlights
        self.shadows[..., rows, :] = band.shadows

    def packed(self, pixels: _Pixels) -> _Rejection:
        """The same rejection on some ``pixels`` only, packed (:meth:`_Pixels.take`): its per-pixel tensors and its
        noise levels (per batch item, now per pixel) are copies; :meth:`unpack` writes the highlight and shadow
        maps back."""
        part = copy.copy(self)
        for name in (*self._PER_PIXEL, "noise", "relative_noise"):
            setattr(part, name, pixels.take(getattr(self, name)))
        return part

    def unpack(self, part: _Rejection, pixels: _Pixels) -> None:
        """Write the highlight and shadow maps of ``part`` (:meth:`packed` on ``pixels``) back into this one's."""
        pixels.put(self.highlights, part.highlights)
        pixels.put(self.shadows, part.shadows)

    def settle_relative_noise(self, field: tuple[Tensor, Tensor, Tensor, Tensor], used: Tensor,
                              mask: Tensor | None) -> None:
        """The highlight rounds' noise level (once, from the pixels of :func:`_noise_sample`): the median over
        pixels of the residual of a fit without each pixel's brightest observation relative to its light, relative
        to the pixel's scale (before the glints are out, the noise model would take them for noise)."""
        if self.relative_noise is not None:
            return
        sample = _noise_sample(self.intensities)
        lx, ly, lz, length = sample(field)
        images, used, mask = sample(self.intensities), sample(used), sample(mask)
        relative = images / length.clamp_min(torch.finfo(length.dtype).tiny)
        ranked = relative.masked_fill(~used, -torch.inf)
        others = used & (ranked < ranked.amax(dim=1, keepdim=True))
        weight = others.to(images.dtype)
        m_others, posed, _ = _fit(images, lx, ly, lz, weight)
        albedo_others, _ = _split(m_others, posed, mask)
        n = _count(others, images.dtype)
        squared = ((images - _predict(m_others, lx, ly, lz)).square() * weight).sum(dim=1, keepdim=True)
        residual = (squared / (n - 3).clamp_min(1)).sqrt() / (albedo_others * length.mean(dim=1, keepdim=True)
                                                             ).clamp_min(1e-12)
        self.relative_noise = _median(residual, (n >= 4) & (albedo_others > 0)).nan_to_num(0.0, posinf=0.0)

    def settle_noise_model(self, field: tuple[Tensor, Tensor, Tensor, Tensor], fit: tuple[Tensor, Tensor, tuple],
                           albedo: Tensor, used: Tensor, mask: Tensor | None) -> None:
        """The noise model from the ``fit`` made with ``used`` (once, from the pixels of :func:`_noise_sample`),
        and the candidates (of every pixel) above its shadow level."""
        if self.noise is not None:
            return
        sample = _noise_sample(self.intensities)
        lx, ly, lz, length = sample(field)
        albedo = sample(albedo)
        pred = _predict(sample(fit[0]), lx, ly, lz)
        scale = albedo * length.mean(dim=1, keepdim=True)
        self.noise = _noise_model(sample(self.intensities), pred, sample(used), sample(self.valid), albedo, scale,
                                  sample(mask), sample(self.noise_scale))
        shadow = self.noise[0].sqrt() * _SHADOW_SIGMAS * self.noise_scale
        self.candidates = _candidates(self.intensities, self.valid & (self.intensities > shadow),
                                      self.options.shadow_fraction)

    def settle(self, used: Tensor) -> Tensor:
        """``used`` without the observations below the noise model's shadow level (:meth:`settle_noise_model`;
        unchanged where fewer than three would remain). Run before the full updates judge any residual: a
        shadowed observation that reads noise, kept in a fit, bends it as much as a glint does, and the brightest
        observation of such a pixel would be taken for a highlight."""
        settled = used & self.candidates
        return _choose(_count(settled) >= 3, settled, used)

    def update(self, field: tuple[Tensor, Tensor, Tensor, Tensor], fit: tuple[Tensor, Tensor, tuple],
               albedo: Tensor, used: Tensor, highlights_only: bool = False) -> Tensor:
        """New weights from the ``fit`` (:func:`_fit`) made with ``used``; (B, K, H, W) bool. With
        ``highlights_only`` only the highlight test runs (its rounds come first: a glint bends the fit that the
        other tests judge by); it needs :meth:`settle_relative_noise`, the full update :meth:`settle_noise_model`.
        Each pixel's result depends on that pixel alone (and the noise levels of its batch item)."""
        lx, ly, lz, length = field
        images, options = self.intensities, self.options
        m, _, matrix = fit
        # (arithmetic on a float copy of the selection: on the CPU, where(), masked_fill() and reductions of
        # booleans over K cost two to five times a float product)
        # (the K-plane terms are computed in place where a term is not needed again: the same operations in the
        # same order, so the same values, with fewer fresh buffers: with the leverage's, a band's update of 8 x 40 x 400
        # took 4.3 against 4.8 ms, its highlight test 2.7 against 3.2 ms)
        tiny = torch.finfo(images.dtype).tiny
        weight = used.to(images.dtype)
        pred = _predict(m, lx, ly, lz)
        positive = pred.clamp_min(0)
        scale = albedo * length.mean(dim=1, keepdim=True)
        relative = length.clamp_min(tiny)
        relative = torch.div(images, relative, out=relative)
        count = weight.sum(dim=1, keepdim=True)
        if highlights_only:
            # shot noise grows with the signal: scaled by the square root of the prediction over the pixel's mean
            shot = positive * self.noise_scale
            level = (shot * weight).sum(dim=1, keepdim=True) / count.clamp_min(1)
            # relative_noise: set by settle_relative_noise, which the highlight rounds run first
            sigma = shot.div_(level.clamp_min(1e-12)).sqrt_().mul_(self.relative_noise * scale)  # type: ignore[operator]
        else:
            s = self.noise_scale
            floor_sq, gain = self.noise  # type: ignore[misc]  # set by settle_noise_model, which runs first
            sigma = (gain * positive).mul_(s).add_(floor_sq * s**2).sqrt_()
        leverage = _leverage(lx, ly, lz, matrix)
        # residuals of each observation against the fit of the others: r / (1 - h) for the observations in the
        # fit (leave-one-out, from the hat matrix), r itself for the others; and their spread in noise levels
        kept = (1 - leverage).clamp_min_(1e-6).sub_(1).mul_(weight).add_(1)
        spread = (1 + leverage).add_(kept.reciprocal().sub_(1).sub_(leverage).mul_(weight)).sqrt_()
        left_out = (images - pred).div_(kept)
        # the two suspects, the brightest and the darkest observation relative to its light (unused observations
        # pushed out of reach; amax: argmax is slow), and how far each lies from the fit of the others in noise
        # levels: only the farther of the two may leave in this update, when beyond its threshold. A cast shadow
        # kept in the fit bends it below the lit observations as a glint bends it above the others: judged alone,
        # the brightest of a pixel whose fit a shadow pulled down looks like a highlight (1% of a matte jute's
        # pixels lost a good observation so, and their normals erred by 7 degrees), and the darkest of a glinting
        # pixel like a cast shadow. One deletion at a time, the largest studentised residual first (Cook and
        # Weisberg).
        beyond = (1 - weight).mul_(torch.finfo(images.dtype).max)
        ranked = relative - beyond
        brightest = used & (ranked == ranked.amax(dim=1, keepdim=True))
        ranked = torch.add(relative, beyond, out=ranked)
        darkest = used & (ranked == ranked.amin(dim=1, keepdim=True))
        studentised = (sigma * spread).clamp_min_(tiny)
        studentised = torch.div(left_out, studentised, out=studentised)
        above = (studentised * brightest).amax(dim=1, keepdim=True)
        below = studentised.neg_().mul_(darkest).amax(dim=1, keepdim=True)
        if options.highlight_fraction is not None:
            sigmas = _FIRST_HIGHLIGHT_SIGMAS if highlights_only else _HIGHLIGHT_SIGMAS
            threshold = torch.maximum(sigma * sigmas * spread, options.highlight_fraction * scale)
            testable = (count >= _HIGHLIGHT_MIN_OBS) & (albedo > 0) & (above >= below)
            self.highlights = self.highlights | (brightest & testable & (left_out > threshold))
        if highlights_only:
            return used & ~self.highlights
        # cast shadows only darken: the darkest observation leaves when the fit of the others predicts it far
        # brighter (with four observations the others still determine the normal)
        threshold = torch.maximum(options.outlier_fraction * scale, _OUTLIER_SIGMAS * sigma * spread)
        testable = (count >= 4) & (albedo > 0) & (below > above)
        self.shadows = self.shadows | (darkest & testable & (left_out < -threshold))
        lit = pred > _GRAZING_COSINE * albedo * length
        bright = self.candidates & lit
        # grazing light: an observation near zero that the fit of the others also puts near zero (but above it) is
        # lit, and n·L ≈ 0 is information that a shadow test on the reading alone would drop; judged against the
        # fit of the others, so that a cast shadow cannot bend the fit of a pixel with few lights toward itself
        others = images - left_out
        grazing = self.valid & ~bright & (others > _GRAZING_LOW * sigma) \
            & (left_out.abs() <= _GRAZING_SIGMAS * sigma * spread)
        proposal = (bright | grazing) & ~self.highlights & ~self.shadows
        enough = _count(proposal) >= 3
        fallback = _choose(count >= 3, used, self.candidates & ~self.highlights)
        return _choose(enough, proposal, fallback)


def _select(rejection: _Rejection, images: Tensor, vectors: tuple[Tensor, Tensor, Tensor, Tensor], used: Tensor,
            fit: tuple,
            albedo: Tensor, normals: Tensor, mask: Tensor | None, updates: int,
            highlight_rounds: int | None = None) -> tuple[Tensor, tuple, Tensor, Tensor]:
    """Highlight rounds (at most ``highlight_rounds``, K - 3 by default, each dropping at most one observation per
    pixel), the noise model and the shadows below its level (:meth:`_Rejection.settle_noise_model`), then
    ``updates`` full updates of the selection, re-solving after each change; returns the selection and its fit.

    Each pixel's update depends on that pixel alone once the noise levels are known (estimated over the image before
    each phase, :func:`_noise_sample`), and it returns a selection that the last update left unchanged unchanged again
    (its fit, and so its tests, are the same; the highlight and shadow maps only grow by what they already hold). So
    only the first update of a phase runs on every pixel, band by band of image rows (:func:`_row_bands`: its dozens of
    passes stay in the core's cache, 47 against 74 ms on a 400² capture); the fits, and the updates after the first, run
    on the pixels that changed, packed (:class:`_Pixels`; 1-5% of a fabric's), until a round changes none. The selection
    and the fits are those of re-solving every pixel after every round.
    """
    highlight_rounds = (images.shape[1] - 3) if highlight_rounds is None else highlight_rounds
    state = _owned((used, fit, albedo, normals))  # written in place from here on
    if rejection.options.highlight_fraction is not None and highlight_rounds > 0:
        rejection.settle_relative_noise(vectors, used, mask)
        _rounds(rejection, images, vectors, mask, state, highlight_rounds, highlights_only=True)
    if updates > 0:
        used, fit, albedo, _ = state  # after the highlight rounds
        rejection.settle_noise_model(vectors, fit, albedo, used, mask)
        _resolve(images, vectors, mask, state, rejection.settle(used))
        _rounds(rejection, images, vectors, mask, state, updates, highlights_only=False)
    return state


def _owned(state):
    """A copy of the state's tensors (nested tuples of them) that :func:`_select` may write into."""
    return tuple(_owned(x) for x in state) if isinstance(state, tuple) else state.clone()


def _rounds(rejection: _Rejection, images: Tensor, vectors: tuple[Tensor, Tensor, Tensor, Tensor],
            mask: Tensor | None, state: tuple,
            rounds: int, highlights_only: bool) -> None:
    """Up to ``rounds`` updates of the selection of one phase of :func:`_select`, re-solving after each change, the
    state ``(used, fit, albedo, normals)`` written in place; stops at the first round that changes nothing."""
    if rounds == 0:
        return
    used = state[0]
    new = _first_update(rejection, images, vectors, state, highlights_only)
    changed = _count(new != used) > 0
    if not bool(changed.any()):
        return
    pixels = _Pixels(changed)
    part = rejection.packed(pixels)
    sub_images, sub_vectors, sub_mask = pixels.take(images), pixels.take(vectors), pixels.take(mask)
    sub_state = _solve_selection(sub_images, sub_vectors, sub_mask, pixels.take(new))
    for _ in range(rounds - 1):
        sub_used, sub_fit, sub_albedo, _ = sub_state
        new = part.update(sub_vectors, sub_fit, sub_albedo, sub_used, highlights_only)
        if bool((new == sub_used).all()):
            break
        sub_state = _solve_selection(sub_images, sub_vectors, sub_mask, new)
    rejection.unpack(part, pixels)
    pixels.put(state, sub_state)


def _first_update(rejection: _Rejection, images: Tensor, vectors: tuple[Tensor, Tensor, Tensor, Tensor], state: tuple,
                  highlights_only: bool) -> Tensor:
    """The update of every pixel's selection from the state's fits, band by band of rows (:func:`_row_bands`)."""
    bands = _row_bands(images)
    if len(bands) == 1:
        used, fit, albedo, _ = state
        return rejection.update(vectors, fit, albedo, used, highlights_only)
    proposals = []
    for rows in bands:
        band = rejection.band(rows)
        used, fit, albedo, _ = _rows_of(state, rows)
        proposals.append(band.update(_rows_of(vectors, rows), fit, albedo, used, highlights_only))
        rejection.absorb(band, rows)
    return torch.cat(proposals, dim=-2)


def _solve_selection(images: Tensor, vectors: tuple[Tensor, Tensor, Tensor, Tensor], mask: Tensor | None,
                     selection: Tensor) -> tuple[Tensor, tuple, Tensor, Tensor]:
    """The state ``(selection, fit, albedo, normals)`` of the fit (:func:`_fit`) with ``selection``."""
    fit = _fit(images, *vectors[:3], selection)
    return (selection, fit, *_split(*fit[:2], mask))


def _resolve(images: Tensor, vectors: tuple[Tensor, Tensor, Tensor, Tensor], mask: Tensor | None, state: tuple,
             selection: Tensor) -> None:
    """The state (written in place) of :func:`_solve_selection` with ``selection``, re-solving only the pixels where
    it differs from the state's."""
    changed = _count(selection != state[0]) > 0
    if not bool(changed.any()):
        return
    pixels = _Pixels(changed)
    part = _solve_selection(pixels.take(images), pixels.take(vectors), pixels.take(mask), pixels.take(selection))
    pixels.put(state, part)


class _Pixels:
    """Some pixels of a (B, ·, H, W) grid, packed: a tensor of the grid becomes (1, C, 1, N), one column per pixel,
    so that the per-pixel kernels (:func:`_fit`, :meth:`_Rejection.update`, which reduce over dimension 1 only)
    run on them alone.

    Args:
        where: (B, 1, H, W) bool, the pixels to pack.
    """

    def __init__(self, where: Tensor) -> None:
        self.batch, _, self.y, self.x = where.nonzero().unbind(dim=1)
        self.count = self.batch.numel()

    def take(self, x):
        """``x`` packed: a tensor (B|1, C, H, W), or (B|1, C, 1, 1) per batch item, becomes (1, C, 1, N); tuples
        are packed item by item, anything else (``None``, a number) is returned as it is."""
        if isinstance(x, tuple):
            return tuple(self.take(item) for item in x)
        if not isinstance(x, Tensor):
            return x
        batch = self.batch if x.shape[0] > 1 else torch.zeros_like(self.batch)
        columns = x[batch, :, 0, 0] if x.shape[-2:] == (1, 1) else x[batch, :, self.y, self.x]  # (N, C)
        return columns.t().contiguous().view(1, x.shape[1], 1, self.count)

    def put(self, whole, part) -> None:
        """Write the packed ``part`` (:meth:`take`'s shape) into the pixels of ``whole`` (a (B, C, H, W) tensor, or
        nested tuples of them, the same nesting), in place."""
        if isinstance(whole, tuple):
            for w, p in zip(whole, part, strict=True):
                self.put(w, p)
            return
        whole[self.batch, :, self.y, self.x] = part.view(part.shape[1], -1).t()


#: Observations (B · K · rows · W) of one band of :func:`_select` on the CPU: about 0.5 MB of float32 per tensor,
#: so that a band's working set stays in a core's L2 cache.
_BAND_ELEMENTS = 2**17
# Fewest rows of a band (each band costs every operation's fixed overhead once).
_MIN_BAND_ROWS = 8


def _row_bands(images: Tensor) -> list[slice]:
    """Bands of image rows for :func:`_select`: one on a GPU (its cache is not the point there), on the CPU bands
    of at most :data:`_BAND_ELEMENTS` observations (at least :data:`_MIN_BAND_ROWS` rows each)."""
    batch, count, height, width = images.shape
    if images.device.type != "cpu":
        return [slice(0, height)]
    rows = max(_MIN_BAND_ROWS, _BAND_ELEMENTS // max(1, batch * count * width))
    return [slice(start, min(start + rows, height)) for start in range(0, height, rows)]


def _rows_of(x, rows: slice):
    """``x`` (a tensor with image rows in its next-to-last dimension, or a tuple of them) on ``rows``; anything
    else (``None``, a number) as it is."""
    if isinstance(x, tuple):
        return tuple(_rows_of(item, rows) for item in x)
    return x[..., rows, :] if isinstance(x, Tensor) else x


def robust_near_light_normals(
    intensities: Tensor,
    light_vectors: Tensor,
    valid: Tensor | None = None,
    mask: Tensor | None = None,
    options: NearLightOptions | None = None,
    rounds: int = 4,
    gain: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Per-pixel least squares with per-pixel lights, dropping shadowed, specular and outlying observations.

    The rejection of :func:`solve_near_light` at fixed light vectors: shadows are left out from the start, then
    ``rounds`` updates each drop at most one highlight or cast shadow per pixel (the brightest or the darkest
    relative to its light, whichever lies farther from the fit of the others in noise levels, when beyond its
    threshold: ``options.highlight_fraction`` of the pixel's scale or four noise levels above, ``outlier_fraction``
    or six below), attached shadows (:math:`n \cdot L_k \le 0.02\,|L_k|`), and re-solve. Pixels with fewer
    than three non-zero observations are left unsolved (albedo 0, normal (0, 0, 1)) with no weights.

    Args:
        intensities: images, shape :math:`(B, K, H, W)` (flat-fielded or dark-subtracted).
        light_vectors: per-pixel light vectors, shape :math:`(B, K, 3, H, W)` (:func:`near_light_vectors`).
        valid: observations to use at all, shape :math:`(B, K, H, W)` bool (saturation, untrusted card).
        mask: pixels to solve, shape :math:`(B, 1, H, W)`.
        options: :class:`NearLightOptions` (its fractions); defaults when omitted.
        rounds: updates of the weights after the first solve.
        gain: the flat-field's gain, :math:`(B|1, K|1, H, W)`, which scales each observation's noise (see
            :func:`solve_near_light`); ``None``: the same noise everywhere.

    Returns:
        albedo :math:`(B, 1, H, W)`, unit normals :math:`(B, 3, H, W)` and the weights used :math:`(B, K, H, W)`.

    Raises:
        ShapeError: when the shapes do not match.
        InputError: for NaN input, a negative gain or ``rounds < 0``.

    Example:
        >>> vectors = torch.tensor([[1.0, 0, 1], [-1.0, 0, 1], [0, 1.0, 1], [0, -1.0, 1]])[None, :, :, None, None]
        >>> normal = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> images = (vectors * normal[:, None]).sum(2)
        >>> albedo, normals, weights = robust_near_light_normals(images, vectors)
        >>> normals.flatten().tolist()
        [0.0, 0.0, 1.0]
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_shape(light_vectors, ["B", "K", "3", "H", "W"], "light_vectors")
    if light_vectors.shape[1] != sizes["K"] or tuple(light_vectors.shape[3:]) != (sizes["H"], sizes["W"]):
        raise ShapeError(f"light_vectors must have shape (B, {sizes['K']}, 3, {sizes['H']}, {sizes['W']}), "
                         f"got {tuple(light_vectors.shape)}")
    check_finite(intensities, "intensities")
    check_finite(light_vectors, "light_vectors")
    if not (isinstance(rounds, int) and rounds >= 0):
        raise InputError(f"rounds must be an integer >= 0, got {rounds!r}")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    valid = _check_valid(valid, intensities)
    gain = _check_gain(gain, intensities)
    options = _check_options(options)
    lx, ly, lz = light_vectors.expand(sizes["B"], -1, -1, -1, -1).unbind(dim=2)
    field = (lx, ly, lz, (lx.square() + ly.square() + lz.square()).sqrt())
    rejection = _Rejection(intensities, valid, options, gain)
    used = rejection.candidates
    fit = _fit(intensities, lx, ly, lz, used)
    albedo, normals = _split(*fit[:2], mask)
    if rounds:
        used, fit, albedo, normals = _select(rejection, intensities, field, used, fit, albedo, normals, mask, rounds)
    return albedo, normals, used & (albedo > 0)


# ----------------------------------------------------------------------------------------------------------------
# Height offset
# ----------------------------------------------------------------------------------------------------------------


def _offset_cost(field: _LightField, images: Tensor, used: Tensor, depth: Tensor, offsets: Tensor) -> Tensor:
    """Relative least-squares residual of each batch item at ``depth + offsets``; offsets (B, n) → costs (B, n).

    The offsets are evaluated in batched passes (the batch becomes B·n): all at once on a GPU, on the CPU as many
    at a time as :data:`_BAND_ELEMENTS` observations hold (at least one), so that each pass's tensors stay in
    the cache (25 offsets on 100² pixels: 37 ms one at a time against 56 ms at once; the same costs)."""
    count = offsets.shape[1]
    per_pass = count if images.device.type != "cpu" else max(1, _BAND_ELEMENTS // images.numel())
    if per_pass >= count:
        return _offset_cost_pass(field, images, used, depth, offsets)
    return torch.cat([_offset_cost_pass(field, images, used, depth, offsets[:, start : start + per_pass])
                      for start in range(0, count, per_pass)], dim=1)


def _offset_cost_pass(field: _LightField, images: Tensor, used: Tensor, depth: Tensor, offsets: Tensor) -> Tensor:
    """:func:`_offset_cost` in one batched pass."""
    batch, count = offsets.shape
    heights = (depth[:, None] + offsets[:, :, None, None, None]).flatten(0, 1)  # (B·n, 1, h, w)
    lx, ly, lz, _ = field(heights)
    if batch > 1 and count > 1:  # (one item's images broadcast over its offsets, one offset's are the items')
        images, used = images.repeat_interleave(count, dim=0), used.repeat_interleave(count, dim=0)
    m, _, _ = _fit(images, lx, ly, lz, used)
    error = (images - _predict(m, lx, ly, lz)).square() * used
    cost = error.flatten(1).sum(1) / (images.square() * used).flatten(1).sum(1).clamp_min(1e-30)
    return cost.view(batch, count)


def _parabola_step(field, images, used, depth, centre: Tensor, step: Tensor) -> Tensor:
    """One Newton step on the cost, from three values at ``centre`` ± ``step`` (both (B,)), kept within ± ``step``
    (downhill by ``step`` where the three values are not convex)."""
    offsets = centre[:, None] + step[:, None] * torch.tensor([-1.0, 0.0, 1.0], device=centre.device, dtype=centre.dtype)
    f0, f1, f2 = _offset_cost(field, images, used, depth, offsets).unbind(1)
    curvature = f0 - 2 * f1 + f2
    newton = step * (f0 - f2) / (2 * curvature).clamp_min(torch.finfo(centre.dtype).tiny)
    downhill = torch.where(f0 < f2, -step, step)
    return centre + torch.where(curvature > 0, torch.minimum(torch.maximum(newton, -step), step), downhill)


def _search_offset(field, images, used, depth, centre: Tensor, search: tuple[float, float] | None,
                   tolerance: float, points: int = _SCAN_POINTS) -> Tensor:
    """Scan :data:`_SCAN_POINTS` offsets over ``search`` around ``centre``, then parabolic steps down to
    ``tolerance``; without ``search``, the steps alone from :data:`_NEWTON_STEP_MM`.

    Each item's step width becomes twice its last move (at least a fourfold shrink): near the minimum the cost is a
    parabola and a step from a close centre lands within micrometres, so refining an offset that barely moved
    (later alternations) takes two steps rather than four; an item whose step fell below ``tolerance`` is not
    evaluated again."""
    if search is None:  # refine around the centre only
        best, width = centre.clone(), _NEWTON_STEP_MM
    else:
        grid = torch.linspace(search[0], search[1], points, device=centre.device, dtype=centre.dtype)
        n = _SCAN_STRIDE
        costs = _offset_cost(field.every(n), images[..., ::n, ::n], used[..., ::n, ::n], depth[..., ::n, ::n],
                             centre[:, None] + grid)
        best = centre + grid[costs.argmin(dim=1)]
        width = (search[1] - search[0]) / (points - 1)
    step = torch.full_like(best, width)
    for _ in range(_MAX_OFFSET_STEPS):
        going = (step > tolerance).nonzero().flatten()
        if going.numel() == 0:
            break
        moved = _parabola_step(field, images[going], used[going], depth[going], best[going], step[going])
        move = (moved - best[going]).abs()
        best[going] = moved
        step[going] = torch.where(move < step[going], torch.minimum(step[going] / 4, 2 * move), step[going])
    return best


def estimate_height_offset(
    intensities: Tensor,
    light_model: nn.Module,
    relative_depth: Tensor,
    pixel_pitch_mm: float,
    weights: Tensor,
    card_height_mm: float | None = None,
    search_mm: tuple[float, float] = (-3.0, 3.0),
    tolerance_mm: float = _OFFSET_TOLERANCE_MM,
) -> Tensor:
    r"""The height offset :math:`c` that makes ``relative_depth + c`` explain the images best.

    Minimises the per-pixel least-squares residual of the images under the light vectors at
    ``relative_depth + c`` over :math:`c`, on every fourth pixel: a scan of 25 values over ``search_mm`` (one
    batched evaluation), then parabolic (Newton) steps on three values at a time, each item's step shrinking to
    twice its last move (at least fourfold) until below ``tolerance_mm``. Each batch item gets its own offset. Not
    differentiated (a search).

    Args:
        intensities: images, shape :math:`(B, K, H, W)`.
        light_model: a module of :mod:`psmini.lights`.
        relative_depth: height up to a constant, shape :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: pixel size, mm.
        weights: observations to use, shape :math:`(B, K, H, W)`.
        card_height_mm: see :func:`near_light_vectors`.
        search_mm: interval of offsets searched, mm, relative to the mean of ``relative_depth``.
        tolerance_mm: step at which the refinement stops, mm.

    Returns:
        offsets :math:`(B, 1, 1, 1)`, mm, such that ``relative_depth + offsets`` is the absolute height.

    Raises:
        ShapeError: for shapes that do not match.
        InputError: for a bad ``search_mm`` or ``tolerance_mm``.

    Example:
        >>> from psmini.lights import PointLights, ring_lights
        >>> lights = PointLights(ring_lights(8, 90.0) * 15.8 + torch.tensor([0.0, 0.0, 10.0]))  # the rig's ring
        >>> flat = torch.zeros(1, 1, 32, 32)
        >>> vectors = near_light_vectors(lights, flat + 0.7, 0.3, card_height_mm=0.0)  # a card 0.7 mm up
        >>> images = vectors[:, :, 2]                                                 # its flat-fielded images
        >>> offset = estimate_height_offset(images, lights, flat, 0.3, images > 0, card_height_mm=0.0)
        >>> round(float(offset), 2)
        0.7
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_shape(relative_depth, ["B", "1", "H", "W"], "relative_depth")
    if relative_depth.shape[0] != sizes["B"] or relative_depth.shape[2:] != intensities.shape[2:]:
        raise ShapeError(f"relative_depth must have shape ({sizes['B']}, 1, {sizes['H']}, {sizes['W']}), "
                         f"got {tuple(relative_depth.shape)}")
    if tuple(weights.shape) != tuple(intensities.shape):
        raise ShapeError(f"weights must have the shape of intensities {tuple(intensities.shape)}, "
                         f"got {tuple(weights.shape)}")
    check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    _check_light_model(light_model)
    if not (len(search_mm) == 2 and search_mm[0] < search_mm[1]):
        raise InputError(f"search_mm must be an increasing pair, got {search_mm}")
    check_positive(tolerance_mm, "tolerance_mm")
    with torch.no_grad():
        field = _LightField(light_model, sizes["H"], sizes["W"], pixel_pitch_mm, card_height_mm, intensities,
                            _OFFSET_STRIDE)
        s = _OFFSET_STRIDE
        mean = relative_depth.mean(dim=(2, 3), keepdim=True)
        images, used = intensities[..., ::s, ::s], weights[..., ::s, ::s].to(intensities)
        depth = (relative_depth - mean)[..., ::s, ::s]
        centre = torch.zeros(sizes["B"], device=intensities.device, dtype=intensities.dtype)
        best = _search_offset(field, images, used, depth, centre, (search_mm[0], search_mm[1]), tolerance_mm)
    return best.view(-1, 1, 1, 1) - mean


# ----------------------------------------------------------------------------------------------------------------
# Tilt: the plane of the height, which integration cannot see across steps
# ----------------------------------------------------------------------------------------------------------------


def _residuals(field: _LightField, images: Tensor, used: Tensor, depth: Tensor) -> Tensor:
    """The residuals of each pixel's least-squares fit with the light vectors at ``depth``, (B, K, H, W)."""
    lx, ly, lz, _ = field(depth)
    m, _, _ = _fit(images, lx, ly, lz, used)
    return images - _predict(m, lx, ly, lz)


def _plane(size: tuple[int, int], domain: Tensor, tilt: Tensor, pitch: float) -> Tensor:
    """The plane of slopes ``tilt`` (B, 2) on the ``size`` pixel grid of ``pitch`` mm, zero mean over the domain,
    (B, 1, H, W)."""
    x, y = pixel_grid_mm(*size, pitch, device=tilt.device, dtype=tilt.dtype)
    weight = domain.to(tilt.dtype)
    count = weight.sum(dim=(1, 2, 3)).clamp_min(1)
    xc, yc = ((weight * c).sum(dim=(1, 2, 3)) / count for c in (x, y))
    a, b = (tilt[:, i].view(-1, 1, 1, 1) for i in (0, 1))
    return a * (x - xc.view(-1, 1, 1, 1)) + b * (y - yc.view(-1, 1, 1, 1))


def _phase_sums(x: Tensor) -> Tensor:
    """Sums of ``x`` (B, C, H, W) over each of the _TILT_PHASES² interleaved pixel lattices, (B, C, P²)."""
    p = _TILT_PHASES
    height, width = x.shape[-2:]
    padded = F.pad(x, (0, -width % p, 0, -height % p))
    b, c, h, w = padded.shape
    return padded.reshape(b, c, h // p, p, w // p, p).sum(dim=(2, 4)).flatten(2)


def _tilt_step(field: _LightField, images: Tensor, used: Tensor, depth: Tensor, tilt: Tensor) -> Tensor:
    r"""The tilt (B, 2) that the images ask of the plane of ``depth`` (which holds ``tilt``), where clear of noise.

    The images' residual is a sum over pixels, each a function of its own height only, so a Gauss–Newton step on
    the plane :math:`c + a x + b y` needs each pixel's residuals :math:`e_p` and their derivative in its height
    :math:`J_p` (a forward difference over :data:`_TILT_STEP_MM`): :math:`H = \sum_p (J_p^T W_p J_p)\,\phi_p
    \phi_p^T`, :math:`g = \sum_p (J_p^T W_p e_p)\,\phi_p`, :math:`\phi = (1, x, y)`. The same step on each of
    the _TILT_PHASES² interleaved lattices of pixels gives independent estimates, whose spread is the tilt's
    standard error :math:`s` (the noise of the images and of the card they were divided by: 2-3 µm/mm on the rig's
    8-bit 400 × 400 captures, 20-40 µm/mm on a 64-pixel field). A slope is kept only where it stands
    :data:`_TILT_SIGMAS` standard errors clear of zero, else it is 0: most cloth has no lost steps, and a smooth
    one keeps its integrated plane rather than take the noise's (a least mean-square shrinkage,
    :math:`t\,\max(0, 1 - s^2/t^2)`, still kept three quarters of a two-sigma draw: 50-80 µm/mm of made-up tilt
    on noisy 64-pixel fields).
    """
    residual = _residuals(field, images, used, depth)
    jacobian = (_residuals(field, images, used, depth + _TILT_STEP_MM) - residual) / _TILT_STEP_MM
    slope = (used * jacobian * residual).sum(dim=1, keepdim=True)
    curvature = (used * jacobian.square()).sum(dim=1, keepdim=True)
    phi = (torch.ones_like(slope), field.x.expand_as(slope), field.y.expand_as(slope))
    # the normal equations' six entries and the right-hand side's three, summed over each lattice and over all
    entries = torch.cat([curvature * phi[i] * phi[j] for i, j in zip(_ROWS, _COLS, strict=True)]
                        + [slope * f for f in phi], dim=1)
    sums = _phase_sums(entries).double()  # (B, 9, P²)
    sums = torch.cat([sums, sums.sum(dim=2, keepdim=True)], dim=2).transpose(1, 2)  # (B, P² + 1, 9)
    matrix = sums[..., [0, 1, 2, 1, 3, 4, 2, 4, 5]].unflatten(-1, (3, 3))
    solution, info = torch.linalg.solve_ex(matrix, -sums[..., 6:].unsqueeze(-1))
    steps = solution[..., 1:, 0]  # (B, P² + 1, 2): the slopes' steps, on each lattice and on all pixels
    lattices, whole = steps[:, :-1], steps[:, -1]
    finite = ((info == 0).all(dim=1) & torch.isfinite(steps).flatten(1).all(dim=1)).view(-1, 1)
    error_sq = lattices.var(dim=1) / lattices.shape[1]  # the squared standard error of the step on all pixels
    raw = tilt.double() + whole
    clear = finite & (raw.square() > _TILT_SIGMAS**2 * error_sq)
    return torch.where(clear, raw, torch.zeros_like(raw)).to(tilt.dtype)


# ----------------------------------------------------------------------------------------------------------------
# Integration of the solved pixels
# ----------------------------------------------------------------------------------------------------------------


def _confidence(fit: tuple[Tensor, Tensor, Tensor], matrix: tuple, used: Tensor, domain: Tensor,
                noise_sq: Tensor | None = None) -> tuple[Tensor, Tensor]:
    r"""Per-pixel confidence of the slopes in the integration, (B, 1, H, W), in [0, 1], and where the slopes are
    noisy: their standard deviation, from the images' noise variance ``noise_sq`` (B, 1, 1, 1), above
    :data:`_SLOPE_NOISE` (none without ``noise_sq``: then every slope is taken as it is).

    The inverse of the slope's variance, relative to its median over the solved pixels: a pixel's normal varies
    as :math:`\sigma^2 \operatorname{tr}(G^{-1}) / \rho^2` (:math:`G` its normal matrix) and its slope
    :math:`-n_x / n_z` as that over :math:`n_z^4` (none for :math:`n_z \le 0`), so steep walls seen by few grazing
    lights (a knit's loops) get little weight where they would otherwise add up to millimetres of tilt. Pixels
    fitted to exactly three observations (no check of their fit) get a tenth; pixels next to an unsolved one (a
    crevice lit by fewer than three LEDs) :data:`_EDGE_CONFIDENCE`, since their normal sees the crevice's wall;
    unsolved pixels 0.
    """
    albedo, normals, solved = fit
    (c00, _, _, c11, _, c22), det = matrix
    variance = (c00 + c11 + c22) / det  # tr(G^-1)
    # a normal facing away from the camera (n_z <= 0: an ill-posed fit, often with an albedo several times the
    # cloth's) has no usable slope: normals_to_gradients caps it at 1/min_nz, and an even power of n_z would
    # give that cap the weight of a well-seen facet (a knit's isolated 1-2 mm spikes beside unsolved crevices)
    facing = normals[:, 2:3].clamp_min(0)
    inverse = albedo.square() * facing.pow(4) / variance.clamp_min(torch.finfo(albedo.dtype).tiny)
    inverse = torch.where(solved, inverse, torch.zeros_like(inverse)).nan_to_num(0.0, posinf=0.0)
    confidence = (inverse / _median(inverse, solved).clamp_min(torch.finfo(albedo.dtype).tiny)).clamp(0, 1)
    confidence = confidence * torch.where(_count(used) >= 4, 1.0, _THREE_OBSERVATIONS_CONFIDENCE)
    gap = (domain & ~solved).to(albedo.dtype)
    padded = F.pad(gap, (1, 1, 1, 1), value=0.0)  # the image border is no gap
    beside = (padded[..., 1:-1, :-2] + padded[..., 1:-1, 2:] + padded[..., :-2, 1:-1] + padded[..., 2:, 1:-1]) > 0
    confidence = torch.where(beside, confidence.clamp(max=_EDGE_CONFIDENCE), confidence)
    noisy = ~solved if noise_sq is None else ~solved | (noise_sq > _SLOPE_NOISE**2 * inverse)
    return torch.where(solved, confidence, torch.zeros_like(confidence)), noisy


def _box(x: Tensor) -> Tensor:
    """Mean over a :data:`_FILL_SIZE`-pixel square around each pixel, zeros beyond the border: two 1-D passes, each
    a sum of shifted views in the window's order divided by its length (``avg_pool2d``'s value, to the bit; on the
    CPU its 9-tap passes took 2.8 ms on 400^2, the views' sums 0.75 ms)."""
    return _box_pass(_box_pass(x, -2), -1)


def _box_pass(x: Tensor, dim: int) -> Tensor:
    """:func:`_box` along one dimension (-2 or -1)."""
    k, size = _FILL_SIZE, x.shape[dim]
    padding = (0, 0, k // 2, k // 2) if dim == -2 else (k // 2, k // 2)
    padded = F.pad(x, padding)
    total = padded.narrow(dim, 0, size).clone()
    for start in range(1, k):
        total += padded.narrow(dim, start, size)
    return total / k


def _fill(p: Tensor, q: Tensor, confidence: Tensor) -> tuple[Tensor, Tensor]:
    """Slopes with the unconfident ones replaced, in proportion, by the confidence-weighted mean around them
    (normalised convolution over :data:`_FILL_SIZE` pixels: the ratio of two box means, whose border counts
    cancel)."""
    den = _box(confidence).clamp_min(1e-6)
    filled_p, filled_q = (confidence * g + (1 - confidence) * _box(g * confidence) / den for g in (p, q))
    return filled_p, filled_q


def _integrate(p: Tensor, q: Tensor, confidence: Tensor, domain: Tensor, method: str, pitch: float,
               previous: Tensor | None, mask_given: bool, noisy: Tensor | None = None) -> Tensor:
    """Height (zero mean over the domain) from the slopes, weighted by ``confidence`` (:func:`_confidence`).

    ``"fill"``: unconfident slopes replaced by their confident surroundings (:func:`_fill`), then a Neumann (DCT)
    solve on the rectangle (fast; the rest of the rectangle is a membrane when a mask is given). ``"masked"``:
    the slopes, those both ``noisy`` (:func:`_confidence`; all when ``None``) and below :data:`_FILL_BELOW`
    confidence replaced by the filled ones, weighted by their confidence (at least :data:`_CONFIDENCE_FLOOR`), by
    least squares on the domain (edges carry the weighted mean of their two pixels' slopes): multigrid-
    preconditioned conjugate gradients warm-started from ``previous`` (mm; the fill's depth when ``None``), to
    :data:`_FINAL_CG_TOLERANCE`. The weights keep the steep, noisy walls of a knit's loops from tilting their
    surroundings; the floor and the filled slopes keep every region tied to its neighbours. Other integrators of
    :func:`psmini.integrate.integrate` get the pixels with any confidence as their mask.
    """
    if method not in ("fill", "masked"):
        return integrate(p, q, method=method, pixel_pitch_mm=pitch, mask=confidence > 0)
    filled = _fill(p, q, confidence)
    if method == "fill" or previous is None:
        start = dct_poisson(*filled, pitch, domain if mask_given else None)
        if method == "fill":
            return start
        previous = start
    weak = confidence < _FILL_BELOW if noisy is None else noisy & (confidence < _FILL_BELOW)  # noisy and unconfident
    p, q = torch.where(weak, filled[0], p), torch.where(weak, filled[1], q)
    half = torch.full_like(p, 0.5)
    wu, wv, tu, tv = _edge_system(p, -q, confidence.clamp_min(_CONFIDENCE_FLOOR), half, half)
    start = previous / pitch
    return pitch * solve_weighted_poisson(wu, wv, tu, tv, domain.to(p.dtype), start, _FINAL_CG_TOLERANCE)


# ----------------------------------------------------------------------------------------------------------------
# The stage
# ----------------------------------------------------------------------------------------------------------------


def _check_light_model(light_model: nn.Module) -> nn.Module:
    if not isinstance(light_model, nn.Module) or not hasattr(light_model, "count"):
        raise InputError(f"light_model must be a module of psmini.lights, got {type(light_model).__name__}")
    return light_model


def _check_options(options: NearLightOptions | None) -> NearLightOptions:
    if options is None:
        return NearLightOptions()
    if not isinstance(options, NearLightOptions):
        raise InputError(f"options must be a NearLightOptions, got {type(options).__name__}")
    return options


def _check_valid(valid: Tensor | None, intensities: Tensor) -> Tensor:
    if valid is None:
        return torch.ones_like(intensities, dtype=torch.bool)
    if not isinstance(valid, Tensor) or valid.shape not in (intensities.shape, (1, *intensities.shape[1:])):
        got = tuple(valid.shape) if isinstance(valid, Tensor) else type(valid).__name__
        raise ShapeError(f"valid must have the shape of the intensities {tuple(intensities.shape)}, got {got}")
    return valid.bool().expand_as(intensities)


def _check_gain(gain: Tensor | None, intensities: Tensor) -> Tensor | None:
    """The flat-field's gain checked as the flat-field checks its frames (broadcastable, finite), and >= 0."""
    batch, count, height, width = intensities.shape
    gain = _check_frame(gain, batch, count, height, width, "gain")
    if gain is None:
        return None
    if bool((gain < 0).any()):
        raise InputError(f"gain must be >= 0 (the flat-field's factor per reading), got a minimum of "
                         f"{float(gain.min()):.3g}")
    return gain.detach() if gain.requires_grad else gain  # the caller's tensor itself: its terms are kept


def solve_near_light(
    intensities: Tensor,
    light_model: nn.Module,
    pixel_pitch_mm: float,
    card_height_mm: float | None,
    valid: Tensor | None = None,
    mask: Tensor | None = None,
    options: NearLightOptions | None = None,
    gain: Tensor | None = None,
) -> NearLightResult:
    r"""The near-light stage: flat-fielded images → albedo, normals, absolute depth, by alternation.

    Starting from the plane at ``options.initial_height_mm``, each alternation evaluates the light vectors at the
    current depth (one fused pass from parts computed once), solves the per-pixel weighted least squares, and
    integrates the slopes weighted by their inverse variance; the result is placed at the height that explains the
    images best (a scan in the first alternation, parabolic Newton steps later) and, at full resolution, tilted by
    the plane the images ask for where it stands clear of their noise (``options.estimate_tilt``: the steps that
    integration loses, which add up on a purl). The selection of observations
    (shadows by a noise model :math:`\sigma^2 = s^2 \sigma_0^2 + s\,g I`, :math:`s` the flat-field's ``gain``,
    highlights and cast shadows by leave-one-out residuals, the farther of the two first, grazing light kept) is
    decided once, in one alternation, and then kept. The first alternations run on 2 × 2-averaged images; at full
    resolution the alternations stop when ``options.change_percentile`` of the solved pixels' normals moved less
    than ``options.tolerance_deg`` since the previous one, and the last normals are integrated by
    ``options.integrator`` (warm-started; see :class:`NearLightOptions`). The images are not flat-fielded here: that
    is the pipeline's first stage (:func:`psmini.flatfield.flatfield`).

    Differentiable with respect to the intensities and the light model's parameters through the last
    alternation's solve (the offset search and the observations' selection are not differentiated). On the CPU a
    batch is solved in chunks of one 8 × 400 × 400 capture's size, whose working set stays in the caches; on CUDA
    in one piece. Either way each sample is solved as it is alone (its own offset, selection and convergence
    test), up to the rounding of batched operations (FFTs, multi-threaded sums round otherwise for another batch
    size), which the alternations' discrete decisions can carry further: on a noisy 64 × 64 capture, 0.9 µm of
    depth and one pixel's selection.

    Args:
        intensities: flat-fielded images :math:`(B, K, H, W)` (divided by the card under the same LEDs and
            multiplied by its albedo), or dark-subtracted raw images when ``card_height_mm`` is ``None``.
        light_model: a point or LED model of :mod:`psmini.lights` (positions in mm, origin on the optical axis at
            the card plane).
        pixel_pitch_mm: pixel size on the cloth, mm.
        card_height_mm: height of the card the images were divided by, mm; ``None`` for raw images (the height is
            then observable only through the inverse-square law).
        valid: observations to use at all, :math:`(B, K, H, W)` bool (the flat-field's validity: saturation,
            untrusted card); all when omitted.
        mask: pixels to solve and integrate, :math:`(B, 1, H, W)`; all when omitted.
        options: :class:`NearLightOptions`; defaults when omitted.
        gain: the flat-field's gain (:attr:`psmini.flatfield.FlatFieldResult.gain`), :math:`(B|1, K|1, H, W)`: the
            factor each raw reading was multiplied by. The noise model scales each observation's noise by it
            (read noise with its square, shot noise with itself): on the rig's card the gain varies sixfold across
            the field, and without it the noise is underestimated where the card is dim, so that the highlight and
            shadow tests judge observations there by too small a noise. ``None``: the same noise for every
            observation (raw images).

    Returns:
        :class:`NearLightResult`; ``depth`` is the absolute height above the card plane's origin, mm (unsolved
        pixels inside the mask are filled from their rims), ``mask`` the solved pixels, ``iterations`` the
        alternations run.

    Raises:
        ShapeError: when the shapes do not match (K of the images vs the light model, mask, valid, gain).
        InputError: for NaN input, a negative gain, a light model without positions, bad options or a light below
            the card.

    Example:
        >>> from psmini.lights import LEDLights, ring_lights
        >>> ring = ring_lights(8, 58.0)
        >>> leds = LEDLights(ring * 18.6, -ring)
        >>> result = solve_near_light(torch.rand(1, 8, 16, 16) + 0.5, leds, 0.025, 0.0,
        ...                           options=NearLightOptions(max_iterations=2))
        >>> result.depth.shape, result.iterations <= 2
        (torch.Size([1, 1, 16, 16]), True)
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_finite(intensities, "intensities")
    check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    if not isinstance(light_model, PointLights) and not hasattr(light_model, "positions_mm"):
        raise InputError(f"the near-light solver needs a point or LED model, got {type(light_model).__name__}")
    _check_light_model(light_model)
    if light_model.count != sizes["K"]:
        raise ShapeError(f"the light model has {light_model.count} lights but intensities has K={sizes['K']}")
    if card_height_mm is not None and not (isinstance(card_height_mm, (int, float)) and math.isfinite(card_height_mm)):
        raise InputError(f"card_height_mm must be a finite number or None, got {card_height_mm!r}")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    valid = _check_valid(valid, intensities)
    gain = _check_gain(gain, intensities)
    options = _check_options(options)
    parts = [_solve(intensities[part], valid[part], batch_part(mask, intensities, part, "mask"), light_model,
                    pixel_pitch_mm, card_height_mm, options, batch_part(gain, intensities, part, "gain"))
             for part in chunks(intensities)]
    return parts[0] if len(parts) == 1 else NearLightResult.concatenate(parts)


def _solve(images: Tensor, valid: Tensor, mask: Tensor | None, light_model: nn.Module, pitch: float,
           card_height: float | None, options: NearLightOptions, gain: Tensor | None = None) -> NearLightResult:
    """:func:`solve_near_light` without its guards: alternations at half resolution, then at full resolution.

    The light field varies slowly with the height (about a degree per millimetre), so the alternations that move
    the surface by tenths of a millimetre run on 2 × 2-averaged images (a quarter of the work, and an integration
    that converges faster); the full-resolution alternations then start from that depth (upsampled), with a
    warm-started integration, and usually stop after two.
    """
    batch, _, height, width = images.shape
    domain = torch.ones(batch, 1, height, width, dtype=torch.bool, device=images.device) if mask is None \
        else mask.bool()
    start = torch.full((batch,), float(options.initial_height_mm), device=images.device, dtype=images.dtype)
    state = _State(depth=start.view(-1, 1, 1, 1).expand(batch, 1, height, width).clone(), offset=start,
                   tilt=images.new_zeros(batch, 2))
    with torch.no_grad():
        if height % 2 == 0 and width % 2 == 0 and min(height, width) >= _MIN_COARSE_SIZE:
            small_mask = None if mask is None else F.avg_pool2d(mask.to(images.dtype), 2) > 0.5
            small_valid = F.avg_pool2d(valid.to(images.dtype), 2) > 0.999
            small_domain = torch.ones_like(small_mask if small_mask is not None else small_valid[:, :1]) \
                if small_mask is None else small_mask
            coarse = _State(depth=F.avg_pool2d(state.depth, 2), offset=start, tilt=state.tilt)
            small_gain = _pooled_gain(gain, images)
            _alternate(F.avg_pool2d(images, 2), small_valid, small_mask, small_domain, light_model, 2 * pitch,
                       card_height, options, coarse, scan=options.search_mm,
                       tolerance=_COARSE_TOLERANCE_FACTOR * options.tolerance_deg, final=False,
                       first_level=True, s=_OFFSET_STRIDE // 2, gain=small_gain)
            size = (height, width)
            state = _State(depth=F.interpolate(coarse.depth, size=size, mode="bilinear", align_corners=False),
                           offset=coarse.offset, tilt=coarse.tilt, changes=coarse.changes,
                           iterations=coarse.iterations,
                           # (the coarse level's alternations set its relative depth)
                           relative=F.interpolate(coarse.relative,  # type: ignore[arg-type]
                                                  size=size, mode="bilinear", align_corners=False))
            scan, first = _FINE_SEARCH_MM, False  # pooling biases the coarse level's offset: scan again
        else:
            scan, first = options.search_mm, True
        field = _alternate(images, valid, mask, domain, light_model, pitch, card_height, options, state, scan=scan,
                           tolerance=options.tolerance_deg, final=True, first_level=first, gain=gain)
    # the last solve, at the final depth, carries the gradients (intensities, light model's parameters); without
    # them, a converged iteration's last fit is that solve already
    learnable = torch.is_grad_enabled() and _needs_gradient(light_model)
    if learnable:  # the alternations' field was built without gradients: its terms hold no graph of the model
        field = _LightField(light_model, height, width, pitch, card_height, images)
    if state.fit is None or learnable or torch.is_grad_enabled() and images.requires_grad:
        vectors = field(state.depth)
        # used and at_noise_floor below: set by the alternations, of which there is at least one
        state.fit = _fit(images, *vectors[:3], state.used)  # type: ignore[arg-type]
    albedo, normals = _split(state.fit[0], state.fit[1], mask)
    p, q = normals_to_gradients(normals)
    depth = state.depth
    if options.integrator == "masked" and mask is None:
        # the edge equations' trapezoidal rule flattens the finest relief (a silk's threads to a third): restored
        # on the rectangle, where the integration ran
        depth = _undo_edge_averaging(depth)
    return NearLightResult(albedo, normals, p, q, depth, albedo > 0,
                           weights=state.used & (albedo > 0),  # type: ignore[operator]
                           offset_mm=_masked_mean(state.depth, domain).view(-1), tilt=state.tilt,
                           iterations=state.iterations,
                           changes_deg=tuple(state.changes), converged=state.converged,
                           at_noise_floor=state.at_noise_floor & (albedo > 0))  # type: ignore[operator]


@dataclass
class _State:
    """What the alternations carry from one to the next (and from the coarse level to the fine one)."""

    depth: Tensor
    offset: Tensor
    tilt: Tensor  # (B, 2): the slopes of the plane added to the integrated height (_tilt_step)
    relative: Tensor | None = None
    used: Tensor | None = None
    changes: list[float] = dataclasses.field(default_factory=list)
    converged: bool = False
    iterations: int = 0
    fit: tuple | None = None
    at_noise_floor: Tensor | None = None  # (B, 1, H, W): see NearLightResult


def _alternate(images: Tensor, valid: Tensor, mask: Tensor | None, domain: Tensor, light_model: nn.Module,
               pitch: float, card_height: float | None, options: NearLightOptions, state: _State,
               scan: tuple[float, float], tolerance: float, final: bool,
               first_level: bool, s: int = _OFFSET_STRIDE, gain: Tensor | None = None) -> _LightField:
    """Alternations at one resolution, updating ``state`` in place; returns the level's light field.

    Each alternation: light vectors at the current depth, normals (with the selection of observations updated in
    the first :data:`_SELECTION_UPDATES`), then, unless the normals moved less than ``tolerance`` degrees (the
    ``change_percentile`` quantile over the solved pixels) since the last alternation, a new depth: integration
    (warm-started) and the offset (scanned over ``scan`` in the first alternation, on every ``s``-th pixel). The
    test on the normals stops without one more integration: the depth is then consistent with its normals.
    The test is made per batch item, and an item that passes leaves the batch: a batch costs what its items cost
    one by one, not its slowest item's alternations times the batch size.
    The alternations at the coarse level integrate by a Neumann (DCT) solve on the rectangle (their depth only
    places the light field); with ``final``, by ``options.integrator``, warm-started from the last depth. When every
    item passed the test, ``state.fit`` keeps their last fits: the fits at the final depth.
    """
    method = options.integrator if final else "fill"
    batch, _, height, width = images.shape
    field = _light_field(light_model, height, width, pitch, card_height, images)
    coarse = _light_field(light_model, height, width, pitch, card_height, images, s)
    tilt_field = _light_field(light_model, height, width, pitch, card_height, images, _TILT_STRIDE) \
        if final and options.estimate_tilt else None
    rejection = _Rejection(images, valid, options, gain)
    used = rejection.candidates
    state.converged = False
    active = torch.arange(batch, device=images.device)  # the items still alternating
    last_m = images.new_zeros(batch, 3, height, width)
    last_posed = torch.zeros(batch, 1, height, width, dtype=torch.bool, device=images.device)
    previous: Tensor | None = None
    level = images.mean(dim=(1, 2, 3), keepdim=True)  # the signal at which the noise model's variance is read
    select_at = 1 if first_level and options.max_iterations > 1 else 0
    for iteration in range(options.max_iterations):
        state.iterations += 1
        take = _taker(active, batch)
        sub_images, sub_mask, sub_domain = take(images), take(mask), take(domain)
        vectors = field(take(state.depth))
        fit = _fit(sub_images, *vectors[:3], take(used))
        albedo, normals = _split(*fit[:2], sub_mask)
        # the observations' selection: its updates (one highlight and one cast shadow per pixel and update) run in
        # one alternation, at fixed lights, once the surface is near its height (the second alternation when the
        # height is still unknown: far from it, model errors look like highlights and shadows); then the selection
        # stays: flips of a few pixels in every alternation would keep the iteration from converging. No item has
        # left the batch yet (the first test comes after it).
        if iteration == select_at:  # fewer rounds at half resolution, which only places the surface
            used, fit, albedo, normals = _select(rejection, images, vectors, used, fit, albedo, normals, mask,
                                                 _SELECTION_UPDATES if final else 1,
                                                 _FINE_HIGHLIGHT_ROUNDS if final else 1)
        state.used = used
        if previous is not None:
            changes = _changes(normals - previous, (albedo > 0) & sub_domain, options.change_percentile)
            state.changes.append(float(changes.max()))
            logger.info("near-light alternation %d at %d x %d: %.0f%% of the normals moved less than %.2e deg",
                        len(state.changes), height, width, 100 * options.change_percentile, state.changes[-1])
            done = changes < tolerance
            if bool(done.any()):  # these items' fits are at their final depth
                last_m[active[done]], last_posed[active[done]] = fit[0][done], fit[1][done]
                if bool(done.all()):
                    state.converged = True
                    break
                keep = ~done
                active, fit, albedo, normals = active[keep], _subset(fit, keep), albedo[keep], normals[keep]
                take = _taker(active, batch)
                sub_images, sub_mask, sub_domain = take(images), take(mask), take(domain)
        sub_used = take(used)
        solved = albedo > 0
        previous = normals
        p, q = normals_to_gradients(normals)
        noise_sq = None if rejection.noise is None else \
            take(rejection.noise[0] + rejection.noise[1] * level)
        confidence, noisy = _confidence((albedo, normals, solved), fit[2], sub_used, sub_domain, noise_sq)
        # warm start from the last depth at this level (the coarse level's lacks the weave: the fill's is closer)
        warm = take(state.relative) if iteration > 0 else None
        relative = _integrate(p, q, confidence, sub_domain, method, pitch, warm, mask is not None, noisy)
        tilt = (tilt_field, take(state.tilt)) if tilt_field is not None else None
        placed = _place(sub_images, sub_used & solved, relative, sub_domain, coarse, take(state.offset), tilt,
                        scan if iteration == 0 else None, options, s)
        if active.numel() == batch:
            state.depth, state.offset, state.relative, state.tilt = placed
        else:
            # (state.relative: set by the first alternation, in which every item is active)
            state.depth, state.offset, state.relative, state.tilt = (
                whole.index_copy(0, active, part)  # type: ignore[union-attr]
                for whole, part in zip((state.depth, state.offset, state.relative, state.tilt), placed, strict=True))
    state.fit = (last_m, last_posed) if state.converged else None
    state.at_noise_floor = _at_noise_floor(rejection, used)
    return field


def _at_noise_floor(rejection: _Rejection, used: Tensor) -> Tensor:
    """Pixels whose selection ``used`` holds exactly three observations, one of them below the shadow level of the
    noise model (:meth:`_Rejection.settle_noise_model`; none before it is known): the selection's fallback keeps such a
    pixel's three rather than leave it with fewer."""
    count = _count(used)
    if rejection.noise is None:
        return torch.zeros_like(count, dtype=torch.bool)
    shadow = rejection.noise[0].sqrt() * _SHADOW_SIGMAS * rejection.noise_scale
    return (count == 3) & (_count(used & (rejection.intensities <= shadow)) > 0)


def _taker(active: Tensor, batch: int):
    """Indexing of full-batch tensors (or ``None``) by the ``active`` items; the tensor itself when all are."""
    if active.numel() == batch:
        return lambda x: x
    return lambda x: None if x is None else x[active]


def _subset(fit: tuple, keep: Tensor) -> tuple:
    """A fit of :func:`_fit` restricted to the ``keep`` items."""
    m, posed, (cofactors, det) = fit
    return m[keep], posed[keep], (tuple(c[keep] for c in cofactors), det[keep])


def _place(images: Tensor, used: Tensor, relative: Tensor, domain: Tensor, coarse: _LightField, offset: Tensor,
           tilt: tuple[_LightField, Tensor] | None, search: tuple[float, float] | None, options: NearLightOptions,
           s: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The depth ``relative`` (re-centred on the domain) plus a plane and the offset that explain the images best.

    The offset is scanned over ``search`` when given, then refined by parabolic steps from ``offset``, on the field
    ``coarse`` of every ``s``-th pixel (kept without ``options.estimate_offset``). ``tilt``, when given, is the
    field of the tilt's pixels and the current tilt (B, 2): the plane of that tilt is added before the offset's
    search, and a new tilt found after it (:func:`_tilt_step`). Returns the depth, the offset (B,), the re-centred
    relative depth and the tilt (zeros without ``tilt``)."""
    relative = relative - _masked_mean(relative, domain)
    if tilt is not None:
        tilt_field, slopes = tilt
        planed = relative + _plane((images.shape[-2], images.shape[-1]), domain, slopes, tilt_field.pitch)
    else:
        planed = relative
    if options.estimate_offset:
        sub_images, sub_used, sub_depth = images[..., ::s, ::s], used[..., ::s, ::s].to(images), planed[..., ::s, ::s]
        points = _SCAN_POINTS if search is None or search[1] - search[0] > 1.5 else _FINE_SCAN_POINTS
        offset = _search_offset(coarse, sub_images, sub_used, sub_depth, offset, search, _OFFSET_TOLERANCE_MM, points)
    if tilt is None:
        return planed + offset.view(-1, 1, 1, 1), offset, relative, images.new_zeros(images.shape[0], 2)
    t = tilt_field.stride
    slopes = _tilt_step(tilt_field, images[..., ::t, ::t], used[..., ::t, ::t].to(images),
                        planed[..., ::t, ::t] + offset.view(-1, 1, 1, 1), slopes)
    plane = _plane((images.shape[-2], images.shape[-1]), domain, slopes, tilt_field.pitch)
    return relative + plane + offset.view(-1, 1, 1, 1), offset, relative, slopes


def _masked_mean(x: Tensor, region: Tensor) -> Tensor:
    weight = region.to(x.dtype)
    return (x * weight).sum(dim=(1, 2, 3), keepdim=True) / weight.sum(dim=(1, 2, 3), keepdim=True).clamp_min(1)


def _changes(difference: Tensor, region: Tensor, percentile: float) -> Tensor:
    """The ``percentile`` quantile over the region of the angle between unit normals whose difference is given,
    degrees, per batch item (B,) (2 asin(|a - b| / 2)); 0 for an item with no pixel in the region."""
    chord = difference.square().sum(dim=1, keepdim=True).sqrt()
    largest = []
    for c, r in zip(chord, region, strict=True):
        values = c.masked_select(r)
        rank = min(values.numel(), max(1, math.ceil(percentile * values.numel())))
        largest.append(float(values.kthvalue(rank).values) if values.numel() else 0.0)
    return torch.tensor([math.degrees(2 * math.asin(min(1.0, x / 2))) for x in largest], device=difference.device)


@dataclass(frozen=True)
class RefineOptions:
    """Options of :func:`refine_depth`.

    Attributes:
        scales: downsampling factors, coarse to fine.
        steps: L-BFGS iterations per scale.
        huber_delta: Huber threshold, relative to the mean intensity.
        estimate_offset: re-estimate the mean height after refining; otherwise keep the mean of the start.

    Raises:
        InputError: for values out of range.

    Example:
        >>> RefineOptions(scales=(2, 1)).scales
        (2, 1)
    """

    scales: tuple[int, ...] = (4, 2, 1)
    steps: int = 30
    huber_delta: float = 0.02
    estimate_offset: bool = True

    def __post_init__(self) -> None:
        if not self.scales or any(not isinstance(s, int) or s < 1 for s in self.scales) or not (
                isinstance(self.steps, int) and self.steps >= 1) or not self.huber_delta > 0:
            raise InputError(f"scales must be positive integers, steps >= 1, huber_delta > 0; got {self.scales}, "
                             f"{self.steps}, {self.huber_delta}")
        object.__setattr__(self, "scales", tuple(self.scales))


def refine_depth(
    intensities: Tensor,
    light_model: nn.Module,
    depth: Tensor,
    pixel_pitch_mm: float,
    weights: Tensor | None = None,
    card_height_mm: float | None = None,
    options: RefineOptions | None = None,
) -> tuple[Tensor, Tensor, list[float]]:
    r"""Refine a depth map by minimising a robust re-rendering loss, coarse to fine (L-BFGS).

    At each scale the depth (downsampled by ``scale``) is the only parameter: normals come from its central
    differences, light vectors from the light model at its points, the albedo per pixel in closed form
    (:math:`\rho = \sum_k w_k I_k s_k / \sum_k w_k s_k^2`, :math:`s_k = \max(n \cdot L_k, 0)`), and the loss is the
    Huber loss of :math:`I_k - \rho s_k` over the weighted observations, divided by the mean intensity. The
    refined depth of one scale, upsampled, starts the next. The loss barely constrains the mean height (a
    shift changes only the light field's slow variation), so with ``estimate_offset`` the refined shape is placed
    at the height found by :func:`estimate_height_offset`.

    Args:
        intensities: images, shape :math:`(B, K, H, W)` (flat-fielded when ``card_height_mm`` is given).
        light_model: a module of :mod:`psmini.lights`.
        depth: starting height, shape :math:`(B, 1, H, W)`, mm (e.g. from :func:`near_light_photometric_stereo`).
        pixel_pitch_mm: pixel size, mm.
        weights: observations to use, :math:`(B, K, H, W)`; all when omitted.
        card_height_mm: see :func:`near_light_vectors`.
        options: :class:`RefineOptions` (scales, L-BFGS steps, Huber threshold, whether to re-estimate the mean
            height); defaults when omitted.

    Returns:
        refined depth :math:`(B, 1, H, W)` (detached), its albedo :math:`(B, 1, H, W)` and the loss after each scale.

    Example:
        >>> from psmini.lights import PointLights
        >>> lights = PointLights(torch.tensor([[10.0, 0, 10], [-10.0, 0, 10], [0, 10.0, 10], [0, -10.0, 10]]))
        >>> images = torch.rand(1, 4, 8, 8) + 0.5
        >>> options = RefineOptions(scales=(1,), steps=3)
        >>> depth, albedo, losses = refine_depth(images, lights, torch.zeros(1, 1, 8, 8), 0.1, options=options)
        >>> depth.shape
        torch.Size([1, 1, 8, 8])
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_finite(intensities, "intensities")
    check_finite(depth, "depth")
    options = RefineOptions() if options is None else options
    if not isinstance(options, RefineOptions):
        raise InputError(f"options must be a RefineOptions, got {type(options).__name__}")
    check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    _check_light_model(light_model)
    scales, steps, huber_delta = options.scales, options.steps, options.huber_delta
    weights = torch.ones_like(intensities) if weights is None else weights.to(intensities)
    norm = intensities.mean().clamp_min(1e-12)
    losses: list[float] = []
    current = depth.detach()
    for scale in scales:
        small = F.avg_pool2d(current, scale) if scale > 1 else current
        images = F.avg_pool2d(intensities, scale) if scale > 1 else intensities
        used = (F.avg_pool2d(weights, scale) > 0.999).to(images) if scale > 1 else weights
        parameter = small.clone().requires_grad_(True)
        optimizer = torch.optim.LBFGS([parameter], max_iter=steps, line_search_fn="strong_wolfe")

        # (this scale's tensors bound as defaults, not read from the loop's variables when the optimiser calls it)
        def closure(optimizer: torch.optim.Optimizer = optimizer, images: Tensor = images,
                    parameter: Tensor = parameter, scale: int = scale, used: Tensor = used) -> Tensor:
            optimizer.zero_grad()
            loss = _rendering_loss(images, light_model, parameter, pixel_pitch_mm * scale, used, card_height_mm,
                                   norm, huber_delta)
            loss.backward()
            return loss

        optimizer.step(closure)
        with torch.no_grad():
            losses.append(float(_rendering_loss(images, light_model, parameter, pixel_pitch_mm * scale, used,
                                                card_height_mm, norm, huber_delta)))
        refined = parameter.detach()
        if scale > 1:
            # carry only the correction to the finer level, so the fine detail of the start survives
            correction = refined - small
            current = current + F.interpolate(correction, size=(sizes["H"], sizes["W"]), mode="bilinear",
                                              align_corners=False)
        else:
            current = refined
    if options.estimate_offset:
        current = current + estimate_height_offset(
            intensities, light_model, current, pixel_pitch_mm, weights > 0, card_height_mm
        )
    with torch.no_grad():
        _, albedo = _shading_and_albedo(intensities, light_model, current, pixel_pitch_mm, weights, card_height_mm)
    return current, albedo, losses


def _shading_and_albedo(images, light_model, depth, pitch, weights, card_height_mm):
    normals = normals_from_height(depth, pitch)
    vectors = near_light_vectors(light_model, depth, pitch, card_height_mm)
    shading = (vectors * normals[:, None]).sum(dim=2).clamp_min(0)
    albedo = ((weights * images * shading).sum(1, keepdim=True)
              / (weights * shading.square()).sum(1, keepdim=True).clamp_min(1e-12))
    return shading, albedo


def _rendering_loss(images, light_model, depth, pitch, weights, card_height_mm, norm, delta) -> Tensor:
    shading, albedo = _shading_and_albedo(images, light_model, depth, pitch, weights, card_height_mm)
    residual = (images - albedo * shading) / norm
    loss = F.huber_loss(residual, torch.zeros_like(residual), reduction="none", delta=delta)
    return (loss * weights).sum() / weights.sum().clamp_min(1)
