r"""The scale-limited surface and the areal parameters of ISO 25178-2, on batched height maps.

Heights are :math:`(B, 1, H, W)` tensors in mm (height toward the camera), with an optional cloth mask of the same
shape. Pixels that are masked out or not finite (unsolved pixels, NaN depth) are *excluded from every sum*: the
form fit, the Gaussian filters (normalised convolution: the filter's weights renormalised over the valid pixels,
as ISO 16610-28 does at the borders), the moments, the gradients (a gradient needs all its stencil pixels valid)
and the autocorrelation (normalised by the valid overlap at each lag). So an unsolved pixel can never become a
spike of the statistics.

Preparation follows ISO 25178-2:2012 §3.1 and ISO 16610-61:2015: the F-operator removes the form (a least-squares
polynomial of degree 0, 1 or 2 over the valid pixels), the S-filter is a Gaussian low-pass with cut-off
:math:`\lambda_s`, the L-filter subtracts a Gaussian low-pass with cut-off :math:`\lambda_c`; the Gaussian
weighting function is

.. math:: s(x, y) = \frac{1}{\alpha^2 \lambda^2} \exp\!\left(-\frac{\pi (x^2 + y^2)}{\alpha^2 \lambda^2}\right),
   \qquad \alpha = \sqrt{\ln 2 / \pi},

whose transmission is 50% at the cut-off wavelength :math:`\lambda`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from psmini._checks import check_shape, check_tensor
from psmini.errors import InputError, ShapeError

__all__ = [
    "SurfaceOptions",
    "ISO_PARAMETERS",
    "ISO_UNITS",
    "valid_pixels",
    "remove_form",
    "gaussian_filter",
    "scale_limited_surface",
    "height_parameters",
    "hybrid_parameters",
    "autocorrelation",
    "spatial_parameters",
    "iso25178",
    "iso_s_cutoff_mm",
]

#: The ISO 25178-2 parameters :func:`iso25178` returns, in this order.
ISO_PARAMETERS = ("Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sa", "Sdq", "Sdr", "Sal", "Str", "Std")
#: Their units (heights in µm, Sdq a slope, Sdr in per cent, Sal in mm, Str a ratio, Std in degrees).
ISO_UNITS = {"Sq": "um", "Ssk": "1", "Sku": "1", "Sp": "um", "Sv": "um", "Sz": "um", "Sa": "um", "Sdq": "1",
             "Sdr": "%", "Sal": "mm", "Str": "1", "Std": "deg"}

_ALPHA = math.sqrt(math.log(2.0) / math.pi)  # ISO 16610-61 Gaussian constant


@dataclass(frozen=True)
class SurfaceOptions:
    """How the scale-limited surface is made and measured.

    Attributes:
        form_degree: degree of the least-squares polynomial the F-operator removes (0: mean, 1: plane,
            2: quadratic, for a cloth that sags or curls).
        s_cutoff_mm: cut-off of the S-filter (Gaussian low-pass), mm; ``None``: no S-filter (the pixel is the
            smallest scale).
        l_cutoff_mm: cut-off of the L-filter (removes wavelengths longer than it), mm; ``None``: no L-filter (an
            S-F surface). A wrinkle or the cloth's drape is removed by an L-filter a few yarn repeats long.
        acf_threshold: the value ``s`` to which the autocorrelation decays for Sal and Str (ISO: 0.2).
        directions: number of directions over 180° in which Sal, Str and Std are evaluated.
    """

    form_degree: int = 1
    s_cutoff_mm: float | None = None
    l_cutoff_mm: float | None = None
    acf_threshold: float = 0.2
    directions: int = 360

    def __post_init__(self) -> None:
        if self.form_degree not in (0, 1, 2):
            raise InputError(f"form_degree must be 0, 1 or 2, got {self.form_degree!r}")
        for name in ("s_cutoff_mm", "l_cutoff_mm"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float)) and 0 < value < math.inf):
                raise InputError(f"SurfaceOptions.{name} must be a positive number or None, got {value!r}")
        if (self.s_cutoff_mm is not None and self.l_cutoff_mm is not None
                and not self.s_cutoff_mm < self.l_cutoff_mm):
            raise InputError(f"the S-filter cut-off ({self.s_cutoff_mm} mm) must be shorter than the L-filter's "
                             f"({self.l_cutoff_mm} mm)")
        if not 0 < self.acf_threshold < 1:
            raise InputError(f"acf_threshold must lie in (0, 1), got {self.acf_threshold!r}")
        if not isinstance(self.directions, int) or self.directions < 8:
            raise InputError(f"directions must be an integer >= 8, got {self.directions!r}")

    def to_dict(self) -> dict:
        """The options as a JSON-ready dict."""
        return asdict(self)


#: The preferred values of the S-filter nesting index within a decade (ISO 25178-3: 1, 2, 2.5, 5, 8 x 10^k µm).
_NESTING_SERIES = (1.0, 2.0, 2.5, 5.0, 8.0)
#: ISO 25178-3 pairs each S-filter nesting index with a largest sampling distance about 3.2 times smaller (80 µm
#: with 25 µm, 25 µm with 8 µm, 8 µm with 2.5 µm): scales shorter than about three samples are not measured.
_SAMPLES_PER_S_CUTOFF = 3.0


def iso_s_cutoff_mm(pixel_pitch_mm: float) -> float:
    r"""The S-filter nesting index that ISO 25178-3 pairs with a sampling distance: the smallest preferred value
    (1, 2, 2.5, 5, 8 times a power of ten, in µm) at least three sampling distances long.

    The S-filter removes the scales an instrument does not resolve, so that a parameter measures the surface
    rather than the instrument: at 25 µm per pixel it is 80 µm, which passes a relief of an 8-pixel period at 90%
    and one of 4 pixels at 64% (:func:`gaussian_filter`'s transmission
    :math:`\exp(-\pi \alpha^2 \lambda_s^2/\lambda^2)`).

    Args:
        pixel_pitch_mm: the sampling distance (pixel size on the surface), mm.

    Returns:
        the nesting index :math:`\lambda_s`, mm.

    Raises:
        InputError: a pitch that is not a positive number.

    Example:
        >>> iso_s_cutoff_mm(0.025), iso_s_cutoff_mm(0.008), iso_s_cutoff_mm(0.0025)
        (0.08, 0.025, 0.008)
    """
    if not (isinstance(pixel_pitch_mm, (int, float)) and 0 < pixel_pitch_mm < math.inf):
        raise InputError(f"pixel_pitch_mm must be a positive number (mm per pixel), got {pixel_pitch_mm!r}")
    least_um = _SAMPLES_PER_S_CUTOFF * pixel_pitch_mm * 1000.0
    decade = 10.0 ** math.floor(math.log10(least_um))
    for scale in (decade, 10 * decade):
        for value in _NESTING_SERIES:
            if value * scale >= least_um * (1 - 1e-9):
                return round(value * scale, 12) / 1000.0
    raise AssertionError("unreachable: the next decade's 1 is always long enough")


def _check_height(height: Tensor, mask: Tensor | None, pixel_pitch_mm: float) -> Tensor:
    """Guards shared by the public functions; returns the valid-pixel map (B, 1, H, W) bool."""
    check_tensor(height, "height")
    sizes = check_shape(height, ["B", "1", "H", "W"], "height")
    if not (isinstance(pixel_pitch_mm, (int, float)) and 0 < pixel_pitch_mm < math.inf):
        raise InputError(f"pixel_pitch_mm must be a positive number (mm per pixel), got {pixel_pitch_mm!r}")
    if mask is not None and (not isinstance(mask, Tensor) or tuple(mask.shape) != tuple(height.shape)):
        got = tuple(mask.shape) if isinstance(mask, Tensor) else type(mask).__name__
        raise ShapeError(f"mask must be a tensor of the height's shape {tuple(height.shape)}, got {got}")
    valid = valid_pixels(height, mask)
    empty = ~valid.flatten(1).any(dim=1)
    if bool(empty.any()):
        raise InputError(f"sample(s) {empty.nonzero().flatten().tolist()} have no valid pixel (empty mask or "
                         f"all-NaN height) of {sizes['H']}x{sizes['W']}")
    return valid


def valid_pixels(height: Tensor, mask: Tensor | None = None) -> Tensor:
    """Pixels that take part in every sum: inside ``mask`` (when given) and finite.

    Args:
        height: :math:`(B, 1, H, W)`.
        mask: optional :math:`(B, 1, H, W)`, bool or 0/1 (or a shape that broadcasts to the height's, e.g. batch 1).

    Returns:
        :math:`(B, 1, H, W)` bool.

    Raises:
        ShapeError: a mask that is not a tensor, or does not broadcast to the height's shape (another H or W, a
            larger batch).

    Example:
        >>> valid_pixels(torch.tensor([[[[0.0, float("nan")]]]])).tolist()
        [[[[True, False]]]]
    """
    valid = torch.isfinite(height)
    if mask is not None:
        _check_fits(mask, height, "mask", "height")
        valid = valid & mask.bool()
    return valid


def _check_fits(x: object, like: Tensor, name: str, like_name: str, same_ndim: bool = False) -> None:
    """Raise :class:`ShapeError` unless ``x`` is a tensor that broadcasts to ``like``'s shape without enlarging it
    (another H or W failed as a bare RuntimeError of broadcasting; a larger batch gave more results than heights);
    ``same_ndim``: with as many dimensions too (a batch of 1 stays a batch of 1: ``(1, 1, H, W)``)."""
    try:
        fits = (isinstance(x, Tensor) and (not same_ndim or x.ndim == like.ndim)
                and torch.broadcast_shapes(x.shape, like.shape) == like.shape)
    except RuntimeError:  # sizes that do not broadcast at all
        fits = False
    if not fits:
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ShapeError(f"{name} must have the {like_name}'s shape {tuple(like.shape)} (or batch 1), got {got}")


def _check_valid(surface: Tensor, valid: Tensor) -> None:
    """Guards of the functions that take a precomputed valid-pixel map: a :math:`(B, 1, H, W)` surface and a bool
    map of its shape (or batch 1)."""
    check_shape(surface, ["B", "1", "H", "W"], "surface")
    _check_fits(valid, surface, "valid", "surface", same_ndim=True)
    if valid.dtype != torch.bool:
        raise InputError(f"valid must be a bool map (the valid pixels scale_limited_surface or valid_pixels return), "
                         f"got {valid.dtype}; turn a 0/1 map into one with valid > 0")


def _masked_mean(x: Tensor, weight: Tensor) -> Tensor:
    """Mean of x over the weight (B, 1, H, W) -> (B,)."""
    return (x * weight).flatten(1).sum(1) / weight.flatten(1).sum(1).clamp_min(1)


def remove_form(height: Tensor, mask: Tensor | None = None, degree: int = 1) -> Tensor:
    r"""The F-operator: subtract the least-squares polynomial of ``degree`` fitted over the valid pixels.

    The polynomial in normalised pixel coordinates (:math:`1, x, y` for a plane, plus :math:`x^2, xy, y^2`) is
    fitted by weighted normal equations, one small solve per sample; invalid pixels do not enter the fit and
    are 0 in the result.

    Args:
        height: :math:`(B, 1, H, W)`, any unit.
        mask: optional :math:`(B, 1, H, W)` valid pixels (bool); non-finite pixels are excluded too.
        degree: 0, 1 or 2.

    Returns:
        the levelled height, :math:`(B, 1, H, W)`, zero-mean over the valid pixels, 0 elsewhere.

    Raises:
        InputError: for another degree, or a sample without valid pixels.
        ShapeError: a height not :math:`(B, 1, H, W)`, or a mask of another size (see :func:`valid_pixels`).

    Example:
        >>> y, x = torch.meshgrid(torch.arange(4.0), torch.arange(5.0), indexing="ij")
        >>> plane = (0.3 * x - 0.2 * y + 1.0)[None, None]
        >>> bool(remove_form(plane).abs().max() < 1e-5)
        True
    """
    if degree not in (0, 1, 2):
        raise InputError(f"form degree must be 0, 1 or 2, got {degree!r}")
    check_tensor(height, "height")
    check_shape(height, ["B", "1", "H", "W"], "height")
    valid = valid_pixels(height, mask)
    if bool((~valid.flatten(1).any(dim=1)).any()):
        raise InputError("remove_form got a sample without valid pixels (empty mask or all-NaN height)")
    b, _, h, w = height.shape
    z = torch.where(valid, height, torch.zeros((), dtype=height.dtype, device=height.device))
    weight = valid.to(height.dtype)
    y = torch.linspace(-1, 1, h, dtype=height.dtype, device=height.device).view(h, 1).expand(h, w)
    x = torch.linspace(-1, 1, w, dtype=height.dtype, device=height.device).view(1, w).expand(h, w)
    terms = [torch.ones_like(x)]
    if degree >= 1:
        terms += [x, y]
    if degree == 2:
        terms += [x * x, x * y, y * y]
    basis = torch.stack(terms).flatten(1)  # (P, N)
    wz = (weight * z).flatten(1)  # (B, N)
    wf = weight.flatten(1)
    normal = torch.einsum("pn,bn,qn->bpq", basis, wf, basis)
    rhs = torch.einsum("pn,bn->bp", basis, wz)
    # a tiny ridge keeps the solve defined when the valid pixels are too few for the degree (a line of pixels)
    eye = torch.eye(basis.shape[0], dtype=height.dtype, device=height.device)
    coef = torch.linalg.solve(normal + 1e-12 * normal.diagonal(dim1=1, dim2=2).mean(1).view(b, 1, 1) * eye, rhs)
    form = torch.einsum("bp,pn->bn", coef, basis).view(b, 1, h, w)
    return torch.where(valid, z - form, torch.zeros((), dtype=height.dtype, device=height.device))


def _gaussian_kernel(cutoff_px: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The ISO 16610-61 weighting function sampled on pixels, truncated at ±1.5 cut-offs, summing to 1."""
    radius = max(1, int(math.ceil(1.5 * cutoff_px)))
    t = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    kernel = torch.exp(-math.pi * (t / (_ALPHA * cutoff_px)).square())
    return kernel / kernel.sum()


def _separable(x: Tensor, kernel: Tensor) -> Tensor:
    """Zero-padded (linear, not circular) convolution of (B, 1, H, W) with the outer product of a 1-D kernel,
    by FFT: the long kernels of an L-filter cost the same as short ones."""
    radius = kernel.numel() // 2
    h, w = x.shape[-2:]
    size = (h + 2 * radius, w + 2 * radius)
    kx = torch.fft.rfft2(torch.outer(kernel, kernel), s=size)
    out = torch.fft.irfft2(torch.fft.rfft2(x, s=size) * kx, s=size)
    return out[..., radius:radius + h, radius:radius + w]


def gaussian_filter(height: Tensor, cutoff_mm: float, pixel_pitch_mm: float, mask: Tensor | None = None) -> Tensor:
    r"""The ISO 16610-61 areal Gaussian low-pass (the mean surface of wavelengths longer than ``cutoff_mm``).

    Normalised convolution: :math:`(s * (m z)) / (s * m)` with :math:`m` the valid pixels, so invalid pixels
    and the field's border are excluded and every output is a weighted mean of valid heights (the end-effect
    correction of ISO 16610-28). The weighting function (module docstring) transmits 50% of a sine of
    wavelength ``cutoff_mm``: :math:`\exp(-\pi \alpha^2 \lambda_c^2 / \lambda^2)`.

    Args:
        height: :math:`(B, 1, H, W)`, any unit.
        cutoff_mm: the cut-off wavelength, mm.
        pixel_pitch_mm: pixel size, mm.
        mask: optional valid pixels :math:`(B, 1, H, W)`.

    Returns:
        the filtered height :math:`(B, 1, H, W)`; 0 where no valid pixel lies within reach of the kernel.

    Raises:
        InputError: for a non-positive cut-off or pitch, or a sample without valid pixels.

    Example:
        >>> x = torch.arange(200.0) * 0.01
        >>> wave = torch.sin(2 * math.pi * x / 0.5).view(1, 1, 1, 200).expand(1, 1, 8, 200)
        >>> low = gaussian_filter(wave, 0.5, 0.01)
        >>> round(float(low[0, 0, 4, 80:120].abs().max()), 2)  # 50% transmission at the cut-off
        0.5
    """
    valid = _check_height(height, mask, pixel_pitch_mm)
    if not (isinstance(cutoff_mm, (int, float)) and 0 < cutoff_mm < math.inf):
        raise InputError(f"cutoff_mm must be a positive number, got {cutoff_mm!r}")
    return _gaussian_filter(height, valid, cutoff_mm / pixel_pitch_mm)


def _gaussian_filter(height: Tensor, valid: Tensor, cutoff_px: float) -> Tensor:
    kernel = _gaussian_kernel(cutoff_px, height.dtype, height.device)
    weight = valid.to(height.dtype)
    z = torch.where(valid, height, torch.zeros((), dtype=height.dtype, device=height.device))
    num = _separable(z * weight, kernel)
    den = _separable(weight, kernel)
    tiny = torch.finfo(height.dtype).tiny ** 0.5
    return torch.where(den > tiny, num / den.clamp_min(tiny), torch.zeros_like(num))


def scale_limited_surface(height: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None,
                          options: SurfaceOptions = SurfaceOptions()) -> tuple[Tensor, Tensor]:
    """The scale-limited surface of ISO 25178-2: F-operator, S-filter, L-filter, over the valid pixels.

    Args:
        height: :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: pixel size, mm.
        mask: optional cloth mask :math:`(B, 1, H, W)`; non-finite heights are excluded as well.
        options: form degree and cut-offs (:class:`SurfaceOptions`).

    Returns:
        the surface :math:`(B, 1, H, W)` in mm, zero-mean over the valid pixels and 0 elsewhere, and the valid
        pixels :math:`(B, 1, H, W)` bool.

    Raises:
        InputError: bad pitch, a sample without valid pixels. ShapeError: bad shapes.

    Example:
        >>> surface, valid = scale_limited_surface(torch.rand(2, 1, 16, 16), 0.025)
        >>> surface.shape, bool(valid.all())
        (torch.Size([2, 1, 16, 16]), True)
    """
    valid = _check_height(height, mask, pixel_pitch_mm)
    z = remove_form(height, valid, options.form_degree)
    if options.s_cutoff_mm is not None:
        z = _gaussian_filter(z, valid, options.s_cutoff_mm / pixel_pitch_mm)
    if options.l_cutoff_mm is not None:
        z = z - _gaussian_filter(z, valid, options.l_cutoff_mm / pixel_pitch_mm)
    weight = valid.to(z.dtype)
    z = z - _masked_mean(z, weight).view(-1, 1, 1, 1)
    return z * weight, valid


def height_parameters(surface: Tensor, valid: Tensor) -> dict[str, Tensor]:
    r"""Height parameters of ISO 25178-2 §4.1 over the valid pixels, in the surface's unit.

    :math:`S_q = \sqrt{\overline{z^2}}`, :math:`S_{sk} = \overline{z^3}/S_q^3`, :math:`S_{ku} = \overline{z^4}/S_q^4`,
    :math:`S_p = \max z`, :math:`S_v = |\min z|`, :math:`S_z = S_p + S_v`, :math:`S_a = \overline{|z|}`, with
    :math:`\overline{\cdot}` the mean over the definition area and :math:`z` measured from the reference (mean)
    surface.

    Args:
        surface: scale-limited surface :math:`(B, 1, H, W)` (:func:`scale_limited_surface`).
        valid: :math:`(B, 1, H, W)` bool (or :math:`(1, 1, H, W)`: the same pixels for every surface).

    Returns:
        ``{"Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sa"}``, each :math:`(B,)`.

    Raises:
        ShapeError: a surface that is not :math:`(B, 1, H, W)`, or a ``valid`` map of another shape (another H or W,
            a larger batch; batch 1 applies to every surface).
        InputError: a ``valid`` map that is not bool.

    Example:
        >>> z = torch.tensor([1.0, -1.0, 1.0, -1.0]).view(1, 1, 2, 2)
        >>> {k: float(v) for k, v in height_parameters(z, z != 0).items()}["Sku"]
        1.0
    """
    _check_valid(surface, valid)
    weight = valid.to(surface.dtype)
    mean = _masked_mean(surface, weight).view(-1, 1, 1, 1)
    z = (surface - mean) * weight
    m2 = _masked_mean(z.square(), weight)
    sq = m2.sqrt()
    tiny = torch.finfo(surface.dtype).tiny ** 0.5
    safe = sq.clamp_min(tiny)
    big = torch.finfo(surface.dtype).max
    sp = torch.where(valid, z, torch.full_like(z, -big)).flatten(1).amax(1)
    sv = -torch.where(valid, z, torch.full_like(z, big)).flatten(1).amin(1)
    return {
        "Sq": sq,
        "Ssk": _masked_mean(z.pow(3), weight) / safe.pow(3),
        "Sku": _masked_mean(z.pow(4), weight) / safe.pow(4),
        "Sp": sp,
        "Sv": sv,
        "Sz": sp + sv,
        "Sa": _masked_mean(z.abs(), weight),
    }


def _gradients(surface: Tensor, valid: Tensor, pixel_pitch_mm: float) -> tuple[Tensor, Tensor, Tensor]:
    """Fourth-order central differences (dz/dx, dz/dy with y up) and where all five stencil pixels are valid."""
    c = torch.tensor([1.0, -8.0, 0.0, 8.0, -1.0], dtype=surface.dtype, device=surface.device) / (12 * pixel_pitch_mm)
    weight = valid.to(surface.dtype)
    zx = F.conv2d(surface, c.flip(0).view(1, 1, 1, 5), padding=(0, 2))
    zy = -F.conv2d(surface, c.flip(0).view(1, 1, 5, 1), padding=(2, 0))  # rows grow downward, y up
    ones = torch.ones(1, 1, 1, 5, dtype=surface.dtype, device=surface.device)
    full_x = F.conv2d(weight, ones, padding=(0, 2)) > 4.5
    full_y = F.conv2d(weight, ones.view(1, 1, 5, 1), padding=(2, 0)) > 4.5
    return zx, zy, full_x & full_y


def hybrid_parameters(surface: Tensor, valid: Tensor, pixel_pitch_mm: float) -> dict[str, Tensor]:
    r"""Hybrid parameters of ISO 25178-2 §4.3: root-mean-square gradient and developed interfacial area ratio.

    :math:`S_{dq} = \sqrt{\overline{(\partial_x z)^2 + (\partial_y z)^2}}` (dimensionless) and
    :math:`S_{dr} = 100\,\overline{\sqrt{1 + (\partial_x z)^2 + (\partial_y z)^2} - 1}` (per cent), the gradients
    by fourth-order central differences, averaged over the pixels whose whole stencil is valid (the border and
    the neighbours of unsolved pixels are left out rather than differenced across).

    Args:
        surface: :math:`(B, 1, H, W)`, mm.
        valid: :math:`(B, 1, H, W)` bool (or :math:`(1, 1, H, W)`: the same pixels for every surface).
        pixel_pitch_mm: pixel size, mm.

    Returns:
        ``{"Sdq", "Sdr"}``, each :math:`(B,)`.

    Raises:
        InputError: when a sample has no pixel with a full stencil (thinner than 5 pixels, or too few valid), or
            the ``valid`` map is not bool.
        ShapeError: a surface that is not :math:`(B, 1, H, W)`, or a ``valid`` map of another shape (another H or W,
            a larger batch).

    Example:
        >>> ramp = (torch.arange(16.0) * 0.5).view(1, 1, 1, 16).expand(1, 1, 16, 16)
        >>> round(float(hybrid_parameters(ramp, ramp >= 0, 1.0)["Sdq"]), 6)
        0.5
    """
    _check_valid(surface, valid)
    zx, zy, inside = _gradients(surface, valid, pixel_pitch_mm)
    if bool((~inside.flatten(1).any(1)).any()):
        raise InputError("no pixel has the 5x5 neighbourhood of valid pixels that the gradients need")
    weight = inside.to(surface.dtype)
    g2 = (zx.square() + zy.square()) * weight
    return {
        "Sdq": _masked_mean(g2, weight).sqrt(),
        "Sdr": 100 * _masked_mean(((1 + g2).sqrt() - 1), weight),
    }


def autocorrelation(surface: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    r"""Normalised areal autocorrelation over the valid pixels, by FFT with zero padding (no wrap-around).

    :math:`f_{ACF}(\tau) = \frac{\sum_p m_p m_{p+\tau} z_p z_{p+\tau} / \sum_p m_p m_{p+\tau}}
    {\sum_p m_p z_p^2 / \sum_p m_p}` (ISO 25178-2 §3.1.6 with the integral over the overlap of the shifted
    definition area); lags with fewer than a quarter of the pixels in the overlap are set to 0.

    Args:
        surface: :math:`(B, 1, H, W)`, zero-mean over ``valid``.
        valid: :math:`(B, 1, H, W)` bool (or :math:`(1, 1, H, W)`: the same pixels for every surface).

    Returns:
        the ACF :math:`(B, 1, 2H-1, 2W-1)` with lag (0, 0) at index (H-1, W-1) (row lag grows downward), and the
        overlap counts of the same shape.

    Raises:
        ShapeError: a surface that is not :math:`(B, 1, H, W)`, or a ``valid`` map of another shape (another H or W,
            a larger batch; batch 1 applies to every surface).
        InputError: a ``valid`` map that is not bool.

    Example:
        >>> acf, _ = autocorrelation(torch.randn(1, 1, 8, 8), torch.ones(1, 1, 8, 8, dtype=torch.bool))
        >>> acf.shape, round(float(acf[0, 0, 7, 7]), 6)
        (torch.Size([1, 1, 15, 15]), 1.0)
    """
    _check_valid(surface, valid)
    b, _, h, w = surface.shape
    weight = valid.to(surface.dtype)
    size = (2 * h, 2 * w)
    spec_z = torch.fft.rfft2(surface * weight, s=size)
    spec_m = torch.fft.rfft2(weight, s=size)
    corr = torch.fft.irfft2(spec_z.abs().square(), s=size)
    count = torch.fft.irfft2(spec_m.abs().square(), s=size).round()
    corr = torch.roll(corr, shifts=(h - 1, w - 1), dims=(-2, -1))[..., : 2 * h - 1, : 2 * w - 1]
    count = torch.roll(count, shifts=(h - 1, w - 1), dims=(-2, -1))[..., : 2 * h - 1, : 2 * w - 1]
    enough = count >= 0.25 * count[..., h - 1 : h, w - 1 : w]
    mean = corr / count.clamp_min(1)
    acf = mean / mean[..., h - 1 : h, w - 1 : w].clamp_min(torch.finfo(surface.dtype).tiny)
    return torch.where(enough, acf, torch.zeros_like(acf)), count


def _polar_samples(field: Tensor, centre: tuple[float, float], angles: Tensor, radii: Tensor) -> Tensor:
    """Bilinear samples of (B, 1, R, C) at centre + r (cos a, -sin a) (y up), shape (B, A, N)."""
    rows, cols = field.shape[-2:]
    dx = torch.cos(angles).view(-1, 1) * radii.view(1, -1)
    dy = -torch.sin(angles).view(-1, 1) * radii.view(1, -1)
    gx = (centre[1] + dx) / (cols - 1) * 2 - 1
    gy = (centre[0] + dy) / (rows - 1) * 2 - 1
    grid = torch.stack([gx, gy], dim=-1).unsqueeze(0).expand(field.shape[0], -1, -1, -1)
    return F.grid_sample(field, grid.to(field.dtype), mode="bilinear", padding_mode="zeros",
                         align_corners=True)[:, 0]


def _decay_lengths(acf: Tensor, threshold: float, directions: int, h: int, w: int) -> Tensor:
    """For each direction over [0°, 180°): the first lag (pixels) at which the ACF falls to ``threshold``;
    infinite when it does not within half the field. Shape (B, A)."""
    angles = torch.arange(directions, dtype=acf.dtype, device=acf.device) * (math.pi / directions)
    reach = (min(h, w) - 1) / 2
    step = 0.25
    radii = torch.arange(0, reach + step / 2, step, dtype=acf.dtype, device=acf.device)
    samples = _polar_samples(acf, (h - 1, w - 1), angles, radii)  # (B, A, N)
    below = samples <= threshold
    has = below.any(dim=-1)
    first = torch.argmax(below.to(torch.int8), dim=-1).clamp_min(1)
    before = samples.gather(-1, (first - 1).unsqueeze(-1)).squeeze(-1)
    after = samples.gather(-1, first.unsqueeze(-1)).squeeze(-1)
    frac = ((before - threshold) / (before - after).clamp_min(torch.finfo(acf.dtype).eps)).clamp(0, 1)
    length = (first.to(acf.dtype) - 1 + frac) * step
    return torch.where(has, length, torch.full_like(length, math.inf))


def spatial_parameters(surface: Tensor, valid: Tensor, pixel_pitch_mm: float, threshold: float = 0.2,
                       directions: int = 360) -> dict[str, Tensor]:
    r"""Spatial parameters of ISO 25178-2 §4.2: autocorrelation length, texture aspect ratio, texture direction.

    - ``Sal`` (mm): the shortest horizontal distance at which the autocorrelation :func:`autocorrelation` decays
      to ``threshold`` (the standard's :math:`s = 0.2`): :math:`\min |\tau|` over
      :math:`\{\tau : f_{ACF}(\tau) \le s\}`, found as the first crossing along each of ``directions`` rays
      (bilinear samples every 0.25 px, linear interpolation of the crossing).
    - ``Str``: that shortest distance divided by the longest such first-crossing distance over the directions;
      0 when the ACF does not decay to ``s`` within half the field in some direction (a lay longer than the
      field: a strongly anisotropic surface).
    - ``Std`` (degrees in [0, 180), counter-clockwise from x, y up): the texture direction, the direction of the
      lay. The angular power spectrum :math:`f_{APS}(\theta) = \int_0^{R} |F(r\cos\theta, r\sin\theta)|^2 r\,dr`
      peaks across the lay (at the direction of the dominant spatial frequency, refined by a parabola through
      the three best directions; the spectrum of the Hann-windowed surface, zero-padded twice); ``Std`` is that
      angle plus 90°, the direction along which the texture runs.

    Args:
        surface: :math:`(B, 1, H, W)`, mm, zero-mean over ``valid``.
        valid: :math:`(B, 1, H, W)` bool (or :math:`(1, 1, H, W)`: the same pixels for every surface).
        pixel_pitch_mm: pixel size, mm.
        threshold: the ACF level ``s`` (0 < s < 1).
        directions: rays over 180°.

    Returns:
        ``{"Sal", "Str", "Std"}``, each :math:`(B,)`; ``Sal`` is infinite when the ACF never decays to ``s``
        within half the field.

    Raises:
        InputError: a ``threshold`` outside (0, 1), or a ``valid`` map that is not bool.
        ShapeError: a surface that is not :math:`(B, 1, H, W)`, or a ``valid`` map of another shape (another H or W,
            a larger batch).

    Example:
        >>> x = torch.arange(64.0)
        >>> z = torch.sin(2 * math.pi * x / 8).view(1, 1, 1, 64).expand(1, 1, 64, 64)
        >>> out = spatial_parameters(z, z == z, 1.0)
        >>> round(float(out["Sal"]) / 8, 2), float(out["Str"]), round(float(out["Std"]), 1)  # acos(0.2)/2pi; lay: y
        (0.22, 0.0, 90.0)
    """
    if not 0 < threshold < 1:
        raise InputError(f"threshold must lie in (0, 1), got {threshold!r}")
    _check_valid(surface, valid)
    b, _, h, w = surface.shape
    acf, _ = autocorrelation(surface, valid)
    lengths = _decay_lengths(acf, threshold, directions, h, w) * pixel_pitch_mm  # (B, A)
    sal = lengths.min(dim=1).values
    longest = lengths.max(dim=1).values
    str_ = torch.where(torch.isfinite(longest), sal / longest.clamp_min(torch.finfo(surface.dtype).tiny),
                       torch.zeros_like(sal))
    return {"Sal": sal, "Str": torch.where(torch.isfinite(sal), str_, torch.full_like(sal, math.nan)),
            "Std": _texture_direction(surface, valid, directions)}


def _texture_direction(surface: Tensor, valid: Tensor, directions: int) -> Tensor:
    """Angle (degrees, [0, 180)) of the lay: the angular power spectrum's maximum plus 90°."""
    b, _, h, w = surface.shape
    n = 2 * max(h, w)
    # a Hann window keeps the leakage of the field's edges (a cross along the axes) out of the angular spectrum
    window = (torch.hann_window(h, periodic=False, dtype=surface.dtype, device=surface.device).view(h, 1)
              * torch.hann_window(w, periodic=False, dtype=surface.dtype, device=surface.device).view(1, w))
    spec = torch.fft.fftshift(torch.fft.fft2(surface * valid.to(surface.dtype) * window, s=(n, n)), dim=(-2, -1))
    power = spec.abs().square()  # (B, 1, n, n), DC at (n // 2, n // 2); row index grows toward -y
    angles = torch.arange(directions, dtype=surface.dtype, device=surface.device) * (math.pi / directions)
    radii = torch.arange(1.0, n / 2 - 1, 0.5, dtype=surface.dtype, device=surface.device)
    samples = _polar_samples(power, (n // 2, n // 2), angles, radii)  # (B, A, N)
    aps = (samples * radii).sum(-1) + 1e-30  # (B, A)
    best = aps.argmax(dim=1)
    left = aps.gather(1, ((best - 1) % directions).unsqueeze(1)).squeeze(1)
    mid = aps.gather(1, best.unsqueeze(1)).squeeze(1)
    right = aps.gather(1, ((best + 1) % directions).unsqueeze(1)).squeeze(1)
    den = left - 2 * mid + right
    shift = torch.where(den.abs() > 0, 0.5 * (left - right) / torch.where(den.abs() > 0, den, torch.ones_like(den)),
                        torch.zeros_like(den)).clamp(-0.5, 0.5)
    spectral = (best.to(surface.dtype) + shift) * (180.0 / directions)
    return torch.remainder(spectral + 90.0, 180.0)


def iso25178(height: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None,
             options: SurfaceOptions = SurfaceOptions()) -> dict[str, Tensor]:
    r"""Areal surface-texture parameters of ISO 25178-2:2012 on the scale-limited surface.

    Heights in µm (Sq, Sp, Sv, Sz, Sa), Ssk and Sku dimensionless, Sdq dimensionless, Sdr in per cent, Sal in
    mm, Str dimensionless, Std in degrees (see :func:`height_parameters`, :func:`hybrid_parameters`,
    :func:`spatial_parameters` for the definitions). Masked and non-finite pixels are excluded from every sum.

    Args:
        height: :math:`(B, 1, H, W)`, mm (height toward the camera).
        pixel_pitch_mm: pixel size, mm.
        mask: optional cloth mask :math:`(B, 1, H, W)`.
        options: the scale-limited surface and the ACF threshold (:class:`SurfaceOptions`).

    Returns:
        a dict of :data:`ISO_PARAMETERS` to :math:`(B,)` tensors (height dtype and device). Height, hybrid
        parameters and Sal are differentiable with respect to ``height``.

    Raises:
        InputError: a sample without valid pixels, a bad pitch; ShapeError: bad shapes.

    Example:
        >>> x = torch.arange(80.0) * 0.025
        >>> z = 0.05 * torch.sin(2 * math.pi * x / 0.5).view(1, 1, 1, 80).expand(1, 1, 80, 80)
        >>> params = iso25178(z, 0.025, options=SurfaceOptions(form_degree=0))
        >>> round(float(params["Sq"]), 2)  # 50 µm / sqrt(2)
        35.36
    """
    surface, valid = scale_limited_surface(height, pixel_pitch_mm, mask, options)
    out = {k: v * 1000.0 if ISO_UNITS[k] == "um" else v for k, v in height_parameters(surface, valid).items()}
    out.update(hybrid_parameters(surface, valid, pixel_pitch_mm))
    out.update(spatial_parameters(surface, valid, pixel_pitch_mm, options.acf_threshold, options.directions))
    return {k: out[k] for k in ISO_PARAMETERS}
