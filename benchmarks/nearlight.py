"""Near-light photometric stereo against the distant-light pipeline on simulated rig captures.

For each fabric of data_synth, the cloth lying 0, 0.5 and 1 mm above the card plane (the card used for
flat-fielding stays at 0), rendered noise-free (16-bit) and with the simulator's default noise at 8 bits:

1. ``far_raw``: distant lights seen from the field centre, dark-subtracted images, no card;
2. ``far_flatfield``: the same after division by the card (the seed paper's method);
3. ``near_true``: near-light photometric stereo with the true LEDs and the card;
4. ``near_calibrated``: the same with LEDs fitted by gradient descent (:func:`psmini.fit_leds`) to the simulator's
   noisy 8-bit card images at 0 and 1 mm, started from the nominal rig geometry.

Mean angular error over cloth pixels that at least three LEDs light with usable observations (not saturated, and
under a card bright enough and not saturated, so that flat-fielding can divide by it; shadows and saturation are
handled by the solvers, not skipped; the fraction of pixels with fewer is reported), and the
depth error: RMSE after removing the mean offset (the dome of the distant-light methods shows here), in µm.

Beside each case: the noise floor, least squares at the TRUE surface with the TRUE LEDs on the images as captured
(dark-subtracted, not divided by the noisy card: the floor must not carry the card's noise) over the readings the
renderer lit whose noise-free value is at least one quantisation step (those a solver could tell from a shadow);
near_true's excess over it; how its predicted errors held (the share of scored pixels whose error is below
``normal_std``: 63% for 2-D Gaussian errors predicted right, and the mean of error² / predicted²: 1); the share of
scored pixels whose near-light depth (true LEDs, mean offset removed) is more than 0.1 mm off, near light's absolute
height error (the mean offset itself), the alternations run, and the seconds of near light and of the distant pipeline
(flat-field, least squares, Frankot–Chellappa) in the same run. At the end, near light on a batch of 16 captures
against 16 single calls (seconds per sample).

With ``--speed`` only that last measurement runs (at 400 px by default: the rig's resolution), recorded on its own.

With ``--stability``, how far a rounding-sized change carries: each fabric's noisy 8-bit capture at 0.5 mm is solved,
then solved again with the card scaled by 1 + 1e-7 (about one float32 ulp), in float64 instead of float32, as the
third item of a batch of four, and with another thread count (two, or one if more were asked: another order of
summation): the mean and the largest change of the normals, and the depth's RMS change, for each. Recorded on its
own.

    python benchmarks/nearlight.py [--quick | --speed | --stability] [--json] [--size N]
                                   [--device cpu|cuda] [--threads N] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import kornia
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import append_results, table  # noqa: E402
from data_synth import make_fabric  # noqa: E402
from data_synth.rig import RigConfig, render_capture, render_card  # noqa: E402
from psmini import PhotometricStereo, albedo_normals, angular_error_deg, fit_leds, flatfield  # noqa: E402
from psmini._compile import compile_blocker  # noqa: E402
from psmini.config import ReconstructionConfig  # noqa: E402
from psmini.nearlight import NearLightOptions, near_light_vectors  # noqa: E402
from tests.user_light_models import GaussianBeamLEDs  # noqa: E402

NEAR, DISTANT = ReconstructionConfig(solver="near"), ReconstructionConfig(solver="distant")

CARD_ALBEDO = 0.8
METHODS = ("far_raw", "far_flatfield", "near_true", "near_calibrated")
FULL_FABRICS = ("cotton", "jute", "silk", "twill", "satin", "knit", "purl", "net", "lurex", "taffeta", "print")
QUICK_FABRICS = ("cotton", "taffeta")


def calibrate(config: RigConfig, device: torch.device) -> tuple[torch.nn.Module, dict[str, float]]:
    """LEDs fitted to the simulator's noisy card images at 0 and 1 mm; errors against the truth."""
    cards = [render_card(config, CARD_ALBEDO, seed=10 + i, height_mm=h, device=device)
             for i, h in enumerate((0.0, 1.0))]
    start = time.perf_counter()
    fit = fit_leds(torch.stack([c.images for c in cards]), [0.0, 1.0], config.pixel_pitch_mm, "nominal",
                   card_albedo=CARD_ALBEDO, dark=torch.stack([c.dark for c in cards]), saturation_level=1.0)
    seconds = time.perf_counter() - start
    truth = cards[0].lights
    position_error = (fit.lights.positions_mm - truth.positions_mm.to(fit.lights.positions_mm)).norm(dim=-1).max()
    relative = truth.intensities / truth.intensities.mean()
    intensity_error = ((fit.lights.intensities - relative.to(fit.lights.intensities)) / relative).abs().max()
    return fit.lights, {"position_error_mm": float(position_error), "intensity_error": float(intensity_error),
                        "seconds": seconds}


def dome_error_um(difference: torch.Tensor, region: torch.Tensor, pixel_pitch_mm: float,
                  sigma_mm: float = 1.0) -> float:
    """RMS over the region of the depth error low-passed at ``sigma_mm``: the dome, without the weave-scale error.

    Normalised convolution (the error outside the region does not leak in): blur(d·m) / blur(m).
    """
    sigma = sigma_mm / pixel_pitch_mm
    size = 2 * int(3 * sigma) + 1
    weight = region.to(difference)[None, None]
    blur = lambda x: kornia.filters.gaussian_blur2d(x, (size, size), (sigma, sigma), border_type="constant")  # noqa: E731
    low = blur(difference[None, None] * weight) / blur(weight).clamp_min(1e-6)
    return float(low[0, 0][region].square().mean().sqrt()) * 1000


def evaluate_case(fabric, config, offset_mm, calibrated, card, device) -> dict[str, dict[str, float]]:
    """All four methods on one rendered capture."""
    capture = render_capture(fabric, config, height_offset_mm=offset_mm, device=device)
    images, dark = capture.images[None], capture.dark[None]
    # usable: lit, not saturated, and under a card that is neither saturated nor too dark to divide by
    valid = flatfield(images, card.images[None], dark, card.dark[None], CARD_ALBEDO,
                      saturation_level=capture.saturation_level).valid[0]
    usable = capture.lit & valid
    region = (usable.sum(0, keepdim=True) >= 3) & capture.mask.bool()
    cloth = capture.mask.bool()
    truth_normals, truth_depth = capture.normals[None], capture.depth_mm[None]
    pitch = config.pixel_pitch_mm
    near = lambda lights: PhotometricStereo(lights, pitch, NEAR)(  # noqa: E731
        images, card.images[None], dark, card.dark[None], card_albedo=CARD_ALBEDO, saturation_level=1.0)
    runs = {
        "far_raw": lambda: PhotometricStereo(capture.lights, pitch, DISTANT)(images, dark=dark, saturation_level=1.0),
        "far_flatfield": lambda: PhotometricStereo(capture.lights, pitch, DISTANT)(
            images, card.images[None], dark, card.dark[None], card_albedo=CARD_ALBEDO, saturation_level=1.0),
        "near_true": lambda: near(capture.lights),
        "near_calibrated": lambda: near(calibrated),
    }
    results, near_result = {}, None
    for method, run in runs.items():
        start = time.perf_counter()
        result = run()
        if method == "near_true":
            near_result = result
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - start
        error = angular_error_deg(result.normals, truth_normals)[0, 0][region[0]]
        difference = (result.depth - truth_depth)[0, 0]
        height_error = difference[region[0]].mean()  # the absolute height's error, which the RMSE below leaves out
        difference = difference - height_error
        results[method] = {
            "angle_deg": float(error.mean()),
            "height_error_um": float(height_error) * 1000,
            "depth_rmse_um": float(difference[region[0]].square().mean().sqrt()) * 1000,
            "dome_um": dome_error_um(difference, region[0], pitch),
            "off_0.1mm": float((difference[region[0]].abs() > 0.1).float().mean()),
            "seconds": seconds,
            "iterations": getattr(result, "iterations", 0),
        }
    # the noise floor: least squares at the true surface with the true LEDs on the images as captured, over the
    # readings the renderer lit whose noise-free value is at least one quantisation step
    clean = render_capture(fabric, config.replace(noise=False, bit_depth=16), height_offset_mm=offset_mm,
                           device=device)
    step = 1 / (2**config.bit_depth - 1) if config.noise else 0.0
    readable = capture.lit & ((clean.images - clean.dark) >= step) & (capture.images < capture.saturation_level)
    vectors = near_light_vectors(capture.lights, truth_depth, pitch, None)
    raw = (images - dark).clamp_min(0)
    scored = lambda normals: float(angular_error_deg(normals, truth_normals)[0, 0][region[0]].mean())  # noqa: E731
    results["floor"] = {"angle_deg": scored(albedo_normals(raw, vectors, weights=readable[None])[1])}
    error = angular_error_deg(near_result.normals, truth_normals)[0, 0][region[0]]
    predicted = near_result.normal_std[0, 0][region[0]]
    results["calibration"] = {"within": float((error < predicted).float().mean()),
                              "ratio": float((error / predicted).square().mean())}
    results["coverage"] = {"fewer_than_3": 1 - float(region.sum()) / float(cloth.sum())}
    return results


def batch_speed(size: int, pitch: float, device: torch.device, count: int = 16) -> dict[str, float]:
    """Seconds per sample of near light on one batch of ``count`` noisy captures against single calls, and of the
    distant pipeline on the same captures one by one (each single call timed twice, interleaved near/distant, the
    faster kept: the machines are shared; the batch timed twice as well); and of near light compiled
    (``NearLightOptions(compile=True)``, where this machine can compile), its first call (the compilation) and how
    far its results are from the eager ones on every capture."""
    config = RigConfig(size=size, pixel_pitch_mm=pitch, noise=True, bit_depth=8, intensity_spread=0.05)
    card = render_card(config, CARD_ALBEDO, device=device)
    fabrics = [make_fabric(FULL_FABRICS[i % len(FULL_FABRICS)], size=size, pixel_pitch_mm=pitch, seed=0)
               for i in range(count)]
    captures = [render_capture(f, config, height_offset_mm=0.5 * (i % 3), device=device) for i, f in enumerate(fabrics)]
    images, dark = torch.stack([c.images for c in captures]), torch.stack([c.dark for c in captures])
    lights = captures[0].lights
    near = PhotometricStereo(lights, pitch, NEAR)
    far = PhotometricStereo(lights, pitch, DISTANT)
    # a user's model as cheap as the LED's (tests/user_light_models.py: a Gaussian beam overriding forward)
    user = PhotometricStereo(GaussianBeamLEDs(lights.positions_mm, lights.principal_directions, lights.intensities),
                             pitch, NEAR)
    fused = PhotometricStereo(lights, pitch, ReconstructionConfig(solver="near", near=NearLightOptions(compile=True)))

    def timed(run) -> float:
        start = time.perf_counter()
        run()
        if device.type == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - start

    reference, reference_dark = card.images[None], card.dark[None]
    def solve(method, i: int):
        return method(images[i : i + 1], reference, dark[i : i + 1], reference_dark, card_albedo=CARD_ALBEDO,
                      saturation_level=1.0)

    last = {}  # each method's last result on each capture, (id(method), i) -> result

    def single_call(method, i: int) -> float:
        def run() -> None:
            last[id(method), i] = solve(method, i)

        return min(timed(run) for _ in range(2))

    can_compile = compile_blocker(device) is None
    first_compiled = timed(lambda: solve(fused, 0)) if can_compile else math.nan
    single = distant = users = compiled = 0.0
    for i in range(count):
        single += single_call(near, i) / count
        distant += single_call(far, i) / count
        users += single_call(user, i) / count
        compiled += single_call(fused, i) / count if can_compile else math.nan
    # the compiled results against the eager ones (those the timed calls returned): the normals' angle, the relief
    # (the depth less its mean height) and the mean height
    apart: dict[str, list[float]] = {"mean_deg": [], "max_deg": [], "relief_um": [], "offset_um": []}
    for i in range(count if can_compile else 0):
        eager, other = last[id(near), i], last[id(fused), i]
        angle = angular_error_deg(eager.normals.double(), other.normals.double())
        offset = other.offset_mm - eager.offset_mm
        apart["mean_deg"].append(float(angle.mean()))
        apart["max_deg"].append(float(angle.max()))
        apart["relief_um"].append(1e3 * float((other.depth - eager.depth - offset.view(-1, 1, 1, 1)).abs().max()))
        apart["offset_um"].append(1e3 * float(offset.abs().max()))
    # the batch timed twice too, the faster kept, like each single call
    batch = min(timed(lambda: near(images, reference, dark, reference_dark, card_albedo=CARD_ALBEDO,
                                   saturation_level=1.0)) for _ in range(2)) / count
    return {"single": single, "batch": batch, "far": distant, "user": users, "compiled": compiled,
            "first_compiled": first_compiled} | {f"compiled_{k}": max(v, default=math.nan) for k, v in apart.items()}


def speed_only(size: int, pitch: float, device: torch.device, args: argparse.Namespace) -> int:
    """The near-light speed alone: single calls, a batch of 16 and the distant pipeline, in one run."""
    speed = batch_speed(size, pitch, device)
    rows = [["near light, single calls", f"{speed['single']:.3f}", f"{speed['single'] / speed['far']:.1f}"],
            ["near light, batch of 16", f"{speed['batch']:.3f}", f"{speed['batch'] / speed['far']:.1f}"],
            ["near light, a user's Gaussian-beam model, single calls", f"{speed['user']:.3f}",
             f"{speed['user'] / speed['far']:.1f}"],
            ["near light compiled (NearLightOptions(compile=True)), single calls", f"{speed['compiled']:.3f}",
             f"{speed['compiled'] / speed['far']:.1f}"],
            ["distant pipeline, single calls", f"{speed['far']:.3f}", "1.0"]]
    report = table(["run", "s per sample", "× distant"], rows)
    note = (f"16 noisy 8-bit captures of the 11 fabrics, 8 × {size} × {size} px at {pitch:.4f} mm/px, on {device}, "
            f"{torch.get_num_threads()} thread(s): flat-field, normals and depth. Each single call and the batch timed "
            f"twice, the faster kept. Batch / single: {speed['batch'] / speed['single']:.2f}; the user's model (a "
            f"LEDLights subclass overriding forward, tests/user_light_models.py) / the built-in LED: "
            f"{speed['user'] / speed['single']:.2f}. Compiled / eager: {speed['compiled'] / speed['single']:.2f}, "
            f"after a first call of {speed['first_compiled']:.0f} s (the compilation); compiled against eager over the "
            f"16 captures: normals {speed['compiled_mean_deg']:.1e}° apart on average (the largest mean), "
            f"{speed['compiled_max_deg']:.2f}° at most (one pixel), the relief (depth less its mean height) "
            f"{speed['compiled_relief_um']:.3f} µm at most, the mean height {speed['compiled_offset_um']:.2f} µm (the "
            f"solver's own sensitivity to rounding: --stability). Load average at the end: "
            f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores.")
    print(report)
    print(note)
    if not args.no_record:
        append_results(f"Near-light speed (benchmarks/nearlight.py --speed, {size} px)", report + "\n\n" + note, device)
    if args.json:
        print(json.dumps(speed, sort_keys=True))
    return 0



def stability_only(size: int, pitch: float, device: torch.device, args: argparse.Namespace) -> int:
    """How far a rounding-sized change carries through near light (see the module docstring)."""
    config = RigConfig(size=size, pixel_pitch_mm=pitch, noise=True, bit_depth=8, intensity_spread=0.05)
    card = render_card(config, CARD_ALBEDO, device=device)
    rows, worst = [], {"card": 0.0, "float64": 0.0, "batch": 0.0, "threads": 0.0}
    threads = torch.get_num_threads()
    other_threads = 2 if threads == 1 else 1
    for name in FULL_FABRICS:
        capture = render_capture(make_fabric(name, size=size, pixel_pitch_mm=pitch, seed=0), config,
                                 height_offset_mm=0.5, device=device)

        def solve(images, reference, dtype=torch.float32, capture=capture):
            lights = capture.lights.to(dtype=dtype)
            return PhotometricStereo(lights, pitch, NEAR)(
                images.to(dtype), reference.to(dtype), capture.dark[None].to(dtype), card.dark[None].to(dtype),
                card_albedo=CARD_ALBEDO, saturation_level=1.0)

        images, reference = capture.images[None], card.images[None]
        base = solve(images, reference)
        others = {"card": solve(images, reference * (1 + 1e-7)),
                  "float64": solve(images, reference, torch.float64),
                  "batch": solve(torch.cat([images.roll(1, -1), images.roll(2, -1), images, images.roll(3, -1)]),
                                 reference).item(2)}
        torch.set_num_threads(other_threads)  # another order of summation
        try:
            others["threads"] = solve(images, reference)
        finally:
            torch.set_num_threads(threads)
        row = [name]
        for key, other in others.items():
            moved = angular_error_deg(base.normals.double(), other.normals.double())
            depth = (base.depth.double() - other.depth.double()).square().mean().sqrt()
            worst[key] = max(worst[key], float(moved.mean()))
            row += [f"{float(moved.mean()):.5f} / {float(moved.max()):.3f}", f"{1e3 * float(depth):.3f}"]
        rows.append(row)
        print(" | ".join(row), flush=True)
    report = table(["fabric", "card × (1 + 1e-7): normals mean / max (°)", "depth RMS (µm)",
                    "float64: normals mean / max (°)", "depth RMS (µm)", "batch of 4: normals mean / max (°)",
                    "depth RMS (µm)", f"{other_threads} thread(s): normals mean / max (°)", "depth RMS (µm)"], rows)
    note = (f"Noisy 8-bit captures, the cloth 0.5 mm above the card, 8 × {size} × {size} px at {pitch:.4f} mm/px, on "
            f"{device}, {torch.get_num_threads()} thread(s): near light (float32, alone) against the same capture with "
            "the card scaled by 1 + 1e-7, solved in float64, solved as the third item of a batch of four (the "
            f"others shifted copies) and solved with {other_threads} thread(s) (another order of summation). Largest "
            f"mean change over the fabrics: card {worst['card']:.5f}°, float64 {worst['float64']:.5f}°, batch "
            f"{worst['batch']:.5f}°, threads {worst['threads']:.5f}°.")
    print(report)
    print(note)
    if not args.no_record:
        append_results(f"Near-light stability (benchmarks/nearlight.py --stability, {size} px)", report + "\n\n" + note,
                       device)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="two fabrics, 128 px, one offset: under a minute on a CPU")
    parser.add_argument("--speed", action="store_true",
                        help="only the speed of near light against the distant pipeline")
    parser.add_argument("--stability", action="store_true",
                        help="only how far a change of one part in 10^7 of the card carries through near light")
    parser.add_argument("--json", action="store_true", help="last line: one JSON object of mean errors")
    parser.add_argument("--size", type=int, default=None, help="image side in pixels (default 400, quick 128)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch's CPU threads (default: torch's own choice, the machine's cores); the speed "
                        "target of near light is set on one")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    if args.threads is not None:
        if args.threads < 1:
            parser.error(f"--threads must be at least 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    size = args.size or (128 if args.quick else 400)
    fabrics = QUICK_FABRICS if args.quick else FULL_FABRICS
    offsets = (1.0,) if args.quick else (0.0, 0.5, 1.0)
    pitch = 10.0 / size  # the rig's 10 mm field at any resolution
    if args.speed:
        return speed_only(size, pitch, device, args)
    if args.stability:
        return stability_only(size, pitch, device, args)

    rows, summary, worst, floors = [], {}, {}, {False: [], True: []}
    per_fabric: dict[str, list[tuple[float, float, float, float]]] = {}
    heights = {False: [], True: []}  # near_true's absolute height error per case, µm
    noisy_config = RigConfig(size=size, pixel_pitch_mm=pitch, noise=True, bit_depth=8, intensity_spread=0.05)
    calibrated, fit = calibrate(noisy_config, device)
    for noisy in (False, True):
        config = noisy_config if noisy else noisy_config.replace(noise=False, bit_depth=16)
        card = render_card(config, CARD_ALBEDO, device=device)
        collected = {method: [] for method in METHODS}
        for name in fabrics:
            fabric = make_fabric(name, size=size, pixel_pitch_mm=pitch, seed=0)
            for offset in offsets:
                case = evaluate_case(fabric, config, offset, calibrated, card, device)
                for method in METHODS:
                    collected[method].append(case[method])
                near_case, far_case = case["near_true"], case["far_flatfield"]
                if noisy:
                    per_fabric.setdefault(name, []).append(
                        (near_case["angle_deg"] - case["floor"]["angle_deg"], case["calibration"]["within"],
                         case["calibration"]["ratio"], near_case["depth_rmse_um"]))
                floors[noisy].append(case["floor"]["angle_deg"])
                heights[noisy].append(near_case["height_error_um"])
                rows.append([name, f"{offset:g}", "8-bit noisy" if noisy else "noise-free"]
                            + [f"{case[m]['angle_deg']:.3f} / {case[m]['depth_rmse_um']:.0f} / {case[m]['dome_um']:.1f}"
                               for m in METHODS]
                            + [f"{case['floor']['angle_deg']:.3f}",
                               f"{near_case['angle_deg'] - case['floor']['angle_deg']:+.3f}",
                               f"{100 * case['calibration']['within']:.0f}% / {case['calibration']['ratio']:.2f}",
                               f"{near_case['depth_rmse_um'] / far_case['depth_rmse_um']:.2f}",
                               f"{100 * near_case['off_0.1mm']:.2f}%", f"{near_case['height_error_um']:+.0f}",
                               f"{100 * case['coverage']['fewer_than_3']:.1f}%", f"{near_case['iterations']}",
                               f"{near_case['seconds']:.2f}", f"{far_case['seconds']:.3f}"])
                print(" | ".join(rows[-1]), flush=True)
        for method in METHODS:
            key = method if noisy else f"{method}_noisefree"
            summary[key] = sum(c["angle_deg"] for c in collected[method]) / len(collected[method])
            worst[key] = (max(c["angle_deg"] for c in collected[method]), max(c["dome_um"] for c in collected[method]))
    header = (["fabric", "offset (mm)", "render"] + [f"{m}: ° / µm / dome µm" for m in METHODS]
              + ["noise floor (°)", "near_true − floor (°)", "below normal_std / (error / std)²",
                 "depth near / far_flatfield", "near > 0.1 mm off", "near height error (µm)",
                 "lit by < 3", "alternations", "near s", "far_flatfield s"])
    report = table(header, rows)
    means = table(["method", "mean error noise-free (°)", "worst case noise-free (°)", "worst dome noise-free (µm)",
                   "mean error 8-bit noisy (°)", "worst case noisy (°)"],
                  [[m, f"{summary[m + '_noisefree']:.3f}", f"{worst[m + '_noisefree'][0]:.3f}",
                    f"{worst[m + '_noisefree'][1]:.1f}", f"{summary[m]:.3f}", f"{worst[m][0]:.3f}"] for m in METHODS]
                  + [["noise floor", f"{sum(floors[False]) / len(floors[False]):.3f}", "", "",
                      f"{sum(floors[True]) / len(floors[True]):.3f}", ""]])
    def mean(values: list[tuple[float, float, float, float]], index: int) -> float:
        return sum(v[index] for v in values) / len(values)

    fabric_rows = [[name, f"{mean(values, 0):+.3f}", f"{100 * mean(values, 1):.0f}%", f"{mean(values, 2):.2f}",
                    f"{mean(values, 3):.1f}"] for name, values in per_fabric.items()]
    within = sum(mean(values, 0) <= 0.05 for values in per_fabric.values())
    by_fabric = table(["fabric (8-bit noisy, mean over offsets)", "near_true − floor (°)", "below normal_std",
                       "(error / normal_std)²", "depth RMSE (µm)"], fabric_rows)
    by_fabric += f"\n\nWithin 0.05° of the floor: {within} of {len(per_fabric)} fabrics."
    speed = batch_speed(size, pitch, device)
    note = (f"{len(fabrics)} fabrics × offsets {offsets} mm, {size}×{size} px at {pitch:.4f} mm/px, on {device}. "
            "Cells: mean angular error over cloth pixels with ≥ 3 usable LEDs (lit, unsaturated, card usable) / depth "
            "RMSE after removing "
            "the mean offset / dome: RMS of that depth error low-passed at σ = 1 mm (normalised convolution over the "
            "same pixels), the low-frequency bend without the weave-scale integration error. Noise floor: least "
            "squares "
            "at the true surface with the true LEDs on the dark-subtracted images (no card), over the lit readings of "
            "at least one quantisation step. Below normal_std: the share of scored pixels whose error is below the "
            "predicted RMS error (63% when right), and the mean of (error / predicted)² (1 when right). Near height "
            f"error: the mean of "
            f"near_true's depth minus the true height over the same pixels (the absolute height, which the RMSE "
            f"leaves out), {min(heights[False]):+.0f} to {max(heights[False]):+.0f} µm noise-free, "
            f"{min(heights[True]):+.0f} to {max(heights[True]):+.0f} µm noisy. Near light on a batch "
            f"of 16 {size}² captures: {speed['batch']:.2f} s per sample, single calls {speed['single']:.2f} s per "
            f"sample (ratio {speed['batch'] / speed['single']:.2f}); distant pipeline {speed['far']:.3f} s per sample "
            f"(near / distant {speed['single'] / speed['far']:.0f}×). LEDs calibrated from noisy 8-bit cards at 0 and "
            f"1 mm in {fit['seconds']:.1f} s: "
            f"largest position error {fit['position_error_mm']:.3f} mm, intensity error "
            f"{100 * fit['intensity_error']:.2f}%.")
    print(report)
    print(means)
    print(by_fabric)
    print(note)
    if not args.no_record:
        title = "Near-light photometric stereo (benchmarks/nearlight.py" + (" --quick)" if args.quick else ")")
        append_results(title, report + "\n\n" + means + "\n\n" + by_fabric + "\n\n" + note, device)
    if args.json:
        payload = {m: summary[m] for m in METHODS}
        payload["near_true_noisefree"] = summary["near_true_noisefree"]
        payload["far_flatfield_noisefree"] = summary["far_flatfield_noisefree"]
        payload["calibration"] = fit
        payload["noise_floor"] = sum(floors[True]) / len(floors[True])
        payload["speed"] = speed
        print(json.dumps(payload, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
