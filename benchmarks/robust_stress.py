"""Every normal estimator on every case, one set of defaults: DiLiGenT ball and cat, the stress set, two fabrics.

Cases: DiLiGenT ball and cat (all 96 images, the protocol of benchmarks/diligent.py); the five scenes of
data_synth.stress (concave and self-occluding surfaces with cast shadows, two bounces of inter-reflection, albedo
edges, three Blinn-Phong lobes and 16-bit noise, every parameter drawn from the seed; "crevices" has pixels where
most readings are cast shadows) under DiLiGenT's 96 light directions, each scene at several seeds (--seeds, default
0 and 1: the estimators were designed on these; --seeds 2,3 holds out two more draws); and data_synth fabrics
(lurex, satin) rendered
by the simulated rig (8 LEDs at ~58°, cast shadows, noise, 10 bits) with the LEDs as distant lights. Every
estimator runs with its defaults (psmini.robust.RobustOptions, psmini.nonlambertian.NonLambertianOptions): nothing
is chosen per case.

For each estimator: the mean angular error on each case; its worst case, the largest ratio of its error to the best
error of the robust Lambertian estimators (psmini.robust.ROBUST_METHODS) on that case; and its mean rank among
those estimators. psmini.robust.RECOMMENDED_ROBUST_METHOD ("robust") should be the one of least worst case. Speed
and the per-pixel loop baseline are in benchmarks/robust_diligent.py.

    python benchmarks/robust_stress.py [ROOT] [--size 128] [--seeds 0,1] [--fabric-size 200] [--threads 1] [--no-record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import SHARED_DATA, append_results, table  # noqa: E402
from data_synth.stress import STRESS_SCENES, diligent_directions, make_stress_case  # noqa: E402
from psmini.metrics import mean_angular_error  # noqa: E402
from psmini.nonlambertian import NonLambertianOptions, nonlambertian_normals  # noqa: E402
from psmini.normals import albedo_normals  # noqa: E402
from psmini.robust import RECOMMENDED_ROBUST_METHOD, ROBUST_METHODS, RobustOptions, robust_normals  # noqa: E402

METHODS = ("lstsq",) + ROBUST_METHODS + ("nonlambertian",)
MAJORITY: dict[str, float] = {}  # per stress case, the share of pixels most of whose readings are shadowed


def estimate(method: str, images: torch.Tensor, lights: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Normals (1, 3, H, W) of ``method`` with its defaults."""
    if method == "lstsq":
        return albedo_normals(images, lights, mask)[1]
    if method == "nonlambertian":
        return nonlambertian_normals(images, lights, mask)[1]
    return robust_normals(images, lights, method, mask)[1]


def cases(root: Path, size: int, fabric_size: int, fabrics: list[str], seeds: tuple[int, ...] = (0, 1)):
    """(name, images (1, K, H, W), lights (K, 3), mask (1, 1, H, W), true normals (1, 3, H, W)) of every case."""
    from benchmarks.diligent import object_folders
    from psmini.io import load_sample
    from psmini.pipeline import distant_light_matrix

    for folder in object_folders(root):
        if folder.name not in ("ball", "cat"):
            continue
        sample = load_sample(folder)
        assert sample.mask is not None and sample.normals_gt is not None, f"{folder} lacks a mask or normals"
        images = sample.images.unsqueeze(0)
        yield (folder.name, images, distant_light_matrix(sample.lights, False, images), sample.mask.unsqueeze(0).bool(),
               torch.nan_to_num(sample.normals_gt.unsqueeze(0)))
    directions = diligent_directions(root)
    for name in STRESS_SCENES:
        for seed in seeds:
            case = make_stress_case(name, directions, size=size, seed=seed)
            MAJORITY[f"{name}/{seed}"] = case.majority_fraction()
            yield f"{name}/{seed}", case.images, case.lights, case.mask, case.normals
    if fabrics:
        from data_synth import make_fabric
        from data_synth.rig import RigConfig, distant_lights, render_capture

        for name in fabrics:
            config = RigConfig(size=fabric_size)
            fabric = make_fabric(name, size=fabric_size)
            lights = distant_lights(config)
            capture = render_capture(fabric, config, lights=lights)
            yield (name, (capture.images - capture.dark).unsqueeze(0), lights.directions * lights.intensities[:, None],
                   fabric.mask, capture.normals.unsqueeze(0))


def summarise(errors: dict[tuple[str, str], float], names: list[str]) -> tuple[dict, dict]:
    """Worst case (largest error / best robust error over the cases) and mean rank among ROBUST_METHODS."""
    worst: dict[str, float] = {}
    ranks: dict[str, list[int]] = {m: [] for m in ROBUST_METHODS}
    for name in names:
        best = min(errors[(name, m)] for m in ROBUST_METHODS)
        for m in METHODS:
            worst[m] = max(worst.get(m, 0.0), errors[(name, m)] / best)
        order = sorted(ROBUST_METHODS, key=lambda m: errors[(name, m)])
        for m in ROBUST_METHODS:
            ranks[m].append(order.index(m) + 1)
    return worst, {m: sum(r) / len(r) for m, r in ranks.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", nargs="?", type=Path, default=SHARED_DATA / "DiLiGenT")
    parser.add_argument("--size", type=int, default=128, help="side of the stress renders, pixels")
    parser.add_argument("--seeds", default="0,1", help="comma-separated seeds of each stress scene")
    parser.add_argument("--fabric-size", type=int, default=200, help="side of the fabric renders, pixels")
    parser.add_argument("--fabrics", default="lurex,satin", help="comma-separated data_synth fabrics (empty: none)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--no-record", action="store_true", help="do not append to benchmarks/results.md")
    args = parser.parse_args(argv)
    if not (args.root / "ball" / "light_directions.txt").is_file():
        print(f"DiLiGenT ball (its light directions) is absent under {args.root}", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    errors, names, pixels, seconds = {}, [], {}, {m: 0.0 for m in METHODS}
    seeds = tuple(int(seed) for seed in args.seeds.split(",") if seed)
    for name, images, lights, mask, truth in cases(args.root, args.size, args.fabric_size,
                                                   [f for f in args.fabrics.split(",") if f], seeds):
        names.append(name)
        pixels[name] = int(mask.sum())
        for method in METHODS:
            begin = time.perf_counter()
            normals = estimate(method, images, lights, mask)
            seconds[method] += time.perf_counter() - begin
            errors[(name, method)] = float(mean_angular_error(normals, truth, mask)[0])
        print(f"{name:8s} " + " ".join(f"{m}={errors[(name, m)]:.2f}" for m in METHODS), flush=True)
    worst, rank = summarise(errors, names)
    chosen = min(ROBUST_METHODS, key=lambda m: (worst[m], rank[m]))
    rows = [[m + (" (= robust)" if m == RECOMMENDED_ROBUST_METHOD else "")] + [errors[(n, m)] for n in names]
            + [f"{worst[m]:.3f}", f"{rank[m]:.2f}" if m in rank else "—", f"{seconds[m]:.1f}"] for m in METHODS]
    report = table(["estimator"] + [f"{n} (°)" for n in names] + ["worst case (× best)", "mean rank", "total s"], rows)
    nl_ok = [n for n in names if errors[(n, "nonlambertian")] <= errors[(n, RECOMMENDED_ROBUST_METHOD)]]
    excepted = f" ({', '.join(n for n in names if n not in nl_ok)} excepted)" if len(nl_ok) < len(names) else ""
    note = (f"Mean angular error (°) over each case's mask. Worst case: the largest ratio, over the cases, of the "
            f"estimator's error to the best error of {', '.join(ROBUST_METHODS)} on that case; mean rank among those. "
            f"Least worst case: {chosen} ({worst[chosen]:.3f}); RECOMMENDED_ROBUST_METHOD = "
            f"{RECOMMENDED_ROBUST_METHOD} ({worst[RECOMMENDED_ROBUST_METHOD]:.3f}). nonlambertian no worse than "
            f"robust on {len(nl_ok)} of {len(names)} cases"
            f"{excepted}. "
            f"Pixels: {pixels}. Stress set: data_synth.stress at {args.size}² px under DiLiGenT's 96 directions, seeds "
            f"{list(seeds)}; share of pixels with most readings shadowed: "
            f"{ {n: round(v, 3) for n, v in MAJORITY.items()} }; fabrics at {args.fabric_size}² px, rig LEDs as "
            f"distant lights. Defaults: "
            f"{RobustOptions().to_dict()}; {NonLambertianOptions().to_dict()}. {torch.get_num_threads()} thread(s).")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Robust estimators on every case (benchmarks/robust_stress.py)", report + "\n\n" + note, "cpu")
    return 0


if __name__ == "__main__":
    sys.exit(main())
