r"""A stress family for normal estimators: concave, self-occluding surfaces under many distant lights.

DiLiGenT's ball and cat are convex or nearly so: a pixel is either lit or in attached shadow, and estimators tuned
on them can lean on "dark means :math:`l \cdot n < 0`". The surfaces here break that: each is a height field whose
parts hide the light from other parts and light each other, rendered with cast shadows by ray marching
(:func:`psmini.render.cast_shadows`) and one bounce of inter-reflection:

- ``"grooves"``: parallel V-grooves whose depth grows across the image (walls from ~40° to ~70°),
- ``"bowl"``: a spherical bowl sunk into a plane, its ~75–80° rim shadowing the inside,
- ``"folds"``: asymmetric folds (a ~50° back and a ~80° front, meandering crests) that shadow the next fold,
- ``"relief"``: packed bumps whose flanks shadow their neighbours,
- ``"crevices"``: a plane cut by narrow slots and pits 2–4 times deeper than wide, with near-vertical walls: at
  their bottoms and on their walls most of the lights are cast-shadowed, and the facing walls light each other. A
  large share of its pixels have a *majority* of readings off the Lambertian law (the failure of M-estimators,
  whose breakdown point is one half).

**Every case is drawn from its seed**: the geometry's parameters (period, depth, orientation, sizes and positions),
the albedo range of the cells, the three Blinn–Phong lobes (exponents log-uniform in [5, 500], weights in
[0.2, 1]), the strength of the inter-reflection, the ambient light, and the sensor noise; the same ``seed`` gives the
same case, and a benchmark scores several seeds per scene so that no estimator is tuned to one surface.

Light transport, per light :math:`k` of unit irradiance and direction :math:`l_k`, at a pixel :math:`x` of albedo
:math:`\rho`:

.. math::
    I_k(x) = \rho(x) \big[v_k(x) \max(n \cdot l_k, 0) + \kappa E^{\rm ind}_k(x) + a\big] + v_k(x)\,
    s(x) [n \cdot l_k > 0] \max(n \cdot h_k, 0)^{\alpha(x)}

with :math:`v_k` the cast-shadow visibility, :math:`a` an ambient term (light from the room beyond the surface) and
:math:`E^{\rm ind}_k = B(E_k) + \kappa B(B(E_k))` two diffuse bounces of the direct irradiance
:math:`E_k = v_k \max(n \cdot l_k, 0)`, where :math:`B(E)(x) = \frac{1}{S}\sum_s \rho(y_s) E(y_s)` gathers the
irradiance that the surface points :math:`y_s` hit by :math:`S` cosine-distributed rays from :math:`x` reflect to it
(the Monte-Carlo estimate of one diffuse bounce, whose form factors the rays sample; rays that leave the field see
a dark room). :math:`\kappa` scales each bounce around its physical value 1. Sensor: the images are scaled so
that the 99.5th percentile of the diffuse readings sits at 0.8 of full scale, then shot noise (``full_well``
electrons at full scale), read noise, clipping at full scale and 16-bit quantisation.

The lights are the caller's (``benchmarks/robust_stress.py`` uses DiLiGenT's 96 directions, read by
:func:`diligent_directions`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from psmini.errors import DataFormatError, InputError
from psmini.geometry import depth_to_points
from psmini.lights import DirectionalLights
from psmini.render import cast_shadows, normals_from_height, render

__all__ = ["STRESS_SCENES", "StressCase", "diligent_directions", "make_stress_case"]

_CELL = 16  # side of the albedo and material cells, pixels
_BOUNCE_RAYS = 32  # rays per pixel of the one-bounce gather
_BOUNCE_REACH = 48  # pixels of travel after which a bounce ray counts as leaving


@dataclass
class StressCase:
    """One rendered stress case with its ground truth.

    Attributes:
        name: the scene (a key of :data:`STRESS_SCENES`).
        images: readings in [0, 1], shape :math:`(1, K, H, W)`.
        lights: unit light directions, :math:`(K, 3)` (unit irradiance).
        mask: scored pixels, bool :math:`(1, 1, H, W)`.
        normals: true unit normals, :math:`(1, 3, H, W)`.
        albedo: true diffuse albedo (times the sensor gain), :math:`(1, 1, H, W)`.
        visible: cast-shadow visibility (1 lit, 0 shadowed), :math:`(1, K, H, W)`.
        specular: the Blinn–Phong lobe's weight (times the sensor gain; 0 on matte cells), :math:`(1, 1, H, W)`.
        shininess: its exponent (1 on matte cells), :math:`(1, 1, H, W)`.
        parameters: what the seed drew (geometry, lobes, inter-reflection, ambient, noise), JSON-ready.
    """

    name: str
    images: Tensor
    lights: Tensor
    mask: Tensor
    normals: Tensor
    albedo: Tensor
    visible: Tensor
    specular: Tensor
    shininess: Tensor
    parameters: dict = field(default_factory=dict)

    def cast_fraction(self) -> float:
        """Share of the mask's readings facing the light (n·l > 0) that a cast shadow darkens."""
        facing = (torch.einsum("kc,bchw->bkhw", self.lights, self.normals) > 0) & self.mask
        return float(((self.visible == 0) & facing).sum() / facing.sum().clamp_min(1))

    def majority_fraction(self) -> float:
        """Share of the mask's pixels where most of the readings are cast-shadowed or in attached shadow while a
        cast shadow darkens at least one of them: the pixels whose lit readings are a minority."""
        facing = torch.einsum("kc,bchw->bkhw", self.lights, self.normals) > 0
        lit = (facing & (self.visible > 0)).sum(dim=1, keepdim=True)
        cast = ((self.visible == 0) & facing).any(dim=1, keepdim=True)
        majority = (2 * lit < self.lights.shape[0]) & cast & self.mask
        return float(majority.sum() / self.mask.sum().clamp_min(1))


def _uniform(gen: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))


def _grid(size: int, pitch: float, angle: float = 0.0) -> tuple[Tensor, Tensor]:
    """x (right) and y (up) of each pixel centre, mm, origin at the image centre, each (size, size), rotated by
    ``angle`` (radians) so that a scene's features take any orientation."""
    coords = (torch.arange(size, dtype=torch.float64) - (size - 1) / 2) * pitch
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    cos, sin = math.cos(angle), math.sin(angle)
    return cos * x + sin * y, -sin * x + cos * y


def _smooth(height: Tensor, sigma_px: float) -> Tensor:
    """Gaussian blur of a (size, size) field (reflect padding): rounds creases the ray marcher samples bilinearly."""
    radius = max(1, int(math.ceil(3 * sigma_px)))
    taps = torch.arange(-radius, radius + 1, dtype=height.dtype)
    kernel = torch.exp(-0.5 * (taps / sigma_px) ** 2)
    kernel = kernel / kernel.sum()
    field = F.pad(height[None, None], (radius, radius, radius, radius), mode="reflect")
    field = F.conv2d(field, kernel.view(1, 1, 1, -1))
    return F.conv2d(field, kernel.view(1, 1, -1, 1))[0, 0]


def _grooves(size: int, pitch: float, gen: torch.Generator, params: dict) -> tuple[Tensor, Tensor]:
    angle = params.setdefault("angle_deg", _uniform(gen, 0.0, 180.0))
    x, y = _grid(size, pitch, math.radians(angle))
    period = params.setdefault("period_px", _uniform(gen, 24.0, 40.0)) * pitch
    shallow = math.tan(math.radians(params.setdefault("shallow_wall_deg", _uniform(gen, 35.0, 45.0))))
    steep = math.tan(math.radians(params.setdefault("steep_wall_deg", _uniform(gen, 65.0, 75.0))))
    # the walls' slope grows from shallow to steep across the image (depth = slope * half period)
    span = (y - y.min()) / (y.max() - y.min())
    depth = (shallow + (steep - shallow) * span) * period / 2
    phase = torch.remainder(x / period, 1.0)
    height = -depth * (1 - (2 * phase - 1).abs())
    return _smooth(height, 1.0), torch.ones_like(height, dtype=torch.bool)


def _bowl(size: int, pitch: float, gen: torch.Generator, params: dict) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    offset = params.setdefault("offset_px", [_uniform(gen, -0.05, 0.05) * size for _ in range(2)])
    x, y = x - offset[0] * pitch, y - offset[1] * pitch
    r = (x.square() + y.square()).sqrt()
    rim = params.setdefault("rim_fraction", _uniform(gen, 0.30, 0.42)) * size * pitch
    steepness = math.radians(params.setdefault("rim_deg", _uniform(gen, 72.0, 82.0)))
    radius = rim / math.sin(steepness)  # the sphere's wall reaches `steepness` at the rim
    # the sphere's cap below the rim: 0 at the rim, -(radius - sqrt(radius² - rim²)) at the centre
    height = torch.where(r < rim, math.sqrt(radius**2 - rim**2) - (radius**2 - r.square()).clamp_min(0).sqrt(),
                         torch.zeros_like(r))
    return _smooth(height, 1.0), r < rim + 4 * pitch


def _folds(size: int, pitch: float, gen: torch.Generator, params: dict) -> tuple[Tensor, Tensor]:
    angle = params.setdefault("angle_deg", _uniform(gen, 0.0, 180.0))
    x, y = _grid(size, pitch, math.radians(angle))
    period = params.setdefault("period_px", _uniform(gen, 32.0, 48.0)) * pitch
    meander = params.setdefault("meander", _uniform(gen, 0.05, 0.2)) * period
    meander = meander * torch.sin(2 * math.pi * y / (1.3 * period))
    phase = torch.remainder((x + meander) / period, 1.0)
    back = params.setdefault("back_share", _uniform(gen, 0.78, 0.9))  # the gentle back's share of the period
    back_slope = math.tan(math.radians(params.setdefault("back_deg", _uniform(gen, 42.0, 52.0))))
    rise = back_slope * back * period  # crest height; the front falls it in the rest of the period (~75–85°)
    height = torch.where(phase < back, rise * phase / back, rise * (1 - phase) / (1 - back))
    return _smooth(height, 1.0), torch.ones_like(height, dtype=torch.bool)


def _relief(size: int, pitch: float, gen: torch.Generator, params: dict) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    spacing = params.setdefault("spacing_px", _uniform(gen, 10.0, 14.0))
    count = int((size / spacing) ** 2)
    centres = (torch.rand(count, 2, generator=gen, dtype=torch.float64) - 0.5) * size * pitch
    sigma = (2.5 + 2.5 * torch.rand(count, generator=gen, dtype=torch.float64)) * pitch
    tall = params.setdefault("peak_per_sigma", _uniform(gen, 1.8, 2.6))
    peak = (1.0 + 1.0 * torch.rand(count, generator=gen, dtype=torch.float64)) * tall * sigma
    height = torch.zeros_like(x)
    for c in range(count):  # a loop over bumps (~100), not pixels
        d2 = (x - centres[c, 0]).square() + (y - centres[c, 1]).square()
        height = torch.maximum(height, peak[c] * torch.exp(-0.5 * d2 / sigma[c] ** 2))
    return height, torch.ones_like(height, dtype=torch.bool)


def _crevices(size: int, pitch: float, gen: torch.Generator, params: dict) -> tuple[Tensor, Tensor]:
    x, y = _grid(size, pitch)
    height = torch.zeros_like(x)
    spacing = params.setdefault("slot_spacing_px", _uniform(gen, 12.0, 18.0))
    ratio = params.setdefault("depth_per_width", _uniform(gen, 2.0, 4.0))
    slots = max(2, round(size / spacing))
    for _ in range(slots):  # a loop over slots (a handful), not pixels
        angle = _uniform(gen, 0.0, math.pi)
        offset = _uniform(gen, -0.5, 0.5) * size * pitch
        width = _uniform(gen, 4.0, 8.0) * pitch
        across = (math.cos(angle) * x + math.sin(angle) * y - offset).abs() / (width / 2)
        # a flat-bottomed slot with near-vertical walls, 2–4 times deeper than wide
        height = torch.minimum(height, -ratio * width * (1 - across**4).clamp_min(0))
    pits = max(2, round((size / spacing) ** 2 / 3))
    for _ in range(pits):
        centre = [_uniform(gen, -0.5, 0.5) * size * pitch for _ in range(2)]
        radius = _uniform(gen, 3.0, 6.0) * pitch
        d = ((x - centre[0]).square() + (y - centre[1]).square()).sqrt() / radius
        height = torch.minimum(height, -ratio * 2 * radius * (1 - d**4).clamp_min(0))
    return _smooth(height, 0.7), torch.ones_like(height, dtype=torch.bool)


#: The scenes: name -> height field generator (size, pitch, generator, parameters) -> (height mm, mask); the
#: generator draws the geometry's parameters and records them in ``parameters``.
STRESS_SCENES = {"grooves": _grooves, "bowl": _bowl, "folds": _folds, "relief": _relief, "crevices": _crevices}


def _cells(size: int, gen: torch.Generator, values: Tensor) -> Tensor:
    """A (size, size) map of cells of :data:`_CELL` pixels, each taking one of ``values`` (drawn by ``gen``)."""
    cells = -(-size // _CELL)
    pick = torch.randint(len(values), (cells, cells), generator=gen)
    return values[pick].repeat_interleave(_CELL, 0).repeat_interleave(_CELL, 1)[:size, :size]


def _bounce_hits(height: Tensor, normals: Tensor, pitch: float, gen: torch.Generator,
                 reach: int = _BOUNCE_REACH) -> tuple[Tensor, Tensor]:
    """Where :data:`_BOUNCE_RAYS` cosine-distributed rays from each pixel first meet the height field.

    ``height`` (H, W) mm, ``normals`` (3, H, W). Each ray leaves the surface point (lifted by a quarter pixel along the
    normal against self-intersection) and is marched in steps of half a pixel; it hits where it passes below the
    bilinearly sampled field, and leaves once it climbs over the field's top, leaves the image or has travelled
    ``reach`` pixels (:data:`_BOUNCE_REACH`). Returns the flat index of the hit pixel and whether there is one, each
    (S, H·W).
    """
    rows, cols = height.shape
    count = rows * cols
    n = normals.reshape(3, 1, count)
    # cosine-weighted directions about each normal: a random frame per pixel and ray
    u1 = torch.rand(_BOUNCE_RAYS, count, generator=gen, dtype=height.dtype)
    u2 = torch.rand(_BOUNCE_RAYS, count, generator=gen, dtype=height.dtype)
    radius, phi = u1.sqrt(), 2 * math.pi * u2
    helper = torch.where(n[2].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0], dtype=height.dtype).view(3, 1, 1),
                         torch.tensor([1.0, 0.0, 0.0], dtype=height.dtype).view(3, 1, 1))
    first = torch.linalg.cross(n.expand(3, 1, count), helper.expand(3, 1, count), dim=0)
    first = first / first.norm(dim=0, keepdim=True)
    second = torch.linalg.cross(n.expand(3, 1, count), first, dim=0)
    direction = (radius * phi.cos()) * first + (radius * phi.sin()) * second + (1 - u1).clamp_min(0).sqrt() * n
    # positions in pixel units (column, row, height / pitch); rows grow downward where y grows upward
    col = torch.arange(cols, dtype=height.dtype).repeat(rows)
    row = torch.arange(rows, dtype=height.dtype).repeat_interleave(cols)
    field = height / pitch
    flip = torch.tensor([1.0, -1.0, 1.0], dtype=height.dtype).view(3, 1, 1)  # y up is row down
    start = torch.stack([col, row, field.flatten()]).view(3, 1, count) + 0.25 * n * flip
    step = 0.5 * direction * flip
    top = float(field.max())
    hit = torch.zeros(_BOUNCE_RAYS, count, dtype=torch.bool)
    gone = torch.zeros_like(hit)
    index = torch.zeros(_BOUNCE_RAYS, count, dtype=torch.long)
    source = field[None, None]
    for t in range(1, 2 * reach + 1):  # a loop over ray steps; every pixel and ray moves at once
        point = start + t * step
        inside = (point[0] >= 0) & (point[0] <= cols - 1) & (point[1] >= 0) & (point[1] <= rows - 1)
        gone = gone | ~inside | (point[2] > top)
        grid = torch.stack([point[0] / max(cols - 1, 1) * 2 - 1, point[1] / max(rows - 1, 1) * 2 - 1], dim=-1)
        surface = F.grid_sample(source, grid.view(1, _BOUNCE_RAYS, count, 2), mode="bilinear",
                                padding_mode="border", align_corners=True)[0, 0]
        new = (point[2] < surface) & ~gone & ~hit
        nearest = point[1].round().clamp(0, rows - 1).long() * cols + point[0].round().clamp(0, cols - 1).long()
        index = torch.where(new, nearest, index)
        hit = hit | new
        if bool((hit | gone).all()):
            break
    return index, hit


def _one_bounce(direct: Tensor, albedo: Tensor, index: Tensor, hit: Tensor) -> Tensor:
    """Irradiance (K, H, W) that the hit points reflect to each pixel: the mean over rays of albedo × direct
    irradiance at the hit (``direct`` (K, H, W), ``albedo`` (H, W)); a miss contributes 0 (a dark room)."""
    count, rays = direct.shape[1] * direct.shape[2], index.shape[0]
    radiance = (direct * albedo).reshape(-1, count)
    total = torch.zeros_like(radiance)
    for s in range(rays):  # a loop over the rays (32), not pixels
        total += radiance[:, index[s]] * hit[s]
    return (total / rays).view_as(direct)


def make_stress_case(
    name: str,
    directions: Tensor,
    size: int = 128,
    seed: int = 0,
    *,
    pixel_pitch_mm: float = 0.05,
    interreflection: float | None = None,
    ambient: float | None = None,
    full_well: float | None = None,
    read_noise: float | None = None,
) -> StressCase:
    r"""Render one stress case (see the module docstring); the seed draws everything the keywords leave ``None``.

    Args:
        name: a key of :data:`STRESS_SCENES`.
        directions: light directions, :math:`(K, 3)`, camera frame (normalised here), K >= 3.
        size: side of the square image, pixels (>= 32).
        seed: seed of the geometry, the cells, the lobes, the light transport's strengths and the noise.
        pixel_pitch_mm: pixel size on the surface, mm.
        interreflection: :math:`\kappa`, the one-bounce irradiance's factor, in [0, 2] (default drawn in
            [0.5, 1.2]; 1 is the physical bounce of the cells' albedos).
        ambient: :math:`a`, light from the room as a fraction of each light's irradiance, in [0, 1) (default
            drawn in [0, 0.03]).
        full_well: electrons at full scale (shot noise); ``0`` turns all noise and quantisation off (default
            drawn log-uniform in [5,000, 50,000]).
        read_noise: read noise standard deviation, fraction of full scale (default drawn in [1e-4, 1e-3]).

    Returns:
        a :class:`StressCase` in float32.

    Raises:
        InputError: for an unknown scene or options out of range.

    Example:
        >>> from psmini.lights import ring_lights
        >>> case = make_stress_case("crevices", ring_lights(8, 30.0), size=32)
        >>> case.images.shape, bool(case.mask.any()), case.majority_fraction() > 0
        (torch.Size([1, 8, 32, 32]), True, True)
    """
    if name not in STRESS_SCENES:
        raise InputError(f"scene must be one of {sorted(STRESS_SCENES)}, got {name!r}")
    if not (isinstance(directions, Tensor) and directions.ndim == 2 and directions.shape[1] == 3
            and directions.shape[0] >= 3):
        got = getattr(directions, "shape", directions)
        raise InputError(f"directions must be a (K, 3) tensor with K >= 3, got {got}")
    if size < 32:
        raise InputError(f"size must be at least 32 pixels, got {size}")
    checks = {"interreflection": (interreflection, 0.0, 2.0), "ambient": (ambient, 0.0, 1.0 - 1e-9),
              "full_well": (full_well, 0.0, math.inf), "read_noise": (read_noise, 0.0, 1.0)}
    for key, (value, low, high) in checks.items():
        if value is not None and not low <= value <= high:
            raise InputError(f"{key} must lie in [{low}, {high}], got {value}")
    if not pixel_pitch_mm > 0:
        raise InputError(f"pixel_pitch_mm must be positive, got {pixel_pitch_mm}")
    # one stream per scene and seed: the scenes' draws do not repeat each other
    gen = torch.Generator().manual_seed(int(seed) * len(STRESS_SCENES) + list(STRESS_SCENES).index(name))
    params: dict = {}
    height, mask = STRESS_SCENES[name](size, pixel_pitch_mm, gen, params)
    low = _uniform(gen, 0.1, 0.3)
    albedo_values = torch.linspace(low, _uniform(gen, 0.75, 0.95), 6, dtype=torch.float64)
    lobes = [(math.exp(_uniform(gen, math.log(5.0), math.log(500.0))), _uniform(gen, 0.2, 1.0)) for _ in range(3)]
    drawn = {"interreflection": _uniform(gen, 0.5, 1.2), "ambient": _uniform(gen, 0.0, 0.03),
             "full_well": math.exp(_uniform(gen, math.log(5e3), math.log(5e4))),
             "read_noise": _uniform(gen, 1e-4, 1e-3)}
    given = {"interreflection": interreflection, "ambient": ambient, "full_well": full_well, "read_noise": read_noise}
    transport = {key: drawn[key] if (value := given[key]) is None else float(value) for key in drawn}
    params.update(albedo=[float(albedo_values[0]), float(albedo_values[-1])],
                  lobes=[[round(a, 2), round(w, 3)] for a, w in lobes], **transport)

    height = height[None, None]
    normals = normals_from_height(height, pixel_pitch_mm)
    points = depth_to_points(height, pixel_pitch_mm)
    albedo = _cells(size, gen, albedo_values)[None, None]
    material = _cells(size, gen, torch.arange(len(lobes) + 1))  # 0 matte, 1..3 the lobes
    lights = DirectionalLights(directions.to(torch.float64))
    visible = cast_shadows(height, lights.directions, pixel_pitch_mm)[:, :, 0]  # (1, K, H, W)
    facing = torch.einsum("kc,bchw->bkhw", lights.directions, normals).clamp_min(0)
    index, hit = _bounce_hits(height[0, 0], normals[0], pixel_pitch_mm, gen)
    # two diffuse bounces: the light the first bounce puts on the surface is gathered once more
    first = transport["interreflection"] * _one_bounce((visible * facing)[0], albedo[0, 0], index, hit)
    bounce = first + transport["interreflection"] * _one_bounce(first, albedo[0, 0], index, hit)
    diffuse = albedo * (visible * facing + bounce[None] + transport["ambient"])
    images = diffuse.clone()
    specular_map, shininess_map = torch.zeros_like(albedo), torch.ones_like(albedo)
    for number, (shininess, weight) in enumerate(lobes, start=1):
        cells = (material == number).to(albedo)[None, None]
        images = images + visible * render(points, normals, torch.zeros_like(albedo), lights, specular=weight * cells,
                                           shininess=shininess)
        specular_map = specular_map + weight * cells
        shininess_map = torch.where(cells > 0, shininess, shininess_map)
    gain = 0.8 / float(torch.quantile(diffuse[:, :, mask].flatten(), 0.995))
    images = images * gain
    if transport["full_well"] > 0:
        noise = torch.randn(images.shape, generator=gen, dtype=images.dtype)
        images = images + noise * (images.clamp_min(0) / transport["full_well"] + transport["read_noise"] ** 2).sqrt()
        images = torch.round(images.clamp(0, 1) * 65535) / 65535
    return StressCase(name, images.float(), lights.directions.float(), mask[None, None], normals.float(),
                      (albedo * gain).float(), visible.float(), (specular_map * gain).float(), shininess_map.float(),
                      params)


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
