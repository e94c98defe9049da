"""The MAT v5 reader against SciPy's ``loadmat`` (an independent implementation), and its error paths."""

from __future__ import annotations

import numpy as np
import pytest

from psmini import DataFormatError
from psmini.io.matfile import read_mat
from tests.conftest import shared_data

scipy_io = pytest.importorskip("scipy.io", reason="SciPy (a dev extra) is the independent reference")

VARIABLES = {
    "double": np.random.default_rng(0).random((3, 4, 5)),
    "single": np.float32([[1.5, -2.0]]),
    "int16": np.arange(6, dtype=np.int16).reshape(2, 3),
    "uint8": np.array([[0, 7, 255]], dtype=np.uint8),
    "complex": np.array([[1 + 2j, 3 - 4j]]),
    "logical": np.array([[True, False, True]]),
    "empty": np.zeros((0, 3)),
    "text": "skipped",
}


@pytest.mark.parametrize("compressed", [False, True], ids=["v6", "v7-compressed"])
def test_matches_scipy(tmp_path, compressed):
    path = tmp_path / "x.mat"
    scipy_io.savemat(path, VARIABLES, do_compression=compressed)
    ours, theirs = read_mat(path), scipy_io.loadmat(path)
    assert set(ours) == set(VARIABLES) - {"text"}
    for name, array in ours.items():
        np.testing.assert_array_equal(array, theirs[name], err_msg=name)
        assert array.shape == theirs[name].shape
    assert ours["logical"].dtype == bool and ours["int16"].dtype == np.int16 and ours["complex"].dtype == complex


@pytest.mark.parametrize("name", ["ball", "cat"])
def test_diligent_normal_gt_matches_scipy(name):
    path = shared_data("DiLiGenT", name, "Normal_gt.mat")
    ours = read_mat(path)["Normal_gt"]
    np.testing.assert_array_equal(ours, scipy_io.loadmat(path)["Normal_gt"])
    assert ours.shape == (512, 612, 3) and ours.dtype == np.float64


def test_stored_in_smaller_type_keeps_class():
    # light.mat stores mu (class double) as uint8 bytes: MATLAB, and read_mat, give doubles
    path = shared_data("near_ps_rig", "light.mat")
    ours = read_mat(path)
    assert ours["mu"].dtype == np.float64
    for key in ("S", "Dir", "Phi", "mu"):
        np.testing.assert_array_equal(ours[key], scipy_io.loadmat(path, mat_dtype=True)[key])


def test_missing_file(tmp_path):
    with pytest.raises(DataFormatError, match="does not exist"):
        read_mat(tmp_path / "none.mat")


def test_not_a_mat_file(tmp_path):
    (tmp_path / "x.mat").write_bytes(b"hello" * 40)
    with pytest.raises(DataFormatError, match="not a level-5 MAT-file"):
        read_mat(tmp_path / "x.mat")


def test_v73_is_refused(tmp_path):
    header = b"MATLAB 7.3 MAT-file".ljust(124, b" ") + b"\x00\x02IM"
    (tmp_path / "x.mat").write_bytes(header + b"\x89HDF\r\n")
    with pytest.raises(DataFormatError, match="v7.3"):
        read_mat(tmp_path / "x.mat")


@pytest.mark.parametrize("compressed", [False, True])
def test_truncated(tmp_path, compressed):
    path = tmp_path / "x.mat"
    scipy_io.savemat(path, {"a": np.random.default_rng(1).random((50, 50))}, do_compression=compressed)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])
    with pytest.raises(DataFormatError, match="corrupt MAT-file"):
        read_mat(path)
