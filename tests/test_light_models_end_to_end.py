"""A user's light model through every entry point of the reconstruction: ``psmini.reconstruct``,
``psmini.evaluation.evaluate_sample``, ``psmini.batch.reconstruct_dataset`` and
``psmini reconstruct DIR --lights FILE``, without any change to psmini (issue 45, "Extensible").

The models are those of ``tests/user_light_models.py``: a tabulated radial beam (a (K, N) table against the angle off
each LED's axis) and a subclass of ``LEDLights`` that overrides ``forward`` with a Gaussian beam. These tests wait for
the energy-based near-light solver: the solver they were written against accepts only point and LED models (and
computes the LED's cos^mu itself for any ``PointLights``, so an overridden ``forward`` would be ignored).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from data_synth import make_fabric
from data_synth.fabrics import CARD_ALBEDO
from data_synth.rig import RigConfig, render_capture, render_card, rig_lights, write_synthetic_capture
from psmini.batch import reconstruct_dataset
from psmini.config import ReconstructionConfig
from psmini.evaluation import evaluate_sample, score_reconstruction
from psmini.io import load_sample, with_lights_file, write_capture, write_lights_file
from psmini.lights import LEDLights
from psmini.metrics import angular_error_deg
from psmini.pipeline import reconstruct
from tests.user_light_models import GaussianBeamLEDs, TabulatedBeamLEDs

REPO = Path(__file__).resolve().parents[1]
SIZE = 48
CONFIG = RigConfig(size=SIZE, pixel_pitch_mm=10.0 / SIZE, noise=False, bit_depth=16)
NEAR = ReconstructionConfig(solver="near")


def _gaussian_truth() -> GaussianBeamLEDs:
    """The rig's LEDs with a Gaussian beam (w = 0.35 rad, ~20°: narrower than the LEDs' cos beam)."""
    leds = rig_lights(CONFIG, dtype=torch.float64)
    return GaussianBeamLEDs(leds.positions_mm, leds.principal_directions, leds.intensities,
                            torch.full((leds.count,), 0.35, dtype=torch.float64))


def _write_rendered(root: Path, fabric_name: str, lights, seed: int = 0, lift_mm: float = 0.3) -> Path:
    """A sample and its card rendered with ``lights`` (any light model), whose manifests name that model."""
    fabric = make_fabric(fabric_name, size=SIZE, pixel_pitch_mm=CONFIG.pixel_pitch_mm, seed=seed)
    capture = render_capture(fabric, CONFIG, seed, lift_mm, lights=lights)
    card = render_card(CONFIG, CARD_ALBEDO, seed + 1, lights=lights)
    write_capture(root / "card", card.images, lights, pixel_pitch_mm=CONFIG.pixel_pitch_mm, kind="flatfield",
                  bit_depth=16, dark=card.dark, card_albedo=CARD_ALBEDO)
    gt = {"normals": capture.normals, "depth": capture.depth_mm, "albedo": capture.albedo, "mask": capture.mask}
    return write_capture(root / fabric_name, capture.images, lights, pixel_pitch_mm=CONFIG.pixel_pitch_mm,
                         kind="sample", bit_depth=16, dark=capture.dark,
                         flatfield={"path": "../card", "albedo": CARD_ALBEDO}, gt=gt)


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("user_models")
    led_sample, _ = write_synthetic_capture(root / "led", "twill", size=SIZE, noise=False, config=CONFIG,
                                            height_offset_mm=0.3)
    gaussian_sample = _write_rendered(root / "gaussian", "knit", _gaussian_truth())
    return {"root": root, "led": led_sample, "gaussian": gaussian_sample}


def _mean_error(result, sample) -> float:
    return float(score_reconstruction(result, sample)["mean_angular_error_deg"])


def test_reconstruct_with_a_tabulated_beam_equals_the_led(captures):
    """A table of the LEDs' own beam (0.05° steps) gives the LEDs' reconstruction."""
    sample = load_sample(captures["led"])
    assert isinstance(sample.lights, LEDLights)
    table = TabulatedBeamLEDs.from_leds(sample.lights, samples=1801, step_deg=0.05)
    tabulated = dataclasses.replace(sample, lights=table)
    reference, result = reconstruct(sample, NEAR), reconstruct(tabulated, NEAR)
    both = reference.mask & result.mask
    assert float(both.float().mean()) > 0.9
    difference = angular_error_deg(result.normals, reference.normals)[both]
    assert float(difference.mean()) < 0.05
    assert float((result.depth - reference.depth)[both].abs().max()) < 0.01  # mm


def test_reconstruct_uses_the_overridden_forward(captures):
    """Cloth lit by Gaussian beams: the Gaussian model (a subclass of LEDLights overriding forward) is what the
    solver must evaluate; the LED model with the same positions (cos^mu) is the wrong light and does worse."""
    sample = load_sample(captures["gaussian"])
    assert isinstance(sample.lights, GaussianBeamLEDs)
    right = _mean_error(reconstruct(sample, NEAR), sample)
    leds = LEDLights(sample.lights.positions_mm, sample.lights.principal_directions, sample.lights.intensities)
    wrong = _mean_error(reconstruct(dataclasses.replace(sample, lights=leds), NEAR), sample)
    assert right < 1.0  # noise-free 16-bit: the model is exact
    assert wrong > right + 0.2


def test_evaluate_sample(captures):
    sample = load_sample(captures["gaussian"])
    scores = evaluate_sample(sample)
    assert scores["config"]["solver"] == "near"  # auto: the model says is_near
    assert scores["pixels"] > 0.9 * SIZE * SIZE * 0.5 and scores["mean_angular_error_deg"] < 1.0


def test_batch(captures, tmp_path):
    out = tmp_path / "out"
    summary = reconstruct_dataset(captures["root"] / "gaussian", out, batch_size=2)
    rows = summary["samples"]
    assert summary["counts"]["done"] == 1 and [row["status"] for row in rows] == ["done"]
    assert (out / "knit" / "normals.png").is_file()
    written = json.loads((out / "knit" / "outputs.json").read_text())
    assert written["metadata"]["config"]["solver"] == "near"
    assert float(rows[0]["mean_angular_error_deg"]) < 1.0


@pytest.mark.slow
def test_cli_with_a_lights_file_naming_an_import_path(captures, tmp_path):
    """``psmini reconstruct DIR --lights FILE`` in a fresh process, the model found by its import path."""
    modules = tmp_path / "mine"
    modules.mkdir()
    (modules / "my_beams.py").write_text((REPO / "tests" / "user_light_models.py").read_text())
    code = ("import sys, torch; from my_beams import TabulatedBeamLEDs; from psmini.io import load_sample, "
            "write_lights_file; s = load_sample(sys.argv[1]); "
            "write_lights_file(sys.argv[2], TabulatedBeamLEDs.from_leds(s.lights, 601, 0.1))")
    env = {**os.environ, "PYTHONPATH": str(modules)}
    lights = tmp_path / "beam.json"
    subprocess.run([sys.executable, "-c", code, str(captures["led"]), str(lights)], check=True, env=env)
    assert json.loads(lights.read_text())["lights"]["model"] == "my_beams:TabulatedBeamLEDs"
    psmini = shutil.which("psmini", path=str(Path(sys.executable).parent)) or "psmini"
    run = subprocess.run([psmini, "reconstruct", str(captures["led"]), "--lights", str(lights),
                          "--out", str(tmp_path / "out"), "--json"], capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert report["solver"] == "near" and (tmp_path / "out" / "normals.png").is_file()
    written = json.loads((tmp_path / "out" / "outputs.json").read_text())
    assert written["metadata"]["config"]["solver"] == "near"


def test_with_lights_file_of_a_user_model(captures, tmp_path):
    """The Python path of ``--lights``: a sample whose lights are replaced by a user's model from a lights file."""
    sample = load_sample(captures["led"])
    path = write_lights_file(tmp_path / "beam.json", TabulatedBeamLEDs.from_leds(sample.lights,
                                                                                 601, 0.1))
    replaced = with_lights_file(sample, path)
    assert isinstance(replaced.lights, TabulatedBeamLEDs)
    assert _mean_error(reconstruct(replaced, NEAR), replaced) < _mean_error(reconstruct(sample, NEAR), sample) + 0.05


def test_a_user_model_is_called_as_often_as_the_led(captures):
    """The solver treats a user's model as it treats the built-in LED: the same calls of its ``forward``, on points of
    the same shapes (what makes its time the LED's when its ``forward`` is as cheap; the times themselves are
    measured by ``benchmarks/nearlight.py --speed``, not here)."""
    sample = load_sample(captures["led"])
    gaussian = GaussianBeamLEDs(sample.lights.positions_mm, sample.lights.principal_directions,
                                sample.lights.intensities)

    def calls(lights) -> list[tuple[int, ...]]:
        shapes: list[tuple[int, ...]] = []
        handle = lights.register_forward_hook(lambda module, args, output: shapes.append(tuple(args[0].shape)))
        try:
            reconstruct(dataclasses.replace(sample, lights=lights), NEAR)
        finally:
            handle.remove()
        return shapes

    led_calls = calls(sample.lights)
    assert len(led_calls) > 0 and calls(gaussian) == led_calls
