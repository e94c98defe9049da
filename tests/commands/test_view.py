"""``psmini view``: the reconstruction as an offline WebGL page, drawn by a real (headless) browser."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
import torch

from psmini.cli import main
from psmini.io import write_outputs

plotly = pytest.importorskip("plotly", reason="psmini view needs plotly (the viz extra)")

SIZE = 64


@pytest.fixture
def out(tmp_path):
    """A reconstruction folder: a 0.3 mm bump on a 1.6 mm field, albedo dark on the left half, bright on the right."""
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    depth = 0.3 * np.exp(-((rows - SIZE / 2) ** 2 + (cols - SIZE / 2) ** 2) / (2 * (SIZE / 6) ** 2))
    albedo = np.where(cols < SIZE / 2, 0.25, 0.9).astype(np.float32)
    mask = np.ones((SIZE, SIZE), bool)
    mask[:4, :4] = False  # an unsolved corner
    result = {"albedo": torch.from_numpy(albedo)[None, None], "normals": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
              .expand(1, 3, SIZE, SIZE), "depth": torch.from_numpy(depth)[None, None],
              "mask": torch.from_numpy(mask)[None, None]}
    write_outputs(tmp_path / "out", result, pixel_pitch_mm=0.025)
    return tmp_path / "out"


def test_writes_a_self_contained_page(out, tmp_path, capsys):
    assert main(["view", str(out), "--html", str(tmp_path / "view.html"), "--json"]) == 0
    page = (tmp_path / "view.html").read_text(encoding="utf-8")
    # plotly.js is inlined: no script is fetched from anywhere
    assert not re.search(r"<script[^>]+src=", page) and len(page) > 1_000_000
    assert '"type":"mesh3d"' in page.replace(" ", "")
    assert '"pixel_pitch_mm": 0.025' in capsys.readouterr().out


def test_errors(tmp_path, capsys):
    assert main(["view", str(tmp_path / "missing")]) == 1
    assert "not a folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--html", str(tmp_path / "x.html")]) == 1
    assert "no depth.npy" in capsys.readouterr().err


def test_corrupt_reconstruction_files(out, tmp_path, capsys):
    """An empty depth.npy raised numpy's EOFError and an outputs.json holding a list an AttributeError: tracebacks."""
    (out / "outputs.json").write_text("[1, 2]")
    assert main(["view", str(out), "--html", str(tmp_path / "x.html")]) == 1
    err = capsys.readouterr().err
    assert "outputs.json must hold a JSON object, got list" in err and "Traceback" not in err
    (out / "depth.npy").write_bytes(b"")
    assert main(["view", str(out), "--html", str(tmp_path / "x.html")]) == 1
    err = capsys.readouterr().err
    assert "cannot read depth" in err and "depth.npy: the file is empty" in err and "Traceback" not in err
    assert not (tmp_path / "x.html").exists()


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow
@pytest.mark.skipif(_chromium() is None, reason="Chromium is not installed (.ci/run installs Debian's as root)")
def test_headless_chromium_draws_the_surface(out, tmp_path):
    """The page, opened offline in headless Chromium (software WebGL), shows the surface with its albedo: a large
    area of dark neutral gray (the dark half of the cloth; plotly's own page has only white, its bluish axes
    background and bluish text), lying left of the bright half as the albedo says."""
    page = tmp_path / "view.html"
    assert main(["view", str(out), "--html", str(page)]) == 0
    shot = tmp_path / "shot.png"
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'profile'}",
             # WebGL without a GPU is SwiftShader, which newer Chromium enables only on request (trusted page)
             "--enable-unsafe-swiftshader", "--window-size=800,760", "--virtual-time-budget=8000",
             f"--screenshot={shot}"]
    run = subprocess.run([_chromium(), *flags, page.as_uri()], capture_output=True, text=True, timeout=120)
    assert shot.is_file(), f"Chromium wrote no screenshot (exit {run.returncode}): {run.stderr[-2000:]}"
    import cv2

    rgb = cv2.imread(str(shot))[..., ::-1].astype(int)
    neutral = (np.ptp(rgb, axis=2) <= 6)
    dark = neutral & (rgb.mean(axis=2) < 140) & (rgb.mean(axis=2) > 20)
    bright = neutral & (rgb.mean(axis=2) >= 140) & (rgb.mean(axis=2) < 245)
    assert dark.mean() > 0.05, f"the dark half of the surface is not drawn ({dark.mean():.1%} dark gray pixels)"
    assert bright.mean() > 0.05, f"the bright half of the surface is not drawn ({bright.mean():.1%})"
    dark_x, bright_x = np.nonzero(dark)[1].mean(), np.nonzero(bright)[1].mean()
    assert dark_x < bright_x, "the dark albedo (left half of the image) is not drawn left of the bright one"


def test_default_page_goes_into_out_and_no_browser_without_a_display(out, capsys, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    opened = []
    monkeypatch.setattr("webbrowser.open", opened.append)
    assert main(["view", str(out)]) == 0
    assert (out / "view.html").is_file() and opened == []
    assert "no display here" in capsys.readouterr().out
