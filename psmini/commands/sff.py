"""``psmini sff STACK --out depth.npy``: shape from focus — a depth map from a focus stack."""

from __future__ import annotations

import argparse
from pathlib import Path

from psmini.commands._common import add_device_flag, add_json_flag, emit_json, resolve_device


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sff",
        help="shape from focus: a depth map from a focus stack",
        description="Score every pixel of every frame of a focus stack with the local form of a focus measure and "
        "write each pixel's position of best focus (interpolated between frames) as a .npy map. STACK is a folder "
        "of frames (a capture.json of kind 'focus' gives their positions_mm, as written by the rig's focus "
        "sweep; otherwise the images in name order, positions = indices or --positions) or a .npy array (N, H, W). "
        "With --focal-plane F the map holds surface heights F - position (a stage lifting the sample toward the "
        "camera).",
    )
    parser.add_argument("stack", type=Path, metavar="STACK")
    parser.add_argument("--out", type=Path, required=True, help="output depth map, .npy (H, W) float64")
    parser.add_argument("--metric", default="lapm", type=str.lower,
                        help="focus operator code or psmini name (default: lapm, Nayar's modified Laplacian)")
    parser.add_argument("--window", type=int, default=9, help="focus measure window, pixels (default 9)")
    parser.add_argument("--positions", default=None, metavar="START:STEP or z0,z1,...",
                        help="frame positions when STACK does not give them")
    parser.add_argument("--interpolation", default="gaussian", choices=["gaussian", "parabola", "none"])
    parser.add_argument("--median", type=int, default=0, help="median filter of the depth map, odd pixels (0: none)")
    parser.add_argument("--focal-plane", type=float, default=None, help="write heights focal-plane - position")
    parser.add_argument("--reliability", type=Path, default=None, help="also write the reliability map (.npy)")
    add_device_flag(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def _positions(text: str | None, count: int) -> list[float] | None:
    from psmini.errors import InputError

    if text is None:
        return None
    try:
        if ":" in text:
            start, step = (float(v) for v in text.split(":"))
            return [start + k * step for k in range(count)]
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(f"--positions must be START:STEP or a comma-separated list, got {text!r}") from None
    if len(values) != count:
        raise InputError(f"--positions gives {len(values)} positions for {count} frames")
    return values


def _load(stack: Path):
    """Frames (N, H, W) tensor and positions from the stack (None: not given)."""
    import numpy as np
    import torch

    from psmini.commands.focus import _frame_list, _read_frames
    from psmini.errors import DataFormatError

    if stack.suffix == ".npy":
        from psmini.io._npy import read_npy

        array = read_npy(stack, "focus stack")
        if array.ndim != 3:
            raise DataFormatError(f"{stack} must hold an (N, H, W) array, got shape {array.shape}")
        if array.dtype not in (np.uint8, np.uint16):
            array = array.astype(np.float32)
        return torch.from_numpy(np.ascontiguousarray(array)), None
    files, positions = _frame_list(stack)
    return _read_frames(files), positions


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from psmini.io._npy import check_npy_target, save_npy
    from psmini.sff import SFFConfig, depth_from_focus

    for target in (args.out, args.reliability):  # both before any work: not the depth written, then a failure
        if target is not None:
            check_npy_target(target)
    device = resolve_device(args.device)
    frames, positions = _load(args.stack)
    given = _positions(args.positions, frames.shape[0])
    positions = given if given is not None else positions
    unit = "mm" if positions is not None else "(index)"
    if positions is None:
        positions = [float(i) for i in range(frames.shape[0])]
    result = depth_from_focus(frames.to(device), positions, args.metric, args.window,
                              SFFConfig(interpolation=args.interpolation, aggregation=args.median))
    depth = result.depth if args.focal_plane is None else result.surface_height(args.focal_plane)
    out = depth.cpu().numpy()
    reliability = result.reliability.cpu().numpy()
    save_npy(args.out, out)  # atomically: an interrupted run leaves no half-written file
    if args.reliability is not None:
        save_npy(args.reliability, reliability)
    kind = "height" if args.focal_plane is not None else "position of best focus"
    print(f"{args.out}: {kind}, {out.shape[0]}×{out.shape[1]}, {frames.shape[0]} frames, {args.metric} window "
          f"{args.window}; range {out.min():.4g} .. {out.max():.4g} {unit}; reliability median "
          f"{np.median(reliability):.3f}, {100 * (reliability < 0.5).mean():.1f}% of pixels below 0.5")
    if args.json:
        emit_json({"out": str(args.out), "kind": kind, "shape": list(out.shape), "frames": int(frames.shape[0]),
                   "metric": args.metric, "window": args.window, "min": float(out.min()), "max": float(out.max()),
                   "unit": unit, "reliability_median": float(np.median(reliability)),
                   "reliability": str(args.reliability) if args.reliability else None})
    return 0
