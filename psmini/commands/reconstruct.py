"""``psmini reconstruct DIR --out OUT``: albedo, normals, depth and a point cloud from a DiLiGenT or capture folder."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from psmini.commands._common import add_reconstruction_flags, config_from_args, emit_json, load_sample_for


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "reconstruct",
        help="reconstruct a DiLiGenT or psmini capture folder",
        description="Reconstruct albedo, normals, depth and a PLY point cloud from a DiLiGenT folder or a psmini "
        "capture folder, and write them into OUT (albedo.png, normals.png, depth.npy, depth.png, points.ply; with "
        "near light normal_std.npy/.png, each normal's predicted error).",
    )
    add_reconstruction_flags(parser)
    parser.add_argument("--out", type=Path, required=True, metavar="OUT", help="output folder (created)")
    parser.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from psmini.io import write_outputs
    from psmini.pipeline import reconstruct

    config = config_from_args(args)
    start = time.perf_counter()
    sample = load_sample_for(args)
    resolved = config.resolved(sample.lights, sample.mask is not None)
    result = reconstruct(sample, config)
    elapsed = time.perf_counter() - start
    written = write_outputs(args.out, result, pixel_pitch_mm=sample.pixel_pitch_mm, overwrite=args.overwrite,
                            metadata={"config": resolved.to_dict()})
    print(f"reconstructed {sample.name} ({sample.images.shape[0]} images, {sample.images.shape[-1]}x"
          f"{sample.images.shape[-2]}) with the {resolved.solver}-light solver on {config.device} in {elapsed:.2f} s")
    for path in written:
        print(f"  wrote {path}")
    predicted = _normal_std_median(result)
    if predicted is not None:
        print(f"  normals' predicted RMS error: median {predicted:.3f} deg over the solved pixels (normal_std.npy)")
    if args.json:
        emit_json({"name": sample.name, "out": str(args.out), "files": [str(p) for p in written], "time_s": elapsed,
                   "solver": resolved.solver, "normal_std_median_deg": predicted, "config": resolved.to_dict()})
    return 0


def _normal_std_median(result) -> float | None:
    """The median over the solved pixels of near light's predicted normal error, degrees (None for distant light)."""
    normal_std = getattr(result, "normal_std", None)
    return None if normal_std is None or not bool(result.mask.any()) else float(normal_std[result.mask].median())
