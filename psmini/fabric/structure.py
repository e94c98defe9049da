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

import functools
import math
from dataclasses import asdict, dataclass, field
from typing import NamedTuple

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
        interlacing_share: when the largest interlacing peak (fractional in both thread coordinates) is below this
            share of the largest thread peak's amplitude, the interlacing is too weak to call a repeat, which is
            then 1 (on the randomised family of :mod:`data_synth.weaves`, ground-truth heights: a knit's stray
            peaks reach 0.041, the weaker interlacing of a plain weave 0.07).
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
    interlacing_share: float = 0.05
    dynamic_db: float = 50.0
    max_peaks: int = 96
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
            2 plain; 3 a 2/1 twill; 4 a 3/1 twill or a 2/2 basket; 5 a 5-end satin), the larger of
            ``repeat_threads``; None with a single system.
        float_length: the longest float, in threads, of a regular weave of that repeat (R - 1 for R >= 2: 1 plain,
            2 for a 2/1 twill, 4 for a 5-end satin; a 2/2 twill, also R = 4, floats over 2); 0 for R = 1; None when
            the interlacing is no regular weave's (a basket, a rib).
        wales_per_cm, courses_per_cm: for a knit-like lattice (repeat 1), the two systems as wales (the stronger
            one: the columns of stitches dominate the face of a jersey) and courses; None otherwise.
        crimp_um: peak-to-peak height of the interlacing wave: twice the largest amplitude of the lattice peaks
            that are not thread harmonics; 0 when there are none.
        openness: share of the field that is a hole: invalid (unsolved, masked) pixels plus those within
            ``openness_level`` of the height range above the lowest level.
        peaks: the refined peaks, strongest first.
        repeat_threads: the repeat along each system, in threads, the same order as ``threads_per_cm`` (2 and 2
            for a plain weave, 2 ends and 4 picks for a 2/2 warp rib, 1 and 1 for a stitch lattice); None with a
            single system.
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
    repeat_threads: list[int] | None = None

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

        def vertex(lo: Tensor, hi: Tensor, centre: Tensor = centre) -> Tensor:
            den = lo - 2 * centre + hi
            return torch.where(den < 0, 0.5 * (lo - hi) / torch.where(den < 0, den, -torch.ones_like(den)),
                               torch.zeros_like(den)).clamp(-1, 1)

        dx = vertex(logp[k, iy, ix - 1], logp[k, iy, ix + 1])
        dy = vertex(logp[k, iy - 1, ix], logp[k, iy + 1, ix])
        f = torch.stack([fx[k, ix] + dx * step, fy[k, iy] + dy * step], dim=1)
        step = step / 2
    ex = torch.exp(-2j * math.pi * f[:, :1] * cols).to(z.dtype)  # (K, W)
    ey = torch.exp(-2j * math.pi * f[:, 1:] * rows_up).to(z.dtype)  # (K, H)
    value = torch.einsum("kh,hw,kw->k", ey, z, ex)
    return f, value.abs().square()


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines (degrees, [0, 90])."""
    cos = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, float(cos))))


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
        results.append(_lattice(peaks, openness, options, field_mm, bool(low[i].any()), pixel_pitch_mm))
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


#: A regular weave (one shift generates its interlacing: plain, twill, satin) is preferred while its lattice holds at
#: least this share of the amplitude that the best lattice of any kind holds: a fibre twist's or a stripe's
#: modulation near a finer grid point must not turn a plain weave into a rib.
_REGULAR_SHARE = 0.4
#: ... and while it holds at least this share when the best lattice holds nearly every fractional peak
#: (:data:`_GENERAL_EXPLAINS` of their amplitude): a 2/2 basket's regular lattice of repeat 4 holds exactly half
#: of its interlacing, a 3/1 twill's all of it.
_REGULAR_EXPLAINS = 0.75
_GENERAL_EXPLAINS = 0.9
#: The repeat lattice must hold at least this share of the amplitude of all the peaks fractional in both thread
#: coordinates: a weave's do (all of it, on ground-truth heights), a knit's fibre twist and meander scatter them.
_ON_REPEAT_SHARE = 0.5

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


#: A peak lies on a lattice when each of its coordinates in the lattice's basis is within this of an integer.
_ON_LATTICE = 0.04
#: The second yarn system of a woven cloth crosses the first at a right angle, within this many degrees (bow and
#: skew of real cloth are a few degrees); the fitted lattice then keeps whatever angle the peaks say.
_RIGHT_ANGLE_DEG = 2.0
#: ... but never further than this many frequency bins of the field (1 / field): refined peaks lie within a
#: fraction of a bin of their lattice point, and a fine yarn's lattice step is many bins.
_REACH_BINS = 0.5
#: How many of the strongest peaks are tried as the first system.
_FIRST_CANDIDATES = 3
#: Interlacing peaks are the low orders of the weave pattern's series: within this many thread frequencies of the
#: origin in each system (a knit's fibre twist leaves its sidebands further out).
_NEAR = 2.5
#: The coarsest thread lattice whose integer peaks hold at least this share of the amplitude that any candidate
#: holds is the thread lattice (a finer one also holds the harmonics of a rib's paired picks, or noise).
_THREAD_SHARE = 0.8


def _vector(p: SpectralPeak) -> np.ndarray:
    return np.array([p.fx_per_mm, p.fy_per_mm])


def _on_lattice(coords: np.ndarray, tolerance: float = _ON_LATTICE) -> np.ndarray:
    return (np.abs(coords - np.round(coords)) <= tolerance).all(axis=-1)


def _second_system(v1: np.ndarray, peaks: list[SpectralPeak], min_frequency: float, sampling_per_mm: float,
                   field_mm: float) -> np.ndarray | None:
    """The second thread system's frequency vector, from the lattice of all the peaks rather than one peak.

    A peak on the thread lattice has an integer coordinate along the first system ``v1``; what is left of it
    across ``v1`` is a whole multiple of the second system's frequency (a satin's or a twill's weft, hidden under
    the warp floats, shows as the peaks (1, ±1) and (0, 2) of its lattice, not as its own (0, 1)). Candidates
    are those perpendicular remainders divided by 1 to 4, within :data:`_RIGHT_ANGLE_DEG` of a right angle (an
    interlacing peak, fractional along ``v1``, never reduces to one). Each is scored by the amplitude of the peaks
    that lie on the lattice it spans with ``v1``, folded into the sampled band (a fine silk's harmonics alias
    back below Nyquist, at 2 and 3 times a fifth of its thread frequency: the lattice explains them, a finer one
    need not), leaving out ``v1``'s own line, which every candidate's lattice holds; a candidate needs a peak of
    its own, at itself plus a whole number of ``v1`` (a satin's weft hides its (0, 1), not its (1, ±1)). The
    coarsest whose score reaches :data:`_THREAD_SHARE` of the best is taken; None when no peak leaves such a
    remainder above ``min_frequency``. ``sampling_per_mm`` is 1 / pixel pitch, ``field_mm`` the field's side."""
    norm2 = float(v1 @ v1)
    vectors = np.array([_vector(p) for p in peaks])
    amplitude = np.array([p.amplitude_um for p in peaks])
    along = vectors @ v1 / norm2
    candidates: list[np.ndarray] = []
    for k in np.flatnonzero(np.abs(along - np.round(along)) <= _ON_LATTICE):
        rest = vectors[k] - np.round(along[k]) * v1
        length = float(np.linalg.norm(rest))
        if length < 1e-12 or _angle_between(rest, v1) < 90.0 - _RIGHT_ANGLE_DEG:
            continue
        rest = rest if rest @ np.array([-v1[1], v1[0]]) >= 0 else -rest  # one side of v1
        for divisor in (1, 2, 3, 4):
            c = rest / divisor
            if np.linalg.norm(c) >= min_frequency and not any(np.linalg.norm(c - d) <= 0.01 * np.linalg.norm(d)
                                                               for d in candidates):
                candidates.append(c)
    if not candidates:
        return None
    orders = np.array([(m, n) for m in range(-6, 7) for n in range(1, 7)], dtype=np.float64)  # n > 0: off v1's line
    # v1's harmonics (and their aliases, on its line) lie on every candidate's lattice, or a fold of it: left out
    across = np.abs(vectors @ np.array([-v1[1], v1[0]])) / math.sqrt(norm2)
    off_line = across > _REACH_BINS / field_mm

    def score(c: np.ndarray) -> tuple[float, bool]:
        points = orders @ np.stack([v1, c], axis=1).T  # (P, 2) lattice points up to one sampling frequency out,
        kept = np.abs(points).max(axis=1) < sampling_per_mm  # folded once into the sampled band
        points = points[kept] - np.round(points[kept] / sampling_per_mm) * sampling_per_mm
        first = orders[kept, 1] == 1
        reach = min(_ON_LATTICE * min(float(np.linalg.norm(v1)), float(np.linalg.norm(c))), _REACH_BINS / field_mm)
        on = np.zeros(len(peaks), dtype=bool)
        own = False
        for sign in (1.0, -1.0):
            close = np.linalg.norm(sign * vectors[:, None, :] - points[None, :, :], axis=2) <= reach  # (K, P)
            on |= close.any(axis=1)
            own |= bool(close[:, first].any())
        return float(amplitude[on & off_line].sum()), own

    scored = [score(c) for c in candidates]
    supported = [k for k in range(len(candidates)) if scored[k][1]]
    if not supported:
        return None
    best = max(scored[k][0] for k in supported)
    order = sorted(supported, key=lambda k: -np.linalg.norm(candidates[k]))
    return candidates[next(k for k in order if scored[k][0] >= _THREAD_SHARE * best)]


def _refine_basis(basis: np.ndarray, peaks: list[SpectralPeak]) -> np.ndarray:
    """The two frequency vectors (columns) fitted to every peak on their lattice at once (weighted least squares,
    weights the peaks' amplitudes): a peak at (3, 1) pins the lattice three times as tightly as the fundamental."""
    vectors = np.array([_vector(p) for p in peaks])
    coords = vectors @ np.linalg.inv(basis).T
    on = _on_lattice(coords) & (np.abs(coords) <= 6.5).all(axis=1) & (np.abs(coords) > 0.5).any(axis=1)
    n = np.round(coords[on])
    if on.sum() < 2 or np.linalg.matrix_rank(n) < 2:
        return basis
    w = np.sqrt(np.array([p.amplitude_um for p in peaks])[on])[:, None]
    solution, *_ = np.linalg.lstsq(n * w, vectors[on] * w, rcond=None)  # vectors ≈ n @ basis.T
    return solution.T


def _reduce(basis: np.ndarray) -> np.ndarray:
    """Lagrange–Gauss reduction: the two shortest independent vectors of the lattice the columns span."""
    a, b = basis[:, 0].copy(), basis[:, 1].copy()
    for _ in range(32):
        if a @ a > b @ b:
            a, b = b, a
        mu = round(float(a @ b) / float(a @ a))
        if mu == 0:
            break
        b = b - mu * a
    return np.stack([a, b], axis=1)


class _RepeatLattice(NamedTuple):
    """A lattice of interlacing (see :func:`_repeat_lattices`)."""

    cells: int  # threads per repeat cell (the sublattice's index)
    repeats: tuple[int, int]  # threads per repeat along each system
    regular: bool  # generated by one shift (1/R, k/R), k coprime to R: plain, twill, satin
    points: np.ndarray  # (index - 1, 2): the interlacing peaks' positions in the unit cell of the thread lattice


@functools.lru_cache(maxsize=4)
def _repeat_lattices(max_index: int) -> tuple[_RepeatLattice, ...]:
    """Every lattice of interlacing a cloth's repeat can have, with up to ``max_index`` threads per repeat cell
    (a 2/2 basket has 8, a 5-end satin 5).

    A repeat is a sublattice Λ of the threads' integer grid (the shifts that map the interlacing onto itself), of
    index N (threads per repeat cell); its spectral peaks sit on the dual lattice Λ*, whose N - 1 points in the unit
    cell, modulo the thread lattice, are the interlacing peaks (Schneider, Holtermann and Merhof's weave lattice;
    the reciprocal lattice of crystallography). Λ runs over the Hermite normal forms ``(a, 0), (b, d)``,
    ``a d = N``, ``0 <= b < a``: the repeat along the first system is a, along the second ``d a / gcd(a, b)``, and
    k ∈ Λ* when ``k1 a`` and ``k1 b + k2 d`` are integers. A regular weave (plain, twill, satin: every thread
    floats once per repeat) is the cyclic case d = 1, gcd(a, b) = 1: Λ* generated by one shift (1/R, k/R)."""
    out = []
    for a in range(1, max_index + 1):
        for d in range(1, max_index // a + 1):
            if a * d < 2:
                continue
            for b in range(a):
                points = np.array([[m / a, ((n - m * b / a) / d) % 1.0] for m in range(a) for n in range(d)
                                   if (m, n) != (0, 0)])
                out.append(_RepeatLattice(a * d, (a, d * a // math.gcd(a, b)), d == 1 and math.gcd(a, b) == 1,
                                          points))
    return tuple(out)


def _on_repeat_lattice(coords: np.ndarray, lattice: _RepeatLattice, tolerance: float) -> np.ndarray:
    """Which peaks (coords (K, 2) in the threads' basis, either sign) lie within ``tolerance`` lattice steps of an
    interlacing point of ``lattice``."""
    if coords.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    reach = tolerance / max(lattice.repeats)
    diff = np.abs(np.mod(coords, 1.0)[:, None, :] - lattice.points[None, :, :])
    close = np.minimum(diff, 1.0 - diff).max(axis=2) <= reach  # (K, P); the lattice holds -p with p
    on = close.any(axis=1)
    return on


def _system_peak(v: np.ndarray, peaks: list[SpectralPeak]) -> SpectralPeak:
    """A system as a peak: its fitted vector (on the upper half plane) with the signal and amplitude of the peak
    nearest to it (0 when none lies within 3%)."""
    v = v if v[1] > 0 or (v[1] == 0 and v[0] > 0) else -v
    near = [p for p in peaks if min(np.linalg.norm(_vector(p) - v), np.linalg.norm(_vector(p) + v))
            <= 0.03 * np.linalg.norm(v)]
    match = max(near, key=lambda p: p.amplitude_um) if near else None
    return SpectralPeak(float(v[0]), float(v[1]), match.snr_db if match else 0.0,
                        match.amplitude_um if match else 0.0)


def _lattice(peaks: list[SpectralPeak], openness: float, options: StructureOptions, field_mm: float,
             low_peak: bool, pixel_pitch_mm: float) -> FabricStructure:
    """Yarn systems, repeat and crimp from the refined peaks (strongest first).

    The first system is the peak of the largest slope amplitude (frequency x amplitude: what shades the image)
    among those clearly above the background, replaced by its fundamental (ranking by signal-to-background would
    favour the high harmonics of sharp yarn edges, by height amplitude what an L-filter leaves of a wrinkle). The
    second comes from the lattice of every peak (:func:`_second_system`), the two are fitted to all the peaks on
    their lattice together (:func:`_refine_basis`) and reduced to the lattice's two shortest vectors
    (:func:`_reduce`); the repeat is the lattice of the peaks between them (:func:`_repeat_lattices`)."""
    strong = sorted((p for p in peaks if p.snr_db >= options.strong_db), key=lambda p: -p.amplitude_um * p.frequency)
    if not strong:
        return FabricStructure(False, _no_peak_reason(low_peak, field_mm, options) if low_peak else
                               f"no spectral peak stands {options.strong_db:.0f} dB above the background (the "
                               f"strongest: {peaks[0].snr_db:.1f} dB): no clear yarn system", openness=openness,
                               peaks=peaks)
    strong = [_fundamental(p, peaks, options) for p in strong]
    vec = [_vector(p) for p in strong]
    # a stitch lattice with alternate courses shifted (purl): two equal diagonal peaks, oblique to each other
    twins = [k for k in range(1, len(strong)) if 20.0 <= _angle_between(vec[0], vec[k]) < 80.0
             and abs(strong[k].frequency / strong[0].frequency - 1) <= 0.03
             and strong[k].amplitude_um * strong[k].frequency >= 0.5 * strong[0].amplitude_um * strong[0].frequency]
    centred = _centred_rectangular([strong[0], strong[twins[0]]], peaks) if twins else None
    if centred is not None:
        systems = list(centred)
    else:
        # the second system: not below 0.2 x the first system's frequency (what an L-filter leaves of a wrinkle;
        # densities of 10 and 40 per cm are a ratio of 0.25). When the strongest peak has none at a right angle
        # it is an interlacing peak (a twill's, beside sparse threads), and the next strongest is tried.
        systems = [strong[0]]
        for first in range(min(_FIRST_CANDIDATES, len(strong))):
            v2 = _second_system(vec[first], peaks, 0.2 * strong[first].frequency, 1.0 / pixel_pitch_mm, field_mm)
            if v2 is not None:
                basis = _reduce(_refine_basis(np.stack([vec[first], v2], axis=1), peaks))
                systems = [_system_peak(basis[:, k], peaks) for k in range(2)]
                break
    systems.sort(key=lambda p: -p.frequency)  # the denser first
    density = [10.0 * p.frequency for p in systems]
    angles = [p.yarn_angle_deg for p in systems]
    if len(systems) == 1:
        return FabricStructure(True, "", density, angles, None, None, None, None, 0.0, openness, peaks)
    basis = np.stack([_vector(p) for p in systems], axis=1)  # columns
    coords = np.array([np.linalg.solve(basis, _vector(p)) for p in peaks])  # (K, 2)
    amplitude = np.array([p.amplitude_um for p in peaks])
    near = np.abs(coords).max(axis=1) <= _NEAR
    # Interlacing peaks are fractional in both coordinates (the shift of a weave's repeat: (1/2, 1/2) plain,
    # (1/3, 2/3) twill, (2/5, 1/5) satin, (1/2, 1/4) a rib); a modulation along one yarn (fibre twist, meander)
    # leaves one integer.
    tol = options.lattice_tolerance
    fractional = near & (np.abs(coords - np.round(coords)) > tol / 2).all(axis=1)
    thread_amp = max((p.amplitude_um for p, c in zip(peaks, coords, strict=True)
                      if np.abs(c - np.round(c)).max() <= tol / 2 and np.abs(np.round(c)).sum() == 1), default=0.0)
    thread_amp = max(thread_amp, *(p.amplitude_um for p in systems))
    lattices = _repeat_lattices(options.max_repeat)
    on = [_on_repeat_lattice(coords[fractional], lattice, tol) for lattice in lattices]
    explained = [float(amplitude[fractional][hit].sum()) for hit in on]
    best_general = max(explained, default=0.0)
    best_regular = max((e for e, lattice in zip(explained, lattices, strict=True) if lattice.regular), default=0.0)
    # a weave's fractional peaks lie on its repeat lattice; a knit's fibre twist or meander scatters them
    scattered = best_general < _ON_REPEAT_SHARE * float(amplitude[fractional].sum())
    repeats, amp_on, regular = (1, 1), np.zeros(0), True
    if centred is not None:  # a stitch lattice: no interlacing; the crimp is the alternate courses' relief wave
        amp_on = np.array([strong[0].amplitude_um, strong[twins[0]].amplitude_um])
    elif best_general > 0 and not scattered and float(amplitude[fractional].max()) >= \
            options.interlacing_share * thread_amp:
        # a regular weave while one explains enough (a fibre twist's modulation near a finer grid point must not
        # turn a plain weave into a rib); otherwise a basket, a rib: the smallest cell that explains enough
        general = best_regular < _REGULAR_SHARE * best_general or (
            best_regular < _REGULAR_EXPLAINS * best_general
            and best_general >= _GENERAL_EXPLAINS * float(amplitude[fractional].sum()))
        pool = list(range(len(lattices))) if general else [k for k, lattice in enumerate(lattices) if lattice.regular]
        best = max(explained[k] for k in pool)
        chosen = min((k for k in pool if explained[k] >= options.lattice_share * best),
                     key=lambda k: (lattices[k].cells, -explained[k]))
        repeats, regular = lattices[chosen].repeats, lattices[chosen].regular
        amp_on = amplitude[fractional][on[chosen]]
    crimp = 2.0 * float(amp_on.max()) if amp_on.size else 0.0
    repeat = max(repeats)
    wales = courses = None
    if centred is not None:
        wales_peak, courses_peak = centred
        wales, courses = 10.0 * wales_peak.frequency, 10.0 * courses_peak.frequency
    elif repeat == 1:
        wales_peak = max(systems, key=lambda p: p.snr_db)
        courses_peak = systems[1] if wales_peak is systems[0] else systems[0]
        wales, courses = 10.0 * wales_peak.frequency, 10.0 * courses_peak.frequency
    return FabricStructure(True, "", density, angles, repeat, max(repeat - 1, 0) if regular else None, wales,
                           courses, crimp, openness, peaks, repeat_threads=list(repeats))
