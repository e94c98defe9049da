"""``psmini evaluate DIR``: reconstruct a folder and score it against its ground truth."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from psmini.commands._common import add_device_flag, add_json_flag, emit_json, resolve_device


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="reconstruct a folder and print its errors against ground truth",
        description="Reconstruct a DiLiGenT folder (Normal_gt.mat) or a synthetic capture folder (gt/) and print the "
        "mean and median angular error of the normals over the mask, and the depth error when ground-truth depth "
        "exists.",
    )
    parser.add_argument("folder", type=Path, metavar="DIR")
    parser.add_argument("--integrator", default="fc", help="integration method (default: fc)")
    parser.add_argument("--lights", type=Path, metavar="FILE",
                        help="lights file (docs/lights-file.md, from 'psmini calibrate sphere') to use instead of "
                        "the folder's own lights")
    parser.add_argument("--light-model", choices=["distant", "near"], default="distant",
                        help="distant: classical least squares with the lights seen from the field centre (default); "
                        "near: near-light photometric stereo with the folder's LED or point-light positions")
    add_device_flag(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from psmini.errors import DataFormatError
    from psmini.evaluation import evaluate_sample
    from psmini.io import load_sample

    device = resolve_device(args.device)
    start = time.perf_counter()
    sample = load_sample(args.folder)
    if args.lights is not None:
        from psmini.calibration import with_lights_file

        sample = with_lights_file(sample, args.lights)
    if sample.normals_gt is None:
        raise DataFormatError(f"{args.folder} has no ground-truth normals (Normal_gt.mat or gt/normals.npy) to evaluate against")
    scores = evaluate_sample(sample, device=device, integrator=args.integrator, light_model=args.light_model)
    scores["time_s"] = time.perf_counter() - start
    print(f"{sample.name}: mean angular error {scores['mean_angular_error_deg']:.3f} deg, "
          f"median {scores['median_angular_error_deg']:.3f} deg over {scores['pixels']} pixels")
    if "depth_rmse_mm" in scores:
        print(f"{sample.name}: depth RMSE {scores['depth_rmse_mm']:.4f} mm, MAE {scores['depth_mae_mm']:.4f} mm "
              "(after removing the mean offset)")
    if args.json:
        emit_json(scores)
    return 0
