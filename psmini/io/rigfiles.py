"""Files of the rig's calibration: the flat-field (card) capture and LED calibrations stored as MAT-files.

The maths of calibration lives in :mod:`psmini.calibration` and :mod:`psmini.ledcal`; this module turns its
results into files (and a published rig's MAT-file into a light model), so that the core never touches files.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from psmini.calibration.reference import CardReference
from psmini.errors import DataFormatError, InputError
from psmini.io.capture import write_capture
from psmini.io.matfile import read_mat
from psmini.lights import LEDLights, LightModel

__all__ = ["write_flatfield_capture", "load_rig_calibration_mat"]

# DiLiGenT's gray weights, for a MAT-file's RGB LED intensities
_GRAY_WEIGHTS = (0.2989, 0.5870, 0.1140)


def write_flatfield_capture(
    folder: str | Path,
    card: CardReference,
    lights: LightModel,
    *,
    card_albedo: float,
    pixel_pitch_mm: float,
    metadata: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a reference as a capture folder of kind ``"flatfield"`` (``docs/capture-format.md``).

    The images stored are the smooth reference plus the averaged dark frame, with that dark frame beside them,
    so that the reader's ``reference - reference_dark`` gives back the smooth reference exactly (and no other
    dark frame is subtracted from it). Untrusted pixels store the dark level (a reference of 0); the mask holds
    the pixels trusted under every LED. 16-bit PNGs.

    Args:
        folder: the destination folder.
        card: the :class:`CardReference`.
        lights: the light model the card was taken under (K lights).
        card_albedo: the card's albedo.
        pixel_pitch_mm: pixel size on the card, mm.
        metadata: free-form provenance.
        overwrite: replace an existing folder.

    Returns:
        the folder.

    Raises:
        InputError, DataFormatError: as :func:`psmini.io.write_capture`; an InputError for a ``card`` that is not a
            :class:`CardReference` (the reference tensor alone) or ``metadata`` that is not a dict.

    Example:
        >>> write_flatfield_capture("card", card_reference(frames), lights, card_albedo=0.8,
        ...                         pixel_pitch_mm=0.025)  # doctest: +SKIP
    """
    # the reference tensor alone failed as a bare AttributeError on dark, a list of metadata as a TypeError
    if not isinstance(card, CardReference):
        raise InputError(f"card must be a CardReference (psmini.calibration.card_reference's result), got "
                         f"{type(card).__name__}")
    if metadata is not None and not isinstance(metadata, dict):
        raise InputError(f"metadata must be a dict or None, got {type(metadata).__name__}")
    dark = card.dark if card.dark is not None else torch.zeros_like(card.reference[:1])
    images = (card.reference + dark).clamp(0, 1)
    info = {"flatfield_reference": {"frames": card.frames, "residual": card.residual.tolist()}}
    return write_capture(
        folder, images, lights, pixel_pitch_mm=pixel_pitch_mm, kind="flatfield", bit_depth=16,
        dark=dark.clamp(0, 1), mask=card.valid.all(dim=0), card_albedo=card_albedo,
        metadata={**(metadata or {}), **info}, overwrite=overwrite,
    )


def load_rig_calibration_mat(path: str | Path, reference_depth_mm: float = 0.0) -> LEDLights:
    r"""Read an LED calibration saved as a MAT-file (``S``, ``Dir``, ``Phi``, ``mu``) into psmini's frame.

    The layout is the one of the near-light rig in ``../shared/data/near_ps_rig/light.mat`` (Quéau et al. 2018's
    calibration format): ``S`` (K × 3) LED positions in mm, ``Dir`` (K × 3) principal directions, ``Phi``
    (K × 3) RGB intensities, ``mu`` (K × 1) anisotropies, in the camera frame of computer vision (origin at the
    centre of projection, x right, y down, z along the optical axis toward the scene). psmini's frame has y up and
    z toward the camera, so positions and directions become :math:`(x, -y, -z)` (a rotation by 180° about x,
    which keeps the frame right-handed) and, with ``reference_depth_mm`` = d, positions are shifted so that the
    plane at depth d (e.g. the card) becomes psmini's reference plane z = 0: :math:`z' = d - z`. Intensities
    become gray with the DiLiGenT weights 0.2989/0.5870/0.1140 and keep the file's (absolute) scale.

    Args:
        path: the ``.mat`` file (MATLAB level 5, read by :func:`psmini.io.read_mat`).
        reference_depth_mm: depth along the file's optical axis of the plane that becomes z = 0, mm (default 0:
            the origin stays at the centre of projection, and the scene lies at negative z).

    Returns:
        an :class:`~psmini.lights.LEDLights` (float32).

    Raises:
        DataFormatError: a missing or unreadable file, missing variables or shapes other than K × 3 / K.
        CalibrationError: values the LED model refuses (zero directions, intensities <= 0, mu < 0).

    Example:
        >>> leds = load_rig_calibration_mat("../shared/data/near_ps_rig/light.mat")  # doctest: +SKIP
        >>> leds.count  # doctest: +SKIP
        8
    """
    variables = read_mat(path)
    missing = [name for name in ("S", "Dir", "Phi", "mu") if name not in variables]
    if missing:
        raise DataFormatError(f"{path}: an LED calibration needs variables S, Dir, Phi and mu; missing {missing}")
    positions = np.asarray(variables["S"], dtype=np.float64)
    directions = np.asarray(variables["Dir"], dtype=np.float64)
    phi = np.asarray(variables["Phi"], dtype=np.float64)
    mu = np.asarray(variables["mu"], dtype=np.float64).reshape(-1)
    count = positions.shape[0]
    if positions.shape != (count, 3) or directions.shape != (count, 3) or mu.shape != (count,) \
            or phi.shape[0] != count or phi.ndim != 2 or phi.shape[1] not in (1, 3):
        raise DataFormatError(
            f"{path}: expected S and Dir K x 3, Phi K x 3 (RGB) or K x 1, mu K x 1; got S {positions.shape}, "
            f"Dir {directions.shape}, Phi {phi.shape}, mu {variables['mu'].shape}"
        )
    if not all(np.isfinite(a).all() for a in (positions, directions, phi, mu)):
        raise DataFormatError(f"{path}: the LED calibration holds NaN or infinite values")
    flip = np.array([1.0, -1.0, -1.0])
    positions = positions * flip + np.array([0.0, 0.0, float(reference_depth_mm)])
    directions = directions * flip
    gray = phi @ np.asarray(_GRAY_WEIGHTS) if phi.shape[1] == 3 else phi[:, 0]
    positions_t, directions_t, gray_t, mu_t = (torch.as_tensor(a, dtype=torch.float32)
                                               for a in (positions, directions, gray, mu))
    return LEDLights(positions_t, directions_t, gray_t, mu_t)
