"""Light and flat-field calibration.

- :mod:`~psmini.calibration.sphere`: the mirror sphere's silhouette (mask or automatic, sub-pixel circle fit),
  its centre in space (tangent cone), and light directions by reflecting the view ray, orthographic or
  perspective;
- :mod:`~psmini.calibration.highlights`: each LED's highlight, robust and sub-pixel;
- :mod:`~psmini.calibration.triangulate`: LED positions from two or more placements;
- :mod:`~psmini.calibration.mirror`: the above end to end (:func:`calibrate_sphere`, :func:`triangulate_leds`);
- :mod:`~psmini.calibration.reference`: the flat-field (card) reference, averaged, dark-subtracted, smoothed;
"""

from __future__ import annotations

from psmini.calibration.highlights import Highlights, locate_highlights
from psmini.calibration.mirror import SphereCalibration, calibrate_sphere, card_distance_from_spheres, triangulate_leds
from psmini.calibration.reference import CardReference, card_reference, polynomial_surface
from psmini.calibration.sphere import (
    SphereSilhouette,
    find_sphere,
    fit_circle,
    pixel_rays,
    reflect_orthographic,
    reflect_perspective,
    segment_sphere,
    silhouette_edges,
    sphere_centre_from_silhouette,
)
from psmini.calibration.triangulate import triangulate_rays

__all__ = [
    "SphereSilhouette",
    "fit_circle",
    "silhouette_edges",
    "segment_sphere",
    "find_sphere",
    "pixel_rays",
    "sphere_centre_from_silhouette",
    "reflect_orthographic",
    "reflect_perspective",
    "Highlights",
    "locate_highlights",
    "triangulate_rays",
    "SphereCalibration",
    "calibrate_sphere",
    "triangulate_leds",
    "card_distance_from_spheres",
    "CardReference",
    "card_reference",
    "polynomial_surface",
]
