"""``psmini demo``: synthesise a fabric, reconstruct it, write the results and score them against ground truth."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path

from psmini.commands._common import add_config_flags, add_json_flag, config_from_args, emit_json


def register(subparsers: argparse._SubParsersAction) -> None:
    from data_synth import FABRICS

    parser = subparsers.add_parser(
        "demo",
        help="synthesise a fabric capture, reconstruct it and score it (no hardware, no data needed)",
        description="Synthesise one fabric capture and its card with the simulated rig, reconstruct it with "
        "near-light photometric stereo (the rig's LED model, flat-fielded by the card), write albedo, normal map, "
        "depth and a PLY point cloud into OUT, and print the mean angular error against the ground truth next to "
        "the classical distant-light pipeline's (flat-fielding, least squares, Frankot-Chellappa).",
    )
    parser.add_argument("--out", type=Path, default=Path("psmini-demo"), metavar="OUT",
                        help="output folder (default: ./psmini-demo; an earlier demo there is replaced)")
    parser.add_argument("--fabric", choices=list(FABRICS), default="jute", help="fabric to synthesise (default: jute)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fabric and the noise (default: 0)")
    parser.add_argument("--size", type=int, default=400, help="side of the square crop, pixels (default: 400)")
    add_config_flags(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def _is_previous_demo(out: Path) -> bool:
    """Whether ``out`` exists and was written by an earlier ``psmini demo`` (refuse to replace anything else)."""
    from psmini.errors import InputError

    if not out.exists():
        return False
    try:
        summary = json.loads((out / "outputs.json").read_text(encoding="utf-8"))
        is_demo = bool(summary.get("metadata", {}).get("demo"))
    except (OSError, ValueError, AttributeError):
        is_demo = False
    if not is_demo:
        raise InputError(f"{out} exists and is not an earlier psmini demo folder; choose another --out")
    return True


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from data_synth.rig import write_synthetic_capture
    from psmini.evaluation import score_reconstruction
    from psmini.io import load_sample, write_outputs
    from psmini.nearlight import NearLightOptions
    from psmini.pipeline import reconstruct

    config = config_from_args(args)
    classical = dataclasses.replace(config, solver="distant", estimator="auto", near=NearLightOptions(),
                                    integrator="auto")
    out: Path = args.out
    replace = _is_previous_demo(out)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="psmini-demo-") as scratch, \
            tqdm(total=4, desc="psmini demo", unit="step", leave=False) as progress:
        progress.set_postfix_str(f"synthesising {args.fabric}")
        sample_dir, _ = write_synthetic_capture(Path(scratch) / "capture", args.fabric, seed=args.seed, size=args.size)
        progress.update()
        progress.set_postfix_str("loading")
        sample = load_sample(sample_dir)
        progress.update()
        progress.set_postfix_str("reconstructing")
        resolved = config.resolved(sample.lights, sample.mask is not None)
        result = reconstruct(sample, config)
        scores = score_reconstruction(result, sample)  # the one scoring rule, as `psmini evaluate` has it
        baseline = score_reconstruction(reconstruct(sample, classical), sample)
        error = scores["mean_angular_error_deg"]
        errors = {resolved.solver: error, "distant (classical)": baseline["mean_angular_error_deg"]}
        progress.update()
        progress.set_postfix_str("writing")
        metadata = {"demo": True, "fabric": args.fabric, "seed": args.seed, "size": args.size,
                    "config": resolved.to_dict(), "scores": scores,
                    "classical_mean_angular_error_deg": baseline["mean_angular_error_deg"]}
        written = write_outputs(out, result, pixel_pitch_mm=sample.pixel_pitch_mm, metadata=metadata,
                                overwrite=replace)
        # keep the synthetic capture beside the results, so that `psmini reconstruct` can be tried on it
        shutil.move(str(Path(scratch) / "capture"), str(out / "capture"))
        progress.update()
    elapsed = time.perf_counter() - start
    print(f"synthesised {args.fabric} ({args.size}x{args.size}) with the simulated rig into {out / 'capture'}")
    print(f"  {out / 'capture' / args.fabric}  (8 LED images, dark frame, gt/)")
    print(f"  {out / 'capture' / 'card'}  (flat-field card)")
    method = {"near": "near-light photometric stereo with the rig's LEDs",
              "distant": "distant lights: flat-field, least squares"}[resolved.solver]
    print(f"reconstructed ({method}, {resolved.integrator} integration) and wrote:")
    for path in written:
        print(f"  {path}")
    print(f"mean angular error against ground truth over the cloth ({scores['pixels']} pixels, "
          f"{scores['unsolved_pixels']} unsolved): {resolved.solver} light {error:.2f} deg; the classical "
          f"distant-light pipeline {baseline['mean_angular_error_deg']:.2f} deg; total {elapsed:.1f} s")
    if args.json:
        emit_json({"fabric": args.fabric, "out": str(out), "files": [str(p) for p in written],
                   "capture": str(out / "capture" / args.fabric), "mean_angular_error_deg": error,
                   "solver": resolved.solver, "config": resolved.to_dict(), "errors_deg": errors,
                   "scores": scores, "time_s": elapsed})
    return 0
