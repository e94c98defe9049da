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


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """The flags of a :class:`~psmini.config.ReconstructionConfig`, the same for every reconstructing command
    (``reconstruct``, ``evaluate``, ``batch``, ``demo``); :func:`config_from_args` turns them into one."""
    from psmini.config import ESTIMATORS, SOLVERS

    parser.add_argument("--light-model", "--solver", dest="solver", choices=SOLVERS, default="auto",
                        help="auto (default): near-light photometric stereo when the folder's lights have positions "
                        "(LEDs, point lights), the classical distant-light pipeline for directions; distant or near "
                        "forces one")
    parser.add_argument("--estimator", "--method", dest="estimator", choices=ESTIMATORS, default="auto",
                        help="normal estimator of the distant solver: auto (= lstsq, least squares), robust (the "
                        "recommended robust one), trimmed, threshold, huber, cauchy, tukey, l1, rpca "
                        "(psmini.robust), nonlambertian (Lambertian + Blinn-Phong lobe)")
    parser.add_argument("--integrator", default="auto", choices=["auto", *sorted(INTEGRATION_METHODS)],
                        help="integration method; auto (default): masked least squares when the folder has a mask "
                        "or near light runs, Frankot-Chellappa otherwise; bilateral keeps depth discontinuities")
    parser.add_argument("--integrator-option", action="append", default=[], metavar="KEY=VALUE",
                        help="an option of the integrator (VALUE as JSON), e.g. boundary=\"periodic\" for fc")
    parser.add_argument("--near-option", action="append", default=[], metavar="KEY=VALUE",
                        help="an option of the near-light solver (VALUE as JSON), e.g. max_iterations=3")
    parser.add_argument("--min-reference", type=float, default=0.02, metavar="F",
                        help="card pixels darker than F x the LED's brightest card pixel are not trusted "
                             "(default 0.02)")
    parser.add_argument("--card-smoothing-px", type=float, default=5.0, metavar="S",
                        help="denoise the card before dividing by it: a local quadratic fit of each LED's share in a "
                             "Gaussian window of S pixels (psmini.flatfield.smooth_card; default 5; 0 divides by the "
                             "card as captured)")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32",
                        help="floating dtype of the computation (default float32)")
    add_device_flag(parser)


def _options(pairs: list[str], flag: str) -> dict[str, Any]:
    options: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise InputError(f"{flag} takes KEY=VALUE, got {pair!r}")
        try:
            options[key] = json.loads(value)
        except ValueError:
            options[key] = value  # a bare word is a string
    return options


def config_from_args(args: argparse.Namespace):
    """The :class:`~psmini.config.ReconstructionConfig` of :func:`add_config_flags`'s flags (built once per run).

    Raises:
        InputError: a malformed option, options of another method, CUDA asked for and absent.
    """
    from psmini.config import ReconstructionConfig

    resolve_device(args.device)
    return ReconstructionConfig(
        solver=args.solver, estimator=args.estimator, integrator=args.integrator,
        integrator_options=_options(args.integrator_option, "--integrator-option"),
        # near's JSON form, which __post_init__ turns into NearLightOptions (naming a bad key as an InputError)
        near=_options(args.near_option, "--near-option"),  # type: ignore[arg-type]
        min_reference=args.min_reference,
        card_smoothing_px=args.card_smoothing_px or None, device=args.device,
        dtype=args.dtype,
    )


def add_reconstruction_flags(parser: argparse.ArgumentParser) -> None:
    """The folder argument and the flags every command reconstructing one folder shares (``reconstruct``,
    ``evaluate``)."""
    parser.add_argument("folder", type=Path, metavar="DIR", help="DiLiGenT object folder or psmini capture folder")
    parser.add_argument("--lights", type=Path, metavar="FILE",
                        help="lights file (docs/lights-file.md, from 'psmini calibrate sphere|leds' or any light "
                        "model's JSON, a model of your own included: docs/guides/light-models.md) to use instead of "
                        "the folder's own lights")
    add_config_flags(parser)
    add_json_flag(parser)


def load_sample_for(args: argparse.Namespace):
    """The sample of ``args.folder``, with the lights of ``--lights`` when given."""
    from psmini.io import load_sample

    sample = load_sample(args.folder)
    if args.lights is None:
        return sample
    from psmini.io import with_lights_file

    return with_lights_file(sample, args.lights)
