"""``psmini integrate``: normal maps from .npy and PNG to depth files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from psmini.cli import main
from tests.conftest import shared_data


def _sphere_normals(size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    row, col = np.mgrid[0:size, 0:size]
    x, y = (col - (size - 1) / 2) / (size / 2), -(row - (size - 1) / 2) / (size / 2)
    inside = x**2 + y**2 < 0.8
    z = np.sqrt(np.clip(1 - x**2 - y**2, 1e-6, None))
    return np.stack([x, y, z], -1).astype(np.float32), inside


def test_npy_orthographic(tmp_path, capsys):
    normals, inside = _sphere_normals()
    np.save(tmp_path / "n.npy", normals.transpose(2, 0, 1))  # (3, H, W) is accepted too
    np.save(tmp_path / "m.npy", inside)
    out = tmp_path / "depth.npy"
    assert main(["integrate", str(tmp_path / "n.npy"), "--mask", str(tmp_path / "m.npy"), "--pixel-pitch", "0.5",
                 "--out", str(out), "--json"]) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["method"] == "masked" and record["shape"] == [48, 48] and record["output"] == str(out)
    depth = np.load(out)
    assert depth.shape == (48, 48) and np.isnan(depth[~inside]).all() and np.isfinite(depth[inside]).all()
    # A sphere of radius 12 mm (24 px at 0.5 mm): the centre stands above the rim.
    assert depth[24, 24] - depth[inside].min() > 5.0


def test_diligent_png_perspective(tmp_path, capsys):
    folder = shared_data("DiLiGenT_depth", "cow")
    out = tmp_path / "cow.npy"
    assert main(["integrate", str(folder / "normal_map.png"), "--mask", str(folder / "mask.png"),
                 "--intrinsics", str(folder / "K.txt"), "--out", str(out), "--json"]) == 0
    depth, gt = np.load(out), np.load(folder / "depth_gt.npz")["depth_gt"]
    sel = np.isfinite(depth) & np.isfinite(gt)
    assert (depth[sel] > 0).all()
    scale = np.median(gt[sel] / depth[sel])
    assert np.abs(depth[sel] * scale - gt[sel]).mean() < 0.5  # mm; 0.17 measured


@pytest.mark.parametrize(
    "extra, message",
    [(["--out", "x.png"], ".npy"), (["--out", "d.npy", "--method", "nope"], None)],
)
def test_errors(tmp_path, capsys, extra, message):
    normals, _ = _sphere_normals(8)
    np.save(tmp_path / "n.npy", normals)
    if message is None:
        with pytest.raises(SystemExit):
            main(["integrate", str(tmp_path / "n.npy"), *extra])
    else:
        assert main(["integrate", str(tmp_path / "n.npy"), *extra]) == 1
        assert message in capsys.readouterr().err


def test_bad_normals_file(tmp_path, capsys):
    np.save(tmp_path / "n.npy", np.zeros((8, 8, 2), np.float32))
    assert main(["integrate", str(tmp_path / "n.npy"), "--out", str(tmp_path / "d.npy")]) == 1
    assert "(H, W, 3)" in capsys.readouterr().err
