"""``psmini integrate NORMALS --out DEPTH.npy``: depth from a normal map, from any source.

Normals come from an ``.npy`` array, shape ``(H, W, 3)`` or ``(3, H, W)``, psmini's camera frame (x right, y up,
z toward the camera), or from a PNG encoded as in DiLiGenT_depth: 16-bit, channels (x, y, z) stored in OpenCV's
BGR order (so R = x), ``n = v / 65535 * 2 - 1`` (8-bit PNGs use 255). The output ``.npy`` holds float32
``(H, W)``: with ``--intrinsics`` the depth along the optical axis (positive, up to one global scale, geometric
mean 1 over the mask); otherwise the height toward the camera in mm at ``--pixel-pitch`` (zero mean over the
mask). NaN outside the mask.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from psmini.commands._common import add_device_flag, add_json_flag, emit_json, resolve_device
from psmini.errors import DataFormatError, InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    from psmini.integrate import METHODS

    parser = subparsers.add_parser(
        "integrate",
        help="integrate a normal map (.npy or 16-bit PNG) to depth",
        description=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("normals", type=Path, metavar="NORMALS", help="normal map: .npy (H,W,3 or 3,H,W) or PNG")
    parser.add_argument("--out", type=Path, required=True, metavar="DEPTH.npy", help="where to write the depth")
    parser.add_argument("--mask", type=Path, metavar="FILE", help="mask image or .npy (nonzero = inside)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--intrinsics", type=Path, metavar="K.txt", help="3x3 pinhole matrix (pixels): perspective")
    source.add_argument("--pixel-pitch", type=float, default=1.0, metavar="MM", help="orthographic pixel size (mm)")
    parser.add_argument("--method", default="masked", choices=sorted(METHODS), help="integrator (default: masked)")
    add_device_flag(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run)


def _read_normals(path: Path) -> np.ndarray:
    """Normals ``(H, W, 3)`` float32 from ``.npy`` or a PNG (DiLiGenT_depth encoding)."""
    if path.suffix.lower() == ".npy":
        from psmini.io._npy import read_npy

        array = read_npy(path, "normals")
        if array.ndim == 3 and array.shape[0] == 3 and array.shape[-1] != 3:
            array = np.moveaxis(array, 0, -1)
        if array.ndim != 3 or array.shape[-1] != 3:
            raise DataFormatError(f"normals {path} must have shape (H, W, 3) or (3, H, W), got {array.shape}")
        return array.astype(np.float32)
    from psmini.io.images import read_image_raw

    pixels, bits = read_image_raw(path)  # RGB order: R = x, G = y, B = z
    if pixels.ndim != 3 or pixels.shape[-1] != 3:
        raise DataFormatError(f"normal map {path} must be a 3-channel image, got shape {pixels.shape}")
    return (pixels.astype(np.float32) / (2**bits - 1) * 2 - 1).astype(np.float32)


def _read_mask(path: Path, height: int, width: int) -> np.ndarray:
    if path.suffix.lower() == ".npy":
        from psmini.io._npy import read_npy

        mask = read_npy(path, "mask")
    else:
        from psmini.io.images import read_image_raw

        mask, _ = read_image_raw(path)
    if mask.ndim == 3:
        mask = np.asarray(mask.any(axis=-1))
    if mask.shape != (height, width):
        got = f"{mask.shape[1]}x{mask.shape[0]}" if mask.ndim == 2 else f"of shape {mask.shape}"
        raise DataFormatError(f"mask {path} is {got}, the normals {width}x{height}")
    return mask != 0


def _read_intrinsics(path: Path) -> np.ndarray:
    try:
        k = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as error:
        raise DataFormatError(f"cannot read intrinsics {path}: {error}") from error
    if k.shape != (3, 3):
        raise DataFormatError(f"intrinsics {path} must hold a 3x3 matrix, got shape {k.shape}")
    return k


def run(args: argparse.Namespace) -> int:
    import torch

    from psmini.integrate import integrate_normals
    from psmini.io._npy import check_npy_target

    device = resolve_device(args.device)
    if args.out.suffix.lower() != ".npy":
        raise InputError(f"--out must name a .npy file, got {args.out}")
    check_npy_target(args.out)  # before the integration, not after it
    normals = _read_normals(args.normals)
    height, width = normals.shape[:2]
    norm = np.linalg.norm(normals, axis=-1, keepdims=True)
    mask = _read_mask(args.mask, height, width) if args.mask else np.ones((height, width), bool)
    mask &= np.isfinite(norm[..., 0]) & (norm[..., 0] > 0.5) & (normals[..., 2] > 0)  # drop empty/back-facing pixels
    if not mask.any():
        raise InputError(f"no pixel of {args.normals} inside the mask holds a camera-facing normal")
    normals = np.where(mask[..., None], normals / np.where(norm > 0, norm, 1), [0.0, 0.0, 1.0]).astype(np.float32)
    n = torch.from_numpy(np.ascontiguousarray(normals.transpose(2, 0, 1)))[None].to(device)
    m = torch.from_numpy(mask)[None, None].to(device)
    k = torch.from_numpy(_read_intrinsics(args.intrinsics)).float().to(device) if args.intrinsics else None
    start = time.perf_counter()
    depth = integrate_normals(n, args.method, m, intrinsics=k, pixel_pitch_mm=args.pixel_pitch)
    elapsed = time.perf_counter() - start
    out = depth[0, 0].cpu().numpy().astype(np.float32)
    out[~mask] = np.nan
    from psmini.io._npy import save_npy

    save_npy(args.out, out)  # atomically: an interrupted run leaves no half-written depth
    what = "depth along the optical axis (up to scale)" if k is not None else "height (mm, up to an offset)"
    print(f"{args.normals} -> {args.out}: {what}, {width}x{height}, method {args.method}, {elapsed:.2f} s")
    if args.json:
        emit_json(
            {"method": args.method, "shape": [height, width], "time_s": round(elapsed, 4), "output": str(args.out),
             "perspective": k is not None, "pixels": int(mask.sum())}
        )
    return 0
