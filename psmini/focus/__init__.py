r"""Focus measures: how sharp each frame of a batch is — every operator of Pertuz et al. (2013), global and local.

Every measure takes a batch of gray frames, shape :math:`(B, H, W)` or :math:`(B, 1, H, W)`, as uint8 or uint16
(scaled to :math:`[0, 1]` by the dtype's maximum, 255 or 65535) or floating point (used as is), an optional region
of interest ``roi = (x, y, w, h)`` in pixels (column, row, width, height; only pixels inside it are read), and
returns a :math:`(B,)` tensor (float32 for integer input, the input's dtype otherwise): larger is sharper.
:func:`focus_volume` gives the local form of every operator, a focus value per pixel over a window, for shape
from focus (:func:`psmini.sff.depth_from_focus`).

- :mod:`psmini.focus.measures`: psmini's first seven measures (Brenner — the seed's —, image contrast, wavelet
  sum, Gaussian derivative, Tenengrad, variance of the Laplacian, normalised variance) and the shared guards;
- :mod:`psmini.focus.operators`: the other 21 operators of Pertuz, Puig and García, "Analysis of focus measure
  operators for shape-from-focus", Pattern Recognition 46 (2013), the registry :data:`FOCUS_OPERATORS` (by
  Pertuz's code; :data:`FOCUS_MEASURES` keeps psmini's seven names, and every function taking a name takes a
  code too), :func:`focus_measure` and :func:`focus_volume`;
- :mod:`psmini.focus._opencv`: OpenCV fast paths, taken for CPU frames (uint8, uint16, float32) that need no
  gradient; the torch path serves autograd, float64 and CUDA, and gives the same value.

All global measures are evaluated on the *valid* part of the region: a pixel contributes only when every
neighbour its formula reads lies inside the region, so nothing depends on padding and a measure over a region
equals the measure of the cropped frame. Every formula is symmetric in edge polarity (squares or absolute
values of differences, or central moments) and in orientation (transposing a square region leaves the score
unchanged), a property public ports of these measures often lack (see FIELD_NOTES, "Focus measures").
Operators normalised by brightness (GLVN, WAVR, DCTE, DCTR, HELM) change with inversion unless the mean stays.

Float input is differentiable with respect to the frames (piecewise smooth), except HISE (a histogram).

Example:
    >>> import torch
    >>> frames = torch.rand(3, 64, 64)
    >>> focus_measure(frames, "brenner").shape, focus_measure(frames, "LAPM").shape
    (torch.Size([3]), torch.Size([3]))
    >>> sorted(FOCUS_FAMILIES)
    ['dct', 'gradient', 'laplacian', 'misc', 'statistics', 'wavelet']
"""

from psmini.focus.measures import (
    Roi,
    brenner,
    gaussian_derivative,
    image_contrast,
    normalized_variance,
    parse_roi,
    tenengrad,
    variance_of_laplacian,
    wavelet_sum,
)
from psmini.focus.operators import (
    FOCUS_FAMILIES,
    FOCUS_MEASURES,
    FOCUS_NAMES,
    FOCUS_OPERATORS,
    FocusMeasure,
    FocusOperator,
    FocusVolume,
    absolute_central_moment,
    curvature,
    dct_energy_ratio,
    dct_reduced_energy_ratio,
    diagonal_laplacian,
    focus_measure,
    focus_volume,
    gradient_energy,
    gray_level_local_variance,
    gray_level_variance,
    helmli_mean,
    histogram_entropy,
    histogram_range,
    laplacian_energy,
    modified_laplacian,
    spatial_frequency,
    squared_gradient,
    steerable_filters,
    tenengrad_variance,
    thresholded_gradient,
    vollath_f4,
    wavelet_ratio,
    wavelet_variance,
)

__all__ = [
    "FOCUS_FAMILIES",
    "FOCUS_MEASURES",
    "FOCUS_NAMES",
    "FOCUS_OPERATORS",
    "FocusMeasure",
    "FocusOperator",
    "FocusVolume",
    "Roi",
    "absolute_central_moment",
    "brenner",
    "curvature",
    "dct_energy_ratio",
    "dct_reduced_energy_ratio",
    "diagonal_laplacian",
    "focus_measure",
    "focus_volume",
    "gaussian_derivative",
    "gradient_energy",
    "gray_level_local_variance",
    "gray_level_variance",
    "helmli_mean",
    "histogram_entropy",
    "histogram_range",
    "image_contrast",
    "laplacian_energy",
    "modified_laplacian",
    "normalized_variance",
    "parse_roi",
    "spatial_frequency",
    "squared_gradient",
    "steerable_filters",
    "tenengrad",
    "tenengrad_variance",
    "thresholded_gradient",
    "variance_of_laplacian",
    "vollath_f4",
    "wavelet_ratio",
    "wavelet_sum",
    "wavelet_variance",
]
