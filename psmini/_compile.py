"""``torch.compile`` where its default backend (inductor) can build kernels, the eager function elsewhere.

Inductor writes C++ for the CPU, which needs a C++ compiler on the machine, and Triton kernels for CUDA GPUs. A
machine without them (a bare container, a laptop without build tools) still runs every psmini command: the caller
gets the eager function and a ``RuntimeWarning`` that says what was missing (once per place it is asked from, by
Python's own filter: a batch of captures is not told again for each).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
import warnings
from collections.abc import Callable
from typing import Any

import torch

__all__ = ["compile_blocker", "compiler"]

Function = Callable[..., Any]


def compile_blocker(device: torch.device) -> str | None:
    """Why ``torch.compile`` cannot build kernels for ``device`` here, or ``None`` when it can.

    Inductor's C++ backend calls the compiler named by ``$CXX`` (``g++``; ``clang++`` on macOS, ``cl`` on Windows);
    CUDA needs the ``triton`` package. Other devices are not checked: they are reported as blocked.

    Example:
        >>> compile_blocker(torch.device("mps"))
        'psmini compiles for the CPU and CUDA only, not for mps'
    """
    if device.type == "cuda":
        return None if importlib.util.find_spec("triton") is not None else "the triton package is not installed"
    if device.type != "cpu":
        return f"psmini compiles for the CPU and CUDA only, not for {device.type}"
    default = {"darwin": "clang++", "win32": "cl"}.get(sys.platform, "g++")
    name = os.environ.get("CXX", default)
    return None if shutil.which(name) is not None else f"no C++ compiler {name!r} on the PATH (set $CXX to one)"


def _eager(function: Function) -> Function:
    return function


def compiler(device: torch.device) -> Callable[[Function], Function]:
    """A decorator: ``torch.compile(function, dynamic=True)`` when :func:`compile_blocker` finds nothing missing for
    ``device`` (one graph for every image size: the solvers call their steps at several), the function itself
    otherwise, with a ``RuntimeWarning``.
    """
    blocker = compile_blocker(device)
    if blocker is None:
        return lambda function: torch.compile(function, dynamic=True)
    warnings.warn(f"torch.compile cannot run on {device}: {blocker}; running eagerly", RuntimeWarning, stacklevel=3)
    return _eager
