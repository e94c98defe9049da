"""``psmini batch``'s error paths that must fail before any work (the batch machinery: tests/test_batch.py)."""

from __future__ import annotations

import pytest

import psmini.batch
from data_synth.rig import write_synthetic_capture
from psmini.cli import main


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("captures")
    write_synthetic_capture(root, "jute", size=32, light_model="directional")
    return root


@pytest.mark.parametrize(("out", "message"), [
    ("results", "the output folder {tmp}/results exists and is not a folder"),
    ("results/run1", "cannot create the output folder {tmp}/results/run1: {tmp}/results is a file, not a folder"),
])
def test_output_under_a_file_fails_before_any_sample_is_solved(root, tmp_path, capsys, monkeypatch, out, message):
    """Every sample was solved (and failed to be written) before the summary's mkdir raised FileExistsError."""
    def no_work(*args, **kwargs):
        raise AssertionError("samples were solved although OUT cannot be written")

    monkeypatch.setattr(psmini.batch, "_local_chunks", no_work)
    (tmp_path / "results").write_text("a file")
    assert main(["batch", str(root), "--out", str(tmp_path / out), "--workers", "0", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == f"psmini batch: error: {message.format(tmp=tmp_path)}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]
