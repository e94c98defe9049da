import json
import shutil

import numpy as np
import pytest
import torch

from psmini.cli import main
from tests.conftest import shared_data


def _last_json(capsys) -> dict:
    lines = capsys.readouterr().out.strip().splitlines()
    return json.loads(lines[-1])


@pytest.mark.slow
@pytest.mark.parametrize(("name", "low", "high"), [("cat", 8.39, 8.43), ("ball", 4.10, 4.20)])
def test_evaluate_reproduces_diligent_baseline(capsys, name, low, high):
    folder = shared_data("DiLiGenT", name)
    assert main(["evaluate", str(folder), "--json"]) == 0
    scores = _last_json(capsys)
    assert low <= scores["mean_angular_error_deg"] <= high
    assert scores["pixels"] > 10000


@pytest.mark.slow
def test_reconstruct_writes_outputs(tmp_path, capsys):
    folder = shared_data("DiLiGenT", "ball")
    out = tmp_path / "ball-out"
    assert main(["reconstruct", str(folder), "--out", str(out), "--json"]) == 0
    report = _last_json(capsys)
    assert {p.rsplit("/", 1)[-1] for p in report["files"]} >= {
        "albedo.png",
        "normals.png",
        "depth.npy",
        "depth.png",
        "points.ply",
    }
    depth = np.load(out / "depth.npy")
    assert depth.shape == (512, 612)
    # the ball bulges toward the camera: its centre stands higher than its rim
    inside = np.isfinite(depth)
    rows, cols = np.nonzero(inside)
    centre = depth[int(rows.mean()), int(cols.mean())]
    assert centre > np.nanpercentile(depth, 10) + 20


def test_missing_folder_fails_cleanly(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path / "nowhere")]) == 1
    assert "nowhere" in capsys.readouterr().err


def test_reconstruct_count_mismatch_fails_cleanly(tmp_path, capsys):
    folder = shared_data("DiLiGenT", "ball")
    copy = tmp_path / "ball"
    shutil.copytree(folder, copy, symlinks=True, ignore=shutil.ignore_patterns("*.png"))
    for image in folder.glob("*.png"):
        (copy / image.name).symlink_to(image)
    lines = (copy / "light_directions.txt").read_text().splitlines()
    (copy / "light_directions.txt").write_text("\n".join(lines[:-1]) + "\n")
    assert main(["reconstruct", str(copy), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "96" in err and "95" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="tests the error raised when CUDA is absent")
def test_cuda_absent_fails_cleanly(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path), "--device", "cuda"]) == 1
    assert "CUDA" in capsys.readouterr().err


def test_evaluate_without_ground_truth_fails_cleanly(tmp_path, capsys):
    folder = shared_data("DiLiGenT", "ball")
    copy = tmp_path / "ball"
    copy.mkdir()
    for item in folder.iterdir():
        if item.name not in ("Normal_gt.mat", "Normal_gt.png"):
            (copy / item.name).symlink_to(item)
    assert main(["evaluate", str(copy)]) == 1
    assert "ground-truth normals" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        (["--integrator", "fc", "--integrator-option", "iterations=3"], "frankot_chellappa takes"),
        (["--light-model", "near", "--estimator", "tukey"], "near-light solver has its own"),
        (["--light-model", "distant", "--near-option", "max_iterations=3"], "solver is 'distant'"),
        (["--near-option", "max_iterations"], "KEY=VALUE"),
        (["--card-smoothing-px", "-2"], "card_smoothing_px"),
    ],
)
@pytest.mark.parametrize("command", ["reconstruct", "evaluate", "batch"])
def test_bad_configuration_fails_before_any_work(tmp_path, capsys, command, flags, match):
    """A bad configuration is refused with one named error before the folder is even looked at."""
    out = ["--out", str(tmp_path / "out")] if command != "evaluate" else []
    assert main([command, str(tmp_path / "nowhere"), *out, *flags]) == 1
    err = capsys.readouterr().err
    assert match.split()[0] in err and "nowhere" not in err
    assert not (tmp_path / "out").exists()


def test_near_light_asked_of_directional_lights_fails(tmp_path, capsys):
    """DiLiGenT's lights are directions: near light is refused, naming what is missing."""
    folder = shared_data("DiLiGenT", "ball")
    assert main(["evaluate", str(folder), "--light-model", "near"]) == 1
    assert "needs light positions" in capsys.readouterr().err


@pytest.mark.slow
def test_diligent_from_python_without_pitch_is_in_pixels_over_the_mask():
    """DiLiGenT has no pixel pitch: depth in pixel units, integrated over the object's outline only."""
    from psmini.config import ReconstructionConfig
    from psmini.io import load_sample
    from psmini.pipeline import reconstruct

    sample = load_sample(shared_data("DiLiGenT", "cat"))
    assert sample.pixel_pitch_mm is None
    result = reconstruct(sample)
    assert ReconstructionConfig().resolved(sample.lights, True).integrator == "masked"
    outside = ~sample.mask.bool().unsqueeze(0)
    assert float(result.depth[outside].abs().max()) == 0.0  # nothing integrated off the outline
    inside = result.depth[~outside]
    # the cat stands a few hundred pixels deep (its outline is ~400 px tall), not the ~2 mm a made-up pitch gave
    assert 20.0 < float(inside.max() - inside.min()) < 400.0


def test_reconstruct_near_light_reports_its_predicted_errors(tmp_path, capsys):
    """A synthetic capture (LEDs: near light) writes normal_std.npy/.png and reports their median over the solved
    pixels; the distant solver reports none."""
    from data_synth.rig import write_synthetic_capture
    from psmini import reconstruct
    from psmini.io import load_sample

    sample_dir, _ = write_synthetic_capture(tmp_path / "captures", "twill", seed=1, size=64)
    assert main(["reconstruct", str(sample_dir), "--out", str(tmp_path / "out"), "--json"]) == 0
    output = capsys.readouterr().out
    report = json.loads(output.strip().splitlines()[-1])
    expected = reconstruct(load_sample(sample_dir))
    median = float(expected.normal_std[expected.mask].median())
    assert report["solver"] == "near" and report["normal_std_median_deg"] == pytest.approx(median, rel=1e-5)
    assert 0 < median < 5 and f"median {median:.3f} deg over the solved pixels" in output
    assert json.loads((tmp_path / "out" / "outputs.json").read_text())["normal_std_median_deg"] == pytest.approx(
        median, rel=1e-5)
    assert main(["reconstruct", str(sample_dir), "--out", str(tmp_path / "distant"), "--solver", "distant",
                 "--json"]) == 0
    output = capsys.readouterr().out
    assert json.loads(output.strip().splitlines()[-1])["normal_std_median_deg"] is None
    assert "predicted RMS error" not in output and not (tmp_path / "distant" / "normal_std.npy").exists()


def test_compiled_near_light_runs_without_a_compiler(tmp_path, monkeypatch):
    """`--near-option compile=true` on a machine without a C++ compiler: a warning, and the eager solve's outputs."""
    assert main(["synth", "twill", "--out", str(tmp_path), "--size", "32", "--seed", "1"]) == 0
    monkeypatch.setenv("CXX", "no-such-compiler-for-psmini")
    assert main(["reconstruct", str(tmp_path / "twill"), "--out", str(tmp_path / "eager")]) == 0
    with pytest.warns(RuntimeWarning, match="torch.compile cannot run on cpu: no C"):
        assert main(["reconstruct", str(tmp_path / "twill"), "--out", str(tmp_path / "fallback"),
                     "--near-option", "compile=true"]) == 0
    depths = [np.load(tmp_path / name / "depth.npy") for name in ("eager", "fallback")]
    assert np.array_equal(*depths, equal_nan=True)
