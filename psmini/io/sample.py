"""The one in-memory form of a photometric-stereo sample, whatever folder it came from."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from torch import Tensor, nn

__all__ = ["Sample"]


@dataclass
class Sample:
    """Images, lights, calibration frames and ground truth of one sample, as tensors on the CPU.

    Produced by :func:`psmini.io.load_sample` (and :func:`psmini.io.read_diligent`); consumed by
    ``psmini.pipeline.reconstruct``. Gray images in [0, 1] (colour data was converted with the DiLiGenT
    recipe: each channel divided by its light intensity, clamped at 0, weighted 0.2989/0.5870/0.1140).

    Attributes:
        name: the folder's name.
        images: one image per light, shape :math:`(K, H, W)`, ``float32`` in [0, 1] (DiLiGenT: divided by the
            light intensities, so values may exceed 1).
        lights: a module of :mod:`psmini.lights` with K lights (``DirectionalLights`` for DiLiGenT).
        mask: pixels to reconstruct, shape :math:`(1, H, W)` bool, or None for all.
        dark: all-LEDs-off frame, shape :math:`(1, H, W)`, or None.
        reference: flat-field (matte card) images under the same K lights, shape :math:`(K, H, W)`, or None.
        reference_dark: the card capture's dark frame, shape :math:`(1, H, W)`, or None.
        card_albedo: the card's albedo (1.0 when there is no reference).
        pixel_pitch_mm: size of one pixel on the object, mm, or None when unknown (DiLiGenT).
        normals_gt: ground-truth unit normals, shape :math:`(3, H, W)`, camera frame, or None.
        depth_gt: ground-truth height, shape :math:`(1, H, W)`, mm, NaN where undefined, or None.
        albedo_gt: ground-truth albedo, shape :math:`(1, H, W)`, or None.
        saturation_level: raw value (in the [0, 1] scale of ``images``) at or above which a pixel is saturated,
            or None when unknown.
        gt_mask: where the ground truth is valid, shape :math:`(1, H, W)` bool, or None (then ``mask`` applies).
        meta: everything else (source kind and path, bit depth, file names, light intensities, metadata).
    """

    name: str
    images: Tensor
    lights: nn.Module
    mask: Tensor | None = None
    dark: Tensor | None = None
    reference: Tensor | None = None
    reference_dark: Tensor | None = None
    card_albedo: float = 1.0
    pixel_pitch_mm: float | None = None
    normals_gt: Tensor | None = None
    depth_gt: Tensor | None = None
    albedo_gt: Tensor | None = None
    saturation_level: float | None = None
    gt_mask: Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def count(self) -> int:
        """Number of images (lights) K."""
        return int(self.images.shape[0])
