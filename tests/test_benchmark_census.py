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


def test_a_clone_named_psmini_does_not_make_its_environment_the_library(tmp_path):
    """A clone in a folder named psmini holds its virtual environment: torch's files there are not psmini's."""
    torch_file = tmp_path / "psmini" / ".venv" / "lib" / "python3.11" / "site-packages" / "torch" / "helper.py"
    namespace: dict = {}
    exec(compile("def double(x):\n    return x * 2\n", str(torch_file), "exec"), namespace)
    census = Census()
    with census:
        namespace["double"](torch.ones(3))
    assert list(census.calls) == ["(outside psmini)"]


def test_library_files_are_named_from_the_package_root():
    import psmini.integrate.poisson
    from benchmarks.op_census import library_file

    assert library_file(psmini.integrate.poisson.__file__) == "integrate/poisson.py"
    assert library_file(torch.__file__) is None
