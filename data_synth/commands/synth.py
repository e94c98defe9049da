"""``psmini synth FABRIC --out DIR``: a synthetic capture of a fabric and its card, with ground truth."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from psmini.commands._common import add_json_flag, emit_json


def _fabric_names() -> list[str]:
    from data_synth import FABRICS

    return list(FABRICS)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "synth",
        help="synthesise a fabric capture and its flat-field card",
        description="Render a procedural fabric as the rig sees it (8 LEDs on a 31.6 mm ring 10 mm above the card, "
        "orthographic macro camera, vignetting, noise, quantisation) and write DIR/FABRIC (the sample, with gt/) "
        "and DIR/card (the matte card under each LED, for flat-fielding; a card already in DIR from an earlier "
        "synth of the same rig is kept, so several fabrics share one folder as one rig session's captures do).",
    )
    parser.add_argument("fabric", choices=_fabric_names(), metavar="FABRIC",
                        help=f"one of {', '.join(_fabric_names())}")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="parent folder of the two captures")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fabric and the noise (default: 0)")
    parser.add_argument("--size", type=int, default=400, help="side of the square crop, pixels (default: 400)")
    parser.add_argument("--noise", action=argparse.BooleanOptionalAction, default=True,
                        help="add shot and read noise (default: on; quantisation always applies)")
    parser.add_argument("--light-model", choices=["rig", "directional"], default="rig",
                        help="rig: near LEDs (default); directional: ideal distant lights along the LED directions")
    parser.add_argument("--lift", type=float, default=0.0, metavar="MM",
                        help="the cloth's height above the card, mm (default: 0, lying on it; near light's case)")
    parser.add_argument("--orientation", type=float, default=None, metavar="DEG",
                        help="direction of the yarns, degrees counter-clockwise from x (default: the fabric's own)")
    parser.add_argument("--bit-depth", type=int, choices=[8, 10, 12, 16], default=10,
                        help="the camera's quantisation, bits (default: 10; the benchmarks' noisy captures use 8)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing captures")
    add_json_flag(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from data_synth.rig import RigConfig, write_synthetic_capture

    start = time.perf_counter()
    card_kept = (args.out / "card").exists() and not args.overwrite  # (write_synthetic_capture checks its rig)
    fabric_params = {} if args.orientation is None else {"orientation_deg": args.orientation}
    sample_dir, card_dir = write_synthetic_capture(
        args.out, args.fabric, seed=args.seed, size=args.size, noise=args.noise, light_model=args.light_model,
        config=RigConfig(bit_depth=args.bit_depth), height_offset_mm=args.lift, overwrite=args.overwrite,
        **fabric_params,
    )
    elapsed = time.perf_counter() - start
    print(f"synthesised {args.fabric} ({args.size}x{args.size}, {args.light_model} lights, "
          f"noise {'on' if args.noise else 'off'}, {args.bit_depth}-bit, {args.lift:g} mm above the card, "
          f"seed {args.seed}) in {elapsed:.1f} s")
    print(f"  wrote {sample_dir} (sample with gt/)")
    print(f"  kept {card_dir} (the flat-field card already there, of the same rig)" if card_kept
          else f"  wrote {card_dir} (flat-field card)")
    if args.json:
        emit_json({"fabric": args.fabric, "sample": str(sample_dir), "card": str(card_dir), "time_s": elapsed})
    return 0
