r"""Procedural textiles at the rig's scale: height fields (mm), albedo, specular weight and cloth mask.

Every generator draws a fabric on a square grid of ``size`` pixels at ``pixel_pitch_mm`` (default 400 px at
0.025 mm/px: 10 mm of cloth) in psmini's camera frame (x right, y up, heights toward the camera). The cloth
lies on a card at height 0: heights are measured from the card plane and the underside of the cloth touches
it. Where no yarn covers the card (the holes of a net, the gaps of an open weave) the ground truth is the card
itself: height 0, normal (0, 0, 1), albedo ``card_albedo`` (default 0.8, the matte card used for
flat-fielding), specular 0, and ``mask`` False.

Woven fabrics follow Peirce's geometry ("The geometry of cloth structure", J. Textile Inst. 1937): yarns of
elliptical cross-section (width × thickness) whose centre lines undulate (crimp) as they pass over and under
the crossing yarns, the interlacing given by a weave pattern (plain 1/1, twill 2/1, satin 5/2). Knits are
built from the stitch shapes of jersey (V-shaped legs on the face, arcs on the purl side). Fibre twist appears
as faint helical stripes in height and albedo; ``randomness`` scales yarn position jitter, meander and albedo
variation. The same ``seed`` always gives the same fabric.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from psmini.errors import InputError

__all__ = ["Fabric", "FABRICS", "make_fabric", "CARD_ALBEDO"]

#: Albedo of the matte card beneath the cloth (seen through holes) and of the flat-field card.
CARD_ALBEDO = 0.8

# Interlacing of one repeat: pattern[i, j] = 1 where warp j passes over weft i.
_PLAIN = [[1, 0], [0, 1]]
_TWILL_2_1 = [[1, 1, 0], [0, 1, 1], [1, 0, 1]]
# 5-end warp-faced satin, move number 2: warp j goes under weft i only where j = 2 i mod 5.
_SATIN_5 = [[0 if j == (2 * i) % 5 else 1 for j in range(5)] for i in range(5)]


@dataclass
class Fabric:
    """A synthetic fabric sample with its ground truth.

    Attributes:
        name: the generator's name (a key of :data:`FABRICS`).
        height_mm: height above the card plane, shape :math:`(1, 1, H, W)`, mm.
        albedo: diffuse albedo in [0, 1], shape :math:`(1, 1, H, W)`.
        specular: Blinn–Phong weight (metallic threads), shape :math:`(1, 1, H, W)`; 0 for matte cloth.
        mask: True where cloth covers the card, shape :math:`(1, 1, H, W)`, bool.
        pixel_pitch_mm: pixel size on the cloth, mm.
        params: every parameter the generator used (defaults included) and the seed.
    """

    name: str
    height_mm: Tensor
    albedo: Tensor
    specular: Tensor
    mask: Tensor
    pixel_pitch_mm: float
    params: dict[str, Any] = field(default_factory=dict)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Fabric:
        """A copy on ``device`` with float maps in ``dtype`` (the mask stays bool)."""
        floats = {k: getattr(self, k).to(device=device, dtype=dtype) for k in ("height_mm", "albedo", "specular")}
        return Fabric(self.name, mask=self.mask.to(device), pixel_pitch_mm=self.pixel_pitch_mm,
                      params=dict(self.params), **floats)


class _Canvas:
    """Pixel coordinates in mm (rotated by the fabric's orientation) and the seeded random source."""

    def __init__(self, size: int, pitch: float, seed: int, orientation_deg: float) -> None:
        self.size, self.pitch = size, pitch
        self.gen = torch.Generator().manual_seed(int(seed))
        centre = (size - 1) / 2
        index = torch.arange(size, dtype=torch.float64)
        x = ((index - centre) * pitch).view(1, size).expand(size, size)
        y = (-(index - centre) * pitch).view(size, 1).expand(size, size)
        angle = math.radians(orientation_deg)
        # u runs across the warp (along the weft), v along the warp.
        self.u = x * math.cos(angle) + y * math.sin(angle)
        self.v = -x * math.sin(angle) + y * math.cos(angle)
        self.x, self.y = x, y

    def normal(self, count: int) -> Tensor:
        return torch.randn(count, generator=self.gen, dtype=torch.float64)

    def uniform(self, count: int) -> Tensor:
        return torch.rand(count, generator=self.gen, dtype=torch.float64)

    def smooth_noise(self, scale_mm: float) -> Tensor:
        """Zero-mean, unit-variance-ish noise varying over ``scale_mm`` (bicubic upsampling of a coarse grid)."""
        cells = max(2, int(math.ceil(self.size * self.pitch / scale_mm)) + 3)
        coarse = torch.randn(1, 1, cells, cells, generator=self.gen, dtype=torch.float64)
        fine = F.interpolate(coarse, size=(self.size, self.size), mode="bicubic", align_corners=True)
        return fine[0, 0]


@dataclass
class _YarnSet:
    """Top surface of one set of parallel yarns: height (-inf off the yarns), yarn id, across/along coordinates."""

    top: Tensor
    yarn: Tensor
    across: Tensor
    along: Tensor


def _yarn_set(
    canvas: _Canvas,
    across: Tensor,
    along: Tensor,
    spacing: float,
    width: float,
    thickness: float,
    crossing_spacing: float,
    crimp: float,
    over: Callable[[Tensor, Tensor], Tensor],
    randomness: float,
    flatness: float = 0.5,
) -> _YarnSet:
    """Parallel yarns along ``along``, centred every ``spacing`` across, crimped by the interlacing ``over``.

    ``over(i, j)`` is +1 where yarn j passes over crossing i and -1 where under. The centre line moves between
    ±crimp/2 with a raised cosine between crossings (Peirce's undulation); the cross-section is
    ``thickness/2 · (1 - r²)^flatness`` (0.5: an ellipse; smaller: a flat tape).
    """
    first = int(math.floor(float(across.min()) / spacing)) - 3
    last = int(math.ceil(float(across.max()) / spacing)) + 3
    count = last - first + 1
    jitter = canvas.normal(count) * 0.08 * spacing * randomness
    phase = canvas.uniform(count) * 2 * math.pi
    meander = 0.06 * spacing * randomness
    meander_len = 20 * spacing
    nearest = torch.round(across / spacing).long()
    best_top = torch.full_like(across, -math.inf)
    best_yarn = torch.zeros_like(nearest)
    best_across = torch.zeros_like(across)
    f = along / crossing_spacing
    i0 = torch.floor(f).long()
    blend = (1 - torch.cos(math.pi * (f - i0))) / 2
    for offset in (-1, 0, 1):  # the yarn a pixel lies on is one of its three nearest (3 passes, not per pixel)
        j = nearest + offset
        k = (j - first).clamp(0, count - 1)
        centre = j * spacing + jitter[k] + meander * torch.sin(2 * math.pi * along / meander_len + phase[k])
        r = (across - centre) / (width / 2)
        centre_z = crimp / 2 * ((1 - blend) * over(i0, j) + blend * over(i0 + 1, j))
        top = centre_z + thickness / 2 * (1 - r.square()).clamp_min(0).pow(flatness)
        top = torch.where(r.abs() < 1, top, torch.full_like(top, -math.inf))
        better = top > best_top
        best_top = torch.where(better, top, best_top)
        best_yarn = torch.where(better, j, best_yarn)
        best_across = torch.where(better, across - centre, best_across)
    return _YarnSet(best_top, best_yarn, best_across, along)


def _pattern_lookup(pattern: list[list[int]], warp: bool) -> Callable[[Tensor, Tensor], Tensor]:
    """``over(crossing, yarn)`` for the warp (yarn j, crossing weft i) or the weft (yarn i, crossing warp j)."""
    table = torch.tensor(pattern, dtype=torch.float64) * 2 - 1
    rows, cols = table.shape

    def over(crossing: Tensor, yarn: Tensor) -> Tensor:
        if warp:
            return table[crossing % rows, yarn % cols]
        return -table[yarn % rows, crossing % cols]

    return over


def _twist(yarns: _YarnSet, twist_pitch: float, twist_deg: float) -> Tensor:
    """Helical fibre stripes on a yarn, in [-1, 1]."""
    phase = yarns.along + yarns.across * math.tan(math.radians(twist_deg))
    return torch.cos(2 * math.pi * phase / twist_pitch)


def _yarn_factor(canvas: _Canvas, yarn: Tensor, spread: float) -> Tensor:
    """A random brightness factor per yarn id, around 1."""
    low = int(yarn.min())
    table = 1 + spread * canvas.normal(int(yarn.max()) - low + 1)
    return table[yarn - low]


def _woven(
    canvas: _Canvas,
    pattern: list[list[int]],
    warp_spacing_mm: float,
    weft_spacing_mm: float,
    warp_width_mm: float,
    weft_width_mm: float,
    thickness_mm: float,
    crimp_mm: float,
    albedo: float,
    randomness: float,
    weft_albedo: float | None = None,
    flatness: float = 0.5,
) -> tuple[Tensor, Tensor, Tensor, _YarnSet, _YarnSet, Tensor]:
    """Height, albedo, cover mask of a woven fabric, plus both yarn sets and the weft-on-top map (``flatness``: the
    cross-section's exponent, see :func:`_yarn_set`)."""
    warp = _yarn_set(canvas, canvas.u, canvas.v, warp_spacing_mm, warp_width_mm, thickness_mm, weft_spacing_mm,
                     crimp_mm, _pattern_lookup(pattern, warp=True), randomness, flatness)
    weft = _yarn_set(canvas, canvas.v, canvas.u, weft_spacing_mm, weft_width_mm, thickness_mm, warp_spacing_mm,
                     crimp_mm, _pattern_lookup(pattern, warp=False), randomness, flatness)
    weft_on_top = weft.top > warp.top
    top = torch.maximum(warp.top, weft.top)
    covered = torch.isfinite(top)
    fibre = torch.where(weft_on_top, _twist(weft, 4 * thickness_mm, 30.0), _twist(warp, 4 * thickness_mm, 30.0))
    # The cloth's underside rests on the card: shift so that the lowest yarn bottom is at 0.
    base = crimp_mm / 2 + thickness_mm / 2
    height = torch.where(covered, top + base + 0.02 * thickness_mm * fibre, torch.zeros_like(top))
    tone = torch.where(
        weft_on_top,
        (weft_albedo if weft_albedo is not None else albedo) * _yarn_factor(canvas, weft.yarn, 0.06 * randomness),
        albedo * _yarn_factor(canvas, warp.yarn, 0.06 * randomness),
    )
    tone = tone * (1 + 0.05 * fibre) * (1 + 0.04 * randomness * canvas.smooth_noise(2.0))
    albedo_map = torch.where(covered, tone.clamp(0.02, 0.98), torch.full_like(tone, CARD_ALBEDO))
    return height, albedo_map, covered, warp, weft, weft_on_top


def _finish(name: str, canvas: _Canvas, height: Tensor, albedo: Tensor, mask: Tensor,
            specular: Tensor | None, params: dict[str, Any]) -> Fabric:
    """Pack float64 maps into a float32 :class:`Fabric` of shape (1, 1, H, W)."""
    def pack(x: Tensor) -> Tensor:
        return x.to(torch.float32)[None, None].contiguous()

    spec = torch.zeros_like(height) if specular is None else specular
    return Fabric(name, pack(height), pack(albedo), pack(spec), mask[None, None].clone(), canvas.pitch, params)


def _weave_fabric(name: str, pattern: list[list[int]], size: int, pixel_pitch_mm: float, seed: int,
                  params: dict[str, Any]) -> Fabric:
    canvas = _Canvas(size, pixel_pitch_mm, seed, params["orientation_deg"])
    height, albedo, covered, _, _, _ = _woven(
        canvas, pattern, params["spacing_mm"], params.get("weft_spacing_mm", params["spacing_mm"]),
        params["width_mm"], params.get("weft_width_mm", params["width_mm"]), params["thickness_mm"],
        params["crimp_mm"], params["albedo"], params["randomness"], params.get("weft_albedo"),
    )
    return _finish(name, canvas, height, albedo, covered, None, params)


def jute(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.62,
         width_mm: float = 0.55, thickness_mm: float = 0.3, crimp_mm: float = 0.22, orientation_deg: float = 0.0,
         randomness: float = 1.0, albedo: float = 0.45) -> Fabric:
    """Coarse 1×1 plain weave of jute (the "Yuta" rug): yarns ~0.5 mm, irregular."""
    return _weave_fabric("jute", _PLAIN, size, pixel_pitch_mm, seed, _params(locals()))


def cotton(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.2,
           width_mm: float = 0.19, thickness_mm: float = 0.1, crimp_mm: float = 0.06, orientation_deg: float = 0.0,
           randomness: float = 0.5, albedo: float = 0.75) -> Fabric:
    """Fine 1×1 plain weave of cotton (yarns ~0.2 mm)."""
    return _weave_fabric("cotton", _PLAIN, size, pixel_pitch_mm, seed, _params(locals()))


def silk(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.06,
         width_mm: float = 0.058, thickness_mm: float = 0.03, crimp_mm: float = 0.015, orientation_deg: float = 0.0,
         randomness: float = 0.3, albedo: float = 0.8) -> Fabric:
    """Very fine 1×1 plain weave of silk (yarns ~0.05 mm, about two pixels)."""
    return _weave_fabric("silk", _PLAIN, size, pixel_pitch_mm, seed, _params(locals()))


def twill(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.14,
          width_mm: float = 0.135, thickness_mm: float = 0.08, crimp_mm: float = 0.04, orientation_deg: float = 0.0,
          randomness: float = 0.4, albedo: float = 0.6, weft_albedo: float = 0.7) -> Fabric:
    """2/1 twill, as in a "Saglia" lining: diagonal ribs from floats over two picks."""
    return _weave_fabric("twill", _TWILL_2_1, size, pixel_pitch_mm, seed, _params(locals()))


def satin(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.08,
          weft_spacing_mm: float = 0.16, width_mm: float = 0.078, weft_width_mm: float = 0.15,
          thickness_mm: float = 0.05, crimp_mm: float = 0.03, orientation_deg: float = 0.0, randomness: float = 0.3,
          albedo: float = 0.7) -> Fabric:
    """5-end warp-faced satin (move number 2): long warp floats, few visible interlacings."""
    return _weave_fabric("satin", _SATIN_5, size, pixel_pitch_mm, seed, _params(locals()))


def net(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 1.1,
        width_mm: float = 0.16, thickness_mm: float = 0.14, crimp_mm: float = 0.1, orientation_deg: float = 45.0,
        randomness: float = 0.5, albedo: float = 0.85) -> Fabric:
    """Elastic net: an open mesh of thin yarns with diamond holes through which the card shows (mask False)."""
    return _weave_fabric("net", _PLAIN, size, pixel_pitch_mm, seed, _params(locals()))


def lurex(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.22,
          width_mm: float = 0.2, thickness_mm: float = 0.1, crimp_mm: float = 0.06, orientation_deg: float = 0.0,
          randomness: float = 0.5, albedo: float = 0.7, metal_every: int = 3, metal_albedo: float = 0.25,
          metal_specular: float = 0.9) -> Fabric:
    """Cotton plain weave with Lurex-like flat metallic tapes as every ``metal_every``-th weft (specular map)."""
    params = _params(locals())
    canvas = _Canvas(size, pixel_pitch_mm, seed, orientation_deg)
    height, albedo_map, covered, _, weft, weft_on_top = _woven(
        canvas, _PLAIN, spacing_mm, spacing_mm, width_mm, width_mm, thickness_mm, crimp_mm, albedo, randomness
    )
    metal = covered & weft_on_top & (weft.yarn % max(int(metal_every), 1) == 0)
    # Tapes are flat: squash the rounded profile's top into a plateau by a power law of the across coordinate.
    r = (weft.across / (width_mm / 2)).clamp(-1, 1)
    tape = thickness_mm / 2 * (1 - r.abs().pow(8)).clamp_min(0).pow(0.5)
    round_ = thickness_mm / 2 * (1 - r.square()).clamp_min(0).pow(0.5)
    height = torch.where(metal, height + tape - round_, height)
    albedo_map = torch.where(metal, torch.full_like(albedo_map, metal_albedo), albedo_map)
    specular = torch.where(metal, torch.full_like(height, metal_specular), torch.zeros_like(height))
    return _finish("lurex", canvas, height, albedo_map, covered, specular, params)


def taffeta(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.08,
            width_mm: float = 0.078, thickness_mm: float = 0.04, crimp_mm: float = 0.02,
            orientation_deg: float = 0.0, randomness: float = 0.3, albedo: float = 0.65,
            wrinkle_height_mm: float = 0.4, wrinkle_width_mm: float = 1.2) -> Fabric:
    """Silk taffeta (fine plain weave) with one wrinkle: a Gaussian ridge across the field, not flat."""
    params = _params(locals())
    canvas = _Canvas(size, pixel_pitch_mm, seed, orientation_deg)
    height, albedo_map, covered, _, _, _ = _woven(
        canvas, _PLAIN, spacing_mm, spacing_mm, width_mm, width_mm, thickness_mm, crimp_mm, albedo, randomness
    )
    angle, offset = canvas.uniform(2)
    direction = math.pi * float(angle)
    extent = size * pixel_pitch_mm
    distance = canvas.x * math.cos(direction) + canvas.y * math.sin(direction) - (float(offset) - 0.5) * 0.4 * extent
    ridge = wrinkle_height_mm * torch.exp(-0.5 * (distance / (wrinkle_width_mm / 2)).square())
    return _finish("taffeta", canvas, height + ridge, albedo_map, covered, None, params)


def printed(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, spacing_mm: float = 0.2,
            width_mm: float = 0.19, thickness_mm: float = 0.1, crimp_mm: float = 0.06, orientation_deg: float = 0.0,
            randomness: float = 0.5, albedo: float = 0.8, ink_thickness_mm: float = 0.004,
            ink_albedo: float = 0.2, ink_scale_mm: float = 2.0) -> Fabric:
    """Cotton plain weave printed with a few-µm ink layer in blotches (dark albedo, slightly raised)."""
    params = _params(locals())
    canvas = _Canvas(size, pixel_pitch_mm, seed, orientation_deg)
    height, albedo_map, covered, _, _, _ = _woven(
        canvas, _PLAIN, spacing_mm, spacing_mm, width_mm, width_mm, thickness_mm, crimp_mm, albedo, randomness
    )
    # A smooth step (over ~3 pixels) of a thresholded noise field gives blotches with soft edges.
    ink = torch.sigmoid(canvas.smooth_noise(ink_scale_mm) * (ink_scale_mm / pixel_pitch_mm) / 3) * covered
    height = height + ink_thickness_mm * ink
    albedo_map = albedo_map * (1 - ink) + ink_albedo * ink
    return _finish("print", canvas, height, albedo_map, covered, None, params)


def knit(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, wale_spacing_mm: float = 0.32,
         course_spacing_mm: float = 0.26, width_mm: float = 0.15, thickness_mm: float = 0.1, crimp_mm: float = 0.06,
         orientation_deg: float = 0.0, randomness: float = 0.4, albedo: float = 0.6) -> Fabric:
    """Micro jersey knit, face side: columns (wales) of V-shaped stitches whose legs dip at the interlocks."""
    params = _params(locals())
    canvas = _Canvas(size, pixel_pitch_mm, seed, orientation_deg)
    a, b = wale_spacing_mm, course_spacing_mm
    wale = torch.round(canvas.u / a)
    du = canvas.u - wale * a
    f = canvas.v / b
    course = torch.floor(f)
    t = f - course
    spread = a * (0.06 + 0.16 * t)  # legs meet at the bottom of the stitch and open toward the top
    tilt = math.atan(0.16 * a / b)
    half = width_mm / 2 / math.cos(tilt)
    dip = crimp_mm / 2 * torch.sin(math.pi * t)
    best = torch.full_like(du, -math.inf)
    leg_id = torch.zeros_like(du)
    for side in (-1.0, 1.0):
        r = (du - side * spread) / half
        top = dip + thickness_mm / 2 * (1 - r.square()).clamp_min(0).sqrt()
        top = torch.where(r.abs() < 1, top, torch.full_like(top, -math.inf))
        leg_id = torch.where(top > best, side, leg_id)
        best = torch.maximum(best, top)
    covered = torch.isfinite(best)
    fibre = torch.cos(2 * math.pi * (canvas.v + leg_id * canvas.u) / (3 * thickness_mm))
    height = torch.where(covered, best + crimp_mm / 2 + thickness_mm / 2 + 0.02 * thickness_mm * fibre,
                         torch.zeros_like(best))
    yarn = (course * 7919 + wale).long()  # one random tone per stitch
    tone = albedo * _yarn_factor(canvas, yarn, 0.05 * randomness) * (1 + 0.05 * fibre)
    albedo_map = torch.where(covered, tone.clamp(0.02, 0.98), torch.full_like(tone, CARD_ALBEDO))
    return _finish("knit", canvas, height, albedo_map, covered, None, params)


def purl(size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, *, wale_spacing_mm: float = 0.4,
         course_spacing_mm: float = 0.3, width_mm: float = 0.2, thickness_mm: float = 0.14, crimp_mm: float = 0.08,
         orientation_deg: float = 0.0, randomness: float = 0.4, albedo: float = 0.55) -> Fabric:
    """Purl (reverse jersey) side of a knit: rows of loop heads and sinker arcs, alternating up and down."""
    params = _params(locals())
    canvas = _Canvas(size, pixel_pitch_mm, seed, orientation_deg)
    a, b = wale_spacing_mm, course_spacing_mm
    nearest = torch.round(canvas.v / b)
    best = torch.full_like(canvas.u, -math.inf)
    row_id = torch.zeros_like(nearest)
    phase = 2 * math.pi * canvas.u / a
    for offset in (-1, 0, 1):
        row = nearest + offset
        centre = row * b + (b / 4) * torch.cos(phase + math.pi * row)
        slope = -(b / 4) * (2 * math.pi / a) * torch.sin(phase + math.pi * row)
        # distance across the arc, measured perpendicular to it
        r = (canvas.v - centre) / torch.sqrt(1 + slope.square()) / (width_mm / 2)
        top = crimp_mm / 2 * torch.cos(phase + math.pi * row) + thickness_mm / 2 * (1 - r.square()).clamp_min(0).sqrt()
        top = torch.where(r.abs() < 1, top, torch.full_like(top, -math.inf))
        row_id = torch.where(top > best, row, row_id)
        best = torch.maximum(best, top)
    covered = torch.isfinite(best)
    fibre = torch.cos(2 * math.pi * (canvas.u + 0.5 * canvas.v) / (3 * thickness_mm))
    height = torch.where(covered, best + crimp_mm / 2 + thickness_mm / 2 + 0.02 * thickness_mm * fibre,
                         torch.zeros_like(best))
    tone = albedo * _yarn_factor(canvas, row_id.long(), 0.05 * randomness) * (1 + 0.05 * fibre)
    albedo_map = torch.where(covered, tone.clamp(0.02, 0.98), torch.full_like(tone, CARD_ALBEDO))
    return _finish("purl", canvas, height, albedo_map, covered, None, params)


def _params(frame: dict[str, Any]) -> dict[str, Any]:
    """The generator's arguments as a plain dict (what :attr:`Fabric.params` records)."""
    return {k: v for k, v in frame.items() if not k.startswith("_")}


#: Fabric generators by name: ``FABRICS[name](size, pixel_pitch_mm, seed, **params) -> Fabric``.
FABRICS: dict[str, Callable[..., Fabric]] = {
    "jute": jute,
    "cotton": cotton,
    "silk": silk,
    "twill": twill,
    "satin": satin,
    "knit": knit,
    "purl": purl,
    "net": net,
    "lurex": lurex,
    "taffeta": taffeta,
    "print": printed,
}


def make_fabric(name: str, size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0, **params: Any) -> Fabric:
    """Generate the fabric ``name`` (a key of :data:`FABRICS`) with its ground truth.

    Args:
        name: one of ``jute, cotton, silk, twill, satin, knit, purl, net, lurex, taffeta, print``.
        size: side of the square field in pixels (>= 8).
        pixel_pitch_mm: pixel size on the cloth, mm (> 0).
        seed: random seed; the same seed and parameters give the same fabric.
        **params: the generator's keyword parameters (yarn spacing, width, thickness, crimp, orientation,
            randomness, albedo, and fabric-specific ones); see each generator's signature.

    Returns:
        a :class:`Fabric` of shape :math:`(1, 1, size, size)` maps, float32, on the CPU.

    Raises:
        InputError: for an unknown name or parameter, or a bad size or pitch.

    Example:
        >>> fabric = make_fabric("jute", size=64, seed=1)
        >>> fabric.height_mm.shape, fabric.params["seed"]
        (torch.Size([1, 1, 64, 64]), 1)
    """
    if name not in FABRICS:
        raise InputError(f"unknown fabric {name!r}; expected one of {', '.join(FABRICS)}")
    if not isinstance(size, int) or size < 8:
        raise InputError(f"size must be an integer >= 8 pixels, got {size!r}")
    if not (isinstance(pixel_pitch_mm, (int, float)) and 0 < pixel_pitch_mm < math.inf):
        raise InputError(f"pixel_pitch_mm must be a positive number, got {pixel_pitch_mm!r}")
    generator = FABRICS[name]
    accepted = {p.name for p in inspect.signature(generator).parameters.values() if p.kind == p.KEYWORD_ONLY}
    unknown = sorted(set(params) - accepted)
    if unknown:
        raise InputError(f"fabric {name!r} has no parameter(s) {unknown}; it accepts {sorted(accepted)}")
    return generator(size, float(pixel_pitch_mm), int(seed), **params)
