r"""Captures of the weave family under two regions of capture conditions: recognition under a shift.

Recognition measured where training and test conditions are alike says little about a single image's ambiguity:
one LED image sees each structure's shading under one light, and a classifier learns it. The seed paper's premise
is that a single image is ambiguous because what it shows changes with the light, the dye and the print, while the
relief does not. :data:`TRAIN` and :data:`TEST` are two disjoint regions of capture conditions:

=========================  ==================================  ============================================
condition                  training region                     test region
=========================  ==================================  ============================================
dye (albedo factor)        0.75-1.0                            0.45-0.75 or 1.0-1.3
print                      blotches on 30%                     blotches on 25%, a print imitating another
                                                               weave's shading on 50%
cloth orientation          0-90°                               90-180°
LED intensities            each within ±2% of its calibration  each drifted up to ±20%
exposure                   within ±0.2 stop                    ±1 stop (a stop over clips the highlights)
cloth above the card       0-0.3 mm                            0.3-1 mm
=========================  ==================================  ============================================

The structure is drawn from :mod:`data_synth.weaves` (any of its weaves, densities, cross-sections, crimps) the
same way in both regions. The reconstruction knows only the calibration: the light model is the nominal one, and
the card was captured at the nominal exposure with the nominal LEDs; the drift, the exposure and the lift are
what the capture does not say.

An imitating print is the shading of *another* member of the family (another weave, drawn from its own seed),
lit from one of the rig's directions (55° zenith, a random azimuth), printed onto the cloth as an albedo
pattern of 50-100% contrast: in one image the cloth looks like that weave; its relief is unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch
import torch.nn.functional as F

from data_synth.fabrics import CARD_ALBEDO, Fabric
from data_synth.rig import RigConfig, render_capture, rig_lights
from data_synth.weaves import WEAVES, draw_weave_params, make_weave
from psmini.errors import InputError
from psmini.lights import LEDLights
from psmini.render import normals_from_height

__all__ = ["ShiftRegion", "TRAIN", "TEST", "ShiftedDraw", "draw_shifted", "render_shifted"]


@dataclass(frozen=True)
class ShiftRegion:
    """A region of capture conditions (see the module docstring).

    Attributes:
        name: the region's name.
        dye: intervals of the dye's albedo factor (one is drawn, then a value in it).
        blotch_print: probability of a print of blotches (random size, edge and tone).
        imitation_print: probability of a print imitating another weave's shading (exclusive with blotches).
        orientation_deg: range of the cloth's orientation.
        led_drift: each LED's intensity is its calibration times 1 + a uniform draw in ±``led_drift``.
        exposure_stops: range of the exposure's change, stops (factors of 2).
        lift_mm: range of the cloth's height above the card, mm.
    """

    name: str
    dye: tuple[tuple[float, float], ...]
    blotch_print: float
    imitation_print: float
    orientation_deg: tuple[float, float]
    led_drift: float
    exposure_stops: tuple[float, float]
    lift_mm: tuple[float, float]

    def __post_init__(self) -> None:
        if not self.dye or any(not 0 < low <= high for low, high in self.dye):
            raise InputError(f"ShiftRegion.dye must be intervals (low, high) with 0 < low <= high, got {self.dye!r}")
        if not (self.blotch_print >= 0 and self.imitation_print >= 0 and self.blotch_print + self.imitation_print <= 1):
            raise InputError("ShiftRegion print probabilities must be >= 0 and add up to at most 1, got "
                             f"{self.blotch_print!r} and {self.imitation_print!r}")
        if not 0 <= self.led_drift < 1:
            raise InputError(f"ShiftRegion.led_drift must lie in [0, 1), got {self.led_drift!r}")
        for name in ("orientation_deg", "exposure_stops", "lift_mm"):
            low, high = getattr(self, name)
            if not low <= high:
                raise InputError(f"ShiftRegion.{name} must be (low, high) with low <= high, got {(low, high)}")
        if self.lift_mm[0] < 0:
            raise InputError(f"ShiftRegion.lift_mm must be >= 0, got {self.lift_mm!r}")


#: The training region: calibrated conditions with some variety.
TRAIN = ShiftRegion("train", dye=((0.75, 1.0),), blotch_print=0.3, imitation_print=0.0, orientation_deg=(0.0, 90.0),
                    led_drift=0.02, exposure_stops=(-0.2, 0.2), lift_mm=(0.0, 0.3))
#: The test region: other dyes and prints (half of them imitating another weave's shading), the cloth turned,
#: LEDs drifted, the exposure off by up to a stop, the cloth off the card.
TEST = ShiftRegion("test", dye=((0.45, 0.75), (1.0, 1.3)), blotch_print=0.25, imitation_print=0.5,
                   orientation_deg=(90.0, 180.0), led_drift=0.2, exposure_stops=(-1.0, 1.0), lift_mm=(0.3, 1.0))


@dataclass
class ShiftedDraw:
    """One drawn sample: the fabric (its albedo dyed and printed) and the capture conditions.

    Attributes:
        fabric: the cloth, with its truth in ``fabric.params["truth"]``.
        led_factors: each LED's intensity relative to its calibration, shape (K,).
        exposure_stops: the exposure's change, stops.
        lift_mm: the cloth's height above the card, mm.
        drawn: everything drawn, JSON-ready.
    """

    fabric: Fabric
    led_factors: torch.Tensor
    exposure_stops: float
    lift_mm: float
    drawn: dict[str, Any] = field(default_factory=dict)


def _uniform(gen: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))


def _blotches(size: int, pitch: float, gen: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
    """A print of blotches: a thresholded smooth noise of random size, edge sharpness and tone, (size, size)."""
    tone, scale_mm, edge_px = _uniform(gen, 0.25, 1.6), _uniform(gen, 0.8, 3.0), _uniform(gen, 1.5, 12.0)
    cells = max(2, math.ceil(size * pitch / scale_mm)) + 3
    coarse = torch.randn(1, 1, cells, cells, generator=gen, dtype=torch.float64)
    noise = F.interpolate(coarse, size=(size, size), mode="bicubic", align_corners=True)[0, 0]
    motif = torch.sigmoid(noise * (scale_mm / pitch) / edge_px)
    return (1 - motif) + tone * motif, {"tone": tone, "scale_mm": scale_mm, "edge_px": edge_px}


def _imitation(weave: str, size: int, pitch: float, gen: torch.Generator) -> tuple[torch.Tensor, dict[str, Any]]:
    """A print of another weave's shading: the Lambertian shading of a member of the family, mean 1."""
    others = [w for w in WEAVES if w != weave]
    other = others[int(torch.randint(len(others), (), generator=gen))]
    seed = int(torch.randint(1_000_000, (), generator=gen))
    model = make_weave(draw_weave_params(seed, weave=other), size, pitch, seed=seed)
    normals = normals_from_height(model.height_mm.double(), pitch)[0]
    azimuth = _uniform(gen, 0.0, 2 * math.pi)
    zenith = math.radians(55.0)
    light = torch.tensor([math.sin(zenith) * math.cos(azimuth), math.sin(zenith) * math.sin(azimuth),
                          math.cos(zenith)], dtype=torch.float64)
    shading = (normals * light.view(3, 1, 1)).sum(0).clamp_min(0.0)
    shading = shading / shading.mean().clamp_min(1e-12)
    contrast = _uniform(gen, 0.5, 1.0)
    return (1 - contrast) + contrast * shading, {"imitates": other, "imitation_seed": seed,
                                                 "azimuth_deg": math.degrees(azimuth), "contrast": contrast}


def draw_shifted(weave: str, seed: int, region: ShiftRegion, size: int = 256, pixel_pitch_mm: float = 0.025,
                 led_count: int = 8) -> ShiftedDraw:
    """Draw a member of the family of structure ``weave`` and its capture conditions in ``region``.

    The structure (densities, cross-section, crimp) is drawn by :func:`data_synth.weaves.draw_weave_params` from
    the seed alone, the orientation and the conditions from ``region``: the same seed gives the same sample.

    Args:
        weave: one of :data:`data_synth.weaves.WEAVES`.
        seed: the sample's seed.
        region: :data:`TRAIN`, :data:`TEST` or another :class:`ShiftRegion`.
        size: side of the field, pixels.
        pixel_pitch_mm: pixel size, mm.
        led_count: the rig's LEDs (one intensity factor each).

    Returns:
        the :class:`ShiftedDraw`.

    Raises:
        InputError: an unknown weave.

    Example:
        >>> draw = draw_shifted("rib", 4, TEST, size=32)
        >>> 90 <= draw.drawn["orientation_deg"] < 180, 0.3 <= draw.lift_mm <= 1.0
        (True, True)
    """
    if weave not in WEAVES:
        raise InputError(f"unknown weave {weave!r}; expected one of {', '.join(WEAVES)}")
    gen = torch.Generator().manual_seed(2_147_483 * int(seed) + 31 * WEAVES.index(weave)
                                        + sum(map(ord, region.name)))
    params = replace(draw_weave_params(seed, weave=weave), orientation_deg=_uniform(gen, *region.orientation_deg))
    fabric = make_weave(params, size, pixel_pitch_mm, seed=int(seed))
    low, high = region.dye[int(torch.randint(len(region.dye), (), generator=gen))]
    dye = _uniform(gen, low, high)
    pattern = torch.full((size, size), dye, dtype=torch.float64)
    drawn: dict[str, Any] = {"weave": weave, "seed": int(seed), "region": region.name, **params.to_dict(), "dye": dye,
                             "print": "none"}
    kind = float(torch.rand((), generator=gen, dtype=torch.float64))
    if kind < region.blotch_print:
        motif, info = _blotches(size, pixel_pitch_mm, gen)
        pattern, drawn["print"] = pattern * motif, "blotches"
        drawn.update(info)
    elif kind < region.blotch_print + region.imitation_print:
        motif, info = _imitation(weave, size, pixel_pitch_mm, gen)
        pattern, drawn["print"] = pattern * motif, "imitation"
        drawn.update(info)
    albedo = (fabric.albedo.double() * pattern).clamp(0.02, 0.98)
    albedo = torch.where(fabric.mask, albedo, torch.full_like(albedo, CARD_ALBEDO))  # the card stays the card
    fabric = replace(fabric, albedo=albedo.float())
    factors = 1 + region.led_drift * (2 * torch.rand(led_count, generator=gen, dtype=torch.float64) - 1)
    exposure = _uniform(gen, *region.exposure_stops)
    lift = _uniform(gen, *region.lift_mm)
    drawn.update(led_factors=factors.tolist(), exposure_stops=exposure, lift_mm=lift)
    return ShiftedDraw(fabric, factors, exposure, lift, drawn)


def render_shifted(draw: ShiftedDraw, rig: RigConfig, card: Any, seed: int = 0):
    """Render a drawn sample and package it as the reconstruction sees it: the nominal calibration.

    The capture is rendered with each LED's intensity times its factor and the exposure changed by the drawn
    stops (clipping at full scale); the :class:`psmini.io.Sample` carries the rig's nominal light model and the
    card ``card`` (a :func:`data_synth.rig.render_card` capture at the nominal exposure and LEDs).

    Args:
        draw: from :func:`draw_shifted`.
        rig: the rig (its size and pitch must be the draw's).
        card: the flat-field card capture.
        seed: the sensor noise's seed.

    Returns:
        ``(sample, capture)``.

    Example:
        >>> from data_synth.rig import render_card
        >>> rig = RigConfig(size=32, bit_depth=8)
        >>> sample, capture = render_shifted(draw_shifted("plain", 1, TRAIN, size=32), rig, render_card(rig))
        >>> sample.images.shape
        torch.Size([8, 32, 32])
    """
    from psmini.io.sample import Sample

    nominal = rig_lights(rig)
    drifted = LEDLights(nominal.positions_mm, nominal.principal_directions,
                        nominal.intensities * draw.led_factors.to(nominal.intensities), nominal.mu)
    config = rig.replace(exposure=rig.exposure * 2.0 ** draw.exposure_stops)
    capture = render_capture(draw.fabric, config, seed=int(seed), height_offset_mm=draw.lift_mm, lights=drifted)
    sample = Sample(name=f"{draw.drawn['weave']}-{draw.drawn['seed']}", images=capture.images, lights=nominal,
                    dark=capture.dark, reference=card.images, reference_dark=card.dark, card_albedo=CARD_ALBEDO,
                    pixel_pitch_mm=rig.pixel_pitch_mm, saturation_level=1.0)
    return sample, capture
