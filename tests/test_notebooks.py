"""Every notebook in notebooks/ runs top to bottom (stored without outputs; executed here with nbclient), and the
gallery script runs; so neither can rot. Needs the ``dev`` extra (nbclient, nbformat, ipykernel,
matplotlib); skipped without it."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


@pytest.fixture(autouse=True)
def kernel_threads(monkeypatch):
    """A notebook's kernel, a process of its own, takes this process's share of the cores (one per xdist worker on
    two cores: conftest), not every core while the other workers use them."""
    import torch

    monkeypatch.setenv("OMP_NUM_THREADS", str(torch.get_num_threads()))


def test_notebooks_are_stored_without_outputs():
    nbformat = pytest.importorskip("nbformat")
    assert len(NOTEBOOKS) >= 5
    for path in NOTEBOOKS:
        notebook = nbformat.read(path, as_version=4)
        stored = [i for i, cell in enumerate(notebook.cells) if cell.get("outputs") or cell.get("execution_count")]
        assert not stored, f"{path.name}: cells {stored} were committed with outputs; clear them"


def _execute(path: Path, cwd: Path):
    """Run the notebook with ``cwd`` as its folder (as Jupyter does); a cell that raises fails the test."""
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    pytest.importorskip("matplotlib")
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(cwd)}})
    start = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as error:
        pytest.fail(f"{path.name}: a cell raised:\n{error}", pytrace=False)
    print(f"{path.name}: {time.perf_counter() - start:.1f} s")
    return notebook


def _text(notebook) -> str:
    return "\n".join(output.get("text", "") for cell in notebook.cells for output in cell.get("outputs", []))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, tmp_path: Path, monkeypatch):
    # what the notebook writes goes to $PSMINI_OUTPUTS (here a temporary folder, not the working tree)
    monkeypatch.setenv("PSMINI_OUTPUTS", str(tmp_path / "outputs"))
    _execute(path, path.parent)


@pytest.mark.slow
def test_quick_start_writes_where_the_reader_can_open_it(tmp_path: Path, monkeypatch):
    """Run from a copy outside the repository (no pyproject.toml above it), with the outputs in a folder that
    outlives the run: the files it lists are there afterwards."""
    copy = tmp_path / "elsewhere" / "01_quick_start.ipynb"
    copy.parent.mkdir()
    copy.write_bytes((ROOT / "notebooks" / "01_quick_start.ipynb").read_bytes())
    monkeypatch.delenv("PSMINI_OUTPUTS", raising=False)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    notebook = _execute(copy, copy.parent)
    out = copy.parent / "outputs"
    assert {p.name for p in (out / "quick_start_jute").iterdir()} >= {"depth.png", "mesh.ply", "points.ply"}
    assert str(out / "quick_start_jute") in _text(notebook)


@pytest.mark.slow
def test_diligent_notebook_without_data_says_where_to_point_it(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("PSMINI_DATA", str(tmp_path / "no-data"))
    notebook = _execute(ROOT / "notebooks" / "02_diligent.ipynb", ROOT / "notebooks")
    assert "set PSMINI_DATA" in _text(notebook)


@pytest.mark.slow
def test_gallery_script_runs(tmp_path: Path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "gallery"
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "make_gallery.py"), "--size", "48", "--out", str(out),
                           "--data-root", str(tmp_path / "no-data")], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    written = sorted(p.name for p in out.glob("*.png"))
    assert written == ["fabrics.png", "focus.png", "nearlight.png"], written
    assert "DiLiGenT" in done.stdout  # says that the real-data figure was skipped, and why
