"""NumPy versions of the 28 focus operators, written from the formulas (Pertuz et al. 2013 and the original
papers, with the choices psmini's docstrings state), not from psmini: the tests check psmini against them and
``benchmarks/focus_operators.py`` times them beside psmini.

Each takes one gray frame ``g`` (2-D float array, intensities in [0, 1]) and returns a float. They are
vectorised NumPy (shifted slices, sliding windows, small matrix products), as a NumPy user would write them, so
they are a fair speed baseline too; kernels are written as 2-D stencils and fits as least squares, not in the
separable or closed forms psmini uses, so the two share no algebra.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def correlate_valid(g: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """2-D correlation, valid part only: Σ_uv k[u, v] g[i+u, j+v]."""
    kh, kw = kernel.shape
    h, w = g.shape
    out = np.zeros((h - kh + 1, w - kw + 1), dtype=g.dtype)
    for u in range(kh):
        for v in range(kw):
            if kernel[u, v] != 0:
                out += kernel[u, v] * g[u : u + h - kh + 1, v : v + w - kw + 1]
    return out


def gaussian_kernels(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Separable Gaussian smoothing (sum 1) and derivative (unit response to a unit ramp), radius ceil(3σ)."""
    r = max(1, math.ceil(3 * sigma))
    x = np.arange(-r, r + 1, dtype=np.float64)
    smooth = np.exp(-0.5 * (x / sigma) ** 2)
    smooth /= smooth.sum()
    slope = x * smooth
    slope /= (x * slope).sum()
    return smooth, slope


def gaussian_gradients(g: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    smooth, slope = gaussian_kernels(sigma)
    gx = correlate_valid(correlate_valid(g, smooth[:, None]), slope[None, :])
    gy = correlate_valid(correlate_valid(g, slope[:, None]), smooth[None, :])
    return gx, gy


SOBEL_X = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], dtype=np.float64)
LAPLACE = np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], dtype=np.float64)
SECOND_X = np.array([[0, 0, 0], [-1, 2, -1], [0, 0, 0]], dtype=np.float64)
SECOND_D1 = np.array([[-1, 0, 0], [0, 2, 0], [0, 0, -1]], dtype=np.float64)
SECOND_D2 = np.array([[0, 0, -1], [0, 2, 0], [-1, 0, 0]], dtype=np.float64)


def _k(kernel: np.ndarray, g: np.ndarray) -> np.ndarray:
    return kernel.astype(g.dtype)


def first_differences(g):
    c = g[:-1, :-1]
    return g[:-1, 1:] - c, g[1:, :-1] - c


def haar(g):
    a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]
    return (a + b + c + d) / 2, (a + b - c - d) / 2, (a - b + c - d) / 2, (a - b - c + d) / 2


def dct_matrix(n: int) -> np.ndarray:
    """Orthonormal DCT-II matrix: C[u, x] = α(u) cos(π (2x + 1) u / 2n)."""
    x = np.arange(n)
    c = np.cos(np.pi * (2 * x[None] + 1) * np.arange(n)[:, None] / (2 * n)) * np.sqrt(2.0 / n)
    c[0] = np.sqrt(1.0 / n)
    return c


def tiles(g: np.ndarray, block: int) -> np.ndarray:
    nh, nw = g.shape[0] // block, g.shape[1] // block
    return g[: nh * block, : nw * block].reshape(nh, block, nw, block).transpose(0, 2, 1, 3)


# --------------------------------------------------------------------------------------------- operators


def GDER(g, sigma=1.0):
    gx, gy = gaussian_gradients(g, sigma)
    return float((gx**2 + gy**2).mean())


def GRAE(g):
    ix, iy = first_differences(g)
    return float((ix**2 + iy**2).mean())


def GRAT(g, threshold=0.0):
    ix, iy = first_differences(g)
    ax, ay = np.abs(ix), np.abs(iy)
    return float((np.where(ax > threshold, ax, 0) + np.where(ay > threshold, ay, 0)).mean())


def GRAS(g, threshold=0.0):
    ix, iy = first_differences(g)
    m = np.maximum(ix**2, iy**2)
    return float(np.where(m > threshold, m, 0).mean())


def TENG(g):
    gx, gy = correlate_valid(g, _k(SOBEL_X, g)), correlate_valid(g, _k(SOBEL_X.T, g))
    return float((gx**2 + gy**2).mean())


def TENV(g):
    gx, gy = correlate_valid(g, _k(SOBEL_X, g)), correlate_valid(g, _k(SOBEL_X.T, g))
    return float(np.sqrt(gx**2 + gy**2).var())


def LAPE(g):
    return float((correlate_valid(g, _k(LAPLACE, g)) ** 2).mean())


def LAPM(g, threshold=0.0):
    m = np.abs(correlate_valid(g, _k(SECOND_X, g))) + np.abs(correlate_valid(g, _k(SECOND_X.T, g)))
    return float(np.where(m >= threshold, m, 0).mean())


def LAPV(g):
    return float(correlate_valid(g, _k(LAPLACE, g)).var())


def LAPD(g):
    m = np.abs(correlate_valid(g, _k(SECOND_X, g))) + np.abs(correlate_valid(g, _k(SECOND_X.T, g)))
    m = m + (np.abs(correlate_valid(g, _k(SECOND_D1, g))) + np.abs(correlate_valid(g, _k(SECOND_D2, g)))) / np.sqrt(2)
    return float(m.mean())


def WAVS(g):
    _, lh, hl, hh = haar(g)
    return float((np.abs(lh) + np.abs(hl) + np.abs(hh)).mean())


def WAVV(g):
    _, lh, hl, hh = haar(g)
    return float(lh.var() + hl.var() + hh.var())


def WAVR(g):
    ll, lh, hl, hh = haar(g)
    low = (ll**2).sum()
    return float((lh**2 + hl**2 + hh**2).sum() / low) if low > 0 else 0.0


def ACMO(g):
    return float(np.abs(g - g.mean()).mean())


def ACMO_histogram(levels: np.ndarray) -> float:
    """Shirvaikar's histogram form on integer levels 0..255, in units of the level scale divided by 255."""
    p = np.bincount(levels.ravel(), minlength=256) / levels.size
    k = np.arange(256)
    mu = (k * p).sum()
    return float((np.abs(k - mu) * p).sum() / 255.0)


def GLVA(g):
    return float(g.var())


def GLLV(g, window=3):
    local = sliding_window_view(g, (window, window)).var(axis=(-2, -1))
    return float(local.var())


def GLVN(g):
    return float(g.var() / max(g.mean(), 1e-6))


def HISE(g, bins=256):
    levels = np.round(np.clip(g, 0, 1) * (bins - 1)).astype(np.int64)
    p = np.bincount(levels.ravel(), minlength=bins) / levels.size
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum())


def HISR(g):
    return float(g.max() - g.min())


def DCTE(g, block=8, eps=1e-6):
    c = dct_matrix(block).astype(g.dtype)
    coefficients = c @ tiles(g, block) @ c.T
    dc = np.maximum(coefficients[..., 0, 0], block * eps)
    ac = (coefficients**2).sum(axis=(-2, -1)) - coefficients[..., 0, 0] ** 2
    return float((ac / dc**2).mean())


def DCTR(g, block=8, eps=1e-6):
    c = dct_matrix(block).astype(g.dtype)
    f = c @ tiles(g, block) @ c.T
    low = f[..., 0, 1] ** 2 + f[..., 1, 0] ** 2 + f[..., 1, 1] ** 2 + f[..., 0, 2] ** 2 + f[..., 2, 0] ** 2
    return float((low / np.maximum(f[..., 0, 0], block * eps) ** 2).mean())


def BREN(g):
    c = g[:-2, :-2]
    return float(np.maximum((g[:-2, 2:] - c) ** 2, (g[2:, :-2] - c) ** 2).mean())


def CONT(g):
    h, w = g.shape
    c = g[1:-1, 1:-1]
    total = np.zeros_like(c)
    for du in (-1, 0, 1):
        for dv in (-1, 0, 1):
            total += np.abs(c - g[1 + du : h - 1 + du, 1 + dv : w - 1 + dv])
    return float(total.mean())


_CURV_DESIGN = np.array([[x, y, x * x, y * y, 1.0] for y in (-1, 0, 1) for x in (-1, 0, 1)])
_CURV_SOLVE = np.linalg.pinv(_CURV_DESIGN)  # least squares: (5, 9)


def CURV(g):
    patches = sliding_window_view(g, (3, 3)).reshape(g.shape[0] - 2, g.shape[1] - 2, 9)
    p = patches @ _CURV_SOLVE.T.astype(g.dtype)  # p0, p1, p2, p3, c per pixel
    return float(np.abs(p[..., :4]).sum(axis=-1).mean())


def HELM(g, window=3, eps=1e-6):
    r = window // 2
    mu = sliding_window_view(g, (window, window)).mean(axis=(-2, -1))
    c = g[r : g.shape[0] - r, r : g.shape[1] - r]
    hi, lo = np.maximum(mu, c), np.minimum(mu, c)
    ratio = np.where(mu >= c, mu / np.where(c > eps, c, 1), c / np.where(mu > eps, mu, 1))
    return float(np.where(lo > eps, ratio - 1, 0).mean()) if hi.size else 0.0


def SFIL(g, sigma=1.0):
    gx, gy = gaussian_gradients(g, sigma)
    angles = np.deg2rad(np.arange(0, 360, 45))
    responses = np.stack([np.cos(a) * gx + np.sin(a) * gy for a in angles])
    return float(responses.max(axis=0).mean())


def SFRQ(g):
    rows = ((g[:, 1:] - g[:, :-1]) ** 2).mean()
    cols = ((g[1:] - g[:-1]) ** 2).mean()
    return float(np.sqrt(rows + cols))


def VOLA(g):
    g0 = g - g.mean()
    rows = (g0[:, :-2] * g0[:, 1:-1]).mean() - (g0[:, :-2] * g0[:, 2:]).mean()
    cols = (g0[:-2] * g0[1:-1]).mean() - (g0[:-2] * g0[2:]).mean()
    return float(rows + cols)


OPERATORS = {
    name: globals()[name]
    for name in ["GDER", "GRAE", "GRAT", "GRAS", "TENG", "TENV", "LAPE", "LAPM", "LAPV", "LAPD", "WAVS", "WAVV",
                 "WAVR", "ACMO", "GLVA", "GLLV", "GLVN", "HISE", "HISR", "DCTE", "DCTR", "BREN", "CONT", "CURV",
                 "HELM", "SFIL", "SFRQ", "VOLA"]
}
