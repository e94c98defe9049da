r"""The 28 focus measure operators of Pertuz, Puig and García (2013), global and local.

Pertuz et al., "Analysis of focus measure operators for shape-from-focus", Pattern Recognition 46 (2013) compare
28 operators in six families. psmini implements every one from its original paper, on batched torch frames
:math:`(B, H, W)` (CPU or CUDA; uint8/uint16 scaled to [0, 1], float used as is):

- a **global** form, ``<function>(frames, roi=None, **params) -> (B,)``: one score per frame over the valid part
  of the region (a pixel counts only when every neighbour its formula reads lies inside the region, so a score
  over a region equals the score of the cropped frame); larger is sharper;
- a **local** form, :func:`focus_volume` ``(frames, name, window) -> (B, H, W)``: a focus value per pixel from a
  ``window`` × ``window`` neighbourhood (replicated border), the input of shape from focus
  (:func:`psmini.sff.depth_from_focus`).

Choices where public implementations disagree (the widely copied MATLAB ``fmeasure`` of Pertuz, and its ports):
every operator reads both orientations (the originals of GRAT, GRAS, SFRQ and VOLA were written along rows
only); every nonlinearity applied to a difference is a square or an absolute value, so a dark-to-bright and a
bright-to-dark edge score alike (``fmeasure``'s BREN takes a signed max); where a least-squares fit or
variance is meant it includes the constant term (``fmeasure``'s CURV fits without it, and its P3 repeats P2's
kernel); Haar wavelets, undecimated, for the three wavelet operators (``fmeasure`` uses db6 decimated by
``wavedec2``; a decimated transform is blind to edges between its blocks). Each docstring says its choice.

Operators divided by a brightness (GLVN, WAVR, DCTE, DCTR, HELM) are contrast *ratios*: inverting a frame
changes their score unless the mean (per block, per window) stays the same — by design.

Float input is differentiable except for HISE (a histogram; its score carries no gradient).

References (the original definitions, as numbered in Pertuz et al. 2013):
    GDER: J. M. Geusebroek et al., "Robust autofocusing in microscopy", Cytometry 39 (2000).
    GRAE: M. Subbarao, T. Choi, A. Nikzad, "Focusing techniques", Opt. Eng. 32 (1993).
    GRAT, GRAS, BREN, VOLA: A. Santos et al., "Evaluation of autofocus functions in molecular cytogenetic
    analysis", J. Microscopy 188 (1997); D. Vollath, "Automatic focusing by correlative methods", J. Microscopy
    147 (1987); A. M. Eskicioglu, P. S. Fisher, "Image quality measures and their performance", IEEE Trans.
    Commun. 43 (1995).
    TENG: E. Krotkov, "Focusing", IJCV 1 (1987). TENV, LAPV, GLLV: J. L. Pech-Pacheco et al., ICPR (2000).
    LAPE: Subbarao et al. (1993). LAPM: S. K. Nayar, Y. Nakagawa, "Shape from focus", IEEE PAMI 16 (1994).
    LAPD: A. Thelen et al., "Improvements in shape-from-focus for holographic reconstructions with regard to
    focus operators, neighborhood-size, and height value interpolation", IEEE TIP 18 (2009).
    WAVS, WAVV: G. Yang, B. J. Nelson, IROS (2003). WAVR: H. Xie, W. Rong, L. Sun, "Wavelet-based focus
    measure and 3-D surface reconstruction method for microscopy images", IROS (2006).
    ACMO: M. V. Shirvaikar, "An optimal measure for camera focus and exposure", SSST (2004).
    GLVA, HISE: Krotkov (1987). GLVN: F. C. A. Groen, I. T. Young, G. Ligthart, Cytometry 6 (1985).
    HISR: L. Firestone et al., "Comparison of autofocus methods for automated microscopy", Cytometry 12 (1991).
    DCTE: C.-H. Shen, H. H. Chen, "Robust focus measure for low-contrast images", ICCE (2006).
    DCTR: S.-Y. Lee et al., "Reduced energy-ratio measure for robust autofocusing in digital camera", IEEE
    Signal Process. Lett. 16 (2009).
    CONT: H. Nanda, R. Cutler, CVPR technical sketch (2001). CURV, HELM: F. S. Helmli, S. Scherer, "Adaptive
    shape from focus with an error estimation in light microscopy", ISPA (2001).
    SFIL: R. Minhas et al., "3D shape from focus and depth map computation using steerable filters", ICIAR
    (2009). SFRQ: Eskicioglu & Fisher (1995).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini.errors import InputError
from psmini.focus import _opencv
from psmini.focus.measures import (
    Roi,
    _as_float,
    _correlate_valid,
    _gaussian_taps,
    _population_variance,
    _region,
    brenner,
    gaussian_derivative,
    image_contrast,
    normalized_variance,
    tenengrad,
    variance_of_laplacian,
    wavelet_sum,
)

__all__ = [
    "FOCUS_FAMILIES",
    "FOCUS_MEASURES",
    "FOCUS_NAMES",
    "FOCUS_OPERATORS",
    "FocusMeasure",
    "FocusOperator",
    "FocusVolume",
    "absolute_central_moment",
    "curvature",
    "dct_energy_ratio",
    "dct_reduced_energy_ratio",
    "diagonal_laplacian",
    "focus_measure",
    "focus_volume",
    "gradient_energy",
    "gray_level_local_variance",
    "gray_level_variance",
    "helmli_mean",
    "histogram_entropy",
    "histogram_range",
    "laplacian_energy",
    "modified_laplacian",
    "spatial_frequency",
    "squared_gradient",
    "steerable_filters",
    "tenengrad_variance",
    "thresholded_gradient",
    "vollath_f4",
    "wavelet_ratio",
    "wavelet_variance",
]

_SQRT_HALF = math.sqrt(0.5)


# --------------------------------------------------------------------------------------------------- guards


def _frames(frames: Tensor, roi: Roi | str | None, min_size: int, name: str) -> Tensor:
    """The region as float (B, h, w): integer frames scaled to [0, 1]."""
    return _as_float(_region(frames, roi, min_size, name))[:, 0]


def _number(name: str, label: str, value: object, minimum: float = 0.0, strict: bool = False) -> float:
    if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and (value > minimum if strict else value >= minimum)):
        relation = ">" if strict else "≥"
        raise InputError(f"{name}: {label} must be a number {relation} {minimum:g}, got {value!r}")
    return float(value)


def _odd_window(name: str, label: str, value: object, minimum: int = 3) -> int:
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= minimum and value % 2 == 1):
        raise InputError(f"{name}: {label} must be an odd integer ≥ {minimum}, got {value!r}")
    return value


def _size(name: str, label: str, value: object, minimum: int = 2) -> int:
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= minimum):
        raise InputError(f"{name}: {label} must be an integer ≥ {minimum}, got {value!r}")
    return value


# -------------------------------------------------------------------------------------------- shared pieces


def _first_differences(g: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences to the right and downwards on the common (h-1, w-1) grid."""
    centre = g[:, :-1, :-1]
    return g[:, :-1, 1:] - centre, g[:, 1:, :-1] - centre


def _sobel(g: Tensor) -> tuple[Tensor, Tensor]:
    """Sobel responses on the valid (h-2, w-2) grid, as [1, 2, 1] ⊗ [-1, 0, 1] shifted slices."""
    smooth_rows = g[:, :-2] + 2.0 * g[:, 1:-1] + g[:, 2:]
    gx = smooth_rows[:, :, 2:] - smooth_rows[:, :, :-2]
    diff_rows = g[:, 2:] - g[:, :-2]
    gy = diff_rows[:, :, :-2] + 2.0 * diff_rows[:, :, 1:-1] + diff_rows[:, :, 2:]
    return gx, gy


def _laplacian(g: Tensor) -> Tensor:
    """4-neighbour Laplacian on the valid (h-2, w-2) grid."""
    return g[:, :-2, 1:-1] + g[:, 2:, 1:-1] + g[:, 1:-1, :-2] + g[:, 1:-1, 2:] - 4.0 * g[:, 1:-1, 1:-1]


def _second_differences(g: Tensor, diagonal: bool) -> Tensor:
    """|2g - left - right| + |2g - up - down| (+ the two diagonals / √2), on the valid (h-2, w-2) grid."""
    centre2 = 2.0 * g[:, 1:-1, 1:-1]
    total = (centre2 - g[:, 1:-1, :-2] - g[:, 1:-1, 2:]).abs() + (centre2 - g[:, :-2, 1:-1] - g[:, 2:, 1:-1]).abs()
    if diagonal:
        diag = (centre2 - g[:, :-2, :-2] - g[:, 2:, 2:]).abs() + (centre2 - g[:, :-2, 2:] - g[:, 2:, :-2]).abs()
        total = total + _SQRT_HALF * diag
    return total


def _haar(g: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Undecimated orthonormal Haar level 1 on every 2 × 2 window: LL, LH, HL, HH, each (h-1, w-1)."""
    a, b, c, d = g[:, :-1, :-1], g[:, :-1, 1:], g[:, 1:, :-1], g[:, 1:, 1:]
    return 0.5 * (a + b + c + d), 0.5 * (a + b - c - d), 0.5 * (a - b + c - d), 0.5 * (a - b - c + d)


def _gaussian_gradients(g: Tensor, sigma: float) -> tuple[Tensor, Tensor, int]:
    """Gaussian-derivative responses (as :func:`gaussian_derivative`) on the valid grid, and the kernel radius."""
    smooth, slope = _gaussian_taps(sigma)
    gx = _correlate_valid(_correlate_valid(g, smooth, -2), slope, -1)
    gy = _correlate_valid(_correlate_valid(g, slope, -2), smooth, -1)
    return gx, gy, len(smooth) // 2


def _steered(gx: Tensor, gy: Tensor) -> Tensor:
    """max over θ ∈ {0°, 45°, …, 315°} of cos θ gx + sin θ gy = the largest |response| of four orientations."""
    diagonal = _SQRT_HALF * torch.maximum((gx + gy).abs(), (gx - gy).abs())
    return torch.maximum(torch.maximum(gx.abs(), gy.abs()), diagonal)


def _curvature_map(g: Tensor) -> Tensor:
    """|p0| + |p1| + |p2| + |p3| of the least-squares quadric on each 3 × 3 neighbourhood, (h-2, w-2)."""
    columns = g[:, :-2] + g[:, 1:-1] + g[:, 2:]  # sums over three rows, (h-2, w)
    left, middle, right = columns[:, :, :-2], columns[:, :, 1:-1], columns[:, :, 2:]
    rows = g[:, :, :-2] + g[:, :, 1:-1] + g[:, :, 2:]  # sums over three columns, (h, w-2)
    top, bottom = rows[:, :-2], rows[:, 2:]
    total = left + middle + right
    third = total / 3.0
    return ((right - left).abs() + (bottom - top).abs()) / 6.0 + (0.5 * (left + right) - third).abs() + (
        0.5 * (top + bottom) - third).abs()


def _helmli_map(g: Tensor, window: int, eps: float) -> Tensor:
    """max(μ/g, g/μ) - 1 with μ the window mean, on the valid grid; 0 where min(μ, g) ≤ eps."""
    mean = F.avg_pool2d(g[:, None], window, stride=1)[:, 0]
    r = window // 2
    centre = g[:, r : g.shape[1] - r, r : g.shape[2] - r]
    high, low = torch.maximum(mean, centre), torch.minimum(mean, centre)
    ok = low > eps
    return torch.where(ok, high / torch.where(ok, low, torch.ones_like(low)) - 1.0, torch.zeros_like(low))


def _vollath_maps(g: Tensor) -> tuple[Tensor, Tensor]:
    """g'(p) (g'(p+1) - g'(p+2)) along rows (h, w-2) and columns (h-2, w), g' = g minus the region's mean."""
    g0 = g - g.mean(dim=(-2, -1), keepdim=True)
    along_rows = g0[:, :, :-2] * (g0[:, :, 1:-1] - g0[:, :, 2:])
    along_cols = g0[:, :-2] * (g0[:, 1:-1] - g0[:, 2:])
    return along_rows, along_cols


def _dct_basis(size: int, rows: int, like: Tensor) -> Tensor:
    """The first ``rows`` orthonormal DCT-II basis vectors of length ``size``, (rows, size), like's dtype/device."""
    x = torch.arange(size, dtype=torch.float64)
    u = torch.arange(rows, dtype=torch.float64)[:, None]
    basis = torch.cos(math.pi * (2 * x + 1) * u / (2 * size)) * math.sqrt(2.0 / size)
    basis[0] = math.sqrt(1.0 / size)
    return basis.to(device=like.device, dtype=like.dtype)


def _blocks(g: Tensor, block: int) -> Tensor:
    """Non-overlapping block × block tiles from the top-left corner: (B, nh, nw, block, block)."""
    batch, h, w = g.shape
    nh, nw = h // block, w // block
    tiles = g[:, : nh * block, : nw * block].reshape(batch, nh, block, nw, block)
    return tiles.transpose(2, 3)


def _tiny(x: Tensor) -> float:
    return torch.finfo(x.dtype).tiny


# ---------------------------------------------------------------------------------------- gradient family


def gradient_energy(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Energy of gradient, GRAE (Subbarao et al. 1993).

    .. math::
        F = \frac{1}{(h-1)(w-1)} \sum_{i<h-1,\,j<w-1} (g_{i,j+1} - g_{i,j})^2 + (g_{i+1,j} - g_{i,j})^2.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 2 × 2.

    Returns:
        :math:`(B,)` scores, squared intensity per squared pixel.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 2 × 2.

    Example:
        >>> gradient_energy(torch.arange(4.0).repeat(1, 4, 1))  # unit ramp along rows
        tensor([1.])
    """
    region = _region(frames, roi, 2, "gradient_energy")
    if _opencv.usable(region):
        return _opencv.gradient_energy(region)
    ix, iy = _first_differences(_as_float(region)[:, 0])
    return (ix.square() + iy.square()).mean(dim=(-2, -1))


def thresholded_gradient(frames: Tensor, roi: Roi | str | None = None, threshold: float = 0.0) -> Tensor:
    r"""Thresholded absolute gradient, GRAT (Santos et al. 1997).

    .. math::
        F = \frac{1}{(h-1)(w-1)} \sum |I_x|\,[|I_x| > T] + |I_y|\,[|I_y| > T],\qquad
        I_x = g_{i,j+1} - g_{i,j},\ I_y = g_{i+1,j} - g_{i,j}.

    Santos et al. sum the horizontal term only; both are summed here so a frame and its transpose score alike
    (``fmeasure`` takes :math:`\max(|I_x|, |I_y|)` and divides by the count above threshold, which is undefined
    on a flat frame).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 2 × 2.
        threshold: :math:`T \ge 0`, intensity units.

    Returns:
        :math:`(B,)` scores, intensity per pixel.

    Raises:
        InputError: bad dtype, non-finite values, negative threshold, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 2 × 2.

    Example:
        >>> thresholded_gradient(torch.arange(4.0).repeat(1, 4, 1))
        tensor([1.])
    """
    t = _number("thresholded_gradient", "threshold", threshold)
    region = _region(frames, roi, 2, "thresholded_gradient")
    if t == 0 and _opencv.usable(region):
        return _opencv.thresholded_gradient(region)
    ix, iy = _first_differences(_as_float(region)[:, 0])
    ax, ay = ix.abs(), iy.abs()
    if t > 0:
        ax, ay = ax * (ax > t), ay * (ay > t)
    return (ax + ay).mean(dim=(-2, -1))


def squared_gradient(frames: Tensor, roi: Roi | str | None = None, threshold: float = 0.0) -> Tensor:
    r"""Squared gradient, GRAS (Eskicioglu & Fisher 1995; Santos et al. 1997).

    .. math::
        F = \frac{1}{(h-1)(w-1)} \sum m\,[m > T],\qquad m = \max(I_x^2, I_y^2),

    with :math:`I_x, I_y` the forward differences of :func:`gradient_energy`. The original squares the
    horizontal difference only; the larger of the two squared differences keeps both orientations (the
    treatment psmini's Brenner gives its two directions) and keeps GRAS distinct from GRAE, their sum.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 2 × 2.
        threshold: :math:`T \ge 0`, squared intensity units.

    Returns:
        :math:`(B,)` scores, squared intensity per squared pixel.

    Raises:
        InputError: bad dtype, non-finite values, negative threshold, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 2 × 2.

    Example:
        >>> squared_gradient(torch.arange(4.0).repeat(1, 4, 1))
        tensor([1.])
    """
    t = _number("squared_gradient", "threshold", threshold)
    region = _region(frames, roi, 2, "squared_gradient")
    if t == 0 and _opencv.usable(region):
        return _opencv.squared_gradient(region)
    ix, iy = _first_differences(_as_float(region)[:, 0])
    m = torch.maximum(ix.square(), iy.square())
    if t > 0:
        m = m * (m > t)
    return m.mean(dim=(-2, -1))


def tenengrad_variance(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Tenengrad variance, TENV (Pech-Pacheco et al. 2000).

    .. math::
        F = \frac{1}{N} \sum_{valid} (G - \bar G)^2,\qquad G = \sqrt{(g * S_x)^2 + (g * S_y)^2},

    the population variance of the Sobel gradient *magnitude* over the :math:`N = (h-2)(w-2)` pixels whose
    3 × 3 neighbourhood is inside the region (the paper's definition; ``fmeasure`` takes the variance of the
    squared magnitude, which weighs the strongest edges far more).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 3 × 3.

    Returns:
        :math:`(B,)` scores, squared intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 3 × 3.

    Example:
        >>> tenengrad_variance(torch.arange(16.0).reshape(1, 4, 4))  # a plane: constant magnitude
        tensor([0.])
    """
    region = _region(frames, roi, 3, "tenengrad_variance")
    if _opencv.usable(region):
        return _opencv.tenengrad_variance(region)
    gx, gy = _sobel(_as_float(region)[:, 0])
    magnitude = (gx.square() + gy.square()).clamp_min(_tiny(gx)).sqrt()
    return _population_variance(magnitude)


# --------------------------------------------------------------------------------------- Laplacian family


def laplacian_energy(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Energy of the Laplacian, LAPE (Subbarao et al. 1993).

    .. math::
        F = \frac{1}{(h-2)(w-2)} \sum_{valid} (g * L)^2,\qquad
        L = \begin{pmatrix} 0 & 1 & 0 \\ 1 & -4 & 1 \\ 0 & 1 & 0 \end{pmatrix},

    the 4-neighbour Laplacian of the paper and of :func:`variance_of_laplacian` (``fmeasure`` uses MATLAB's
    ``fspecial('laplacian', 0.2)``, a blend with the diagonal stencil).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 3 × 3.

    Returns:
        :math:`(B,)` scores, squared intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 3 × 3.

    Example:
        >>> laplacian_energy(torch.arange(9.0).reshape(1, 3, 3))  # a plane
        tensor([0.])
    """
    region = _region(frames, roi, 3, "laplacian_energy")
    if _opencv.usable(region):
        return _opencv.laplacian_energy(region)
    return _laplacian(_as_float(region)[:, 0]).square().mean(dim=(-2, -1))


def modified_laplacian(frames: Tensor, roi: Roi | str | None = None, threshold: float = 0.0) -> Tensor:
    r"""Sum-modified Laplacian, LAPM (Nayar & Nakagawa 1994), step 1.

    .. math::
        M = |2g_{i,j} - g_{i,j-1} - g_{i,j+1}| + |2g_{i,j} - g_{i-1,j} - g_{i+1,j}|,\qquad
        F = \frac{1}{(h-2)(w-2)} \sum_{valid} M\,[M \ge T].

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 3 × 3.
        threshold: :math:`T \ge 0`, intensity units (Nayar's threshold; 0 keeps every pixel).

    Returns:
        :math:`(B,)` scores, intensity units.

    Raises:
        InputError: bad dtype, non-finite values, negative threshold, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 3 × 3.

    Example:
        >>> modified_laplacian(torch.tensor([[[0.0, 1.0, 0.0]] * 3]))  # one ridge: |2 - 0 - 0|
        tensor([2.])
    """
    t = _number("modified_laplacian", "threshold", threshold)
    region = _region(frames, roi, 3, "modified_laplacian")
    if t == 0 and _opencv.usable(region):
        return _opencv.modified_laplacian(region, diagonal=False)
    m = _second_differences(_as_float(region)[:, 0], diagonal=False)
    if t > 0:
        m = m * (m >= t)
    return m.mean(dim=(-2, -1))


def diagonal_laplacian(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Diagonal Laplacian, LAPD (Thelen et al. 2009).

    .. math::
        F = \frac{1}{(h-2)(w-2)} \sum_{valid} |g * L_x| + |g * L_y| + \tfrac{1}{\sqrt 2}\,|g * L_{xy}|
            + \tfrac{1}{\sqrt 2}\,|g * L_{yx}|,

    :math:`L_x = (-1, 2, -1)` along rows, :math:`L_y` along columns, :math:`L_{xy}, L_{yx}` along the two
    diagonals (weighted :math:`1/\sqrt 2` for their longer step).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 3 × 3.

    Returns:
        :math:`(B,)` scores, intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 3 × 3.

    Example:
        >>> diagonal_laplacian(torch.ones(1, 5, 5))
        tensor([0.])
    """
    region = _region(frames, roi, 3, "diagonal_laplacian")
    if _opencv.usable(region):
        return _opencv.modified_laplacian(region, diagonal=True)
    return _second_differences(_as_float(region)[:, 0], diagonal=True).mean(dim=(-2, -1))


# ----------------------------------------------------------------------------------------- wavelet family


def wavelet_variance(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Variance of wavelet coefficients, WAVV (Yang & Nelson 2003): Haar, level 1, undecimated.

    .. math::
        F = \frac{1}{N} \sum_{windows} (LH - \overline{LH})^2 + (HL - \overline{HL})^2 + (HH - \overline{HH})^2

    with the detail coefficients of :func:`wavelet_sum` on every 2 × 2 window (:math:`N = (h-1)(w-1)`).
    ``fmeasure`` adds the variance of one band to the standard deviations of the other two; the paper sums
    three variances.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 2 × 2.

    Returns:
        :math:`(B,)` scores, squared intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 2 × 2.

    Example:
        >>> wavelet_variance(torch.rand(2, 8, 8)).shape
        torch.Size([2])
    """
    region = _region(frames, roi, 2, "wavelet_variance")
    if _opencv.usable(region):
        return _opencv.wavelet_variance(region)
    _, lh, hl, hh = _haar(_as_float(region)[:, 0])
    return _population_variance(lh) + _population_variance(hl) + _population_variance(hh)


def wavelet_ratio(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Ratio of wavelet coefficients, WAVR (Xie et al. 2006): Haar, level 1, undecimated.

    .. math::
        F = \frac{\sum (LH^2 + HL^2 + HH^2)}{\sum LL^2},

    the energy of the details over the energy of the approximation, over every 2 × 2 window; 0 for a black
    frame. Xie et al. sum details over several levels; one level keeps the support that of WAVS and WAVV
    (coarser levels answer to blur that finer ones have already seen).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 2 × 2.

    Returns:
        :math:`(B,)` dimensionless scores.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 2 × 2.

    Example:
        >>> wavelet_ratio(torch.tensor([[[0.0, 1.0], [0.0, 1.0]]]))  # HL = -1, LL = 1
        tensor([1.])
    """
    region = _region(frames, roi, 2, "wavelet_ratio")
    if _opencv.usable(region):
        return _opencv.wavelet_ratio(region)
    ll, lh, hl, hh = _haar(_as_float(region)[:, 0])
    high = (lh.square() + hl.square() + hh.square()).mean(dim=(-2, -1))
    return high / ll.square().mean(dim=(-2, -1)).clamp_min(_tiny(ll))


# -------------------------------------------------------------------------------------- statistics family


def absolute_central_moment(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Absolute central moment, ACMO (Shirvaikar 2004).

    .. math::
        F = \sum_k |k - \mu|\,P_k = \frac{1}{N} \sum_{pixels} |g - \mu|,\qquad \mu = \frac{1}{N} \sum g,

    with :math:`P_k` the normalised histogram: the histogram sum and the pixel mean are the same number, so the
    pixel form is used (exact for every dtype, differentiable). ``fmeasure`` converts to uint8 first.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``.

    Returns:
        :math:`(B,)` scores, intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape.

    Example:
        >>> absolute_central_moment(torch.tensor([[[0.0, 1.0], [0.0, 1.0]]]))
        tensor([0.5000])
    """
    region = _region(frames, roi, 1, "absolute_central_moment")
    if _opencv.usable(region):
        return _opencv.absolute_central_moment(region)
    g = _as_float(region)[:, 0]
    return (g - g.mean(dim=(-2, -1), keepdim=True)).abs().mean(dim=(-2, -1))


def gray_level_variance(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Gray-level variance, GLVA (Krotkov 1987).

    .. math::
        F = \frac{1}{N} \sum (g - \mu)^2

    over every pixel of the region (the variance, as in the paper; ``fmeasure`` returns the standard deviation,
    which ranks frames identically).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``.

    Returns:
        :math:`(B,)` scores, squared intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape.

    Example:
        >>> gray_level_variance(torch.tensor([[[0.0, 1.0], [0.0, 1.0]]]))
        tensor([0.2500])
    """
    region = _region(frames, roi, 1, "gray_level_variance")
    if _opencv.usable(region):
        return _opencv.gray_level_variance(region)
    return _population_variance(_as_float(region)[:, 0])


def gray_level_local_variance(frames: Tensor, roi: Roi | str | None = None, window: int = 3) -> Tensor:
    r"""Gray-level local variance, GLLV (Pech-Pacheco et al. 2000).

    .. math::
        V_{i,j} = \frac{1}{w^2} \sum_{window} (g - \mu_{i,j})^2,\qquad F = \frac{1}{N} \sum (V - \bar V)^2,

    the population variance, over every ``window`` × ``window`` window inside the region, of the local variance.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least ``window`` × ``window``.
        window: odd side of the local window, pixels (≥ 3).

    Returns:
        :math:`(B,)` scores, intensity units to the fourth power.

    Raises:
        InputError: bad dtype, non-finite values, a bad window, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than the window.

    Example:
        >>> gray_level_local_variance(torch.ones(1, 6, 6))
        tensor([0.])
    """
    window = _odd_window("gray_level_local_variance", "window", window)
    region = _region(frames, roi, window, "gray_level_local_variance")
    if _opencv.usable(region):
        return _opencv.gray_level_local_variance(region, window)
    g = _as_float(region)[:, 0]
    g = g - g.mean(dim=(-2, -1), keepdim=True)  # fewer digits lost in E[g²] - E[g]²
    mean = F.avg_pool2d(g[:, None], window, stride=1)[:, 0]
    local = (F.avg_pool2d(g[:, None].square(), window, stride=1)[:, 0] - mean.square()).clamp_min(0)
    return _population_variance(local)


def histogram_entropy(frames: Tensor, roi: Roi | str | None = None, bins: int = 256) -> Tensor:
    r"""Histogram entropy, HISE (Krotkov 1987), in bits.

    .. math::
        F = -\sum_{k} P_k \log_2 P_k,

    :math:`P_k` the fraction of the region's pixels at level :math:`k = \mathrm{round}(g\,(\mathrm{bins} - 1))`
    with intensities clamped to [0, 1] (uint8 frames: their own 256 levels with the default ``bins``; uint16
    and float frames are quantised to ``bins`` levels). A histogram has no useful derivative: the score never
    requires grad.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``.
        bins: number of gray levels (≥ 2).

    Returns:
        :math:`(B,)` scores, bits.

    Raises:
        InputError: bad dtype, non-finite values, a bad ``bins``, or a region outside the frame.
        ShapeError: frames of the wrong shape.

    Example:
        >>> histogram_entropy(torch.tensor([[[0.0, 1.0], [0.0, 1.0]]]))  # two levels, half each
        tensor([1.])
    """
    bins = _size("histogram_entropy", "bins", bins)
    region = _region(frames, roi, 1, "histogram_entropy")
    if _opencv.usable(region):
        return _opencv.histogram_entropy(region, bins)
    g = _as_float(region)[:, 0].detach()
    levels = _levels(g, bins)
    batch = g.shape[0]
    offsets = torch.arange(batch, device=g.device)[:, None] * bins
    counts = torch.bincount((levels.reshape(batch, -1) + offsets).reshape(-1), minlength=batch * bins)
    p = counts.reshape(batch, bins).to(g.dtype) / levels[0].numel()
    return -(p * torch.where(p > 0, p, torch.ones_like(p)).log2()).sum(dim=-1)


def _levels(g: Tensor, bins: int) -> Tensor:
    return (g.clamp(0, 1) * (bins - 1)).round().long()


def histogram_range(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Histogram range, HISR (Firestone et al. 1991).

    .. math::
        F = \max g - \min g

    over the region (the distance between the highest and lowest occupied histogram levels, without binning).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``.

    Returns:
        :math:`(B,)` scores, intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape.

    Example:
        >>> histogram_range(torch.tensor([[[0.2, 0.9], [0.5, 0.4]]]))
        tensor([0.7000])
    """
    region = _region(frames, roi, 1, "histogram_range")
    if _opencv.usable(region):
        return _opencv.histogram_range(region)
    g = _as_float(region)[:, 0]
    return g.amax(dim=(-2, -1)) - g.amin(dim=(-2, -1))


# ---------------------------------------------------------------------------------------------- DCT family


def dct_energy_ratio(frames: Tensor, roi: Roi | str | None = None, block: int = 8, eps: float = 1e-6) -> Tensor:
    r"""DCT energy ratio, DCTE (Shen & Chen 2006).

    On every non-overlapping ``block`` × ``block`` tile from the region's top-left corner (a partial tile at the
    right or bottom is not read), with :math:`C_{u,v}` its orthonormal 2-D DCT-II,

    .. math::
        F = \frac{1}{n_{tiles}} \sum_{tiles} \frac{\sum_{(u,v) \ne (0,0)} C_{u,v}^2}{C_{0,0}^2}
          = \frac{1}{n_{tiles}} \sum_{tiles} \frac{\sigma^2_{tile}}{\mu^2_{tile}}

    by Parseval (the AC energy of an orthonormal transform is the tile's sum of squared deviations, and
    :math:`C_{0,0}` its sum over ``block``), which is how it is computed; the tile mean is floored at ``eps``.
    ``fmeasure`` slides the 8 × 8 window over every pixel; the paper's tiles are JPEG's.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float (non-negative).
        roi: optional region ``(x, y, w, h)``, at least ``block`` × ``block``.
        block: tile side, pixels (≥ 2).
        eps: floor on a tile's mean, intensity units (> 0).

    Returns:
        :math:`(B,)` dimensionless scores.

    Raises:
        InputError: bad dtype, non-finite values, bad parameters, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than one tile.

    Example:
        >>> dct_energy_ratio(torch.tensor([[[0.0, 1.0], [0.0, 1.0]]]), block=2)  # σ² 0.25 over μ² 0.25
        tensor([1.])
    """
    block = _size("dct_energy_ratio", "block", block)
    eps = _number("dct_energy_ratio", "eps", eps, strict=True)
    region = _region(frames, roi, block, "dct_energy_ratio")
    if _opencv.usable(region):
        return _opencv.dct_energy_ratio(region, block, eps)
    tiles = _blocks(_as_float(region)[:, 0], block)
    mean = tiles.mean(dim=(-2, -1), keepdim=True)
    variance = (tiles - mean).square().mean(dim=(-2, -1))
    return (variance / mean[..., 0, 0].clamp_min(eps).square()).mean(dim=(-2, -1))


_REDUCED = ((0, 1), (1, 0), (1, 1), (0, 2), (2, 0))


def dct_reduced_energy_ratio(frames: Tensor, roi: Roi | str | None = None, block: int = 8,
                             eps: float = 1e-6) -> Tensor:
    r"""DCT reduced energy ratio, DCTR (Lee et al. 2009).

    On every non-overlapping ``block`` × ``block`` tile (as in :func:`dct_energy_ratio`), with :math:`C_{u,v}`
    its orthonormal 2-D DCT-II,

    .. math::
        F = \frac{1}{n_{tiles}} \sum_{tiles}
            \frac{C_{0,1}^2 + C_{1,0}^2 + C_{1,1}^2 + C_{0,2}^2 + C_{2,0}^2}{C_{0,0}^2},

    the five lowest AC frequencies (a set closed under transposition, so both orientations score alike); the
    DC term is floored at ``block · eps`` (a tile mean of ``eps``).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float (non-negative).
        roi: optional region ``(x, y, w, h)``, at least ``block`` × ``block``.
        block: tile side, pixels (≥ 3).
        eps: floor on a tile's mean, intensity units (> 0).

    Returns:
        :math:`(B,)` dimensionless scores.

    Raises:
        InputError: bad dtype, non-finite values, bad parameters, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than one tile.

    Example:
        >>> dct_reduced_energy_ratio(torch.zeros(1, 8, 8))  # black: the DC floor keeps it finite
        tensor([0.])
    """
    block = _size("dct_reduced_energy_ratio", "block", block, minimum=3)
    eps = _number("dct_reduced_energy_ratio", "eps", eps, strict=True)
    region = _region(frames, roi, block, "dct_reduced_energy_ratio")
    if _opencv.usable(region):
        return _opencv.dct_reduced_energy_ratio(region, block, eps)
    tiles = _blocks(_as_float(region)[:, 0], block)
    basis = _dct_basis(block, 3, tiles)
    coefficients = basis @ tiles @ basis.T  # (B, nh, nw, 3, 3): rows u (vertical), columns v (horizontal)
    low = sum(coefficients[..., u, v].square() for u, v in _REDUCED)
    dc = coefficients[..., 0, 0].clamp_min(block * eps)
    return (low / dc.square()).mean(dim=(-2, -1))


# ------------------------------------------------------------------------------------ miscellaneous family


def curvature(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Image curvature, CURV (Helmli & Scherer 2001).

    Each 3 × 3 neighbourhood (offsets :math:`x, y \in \{-1, 0, 1\}`) is fitted in least squares by
    :math:`f(x, y) = p_0 x + p_1 y + p_2 x^2 + p_3 y^2 + c`, which gives

    .. math::
        p_0 = \tfrac{1}{6} \sum x g,\quad p_1 = \tfrac{1}{6} \sum y g,\quad
        p_2 = \tfrac{1}{2} \sum x^2 g - \tfrac{1}{3} \sum g,\quad p_3 = \tfrac{1}{2} \sum y^2 g - \tfrac{1}{3} \sum g,

    .. math::
        F = \frac{1}{(h-2)(w-2)} \sum_{valid} |p_0| + |p_1| + |p_2| + |p_3|.

    The constant :math:`c` is fitted (``fmeasure`` fits without it, so its :math:`p_2, p_3` change with the
    brightness and an inverted frame scores differently; its :math:`p_3` also reuses :math:`p_2`'s kernel).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 3 × 3.

    Returns:
        :math:`(B,)` scores, intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 3 × 3.

    Example:
        >>> x = torch.arange(-1.0, 2.0)
        >>> round(float(curvature((x[None] ** 2).expand(3, 3)[None])), 6)  # f = x²: p2 = 1
        1.0
    """
    region = _region(frames, roi, 3, "curvature")
    if _opencv.usable(region):
        return _opencv.curvature(region)
    return _curvature_map(_as_float(region)[:, 0]).mean(dim=(-2, -1))


def helmli_mean(frames: Tensor, roi: Roi | str | None = None, window: int = 3, eps: float = 1e-6) -> Tensor:
    r"""Helmli and Scherer's mean method, HELM (Helmli & Scherer 2001).

    .. math::
        R_{i,j} = \begin{cases} \mu_{i,j} / g_{i,j} & \mu_{i,j} \ge g_{i,j} \\
                                g_{i,j} / \mu_{i,j} & \text{otherwise} \end{cases},\qquad
        F = \frac{1}{N} \sum_{valid} (R - 1),

    :math:`\mu` the mean of the ``window`` × ``window`` neighbourhood, over the pixels whose window is inside
    the region. The paper sums :math:`R`; subtracting 1 (which orders frames identically) makes a flat frame
    score 0. Pixels where :math:`\min(\mu, g) \le` ``eps`` contribute 0 (``fmeasure`` sets :math:`R = 1`
    where :math:`g = 0`). A ratio of intensities: inverting a frame changes its score.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float (non-negative).
        roi: optional region ``(x, y, w, h)``, at least ``window`` × ``window``.
        window: odd side of the mean window, pixels (≥ 3).
        eps: intensity at or below which a pixel is not scored (> 0).

    Returns:
        :math:`(B,)` dimensionless scores.

    Raises:
        InputError: bad dtype, non-finite values, bad parameters, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than the window.

    Example:
        >>> helmli_mean(torch.full((1, 5, 5), 0.5))
        tensor([0.])
    """
    window = _odd_window("helmli_mean", "window", window)
    eps = _number("helmli_mean", "eps", eps, strict=True)
    region = _region(frames, roi, window, "helmli_mean")
    if _opencv.usable(region):
        return _opencv.helmli_mean(region, window, eps)
    return _helmli_map(_as_float(region)[:, 0], window, eps).mean(dim=(-2, -1))


def steerable_filters(frames: Tensor, roi: Roi | str | None = None, sigma: float = 1.0) -> Tensor:
    r"""Steerable filters, SFIL (Minhas et al. 2009).

    The Gaussian-derivative responses :math:`g_x, g_y` of :func:`gaussian_derivative` are steered to
    :math:`R_\theta = g_x \cos\theta + g_y \sin\theta` for :math:`\theta \in \{0°, 45°, \dots, 315°\}`, and

    .. math::
        F = \frac{1}{N} \sum_{valid} \max_\theta R_\theta
          = \frac{1}{N} \sum_{valid} \max\big(|g_x|, |g_y|,
            \tfrac{|g_x + g_y|}{\sqrt 2}, \tfrac{|g_x - g_y|}{\sqrt 2}\big)

    (opposite angles give opposite responses, so the maximum over eight angles is the largest absolute
    response of four). ``fmeasure`` ties :math:`\sigma` to its window; here it is a parameter.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least (2r+1) × (2r+1), :math:`r = \lceil 3\sigma \rceil`.
        sigma: the Gaussian's standard deviation, pixels (> 0).

    Returns:
        :math:`(B,)` scores, intensity per pixel.

    Raises:
        InputError: bad dtype, non-finite values, non-positive sigma, or a region outside the frame.
        ShapeError: frames of the wrong shape or too small for the kernel.

    Example:
        >>> ramp = torch.arange(16.0).repeat(1, 16, 1)
        >>> round(float(steerable_filters(ramp)), 5)
        1.0
    """
    sigma = _number("steerable_filters", "sigma", sigma, strict=True)
    radius = max(1, math.ceil(3.0 * sigma))
    region = _region(frames, roi, 2 * radius + 1, "steerable_filters")
    if _opencv.usable(region):
        return _opencv.steerable_filters(region, sigma)
    gx, gy, _ = _gaussian_gradients(_as_float(region)[:, 0], sigma)
    return _steered(gx, gy).mean(dim=(-2, -1))


def spatial_frequency(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Spatial frequency, SFRQ (Eskicioglu & Fisher 1995).

    .. math::
        F = \sqrt{\frac{1}{h(w-1)} \sum (g_{i,j+1} - g_{i,j})^2 + \frac{1}{(h-1)w} \sum (g_{i+1,j} - g_{i,j})^2},

    the row frequency and the column frequency, each over every difference inside the region (``fmeasure``
    averages the per-pixel gradient magnitude instead).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 2 × 2.

    Returns:
        :math:`(B,)` scores, intensity per pixel.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 2 × 2.

    Example:
        >>> spatial_frequency(torch.arange(4.0).repeat(1, 4, 1))
        tensor([1.])
    """
    region = _region(frames, roi, 2, "spatial_frequency")
    if _opencv.usable(region):
        return _opencv.spatial_frequency(region)
    g = _as_float(region)[:, 0]
    rows = (g[:, :, 1:] - g[:, :, :-1]).square().mean(dim=(-2, -1))
    cols = (g[:, 1:] - g[:, :-1]).square().mean(dim=(-2, -1))
    return (rows + cols).clamp_min(_tiny(g)).sqrt()


def vollath_f4(frames: Tensor, roi: Roi | str | None = None) -> Tensor:
    r"""Vollath's autocorrelation F4, VOLA (Vollath 1987; Santos et al. 1997).

    .. math::
        F = \frac{1}{h(w-2)} \sum g'_{i,j} (g'_{i,j+1} - g'_{i,j+2})
          + \frac{1}{(h-2)w} \sum g'_{i,j} (g'_{i+1,j} - g'_{i+2,j}),\qquad g' = g - \mu,

    the lag-1 minus the lag-2 autocorrelation along rows and along columns (the original: rows only). The
    region's mean :math:`\mu` is removed first: Vollath's difference cancels the mean except for border terms,
    which would otherwise make a frame and its inverse score differently.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        roi: optional region ``(x, y, w, h)``, at least 3 × 3.

    Returns:
        :math:`(B,)` scores, squared intensity units.

    Raises:
        InputError: bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape or smaller than 3 × 3.

    Example:
        >>> vollath_f4(torch.ones(1, 4, 4))
        tensor([0.])
    """
    region = _region(frames, roi, 3, "vollath_f4")
    if _opencv.usable(region):
        return _opencv.vollath_f4(region)
    along_rows, along_cols = _vollath_maps(_as_float(region)[:, 0])
    return along_rows.mean(dim=(-2, -1)) + along_cols.mean(dim=(-2, -1))


# ------------------------------------------------------------------------------------ local (focus volume)


def _place(values: Tensor, top: int, left: int, height: int, width: int) -> Tensor:
    """A map of the valid grid, (B, h, w), at offset (top, left) of a (B, height, width) frame, edges replicated."""
    h, w = values.shape[-2:]
    padded = F.pad(values[:, None], (left, width - w - left, top, height - h - top), mode="replicate")
    return padded[:, 0]


def _box(x: Tensor, window: int) -> Tensor:
    """Mean over the window × window neighbourhood of every pixel, edges replicated; same shape (B, H, W)."""
    if window == 1:
        return x
    return _box_channels(x[:, None], window)[:, 0]


def _box_channels(x: Tensor, window: int) -> Tensor:
    """:func:`_box` of (B, C, H, W), separable, by running sums: a cumulative sum along each axis and the
    difference of two of its slices (2 reads per pixel whatever the window; ``avg_pool2d`` measured 5–10×
    slower on the CPU). Sums run in float64 so float32 input keeps its precision on wide frames."""
    before = window // 2
    after = window - 1 - before
    padded = F.pad(x, (before, after, before, after), mode="replicate")
    wide = padded if padded.dtype == torch.float64 else padded.double()
    for dim in (-2, -1):
        running = F.pad(wide.cumsum(dim), (1, 0) if dim == -1 else (0, 0, 1, 0))
        length = running.shape[dim] - window
        wide = running.narrow(dim, window, length) - running.narrow(dim, 0, length)
    return (wide / (window * window)).to(x.dtype)


def _local_variance(x: Tensor, window: int) -> Tensor:
    x = x - x.mean(dim=(-2, -1), keepdim=True)
    mean = _box(x, window)
    return (_box(x.square(), window) - mean.square()).clamp_min(0)


def _max_pool(x: Tensor, window: int) -> Tensor:
    before = window // 2
    after = window - 1 - before
    padded = F.pad(x[:, None], (before, after, before, after), mode="replicate")
    return F.max_pool2d(padded, window, stride=1)[:, 0]


def _local_entropy(g: Tensor, window: int, bins: int) -> Tensor:
    """Entropy of each window's histogram: the window fraction of every gray level by one box filter per chunk of
    levels (one-hot channels), over the levels present only."""
    levels = _levels(g.detach(), bins)
    present = torch.unique(levels)
    total = torch.zeros_like(g)
    chunk = max(1, min(64, (1 << 24) // max(1, levels.numel())))  # bounds the one-hot block to ~16M values
    for start in range(0, present.numel(), chunk):
        values = present[start : start + chunk]
        onehot = (levels[:, None] == values[None, :, None, None]).to(g.dtype)  # (B, C, H, W)
        p = _box_channels(onehot, window)
        total = total - (p * torch.where(p > 0, p, torch.ones_like(p)).log2()).sum(dim=1)
    return total.detach()


def _local_dct_reduced(g: Tensor, window: int, eps: float) -> Tensor:
    before = window // 2
    after = window - 1 - before
    padded = F.pad(g[:, None], (before, after, before, after), mode="replicate")[:, 0]
    basis = _dct_basis(window, 3, g).tolist()
    rows = [_correlate_valid(padded, basis[u], -2) for u in range(3)]  # along columns: vertical frequency u
    coefficient = {(u, v): _correlate_valid(rows[u], basis[v], -1) for u in range(3) for v in range(3) if u + v <= 2}
    low = sum(coefficient[key].square() for key in _REDUCED)
    return low / coefficient[(0, 0)].clamp_min(window * eps).square()


def _volume(code: str, g: Tensor, window: int, params: dict) -> Tensor:
    """The local focus measure ``code`` of float frames g (B, H, W): (B, H, W)."""
    height, width = g.shape[-2:]

    def boxed(values: Tensor, offset: int) -> Tensor:
        return _box(_place(values, offset, offset, height, width), window)

    if code == "BREN":
        centre = g[:, :-2, :-2]
        return boxed(torch.maximum((g[:, :-2, 2:] - centre).square(), (g[:, 2:, :-2] - centre).square()), 1)
    if code == "CONT":
        centre = g[:, 1:-1, 1:-1]
        total = torch.zeros_like(centre)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                if du or dv:
                    total = total + (centre - g[:, 1 + du : height - 1 + du, 1 + dv : width - 1 + dv]).abs()
        return boxed(total, 1)
    if code == "CURV":
        return boxed(_curvature_map(g), 1)
    if code in ("GDER", "SFIL"):
        gx, gy, radius = _gaussian_gradients(g, params.get("sigma", 1.0))
        values = gx.square() + gy.square() if code == "GDER" else _steered(gx, gy)
        return boxed(values, radius)
    if code in ("GRAE", "GRAT", "GRAS"):
        ix, iy = _first_differences(g)
        t = params.get("threshold", 0.0)
        if code == "GRAE":
            values = ix.square() + iy.square()
        elif code == "GRAT":
            ax, ay = ix.abs(), iy.abs()
            values = ax * (ax > t) + ay * (ay > t) if t > 0 else ax + ay
        else:
            values = torch.maximum(ix.square(), iy.square())
            values = values * (values > t) if t > 0 else values
        return boxed(values, 0)
    if code in ("TENG", "TENV"):
        gx, gy = _sobel(g)
        energy = gx.square() + gy.square()
        t = params.get("threshold", 0.0)
        if code == "TENG":
            return boxed(energy * (energy > t) if t > 0 else energy, 1)
        return _local_variance(_place(energy.clamp_min(_tiny(g)).sqrt(), 1, 1, height, width), window)
    if code == "LAPE":
        return boxed(_laplacian(g).square(), 1)
    if code == "LAPV":
        return _local_variance(_place(_laplacian(g), 1, 1, height, width), window)
    if code in ("LAPM", "LAPD"):
        values = _second_differences(g, diagonal=code == "LAPD")
        t = params.get("threshold", 0.0)
        return boxed(values * (values >= t) if t > 0 else values, 1)
    if code in ("WAVS", "WAVV", "WAVR"):
        ll, lh, hl, hh = _haar(g)
        if code == "WAVS":
            return boxed(lh.abs() + hl.abs() + hh.abs(), 0)
        if code == "WAVV":
            first, second, third = (_local_variance(_place(band, 0, 0, height, width), window) for band in (lh, hl, hh))
            return first + second + third
        high = boxed(lh.square() + hl.square() + hh.square(), 0)
        return high / boxed(ll.square(), 0).clamp_min(_tiny(g))
    if code == "ACMO":
        return _box((g - _box(g, window)).abs(), window)
    if code == "GLVA":
        return _local_variance(g, window)
    if code == "GLLV":
        inner = params.get("window", 3)
        return _local_variance(_local_variance(g, inner), window)
    if code == "GLVN":
        return _local_variance(g, window) / _box(g, window).clamp_min(params.get("eps", 1e-6))
    if code == "HISE":
        return _local_entropy(g, window, params.get("bins", 256))
    if code == "HISR":
        return _max_pool(g, window) + _max_pool(-g, window)
    if code == "DCTE":
        return _local_variance(g, window) / _box(g, window).clamp_min(params.get("eps", 1e-6)).square()
    if code == "DCTR":
        return _local_dct_reduced(g, window, params.get("eps", 1e-6))
    if code == "HELM":
        inner = params.get("window", 3)
        return boxed(_helmli_map(g, inner, params.get("eps", 1e-6)), inner // 2)
    if code == "SFRQ":
        rows = _box(_place((g[:, :, 1:] - g[:, :, :-1]).square(), 0, 0, height, width), window)
        cols = _box(_place((g[:, 1:] - g[:, :-1]).square(), 0, 0, height, width), window)
        return (rows + cols).clamp_min(_tiny(g)).sqrt()
    if code == "VOLA":
        along_rows, along_cols = _vollath_maps(g)
        return _box(_place(along_rows, 0, 1, height, width), window) + _box(_place(along_cols, 1, 0, height, width),
                                                                             window)
    raise InputError(f"no local form for focus operator {code!r}")  # unreachable: every code is listed above


# ----------------------------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class FocusOperator:
    """One operator of Pertuz et al. (2013): its code, family, name, reference and global function.

    Attributes:
        code: Pertuz's four-letter code, e.g. ``"TENG"``.
        family: ``"gradient"``, ``"laplacian"``, ``"wavelet"``, ``"statistics"``, ``"dct"`` or ``"misc"``.
        title: the operator's name.
        reference: its original paper, short form.
        measure: the global function ``measure(frames, roi=None, **params) -> (B,)``.
        params: the names of its parameters (besides ``frames`` and ``roi``).
    """

    code: str
    family: str
    title: str
    reference: str
    measure: Callable[..., Tensor]
    params: tuple[str, ...] = ()


FOCUS_OPERATORS: dict[str, FocusOperator] = {
    op.code: op
    for op in (
        FocusOperator("GDER", "gradient", "Gaussian derivative", "Geusebroek et al. 2000", gaussian_derivative,
                      ("sigma",)),
        FocusOperator("GRAE", "gradient", "Energy of gradient", "Subbarao et al. 1993", gradient_energy),
        FocusOperator("GRAT", "gradient", "Thresholded absolute gradient", "Santos et al. 1997",
                      thresholded_gradient, ("threshold",)),
        FocusOperator("GRAS", "gradient", "Squared gradient", "Eskicioglu & Fisher 1995", squared_gradient,
                      ("threshold",)),
        FocusOperator("TENG", "gradient", "Tenengrad", "Krotkov 1987", tenengrad, ("threshold",)),
        FocusOperator("TENV", "gradient", "Tenengrad variance", "Pech-Pacheco et al. 2000", tenengrad_variance),
        FocusOperator("LAPE", "laplacian", "Energy of Laplacian", "Subbarao et al. 1993", laplacian_energy),
        FocusOperator("LAPM", "laplacian", "Modified Laplacian", "Nayar & Nakagawa 1994", modified_laplacian,
                      ("threshold",)),
        FocusOperator("LAPV", "laplacian", "Variance of Laplacian", "Pech-Pacheco et al. 2000",
                      variance_of_laplacian),
        FocusOperator("LAPD", "laplacian", "Diagonal Laplacian", "Thelen et al. 2009", diagonal_laplacian),
        FocusOperator("WAVS", "wavelet", "Sum of wavelet coefficients", "Yang & Nelson 2003", wavelet_sum),
        FocusOperator("WAVV", "wavelet", "Variance of wavelet coefficients", "Yang & Nelson 2003",
                      wavelet_variance),
        FocusOperator("WAVR", "wavelet", "Ratio of wavelet coefficients", "Xie et al. 2006", wavelet_ratio),
        FocusOperator("ACMO", "statistics", "Absolute central moment", "Shirvaikar 2004",
                      absolute_central_moment),
        FocusOperator("GLVA", "statistics", "Gray-level variance", "Krotkov 1987", gray_level_variance),
        FocusOperator("GLLV", "statistics", "Gray-level local variance", "Pech-Pacheco et al. 2000",
                      gray_level_local_variance, ("window",)),
        FocusOperator("GLVN", "statistics", "Normalized gray-level variance", "Groen et al. 1985",
                      normalized_variance, ("eps",)),
        FocusOperator("HISE", "statistics", "Histogram entropy", "Krotkov 1987", histogram_entropy, ("bins",)),
        FocusOperator("HISR", "statistics", "Histogram range", "Firestone et al. 1991", histogram_range),
        FocusOperator("DCTE", "dct", "DCT energy ratio", "Shen & Chen 2006", dct_energy_ratio,
                      ("block", "eps")),
        FocusOperator("DCTR", "dct", "DCT reduced energy ratio", "Lee et al. 2009", dct_reduced_energy_ratio,
                      ("block", "eps")),
        FocusOperator("BREN", "misc", "Brenner's measure", "Brenner et al. 1976", brenner),
        FocusOperator("CONT", "misc", "Image contrast", "Nanda & Cutler 2001", image_contrast),
        FocusOperator("CURV", "misc", "Image curvature", "Helmli & Scherer 2001", curvature),
        FocusOperator("HELM", "misc", "Helmli's mean method", "Helmli & Scherer 2001", helmli_mean,
                      ("window", "eps")),
        FocusOperator("SFIL", "misc", "Steerable filters", "Minhas et al. 2009", steerable_filters, ("sigma",)),
        FocusOperator("SFRQ", "misc", "Spatial frequency", "Eskicioglu & Fisher 1995", spatial_frequency),
        FocusOperator("VOLA", "misc", "Vollath's autocorrelation", "Vollath 1987", vollath_f4),
    )
}
"""The 28 operators of Pertuz et al. (2013) by code, in the paper's order of families."""

FOCUS_FAMILIES: dict[str, tuple[str, ...]] = {
    family: tuple(code for code, op in FOCUS_OPERATORS.items() if op.family == family)
    for family in ("gradient", "laplacian", "wavelet", "statistics", "dct", "misc")
}
"""Operator codes by family."""

_LEGACY = {
    "brenner": "BREN",
    "contrast": "CONT",
    "wavelet": "WAVS",
    "gaussian": "GDER",
    "tenengrad": "TENG",
    "laplacian": "LAPV",
    "variance": "GLVN",
}

FOCUS_MEASURES: dict[str, Callable[..., Tensor]] = {
    name: FOCUS_OPERATORS[code].measure for name, code in _LEGACY.items()
}
"""psmini's seven focus measures by name: ``brenner`` (the seed's), ``contrast``, ``wavelet``, ``gaussian``,
``tenengrad``, ``laplacian`` (variance of the Laplacian), ``variance`` (normalised gray-level variance). Every
function that takes a measure name also takes any operator code of :data:`FOCUS_OPERATORS`, in either case
(``"LAPM"``, ``"teng"``)."""

FOCUS_NAMES: tuple[str, ...] = (*_LEGACY, *(code.lower() for code in FOCUS_OPERATORS))
"""Every name :func:`focus_measure` accepts: psmini's seven and the 28 lower-case operator codes."""


def _code(name: str) -> str:
    """Pertuz's code of a measure name (a psmini name or a code in either case)."""
    if isinstance(name, str):
        if name in _LEGACY:
            return _LEGACY[name]
        if name.upper() in FOCUS_OPERATORS:
            return name.upper()
    raise InputError(f"unknown focus measure {name!r}; expected one of {', '.join(FOCUS_MEASURES)} or an "
                     f"operator code ({', '.join(FOCUS_OPERATORS)})")


def _lookup(name: str) -> Callable[..., Tensor]:
    return FOCUS_OPERATORS[_code(name)].measure


def focus_measure(frames: Tensor, name: str = "brenner", roi: Roi | str | None = None, **params: float) -> Tensor:
    """Score each frame of a batch with the focus measure ``name`` (see :data:`FOCUS_MEASURES`).

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float.
        name: a key of :data:`FOCUS_MEASURES` or an operator code of :data:`FOCUS_OPERATORS` (``"TENG"``).
        roi: optional region ``(x, y, w, h)`` in pixels.
        **params: the measure's own parameters (``sigma`` for ``gaussian``, ``threshold`` for ``tenengrad``, …;
            see :attr:`FocusOperator.params`).

    Returns:
        :math:`(B,)` scores, larger is sharper.

    Raises:
        InputError: an unknown name or parameter, bad dtype, non-finite values, or a region outside the frame.
        ShapeError: frames of the wrong shape.

    Example:
        >>> focus_measure(torch.rand(4, 1, 32, 32), "tenengrad").shape
        torch.Size([4])
        >>> focus_measure(torch.rand(4, 32, 32), "LAPD").shape
        torch.Size([4])
    """
    code = _code(name)
    unknown = set(params) - set(FOCUS_OPERATORS[code].params)
    if unknown:
        raise InputError(f"focus measure {name!r} takes no parameter {', '.join(sorted(unknown))}; "
                         f"its parameters: {', '.join(FOCUS_OPERATORS[code].params) or 'none'}")
    return FOCUS_OPERATORS[code].measure(frames, roi, **params)


def focus_volume(frames: Tensor, name: str = "tenengrad", window: int = 9, **params: float) -> Tensor:
    r"""The local form of a focus measure: a focus value for every pixel of every frame.

    Each operator's per-pixel response (the summand of its global formula: squared gradient, absolute
    Laplacian, wavelet details, …) is averaged over the ``window`` × ``window`` neighbourhood of each pixel;
    operators defined by a statistic of the frame take that statistic over the window instead: the local
    variance (GLVA, LAPV of the Laplacian, TENV of the gradient magnitude, WAVV of each band, GLLV of the local
    variance), the local variance over the local mean (GLVN) or its square (DCTE, by Parseval: the energy ratio
    of the window's DCT), the local range (HISR), the entropy of the window's histogram (HISE), the five low
    DCT coefficients of the window (DCTR), and for ACMO the window mean of :math:`|g - \mu_{window}|`. Borders
    are replicated, so the volume has the frames' size.

    Args:
        frames: :math:`(B, H, W)` or :math:`(B, 1, H, W)`, uint8, uint16 or float: a focus stack is a batch.
        name: a measure name or operator code (see :func:`focus_measure`).
        window: side of the neighbourhood, pixels (≥ 1; 3 or more for DCTR).
        **params: the operator's own parameters (for GLLV and HELM ``window`` is their inner window: pass it
            as ``inner_window``).

    Returns:
        :math:`(B, H, W)` focus values (float32 for integer input, the input's dtype otherwise).

    Raises:
        InputError: an unknown name or parameter, a bad window, bad dtype or non-finite values.
        ShapeError: frames of the wrong shape or too small for the operator.

    Example:
        >>> focus_volume(torch.rand(5, 32, 40), "LAPM", window=7).shape
        torch.Size([5, 32, 40])
    """
    code = _code(name)
    if "inner_window" in params:
        params = dict(params)
        params["window"] = params.pop("inner_window")
    unknown = set(params) - set(FOCUS_OPERATORS[code].params)
    if unknown:
        raise InputError(f"focus operator {code} takes no parameter {', '.join(sorted(unknown))}; "
                         f"its parameters: {', '.join(FOCUS_OPERATORS[code].params) or 'none'}")
    minimum = 3 if code == "DCTR" else 1
    window = _size("focus_volume", "window", window, minimum=minimum)
    # the global function validates the parameters and the frame size on a small crop (cheap)
    small = _region(frames, None, 1, "focus_volume")
    FOCUS_OPERATORS[code].measure(small[:1], None, **params)
    return _volume(code, _as_float(small)[:, 0], window, params)


class FocusMeasure(nn.Module):
    """A focus measure with its name, region and parameters fixed; ``forward(frames) -> (B,)`` scores.

    Args:
        name: a key of :data:`FOCUS_MEASURES` or an operator code.
        roi: optional region ``(x, y, w, h)`` in pixels, checked against each batch.
        **params: the measure's own parameters.

    Raises:
        InputError: an unknown name.

    Example:
        >>> measure = FocusMeasure("brenner", roi=(0, 0, 16, 16))
        >>> measure(torch.rand(3, 32, 32)).shape
        torch.Size([3])
    """

    def __init__(self, name: str = "brenner", roi: Roi | str | None = None, **params: float) -> None:
        super().__init__()
        self.func = _lookup(name)
        self.name, self.roi, self.params = name, roi, params

    def forward(self, frames: Tensor) -> Tensor:
        return self.func(frames, self.roi, **self.params)

    def extra_repr(self) -> str:
        return f"name={self.name!r}, roi={self.roi!r}" + "".join(f", {k}={v!r}" for k, v in self.params.items())


class FocusVolume(nn.Module):
    """The local form of a focus measure with its window and parameters fixed; ``forward(frames) -> (B, H, W)``.

    Args:
        name: a measure name or operator code.
        window: side of the neighbourhood, pixels.
        **params: the operator's own parameters (see :func:`focus_volume`).

    Raises:
        InputError: an unknown name.

    Example:
        >>> FocusVolume("TENG", window=5)(torch.rand(3, 16, 16)).shape
        torch.Size([3, 16, 16])
    """

    def __init__(self, name: str = "tenengrad", window: int = 9, **params: float) -> None:
        super().__init__()
        _code(name)
        self.name, self.window, self.params = name, window, params

    def forward(self, frames: Tensor) -> Tensor:
        return focus_volume(frames, self.name, self.window, **self.params)

    def extra_repr(self) -> str:
        return f"name={self.name!r}, window={self.window}" + "".join(f", {k}={v!r}" for k, v in self.params.items())
