import json

import numpy as np
import pytest
import torch

from psmini.cli import main


def _last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_synth_writes_sample_and_card(tmp_path, capsys):
    assert main(["synth", "twill", "--out", str(tmp_path), "--size", "40", "--no-noise", "--seed", "3", "--json"]) == 0
    report = _last_json(capsys)
    manifest = json.loads((tmp_path / "twill" / "capture.json").read_text())
    assert manifest["kind"] == "sample" and manifest["flatfield"]["path"] == "../card"
    assert manifest["lights"]["model"] == "led" and manifest["metadata"]["seed"] == 3
    assert json.loads((tmp_path / "card" / "capture.json").read_text())["kind"] == "flatfield"
    assert report["sample"].endswith("twill")


def test_synth_directional_and_errors(tmp_path, capsys):
    assert main(["synth", "silk", "--out", str(tmp_path), "--size", "32", "--light-model", "directional"]) == 0
    assert json.loads((tmp_path / "silk" / "capture.json").read_text())["lights"]["model"] == "directional"
    assert main(["synth", "silk", "--out", str(tmp_path), "--size", "32"]) == 1  # exists, no --overwrite
    assert "exists" in capsys.readouterr().err
    assert main(["synth", "satin", "--out", str(tmp_path), "--size", "32", "--light-model", "directional"]) == 0
    assert "kept" in capsys.readouterr().out  # the card of the same rig, shared
    assert main(["synth", "satin", "--out", str(tmp_path), "--size", "32", "--overwrite"]) == 0  # another rig
    assert "wrote" in capsys.readouterr().out.splitlines()[-1]
    with pytest.raises(SystemExit):
        main(["synth", "denim", "--out", str(tmp_path)])


def test_synth_lift_orientation_and_bit_depth(tmp_path, capsys):
    """The capture as the benchmarks render it (8 bits, the cloth lifted, the yarns turned): in the manifest and
    the ground truth; a negative lift is refused before anything is written."""
    args = ["synth", "net", "--out", str(tmp_path), "--size", "48", "--lift", "0.5", "--orientation", "30",
            "--bit-depth", "8", "--seed", "2"]
    assert main(args) == 0 and "8-bit, 0.5 mm above the card" in capsys.readouterr().out
    manifest = json.loads((tmp_path / "net" / "capture.json").read_text())
    assert manifest["bit_depth"] == 8 and manifest["metadata"]["height_offset_mm"] == 0.5
    assert manifest["metadata"]["fabric_params"]["orientation_deg"] == 30.0
    from data_synth import make_fabric
    from psmini.io import load_sample

    truth = make_fabric("net", size=48, seed=2, orientation_deg=30.0).height_mm[0]
    assert torch.allclose(load_sample(tmp_path / "net").depth_gt, truth + 0.5)
    assert main(["synth", "knit", "--out", str(tmp_path / "low"), "--size", "32", "--lift", "-0.2"]) == 1
    assert "lift above the card" in capsys.readouterr().err and not (tmp_path / "low" / "knit").exists()


@pytest.mark.slow
def test_demo_reconstructs_and_scores(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "64", "--fabric", "cotton", "--json"]) == 0
    report = _last_json(capsys)
    for name in ("albedo.png", "normals.png", "depth.npy", "points.ply", "outputs.json"):
        assert (out / name).is_file()
    assert (out / "capture" / "cotton" / "capture.json").is_file()
    assert np.load(out / "depth.npy").shape == (64, 64)
    assert 0.0 < report["mean_angular_error_deg"] < 10.0
    # with no flag the rig's LEDs pick the near-light solver, which beats the classical pipeline
    assert report["solver"] == "near" and report["config"]["integrator"] == "masked"
    assert (
        report["mean_angular_error_deg"] == report["errors_deg"]["near"] < report["errors_deg"]["distant (classical)"]
    )
    # the one scoring rule: `psmini evaluate` on the demo's capture gives the demo's figure
    assert main(["evaluate", str(out / "capture" / "cotton"), "--json"]) == 0
    evaluated = _last_json(capsys)
    assert evaluated["solver"] == "near" and evaluated["pixels"] == report["scores"]["pixels"]
    assert abs(evaluated["mean_angular_error_deg"] - report["mean_angular_error_deg"]) < 1e-6
    # an earlier demo is replaced; any other folder is refused
    assert main(["demo", "--out", str(out), "--size", "32"]) == 0
    other = tmp_path / "mine"
    other.mkdir()
    assert main(["demo", "--out", str(other), "--size", "32"]) == 1
