"""Per-pixel time of every normal estimator against an earlier revision of psmini, measured in the same run.

Issue 20 asks that no estimator get slower per pixel. Absolute times on a shared machine swing by 2x with the load
(the ledger's DiLiGenT tables show cat tukey from 6 to 44 µs/px), so this script times the working tree and a
reference revision (``--against``, by default ``5c7c1dc``: the last commit the ledger's DiLiGenT table timed before
the estimator work of issue 20 began) side by side. The reference's ``psmini`` package is extracted with
``git archive`` into a temporary folder; each version runs in its own worker process (one torch thread), the two
alternating over ``--rounds`` rounds in swapped order, each worker keeping the best of ``--repeat`` calls per
estimator. Time is the worker's CPU time (``time.process_time``), which another process's load inflates less than
the wall clock. Both versions solve the same DiLiGenT object (images, mask and light matrix prepared once by the
working tree and handed to the workers in a file), so the figures are µs per mask pixel of the same work.

Run:  python benchmarks/estimator_speed.py [--against REV] [--object cat] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._ledger import REPO, SHARED_DATA, append_results, table  # noqa: E402

METHODS = ("lstsq", "trimmed", "threshold", "huber", "cauchy", "tukey", "l1", "rpca", "nonlambertian")
REFERENCE = "5c7c1dc"
MIN_SECONDS, MAX_CALLS = 2.0, 40


def _worker(package_root: str, data: str, methods: list[str], repeat: int) -> None:
    """Time each estimator of the psmini found under ``package_root``; print {method: best CPU seconds} as JSON."""
    sys.path.insert(0, package_root)
    torch.set_num_threads(1)
    import psmini

    if not Path(psmini.__file__).resolve().is_relative_to(Path(package_root).resolve()):
        raise RuntimeError(f"imported psmini from {psmini.__file__}, not from {package_root}")
    from psmini.nonlambertian import nonlambertian_normals
    from psmini.normals import albedo_normals
    from psmini.robust import robust_normals

    sample = torch.load(data)
    images, lights, mask = sample["images"], sample["lights"], sample["mask"]
    calls = {"lstsq": lambda: albedo_normals(images, lights, mask),
             "nonlambertian": lambda: nonlambertian_normals(images, lights, mask)}
    best = {}
    for method in methods:
        call = calls.get(method, lambda method=method: robust_normals(images, lights, method, mask))
        call()  # warm-up: first-call allocations and lazy imports
        times: list[float] = []
        # at least `repeat` calls, and for the cheap estimators as many as fill MIN_SECONDS (at most MAX_CALLS):
        # their best of 3 moved by +-10% between runs on the shared machine
        while len(times) < (repeat if method != "nonlambertian" else 1) or (
                sum(times) < MIN_SECONDS and len(times) < MAX_CALLS):
            start = time.process_time()
            call()
            times.append(time.process_time() - start)
        best[method] = min(times)
    print(json.dumps(best))


def _prepare(folder: Path, path: Path) -> int:
    """Save the object's images, mask and distant-light matrix for the workers; returns its mask pixels."""
    from psmini.io import load_sample
    from psmini.pipeline import distant_light_matrix

    sample = load_sample(folder)
    assert sample.mask is not None, f"{folder} has no mask"
    images = sample.images.unsqueeze(0)
    mask = sample.mask.unsqueeze(0).bool()
    torch.save({"images": images, "mask": mask, "lights": distant_light_matrix(sample.lights, False, images)}, path)
    return int(mask.sum())


def _extract(revision: str, target: Path) -> str:
    """The ``psmini`` package of ``revision`` under ``target``; returns the revision's short hash."""
    short = subprocess.run(["git", "rev-parse", "--short", revision], cwd=REPO, capture_output=True, text=True,
                           check=True).stdout.strip()
    archive = subprocess.run(["git", "archive", revision, "psmini"], cwd=REPO, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
    return short


def _run_worker(root: Path, data: Path, methods: list[str], repeat: int) -> dict[str, float]:
    command = [sys.executable, __file__, "--worker", str(root), "--data", str(data), "--methods", ",".join(methods),
               "--repeat", str(repeat)]
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if result.returncode:
        raise RuntimeError(f"worker for {root} failed:\n{result.stderr}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--against", default=REFERENCE, help="git revision to compare with")
    parser.add_argument("--object", default="cat", help="DiLiGenT object folder name")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of the two versions")
    parser.add_argument("--repeat", type=int, default=3, help="calls per estimator in a worker (best kept)")
    parser.add_argument("--no-record", action="store_true", help="do not append to benchmarks/results.md")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--data", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    methods = args.methods.split(",")
    if args.worker:
        _worker(args.worker, args.data, methods, args.repeat)
        return 0
    folder = SHARED_DATA / "DiLiGenT" / args.object
    if not folder.is_dir():
        print(f"no DiLiGenT object at {folder}", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as name:
        temporary = Path(name)
        pixels = _prepare(folder, temporary / "sample.pt")
        reference = _extract(args.against, temporary)
        roots: dict[str, Path] = {"now": REPO, reference: temporary}
        best = {(version, method): float("inf") for version in roots for method in methods}
        for round_ in range(args.rounds):
            order = list(roots) if round_ % 2 == 0 else list(roots)[::-1]
            for version in order:
                for method, seconds in _run_worker(roots[version], temporary / "sample.pt", methods,
                                                   args.repeat).items():
                    best[version, method] = min(best[version, method], seconds)
                print(f"round {round_ + 1} {version}: done", flush=True)
    rows = [[method, 1e6 * best[reference, method] / pixels, 1e6 * best["now", method] / pixels,
             best["now", method] / best[reference, method]] for method in methods]
    header = ["estimator", f"{reference} (µs/px)", "now (µs/px)", "now / reference"]
    body = table(header, rows)
    print(body)
    note = (f"DiLiGenT {args.object}, {pixels} mask pixels, one torch thread; best CPU time (process_time) over "
            f"{args.rounds} alternating rounds of a worker process per version, each the best of at least "
            f"{args.repeat} calls and of as many as fill {MIN_SECONDS:g} s (at most {MAX_CALLS}; nonlambertian: 1 "
            "call per round). Both versions solve the same images, mask and light matrix with "
            "their default options.")
    if not args.no_record:
        append_results(f"Estimator speed against {reference} (benchmarks/estimator_speed.py)", body + "\n\n" + note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
