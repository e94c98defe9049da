"""Least-squares photometric stereo on every DiLiGenT object folder under a root, next to the published baseline.

The protocol is DiLiGenT's (Shi et al., CVPR 2016 / TPAMI 2019): all images, each RGB channel divided by its light
intensity, clamped at 0, gray with 0.2989/0.5870/0.1140, least squares, mean angular error over the mask.

    python benchmarks/diligent.py [ROOT] [--device cpu|cuda] [--no-record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import SHARED_DATA, append_results, table  # noqa: E402
from psmini.config import ReconstructionConfig  # noqa: E402
from psmini.evaluation import evaluate_sample  # noqa: E402
from psmini.io import load_sample  # noqa: E402

# Least-squares row of the DiLiGenT benchmark (Shi et al., TPAMI 2019, Table 2), mean angular error in degrees.
PUBLISHED_LEAST_SQUARES = {
    "ball": 4.10, "bear": 8.39, "buddha": 14.92, "cat": 8.41, "cow": 25.60,
    "goblet": 18.50, "harvest": 30.62, "pot1": 8.89, "pot2": 14.65, "reading": 19.80,
}


def object_folders(root: Path) -> list[Path]:
    """Every folder under ``root`` (itself included) that holds a DiLiGenT object."""
    return sorted({p.parent for p in root.rglob("filenames.txt") if (p.parent / "light_directions.txt").exists()})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", nargs="?", type=Path, default=SHARED_DATA / "DiLiGenT")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-record", action="store_true", help="do not append to benchmarks/results.md")
    args = parser.parse_args(argv)
    folders = object_folders(args.root)
    if not folders:
        print(f"no DiLiGenT object folder under {args.root}", file=sys.stderr)
        return 1
    rows = []
    for folder in folders:
        start = time.perf_counter()
        sample = load_sample(folder)
        loaded = time.perf_counter()
        scores = evaluate_sample(sample, ReconstructionConfig(device=args.device))
        solved = time.perf_counter()
        published = PUBLISHED_LEAST_SQUARES.get(folder.name)
        rows.append([
            folder.name, sample.images.shape[0], scores["mean_angular_error_deg"], scores["median_angular_error_deg"],
            "—" if published is None else published, loaded - start, solved - loaded,
        ])
    header = ["object", "images", "mean error (°)", "median error (°)", "published LS (°)", "load (s)", "solve (s)"]
    report = table(header, rows)
    print(report)
    if not args.no_record:
        append_results("DiLiGenT least squares (benchmarks/diligent.py)", report, args.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
