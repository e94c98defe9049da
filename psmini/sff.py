r"""Shape from focus: a depth map from a focus stack, with a reliability map.

The stage sweeps the sample through the focal plane; every frame is scored pixel by pixel with the local form
of a focus measure (:func:`psmini.focus.focus_volume`), and each pixel's depth is the sweep position where its
focus value peaks (Nayar & Nakagawa, "Shape from focus", IEEE PAMI 16, 1994), refined between samples by a
Gaussian (a parabola through the logarithms of the three values around the peak, Nayar & Nakagawa's Gaussian
interpolation) or a parabola. The result is in the units of ``positions``: the position at which each pixel is
sharpest. With a stage that lifts the sample toward a camera focused at height :math:`f`, the surface height is
:math:`f - \text{position}` (:meth:`DepthFromFocus.surface_height`).

Reliability (peak sharpness): :math:`r = 1 - \operatorname{median}_k F_k / \max_k F_k` per pixel, in [0, 1]. A
textured pixel whose focus curve has a clear peak scores near 1; a textureless pixel, whose curve is flat (or
only noise), scores near 0 (0 when its focus values are all 0). It is the ratio form of the peak's prominence
above the curve's typical level; Pertuz, Puig and García ("Reliability measure for shape-from-focus", Image and
Vision Computing 31, 2013) use the fit of the curve instead.

Optional aggregation: a median filter of the depth map (its size in pixels), which removes isolated outliers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from psmini.errors import InputError, ShapeError
from psmini.focus import focus_volume

__all__ = ["DepthFromFocus", "SFFConfig", "depth_from_focus"]

_INTERPOLATION = ("gaussian", "parabola", "none")
_CHUNK = 8  # frames per focus-volume call: bounds the intermediates of long stacks of large frames


@dataclass(frozen=True)
class SFFConfig:
    """Options of :func:`depth_from_focus` beyond the measure and the window.

    Attributes:
        interpolation: ``"gaussian"`` (Nayar & Nakagawa), ``"parabola"`` or ``"none"`` (the sampled position).
        aggregation: side of a median filter applied to the depth map, odd pixels; 0 or 1: none.
        params: the focus operator's own parameters (e.g. ``{"sigma": 1.5}`` for ``GDER``).
    """

    interpolation: str = "gaussian"
    aggregation: int = 0
    params: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class DepthFromFocus:
    """The result of :func:`depth_from_focus`.

    Attributes:
        depth: :math:`(H, W)` position of best focus per pixel, the units of ``positions`` (float64).
        index: :math:`(H, W)` index of the sharpest frame per pixel (int64).
        reliability: :math:`(H, W)` peak sharpness in [0, 1]: near 0 where the focus curve is flat.
        peak: :math:`(H, W)` the largest focus value per pixel.
        refined: :math:`(H, W)` bool, True where the interpolation was accepted.
    """

    depth: Tensor
    index: Tensor
    reliability: Tensor
    peak: Tensor
    refined: Tensor

    def surface_height(self, focal_plane: float) -> Tensor:
        """Heights :math:`f - \\text{depth}` for a stage that lifts the sample toward a camera focused at ``f``."""
        return focal_plane - self.depth


def depth_from_focus(stack: Tensor, positions: Sequence[float] | Tensor, measure: str = "LAPM", window: int = 9,
                     config: SFFConfig | None = None) -> DepthFromFocus:
    """A depth map from a focus stack: per pixel, the peak of the focus volume, interpolated.

    Args:
        stack: :math:`(N, H, W)` or :math:`(N, 1, H, W)` frames in sweep order, uint8, uint16 or float, N ≥ 3.
        positions: :math:`(N,)` the sweep's positions, strictly monotonic (any spacing), e.g. mm.
        measure: a focus measure name or operator code (:data:`psmini.focus.FOCUS_MEASURES`); its local form
            scores each pixel. Default: ``LAPM``, Nayar's sum-modified Laplacian.
        window: side of the focus measure's window, pixels.
        config: interpolation, aggregation and the operator's parameters (:class:`SFFConfig`).

    Returns:
        a :class:`DepthFromFocus` (depth, index, reliability, peak, refined), on the stack's device.

    Raises:
        ShapeError: a stack of the wrong shape or fewer than 3 frames.
        InputError: positions that are not numbers (``None``, strings), of another length, not finite or not
            strictly monotonic; a bad option; any error of :func:`psmini.focus.focus_volume`.

    Example:
        >>> from data_synth.focus_stacks import focus_stack_of
        >>> stack = focus_stack_of("tilted_plane", size=48, frames=11)
        >>> result = depth_from_focus(stack.frames, stack.positions_mm, "LAPM", window=7)
        >>> error = (result.depth - stack.best_position_mm).square().mean().sqrt()
        >>> bool(error < stack.step_mm)
        True
    """
    config = config or SFFConfig()
    if config.interpolation not in _INTERPOLATION:
        raise InputError(f"interpolation must be one of {', '.join(_INTERPOLATION)}, got {config.interpolation!r}")
    if not (isinstance(config.aggregation, int) and config.aggregation >= 0
            and (config.aggregation <= 1 or config.aggregation % 2 == 1)):
        raise InputError(f"aggregation must be 0 (none) or an odd median size ≥ 3, got {config.aggregation!r}")
    if not isinstance(stack, Tensor):
        raise InputError(f"stack must be a torch.Tensor, got {type(stack).__name__}")
    if stack.ndim == 4 and stack.shape[1] == 1:
        stack = stack[:, 0]
    if stack.ndim != 3 or stack.shape[0] < 3:
        raise ShapeError(f"stack must have shape (N, H, W) or (N, 1, H, W) with N ≥ 3 frames, got {tuple(stack.shape)}")
    try:
        z = torch.as_tensor(positions, dtype=torch.float64).detach().cpu().flatten()
    except (TypeError, ValueError, RuntimeError):  # None failed as a bare TypeError of torch
        raise InputError(f"positions must be a sequence or a 1-D tensor of the {stack.shape[0]} frames' positions "
                         f"(numbers), got {type(positions).__name__}") from None
    if z.numel() != stack.shape[0]:
        raise InputError(f"positions ({z.numel()}) and frames ({stack.shape[0]}) must have the same length")
    steps = z[1:] - z[:-1]
    if not bool(torch.isfinite(z).all()) or not (bool((steps > 0).all()) or bool((steps < 0).all())):
        raise InputError("positions must be finite and strictly monotonic")
    params = dict(config.params)
    with torch.no_grad():
        volume = torch.cat([focus_volume(stack[i : i + _CHUNK], measure, window, **params)
                            for i in range(0, stack.shape[0], _CHUNK)])
    return _peaks(volume.double(), z.to(volume.device), config)


def _peaks(volume: Tensor, z: Tensor, config: SFFConfig) -> DepthFromFocus:
    """Per-pixel peak, interpolation and reliability of a (N, H, W) float64 focus volume."""
    n = volume.shape[0]
    peak, index = volume.max(dim=0)
    sampled = z[index]
    inner = (index > 0) & (index < n - 1)
    centre = index.clamp(1, n - 2)
    s0, s1, s2 = (volume.gather(0, (centre + k)[None])[0] for k in (-1, 0, 1))
    z0, z1, z2 = z[centre - 1], z[centre], z[centre + 1]
    valid = inner.clone()
    if config.interpolation == "gaussian":
        positive = (s0 > 0) & (s1 > 0) & (s2 > 0)
        tiny = torch.finfo(volume.dtype).tiny
        s0, s1, s2 = (s.clamp_min(tiny).log() for s in (s0, s1, s2))
        valid &= positive
    depth = sampled.clone()
    refined = torch.zeros_like(inner)
    if config.interpolation != "none":
        d01, d12 = (s1 - s0) / (z1 - z0), (s2 - s1) / (z2 - z1)
        curvature = (d12 - d01) / (z2 - z0)
        safe = torch.where(curvature < 0, curvature, -torch.ones_like(curvature))
        vertex = 0.5 * (z0 + z1) - d01 / (2.0 * safe)
        low, high = torch.minimum(z0, z2), torch.maximum(z0, z2)
        refined = valid & (curvature < 0) & (vertex >= low) & (vertex <= high) & torch.isfinite(vertex)
        depth = torch.where(refined, vertex, sampled)
    typical = volume.median(dim=0).values
    reliability = torch.where(peak > 0, 1.0 - typical / peak.clamp_min(torch.finfo(volume.dtype).tiny),
                              torch.zeros_like(peak)).clamp(0, 1)
    if config.aggregation > 1:
        k = config.aggregation
        if k > min(depth.shape):
            raise InputError(f"aggregation {k} is larger than the {depth.shape[0]}×{depth.shape[1]} map")
        padded = F.pad(depth[None, None], (k // 2,) * 4, mode="replicate")  # kornia pads with zeros
        depth = kornia.filters.median_blur(padded, (k, k))[0, 0, k // 2 : -(k // 2), k // 2 : -(k // 2)]
    return DepthFromFocus(depth, index, reliability, peak, refined)
