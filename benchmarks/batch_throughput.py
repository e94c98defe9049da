"""Throughput of ``psmini batch`` on a folder of synthetic rig captures, against a plain NumPy/OpenCV loop.

The data: ``--distinct`` synthetic fabrics rendered at 8 LEDs × ``--size``² under one card
(:func:`data_synth.rig.write_synthetic_capture`), each hard-linked into ``--count / --distinct`` capture folders
(every folder is decoded from its own files; the page cache holds them, as it would after the first pass).

Measured in the same run, each end-to-end run in its own child process (its peak memory is its own):

- psmini end to end: :func:`psmini.batch.reconstruct_dataset` on the CPU with ``--workers`` processes (each
  decodes, solves and writes whole chunks of ``--batch-size`` samples) and with none (everything in one process,
  the per-core comparison), and on CUDA when present (batches of ``--gpu-batch-size``); the card decoded once
  per process, depth written atomically, no ground-truth scoring;
- NumPy end to end: for each folder, read the manifest, decode the PNGs with OpenCV (the card once), the
  same maths in NumPy (dark subtraction, card division where trusted and unsaturated, least squares over each
  pixel's usable observations, gradients, mirrored Frankot–Chellappa over the solved pixels), the same depth
  files written (npy, png, json; NaN where unsolved);
- the computation alone for both, on decoded samples in memory (torch: one batch, on one thread and on all);
- near light end to end: ``psmini batch --light-model near`` (:func:`psmini.batch.reconstruct_dataset` with
  ``ReconstructionConfig(solver="near")``) on the first ``--near-count`` captures (near light costs seconds per sample:
  its throughput is recorded beside the distant one, not raced against the NumPy loop).

    python benchmarks/batch_throughput.py [--count 200] [--batch-size 4] [--workers 2] [--repeat 2] [--near-count 8]
        [--no-record]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import append_results, best_time, machine, table  # noqa: E402
from benchmarks.pipeline_speed import numpy_frankot_chellappa  # noqa: E402
from psmini.batch import reconstruct_dataset  # noqa: E402
from psmini.config import ReconstructionConfig  # noqa: E402
from psmini.io import load_sample, save_depth  # noqa: E402
from psmini.io._png import available as png_fast_path  # noqa: E402
from psmini.pipeline import PhotometricStereo, distant_light_matrix  # noqa: E402

FABRICS = ("jute", "twill", "cotton", "silk")


def make_dataset(root: Path, count: int, distinct: int, size: int) -> list[Path]:
    """``count`` capture folders under ``root/lot`` sharing ``root/lot/card``: hard links to ``distinct`` renders."""
    from data_synth.rig import write_synthetic_capture

    lot, renders = root / "lot", root / "renders"
    originals = []
    for index in range(distinct):
        fabric = FABRICS[index % len(FABRICS)]
        sample_dir, card_dir = write_synthetic_capture(renders, fabric, size=size, seed=index, overwrite=True)
        originals.append(sample_dir)
    shutil.copytree(card_dir, lot / "card", copy_function=os.link)
    folders = []
    for index in range(count):
        folder = lot / f"s{index:04d}"
        shutil.copytree(originals[index % distinct], folder, copy_function=os.link)
        folders.append(folder)
    shutil.rmtree(renders / "card")  # renders/ holds samples without a card now: keep the walk on lot/
    return folders


# ------------------------------------------------------------------------------------------- NumPy baseline


def _read(folder: Path, name: str, scale: float) -> np.ndarray:
    image = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise OSError(f"cannot decode {folder / name}")
    return image.astype(np.float32) / scale


def numpy_decode(folder: Path) -> dict:
    """A capture folder's images, dark frame, light directions and card path, decoded with OpenCV."""
    manifest = json.loads((folder / "capture.json").read_text())
    scale = float(2 ** manifest["bit_depth"] - 1)
    images = np.stack([_read(folder, name, scale) for name in manifest["images"]])
    dark = _read(folder, manifest["dark"], scale)
    card = None if manifest["flatfield"] is None else (folder / manifest["flatfield"]["path"]).resolve()
    return {"images": images, "dark": dark, "card": card, "manifest": manifest}


def numpy_solve(images, dark, card, card_dark, directions, card_albedo, pitch, min_reference=0.02, min_nz=1e-2):
    """psmini's distant pipeline in plain NumPy for one sample; returns the depth (H, W) and the solved pixels.

    The same maths as :class:`psmini.pipeline.PhotometricStereo`: dark subtraction and card division where the
    card is trusted and nothing is saturated; least squares per pixel over its usable observations (the
    pseudo-inverse where all are usable, the 3×3 normal equations where some are not, unsolved below three);
    mirrored Frankot–Chellappa with the mean slope over the solved pixels, unsolved pixels at that slope.
    """
    matrix = directions / directions[:, 2:3]
    reference = card - card_dark
    trusted = ((reference > min_reference * reference.max(axis=(1, 2), keepdims=True)) & (reference > 0)
               & (card < 1.0) & (images < 1.0))
    signal = np.clip(images - dark, 0, None)
    flat = np.where(trusted, card_albedo * signal / np.where(trusted, reference, 1), 0)
    m = np.tensordot(np.linalg.pinv(matrix), flat, axes=(1, 0))
    partial = ~trusted.all(axis=0)
    if partial.any():  # pixels that lost an observation (a saturated card, a dark card corner)
        used = trusted[:, partial].astype(matrix.dtype)
        gram = np.einsum("ki,kj,kn->nij", matrix, matrix, used)
        rhs = (matrix.T @ flat[:, partial]).T
        enough = used.sum(axis=0) >= 3
        part = np.zeros((3, used.shape[1]))
        part[:, enough] = np.linalg.solve(gram[enough], rhs[enough][..., None])[..., 0].T
        m[:, partial] = part
    albedo = np.sqrt(np.einsum("chw,chw->hw", m, m))
    solved = albedo > np.finfo(m.dtype).eps
    # slopes of the unit normal m / |m|: -m_x / max(m_z, min_nz |m|); unsolved pixels (normal (0, 0, 1)) get 0
    denominator = np.maximum(m[2], min_nz * albedo)
    denominator[~solved] = np.inf
    p, q = -m[0] / denominator, -m[1] / denominator
    count = solved.sum()
    p0, q0 = p.sum() / count, q.sum() / count  # unsolved pixels hold 0: the sums are over the solved ones
    p[~solved], q[~solved] = p0, q0
    depth = numpy_frankot_chellappa(p, q, pitch)
    return depth - depth.mean(where=solved), solved


def numpy_loop(folders: list[Path], out: Path, directions: np.ndarray) -> dict:
    """Decode, solve and write every folder one after the other; the card is decoded once."""
    cards: dict[Path, tuple] = {}
    decode = compute = write = 0.0
    for folder in folders:
        start = time.perf_counter()
        sample = numpy_decode(folder)
        if sample["card"] not in cards:
            card = numpy_decode(sample["card"])
            cards[sample["card"]] = (card["images"], card["dark"], card["manifest"]["card_albedo"])
        card, card_dark, card_albedo = cards[sample["card"]]
        middle = time.perf_counter()
        depth, solved = numpy_solve(sample["images"], sample["dark"], card, card_dark, directions, card_albedo,
                                    sample["manifest"]["pixel_pitch_mm"])
        end = time.perf_counter()
        target = out / folder.name
        target.mkdir(parents=True)
        save_depth(target / "depth.npy", depth, solved)  # the files psmini writes: npy, png and json, NaN unsolved
        decode, compute, write = decode + middle - start, compute + end - middle, write + time.perf_counter() - end
    return {"decode_s": decode, "compute_s": compute, "write_s": write}


# ------------------------------------------------------------------------------------------- children


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the decoding workers), user + system."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def child(args: argparse.Namespace) -> dict:
    """One measurement in this process; returns its figures and its peak memory."""
    if args.threads:
        torch.set_num_threads(args.threads)
    root = Path(args.root)
    folders = sorted((root / "lot").glob("s*"))
    out = Path(tempfile.mkdtemp(prefix="out-", dir=root))
    device = torch.device(args.device)
    figures: dict = {}
    if args.child == "numpy":
        lights = load_sample(folders[0]).lights.double()
        directions = lights(torch.zeros(1, 3, 1, 1, dtype=torch.float64))[0][0, :, :, 0, 0].numpy()
        start, cpu = time.perf_counter(), _cpu_seconds()
        parts = numpy_loop(folders, out, directions)
        figures = {"seconds": time.perf_counter() - start, "cpu_s": _cpu_seconds() - cpu, **parts}
        sample = numpy_decode(folders[0])
        card = numpy_decode(sample["card"])
        figures["compute_only_s"] = best_time(lambda: numpy_solve(
            sample["images"], sample["dark"], card["images"], card["dark"], directions, 0.8, 0.025), repeat=3)
    elif args.child in ("psmini", "near"):
        lot = root / "lot" if args.child == "psmini" else root / "near" / "lot"
        folders = sorted(lot.glob("s*"))
        start, cpu = time.perf_counter(), _cpu_seconds()
        config = ReconstructionConfig(solver="distant" if args.child == "psmini" else "near", device=str(device))
        summary = reconstruct_dataset(lot, out, config, batch_size=args.batch_size, workers=args.workers,
                                      outputs="depth", score=False)
        figures["seconds"], figures["cpu_s"] = time.perf_counter() - start, _cpu_seconds() - cpu
        figures["count"] = len(folders)
        rows = summary["samples"]
        assert summary["counts"]["done"] == len(folders), summary["counts"]
        for part in ("decode_s", "compute_s", "write_s"):
            figures[part] = sum(row[part] for row in rows)
    else:  # computation alone, one batch in memory
        samples = [load_sample(f) for f in folders[: args.batch_size]]
        images = torch.stack([s.images for s in samples]).to(device)
        dark = torch.stack([s.dark for s in samples]).to(device)
        reference, reference_dark = samples[0].reference[None].to(device), samples[0].reference_dark[None].to(device)
        model = PhotometricStereo(samples[0].lights.to(device), 0.025, ReconstructionConfig(solver="distant"))
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        with torch.no_grad():
            seconds = best_time(lambda: model(images, reference, dark, reference_dark, None, 0.8, 1.0), repeat=5,
                                device=str(device))
        figures["compute_only_s"] = seconds / len(samples)
        if device.type == "cuda":
            figures["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    shutil.rmtree(out, ignore_errors=True)
    figures["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    figures["workers_peak_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return figures


def run_child(root: Path, kind: str, device: str, args: argparse.Namespace, threads: int = 0,
              batch_size: int | None = None, workers: int | None = None) -> dict:
    command = [sys.executable, __file__, "--child", kind, "--root", str(root), "--device", device,
               "--batch-size", str(batch_size or args.batch_size),
               "--workers", str(args.workers if workers is None else workers), "--threads", str(threads)]
    output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def _seconds(run: dict) -> float:
    return run.get("seconds", run.get("compute_only_s"))


def check_agreement(root: Path) -> float:
    """Largest depth difference (mm) between psmini and the NumPy loop on the first sample, float64."""
    folder = sorted((root / "lot").glob("s*"))[0]
    sample = load_sample(folder)
    lights = sample.lights.double()
    model = PhotometricStereo(lights, sample.pixel_pitch_mm, ReconstructionConfig(solver="distant"))
    result = model(sample.images[None].double(), sample.reference[None].double(), sample.dark[None].double(),
                   sample.reference_dark[None].double(), None, sample.card_albedo, 1.0)
    directions = lights(torch.zeros(1, 3, 1, 1, dtype=torch.float64))[0][0, :, :, 0, 0].numpy()
    assert np.allclose(distant_light_matrix(lights, True, torch.zeros(1, dtype=torch.float64)).numpy(),
                       directions / directions[:, 2:3])
    decoded, card = numpy_decode(folder), numpy_decode(folder.parent / "card")
    expected, expected_solved = numpy_solve(decoded["images"].astype(np.float64), decoded["dark"], card["images"],
                                            card["dark"], directions, sample.card_albedo, sample.pixel_pitch_mm)
    solved = result.mask[0, 0].numpy()
    assert (solved == expected_solved).all(), "psmini and NumPy solve different pixels"
    difference = result.depth[0, 0].numpy() - expected
    return float(np.abs(difference[solved]).max())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=200, help="capture folders (default 200)")
    parser.add_argument("--distinct", type=int, default=4, help="distinct renders among them (default 4)")
    parser.add_argument("--size", type=int, default=400)
    parser.add_argument("--batch-size", type=int, default=4, help="CPU batch (default 4: fastest per sample)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--gpu-batch-size", type=int, default=64)
    parser.add_argument("--repeat", type=int, default=2, help="rounds of all measurements; the best of each is kept")
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--near-count", type=int, default=8,
                        help="captures reconstructed with near light (default 8; 0 skips the row)")
    parser.add_argument("--child", choices=["numpy", "psmini", "compute", "near"], help=argparse.SUPPRESS)
    parser.add_argument("--root", help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args)))
        return 0

    with tempfile.TemporaryDirectory(prefix="psmini-batch-bench-") as temporary:
        root = Path(temporary)
        start = time.perf_counter()
        make_dataset(root, args.count, args.distinct, args.size)
        print(f"made {args.count} captures in {time.perf_counter() - start:.1f} s", file=sys.stderr)
        difference = check_agreement(root)
        if args.near_count:  # the first captures again, with the card, for the near-light row
            near = root / "near" / "lot"
            shutil.copytree(root / "lot" / "card", near / "card", copy_function=os.link)
            for folder in sorted((root / "lot").glob("s*"))[: args.near_count]:
                shutil.copytree(folder, near / folder.name, copy_function=os.link)
        load_before = os.getloadavg()[0]
        threads = torch.get_num_threads()
        children = {"numpy": ("numpy", "cpu", {}),
                    f"psmini batch (cpu, {args.workers} workers)": ("psmini", "cpu", {}),
                    "psmini batch (cpu, one process)": ("psmini", "cpu", {"workers": 0, "threads": 1}),
                    "compute cpu": ("compute", "cpu", {}),
                    "compute cpu 1": ("compute", "cpu", {"threads": 1})}
        if torch.cuda.is_available():
            children["psmini batch (cuda)"] = ("psmini", "cuda", {"batch_size": args.gpu_batch_size})
            children["compute cuda"] = ("compute", "cuda", {"batch_size": args.gpu_batch_size})
        # the children take turns, --repeat rounds, and each keeps its fastest round: load from other processes
        # that comes and goes then hits every implementation alike
        runs: dict[str, dict] = {}
        for _ in range(args.repeat):
            for key, (kind, device, options) in children.items():
                run = run_child(root, kind, device, args, **options)
                if key not in runs or _seconds(run) < _seconds(runs[key]):
                    runs[key] = run
        if args.near_count:  # once: it takes seconds per sample
            runs["near"] = run_child(root, "near", "cpu", args)
        load_after = os.getloadavg()[0]
    numpy_run, n = runs["numpy"], args.count
    baseline_e2e, baseline_compute = n / numpy_run["seconds"], 1 / numpy_run["compute_only_s"]

    def parts(run: dict) -> str:
        return f"{run['decode_s'] / n * 1e3:.1f} / {run['compute_s'] / n * 1e3:.1f} / {run['write_s'] / n * 1e3:.1f}"

    rows = [["NumPy/OpenCV loop (cpu, one process)", f"{baseline_e2e:.2f}", "1.00×",
             f"{numpy_run['cpu_s'] / n * 1e3:.0f}", f"{baseline_compute:.2f} (1 thread)", "1.00×", parts(numpy_run),
             f"{numpy_run['peak_mb']:.0f}"]]
    compute_of = {f"psmini batch (cpu, {args.workers} workers)": ("compute cpu", f"{threads} threads"),
                  "psmini batch (cpu, one process)": ("compute cpu 1", "1 thread"),
                  "psmini batch (cuda)": ("compute cuda", f"batch {args.gpu_batch_size}")}
    for label, (compute_key, compute_label) in compute_of.items():
        if label not in runs:
            continue
        e2e, compute = runs[label], runs[compute_key]
        memory = f"{e2e['peak_mb']:.0f} + workers {e2e['workers_peak_mb']:.0f}"
        if "cuda_peak_mb" in compute:
            memory += f" (GPU {compute['cuda_peak_mb']:.0f})"
        rows.append([label, f"{n / e2e['seconds']:.2f}", f"{n / e2e['seconds'] / baseline_e2e:.2f}×",
                     f"{e2e['cpu_s'] / n * 1e3:.0f}", f"{1 / compute['compute_only_s']:.2f} ({compute_label})",
                     f"{1 / compute['compute_only_s'] / baseline_compute:.2f}×", parts(e2e), memory])
    if "near" in runs:
        near, label = runs["near"], f"psmini batch --light-model near (cpu, {args.workers} workers)"
        count = near["count"]
        distant = runs[f"psmini batch (cpu, {args.workers} workers)"]
        rows.append([f"{label}, {count} captures", f"{count / near['seconds']:.3f}",
                     f"{count / near['seconds'] / baseline_e2e:.3f}× "
                     f"({count / near['seconds'] / (n / distant['seconds']):.3f}× distant)",
                     f"{near['cpu_s'] / count * 1e3:.0f}", "—", "—",
                     f"{near['decode_s'] / count * 1e3:.1f} / {near['compute_s'] / count * 1e3:.1f} / "
                     f"{near['write_s'] / count * 1e3:.1f}",
                     f"{near['peak_mb']:.0f} + workers {near['workers_peak_mb']:.0f}"])
    report = table(["implementation", "samples/s end to end", "vs NumPy", "CPU ms/sample end to end",
                    "samples/s compute alone", "vs NumPy",
                    "ms/sample decode / compute / write", "peak RSS (MB)"], rows)
    note = (f"{n} capture folders of 8 LEDs × {args.size}×{args.size} (10-bit PNGs, {args.distinct} distinct "
            f"renders hard-linked, one card), distant lights, depth written by both (npy + png + json, NaN where "
            f"unsolved; psmini adds its outputs.json resume marker and writes each folder atomically), no "
            f"ground-truth scoring. PNGs decoded by OpenCV in the NumPy loop, by psmini.io's reader in psmini "
            f"({'its ISA-L fast path for OpenCV-written PNGs' if png_fast_path() else 'OpenCV: isal not installed'}). "
            f"psmini on CPU: batch size {args.batch_size}, {args.workers} worker processes "
            f"each decoding, solving and writing whole batches with {max(1, threads // max(args.workers, 1))} "
            f"torch thread(s), or everything in one process on 1 thread; NumPy single process. Compute alone: "
            f"psmini on one in-memory batch of {args.batch_size} on CPU"
            + (f" and {args.gpu_batch_size} on CUDA" if "compute cuda" in runs else "")
            + f"; NumPy on one sample. Best of {args.repeat} interleaved rounds. CPU ms/sample: user + system time of "
            "the run and its worker processes over the samples (less sensitive to other processes than the "
            "wall clock; on idle cores the wall-clock ratio tends to cores used × the inverse CPU-time ratio). Decode "
            "/ compute / write: "
            f"per-sample sums over the run (in the workers, they run in parallel). {os.cpu_count()} CPU cores; load "
            f"average {load_before:.1f} before the "
            f"measurements and {load_after:.1f} after (other processes share the cores). Depth agreement psmini vs "
            f"NumPy (float64, one sample): max |Δz| = {difference:.2e} mm over the solved pixels, and the same "
            f"pixels solved.")
    print(report)
    print(note)
    if not args.no_record:
        device = "cuda" if torch.cuda.is_available() else "cpu"
        append_results("Batch throughput (benchmarks/batch_throughput.py)", report + "\n\n" + note, device)
    print(machine("cuda" if torch.cuda.is_available() else "cpu"), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
