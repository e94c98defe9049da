"""OpenCV fast paths of the focus operators, for frames that need no gradient on the CPU.

Each function here computes exactly the formula of its torch twin in :mod:`psmini.focus.operators` or
:mod:`psmini.focus.measures` (same valid region, same normalisation) on a ``(B, h, w)`` CPU region of dtype
uint8, uint16 or float32 that does not require grad, one frame at a time, and returns a ``(B,)`` float32 tensor.
Integer frames are processed in their own units and the score is rescaled at the end (a quadratic score by
``1/255²``, a linear one by ``1/255``, a ratio not at all), so no converted copy of the frame is made where a
formula allows. Fused OpenCV reductions do most of the work: ``cv2.norm(a, b, NORM_L2SQR)`` on two shifted views
of a frame is a sum of squared differences with no temporary at all.

OpenCV is imported lazily (the first time a measure takes this path); without it, or with
``psmini.focus._opencv.enabled = False``, the torch path runs. ``tests/test_focus_operators.py`` checks that both
paths give the same value for every operator.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

enabled = True
"""Use OpenCV for no-grad CPU frames (set False to force the torch path, e.g. to time it)."""

_available: bool | None = None  # whether OpenCV imports; None until the first measure asks
_DTYPES = (torch.uint8, torch.uint16, torch.float32)
_SCALE = {torch.uint8: 1.0 / 255.0, torch.uint16: 1.0 / 65535.0, torch.float32: 1.0}


def _opencv() -> bool:
    """Whether OpenCV imports (tried once). The functions below import it where they use it: after this first import,
    ``import cv2`` is a lookup in ``sys.modules`` (about 0.1 µs), and the type checker sees OpenCV's own stubs."""
    global _available, enabled
    if _available is None:
        try:
            import cv2  # noqa: F401
        except ImportError:  # the torch path stays
            enabled = False
            _available = False
        else:
            _available = True
    return _available


def usable(region: Tensor) -> bool:
    """True when ``region`` can take the OpenCV path: CPU, uint8/uint16/float32, no grad, OpenCV importable."""
    return (
        enabled
        and region.device.type == "cpu"
        and region.dtype in _DTYPES
        and not (region.requires_grad and torch.is_grad_enabled())
        and _opencv()
    )


def _each(region: Tensor):
    """(frame as a 2-D numpy array (a view when possible), scale to [0, 1]) for each frame of the region."""
    scale = _SCALE[region.dtype]
    array = region.numpy() if not region.requires_grad else region.detach().numpy()
    for frame in array:
        if frame.strides[-1] != frame.itemsize or frame.strides[0] < 0:
            frame = np.ascontiguousarray(frame)
        yield frame, scale


_pool = threading.local()
_POOL_BYTES = 1 << 26  # at most 64 MiB of scratch per (shape, dtype): five 12-megapixel float32 frames are not kept


def _scratch(shape: tuple[int, int], count: int, dtype: type = np.float32) -> list[np.ndarray]:
    """``count`` arrays of ``shape`` and ``dtype``, reused per thread across calls (frame sizes repeat in a sweep).

    Fresh frame-sized outputs cost page faults on every call (measured: SFIL 44 ms with fresh arrays, 3.5 ms
    with the allocator keeping memory); OpenCV writes into these through ``dst=``. Only the last four
    (shape, dtype) keys are kept, and none above 64 MiB, so memory stays a few frames' worth.
    """
    if count * shape[0] * shape[1] * np.dtype(dtype).itemsize > _POOL_BYTES:  # huge frames: nothing kept
        return [np.empty(shape, dtype) for _ in range(count)]
    cache = getattr(_pool, "cache", None)
    if cache is None:
        cache = _pool.cache = {}
    key = (tuple(shape), np.dtype(dtype))
    arrays = cache.get(key)
    if arrays is None or len(arrays) < count:
        if arrays is None and len(cache) >= 4:
            cache.clear()
        arrays = cache[key] = [np.empty(shape, dtype) for _ in range(max(count, len(arrays or ())))]
    return arrays[:count]


def _out(values: list[float]) -> Tensor:
    return torch.from_numpy(np.array(values, dtype=np.float32))


def _float(frame: np.ndarray) -> np.ndarray:
    return frame if frame.dtype == np.float32 else frame.astype(np.float32)


_STRIP_ROWS = 96
"""Output rows per strip of the strip-mined operators: a few float32 strip buffers of a 640-pixel-wide frame
(about 0.25 MB each) stay in the core's L2 cache between the element-wise passes, where whole-frame buffers
(1.2 MB each, five of them) went to L3 or memory on every pass (measured on SFIL, 640 x 480 uint8: 2.3 ms whole
frame, 1.4 ms in 96-row strips; 3.1 vs 1.9 ms with the caches flushed before each call)."""


def _strips(first: int, stop: int, rows: int = _STRIP_ROWS):
    """Output row ranges ``(a, b)`` covering ``[first, stop)`` in steps of ``rows``."""
    for a in range(first, stop, rows):
        yield a, min(a + rows, stop)


# --------------------------------------------------------------------------------------------- the seven


def brenner(region: Tensor) -> Tensor:
    """mean of max(|g(i,j+2) - g(i,j)|, |g(i+2,j) - g(i,j)|)²: absdiff + max + norm(NORM_L2SQR), fused.

    A C-contiguous frame is read as one long row (``absdiff`` and ``max`` then run without a per-row loop, into
    two reused buffers); the two columns per row whose right neighbour wraps into the next row are left out by
    the final norm's strided view. A strided region takes the same calls on 2-D views.
    """
    import cv2
    out = []
    for f, s in _each(region):
        h, w = f.shape
        if f.flags.c_contiguous:
            n = (h - 2) * w
            flat = f.reshape(1, -1)
            centre = flat[:, :n]
            first, second = _buffers(n, f.dtype)
            cv2.absdiff(centre, flat[:, 2 : n + 2], dst=first)
            cv2.absdiff(centre, flat[:, 2 * w : 2 * w + n], dst=second)
            cv2.max(first, second, dst=first)
            total = cv2.norm(first.reshape(h - 2, w)[:, : w - 2], cv2.NORM_L2SQR)
        else:
            centre = f[:-2, :-2]
            total = cv2.norm(cv2.max(cv2.absdiff(centre, f[:-2, 2:]), cv2.absdiff(centre, f[2:, :-2])), cv2.NORM_L2SQR)
        out.append(total * s * s / ((h - 2) * (w - 2)))
    return _out(out)


_brenner_rows = threading.local()


def _buffers(n: int, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """Two (1, n) scratch rows, kept per thread for the last size asked (no fresh pages for every frame)."""
    key = (n, dtype)
    if getattr(_brenner_rows, "key", None) != key:
        _brenner_rows.key = key
        _brenner_rows.value = (np.empty((1, n), dtype), np.empty((1, n), dtype))
    return _brenner_rows.value


def brenner_uint8_frames(frames: Tensor) -> Tensor | None:
    """Brenner of a plain (B, H, W) uint8 CPU batch with the fewest Python steps, or None when not plain.

    The autofocus loop's case (one camera frame, no region): the checks of :func:`usable` and the region guards
    are inlined, each C-contiguous frame goes through three OpenCV passes on one long row (``absdiff`` twice into
    reused buffers, ``max`` in place) and one ``norm(NORM_L2SQR)`` over the whole buffer, from which the norm of
    the two wrapped columns per row (a small strided view) is subtracted.
    """
    if not (enabled and frames.dtype is torch.uint8 and frames.ndim == 3 and frames.is_cpu
            and not frames.requires_grad):
        return None
    batch, h, w = frames.shape
    if batch == 0 or h < 3 or w < 3 or not _opencv():
        return None
    array = frames.numpy()
    if not array.flags.c_contiguous:
        return brenner(frames)
    import cv2
    n = (h - 2) * w
    first, second = _buffers(n, array.dtype)
    wrapped = first.reshape(h - 2, w)[:, w - 2 :]
    values = np.empty(batch, dtype=np.float32)
    scale = 1.0 / (65025.0 * (h - 2) * (w - 2))
    for k in range(batch):
        flat = array[k].reshape(1, -1)
        centre = flat[:, :n]
        cv2.absdiff(centre, flat[:, 2 : n + 2], dst=first)
        cv2.absdiff(centre, flat[:, 2 * w : 2 * w + n], dst=second)
        cv2.max(first, second, dst=first)
        values[k] = (cv2.norm(first, cv2.NORM_L2SQR) - cv2.norm(wrapped, cv2.NORM_L2SQR)) * scale
    return torch.from_numpy(values)


def image_contrast(region: Tensor) -> Tensor:
    """Nanda & Cutler's 8-neighbour contrast: each unordered pair differenced once, two window sums each."""
    import cv2
    out = []
    for f, s in _each(region):
        h, w = f.shape
        total = 0.0
        for du, dv in ((0, 1), (1, 0), (1, 1), (1, -1)):
            c0, c1 = max(0, -dv), w - max(0, dv)
            diff = cv2.absdiff(f[0 : h - du, c0:c1], f[du:h, c0 + dv : c1 + dv])
            for row, col in ((1, 1 - c0), (1 - du, 1 - dv - c0)):
                total += cv2.sumElems(diff[row : row + h - 2, col : col + w - 2])[0]
        out.append(total * s / ((h - 2) * (w - 2)))
    return _out(out)


def _haar_rows(f: np.ndarray):
    """Sums and differences of horizontal neighbours, float32 (h, w-1), in reused buffers, and a third buffer."""
    import cv2
    sums, diffs, spare = _scratch((f.shape[0], f.shape[1] - 1), 3)
    cv2.add(f[:, :-1], f[:, 1:], dst=sums, dtype=cv2.CV_32F)
    cv2.subtract(f[:, :-1], f[:, 1:], dst=diffs, dtype=cv2.CV_32F)
    return sums, diffs, spare[:-1]


def wavelet_sum(region: Tensor) -> Tensor:
    """Σ|LH| + |HL| + |HH| of the undecimated Haar transform, from row sums and differences."""
    import cv2
    out = []
    for f, s in _each(region):
        h, w = f.shape
        sums, diffs, spare = _haar_rows(f)
        lh = cv2.norm(sums[:-1], sums[1:], cv2.NORM_L1)
        hh = cv2.norm(diffs[:-1], diffs[1:], cv2.NORM_L1)
        hl = cv2.norm(cv2.add(diffs[:-1], diffs[1:], dst=spare), cv2.NORM_L1)
        out.append(0.5 * (lh + hl + hh) * s / ((h - 1) * (w - 1)))
    return _out(out)


def _haar_moments(f: np.ndarray):
    """Per band (LH, HL, HH, LL): (sum, sum of squares) over every 2 × 2 window, in the frame's units.

    The frame is read in strips of rows that overlap by one (each 2 × 2 window lies in exactly one strip), so
    the row sums and differences of a strip are still in cache when the norms read them; a uint8 frame's sums
    and differences are exact int16.
    """
    import cv2
    h, w = f.shape
    # uint8 frames in int16: every sum and difference below is exact there, in half the bytes of float32
    exact = f.dtype == np.uint8
    buffers = _scratch((min(_STRIP_ROWS, h - 1) + 1, w - 1), 3, np.int16 if exact else np.float32)
    depth = cv2.CV_16S if exact else cv2.CV_32F
    totals = np.zeros(8)  # (sum, sum of squares) of LH, HL, HH, LL
    for a, b in _strips(0, h - 1):
        rows = f[a : b + 1]
        n = b - a + 1
        sums, diffs, spare = (x[:n] for x in buffers)
        cv2.add(rows[:, :-1], rows[:, 1:], dst=sums, dtype=depth)
        cv2.subtract(rows[:, :-1], rows[:, 1:], dst=diffs, dtype=depth)
        s_top, s_bottom = cv2.sumElems(sums[:-1])[0], cv2.sumElems(sums[1:])[0]
        d_top, d_bottom = cv2.sumElems(diffs[:-1])[0], cv2.sumElems(diffs[1:])[0]
        totals += (
            0.5 * (s_top - s_bottom), 0.25 * cv2.norm(sums[:-1], sums[1:], cv2.NORM_L2SQR),
            0.5 * (d_top + d_bottom), 0.25 * cv2.norm(cv2.add(diffs[:-1], diffs[1:], dst=spare[:-1]), cv2.NORM_L2SQR),
            0.5 * (d_top - d_bottom), 0.25 * cv2.norm(diffs[:-1], diffs[1:], cv2.NORM_L2SQR),
            0.5 * (s_top + s_bottom), 0.25 * cv2.norm(cv2.add(sums[:-1], sums[1:], dst=spare[:-1]), cv2.NORM_L2SQR),
        )
    lh, hl, hh, ll = (tuple(totals[i : i + 2]) for i in range(0, 8, 2))
    return lh, hl, hh, ll


def wavelet_variance(region: Tensor) -> Tensor:
    out = []
    for f, s in _each(region):
        n = (f.shape[0] - 1) * (f.shape[1] - 1)
        bands = _haar_moments(f)[:3]
        out.append(sum(max(sq / n - (total / n) ** 2, 0.0) for total, sq in bands) * s * s)
    return _out(out)


def wavelet_ratio(region: Tensor) -> Tensor:
    out = []
    for f, _ in _each(region):
        lh, hl, hh, ll = _haar_moments(f)
        high = lh[1] + hl[1] + hh[1]
        out.append(high / ll[1] if ll[1] > 0 else 0.0)
    return _out(out)


def _gaussian_taps(sigma: float):
    from psmini.focus.measures import _gaussian_taps

    smooth, slope = _gaussian_taps(sigma)
    return np.asarray(smooth, np.float32), np.asarray(slope, np.float32)


def _gaussian_gradients(f: np.ndarray, sigma: float, crop: bool = True):
    """Gaussian-derivative responses (correlation, as the torch path), float32; the valid grid, or the whole
    frame (border replicated) and the radius when ``crop`` is False."""
    import cv2
    smooth, slope = _gaussian_taps(sigma)
    r = len(smooth) // 2
    gx, gy = _scratch(f.shape, 2)
    cv2.sepFilter2D(f, cv2.CV_32F, slope, smooth, dst=gx, borderType=cv2.BORDER_REPLICATE)
    cv2.sepFilter2D(f, cv2.CV_32F, smooth, slope, dst=gy, borderType=cv2.BORDER_REPLICATE)
    if not crop:
        return gx, gy, r
    return gx[r:-r, r:-r], gy[r:-r, r:-r]


def gaussian_derivative(region: Tensor, sigma: float) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        gx, gy = _gaussian_gradients(f, sigma)
        out.append((cv2.norm(gx, cv2.NORM_L2SQR) + cv2.norm(gy, cv2.NORM_L2SQR)) * s * s / gx.size)
    return _out(out)


def _sobel(f: np.ndarray):
    import cv2
    gx, gy = _scratch(f.shape, 2)
    cv2.Sobel(f, cv2.CV_32F, 1, 0, dst=gx, ksize=3)
    cv2.Sobel(f, cv2.CV_32F, 0, 1, dst=gy, ksize=3)
    return gx[1:-1, 1:-1], gy[1:-1, 1:-1]


def tenengrad(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        gx, gy = _sobel(f)
        out.append((cv2.norm(gx, cv2.NORM_L2SQR) + cv2.norm(gy, cv2.NORM_L2SQR)) * s * s / gx.size)
    return _out(out)


def _variance(x: np.ndarray) -> float:
    import cv2

    _, std = cv2.meanStdDev(x)
    return float(std[0, 0]) ** 2


def tenengrad_variance(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        gx, gy, magnitude = _scratch(f.shape, 3)
        cv2.Sobel(f, cv2.CV_32F, 1, 0, dst=gx, ksize=3)
        cv2.Sobel(f, cv2.CV_32F, 0, 1, dst=gy, ksize=3)
        cv2.magnitude(gx, gy, magnitude=magnitude)
        out.append(_variance(magnitude[1:-1, 1:-1]) * s * s)
    return _out(out)


def _laplacian(f: np.ndarray) -> np.ndarray:
    import cv2
    (lap,) = _scratch(f.shape, 1)
    cv2.Laplacian(f, cv2.CV_32F, dst=lap, ksize=1)
    return lap[1:-1, 1:-1]


def variance_of_laplacian(region: Tensor) -> Tensor:
    return _out([_variance(_laplacian(f)) * s * s for f, s in _each(region)])


def laplacian_energy(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        lap = _laplacian(f)
        out.append(cv2.norm(lap, cv2.NORM_L2SQR) * s * s / lap.size)
    return _out(out)


_DIAGONALS = (
    np.array([[1, 0, 0], [0, -2, 0], [0, 0, 1]], np.float32),
    np.array([[0, 0, 1], [0, -2, 0], [1, 0, 0]], np.float32),
)


def modified_laplacian(region: Tensor, diagonal: bool) -> Tensor:
    """LAPM (threshold 0 only: the caller keeps the torch path otherwise) and LAPD, in row strips
    (:func:`_strip_l1`)."""
    import cv2
    # integer frames are filtered as they are, into float32 (no converted copy)
    filters: list[tuple[float, _Filter]] = [
               (1.0, lambda src, dst: cv2.Sobel(src, cv2.CV_32F, 2, 0, dst=dst, ksize=1)),
               (1.0, lambda src, dst: cv2.Sobel(src, cv2.CV_32F, 0, 2, dst=dst, ksize=1))]
    if diagonal:
        filters += [(math.sqrt(0.5), _filter2d(kernel)) for kernel in _DIAGONALS]
    return _out([_strip_l1(f, filters) * s / ((f.shape[0] - 2) * (f.shape[1] - 2)) for f, s in _each(region)])


_Filter = Callable[[np.ndarray, np.ndarray], object]
"""A filter of :func:`_strip_l1`: ``apply(src, dst)`` writes its float32 response to ``src`` into ``dst``."""


def _filter2d(kernel: np.ndarray) -> _Filter:
    """The 2-D correlation with ``kernel`` as a strip filter."""
    import cv2

    return lambda src, dst: cv2.filter2D(src, cv2.CV_32F, kernel, dst=dst)


def _sep_filter2d(kx: np.ndarray, ky: np.ndarray) -> _Filter:
    """The separable correlation with ``kx`` along rows and ``ky`` along columns as a strip filter."""
    import cv2

    return lambda src, dst: cv2.sepFilter2D(src, cv2.CV_32F, kx, ky, dst=dst)


def _strip_l1(f: np.ndarray, filters: list[tuple[float, _Filter]]) -> float:
    """Sum over ``filters`` (weight, apply) of weight times the L1 norm of each 3 × 3 filter's response on the
    frame's interior, in row strips (see :data:`_STRIP_ROWS`): each strip filters its rows plus one on either
    side into one small reused buffer (``apply(src, dst)`` writes a float32 response)."""
    import cv2

    h, w = f.shape
    (buffer,) = _scratch((min(_STRIP_ROWS, h - 2) + 2, w), 1)
    total = 0.0
    for a, b in _strips(1, h - 1):
        n = b - a + 2
        src, response = f[a - 1 : b + 1], buffer[:n]
        interior = response[1 : n - 1, 1 : w - 1]
        for weight, apply in filters:
            apply(src, response)
            total += weight * cv2.norm(interior, cv2.NORM_L1)
    return total


def normalized_variance(region: Tensor, eps: float) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        mean, std = cv2.meanStdDev(f)
        out.append(float(std[0, 0]) ** 2 * s * s / max(float(mean[0, 0]) * s, eps))
    return _out(out)


# ------------------------------------------------------------------------------------------ the new ones


def gradient_energy(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        centre = f[:-1, :-1]
        total = cv2.norm(centre, f[:-1, 1:], cv2.NORM_L2SQR) + cv2.norm(centre, f[1:, :-1], cv2.NORM_L2SQR)
        out.append(total * s * s / centre.size)
    return _out(out)


def thresholded_gradient(region: Tensor) -> Tensor:
    """GRAT with threshold 0 (the caller keeps the torch path otherwise)."""
    import cv2
    out = []
    for f, s in _each(region):
        centre = f[:-1, :-1]
        total = cv2.norm(centre, f[:-1, 1:], cv2.NORM_L1) + cv2.norm(centre, f[1:, :-1], cv2.NORM_L1)
        out.append(total * s / centre.size)
    return _out(out)


def squared_gradient(region: Tensor) -> Tensor:
    """GRAS with threshold 0 (the caller keeps the torch path otherwise)."""
    import cv2
    out = []
    for f, s in _each(region):
        centre = f[:-1, :-1]
        largest = cv2.max(cv2.absdiff(centre, f[:-1, 1:]), cv2.absdiff(centre, f[1:, :-1]))
        out.append(cv2.norm(largest, cv2.NORM_L2SQR) * s * s / centre.size)
    return _out(out)


def absolute_central_moment(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        if f.dtype == np.uint8:  # Shirvaikar's histogram form, exact for 256 levels
            hist = cv2.calcHist([f], [0], None, [256], [0, 256]).reshape(-1).astype(np.float64)
            levels = np.arange(256.0)
            mean = float(hist @ levels) / f.size
            out.append(float(hist @ np.abs(levels - mean)) * s / f.size)
        else:
            mean = cv2.mean(f)[0]
            centred = cv2.subtract(f, mean, dtype=cv2.CV_32F)  # type: ignore[call-overload]  # a number is a scalar operand to OpenCV; its stubs list arrays only
            out.append(cv2.norm(centred, cv2.NORM_L1) * s / f.size)
    return _out(out)


def gray_level_variance(region: Tensor) -> Tensor:
    return _out([_variance(f) * s * s for f, s in _each(region)])


def gray_level_local_variance(region: Tensor, window: int) -> Tensor:
    r"""Local variances E[g²] - E[g]² from a box filter and a squared-box filter, then their population variance.

    uint8 frames whose window sums stay below 2^24 (``window`` ≤ 3) are computed exactly: with the window sums
    :math:`S_1 = \sum g` and :math:`S_2 = \sum g^2` (integers, exact in float32), :math:`n^2 V = n S_2 - S_1^2`
    is an integer below 2^24, exact in float32 too, and the variance of it comes from its sum and sum of squares
    (accumulated in double by OpenCV). Other frames are centred first (fewer digits lost in E[g²] - E[g]²);
    rounding can then leave a flat window's local variance at -1e-9 instead of the torch path's clamped 0, far
    below float32 resolution of the score."""
    import cv2
    out = []
    r = window // 2
    n = window * window
    for f, s in _each(region):
        if f.dtype == np.uint8 and n * n * 255 * 255 < 1 << 24:
            first, second, _ = _scratch(f.shape, 3)
            cv2.boxFilter(f, cv2.CV_32F, (window, window), dst=first, normalize=False, borderType=cv2.BORDER_REPLICATE)
            cv2.sqrBoxFilter(f, cv2.CV_32F, (window, window), dst=second, normalize=False,
                             borderType=cv2.BORDER_REPLICATE)
            scaled = cv2.addWeighted(second, float(n), cv2.multiply(first, first, dst=first), -1.0, 0.0, dst=second)
            valid = scaled[r:-r, r:-r]
            count = valid.shape[0] * valid.shape[1]
            mean = cv2.sumElems(valid)[0] / count
            variance = max(cv2.norm(valid, cv2.NORM_L2SQR) / count - mean * mean, 0.0)
            out.append(variance * (s / n) ** 4)
            continue
        src, mean, squares = _scratch(f.shape, 3)
        # centred: fewer digits lost in E[g²] - E[g]²
        cv2.subtract(f, cv2.mean(f)[0], dst=src, dtype=cv2.CV_32F)  # type: ignore[call-overload]  # a number is a scalar operand to OpenCV; its stubs list arrays only
        cv2.blur(src, (window, window), dst=mean, borderType=cv2.BORDER_REPLICATE)
        cv2.sqrBoxFilter(src, cv2.CV_32F, (window, window), dst=squares, borderType=cv2.BORDER_REPLICATE)
        local = cv2.subtract(squares, cv2.multiply(mean, mean, dst=src), dst=squares)
        out.append(_variance(local[r:-r, r:-r]) * s**4)
    return _out(out)


def histogram_entropy(region: Tensor, bins: int) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        if f.dtype == np.uint8 and bins == 256:
            hist = cv2.calcHist([f], [0], None, [256], [0, 256]).reshape(-1)
        else:  # levels round(g (bins - 1)): bins centred on the levels, values clamped into [0, 1]
            g = cv2.multiply(_float(f), s) if s != 1.0 else f
            low, high, _, _ = cv2.minMaxLoc(g)
            if low < 0 or high > 1:
                g = np.clip(g, 0.0, 1.0)
            half = 0.5 / (bins - 1)
            hist = cv2.calcHist([g], [0], None, [bins], [-half, 1.0 + half]).reshape(-1)
        p = hist[hist > 0].astype(np.float64) / f.size
        out.append(float(-(p * np.log2(p)).sum()))
    return _out(out)


def histogram_range(region: Tensor) -> Tensor:
    import cv2

    out = []
    for f, s in _each(region):
        low, high, _, _ = cv2.minMaxLoc(f)
        out.append((high - low) * s)
    return _out(out)


def dct_energy_ratio(region: Tensor, block: int, eps: float) -> Tensor:
    """Tile means of g and g² by area resampling; AC/DC energy = σ²/μ² per tile (Parseval)."""
    import cv2
    out = []
    for f, s in _each(region):
        nh, nw = f.shape[0] // block, f.shape[1] // block
        src = _float(f[: nh * block, : nw * block])
        mean = cv2.resize(src, (nw, nh), interpolation=cv2.INTER_AREA).astype(np.float64)
        squares = cv2.resize(cv2.multiply(src, src), (nw, nh), interpolation=cv2.INTER_AREA).astype(np.float64)
        variance = np.maximum(squares - mean * mean, 0.0)
        out.append(float((variance / np.maximum(mean * s, eps) ** 2).mean()) * s * s)
    return _out(out)


def dct_reduced_energy_ratio(region: Tensor, block: int, eps: float) -> Tensor:
    """The 3 × 3 lowest DCT coefficients of every tile as two small matrix products."""
    from psmini.focus.operators import _REDUCED

    x = np.arange(block)
    basis = np.cos(np.pi * (2 * x + 1) * np.arange(3)[:, None] / (2 * block)) * math.sqrt(2.0 / block)
    basis[0] = math.sqrt(1.0 / block)
    basis = basis.astype(np.float32)
    out = []
    for f, s in _each(region):
        nh, nw = f.shape[0] // block, f.shape[1] // block
        tiles = _float(f[: nh * block, : nw * block]).reshape(nh, block, nw * block)
        columns = (basis @ tiles).reshape(nh, 3, nw, block)  # (nh, u, nw, x)
        coefficients = columns @ basis.T  # (nh, u, nw, v)
        low = sum(coefficients[:, u, :, v].astype(np.float64) ** 2 for u, v in _REDUCED)
        dc = np.maximum(coefficients[:, 0, :, 0].astype(np.float64) * s, block * eps)
        out.append(float((low * s * s / dc**2).mean()))
    return _out(out)


_ONES = np.ones(3, np.float32)
_CURVATURE = (  # (row taps, column taps) of p0 = Σx g/6, p1 = Σy g/6, p2 = Σx² g/2 - Σg/3, p3 = Σy² g/2 - Σg/3
    (np.array([-1, 0, 1], np.float32) / 6, _ONES),
    (_ONES, np.array([-1, 0, 1], np.float32) / 6),
    (np.array([1 / 6, -1 / 3, 1 / 6], np.float32), _ONES),
    (_ONES, np.array([1 / 6, -1 / 3, 1 / 6], np.float32)),
)


def curvature(region: Tensor) -> Tensor:
    """Helmli & Scherer's four curvature coefficients, each a separable 3 × 3 filter, in row strips
    (:func:`_strip_l1`)."""
    filters = [(1.0, _sep_filter2d(kx, ky)) for kx, ky in _CURVATURE]
    return _out([_strip_l1(f, filters) * s / ((f.shape[0] - 2) * (f.shape[1] - 2)) for f, s in _each(region)])


def helmli_mean(region: Tensor, window: int, eps: float) -> Tensor:
    """max(μ, g) / max(min(μ, g), eps) - 1 where min(μ, g) > eps, as a masked mean, in row strips (see
    :data:`_STRIP_ROWS`): each strip reads its rows plus ``window // 2`` on either side and keeps the valid grid."""
    import cv2
    out = []
    r = window // 2
    for f, s in _each(region):
        h, w = f.shape
        rows = min(_STRIP_ROWS, h - 2 * r)
        buffers = _scratch((rows + 2 * r, w), 4)
        (masks,) = _scratch((rows, w - 2 * r), 1, np.uint8)
        total = 0.0
        for a, b in _strips(r, h - r):
            n = b - a + 2 * r
            scaled, mean, low, high = (x[:n] for x in buffers)
            src = f[a - r : b + r]
            src = cv2.multiply(src, s, dst=scaled, dtype=cv2.CV_32F) if s != 1.0 else src
            cv2.blur(src, (window, window), dst=mean, borderType=cv2.BORDER_REPLICATE)
            cv2.min(mean, src, dst=low)
            cv2.max(mean, src, dst=high)
            ratio = cv2.divide(high, cv2.max(low, eps, dst=mean), dst=high)
            scored = cv2.compare(low[r : n - r, r : w - r], eps, cv2.CMP_GT, dst=masks[: b - a])  # type: ignore[call-overload]  # a number is a scalar operand to OpenCV; its stubs list arrays only
            count = cv2.countNonZero(scored)
            if count:  # 255 where min(μ, g) > eps
                total += cv2.mean(ratio[r : n - r, r : w - r], mask=scored)[0] * count - count
        out.append(total / ((h - 2 * r) * (w - 2 * r)))
    return _out(out)


def steerable_filters(region: Tensor, sigma: float) -> Tensor:
    """max(|gx|, |gy|, |gx + gy|/√2, |gx - gy|/√2) from u = |gx + gy| and v = |gx - gy|: max(|gx|, |gy|) is
    (u + v)/2 and max(u, v) is |gx| + |gy|. Row strips (see :data:`_STRIP_ROWS`): each strip filters its rows
    plus the kernel radius on either side and sums its valid grid."""
    import cv2
    out = []
    half = math.sqrt(0.5)
    smooth, slope = _gaussian_taps(sigma)
    r = len(smooth) // 2
    for f, s in _each(region):
        h, w = f.shape
        buffers = _scratch((min(_STRIP_ROWS, h - 2 * r) + 2 * r, w), 5)
        total = 0.0
        for a, b in _strips(r, h - r):
            n = b - a + 2 * r
            gx, gy, negative, u, v = (x[:n] for x in buffers)
            src = f[a - r : b + r]
            cv2.sepFilter2D(src, cv2.CV_32F, slope, smooth, dst=gx, borderType=cv2.BORDER_REPLICATE)
            cv2.sepFilter2D(src, cv2.CV_32F, smooth, slope, dst=gy, borderType=cv2.BORDER_REPLICATE)
            np.negative(gy, out=negative)
            cv2.absdiff(gx, negative, dst=u)  # |gx + gy|
            cv2.absdiff(gx, gy, dst=v)  # |gx - gy|
            # max((u + v)/2, max(u, v)/√2) = max((u + v)/√2, max(u, v)) / √2
            cv2.addWeighted(u, half, v, half, 0.0, dst=gx)
            cv2.max(u, v, dst=gy)
            largest = cv2.max(gx, gy, dst=gx)
            total += cv2.sumElems(largest[r : n - r, r : w - r])[0]
        out.append(total * half * s / ((h - 2 * r) * (w - 2 * r)))
    return _out(out)


def spatial_frequency(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        h, w = f.shape
        rows = cv2.norm(f[:, 1:], f[:, :-1], cv2.NORM_L2SQR) / (h * (w - 1))
        cols = cv2.norm(f[1:], f[:-1], cv2.NORM_L2SQR) / ((h - 1) * w)
        out.append(math.sqrt(rows + cols) * s)
    return _out(out)


def vollath_f4(region: Tensor) -> Tensor:
    import cv2
    out = []
    for f, s in _each(region):
        h, w = f.shape
        g = cv2.subtract(f, cv2.mean(f)[0], dtype=cv2.CV_32F)  # type: ignore[call-overload]  # a number is a scalar operand to OpenCV; its stubs list arrays only
        rows = cv2.sumElems(cv2.multiply(g[:, :-2], cv2.subtract(g[:, 1:-1], g[:, 2:])))[0] / (h * (w - 2))
        cols = cv2.sumElems(cv2.multiply(g[:-2], cv2.subtract(g[1:-1], g[2:])))[0] / ((h - 2) * w)
        out.append((rows + cols) * s * s)
    return _out(out)
