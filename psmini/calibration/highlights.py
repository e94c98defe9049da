r"""Locating each LED's highlight on a mirror sphere, robustly and to sub-pixel accuracy.

Per LED image, only the sphere's disc counts (stray reflections elsewhere in the frame are ignored). Within it:

1. the background is the median of the disc and the noise 1.4826 × its median absolute deviation; the LED is
   seen when its brightest pixel stands ``min_snr`` noise levels (and ``min_contrast`` of full scale) above
   the background — relative to its own image, so a dim LED is found as well as a bright one;
2. the pixels above half the peak's contrast form connected blobs; one blob is the highlight, and a second
   blob of at least half the first's contrast is an error ("two highlights"): a double reflection, a second
   lamp, a scratch;
3. the highlight's position is the centre of mass of the blob weighted by the intensity above the half
   level (the thresholded centroid of star trackers, e.g. Liebe, "Accuracy performance of star trackers",
   IEEE TAES 2002): a saturated core weighs uniformly, the shoulders around it by their intensity, and
   blooming, which is symmetric about the core, does not move it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from psmini._checks import check_finite, check_shape
from psmini.calibration.sphere import _label
from psmini.errors import CalibrationError, ShapeError

__all__ = ["Highlights", "locate_highlights"]

# Pixels this close to the outline are left out: they mix the sphere with the background.
_RIM_PX = 1.5
# Half-side of the window of the peak fit, pixels, and the fraction of the contrast below which pixels are
# left out of it.
_PEAK_WINDOW = 2
_PEAK_FLOOR = 0.1
# A second blob whose contrast reaches this fraction of the highlight's is a second highlight.
_SECOND_RATIO = 0.5


@dataclass
class Highlights:
    """The highlight of each LED.

    Attributes:
        positions_px: sub-pixel positions ``(u, v)``, shape :math:`(K, 2)`.
        contrast: peak minus background, shape :math:`(K,)`, in the images' units.
        snr: contrast over the disc's noise level, shape :math:`(K,)`.
        area_px: pixels of the highlight's blob, shape :math:`(K,)`.
        saturated: whether the highlight's peak reached the saturation level, shape :math:`(K,)` bool.
    """

    positions_px: Tensor
    contrast: Tensor
    snr: Tensor
    area_px: Tensor
    saturated: Tensor


def _name(index: int, names: Sequence[str] | None) -> str:
    return f"LED {index}" + (f" ({names[index]})" if names is not None else "")


def locate_highlights(
    images: Tensor,
    centre_px: Tensor,
    radius_px: Tensor | float,
    *,
    dark: Tensor | None = None,
    saturation_level: float | None = 1.0,
    min_snr: float = 10.0,
    min_contrast: float = 0.01,
    names: Sequence[str] | None = None,
) -> Highlights:
    r"""Find the highlight of each LED on the sphere's disc.

    Args:
        images: one image per LED, shape :math:`(K, H, W)`, linear values (e.g. in [0, 1]).
        centre_px: the sphere's centre ``(u, v)`` in the image, shape :math:`(2,)`.
        radius_px: its radius in the image, pixels.
        dark: optional all-LEDs-off frame, shape :math:`(H, W)` or :math:`(1, H, W)`, subtracted first.
        saturation_level: level at which a pixel is saturated (only reported), or None.
        min_snr: the least contrast of a highlight in units of the disc's noise level.
        min_contrast: the least contrast of a highlight, in the images' units.
        names: optional name of each LED's image, for the messages.

    Returns:
        :class:`Highlights`.

    Raises:
        ShapeError: for images not (K, H, W) or a dark frame of another size.
        CalibrationError: naming the LED, for no highlight on the sphere ("no highlight", or "highlight outside
            the sphere" when the image's brightest spot lies off the sphere), and for two highlights.

    Example:
        >>> v, u = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
        >>> spot = torch.exp(-((u - 30.3).square() + (v - 25.8).square()) / 4)
        >>> found = locate_highlights(spot[None] + 0.01, torch.tensor([32.0, 32.0]), 20.0)
        >>> [round(x, 2) for x in found.positions_px[0].tolist()]
        [30.3, 25.8]
    """
    sizes = check_shape(images, ["K", "H", "W"], "images")
    check_finite(images, "images")
    count, height, width = sizes["K"], sizes["H"], sizes["W"]
    if names is not None and len(names) != count:
        raise ShapeError(f"names must hold one name per image ({count}), got {len(names)}")
    signal = images
    if dark is not None:
        dark = dark.reshape(-1, *dark.shape[-2:]) if dark.ndim >= 2 else dark
        if dark.ndim != 3 or dark.shape[0] != 1 or tuple(dark.shape[1:]) != (height, width):
            raise ShapeError(f"dark must have shape ({height}, {width}) or (1, {height}, {width}), "
                             f"got {tuple(dark.shape)}")
        signal = images - dark.to(images)
    centre = centre_px.to(images)
    radius = torch.as_tensor(radius_px, device=images.device, dtype=images.dtype)
    v, u = torch.meshgrid(
        torch.arange(height, device=images.device, dtype=images.dtype),
        torch.arange(width, device=images.device, dtype=images.dtype),
        indexing="ij",
    )
    disc = (u - centre[0]).square() + (v - centre[1]).square() <= (radius - _RIM_PX).clamp_min(1).square()
    inside = signal[:, disc]  # (K, P)
    background = inside.median(dim=1).values
    noise = 1.4826 * (inside - background[:, None]).abs().median(dim=1).values
    peak = inside.amax(dim=1)
    contrast = peak - background
    floor = torch.maximum(min_snr * noise, torch.full_like(noise, min_contrast))
    _check_seen(signal, disc, contrast, floor, background, names)

    half = background + contrast / 2
    above = (signal > half[:, None, None]) & disc
    labels = _label(above)  # (K, H, W)
    main = _main_blobs(signal, labels, background, contrast, names)
    blob = labels == main[:, None, None]
    weights = torch.where(blob, signal - half[:, None, None], torch.zeros_like(signal))
    total = weights.sum(dim=(1, 2))
    positions = torch.stack([(weights * u).sum(dim=(1, 2)), (weights * v).sum(dim=(1, 2))], dim=-1) / total[:, None]
    saturated = torch.zeros(count, dtype=torch.bool, device=images.device)
    if saturation_level is not None:
        saturated = (images * blob).amax(dim=(1, 2)) >= saturation_level
    peaks = _fit_peaks(signal, background, contrast, positions)
    positions = torch.where((~saturated & torch.isfinite(peaks).all(-1))[:, None], peaks, positions)
    return Highlights(positions, contrast, contrast / noise.clamp_min(torch.finfo(images.dtype).tiny),
                      blob.sum(dim=(1, 2)), saturated)


def _fit_peaks(signal: Tensor, background: Tensor, contrast: Tensor, start: Tensor) -> Tensor:
    """Sub-pixel maxima by a least-squares Gaussian (a quadratic in log intensity) over the 5×5 window around
    ``start`` (K, 2); NaN where the fit has no maximum within the window."""
    count, height, width = signal.shape
    steps = torch.arange(-_PEAK_WINDOW, _PEAK_WINDOW + 1, device=signal.device)
    dv, du = (g.flatten() for g in torch.meshgrid(steps, steps, indexing="ij"))
    corner = start.detach().round().long()
    cols = (corner[:, :1] + du).clamp(0, width - 1)
    rows = (corner[:, 1:] + dv).clamp(0, height - 1)
    values = signal[torch.arange(count, device=signal.device)[:, None], rows, cols] - background[:, None]  # (K, M)
    x, y = (cols - corner[:, :1]).to(signal), (rows - corner[:, 1:]).to(signal)
    design = torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y], dim=-1)
    # weight by the value: the log's noise falls as 1/value; dim pixels carry mostly noise
    weights = torch.where(values > _PEAK_FLOOR * contrast[:, None], values, torch.zeros_like(values))
    logs = values.clamp_min(torch.finfo(signal.dtype).tiny).log()
    coef = torch.linalg.lstsq(design * weights[..., None], (logs * weights)[..., None]).solution[..., 0]
    hessian = torch.stack([2 * coef[:, 3], coef[:, 4], coef[:, 4], 2 * coef[:, 5]], dim=-1).view(count, 2, 2)
    maximum = (torch.linalg.eigvalsh(hessian) < 0).all(-1) & ((weights > 0).sum(-1) >= 6)
    safe = torch.where(maximum[:, None, None], hessian, -torch.eye(2, device=signal.device, dtype=signal.dtype))
    offset = torch.linalg.solve(safe, -coef[:, 1:3, None])[..., 0]
    inside = maximum & (offset.abs() <= _PEAK_WINDOW - 1).all(-1)
    return torch.where(inside[:, None], corner.to(signal) + offset, torch.full_like(offset, float("nan")))


def _check_seen(signal: Tensor, disc: Tensor, contrast: Tensor, floor: Tensor, background: Tensor,
                names: Sequence[str] | None) -> None:
    """Raise for the first LED without a highlight on the sphere, saying whether one shows off it."""
    missing = torch.nonzero(contrast < floor).flatten().tolist()
    if not missing:
        return
    index = missing[0]
    outside = signal[index].masked_fill(disc, float("-inf"))
    spot = int(outside.flatten().argmax())
    off_peak = float(outside.flatten()[spot])
    off_level = float(signal[index][~disc].median())
    others = f" (also LED(s) {missing[1:]})" if len(missing) > 1 else ""
    if off_peak - off_level >= 2 * float(floor[index]) and off_peak - float(background[index]) > float(contrast[index]):
        row, col = divmod(spot, signal.shape[-1])
        raise CalibrationError(
            f"{_name(index, names)}: highlight outside the sphere: its brightest spot at (u, v) = ({col}, {row}) lies "
            f"off the sphere's disc and no highlight shows on it; check the sphere's mask or position{others}"
        )
    raise CalibrationError(
        f"{_name(index, names)}: no highlight on the sphere: its brightest pixel stands {float(contrast[index]):.4g} "
        f"above the background, below the {float(floor[index]):.4g} needed (is the LED on? is the image "
        f"black?){others}"
    )


def _main_blobs(signal: Tensor, labels: Tensor, background: Tensor, contrast: Tensor,
                names: Sequence[str] | None) -> Tensor:
    """The label of each LED's brightest blob; raise when a second blob is nearly as bright."""
    count = signal.shape[0]
    flat_labels = labels.flatten(1)
    flat_signal = signal.flatten(1)
    # peak of every blob, indexed by label, per LED: one scatter over all LEDs at once
    peaks = torch.full((count, flat_labels.shape[1] + 1), float("-inf"), device=signal.device, dtype=signal.dtype)
    peaks.scatter_reduce_(1, flat_labels, flat_signal, reduce="amax")
    peaks[:, 0] = float("-inf")  # label 0 is the background
    main = peaks.argmax(dim=1)
    second = peaks.scatter(1, main[:, None], float("-inf"))
    second_contrast = second.amax(dim=1) - background
    double = second_contrast >= _SECOND_RATIO * contrast
    if bool(double.any()):
        index = int(torch.nonzero(double)[0])
        first_at = divmod(int(main[index]) - 1, signal.shape[-1])
        other = int(second[index].argmax()) - 1
        other_at = divmod(other, signal.shape[-1])
        raise CalibrationError(
            f"{_name(index, names)}: two highlights on the sphere, near (u, v) = ({first_at[1]}, {first_at[0]}) and "
            f"({other_at[1]}, {other_at[0]}), the second with {float(second_contrast[index] / contrast[index]):.0%} of "
            "the first's contrast: a second light source or reflection; only one highlight per LED image is allowed"
        )
    return main
