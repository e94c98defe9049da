"""``psmini integrate``'s error paths: unreadable inputs and unwritable outputs end with one line, no traceback,
and no half-written depth (the method's own tests: tests/test_integrate_cli.py)."""

from __future__ import annotations

import numpy as np
import pytest

from psmini.cli import main
from tests.commands._cli import fails_in_one_line


@pytest.fixture
def normals(tmp_path):
    flat = np.zeros((8, 8, 3), np.float32)
    flat[..., 2] = 1.0
    np.save(tmp_path / "n.npy", flat)
    return tmp_path / "n.npy"


def test_empty_or_missing_inputs(tmp_path, capsys, normals):
    (tmp_path / "empty.npy").write_bytes(b"")
    out = str(tmp_path / "d.npy")
    fails_in_one_line(capsys, ["integrate", str(tmp_path / "empty.npy"), "--out", out], "normals", "empty.npy", "empty")
    fails_in_one_line(capsys, ["integrate", str(normals), "--mask", str(tmp_path / "empty.npy"), "--out", out],
           "mask", "empty.npy", "empty")
    fails_in_one_line(capsys, ["integrate", str(normals), "--mask", str(tmp_path / "nowhere.npy"), "--out", out],
           "mask file", "nowhere.npy", "does not exist")
    np.save(tmp_path / "flat.npy", np.ones(8))
    fails_in_one_line(capsys, ["integrate", str(normals), "--mask", str(tmp_path / "flat.npy"), "--out", out],
           "mask", "the normals 8x8")
    assert not (tmp_path / "d.npy").exists()


def test_unwritable_output(tmp_path, capsys, normals):
    (tmp_path / "results").write_text("a file")
    fails_in_one_line(capsys, ["integrate", str(normals), "--out", str(tmp_path / "results" / "d.npy")],
           "cannot write", "results")
    (tmp_path / "d.npy").mkdir()
    fails_in_one_line(capsys, ["integrate", str(normals), "--out", str(tmp_path / "d.npy")], "is a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npy", "n.npy", "results"]


def test_output_written_whole(tmp_path, capsys, normals, monkeypatch):
    """The depth goes through a temporary file: a run stopped while writing leaves no .npy that looks complete."""
    import psmini.io._npy as npy

    def interrupted(stream, array):
        stream.write(b"\x93NUMPY")
        raise KeyboardInterrupt

    monkeypatch.setattr(npy.np, "save", interrupted)
    assert main(["integrate", str(normals), "--out", str(tmp_path / "out" / "d.npy")]) == 130
    monkeypatch.undo()
    assert list((tmp_path / "out").iterdir()) == []
    assert main(["integrate", str(normals), "--out", str(tmp_path / "out" / "d.npy")]) == 0
    assert np.load(tmp_path / "out" / "d.npy").shape == (8, 8)
