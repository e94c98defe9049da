r"""Mirror-sphere calibration end to end: silhouette, highlights, directions, and LED positions.

:func:`calibrate_sphere` turns one placement's images (one per LED) into light directions, orthographic when
no intrinsics are given and perspective (exact at close range) when they are; :func:`triangulate_leds`
intersects the reflected rays of two or more placements into LED positions. The pieces are in
:mod:`psmini.calibration.sphere`, :mod:`psmini.calibration.highlights` and
:mod:`psmini.calibration.triangulate`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from psmini._checks import check_finite, check_positive, check_shape
from psmini.calibration.highlights import Highlights, locate_highlights
from psmini.calibration.sphere import (
    SphereSilhouette,
    find_sphere,
    reflect_orthographic,
    reflect_perspective,
    sphere_centre_from_silhouette,
)
from psmini.calibration.triangulate import triangulate_rays
from psmini.errors import CalibrationError, InputError, ShapeError

__all__ = ["SphereCalibration", "calibrate_sphere", "triangulate_leds", "card_distance_from_spheres"]

logger = logging.getLogger(__name__)


@dataclass
class SphereCalibration:
    """One sphere placement's calibration.

    Attributes:
        directions: unit light directions, shape :math:`(K, 3)`, camera frame (x right, y up, z toward the
            camera), measured at the highlights.
        highlights: the highlights (:class:`~psmini.calibration.highlights.Highlights`).
        silhouette: the sphere's outline (:class:`~psmini.calibration.sphere.SphereSilhouette`).
        model: ``"perspective"`` or ``"orthographic"``.
        centre_mm: the sphere's centre, shape :math:`(3,)`, mm, origin at the centre of projection
            (perspective only, else None).
        radius_mm: the sphere's radius, mm (perspective only, else None).
        points_mm: the reflection points on the sphere, shape :math:`(K, 3)`, mm, same frame (perspective
            only, else None).
    """

    directions: Tensor
    highlights: Highlights
    silhouette: SphereSilhouette
    model: str
    centre_mm: Tensor | None = None
    radius_mm: float | None = None
    points_mm: Tensor | None = None


def calibrate_sphere(
    images: Tensor,
    *,
    mask: Tensor | None = None,
    dark: Tensor | None = None,
    intrinsics: Tensor | None = None,
    radius_mm: float | None = None,
    saturation_level: float | None = 1.0,
    names: Sequence[str] | None = None,
) -> SphereCalibration:
    r"""Light directions from the images of a mirror sphere, one image per LED.

    The silhouette comes from ``mask`` when given, else from the sum of the (dark-subtracted) images; each
    LED's highlight is located (:func:`~psmini.calibration.highlights.locate_highlights`); the view ray is
    reflected at it, orthographically (view ``(0, 0, 1)``) without ``intrinsics``, or through the pinhole
    camera with the sphere's centre placed in space from its outline, ``intrinsics`` and ``radius_mm``.

    Args:
        images: one image per LED, shape :math:`(K, H, W)`, linear values in [0, 1].
        mask: the sphere's pixels, shape :math:`(H, W)` or :math:`(1, H, W)`, non-zero inside.
        dark: all-LEDs-off frame, shape :math:`(H, W)` or :math:`(1, H, W)`.
        intrinsics: OpenCV pinhole matrix ``K``, shape :math:`(3, 3)`; with it the perspective model.
        radius_mm: the sphere's radius, mm; required with ``intrinsics``.
        saturation_level: the saturation level of the images (reported per highlight), or None.
        names: the name of each LED's image, for the messages.

    Returns:
        :class:`SphereCalibration`.

    Raises:
        ShapeError: for images that are not (K, H, W), or a mask or dark frame of another size.
        InputError: ``intrinsics`` without ``radius_mm``.
        CalibrationError: sphere not found; per LED (named): no highlight, two highlights, a highlight
            outside the sphere.

    Example:
        >>> from data_synth.rig import RigConfig, render_sphere  # doctest: +SKIP
        >>> sphere = render_sphere(RigConfig(noise=False))  # doctest: +SKIP
        >>> calibrate_sphere(sphere.images, dark=sphere.dark).directions.shape  # doctest: +SKIP
        torch.Size([8, 3])
    """
    sizes = check_shape(images, ["K", "H", "W"], "images")
    check_finite(images, "images")
    height, width = sizes["H"], sizes["W"]
    if intrinsics is not None and radius_mm is None:
        raise InputError("the perspective model needs the sphere's radius in mm (radius_mm) beside the intrinsics")
    dark = _plane(dark, height, width, "dark")
    mask = _plane(mask, height, width, "mask")
    signal = images if dark is None else images - dark.to(images)
    silhouette = find_sphere(image=None if mask is not None else signal.sum(0), mask=mask)
    highlights = locate_highlights(
        signal, silhouette.centre_px, silhouette.radius_px, saturation_level=saturation_level, names=names
    )
    logger.info("sphere at (%.2f, %.2f) px, radius %.2f px, outline rms %.3f px", *silhouette.centre_px.tolist(),
                float(silhouette.radius_px), silhouette.rms_px)
    if intrinsics is None:
        directions = reflect_orthographic(highlights.positions_px, silhouette.centre_px, silhouette.radius_px)
        return SphereCalibration(directions, highlights, silhouette, "orthographic")
    radius_mm = check_positive(radius_mm, "radius_mm")
    intrinsics = intrinsics.to(images)
    edges = silhouette.edge_px.to(images)
    centre = sphere_centre_from_silhouette(edges, intrinsics, radius_mm, weights=silhouette.inliers.to(images))
    directions, points = reflect_perspective(highlights.positions_px, intrinsics, centre, radius_mm)
    return SphereCalibration(directions, highlights, silhouette, "perspective", centre, radius_mm, points)


def _plane(frame: Tensor | None, height: int, width: int, name: str) -> Tensor | None:
    """An optional (H, W) or (1, H, W) frame as (H, W)."""
    if frame is None:
        return None
    if frame.ndim == 3 and frame.shape[0] == 1:
        frame = frame[0]
    if frame.ndim != 2 or tuple(frame.shape) != (height, width):
        raise ShapeError(f"{name} must have shape ({height}, {width}) or (1, {height}, {width}), "
                         f"got {tuple(frame.shape)}")
    return frame


def triangulate_leds(placements: Sequence[SphereCalibration]) -> tuple[Tensor, Tensor]:
    r"""LED positions from two or more perspective sphere placements (:func:`triangulate_rays`).

    Args:
        placements: perspective :class:`SphereCalibration` s of the same K LEDs.

    Returns:
        positions :math:`(K, 3)` mm, origin at the centre of projection (camera frame), and residuals
        :math:`(K,)` mm.

    Raises:
        InputError: ``placements`` that is not a sequence of :class:`SphereCalibration` (a tensor of directions or
            points: pass the calibrations themselves).
        CalibrationError: fewer than 2 placements, orthographic ones, different LED counts, parallel rays.

    Example:
        >>> positions, residuals = triangulate_leds([first, second])  # doctest: +SKIP
    """
    _check_placements(placements)
    if len(placements) < 2:
        raise CalibrationError(f"LED positions need at least 2 sphere placements, got {len(placements)}")
    points = [p.points_mm for p in placements if p.points_mm is not None]
    if len(points) != len(placements):
        raise CalibrationError("LED positions need perspective placements (intrinsics and the sphere's radius)")
    counts = {int(p.directions.shape[0]) for p in placements}
    if len(counts) != 1:
        raise CalibrationError(f"the sphere placements count different LEDs: {sorted(counts)}")
    origins = torch.stack(points, dim=1)
    directions = torch.stack([p.directions for p in placements], dim=1)
    return triangulate_rays(origins, directions)


def _check_placements(placements: object) -> None:
    """A sequence of :class:`SphereCalibration` (a list of tensors failed as a bare AttributeError on points_mm)."""
    if not isinstance(placements, Sequence):
        raise InputError(f"placements must be a sequence of SphereCalibration (calibrate_sphere's results), got "
                         f"{type(placements).__name__}")
    wrong = [i for i, p in enumerate(placements) if not isinstance(p, SphereCalibration)]
    if wrong:
        raise InputError(f"placements must each be a SphereCalibration (calibrate_sphere's results), got "
                         f"{type(placements[wrong[0]]).__name__} at index {wrong[0]}")


def card_distance_from_spheres(placements: Sequence[SphereCalibration]) -> float:
    """Distance from the centre of projection to the card plane, for spheres resting on the card.

    A sphere of radius R resting on the card has its centre R above it, so the card plane lies at
    ``z = centre_z - R`` in the camera frame; the mean over placements is returned (positive, mm).

    Raises:
        InputError: something that is not a sequence of :class:`SphereCalibration` (a list of tensors).
        CalibrationError: no placement, or one that is not perspective (no centre in space).

    Example:
        >>> card_distance_from_spheres([first, second])  # doctest: +SKIP
        40.0
    """
    _check_placements(placements)  # a list of tensors failed as a bare AttributeError on centre_mm
    spheres = [(p.centre_mm, p.radius_mm) for p in placements if p.centre_mm is not None and p.radius_mm is not None]
    if not placements or len(spheres) != len(placements):
        raise CalibrationError("the card's distance follows only from perspective placements")
    return float(sum(radius - float(centre[2]) for centre, radius in spheres) / len(spheres))
