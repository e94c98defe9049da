"""The result type every reconstruction returns."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

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

    def show(self, pixel_pitch_mm: float | None = None, *, index: int = 0, exaggeration: float = 1.0,
             max_size: int = 300):
        """The surface of batch item ``index`` as an interactive 3D view (plotly, WebGL), coloured by albedo.

        In Jupyter the returned figure draws itself as the cell's output; elsewhere call ``.show()`` on it or
        write it with :func:`psmini.viz.write_html` (one offline file). Needs plotly (the ``viz`` extra).

        Args:
            pixel_pitch_mm: the sample's pixel pitch (``sample.pixel_pitch_mm``) when the depth is in mm; None when
                the depth is in pixel units (no pitch known, e.g. DiLiGenT), so that proportions are true.
            index: which item of the batch.
            exaggeration: vertical exaggeration (1: true proportions; the title says which).
            max_size: the most vertices along the longer side (the grid is subsampled by a whole stride).

        Returns:
            a ``plotly.graph_objects.Figure`` (see :func:`psmini.viz.surface_figure`).

        Raises:
            InputError: plotly missing, nothing solved, an index outside the batch.

        Example:
            >>> result.show(sample.pixel_pitch_mm)  # doctest: +SKIP
        """
        from psmini.viz import surface_figure

        index = self._batch_index(index)
        return surface_figure(self.depth[index], self.albedo[index], self.mask[index], pixel_pitch_mm,
                              exaggeration=exaggeration, max_size=max_size)

    def item(self, index: int) -> Reconstruction:
        """Item ``index`` of the batch as a batch of one, of the same type: every tensor field sliced along its
        first dimension (a near-light result's counts and flags kept as they are).

        Raises:
            InputError: an index outside the batch.

        Example:
            >>> import torch
            >>> zeros = torch.zeros(2, 1, 4, 4)
            >>> batch = Reconstruction(zeros, zeros.expand(2, 3, 4, 4), zeros, zeros, zeros, zeros > 0)
            >>> batch.item(1).normals.shape
            torch.Size([1, 3, 4, 4])
        """
        index = self._batch_index(index)
        return replace(self, **{f.name: getattr(self, f.name)[index : index + 1] for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})

    def _batch_index(self, index: int) -> int:
        """``index`` as a position in the batch (negative ones count from its end); InputError outside it."""
        from psmini.errors import InputError

        batch = self.depth.shape[0]
        if not -batch <= index < batch:
            raise InputError(f"index {index} is outside the batch of {batch}")
        return index % batch

    def to(self, device: torch.device | str) -> Reconstruction:
        """A copy of the same type with every tensor field on ``device`` (the others, such as a near-light result's
        iteration count, as they are)."""
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})
