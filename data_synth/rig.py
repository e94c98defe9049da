r"""The psmini rig in simulation: eight LEDs on a ring above the cloth, a macro camera, a card, a mirror sphere.

Geometry (psmini's camera frame, mm: x right, y up, z toward the camera, origin on the optical axis at the card
plane): ``led_count`` LEDs evenly spaced on a ring of diameter ``ring_diameter_mm`` (31.6 mm) at
``led_height_mm`` (10 mm) above the card, each a :class:`psmini.lights.LEDLights` emitter pointing at the field
centre with ``mu = 1`` (Lambertian LED). At the field centre the LEDs sit about 58° from the optical axis.

Camera. The main camera is orthographic with a pixel pitch (0.025 mm/px, a 400×400 crop: 10 mm of cloth).
The macro lens sees a 10 mm field from a working distance (``working_distance_mm``, 40 mm by default) several
times the field and two orders of magnitude more than the cloth's relief (< 1 mm), so the viewing direction
changes by at most ~7° over the field and the magnification by < 3% over the relief; psmini's core geometry
(:mod:`psmini.geometry`) is orthographic too, so the simulation and the solver share one camera. The mirror
sphere is the exception: its highlights are a reflection of the view ray, which is sensitive to the few
degrees the orthographic model drops, so :func:`render_sphere` traces perspective rays from a centre of
projection at ``working_distance_mm`` on the axis.

Sensor (applied in this order): radiance × ``gain`` (set so that a white card at the field centre reads
``exposure`` of full scale) × vignetting (quadratic radial fall-off to ``1 - vignetting`` at the corners), plus
stray ``ambient`` light; optional defocus (Gaussian blur growing with the distance from the focal plane beyond
half the depth of field); shot noise (Gaussian approximation of Poisson with ``full_well`` electrons at full
scale) and read noise; the black level; clipping to [0, 1] (saturation) and quantisation to ``bit_depth`` bits.
The dark frame (all LEDs off) carries ambient light, black level and noise.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import kornia.filters
import torch
from torch import Tensor, nn

from data_synth.fabrics import CARD_ALBEDO, FABRICS, Fabric, make_fabric
from psmini._files import nearest_existing
from psmini.errors import DataFormatError, InputError
from psmini.geometry import depth_to_points, pixel_grid_mm
from psmini.lights import DirectionalLights, LEDLights
from psmini.render import cast_shadows, normals_from_height, render

__all__ = [
    "RigConfig",
    "SyntheticCapture",
    "SphereCapture",
    "rig_lights",
    "distant_lights",
    "render_capture",
    "render_card",
    "render_sphere",
    "defocus",
    "focus_stack",
    "write_synthetic_capture",
]

# Blur levels (pixels) between which :func:`defocus` interpolates per pixel.
_BLUR_LEVELS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0)


@dataclass(frozen=True)
class RigConfig:
    """Everything the simulated rig needs; the defaults describe the psmini rig.

    Attributes:
        led_count: number of LEDs on the ring.
        ring_diameter_mm: diameter of the LED ring, mm.
        led_height_mm: height of the LEDs above the card plane, mm.
        azimuth_offset_deg: azimuth of LED 0, degrees counter-clockwise from +x.
        mu: LED anisotropy (1: Lambertian LED).
        intensity_spread: relative standard deviation of the LEDs' intensities (drawn from ``led_seed``).
        led_seed: seed of the LED intensity draw (the rig's LEDs do not change between captures).
        size: side of the square crop, pixels.
        pixel_pitch_mm: pixel size on the cloth, mm.
        working_distance_mm: distance from the centre of projection to the card plane, mm (sphere renders).
        exposure: level (fraction of full scale) of a white card at the field centre under one LED.
        vignetting: relative fall-off of the lens at the image corners.
        ambient: stray light, fraction of full scale (also present in the dark frame).
        black_level: sensor offset, fraction of full scale.
        full_well: electrons at full scale (shot noise).
        read_noise: read noise standard deviation, fraction of full scale.
        bit_depth: quantisation, bits (8, 10, 12 or 16).
        noise: add shot and read noise.
        shadows: compute cast shadows.
        shininess: Blinn–Phong exponent of metallic threads.
        focal_plane_mm: height of the plane in focus, mm.
        depth_of_field_mm: total depth of field, mm; ``None``: everything in focus.
        blur_at_dof_edge_px: Gaussian blur (sigma, pixels) at the edge of the depth of field.
    """

    led_count: int = 8
    ring_diameter_mm: float = 31.6
    led_height_mm: float = 10.0
    azimuth_offset_deg: float = 0.0
    mu: float = 1.0
    intensity_spread: float = 0.0
    led_seed: int = 0
    size: int = 400
    pixel_pitch_mm: float = 0.025
    working_distance_mm: float = 40.0
    exposure: float = 0.6
    vignetting: float = 0.15
    ambient: float = 0.01
    black_level: float = 0.01
    full_well: float = 10000.0
    read_noise: float = 0.002
    bit_depth: int = 10
    noise: bool = True
    shadows: bool = True
    shininess: float = 40.0
    focal_plane_mm: float = 0.0
    depth_of_field_mm: float | None = None
    blur_at_dof_edge_px: float = 1.0

    def __post_init__(self) -> None:
        if self.led_count < 3:
            raise InputError(f"the rig needs at least 3 LEDs, got led_count={self.led_count}")
        for name in ("ring_diameter_mm", "led_height_mm", "pixel_pitch_mm", "working_distance_mm", "exposure",
                     "full_well", "shininess", "blur_at_dof_edge_px"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < math.inf):
                raise InputError(f"RigConfig.{name} must be a positive number, got {value!r}")
        for name in ("vignetting", "ambient", "black_level", "read_noise", "intensity_spread", "mu"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < math.inf):
                raise InputError(f"RigConfig.{name} must be a number >= 0, got {value!r}")
        if self.vignetting >= 1:
            raise InputError(f"RigConfig.vignetting must be < 1 (a fraction of light lost), got {self.vignetting}")
        if self.bit_depth not in (8, 10, 12, 16):
            raise InputError(f"RigConfig.bit_depth must be 8, 10, 12 or 16, got {self.bit_depth!r}")
        if not isinstance(self.size, int) or self.size < 8:
            raise InputError(f"RigConfig.size must be an integer >= 8, got {self.size!r}")
        if self.depth_of_field_mm is not None and not self.depth_of_field_mm > 0:
            raise InputError(f"RigConfig.depth_of_field_mm must be positive or None, got {self.depth_of_field_mm!r}")

    def replace(self, **changes: Any) -> RigConfig:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


@dataclass
class SyntheticCapture:
    """A simulated capture and its ground truth (all on the CPU or the device asked for).

    Attributes:
        images: one image per LED, shape :math:`(K, H, W)`, in [0, 1] (quantised, clipped).
        dark: all-LEDs-off frame, shape :math:`(1, H, W)`.
        lights: the light model that lit the scene (true LED positions and intensities).
        normals: true unit normals, shape :math:`(3, H, W)`.
        depth_mm: true height above the card plane, shape :math:`(1, H, W)`, mm (offset included).
        albedo: true albedo, shape :math:`(1, H, W)`.
        mask: True on cloth (False where the card shows), shape :math:`(1, H, W)`.
        lit: True where LED k lights the pixel (no attached or cast shadow), shape :math:`(K, H, W)`.
        saturation_level: the [0, 1] value at which the sensor clips (1.0).
    """

    images: Tensor
    dark: Tensor
    lights: nn.Module
    normals: Tensor
    depth_mm: Tensor
    albedo: Tensor
    mask: Tensor
    lit: Tensor
    saturation_level: float = 1.0


@dataclass
class SphereCapture:
    """A mirror sphere under each LED, seen by the perspective camera.

    Attributes:
        images: one image per LED, shape :math:`(K, H, W)`, in [0, 1].
        dark: all-LEDs-off frame, shape :math:`(1, H, W)`.
        mask: pixels on the sphere, shape :math:`(1, H, W)`.
        lights: the true LED model.
        centre_mm: sphere centre, shape :math:`(3,)`, mm.
        radius_mm: sphere radius, mm.
        camera_centre_mm: centre of projection, shape :math:`(3,)`, mm (on the axis, ``working_distance_mm``
            above the card). Pixel (row, col) looks along the ray from it through the card-plane point
            ``(x, y, 0)`` of :func:`psmini.geometry.pixel_grid_mm`: a pinhole of focal length
            ``working_distance_mm / pixel_pitch_mm`` pixels with the principal point at the image centre.
    """

    images: Tensor
    dark: Tensor
    mask: Tensor
    lights: nn.Module
    centre_mm: Tensor
    radius_mm: float
    camera_centre_mm: Tensor


def rig_lights(config: RigConfig | None = None, *, device: torch.device | str | None = None,
               dtype: torch.dtype = torch.float32) -> LEDLights:
    """The rig's LEDs: positions on the ring, principal directions toward the field centre, intensities, mu.

    Intensities are 1 for every LED, times ``1 + intensity_spread · N(0, 1)`` drawn with ``led_seed``.

    Example:
        >>> rig_lights().positions_mm[0].tolist()
        [15.800000190734863, 0.0, 10.0]
    """
    config = config or RigConfig()
    azimuth = torch.arange(config.led_count, dtype=torch.float64) * (2 * math.pi / config.led_count)
    azimuth = azimuth + math.radians(config.azimuth_offset_deg)
    radius = config.ring_diameter_mm / 2
    positions = torch.stack(
        [radius * azimuth.cos(), radius * azimuth.sin(), torch.full_like(azimuth, config.led_height_mm)], dim=-1
    )
    gen = torch.Generator().manual_seed(config.led_seed)
    spread = 1 + config.intensity_spread * torch.randn(config.led_count, generator=gen, dtype=torch.float64)
    if bool((spread <= 0).any()):
        raise InputError(f"intensity_spread {config.intensity_spread} drew a non-positive LED intensity")
    mu = torch.full((config.led_count,), float(config.mu), dtype=torch.float64)
    # the light modules keep their tensors as plain attributes: build them in the target dtype and device
    def cast(x: Tensor) -> Tensor:
        return x.to(device=device, dtype=dtype)

    return LEDLights(cast(positions), cast(-positions / positions.norm(dim=-1, keepdim=True)), cast(spread), cast(mu))


def distant_lights(config: RigConfig | None = None, *, device: torch.device | str | None = None,
                   dtype: torch.dtype = torch.float32) -> DirectionalLights:
    """Distant lights along the directions from the field centre to the rig's LEDs, unit intensity.

    Example:
        >>> round(math.degrees(math.acos(float(distant_lights().directions[0, 2]))), 1)
        57.7
    """
    positions = rig_lights(config, dtype=torch.float64).positions_mm
    return DirectionalLights((positions / positions.norm(dim=-1, keepdim=True)).to(device=device, dtype=dtype))


def _gain(lights: nn.Module, config: RigConfig, like: Tensor) -> Tensor:
    """Scale that makes a white card at the field centre read ``exposure`` (mean over the lights)."""
    centre = torch.zeros(1, 3, 1, 1, device=like.device, dtype=like.dtype)
    directions, irradiance = lights(centre)
    return config.exposure / (irradiance[:, :, 0] * directions[:, :, 2].clamp_min(0)).mean()


def _card_level(lights: nn.Module, height_mm: float) -> Tensor:
    """Mean over the lights of the irradiance times the cosine on a flat card at the field centre."""
    centre = torch.zeros(1, 3, 1, 1)
    centre[:, 2] = height_mm
    directions, irradiance = lights(centre)
    return (irradiance[:, :, 0] * directions[:, :, 2].clamp_min(0)).mean()


def _vignette(config: RigConfig, like: Tensor) -> Tensor:
    """Radial fall-off, shape (1, 1, H, W): 1 at the centre, ``1 - vignetting`` at the corners."""
    x, y = pixel_grid_mm(config.size, config.size, config.pixel_pitch_mm, device=like.device, dtype=like.dtype)
    r2 = (x.square() + y.square()) / (x.square() + y.square()).max()
    return (1 - config.vignetting * r2)[None, None]


def _sensor(signal: Tensor, config: RigConfig, gen: torch.Generator) -> Tensor:
    """Light (fraction of full scale, any shape) → noisy, clipped, quantised readings in [0, 1]."""
    if config.noise:
        noise = torch.randn(signal.shape, generator=gen, dtype=torch.float64).to(signal)
        shot = (signal.clamp_min(0) / config.full_well).sqrt()
        signal = signal + noise * (shot.square() + config.read_noise**2).sqrt()
    top = 2**config.bit_depth - 1
    return torch.round((signal + config.black_level).clamp(0, 1) * top) / top


def defocus(images: Tensor, sigma_px: Tensor) -> Tensor:
    """Blur images with a per-pixel Gaussian sigma by interpolating between a few uniformly blurred copies.

    A layered approximation of a depth-dependent point-spread function: the image is blurred at fixed levels
    (0 to 16 px) and each pixel takes the linear blend of the two levels that bracket its sigma.

    Args:
        images: images, shape :math:`(B, C, H, W)`.
        sigma_px: blur per pixel, shape :math:`(B, 1, H, W)` or :math:`(1, 1, H, W)`, pixels (clipped to 16).

    Returns:
        blurred images, shape :math:`(B, C, H, W)`.

    Example:
        >>> flat = torch.ones(1, 2, 16, 16)
        >>> torch.allclose(defocus(flat, torch.full((1, 1, 16, 16), 2.5)), flat)
        True
    """
    sigma = sigma_px.clamp(0, _BLUR_LEVELS[-1])
    low, high = float(sigma.min()), float(sigma.max())
    result = torch.zeros_like(images)
    for index in range(len(_BLUR_LEVELS) - 1):
        a, b = _BLUR_LEVELS[index], _BLUR_LEVELS[index + 1]
        if b < low or a > high:
            continue
        weight_a = ((b - sigma) / (b - a)).clamp(0, 1) * ((sigma >= a) & (sigma < b))
        inside = (sigma >= a) & ((sigma < b) | (index == len(_BLUR_LEVELS) - 2))
        weight_b = ((sigma - a) / (b - a)).clamp(0, 1) * inside
        result = result + weight_a * _blur(images, a) + weight_b * _blur(images, b)
    return result


def _blur(images: Tensor, sigma: float) -> Tensor:
    if sigma == 0:
        return images
    size = 2 * int(math.ceil(3 * sigma)) + 1
    size = min(size, 2 * (min(images.shape[-2:]) // 2) - 1)  # reflect padding needs the kernel inside the image
    return kornia.filters.gaussian_blur2d(images, (size, size), (sigma, sigma), border_type="reflect")


def _defocus_sigma(height_mm: Tensor, config: RigConfig, focal_plane_mm: float, depth_of_field_mm: float) -> Tensor:
    """Blur sigma (px) growing linearly with the distance from the focal plane, the depth of field's half width
    giving ``blur_at_dof_edge_px`` (thin-lens circle of confusion: proportional to the defocus distance)."""
    return config.blur_at_dof_edge_px * (height_mm - focal_plane_mm).abs() / (depth_of_field_mm / 2)


def _shade(fabric: Fabric, lights: nn.Module, config: RigConfig, height_offset_mm: float,
           device: torch.device | str | None, dtype: torch.dtype,
           visible: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """Noise-free radiance (1, K, H, W) × gain, normals, heights, the lit map and the cast-shadow visibility.

    ``visible`` reuses a visibility computed before (a focus sweep lifts the cloth by millimetres: its cast
    shadows barely move, and ray marching is the expensive part of a render)."""
    height = fabric.height_mm.to(device=device, dtype=dtype) + height_offset_mm
    normals = normals_from_height(height, fabric.pixel_pitch_mm)
    points = depth_to_points(height, fabric.pixel_pitch_mm)
    albedo, specular = fabric.albedo.to(points), fabric.specular.to(points)
    radiance = render(points, normals, albedo, lights, specular=specular if bool(specular.any()) else None,
                      shininess=config.shininess)
    directions, _ = lights(points)
    lit = (directions * normals[:, None]).sum(dim=2) > 0
    if config.shadows:
        if visible is None:
            visible = cast_shadows(height, directions, fabric.pixel_pitch_mm)
        radiance = radiance * visible[:, :, 0]
        lit = lit & (visible[:, :, 0] > 0)
    return radiance * _gain(lights, config, points), normals, height, lit, visible


def render_capture(
    fabric: Fabric,
    config: RigConfig | None = None,
    seed: int = 0,
    height_offset_mm: float = 0.0,
    *,
    lights: nn.Module | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> SyntheticCapture:
    """Simulate the rig's capture of a fabric: one image per LED and a dark frame, with ground truth.

    Args:
        fabric: a :class:`~data_synth.fabrics.Fabric` (its pitch should equal the config's).
        config: the rig; :class:`RigConfig` defaults when omitted.
        seed: seed of the sensor noise.
        height_offset_mm: lift of the cloth above the card plane, mm (the card used for flat-fielding stays at 0).
        lights: a light model replacing the rig's LEDs (e.g. :func:`distant_lights` for ideal renders).
        device: where to render.
        dtype: floating dtype of the render.

    Returns:
        a :class:`SyntheticCapture` of :math:`(K, H, W)` images.

    Raises:
        InputError: when the fabric's size or pitch differs from the config's.

    Example:
        >>> from data_synth import make_fabric
        >>> config = RigConfig(size=32)
        >>> capture = render_capture(make_fabric("cotton", size=32), config)
        >>> capture.images.shape, capture.dark.shape
        (torch.Size([8, 32, 32]), torch.Size([1, 32, 32]))
    """
    config = config or RigConfig()
    _check_fabric(fabric, config)
    if not (isinstance(height_offset_mm, (int, float)) and math.isfinite(height_offset_mm) and height_offset_mm >= 0):
        raise InputError(f"height_offset_mm (the cloth's lift above the card) must be a finite number >= 0 mm, got "
                         f"{height_offset_mm!r}")
    lights = lights if lights is not None else rig_lights(config, device=device, dtype=dtype)
    radiance, normals, height, lit, _ = _shade(fabric, lights, config, height_offset_mm, device, dtype)
    signal = radiance * _vignette(config, radiance) + config.ambient
    if config.depth_of_field_mm is not None:
        sigma = _defocus_sigma(height, config, config.focal_plane_mm, config.depth_of_field_mm)
        signal = defocus(signal, sigma)
    gen = torch.Generator().manual_seed(int(seed))
    images = _sensor(signal, config, gen)[0]
    dark = _sensor(torch.full_like(images[:1], config.ambient), config, gen)
    return SyntheticCapture(images, dark, lights, normals[0], height[0], fabric.albedo[0].to(images),
                            fabric.mask[0].to(images.device), lit[0])


def render_card(config: RigConfig | None = None, albedo: float = CARD_ALBEDO, seed: int = 1, height_mm: float = 0.0,
                *, lights: nn.Module | None = None, device: torch.device | str | None = None,
                dtype: torch.dtype = torch.float32) -> SyntheticCapture:
    """The matte card (flat, uniform ``albedo``) at ``height_mm`` under each LED, for flat-fielding.

    Example:
        >>> card = render_card(RigConfig(size=16, noise=False))
        >>> card.images.shape
        torch.Size([8, 16, 16])
    """
    config = config or RigConfig()
    if not 0 < albedo <= 1:
        raise InputError(f"card albedo must lie in (0, 1], got {albedo!r}")
    size = config.size
    card = Fabric("card", torch.full((1, 1, size, size), float(height_mm)), torch.full((1, 1, size, size), albedo),
                  torch.zeros(1, 1, size, size), torch.ones(1, 1, size, size, dtype=torch.bool),
                  config.pixel_pitch_mm, {"albedo": albedo})
    return render_capture(card, config.replace(shadows=False), seed, lights=lights, device=device, dtype=dtype)


def render_sphere(config: RigConfig | None = None, radius_mm: float = 1.5,
                  centre_mm: tuple[float, float, float] | None = None, seed: int = 2, *, led_radius_mm: float = 1.0,
                  background_albedo: float = 0.05, device: torch.device | str | None = None,
                  dtype: torch.dtype = torch.float32) -> SphereCapture:
    """A mirror sphere (resting on the card unless ``centre_mm`` says otherwise) under each LED.

    Each pixel's perspective ray (see :class:`SphereCapture`) is intersected with the sphere and reflected about
    its normal; the LED, a small disc of radius ``led_radius_mm``, shows where the reflected ray passes near it
    (a Gaussian in the miss distance), at about full scale. Off the sphere the camera sees the matte card lit
    by the LED. The sphere's shadow on the card and inter-reflections are not modelled.

    Returns:
        a :class:`SphereCapture`.

    Example:
        >>> sphere = render_sphere(RigConfig(size=64, pixel_pitch_mm=0.1, noise=False))
        >>> sphere.images.shape, bool(sphere.mask.any())
        (torch.Size([8, 64, 64]), True)
    """
    config = config or RigConfig()
    if not radius_mm > 0 or not led_radius_mm > 0:
        raise InputError(f"radius_mm and led_radius_mm must be positive, got {radius_mm!r}, {led_radius_mm!r}")
    leds = rig_lights(config, device=device, dtype=dtype)
    centre = torch.tensor(centre_mm if centre_mm is not None else (0.0, 0.0, radius_mm), device=device, dtype=dtype)
    camera = torch.tensor([0.0, 0.0, config.working_distance_mm], device=device, dtype=dtype)
    x, y = pixel_grid_mm(config.size, config.size, config.pixel_pitch_mm, device=device, dtype=dtype)
    rays = torch.stack([x, y, torch.zeros_like(x)]) - camera.view(3, 1, 1)
    rays = rays / rays.norm(dim=0, keepdim=True)  # (3, H, W)
    # |camera + t·ray - centre|² = r²  →  t² + 2 b t + c = 0
    offset = (camera - centre).view(3, 1, 1)
    b = (rays * offset).sum(0)
    c = offset.square().sum() - radius_mm**2
    disc = b.square() - c
    on_sphere = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    hit = camera.view(3, 1, 1) + t * rays
    normal = (hit - centre.view(3, 1, 1)) / radius_mm
    reflected = rays - 2 * (rays * normal).sum(0, keepdim=True) * normal
    to_led = leds.positions_mm.view(-1, 3, 1, 1) - hit[None]  # (K, 3, H, W)
    along = (to_led * reflected[None]).sum(1)
    miss2 = (to_led.square().sum(1) - along.square()).clamp_min(0)
    highlight = torch.exp(-0.5 * miss2 / led_radius_mm**2) * (along > 0)
    card = render(depth_to_points(torch.zeros(1, 1, config.size, config.size, device=device, dtype=dtype),
                                  config.pixel_pitch_mm),
                  torch.tensor([0.0, 0.0, 1.0], device=device, dtype=dtype).view(1, 3, 1, 1)
                  .expand(1, 3, config.size, config.size),
                  torch.full((1, 1, config.size, config.size), background_albedo, device=device, dtype=dtype), leds)
    card = card * _gain(leds, config, card)
    signal = torch.where(on_sphere, 0.95 * highlight, card[0]) * _vignette(config, card)[0] + config.ambient
    gen = torch.Generator().manual_seed(int(seed))
    images = _sensor(signal, config, gen)
    dark = _sensor(torch.full_like(images[:1], config.ambient), config, gen)
    return SphereCapture(images, dark, on_sphere[None], leds, centre, float(radius_mm), camera)


def focus_stack(
    fabric: Fabric,
    positions_mm: Tensor | list[float],
    focal_plane_mm: float = 0.0,
    depth_of_field_mm: float = 2.0,
    noise: float = 0.002,
    seed: int = 0,
    *,
    config: RigConfig | None = None,
) -> Tensor:
    """Frames of a focus sweep: the cloth lit by all LEDs, moved along z, blurred away from the focal plane.

    Frame ``i`` shows the cloth lifted by ``positions_mm[i]`` (the stage travels toward the camera; its
    brightness changes with it as the LEDs are fixed, by the change of irradiance at the field centre), so its
    surface lies at ``height + position``; the camera focuses on
    the plane ``z = focal_plane_mm``. The blur (Gaussian sigma) grows linearly with the distance from that plane,
    reaching ``config.blur_at_dof_edge_px`` (1 px) at half the depth of field. The sharpest frame is therefore
    near ``position = focal_plane_mm - mean height of the cloth``.

    Args:
        fabric: the cloth.
        positions_mm: stage positions, length N, mm.
        focal_plane_mm: height of the plane in focus, mm.
        depth_of_field_mm: total depth of field, mm (> 0).
        noise: standard deviation of Gaussian read noise, fraction of full scale (0: none).
        seed: seed of the noise.
        config: the rig (LEDs, size, exposure); :class:`RigConfig` defaults.

    Returns:
        frames, shape :math:`(N, H, W)`, float32 in [0, 1] (clipped, not quantised).

    Raises:
        InputError: for an empty sweep or a non-positive depth of field.

    Example:
        >>> from data_synth import make_fabric
        >>> frames = focus_stack(make_fabric("jute", size=32), [-1.0, 0.0, 1.0], config=RigConfig(size=32))
        >>> frames.shape
        torch.Size([3, 32, 32])
    """
    config = config or RigConfig()
    _check_fabric(fabric, config)
    positions = torch.as_tensor(positions_mm, dtype=torch.float64).flatten().tolist()
    if not positions:
        raise InputError("focus_stack needs at least one position")
    if not depth_of_field_mm > 0:
        raise InputError(f"depth_of_field_mm must be positive, got {depth_of_field_mm!r}")
    if noise < 0:
        raise InputError(f"noise must be >= 0, got {noise!r}")
    leds = rig_lights(config)
    radiance, _, height, _, _ = _shade(fabric, leds, config, 0.0, None, torch.float32)
    lit_image = radiance.mean(dim=1, keepdim=True) * _vignette(config, radiance)
    gen = torch.Generator().manual_seed(int(seed))
    frames = []
    for position in positions:  # a loop over frames; each is a few whole-image operations
        # The LEDs are fixed: lifting the cloth changes its irradiance, taken here as the change at the field
        # centre (the relief is small beside the LED distance); the shading pattern is the one at position 0.
        signal = lit_image * _card_level(leds, position) / _card_level(leds, 0.0) + config.ambient
        signal = defocus(signal, _defocus_sigma(height + position, config, focal_plane_mm, depth_of_field_mm))
        if noise > 0:
            signal = signal + noise * torch.randn(signal.shape, generator=gen)
        frames.append(signal[0, 0].clamp(0, 1))
    return torch.stack(frames)


def _check_fabric(fabric: Fabric, config: RigConfig) -> None:
    size = tuple(fabric.height_mm.shape[-2:])
    if size != (config.size, config.size):
        raise InputError(f"the fabric is {size[0]}x{size[1]} pixels but the rig crops {config.size}x{config.size}")
    if not math.isclose(fabric.pixel_pitch_mm, config.pixel_pitch_mm, rel_tol=1e-6):
        raise InputError(
            f"the fabric's pixel pitch ({fabric.pixel_pitch_mm} mm) differs from the rig's ({config.pixel_pitch_mm} mm)"
        )


def _reusable_card_seed(card_dir: Path, rig: dict[str, Any], overwrite: bool) -> int | None:
    """The noise seed of the card already in ``card_dir`` when :func:`write_synthetic_capture` wrote it for the same
    ``rig``; ``None`` when there is none, or with ``overwrite`` (a new one is written)."""
    from psmini.io.capture import read_manifest

    if overwrite or not card_dir.exists():
        return None
    metadata = read_manifest(card_dir).get("metadata") or {}
    theirs = {key: metadata.get(key) for key in rig}
    if theirs != rig:
        differing = sorted(key for key in rig["rig"] if (theirs["rig"] or {}).get(key) != rig["rig"][key]) \
            if isinstance(theirs["rig"], dict) else ["rig"]
        if theirs["light_model"] != rig["light_model"]:
            differing.insert(0, "light_model")
        raise DataFormatError(f"{card_dir} holds a card for another rig (differing: {', '.join(differing)}); "
                              "synthesise into another folder, or pass overwrite=True (--overwrite) to replace it")
    return int(metadata["seed"])


def write_synthetic_capture(
    out_dir: str | Path,
    fabric_name: str,
    *,
    seed: int = 0,
    size: int = 400,
    noise: bool = True,
    light_model: str = "rig",
    config: RigConfig | None = None,
    height_offset_mm: float = 0.0,
    overwrite: bool = False,
    **fabric_params: Any,
) -> tuple[Path, Path]:
    """Write a synthetic sample capture and its card capture (``kind: "flatfield"``) with ground truth.

    Layout: ``out_dir/<fabric_name>/`` (the sample, with ``gt/``: normals, depth (height above the card, mm),
    albedo, mask (True on cloth), and the true light model) and ``out_dir/card/`` (the card, albedo
    :data:`~data_synth.fabrics.CARD_ALBEDO`), referenced from the sample's manifest as ``../card``.

    Several fabrics share one folder as captures of one rig session share one card: a card that an earlier call
    wrote into ``out_dir`` for the same rig (size, noise, light model and every :class:`RigConfig` field) is kept
    and referenced (its noise then comes from that call's seed, which the sample's metadata records as
    ``card_seed``); a card for another rig is an error, not silently reused.

    Args:
        out_dir: parent folder (created if needed).
        fabric_name: a key of :data:`data_synth.FABRICS`.
        seed: seed of the fabric and of the sensor noise.
        size: side of the crop, pixels.
        noise: add sensor noise (quantisation always applies).
        light_model: ``"rig"`` (the LEDs, near light; the manifest gives the LED model) or ``"directional"``
            (ideal distant lights along the LEDs' directions from the field centre; no vignetting or ambient).
        config: the rig; defaults to :class:`RigConfig` with ``size`` and ``noise``.
        height_offset_mm: lift of the cloth above the card plane, mm.
        overwrite: replace existing folders.
        **fabric_params: parameters of the fabric generator.

    Returns:
        the sample folder and the card folder.

    Raises:
        InputError: for an unknown fabric or light model, bad parameters.
        DataFormatError: when the sample folder exists, or ``out_dir/card`` holds a card for another rig
            (without ``overwrite``), or a folder cannot be written.

    Example:
        >>> sample_dir, card_dir = write_synthetic_capture("synthetic", "jute", size=64)  # doctest: +SKIP
    """
    from psmini.io import write_capture  # the io layer stays out of the core imports of this module

    if fabric_name not in FABRICS:
        raise InputError(f"unknown fabric {fabric_name!r}; expected one of {', '.join(FABRICS)}")
    if light_model not in ("rig", "directional"):
        raise InputError(f"light_model must be 'rig' or 'directional', got {light_model!r}")
    config = (config or RigConfig()).replace(size=size, noise=noise)
    lights = None
    if light_model == "directional":
        config = config.replace(vignetting=0.0, ambient=0.0)
        lights = distant_lights(config)
    fabric = make_fabric(fabric_name, size=size, pixel_pitch_mm=config.pixel_pitch_mm, seed=seed, **fabric_params)
    out_dir = Path(out_dir)
    sample_dir = out_dir / fabric_name
    if sample_dir.exists() and not overwrite:  # before anything is rendered or written
        raise DataFormatError(f"{sample_dir} already exists; pass overwrite=True (--overwrite) to replace it")
    existing = nearest_existing(out_dir)
    if not existing.is_dir():  # a file where a folder of the path should be: found before rendering, not after
        raise DataFormatError(f"cannot write into {out_dir}: {existing} is a file, not a folder")
    # as the manifest will hold it (JSON: tuples come back as lists), to compare with a card already there
    rig = json.loads(json.dumps({"light_model": light_model, "rig": dataclasses.asdict(config)}))
    card_dir, card_seed = out_dir / "card", _reusable_card_seed(out_dir / "card", rig, overwrite)
    capture = render_capture(fabric, config, seed, height_offset_mm, lights=lights)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:  # a folder that cannot be written
        raise DataFormatError(f"cannot create the folder {out_dir}: {error}") from error
    camera = {"model": "orthographic", "simulated": True, "bit_depth": config.bit_depth,
              "exposure": config.exposure, "vignetting": config.vignetting}
    if card_seed is None:
        card_seed = seed + 1
        card = render_card(config, CARD_ALBEDO, card_seed, lights=lights)
        write_capture(card_dir, card.images, card.lights, pixel_pitch_mm=config.pixel_pitch_mm, kind="flatfield",
                      bit_depth=config.bit_depth, dark=card.dark, card_albedo=CARD_ALBEDO, camera=camera,
                      metadata={"synthetic": True, "seed": card_seed, **rig}, overwrite=overwrite)
    gt = {"normals": capture.normals, "depth": capture.depth_mm, "albedo": capture.albedo, "mask": capture.mask,
          "lights": capture.lights}
    metadata = {"synthetic": True, "fabric": fabric.name, "fabric_params": fabric.params, "seed": seed,
                "height_offset_mm": height_offset_mm, "card_seed": card_seed, **rig}
    sample_dir = write_capture(sample_dir, capture.images, capture.lights,
                               pixel_pitch_mm=config.pixel_pitch_mm, kind="sample", bit_depth=config.bit_depth,
                               dark=capture.dark, flatfield={"path": "../card", "albedo": CARD_ALBEDO}, gt=gt,
                               camera=camera, metadata=metadata, overwrite=overwrite)
    return sample_dir, card_dir
