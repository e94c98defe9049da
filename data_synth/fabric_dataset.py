r"""Randomised fabrics for recognition: every class of :data:`data_synth.FABRICS`, varied as real samples vary.

One integer ``seed`` decides everything about a sample (the draw below, the generator's own randomness, the
sensor noise), so a train/test split by seed keeps every sample on one side. For each sample:

- yarn spacing (every ``*spacing_mm`` parameter, one common factor), yarn width (with the spacing, times its own
  factor) and crimp scaled by factors drawn uniformly from :class:`DatasetOptions`' ranges; the orientation
  uniform over [0°, 180°);
- an albedo pattern independent of the relief, drawn by :func:`albedo_pattern` for every class: the generator's
  own albedo times a random dye level, and with probability ``print_probability`` a printed motif (blotches of
  random size, edge sharpness and a darker or lighter tone, a range that holds the ``print`` class's own ink) —
  so that colour and print tell nothing about the class, and a printed cotton looks like the ``print`` class in
  any single image; only the ink layer's few µm of relief tell them apart;
- the cloth lifted ``0..max_lift_mm`` above the card, and with probability ``wrinkle_probability`` a wrinkle (a
  Gaussian ridge of random height, width and direction added to the height);
- the simulator's sensor (noise, 8-bit quantisation by default), flat-fielded by a card capture.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch
import torch.nn.functional as F

from data_synth.fabrics import CARD_ALBEDO, FABRICS, Fabric, make_fabric
from data_synth.rig import RigConfig, render_capture, render_card
from psmini.errors import InputError

__all__ = ["DatasetOptions", "FabricDraw", "draw_fabric", "albedo_pattern", "render_sample", "CLASSES"]

#: The class names (every generator of :data:`data_synth.FABRICS`).
CLASSES = tuple(FABRICS)


@dataclass(frozen=True)
class DatasetOptions:
    """Ranges of the random draw.

    Attributes:
        spacing_range: factor on every yarn spacing (and, with it, width).
        width_range: extra factor on the yarn width (clamped so that yarns never exceed their spacing).
        crimp_range: factor on the crimp amplitude.
        max_lift_mm: the cloth lies 0..max_lift_mm above the card.
        wrinkle_probability: share of samples with a wrinkle.
        wrinkle_height_mm: range of the wrinkle's height, mm.
        print_probability: share of samples with a printed albedo motif.
        size: crop, pixels.
        rig: the simulated rig (pitch, LEDs, sensor); 8-bit by default.
    """

    spacing_range: tuple[float, float] = (0.92, 1.08)
    width_range: tuple[float, float] = (0.9, 1.0)
    crimp_range: tuple[float, float] = (0.7, 1.3)
    max_lift_mm: float = 1.0
    wrinkle_probability: float = 0.3
    wrinkle_height_mm: tuple[float, float] = (0.05, 0.3)
    print_probability: float = 0.5
    size: int = 256
    rig: RigConfig = field(default_factory=lambda: RigConfig(bit_depth=8))

    def __post_init__(self) -> None:
        for name in ("spacing_range", "width_range", "crimp_range", "wrinkle_height_mm"):
            low, high = getattr(self, name)
            if not 0 < low <= high:
                raise InputError(f"DatasetOptions.{name} must be (low, high) with 0 < low <= high, got {(low, high)}")
        for name in ("wrinkle_probability", "print_probability"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"DatasetOptions.{name} must lie in [0, 1], got {getattr(self, name)!r}")
        if self.max_lift_mm < 0:
            raise InputError(f"DatasetOptions.max_lift_mm must be >= 0, got {self.max_lift_mm!r}")


@dataclass
class FabricDraw:
    """One drawn sample: the fabric (with its changed albedo and height) and what was drawn."""

    fabric: Fabric
    lift_mm: float
    drawn: dict[str, Any]


def _uniform(gen: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))


def _smooth_noise(size: int, cells: int, gen: torch.Generator) -> torch.Tensor:
    coarse = torch.randn(1, 1, cells, cells, generator=gen, dtype=torch.float64)
    return F.interpolate(coarse, size=(size, size), mode="bicubic", align_corners=True)[0, 0]


def albedo_pattern(size: int, gen: torch.Generator, print_probability: float,
                   pixel_pitch_mm: float = 0.025) -> tuple[torch.Tensor, dict]:
    """A multiplicative albedo pattern (1, 1, size, size): a dye level, maybe a printed motif.

    The motif is a field of blotches (a thresholded smooth noise) of random size (0.8-3 mm), edge (1.5-12 px,
    from a sharp screen print to a soft dye), and tone (0.25-1.6 times the cloth's, darker or lighter): the
    range holds the ``print`` class's own ink (dark, 2 mm, ~3 px edges), so the albedo alone cannot tell a
    printed cloth of any class from the ``print`` class; only the ink layer's relief can.
    """
    dye = _uniform(gen, 0.45, 1.25)
    pattern = torch.full((size, size), dye, dtype=torch.float64)
    printed = bool(torch.rand((), generator=gen) < print_probability)
    info: dict[str, Any] = {"dye": dye, "printed": printed}
    if printed:
        ink = _uniform(gen, 0.25, 1.6)
        scale_mm = _uniform(gen, 0.8, 3.0)
        edge_px = _uniform(gen, 1.5, 12.0)
        cells = max(2, math.ceil(size * pixel_pitch_mm / scale_mm)) + 3
        motif = torch.sigmoid(_smooth_noise(size, cells, gen) * (scale_mm / pixel_pitch_mm) / edge_px)
        pattern = pattern * (1 - motif) + ink * dye * motif
        info.update(ink=ink, scale_mm=scale_mm, edge_px=edge_px)
    return pattern[None, None], info


def draw_fabric(name: str, seed: int, options: DatasetOptions = DatasetOptions()) -> FabricDraw:
    """Draw the fabric of class ``name`` for ``seed`` (see the module docstring).

    Raises:
        InputError: an unknown class.

    Example:
        >>> draw = draw_fabric("twill", 3, DatasetOptions(size=32))
        >>> draw.fabric.height_mm.shape, 0 <= draw.drawn["orientation_deg"] < 180
        (torch.Size([1, 1, 32, 32]), True)
    """
    if name not in FABRICS:
        raise InputError(f"unknown fabric {name!r}; expected one of {', '.join(FABRICS)}")
    gen = torch.Generator().manual_seed(1_000_003 * int(seed) + CLASSES.index(name))
    defaults = {p.name: p.default for p in inspect.signature(FABRICS[name]).parameters.values()
                if p.kind == p.KEYWORD_ONLY}
    spacing = _uniform(gen, *options.spacing_range)
    width = _uniform(gen, *options.width_range)
    crimp = _uniform(gen, *options.crimp_range)
    params: dict[str, Any] = {"orientation_deg": _uniform(gen, 0.0, 180.0)}
    for key, value in defaults.items():
        if key.endswith("spacing_mm"):
            params[key] = value * spacing
        elif key.endswith("width_mm") and not key.startswith("wrinkle"):
            partner = key.replace("width", "spacing")
            limit = defaults.get(partner, defaults.get("spacing_mm", defaults.get("wale_spacing_mm", math.inf)))
            params[key] = min(value * spacing * width, 0.99 * limit * spacing)
        elif key == "crimp_mm":
            params[key] = value * crimp
    pitch = options.rig.pixel_pitch_mm
    fabric = make_fabric(name, size=options.size, pixel_pitch_mm=pitch, seed=int(seed), **params)
    pattern, albedo_info = albedo_pattern(options.size, gen, options.print_probability, pitch)
    albedo = (fabric.albedo.double() * pattern).clamp(0.02, 0.98)
    albedo = torch.where(fabric.mask, albedo, fabric.albedo.double())  # the card stays the card
    height = fabric.height_mm.double()
    wrinkled = bool(torch.rand((), generator=gen) < options.wrinkle_probability)
    drawn: dict[str, Any] = {"class": name, "seed": int(seed), "spacing_factor": spacing, "width_factor": width,
                             "crimp_factor": crimp, **params, "albedo": albedo_info, "wrinkle": wrinkled}
    if wrinkled:
        extent = options.size * pitch
        angle = _uniform(gen, 0.0, math.pi)
        ridge_height = _uniform(gen, *options.wrinkle_height_mm)
        ridge_width = _uniform(gen, 0.8, 2.5)
        offset = _uniform(gen, -0.3, 0.3) * extent
        idx = (torch.arange(options.size, dtype=torch.float64) - (options.size - 1) / 2) * pitch
        y, x = torch.meshgrid(-idx, idx, indexing="ij")
        distance = x * math.cos(angle) + y * math.sin(angle) - offset
        height = height + ridge_height * torch.exp(-0.5 * (distance / (ridge_width / 2)).square())
        drawn.update(wrinkle_height_mm=ridge_height, wrinkle_width_mm=ridge_width)
    lift = _uniform(gen, 0.0, options.max_lift_mm)
    drawn["lift_mm"] = lift
    fabric = replace(fabric, height_mm=height.float(), albedo=albedo.float())
    return FabricDraw(fabric, lift, drawn)


def render_sample(name: str, seed: int, options: DatasetOptions = DatasetOptions(), card: Any = None):
    """Draw, render and package one sample as a :class:`psmini.io.Sample` (flat-fielded by a card capture).

    Args:
        name: the class.
        seed: the sample's seed.
        options: the draw's ranges and the rig.
        card: a card capture of :func:`data_synth.rig.render_card` for this rig, reused across samples (rendered
            when None).

    Returns:
        ``(sample, draw, capture)``: the :class:`psmini.io.Sample`, the :class:`FabricDraw` and the
        :class:`data_synth.rig.SyntheticCapture` (its ``images[k]`` are the single LED images).

    Example:
        >>> sample, draw, _ = render_sample("cotton", 1, DatasetOptions(size=32))
        >>> sample.images.shape
        torch.Size([8, 32, 32])
    """
    from psmini.io.sample import Sample

    config = options.rig.replace(size=options.size)
    draw = draw_fabric(name, seed, options)
    capture = render_capture(draw.fabric, config, seed=int(seed), height_offset_mm=draw.lift_mm)
    card = card if card is not None else render_card(config, seed=10_007)
    sample = Sample(name=f"{name}-{seed}", images=capture.images, lights=capture.lights, dark=capture.dark,
                    reference=card.images, reference_dark=card.dark, card_albedo=CARD_ALBEDO,
                    pixel_pitch_mm=config.pixel_pitch_mm, saturation_level=1.0)
    return sample, draw, capture
