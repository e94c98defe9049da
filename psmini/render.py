r"""Differentiable rendering of surfaces under psmini's light models.

The forward model of photometric stereo, on batched tensors: a Lambertian surface with albedo
:math:`\rho` and unit normal :math:`n`, lit by light ``k`` with unit vector :math:`l_k` and irradiance
:math:`E_k`, reads

.. math::
    I_k = E_k \, v_k \left( \rho \max(n \cdot l_k, 0) + s \, [n \cdot l_k > 0] \max(n \cdot h_k, 0)^{\alpha} \right)

where ``max(n·l, 0)`` is the attached shadow, :math:`v_k \in \{0, 1\}` the cast shadow found by ray marching
on the height field toward the light, and the optional Blinn–Phong lobe (Blinn, "Models of light reflection
for computer synthesized pictures", SIGGRAPH 1977) uses the half vector :math:`h_k = (l_k + v)/\lVert l_k + v
\rVert` with the orthographic view vector :math:`v = (0, 0, 1)` and a per-pixel specular weight :math:`s`
(metallic threads). The light physics (directions, inverse-square and LED fall-off) comes from the modules of
:mod:`psmini.lights`; this module only shades.

Camera frame: x right, y up, z toward the camera; image rows grow downward, so ``y = -row``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import check_finite, check_light_module, check_positive, check_shape, check_tensor
from psmini._tensor import vector_length
from psmini.errors import InputError, ShapeError
from psmini.lights import as_batched_lights

__all__ = [
    "normals_from_height",
    "render_lambertian",
    "cast_shadows",
    "render",
    "Renderer",
]

# Ray marching stops after this many one-pixel steps whatever the height range: at 55° zenith a 1 mm tall
# relief casts shadows ~1.4 mm (57 pixels at 0.025 mm/px) long, well inside this bound.
_MAX_MARCH_STEPS = 512


def normals_from_height(height_mm: Tensor, pixel_pitch_mm: float) -> Tensor:
    r"""Unit normals of a height field by central differences.

    With ``p = ∂z/∂x`` (x right, along columns) and ``q = ∂z/∂y`` (y up, against the row index), the normal is
    :math:`(-p, -q, 1) / \sqrt{p^2 + q^2 + 1}`. Border pixels use one-sided differences (the field is
    extended linearly), so a tilted plane has the same normal everywhere.

    Args:
        height_mm: height toward the camera, shape :math:`(B, 1, H, W)`, millimetres; H, W >= 2.
        pixel_pitch_mm: size of one pixel on the surface, mm.

    Returns:
        unit normals, shape :math:`(B, 3, H, W)`.

    Raises:
        ShapeError: when ``height_mm`` is not :math:`(B, 1, H, W)` with H, W >= 2.
        InputError: when the height holds NaN or infinite values, or the pitch is not positive.

    Example:
        >>> rows = torch.arange(4.0).view(1, 1, 4, 1).expand(1, 1, 4, 4)
        >>> n = normals_from_height(-0.5 * rows, pixel_pitch_mm=0.5)   # z grows with y (up): q = 1
        >>> [round(float(v), 4) for v in n[0, 1:, 1, 1]]
        [-0.7071, 0.7071]
    """
    sizes = check_shape(height_mm, ["B", "1", "H", "W"], "height_mm")
    if sizes["H"] < 2 or sizes["W"] < 2:
        raise ShapeError(f"height_mm needs at least 2x2 pixels for differences, got {tuple(height_mm.shape)}")
    check_finite(height_mm, "height_mm")
    pitch = check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    p, q = _height_gradients(height_mm, pitch)
    normals = torch.cat([-p, -q, torch.ones_like(p)], dim=1)
    return normals / vector_length(normals, dim=1)


def _height_gradients(height: Tensor, pitch: float) -> tuple[Tensor, Tensor]:
    """Central differences ``p = dz/dx`` and ``q = dz/dy`` (y up), one-sided at the borders."""
    # Linear extrapolation by one pixel turns the central difference at the border into a one-sided one.
    left, right = 2 * height[..., :, :1] - height[..., :, 1:2], 2 * height[..., :, -1:] - height[..., :, -2:-1]
    wide = torch.cat([left, height, right], dim=-1)
    top, bottom = 2 * height[..., :1, :] - height[..., 1:2, :], 2 * height[..., -1:, :] - height[..., -2:-1, :]
    tall = torch.cat([top, height, bottom], dim=-2)
    p = (wide[..., :, 2:] - wide[..., :, :-2]) / (2 * pitch)
    q = -(tall[..., 2:, :] - tall[..., :-2, :]) / (2 * pitch)  # y up: against the row index
    return p, q


def render_lambertian(normals: Tensor, albedo: Tensor, lights: Tensor) -> Tensor:
    r"""Lambertian images under distant lights, with attached shadows: :math:`I_k = \rho \max(L_k \cdot n, 0)`.

    The exact forward model of least-squares photometric stereo (Woodham, "Photometric method for determining
    surface orientation from multiple images", Opt. Eng. 1980).

    Args:
        normals: unit normals, shape :math:`(B, 3, H, W)`, camera frame.
        albedo: albedo, shape :math:`(B, 1, H, W)`.
        lights: light directions scaled by their intensities, shape :math:`(K, 3)` or :math:`(B, K, 3)`.

    Returns:
        images, shape :math:`(B, K, H, W)`.

    Raises:
        ShapeError: when the shapes do not match.
        InputError: when an input is not a floating-point tensor.

    Example:
        >>> from psmini.lights import ring_lights
        >>> normals = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 4, 4)
        >>> images = render_lambertian(normals, torch.ones(1, 1, 4, 4), ring_lights(8, 60.0))
        >>> round(float(images[0, 0, 0, 0]), 4)
        0.5
    """
    sizes = check_shape(normals, ["B", "3", "H", "W"], "normals")
    _check_map(albedo, sizes, "albedo")
    batched = as_batched_lights(lights, sizes["B"], normals)
    shading = torch.einsum("bkc,bchw->bkhw", batched, normals)
    return albedo * shading.clamp_min(0)


def cast_shadows(height_mm: Tensor, light_vectors: Tensor, pixel_pitch_mm: float, bias_mm: float = 1e-4) -> Tensor:
    r"""Visibility of each light from each pixel of a height field, by ray marching (1 = lit, 0 = cast shadow).

    From every pixel's surface point a ray leaves toward the light along its (per-pixel) unit vector; it is
    sampled every pixel of horizontal travel, bilinearly, for all pixels and lights at once. The pixel is in
    shadow when the height field rises above the ray (by more than ``bias_mm``) anywhere before the ray climbs
    over the highest point of the field or leaves the image. Outside the image nothing occludes. The number of
    steps comes from the height range and the lowest light (one device sync per call). Visibility is a step
    function: it carries no gradient.

    Args:
        height_mm: height field, shape :math:`(B, 1, H, W)`, mm (toward the camera).
        light_vectors: unit vectors toward the lights, shape :math:`(B, K, 3, H, W)` (as returned by the light
            models) or :math:`(B, K, 3)` / :math:`(K, 3)` for distant lights.
        pixel_pitch_mm: pixel size on the surface, mm.
        bias_mm: tolerance against self-shadowing from interpolation, mm.

    Returns:
        visibility, shape :math:`(B, K, 1, H, W)`, in the dtype of ``height_mm`` (values 0 or 1).

    Raises:
        ShapeError: when the shapes do not match.
        InputError: when the height is not finite or the pitch not positive.

    Example:
        >>> height = torch.zeros(1, 1, 8, 8)
        >>> height[..., :, 4] = 1.0                                  # a wall one column wide
        >>> light = torch.tensor([[-0.7071, 0.0, 0.7071]])            # from the left, 45° up
        >>> vis = cast_shadows(height, light, pixel_pitch_mm=0.25)
        >>> vis[0, 0, 0, 0].tolist()
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]
    """
    sizes = check_shape(height_mm, ["B", "1", "H", "W"], "height_mm")
    check_finite(height_mm, "height_mm")
    pitch = check_positive(pixel_pitch_mm, "pixel_pitch_mm")
    batch, height, width = sizes["B"], sizes["H"], sizes["W"]
    vectors = _per_pixel_vectors(light_vectors, batch, height, width, height_mm)
    z = height_mm.detach()
    vectors = vectors.detach()
    count = vectors.shape[1]
    horizontal = vector_length(vectors[:, :, :2], dim=2, keepdim=False)  # (B, K, H, W)
    safe = horizontal.clamp_min(1e-12)
    # Height gained per pixel of horizontal travel; a light straight overhead (horizontal 0) casts no shadow.
    rise = vectors[:, :, 2] / safe * pitch
    # Work relative to the lowest point plus one: grid_sample's zero padding then reads "below every ray"
    # outside the image, so nothing there occludes.
    field = z - z.amin(dim=(-2, -1), keepdim=True) + 1  # (B, 1, H, W)
    start = field.expand(batch, count, height, width) + bias_mm
    steps = _march_steps(field, start, rise)
    # One pixel of travel moves 2/(W-1) in grid_sample's normalised x (columns follow x) and -2/(H-1)·l_y in y.
    delta = torch.stack(
        [vectors[:, :, 0] / safe * (2 / max(width - 1, 1)), -vectors[:, :, 1] / safe * (2 / max(height - 1, 1))],
        dim=-1,
    ).reshape(batch * count, height, width, 2)
    ys = torch.linspace(-1, 1, height, device=z.device, dtype=z.dtype)
    xs = torch.linspace(-1, 1, width, device=z.device, dtype=z.dtype)
    base = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).expand(batch * count, height, width, 2)
    source = field.repeat_interleave(count, dim=0)  # (B*K, 1, H, W)
    excess = torch.full((batch, count, height, width), -math.inf, device=z.device, dtype=z.dtype)
    for step in range(1, steps + 1):  # a loop over ray steps; every pixel and light moves at once
        grid = torch.add(base, delta, alpha=step)
        sampled = F.grid_sample(source, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        excess = torch.maximum(excess, sampled.view(batch, count, height, width) - torch.add(start, rise, alpha=step))
    return (excess <= 0).to(height_mm.dtype).unsqueeze(2)


def _march_steps(field: Tensor, start: Tensor, rise: Tensor) -> int:
    """Steps after which every ray has climbed above the highest point of its field (one device sync)."""
    top = field.amax(dim=(-2, -1), keepdim=True)
    climbing = rise > 0
    needed = torch.where(climbing, (top - start) / rise.clamp_min(1e-12), torch.zeros_like(rise))
    return min(_MAX_MARCH_STEPS, int(math.ceil(float(needed.max().clamp_min(0)))))


def _per_pixel_vectors(vectors: Tensor, batch: int, height: int, width: int, like: Tensor) -> Tensor:
    """Light vectors as (B, K, 3, H, W); distant (K, 3) or (B, K, 3) vectors are broadcast over pixels."""
    check_tensor(vectors, "light_vectors")
    if vectors.ndim in (2, 3):
        batched = as_batched_lights(vectors, batch, like, "light_vectors")
        batched = batched / batched.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(like.dtype).tiny)
        return batched[..., None, None].expand(-1, -1, -1, height, width)
    sizes = check_shape(vectors, ["B", "K", "3", "H", "W"], "light_vectors")
    if sizes["B"] not in (1, batch) or (sizes["H"], sizes["W"]) != (height, width):
        raise ShapeError(
            f"light_vectors must have shape ({batch}, K, 3, {height}, {width}), got {tuple(vectors.shape)}"
        )
    return vectors.to(like).expand(batch, -1, -1, -1, -1)


def render(
    points: Tensor,
    normals: Tensor,
    albedo: Tensor,
    light_model: nn.Module,
    *,
    specular: Tensor | None = None,
    shininess: float = 40.0,
    shadows: bool = False,
    pixel_pitch_mm: float | None = None,
) -> Tensor:
    r"""Images of a surface under any light model of :mod:`psmini.lights`, with optional cast shadows and gloss.

    Args:
        points: surface points, shape :math:`(B, 3, H, W)`, mm, camera frame (z is the height field).
        normals: unit normals, shape :math:`(B, 3, H, W)`.
        albedo: diffuse albedo, shape :math:`(B, 1, H, W)`.
        light_model: a :class:`~psmini.lights.DirectionalLights`, :class:`~psmini.lights.PointLights` or
            :class:`~psmini.lights.LEDLights` (anything whose ``forward(points)`` returns unit vectors
            :math:`(B, K, 3, H, W)` and irradiance :math:`(B, K, 1, H, W)`).
        specular: Blinn–Phong weight per pixel, shape :math:`(B, 1, H, W)`, >= 0 (0 or ``None``: matte).
        shininess: Blinn–Phong exponent :math:`\alpha` (> 0).
        shadows: also compute cast shadows by ray marching on ``points[:, 2]`` (needs ``pixel_pitch_mm``;
            points must lie on the orthographic pixel grid).
        pixel_pitch_mm: pixel size on the surface, mm; required when ``shadows`` is true.

    Returns:
        images, shape :math:`(B, K, H, W)`, in the units of irradiance times albedo.

    Raises:
        ShapeError: when the shapes do not match.
        InputError: when ``light_model`` is not a light model (an ``nn.Module``: a tensor of directions goes to
            :func:`render_lambertian`, or wrapped in a :class:`~psmini.lights.DirectionalLights`), when ``shadows``
            is asked without a pitch, or weights/exponent are invalid.

    Example:
        >>> from psmini.lights import PointLights
        >>> lights = PointLights(torch.tensor([[0.0, 0.0, 10.0], [5.0, 0.0, 10.0], [0.0, 5.0, 10.0]]))
        >>> points = torch.zeros(1, 3, 2, 2)
        >>> normals = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
        >>> images = render(points, normals, torch.ones(1, 1, 2, 2), lights)
        >>> round(float(images[0, 0, 0, 0]), 4)                     # 1 / 10² at normal incidence
        0.01
    """
    check_light_module(light_model, "light_model")
    sizes = check_shape(points, ["B", "3", "H", "W"], "points")
    check_shape(normals, ["B", "3", "H", "W"], "normals")
    if normals.shape != points.shape:
        raise ShapeError(f"normals {tuple(normals.shape)} and points {tuple(points.shape)} must have the same shape")
    _check_map(albedo, sizes, "albedo")
    if specular is not None:
        _check_map(specular, sizes, "specular")
    check_positive(shininess, "shininess")
    if shadows and pixel_pitch_mm is None:
        raise InputError("render(shadows=True) needs pixel_pitch_mm to march rays on the height field")
    directions, irradiance = light_model(points)  # (B, K, 3, H, W), (B, K, 1, H, W)
    cosine = (directions * normals[:, None]).sum(dim=2, keepdim=True)  # (B, K, 1, H, W)
    radiance = albedo[:, None] * cosine.clamp_min(0)
    if specular is not None:
        radiance = radiance + specular[:, None] * _blinn_phong(directions, normals, cosine, shininess)
    images = irradiance * radiance
    if shadows and pixel_pitch_mm is not None:  # (shadows without a pitch were refused above)
        images = images * cast_shadows(points[:, 2:3], directions, pixel_pitch_mm)
    return images.squeeze(2)


def _blinn_phong(directions: Tensor, normals: Tensor, cosine: Tensor, shininess: float) -> Tensor:
    """Blinn–Phong lobe ``[n·l > 0] max(n·h, 0)^α`` with the view vector (0, 0, 1); shape (B, K, 1, H, W)."""
    view = torch.zeros(3, device=directions.device, dtype=directions.dtype)
    view[2] = 1
    half = directions + view[None, None, :, None, None]
    half = half / half.norm(dim=2, keepdim=True).clamp_min(torch.finfo(half.dtype).tiny)
    n_dot_h = (half * normals[:, None]).sum(dim=2, keepdim=True)
    # clamp to a tiny positive value: x**α has an infinite gradient at 0 for α < 1
    lobe = n_dot_h.clamp_min(torch.finfo(half.dtype).tiny).pow(shininess)
    return lobe * (cosine > 0).to(lobe.dtype)


def _check_map(x: Tensor, sizes: dict[str, int], name: str) -> None:
    """A (B, 1, H, W) map matching the batch (or 1) and the image size."""
    check_tensor(x, name)
    batch, height, width = sizes["B"], sizes["H"], sizes["W"]
    if x.ndim != 4 or x.shape[1] != 1 or tuple(x.shape[2:]) != (height, width) or x.shape[0] not in (1, batch):
        raise ShapeError(f"{name} must have shape ({batch}, 1, {height}, {width}), got {tuple(x.shape)}")


class Renderer(nn.Module):
    """A light model with fixed shading options: ``Renderer(lights)(points, normals, albedo)`` (see :func:`render`).

    Args:
        light_model: a module of :mod:`psmini.lights` (its parameters stay learnable through the renderer).
        shininess: Blinn–Phong exponent.
        shadows: compute cast shadows (needs ``pixel_pitch_mm``).
        pixel_pitch_mm: pixel size on the surface, mm.

    Raises:
        InputError: when ``light_model`` is not a light model (see :func:`render`), or ``shadows`` is asked
            without a pitch.

    Example:
        >>> from psmini.lights import DirectionalLights, ring_lights
        >>> renderer = Renderer(DirectionalLights(ring_lights(8, 55.0)))
        >>> normals = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 4, 4)
        >>> renderer(torch.zeros(1, 3, 4, 4), normals, torch.ones(1, 1, 4, 4)).shape
        torch.Size([1, 8, 4, 4])
    """

    def __init__(
        self,
        light_model: nn.Module,
        shininess: float = 40.0,
        shadows: bool = False,
        pixel_pitch_mm: float | None = None,
    ) -> None:
        super().__init__()
        check_light_module(light_model, "light_model")
        if shadows and pixel_pitch_mm is None:
            raise InputError("Renderer(shadows=True) needs pixel_pitch_mm")
        self.light_model = light_model
        self.shininess = check_positive(shininess, "shininess")
        self.shadows, self.pixel_pitch_mm = shadows, pixel_pitch_mm

    def forward(self, points: Tensor, normals: Tensor, albedo: Tensor, specular: Tensor | None = None) -> Tensor:
        """Images, shape :math:`(B, K, H, W)`."""
        return render(
            points,
            normals,
            albedo,
            self.light_model,
            specular=specular,
            shininess=self.shininess,
            shadows=self.shadows,
            pixel_pitch_mm=self.pixel_pitch_mm,
        )
