"""``psmini capture``: a capture folder from the rig (``--port URL --camera ID``) or the simulated rig
(``--simulate``)."""

from __future__ import annotations

import argparse
import importlib.metadata
import time
from pathlib import Path

from psmini.commands._common import add_json_flag, emit_json

_FAULTS = ("no-banner", "timeout", "garbage", "disconnect", "no-frame", "stale-frame")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "capture",
        help="capture a sample (or a calibration target) on the rig or the simulated rig",
        description="Take the dark frame and one frame per LED and write them as a psmini capture folder "
        "(docs/capture-format.md), atomically. With --port and --camera the real rig is used (psmini-leds firmware, "
        "see docs/rig-protocol.md); with --simulate a simulated rig renders a synthetic fabric: it captures the card "
        "and then the fabric, and writes OUT with the card inside (OUT/card) and ground truth, so that "
        "`psmini reconstruct OUT` and `psmini evaluate OUT` work on it as it is.",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="the capture folder to create")
    parser.add_argument("--simulate", action="store_true", help="use the simulated rig instead of hardware")
    parser.add_argument("--port", metavar="URL", help="LED controller port or pyserial URL (/dev/ttyUSB0, COM3, "
                        "psminisim://...)")
    parser.add_argument("--camera", metavar="ID", help="camera index or device path for OpenCV")
    parser.add_argument("--backend", default=None,
                        help="OpenCV backend: v4l2, dshow, msmf, avfoundation, gstreamer, any "
                             "(default: the platform's)")
    parser.add_argument("--kind", choices=["sample", "flatfield", "sphere"], default="sample",
                        help="what lies under the camera (hardware only; default: sample)")
    parser.add_argument("--flatfield", type=Path, metavar="CARD", help="the card capture to flat-field by (hardware)")
    parser.add_argument("--card-albedo", type=float, default=None, help="albedo of the card (--kind flatfield)")
    parser.add_argument("--lights", type=Path, metavar="FILE", help="a lights file from `psmini calibrate` "
                        "(docs/lights-file.md) for the manifest; default: the nominal ring (31.6 mm, 10 mm high)")
    parser.add_argument("--frames", type=int, default=1, help="frames averaged per LED (default: 1)")
    parser.add_argument("--exposure", type=float, help="camera exposure, the backend's unit")
    parser.add_argument("--gain", type=float, help="camera gain")
    parser.add_argument("--white-balance", type=float, help="white balance temperature, K")
    parser.add_argument("--pixel-pitch", type=float, default=0.025, help="mm per pixel on the cloth (default: 0.025)")
    parser.add_argument("--handshake-timeout", type=float, default=3.0, help="s to wait for READY (default: 3)")
    parser.add_argument("--command-timeout", type=float, default=0.5, help="s to wait for each reply (default: 0.5)")
    parser.add_argument("--fabric", default="jute", help="fabric of the simulated rig (default: jute)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated fabric and noise (default: 0)")
    parser.add_argument("--size", type=int, default=400, help="crop side of the simulated rig, pixels (default: 400)")
    parser.add_argument("--fault", choices=_FAULTS, help="inject a fault into the simulated rig")
    parser.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    add_json_flag(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from psmini.errors import InputError

    if args.simulate == bool(args.port):
        raise InputError("give either --simulate or --port URL (with --camera ID)")
    if args.fault and not args.simulate:
        raise InputError("--fault injects faults into the simulated rig; add --simulate")
    start = time.perf_counter()
    summary = _simulated(args) if args.simulate else _hardware(args)
    summary["time_s"] = time.perf_counter() - start
    print(f"captured {summary['kind']} with {summary['leds']} LEDs ({summary['firmware']}) "
          f"in {summary['time_s']:.1f} s")
    print(f"  wrote {summary['out']}")
    if args.json:
        emit_json(summary)
    return 0


def _simulated(args: argparse.Namespace) -> dict:
    """Hand ``--simulate`` to the installed rig simulator (data_synth's, through the ``psmini.rig_simulators``
    group)."""
    from psmini.errors import InputError

    simulators = list(importlib.metadata.entry_points(group="psmini.rig_simulators"))
    if not simulators:
        raise InputError("--simulate needs a rig simulator; none is installed (data_synth, installed with psmini from "
                         "its repository, provides one)")
    return simulators[0].load()(args)


def _hardware(args: argparse.Namespace) -> dict:
    from psmini.errors import InputError
    from psmini.io import read_lights_file
    from psmini.rig import CameraSettings, CaptureSession, LEDController, RigCamera, nominal_ring_lights

    if args.camera is None:
        raise InputError("--port needs --camera ID (the webcam's index or device path)")
    if args.kind == "flatfield" and not (args.card_albedo and args.card_albedo > 0):
        raise InputError("--kind flatfield needs --card-albedo, the card's albedo (a positive number)")
    lights = read_lights_file(args.lights).lights if args.lights is not None else None
    source: int | str = int(args.camera) if args.camera.isdigit() else args.camera
    settings = CameraSettings(exposure=args.exposure, gain=args.gain, white_balance=args.white_balance)
    with LEDController(args.port, handshake_timeout_s=args.handshake_timeout,
                       command_timeout_s=args.command_timeout) as leds, \
            RigCamera(source, backend=args.backend, settings=settings) as camera:
        if lights is None:
            lights = nominal_ring_lights(leds.led_count)
        session = CaptureSession(leds, camera, lights, pixel_pitch_mm=args.pixel_pitch, frames_per_led=args.frames)
        flatfield = {"path": str(args.flatfield.resolve())} if args.flatfield is not None else None
        session.capture(args.out, args.kind, flatfield=flatfield, card_albedo=args.card_albedo,
                        overwrite=args.overwrite)
        return {"out": str(args.out), "kind": args.kind, "leds": leds.led_count, "firmware": str(leds.identity),
                "simulated": False, "camera": camera.report}
