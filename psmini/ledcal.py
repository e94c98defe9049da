r"""Calibration of light models by gradient descent from images of a matte card at known heights.

A flat Lambertian card of albedo :math:`\rho_n` at height :math:`h_n` (normal :math:`e_z`, toward the camera) lit
by light ``k`` reads at pixel ``x``

.. math::
    R_k(x, h_n) = g(x)\, \rho_n\, M_k(x, h_n), \qquad M_k(x, h) = E_k(x, h)\, \max(e_z \cdot l_k(x, h), 0),

with the light model (any :class:`psmini.lights.LightModel`; for LEDs the model of Quéau et al., "LED-based
photometric stereo: modeling, calibration and numerical solution", JMIV 2018) giving the irradiance :math:`E_k` and
the unit light vector :math:`l_k`, and :math:`g(x)` the camera's gain times its vignetting, unknown and common to
every light and height. For a given model the best :math:`g` has a closed form per pixel (variable projection,
Golub and Pereyra, "The differentiation of pseudo-inverses and nonlinear least squares problems whose variables
separate", SIAM J. Numer. Anal. 1973):

.. math::
    g(x) = \frac{\sum_{k,n} R_k(x, h_n)\, \rho_n M_k(x, h_n)}{\sum_{k,n} \rho_n^2 M_k(x, h_n)^2},

so the fit minimises a robust (Huber) loss of :math:`R - g\,\rho M` over the model's parameters alone and does not
depend on the vignetting. What is left observable is the *shape* of each light over the field and across heights;
one overall scale of the irradiance goes into ``g``.

:func:`fit_lights` fits the ``nn.Parameter`` s of any light model this way (Levenberg–Marquardt on the Huber loss, or
Adam and L-BFGS, projecting the parameters back onto their constraints after every step with the model's
``project_()``). :func:`fit_leds` is
its use for LEDs: positions (mm), principal directions, anisotropies :math:`\mu` and relative intensities, coarse
to fine (as in the near-light literature, e.g. Santo et al., "Light structure from pin motion", ECCV 2020): first
positions and intensities with the beams held at the start's, then every parameter, each stage a call of
:func:`fit_lights` started from the previous one, on variables scaled so that unit steps change the cards
comparably; it fixes the intensities' scale so that they average 1. Cards are smooth, so the images are averaged
down to a few thousand pixels first.

Frames: psmini's camera frame (x right, y up, z toward the camera), millimetres, origin on the optical axis at the
reference (card) plane ``z = 0``; card heights are measured along +z from that plane.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import check_finite, check_light_module, check_positive, check_shape, check_tensor
from psmini.errors import CalibrationError, InputError, ShapeError
from psmini.geometry import pixel_grid_mm
from psmini.lights import DirectionalLights, LEDLights, LightModel, PointLights, lights_from_dict, lights_to_dict

__all__ = [
    "fit_lights",
    "LightFit",
    "LightFitOptions",
    "LEDFit",
    "LEDFitOptions",
    "fit_leds",
    "nominal_leds",
    "card_shading",
    "eliminate_gain",
    "card_loss",
]

logger = logging.getLogger(__name__)

# Nominal geometry of the psmini rig (DESIGN.md): 8 LEDs on a 31.6 mm ring 10 mm above the card.
NOMINAL_RING_DIAMETER_MM = 31.6
NOMINAL_LED_HEIGHT_MM = 10.0

# A card image whose mean signal is below this fraction of the median image's is taken as an LED that did not
# light (or a missing card): it would pull the shared gain toward zero and the LED's parameters anywhere.
_MIN_SIGNAL_FRACTION = 0.05

STAGES = ("point", "led")

# L-BFGS iterations between projections (and between convergence checks).
_LBFGS_ITERATIONS_PER_STEP = 20


def nominal_leds(
    count: int = 8,
    ring_diameter_mm: float = NOMINAL_RING_DIAMETER_MM,
    led_height_mm: float = NOMINAL_LED_HEIGHT_MM,
    azimuth_offset_deg: float = 0.0,
    mu: float = 1.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> LEDLights:
    """LEDs evenly spaced on a ring above the card, pointing at the field centre, unit intensities.

    Args:
        count: number of LEDs K (LED 0 at ``azimuth_offset_deg``, counter-clockwise from +x).
        ring_diameter_mm: diameter of the ring, mm.
        led_height_mm: height of the ring above the card plane, mm.
        azimuth_offset_deg: azimuth of LED 0, degrees.
        mu: anisotropy of every LED (1: Lambertian LED).
        device: device of the parameters.
        dtype: floating dtype (default: torch's default dtype).

    Returns:
        an :class:`~psmini.lights.LEDLights` of K LEDs.

    Raises:
        InputError: a count below 1, a non-positive diameter or height, a negative ``mu``.

    Example:
        >>> nominal_leds().positions_mm[0].tolist()
        [15.800000190734863, 0.0, 10.0]
    """
    if not isinstance(count, int) or count < 1:
        raise InputError(f"count must be an integer >= 1, got {count!r}")
    radius = check_positive(ring_diameter_mm, "ring_diameter_mm") / 2
    height = check_positive(led_height_mm, "led_height_mm")
    if not (isinstance(mu, (int, float)) and 0 <= mu < math.inf):
        raise InputError(f"mu must be a finite number >= 0, got {mu!r}")
    azimuth = torch.arange(count, dtype=torch.float64) * (2 * math.pi / count) + math.radians(azimuth_offset_deg)
    positions = torch.stack([radius * azimuth.cos(), radius * azimuth.sin(), torch.full_like(azimuth, height)], -1)
    directions = -positions / positions.norm(dim=-1, keepdim=True)
    dtype = dtype or torch.get_default_dtype()

    def cast(x: Tensor) -> Tensor:
        return x.to(device=device, dtype=dtype)

    return LEDLights(cast(positions), cast(directions), cast(torch.ones(count, dtype=torch.float64)),
                     cast(torch.full((count,), float(mu), dtype=torch.float64)))


def card_shading(lights: Callable[[Tensor], tuple[Tensor, Tensor]], points: Tensor) -> Tensor:
    r"""Shading of a flat card facing the camera: :math:`M_k = E_k \max(e_z \cdot l_k, 0)` per pixel.

    Args:
        lights: a light model of :mod:`psmini.lights` (K lights), or any function of the points that returns
            unit light vectors :math:`(N, K, 3, H, W)` and irradiance :math:`(N, K, 1, H, W)` as models do.
        points: card points, shape :math:`(N, 3, H, W)`, mm, camera frame (one card height per batch entry).

    Returns:
        shading, shape :math:`(N, K, H, W)`: what a card of albedo 1 reads under each light with unit camera
        gain.

    Example:
        >>> points = torch.zeros(1, 3, 2, 2)
        >>> card_shading(nominal_leds(4), points).shape
        torch.Size([1, 4, 2, 2])
    """
    directions, irradiance = lights(points)
    return irradiance[:, :, 0] * directions[:, :, 2].clamp_min(0)


def eliminate_gain(images: Tensor, shading: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    r"""Residuals of the card images once the per-pixel gain is solved in closed form (variable projection).

    For each pixel, :math:`g = \sum w R M / \sum w M^2` over lights and heights (the weighted least-squares
    gain common to all of them), and the residual is :math:`R - g M`.

    Args:
        images: card readings R, shape :math:`(N, K, H, W)` (dark-subtracted, divided by the card's albedo).
        shading: model shading M, shape :math:`(N, K, H, W)` (see :func:`card_shading`).
        weights: optional observation weights, shape :math:`(N, K, H, W)` (0 drops an observation).

    Returns:
        residuals :math:`(N, K, H, W)` and gain :math:`(1, 1, H, W)` (0 where no weighted shading is left).

    Raises:
        ShapeError: when the shapes differ.

    Example:
        >>> shading = torch.rand(2, 3, 4, 4) + 0.5
        >>> residuals, gain = eliminate_gain(0.7 * shading, shading)
        >>> bool(residuals.abs().max() < 1e-6), bool(torch.allclose(gain, torch.full_like(gain, 0.7)))
        (True, True)
    """
    check_shape(images, ["N", "K", "H", "W"], "images")
    if shading.shape != images.shape:
        raise ShapeError(f"shading must have the images' shape {tuple(images.shape)}, got {tuple(shading.shape)}")
    weighted = shading if weights is None else shading * weights
    numerator = (weighted * images).sum(dim=(0, 1), keepdim=True)
    denominator = (weighted * shading).sum(dim=(0, 1), keepdim=True)
    tiny = torch.finfo(images.dtype).tiny
    gain = torch.where(denominator > tiny, numerator / denominator.clamp_min(tiny), torch.zeros_like(numerator))
    return images - gain * shading, gain


def card_loss(
    lights: nn.Module,
    images: Tensor,
    points: Tensor,
    weights: Tensor | None = None,
    huber_delta: float = 0.05,
) -> Tensor:
    r"""The calibration objective: mean Huber loss of the card residuals after eliminating the gain.

    Args:
        lights: a light model of :mod:`psmini.lights` (K lights).
        images: card readings, shape :math:`(N, K, H, W)`, scaled so that their mean is about 1 (the Huber
            threshold is in that scale).
        points: card points, shape :math:`(N, 3, H, W)`, mm.
        weights: optional observation weights, shape :math:`(N, K, H, W)`.
        huber_delta: residual (in the images' scale) where the loss turns from quadratic to linear.

    Returns:
        a scalar, differentiable with respect to the light model's parameters.

    Raises:
        InputError: ``lights`` that are not a light model (a tensor of directions), a ``huber_delta`` that is not
            a positive number. ShapeError: images, points or weights of the wrong shape (images and shading of
            another K: the model's light count).

    Example:
        >>> points = torch.zeros(1, 3, 3, 3)
        >>> images = card_shading(nominal_leds(4), points)
        >>> float(card_loss(nominal_leds(4), images / images.mean(), points)) < 1e-12
        True
    """
    # a tensor of directions failed as a bare TypeError (not callable), a delta of 0 and weights of another shape
    # as bare RuntimeErrors of huber_loss and broadcasting; python checks only: the loss runs at every fit step
    check_light_module(lights, "lights")
    check_positive(huber_delta, "huber_delta")
    check_shape(images, ["N", "K", "H", "W"], "images")
    if weights is not None and (not isinstance(weights, Tensor) or weights.shape != images.shape):
        got = tuple(weights.shape) if isinstance(weights, Tensor) else type(weights).__name__
        raise ShapeError(f"weights must have the images' shape {tuple(images.shape)}, got {got}")
    residuals, _ = eliminate_gain(images, card_shading(lights, points), weights)
    loss = F.huber_loss(residuals, torch.zeros_like(residuals), reduction="none", delta=huber_delta)
    if weights is None:
        return loss.mean()
    return (loss * weights).sum() / weights.sum().clamp_min(1)


@dataclass
class LEDFit:
    """What :func:`fit_leds` returns.

    Attributes:
        lights: the fitted :class:`~psmini.lights.LEDLights` (plain tensors, detached), in the images' dtype and
            device; intensities relative, averaging 1.
        residual_rms: root mean square residual over every used observation, as a fraction of the mean card
            reading (dimensionless).
        residual_rms_per_led: the same per LED, shape :math:`(K,)`.
        residual_rms_per_height: the same per card height, shape :math:`(N,)`.
        gain: the per-pixel camera gain times vignetting found with the fit, shape :math:`(1, 1, h, w)` at the
            fit's resolution, in image units per unit of (card albedo × shading), scaled like the intensities.
        heights_mm: the card heights, shape :math:`(N,)`.
        stages: one record per stage: name, optimiser iterations, final mean loss, seconds.
        start: the start model, as an :class:`~psmini.lights.LEDLights`.
    """

    lights: LEDLights
    residual_rms: float
    residual_rms_per_led: Tensor
    residual_rms_per_height: Tensor
    gain: Tensor
    heights_mm: Tensor
    stages: list[dict[str, Any]] = field(default_factory=list)
    start: LEDLights | None = None

    @property
    def positions_mm(self) -> Tensor:
        """Fitted LED positions, :math:`(K, 3)`, mm."""
        return self.lights.positions_mm

    @property
    def principal_directions(self) -> Tensor:
        """Fitted unit principal directions, :math:`(K, 3)`."""
        return self.lights.principal_directions

    @property
    def intensities(self) -> Tensor:
        """Fitted relative intensities, :math:`(K,)`, mean 1."""
        return self.lights.intensities

    @property
    def mu(self) -> Tensor:
        """Fitted anisotropies, :math:`(K,)`."""
        return self.lights.mu

    def to_dict(self) -> dict[str, Any]:
        """The fitted model as a light object of ``docs/capture-format.md`` (``"model": "led"``), plus residuals.

        The extra keys (``residuals``, ``intensity_scale``, ``calibration``) are ignored by
        :func:`psmini.lights.lights_from_dict`, so the object can be written as a lights file and read back.
        """
        data = _calibration_dict(self.lights, self.residual_rms, self.residual_rms_per_led,
                                 self.residual_rms_per_height, self.heights_mm, self.stages)
        return {**lights_to_dict(self.lights),
                "intensity_scale": "relative: mean 1 (a card calibration leaves the overall scale to the camera gain)",
                "residuals": data["residuals"], "calibration": data["calibration"]}


# ------------------------------------------------------------------------------------------------ the fit


def _stack_images(card_images: Tensor | Sequence[Tensor]) -> Tensor:
    """Card images as one (N, K, H, W) tensor."""
    if isinstance(card_images, Tensor):
        check_shape(card_images, ["N", "K", "H", "W"], "card_images")
        stack = card_images
    else:
        if not isinstance(card_images, Sequence) or len(card_images) == 0:
            raise InputError("card_images must hold the images of at least one card height, got none")
        for index, images in enumerate(card_images):
            check_shape(images, ["K", "H", "W"], f"card_images[{index}]")
        shapes = {tuple(images.shape) for images in card_images}
        if len(shapes) > 1:
            raise ShapeError(f"card images of every height must have one shape (K, H, W), got {sorted(shapes)}")
        stack = torch.stack(list(card_images))
    if stack.shape[0] < 1:
        raise InputError("card_images must hold the images of at least one card height, got none")
    return stack


def _stack_dark(dark: Tensor | Sequence[Tensor | None] | None, like: Tensor) -> Tensor | None:
    """Dark frames as an (N or 1, 1, H, W) tensor, or None."""
    if dark is None:
        return None
    count, _, height, width = like.shape
    if not isinstance(dark, Tensor):
        if len(dark) != count:
            raise ShapeError(f"dark must hold one frame per card height ({count}), got {len(dark)}")
        dark = torch.stack([torch.zeros(1, height, width, dtype=like.dtype, device=like.device) if d is None
                            else d.to(like) for d in dark])
    check_tensor(dark, "dark")
    if (dark.ndim != 4 or dark.shape[1] != 1 or dark.shape[0] not in (1, count)
            or tuple(dark.shape[2:]) != (height, width)):
        raise ShapeError(f"dark must have shape ({count}, 1, {height}, {width}) or (1, 1, {height}, {width}), "
                         f"got {tuple(dark.shape)}")
    return check_finite(dark, "dark").to(like)


def _per_height(values: float | Sequence[float] | Tensor, count: int, name: str, positive: bool) -> Tensor:
    """A float (the same for every card height) or one value per card height, as a float64 (N,) tensor on the CPU. A
    sequence of one value for several heights is refused, not stretched: a list of captures with one height too few
    would otherwise fit every card at the first one's height."""
    tensor = torch.as_tensor(values, dtype=torch.float64).detach().cpu()
    tensor = tensor.expand(count) if tensor.dim() == 0 else tensor.flatten()
    if tensor.numel() != count:
        raise ShapeError(f"{name} must hold one value per card height ({count}), got {tensor.numel()}")
    if not bool(torch.isfinite(tensor).all()) or (positive and bool((tensor <= 0).any())):
        raise InputError(f"{name} must be finite{' and positive' if positive else ''}, got {tensor.tolist()}")
    return tensor


def _start_lights(init: Any, count: int, nominal_distance_mm: float, mu_init: float) -> LEDLights:
    """The start of the fit as float64 LEDs on the CPU (see :func:`fit_leds` for what ``init`` may be)."""
    if isinstance(init, Mapping):
        init = lights_from_dict(init, dtype=torch.float64)
    if isinstance(init, Tensor):
        check_shape(init, ["K", "3"], "init (directions)")
        init = DirectionalLights(init.detach().to(torch.float64))
    if init is None or (isinstance(init, str) and init == "nominal"):
        init = nominal_leds(count, dtype=torch.float64)
    elif hasattr(init, "ring_diameter_mm") and hasattr(init, "led_height_mm"):  # a rig description (RigConfig)
        init = nominal_leds(int(getattr(init, "led_count", count)), float(init.ring_diameter_mm),
                            float(init.led_height_mm), float(getattr(init, "azimuth_offset_deg", 0.0)),
                            float(getattr(init, "mu", mu_init)), dtype=torch.float64)
    if not isinstance(init, (DirectionalLights, PointLights)):
        raise InputError(
            "init must be 'nominal', a rig description (ring_diameter_mm, led_height_mm), a light model of "
            f"psmini.lights, a light-model dict or a (K, 3) tensor of directions; got {type(init).__name__}"
        )
    if init.count != count:
        raise ShapeError(f"the start model has {init.count} lights but the card images have K={count}")

    def cpu64(x: Tensor) -> Tensor:
        return x.detach().to(device="cpu", dtype=torch.float64).clone()

    intensities = cpu64(init.intensities)
    if isinstance(init, DirectionalLights):
        unit = cpu64(init.directions)
        unit = unit / unit.norm(dim=-1, keepdim=True)
        positions = unit * nominal_distance_mm
    else:
        positions = cpu64(init.positions_mm)
    if isinstance(init, LEDLights):
        directions, mu = cpu64(init.principal_directions), cpu64(init.mu)
    else:
        directions = -positions / positions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        mu = torch.full((count,), float(mu_init), dtype=torch.float64)
    if bool((positions[:, 2] <= 0).any()):
        raise CalibrationError(
            f"every LED of the start must lie above the card plane (z > 0), got z = {positions[:, 2].tolist()}"
        )
    return LEDLights(positions, directions, intensities / intensities.mean(), mu, learnable=True)


def _downsample(images: Tensor, valid: Tensor, pixel_pitch_mm: float, max_size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Block averages of the images, the blocks' validity (every pixel valid) and their centres (x, y) in mm."""
    height, width = images.shape[-2:]
    factor = max(1, math.ceil(max(height, width) / max_size))
    x, y = pixel_grid_mm(height, width, pixel_pitch_mm, device=images.device, dtype=images.dtype)
    if factor == 1:
        return images, valid, torch.stack([x, y])[None]
    pooled = F.avg_pool2d(images, factor)
    pooled_valid = F.avg_pool2d(valid.to(images.dtype), factor) > 1 - 1e-6
    centres = F.avg_pool2d(torch.stack([x, y])[None], factor)
    return pooled, pooled_valid, centres


@dataclass
class _Cards:
    """Card images ready for the fit: pooled, dark-subtracted, divided by the albedo, scaled to mean 1."""

    images: Tensor   # (N, K, h, w) float64
    points: Tensor   # (N, 3, h, w) float64, mm
    weights: Tensor  # (N, K, h, w) float64, 1 where every pooled reading was valid
    scale: float     # the mean reading the images were divided by
    heights: Tensor  # (N,) float64 on the CPU
    count: int       # K
    dtype: torch.dtype
    device: torch.device


def _prepare_cards(card_images: Tensor | Sequence[Tensor], heights_mm: float | Sequence[float] | Tensor,
                   pixel_pitch_mm: float, card_albedo: float | Sequence[float],
                   dark: Tensor | Sequence[Tensor | None] | None, saturation_level: float | None,
                   max_size: int) -> _Cards:
    """Check the card images and their companions; pool, subtract, divide, scale (see :func:`fit_lights`)."""
    images = _stack_images(card_images)
    count, leds, _, _ = images.shape
    pitch = check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    heights = _per_height(heights_mm, count, "heights_mm", positive=False)
    albedo = _per_height(card_albedo, count, "card_albedo", positive=True)
    if count * leds < 2:
        raise CalibrationError("the fit needs at least two card images in all (the gain absorbs one), "
                               f"got {count * leds}")
    check_finite(images, "card_images")
    dark_frames = _stack_dark(dark, images)
    device = images.device
    work = images.to(torch.float64)
    valid = torch.ones_like(work, dtype=torch.bool)
    if saturation_level is not None:
        valid = work < check_positive(saturation_level, "saturation_level")
    if dark_frames is not None:
        work = work - dark_frames.to(torch.float64)
    work = work / albedo.to(device)[:, None, None, None]
    _check_signal(work, valid)

    pooled, pooled_valid, centres = _downsample(work, valid, pitch, max_size)
    scale = pooled[pooled_valid].mean()
    size = pooled.shape[-2:]
    z = heights.to(device)[:, None, None, None].expand(count, 1, *size)
    points = torch.cat([centres.expand(count, -1, -1, -1), z], dim=1)
    return _Cards(pooled / scale, points, pooled_valid.to(torch.float64), float(scale), heights, leds,
                  images.dtype if images.is_floating_point() else torch.get_default_dtype(), device)


def _check_signal(work: Tensor, valid: Tensor) -> None:
    """Raise CalibrationError for a card image without signal (an LED off, a lens cap, a missing card)."""
    means = (work * valid).sum(dim=(2, 3)) / valid.sum(dim=(2, 3)).clamp_min(1)  # (N, K)
    reference = means.flatten().median()
    dark = (means <= _MIN_SIGNAL_FRACTION * reference) | (means <= 0)
    if bool(dark.any()):
        height, led = (int(i) for i in dark.nonzero()[0])
        raise CalibrationError(
            f"the card image of LED {led} at height index {height} has no signal (mean {float(means[height, led]):.3g} "
            f"after dark subtraction, median image {float(reference):.3g}): did the LED light?"
        )


class _ScaledLEDs(LightModel):
    r"""LEDs in the optimiser's variables, scaled so that unit steps in each change the card images comparably.

    Positions in units of 10 mm; the intensity as the log of :math:`\phi / \lVert s \rVert^2` (the LED's
    irradiance level at the field centre, nearly independent of its distance: without it, moving an LED and
    changing its intensity are strongly coupled, and it keeps :math:`\phi > 0`); :math:`\mu` in units of 10.
    """

    POSITION_SCALE_MM = 10.0
    MU_SCALE = 10.0
    # the parameters of each stage of fit_leds (None: all)
    STAGE_PARAMETERS: dict[str, tuple[str, ...] | None] = {"point": ("position", "log_level"), "led": None}

    def __init__(self, leds: LEDLights) -> None:
        super().__init__()
        positions = leds.positions_mm.detach()
        self.position = nn.Parameter(positions / self.POSITION_SCALE_MM)
        self.log_level = nn.Parameter((leds.intensities.detach() / positions.square().sum(-1)).log())
        self.direction = nn.Parameter(leds.principal_directions.detach().clone())
        self.mu = nn.Parameter(leds.mu.detach() / self.MU_SCALE)

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def leds(self) -> LEDLights:
        """The LED model these variables describe."""
        positions = self.position * self.POSITION_SCALE_MM
        intensities = self.log_level.exp() * positions.square().sum(-1)
        # the line search may try mu < 0 between projections: such trial points see mu = 0
        return LEDLights(positions, self.direction, intensities, (self.mu * self.MU_SCALE).clamp_min(0.0))

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        return self.leds()(points)

    def project_(self) -> None:
        """Constraints after a step: unit principal directions, mu >= 0 (intensities are positive by design)."""
        with torch.no_grad():
            self.direction.div_(self.direction.norm(dim=-1, keepdim=True).clamp_min(1e-12))
            self.mu.clamp_(min=0.0)


def _led_lights(tensors: Iterable[Tensor]) -> LEDLights:
    """The LED model of its four parameters in order: positions, principal directions, intensities, mu."""
    positions, directions, intensities, mu = tensors
    return LEDLights(positions, directions, intensities, mu)


def _rms_and_gain(lights: nn.Module, cards: _Cards, huber_delta: float
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Residual RMS over everything, per light and per height, the gain map (in image units per unit shading) and
    the mean Huber loss."""
    with torch.no_grad():
        residuals, gain = eliminate_gain(cards.images, card_shading(lights, cards.points), cards.weights)

        def rms(dims: tuple[int, ...]) -> Tensor:
            return ((residuals.square() * cards.weights).sum(dims) / cards.weights.sum(dims).clamp_min(1)).sqrt()

        loss = card_loss(lights, cards.images, cards.points, cards.weights, huber_delta)
        return rms((0, 1, 2, 3)), rms((0, 2, 3)), rms((1, 2, 3)), gain * cards.scale, loss


def _calibration_dict(lights: LightModel, residual_rms: float, per_light: Tensor, per_height: Tensor,
                      heights_mm: Tensor, stages: list[dict[str, Any]]) -> dict[str, Any]:
    """A fitted model as a light object, plus its residuals and how it was fitted (keys the reader ignores)."""
    data = lights_to_dict(lights)
    data["residuals"] = {
        "rms": residual_rms,
        "per_led": per_light.detach().cpu().double().tolist(),
        "per_height": per_height.detach().cpu().double().tolist(),
        "unit": "fraction of the mean card reading",
    }
    data["calibration"] = {
        "method": "card images, variable projection of the gain, Huber loss",
        "heights_mm": heights_mm.detach().cpu().double().tolist(),
        "stages": stages,
    }
    return data


@dataclass
class LightFit:
    """What :func:`fit_lights` returns.

    Attributes:
        lights: the fitted model: a copy of the one given, with the fitted parameters, on the card images' device,
            in the model's floating dtype (each parameter's ``requires_grad`` as it was given). Its overall scale is
            not observable (the gain absorbs it): it stays where the start had it, up to the optimiser's drift.
        residual_rms: root mean square residual over every used observation, as a fraction of the mean card
            reading (dimensionless).
        loss: the final mean Huber loss (:func:`card_loss`).
        residual_rms_per_light: the same per light, shape :math:`(K,)`.
        residual_rms_per_height: the same per card height, shape :math:`(N,)`.
        gain: the per-pixel camera gain times vignetting found with the fit, shape :math:`(1, 1, h, w)` at the
            fit's resolution, in image units per unit of (card albedo × the fitted model's shading).
        heights_mm: the card heights, shape :math:`(N,)`.
        stages: one record per optimiser run (``optimizer``: ``"adam"``, ``"lm"`` or ``"lbfgs"``, ``iterations``,
            final mean ``loss``, ``seconds``).
        losses: the loss after each step (Adam steps, Levenberg–Marquardt steps or L-BFGS steps of 20 iterations),
            the Huber loss summed over the observations in units of the squared threshold.
        start: a copy of the model as given (the start), on the images' device.
        parameters: the names of the parameters fitted.
    """

    lights: LightModel
    residual_rms: float
    loss: float
    residual_rms_per_light: Tensor
    residual_rms_per_height: Tensor
    gain: Tensor
    heights_mm: Tensor
    stages: list[dict[str, Any]] = field(default_factory=list)
    losses: list[float] = field(default_factory=list)
    start: LightModel | None = None
    parameters: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The fitted model as a light object of ``docs/capture-format.md``, plus residuals and how it was fitted.

        The extra keys (``residuals``, ``calibration``) are ignored by :func:`psmini.lights.lights_from_dict`, so
        the object can be written as a lights file and read back.
        """
        data = _calibration_dict(self.lights, self.residual_rms, self.residual_rms_per_light,
                                 self.residual_rms_per_height, self.heights_mm, self.stages)
        data["calibration"]["parameters"] = list(self.parameters)
        return data


@dataclass(frozen=True)
class LightFitOptions:
    r"""Options of :func:`fit_lights`.

    Attributes:
        parameters: names of the model's parameters to fit (as ``model.named_parameters()`` names them, e.g.
            ``("positions_mm", "beam")``); the others are held. ``None``: every parameter that requires gradients.
        max_size: the images are averaged over square blocks down to at most this many pixels a side (cards are
            smooth; 32 keeps the fit to seconds).
        huber_delta: Huber threshold, as a fraction of the mean card reading.
        adam_iterations: Adam steps first (a projection after each), e.g. from a start far from the solution.
        learning_rate: Adam's step size, in the parameters' own units.
        optimizer: then ``"lm"`` (default: Levenberg–Marquardt on the Huber loss by iteratively reweighted least
            squares, with the Jacobian of the residuals by forward-mode differentiation; invariant to the
            parameters' units, so a model needs no rescaling) or ``"lbfgs"`` (strong Wolfe line search; for a model
            whose ``forward`` forward-mode differentiation cannot go through, or with thousands of parameters).
        iterations: Levenberg–Marquardt steps (one Jacobian each) or L-BFGS iterations (a projection every 20);
            ``None``: 50 or 400; 0: Adam only.
        tolerance: stop when the loss changes by less than this relative amount in one step (20 L-BFGS
            iterations).

    Raises:
        InputError: an unknown optimizer, counts that are not integers >= 0, ``max_size`` < 2, a non-positive
            ``huber_delta`` or ``learning_rate``, a negative ``tolerance``, parameters that are not names.

    Example:
        >>> LightFitOptions(parameters=("positions_mm",), optimizer="lbfgs").to_dict()["iterations"]
        400
    """

    parameters: tuple[str, ...] | None = None
    max_size: int = 32
    huber_delta: float = 0.05
    adam_iterations: int = 0
    learning_rate: float = 0.01
    optimizer: str = "lm"
    iterations: int | None = None
    tolerance: float = 1e-10

    def __post_init__(self) -> None:
        if self.parameters is not None:
            names: Any = self.parameters  # a str would pass for a tuple of one-letter names
            if isinstance(names, str) or not all(isinstance(n, str) for n in names):
                raise InputError(f"parameters must be a tuple of parameter names or None, got {self.parameters!r}")
            object.__setattr__(self, "parameters", tuple(self.parameters))
        if self.optimizer not in ("lm", "lbfgs"):
            raise InputError(f"optimizer must be 'lm' or 'lbfgs', got {self.optimizer!r}")
        if self.iterations is None:
            object.__setattr__(self, "iterations", 50 if self.optimizer == "lm" else 400)
        if not isinstance(self.max_size, int) or self.max_size < 2:
            raise InputError(f"max_size must be an integer >= 2, got {self.max_size!r}")
        check_positive(self.huber_delta, "huber_delta")
        check_positive(self.learning_rate, "learning_rate")
        for name in ("adam_iterations", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InputError(f"{name} must be an integer >= 0, got {value!r}")
        if not (isinstance(self.tolerance, (int, float)) and 0 <= self.tolerance < math.inf):
            raise InputError(f"tolerance must be a finite number >= 0, got {self.tolerance!r}")

    def to_dict(self) -> dict[str, Any]:
        """The options as a JSON-ready dict."""
        data = {f: getattr(self, f) for f in self.__dataclass_fields__}
        data["parameters"] = None if self.parameters is None else list(self.parameters)
        return data


def _working_copy(model: LightModel, device: torch.device) -> tuple[LightModel, torch.dtype, dict[str, bool]]:
    """A float64 copy of the model on ``device``, its floating dtype and its parameters' ``requires_grad``."""
    named = dict(model.named_parameters())
    if not named:
        raise InputError(f"{type(model).__qualname__} has no nn.Parameter to fit: build it with learnable=True (the "
                         "built-in models) or keep its unknowns as nn.Parameter attributes")
    floating = [p.dtype for p in named.values() if p.is_floating_point()]
    dtype = floating[0] if floating else torch.get_default_dtype()
    try:
        fitted = copy.deepcopy(model)
    except RuntimeError as error:  # a tensor attribute that is no leaf (computed from a tensor that needs gradients)
        raise InputError(f"{type(model).__qualname__} cannot be copied for the fit ({error}); keep its tensors as "
                         "parameters or detached tensors") from error
    return fitted.to(device=device, dtype=torch.float64), dtype, {n: p.requires_grad for n, p in named.items()}


def _chosen(model: LightModel, names: tuple[str, ...] | None, flags: dict[str, bool]) -> tuple[str, ...]:
    """The names of the parameters to fit; raises InputError for unknown names or none at all."""
    available = dict(model.named_parameters())
    if names is None:
        names = tuple(n for n in available if flags[n])
    unknown = [n for n in names if n not in available]
    if unknown:
        raise InputError(f"{type(model).__qualname__} has no parameter {unknown[0]!r}; its parameters are "
                         f"{sorted(available)}")
    if not names:
        raise InputError(f"no parameter of {type(model).__qualname__} to fit: every one has requires_grad=False; "
                         "name them in LightFitOptions(parameters=...)")
    return tuple(names)


def _gradient_descent(model: LightModel, params: list[Tensor], cards: _Cards, options: LightFitOptions,
                      optimizer: str, max_steps: int, losses: list[float]) -> int:
    """Adam or L-BFGS steps on ``params``, projecting after each; the iterations run."""
    project = getattr(model, "project_", None)
    # The optimiser sees the summed loss in units of the Huber threshold: L-BFGS skips curvature pairs with
    # s·y < 1e-10, which a mean loss near convergence on noise-free cards falls below.
    loss_scale = float(cards.weights.sum()) / options.huber_delta**2
    if optimizer == "lbfgs":
        chunk = _LBFGS_ITERATIONS_PER_STEP
        opt: torch.optim.Optimizer = torch.optim.LBFGS(
            params, lr=1.0, max_iter=chunk, history_size=30, line_search_fn="strong_wolfe",
            tolerance_grad=0.0, tolerance_change=0.0,
        )
    else:
        chunk = 1
        opt = torch.optim.Adam(params, lr=options.learning_rate)

    def closure() -> Tensor:
        opt.zero_grad()
        loss = card_loss(model, cards.images, cards.points, cards.weights, options.huber_delta) * loss_scale
        loss.backward()
        return loss

    previous = math.inf
    iterations = 0
    while iterations < max_steps:
        # one sync per step, to stop at convergence; step() returns the closure's loss tensor, where torch's stubs
        # type closures and results as floats
        loss = float(opt.step(closure).detach())  # type: ignore[arg-type, attr-defined]
        if callable(project):
            project()
        losses.append(loss)
        iterations += chunk
        if optimizer == "lbfgs" and abs(previous - loss) <= options.tolerance * abs(loss):
            break
        previous = loss
    return iterations


# Levenberg–Marquardt: tangents per vectorised Jacobian pass, and the damping's range.
_JACOBIAN_CHUNK = 32
_DAMPING_START, _DAMPING_MAX = 1e-3, 1e10


def _weighted_residuals(model: LightModel, names: tuple[str, ...], cards: _Cards) -> Any:
    """The function θ ↦ residuals (after eliminating the gain) of the card images, flattened, for the parameters
    ``names`` concatenated in θ; zero where an observation is not used."""
    shapes = {n: p.shape for n, p in model.named_parameters() if n in names}
    sizes = [shapes[n].numel() for n in names]
    root = cards.weights.sqrt()

    def residuals(theta: Tensor) -> Tensor:
        values = {n: t.reshape(shapes[n]) for n, t in zip(names, theta.split(sizes), strict=True)}
        shading = card_shading(lambda points: torch.func.functional_call(model, values, (points,)), cards.points)
        return (eliminate_gain(cards.images, shading, cards.weights)[0] * root).reshape(-1)

    return residuals


def _jacobian_transposed(residuals: Any, theta: Tensor) -> Tensor:
    """(P, n): the residuals' Jacobian, transposed, by forward-mode differentiation along each parameter."""
    basis = torch.eye(theta.numel(), dtype=theta.dtype, device=theta.device)

    def along(tangent: Tensor) -> Tensor:
        return torch.func.jvp(residuals, (theta,), (tangent,))[1]

    try:
        return torch.cat([torch.func.vmap(along)(chunk) for chunk in basis.split(_JACOBIAN_CHUNK)])
    except (RuntimeError, NotImplementedError):  # an operation vmap cannot batch: one direction at a time
        try:
            return torch.stack([along(tangent) for tangent in basis])
        except (RuntimeError, NotImplementedError) as error:
            raise InputError(f"the light model's forward cannot be differentiated in forward mode ({error}); fit it "
                             "with LightFitOptions(optimizer='lbfgs')") from error


def _levenberg_marquardt(model: LightModel, names: tuple[str, ...], cards: _Cards, options: LightFitOptions,
                         max_steps: int, losses: list[float]) -> int:
    r"""Levenberg–Marquardt steps on the Huber loss (iteratively reweighted least squares, weights
    :math:`\min(1, \delta / |r|)`), Marquardt's scaling of the damping, the model's projection after each step.
    Returns the Jacobians computed."""
    params = dict(model.named_parameters())
    project = getattr(model, "project_", None)
    residuals = _weighted_residuals(model, names, cards)
    delta = options.huber_delta

    def gather() -> Tensor:
        return torch.cat([params[n].detach().reshape(-1) for n in names])

    def assign(theta: Tensor) -> None:
        with torch.no_grad():
            for name, value in zip(names, theta.split([params[n].numel() for n in names]), strict=True):
                params[name].copy_(value.reshape(params[name].shape))
        if callable(project):
            project()

    def huber(theta: Tensor) -> float:
        r = residuals(theta)
        return float(F.huber_loss(r, torch.zeros_like(r), reduction="sum", delta=delta)) / delta**2

    theta = gather()
    current = huber(theta)
    damping = _DAMPING_START
    steps = 0
    with torch.no_grad():
        while steps < max_steps and damping < _DAMPING_MAX:
            steps += 1
            r = residuals(theta)
            jt = _jacobian_transposed(residuals, theta)  # (P, n)
            w = (delta / r.abs().clamp_min(torch.finfo(r.dtype).tiny)).clamp(max=1.0)
            normal = (jt * w) @ jt.T
            gradient = (jt * w) @ r
            scale = normal.diagonal().clamp_min(1e-12 * float(normal.diagonal().max().clamp_min(1e-300)))
            previous = current
            while damping < _DAMPING_MAX:
                step = torch.linalg.solve(normal + damping * torch.diag(scale), -gradient)
                assign(theta + step)
                trial = gather()
                loss = huber(trial)
                if loss < current:
                    theta, current, damping = trial, loss, max(damping / 3, 1e-12)
                    break
                damping *= 4
            assign(theta)
            losses.append(current)
            if previous - current <= options.tolerance * current:
                break
    return steps


def _optimise(model: LightModel, names: tuple[str, ...], cards: _Cards, options: LightFitOptions
              ) -> tuple[list[dict[str, Any]], list[float]]:
    """Adam, then L-BFGS or Levenberg–Marquardt, on the chosen parameters; the runs' records and step losses."""
    params: list[Tensor] = [p for n, p in model.named_parameters() if n in names]
    for name, parameter in model.named_parameters():
        parameter.requires_grad_(name in names)
    records: list[dict[str, Any]] = []
    losses: list[float] = []
    for optimizer, max_steps in (("adam", options.adam_iterations), (options.optimizer, options.iterations or 0)):
        if max_steps == 0:
            continue
        start = time.perf_counter()
        if optimizer == "lm":
            iterations = _levenberg_marquardt(model, names, cards, options, max_steps, losses)
        else:
            iterations = _gradient_descent(model, params, cards, options, optimizer, max_steps, losses)
        with torch.no_grad():
            final = float(card_loss(model, cards.images, cards.points, cards.weights, options.huber_delta))
        records.append({"optimizer": optimizer, "iterations": iterations, "loss": final,
                        "seconds": time.perf_counter() - start})
        logger.info("light fit (%s): %d iterations, loss %.3e, %.2f s", optimizer, iterations, final,
                    records[-1]["seconds"])
    return records, losses


def fit_lights(
    model: LightModel,
    cards: Tensor | Sequence[Tensor],
    heights_mm: float | Sequence[float] | Tensor,
    pixel_pitch_mm: float,
    *,
    card_albedo: float | Sequence[float] = 1.0,
    dark: Tensor | Sequence[Tensor | None] | None = None,
    saturation_level: float | None = None,
    options: LightFitOptions | None = None,
) -> LightFit:
    r"""Fit any light model's parameters to images of a matte card at known heights.

    The card model (see the module's docstring): a flat card of albedo :math:`\rho_n` at height :math:`h_n` reads
    :math:`g(x)\,\rho_n\,E_k(x)\max(l_{k,z}(x), 0)` under light k, with :math:`(l_k, E_k)` = ``model(points)`` at
    the card's points and :math:`g` the camera's gain × vignetting, eliminated per pixel in closed form. The fit
    minimises the mean Huber loss of the residuals (:func:`card_loss`) over the chosen ``nn.Parameter`` s of the
    model: ``options.adam_iterations`` Adam steps (none by default), then Levenberg–Marquardt steps (the default) or
    L-BFGS iterations; after each step, the model's ``project_()`` method, if it has one, puts the parameters back
    onto their constraints. Levenberg–Marquardt does not depend on the parameters' units: on rendered cards it
    brings LEDs (``LEDLights``), Gaussian and tabulated beams 0.5-1 mm off back to within 0.01 mm in about ten steps
    where L-BFGS on the same raw parameters stops 0.4-0.7 mm off after 400 iterations.
    It runs in float64 on the images' device, on a copy of the model (the one given is not changed), on images
    averaged down to at most ``options.max_size`` pixels a side. :func:`fit_leds` is this fit, run twice (positions
    and intensities, then every parameter) on a rescaled LED model.

    What the cards cannot tell: one overall scale of the irradiance (the gain absorbs it), and whatever the model
    does outside the angles and distances the cards cover (a table's entries beyond them keep their start values).

    Args:
        model: a :class:`~psmini.lights.LightModel` with ``nn.Parameter`` s (built-ins: ``learnable=True``), the
            start of the fit; K lights.
        cards: the card under each light at N heights: shape :math:`(N, K, H, W)` or a list of N
            :math:`(K, H, W)` tensors; linear readings, dark-subtracted unless ``dark`` is given.
        heights_mm: card height(s) above the reference plane z = 0, mm, one per N (toward the camera).
        pixel_pitch_mm: size of one pixel on the card, mm (orthographic camera, optical axis at the image centre).
        card_albedo: the card's albedo, or one per height (only ratios between heights matter).
        dark: dark frames to subtract, shape :math:`(N, 1, H, W)` or :math:`(1, 1, H, W)` or a list of N
            :math:`(1, H, W)` tensors (``None`` entries: none).
        saturation_level: raw readings at or above it are dropped (with the pixel blocks that hold them); ``1.0``
            for images decoded from 8- or 16-bit files.
        options: the :class:`LightFitOptions` (parameters, pooling, Huber threshold, optimisers); ``None``: the
            defaults.

    Returns:
        a :class:`LightFit`.

    Raises:
        ShapeError: cards not :math:`(N, K, H, W)`, a model with another K, heights, albedos or dark frames that do
            not match N.
        InputError: a model that is no ``LightModel``, without parameters, or an unknown parameter name; no images,
            NaN or infinite values, bad options.
        CalibrationError: a card image without signal (a light that did not light), fewer than two images in all.

    Example:
        >>> from data_synth.rig import RigConfig, render_card
        >>> config = RigConfig(size=32, pixel_pitch_mm=0.3, noise=False, bit_depth=16)
        >>> cards = [render_card(config, height_mm=h) for h in (0.0, 1.0)]
        >>> truth = cards[0].lights
        >>> start = LEDLights(truth.positions_mm + 0.5, truth.principal_directions, learnable=True)  # 0.87 mm off
        >>> images, dark = torch.stack([c.images for c in cards]), torch.stack([c.dark for c in cards])
        >>> fit = fit_lights(start, images, [0.0, 1.0], 0.3, dark=dark, saturation_level=1.0)
        >>> error = (fit.lights.positions_mm.detach() - truth.positions_mm).norm(dim=-1)
        >>> float(error.max()) < 0.01, fit.stages[-1]["optimizer"]
        (True, 'lm')
    """
    options = LightFitOptions() if options is None else options
    if not isinstance(options, LightFitOptions):
        raise InputError(f"options must be a LightFitOptions, got {type(options).__name__}")
    if not isinstance(model, LightModel):
        raise InputError(f"model must be a psmini.lights.LightModel, got {type(model).__name__}")
    cards_data = _prepare_cards(cards, heights_mm, pixel_pitch_mm, card_albedo, dark, saturation_level,
                                options.max_size)
    if model.count != cards_data.count:
        raise ShapeError(f"the model has {model.count} lights but the card images have K={cards_data.count}")
    fitted, dtype, flags = _working_copy(model, cards_data.device)
    names = _chosen(fitted, options.parameters, flags)
    start = copy.deepcopy(fitted).to(dtype=dtype)
    records, losses = _optimise(fitted, names, cards_data, options)
    total, per_light, per_height, gain, loss = _rms_and_gain(fitted, cards_data, options.huber_delta)
    for name, parameter in fitted.named_parameters():
        parameter.requires_grad_(flags[name])
    return LightFit(
        lights=fitted.to(dtype=dtype),
        residual_rms=float(total),
        loss=float(loss),
        residual_rms_per_light=per_light.to(cards_data.dtype),
        residual_rms_per_height=per_height.to(cards_data.dtype),
        gain=gain.to(cards_data.dtype),
        heights_mm=cards_data.heights.to(device=cards_data.device, dtype=cards_data.dtype),
        stages=records,
        losses=losses,
        start=start,
        parameters=names,
    )


@dataclass(frozen=True)
class LEDFitOptions:
    r"""Options of :func:`fit_leds`; the defaults are those ``benchmarks/nearlight.py`` measures.

    Attributes:
        nominal_distance_mm: distance from the field centre at which directional starts place the LEDs
            (``None``: the nominal rig's, 18.7 mm).
        mu_init: :math:`\mu` of starts that have none (point or directional lights).
        max_size: the images are averaged over square blocks down to at most this many pixels a side.
        huber_delta: Huber threshold, as a fraction of the mean card reading.
        optimizer: ``"lbfgs"`` (strong Wolfe line search; default) or ``"adam"``.
        iterations: maximum optimiser iterations (L-BFGS iterations or Adam steps) of the ``point`` and ``led``
            stages.
        learning_rate: Adam's step size (unused by L-BFGS).
        tolerance: L-BFGS stops a stage when the loss changes by less than this relative amount in one step.

    Raises:
        InputError: an unknown optimizer, ``max_size`` < 2, a non-positive ``huber_delta`` or
            ``nominal_distance_mm``, or iterations that are not one count >= 0 per stage.

    Example:
        >>> LEDFitOptions(iterations=(50, 50)).to_dict()["iterations"]
        [50, 50]
    """

    nominal_distance_mm: float | None = None
    mu_init: float = 1.0
    max_size: int = 32
    huber_delta: float = 0.05
    optimizer: str = "lbfgs"
    iterations: tuple[int, int] = (200, 400)
    learning_rate: float = 0.01
    tolerance: float = 1e-10

    def __post_init__(self) -> None:
        if self.optimizer not in ("lbfgs", "adam"):
            raise InputError(f"optimizer must be 'lbfgs' or 'adam', got {self.optimizer!r}")
        if not isinstance(self.max_size, int) or self.max_size < 2:
            raise InputError(f"max_size must be an integer >= 2, got {self.max_size!r}")
        check_positive(self.huber_delta, "huber_delta")
        if len(self.iterations) != len(STAGES) or any(not isinstance(n, int) or n < 0 for n in self.iterations):
            raise InputError(
                f"iterations must hold {len(STAGES)} counts >= 0 (stages {STAGES}), got {self.iterations!r}")
        if self.nominal_distance_mm is not None:
            check_positive(self.nominal_distance_mm, "nominal_distance_mm")

    def to_dict(self) -> dict[str, Any]:
        """The options as a JSON-ready dict."""
        return {**{f: getattr(self, f) for f in self.__dataclass_fields__}, "iterations": list(self.iterations)}


def fit_leds(
    card_images: Tensor | Sequence[Tensor],
    heights_mm: float | Sequence[float] | Tensor,
    pixel_pitch_mm: float,
    init: Any = "nominal",
    *,
    card_albedo: float | Sequence[float] = 1.0,
    dark: Tensor | Sequence[Tensor | None] | None = None,
    saturation_level: float | None = None,
    options: LEDFitOptions | None = None,
) -> LEDFit:
    r"""Fit LED positions, principal directions, intensities and :math:`\mu` to images of a matte card.

    The camera's per-pixel gain × vignetting is eliminated in closed form (see the module's docstring), so the
    result does not depend on it, and intensities are relative: they are scaled to average 1. Two stages, each
    started from the previous: ``point`` (positions and intensities, the beams held at the start's) and ``led``
    (every parameter). Each stage runs up to ``options.iterations`` optimiser iterations; L-BFGS (the default)
    projects onto the constraints every 20 iterations and stops when the loss no longer changes, Adam projects after
    every step. The fit runs in float64 on the images' device, on images averaged down to at most
    ``options.max_size`` pixels a side.

    Args:
        card_images: the card under each LED at N heights: shape :math:`(N, K, H, W)` or a list of N
            :math:`(K, H, W)` tensors; linear readings, dark-subtracted unless ``dark`` is given.
        heights_mm: card height(s) above the reference plane, mm, one per N (toward the camera).
        pixel_pitch_mm: size of one pixel on the card, mm (orthographic camera).
        init: the start. ``"nominal"`` (the psmini rig: K LEDs on a 31.6 mm ring, 10 mm up, pointing at the
            field centre, :math:`\mu = 1`); an object with ``ring_diameter_mm`` and ``led_height_mm`` (such as
            ``data_synth.rig.RigConfig``); an ``LEDLights`` or ``PointLights`` (positions; point lights get beams
            toward the field centre and ``options.mu_init``); a ``DirectionalLights`` or a :math:`(K, 3)` tensor of
            directions (a mirror-sphere calibration: positions along them at ``options.nominal_distance_mm``); or a
            light object of ``docs/capture-format.md``.
        card_albedo: the card's albedo, or one per height when different cards were used (only ratios between
            heights matter: one overall scale goes into the gain).
        dark: dark frames to subtract, shape :math:`(N, 1, H, W)` or :math:`(1, 1, H, W)` or a list of N
            :math:`(1, H, W)` tensors (``None`` entries: none).
        saturation_level: raw readings at or above it are dropped (with the pixel blocks that hold them). Pass
            ``1.0`` for images decoded from 8- or 16-bit files: a clipped reading looks darker than the LED
            really is, and about 1% of clipped 8-bit card readings near the field's edge pulled the fitted
            positions 2.1 mm off (``psmini calibrate leds`` passes it).
        options: the :class:`LEDFitOptions` (start distance and mu, pooling, Huber threshold, optimiser,
            iterations); ``None``: the defaults.

    Returns:
        an :class:`LEDFit`.

    Raises:
        ShapeError: images not :math:`(N, K, H, W)`, a start with another K, heights, albedos or dark frames
            that do not match N.
        InputError: no images, NaN or infinite values, bad options.
        CalibrationError: a card image without signal (an LED that did not light), a start with LEDs at or
            below the card plane, fewer than two images in all.

    Example:
        >>> from data_synth.rig import RigConfig, render_card
        >>> config = RigConfig(size=40, pixel_pitch_mm=0.25, noise=False, bit_depth=16)
        >>> cards = [render_card(config, height_mm=h) for h in (0.0, 1.0)]
        >>> images, dark = torch.stack([c.images for c in cards]), torch.stack([c.dark for c in cards])
        >>> fit = fit_leds(images, [0.0, 1.0], 0.25, dark=dark, saturation_level=1.0,
        ...                options=LEDFitOptions(iterations=(50, 50)))
        >>> fit.positions_mm.shape, fit.residual_rms < 1e-3
        (torch.Size([8, 3]), True)
    """
    options = LEDFitOptions() if options is None else options
    if not isinstance(options, LEDFitOptions):
        raise InputError(f"options must be an LEDFitOptions, got {type(options).__name__}")
    images = _stack_images(card_images)
    distance = options.nominal_distance_mm if options.nominal_distance_mm is not None else math.hypot(
        NOMINAL_RING_DIAMETER_MM / 2, NOMINAL_LED_HEIGHT_MM)
    lights = _start_lights(init, images.shape[1], distance, options.mu_init)
    start = _led_lights(t.detach().clone() for t in (lights.positions_mm, lights.principal_directions,
                                                     lights.intensities, lights.mu))
    model: LightModel = _ScaledLEDs(lights)
    records: list[dict[str, Any]] = []
    for stage, steps in zip(STAGES, options.iterations, strict=True):
        adam = options.optimizer == "adam"
        stage_options = LightFitOptions(
            parameters=_ScaledLEDs.STAGE_PARAMETERS[stage], max_size=options.max_size, huber_delta=options.huber_delta,
            adam_iterations=steps if adam else 0, learning_rate=options.learning_rate, optimizer="lbfgs",
            iterations=0 if adam else steps, tolerance=options.tolerance)
        fit = fit_lights(model, images, heights_mm, pixel_pitch_mm, card_albedo=card_albedo, dark=dark,
                         saturation_level=saturation_level, options=stage_options)
        model = fit.lights
        records.append({"stage": stage, "iterations": sum(r["iterations"] for r in fit.stages), "loss": fit.loss,
                        "seconds": sum(r["seconds"] for r in fit.stages)})
        logger.info("LED fit stage %s: %d iterations, loss %.3e, %.2f s", stage, records[-1]["iterations"],
                    fit.loss, records[-1]["seconds"])
    assert isinstance(model, _ScaledLEDs)
    dtype = images.dtype if images.is_floating_point() else torch.get_default_dtype()
    with torch.no_grad():
        leds = model.leds()
        scale = leds.intensities.mean()
        fitted = _led_lights(t.detach().to(dtype).clone() for t in (
            leds.positions_mm, leds.principal_directions, leds.intensities / scale, leds.mu))
    return LEDFit(
        lights=fitted,
        residual_rms=fit.residual_rms,
        residual_rms_per_led=fit.residual_rms_per_light,
        residual_rms_per_height=fit.residual_rms_per_height,
        gain=(fit.gain.double() * scale).to(fit.gain.dtype),  # image units per unit shading of mean-1 intensities
        heights_mm=fit.heights_mm,
        stages=records,
        start=_led_lights(t.to(device=images.device, dtype=dtype) for t in (
            start.positions_mm, start.principal_directions, start.intensities, start.mu)),
    )
