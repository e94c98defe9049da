"""Normal integration: surface gradients (or normals) to depth.

One entry point, :func:`integrate`, dispatches on ``method=``; each method is also a functional of its own.
"""

from __future__ import annotations

from psmini.integrate.fourier import FrankotChellappa, frankot_chellappa
from psmini.integrate.api import METHODS, integrate

__all__ = ["integrate", "METHODS", "frankot_chellappa", "FrankotChellappa"]
