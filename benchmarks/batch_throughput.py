"""Throughput of ``psmini batch`` on a folder of synthetic rig captures, against a plain NumPy/OpenCV loop.

The data: ``--distinct`` synthetic fabrics rendered at 8 LEDs × ``--size``² under one card
(:func:`data_synth.rig.write_synthetic_capture`), each hard-linked into ``--count / --distinct`` capture folders
(every folder is decoded from its own files; the page cache holds them, as it would after the first pass).

Measured in the same run, each end-to-end run in its own child process (its peak memory is its own):

- psmini end to end: :func:`psmini.batch.reconstruct_dataset` (decode in ``--workers`` processes, batches of
  ``--batch-size``, the card decoded once, depth written atomically, no ground-truth scoring);
- NumPy end to end: for each folder, read the manifest, decode the PNGs with OpenCV (the card once), the
  same maths in NumPy (dark subtraction, card division, pseudo-inverse normals, gradients, mirrored
  Frankot–Chellappa of ``benchmarks/pipeline_speed.py``), the same depth files written;
- the computation alone for both, on decoded samples in memory (torch: one batch of ``--batch-size``).

    python benchmarks/batch_throughput.py [--count 200] [--batch-size 16] [--workers 2] [--no-record]
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
from psmini.io import load_sample, save_depth  # noqa: E402
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
    """psmini's distant pipeline in plain NumPy for one sample: flat-field, least squares, Frankot–Chellappa."""
    matrix = directions / directions[:, 2:3]
    pinv = np.linalg.pinv(matrix)
    reference = card - card_dark
    trusted = (reference > min_reference * reference.max(axis=(1, 2), keepdims=True)) & (card < 1.0) & (images < 1.0)
    signal = np.clip(images - dark, 0, None)
    flat = np.where(trusted, card_albedo * signal / np.where(trusted, reference, 1), 0)
    m = np.tensordot(pinv, flat, axes=(1, 0))
    normals = m / np.maximum(np.linalg.norm(m, axis=0), 1e-30)
    nz = np.maximum(normals[2], min_nz)
    return numpy_frankot_chellappa(-normals[0] / nz, -normals[1] / nz, pitch)


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
        depth = numpy_solve(sample["images"], sample["dark"], card, card_dark, directions, card_albedo,
                            sample["manifest"]["pixel_pitch_mm"])
        end = time.perf_counter()
        target = out / folder.name
        target.mkdir(parents=True)
        save_depth(target / "depth.npy", depth)
        decode, compute, write = decode + middle - start, compute + end - middle, write + time.perf_counter() - end
    return {"decode_s": decode, "compute_s": compute, "write_s": write}


# ------------------------------------------------------------------------------------------- children


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
        start = time.perf_counter()
        parts = numpy_loop(folders, out, directions)
        figures = {"seconds": time.perf_counter() - start, **parts}
        sample = numpy_decode(folders[0])
        card = numpy_decode(sample["card"])
        figures["compute_only_s"] = best_time(lambda: numpy_solve(
            sample["images"], sample["dark"], card["images"], card["dark"], directions, 0.8, 0.025), repeat=3)
    elif args.child == "psmini":
        start = time.perf_counter()
        summary = reconstruct_dataset(root / "lot", out, device=device, batch_size=args.batch_size,
                                      workers=args.workers, outputs="depth", score=False)
        figures["seconds"] = time.perf_counter() - start
        rows = summary["samples"]
        assert summary["counts"]["done"] == len(folders), summary["counts"]
        for part in ("decode_s", "compute_s", "write_s"):
            figures[part] = sum(row[part] for row in rows)
    else:  # computation alone, one batch in memory
        samples = [load_sample(f) for f in folders[: args.batch_size]]
        images = torch.stack([s.images for s in samples]).to(device)
        dark = torch.stack([s.dark for s in samples]).to(device)
        reference, reference_dark = samples[0].reference[None].to(device), samples[0].reference_dark[None].to(device)
        model = PhotometricStereo(samples[0].lights.to(device), pixel_pitch_mm=0.025, saturation_level=1.0,
                                  solver="distant")
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        with torch.no_grad():
            seconds = best_time(lambda: model(images, reference, dark, reference_dark, None, 0.8), repeat=5,
                                device=str(device))
        figures["compute_only_s"] = seconds / len(samples)
        if device.type == "cuda":
            figures["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    shutil.rmtree(out, ignore_errors=True)
    figures["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    figures["workers_peak_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return figures


def run_child(root: Path, kind: str, device: str, args: argparse.Namespace, threads: int = 0,
              batch_size: int | None = None) -> dict:
    command = [sys.executable, __file__, "--child", kind, "--root", str(root), "--device", device,
               "--batch-size", str(batch_size or args.batch_size), "--workers", str(args.workers),
               "--threads", str(threads)]
    output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def check_agreement(root: Path) -> float:
    """Largest depth difference (mm) between psmini and the NumPy loop on the first sample, float64."""
    folder = sorted((root / "lot").glob("s*"))[0]
    sample = load_sample(folder)
    lights = sample.lights.double()
    model = PhotometricStereo(lights, pixel_pitch_mm=sample.pixel_pitch_mm, saturation_level=1.0, solver="distant")
    result = model(sample.images[None].double(), sample.reference[None].double(), sample.dark[None].double(),
                   sample.reference_dark[None].double(), None, sample.card_albedo)
    directions = lights(torch.zeros(1, 3, 1, 1, dtype=torch.float64))[0][0, :, :, 0, 0].numpy()
    assert np.allclose(distant_light_matrix(lights, True, torch.zeros(1, dtype=torch.float64)).numpy(),
                       directions / directions[:, 2:3])
    decoded, card = numpy_decode(folder), numpy_decode(folder.parent / "card")
    expected = numpy_solve(decoded["images"].astype(np.float64), decoded["dark"], card["images"], card["dark"],
                           directions, sample.card_albedo, sample.pixel_pitch_mm)
    solved = result.mask[0, 0].numpy()
    difference = result.depth[0, 0].numpy() - expected
    difference -= difference[solved].mean()
    return float(np.abs(difference[solved]).max())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=200, help="capture folders (default 200)")
    parser.add_argument("--distinct", type=int, default=4, help="distinct renders among them (default 4)")
    parser.add_argument("--size", type=int, default=400)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--gpu-batch-size", type=int, default=64)
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--child", choices=["numpy", "psmini", "compute"], help=argparse.SUPPRESS)
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
        runs = {"numpy": run_child(root, "numpy", "cpu", args), "psmini cpu": run_child(root, "psmini", "cpu", args),
                "compute cpu": run_child(root, "compute", "cpu", args)}
        if torch.cuda.is_available():
            runs["psmini cuda"] = run_child(root, "psmini", "cuda", args)
            runs["compute cuda"] = run_child(root, "compute", "cuda", args, batch_size=args.gpu_batch_size)
    numpy_run, n = runs["numpy"], args.count
    baseline_e2e, baseline_compute = n / numpy_run["seconds"], 1 / numpy_run["compute_only_s"]
    rows = [["NumPy/OpenCV loop (cpu)", f"{baseline_e2e:.2f}", "1.00×", f"{baseline_compute:.2f}", "1.00×",
             f"{numpy_run['decode_s'] / n * 1e3:.1f} / {numpy_run['compute_s'] / n * 1e3:.1f} / "
             f"{numpy_run['write_s'] / n * 1e3:.1f}", f"{numpy_run['peak_mb']:.0f}"]]
    for device in ("cpu", "cuda"):
        if f"psmini {device}" not in runs:
            continue
        e2e, compute = runs[f"psmini {device}"], runs[f"compute {device}"]
        memory = f"{e2e['peak_mb']:.0f} + workers {e2e['workers_peak_mb']:.0f}"
        if "cuda_peak_mb" in compute:
            memory += f" (GPU {compute['cuda_peak_mb']:.0f} at batch {args.gpu_batch_size})"
        rows.append([f"psmini batch ({device})", f"{n / e2e['seconds']:.2f}",
                     f"{n / e2e['seconds'] / baseline_e2e:.2f}×", f"{1 / compute['compute_only_s']:.2f}",
                     f"{1 / compute['compute_only_s'] / baseline_compute:.2f}×",
                     f"{e2e['decode_s'] / n * 1e3:.1f} / {e2e['compute_s'] / n * 1e3:.1f} / "
                     f"{e2e['write_s'] / n * 1e3:.1f}", memory])
    report = table(["implementation", "samples/s end to end", "vs NumPy", "samples/s compute alone", "vs NumPy",
                    "ms/sample decode / compute / write", "peak RSS (MB)"], rows)
    note = (f"{n} capture folders of 8 LEDs × {args.size}×{args.size} (10-bit PNGs, {args.distinct} distinct "
            f"renders hard-linked, one card), distant lights, depth written (npy + png + json), no ground-truth "
            f"scoring. psmini: batch size {args.batch_size}, {args.workers} decoding workers, torch "
            f"{torch.get_num_threads()} threads; NumPy single process. Compute alone: psmini on one in-memory batch "
            f"of {args.batch_size} on CPU" + (f" and {args.gpu_batch_size} on CUDA" if "compute cuda" in runs else "")
            + "; NumPy on one sample. Decode / compute / write: per-sample sums over the run (psmini decodes in "
            f"workers, in parallel with the compute). Depth agreement psmini vs NumPy (float64, one sample, after "
            f"removing the mean): max |Δz| = {difference:.2e} mm.")
    print(report)
    print(note)
    if not args.no_record:
        device = "cuda" if torch.cuda.is_available() else "cpu"
        append_results("Batch throughput (benchmarks/batch_throughput.py)", report + "\n\n" + note, device)
    print(machine("cuda" if torch.cuda.is_available() else "cpu"), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
