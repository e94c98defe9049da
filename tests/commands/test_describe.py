"""``psmini describe``'s error paths on a corrupt reconstruction folder: one line, no traceback (the measurements'
own tests: tests/test_fabric_cli.py)."""

from __future__ import annotations

import numpy as np
import torch

from psmini.cli import main
from psmini.io import write_outputs


def _reconstruction(folder):
    size = 32
    result = {"albedo": torch.full((1, 1, size, size), 0.5), "normals": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
              .expand(1, 3, size, size), "depth": torch.zeros(1, 1, size, size),
              "mask": torch.ones(1, 1, size, size, dtype=torch.bool)}
    write_outputs(folder, result, pixel_pitch_mm=0.025)
    return folder


def test_corrupt_reconstruction_files(tmp_path, capsys):
    """An empty depth.npy raised numpy's EOFError and an outputs.json holding a list an AttributeError: tracebacks."""
    out = _reconstruction(tmp_path / "rec")
    (out / "outputs.json").write_text("[1, 2]")
    assert main(["describe", str(out)]) == 1
    err = capsys.readouterr().err
    assert "outputs.json must hold a JSON object, got list" in err and "Traceback" not in err
    (out / "depth.npy").write_bytes(np.zeros(4).tobytes()[:0])
    assert main(["describe", str(out)]) == 1
    err = capsys.readouterr().err
    assert "cannot read depth" in err and "depth.npy: the file is empty" in err and "Traceback" not in err
