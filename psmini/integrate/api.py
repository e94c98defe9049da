"""The one entry point of normal integration, dispatching on ``method=``."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import torch  # noqa: F401  (the docstring example uses it)
from torch import Tensor

from psmini.errors import InputError
from psmini.integrate.bilateral import bilateral_integration
from psmini.integrate.fourier import dct_poisson, frankot_chellappa
from psmini.integrate.least_squares import masked_least_squares

__all__ = ["integrate", "METHODS", "method_options"]

METHODS: dict[str, Callable[..., Tensor]] = {
    "fc": frankot_chellappa,
    "dct": dct_poisson,
    "masked": masked_least_squares,
    "bilateral": bilateral_integration,
}


def method_options(method: str) -> set[str]:
    """The options integration ``method`` takes beyond the gradients, pitch and mask (what ``**options`` may hold).

    Example:
        >>> sorted(method_options("fc"))
        ['boundary']
    """
    if method not in METHODS:
        raise InputError(f"unknown integration method {method!r}; expected one of {', '.join(sorted(METHODS))}")
    return set(inspect.signature(METHODS[method]).parameters) - {"p", "q", "pixel_pitch_mm", "mask"}


def integrate(
    p: Tensor, q: Tensor, method: str = "fc", pixel_pitch_mm: float = 1.0, mask: Tensor | None = None, **options: Any
) -> Tensor:
    r"""Integrate surface gradients to height, with the integrator named by ``method``.

    Args:
        p: :math:`\partial z/\partial x`, shape :math:`(B, 1, H, W)` (x right).
        q: :math:`\partial z/\partial y`, shape :math:`(B, 1, H, W)` (y up).
        method: one of :data:`METHODS`: ``"fc"`` (:func:`frankot_chellappa`), ``"dct"`` (:func:`dct_poisson`),
            ``"masked"`` (:func:`masked_least_squares`), ``"bilateral"`` (:func:`bilateral_integration`,
            discontinuity-preserving).
            For perspective integration from normals and intrinsics see :func:`integrate_normals`.
        pixel_pitch_mm: size of one pixel on the surface in mm.
        mask: optional pixels to integrate, shape :math:`(B, 1, H, W)`.
        **options: passed to the method (e.g. ``boundary="periodic"`` for ``"fc"``).

    Returns:
        height toward the camera in mm, shape :math:`(B, 1, H, W)`; see each method for its offset convention.

    Raises:
        InputError: when ``method`` is unknown or an option does not belong to it; see each method.

    Example:
        >>> z = integrate(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8), method="fc", pixel_pitch_mm=0.025)
        >>> z.shape
        torch.Size([1, 1, 8, 8])
    """
    accepted = method_options(method)
    func = METHODS[method]
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise InputError(f"method {method!r} takes options {sorted(accepted)}, got unknown {unknown}")
    return func(p, q, pixel_pitch_mm=pixel_pitch_mm, mask=mask, **options)
