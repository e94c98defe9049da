"""Integrators on the full rectangle by fast transforms: Frankot–Chellappa (FFT/DCT) and a DCT Poisson solver."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from psmini._checks import all_true, records_gradient
from psmini.errors import InputError
from psmini.integrate._common import centred_grid, check_gradients, masked_mean
from psmini.integrate._dct import (
    Plan,
    complex_dtype,
    dct2,
    from_reordered_spectrum,
    half_spectra,
    halves,
    idct2,
    inverse_spectrum,
    reordered_spectrum,
)
from psmini.integrate._dct import plan as dct_plan

__all__ = ["frankot_chellappa", "FrankotChellappa", "dct_poisson", "DCTPoisson"]

_FC_BOUNDARIES = ("mirror", "periodic")


def _mirror(gu: Tensor, gv: Tensor) -> tuple[Tensor, Tensor]:
    """Extend pixel-grid gradients to ``(2H, 2W)`` as the gradients of the even (mirrored) depth.

    The depth is mirrored about the half-pixel beyond each edge, so its column derivative is odd under a
    left-right flip and even under an up-down flip (and the other way round for the row derivative). Kept as
    the reference of the tests: :func:`_mirror_item` solves the same problem on the ``(H, W)`` grid.
    """
    gu = torch.cat([gu, -gu.flip(-1)], dim=-1)
    gv = torch.cat([gv, gv.flip(-1)], dim=-1)
    gu = torch.cat([gu, gu.flip(-2)], dim=-2)
    gv = torch.cat([gv, -gv.flip(-2)], dim=-2)
    return gu, gv


def _fc_periodic(gu: Tensor, gv: Tensor) -> Tensor:
    """Least-squares periodic surface for pixel-grid gradients ``(B, 1, H, W)``, zero mean (Frankot–Chellappa)."""
    height, width = gu.shape[-2:]
    # Angular frequencies in radians per pixel; the spectral derivative of exp(i w u) is i w.
    wu = 2 * math.pi * torch.fft.rfftfreq(width, device=gu.device, dtype=gu.dtype).view(1, 1, 1, -1)
    wv = 2 * math.pi * torch.fft.fftfreq(height, device=gu.device, dtype=gu.dtype).view(1, 1, -1, 1)
    denom = wu**2 + wv**2
    denom[..., 0, 0] = 1.0  # the mean is free: its numerator is zero, keep the division finite
    # z^ = -i (wu gu^ + wv gv^) / (wu² + wv²): real factors first, so that each transform is multiplied once by a
    # real array (complex-by-complex products and a complex division cost several times more per element)
    spectrum = torch.fft.rfft2(gu) * (wu / denom) + torch.fft.rfft2(gv) * (wv / denom)
    return torch.fft.irfft2(spectrum * -1j, s=(height, width))


class _MirrorReference(NamedTuple):
    """Constants of the reference steps of the mirrored solve between its two FFTs (:func:`_reference_solution`),
    in float64 on the CPU: the plan's spectral map and its other constants are derived from them."""

    transform: Plan
    along_u: Tensor  # (H, W): -w_u / (w_u² + w_v²), 0 at (0, 0), signed as the halves it multiplies
    along_v: Tensor  # (H, W): -w_v / (w_u² + w_v²), 0 at (0, 0), signed likewise
    flipped_rows: Tensor  # k_v -> (H - k_v) mod H
    nyquist: Tensor  # (W, W): a DCT row at k_v = 0 -> the doubled grid's Nyquist row profile along u


class _MirrorPlan(NamedTuple):
    """Constants of the mirrored Frankot–Chellappa solve on one (H, W) grid, pitch, device and dtype."""

    transform: Plan
    scale: Tensor  # (1, 2, H, W): pitch (-1)^u for gu, -pitch (-1)^v for gv (the signs turn DCTs into DSTs)
    reordered_scale: Tensor  # (1, 2, H, W): ``scale`` in the transform's reordering (Makhoul's interleaving)
    spectral_map: Tensor  # (2, 8, H, K): the solution's spectrum (real, imaginary) from the 8 planes of
    # :func:`_solution_spectrum` (real and imaginary parts of both transforms, at k_v and at -k_v)
    first_row: Tensor  # (2 K, W): channel 1's row k_v = 0 (real, imaginary interleaved) -> the Nyquist row profile
    row_ramp: Tensor  # (K,) complex: the spectrum's row k_v = 0 for a unit mean slope p0 (the plane less what the
    # solve of the unit slope gives)
    column_ramp: Tensor  # (H,) complex: the spectrum's column k_u = 0 for a unit mean slope q0, likewise
    corner: Tensor  # () complex: the spectrum at (0, 0) of a unit DCT coefficient there
    alternating: Tensor  # (H, 1): (-1)^v
    nyquist_mean: Tensor  # (W, 1): r -> 4 H W times the grid mean of (-1)^v r(u)


@functools.lru_cache(maxsize=16)
def _mirror_plan(height: int, width: int, pitch: float, device: torch.device, dtype: torch.dtype) -> _MirrorPlan:
    """Build the constants of :func:`_mirror_item` (in float64, then cast)."""
    f64 = torch.float64
    ku, kv = torch.arange(width, dtype=f64), torch.arange(height, dtype=f64)
    alternating = (1 - 2 * (kv % 2)).view(height, 1)
    scale = torch.stack([pitch * (1 - 2 * (ku % 2)).view(1, width).expand(height, width),
                         -pitch * alternating.expand(height, width)]).view(1, 2, height, width)
    # DCT-II of a plane f(u) over the grid: 2 H DCT_u(f) on the row k_v = 0 (and likewise for f(v))
    u = torch.arange(width, dtype=f64) + 0.5
    cos_u = torch.cos(math.pi * ku.view(width, 1) * u.view(1, width) / width)
    cos_v = torch.cos(math.pi * kv.view(height, 1) * (kv + 0.5).view(1, height) / height)
    ramp_u = 2 * height * pitch * (2 * cos_u @ (u - width / 2))
    ramp_v = -2 * width * pitch * (2 * cos_v @ (kv + 0.5 - height / 2))
    nyquist_mean = torch.full((width, 1), 4.0 * float(alternating.sum()))  # 4 H W * sum_v (-1)^v / H * mean_u
    reference = _mirror_reference(height, width)
    transform = reference.transform
    # the solution's coefficients for p = 1, q = 0 (all on the row k_v = 0) and for p = 0, q = 1 (all on the
    # column k_u = 0), neither with a Nyquist row: what the mean slopes add when they are not taken out first
    unit = _reference_coefficients(*half_spectra(scale * torch.eye(2, dtype=f64).view(2, 2, 1, 1), transform),
                                   reference)[0]
    ramps = torch.zeros(2, height, width, dtype=f64)
    ramps[0, 0], ramps[1, :, 0] = ramp_u - unit[0, 0, 0], ramp_v - unit[1, 0, :, 0]
    ramps = inverse_spectrum(ramps, transform)  # each lies on one row or one column of the spectrum
    complex_ = complex_dtype(dtype)
    reordered_scale = scale.flatten(2)[..., transform.order].view(1, 2, height, width)
    return _MirrorPlan(
        dct_plan(height, width, device, dtype),
        scale.to(device, dtype),
        reordered_scale.to(device, dtype),
        _spectral_map(reference, height, width).to(device, dtype),
        _first_row_map(reference, width).to(device, dtype),
        ramps[0, 0].to(device, complex_),
        ramps[1, :, 0].to(device, complex_),
        transform.inverse[0, 0].to(device, complex_),
        alternating.to(device, dtype),
        nyquist_mean.to(device, dtype),
    )


def _mirror_reference(height: int, width: int) -> _MirrorReference:
    """The constants of :func:`_reference_coefficients` on an ``(height, width)`` grid (float64, CPU)."""
    f64 = torch.float64
    ku, kv = torch.arange(width, dtype=f64), torch.arange(height, dtype=f64)
    wu, wv = (math.pi * ku / width).view(1, width), (math.pi * kv / height).view(height, 1)
    denom = wu**2 + wv**2
    denom[0, 0] = 1.0
    u = torch.arange(width, dtype=f64) + 0.5
    nyquist = (-math.pi / ((wu**2 + math.pi**2) * 2 * height * width)).view(width, 1) * torch.sin(
        math.pi * ku.view(width, 1) * u.view(1, width) / width
    )
    # the columns that come from the negated imaginary halves: 1..R of T_u, W-R..W-1 of the DCT of gv (-1)^v
    right = (width - 1) // 2
    along_u, along_v = -wu / denom, (-wv / denom).expand(height, width).clone()
    along_u[:, 1 : right + 1] *= -1
    along_v[:, width - right :] *= -1
    nyquist[width - right :] *= -1
    return _MirrorReference(dct_plan(height, width, torch.device("cpu"), f64), along_u, along_v,
                            (height - torch.arange(height)) % height, nyquist)


def _reference_coefficients(real: Tensor, negated: Tensor, reference: _MirrorReference) -> tuple[Tensor, Tensor]:
    r"""Frankot–Chellappa of the mirrored :math:`(2H, 2W)` extension, on the :math:`(H, W)` grid, as coefficients.

    ``real`` and ``negated`` are the :func:`~psmini.integrate._dct.halves` :math:`(B, 2, H, K)` of the DCT-II of
    the pixel-grid gradients times the plan's ``scale``: :math:`(-1)^u g_u` and :math:`(-1)^v g_v`. Returns the
    DCT-II coefficients :math:`(B, 1, H, W)` of the solution and the Nyquist row's profile :math:`r`
    :math:`(B, 1, 1, W)`: the depth is ``idct2(coefficients) + (-1)^v r``.

    The mirrored depth is even about the half-pixel beyond each edge, so its spectrum on the doubled grid is its
    DCT-II up to a half-sample phase, and the odd extensions of the gradients give sine transforms: the
    doubled-grid solution is :math:`\mathrm{IDCT}[-(\omega_u T_u + \omega_v T_v)/(\omega_u^2 + \omega_v^2)]`
    with :math:`\omega = \pi k / N`, :math:`T_u = \mathrm{DCT}_v \mathrm{DST}_u\, g_u` and
    :math:`T_v = \mathrm{DST}_v \mathrm{DCT}_u\, g_v` (a DST-II is the DCT-II of :math:`(-1)^n x` read at
    :math:`N - k`), plus the doubled grid's Nyquist row :math:`k_v = H`, whose derivative weight the FFT does
    not make odd: :math:`(-1)^v r(u)`, :math:`r` a sine series of the DCT of :math:`(-1)^v g_v` at :math:`k_v = 0`.

    These are the steps the plan's spectral map replaces (:func:`_spectral_map`), kept as its definition.
    """
    right = reference.transform.right
    # T_u[k_u] = DCT[(-1)^u g_u][W - k_u]: the imaginary half in place, the real half reversed (k_u = 0 unused);
    # the imaginary halves come negated, and their signs are folded into the weights
    t_u = torch.cat([real[:, 0:1, :, 0:1], negated[:, 0:1, :, 1 : right + 1], real[:, 0:1, :, 1:].flip(-1)], dim=-1)
    b = _row_transform(real[:, 1:2], negated[:, 1:2], right)  # DCT[(-1)^v g_v], signed
    coefficients = torch.addcmul(reference.along_u * t_u, reference.along_v,
                                 b.index_select(-2, reference.flipped_rows))
    return coefficients, b[..., 0:1, :] @ reference.nyquist


def _row_transform(real: Tensor, negated: Tensor, right: int) -> Tensor:
    """The DCT of the second channel along its rows, signed as the weights expect, from its two halves."""
    return torch.cat([real, negated[..., 1 : right + 1].flip(-1)], dim=-1)


def _reference_solution(spectrum: Tensor, reference: _MirrorReference) -> Tensor:
    """The reference steps from the gradients' :func:`~psmini.integrate._dct.reordered_spectrum` (B, 2, H, K) to
    the solution's (B, 1, H, K), without the mean slopes and the Nyquist row (see :func:`_reference_coefficients`)."""
    coefficients, _ = _reference_coefficients(*halves(spectrum, reference.transform), reference)
    return inverse_spectrum(coefficients, reference.transform)


def _spectral_map(reference: _MirrorReference, height: int, width: int) -> Tensor:
    r"""The solution's spectrum as a per-frequency linear map of the gradients' (:func:`_solution_spectrum`),
    ``(2, 8, H, K)`` float64, found by applying the reference steps to unit spectra.

    Every step between the two FFTs (twiddle products, the row negation :math:`k_v \to -k_v`, the halves'
    rearrangement into sine and cosine transforms, the weights, the inverse DCT's index flips) is real-linear and
    maps the frequency :math:`(k_v, k_u)` of the output from :math:`(\pm k_v, k_u)` of the input alone (a test
    checks it). So the output at :math:`(k_v, k_u)` is a real 2 × 8 matrix times the real and imaginary parts of
    both gradients' spectra at :math:`k_v` and at :math:`-k_v`. Eight probes find all of them: each puts a unit real
    or imaginary value in one channel, on the rows of one of two sets that hold one row of each pair
    :math:`\{k_v, -k_v\}` (a row that is its own partner, 0 and H/2, counts as the first of its pair).
    """
    k = width // 2 + 1
    rows = torch.arange(height)
    partner_rows = (-rows) % height
    first = (rows > 0) & (rows < partner_rows)  # one row of each pair of distinct rows
    on_first = first.view(height, 1)
    own, partner = [], []
    for channel, unit in ((c, u) for c in range(2) for u in (1.0, 1j)):  # the planes' order in _solution_spectrum
        probes = torch.zeros(2, 2, height, k, dtype=torch.complex128)  # a plane at a time: 5 MB at 400^2
        # torch takes a Python complex into a complex tensor; its stubs list int | float | bool only
        probes[0, channel, first], probes[1, channel, ~first] = unit, unit  # type: ignore[assignment]
        on, off = _reference_solution(probes, reference)[:, 0]
        own.append(torch.where(on_first, on, off))
        partner.append(torch.where(on_first, off, on))
    both = torch.stack(own + partner)  # (8, H, K) complex: the 8 planes' unit responses
    both[4:, rows == partner_rows] = 0  # a row that is its own partner: its own response holds both
    return torch.stack([both.real, both.imag])


def _first_row_map(reference: _MirrorReference, width: int) -> Tensor:
    """The Nyquist row profile :math:`r` (W,) as a matrix ``(2 K, W)`` of the real and imaginary parts
    (interleaved) of the second channel's spectrum on its row k_v = 0, from :func:`_reference_coefficients`'s
    steps on that row (the halves' row 0 depends on the spectrum's row 0 alone)."""
    transform, k = reference.transform, width // 2 + 1
    units = torch.view_as_complex(torch.eye(2 * k, dtype=torch.float64).view(2 * k, k, 2))
    row = (transform.forward[0, 0] + transform.forward[1, 0]) * units  # the halves' row 0, P + conj(Q) there
    return _row_transform(row.real, row.imag, transform.right) @ reference.nyquist


def _solution_spectrum(spectrum: Tensor, plan: _MirrorPlan) -> Tensor:
    """The solution's spectrum (B, 1, H, K) from the gradients' (B, 2, H, K) by the plan's spectral map.

    Sixteen real products over contiguous planes where the reference steps (:func:`_reference_solution`) make
    some forty passes over strided and complex arrays (in the cache, a product over the strided real view of a
    complex array took 44 us, over a contiguous plane 8): 0.74 against 1.39 ms on 400^2 on one thread of the 2-core
    Xeon.
    """
    planes = torch.stack([spectrum.real, spectrum.imag], dim=2).flatten(1, 2)  # (B, 4, H, K)
    partners = planes.index_select(-2, plan.transform.negated)  # the same at -k_v
    weights = plan.spectral_map
    real, imag = weights[0, 0] * planes[:, 0:1], weights[1, 0] * planes[:, 0:1]
    for j in range(1, 8):
        source = (planes if j < 4 else partners)[:, j % 4 : j % 4 + 1]
        real.addcmul_(weights[0, j], source)
        imag.addcmul_(weights[1, j], source)
    return torch.complex(real, imag)


def frankot_chellappa(
    p: Tensor, q: Tensor, pixel_pitch_mm: float = 1.0, boundary: str = "mirror", mask: Tensor | None = None
) -> Tensor:
    r"""Depth from surface gradients by Frankot–Chellappa's Fourier projection, keeping the mean slope.

    Frankot and Chellappa (TPAMI 1988) project the gradient field onto the integrable fields with the FFT:
    :math:`\hat z = (-i\omega_u \hat g_u - i\omega_v \hat g_v)/(\omega_u^2 + \omega_v^2)`. The zero frequency
    carries no slope, so the classical method returns a tilted plane flat. Here the mean slope
    :math:`(\bar p, \bar q)` is subtracted before the transform and the plane :math:`\bar p x + \bar q y` added
    back, so planes come back exactly. ``boundary="mirror"`` integrates the mirrored :math:`(2H, 2W)` extension
    (even depth, no periodic wrap-around), ``"periodic"`` the rectangle as a torus.

    The mirrored problem is solved on the :math:`(H, W)` grid itself, with no :math:`2H \times 2W` transform: the
    even extension's spectrum is its DCT-II and the odd extensions of the gradients give sine transforms
    (Simchony, Chellappa and Shao, "Direct analytical methods for solving Poisson equations in computer vision
    problems", TPAMI 1990), computed with Makhoul's N-point DCT from real FFTs (IEEE Trans. ASSP 1980; see
    :mod:`psmini.integrate._dct`). Every step between the forward and the inverse FFT is linear and maps each
    frequency from itself and its row-negated partner alone, so those steps run as one per-frequency map
    precomputed from them (sixteen real products per frequency). The result is the doubled-grid FFT solution's,
    Nyquist row included, to float rounding (1e-14 relative in float64).

    Args:
        p: :math:`\partial z/\partial x`, shape :math:`(B, 1, H, W)`, camera frame (x right).
        q: :math:`\partial z/\partial y`, shape :math:`(B, 1, H, W)`, camera frame (y up; image rows grow
            downward, so the derivative along a row index is :math:`-q`).
        pixel_pitch_mm: size of one pixel on the surface in mm (the step of x and y).
        boundary: ``"mirror"`` (default) or ``"periodic"``.
        mask: optional pixels to trust, shape :math:`(B, 1, H, W)` (bool, or float weights). The mean slope is
            taken over the mask and the gradients outside it are replaced by that mean slope (float weights
            :math:`w` blend: :math:`w g + (1 - w) \bar g`, with the weighted mean); the solve still runs on the
            whole rectangle (use ``integrate(..., method="masked")`` for a solve on the mask alone).

    Returns:
        height toward the camera in mm, shape :math:`(B, 1, H, W)`, with zero mean over the mask (over every
        pixel without a mask). Differentiable with respect to ``p``, ``q`` and float weights.

    Raises:
        ShapeError: when ``p`` and ``q`` differ in shape, are not :math:`(B, 1, H, W)`, or the mask does not fit.
        InputError: when the gradients hold NaN/inf, the pitch is not positive, or ``boundary`` is unknown.

    Example:
        >>> ys, xs = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
        >>> p, q = torch.full((1, 1, 8, 8), 0.2), torch.full((1, 1, 8, 8), -0.1)
        >>> z = frankot_chellappa(p, q, pixel_pitch_mm=0.5)
        >>> round(float(z[0, 0, 0, 1] - z[0, 0, 0, 0]), 4)  # 0.2 * 0.5 mm per column
        0.1
    """
    tested = isinstance(mask, Tensor) and mask.dtype == torch.bool and mask.shape == p.shape
    if tested and isinstance(mask, Tensor) and all_true(mask):
        mask = None  # an all-true mask: the same result without passes over it
    mask, pitch = check_gradients(p, q, mask, pixel_pitch_mm)
    if boundary not in _FC_BOUNDARIES:
        raise InputError(f"boundary must be one of {', '.join(_FC_BOUNDARIES)}, got {boundary!r}")
    height, width = p.shape[-2:]
    # a float (or broadcast) mask of ones: the same result without a pass over the mask per step (a bool mask of
    # the slopes' shape was tested above: comparing its float copy to 1 again took 0.78 ms on 4 x 400^2)
    if mask is not None and not tested and all_true(mask == 1):
        mask = None
    if boundary == "mirror":
        return _frankot_chellappa_mirror(p, q, pitch, mask)
    p0, q0 = masked_mean(p, mask), masked_mean(q, mask)
    # Residual slopes in mm per pixel step along columns (u) and rows (v, downward: -q).
    gu, gv = (p - p0) * pitch, -(q - q0) * pitch
    if mask is not None:
        gu, gv = gu * mask, gv * mask
    z = _fc_periodic(gu, gv)
    u, v = centred_grid(height, width, p)
    z = z + (p0 * u - q0 * v) * pitch
    return z - masked_mean(z, mask)


def _frankot_chellappa_mirror(p: Tensor, q: Tensor, pitch: float, mask: Tensor | None) -> Tensor:
    """The ``boundary="mirror"`` branch of :func:`frankot_chellappa` (checked inputs, float mask or None).

    On the CPU the batch is solved one item at a time: the ~25 passes of an item's transforms then stay in the
    core's cache (a batch of 8 took 3.0 ms per 400^2 item so, against 3.9-4.4 ms at once, in separate runs on
    this 2-core Xeon); on a GPU the whole batch runs at once. With no gradient to record, each item's depth is
    written straight into the batch's (concatenating the items afterwards was one more pass: 0.1 ms per item).
    """
    if p.device.type == "cpu" and p.shape[0] > 1:
        depth = None if records_gradient(p, q, mask) else p.new_empty(p.shape)
        items = [_mirror_item(p[i : i + 1], q[i : i + 1], pitch, None if mask is None else mask[i : i + 1],
                              None if depth is None else depth[i : i + 1])
                 for i in range(p.shape[0])]
        return torch.cat(items) if depth is None else depth
    return _mirror_item(p, q, pitch, mask)


def _reordered_slopes(p: Tensor, q: Tensor, plan: _MirrorPlan) -> Tensor:
    """The slopes times the plan's ``scale`` (B, 2, H, W), in the transform's reordering: the input of its real
    FFT, gathered straight from ``p`` and ``q`` (not differentiable: ``index_select`` into ``out``).

    Concatenating ``p`` and ``q``, scaling the pair and gathering it made three passes; gathering each slope into
    its half of one tensor and scaling that in place makes two (the concatenation was 0.12 ms of an item's 2.5 ms
    on 400^2, one thread of the 2-core Xeon).
    """
    batch, _, height, width = p.shape
    reordered = p.new_empty(batch, 2, height * width)
    for channel, slope in enumerate((p, q)):
        torch.index_select(slope.reshape(batch, -1), 1, plan.transform.order, out=reordered[:, channel])
    return reordered.view(batch, 2, height, width).mul_(plan.reordered_scale)


def _mirror_item(p: Tensor, q: Tensor, pitch: float, mask: Tensor | None, out: Tensor | None = None) -> Tensor:
    """:func:`_frankot_chellappa_mirror` on one batch (an item on the CPU), into ``out`` when given (no gradient
    recorded)."""
    height, width = p.shape[-2:]
    plan = _mirror_plan(height, width, pitch, p.device, p.dtype)
    # slopes in mm per pixel step along columns (u) and rows (v, downward: -q), with the DST signs; the mean
    # slopes are taken out in the spectrum below (p0 changes its row k_v = 0 only, q0 its column k_u = 0)
    if mask is None and not records_gradient(p, q):
        means = torch.cat([masked_mean(p, None), masked_mean(q, None)], dim=1)  # (B, 2, 1, 1): (p0, q0)
        spectrum = torch.fft.rfft2(_reordered_slopes(p, q, plan))
    else:
        pq = torch.cat([p, q], dim=1)
        means = masked_mean(pq, mask)
        if mask is not None:
            # the gradients outside the mask replaced by the mean slopes (weighted: m g + (1 - m) mean for a float
            # mask): the field's mean is then the masked mean, and the solve below keeps it as for an unmasked field
            pq = torch.lerp(means.expand_as(pq), pq, mask)
        spectrum = reordered_spectrum(pq.mul_(plan.scale), plan.transform)
    solution = _solution_spectrum(spectrum, plan)
    nyquist = torch.view_as_real(spectrum[:, 1:2, 0:1]).flatten(-2) @ plan.first_row  # (B, 1, 1, W)
    # the mean-slope plane and the zero mean: the plane p0 u - q0 v lives on the row k_v = 0 and the column
    # k_u = 0 of the DCT, a constant on (0, 0); the inverse DCT has zero mean but the Nyquist row not
    solution[..., 0, :] += means[:, 0:1, 0] * plan.row_ramp
    solution[..., :, 0] += means[:, 1:2, 0] * plan.column_ramp
    solution[..., 0, 0] -= (nyquist @ plan.nyquist_mean)[..., 0, 0] * plan.corner
    z = from_reordered_spectrum(solution, plan.transform, p.shape, out=out).addcmul_(plan.alternating, nyquist)
    if mask is None:
        return z
    return z - masked_mean(z, mask) if out is None else z.sub_(masked_mean(z, mask))  # zero mean over the mask


class FrankotChellappa(nn.Module):
    """Module form of :func:`frankot_chellappa` holding the pixel pitch and the boundary.

    Example:
        >>> integrator = FrankotChellappa(pixel_pitch_mm=0.025)
        >>> integrator(torch.zeros(2, 1, 16, 16), torch.zeros(2, 1, 16, 16)).shape
        torch.Size([2, 1, 16, 16])
    """

    def __init__(self, pixel_pitch_mm: float = 1.0, boundary: str = "mirror") -> None:
        super().__init__()
        self.pixel_pitch_mm, self.boundary = pixel_pitch_mm, boundary

    def forward(self, p: Tensor, q: Tensor, mask: Tensor | None = None) -> Tensor:
        return frankot_chellappa(p, q, self.pixel_pitch_mm, self.boundary, mask)


@functools.lru_cache(maxsize=16)
def _neumann_eigenvalues(height: int, width: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """Reciprocal eigenvalues ``(H, W)`` of the 5-point Neumann Laplacian in the DCT-II basis, 0 for the constant."""
    ku = torch.arange(width, dtype=torch.float64).view(1, width)
    kv = torch.arange(height, dtype=torch.float64).view(height, 1)
    eigen = (2 - 2 * torch.cos(math.pi * ku / width)) + (2 - 2 * torch.cos(math.pi * kv / height))
    eigen[0, 0] = math.inf  # the constant mode: its coefficient is zero for a solvable right side
    return (1 / eigen).to(device=device, dtype=dtype)


def _neumann_poisson(b: Tensor) -> Tensor:
    """Solve the 5-point Neumann Poisson problem ``L z = b`` (``b`` sums to 0) by the DCT, zero-mean ``z``.

    The DCT-II diagonalises the Neumann Laplacian (its eigenvalues are ``4 - 2 cos(pi k_u / W) - 2 cos(pi k_v / H)``);
    the transforms are N-point ones (:mod:`psmini.integrate._dct`).
    """
    return idct2(dct2(b) * _neumann_eigenvalues(b.shape[-2], b.shape[-1], b.device, b.dtype))


def dct_poisson(p: Tensor, q: Tensor, pixel_pitch_mm: float = 1.0, mask: Tensor | None = None) -> Tensor:
    r"""Depth from surface gradients by the least-squares (Neumann) Poisson solver with the DCT.

    Minimises :math:`\sum (z_{i,j+1} - z_{ij} - \bar g^u)^2 + (z_{i+1,j} - z_{ij} - \bar g^v)^2` over the
    rectangle, with the targets :math:`\bar g` the trapezoidal averages of the two pixels' gradients; its
    normal equations are the Poisson equation with natural (Neumann) boundaries, diagonalised by the DCT
    (Simchony, Chellappa and Shao, "Direct analytical methods for solving Poisson equations in computer
    vision problems", TPAMI 1990). Unlike Frankot–Chellappa it assumes no periodicity, so smooth
    non-periodic surfaces come back to second order in the pixel pitch.

    Args:
        p: :math:`\partial z/\partial x`, shape :math:`(B, 1, H, W)` (x right).
        q: :math:`\partial z/\partial y`, shape :math:`(B, 1, H, W)` (y up).
        pixel_pitch_mm: size of one pixel on the surface in mm.
        mask: optional pixels to trust :math:`(B, 1, H, W)`; edges leaving it get a zero target (the solve
            still covers the rectangle: use ``method="masked"`` for a solve on the mask alone).

    Returns:
        height toward the camera in mm, :math:`(B, 1, H, W)`, zero mean over the mask (every pixel without).
        Differentiable with respect to ``p`` and ``q``.

    Raises:
        ShapeError: when ``p`` and ``q`` differ in shape, are not :math:`(B, 1, H, W)`, or the mask does not fit.
        InputError: when the gradients hold NaN/inf or the pitch is not positive.

    Example:
        >>> z = dct_poisson(torch.full((1, 1, 6, 9), 0.5), torch.zeros(1, 1, 6, 9), pixel_pitch_mm=2.0)
        >>> round(float(z[0, 0, 3, 5] - z[0, 0, 3, 4]), 4)  # 0.5 * 2 mm per column
        1.0
    """
    mask, pitch = check_gradients(p, q, mask, pixel_pitch_mm)
    gu, gv = p * pitch, -q * pitch
    tu, tv = (gu[..., :, 1:] + gu[..., :, :-1]) / 2, (gv[..., 1:, :] + gv[..., :-1, :]) / 2
    if mask is not None:
        tu, tv = tu * mask[..., :, 1:] * mask[..., :, :-1], tv * mask[..., 1:, :] * mask[..., :-1, :]
    # Right side D^T t: the divergence of the edge targets.
    b = F.pad(tu, (1, 0)) - F.pad(tu, (0, 1)) + F.pad(tv, (0, 0, 1, 0)) - F.pad(tv, (0, 0, 0, 1))
    z = _neumann_poisson(b)
    return z - masked_mean(z, mask)


class DCTPoisson(nn.Module):
    """Module form of :func:`dct_poisson` holding the pixel pitch.

    Example:
        >>> DCTPoisson(0.025)(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8)).shape
        torch.Size([1, 1, 8, 8])
    """

    def __init__(self, pixel_pitch_mm: float = 1.0) -> None:
        super().__init__()
        self.pixel_pitch_mm = pixel_pitch_mm

    def forward(self, p: Tensor, q: Tensor, mask: Tensor | None = None) -> Tensor:
        return dct_poisson(p, q, self.pixel_pitch_mm, mask)
