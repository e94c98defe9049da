"""Chunks of a batch on the CPU: one capture's worth of observations at a time.

On the CPU every new tensor of more than 32 MB (glibc's largest ``mmap`` threshold: an (8, 8, 400, 400) float32
batch is 41 MB) is fresh memory from the kernel, page-faulted and zeroed on first touch: the dark subtraction of
such a batch measured 32 ms (4 ms per capture) where the same arithmetic on one capture's 5 MB at a time took
0.7-1.4 ms per capture in the same profile, and near light on a batch of 16 captures ran 1.4 times slower per
sample than single calls (its working set leaves the caches). Solving a CPU batch capture by capture keeps every
temporary in the heap and in the caches; devices, whose allocators cache, take the whole batch at once.
"""

from __future__ import annotations

from typing import overload

from torch import Tensor

from psmini.errors import ShapeError

#: Observations (B · K · H · W) solved at once on the CPU: one 8 × 400 × 400 capture.
CPU_CHUNK_ELEMENTS = 8 * 400 * 400


def chunks(batch: Tensor) -> list[slice]:
    """The chunks of ``batch`` (its first dimension the batch items): one slice of them all off the CPU; on the
    CPU, consecutive slices of as many items as :data:`CPU_CHUNK_ELEMENTS` holds (at least one each)."""
    items = batch.shape[0]
    if batch.device.type != "cpu" or items <= 1:
        return [slice(0, items)]
    size = max(1, CPU_CHUNK_ELEMENTS // max(1, batch[0].numel()))
    return [slice(start, min(start + size, items)) for start in range(0, items, size)]


@overload
def batch_part(x: Tensor, images: Tensor, part: slice, name: str) -> Tensor: ...
@overload
def batch_part(x: None, images: Tensor, part: slice, name: str) -> None: ...
@overload
def batch_part(x: Tensor | None, images: Tensor, part: slice, name: str) -> Tensor | None: ...
def batch_part(x: Tensor | None, images: Tensor, part: slice, name: str) -> Tensor | None:
    """``x[part]`` when ``x`` is a 4-D tensor with an item per item of the batch ``images``, ``x`` itself otherwise
    (``None``, or one frame or stack broadcast over the batch).

    Raises:
        ShapeError: for a 4-D ``x`` of neither 1 nor ``images``' count of items (a chunk would hide the mismatch).
    """
    if x is None or x.ndim != 4:
        return x
    if x.shape[0] not in (1, images.shape[0]):
        raise ShapeError(f"{name} must broadcast to the images' shape {tuple(images.shape)} (1 or "
                         f"{images.shape[0]} items), got {tuple(x.shape)}")
    return x if x.shape[0] == 1 else x[part]
