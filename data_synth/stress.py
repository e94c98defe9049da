r"""A stress set for normal estimators: concave, self-occluding surfaces under many distant lights.

DiLiGenT's ball and cat are convex or nearly so: a pixel is either lit or in attached shadow, and the robust
estimators tuned on them can lean on "dark means :math:`l \cdot n < 0`". The surfaces here break that: each is a
height field whose parts hide the light from other parts, rendered by :func:`psmini.render.render` with cast
shadows by ray marching (:func:`psmini.render.cast_shadows`):

- ``"grooves"``: parallel V-grooves whose depth grows across the image (walls from ~40° to ~70°),
- ``"bowl"``: a spherical bowl sunk into a plane, its ~80° rim shadowing the inside,
- ``"folds"``: asymmetric folds (a ~50° back and a ~80° front, meandering crests) that shadow the next fold,
- ``"relief"``: packed bumps whose flanks shadow their neighbours.

Every surface carries albedo edges (piecewise-constant albedo in cells, 0.15–0.9) and Blinn–Phong lobes of three
widths (exponents 10, 50 and 300, each on its own cells, a third of the cells matte). A cast-shadowed reading is not
0 in real captures: light bounces off the surfaces around. Here it reads ``bounce`` × albedo × irradiance (a crude
inter-reflection model, 0.08 by default: above a 5%-of-the-brightest threshold). Sensor noise is that of a 16-bit
camera: the images are scaled so the 99.5th percentile of the diffuse readings sits at 0.8 of full scale, then
shot noise (``full_well`` electrons at full scale), read noise, clipping at full scale and 16-bit quantisation.

The lights are the caller's (``benchmarks/robust_stress.py`` uses DiLiGenT's 96 directions, read by
:func:`diligent_directions`). The same ``seed`` gives the same case.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from psmini.errors import DataFormatError, InputError
from psmini.geometry import depth_to_points
from psmini.lights import DirectionalLights
from psmini.render import cast_shadows, normals_from_height, render

__all__ = ["STRESS_SCENES", "StressCase", "diligent_directions", "make_stress_case"]

# Blinn–Phong exponents of the three lobes (broad, medium, narrow) and the specular weight of each
_LOBES = ((10.0, 0.3), (50.0, 0.6), (300.0, 1.0))
_CELL = 16  # side of the albedo and material cells, pixels


@dataclass
class StressCase:
    """One rendered stress case with its ground truth.

    Attributes:
        name: the scene (a key of :data:`STRESS_SCENES`).
        images: readings in [0, 1], shape :math:`(1, K, H, W)`.
        lights: unit light directions, :math:`(K, 3)` (unit irradiance).
        mask: scored pixels, bool :math:`(1, 1, H, W)`.
        normals: true unit normals, :math:`(1, 3, H, W)`.
        albedo: true diffuse albedo, :math:`(1, 1, H, W)`.
        visible: cast-shadow visibility (1 lit, 0 shadowed), :math:`(1, K, H, W)`.
    """

    name: str
    images: Tensor
    lights: Tensor
    mask: Tensor
    normals: Tensor
    albedo: Tensor
    visible: Tensor

    def cast_fraction(self) -> float:
        """Share of the mask's readings facing the light (n·l > 0) that a cast shadow darkens."""
        facing = (torch.einsum("kc,bchw->bkhw", self.lights, self.normals) > 0) & self.mask
        return float(((self.visible == 0) & facing).sum() / facing.sum().clamp_min(1))


def _grid(size: int, pitch: float) -> tuple[Tensor, Tensor]:
    """x (right) and y (up) of each pixel centre, mm, origin at the image centre, each (size, size)."""
    coords = (torch.arange(size, dtype=torch.float64) - (size - 1) / 2) * pitch
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    return x, y


def _smooth(height: Tensor, sigma_px: float) -> Tensor:
    """Gaussian blur of a (size, size) field (reflect padding): rounds creases the ray marcher samples bilinearly."""
    radius = max(1, int(math.ceil(3 * sigma_px)))
    taps = torch.arange(-radius, radius + 1, dtype=height.dtype)
    kernel = torch.exp(-0.5 * (taps / sigma_px) ** 2)
    kernel = kernel / kernel.sum()
    field = F.pad(height[None, None], (radius, radius, radius, radius), mode="reflect")
    field = F.conv2d(field, kernel.view(1, 1, 1, -1))
    return F.conv2d(field, kernel.view(1, 1, -1, 1))[0, 0]


def _grooves(size: int, pitch: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    period = 32 * pitch
    depth = 0.4 * period + 1.0 * period * (y - y.min()) / (y.max() - y.min())  # walls ~40° to ~70°
    phase = torch.remainder(x / period, 1.0)
    height = -depth * (1 - (2 * phase - 1).abs())
    return _smooth(height, 1.0), torch.ones_like(height, dtype=torch.bool)


def _bowl(size: int, pitch: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    r = (x.square() + y.square()).sqrt()
    rim = 0.4 * size * pitch
    radius = 1.02 * rim  # sphere radius: the bowl's wall reaches ~79° at the rim
    # the sphere's cap below the rim: 0 at the rim, -(radius - sqrt(radius² - rim²)) at the centre
    height = torch.where(r < rim, math.sqrt(radius**2 - rim**2) - (radius**2 - r.square()).clamp_min(0).sqrt(),
                         torch.zeros_like(r))
    return _smooth(height, 1.0), r < rim + 4 * pitch


def _folds(size: int, pitch: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    period = 40 * pitch
    meander = 0.15 * period * torch.sin(2 * math.pi * y / (1.3 * period))
    phase = torch.remainder((x + meander) / period, 1.0)
    back = 0.85  # share of the period on the gentle back (~50°); the front (~80°) falls in the rest
    rise = 0.85 * period  # crest height
    height = torch.where(phase < back, rise * phase / back, rise * (1 - phase) / (1 - back))
    return _smooth(height, 1.0), torch.ones_like(height, dtype=torch.bool)


def _relief(size: int, pitch: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    spacing = 12
    count = (size // spacing) ** 2
    centres = (torch.rand(count, 2, generator=gen, dtype=torch.float64) - 0.5) * size * pitch
    sigma = (2.5 + 2.5 * torch.rand(count, generator=gen, dtype=torch.float64)) * pitch
    peak = (1.0 + 1.0 * torch.rand(count, generator=gen, dtype=torch.float64)) * 2.2 * sigma
    height = torch.zeros_like(x)
    for c in range(count):  # a loop over bumps (~100), not pixels
        d2 = (x - centres[c, 0]).square() + (y - centres[c, 1]).square()
        height = torch.maximum(height, peak[c] * torch.exp(-0.5 * d2 / sigma[c] ** 2))
    return height, torch.ones_like(height, dtype=torch.bool)


#: The scenes: name -> height field generator (size, pitch, generator) -> (height (size, size) mm, mask).
STRESS_SCENES = {"grooves": _grooves, "bowl": _bowl, "folds": _folds, "relief": _relief}


def _cells(size: int, gen: torch.Generator, values: Tensor) -> Tensor:
    """A (size, size) map of cells of :data:`_CELL` pixels, each taking one of ``values`` (drawn by ``gen``)."""
    cells = -(-size // _CELL)
    pick = torch.randint(len(values), (cells, cells), generator=gen)
    return values[pick].repeat_interleave(_CELL, 0).repeat_interleave(_CELL, 1)[:size, :size]


def make_stress_case(
    name: str,
    directions: Tensor,
    size: int = 128,
    seed: int = 0,
    *,
    pixel_pitch_mm: float = 0.05,
    bounce: float = 0.08,
    full_well: float = 20000.0,
    read_noise: float = 3e-4,
) -> StressCase:
    """Render one stress case (see the module docstring).

    Args:
        name: a key of :data:`STRESS_SCENES`.
        directions: light directions, :math:`(K, 3)`, camera frame (normalised here), K >= 3.
        size: side of the square image, pixels (>= 32).
        seed: seed of the relief, the albedo and material cells and the noise.
        pixel_pitch_mm: pixel size on the surface, mm.
        bounce: reading of a cast-shadowed pixel, as a fraction of albedo × irradiance, in [0, 1).
        full_well: electrons at full scale (shot noise); ``0`` turns all noise and quantisation off.
        read_noise: read noise standard deviation, fraction of full scale.

    Returns:
        a :class:`StressCase` in float32.

    Raises:
        InputError: for an unknown scene or options out of range.

    Example:
        >>> from psmini.lights import ring_lights
        >>> case = make_stress_case("bowl", ring_lights(8, 50.0), size=32)
        >>> case.images.shape, bool(case.mask.any())
        (torch.Size([1, 8, 32, 32]), True)
    """
    if name not in STRESS_SCENES:
        raise InputError(f"scene must be one of {sorted(STRESS_SCENES)}, got {name!r}")
    if not (isinstance(directions, Tensor) and directions.ndim == 2 and directions.shape[1] == 3
            and directions.shape[0] >= 3):
        raise InputError("directions must be a (K, 3) tensor with K >= 3, got "
                         f"{getattr(directions, 'shape', directions)}")
    if size < 32:
        raise InputError(f"size must be at least 32 pixels, got {size}")
    if not 0 <= bounce < 1 or not full_well >= 0 or not read_noise >= 0 or not pixel_pitch_mm > 0:
        raise InputError(f"bounce must lie in [0, 1) and full_well, read_noise >= 0, pixel_pitch_mm > 0; got "
                         f"bounce={bounce}, full_well={full_well}, read_noise={read_noise}, "
                         f"pixel_pitch_mm={pixel_pitch_mm}")
    gen = torch.Generator().manual_seed(int(seed))
    height, mask = STRESS_SCENES[name](size, pixel_pitch_mm, gen)
    height = height[None, None]
    normals = normals_from_height(height, pixel_pitch_mm)
    points = depth_to_points(height, pixel_pitch_mm)
    albedo = _cells(size, gen, torch.linspace(0.15, 0.9, 6, dtype=torch.float64))[None, None]
    material = _cells(size, gen, torch.arange(len(_LOBES) + 1))  # 0 matte, 1..3 the lobes
    lights = DirectionalLights(directions.to(torch.float64))
    diffuse = render(points, normals, albedo, lights)
    images = diffuse.clone()
    for index, (shininess, weight) in enumerate(_LOBES, start=1):
        specular = (weight * (material == index).to(albedo))[None, None]
        images = images + render(points, normals, torch.zeros_like(albedo), lights, specular=specular,
                                 shininess=shininess)
    visible = cast_shadows(height, lights.directions, pixel_pitch_mm)[:, :, 0]  # (1, K, H, W)
    images = images * visible + bounce * albedo * (1 - visible)
    gain = 0.8 / float(torch.quantile(diffuse[:, :, mask].flatten(), 0.995))
    images = images * gain
    if full_well > 0:
        noise = torch.randn(images.shape, generator=gen, dtype=images.dtype)
        images = images + noise * (images.clamp_min(0) / full_well + read_noise**2).sqrt()
        images = torch.round(images.clamp(0, 1) * 65535) / 65535
    return StressCase(name, images.float(), lights.directions.float(), mask[None, None], normals.float(),
                      (albedo * gain).float(), visible.float())


def diligent_directions(folder: str | Path) -> Tensor:
    """DiLiGenT's light directions (``light_directions.txt`` of an object folder, or a folder holding ``ball``).

    Args:
        folder: an object folder, or the DiLiGenT root.

    Returns:
        unit directions, :math:`(K, 3)` float32, camera frame (x right, y up, z toward the camera).

    Raises:
        DataFormatError: when the file is absent or not K rows of 3 numbers.

    Example:
        >>> diligent_directions("nowhere")
        Traceback (most recent call last):
        ...
        psmini.errors.DataFormatError: no light_directions.txt in nowhere or nowhere/ball
    """
    folder = Path(folder)
    for candidate in (folder / "light_directions.txt", folder / "ball" / "light_directions.txt"):
        if candidate.is_file():
            rows = [line.split() for line in candidate.read_text().splitlines() if line.strip()]
            if not rows or any(len(row) != 3 for row in rows):
                raise DataFormatError(f"{candidate}: expected K rows of 3 numbers")
            directions = torch.tensor([[float(v) for v in row] for row in rows])
            return directions / directions.norm(dim=1, keepdim=True)
    raise DataFormatError(f"no light_directions.txt in {folder} or {folder / 'ball'}")
