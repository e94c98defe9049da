import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from psmini.errors import DataFormatError, InputError
from psmini.io import Sample, read_lights_file, with_lights_file, write_lights_file
from psmini.lights import DirectionalLights, PointLights, ring_lights


def test_round_trip(tmp_path):
    positions = torch.tensor([[15.8, 0.0, 10.0], [0.0, 15.8, 10.0], [-15.8, 0.0, 10.0]], dtype=torch.float64)
    leds = [{"name": f"led_{k}.png", "residual_mm": 0.01 * k} for k in range(3)]
    path = write_lights_file(tmp_path / "lights.json", PointLights(positions), leds=leds,
                             provenance={"method": "mirror sphere"})
    loaded = read_lights_file(path)
    assert isinstance(loaded.lights, PointLights) and loaded.count == 3
    assert torch.allclose(loaded.lights.positions_mm.double(), positions)
    assert loaded.leds[2]["residual_mm"] == 0.02 and loaded.provenance["method"] == "mirror sphere"
    assert "created" in loaded.provenance and loaded.provenance["software"].startswith("psmini")
    with pytest.raises(DataFormatError, match="exists"):
        write_lights_file(path, PointLights(positions))


def test_write_under_a_file_is_a_data_format_error(tmp_path):
    """A path whose folder is a file raised FileExistsError from mkdir (a traceback from psmini calibrate)."""
    (tmp_path / "calibration").write_text("not a folder")
    with pytest.raises(DataFormatError, match=r"cannot write .*lights\.json: cannot create a file in"):
        write_lights_file(tmp_path / "calibration" / "lights.json", DirectionalLights(ring_lights(8, 55.0)))
    assert [p.name for p in tmp_path.iterdir()] == ["calibration"]


def test_bad_files(tmp_path):
    path = tmp_path / "lights.json"
    with pytest.raises(DataFormatError, match="does not exist"):
        read_lights_file(path)
    for document, message in [
        ({"format": "other", "version": 1}, "format"),
        ({"format": "psmini-lights", "version": 99, "lights": {}}, "newer"),
        ({"format": "psmini-lights", "version": 1, "lights": {"model": "sun"}}, "light model"),
        ({"format": "psmini-lights", "version": 1, "lights": {"model": "directional",
          "directions": [[0, 0, 1], [1, 0, 1], [0, 1, 1]]}, "leds": [{}]}, "leds"),
    ]:
        path.write_text(json.dumps(document))
        with pytest.raises(DataFormatError, match=message):
            read_lights_file(path)
    path.write_text("{not json")
    with pytest.raises(DataFormatError, match="JSON"):
        read_lights_file(path)
    with pytest.raises(InputError, match="one object per LED"):
        write_lights_file(tmp_path / "x.json", DirectionalLights(ring_lights(3, 50.0)), leds=[{}])


def test_with_lights_file(tmp_path):
    path = write_lights_file(tmp_path / "lights.json", DirectionalLights(ring_lights(4, 50.0)))
    sample = Sample("s", torch.rand(4, 5, 5), DirectionalLights(ring_lights(4, 30.0)))
    replaced = with_lights_file(sample, path)
    assert torch.allclose(replaced.lights.directions, ring_lights(4, 50.0), atol=1e-6)
    assert replaced.meta["lights_file"] == str(path)
    with pytest.raises(DataFormatError, match="4 LEDs but sample s has 3 images"):
        with_lights_file(Sample("s", torch.rand(3, 5, 5), DirectionalLights(ring_lights(3, 30.0))), path)


# ------------------------------------------------------------------------------------------------ user models

REPO = Path(__file__).resolve().parents[2]


def _run(code: str, *args: str, pythonpath: Path | None = None, cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, cwd=cwd,
                          check=False)


@pytest.mark.slow
def test_user_model_round_trip_in_fresh_processes(tmp_path):
    """A model defined in a user's module: written by one process, read back by a fresh one through its import path
    (the folder on PYTHONPATH), refused with a clear message by a process that cannot import it."""
    modules = tmp_path / "mine"
    modules.mkdir()
    (modules / "my_beams.py").write_text((REPO / "tests" / "user_light_models.py").read_text())
    write = ("import sys, torch; from my_beams import TabulatedBeamLEDs; from psmini.io import write_lights_file; "
             "from psmini.ledcal import nominal_leds; "
             "m = TabulatedBeamLEDs.from_leds(nominal_leds(8, dtype=torch.float64)); "
             "write_lights_file(sys.argv[1], m, provenance={'method': 'table'}); "
             "print(float(m(torch.tensor([[[[1.0]], [[-2.0]], [[0.5]]]], dtype=torch.float64))[1][0, 3]))")
    path = tmp_path / "beam.json"
    written = _run(write, str(path), pythonpath=modules, cwd=tmp_path)
    assert written.returncode == 0, written.stderr
    assert json.loads(path.read_text())["lights"]["model"] == "my_beams:TabulatedBeamLEDs"
    read = ("import sys, torch; from psmini.io import read_lights_file; f = read_lights_file(sys.argv[1]); "
            "m = f.lights; print(type(m).__module__, type(m).__name__, m.count, f.provenance['method']); "
            "print(float(m(torch.tensor([[[[1.0]], [[-2.0]], [[0.5]]]], dtype=torch.float64))[1][0, 3]))")
    back = _run(read, str(path), pythonpath=modules, cwd=tmp_path)
    assert back.returncode == 0, back.stderr
    first, second = back.stdout.splitlines()
    assert first.split() == ["my_beams", "TabulatedBeamLEDs", "8", "table"]
    assert float(second) == pytest.approx(float(written.stdout), rel=1e-6)  # read back in float32
    refused = _run(read, str(path), cwd=tmp_path)
    assert refused.returncode != 0
    assert "DataFormatError" in refused.stderr and "no module named 'my_beams'" in refused.stderr
    assert "PYTHONPATH" in refused.stderr


def test_user_model_in_a_lights_file_and_a_capture(tmp_path):
    from psmini.io import load_sample, write_capture
    from psmini.ledcal import nominal_leds
    from tests.user_light_models import GaussianBeamLEDs, TabulatedBeamLEDs

    leds = nominal_leds(8, dtype=torch.float64)
    beam = TabulatedBeamLEDs.from_leds(leds)
    path = write_lights_file(tmp_path / "beam.json", beam)
    loaded = read_lights_file(path)
    assert isinstance(loaded.lights, TabulatedBeamLEDs) and loaded.lights.beam.shape == (8, 13)
    gaussian = GaussianBeamLEDs(leds.positions_mm, leds.principal_directions)
    folder = write_capture(tmp_path / "capture", torch.rand(8, 6, 6), gaussian, pixel_pitch_mm=0.1)
    manifest = json.loads((folder / "capture.json").read_text())
    assert manifest["lights"]["model"] == "gaussian_beam_leds"
    sample = load_sample(folder)
    assert isinstance(sample.lights, GaussianBeamLEDs) and sample.lights.count == 8
    sample = with_lights_file(sample, path)
    assert isinstance(sample.lights, TabulatedBeamLEDs)


def test_lights_file_naming_an_unknown_model(tmp_path):
    path = tmp_path / "lights.json"
    for model, message in [("fresnel_leds", "entry point of group 'psmini.light_models'"),
                           ("absent_pkg_xyz.beams:Beam", "no module named 'absent_pkg_xyz'")]:
        path.write_text(json.dumps({"format": "psmini-lights", "version": 1,
                                    "lights": {"model": model, "positions_mm": [[0, 0, 10]] * 3}}))
        with pytest.raises(DataFormatError, match=f"lights file .*: bad light model: .*{message}"):
            read_lights_file(path)
