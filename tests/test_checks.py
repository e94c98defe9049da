"""Internal guards of psmini._checks that other tests do not reach directly."""

from __future__ import annotations

import pytest
import torch

from psmini._checks import all_true, any_true


@pytest.mark.parametrize("shape", [(4, 8, 40, 40), (1, 1, 3, 5), (0, 3), (7,)])
def test_all_and_any_agree_with_torch(shape):
    gen = torch.Generator().manual_seed(0)
    for share in (0.0, 0.5, 0.999, 1.0):
        mask = torch.rand(shape, generator=gen) < share
        views = [mask, mask.expand(2, *shape)[1], mask.transpose(0, -1)] if mask.ndim > 1 else [mask]
        for view in views:
            assert all_true(view) is bool(view.all()) and any_true(view) is bool(view.any())
        for other in (mask.float(), mask.to(torch.uint8)):  # other dtypes go through torch's own reductions
            assert all_true(other) is bool(other.all()) and any_true(other) is bool(other.any())


def test_a_single_false_or_true_is_found():
    mask = torch.ones(4, 8, 400, 400, dtype=torch.bool)
    mask[3, 7, 399, 399] = False
    assert not all_true(mask) and any_true(mask)
    mask.zero_()[2, 5, 0, 0] = True
    assert any_true(mask) and not all_true(mask)
