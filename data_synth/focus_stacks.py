"""Synthetic focus stacks with known depth, for shape from focus and the comparison of focus measures.

A surface of known height :math:`z(x, y)` (a fabric of :mod:`data_synth.fabrics`, or a smooth shape: a plane, a
tilted plane, a cone, a sphere cap) carries an all-in-focus texture; the stage lifts it by ``positions_mm[k]``
for frame ``k`` and the camera focuses on the plane ``z = focal_plane_mm``, so pixel :math:`p` is sharpest at
the position :math:`f - z(p)`. Its blur grows linearly with the distance from focus (thin-lens circle of
confusion): Gaussian sigma ``blur_per_mm · |z + position - f|`` pixels, rendered as in
:func:`data_synth.rig.defocus` by interpolating per pixel between uniformly blurred copies of the texture. The
illumination does not change along the sweep (unlike :func:`data_synth.rig.focus_stack`, which keeps the
LEDs' fall-off), so the only cue is focus; Pertuz et al.'s conditions are then applied to every frame: reduced
contrast, saturation (a gain and clipping) and additive Gaussian noise (S. Pertuz, D. Puig, M. A. Garcia,
"Analysis of focus measure operators for shape-from-focus", Pattern Recognition 46, 2013).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch
from torch import Tensor

from psmini.errors import InputError

__all__ = ["SHAPES", "SyntheticFocusStack", "focus_stack_of", "render_focus_stack", "shape_height", "texture_image"]

SHAPES = ("plane", "tilted_plane", "cone", "sphere_cap")
"""The smooth surfaces of :func:`shape_height`."""

_LEVELS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0)


@dataclass(frozen=True)
class SyntheticFocusStack:
    """A focus stack and its ground truth.

    Attributes:
        frames: :math:`(N, H, W)` float32 in [0, 1].
        positions_mm: :math:`(N,)` stage positions, mm (float64).
        height_mm: :math:`(H, W)` the surface height, mm.
        best_position_mm: :math:`(H, W)` the position at which each pixel is sharpest, ``focal - height``, mm.
        textured: :math:`(H, W)` bool, False where the texture was made flat (no focus cue).
        sharpest_frame: index of the frame with the smallest mean defocus, each pixel weighted by how much
            texture it shows (the squared gradient of the all-in-focus texture, so flat pixels, which carry no
            focus cue, do not count).
        focal_plane_mm: the height in focus at position 0, mm.
    """

    frames: Tensor
    positions_mm: Tensor
    height_mm: Tensor
    best_position_mm: Tensor
    textured: Tensor
    sharpest_frame: int
    focal_plane_mm: float

    @property
    def step_mm(self) -> float:
        """The mean spacing of the positions, mm."""
        return float((self.positions_mm[-1] - self.positions_mm[0]).abs() / max(1, len(self.positions_mm) - 1))


def shape_height(shape: str, size: int, depth_mm: float = 1.0) -> Tensor:
    """A smooth surface on a ``size`` × ``size`` grid, heights in [0, ``depth_mm``] mm.

    Args:
        shape: ``"plane"`` (flat, at ``depth_mm / 2``), ``"tilted_plane"`` (rising along x and y),
            ``"cone"`` (apex at the centre), ``"sphere_cap"`` (a cap of a sphere, highest at the centre).
        size: side, pixels.
        depth_mm: the height range, mm (> 0).

    Returns:
        :math:`(size, size)` float64 heights, mm.

    Raises:
        InputError: an unknown shape or a non-positive depth.

    Example:
        >>> h = shape_height("tilted_plane", 5, 2.0)
        >>> float(h.min()), float(h.max())
        (0.0, 2.0)
    """
    if shape not in SHAPES:
        raise InputError(f"shape must be one of {', '.join(SHAPES)}, got {shape!r}")
    if not depth_mm > 0:
        raise InputError(f"depth_mm must be positive, got {depth_mm!r}")
    u = torch.linspace(-1.0, 1.0, size, dtype=torch.float64)
    y, x = torch.meshgrid(u, u, indexing="ij")
    r = (x.square() + y.square()).sqrt()
    if shape == "plane":
        return torch.full((size, size), depth_mm / 2, dtype=torch.float64)
    if shape == "tilted_plane":
        return depth_mm * (0.6 * (x + 1) / 2 + 0.4 * (y + 1) / 2)
    if shape == "cone":
        return depth_mm * (1 - r / math.sqrt(2))
    radius = 1.5  # sphere of radius 1.5 (grid units) centred below the grid: a cap over the square
    # the corners (x² + y² = 2) are the cap's rim: rounding of the square root squared put them at -9e-16 mm
    cap = ((radius**2 - (x.square() + y.square())).sqrt() - math.sqrt(radius**2 - 2.0)).clamp_min(0)
    return depth_mm * cap / cap.max()


def texture_image(size: int, seed: int = 0, scale_px: float = 1.0, fabric: str | None = None) -> Tensor:
    """An all-in-focus texture in [0.1, 0.9]: band-limited noise, or a fabric's shaded albedo.

    Args:
        size: side, pixels.
        seed: seed of the noise or of the fabric.
        scale_px: correlation length of the noise, pixels (Gaussian-filtered white noise).
        fabric: a key of :data:`data_synth.FABRICS`: the fabric's albedo times the shading of its relief under
            a light from above (its texture as the rig's camera sees it); ``None``: noise.

    Returns:
        :math:`(size, size)` float32 texture and, for a fabric, its height (mm) as a second item; see
        :func:`focus_stack_of`.

    Raises:
        InputError: a non-positive scale.

    Example:
        >>> t = texture_image(32, seed=1)
        >>> t.shape, bool(t.min() >= 0.1), bool(t.max() <= 0.9)
        (torch.Size([32, 32]), True, True)
    """
    if not scale_px > 0:
        raise InputError(f"scale_px must be positive, got {scale_px!r}")
    if fabric is None:
        gen = torch.Generator().manual_seed(int(seed))
        noise = torch.randn(1, 1, size, size, generator=gen, dtype=torch.float64)
        k = 2 * math.ceil(3 * scale_px) + 1
        smooth = kornia.filters.gaussian_blur2d(noise, (k, k), (scale_px, scale_px), border_type="reflect")[0, 0]
        smooth = (smooth - smooth.mean()) / smooth.std()
        return (0.5 + 0.13 * smooth).clamp(0.1, 0.9).float()
    return _fabric_texture(fabric, size, seed)[0]


def _fabric_texture(name: str, size: int, seed: int) -> tuple[Tensor, Tensor]:
    from data_synth.fabrics import make_fabric

    fabric = make_fabric(name, size=size, seed=seed)
    height = fabric.height_mm[0, 0].double()
    pitch = fabric.pixel_pitch_mm
    gy, gx = torch.gradient(height, spacing=pitch)
    light = torch.tensor([0.4, 0.3, 0.866], dtype=torch.float64)
    shading = (-gx * light[0] - gy * light[1] + light[2]) / (1 + gx.square() + gy.square()).sqrt()
    image = fabric.albedo[0, 0].double() * shading.clamp_min(0)
    image = 0.1 + 0.8 * (image - image.min()) / (image.max() - image.min()).clamp_min(1e-12)
    return image.float(), height


def render_focus_stack(texture: Tensor, height_mm: Tensor, positions_mm: Tensor | list[float], *,
                       focal_plane_mm: float = 0.0, blur_per_mm: float = 4.0, noise: float = 0.0,
                       contrast: float = 1.0, gain: float = 1.0, seed: int = 0,
                       flat: Tensor | None = None) -> SyntheticFocusStack:
    """Render the frames of a focus sweep over a textured surface of known height.

    Args:
        texture: :math:`(H, W)` all-in-focus texture in [0, 1].
        height_mm: :math:`(H, W)` surface height, mm.
        positions_mm: :math:`(N,)` stage positions (the lift of the surface), mm.
        focal_plane_mm: height in focus at position 0, mm.
        blur_per_mm: blur sigma per mm of defocus, pixels/mm (> 0); clipped at 12 px.
        noise: standard deviation of additive Gaussian noise, fraction of full scale (≥ 0).
        contrast: factor on the deviation from mid-gray, ``0.5 + contrast (I - 0.5)`` (0 < contrast ≤ 1).
        gain: exposure gain before clipping at 1: values above 1 saturate the brightest pixels (≥ 1).
        seed: seed of the noise.
        flat: optional :math:`(H, W)` bool, True where the texture is replaced by its mean (textureless).

    Returns:
        the :class:`SyntheticFocusStack`.

    Raises:
        InputError: mismatched shapes, an empty sweep or parameters out of range.

    Example:
        >>> stack = render_focus_stack(texture_image(32), shape_height("plane", 32), [-0.5, 0.0, 0.5],
        ...                            focal_plane_mm=0.5)
        >>> stack.frames.shape, stack.sharpest_frame
        (torch.Size([3, 32, 32]), 1)
    """
    texture = torch.as_tensor(texture, dtype=torch.float64)
    height = torch.as_tensor(height_mm, dtype=torch.float64)
    positions = torch.as_tensor(positions_mm, dtype=torch.float64).flatten()
    if texture.ndim != 2 or texture.shape != height.shape:
        raise InputError(f"texture and height_mm must be two (H, W) maps of one size, got {tuple(texture.shape)} "
                         f"and {tuple(height.shape)}")
    if positions.numel() == 0:
        raise InputError("render_focus_stack needs at least one position")
    if not blur_per_mm > 0 or noise < 0 or not 0 < contrast <= 1 or gain < 1:
        raise InputError(f"need blur_per_mm > 0, noise ≥ 0, 0 < contrast ≤ 1, gain ≥ 1; got {blur_per_mm}, {noise}, "
                         f"{contrast}, {gain}")
    textured = torch.ones_like(height, dtype=torch.bool)
    if flat is not None:
        textured = ~torch.as_tensor(flat, dtype=torch.bool)
        texture = torch.where(textured, texture, texture[textured].mean() if textured.any() else texture.mean())
    layers = torch.stack([_blurred(texture, s) for s in _LEVELS])  # (L, H, W)
    levels = torch.tensor(_LEVELS, dtype=torch.float64)
    gen = torch.Generator().manual_seed(int(seed))
    frames = []
    for position in positions.tolist():  # a loop over frames, each a few whole-image operations
        sigma = (blur_per_mm * (height + position - focal_plane_mm).abs()).clamp(max=_LEVELS[-1])
        upper = torch.searchsorted(levels, sigma.reshape(-1), right=True).clamp(1, len(_LEVELS) - 1)
        upper = upper.reshape(sigma.shape)
        low, high = levels[upper - 1], levels[upper]
        weight = ((sigma - low) / (high - low)).clamp(0, 1)
        below = layers.gather(0, (upper - 1)[None])[0]
        above = layers.gather(0, upper[None])[0]
        frame = (1 - weight) * below + weight * above
        frame = 0.5 + contrast * (frame - 0.5)
        frame = frame * gain
        if noise > 0:
            frame = frame + noise * torch.randn(frame.shape, generator=gen, dtype=torch.float64)
        frames.append(frame.clamp(0, 1))
    best = focal_plane_mm - height
    defocus = (best[None] - positions[:, None, None]).abs()
    gy, gx = torch.gradient(texture)
    weight = _blurred(gx.square() + gy.square(), 1.0) + 1e-12
    sharpest = int((defocus * weight).sum(dim=(-2, -1)).argmin())
    return SyntheticFocusStack(torch.stack(frames).float(), positions, height, best, textured, sharpest,
                               float(focal_plane_mm))


def _blurred(texture: Tensor, sigma: float) -> Tensor:
    if sigma == 0:
        return texture
    size = min(2 * math.ceil(3 * sigma) + 1, 2 * (min(texture.shape) // 2) - 1)
    blurred = kornia.filters.gaussian_blur2d(texture[None, None], (size, size), (sigma, sigma), border_type="reflect")
    return blurred[0, 0]


def focus_stack_of(surface: str, *, size: int = 96, frames: int = 15, depth_mm: float = 1.0, seed: int = 0,
                   margin_steps: int = 2, blur_per_step: float = 0.6, **conditions: float) -> SyntheticFocusStack:
    """A ready-made stack: a smooth shape with a noise texture, or a fabric with its own texture and relief.

    The sweep covers the surface's heights (``depth_mm`` for a plane) with ``margin_steps`` steps to spare on
    each side, ``frames`` positions in all; the focal plane is at the surface's lowest point plus half its range.
    The blur grows by ``blur_per_step`` pixels (sigma) per sweep step, whatever the step in mm, so stacks of
    fabrics of different relief are alike in difficulty.

    Args:
        surface: one of :data:`SHAPES` or a key of :data:`data_synth.FABRICS`.
        size: side, pixels.
        frames: number of positions (≥ 3).
        depth_mm: the height range of a smooth shape, mm (a fabric keeps its own).
        seed: seed of the texture, the fabric and the noise.
        margin_steps: sweep steps beyond the surface's range on each side.
        blur_per_step: blur sigma added per step of defocus, pixels (> 0).
        **conditions: ``noise``, ``contrast``, ``gain`` of :func:`render_focus_stack`.

    Returns:
        the :class:`SyntheticFocusStack`.

    Raises:
        InputError: an unknown surface or parameters out of range.

    Example:
        >>> stack = focus_stack_of("sphere_cap", size=32, frames=9)
        >>> stack.frames.shape
        torch.Size([9, 32, 32])
    """
    from data_synth.fabrics import FABRICS

    if frames < 3:
        raise InputError(f"frames must be at least 3, got {frames}")
    if surface in SHAPES:
        height = shape_height(surface, size, depth_mm)
        texture = texture_image(size, seed)
    elif surface in FABRICS:
        texture, height = _fabric_texture(surface, size, seed)
    else:
        raise InputError(f"surface must be one of {', '.join(SHAPES)} or a fabric ({', '.join(FABRICS)}), got "
                         f"{surface!r}")
    if not blur_per_step > 0:
        raise InputError(f"blur_per_step must be positive, got {blur_per_step!r}")
    low, high = float(height.min()), float(height.max())
    span = high - low if high - low > 1e-6 else depth_mm
    step = span / max(1, frames - 1 - 2 * margin_steps)
    focal = low + span / 2
    # position p brings height focal - p into focus: the sweep is centred on the middle of the heights
    first = focal - (low + high) / 2 - span / 2 - margin_steps * step
    positions = [first + k * step for k in range(frames)]
    return render_focus_stack(texture, height, positions, focal_plane_mm=focal, seed=seed,
                              blur_per_mm=blur_per_step / step, **conditions)
