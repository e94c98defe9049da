import json

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
