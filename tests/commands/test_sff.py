"""``psmini sff``'s error paths: an unreadable stack or an unwritable output ends with one line, no traceback,
and no half-written map (the method's own tests: tests/test_sff.py)."""

from __future__ import annotations

import numpy as np
import pytest

from psmini.cli import main
from tests.commands._cli import fails_in_one_line


@pytest.fixture
def stack(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "stack.npy", rng.random((5, 16, 16)).astype(np.float32))
    return tmp_path / "stack.npy"


def test_empty_cut_or_missing_stack(tmp_path, capsys, stack):
    out = str(tmp_path / "d.npy")
    (tmp_path / "empty.npy").write_bytes(b"")
    fails_in_one_line(capsys, ["sff", str(tmp_path / "empty.npy"), "--out", out], "focus stack", "empty.npy", "empty")
    (tmp_path / "cut.npy").write_bytes(stack.read_bytes()[:500])
    fails_in_one_line(capsys, ["sff", str(tmp_path / "cut.npy"), "--out", out], "focus stack", "cut.npy")
    fails_in_one_line(capsys, ["sff", str(tmp_path / "nowhere.npy"), "--out", out], "nowhere.npy", "does not exist")
    assert not (tmp_path / "d.npy").exists()


def test_unwritable_output(tmp_path, capsys, stack):
    (tmp_path / "results").write_text("a file")
    fails_in_one_line(capsys, ["sff", str(stack), "--window", "3", "--out", str(tmp_path / "results" / "d.npy")],
           "cannot write", "results")
    (tmp_path / "d.npy").mkdir()
    fails_in_one_line(capsys, ["sff", str(stack), "--window", "3", "--out", str(tmp_path / "d.npy")], "is a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npy", "results", "stack.npy"]


def test_writes_as_numpy_would(tmp_path, stack):
    assert main(["sff", str(stack), "--window", "3", "--out", str(tmp_path / "depth"),
                 "--reliability", str(tmp_path / "r.npy")]) == 0
    assert np.load(tmp_path / "depth.npy").shape == (16, 16) and np.load(tmp_path / "r.npy").shape == (16, 16)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.npy", "r.npy", "stack.npy"]


def test_unwritable_reliability_leaves_no_depth(tmp_path, capsys, stack):
    # the depth map was written whole, then the run failed on the reliability map's path
    (tmp_path / "r.npy").mkdir()
    fails_in_one_line(capsys, ["sff", str(stack), "--window", "3", "--out", str(tmp_path / "d.npy"), "--reliability",
                    str(tmp_path / "r.npy")], "r.npy is a folder")
    assert not (tmp_path / "d.npy").exists()
