"""The operation census of ``benchmarks/op_census.py`` on operations whose calls and bytes are known."""

import torch

from benchmarks.op_census import Census


def test_counts_calls_and_the_bytes_of_computing_calls_only():
    x, y = torch.ones(10, 4), torch.ones(10, 4)  # 40 float32 each: 160 bytes
    census = Census()
    with census:
        z = x * y  # reads two, writes one: 480 bytes
        row = z[0]  # a view: a call, no bytes
        total = z.sum()  # reads 160, writes 4
    assert float(total) == 40.0 and row.shape == (4,)
    assert sum(census.calls.values()) == 3
    assert sum(census.bytes.values()) == 480 + 160 + 4


def test_groups_by_the_psmini_function_that_called():
    from psmini.normals import normals_to_gradients

    normals = torch.nn.functional.normalize(torch.rand(1, 3, 4, 4) + 0.5, dim=1)
    census = Census()
    with census:
        normals_to_gradients(normals)
    assert census.calls and all(name.startswith("normals.py:") for name in census.calls)
