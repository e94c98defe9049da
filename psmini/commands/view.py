"""``psmini view OUT [--html FILE]``: a reconstruction's surface as an interactive 3D page (WebGL, offline)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from psmini.commands._common import add_json_flag, emit_json


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "view",
        help="look at a reconstruction in 3D (an interactive page for the browser)",
        description="Draw the surface of a reconstruction folder (what psmini reconstruct, demo or batch wrote: "
        "depth.npy, albedo.png, outputs.json) as an interactive WebGL mesh coloured by its albedo, in true "
        "proportions unless --exaggeration says otherwise, and write it as one self-contained HTML file that works "
        "offline. Needs plotly (pip install 'psmini[viz]').",
    )
    parser.add_argument("out", type=Path, metavar="OUT", help="a reconstruction folder")
    parser.add_argument("--html", type=Path, metavar="FILE",
                        help="write the page here (default: OUT/view.html, then open it in the browser)")
    parser.add_argument("--exaggeration", type=float, default=1.0, help="vertical exaggeration (default: 1, true)")
    parser.add_argument("--max-size", type=int, default=300,
                        help="most vertices along the longer side; larger grids are subsampled (default: 300)")
    parser.add_argument("--no-open", action="store_true", help="do not open the page in the browser")
    add_json_flag(parser)
    parser.set_defaults(run=run)


def _read(out: Path):
    """Depth, albedo (or None), pitch and depth units of a reconstruction folder."""
    from psmini.errors import DataFormatError, InputError
    from psmini.io._npy import read_npy
    from psmini.io.images import read_image

    if not out.is_dir():
        raise InputError(f"{out} does not exist or is not a folder (expected a reconstruction folder)")
    depth_file = out / "depth.npy"
    if not depth_file.is_file():
        raise DataFormatError(f"{out} holds no depth.npy: not a reconstruction folder (psmini reconstruct --out)")
    depth = read_npy(depth_file, "depth")  # empty or cut short: a DataFormatError naming it
    if depth.ndim != 2:
        raise DataFormatError(f"{depth_file} must hold an (H, W) array, got shape {depth.shape}")
    pitch = None
    summary_file = out / "outputs.json"
    if summary_file.is_file():
        try:
            summary = json.loads(summary_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as error:
            raise DataFormatError(f"cannot read {summary_file}: {error}") from error
        if not isinstance(summary, dict):
            raise DataFormatError(f"{summary_file} must hold a JSON object, got {type(summary).__name__}")
        pitch = summary.get("pixel_pitch_mm")
    albedo = read_image(out / "albedo.png")[0] if (out / "albedo.png").is_file() else None
    if albedo is not None and albedo.ndim == 3:
        albedo = albedo.mean(axis=2)
    if albedo is not None and albedo.shape != depth.shape:
        raise DataFormatError(f"{out / 'albedo.png'} is {albedo.shape} (HxW) but depth.npy is {depth.shape}")
    return depth, albedo, pitch


def _open(page: Path) -> None:
    """Open ``page`` in the desktop's browser; on a machine without a display (a server, CI) only say where it is,
    as Python's webbrowser would otherwise start a text browser in the terminal."""
    import os
    import sys
    import webbrowser

    if sys.platform in ("darwin", "win32") or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        webbrowser.open(page.resolve().as_uri())
    else:
        print("no display here: copy the page to a machine with a browser, or use --html FILE")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from psmini.viz import surface_figure, write_html

    depth, albedo, pitch = _read(args.out)
    figure = surface_figure(depth, albedo, np.isfinite(depth), pitch, max_size=args.max_size,
                            exaggeration=args.exaggeration, title=f"{args.out.resolve().name}: surface, "
                            f"{'mm' if pitch is not None else 'pixels'}"
                            f"{'' if args.exaggeration == 1 else f', height x{args.exaggeration:g}'}")
    target = args.html if args.html is not None else args.out / "view.html"
    write_html(figure, target)
    print(f"wrote {target} ({target.stat().st_size / 1e6:.1f} MB, opens offline)")
    if args.html is None and not args.no_open:
        _open(target)
    if args.json:
        emit_json({"out": str(args.out), "html": str(target), "pixel_pitch_mm": pitch})
    return 0
