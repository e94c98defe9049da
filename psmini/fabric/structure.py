r"""Textile structure from a height map: the yarn systems' directions and densities, the weave repeat.

The height of a woven or knitted fabric is periodic on a 2-D lattice, so its power spectrum is a lattice of peaks
(Pan et al., "Automatic inspection of woven fabric density", 2010, and Techniková & Tunák, 2013: thread densities
from the 2-D Fourier transform). A yarn system's peak lies along the direction *across* its yarns, at the thread
frequency; the interlacing repeats every R threads (R = 2 plain, 3 for a 2/1 twill, 5 for a 5-end satin), which
adds peaks at fractions 1/R of the thread frequencies (the lattice is finer than the thread grid), so the
strongest peak is not always the thread count. This module:

1. levels the height (form removal and an ISO 16610-61 L-filter, :mod:`psmini.fabric.surface`), windows it with
   a 2-D Hann window over the valid pixels and zero-pads it twice;
2. finds the spectral peaks that stand ``weak_db`` above the local background (the geometric mean of the power
   in the ring of the same frequency), between two periods per field and 90% of Nyquist;
3. refines each peak below the FFT bin by evaluating the windowed discrete-time Fourier transform on a grid of
   quarter-bin steps around it and fitting a parabola to the log power (twice, re-centred), which turns the
   bins (20 per 2 mm⁻¹ on a 10 mm field) into frequencies within a fraction of a per cent;
4. takes the strongest peak as the first yarn system and the strongest one roughly perpendicular to it
   (within 2°, else 10°, else any one 30° off) as the second, expresses every peak in that basis and finds the smallest
   repeat R whose regular weave lattice (the multiples of one shift ``(1/R, k/R)``, k the move number) holds
   the interlacing peaks; peaks of a modulation incommensurate with the threads do not count;
5. recognises the stitch lattice of a purl (alternate courses shifted by half a wale): two equally strong
   oblique peaks of equal frequency are the diagonals of a centred-rectangular lattice, whose axes give the
   wales and courses.

The directions are those in which the yarns run: degrees in [0, 180), counter-clockwise from x (x right,
y up), i.e. the peak's direction plus 90°; densities are threads per cm counted across the yarns
(10 × the peak frequency in cycles/mm). When nothing stands out, or the field spans fewer than two periods of its
relief, the result says so (:attr:`FabricStructure.found` False with a ``reason``) instead of giving a number.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from psmini.errors import InputError
from psmini.fabric.surface import SurfaceOptions, _check_height, remove_form, scale_limited_surface

__all__ = ["StructureOptions", "FabricStructure", "SpectralPeak", "structure_spectrum", "fabric_structure"]


@dataclass(frozen=True)
class StructureOptions:
    """Options of :func:`fabric_structure`; the defaults are the ones the tests and benchmark measure.

    Attributes:
        l_cutoff_mm: L-filter cut-off before the spectrum, mm (removes wrinkles and drape; 2.5 mm passes 97% of a
            1.1 mm net repeat); ``None``: form removal only.
        form_degree: polynomial degree of the form removal (see :class:`~psmini.fabric.SurfaceOptions`).
        strong_db: how far above the local background (dB of power) a peak must stand to be a yarn system.
        weak_db: the same for the lattice peaks used to find the repeat and the crimp.
        max_repeat: largest weave repeat tried.
        lattice_tolerance: how far (in units of the lattice step 1/R) a peak may sit from the lattice.
        lattice_share: the repeat is the smallest one whose regular weave lattice explains at least this share
            of the interlacing amplitude that the best lattice of any repeat up to ``max_repeat`` explains.
        interlacing_share: below this share of the two systems' amplitude, the interlacing peaks (fractional in
            both coordinates) on the best regular weave lattice are too weak to call a repeat, which is then 1.
        dynamic_db: peaks more than this far below the strongest bin of the band are ignored (the window's
            leakage far from a steep spectrum's energy).
        max_peaks: most peaks kept per sample (strongest first).
        spike_fence: pixels of the levelled height further than this many times its 5th-95th percentile range
            outside that range (and 2 pixels around them) are treated as unsolved and the height levelled again
            without them: the spikes that a near-light reconstruction leaves in the holes of a knit or a net
            (up to 2 mm on a 0.2 mm relief), which otherwise bury the yarn peaks; ``None``: none removed.
        openness_level: share of the height range (1st to 99th percentile) above the lowest level below which a
            pixel counts as a hole (the card showing), for :attr:`FabricStructure.openness`.
    """

    l_cutoff_mm: float | None = 2.5
    form_degree: int = 2
    strong_db: float = 30.0
    weak_db: float = 18.0
    max_repeat: int = 8
    lattice_tolerance: float = 0.15
    lattice_share: float = 0.6
    interlacing_share: float = 0.03
    dynamic_db: float = 50.0
    max_peaks: int = 48
    openness_level: float = 0.1
    spike_fence: float | None = 2.0

    def __post_init__(self) -> None:
        if self.spike_fence is not None and not self.spike_fence > 0:
            raise InputError(f"spike_fence must be > 0 or None, got {self.spike_fence!r}")
        if not self.strong_db >= self.weak_db > 0:
            raise InputError(f"need strong_db >= weak_db > 0, got {self.strong_db!r} and {self.weak_db!r}")
        if not isinstance(self.max_repeat, int) or not 1 <= self.max_repeat <= 16:
            raise InputError(f"max_repeat must be an integer in [1, 16], got {self.max_repeat!r}")
        if not 0 < self.lattice_tolerance < 0.5:
            raise InputError(f"lattice_tolerance must lie in (0, 0.5), got {self.lattice_tolerance!r}")
        if not 0 <= self.interlacing_share < 1:
            raise InputError(f"interlacing_share must lie in [0, 1), got {self.interlacing_share!r}")
        if not 0 < self.lattice_share <= 1:
            raise InputError(f"lattice_share must lie in (0, 1], got {self.lattice_share!r}")
        if not 0 < self.openness_level < 1:
            raise InputError(f"openness_level must lie in (0, 1), got {self.openness_level!r}")
        SurfaceOptions(form_degree=self.form_degree, l_cutoff_mm=self.l_cutoff_mm)  # same checks

    def to_dict(self) -> dict:
        """The options as a JSON-ready dict."""
        return asdict(self)


@dataclass
class SpectralPeak:
    """One refined peak of the height's power spectrum.

    Attributes:
        fx_per_mm, fy_per_mm: the frequency vector, cycles/mm (x right, y up; fy >= 0).
        snr_db: power above the local background, dB.
        amplitude_um: amplitude of the sinusoid the peak stands for, µm.
    """

    fx_per_mm: float
    fy_per_mm: float
    snr_db: float
    amplitude_um: float

    @property
    def frequency(self) -> float:
        """Cycles per mm."""
        return math.hypot(self.fx_per_mm, self.fy_per_mm)

    @property
    def yarn_angle_deg(self) -> float:
        """Direction in which the yarns of this peak run, degrees in [0, 180) (the peak's direction + 90°)."""
        # rounded to 1e-4° before the wrap (float32 sub-bin refinement is good to ~1e-4° at best): a direction a hair
        # below 180° on a vertical peak is 0°, not 179.99997° (which prints as 180)
        return round(math.degrees(math.atan2(self.fy_per_mm, self.fx_per_mm)) + 90.0, 4) % 180.0


@dataclass
class FabricStructure:
    """What :func:`fabric_structure` finds in one sample.

    Attributes:
        found: whether a periodic structure was found; when False, ``reason`` says why and the numbers are None.
        reason: empty when found.
        threads_per_cm: densities of the yarn systems, counted across the yarns, the denser first (one entry for
            a single system, e.g. a rib).
        thread_angles_deg: the directions in which those yarns run, degrees in [0, 180), the same order.
        weave_repeat: threads per repeat of the interlacing (1: every crossing alike, as in a knit's stitch grid;
            2 plain; 3 a 2/1 twill; 5 a 5-end satin); None with a single system.
        float_length: the longest float, in threads, of a regular weave of that repeat (R - 1 for R >= 2: 1 plain,
            2 for a 2/1 twill, 4 for a 5-end satin; a 2/2 twill, also R = 4, floats over 2); 0 for R = 1.
        wales_per_cm, courses_per_cm: for a knit-like lattice (repeat 1), the two systems as wales (the stronger
            one: the columns of stitches dominate the face of a jersey) and courses; None otherwise.
        crimp_um: peak-to-peak height of the interlacing wave: twice the largest amplitude of the lattice peaks
            that are not thread harmonics; 0 when there are none.
        openness: share of the field that is a hole: invalid (unsolved, masked) pixels plus those within
            ``openness_level`` of the height range above the lowest level.
        peaks: the refined peaks, strongest first.
    """

    found: bool
    reason: str = ""
    threads_per_cm: list[float] | None = None
    thread_angles_deg: list[float] | None = None
    weave_repeat: int | None = None
    float_length: int | None = None
    wales_per_cm: float | None = None
    courses_per_cm: float | None = None
    crimp_um: float | None = None
    openness: float | None = None
    peaks: list[SpectralPeak] = field(default_factory=list)

    def to_dict(self) -> dict:
        """A JSON-ready dict (peaks as dicts)."""
        out = asdict(self)
        out["peaks"] = [asdict(p) for p in self.peaks]
        return out


def _hann(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.hann_window(n, periodic=False, dtype=dtype, device=device)


def _levelled(height: Tensor, pixel_pitch_mm: float, mask: Tensor | None,
              options: StructureOptions) -> tuple[Tensor, Tensor, Tensor]:
    """Scale-limited height and the windowed weights (B, 1, H, W), and the valid pixels."""
    levelling = SurfaceOptions(form_degree=options.form_degree, l_cutoff_mm=options.l_cutoff_mm)
    surface, valid = scale_limited_surface(height, pixel_pitch_mm, mask, levelling)
    if options.spike_fence is not None:
        spikes = torch.zeros_like(valid)
        for i in range(height.shape[0]):
            values = surface[i][valid[i]]
            if values.numel() < 2:
                continue
            lo, hi = torch.quantile(values.double(), torch.tensor([0.05, 0.95], dtype=torch.float64,
                                                                  device=values.device)).to(surface.dtype)
            reach = options.spike_fence * (hi - lo)
            spikes[i] = valid[i] & ((surface[i] < lo - reach) | (surface[i] > hi + reach))
        if bool(spikes.any()):
            spikes = F.max_pool2d(spikes.to(height.dtype), 5, stride=1, padding=2) > 0  # and 2 px around
            surface, valid = scale_limited_surface(height, pixel_pitch_mm, valid & ~spikes, levelling)
    h, w = height.shape[-2:]
    window = _hann(h, height.dtype, height.device).view(h, 1) * _hann(w, height.dtype, height.device).view(1, w)
    return surface, window * valid.to(height.dtype), valid


def structure_spectrum(height: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None,
                       options: StructureOptions = StructureOptions()) -> tuple[Tensor, float]:
    """The power spectrum :func:`fabric_structure` searches: levelled, Hann-windowed, zero-padded twice.

    Args:
        height: :math:`(B, 1, H, W)`, mm.
        pixel_pitch_mm: pixel size, mm.
        mask: optional cloth mask :math:`(B, 1, H, W)`.
        options: :class:`StructureOptions`.

    Returns:
        the power :math:`(B, 1, N, N)` with N = 2 max(H, W), zero frequency at (N/2, N/2), fx along columns
        (growing right) and fy along rows (growing *up*: row N/2 - k is fy = k steps), and the frequency step in
        cycles/mm.

    Example:
        >>> power, step = structure_spectrum(torch.rand(1, 1, 32, 32), 0.025)
        >>> power.shape, step
        (torch.Size([1, 1, 64, 64]), 0.625)
    """
    _check_height(height, mask, pixel_pitch_mm)
    surface, weight, _ = _levelled(height, pixel_pitch_mm, mask, options)
    return _spectrum(surface, weight), 1.0 / (2 * max(height.shape[-2:]) * pixel_pitch_mm)


def _spectrum(surface: Tensor, weight: Tensor) -> Tensor:
    n = 2 * max(surface.shape[-2:])
    spec = torch.fft.fft2(surface * weight, s=(n, n))
    # row frequency k (rows grow downward) is fy = -k with y up: row N/2 - k holds fy = k
    return torch.fft.fftshift(spec.abs().square(), dim=(-2, -1))


def _box_mean(x: Tensor, size: int) -> Tensor:
    """Mean over a size x size box (zero padded at the borders), separable."""
    pad = size // 2
    x = F.avg_pool2d(x, (1, size), stride=1, padding=(0, pad), count_include_pad=True)
    return F.avg_pool2d(x, (size, 1), stride=1, padding=(pad, 0), count_include_pad=True)


def _background(power: Tensor, inner: int = 5, outer: int = 12) -> Tensor:
    """Local background of every bin: the geometric mean of the power over the square annulus between
    ``inner`` and ``outer`` bins around it (a periodic peak's main lobe, ±4 bins of the padded Hann spectrum, lies
    inside; a smooth random surface's spectrum is as high there as at the bin)."""
    logp = power.clamp_min(torch.finfo(power.dtype).tiny).log()
    big, small = 2 * outer + 1, 2 * inner + 1
    annulus = (_box_mean(logp, big) * big**2 - _box_mean(logp, small) * small**2) / (big**2 - small**2)
    return annulus.exp()


def _refine(surface: Tensor, weight: Tensor, freqs: Tensor, step: float, rounds: int = 3) -> tuple[Tensor, Tensor]:
    """Sub-bin peaks: parabolic fit of log |DTFT|² on a 5×5 grid of ``step`` (cycles/px) around each frequency.

    ``freqs`` (K, 2) are (fx, fy) in cycles/px (y up); returns the refined (K, 2) and |DTFT|² at them (K,)."""
    h, w = surface.shape[-2:]
    z = (surface * weight).to(torch.complex128 if surface.dtype == torch.float64 else torch.complex64)
    cols = torch.arange(w, dtype=surface.dtype, device=surface.device)
    rows_up = -torch.arange(h, dtype=surface.dtype, device=surface.device)  # y up
    offsets = torch.arange(-2, 3, dtype=surface.dtype, device=surface.device)
    f = freqs.clone()
    for _ in range(rounds):
        fx = f[:, :1] + offsets * step  # (K, 5)
        fy = f[:, 1:] + offsets * step
        ex = torch.exp(-2j * math.pi * fx.unsqueeze(-1) * cols).to(z.dtype)  # (K, 5, W)
        ey = torch.exp(-2j * math.pi * fy.unsqueeze(-1) * rows_up).to(z.dtype)  # (K, 5, H)
        dtft = ey @ z.unsqueeze(0) @ ex.transpose(1, 2)  # (K, 5[fy], 5[fx])
        logp = dtft.abs().square().clamp_min(1e-300).log()
        best = logp.flatten(1).argmax(1)
        iy, ix = (best // 5).clamp(1, 3), (best % 5).clamp(1, 3)
        k = torch.arange(f.shape[0], device=f.device)
        centre = logp[k, iy, ix]
        dx = _vertex(logp[k, iy, ix - 1], centre, logp[k, iy, ix + 1])
        dy = _vertex(logp[k, iy - 1, ix], centre, logp[k, iy + 1, ix])
        f = torch.stack([fx[k, ix] + dx * step, fy[k, iy] + dy * step], dim=1)
        step = step / 2
    ex = torch.exp(-2j * math.pi * f[:, :1] * cols).to(z.dtype)  # (K, W)
    ey = torch.exp(-2j * math.pi * f[:, 1:] * rows_up).to(z.dtype)  # (K, H)
    value = torch.einsum("kh,hw,kw->k", ey, z, ex)
    return f, value.abs().square()


def _vertex(lo: Tensor, centre: Tensor, hi: Tensor) -> Tensor:
    """The parabola's vertex through three equally spaced values, as an offset in [-1, 1] steps from the centre
    (0 where the three are not concave)."""
    den = lo - 2 * centre + hi
    return torch.where(den < 0, 0.5 * (lo - hi) / torch.where(den < 0, den, -torch.ones_like(den)),
                       torch.zeros_like(den)).clamp(-1, 1)


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines (degrees, [0, 90])."""
    cos = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, cos)))


def fabric_structure(height: Tensor, pixel_pitch_mm: float, mask: Tensor | None = None,
                     options: StructureOptions = StructureOptions()) -> list[FabricStructure]:
    r"""The yarn systems, weave repeat, crimp and openness of each sample (see the module docstring).

    Not differentiable (peak picking). The spectrum, background and sub-bin refinement run on the input's
    device; the lattice fit (a few dozen peaks) runs on the CPU.

    Args:
        height: :math:`(B, 1, H, W)`, mm (heights toward the camera).
        pixel_pitch_mm: pixel size, mm.
        mask: optional cloth mask :math:`(B, 1, H, W)` (unsolved pixels: False); non-finite heights are excluded.
        options: :class:`StructureOptions`.

    Returns:
        one :class:`FabricStructure` per sample.

    Raises:
        InputError: a sample without valid pixels, a bad pitch. ShapeError: bad shapes.

    Example:
        >>> y, x = torch.meshgrid(torch.arange(200.0), torch.arange(200.0), indexing="ij")
        >>> z = 0.05 * torch.cos(2 * math.pi * x * 0.025 / 0.25) + 0.05 * torch.cos(2 * math.pi * y * 0.025 / 0.5)
        >>> found = fabric_structure(z[None, None], 0.025)[0]
        >>> [round(t, 2) for t in found.threads_per_cm], [round(a, 2) for a in found.thread_angles_deg]
        ([40.0, 20.0], [90.0, 0.0])
    """
    valid = _check_height(height, mask, pixel_pitch_mm)
    surface, weight, valid = _levelled(height, pixel_pitch_mm, valid, options)
    b, _, h, w = height.shape
    n = 2 * max(h, w)
    power = _spectrum(surface, weight)
    dev, dt = height.device, height.dtype
    idx = torch.arange(n, device=dev, dtype=dt) - n // 2
    fy_bins, fx_bins = -idx.view(n, 1).expand(n, n), idx.view(1, n).expand(n, n)  # rows up
    radius = torch.sqrt(fx_bins.square() + fy_bins.square())
    background = _background(power)
    snr = power / background.clamp_min(torch.finfo(dt).tiny)
    local_max = power >= F.max_pool2d(F.max_pool2d(power, (1, 7), stride=1, padding=(0, 3)), (7, 1), stride=1,
                                      padding=(3, 0))
    field_mm = min(h, w) * pixel_pitch_mm
    min_bins = 2.0 / field_mm * (n * pixel_pitch_mm)  # two periods per field
    half = (fy_bins > 0) | ((fy_bins == 0) & (fx_bins > 0))
    band = half & (radius >= min_bins) & (radius <= 0.45 * n)
    weak = 10 ** (options.weak_db / 10)
    ceiling = torch.where(band, power, torch.zeros_like(power)).flatten(1).amax(1).view(b, 1, 1, 1)
    loud = power >= ceiling * 10 ** (-options.dynamic_db / 10)
    candidate = local_max & band & (snr >= weak) & loud
    low = local_max & half & (radius >= 2) & (radius < min_bins) & (snr >= 10 ** (options.strong_db / 10))
    results = []
    for i in range(b):
        flat = torch.where(candidate[i, 0].flatten(), snr[i, 0].flatten(), torch.zeros((), dtype=dt, device=dev))
        count = int(min(options.max_peaks, int(candidate[i, 0].sum())))
        openness = _openness(height[i:i + 1], valid[i:i + 1], options)
        if count == 0:
            results.append(FabricStructure(False, _no_peak_reason(bool(low[i].any()), field_mm, options),
                                           openness=openness))
            continue
        top = flat.topk(count).indices
        start = torch.stack([fx_bins.flatten()[top], fy_bins.flatten()[top]], dim=1) / n  # cycles/px
        freqs, value = _refine(surface[i, 0], weight[i, 0], start, 0.25 / n)
        bg = background[i, 0].flatten()[top]
        snr_db = (10 * torch.log10(value / bg)).cpu().numpy()
        amp_um = (2 * value.sqrt() / weight[i, 0].sum() * 1000).cpu().numpy()
        fmm = (freqs / pixel_pitch_mm).cpu().numpy().astype(np.float64)
        order = np.argsort(-snr_db)
        peaks = [SpectralPeak(float(fmm[k, 0]), float(fmm[k, 1]), float(snr_db[k]), float(amp_um[k]))
                 for k in order]
        results.append(_lattice(peaks, openness, options, field_mm, bool(low[i].any())))
    return results


def _no_peak_reason(low_peak: bool, field_mm: float, options: StructureOptions) -> str:
    if low_peak:
        return (f"the field ({field_mm:.2f} mm) spans fewer than two periods of its strongest relief; a structure "
                "needs at least two periods in the crop")
    return (f"no spectral peak stands {options.weak_db:.0f} dB above the background between two periods per field "
            "and Nyquist: the surface has no periodic structure")


def _openness(height: Tensor, valid: Tensor, options: StructureOptions) -> float:
    """Share of holes: invalid pixels plus valid ones near the lowest level of the form-removed height."""
    z = remove_form(height, valid, 1)[valid]
    total = valid.numel()
    if z.numel() < 2:
        return float(1 - z.numel() / total)
    lo, hi = torch.quantile(z.double(), torch.tensor([0.01, 0.99], dtype=torch.float64, device=z.device))
    holes = (z < lo + options.openness_level * (hi - lo)).sum()
    return float((total - z.numel() + holes) / total)


def _fundamental(peak: SpectralPeak, peaks: list[SpectralPeak], options: StructureOptions) -> SpectralPeak:
    """The peak's fundamental: the peak at the lowest 1/d (d = 2..6) of its frequency vector that holds at least
    80% of its amplitude (thin yarns far apart, as in a net, have harmonics nearly as strong as the
    fundamental; the aliases of fine yarns' harmonics are weaker than the thread peak)."""
    for divisor in (6, 5, 4, 3, 2):
        target = np.array([peak.fx_per_mm, peak.fy_per_mm]) / divisor
        for p in peaks:
            v = np.array([p.fx_per_mm, p.fy_per_mm])
            close = min(np.linalg.norm(v - target), np.linalg.norm(v + target))
            if close <= 0.03 * np.linalg.norm(target) and p.amplitude_um >= 0.8 * peak.amplitude_um \
                    and p.snr_db >= options.strong_db:
                return p
    return peak


def _regular_lattice_fit(coords: np.ndarray, amplitude: np.ndarray, repeat: int,
                         tolerance: float) -> tuple[float, np.ndarray]:
    """The summed amplitude of the interlacing peaks on the best regular weave lattice of ``repeat``, and which.

    A regular weave of repeat R (plain, twill, sateen: every thread floats once per repeat) shifts its interlacing
    by s = (1/R, k/R) from thread to thread, k coprime to R (the move number), so its interlacing peaks sit at
    m s modulo the thread lattice, m = 1..R-1 (Schneider, Holtermann and Merhof's weave lattice; the 2-D analogue
    of a crystal's reciprocal lattice). Peaks at other positions of the finer grid (i/R, j/R), such as a
    modulation incommensurate with the threads (fibre twist, stripes) that happens to sit near one, do not count.
    ``coords`` (K, 2) are the peaks in the yarn systems' basis; a peak counts when it lies within ``tolerance``
    lattice steps (1/R) of a lattice point, with its sign either way (the spectrum is symmetric)."""
    if coords.shape[0] == 0:
        return 0.0, np.zeros(0, dtype=bool)
    best, best_on = -1.0, np.zeros(coords.shape[0], dtype=bool)
    m = np.arange(1, repeat)
    for k in (k for k in range(1, repeat) if math.gcd(k, repeat) == 1):
        points = np.stack([m / repeat, (m * k % repeat) / repeat], axis=1)  # (R-1, 2)
        on = np.zeros(coords.shape[0], dtype=bool)
        for sign in (1.0, -1.0):
            wrapped = np.mod(sign * coords, 1.0)  # (K, 2)
            diff = np.abs(wrapped[:, None, :] - points[None, :, :])
            diff = np.minimum(diff, 1.0 - diff).max(axis=2) * repeat  # in lattice steps
            on |= diff.min(axis=1) <= tolerance
        total = float(amplitude[on].sum())
        if total > best:
            best, best_on = total, on
    return best, best_on


#: Courses per wale of a relaxed plain knit (Munden's loop-shape ratio K_c / K_w, about 1.3): which of the two
#: readings of a centred-rectangular stitch lattice is the knit (see :func:`_centred_rectangular`).
_COURSE_WALE_RATIO = 1.3


def _centred_rectangular(systems: list[SpectralPeak], peaks: list[SpectralPeak]) -> list[SpectralPeak] | None:
    """Wales and courses of a knit whose alternate courses are shifted by half a wale (the purl side of a jersey:
    loop heads and sinker arcs alternate from row to row), or None for any other lattice.

    Such a stitch lattice is centred rectangular: its strongest spectral peaks are the two diagonal ones g1, g2 =
    (±1/2 course-step, 1 wale-step) of equal frequency, crossing at an oblique angle, and the rectangular axes are
    g1 + g2 and g1 - g2 (both peaks of the lattice). Read with rows along the shift, the wales are |g1 + g2| / 2
    and the courses |g1 - g2|; read with columns along it, |g1 + g2| and |g1 - g2| / 2. The reading whose courses
    per wale is nearer Munden's 1.3 for a relaxed knit is returned, as (wales, courses) peaks. Two systems that
    cross near a right angle, differ in frequency by more than 3% or in amplitude by more than 1.5x, or whose
    axis g1 - g2 is no peak of the spectrum, are not such a lattice."""
    g1 = np.array([systems[0].fx_per_mm, systems[0].fy_per_mm])
    g2 = np.array([systems[1].fx_per_mm, systems[1].fy_per_mm])
    if g1 @ g2 < 0:
        g2 = -g2
    a1, a2 = systems[0].amplitude_um, systems[1].amplitude_um
    if _angle_between(g1, g2) >= 80.0 or abs(np.linalg.norm(g1) / np.linalg.norm(g2) - 1) > 0.03 \
            or max(a1, a2) > 1.5 * min(a1, a2):
        return None
    plus, minus = g1 + g2, g1 - g2
    axis = next((p for p in peaks if min(np.linalg.norm(np.array([p.fx_per_mm, p.fy_per_mm]) - s * minus)
                                         for s in (1, -1)) <= 0.03 * np.linalg.norm(minus)), None)
    if axis is None:
        return None
    readings = [(plus / 2, minus), (plus, minus / 2)]  # (wales, courses)
    wales, courses = min(readings, key=lambda r: abs(math.log(np.linalg.norm(r[1]) / np.linalg.norm(r[0])
                                                              / _COURSE_WALE_RATIO)))

    def peak(v: np.ndarray) -> SpectralPeak:
        v = v if v[1] > 0 or (v[1] == 0 and v[0] > 0) else -v
        return SpectralPeak(float(v[0]), float(v[1]), min(systems[0].snr_db, systems[1].snr_db), axis.amplitude_um)

    return [peak(wales), peak(courses)]


def _lattice(peaks: list[SpectralPeak], openness: float, options: StructureOptions, field_mm: float,
             low_peak: bool) -> FabricStructure:
    """Yarn systems, repeat and crimp from the refined peaks (strongest first)."""
    # The yarn systems are the peaks of the largest slope amplitude (frequency x amplitude: what shades the
    # image) among those clearly above the background. Ranking by signal-to-background would favour the high
    # harmonics of sharp yarn edges, where the background is faint; by height amplitude, what an L-filter leaves
    # of a wrinkle.
    strong = sorted((p for p in peaks if p.snr_db >= options.strong_db), key=lambda p: -p.amplitude_um * p.frequency)
    if not strong:
        return FabricStructure(False, _no_peak_reason(low_peak, field_mm, options) if low_peak else
                               f"no spectral peak stands {options.strong_db:.0f} dB above the background (the "
                               f"strongest: {peaks[0].snr_db:.1f} dB): no clear yarn system", openness=openness,
                               peaks=peaks)
    strong = [_fundamental(p, peaks, options) for p in strong]
    vec = [np.array([p.fx_per_mm, p.fy_per_mm]) for p in strong]
    first = 0
    # The second system: the largest slope amplitude among the peaks perpendicular to the first within 2° (else
    # 10°, else any 30° off; the fine detail of a satin aliases to peaks a few degrees off), not below 0.3 x the
    # first system's frequency (what an L-filter leaves of a wrinkle).
    second = None
    # a stitch lattice with alternate courses shifted (purl): two equal diagonal peaks, oblique to each other
    twins = [k for k in range(1, len(strong)) if 20.0 <= _angle_between(vec[0], vec[k]) < 80.0
             and abs(strong[k].frequency / strong[0].frequency - 1) <= 0.03
             and strong[k].amplitude_um * strong[k].frequency >= 0.5 * strong[0].amplitude_um * strong[0].frequency]
    centred = _centred_rectangular([strong[0], strong[twins[0]]], peaks) if twins else None
    for least in (88.0, 80.0, 30.0):
        pool = [k for k in range(1, len(strong)) if _angle_between(vec[0], vec[k]) >= least
                and strong[k].frequency >= 0.3 * strong[0].frequency]
        if pool:
            second = pool[0]  # strong is sorted by slope amplitude
            break
    systems = list(centred) if centred is not None else \
        [strong[first]] + ([strong[second]] if second is not None else [])
    systems.sort(key=lambda p: -p.frequency)  # the denser first
    density = [10.0 * p.frequency for p in systems]
    angles = [p.yarn_angle_deg for p in systems]
    if len(systems) == 1:
        return FabricStructure(True, "", density, angles, None, None, None, None, 0.0, openness, peaks)
    basis = np.stack([[p.fx_per_mm, p.fy_per_mm] for p in systems], axis=1)  # columns
    inverse = np.linalg.inv(basis)
    coords = np.array([inverse @ np.array([p.fx_per_mm, p.fy_per_mm]) for p in peaks])  # (K, 2)
    amplitude = np.array([p.amplitude_um for p in peaks])
    near = np.abs(coords).max(axis=1) <= 4.2
    # Interlacing peaks are fractional in both coordinates (the shift of a weave's repeat: (1/2, 1/2) plain,
    # (1/3, 2/3) twill, (2/5, 1/5) satin); a modulation along one yarn (fibre twist, meander) leaves one integer.
    tol = options.lattice_tolerance
    fractional = near & (np.abs(coords - np.round(coords)) > tol / 2).all(axis=1)
    system_amp = sum(p.amplitude_um for p in systems)
    explained = {r: _regular_lattice_fit(coords[fractional], amplitude[fractional], r, tol)
                 for r in range(2, options.max_repeat + 1)}  # r -> (amplitude on the best lattice, its peaks)
    best = max((amp for amp, _ in explained.values()), default=0.0)
    repeat, amp_on = 1, np.zeros(0)
    if centred is not None:  # a stitch lattice: no interlacing; the crimp is the alternate courses' relief wave
        amp_on = np.array([strong[0].amplitude_um, strong[twins[0]].amplitude_um])
    elif best > 0 and best >= options.interlacing_share * system_amp:
        repeat = min(r for r, (amp, _) in explained.items() if amp >= options.lattice_share * best)
        amp_on = amplitude[fractional][explained[repeat][1]]
    crimp = 2.0 * float(amp_on.max()) if amp_on.size else 0.0
    wales = courses = None
    if centred is not None:
        wales_peak, courses_peak = centred
        wales, courses = 10.0 * wales_peak.frequency, 10.0 * courses_peak.frequency
    elif repeat == 1:
        wales_peak = max(systems, key=lambda p: p.snr_db)
        courses_peak = systems[1] if wales_peak is systems[0] else systems[0]
        wales, courses = 10.0 * wales_peak.frequency, 10.0 * courses_peak.frequency
    return FabricStructure(True, "", density, angles, repeat, max(repeat - 1, 0), wales, courses, crimp, openness,
                           peaks)
