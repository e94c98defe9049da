"""Speed and memory of flat-field + least-squares normals + Frankot–Chellappa on a batch of rig-sized samples.

psmini's batched torch pipeline against a plain NumPy implementation of the same maths (dark subtraction, card
division, pseudo-inverse normals, gradients, mirrored Frankot–Chellappa on the doubled grid keeping the mean
slope: the maths of psmini before its N-point cosine-transform solver), measured in the same run. Each
implementation runs in its own child process so that its peak resident memory is its own.

Times are the best of ``--repeat`` runs, both as wall time and as the process's CPU time: on one thread the CPU
time is what a quiet machine's wall time would be, and it does not count the time other processes on a shared
machine take the core away (the wall time then does). The torch child also times each stage on its own.

    python benchmarks/pipeline_speed.py [--batch 8] [--size 400] [--repeat 5] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import append_results, table  # noqa: E402
from psmini import PhotometricStereo, ring_lights  # noqa: E402

LEDS, ZENITH_DEG, PITCH_MM, CARD_ALBEDO = 8, 55.0, 0.025, 0.8


def make_inputs(batch: int, size: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random but plausible raw images, card images and dark frames, float32.

    The card capture's dark frame is the first sample's (``dark[:1]``), passed as such to both implementations: a
    card capture has its own dark frame, and card-only work is then done once per batch, not per sample.
    """
    rng = np.random.default_rng(seed)
    card = (0.5 + 0.3 * rng.random((LEDS, size, size))).astype(np.float32)
    dark = np.full((batch, 1, size, size), 0.02, np.float32)
    images = (card[None] * rng.random((batch, LEDS, size, size)) + dark).astype(np.float32)
    return {"images": images, "reference": card + np.float32(0.02), "dark": dark}


def numpy_pipeline(images, reference, dark, lights, min_reference=0.02, min_nz=1e-2, pitch=PITCH_MM):
    """The same maths as psmini.PhotometricStereo, in plain NumPy, one sample at a time."""
    matrix = lights / lights[:, 2:3]
    pinv = np.linalg.pinv(matrix)
    card = reference - dark[0]
    trusted = card > min_reference * card.max(axis=(1, 2), keepdims=True)
    depths = []
    for sample, sample_dark in zip(images, dark, strict=True):
        signal = np.clip(sample - sample_dark, 0, None)
        flat = np.where(trusted, CARD_ALBEDO * signal / np.where(trusted, card, 1), 0)
        m = np.tensordot(pinv, flat, axes=(1, 0))
        normals = m / np.maximum(np.linalg.norm(m, axis=0), 1e-30)
        nz = np.maximum(normals[2], min_nz)
        p, q = -normals[0] / nz, -normals[1] / nz
        depths.append(numpy_frankot_chellappa(p, q, pitch))
    return np.stack(depths)


def numpy_frankot_chellappa(p, q, pitch):
    """Mirrored Frankot–Chellappa with the mean slope kept (see psmini.integrate.frankot_chellappa)."""
    height, width = p.shape
    p0, q0 = p.mean(), q.mean()
    gu, gv = (p - p0) * pitch, -(q - q0) * pitch
    gu = np.concatenate([gu, -gu[:, ::-1]], 1)
    gv = np.concatenate([gv, gv[:, ::-1]], 1)
    gu = np.concatenate([gu, gu[::-1]], 0)
    gv = np.concatenate([gv, -gv[::-1]], 0)
    wu = 2 * np.pi * np.fft.rfftfreq(2 * width)[None, :]
    wv = 2 * np.pi * np.fft.fftfreq(2 * height)[:, None]
    denom = wu**2 + wv**2
    denom[0, 0] = 1
    z = np.fft.irfft2((-1j * wu * np.fft.rfft2(gu) - 1j * wv * np.fft.rfft2(gv)) / denom, s=gu.shape)[:height, :width]
    v, u = np.meshgrid(np.arange(height) - (height - 1) / 2, np.arange(width) - (width - 1) / 2, indexing="ij")
    z = z + (p0 * u - q0 * v) * pitch
    return z - z.mean()


def best_times(func, repeat: int, device: str = "cpu") -> tuple[float, float]:
    """Best wall time and best process CPU time of ``func`` in seconds over ``repeat`` runs, after one warm-up."""
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    func()
    sync()
    wall, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        func()
        sync()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return min(wall), min(cpu)


def torch_stages(model, tensors: dict, repeat: int) -> dict[str, float]:
    """CPU seconds of each stage of the distant pipeline on its own (best of ``repeat``), for the whole batch;
    flat-field and normals capture by capture, as the pipeline runs them on the CPU (``psmini._chunks``)."""
    from psmini._chunks import chunks
    from psmini.flatfield import flatfield
    from psmini.integrate import integrate
    from psmini.normals import albedo_normals, normals_to_gradients
    from psmini.pipeline import distant_light_matrix

    images, reference, dark = tensors["images"], tensors["reference"], tensors["dark"]
    parts = chunks(images)
    flat = [flatfield(images[part], reference, dark[part], dark[:1], CARD_ALBEDO).images for part in parts]
    matrix = distant_light_matrix(model.lights, True, images)
    albedo, normals = (torch.cat(x) for x in zip(*(albedo_normals(chunk, matrix) for chunk in flat), strict=True))
    p, q = normals_to_gradients(normals)
    solved = albedo > 0

    def flatfield_chunks():  # each chunk's images dropped before the next, as in the pipeline
        for part in parts:
            flatfield(images[part], reference, dark[part], dark[:1], CARD_ALBEDO)

    stages = {
        "flat-field": flatfield_chunks,
        "normals": lambda: [albedo_normals(chunk, matrix) for chunk in flat],
        "gradients": lambda: normals_to_gradients(normals),
        "Frankot–Chellappa": lambda: integrate(p, q, method="fc", pixel_pitch_mm=PITCH_MM, mask=solved),
    }
    return {name: best_times(func, repeat)[1] for name, func in stages.items()}


def run_child(impl: str, device: str, batch: int, size: int, repeat: int) -> dict:
    """Time one implementation in this process; report seconds per sample (wall, CPU) and peak memory."""
    inputs = make_inputs(batch, size)
    lights = ring_lights(LEDS, ZENITH_DEG, dtype=torch.float64).numpy()
    if impl == "numpy":
        wall, cpu = best_times(lambda: numpy_pipeline(**inputs, lights=lights), repeat)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return {"s_per_sample": wall / batch, "cpu_per_sample": cpu / batch, "peak_mb": peak}
    tensors = {k: torch.from_numpy(v).to(device) for k, v in inputs.items()}
    model = PhotometricStereo(torch.from_numpy(lights).float(), pixel_pitch_mm=PITCH_MM).to(device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    with torch.no_grad():
        wall, cpu = best_times(
            lambda: model(tensors["images"], tensors["reference"], tensors["dark"], tensors["dark"][:1],
                          card_albedo=CARD_ALBEDO),
            repeat, device,
        )
        stages = torch_stages(model, tensors, repeat) if device == "cpu" and torch.get_num_threads() == 1 else {}
    peak = (
        torch.cuda.max_memory_allocated() / 2**20 if device == "cuda"
        else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    )
    return {"s_per_sample": wall / batch, "cpu_per_sample": cpu / batch, "peak_mb": peak,
            "stages": {name: seconds / batch for name, seconds in stages.items()}}


def child_env(impl: str) -> dict[str, str]:
    """The child's environment: NumPy's BLAS on one thread (like for like with torch's one thread: with two, its
    CPU time counted both cores, 55 against 25-30 ms per sample), without this workplace's OPENBLAS_CORETYPE and
    OPENBLAS_L2_SIZE, which are there for older OpenBLAS builds and slow a current one."""
    env = dict(os.environ)
    if impl == "numpy":
        env = {k: v for k, v in env.items() if k not in ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")}
        env["OPENBLAS_NUM_THREADS"] = "1"
    return env


def check_agreement(batch: int, size: int, dtype: torch.dtype = torch.float64) -> tuple[float, float]:
    """Largest depth difference (mm) and that difference over the largest |depth|, torch in ``dtype`` vs NumPy
    (float64, the doubled-grid solver) on the same input."""
    inputs = make_inputs(batch, size)
    lights = ring_lights(LEDS, ZENITH_DEG, dtype=torch.float64)
    expected = numpy_pipeline(**inputs, lights=lights.numpy())
    tensors = {k: torch.from_numpy(v).to(dtype) for k, v in inputs.items()}
    with torch.no_grad():
        result = PhotometricStereo(lights.to(dtype), pixel_pitch_mm=PITCH_MM)(
            tensors["images"], tensors["reference"], tensors["dark"], tensors["dark"][:1], card_albedo=CARD_ALBEDO
        )
    difference = float(np.abs(result.depth[:, 0].double().numpy() - expected).max())
    return difference, difference / float(np.abs(expected).max())


def check_fc_against_doubled_grid(size: int) -> dict[str, float]:
    """psmini's FC (N-point cosine transforms) against the doubled-grid FFT solve that it replaced (``_mirror`` +
    ``_fc_periodic``, in torch) on one benchmark sample's slopes: max |Δz| / max |z| of each in float32 against
    the doubled grid in float64, of the two float32 results, and of the two float64 results."""
    from psmini.integrate._common import centred_grid
    from psmini.integrate.fourier import _fc_periodic, _mirror, frankot_chellappa
    from psmini.normals import normals_to_gradients

    def doubled_grid(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        p0, q0 = p.mean(dim=(-2, -1), keepdim=True), q.mean(dim=(-2, -1), keepdim=True)
        z = _fc_periodic(*_mirror((p - p0) * PITCH_MM, -(q - q0) * PITCH_MM))[..., :size, :size]
        u, v = centred_grid(size, size, p)
        z = z + (p0 * u - q0 * v) * PITCH_MM
        return z - z.mean()

    inputs = {k: torch.from_numpy(v) for k, v in make_inputs(1, size).items()}
    model = PhotometricStereo(ring_lights(LEDS, ZENITH_DEG), pixel_pitch_mm=PITCH_MM)
    with torch.no_grad():
        result = model(inputs["images"], inputs["reference"], inputs["dark"], inputs["dark"][:1],
                       card_albedo=CARD_ALBEDO)
        p, q = normals_to_gradients(result.normals)
        exact = doubled_grid(p.double(), q.double())
        new32, old32 = frankot_chellappa(p, q, PITCH_MM).double(), doubled_grid(p, q).double()
        new64 = frankot_chellappa(p.double(), q.double(), PITCH_MM)
    scale = float(exact.abs().max())
    return {name: float((a - b).abs().max()) / scale for name, (a, b) in
            {"new32": (new32, exact), "old32": (old32, exact), "new_old32": (new32, old32),
             "new_old64": (new64, exact)}.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--size", type=int, default=400)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--child", choices=["numpy", "torch"], help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        if args.threads:
            torch.set_num_threads(args.threads)
        print(json.dumps(run_child(args.child, args.device, args.batch, args.size, args.repeat)))
        return 0

    difference, relative = check_agreement(min(args.batch, 2), min(args.size, 128))
    difference32, relative32 = check_agreement(1, args.size, torch.float32)
    fc = check_fc_against_doubled_grid(args.size)
    threads = torch.get_num_threads()
    # NumPy's maths here is single-threaded: torch is timed on one thread (like for like) and on all of them
    runs = [("numpy", "cpu", 1), ("torch", "cpu", 1)] + ([("torch", "cpu", threads)] if threads > 1 else [])
    runs += [("torch", "cuda", threads)] if torch.cuda.is_available() else []
    figures = {}
    for impl, device, count in runs:
        command = [sys.executable, __file__, "--child", impl, "--device", device, "--batch", str(args.batch),
                   "--size", str(args.size), "--repeat", str(args.repeat), "--threads", str(count)]
        output = subprocess.run(command, capture_output=True, text=True, check=True, env=child_env(impl)).stdout
        figures[(impl, device, count)] = json.loads(output.strip().splitlines()[-1])
    base_wall, base_cpu = figures[("numpy", "cpu", 1)]["s_per_sample"], figures[("numpy", "cpu", 1)]["cpu_per_sample"]
    rows = []
    for (impl, device, count), fig in figures.items():
        single = count == 1 and device == "cpu"
        rows.append([
            f"{impl} ({device}, {count} thread{'s' if count > 1 else ''})",
            f"{fig['cpu_per_sample'] * 1e3:.1f}" if single else "—",
            f"{base_cpu / fig['cpu_per_sample']:.2f}×" if single else "—",
            f"{fig['s_per_sample'] * 1e3:.1f}", f"{base_wall / fig['s_per_sample']:.2f}×", f"{fig['peak_mb']:.0f}",
        ])
    report = table(["implementation", "ms per sample (CPU time)", "speed-up vs NumPy (CPU time)",
                    "ms per sample (wall)", "speed-up vs NumPy (wall)", "peak memory (MB)"], rows)
    stages = figures[("torch", "cpu", 1)].get("stages", {})
    if stages:
        report += "\n\n" + table(["torch stage (cpu, 1 thread, on its own)", "ms per sample (CPU time)"],
                                  [[name, f"{seconds * 1e3:.2f}"] for name, seconds in stages.items()])
    note = (f"Batch of {args.batch} samples × {LEDS} LEDs × {args.size}×{args.size}, float32: flat-field, "
            f"least-squares normals, mirrored Frankot–Chellappa (torch: N-point cosine transforms; NumPy: the "
            f"doubled-grid FFT). Best of {args.repeat}, CPU time of the process (one thread) and wall time. Peak "
            f"memory: process peak RSS on CPU (includes the inputs and the interpreter), `max_memory_allocated` on "
            f"CUDA. Depth agreement torch vs NumPy: float64, 2×128²: max |Δz| = {difference:.2e} mm "
            f"({relative:.1e} of max |z|); float32, 1×{args.size}²: max |Δz| = {difference32:.2e} mm "
            f"({relative32:.1e} of max |z|: float32 rounding of the whole pipeline). FC alone on one sample's "
            f"slopes, N-point cosine transforms (new) vs the doubled-grid FFT they replaced (old), max |Δz| / max "
            f"|z|: new vs old in float64 {fc['new_old64']:.1e}; in float32 new vs old {fc['new_old32']:.1e}, new "
            f"vs exact (old, float64) {fc['new32']:.1e}, old vs exact {fc['old32']:.1e}.")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Pipeline speed (benchmarks/pipeline_speed.py)", report + "\n\n" + note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
