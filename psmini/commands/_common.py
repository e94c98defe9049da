"""Helpers shared by the sub-commands: common flags, device choice, the final JSON line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import torch

from psmini.errors import InputError
from psmini.integrate import METHODS as INTEGRATION_METHODS


def add_json_flag(parser: argparse.ArgumentParser) -> None:
    """Add ``--json``: the last line of output is one JSON object."""
    parser.add_argument("--json", action="store_true", help="make the last line of output one JSON object")


def add_device_flag(parser: argparse.ArgumentParser) -> None:
    """Add ``--device cpu|cuda``."""
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where to compute (default: cpu)")


def resolve_device(name: str) -> torch.device:
    """The torch device for ``--device``; a clear error when CUDA is asked for and absent."""
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda was asked for, but torch sees no CUDA device on this machine")
    return torch.device(name)


def emit_json(payload: dict[str, Any]) -> None:
    """Print ``payload`` as one JSON line on stdout (the last line a ``--json`` run prints)."""
    sys.stdout.write(json.dumps(payload, sort_keys=True) + "\n")
    sys.stdout.flush()


def add_reconstruction_flags(parser: argparse.ArgumentParser) -> None:
    """The folder argument and the flags every reconstructing command shares (``reconstruct``, ``evaluate``)."""
    parser.add_argument("folder", type=Path, metavar="DIR", help="DiLiGenT object folder or psmini capture folder")
    parser.add_argument("--integrator", default=None, choices=sorted(INTEGRATION_METHODS),
                        help="integration method (default: fc, Frankot-Chellappa, for distant lights; masked least "
                        "squares for near lights; bilateral keeps depth discontinuities)")
    parser.add_argument("--lights", type=Path, metavar="FILE",
                        help="lights file (docs/lights-file.md, from 'psmini calibrate sphere') to use instead of "
                        "the folder's own lights")
    parser.add_argument("--light-model", choices=["distant", "near"], default="distant",
                        help="distant: classical least squares with the lights seen from the field centre (default); "
                        "near: near-light photometric stereo with the folder's LED or point-light positions")
    from psmini.pipeline import NORMAL_METHODS

    parser.add_argument("--method", choices=NORMAL_METHODS, default="lstsq",
                        help="normal estimator for distant lights: lstsq (least squares, default); robust (the "
                        "recommended robust one); trimmed, threshold, huber, cauchy, tukey, l1, rpca (psmini.robust); or "
                        "nonlambertian (Lambertian + Blinn-Phong lobe, psmini.nonlambertian)")
    add_device_flag(parser)
    add_json_flag(parser)


def load_sample_for(args: argparse.Namespace):
    """The sample of ``args.folder``, with the lights of ``--lights`` when given."""
    from psmini.io import load_sample

    sample = load_sample(args.folder)
    if args.lights is None:
        return sample
    from psmini.io import with_lights_file

    return with_lights_file(sample, args.lights)
