"""``psmini batch ROOT --out OUT``: reconstruct every sample folder under ROOT, in batches, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from psmini.commands._common import add_config_flags, add_json_flag, config_from_args, emit_json


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "batch",
        help="reconstruct every capture and DiLiGenT folder under ROOT (batched, resumable)",
        description="Find every psmini capture folder and DiLiGenT folder under ROOT, decode them in worker "
        "processes, solve samples of equal size and calibration together, and write each one atomically into "
        "OUT/<path relative to ROOT>, with OUT/summary.csv and OUT/summary.json. A second run skips the samples "
        "already finished; a sample that fails is reported in the summary and the others go on. With --scheduler "
        "the chunks run as tasks of a Dask cluster (pip install 'psmini[dask]'), on each worker's --device.",
    )
    parser.add_argument("root", type=Path, metavar="ROOT", help="folder holding the sample folders (any depth)")
    parser.add_argument("--out", type=Path, required=True, metavar="OUT", help="output folder (created)")
    parser.add_argument("--batch-size", type=int, default=8, metavar="N",
                        help="samples decoded together; those of equal size and card are solved together (default 8)")
    parser.add_argument("--workers", type=int, default=2, metavar="W",
                        help="local worker processes: on CPU each decodes, solves and writes whole batches, on CUDA "
                        "they decode; 0 does everything in this process (default 2; not used with --scheduler)")
    parser.add_argument("--outputs", default=",".join(_kinds()), metavar="LIST",
                        help="comma-separated outputs to write, of normals,albedo,depth,ply (default: all)")
    parser.add_argument("--no-score", action="store_true",
                        help="skip the errors against ground truth (they cost about as much as the reconstruction)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="run on a Dask cluster: a scheduler address (tcp://HOST:8786, from `dask scheduler`), "
                        "or local[:N] for N single-threaded worker processes on this machine; ROOT and OUT must be "
                        "the same paths on every worker")
    parser.add_argument("--scheduler-timeout", type=float, default=10.0, metavar="S",
                        help="seconds to wait for the scheduler and its first worker (default 10)")
    parser.add_argument("--describe", action="store_true",
                        help="add the fabric structure columns of `psmini describe` (threads per cm, yarn angles, "
                        "weave repeat, crimp, openness, ISO 25178-2 parameters) to summary.csv and summary.json; "
                        "needs the depth output")
    add_config_flags(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def _kinds() -> tuple[str, ...]:
    from psmini.batch import OUTPUT_KINDS

    return OUTPUT_KINDS


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from psmini.batch import parse_outputs, reconstruct_dataset

    outputs = parse_outputs(args.outputs)  # before any work: a typo fails at once
    if args.describe and "depth" not in outputs:
        from psmini.errors import InputError

        raise InputError(f"--describe measures the written depth: --outputs must include depth, got {args.outputs!r}")
    if args.scheduler:  # with a cluster the workers' devices count, not this machine's
        args = argparse.Namespace(**{**vars(args), "device": "cpu"}) if args.device == "cuda" else args
    config = config_from_args(args)
    bar = tqdm(unit="sample", disable=args.no_progress, dynamic_ncols=True)

    def progress(record) -> None:
        bar.update(1)
        bar.set_postfix_str(f"{record.status} {record.sample}", refresh=False)

    try:
        summary = reconstruct_dataset(args.root, args.out, config, batch_size=args.batch_size, workers=args.workers,
                                      outputs=outputs, score=not args.no_score, progress=progress,
                                      scheduler=args.scheduler, scheduler_timeout_s=args.scheduler_timeout)
    finally:
        bar.close()
    if args.describe:
        from psmini.commands.describe import add_structure_columns

        summary = add_structure_columns(args.out, summary, config)
    counts = summary["counts"]
    for row in summary["samples"]:
        if row["status"] == "failed":
            print(f"  failed {row['sample']}: {row['error']}")
    print(f"{counts['done']} reconstructed, {counts['skipped']} already done, {counts['failed']} failed; "
          f"summary in {args.out / 'summary.csv'} and {args.out / 'summary.json'}")
    if args.json:
        emit_json({"out": str(args.out), "counts": counts, "summary_csv": str(args.out / "summary.csv"),
                   "summary_json": str(args.out / "summary.json"), "config": config.to_dict(),
                   "solvers": sorted({row["solver"] for row in summary["samples"] if row.get("solver")})})
    return 1 if counts["failed"] else 0
