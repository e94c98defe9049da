"""``psmini calibrate sphere|flatfield|leds``: lights from a mirror sphere; the card reference; LEDs fitted to cards."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from psmini.commands._calibrate_leds import register_leds
from psmini.commands._common import add_json_flag, emit_json


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="calibrate the lights (mirror sphere) or the flat-field reference (matte card)",
        description="Calibrate the rig: 'sphere' finds light directions (and, from two or more placements, LED "
        "positions) from images of a mirror sphere; 'flatfield' builds the card reference; 'leds' fits the near-light "
        "LED model to card captures by gradient descent.",
    )
    kinds = parser.add_subparsers(dest="target", metavar="TARGET", required=True)
    register_leds(kinds)

    sphere = kinds.add_parser(
        "sphere",
        help="light directions (and LED positions) from a mirror sphere",
        description="Each DIR holds one image of the mirror sphere per LED, listed in filenames.txt (8- or 16-bit, "
        "gray or RGB, any format OpenCV reads) or in a capture manifest (capture.json). Several DIRs are several "
        "placements of the sphere: with --intrinsics and --sphere-radius-mm the reflected rays are intersected "
        "into LED positions. Writes a lights file (docs/lights-file.md).",
    )
    sphere.add_argument("folders", type=Path, nargs="+", metavar="DIR", help="one folder per sphere placement")
    sphere.add_argument("--mask", type=Path, action="append", metavar="FILE",
                        help="image of the sphere's pixels (non-zero inside); once, or once per DIR in order; "
                        "default: the capture's mask, else detected from the summed images")
    sphere.add_argument("--intrinsics", type=Path, metavar="FILE",
                        help="camera matrix K: JSON {\"K\": [[fx,0,cx],[0,fy,cy],[0,0,1]]} (optionally with "
                        "\"card_distance_mm\") or a text file of 3x3 numbers; enables the perspective model")
    sphere.add_argument("--sphere-radius-mm", type=float, metavar="R", help="the sphere's radius, mm (perspective)")
    sphere.add_argument("--card-distance-mm", type=float, metavar="D",
                        help="distance from the camera's centre to the card plane, mm, for LED positions relative "
                        "to the card (default: the intrinsics file's, else from spheres resting on the card)")
    sphere.add_argument("--leds", type=int, metavar="N", help="expected number of LEDs (images per DIR)")
    sphere.add_argument("--out", type=Path, required=True, metavar="FILE", help="the lights file to write (.json)")
    sphere.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    add_json_flag(sphere)
    sphere.set_defaults(run=run_sphere)

    card = kinds.add_parser(
        "flatfield",
        help="the flat-field reference from repeated images of the matte card",
        description="Each DIR holds the card under every LED (a capture folder, or filenames.txt with --lights "
        "and --pixel-pitch-mm); several DIRs are repeats, averaged. The dark frame is averaged and subtracted, "
        "the card is smoothed (a 2-D polynomial by default) and written as a capture folder of kind 'flatfield' "
        "that a sample's manifest can reference.",
    )
    card.add_argument("folders", type=Path, nargs="+", metavar="DIR", help="card captures (repeats)")
    card.add_argument("--out", type=Path, required=True, metavar="DIR", help="the flat-field capture folder to write")
    card.add_argument("--card-albedo", type=float, metavar="A", help="the card's albedo (default: the capture's)")
    card.add_argument("--method", choices=["polynomial", "gaussian", "mean"], default="polynomial",
                      help="smoothing of the card (default: polynomial)")
    card.add_argument("--degree", type=int, default=6, help="total degree of the polynomial (default: 6)")
    card.add_argument("--sigma-px", type=float, default=8.0, help="Gaussian sigma, pixels (default: 8)")
    card.add_argument("--min-level", type=float, default=0.02,
                      help="fraction of each LED's brightest card pixel below which pixels are not trusted")
    card.add_argument("--lights", type=Path, metavar="FILE", help="lights file, for folders without a manifest")
    card.add_argument("--pixel-pitch-mm", type=float, metavar="P", help="pixel pitch, for folders without a manifest")
    card.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    add_json_flag(card)
    card.set_defaults(run=run_flatfield)


# ---------------------------------------------------------------------------------------------- reading


def _read_folder(folder: Path) -> dict[str, Any]:
    """Images (K, H, W), dark, mask, names and the manifest's fields of a capture or filenames.txt folder."""
    import torch

    from psmini.errors import DataFormatError
    from psmini.io import read_capture, read_image_stack, rgb_to_gray

    if (folder / "capture.json").is_file():
        capture = read_capture(folder)
        return {"images": capture.images, "dark": capture.dark, "mask": capture.mask,
                "names": list(capture.manifest["images"]), "lights": capture.lights,
                "pixel_pitch_mm": capture.pixel_pitch_mm, "card_albedo": capture.card_albedo,
                "saturation_level": 1.0}
    listing = folder / "filenames.txt"
    if not listing.is_file():
        raise DataFormatError(f"{folder} holds neither capture.json nor filenames.txt (one image file per LED)")
    names = [line.strip() for line in listing.read_text(encoding="utf-8").splitlines() if line.strip()]
    if not names:
        raise DataFormatError(f"{listing} lists no image files")
    stack, _ = read_image_stack([folder / name for name in names], transform=lambda _, image: rgb_to_gray(image))
    return {"images": torch.from_numpy(stack), "dark": None, "mask": None, "names": names, "lights": None,
            "pixel_pitch_mm": None, "card_albedo": None, "saturation_level": 1.0}


def _read_mask(path: Path):
    import torch

    from psmini.io import read_image

    image, _ = read_image(path)
    return torch.from_numpy(np.ascontiguousarray(image if image.ndim == 2 else image[..., :3].max(axis=-1)) > 0)


def _read_intrinsics(path: Path) -> tuple[Any, float | None]:
    """K (3, 3) float64 and the optional card distance from a JSON or text file."""
    import torch

    from psmini.errors import DataFormatError

    if not path.is_file():
        raise DataFormatError(f"intrinsics file {path} does not exist")
    text = path.read_text(encoding="utf-8")
    distance = None
    try:
        if path.suffix.lower() == ".json":
            document = json.loads(text)
            matrix = np.asarray(document["K"], dtype=np.float64)
            distance = document.get("card_distance_mm")
        else:
            matrix = np.loadtxt(path, dtype=np.float64)
    except (ValueError, KeyError, TypeError) as error:
        raise DataFormatError(f"intrinsics file {path}: expected a 3x3 matrix K ({error})") from error
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
        raise DataFormatError(f"intrinsics file {path}: expected a 3x3 matrix K, got shape {matrix.shape}")
    return torch.from_numpy(matrix), distance


# ----------------------------------------------------------------------------------------------- sphere


def run_sphere(args: argparse.Namespace) -> int:
    import torch

    from psmini.calibration import calibrate_sphere, card_distance_from_spheres, triangulate_leds
    from psmini.errors import DataFormatError, InputError
    from psmini.io import write_lights_file
    from psmini.lights import DirectionalLights, LightModel, PointLights

    start = time.perf_counter()
    masks = args.mask or []
    if len(masks) not in (0, 1, len(args.folders)):
        raise InputError(f"give --mask once or once per DIR ({len(args.folders)}), got {len(masks)}")
    intrinsics, card_distance = (None, None) if args.intrinsics is None else _read_intrinsics(args.intrinsics)
    if intrinsics is not None and args.sphere_radius_mm is None:
        raise InputError("--intrinsics needs --sphere-radius-mm (the perspective model places the sphere in space)")
    card_distance = args.card_distance_mm if args.card_distance_mm is not None else card_distance
    placements, expected = [], args.leds
    for index, folder in enumerate(args.folders):
        data = _read_folder(folder)
        count = int(data["images"].shape[0])
        if expected is not None and count != expected:
            raise DataFormatError(f"{folder} holds {count} LED images but {expected} LEDs are expected "
                                  f"({'--leds' if args.leds else args.folders[0]}); one image per LED is needed")
        expected = count
        mask = data["mask"]
        if masks:
            mask = _read_mask(masks[index] if len(masks) > 1 else masks[0])
        mask = None if mask is None else mask.reshape(mask.shape[-2:])
        names = [f"{folder / name}" for name in data["names"]]
        calibration = calibrate_sphere(
            data["images"].double(), mask=mask, dark=None if data["dark"] is None else data["dark"].double(),
            intrinsics=intrinsics, radius_mm=args.sphere_radius_mm, saturation_level=data["saturation_level"],
            names=names,
        )
        placements.append((folder, data["names"], calibration))
        silhouette = calibration.silhouette
        print(f"{folder}: sphere at (u, v) = ({silhouette.centre_px[0]:.2f}, {silhouette.centre_px[1]:.2f}) px, "
              f"radius {float(silhouette.radius_px):.2f} px, {calibration.model} reflection, {count} highlights")
    calibrations = [c for _, _, c in placements]
    first = calibrations[0]
    positions = residuals = None
    if len(calibrations) >= 2 and intrinsics is not None:
        positions, residuals = triangulate_leds(calibrations)
        if card_distance is None:
            card_distance = card_distance_from_spheres(calibrations)
        positions = positions + torch.tensor([0.0, 0.0, card_distance], dtype=positions.dtype)
        lights: LightModel = PointLights(positions.float())
    else:
        lights = DirectionalLights(first.directions.float())
    leds = []
    for k in range(expected):
        led: dict[str, Any] = {
            "name": placements[0][1][k],
            "direction": first.directions[k].tolist(),
            "highlights_px": [c.highlights.positions_px[k].tolist() for c in calibrations],
            "highlight_snr": [float(c.highlights.snr[k]) for c in calibrations],
        }
        if positions is not None and residuals is not None:  # set together
            led["position_mm"] = positions[k].tolist()
            led["residual_mm"] = float(residuals[k])
        leds.append(led)
    provenance = {
        "method": f"mirror sphere, {first.model} reflection" + (", rays intersected" if positions is not None else ""),
        "sources": [str(folder) for folder, _, _ in placements],
        "intrinsics": None if intrinsics is None else intrinsics.tolist(),
        "sphere_radius_mm": args.sphere_radius_mm,
        "card_distance_mm": card_distance if positions is not None else None,
        "directions_measured_at": "the highlights of the first placement",
        "placements": [
            {"source": str(folder), "centre_px": c.silhouette.centre_px.tolist(),
             "radius_px": float(c.silhouette.radius_px), "outline_rms_px": c.silhouette.rms_px,
             "centre_mm": None if c.centre_mm is None else c.centre_mm.tolist()}
            for folder, _, c in placements
        ],
    }
    write_lights_file(args.out, lights, leds=leds, provenance=provenance, overwrite=args.overwrite)
    elapsed = time.perf_counter() - start
    for k, led in enumerate(leds):
        line = f"  LED {k}: direction ({', '.join(f'{v:+.4f}' for v in led['direction'])})"
        if positions is not None:
            line += f", position ({', '.join(f'{v:+.2f}' for v in led['position_mm'])}) mm, residual " \
                    f"{led['residual_mm']:.3f} mm"
        print(line)
    print(f"wrote {args.out} ({'point' if positions is not None else 'directional'} lights) in {elapsed:.2f} s")
    if args.json:
        payload: dict[str, Any] = {"out": str(args.out), "model": first.model,
                                   "directions": first.directions.tolist(), "time_s": elapsed}
        if positions is not None and residuals is not None:  # set together
            payload["positions_mm"] = positions.tolist()
            payload["residuals_mm"] = residuals.tolist()
        emit_json(payload)
    return 0


# -------------------------------------------------------------------------------------------- flatfield


def run_flatfield(args: argparse.Namespace) -> int:
    import torch

    from psmini.calibration import card_reference
    from psmini.errors import DataFormatError, InputError
    from psmini.io import read_lights_file, write_flatfield_capture

    start = time.perf_counter()
    repeats = [_read_folder(folder) for folder in args.folders]
    first = repeats[0]
    for folder, data in zip(args.folders[1:], repeats[1:], strict=True):
        if data["images"].shape != first["images"].shape:
            raise DataFormatError(f"{folder} holds images {tuple(data['images'].shape)} (K, H, W) but "
                                  f"{args.folders[0]} holds {tuple(first['images'].shape)}; repeats must match")
    lights = read_lights_file(args.lights).lights if args.lights is not None else first["lights"]
    if lights is None:
        raise InputError(f"{args.folders[0]} has no manifest with lights: give --lights FILE")
    if lights.count != first["images"].shape[0]:
        raise DataFormatError(f"{first['images'].shape[0]} card images but {lights.count} lights")
    pitch = args.pixel_pitch_mm or first["pixel_pitch_mm"]
    if pitch is None:
        raise InputError(f"{args.folders[0]} has no manifest with a pixel pitch: give --pixel-pitch-mm")
    albedo = args.card_albedo or first["card_albedo"]
    if albedo is None:
        raise InputError("the card's albedo is unknown: give --card-albedo (the capture has no card_albedo)")
    frames = torch.stack([data["images"] for data in repeats])
    darks = [data["dark"] for data in repeats if data["dark"] is not None]
    dark = torch.stack(darks) if darks else None
    card = card_reference(frames, dark, method=args.method, degree=args.degree, sigma_px=args.sigma_px,
                          min_level=args.min_level, saturation_level=first["saturation_level"])
    metadata = {"sources": [str(f) for f in args.folders], "method": args.method,
                "degree": args.degree if args.method == "polynomial" else None,
                "sigma_px": args.sigma_px if args.method == "gaussian" else None}
    write_flatfield_capture(args.out, card, lights, card_albedo=albedo, pixel_pitch_mm=pitch, metadata=metadata,
                            overwrite=args.overwrite)
    elapsed = time.perf_counter() - start
    trusted = float(card.valid.float().mean())
    print(f"averaged {card.frames} frame(s) of {len(frames[0])} LEDs, {args.method} smoothing removed "
          f"{float(card.residual.mean()):.5f} rms; {trusted:.1%} of pixels trusted")
    print(f"wrote {args.out} (flat-field capture, card albedo {albedo}) in {elapsed:.2f} s")
    if args.json:
        emit_json({"out": str(args.out), "frames": card.frames, "method": args.method,
                   "residual": card.residual.tolist(), "trusted_fraction": trusted, "time_s": elapsed})
    return 0
