"""``psmini calibrate leds DIR [DIR ...] --out FILE``: fit the LED model to flat-field (card) captures.

``register_leds(calibrate_subparsers)`` adds the ``leds`` parser under ``psmini calibrate``; the calibrate
command wires it in. Each DIR is a capture folder of kind ``flatfield`` (the matte card under each LED, with its
dark frame); its card height comes from ``metadata.card_height_mm`` in the manifest (0 when absent) or from
``--heights-mm``. The fitted model is written as a lights file (``docs/lights-file.md``: the light object of
``docs/capture-format.md``, per-LED residuals, provenance) that ``reconstruct --lights`` reads.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from psmini.commands._common import add_device_flag, add_json_flag, emit_json, resolve_device
from psmini.errors import DataFormatError, InputError


def register_leds(calibrate_subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``leds`` sub-command to the sub-parsers of ``psmini calibrate``; return its parser."""
    parser = calibrate_subparsers.add_parser(
        "leds",
        help="fit LED positions, directions, intensities and mu to card captures at known heights",
        description="Fit the near-light LED model (positions in mm, principal directions, relative intensities, "
        "anisotropy mu) to flat-field captures of a matte card at one or more known heights, by gradient descent "
        "with the camera's vignetting eliminated per pixel. Two heights or more pin the LEDs' distance best.",
    )
    parser.add_argument("dirs", nargs="+", type=Path, metavar="DIR", help="flat-field capture folders (kind flatfield)")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE",
                        help="lights file to write (JSON, docs/lights-file.md)")
    parser.add_argument("--heights-mm", type=float, nargs="+", metavar="H",
                        help="card height of each DIR, mm (default: metadata.card_height_mm of each, else 0)")
    parser.add_argument("--init", default="nominal", metavar="nominal|FILE",
                        help="start: the nominal rig (default) or a JSON light model (a lights file, a manifest "
                        "with 'lights', or a mirror-sphere calibration's directions)")
    parser.add_argument("--ring-diameter-mm", type=float, default=31.6, help="nominal ring diameter (default 31.6)")
    parser.add_argument("--led-height-mm", type=float, default=10.0, help="nominal LED height (default 10)")
    parser.add_argument("--nominal-distance-mm", type=float, default=None,
                        help="distance at which a directional start places the LEDs (default: the nominal rig's)")
    parser.add_argument("--max-size", type=int, default=32, help="fit on images averaged down to this side (32)")
    parser.add_argument("--optimizer", choices=["lbfgs", "adam"], default="lbfgs", help="optimiser (default lbfgs)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing FILE")
    add_device_flag(parser)
    add_json_flag(parser)
    parser.set_defaults(run=run_leds)
    return parser


def _read_init(spec: str) -> Any:
    """``nominal`` or the light model in a JSON file (a light object, or an object holding one under 'lights')."""
    if spec == "nominal":
        return spec
    path = Path(spec)
    if not path.is_file():
        raise InputError(f"--init must be 'nominal' or an existing JSON file, got {spec!r}")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise DataFormatError(f"cannot read the start model {path}: {error}") from error
    if isinstance(data, dict) and "model" not in data and isinstance(data.get("lights"), dict):
        data = data["lights"]
    if not isinstance(data, dict):
        raise DataFormatError(f"{path} holds no light model object")
    return data


def _load_cards(dirs: list[Path], heights: list[float] | None) -> tuple[list, list[float]]:
    from psmini.io import read_capture

    if heights is not None and len(heights) != len(dirs):
        raise InputError(f"--heights-mm needs one height per DIR ({len(dirs)}), got {len(heights)}")
    captures = [read_capture(folder) for folder in dirs]
    for capture in captures:
        if capture.kind != "flatfield":
            raise InputError(f"{capture.path} is a capture of kind {capture.kind!r}; calibrate leds needs flatfield")
    if heights is None:
        heights = []
        for capture in captures:
            value = capture.metadata.get("card_height_mm", 0.0)
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise DataFormatError(f"{capture.path}: metadata.card_height_mm must be a number, got {value!r}")
            heights.append(float(value))
    pitches = {capture.pixel_pitch_mm for capture in captures}
    if len(pitches) > 1:
        raise InputError(f"the card captures have different pixel pitches: {sorted(pitches)}")
    return captures, heights


def run_leds(args: argparse.Namespace) -> int:
    import torch

    from psmini.io.lightsfile import write_lights_file
    from psmini.ledcal import LEDFitOptions, fit_leds, nominal_leds

    device = resolve_device(args.device)
    captures, heights = _load_cards(list(args.dirs), args.heights_mm)
    count = captures[0].images.shape[0]
    init = _read_init(args.init)
    if init == "nominal":
        init = nominal_leds(count, args.ring_diameter_mm, args.led_height_mm, dtype=torch.float64)
    images = [capture.images.to(device) for capture in captures]
    dark = [None if capture.dark is None else capture.dark.to(device) for capture in captures]
    start = time.perf_counter()
    fit = fit_leds(images, heights, captures[0].pixel_pitch_mm, init, card_albedo=[c.card_albedo for c in captures],
                   dark=dark, saturation_level=1.0,
                   options=LEDFitOptions(nominal_distance_mm=args.nominal_distance_mm, max_size=args.max_size,
                                         optimizer=args.optimizer))
    elapsed = time.perf_counter() - start
    record = fit.to_dict()
    leds = [{"name": f"led_{k}", "residual_rms": record["residuals"]["per_led"][k]} for k in range(count)]
    provenance = {**record["calibration"], "residuals": record["residuals"], "sources": [str(d) for d in args.dirs],
                  "intensity_scale": record["intensity_scale"], "init": args.init}
    write_lights_file(args.out, fit.lights, leds=leds, provenance=provenance, overwrite=args.overwrite)
    print(f"fitted {count} LEDs to {len(captures)} card height(s) {heights} mm in {elapsed:.1f} s; "
          f"residual RMS {100 * fit.residual_rms:.3f}% of the mean card reading")
    print(f"{'LED':>3}  {'x mm':>8} {'y mm':>8} {'z mm':>8}  {'intensity':>9}  {'mu':>6}  {'residual %':>10}")
    for k in range(count):
        x, y, z = fit.positions_mm[k].tolist()
        print(f"{k:>3}  {x:8.3f} {y:8.3f} {z:8.3f}  {float(fit.intensities[k]):9.4f}  {float(fit.mu[k]):6.3f}  "
              f"{100 * float(fit.residual_rms_per_led[k]):10.3f}")
    print(f"wrote {args.out}")
    if args.json:
        emit_json({
            "positions_mm": fit.positions_mm.tolist(),
            "principal_directions": fit.principal_directions.tolist(),
            "intensities": fit.intensities.tolist(),
            "mu": fit.mu.tolist(),
            "residual_rms": fit.residual_rms,
            "residual_rms_per_led": fit.residual_rms_per_led.tolist(),
            "heights_mm": heights,
            "out": str(args.out),
            "time_s": elapsed,
        })
    return 0
