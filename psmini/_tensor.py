"""Small tensor helpers shared by the maths modules."""

from __future__ import annotations

import torch
from torch import Tensor


def vector_length(x: Tensor, dim: int, keepdim: bool = True) -> Tensor:
    """The Euclidean length of ``x`` along ``dim``, as the square root of the summed squares.

    ``torch.linalg.vector_norm`` (and ``Tensor.norm``) along a dimension that is not the innermost one runs 25-45
    times slower on torch's CPU build than these three passes: 182 ms against 4 ms for the light vectors of one
    8 × 400 × 400 capture, (1, 8, 3, 400, 400) along dim 2, on one thread. The square root's argument is kept at the
    smallest normal number, so that a zero vector has length ~1e-19 (float32) and a finite gradient.

    Example:
        >>> vector_length(torch.tensor([[3.0, 4.0]]), dim=1)
        tensor([[5.]])
    """
    return x.square().sum(dim=dim, keepdim=keepdim).clamp_min(torch.finfo(x.dtype).tiny).sqrt()
