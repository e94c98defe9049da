"""The one exception family of psmini.

Every error psmini raises on purpose is a :class:`PsminiError`. The subclasses also derive from the
builtin that fits (``ValueError``, ``OSError``, ``RuntimeError``), so code that catches the builtin keeps
working. Messages say what was expected and what came.
"""

from __future__ import annotations

__all__ = [
    "PsminiError",
    "InputError",
    "ShapeError",
    "CalibrationError",
    "DataFormatError",
    "RigError",
]


class PsminiError(Exception):
    """Base class of every error psmini raises on purpose."""


class InputError(PsminiError, ValueError):
    """An argument has a wrong value: NaN or infinite numbers, a bad dtype, an unknown option."""


class ShapeError(InputError):
    """A tensor has the wrong number of dimensions or sizes that do not match."""


class CalibrationError(PsminiError, ValueError):
    """A light or camera calibration cannot be used: too few lights, coplanar lights, bad parameters."""


class DataFormatError(PsminiError, OSError):
    """A file or folder is missing, unreadable, corrupt or inconsistent (counts, sizes, bit depths)."""


class RigError(PsminiError, RuntimeError):
    """The rig (LED controller or camera) failed: timeout, garbage, disconnect, stale frames."""
