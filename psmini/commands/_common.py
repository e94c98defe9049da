"""Helpers shared by the sub-commands: common flags, device choice, the final JSON line."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import torch

from psmini.errors import InputError


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
