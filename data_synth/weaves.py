r"""A randomised family of woven and knitted structures with their ground-truth structure descriptors.

:mod:`data_synth.fabrics` draws psmini's named fabrics, each around one set of parameters. Descriptors checked on
them alone can be tuned to them. This module draws from a *family* instead, as wide as the cloth that a textile
laboratory sees:

- the weave: plain, 2/2 basket, 2/1 and 3/1 twill, 5-end satin, 2/2 warp rib (each end floats over two picks,
  so the weft's repeat is four picks and the warp's two ends) and single jersey knit (face side);
- unbalanced densities, 10-40 threads per cm in each system, drawn independently (ends and picks; wales and
  courses for the knit);
- any orientation over [0°, 180°);
- the yarn cross-section: the top of a yarn is ``thickness/2 · (1 - r²)^flatness`` across its width, flatness
  0.3 (a flat tape) to 0.8 (a lens), the width 70-100% of the spacing (gaps where the card shows, to a closed
  cloth);
- the crimp amplitude from 0.15 to 2 times the yarn's own height (log-uniform), so that either the yarn spacing
  or the crossing pattern dominates the height's spectrum (Peirce: in a jammed cloth the crimp heights of the two
  systems add up to the sum of the yarn diameters, so one system's crimp can reach twice a yarn's height);
- yarn jitter and meander (``randomness`` 0.1-0.4).

:func:`draw_weave` draws one sample from a seed; its :class:`WeaveTruth` holds what a structure descriptor must
find: the two systems' densities (threads per cm counted across the yarns, the denser first), the directions in
which their yarns run (degrees in [0, 180), counter-clockwise from x, y up) and the repeat of the interlacing along
each system (threads per repeat; 1 for a knit's stitch lattice).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch

from data_synth.fabrics import Fabric, _Canvas, _finish, _woven, knit
from psmini.errors import InputError

__all__ = ["WEAVES", "WEAVE_PATTERNS", "WeaveParams", "WeaveTruth", "FamilyOptions", "draw_weave_params",
           "draw_weave", "make_weave", "pattern_repeats"]

# pattern[i][j] = 1 where warp end j passes over weft pick i (data_synth.fabrics' convention).
WEAVE_PATTERNS: dict[str, list[list[int]]] = {
    "plain": [[1, 0], [0, 1]],
    "basket": [[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1], [0, 0, 1, 1]],
    "twill_2_1": [[1, 1, 0], [0, 1, 1], [1, 0, 1]],
    "twill_3_1": [[1, 1, 1, 0], [0, 1, 1, 1], [1, 0, 1, 1], [1, 1, 0, 1]],
    "satin_5": [[0 if j == (2 * i) % 5 else 1 for j in range(5)] for i in range(5)],
    "rib": [[1, 0], [1, 0], [0, 1], [0, 1]],
}

#: The structures of the family: the woven patterns of :data:`WEAVE_PATTERNS` and the single jersey knit.
WEAVES = (*WEAVE_PATTERNS, "jersey")


def pattern_repeats(pattern: list[list[int]]) -> tuple[int, int]:
    """The repeat of an interlacing pattern along each system: (ends, picks) after which it comes back.

    The ends' repeat is the smallest shift ``a`` of the end index with ``pattern[i][j + a] == pattern[i][j]`` for
    every pick and end (cyclically); the picks' likewise along the pick index.

    Example:
        >>> pattern_repeats(WEAVE_PATTERNS["rib"]), pattern_repeats(WEAVE_PATTERNS["satin_5"])
        ((2, 4), (5, 5))
    """
    rows, cols = len(pattern), len(pattern[0])

    def smallest(count: int, same) -> int:
        return next(a for a in range(1, count + 1) if count % a == 0 and same(a))

    ends = smallest(cols, lambda a: all(pattern[i][(j + a) % cols] == pattern[i][j]
                                        for i in range(rows) for j in range(cols)))
    picks = smallest(rows, lambda a: all(pattern[(i + a) % rows][j] == pattern[i][j]
                                         for i in range(rows) for j in range(cols)))
    return ends, picks


@dataclass(frozen=True)
class WeaveParams:
    """One member of the family (lengths in mm).

    Attributes:
        weave: one of :data:`WEAVES`.
        warp_per_cm, weft_per_cm: densities of the two systems (for the knit: wales and courses per cm).
        orientation_deg: rotation of the cloth; the weft (courses) run along it, the warp (wales) 90° from it.
        warp_width_ratio, weft_width_ratio: yarn width over its spacing.
        thickness_ratio: yarn height over the narrower yarn's width.
        flatness: exponent of the cross-section (0.5: an ellipse).
        crimp_ratio: crimp amplitude (peak to peak of a yarn's centre line) over the yarn's height.
        randomness: yarn jitter and meander (see :mod:`data_synth.fabrics`).
    """

    weave: str
    warp_per_cm: float
    weft_per_cm: float
    orientation_deg: float
    warp_width_ratio: float = 0.9
    weft_width_ratio: float = 0.9
    thickness_ratio: float = 0.5
    flatness: float = 0.5
    crimp_ratio: float = 0.6
    randomness: float = 0.25

    def __post_init__(self) -> None:
        if self.weave not in WEAVES:
            raise InputError(f"unknown weave {self.weave!r}; expected one of {', '.join(WEAVES)}")
        for name in ("warp_per_cm", "weft_per_cm", "warp_width_ratio", "weft_width_ratio", "thickness_ratio",
                     "flatness", "crimp_ratio"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < math.inf):
                raise InputError(f"WeaveParams.{name} must be a positive number, got {value!r}")
        if not (self.warp_width_ratio <= 1 and self.weft_width_ratio <= 1):
            raise InputError("yarn width ratios must be at most 1 (a yarn no wider than its spacing), got "
                             f"{self.warp_width_ratio!r} and {self.weft_width_ratio!r}")
        if not 0 <= self.randomness <= 1:
            raise InputError(f"WeaveParams.randomness must lie in [0, 1], got {self.randomness!r}")

    def to_dict(self) -> dict[str, Any]:
        """The parameters as a JSON-ready dict."""
        return asdict(self)


@dataclass(frozen=True)
class WeaveTruth:
    """The structure a descriptor must find in a member of the family.

    Attributes:
        threads_per_cm: the two systems' densities, counted across their yarns, the denser first.
        thread_angles_deg: the directions in which those yarns run, degrees in [0, 180), the same order.
        repeat_threads: threads per repeat of the interlacing along each system, the same order (1 and 1 for a
            knit's stitch lattice).
        knit: whether the structure is a knit (wales and courses instead of ends and picks).
    """

    threads_per_cm: tuple[float, float]
    thread_angles_deg: tuple[float, float]
    repeat_threads: tuple[int, int]
    knit: bool

    def to_dict(self) -> dict[str, Any]:
        """The truth as a JSON-ready dict."""
        return asdict(self)


def weave_truth(params: WeaveParams) -> WeaveTruth:
    """The ground-truth structure of ``params`` (see :class:`WeaveTruth`).

    Example:
        >>> weave_truth(WeaveParams("rib", 30.0, 20.0, 10.0)).repeat_threads
        (2, 4)
    """
    repeats = (1, 1) if params.weave == "jersey" else pattern_repeats(WEAVE_PATTERNS[params.weave])
    # the warp (wales) runs along v, 90° from the orientation, and is counted across u; the weft (courses) along u
    systems = [(params.warp_per_cm, (params.orientation_deg + 90.0) % 180.0, repeats[0]),
               (params.weft_per_cm, params.orientation_deg % 180.0, repeats[1])]
    systems.sort(key=lambda s: -s[0])
    return WeaveTruth((systems[0][0], systems[1][0]), (systems[0][1], systems[1][1]),
                      (systems[0][2], systems[1][2]), params.weave == "jersey")


def make_weave(params: WeaveParams, size: int = 400, pixel_pitch_mm: float = 0.025, seed: int = 0,
               albedo: float = 0.6) -> Fabric:
    """Render the height, albedo and mask of one member of the family.

    Args:
        params: the member (:class:`WeaveParams`).
        size: side of the square field, pixels (>= 8).
        pixel_pitch_mm: pixel size on the cloth, mm.
        seed: the yarns' jitter, meander and tone.
        albedo: the yarns' mean albedo.

    Returns:
        a :class:`~data_synth.fabrics.Fabric` named after the weave; its ``params`` hold ``params.to_dict()``,
        the seed and the truth (``params["truth"]``, :meth:`WeaveTruth.to_dict`).

    Raises:
        InputError: a bad size or pitch.

    Example:
        >>> fabric = make_weave(WeaveParams("twill_2_1", 25.0, 18.0, 30.0), size=64)
        >>> fabric.height_mm.shape, fabric.params["truth"]["repeat_threads"]
        (torch.Size([1, 1, 64, 64]), (3, 3))
    """
    if not isinstance(size, int) or size < 8:
        raise InputError(f"size must be an integer >= 8 pixels, got {size!r}")
    if not (isinstance(pixel_pitch_mm, (int, float)) and 0 < pixel_pitch_mm < math.inf):
        raise InputError(f"pixel_pitch_mm must be a positive number, got {pixel_pitch_mm!r}")
    warp_spacing, weft_spacing = 10.0 / params.warp_per_cm, 10.0 / params.weft_per_cm
    warp_width, weft_width = params.warp_width_ratio * warp_spacing, params.weft_width_ratio * weft_spacing
    thickness = params.thickness_ratio * min(warp_width, weft_width)
    crimp = params.crimp_ratio * thickness
    record = {**params.to_dict(), "seed": int(seed), "truth": weave_truth(params).to_dict()}
    if params.weave == "jersey":
        # a stitch's two legs share a wale: each leg about half the wale's width, its height in proportion
        leg = 0.5 * warp_width
        fabric = knit(size, float(pixel_pitch_mm), int(seed), wale_spacing_mm=warp_spacing,
                      course_spacing_mm=weft_spacing, width_mm=leg, thickness_mm=params.thickness_ratio * leg,
                      crimp_mm=params.crimp_ratio * params.thickness_ratio * leg,
                      orientation_deg=params.orientation_deg, randomness=params.randomness, albedo=albedo)
        fabric.name, fabric.params = "jersey", record
        return fabric
    canvas = _Canvas(size, float(pixel_pitch_mm), int(seed), params.orientation_deg)
    height, albedo_map, covered, _, _, _ = _woven(
        canvas, WEAVE_PATTERNS[params.weave], warp_spacing, weft_spacing, warp_width, weft_width, thickness,
        crimp, albedo, params.randomness, flatness=params.flatness)
    return _finish(params.weave, canvas, height, albedo_map, covered, None, record)


@dataclass(frozen=True)
class FamilyOptions:
    """Ranges of :func:`draw_weave_params`.

    Attributes:
        weaves: the structures drawn from (uniformly).
        density_per_cm: range of each system's density (drawn independently, uniform).
        width_ratio: range of a yarn's width over its spacing.
        thickness_ratio: range of a yarn's height over the narrower width.
        flatness: range of the cross-section's exponent.
        crimp_ratio: range of the crimp over the yarn's height (log-uniform).
        randomness: range of the yarn jitter and meander.
    """

    weaves: tuple[str, ...] = WEAVES
    density_per_cm: tuple[float, float] = (10.0, 40.0)
    width_ratio: tuple[float, float] = (0.7, 1.0)
    thickness_ratio: tuple[float, float] = (0.35, 0.6)
    flatness: tuple[float, float] = (0.3, 0.8)
    crimp_ratio: tuple[float, float] = (0.15, 2.0)
    randomness: tuple[float, float] = (0.1, 0.4)

    def __post_init__(self) -> None:
        unknown = sorted(set(self.weaves) - set(WEAVES))
        if not self.weaves or unknown:
            raise InputError(f"FamilyOptions.weaves must be a non-empty subset of {WEAVES}, got {self.weaves!r}")
        for name in ("density_per_cm", "width_ratio", "thickness_ratio", "flatness", "crimp_ratio", "randomness"):
            low, high = getattr(self, name)
            if not 0 <= low <= high or (name != "randomness" and low <= 0):
                raise InputError(f"FamilyOptions.{name} must be (low, high) with 0 < low <= high, got {(low, high)}")
        if self.width_ratio[1] > 1:
            raise InputError(f"FamilyOptions.width_ratio must not exceed 1, got {self.width_ratio!r}")


def _uniform(gen: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))


def draw_weave_params(seed: int, options: FamilyOptions = FamilyOptions(), weave: str | None = None) -> WeaveParams:
    """Draw one member of the family from ``seed`` (the same seed, options and weave give the same member).

    Args:
        seed: the draw's seed.
        options: the ranges (:class:`FamilyOptions`).
        weave: fix the structure (one of :data:`WEAVES`) instead of drawing it.

    Returns:
        the :class:`WeaveParams`.

    Raises:
        InputError: an unknown weave.

    Example:
        >>> params = draw_weave_params(7)
        >>> 10 <= params.warp_per_cm <= 40 and 0 <= params.orientation_deg < 180
        True
    """
    if weave is not None and weave not in WEAVES:
        raise InputError(f"unknown weave {weave!r}; expected one of {', '.join(WEAVES)}")
    gen = torch.Generator().manual_seed(7_919 * int(seed) + 17)
    drawn = options.weaves[int(torch.randint(len(options.weaves), (), generator=gen))]
    low, high = options.crimp_ratio
    return WeaveParams(
        weave=weave if weave is not None else drawn,
        warp_per_cm=_uniform(gen, *options.density_per_cm),
        weft_per_cm=_uniform(gen, *options.density_per_cm),
        orientation_deg=_uniform(gen, 0.0, 180.0),
        warp_width_ratio=_uniform(gen, *options.width_ratio),
        weft_width_ratio=_uniform(gen, *options.width_ratio),
        thickness_ratio=_uniform(gen, *options.thickness_ratio),
        flatness=_uniform(gen, *options.flatness),
        crimp_ratio=math.exp(_uniform(gen, math.log(low), math.log(high))),
        randomness=_uniform(gen, *options.randomness),
    )


def draw_weave(seed: int, size: int = 400, pixel_pitch_mm: float = 0.025, options: FamilyOptions = FamilyOptions(),
               weave: str | None = None) -> tuple[Fabric, WeaveTruth]:
    """Draw and render one member of the family: ``(fabric, truth)``.

    Example:
        >>> fabric, truth = draw_weave(3, size=48)
        >>> fabric.height_mm.shape, len(truth.threads_per_cm)
        (torch.Size([1, 1, 48, 48]), 2)
    """
    params = draw_weave_params(seed, options, weave)
    return make_weave(params, size, pixel_pitch_mm, seed=int(seed)), weave_truth(params)
