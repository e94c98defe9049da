"""``psmini focus DIR``: score every frame of a focus sweep and report the sharpest one."""

from __future__ import annotations

import argparse
from pathlib import Path

from psmini.commands._common import add_device_flag, add_json_flag, emit_json, resolve_device

_IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm"}
_CHUNK = 32  # frames scored per batch: bounds memory on long sweeps of large frames


def register(subparsers: argparse._SubParsersAction) -> None:
    from psmini.focus import FOCUS_NAMES

    parser = subparsers.add_parser(
        "focus",
        help="score the frames of a focus sweep and print the sharpest",
        description="Score each frame of a folder with a focus measure and print the best index, the best position "
        "and every score. Frames are the folder's images in name order (positions = indices), or, when the folder "
        "holds a capture.json of kind 'focus', its images with their positions_mm. The best position is refined "
        "by a 3-point parabola around the largest score (the sampled position when the fit is rejected).",
    )
    parser.add_argument("folder", type=Path, metavar="DIR")
    parser.add_argument("--metric", default="brenner", type=str.lower, choices=[*FOCUS_NAMES, "all"],
                        help="focus measure: a psmini name, an operator code of Pertuz et al. 2013 (lapm, teng, ...) "
                        "or 'all' (every one of the 28 operators: best frame and score of each; default: brenner, "
                        "the seed's)")
    parser.add_argument("--roi", default=None, metavar="x,y,w,h", help="region of interest in pixels")
    add_device_flag(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def _frame_list(folder: Path) -> tuple[list[Path], list[float] | None]:
    """The frame files in sweep order and their positions (None: use indices)."""
    from psmini.errors import DataFormatError
    from psmini.io.capture import read_manifest

    if not folder.is_dir():
        raise DataFormatError(f"{folder} is not a folder of frames")
    if (folder / "capture.json").is_file():
        manifest = read_manifest(folder)
        if manifest["kind"] != "focus":
            raise DataFormatError(f"{folder / 'capture.json'} is a capture of kind {manifest['kind']!r}, not a focus "
                                  "sweep (kind 'focus' with positions_mm)")
        return [folder / name for name in manifest["images"]], [float(p) for p in manifest["positions_mm"]]
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)
    if not files:
        raise DataFormatError(f"{folder} holds no image files ({', '.join(sorted(_IMAGE_SUFFIXES))})")
    return files, None


def _read_frames(files: list[Path]):
    """The frames as one (N, H, W) tensor: uint8/uint16 when every file is gray of one bit depth, else float."""
    import numpy as np
    import torch

    from psmini.errors import DataFormatError
    from psmini.io.images import read_gray, read_image_raw

    frames: list[tuple[np.ndarray, int]] = []  # pixels and bit depth (0: float gray in [0, 1])
    for path in files:
        pixels, bits = read_image_raw(path)
        if pixels.ndim == 3:
            pixels, bits = read_gray(path)[0], 0  # colour: gray float in [0, 1] (DiLiGenT weights)
        if frames and pixels.shape != frames[0][0].shape:
            first = frames[0][0].shape
            raise DataFormatError(f"frames of different sizes: {files[0].name} is {first[1]}×{first[0]}, "
                                  f"{path.name} is {pixels.shape[1]}×{pixels.shape[0]}")
        frames.append((pixels, bits))
    if len({bits for _, bits in frames}) == 1 and frames[0][1] != 0:
        return torch.from_numpy(np.stack([p for p, _ in frames]))  # integer: Brenner's fast uint8 path
    return torch.from_numpy(np.stack([p.astype(np.float32) / (2**b - 1 if b else 1) for p, b in frames]))


def _scores(frames, metric: str, roi, device):
    import torch

    from psmini.focus import focus_measure

    return torch.cat([
        focus_measure(frames[i : i + _CHUNK].to(device), metric, roi=roi).cpu()
        for i in range(0, frames.shape[0], _CHUNK)
    ]).double()


def run(args: argparse.Namespace) -> int:
    from psmini.autofocus import best_of_scores
    from psmini.focus import parse_roi

    device = resolve_device(args.device)
    files, positions = _frame_list(args.folder)
    frames = _read_frames(files)
    roi = parse_roi(args.roi, frames.shape[-2], frames.shape[-1])
    if args.metric == "all":
        return _run_all(args, files, positions, frames, roi, device)
    result = best_of_scores(_scores(frames, args.metric, roi, device), positions)
    unit = "mm" if positions is not None else "(index)"
    sampled = result.positions[result.best_index]
    for i, (path, z, s) in enumerate(zip(files, result.positions, result.scores, strict=True)):
        mark = "  <- best" if i == result.best_index else ""
        print(f"{i:4d}  {path.name:<32s}  z={z:10.4f}  {args.metric}={s:.6g}{mark}")
    print(f"best index {result.best_index} ({files[result.best_index].name}), sampled position {sampled:g} {unit}, "
          f"refined position {result.best_position:.4f} {unit}" + ("" if result.refined else " (fit rejected)"))
    if result.at_edge:
        print("warning: the sharpest frame is at the end of the sweep; the focus may lie outside it")
    if args.json:
        emit_json({
            "best_index": result.best_index,
            "best_position": result.best_position,
            "best_sampled_position": sampled,
            "refined": result.refined,
            "at_edge": result.at_edge,
            "metric": args.metric,
            "roi": list(roi) if roi else None,
            "files": [p.name for p in files],
            "positions": result.positions,
            "positions_are_indices": positions is None,
            "scores": result.scores,
            "stop_index": result.stop_index,
            "stopped_by_rule": result.stopped_by_rule,
        })
    return 0


def _run_all(args, files, positions, frames, roi, device) -> int:
    """Every operator of Pertuz et al. (2013): its best frame, refined position and best score."""
    from psmini.autofocus import best_of_scores
    from psmini.focus import FOCUS_OPERATORS

    unit = "mm" if positions is not None else "(index)"
    print(f"{'code':<5s} {'family':<10s} {'best':>4s}  {'file':<32s} {'position ' + unit:>16s}  score")
    rows = {}
    for code, op in FOCUS_OPERATORS.items():
        result = best_of_scores(_scores(frames, code, roi, device), positions)
        rows[code] = result
        print(f"{code:<5s} {op.family:<10s} {result.best_index:4d}  {files[result.best_index].name:<32s} "
              f"{result.best_position:16.4f}  {result.best_score:.6g}")
    indices = [r.best_index for r in rows.values()]
    consensus = max(set(indices), key=indices.count)
    print(f"{indices.count(consensus)} of {len(indices)} operators pick index {consensus} "
          f"({files[consensus].name})")
    if args.json:
        emit_json({
            "metric": "all",
            "roi": list(roi) if roi else None,
            "files": [p.name for p in files],
            "positions_are_indices": positions is None,
            "operators": {code: {"family": FOCUS_OPERATORS[code].family, "best_index": r.best_index,
                                 "best_position": r.best_position, "best_score": r.best_score,
                                 "refined": r.refined, "scores": r.scores} for code, r in rows.items()},
            "consensus_index": consensus,
        })
    return 0
