"""The result type every reconstruction returns."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

__all__ = ["Reconstruction"]


@dataclass
class Reconstruction:
    """What :class:`PhotometricStereo` returns; every field is batched.

    Attributes:
        albedo: :math:`(B, 1, H, W)`, relative to the card's albedo scale when flat-fielded.
        normals: unit normals :math:`(B, 3, H, W)`, camera frame.
        p: :math:`\\partial z / \\partial x`, :math:`(B, 1, H, W)`.
        q: :math:`\\partial z / \\partial y` (y up), :math:`(B, 1, H, W)`.
        depth: height toward the camera :math:`(B, 1, H, W)`, mm (pixel units when no pitch is known).
        mask: where a normal was solved, :math:`(B, 1, H, W)` bool.
    """

    albedo: Tensor
    normals: Tensor
    p: Tensor
    q: Tensor
    depth: Tensor
    mask: Tensor

    def to(self, device: torch.device | str) -> Reconstruction:
        """A copy with every field on ``device``."""
        return Reconstruction(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})
