"""Pictures that read: normal maps, angular-error maps, hill-shaded depth, and the surface in 3D.

Three layers, each usable without the next:

- **arrays** (NumPy only, no plotting library): :func:`robust_limits`, :func:`normals_to_rgb`, :func:`hillshade`,
  :func:`apply_colormap`, :func:`shaded_depth` and :func:`depth_preview` (the ``depth.png`` that
  :func:`psmini.io.write_outputs` writes: a hill-shaded relief in a perceptual colour map, a colour bar and a scale
  bar in mm, unsolved pixels hatched; drawn with OpenCV);
- **matplotlib figures** (imported when called): :func:`plot_normals`, :func:`plot_angular_error`,
  :func:`plot_depth`, each on a given ``Axes`` with a colour bar labelled in its unit that does not overlap
  the neighbouring axes;
- **3D in the browser** (plotly, imported when called): :func:`surface_figure` (the pixel grid triangulated over
  the mask, coloured by albedo, true proportions unless asked) and :func:`write_html` (one self-contained file
  with plotly.js inlined: it opens offline, no CDN). ``Reconstruction.show()`` and ``psmini view`` use them.

Inputs are tensors or arrays with a batch of one or none: depth, albedo, masks :math:`(1, 1, H, W)`,
:math:`(1, H, W)` or :math:`(H, W)`; normals :math:`(1, 3, H, W)` or :math:`(3, H, W)`, camera frame (x right,
y up, z toward the camera). Colour limits default to the 1st and 99th percentiles over the valid pixels, so a few
outliers do not flatten the picture; pass ``limits`` to compare pictures on one scale.

Hill shading follows Horn (1981), "Hill shading and the reflectance map", Proc. IEEE 69(1): the Lambertian
shading of the surface under a light from the upper left (azimuth 315°, altitude 45°). The colour map is
viridis (van der Walt and Smith, 2015; CC0), perceptually uniform and readable in gray and by colour-blind readers.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from psmini.errors import InputError, ShapeError

__all__ = [
    "robust_limits",
    "normals_to_rgb",
    "hillshade",
    "apply_colormap",
    "shaded_depth",
    "scale_bar_length",
    "depth_preview",
    "plot_normals",
    "plot_angular_error",
    "plot_depth",
    "triangulate_grid",
    "surface_figure",
    "write_html",
]

#: viridis sampled at 33 evenly spaced points (matplotlib's table, CC0), interpolated linearly.
_VIRIDIS = np.array([
    (0.2670, 0.0049, 0.3294), (0.2770, 0.0503, 0.3757), (0.2823, 0.0950, 0.4173), (0.2829, 0.1359, 0.4534),
    (0.2788, 0.1755, 0.4834), (0.2706, 0.2141, 0.5071), (0.2590, 0.2515, 0.5247), (0.2450, 0.2877, 0.5373),
    (0.2297, 0.3224, 0.5457), (0.2143, 0.3556, 0.5512), (0.1994, 0.3876, 0.5546), (0.1856, 0.4186, 0.5568),
    (0.1727, 0.4488, 0.5579), (0.1607, 0.4785, 0.5581), (0.1490, 0.5081, 0.5573), (0.1378, 0.5375, 0.5549),
    (0.1276, 0.5669, 0.5506), (0.1206, 0.5964, 0.5436), (0.1206, 0.6258, 0.5335), (0.1323, 0.6550, 0.5197),
    (0.1579, 0.6838, 0.5017), (0.1966, 0.7118, 0.4792), (0.2461, 0.7389, 0.4520), (0.3041, 0.7647, 0.4199),
    (0.3692, 0.7889, 0.3829), (0.4401, 0.8111, 0.3410), (0.5160, 0.8312, 0.2943), (0.5958, 0.8487, 0.2433),
    (0.6785, 0.8637, 0.1895), (0.7624, 0.8764, 0.1371), (0.8456, 0.8873, 0.0997), (0.9261, 0.8973, 0.1041),
    (0.9932, 0.9062, 0.1439),
])
#: Entries of the colour lookup table between two of those samples: the table holds the linear interpolation at
#: 2049 evenly spaced points, and a value takes the nearest (at most 1/4096 of the range away: under 0.2 of an
#: 8-bit level of any channel, where interpolating each pixel cost three gathers and four (H, W) temporaries).
_TABLE_STEPS = 64
#: Colours of the hatching that marks unsolved pixels (light gray and white stripes: no colour of viridis).
_HATCH = (np.array([0.80, 0.80, 0.80]), np.array([1.0, 1.0, 1.0]))
#: Default robust colour limits, percentiles over the valid pixels.
DEFAULT_PERCENTILES = (1.0, 99.0)


# ------------------------------------------------------------------------------------------------ inputs


def _array(x: Any, name: str) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().to("cpu", torch.float64 if x.is_floating_point() else x.dtype).numpy()
    if isinstance(x, np.ndarray):
        return x
    raise InputError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")


def _plane(x: Any, name: str) -> np.ndarray:
    """``x`` as (H, W): accepts (1, 1, H, W), (1, H, W) and (H, W)."""
    array = _array(x, name)
    while array.ndim > 2 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != 2:
        raise ShapeError(f"{name} must have shape (1, 1, H, W), (1, H, W) or (H, W), got {_array(x, name).shape}")
    return array


def _valid(values: np.ndarray, mask: Any) -> np.ndarray:
    """Where ``values`` are finite and inside ``mask`` (all pixels when None)."""
    valid = np.isfinite(values)
    if mask is not None:
        inside = _plane(mask, "mask") != 0
        if inside.shape != values.shape:
            raise ShapeError(f"mask must be {values.shape[0]}x{values.shape[1]} (HxW) like the data, "
                             f"got {inside.shape}")
        valid &= inside
    return valid


# ------------------------------------------------------------------------------------------------ arrays


def robust_limits(values: Any, mask: Any = None,
                  percentiles: tuple[float, float] = DEFAULT_PERCENTILES) -> tuple[float, float]:
    """Colour limits that a few outliers do not set: percentiles of the finite values inside ``mask``.

    Args:
        values: any shape (a batch of one is fine).
        mask: optional, same number of elements, non-zero = use.
        percentiles: ``(low, high)`` in [0, 100], low < high.

    Returns:
        ``(low, high)``; ``high > low`` always (a constant field gives ``value ± 0.5``, or ``±0.5 · |value|``).

    Raises:
        InputError: percentiles out of order or range, or no finite value inside the mask.

    Example:
        >>> values = np.r_[np.linspace(0.0, 0.5, 1000), np.full(10, -2.5)]   # 1% outliers far below
        >>> [round(v, 3) for v in robust_limits(values)]
        [0.0, 0.495]
    """
    low_p, high_p = percentiles
    if not 0 <= low_p < high_p <= 100:
        raise InputError(f"percentiles must satisfy 0 <= low < high <= 100, got {percentiles}")
    flat = _array(values, "values").reshape(-1).astype(np.float64)
    keep = np.isfinite(flat)
    if mask is not None:
        inside = _array(mask, "mask").reshape(-1) != 0
        if inside.size != flat.size:
            raise ShapeError(f"mask must have as many elements as values ({flat.size}), got {inside.size}")
        keep &= inside
    if not keep.any():
        raise InputError("no finite value inside the mask: nothing to set colour limits from")
    low, high = (float(v) for v in np.percentile(flat[keep], [low_p, high_p]))
    if high <= low:
        half = 0.5 * abs(low) if low != 0 else 0.5
        low, high = low - half, high + half
    return low, high


def normals_to_rgb(normals: Any, mask: Any = None, background: float = 0.0) -> np.ndarray:
    """A normal map as an RGB picture, ``RGB = (n + 1) / 2`` (the convention of ``normals.png``).

    R holds n_x (right), G n_y (up), B n_z (toward the camera): a surface facing the camera is (0.5, 0.5, 1).

    Args:
        normals: unit normals, shape :math:`(1, 3, H, W)` or :math:`(3, H, W)`.
        mask: optional :math:`(H, W)` (or with leading ones); outside it and at non-finite normals, ``background``.
        background: the gray level outside the mask, in [0, 1].

    Returns:
        :math:`(H, W, 3)` float64 in [0, 1].

    Raises:
        ShapeError: not three channels, or a mask of another size.

    Example:
        >>> flat = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
        >>> normals_to_rgb(flat)[0, 0].tolist()
        [0.5, 0.5, 1.0]
    """
    array = _array(normals, "normals")
    if array.ndim == 4 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != 3 or array.shape[0] != 3:
        raise ShapeError(f"normals must have shape (1, 3, H, W) or (3, H, W), got {_array(normals, 'normals').shape}")
    rgb = np.clip((array.transpose(1, 2, 0).astype(np.float64) + 1.0) / 2.0, 0.0, 1.0)
    valid = _valid(array.sum(0), mask)
    return np.where(valid[..., None], np.nan_to_num(rgb), float(background))


def hillshade(depth: Any, pixel_pitch_mm: float = 1.0, *, azimuth_deg: float = 315.0, altitude_deg: float = 45.0,
              exaggeration: float = 1.0) -> np.ndarray:
    r"""Lambertian shading of a height field under a distant light (Horn 1981), for reading relief.

    Slopes are central differences of ``exaggeration · depth`` over ``pixel_pitch_mm`` (one-sided at the border
    and beside non-finite pixels, which count as flat). The light comes from ``azimuth_deg`` clockwise from up
    (315°: the upper left, as cartographers draw it) at ``altitude_deg`` above the image plane.

    Args:
        depth: height toward the camera, mm (or pixels), :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        pixel_pitch_mm: size of a pixel in the units of ``depth``.
        azimuth_deg: light azimuth, degrees clockwise from the image's up direction.
        altitude_deg: light altitude above the image plane, degrees, in (0, 90].
        exaggeration: vertical scale applied before shading (1: true slopes).

    Returns:
        :math:`(H, W)` in [0, 1]: :math:`\max(0, n \cdot l)`; a flat surface gives :math:`\sin(\text{altitude})`.
        float32 for a float32 ``depth`` (a picture needs no more), float64 otherwise.

    Raises:
        InputError: a non-positive pitch or exaggeration, an altitude outside (0, 90].

    Example:
        >>> round(float(hillshade(np.zeros((4, 4)))[0, 0]), 4)   # flat: sin 45°
        0.7071
    """
    if not pixel_pitch_mm > 0 or not exaggeration > 0:
        raise InputError(f"pixel_pitch_mm and exaggeration must be > 0, got {pixel_pitch_mm} and {exaggeration}")
    if not 0 < altitude_deg <= 90:
        raise InputError(f"altitude_deg must be in (0, 90], got {altitude_deg}")
    z = _plane(depth, "depth")
    z = z.astype(np.float32 if z.dtype == np.float32 else np.float64)  # a float32 map is shaded in float32
    finite = np.isfinite(z)
    fill = float(np.mean(z[finite])) if finite.any() else 0.0
    z = np.where(finite, z, fill) * exaggeration
    if min(z.shape) < 2:
        gx = np.zeros_like(z)
        gy = np.zeros_like(z)
    else:
        g_row, g_col = np.gradient(z, pixel_pitch_mm)
        gx, gy = np.asarray(g_col), -np.asarray(g_row)  # x right along columns, y up against rows
    azimuth, altitude = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = np.array([math.sin(azimuth) * math.cos(altitude), math.cos(azimuth) * math.cos(altitude),
                      math.sin(altitude)], dtype=z.dtype)
    shade = (-gx * light[0] - gy * light[1] + light[2]) / np.sqrt(gx**2 + gy**2 + 1.0)
    return np.clip(shade, 0.0, 1.0)


def apply_colormap(values: Any, limits: tuple[float, float]) -> np.ndarray:
    """Viridis colours of ``values`` between ``limits`` (clipped beyond them), without matplotlib.

    Args:
        values: any 2-D field (or with leading ones); non-finite values get the lowest colour.
        limits: ``(low, high)``, low < high.

    Returns:
        :math:`(H, W, 3)` float64 RGB in [0, 1].

    Raises:
        InputError: ``limits`` not increasing.

    Example:
        >>> apply_colormap(np.array([[0.0, 1.0]]), (0.0, 1.0)).round(3).tolist()
        [[[0.267, 0.005, 0.329], [0.993, 0.906, 0.144]]]
    """
    return _colours(_plane(values, "values"), limits, np.float64)


@functools.lru_cache(maxsize=2)
def _viridis_table(dtype: type) -> np.ndarray:
    """``(32 · _TABLE_STEPS + 1, 3)``: :data:`_VIRIDIS` interpolated linearly at evenly spaced points (read-only)."""
    samples = np.arange(len(_VIRIDIS))
    points = np.linspace(0, len(_VIRIDIS) - 1, (len(_VIRIDIS) - 1) * _TABLE_STEPS + 1)
    table = np.stack([np.interp(points, samples, _VIRIDIS[:, channel]) for channel in range(3)], axis=-1)
    table = np.ascontiguousarray(table, dtype=dtype)
    table.flags.writeable = False
    return table


def _colours(values: np.ndarray, limits: tuple[float, float], dtype: type) -> np.ndarray:
    """:func:`apply_colormap` of an (H, W) array, as ``dtype`` (float32 halves the traffic of a preview)."""
    low, high = (float(v) for v in limits)
    if not high > low:
        raise InputError(f"limits must be increasing (low < high), got {limits}")
    table = _viridis_table(dtype)
    v: np.ndarray = np.nan_to_num(values.astype(dtype, copy=False), nan=low)
    np.clip(v, low, high, out=v)  # before scaling: an infinite value cannot overflow
    position = (v - low) * ((len(table) - 1) / (high - low))
    position += 0.5
    return table.take(position.astype(np.intp), axis=0)


@functools.lru_cache(maxsize=4)
def _hatch(shape: tuple[int, int], period: int = 6, dtype: type = np.float64) -> np.ndarray:
    """The hatch pattern of a picture size, built once per size and dtype (read-only: callers only select from
    it)."""
    rows, cols = np.indices(shape)
    stripe = ((rows + cols) // max(1, period // 2)) % 2 == 0
    pattern: np.ndarray = np.where(stripe[..., None], _HATCH[0], _HATCH[1]).astype(dtype)
    pattern.flags.writeable = False
    return pattern


def shaded_depth(depth: Any, mask: Any = None, pixel_pitch_mm: float = 1.0, *,
                 limits: tuple[float, float] | None = None, ambient: float = 0.35,
                 exaggeration: float = 1.0) -> tuple[np.ndarray, tuple[float, float]]:
    """Depth as a hill-shaded relief in viridis: colour says the height, shading says the shape.

    Each pixel's colour (:func:`apply_colormap` between ``limits``) is multiplied by
    ``ambient + (1 - ambient) · shade`` with the shade of :func:`hillshade`, normalised so that a flat surface
    keeps its colour. Unsolved pixels (outside ``mask`` or non-finite) are hatched in light gray and white, a
    pattern no height can take.

    Args:
        depth: height toward the camera, :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        mask: optional solved pixels, same shapes.
        pixel_pitch_mm: pixel size in the units of ``depth`` (for the slopes of the shading).
        limits: colour limits; default :func:`robust_limits` (1st and 99th percentiles over solved pixels).
        ambient: the share of the colour kept in full shadow, in [0, 1].
        exaggeration: vertical exaggeration of the shading only.

    Returns:
        the :math:`(H, W, 3)` RGB picture in [0, 1] (float32 for a float32 ``depth``, float64 otherwise) and the
        limits used.

    Raises:
        InputError: no solved pixel, ``ambient`` outside [0, 1], bad limits or pitch.
        ShapeError: a mask of another size.

    Example:
        >>> rows, cols = np.mgrid[0:32, 0:32]
        >>> bump = np.exp(-((rows - 16.0) ** 2 + (cols - 16.0) ** 2) / 50.0)
        >>> rgb, limits = shaded_depth(bump, pixel_pitch_mm=0.1)
        >>> rgb.shape, [round(v, 2) for v in limits]
        ((32, 32, 3), [0.0, 0.92])
    """
    if not 0.0 <= ambient <= 1.0:
        raise InputError(f"ambient must be in [0, 1], got {ambient}")
    z = _plane(depth, "depth")
    valid = _valid(z, mask)
    if not valid.any():
        raise InputError("no solved pixel: the depth is non-finite or outside the mask everywhere")
    limits = robust_limits(z, valid) if limits is None else limits
    dtype = np.float32 if z.dtype == np.float32 else np.float64
    rgb = _colours(z, limits, dtype)
    shade = hillshade(np.where(valid, z, np.nan), pixel_pitch_mm, exaggeration=exaggeration)
    flat = math.sin(math.radians(45.0))
    factor = (ambient + (1.0 - ambient) * shade) / (ambient + (1.0 - ambient) * flat)
    rgb *= factor.astype(dtype, copy=False)[..., None]
    np.minimum(rgb, 1.0, out=rgb)  # colours and factors are >= 0: only the top can leave [0, 1]
    np.copyto(rgb, _hatch(z.shape, dtype=dtype), where=~valid[..., None])
    return rgb, (float(limits[0]), float(limits[1]))


def scale_bar_length(field_width: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) near a fifth of ``field_width``, for a scale bar.

    Args:
        field_width: the width of the picture in the unit of the bar (e.g. mm), > 0.

    Returns:
        the bar's length, in the same unit.

    Raises:
        InputError: a non-positive or non-finite width.

    Example:
        >>> scale_bar_length(10.0), scale_bar_length(15.3), scale_bar_length(0.4)
        (2.0, 2.0, 0.05)
    """
    if not (math.isfinite(field_width) and field_width > 0):
        raise InputError(f"field_width must be a positive number, got {field_width}")
    target = field_width / 5.0
    power = 10.0 ** math.floor(math.log10(target))
    best = max((m for m in (1.0, 2.0, 5.0) if m * power <= target), default=1.0)
    return float(f"{best * power:.6g}")


def _format_length(value: float, units: str) -> str:
    if units == "mm" and abs(value) < 1.0:
        return f"{value * 1000:.3g} um"
    return f"{value:.3g} {units}"


def depth_preview(depth: Any, mask: Any = None, pixel_pitch_mm: float | None = None, *,
                  limits: tuple[float, float] | None = None, units: str = "mm", min_width: int = 320) -> np.ndarray:
    """The depth preview picture (``depth.png``): shaded relief, colour bar and scale bar, as 8-bit RGB.

    The relief is :func:`shaded_depth` (viridis between the 1st and 99th percentiles unless ``limits``, hill
    shading, unsolved pixels hatched), enlarged by a whole factor to at least ``min_width`` pixels (nearest
    neighbour: every pixel stays a square). A scale bar (:func:`scale_bar_length`) sits in the lower left corner
    of the relief; below it, a strip holds the colour bar with its limits and unit, and says how unsolved
    pixels look. Drawn with OpenCV (no plotting library).

    Args:
        depth: height toward the camera, :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        mask: optional solved pixels, same shapes.
        pixel_pitch_mm: size of a pixel in mm; None when unknown (then the scale bar is in pixels).
        limits: colour limits in the unit of ``depth``; default robust.
        units: the unit of ``depth`` (``"mm"`` or ``"pixels"``), written on the colour bar.
        min_width: the least width of the relief in the picture, pixels.

    Returns:
        :math:`(H', W', 3)` uint8 RGB.

    Raises:
        InputError: no solved pixel, a non-positive pitch, bad limits.

    Example:
        >>> picture = depth_preview(np.random.default_rng(0).random((40, 50)), pixel_pitch_mm=0.025)
        >>> picture.dtype, picture.shape[1]
        (dtype('uint8'), 350)
    """
    import cv2

    if pixel_pitch_mm is not None and not pixel_pitch_mm > 0:
        raise InputError(f"pixel_pitch_mm must be > 0 or None, got {pixel_pitch_mm}")
    z = _plane(depth, "depth")
    pitch = 1.0 if pixel_pitch_mm is None else float(pixel_pitch_mm)
    rgb, (low, high) = shaded_depth(z, mask, pitch, limits=limits)
    height, width = z.shape
    scale = max(1, math.ceil(min_width / width))
    relief = rgb if scale == 1 else np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)
    picture_w = relief.shape[1]
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 1
    size = 0.4 if picture_w < 500 else 0.55
    # the scale bar, white with a black outline, 12 px from the lower left corner
    bar_units = "mm" if pixel_pitch_mm is not None else "px"
    bar = scale_bar_length(width * pitch)
    bar_px = max(2, int(round(bar / pitch * scale)))
    canvas = np.ascontiguousarray((relief * 255).round().astype(np.uint8))
    x0, y0 = 12, canvas.shape[0] - 14
    cv2.rectangle(canvas, (x0 - 1, y0 - 4), (x0 + bar_px + 1, y0 + 4), (0, 0, 0), -1)
    cv2.rectangle(canvas, (x0, y0 - 3), (x0 + bar_px, y0 + 3), (255, 255, 255), -1)
    label = _format_length(bar, "mm") if bar_units == "mm" else f"{bar:g} px"
    cv2.putText(canvas, label, (x0, y0 - 9), font, size, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, label, (x0, y0 - 9), font, size, (255, 255, 255), thick, cv2.LINE_AA)
    # the strip: colour bar with its limits, and the key to the hatching
    strip_h = 46
    strip = np.full((strip_h, picture_w, 3), 255, np.uint8)
    bar_w = max(60, int(picture_w * 0.45))
    ramp = apply_colormap(np.linspace(0.0, 1.0, bar_w)[None], (0.0, 1.0))
    strip[6:18, 10 : 10 + bar_w] = (ramp * 255).round().astype(np.uint8)
    cv2.rectangle(strip, (9, 5), (10 + bar_w, 18), (0, 0, 0), 1)
    unit, factor = ("um", 1000.0) if units == "mm" and high - low < 1.0 else (units if units != "pixels" else "px", 1.0)
    decimals = max(0, 2 - math.floor(math.log10((high - low) * factor)))
    low_text, high_text = f"{low * factor:.{decimals}f}", f"{high * factor:.{decimals}f} {unit}"
    cv2.putText(strip, low_text, (10, 34), font, size, (0, 0, 0), thick, cv2.LINE_AA)
    (text_w, _), _ = cv2.getTextSize(high_text, font, size, thick)
    cv2.putText(strip, high_text, (10 + bar_w - text_w, 34), font, size, (0, 0, 0), thick, cv2.LINE_AA)
    cv2.putText(strip, "height (1-99%)", (10, 44), font, size * 0.8, (80, 80, 80), thick, cv2.LINE_AA)
    key_x = 20 + bar_w
    if picture_w - key_x > 60:
        swatch = (_hatch((12, 24)) * 255).round().astype(np.uint8)
        strip[6:18, key_x : key_x + 24] = swatch
        cv2.rectangle(strip, (key_x - 1, 5), (key_x + 24, 18), (0, 0, 0), 1)
        cv2.putText(strip, "unsolved", (key_x + 30, 16), font, size, (0, 0, 0), thick, cv2.LINE_AA)
    return np.concatenate([canvas, strip], axis=0)


# ------------------------------------------------------------------------------------------------ matplotlib


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise InputError("psmini.viz's figures need matplotlib: pip install 'psmini[viz]'") from error
    return plt


def _colorbar(ax, image, label: str):
    """A colour bar beside ``ax`` whose room is taken from ``ax`` (and that a constrained layout keeps clear of
    the neighbouring axes), labelled with the unit."""
    bar = ax.figure.colorbar(image, ax=ax, fraction=0.046, pad=0.03)
    bar.set_label(label)
    return bar


def plot_normals(ax, normals: Any, mask: Any = None, *, title: str | None = "normals, RGB = (n + 1) / 2"):
    """Draw a normal map (:func:`normals_to_rgb`) on ``ax``; black outside the mask.

    Args:
        ax: a matplotlib ``Axes``.
        normals: :math:`(1, 3, H, W)` or :math:`(3, H, W)`.
        mask: optional solved pixels.
        title: the axes' title, or None.

    Returns:
        the ``AxesImage``.

    Raises:
        ShapeError: as :func:`normals_to_rgb`.

    Example:
        >>> import matplotlib; matplotlib.use("Agg")
        >>> import matplotlib.pyplot as plt
        >>> fig, ax = plt.subplots()
        >>> image = plot_normals(ax, torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 4, 4))
        >>> plt.close(fig)
    """
    image = ax.imshow(normals_to_rgb(normals, mask), interpolation="nearest")
    ax.set_axis_off()
    if title:
        ax.set_title(title)
    return image


def plot_angular_error(ax, error_deg: Any, mask: Any = None, *, limits: tuple[float, float] | None = None,
                       title: str | None = None, cmap: str = "magma"):
    """Draw an angular-error map on ``ax`` with a colour bar in degrees; unsolved pixels hatched gray.

    Args:
        ax: a matplotlib ``Axes``.
        error_deg: angular error in degrees, :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`
            (e.g. :func:`psmini.metrics.angular_error_deg`).
        mask: optional pixels where the error is defined.
        limits: colour limits in degrees; default 0 to the 99th percentile.
        title: the axes' title; default the mean and median error.
        cmap: a sequential matplotlib colour map.

    Returns:
        the colour bar.

    Raises:
        InputError: no finite error inside the mask.

    Example:
        >>> import matplotlib; matplotlib.use("Agg")
        >>> import matplotlib.pyplot as plt
        >>> fig, ax = plt.subplots()
        >>> bar = plot_angular_error(ax, np.full((4, 4), 2.0))
        >>> bar.ax.get_ylabel(), ax.get_title()
        ('angular error (°)', 'mean 2.00°, median 2.00°')
        >>> plt.close(fig)
    """
    _pyplot()
    values = _plane(error_deg, "error_deg").astype(np.float64)
    valid = _valid(values, mask)
    if not valid.any():
        raise InputError("no finite angular error inside the mask")
    if limits is None:
        limits = (0.0, max(robust_limits(values, valid, (0.0, 99.0))[1], 1e-6))
    ax.imshow(_hatch(values.shape), interpolation="nearest")
    shown = np.ma.masked_array(values, mask=~valid)
    image = ax.imshow(shown, cmap=cmap, vmin=limits[0], vmax=limits[1], interpolation="nearest")
    ax.set_axis_off()
    inside = values[valid]
    ax.set_title(title if title is not None else f"mean {inside.mean():.2f}°, median {np.median(inside):.2f}°")
    return _colorbar(ax, image, "angular error (°)")


def plot_depth(ax, depth: Any, mask: Any = None, pixel_pitch_mm: float | None = None, *,
               limits: tuple[float, float] | None = None, units: str = "mm", title: str | None = None,
               exaggeration: float = 1.0):
    """Draw depth as a hill-shaded relief (:func:`shaded_depth`) with a colour bar and a scale bar.

    The colour bar is labelled ``height (mm)`` (or µm when the limits span under 1 mm, or the given units); the
    scale bar in the lower left corner is in mm when ``pixel_pitch_mm`` is known. Unsolved pixels are hatched.
    Pass the same ``limits`` to draw a reconstruction beside its ground truth on one scale.

    Args:
        ax: a matplotlib ``Axes``.
        depth: :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        mask: optional solved pixels.
        pixel_pitch_mm: pixel size in mm, or None (scale bar in pixels).
        limits: colour limits in the unit of ``depth``; default the 1st and 99th percentiles.
        units: the unit of ``depth`` (``"mm"`` or ``"pixels"``).
        title: the axes' title, or None.
        exaggeration: vertical exaggeration of the shading only.

    Returns:
        the colour bar.

    Raises:
        InputError: no solved pixel, a non-positive pitch.

    Example:
        >>> import matplotlib; matplotlib.use("Agg")
        >>> import matplotlib.pyplot as plt
        >>> fig, ax = plt.subplots()
        >>> bar = plot_depth(ax, np.outer(np.linspace(0, 0.4, 40), np.ones(40)), pixel_pitch_mm=0.025)
        >>> bar.ax.get_ylabel()
        'height (µm)'
        >>> plt.close(fig)
    """
    plt = _pyplot()
    from matplotlib.colors import LinearSegmentedColormap, Normalize
    from matplotlib.patches import Rectangle

    if pixel_pitch_mm is not None and not pixel_pitch_mm > 0:
        raise InputError(f"pixel_pitch_mm must be > 0 or None, got {pixel_pitch_mm}")
    z = _plane(depth, "depth")
    pitch = 1.0 if pixel_pitch_mm is None else float(pixel_pitch_mm)
    rgb, (low, high) = shaded_depth(z, mask, pitch, limits=limits, exaggeration=exaggeration)
    micro = units == "mm" and (high - low) < 1.0
    factor, label = (1000.0, "height (µm)") if micro else (1.0, f"height ({units})")
    ax.imshow(rgb, interpolation="nearest")
    ax.set_axis_off()
    if title:
        ax.set_title(title)
    viridis = LinearSegmentedColormap.from_list("psmini_viridis", _VIRIDIS)
    mappable = plt.cm.ScalarMappable(norm=Normalize(low * factor, high * factor), cmap=viridis)
    bar = _colorbar(ax, mappable, label)
    height, width = z.shape
    length = scale_bar_length(width * pitch)
    text = _format_length(length, "mm").replace("um", "µm") if pixel_pitch_mm is not None else f"{length:g} px"
    x0, y0 = 0.04 * width, height - 0.06 * height
    ax.add_patch(Rectangle((x0, y0), length / pitch, max(1.0, 0.015 * height), facecolor="white", edgecolor="black",
                           linewidth=0.8))
    ax.text(x0, y0 - 0.02 * height, text, color="white", fontsize=8, va="bottom",
            bbox={"facecolor": "black", "alpha": 0.5, "pad": 1, "linewidth": 0})
    return bar


# ------------------------------------------------------------------------------------------------ 3D


def triangulate_grid(mask: Any) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the pixel grid over ``mask``: two per 2×2 cell inside it, one where a corner is missing.

    Vertices are the mask's pixels in row-major order; every triangle is counter-clockwise seen from the camera
    (+z, with x right and y up, rows growing downward), so its normal faces the viewer.

    Args:
        mask: :math:`(H, W)` (or with leading ones), non-zero = a vertex.

    Returns:
        ``(vertex_index, faces)``: the flat pixel index (``row * W + col``) of each vertex, :math:`(N,)` int64;
        and the triangles as vertex numbers, :math:`(F, 3)` int64.

    Raises:
        ShapeError: a mask that is not 2-D.

    Example:
        >>> index, faces = triangulate_grid(np.ones((2, 3), bool))
        >>> index.tolist(), faces.tolist()
        ([0, 1, 2, 3, 4, 5], [[0, 3, 1], [1, 4, 2], [1, 3, 4], [2, 4, 5]])
    """
    inside = _plane(mask, "mask") != 0
    height, width = inside.shape
    number = np.full(inside.shape, -1, dtype=np.int64)
    vertex_index = np.flatnonzero(inside)
    number.reshape(-1)[vertex_index] = np.arange(vertex_index.size)
    a, b = number[:-1, :-1], number[:-1, 1:]  # top left, top right
    c, d = number[1:, :-1], number[1:, 1:]  # bottom left, bottom right
    ia, ib, ic, id_ = a >= 0, b >= 0, c >= 0, d >= 0
    candidates = [  # (triangle, where it is drawn): CCW seen from +z
        (np.stack([a, c, b], -1), ia & ib & ic),  # upper-left half (also when only d is missing)
        (np.stack([b, c, d], -1), ib & ic & id_),  # lower-right half (also when only a is missing)
        (np.stack([a, c, d], -1), ia & ic & id_ & ~ib),  # b missing
        (np.stack([a, d, b], -1), ia & ib & id_ & ~ic),  # c missing
    ]
    if height < 2 or width < 2:
        return vertex_index, np.zeros((0, 3), np.int64)
    faces = np.concatenate([tri[where] for tri, where in candidates], axis=0)
    return vertex_index, faces.astype(np.int64)


def surface_figure(depth: Any, albedo: Any = None, mask: Any = None, pixel_pitch_mm: float | None = None, *,
                   max_size: int = 300, exaggeration: float = 1.0, title: str | None = None):
    """The reconstructed surface as an interactive plotly figure (WebGL): a mesh coloured by albedo.

    The pixel grid is triangulated over the solved pixels (:func:`triangulate_grid`), subsampled by a whole
    stride so that the longer side has at most ``max_size`` vertices (a 400×400 reconstruction becomes 200×200,
    which a browser turns at ease). Axes are in mm (pixels without a pitch) with true proportions unless
    ``exaggeration`` is given, and the title says which. Vertex colours are the albedo in gray, scaled by its
    99.5th percentile, with plotly's default lighting on top; without albedo, the height in viridis.

    Args:
        depth: height toward the camera, :math:`(1, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.
        albedo: optional, same shapes.
        mask: optional solved pixels, same shapes (non-finite depth is left out too).
        pixel_pitch_mm: size of a pixel in mm, or None (pixel units).
        max_size: the most vertices along the longer side.
        exaggeration: vertical exaggeration (1: true proportions).
        title: the figure's title; default says the units and the exaggeration.

    Returns:
        a ``plotly.graph_objects.Figure``.

    Raises:
        InputError: plotly missing, no solved pixel, a non-positive pitch, exaggeration or ``max_size``.
        ShapeError: albedo or mask of another size.

    Example:
        >>> fig = surface_figure(np.zeros((8, 8)), np.ones((8, 8)), pixel_pitch_mm=0.025)  # doctest: +SKIP
        >>> len(fig.data[0].i)  # doctest: +SKIP
        98
    """
    try:
        import plotly.graph_objects as go
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise InputError("3D views need plotly: pip install 'psmini[viz]'") from error
    if pixel_pitch_mm is not None and not pixel_pitch_mm > 0:
        raise InputError(f"pixel_pitch_mm must be > 0 or None, got {pixel_pitch_mm}")
    if not exaggeration > 0 or not (isinstance(max_size, int) and max_size >= 2):
        raise InputError(f"exaggeration must be > 0 and max_size an integer >= 2, got {exaggeration} and {max_size}")
    z = _plane(depth, "depth").astype(np.float64)
    valid = _valid(z, mask)
    if not valid.any():
        raise InputError("no solved pixel: nothing to draw")
    stride = max(1, math.ceil(max(z.shape) / max_size))
    pitch = (1.0 if pixel_pitch_mm is None else float(pixel_pitch_mm)) * stride
    z, valid = z[::stride, ::stride], valid[::stride, ::stride]
    index, faces = triangulate_grid(valid)
    rows, cols = np.divmod(index, z.shape[1])
    x, y, height = cols * pitch, -rows * pitch, z.reshape(-1)[index] * exaggeration
    unit = "mm" if pixel_pitch_mm is not None else "px"
    if albedo is not None:
        rho = _plane(albedo, "albedo").astype(np.float64)
        if rho.shape != _plane(depth, "depth").shape:
            raise ShapeError(f"albedo must be {_plane(depth, 'depth').shape} (HxW) like depth, got {rho.shape}")
        rho = rho[::stride, ::stride].reshape(-1)[index]
        rho = np.nan_to_num(rho / robust_limits(rho, None, (0.0, 99.5))[1])
        # the brightest albedo maps to light gray, not white, so that the lighting's shading still shows on it
        intensity, colorscale, cmin, cmax = np.clip(rho, 0.0, 1.0), "gray", 0.0, 1.3
    else:
        low, high = robust_limits(height)
        intensity, colorscale, cmin, cmax = height, "viridis", low, high
    mesh = go.Mesh3d(x=x, y=y, z=height, i=faces[:, 0], j=faces[:, 1], k=faces[:, 2], intensity=intensity,
                     colorscale=colorscale, cmin=cmin, cmax=cmax, showscale=albedo is None, flatshading=False,
                     lighting={"ambient": 0.45, "diffuse": 0.65, "specular": 0.05, "roughness": 0.9},
                     lightposition={"x": -5e4, "y": 5e4, "z": 5e4}, hoverinfo="skip", name="surface")
    scale_note = "true proportions" if exaggeration == 1 else f"height exaggerated {exaggeration:g}×"
    fig = go.Figure(mesh)
    fig.update_layout(
        title=title if title is not None else f"surface, {unit} ({scale_note})",
        scene={"aspectmode": "data", "xaxis_title": f"x ({unit})", "yaxis_title": f"y ({unit})",
               "zaxis_title": f"height ({unit})", "camera": {"eye": {"x": 0.0, "y": -1.9, "z": 1.7}}},
        margin={"l": 0, "r": 0, "t": 40, "b": 0}, height=720,
    )
    return fig


def write_html(figure: Any, path: str | Path) -> Path:
    """Write a plotly figure as one self-contained HTML file (plotly.js inlined: works offline, no CDN).

    Args:
        figure: a ``plotly.graph_objects.Figure`` (e.g. :func:`surface_figure`).
        path: the ``.html`` file.

    Returns:
        the path written.

    Raises:
        DataFormatError: the file cannot be written (nothing is left at ``path`` then; an earlier file is kept).

    Example:
        >>> write_html(surface_figure(np.zeros((8, 8))), "surface.html")  # doctest: +SKIP
        PosixPath('surface.html')
    """
    from psmini._files import atomic_file

    path = Path(path)
    # beside it first, renamed when complete: an interrupted write leaves no page that looks whole
    with atomic_file(path) as temporary:
        figure.write_html(str(temporary), include_plotlyjs=True, full_html=True, auto_open=False)
    return path
