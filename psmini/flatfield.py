r"""Flat-fielding: dark-frame subtraction and division by the image of a matte card under the same LED.

Under LED k a Lambertian pixel of the cloth reads :math:`I_k = \rho\,E_k(x)\,(n \cdot l_k)` and the card of known
albedo :math:`\rho_c` lying flat at the same place reads :math:`R_k = \rho_c\,E_k(x)\,(e_z \cdot l_k)`. Their ratio

.. math:: \hat I_k = \rho_c \, \frac{I_k - D}{R_k - D_R}

cancels the LED's inverse-square fall-off, its beam shape, vignetting and gain, leaving what a distant light of
unit intensity with direction :math:`l_k` would give, up to the factor :math:`e_z \cdot l_k` that the light
directions account for (the seed paper's step 1; Woodham 1980 for the model). The cancellation is exact only
while the cloth lies at the card's height; see :mod:`psmini.lights` for the near-light models.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import check_finite, check_out, check_positive, check_shape, check_tensor
from psmini.errors import InputError, ShapeError
from psmini.normals import _symmetric_adjugate

__all__ = ["FlatFieldResult", "flatfield", "FlatField", "smooth_card", "fill_saturated_card"]


@dataclass
class FlatFieldResult:
    """What :func:`flatfield` returns.

    Attributes:
        images: flat-fielded intensities, shape :math:`(B, K, H, W)`, clamped at 0; 0 where not valid.
        valid: observations to trust, shape :math:`(B, K, H, W)`, bool: not saturated, and the reference
            bright enough there.
        all_valid: whether every observation is valid when that is known from the card alone, without a pass
            over ``valid`` (no saturation level given); ``None`` otherwise (use ``bool(valid.all())``).
        gain: the factor each dark-subtracted reading was multiplied by, ``card_albedo / (reference -
            reference_dark)`` (0 where the card is not trusted), broadcastable to :math:`(B, K, H, W)`; ``None``
            without a reference. The flat-fielded noise scales with it: where an LED lights the card six times
            more dimly, the division amplifies the camera's read noise six times (the near-light solver's noise
            model uses it).
    """

    images: Tensor
    valid: Tensor
    all_valid: bool | None = None
    gain: Tensor | None = None


def _check_frame(frame: Tensor | None, batch: int, count: int, height: int, width: int, name: str,
                 finite: bool = True) -> Tensor | None:
    """Check a dark frame or a reference stack, broadcastable to (B, K, H, W); return it 4-D. ``finite=False``
    leaves the test for NaN and infinities to the caller."""
    if frame is None:
        return None
    check_tensor(frame, name)
    if frame.ndim == 2:
        frame = frame[None, None]
    elif frame.ndim == 3:
        frame = frame.unsqueeze(0)
    ok = (
        frame.ndim == 4
        and frame.shape[0] in (1, batch)
        and frame.shape[1] in (1, count)
        and tuple(frame.shape[2:]) == (height, width)
    )
    if not ok:
        raise ShapeError(
            f"{name} must broadcast to the images' shape ({batch}, {count}, {height}, {width}) "
            f"(as (B|1, K|1, H, W), (K|1, H, W) or (H, W)), got {tuple(frame.shape)}"
        )
    return check_finite(frame, name) if finite else frame


def flatfield(
    images: Tensor,
    reference: Tensor | None = None,
    dark: Tensor | None = None,
    reference_dark: Tensor | None = None,
    card_albedo: float = 1.0,
    min_reference: float = 0.02,
    saturation_level: float | None = None,
    *,
    card_smoothing_px: float | None = None,
    card_shading: Tensor | None = None,
    out: Tensor | None = None,
) -> FlatFieldResult:
    r"""Subtract the dark frame and divide by the per-LED reference (matte card) images.

    Args:
        images: raw images, shape :math:`(B, K, H, W)`, linear values (e.g. in [0, 1]).
        reference: the matte card under each LED, broadcastable to :math:`(B, K, H, W)`; when omitted only the
            dark frame is subtracted (distant, equal lights assumed).
        dark: all-LEDs-off frame of the sample, broadcastable to :math:`(B, K, H, W)` (usually :math:`(B, 1, H, W)`).
        reference_dark: all-LEDs-off frame of the card capture; defaults to ``dark``.
        card_albedo: the card's known albedo, so that the result is the cloth's albedo times shading.
        min_reference: reference values below this fraction of that LED's brightest reference pixel are not
            trusted (the LED barely lights the card there): those observations are marked not valid.
        saturation_level: raw values at or above it are saturated and marked not valid (in the images and in
            the reference); ``None`` disables the check.
        card_smoothing_px: when given, the dark-subtracted card is first denoised by :func:`smooth_card` with
            this window (pixels); ``None`` (default) divides by the card as captured.
        card_shading: what each LED's card reading is proportional to, :math:`E_k(x)\,l_{k,z}(x)` (the irradiance
            times the foreshortening on the card, from a light model: the near-light pipeline passes its
            :func:`~psmini.nearlight.near_light_vectors`' z component at the card's height), broadcastable to
            :math:`(B, K, H, W)`. With ``saturation_level``, the card's saturated readings (and those at the dark
            level, which a flat-field capture written by ``psmini calibrate flatfield`` stores for them) are then
            predicted instead of dropped: the pixel's gain (the camera's and the card's, common to its LEDs) is
            fitted to its other readings by least squares and times the shading gives the missing ones (see
            :func:`fill_saturated_card`), so that the LEDs that saturate the card near them still count there; a
            prediction below ``min_reference`` of the LED's brightest stays untrusted.
            ``None`` (default): a saturated card reading is not trusted, and neither is any reading divided by it.
        out: optional :math:`(B, K, H, W)` tensor of the images' dtype and device that receives the flat-fielded
            images (the pipeline reuses one such buffer chunk after chunk of a CPU batch: a fresh one of several
            MB is page-faulted in on every first touch). Not differentiable: refused when an input requires grad
            with grad enabled.

    Returns:
        :class:`FlatFieldResult` with ``images`` :math:`(B, K, H, W)` (``out`` when given), ``valid``
        :math:`(B, K, H, W)` and the card's ``gain``.

    Raises:
        ShapeError: when a frame, or ``out``, does not fit the images' shape.
        InputError: when a value is NaN or infinite, an option is out of range, or ``out`` cannot take the result
            (it requires grad, shares memory with an input, or an input requires grad).

    Example:
        >>> images = torch.rand(2, 8, 16, 16)
        >>> card = torch.full((8, 16, 16), 0.5)
        >>> result = flatfield(images, card, card_albedo=0.8)
        >>> torch.allclose(result.images, images / 0.5 * 0.8)
        True
        >>> round(float(result.gain.max()), 6)   # 0.8 / 0.5: the factor applied to each reading (and to its noise)
        1.6
    """
    sizes = check_shape(images, ["B", "K", "H", "W"], "images")
    check_finite(images, "images")
    if not 0.0 <= min_reference < 1.0:
        raise InputError(f"min_reference must lie in [0, 1), got {min_reference}")
    if not card_albedo > 0.0:
        raise InputError(f"card_albedo must be positive, got {card_albedo}")
    shape = (sizes["B"], sizes["K"], sizes["H"], sizes["W"])
    if card_smoothing_px is not None:
        check_positive(card_smoothing_px, "card_smoothing_px")
    card_tensors = (reference, dark if reference_dark is None else reference_dark)  # the caller's, for the cache
    dark = _check_frame(dark, *shape, "dark")
    reference = _check_frame(reference, *shape, "reference", finite=False)  # in _card_terms, once per card
    reference_dark = _check_frame(reference_dark, *shape, "reference_dark") if reference_dark is not None else dark
    if out is not None:
        check_out((out,), (shape,), ("images",), (images, reference, dark, reference_dark))

    # One new tensor per sample (or ``out``), updated in place: the difference, its clamp, the card's scale (each a
    # pass over memory; there is no fused kernel for max(I - D, 0) * s in eager torch).
    if dark is None:
        signal = torch.clamp_min(images, 0, out=out)
    else:
        signal = torch.sub(images, dark.to(images), out=out).clamp_min_(0)
    # one read of the images decides whether anything is saturated: when nothing is (the usual capture), the
    # bool map, its masked fill and the per-observation valid map are skipped, and the card alone decides
    # (the unsaturated map multiplies: a float product by a bool map took half a masked_fill_'s 1.6 ms on a capture)
    unsaturated = None
    if saturation_level is not None and bool(images.detach().amax() >= saturation_level):
        unsaturated = images < saturation_level
    if reference is None:
        if unsaturated is None:
            return FlatFieldResult(signal, torch.ones_like(images, dtype=torch.bool), True)
        return FlatFieldResult(signal.mul_(unsaturated), unsaturated)

    # card_tensors[0] is the caller's reference, which is not None here: mypy does not relate the two
    card_shading = _check_frame(card_shading, *shape, "card_shading")
    scale, trusted, all_trusted = _card_terms(reference, reference_dark, card_tensors,  # type: ignore[arg-type]
                                              images, card_albedo, min_reference, saturation_level, card_smoothing_px,
                                              card_shading)
    ratio = signal.mul_(scale)
    valid = trusted.expand(shape)
    if unsaturated is not None:
        return FlatFieldResult(ratio.mul_(unsaturated), valid & unsaturated, gain=scale)
    return FlatFieldResult(ratio, valid, all_trusted, scale)


class _CardEntry(NamedTuple):
    key: tuple
    sources: tuple[weakref.ref | None, ...]  # the reference's and its dark frame's data
    shading: Tensor | None  # compared by value: the near-light pipeline computes it afresh in every call
    terms: tuple[Tensor, Tensor, bool]


#: How many cards' terms are kept, the latest first: a batch run flat-fields every sample with one card, and a
#: comparison of the two solvers alternates two sets of terms for it (near light's card is smoothed with its shading).
_KEPT_CARDS = 2
_kept_cards: list[_CardEntry] = []


def _forget(key: tuple, _: weakref.ref) -> None:
    """Drop the kept terms once their card (or its dark frame) is freed."""
    _kept_cards[:] = [entry for entry in _kept_cards if entry.key != key]


def _data_of(x: Tensor) -> tuple[Tensor, tuple]:
    """The tensor that owns ``x``'s data (its base, for a view) and where ``x`` lies in it: a view made afresh
    in every call (``dark[:1]``) of unchanged data gives the same pair (a view shares its base's version)."""
    base = x if x._base is None else x._base
    return base, (id(base), x.storage_offset(), tuple(x.shape), x.stride(), x._version)


def _card_terms(reference: Tensor, reference_dark: Tensor | None, originals: tuple[Tensor, Tensor | None],
                images: Tensor, card_albedo: float, min_reference: float,
                saturation_level: float | None, smoothing_px: float | None = None,
                shading: Tensor | None = None) -> tuple[Tensor, Tensor, bool]:
    """The card's scale ``card_albedo / (R - D_R)`` (0 where not trusted), where it is trusted, and whether it
    is everywhere: everything that depends on the card alone, computed at the card's size, not per sample.

    The last :data:`_KEPT_CARDS` cards' terms are kept while the caller's reference (and dark) data (``originals``,
    before any reshaping view: the tensors that own their data, and where they lie in it) are alive and unmodified
    (same ``_version``), the shading is equal (compared by value: a light model computes it afresh), and none needs
    a gradient: a batch run passes one card with every batch, and its ten passes over the card (a third of the
    flat-field's time at batch 4; with near light's smoothing and shading, half a second) are then done once, also
    when the caller slices the card's dark frame afresh in every call. The card's test for NaN and infinities runs
    with the terms: a kept card was tested when they were computed (8 of the ~40 passes over a capture's worth of
    memory that a flat-field, normals and Frankot–Chellappa make per capture, were that test on an unchanged card).
    """
    cacheable = not any(x is not None and x.requires_grad for x in (*originals, shading))
    owners, wheres = zip(*((None, None) if x is None else _data_of(x) for x in originals), strict=True)
    key = (wheres, images.dtype, images.device, card_albedo, min_reference, saturation_level, smoothing_px,
           None if shading is None else (tuple(shading.shape), shading.dtype, shading.device))
    for entry in _kept_cards if cacheable else []:
        if (entry.key == key and all((ref is None and owner is None) or (ref is not None and ref() is owner)
                                     for ref, owner in zip(entry.sources, owners, strict=True))
                and (shading is None or (entry.shading is not None and torch.equal(entry.shading, shading)))):
            return entry.terms  # a card already checked for NaN and infinities, unchanged since
    converted = check_finite(reference, "reference").to(images)
    card = converted if reference_dark is None else converted - reference_dark.to(images)
    unsaturated = None if saturation_level is None else converted < saturation_level
    if shading is not None and unsaturated is not None:
        # a reading at the dark level is missing too: a flat-field capture written by `psmini calibrate flatfield`
        # stores the card's saturated pixels as the dark frame (a reference of 0)
        card, unsaturated = fill_saturated_card(card, unsaturated & (card > 0), shading.to(card))
    if smoothing_px is not None:
        card = smooth_card(card, smoothing_px, unsaturated)
    trusted = (card > min_reference * card.amax(dim=(-2, -1), keepdim=True)) & (card > 0)
    if unsaturated is not None:
        trusted = trusted & unsaturated
    # the scale is card_albedo / card where trusted and 0 elsewhere (an infinite denominator gives the 0 with a
    # zero gradient, where a 0/0 would send NaN back)
    scale = card_albedo / torch.where(trusted, card, torch.inf)
    terms = (scale, trusted, bool(trusted.all()))
    if cacheable:
        entry = _CardEntry(key, tuple(None if owner is None else weakref.ref(owner, partial(_forget, key))
                                      for owner in owners), shading, terms)
        _kept_cards[:] = [entry, *(kept for kept in _kept_cards if kept.key != key)][:_KEPT_CARDS]
    return terms


def fill_saturated_card(card: Tensor, unsaturated: Tensor, shading: Tensor) -> tuple[Tensor, Tensor]:
    r"""The card's saturated readings predicted from the unsaturated ones of the same pixel and a light model.

    A matte card reads :math:`R_k(x) = g(x)\,S_k(x)` under LED k: the camera's gain, vignetting and the card's
    albedo, common to the LEDs, times the LED's shading :math:`S_k = E_k\,l_{k,z}` on the card. Where some LEDs
    saturate it (the ones nearest a corner of the field), :math:`g` is fitted to the pixel's unsaturated readings by
    least squares, :math:`\hat g = \sum_j R_j S_j / \sum_j S_j^2`, and the saturated ones become
    :math:`\hat g\,S_k`. Exact for an exact model (the error of the model's shading between LEDs otherwise); a
    pixel with no unsaturated reading keeps its readings, still saturated. Differentiable in ``card`` and
    ``shading``.

    Args:
        card: dark-subtracted card images, :math:`(B, K, H, W)`.
        unsaturated: bool map of the card's unsaturated readings, the card's shape.
        shading: :math:`S_k(x)`, :math:`(B|1, K|1, H, W)`, positive where the LED lights the card.

    Returns:
        the completed card and the map of its readings that are now usable (the unsaturated ones and the
        predicted ones).

    Raises:
        ShapeError: when ``unsaturated`` does not have the card's shape or ``shading`` does not fit it.

    Example:
        >>> shading = torch.tensor([1.0, 2.0, 4.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
        >>> card = (0.3 * shading).clamp(max=1.0)    # the third LED saturates the card (1.2 clipped at 1.0)
        >>> filled, usable = fill_saturated_card(card, card < 1.0, shading)
        >>> [round(float(v), 4) for v in filled[0, :, 0, 0]], bool(usable.all())
        ([0.3, 0.6, 1.2], True)
    """
    check_shape(card, ["B", "K", "H", "W"], "card")
    if unsaturated.shape != card.shape:
        raise ShapeError(f"unsaturated must have the card's shape {tuple(card.shape)}, got {tuple(unsaturated.shape)}")
    if shading.ndim != 4 or shading.shape[-2:] != card.shape[-2:] or shading.shape[1] not in (1, card.shape[1]):
        raise ShapeError(f"shading must be (B|1, K|1, H, W) for the card's shape {tuple(card.shape)}, got "
                         f"{tuple(shading.shape)}")
    weight = (unsaturated & (card > 0)).to(card.dtype)
    gain, fitted = _common_gain(card, shading, weight)
    predicted = ~unsaturated & (fitted > 0) & (shading > 0)
    return torch.where(predicted, gain * shading, card), unsaturated | predicted


#: Least share of a pixel's window (in Gaussian weight) that must hold usable card pixels for :func:`smooth_card`
#: to fit there; a pixel with less keeps its reading.
_MIN_CARD_SUPPORT = 0.1


def _gaussian_taps(sigma: float, like: Tensor) -> list[Tensor]:
    """A Gaussian window of ``sigma`` pixels out to 3 sigma, normalised to sum 1, and its moments up to the fourth:
    the taps times the offset (in units of sigma) to the powers 0 to 4."""
    radius = max(1, math.ceil(3 * sigma))
    offset = torch.arange(-radius, radius + 1, device=like.device, dtype=like.dtype) / sigma
    taps = torch.exp(-0.5 * offset.square())
    taps = taps / taps.sum()
    return [taps * offset**power for power in range(5)]


def _window_sums(x: Tensor, taps: list[Tensor], powers: list[tuple[int, int]]) -> dict[tuple[int, int], Tensor]:
    """Sums over each pixel's window of ``x`` (N, C, H, W) weighted by separable taps, zero outside the image, for
    each ``(u, v)`` of ``powers``: ``taps[u]`` weights the offset within a row, ``taps[v]`` the offset within a
    column. The pass along the rows is made once for each ``u`` and shared by its column passes.

    Each pass is the sum of the taps times shifted views of the zero-padded image: 12 times faster than ``conv2d``
    with a 1 × 19 kernel on one channel, which torch's CPU build runs as a general convolution (76 against 6.4 ms on
    8 × 400², one thread).
    """
    rows = {u: _tap_sum(x, taps[u], -1) for u in dict.fromkeys(u for u, _ in powers)}
    return {(u, v): _tap_sum(rows[u], taps[v], -2) for u, v in powers}


def _tap_sum(x: Tensor, taps: Tensor, dim: int) -> Tensor:
    """The sum of ``taps`` times ``x`` shifted along ``dim`` (-1 or -2) by each tap's offset, zero outside."""
    radius, size = taps.numel() // 2, x.shape[dim]
    padded = F.pad(x, (radius, radius) if dim == -1 else (0, 0, radius, radius))
    total = taps[0] * padded.narrow(dim, 0, size)
    for i in range(1, taps.numel()):
        total = total + taps[i] * padded.narrow(dim, i, size)
    return total


def smooth_card(card: Tensor, sigma_px: float = 5.0, usable: Tensor | None = None) -> Tensor:
    r"""The dark-subtracted card images with their noise smoothed away, keeping what is common to every LED.

    A matte card under LED k reads :math:`R_k(x) = g(x)\,E_k(x)`: the camera's gain :math:`g` (vignetting and the
    pixels' own response, which need not be smooth) times the LED's irradiance and foreshortening :math:`E_k`,
    which vary over millimetres. So each LED's ratio to the mean over the LEDs, :math:`E_k / \bar E`, is smooth:
    it is replaced by a local quadratic fit in a Gaussian window of ``sigma_px`` (normalised convolution with a
    quadratic basis, Knutsson and Westin, "Normalized and differential convolution", CVPR 1993), weighted to the
    pixels where every LED is usable, which has no bias on a quadric and none at the image's borders (a local
    linear fit errs by :math:`\sigma^2/2` times the share's curvature: near LEDs' shares curve over millimetres,
    and at 64² over the rig's 10 mm field, 3 pixels being 0.47 mm, that bias put the noise-free minimum of a
    self-calibration 0.7 mm from the true LEDs, 0.18 mm with the quadratic fit). Where the window's usable pixels
    do not pin a quadric (along a line) the local linear fit is kept. Then each
    pixel's common factor is fitted back to its own readings by least squares over its usable LEDs:
    :math:`\hat R_k = \hat g\,\hat s_k` with :math:`\hat g = \sum_k R_k \hat s_k / \sum_k \hat s_k^2`. The
    card's noise in the LED-dependent part, which every flat-fielded capture inherits, shrinks by about the
    window's size; the common part keeps :math:`1/\sqrt{K}` of it, which scales a pixel's readings together and
    leaves its normal alone. Pixels whose window holds less than a tenth of usable weight, or not usable
    themselves, keep their readings.

    Args:
        card: dark-subtracted card images, shape :math:`(B, K, H, W)` (linear values; :math:`B` is usually 1).
        sigma_px: standard deviation of the Gaussian window, pixels (positive; the window reaches 3 sigma). The
            default, 5, leaves the LED-dependent part of an 8-bit card 1.4e-3 of noise, as much as the local
            linear fit over 3 pixels did (a quadratic fit over the same window keeps 1.6 times the linear one's).
        usable: optional bool map of the card readings to fit to (e.g. unsaturated), :math:`(B, K, H, W)`;
            readings at or below 0 are never used.

    Returns:
        the denoised card, shape and dtype of ``card``. Differentiable with respect to ``card``.

    Raises:
        ShapeError: when ``card`` is not :math:`(B, K, H, W)` or ``usable`` does not match it.
        InputError: when ``card`` holds NaN/inf or ``sigma_px`` is not a positive number.

    Example:
        >>> seeded = torch.Generator().manual_seed(0)
        >>> u = torch.linspace(-1, 1, 32).view(1, 1, 1, 32)
        >>> gain = 0.8 + 0.1 * torch.rand(1, 1, 32, 32, generator=seeded)  # pixel to pixel, common to the LEDs: kept
        >>> card = gain * torch.cat([1 + 0.3 * u, 1 - 0.3 * u], dim=1)  # two LEDs, linear irradiance
        >>> bool(torch.allclose(smooth_card(card, 2.0), card, rtol=1e-5))
        True
        >>> noisy = card + 0.01 * torch.randn(card.shape, generator=seeded)
        >>> share = lambda c: c / c.mean(dim=1, keepdim=True)  # each LED's part, which the normals see
        >>> bool((share(smooth_card(noisy, 2.0)) - share(card)).std() < 0.5 * (share(noisy) - share(card)).std())
        True
    """
    check_shape(card, ["B", "K", "H", "W"], "card")
    check_finite(card, "card")
    sigma = check_positive(sigma_px, "sigma_px")
    positive = card > 0
    if usable is not None:
        if not isinstance(usable, Tensor) or usable.shape != card.shape:
            raise ShapeError(f"usable must be a bool tensor of the card's shape {tuple(card.shape)}, got "
                             f"{getattr(usable, 'shape', type(usable).__name__)}")
        positive = positive & usable.bool()
    weight = positive.to(card.dtype)
    mean = (card * weight).sum(dim=1, keepdim=True) / weight.sum(dim=1, keepdim=True).clamp_min(1)
    ratio = card / torch.where(mean > 0, mean, torch.ones_like(mean))
    window = positive.all(dim=1, keepdim=True).to(card.dtype)  # pixels where every LED is usable
    taps = _gaussian_taps(sigma, card)
    moments = _window_sums(window, taps, [(u, v) for u in range(5) for v in range(5 - u)])
    basis = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))  # powers of the offsets (u along a row, v down)
    weighted = ratio * window
    sums = list(_window_sums(weighted, taps, list(basis)).values())  # each (B, K, H, W), in the basis' order
    linear, plane_pinned = _linear_fit([moments[key] for key in basis], sums[:3])
    quadratic, quadric_pinned = _quadratic_fit(moments, basis, sums)
    fitted = torch.where(quadric_pinned, quadratic, linear)
    shape = torch.where((moments[(0, 0)] >= _MIN_CARD_SUPPORT) & (quadric_pinned | plane_pinned), fitted, ratio)
    common, _ = _common_gain(card, shape, weight)
    return torch.where(positive, common * shape, card)


def _common_gain(card: Tensor, shape: Tensor, weight: Tensor) -> tuple[Tensor, Tensor]:
    """Each pixel's gain common to its LEDs, fitted to its card readings by weighted least squares,
    :math:`\\hat g = \\sum_k w_k R_k S_k / \\sum_k w_k S_k^2`, and the denominator (0 where no reading counts):
    ``(B, 1, H, W)`` each, from the card ``(B, K, H, W)``, each LED's ``shape`` and the readings' ``weight``."""
    support = (shape.square() * weight).sum(dim=1, keepdim=True)
    return (card * shape * weight).sum(dim=1, keepdim=True) / support.clamp_min(torch.finfo(card.dtype).tiny), support


def _linear_fit(moments: list[Tensor], sums: list[Tensor]) -> tuple[Tensor, Tensor]:
    """The local linear fit's value at each window's centre from its six moments (1, u, v, u², uv, v²) and the
    windowed sums of the data times 1, u, v; and where the window pins a plane (elsewhere the value means nothing)."""
    m00, m10, m01, m20, m11, m02 = moments
    (c00, c01, c02, _, _, _), det, well_posed = _symmetric_adjugate(m00, m10, m01, m20, m11, m02)
    fitted = (c00 * sums[0] + c01 * sums[1] + c02 * sums[2]) / torch.where(well_posed, det, torch.ones_like(det))
    return fitted, well_posed


def _quadratic_fit(moments: dict[tuple[int, int], Tensor], basis: tuple[tuple[int, int], ...],
                   sums: list[Tensor]) -> tuple[Tensor, Tensor]:
    """The local quadratic fit's value at each window's centre: the first row of the 6 × 6 moment matrix's inverse
    (by Cholesky in float64, one per pixel, shared by the LEDs) times the windowed sums; and where that matrix is
    well conditioned (no pivot under 10⁻⁸ of the largest moment; elsewhere the value means nothing)."""
    matrix = torch.stack([torch.stack([moments[(a[0] + b[0], a[1] + b[1])] for b in basis], -1) for a in basis], -2)
    matrix = matrix.double()  # (B, 1, H, W, 6, 6)
    factor, info = torch.linalg.cholesky_ex(matrix)
    pivots = factor.diagonal(dim1=-2, dim2=-1).square()
    well_posed = (info == 0) & (pivots.amin(-1) > 1e-8 * matrix.diagonal(dim1=-2, dim2=-1).amax(-1))
    unit = torch.zeros(6, 1, dtype=matrix.dtype, device=matrix.device)
    unit[0] = 1
    safe = torch.where(well_posed[..., None, None], factor, torch.eye(6, dtype=matrix.dtype, device=matrix.device))
    row = torch.cholesky_solve(unit.expand(*safe.shape[:-2], 6, 1), safe)[..., 0].to(sums[0].dtype)  # (B,1,H,W,6)
    fitted = row[..., 0] * sums[0]
    for j in range(1, 6):
        fitted = fitted + row[..., j] * sums[j]
    return fitted, well_posed


class FlatField(nn.Module):
    """Flat-fielding with a stored reference (card) capture; see :func:`flatfield`.

    Args:
        reference: the card under each LED, :math:`(K, H, W)` or :math:`(1, K, H, W)`.
        reference_dark: the card capture's dark frame, :math:`(H, W)`, :math:`(1, H, W)` or :math:`(1, 1, H, W)`.
        card_albedo: the card's albedo.
        min_reference: fraction of each LED's brightest card pixel below which it is not trusted.
        saturation_level: raw level at which pixels count as saturated, or ``None``.

    Example:
        >>> module = FlatField(torch.full((8, 16, 16), 0.5), card_albedo=0.8)
        >>> module(torch.rand(2, 8, 16, 16)).images.shape
        torch.Size([2, 8, 16, 16])
    """

    reference: Tensor  # buffers
    reference_dark: Tensor | None

    def __init__(
        self,
        reference: Tensor,
        reference_dark: Tensor | None = None,
        card_albedo: float = 1.0,
        min_reference: float = 0.02,
        saturation_level: float | None = None,
    ) -> None:
        super().__init__()
        check_tensor(reference, "reference")
        self.register_buffer("reference", reference)
        self.register_buffer("reference_dark", reference_dark)
        self.card_albedo, self.min_reference, self.saturation_level = card_albedo, min_reference, saturation_level

    def forward(self, images: Tensor, dark: Tensor | None = None) -> FlatFieldResult:
        """Flat-field ``images`` :math:`(B, K, H, W)` with the stored reference."""
        reference_dark = self.reference_dark if self.reference_dark is not None else dark
        return flatfield(
            images, self.reference, dark, reference_dark, self.card_albedo, self.min_reference, self.saturation_level
        )
