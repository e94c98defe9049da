r"""Two-dimensional cosine transforms (DCT-II and its inverse) from real FFTs of the same size. Internal.

torch has no DCT. Makhoul ("A fast cosine transform in one and multiple dimensions", IEEE Trans. ASSP 28(1),
1980) computes the N-point DCT-II from one N-point FFT of the reordered sequence
:math:`v = (x_0, x_2, x_4, \dots, x_5, x_3, x_1)`: with :math:`V = \mathrm{FFT}(v)` and
:math:`\omega_k = e^{-i\pi k/(2N)}`, :math:`C_k = 2\,\mathrm{Re}(\omega_k V_k)`. In two dimensions one real 2-D FFT
of the array reordered along both axes gives, for the columns :math:`k_2 < K_2 = \lfloor N_2/2 \rfloor + 1` that
the real FFT keeps, with :math:`P = 2\omega_{k_1}\omega_{k_2} V_{k_1 k_2}` and
:math:`Q = 2\omega_{k_1}\bar\omega_{k_2} \overline{V_{-k_1, k_2}}`,

.. math::
    C_{k_1, k_2} = \mathrm{Re}(P + Q), \qquad C_{k_1, N_2 - k_2} = \mathrm{Im}(Q - P),

and the inverse runs the same steps backwards:
:math:`V_{k_1 k_2} = \tfrac14 \bar\omega_{k_1}\bar\omega_{k_2}[(C_{k_1,k_2} - C_{N_1-k_1,N_2-k_2})
- i(C_{N_1-k_1,k_2} + C_{k_1,N_2-k_2})]` with :math:`C_{N_1,\cdot} = C_{\cdot,N_2} = 0`, an inverse real FFT and
the inverse reordering. The reorderings are one gather over the flattened image (which costs about a copy on the
CPU), the index flips are whole-row gathers and ``flip``; everything is a composition of differentiable torch
operations, so autograd, float64 and CUDA work as for any other op. The constants are built once per shape,
dtype and device.

The convention is SciPy's unnormalised one (``scipy.fft.dctn(x, type=2)`` and ``idctn``):
:math:`C_{k_1 k_2} = 4 \sum_{n_1, n_2} x_{n_1 n_2} \cos\frac{\pi k_1 (2n_1+1)}{2N_1} \cos\frac{\pi k_2 (2n_2+1)}{2N_2}`.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor


class Plan(NamedTuple):
    """Constants of the transforms on one (N1, N2) grid, on one device and dtype."""

    order: Tensor  # flat index: reordered position -> source pixel (Makhoul's interleaving along both axes)
    unorder: Tensor  # its inverse permutation
    negated: Tensor  # rows k1 -> (-k1) mod N1
    flipped: Tensor  # rows k1 -> N1 - k1, into an array padded with a zero row N1
    forward: Tensor  # (2, N1, K2) complex: 2 w_k1 w_k2 and 2 conj(w_k1) w_k2 (the conjugate of Q's weight)
    inverse: Tensor  # (N1, K2) complex: conj(w_k1 w_k2) / 4
    right: int  # columns N2 - k2 for k2 = 1..right come from the imaginary parts


def _interleave(n: int) -> Tensor:
    """Makhoul's reordering of n samples: the even ones ascending, then the odd ones descending."""
    index = torch.arange(n)
    return torch.cat([index[0::2], index[1::2].flip(0)])


def complex_dtype(dtype: torch.dtype) -> torch.dtype:
    """The complex dtype of a real one (complex128 for float64, complex64 otherwise)."""
    return torch.complex128 if dtype == torch.float64 else torch.complex64


def twiddles(n1: int, n2: int) -> tuple[Tensor, Tensor]:
    r"""Half-sample twiddles :math:`e^{-i\pi k/(2N)}`, complex128: ``(N1, 1)`` for ``k < N1``, ``(1, K2)`` for
    ``k < K2``."""
    k1, k2 = torch.arange(n1, dtype=torch.float64), torch.arange(n2 // 2 + 1, dtype=torch.float64)
    w1 = torch.polar(torch.ones_like(k1), -math.pi * k1 / (2 * n1))
    w2 = torch.polar(torch.ones_like(k2), -math.pi * k2 / (2 * n2))
    return w1.view(-1, 1), w2.view(1, -1)


@functools.lru_cache(maxsize=32)
def plan(n1: int, n2: int, device: torch.device, dtype: torch.dtype) -> Plan:
    """The constants of an ``(n1, n2)`` grid on ``device`` in ``dtype`` (cached)."""
    order = (_interleave(n1)[:, None] * n2 + _interleave(n2)[None, :]).flatten()
    unorder = torch.empty_like(order)
    unorder[order] = torch.arange(order.numel())
    rows = torch.arange(n1)
    w1, w2 = twiddles(n1, n2)
    forward = torch.stack([2 * w1 * w2, 2 * w1.conj() * w2])
    cdtype = complex_dtype(dtype)
    return Plan(
        order.to(device),
        unorder.to(device),
        ((-rows) % n1).to(device),
        (n1 - rows).to(device),
        forward.to(device=device, dtype=cdtype),
        ((w1 * w2).conj() / 4).to(device=device, dtype=cdtype),
        (n2 - 1) // 2,
    )


def plan_for(x: Tensor) -> Plan:
    """The cached constants for the last two dimensions of ``x``."""
    return plan(x.shape[-2], x.shape[-1], x.device, x.dtype)


def reordered_spectrum(x: Tensor, p: Plan) -> Tensor:
    """The real 2-D FFT ``(..., N1, K2)`` of ``x`` reordered along both axes: the FFT that every transform here
    starts from."""
    n1, n2 = x.shape[-2:]
    return torch.fft.rfft2(x.reshape(-1, n1 * n2).index_select(1, p.order).view(x.shape))


def halves(spectrum: Tensor, p: Plan) -> tuple[Tensor, Tensor]:
    r"""``Re(P + Q)`` and ``-Im(Q - P)``, each ``(..., N1, K2)`` real: the DCT-II in two halves (see above), from
    :func:`reordered_spectrum`.

    Both are read from one complex array, :math:`P + \bar Q` (its real part is :math:`\mathrm{Re}(P + Q)`, its
    imaginary part :math:`\mathrm{Im}(P - Q)`), formed by one product and one fused multiply-add: :math:`\bar Q`
    is a product with the negated rows, where a product with a conjugated tensor materialises the conjugate first
    (3.5x the product here), and the complex sum replaces two strided real sums. The halves are strided views.
    """
    combined = torch.view_as_real(torch.addcmul(p.forward[0] * spectrum, p.forward[1],
                                                spectrum.index_select(-2, p.negated)))
    return combined[..., 0], combined[..., 1]


def half_spectra(x: Tensor, p: Plan) -> tuple[Tensor, Tensor]:
    """:func:`halves` of the :func:`reordered_spectrum` of ``x``: the DCT-II of ``x`` in two halves."""
    return halves(reordered_spectrum(x, p), p)


def from_halves(real: Tensor, negated_imag: Tensor, p: Plan) -> Tensor:
    """Assemble the DCT-II coefficients ``(..., N1, N2)`` from :func:`half_spectra`."""
    if p.right == 0:  # N2 <= 2: the real FFT keeps every column
        return real.contiguous()
    return torch.cat([real, -negated_imag[..., 1 : p.right + 1].flip(-1)], dim=-1)


def dct2(x: Tensor) -> Tensor:
    """Unnormalised 2-D DCT-II over the last two dimensions (``scipy.fft.dctn(x, type=2, axes=(-2, -1))``).

    ``x`` is real, shape ``(..., N1, N2)``; the result has the same shape and dtype.
    """
    p = plan_for(x)
    return from_halves(*half_spectra(x, p), p)


def inverse_spectrum(c: Tensor, p: Plan) -> Tensor:
    """The complex ``(..., N1, K2)`` spectrum whose :func:`from_reordered_spectrum` is the inverse DCT of ``c``."""
    n1, n2 = c.shape[-2:]
    k2 = n2 // 2 + 1
    padded = F.pad(c, (0, 1, 0, 1))  # C at N1 and N2 is 0
    rows = padded.index_select(-2, p.flipped)  # C[N1 - k1, :]
    # C[., N2 - k2] for k2 < K2: the last K2 columns of the padded array, reversed (only those columns copied)
    real = padded[..., :n1, :k2] - rows[..., n2 + 1 - k2 :].flip(-1)
    negated_imag = (rows[..., :k2] + padded[..., :n1, n2 + 1 - k2 :].flip(-1)).neg_()
    return torch.complex(real, negated_imag).mul_(p.inverse)


def from_reordered_spectrum(spectrum: Tensor, p: Plan, shape: torch.Size, out: Tensor | None = None) -> Tensor:
    """The real array of ``shape`` (..., N1, N2) whose :func:`reordered_spectrum` is ``spectrum``: the inverse real
    FFT and the inverse reordering, into ``out`` (contiguous, of ``shape``; not differentiable) when given."""
    n1, n2 = shape[-2:]
    v = torch.fft.irfft2(spectrum, s=(n1, n2)).reshape(-1, n1 * n2)
    if out is None:
        return v.index_select(1, p.unorder).view(shape)
    return torch.index_select(v, 1, p.unorder, out=out.view(-1, n1 * n2)).view(shape)


def idct2(c: Tensor) -> Tensor:
    """Inverse of :func:`dct2` over the last two dimensions (``scipy.fft.idctn(c, type=2, axes=(-2, -1))``)."""
    p = plan_for(c)
    return from_reordered_spectrum(inverse_spectrum(c, p), p, c.shape)
