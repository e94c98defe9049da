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

The absolute height of the cloth is observable because the light field is not uniform: the per-pixel
least-squares residual is zero only at the true height (noise-free, Lambertian). The solver estimates the
height offset by a one-dimensional search of that residual after each integration. With a card the search is
sharp (about a micrometre on noise-free renders of the rig); on raw images the height shows only through the
inverse-square law's variation across the field and is found to tens of micrometres.

Two departures from plain least squares keep textiles within the Lambertian model's reach. Metallic threads add a
specular lobe that only brightens: each pixel's brightest observation is tested against the fit of the others (a
leave-one-out residual, from the hat matrix) before any fit can be pulled by it. Crevices lit by fewer than three
LEDs stay unsolved, and the pixels on their rims, whose normals see the crevice's wall, get little weight in the
integration, so that the many crevices of a knit do not add up to a dome.

A second, joint refinement (:func:`refine_depth`) minimises a robust (Huber) re-rendering loss over the depth
map by gradient descent, coarse to fine, with the albedo solved in closed form at each step.
"""

from __future__ import annotations

import inspect
import logging
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import check_finite, check_mask, check_positive, check_shape
from psmini.errors import InputError, ShapeError
from psmini.flatfield import flatfield
from psmini.geometry import depth_to_points
from psmini.integrate import METHODS as INTEGRATORS
from psmini.integrate import integrate
from psmini.normals import albedo_normals, normals_to_gradients
from psmini.render import normals_from_height
from psmini.result import Reconstruction

__all__ = [
    "near_light_vectors",
    "robust_near_light_normals",
    "estimate_height_offset",
    "NearLightResult",
    "near_light_photometric_stereo",
    "refine_depth",
]

logger = logging.getLogger(__name__)

# Observations whose residual exceeds this fraction of the pixel's brightness scale are outliers (cast shadows,
# highlights): about ten times the noise of an 8-bit sensor at the rig's exposure.
_OUTLIER_FRACTION = 0.15
# Observations darker than this fraction of the pixel's brightest are taken as shadowed from the start: a cast or
# attached shadow reads only what the dark frame already removed.
_SHADOW_FRACTION = 0.02
# Light vectors within this cosine of the tangent plane count as attached shadows (grazing light).
_GRAZING_COSINE = 0.02
# Stride of the pixel grid on which the height offset is searched (the residual is smooth across pixels).
_OFFSET_STRIDE = 4
# An observation brighter than the fit of the others by more than this fraction of the pixel's brightness scale is
# a highlight: a few per cent of specular lobe is already degrees of normal error, while the fit of the others
# predicts a Lambertian observation to about the noise of an 8-bit sensor.
_HIGHLIGHT_FRACTION = 0.02
# ... or by more than this many times the image's typical residual per observation, when noise makes that larger.
_HIGHLIGHT_SIGMAS = 4.0
# A pixel is tested for a highlight only with at least this many observations: the fit of the others then stays
# overdetermined (an exactly determined fit of three turns noise into false highlights where light is scarce).
_HIGHLIGHT_MIN_OBS = 5
# Observations within this many noise levels of zero (relative to the pixel's brightest) are shadows, not light.
_SHADOW_SIGMAS = 3.0
# ... but an observation above this fraction of the brightest is light whatever the noise estimate says (a lobe
# spread over many LEDs inflates the estimate).
_SHADOW_CAP = 0.1
# Pixels next to an unsolved one get this confidence in the integration (see near_light_photometric_stereo).
_EDGE_CONFIDENCE = 0.01


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

    Example:
        >>> from psmini.lights import PointLights
        >>> lights = PointLights(torch.tensor([[10.0, 0, 10], [-10.0, 0, 10], [0, 10.0, 10]]))
        >>> vectors = near_light_vectors(lights, torch.zeros(1, 1, 4, 4), 0.025, card_height_mm=0.0)
        >>> torch.allclose(vectors[:, :, 2], torch.ones(1, 3, 4, 4))   # on the card itself l_z / l_z = 1
        True
    """
    check_shape(depth, ["B", "1", "H", "W"], "depth")
    directions, irradiance = light_model(depth_to_points(depth, pixel_pitch_mm))
    vectors = directions * irradiance
    if card_height_mm is None:
        return vectors
    card = depth_to_points(torch.full_like(depth[:1], float(card_height_mm)), pixel_pitch_mm)
    card_directions, card_irradiance = light_model(card)
    facing = card_directions[:, :, 2:3]
    if bool((facing.detach() <= 0).any()):
        raise InputError("flat-fielding needs every light above the card plane at every pixel")
    return vectors / (card_irradiance * facing)


def _predict(albedo: Tensor, normals: Tensor, vectors: Tensor) -> Tensor:
    """Unclamped Lambertian prediction ρ n·L_k, shape (B, K, H, W)."""
    return albedo * (vectors * normals[:, None]).sum(dim=2)


def _candidates(intensities: Tensor, valid: Tensor, shadow_fraction: float) -> Tensor:
    """Observations that may be lit: brighter than ``shadow_fraction`` of the pixel's brightest.

    Where fewer than three pass, a grazing light may still be real (0.01 next to 0.8 is lit, not shadowed): such
    pixels take their three brightest valid observations, provided the third is not zero. A pixel with fewer than
    three non-zero observations cannot be solved and gets none (it is left unsolved rather than fitted to shadows).
    """
    bright = valid & (intensities > shadow_fraction * intensities.amax(dim=1, keepdim=True))
    ranked = intensities.masked_fill(~valid, -torch.inf)
    third = ranked.topk(min(3, intensities.shape[1]), dim=1).values[:, -1:]
    brightest_three = valid & (intensities >= third) & (third > 0)
    return torch.where(bright.sum(dim=1, keepdim=True) >= 3, bright, brightest_three)


def robust_near_light_normals(
    intensities: Tensor,
    light_vectors: Tensor,
    valid: Tensor | None = None,
    mask: Tensor | None = None,
    iterations: int = 3,
    outlier_fraction: float = _OUTLIER_FRACTION,
    shadow_fraction: float = _SHADOW_FRACTION,
    highlight_fraction: float | None = _HIGHLIGHT_FRACTION,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Per-pixel least squares with per-pixel lights, dropping shadowed, specular and outlying observations.

    Observations darker than ``shadow_fraction`` of the pixel's brightest are left out throughout (a shadow
    reads about zero once the dark frame is subtracted), unless that leaves fewer than three: then the three
    brightest are used when none of them is zero. Highlights go next, before any fit can be pulled by them: while a
    pixel keeps five or more observations, its brightest relative to the light's strength (:math:`I_k / |L_k|`) is
    dropped when the least-squares fit of the others misses it by more than ``highlight_fraction`` of the
    pixel's scale :math:`\rho\,\overline{|L|}`, or by more than four times the image's noise level where that is
    larger (a specular lobe only adds light; leaving the suspect out of its own test avoids the masking of a plain
    residual test, where a glint tilts the fit until good observations look like the outliers). A shadow left
    among the others would make the brightest look like a highlight, so with the highlight test the shadow
    threshold also rises to three noise levels when that exceeds ``shadow_fraction``. After each solve, an
    observation is dropped when the light grazes or lies behind the estimated tangent plane (attached shadow:
    :math:`n \cdot L_k \le 0.02\,|L_k|`) or when its residual exceeds ``outlier_fraction`` of the pixel's scale
    (cast shadows); a pixel keeps its previous observations rather than fall below three. Pixels with fewer than three non-zero observations are left unsolved (albedo 0, normal
    (0, 0, 1)) with no weights.

    Args:
        intensities: images, shape :math:`(B, K, H, W)` (flat-fielded or dark-subtracted).
        light_vectors: per-pixel light vectors, shape :math:`(B, K, 3, H, W)` (:func:`near_light_vectors`).
        valid: observations to use at all, shape :math:`(B, K, H, W)` bool (saturation, untrusted card).
        mask: pixels to solve, shape :math:`(B, 1, H, W)`.
        iterations: re-solves after the first.
        outlier_fraction: residual threshold relative to the pixel's brightness scale.
        shadow_fraction: observations darker than this fraction of the pixel's brightest start as shadowed.
        highlight_fraction: excess over the fit of the others, relative to the pixel's brightness scale, at which
            the brightest observation is a highlight; ``None`` keeps every observation (purely Lambertian cloth).

    Returns:
        albedo :math:`(B, 1, H, W)`, unit normals :math:`(B, 3, H, W)` and the weights used :math:`(B, K, H, W)`.

    Example:
        >>> vectors = torch.tensor([[1.0, 0, 1], [-1.0, 0, 1], [0, 1.0, 1], [0, -1.0, 1]])[None, :, :, None, None]
        >>> normal = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> images = (vectors * normal[:, None]).sum(2)
        >>> albedo, normals, weights = robust_near_light_normals(images, vectors)
        >>> normals.flatten().tolist()
        [0.0, 0.0, 1.0]
    """
    if iterations < 0 or not 0 < outlier_fraction or not 0 <= shadow_fraction < 1:
        raise InputError(
            "iterations must be >= 0, outlier_fraction > 0 and shadow_fraction in [0, 1); "
            f"got {iterations}, {outlier_fraction}, {shadow_fraction}"
        )
    if highlight_fraction is not None and not highlight_fraction > 0:
        raise InputError(f"highlight_fraction must be > 0 or None, got {highlight_fraction}")
    valid_observations = torch.ones_like(intensities, dtype=torch.bool) if valid is None else valid.bool()
    candidates = _candidates(intensities, valid_observations, shadow_fraction)
    length = light_vectors.norm(dim=2)
    if highlight_fraction is not None:
        noise = _noise_level(intensities, light_vectors, length, candidates, mask)
        shadow_level = (noise * _SHADOW_SIGMAS).clamp(min=shadow_fraction, max=max(shadow_fraction, _SHADOW_CAP))
        candidates = _candidates(intensities, valid_observations, shadow_level)
        candidates = _reject_highlights(intensities, light_vectors, length, candidates, mask, highlight_fraction, noise)
    weights = candidates
    albedo, normals = albedo_normals(intensities, light_vectors, mask, weights)
    for _ in range(iterations):
        predicted = _predict(albedo, normals, light_vectors)
        scale = albedo * length.mean(dim=1, keepdim=True)
        lit = predicted > _GRAZING_COSINE * albedo * length
        inlier = (intensities - predicted).abs() <= outlier_fraction * scale
        proposal = candidates & lit & inlier  # from all candidates each time: an early drop can be undone
        enough = proposal.sum(dim=1, keepdim=True) >= 3
        weights = torch.where(enough, proposal, weights)
        albedo, normals = albedo_normals(intensities, light_vectors, mask, weights)
    return albedo, normals, weights & (albedo > 0)


def _reject_highlights(
    intensities: Tensor, vectors: Tensor, length: Tensor, weights: Tensor, mask: Tensor | None, fraction: float,
    noise: Tensor,
) -> Tensor:
    r"""Drop, one per pixel and round, the brightest observation (relative to its light) while the others find it too
    bright.

    For linear least squares the leave-one-out residual follows from the full fit: :math:`r_k / (1 - h_k)`, with
    :math:`r_k` the residual and :math:`h_k = L_k^T (\sum_j L_j L_j^T)^{-1} L_k` the leverage of light k (the hat
    matrix's diagonal; Cook and Weisberg, "Residuals and influence in regression", 1982). The brightest is a
    highlight when the magnitude of that residual exceeds, relative to the pixel's scale
    :math:`\rho\,\overline{|L|}`, ``fraction`` or :data:`_HIGHLIGHT_SIGMAS` times the image's noise level
    (:func:`_noise_level`) times the prediction's spread :math:`1 / \sqrt{1 - h_k}`, whichever is larger. At most K - 3 rounds; only pixels with
    :data:`_HIGHLIGHT_MIN_OBS` observations are tested, so a pixel keeps at least four.
    """
    scale = length.mean(dim=1, keepdim=True)
    relative = intensities / length.clamp_min(torch.finfo(length.dtype).tiny)
    for _ in range(intensities.shape[1] - 3):
        albedo, normals = albedo_normals(intensities, vectors, mask, weights)
        kept = (1 - _leverage(vectors, weights)).clamp_min(1e-6)  # 1 - h_k
        left_out = (intensities - _predict(albedo, normals, vectors)) / kept
        threshold = torch.maximum(noise * _HIGHLIGHT_SIGMAS / kept.sqrt(), torch.full_like(kept, fraction))
        brightest = relative.masked_fill(~weights, -torch.inf).argmax(dim=1, keepdim=True)
        suspect = torch.zeros_like(weights).scatter_(1, brightest, True)
        testable = (weights.sum(dim=1, keepdim=True) >= _HIGHLIGHT_MIN_OBS) & (albedo > 0)
        highlight = suspect & testable & (left_out.abs() > threshold * albedo * scale)
        if not bool(highlight.any()):  # one sync per round: most pixels of matte cloth stop after the first
            break
        weights = weights & ~highlight
    return weights


def _leverage(vectors: Tensor, weights: Tensor) -> Tensor:
    r"""Leverage :math:`L_k^T (\sum_{j \in weights} L_j L_j^T)^{-1} L_k` of every light, shape (B, K, H, W)."""
    moved = vectors.permute(0, 3, 4, 1, 2)  # (B, H, W, K, 3)
    used = weights.permute(0, 2, 3, 1).unsqueeze(-1).to(vectors)
    gram = (moved * used).transpose(-1, -2) @ moved
    ridge = 1e-9 * gram.diagonal(dim1=-2, dim2=-1).sum(dim=-1).clamp_min(1e-30)  # keeps dark pixels invertible
    gram = gram + ridge[..., None, None] * torch.eye(3, device=vectors.device, dtype=vectors.dtype)
    leverage = (moved * torch.linalg.solve(gram, moved.transpose(-1, -2)).transpose(-1, -2)).sum(dim=-1)
    return leverage.permute(0, 3, 1, 2)


def _noise_level(intensities: Tensor, vectors: Tensor, length: Tensor, weights: Tensor, mask: Tensor | None) -> Tensor:
    """The image's noise level relative to each pixel's scale, shape (B, 1, 1, 1).

    The median over pixels of the RMS residual per degree of freedom of a fit without the pixel's brightest
    observation (relative to its light), on pixels left with at least four: leaving the brightest out keeps a
    glint, which lifts mostly one observation, from passing for noise (a lobe spread over several LEDs still
    does, which makes the highlight test stricter, never looser).
    """
    relative = intensities / length.clamp_min(torch.finfo(length.dtype).tiny)
    brightest = relative.masked_fill(~weights, -torch.inf).argmax(dim=1, keepdim=True)
    weights = weights & ~torch.zeros_like(weights).scatter_(1, brightest, True)
    albedo, normals = albedo_normals(intensities, vectors, mask, weights)
    count = weights.sum(dim=1, keepdim=True)
    squared = ((intensities - _predict(albedo, normals, vectors)).square() * weights).sum(dim=1, keepdim=True)
    scale = (albedo * length.mean(dim=1, keepdim=True)).clamp_min(1e-12)
    residual = (squared / (count - 3).clamp_min(1)).sqrt() / scale
    usable = (count >= 4) & (albedo > 0)
    ranked = residual.masked_fill(~usable, torch.inf).flatten(1).sort(dim=1).values
    middle = (usable.flatten(1).sum(dim=1, keepdim=True) - 1).clamp_min(0) // 2
    return ranked.gather(1, middle).nan_to_num(0.0, posinf=0.0).view(-1, 1, 1, 1)


def _residual(intensities: Tensor, vectors: Tensor, weights: Tensor) -> Tensor:
    """Weighted least-squares residual per batch item, relative to the weighted signal, shape (B,)."""
    albedo, normals = albedo_normals(intensities, vectors, weights=weights)
    error = (intensities - _predict(albedo, normals, vectors)).square() * weights
    return error.flatten(1).sum(1) / (intensities.square() * weights).flatten(1).sum(1).clamp_min(1e-30)


def estimate_height_offset(
    intensities: Tensor,
    light_model: nn.Module,
    relative_depth: Tensor,
    pixel_pitch_mm: float,
    weights: Tensor,
    card_height_mm: float | None = None,
    search_mm: tuple[float, float] = (-3.0, 3.0),
    tolerance_mm: float = 1e-3,
) -> Tensor:
    r"""The height offset :math:`c` that makes ``relative_depth + c`` explain the images best.

    Minimises the per-pixel least-squares residual of the images under the light vectors at
    ``relative_depth + c`` over :math:`c`: a scan of 25 values over ``search_mm`` followed by a golden-section
    search in the best bracket, on every fourth pixel. Each batch item gets its own offset.

    Args:
        intensities: images, shape :math:`(B, K, H, W)`.
        light_model: a module of :mod:`psmini.lights`.
        relative_depth: height up to a constant, shape :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: pixel size, mm.
        weights: observations to use, shape :math:`(B, K, H, W)`.
        card_height_mm: see :func:`near_light_vectors`.
        search_mm: interval of offsets searched, mm, relative to the mean of ``relative_depth``.
        tolerance_mm: width at which the golden-section search stops, mm.

    Returns:
        offsets :math:`(B, 1, 1, 1)`, mm, such that ``relative_depth + offsets`` is the absolute height.

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
    low, high = search_mm
    if not low < high:
        raise InputError(f"search_mm must be an increasing pair, got {search_mm}")
    stride = _OFFSET_STRIDE
    images = intensities[..., ::stride, ::stride]
    used = weights[..., ::stride, ::stride].to(images)
    depth = relative_depth[..., ::stride, ::stride] - relative_depth.mean(dim=(2, 3), keepdim=True)
    pitch = pixel_pitch_mm * stride
    offsets = []
    with torch.no_grad():
        for b in range(images.shape[0]):  # one scalar search per sample; the work inside is batched over pixels

            def cost(c: float, b: int = b) -> float:
                vectors = near_light_vectors(light_model, depth[b : b + 1] + c, pitch, card_height_mm)
                return float(_residual(images[b : b + 1], vectors, used[b : b + 1])[0])

            grid = torch.linspace(low, high, 25).tolist()
            values = [cost(c) for c in grid]
            best = min(range(len(grid)), key=values.__getitem__)
            a, z = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
            offsets.append(_golden_section(cost, a, z, tolerance_mm))
    mean = relative_depth.mean(dim=(2, 3), keepdim=True)
    return torch.tensor(offsets, device=relative_depth.device, dtype=relative_depth.dtype).view(-1, 1, 1, 1) - mean


def _golden_section(cost, a: float, b: float, tolerance: float) -> float:
    """Minimum of a unimodal function on [a, b] by golden-section search."""
    ratio = (math.sqrt(5) - 1) / 2
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = cost(c), cost(d)
    while b - a > tolerance:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = cost(c)
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = cost(d)
    return (a + b) / 2


@dataclass
class NearLightResult(Reconstruction):
    """A :class:`~psmini.pipeline.Reconstruction` with the near-light solver's diagnostics.

    Attributes:
        weights: observations used in the last solve, :math:`(B, K, H, W)` bool (False: shadow, outlier, invalid).
        offset_mm: estimated mean height of the cloth above the card plane, :math:`(B,)`, mm.
        iterations: alternations run.
        changes_mm: largest depth change of each alternation, mm.
    """

    weights: Tensor | None = None
    offset_mm: Tensor | None = None
    iterations: int = 0
    changes_mm: tuple[float, ...] = ()


def _check_light_model(light_model: nn.Module) -> nn.Module:
    if not isinstance(light_model, nn.Module):
        raise InputError(f"light_model must be a module of psmini.lights, got {type(light_model).__name__}")
    return light_model


def near_light_photometric_stereo(
    images: Tensor,
    light_model: nn.Module,
    pixel_pitch_mm: float,
    *,
    reference: Tensor | None = None,
    dark: Tensor | None = None,
    reference_dark: Tensor | None = None,
    card_albedo: float = 1.0,
    card_height_mm: float = 0.0,
    initial_depth: Tensor | float = 0.0,
    estimate_offset: bool = True,
    mask: Tensor | None = None,
    saturation_level: float | None = None,
    min_reference: float = 0.02,
    integrator: str = "masked",
    max_iterations: int = 10,
    tolerance_mm: float = 1e-3,
    highlight_fraction: float | None = _HIGHLIGHT_FRACTION,
) -> NearLightResult:
    r"""Near-light photometric stereo by alternating per-pixel lights, normals and integrated depth.

    Starting from ``initial_depth`` (the card plane by default): the light vectors at the current depth
    (:func:`near_light_vectors`), robust per-pixel normals (:func:`robust_near_light_normals`), integration of
    their gradients, and, with ``estimate_offset``, the height offset that best explains the images
    (:func:`estimate_height_offset`); until the depth changes by less than ``tolerance_mm``.

    Args:
        images: raw images, shape :math:`(B, K, H, W)`, linear.
        light_model: a module of :mod:`psmini.lights` (LED positions in mm, origin on the axis at the card plane).
        pixel_pitch_mm: pixel size on the cloth, mm.
        reference: card images under the same LEDs (see :func:`psmini.flatfield.flatfield`); with it the images are
            flat-fielded and the vectors made relative to the card (gain, vignetting and LED intensities cancel).
        dark: the sample's dark frame.
        reference_dark: the card capture's dark frame.
        card_albedo: the card's albedo.
        card_height_mm: height of the card plane when its images were taken, mm.
        initial_depth: starting height, a number or :math:`(B, 1, H, W)`, mm.
        estimate_offset: search the absolute height after each integration; otherwise keep the mean height of
            ``initial_depth``.
        mask: pixels to solve, :math:`(B, 1, H, W)`.
        saturation_level: raw level of saturation, or ``None``.
        min_reference: see :func:`psmini.flatfield.flatfield`.
        integrator: method of :func:`psmini.integrate.integrate`. The default, least squares on the solved pixels
            (``"masked"``), keeps pixels left unsolved (lit by fewer than three LEDs: deep crevices of knits) from
            pulling the whole surface, as a solve on the full rectangle (``"fc"``) would; their depth is the
            solver's 0 plus the offset, and ``mask`` marks them. Pixels beside an unsolved one get a low
            confidence in integrators that take per-pixel weights (their normals see the crevice's wall; without
            this the knits' crevices added up to a dome of 17–29 µm, see ``benchmarks/nearlight.py``).
        max_iterations: most alternations.
        tolerance_mm: stop when the largest depth change falls below it, mm.
        highlight_fraction: see :func:`robust_near_light_normals`; ``None`` turns the highlight test off.

    Returns:
        :class:`NearLightResult`; ``depth`` is the absolute height above the card plane's origin, mm.

    Raises:
        ShapeError: when the shapes do not match (K of images vs the light model, mask, initial depth).
        InputError: for NaN input or bad options.

    Example:
        >>> from psmini.lights import LEDLights, ring_lights
        >>> ring = ring_lights(8, 58.0)
        >>> leds = LEDLights(ring * 18.6, -ring)
        >>> result = near_light_photometric_stereo(torch.rand(1, 8, 16, 16) + 0.5, leds, 0.025, max_iterations=2)
        >>> result.depth.shape
        torch.Size([1, 1, 16, 16])
    """
    sizes = check_shape(images, ["B", "K", "H", "W"], "images")
    check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    _check_light_model(light_model)
    if getattr(light_model, "count", sizes["K"]) != sizes["K"]:
        raise ShapeError(f"the light model has {light_model.count} lights but images has K={sizes['K']}")
    if max_iterations < 1 or not tolerance_mm > 0:
        raise InputError(f"max_iterations must be >= 1 and tolerance_mm > 0, got {max_iterations}, {tolerance_mm}")
    mask = check_mask(mask, sizes["B"], sizes["H"], sizes["W"])
    flat = flatfield(images, reference, dark, reference_dark, card_albedo, min_reference, saturation_level)
    card_height = card_height_mm if reference is not None else None
    depth = _initial_depth(initial_depth, images, sizes)
    fixed_mean = depth.mean(dim=(2, 3), keepdim=True)
    changes: list[float] = []
    offset = fixed_mean
    for _ in range(max_iterations):
        vectors = near_light_vectors(light_model, depth, pixel_pitch_mm, card_height)
        albedo, normals, weights = robust_near_light_normals(
            flat.images, vectors, flat.valid, mask, highlight_fraction=highlight_fraction
        )
        relative = _integrate_solved(normals, albedo > 0, integrator, pixel_pitch_mm)
        if estimate_offset:
            offset = estimate_height_offset(flat.images, light_model, relative, pixel_pitch_mm, weights, card_height)
        else:
            offset = fixed_mean - relative.mean(dim=(2, 3), keepdim=True)
        new_depth = relative + offset
        changes.append(float((new_depth - depth).abs().max()))
        depth = new_depth
        logger.info("near-light iteration %d: largest depth change %.2e mm", len(changes), changes[-1])
        if changes[-1] < tolerance_mm:
            break
    vectors = near_light_vectors(light_model, depth, pixel_pitch_mm, card_height)
    albedo, normals, weights = robust_near_light_normals(
        flat.images, vectors, flat.valid, mask, highlight_fraction=highlight_fraction
    )
    p, q = normals_to_gradients(normals)
    return NearLightResult(
        albedo, normals, p, q, depth, albedo > 0,
        weights=weights, offset_mm=depth.mean(dim=(1, 2, 3)), iterations=len(changes), changes_mm=tuple(changes),
    )


def _integrate_solved(normals: Tensor, solved: Tensor, method: str, pixel_pitch_mm: float) -> Tensor:
    """Height (up to an offset) from the normals of the solved pixels, beside-the-gap pixels nearly left out.

    A pixel next to an unsolved one (a crevice lit by fewer than three LEDs) sees the crevice's wall: its normal,
    the slope over its footprint, takes in a drop that does not lie between it and its solved neighbours. Edges
    of the integration grid carry the confidence-weighted mean of their two pixels' slopes, so such a pixel gets
    confidence :data:`_EDGE_CONFIDENCE` and its edges take the slope of the pixel on the solved side; otherwise
    each crevice pulls its rim down and the knits' many crevices add up to a dome (26 µm on data_synth's knit).
    Integrators without per-pixel weights get the plain solved mask.
    """
    p, q = normals_to_gradients(normals)
    accepts_weights = method in INTEGRATORS and "weights" in inspect.signature(INTEGRATORS[method]).parameters
    if not accepts_weights:  # an unknown method is reported by integrate itself
        return integrate(p, q, method=method, pixel_pitch_mm=pixel_pitch_mm, mask=solved)
    inside = F.pad(solved.to(p.dtype), (1, 1, 1, 1), value=1.0)  # the image border is no gap
    neighbours = torch.stack(
        [inside[..., 1:-1, :-2], inside[..., 1:-1, 2:], inside[..., :-2, 1:-1], inside[..., 2:, 1:-1]]
    )
    beside_gap = solved & (neighbours.amin(dim=0) < 1)
    confidence = torch.where(beside_gap, torch.full_like(p, _EDGE_CONFIDENCE), torch.ones_like(p))
    return integrate(p, q, method=method, pixel_pitch_mm=pixel_pitch_mm, mask=solved, weights=confidence)


def _initial_depth(initial: Tensor | float, images: Tensor, sizes: dict[str, int]) -> Tensor:
    shape = (sizes["B"], 1, sizes["H"], sizes["W"])
    if isinstance(initial, Tensor):
        check_finite(initial, "initial_depth")
        if initial.ndim != 4 or initial.shape[1:] != shape[1:] or initial.shape[0] not in (1, sizes["B"]):
            raise ShapeError(f"initial_depth must have shape {shape}, got {tuple(initial.shape)}")
        return initial.to(images).expand(shape).clone()
    if not math.isfinite(float(initial)):
        raise InputError(f"initial_depth must be finite, got {initial}")
    return torch.full(shape, float(initial), device=images.device, dtype=images.dtype)


def refine_depth(
    intensities: Tensor,
    light_model: nn.Module,
    depth: Tensor,
    pixel_pitch_mm: float,
    weights: Tensor | None = None,
    card_height_mm: float | None = None,
    scales: tuple[int, ...] = (4, 2, 1),
    steps: int = 30,
    huber_delta: float = 0.02,
    estimate_offset: bool = True,
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
        scales: downsampling factors, coarse to fine.
        steps: L-BFGS iterations per scale.
        huber_delta: Huber threshold, relative to the mean intensity.
        estimate_offset: re-estimate the mean height after refining; otherwise keep the mean of ``depth``.

    Returns:
        refined depth :math:`(B, 1, H, W)` (detached), its albedo :math:`(B, 1, H, W)` and the loss after each scale.

    Example:
        >>> from psmini.lights import PointLights
        >>> lights = PointLights(torch.tensor([[10.0, 0, 10], [-10.0, 0, 10], [0, 10.0, 10], [0, -10.0, 10]]))
        >>> images = torch.rand(1, 4, 8, 8) + 0.5
        >>> depth, albedo, losses = refine_depth(images, lights, torch.zeros(1, 1, 8, 8), 0.1, scales=(1,), steps=3)
        >>> depth.shape
        torch.Size([1, 1, 8, 8])
    """
    sizes = check_shape(intensities, ["B", "K", "H", "W"], "intensities")
    check_shape(depth, ["B", "1", "H", "W"], "depth")
    check_finite(intensities, "intensities")
    check_finite(depth, "depth")
    if not scales or any(int(s) < 1 for s in scales) or steps < 1 or not huber_delta > 0:
        raise InputError(f"scales must be positive integers, steps >= 1, huber_delta > 0; got {scales}, {steps}, {huber_delta}")
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

        def closure() -> Tensor:
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
    if estimate_offset:
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
    albedo = (weights * images * shading).sum(1, keepdim=True) / (weights * shading.square()).sum(1, keepdim=True).clamp_min(1e-12)
    return shading, albedo


def _rendering_loss(images, light_model, depth, pitch, weights, card_height_mm, norm, delta) -> Tensor:
    shading, albedo = _shading_and_albedo(images, light_model, depth, pitch, weights, card_height_mm)
    residual = (images - albedo * shading) / norm
    loss = F.huber_loss(residual, torch.zeros_like(residual), reduction="none", delta=delta)
    return (loss * weights).sum() / weights.sum().clamp_min(1)
