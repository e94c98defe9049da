"""Normal integration: surface gradients (or normals) to depth.

One entry point, :func:`integrate`, dispatches on ``method=``; each method is also a functional of its own.
The package itself is callable as that entry point, so ``psmini.integrate(p, q, ...)`` and
``psmini.integrate.frankot_chellappa(...)`` both work without the function shadowing the package.
"""

from __future__ import annotations

import sys
import types

from psmini.integrate.api import METHODS, integrate
from psmini.integrate.bilateral import BilateralIntegration, bilateral_integration
from psmini.integrate.fourier import DCTPoisson, FrankotChellappa, dct_poisson, frankot_chellappa
from psmini.integrate.least_squares import MaskedLeastSquares, masked_least_squares
from psmini.integrate.normals import integrate_normals, perspective_log_gradients

__all__ = [
    "integrate",
    "integrate_normals",
    "METHODS",
    "frankot_chellappa",
    "FrankotChellappa",
    "dct_poisson",
    "DCTPoisson",
    "masked_least_squares",
    "MaskedLeastSquares",
    "perspective_log_gradients",
    "bilateral_integration",
    "BilateralIntegration",
]


class _CallablePackage(types.ModuleType):
    """This package, callable as :func:`integrate`."""

    def __call__(self, *args, **kwargs):
        return integrate(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage
