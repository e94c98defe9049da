"""Robust normal estimators (psmini.robust) on every DiLiGenT object under a root, next to the published rows.

For each object and method: the mean and median angular error over the mask (DiLiGenT's protocol, see
benchmarks/diligent.py), the best time of the batched torch estimator over the mask pixels, and the speed-up
over a straightforward per-pixel Python loop of the same estimator (NumPy, ``np.linalg.lstsq`` per pixel and
IRLS iteration) measured in the same run. The loop is timed on a random subset of mask pixels (``--loop-pixels``,
2,000 by default) and extrapolated linearly to the whole mask; its normals on that subset are compared with
the torch ones (last column) to show it is the same estimator. Every method runs with its defaults: nothing is
tuned per object.

    python benchmarks/robust_diligent.py [ROOT] [--device cpu|cuda] [--threads N] [--loop-pixels N] [--no-record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import SHARED_DATA, append_results, best_time, table  # noqa: E402
from benchmarks.diligent import object_folders  # noqa: E402
from psmini.io import load_sample  # noqa: E402
from psmini.metrics import mean_angular_error, median_angular_error  # noqa: E402
from psmini.normals import albedo_normals  # noqa: E402
from psmini.pipeline import distant_light_matrix  # noqa: E402
from psmini.robust import RECOMMENDED_ROBUST_METHOD, ROBUST_METHODS, robust_normals  # noqa: E402

# Mean angular error (degrees) on ball / cat, DiLiGenT benchmark (Shi et al., TPAMI 2019, Table 2).
PUBLISHED = {
    "least squares (Woodham 1980)": {"ball": 4.10, "cat": 8.41},
    "RPCA (Wu et al. 2010)": {"ball": 2.06, "cat": 6.73},
    "sparse regression (Ikehata et al. 2012)": {"ball": 2.54, "cat": 7.21},
    "bi-polynomial BRDF (Shi et al. 2014)": {"ball": 1.74, "cat": 6.12},
}
TUNING = {"huber": 1.345, "cauchy": 2.385, "tukey": 4.685}
DEFAULTS = {"low": 0.25, "high": 0.10, "shadow": 0.05, "iterations": 10, "l1_epsilon": 1e-3}


def loop_pixel(values: np.ndarray, lights: np.ndarray, method: str) -> np.ndarray:
    """One pixel's m = albedo * normal by the per-pixel textbook version of ``method`` (``values`` (K,))."""
    k = values.shape[0]
    if method == "lstsq":
        return np.linalg.lstsq(lights, values, rcond=None)[0]
    if method == "trimmed":
        order = np.argsort(values, kind="stable")
        keep = order[int(np.floor(k * DEFAULTS["low"])): k - int(np.floor(k * DEFAULTS["high"]))]
        return np.linalg.lstsq(lights[keep], values[keep], rcond=None)[0]
    keep = values > DEFAULTS["shadow"] * values.max()
    if keep.sum() < 3:
        return np.zeros(3)
    sub_lights, sub_values = lights[keep], values[keep]
    m = np.linalg.lstsq(sub_lights, sub_values, rcond=None)[0]
    if method == "threshold":
        return m
    for _ in range(DEFAULTS["iterations"]):
        size = np.abs(sub_values - sub_lights @ m)
        if method == "l1":
            weights = 1.0 / np.maximum(size, DEFAULTS["l1_epsilon"] * np.abs(values).mean())
        else:
            scale = 1.4826 * np.median(size) + 1e-6 * np.abs(values).max() + 1e-30
            u = size / (TUNING[method] * scale)
            if method == "huber":
                weights = 1.0 / np.maximum(u, 1.0)
            elif method == "cauchy":
                weights = 1.0 / (1.0 + u * u)
            else:
                weights = np.clip(1.0 - u * u, 0.0, None) ** 2
        if np.count_nonzero(weights) < 3:
            break
        root = np.sqrt(weights)
        m = np.linalg.lstsq(sub_lights * root[:, None], sub_values * root, rcond=None)[0]
    return m


def torch_normals(images, lights, mask, method):
    if method == "lstsq":
        return albedo_normals(images, lights, mask)[1]
    return robust_normals(images, lights, method, mask)[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", nargs="?", type=Path, default=SHARED_DATA / "DiLiGenT")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--loop-pixels", type=int, default=2000, help="mask pixels the per-pixel loop is timed on")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs of each torch estimator (best is kept)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: the loop is single-threaded, and on a shared machine "
                        "more threads than free cores stall every parallel op)")
    parser.add_argument("--no-record", action="store_true", help="do not append to benchmarks/results.md")
    args = parser.parse_args(argv)
    folders = object_folders(args.root)
    if not folders:
        print(f"no DiLiGenT object folder under {args.root}", file=sys.stderr)
        return 1
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)
    methods = ("lstsq",) + ROBUST_METHODS
    rows, errors = [], {}
    for folder in folders:
        sample = load_sample(folder)
        images = sample.images.to(device).unsqueeze(0)
        mask = sample.mask.to(device).unsqueeze(0).bool()
        normals_gt = torch.nan_to_num(sample.normals_gt.to(device).unsqueeze(0))
        lights = distant_light_matrix(sample.lights.to(device), False, images)
        pixels = int(mask.sum())
        rng = np.random.default_rng(0)
        subset = rng.choice(pixels, size=min(args.loop_pixels, pixels), replace=False)
        values_np = images[0][:, mask[0, 0]].double().cpu().numpy()[:, subset]  # (K, n)
        lights_np = lights.double().cpu().numpy()
        for method in methods:
            normals = torch_normals(images, lights, mask, method)
            seconds = best_time(lambda: torch_normals(images, lights, mask, method), args.repeat, 1, args.device)
            start = time.perf_counter()
            loop_m = np.stack([loop_pixel(values_np[:, i], lights_np, method) for i in range(len(subset))], 1)
            loop_per_pixel = (time.perf_counter() - start) / len(subset)
            loop_n = loop_m / np.maximum(np.linalg.norm(loop_m, axis=0, keepdims=True), 1e-30)
            ours = normals[0][:, mask[0, 0]].double().cpu().numpy()[:, subset]
            agreement = np.degrees(np.arccos(np.clip((loop_n * ours).sum(0), -1.0, 1.0))).mean()
            mean = float(mean_angular_error(normals, normals_gt, mask)[0])
            errors[(folder.name, method)] = mean
            rows.append([
                folder.name, method, mean, float(median_angular_error(normals, normals_gt, mask)[0]), pixels, seconds,
                seconds / pixels * 1e6, loop_per_pixel * 1e6, loop_per_pixel * pixels / seconds, f"{agreement:.2g}",
            ])
            print(f"{folder.name:8s} {method:9s} {mean:6.3f} deg  {seconds:7.3f} s  "
                  f"loop {loop_per_pixel * 1e6:7.1f} us/px", flush=True)
    header = ["object", "method", "mean (°)", "median (°)", "mask pixels", "torch (s)", "torch (µs/px)",
              "loop (µs/px)", "speed-up", "loop vs torch (°)"]
    report = table(header, rows)
    names = [f.name for f in folders]
    published = table(["method (published)"] + names,
                      [[m] + [by.get(n, "—") for n in names] for m, by in PUBLISHED.items()]
                      + [[f"psmini {m}" + (" (= robust)" if m == RECOMMENDED_ROBUST_METHOD else "")]
                         + [errors[(n, m)] for n in names] for m in methods])
    note = (f"Loop: per-pixel NumPy (np.linalg.lstsq per pixel and IRLS iteration), timed on {args.loop_pixels} "
            "random mask pixels and extrapolated linearly to the whole mask (speed-up = loop time for the mask / "
            f"torch time for the mask). Torch: best of {args.repeat}, device {args.device}, "
            f"{torch.get_num_threads()} threads. Defaults for every method: {DEFAULTS}; no per-object tuning.")
    print(report)
    print()
    print(published)
    print(note)
    if not args.no_record:
        append_results("Robust normals on DiLiGenT (benchmarks/robust_diligent.py)",
                       report + "\n\n" + published + "\n\n" + note, args.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
