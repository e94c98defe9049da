"""Analytic surfaces for tests: a hemisphere's normals and a Lambertian rendering written independently of psmini."""

from __future__ import annotations

import torch


def analytic_sphere(size: int, *, device=None, dtype=torch.float32, radius_fraction: float = 0.9):
    """Normals (1, 3, H, W), a mask (1, 1, H, W) of the sphere's disc and a smooth albedo (1, 1, H, W)."""
    coords = torch.linspace(-1, 1, size, device=device, dtype=dtype) / radius_fraction
    y, x = torch.meshgrid(-coords, coords, indexing="ij")
    r2 = x**2 + y**2
    inside = r2 < 1
    z = torch.sqrt((1 - r2).clamp_min(0))
    # normalised again: in about one process in seven on the 2-core Xeon the first sqrt of the process returned
    # values off by up to 4e-4 (sqrt(v)^2 - v), which left a few of these "unit" normals 2e-4 too long
    normals = torch.nn.functional.normalize(torch.stack([x, y, z]), dim=0) * inside
    normals[2][~inside] = 1
    albedo = (0.5 + 0.3 * x.clamp(-1, 1)).clamp(0.2, 1.0)
    return normals.unsqueeze(0), inside[None, None], albedo[None, None]


def render(normals, albedo, lights):
    """I_k = albedo * max(l_k · n, 0), lights (K, 3) scaled directions."""
    shading = torch.einsum("kc,bchw->bkhw", lights.to(normals), normals).clamp_min(0)
    return albedo * shading
