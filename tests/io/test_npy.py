"""``.npy`` reading and atomic writing: every failure a DataFormatError naming the file, nothing half-written."""

from __future__ import annotations

import numpy as np
import pytest

from psmini.errors import DataFormatError
from psmini.io import _npy
from psmini.io._npy import read_npy, save_npy


def test_round_trip_and_numpy_suffix_rule(tmp_path):
    array = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert save_npy(tmp_path / "a.npy", array) == tmp_path / "a.npy"
    np.testing.assert_array_equal(read_npy(tmp_path / "a.npy"), array)
    assert save_npy(tmp_path / "b", array) == tmp_path / "b.npy"  # as np.save: .npy appended
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy", "b.npy"]


@pytest.mark.parametrize(("content", "message"), [
    (b"", "empty or cut short"),
    (None, "cut short|Failed to read all data"),  # half of a valid file
    (b"not an array at all", "cannot read depth"),
])
def test_unreadable_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "depth.npy"
    if content is None:
        np.save(path, np.zeros((16, 16), np.float32))
        content = path.read_bytes()[:300]
    path.write_bytes(content)
    with pytest.raises(DataFormatError, match=message) as caught:
        read_npy(path, "depth")
    assert str(path) in str(caught.value)


def test_missing_folder_and_archive(tmp_path):
    with pytest.raises(DataFormatError, match="mask file .* does not exist"):
        read_npy(tmp_path / "nowhere.npy", "mask")
    with pytest.raises(DataFormatError, match="is not a file"):
        read_npy(tmp_path, "mask")
    np.savez(tmp_path / "a.npz", x=np.zeros(3))
    (tmp_path / "a.npz").rename(tmp_path / "a.npy")
    with pytest.raises(DataFormatError, match="npz archive"):
        read_npy(tmp_path / "a.npy")


def test_save_refuses_a_folder_and_a_path_under_a_file(tmp_path):
    (tmp_path / "d.npy").mkdir()
    with pytest.raises(DataFormatError, match="is a folder"):
        save_npy(tmp_path / "d.npy", np.zeros(3))
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataFormatError, match="cannot create its folder"):
        save_npy(tmp_path / "file" / "x.npy", np.zeros(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npy", "file"]


def test_interrupted_write_keeps_the_old_file_and_leaves_nothing(tmp_path, monkeypatch):
    path = tmp_path / "depth.npy"
    save_npy(path, np.ones(4))

    def dies_half_way(stream, array):
        stream.write(b"\x93NUMPY half")
        raise KeyboardInterrupt

    monkeypatch.setattr(_npy.np, "save", dies_half_way)
    with pytest.raises(KeyboardInterrupt):
        save_npy(path, np.zeros(4))
    monkeypatch.undo()
    np.testing.assert_array_equal(np.load(path), np.ones(4))
    assert [p.name for p in tmp_path.iterdir()] == ["depth.npy"]


def test_disk_error_becomes_a_data_format_error(tmp_path, monkeypatch):
    def disk_full(stream, array):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_npy.np, "save", disk_full)
    with pytest.raises(DataFormatError, match=r"cannot write .*x\.npy: .*No space left"):
        save_npy(tmp_path / "x.npy", np.zeros(4))
    assert list(tmp_path.iterdir()) == []
