"""Shared helpers of the calibration tests: the rig's pinhole camera and exact mirror-sphere geometry."""

from __future__ import annotations

import torch
from torch import Tensor


def rig_intrinsics(config, dtype: torch.dtype = torch.float64) -> Tensor:
    """K of data_synth's sphere camera: focal length working distance / pixel pitch, centre of the image."""
    focal = config.working_distance_mm / config.pixel_pitch_mm
    centre = (config.size - 1) / 2
    return torch.tensor([[focal, 0.0, centre], [0.0, focal, centre], [0.0, 0.0, 1.0]], dtype=dtype)


def specular_points(camera: Tensor, centre: Tensor, radius: float, leds: Tensor, iterations: int = 200) -> Tensor:
    """Exact reflection points (K, 3) on a sphere: the normal bisects the unit vectors to camera and LED.

    Fixed-point iteration on the bisector, independent of the library's ray-sphere intersection.
    """
    camera, centre, leds = camera.double(), centre.double(), leds.double()
    normal = torch.nn.functional.normalize((leds + camera) / 2 - centre, dim=-1)
    for _ in range(iterations):
        point = centre + radius * normal
        to_camera = torch.nn.functional.normalize(camera - point, dim=-1)
        to_led = torch.nn.functional.normalize(leds - point, dim=-1)
        normal = torch.nn.functional.normalize(to_camera + to_led, dim=-1)
    return centre + radius * normal


def angle_deg(a: Tensor, b: Tensor) -> Tensor:
    """Angle between vectors (..., 3), degrees, accurate near 0."""
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1)))


def project(points: Tensor, intrinsics: Tensor) -> Tensor:
    """Pixels (u, v) of points (..., 3) in psmini's camera frame (origin at the centre of projection)."""
    depth = -points[..., 2]
    u = intrinsics[0, 0] * points[..., 0] / depth + intrinsics[0, 2]
    v = -intrinsics[1, 1] * points[..., 1] / depth + intrinsics[1, 2]
    return torch.stack([u, v], dim=-1)
