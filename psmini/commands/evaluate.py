"""``psmini evaluate DIR``: reconstruct a folder and score it against its ground truth."""

from __future__ import annotations

import argparse
import time

from psmini.commands._common import add_reconstruction_flags, config_from_args, emit_json, load_sample_for


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="reconstruct a folder and print its errors against ground truth",
        description="Reconstruct a DiLiGenT folder (Normal_gt.mat) or a synthetic capture folder (gt/) and print the "
        "mean and median angular error of the normals over the mask, and the depth error when ground-truth depth "
        "exists.",
    )
    add_reconstruction_flags(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from psmini.errors import DataFormatError
    from psmini.evaluation import evaluate_sample

    config = config_from_args(args)
    start = time.perf_counter()
    sample = load_sample_for(args)
    if sample.normals_gt is None:
        raise DataFormatError(f"{args.folder} has no ground-truth normals (Normal_gt.mat or gt/normals.npy) to "
                              "evaluate against")
    scores = evaluate_sample(sample, config)
    scores["solver"] = scores["config"]["solver"]
    scores["time_s"] = time.perf_counter() - start
    print(f"{sample.name} ({scores['solver']}-light solver): mean angular error "
          f"{scores['mean_angular_error_deg']:.3f} deg, median {scores['median_angular_error_deg']:.3f} deg over "
          f"{scores['pixels']} pixels ({scores['unsolved_pixels']} of them unsolved)")
    if "normal_std_median_deg" in scores:
        print(f"{sample.name}: predicted normal error (normal_std) median {scores['normal_std_median_deg']:.3f} deg; "
              f"{100 * scores['within_normal_std_share']:.0f}% of the errors below it (63% when it is right), "
              f"mean (error / predicted)^2 {scores['error_to_normal_std_ratio']:.2f} (1 when right)")
    if "depth_rmse_mm" in scores:
        print(f"{sample.name}: depth RMSE {scores['depth_rmse_mm']:.4f} mm, MAE {scores['depth_mae_mm']:.4f} mm "
              "(after removing the mean offset)")
    if args.json:
        emit_json(scores)
    return 0
