"""``psmini calibrate`` and ``--lights`` end to end on synthetic renders written as files."""

import json

import numpy as np
import pytest
import torch

from data_synth.rig import RigConfig, render_card, render_sphere
from psmini.cli import main
from psmini.io import read_capture, write_capture, write_image
from psmini.lights import DirectionalLights, ring_lights
from tests.calibration._helpers import angle_deg, rig_intrinsics, specular_points

CONFIG = RigConfig(size=200, pixel_pitch_mm=0.05)  # the rig's 10 mm field at half the resolution


def _last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def spheres():
    return [
        render_sphere(CONFIG, 1.5, (x, y, 1.5), seed=i)
        for i, (x, y) in enumerate([(0.0, 0.0), (3.0, 3.0), (-3.0, 3.0)])
    ]


def _true_directions(render):
    leds = render.lights.positions_mm.double()
    return leds - specular_points(render.camera_centre_mm, render.centre_mm, render.radius_mm, leds)


def _write_rgb8(folder, render):
    """8-bit RGB PNGs listed in filenames.txt, and the sphere's mask image."""
    folder.mkdir()
    names = []
    for k, image in enumerate((render.images - render.dark).clamp(0, 1)):
        codes = np.rint(image.numpy() * 255).astype(np.uint8)
        write_image(folder / f"{k:03d}.png", np.stack([codes] * 3, axis=-1))
        names.append(f"{k:03d}.png")
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    write_image(folder / "mask.png", render.mask[0].numpy().astype(np.uint8) * 255)
    return folder


def test_rgb8_with_mask_orthographic(tmp_path, capsys, spheres):
    folder = _write_rgb8(tmp_path / "sphere", spheres[0])
    out = tmp_path / "lights.json"
    assert (
        main(["calibrate", "sphere", str(folder), "--mask", str(folder / "mask.png"), "--out", str(out), "--json"]) == 0
    )
    report = _last_json(capsys)
    directions = torch.tensor(report["directions"])
    assert directions.shape == (8, 3) and "positions_mm" not in report
    # orthographic at 10 mm is a degree or so off (FIELD_NOTES); the command path must get that far, not further
    assert float(angle_deg(directions, _true_directions(spheres[0])).max()) < 3.0
    assert json.loads(out.read_text())["lights"]["model"] == "directional"


@pytest.mark.slow
def test_placements_positions_and_reconstruct_with_lights(tmp_path, capsys, spheres):
    folders = []
    for i, render in enumerate(spheres):
        folders.append(
            write_capture(
                tmp_path / f"sphere{i}",
                render.images,
                DirectionalLights(ring_lights(8, 20.0)),
                pixel_pitch_mm=CONFIG.pixel_pitch_mm,
                kind="sphere",
                bit_depth=10,
                dark=render.dark,
            )
        )
    intrinsics = tmp_path / "K.json"
    intrinsics.write_text(json.dumps({"K": rig_intrinsics(CONFIG).tolist()}))
    out = tmp_path / "lights.json"
    args = ["calibrate", "sphere", *map(str, folders), "--intrinsics", str(intrinsics), "--sphere-radius-mm", "1.5",
            "--out", str(out), "--json"]
    assert main(args) == 0
    report = _last_json(capsys)
    assert float(angle_deg(torch.tensor(report["directions"]), _true_directions(spheres[0])).max()) < 0.5
    found = torch.tensor(report["positions_mm"], dtype=torch.float64)
    error = (found - spheres[0].lights.positions_mm.double()).norm(dim=-1)
    assert float(error.max()) < 0.5  # half the rig's resolution
    assert len(report["residuals_mm"]) == 8

    # a flat card reconstructed with the calibrated lights (not the folder's) comes out flat
    card = render_card(CONFIG, albedo=0.8)
    reference = render_card(CONFIG, albedo=0.8, seed=5)
    card_dir = write_capture(
        tmp_path / "card",
        reference.images,
        reference.lights,
        pixel_pitch_mm=CONFIG.pixel_pitch_mm,
        kind="flatfield",
        bit_depth=10,
        dark=reference.dark,
        card_albedo=0.8,
    )
    sample = write_capture(tmp_path / "sample", card.images, DirectionalLights(ring_lights(8, 20.0)),
                           pixel_pitch_mm=CONFIG.pixel_pitch_mm, bit_depth=10, dark=card.dark,
                           flatfield={"path": str(card_dir)})
    assert main(["reconstruct", str(sample), "--lights", str(out), "--out", str(tmp_path / "out"), "--json"]) == 0
    depth = np.load(tmp_path / "out" / "depth.npy")
    assert depth.shape == (200, 200) and float(np.nanstd(depth)) < 0.05  # mm: flat


def test_flatfield_command(tmp_path, capsys):
    folders = []
    for seed in range(2):
        card = render_card(CONFIG, albedo=0.8, seed=seed)
        folders.append(write_capture(tmp_path / f"card{seed}", card.images, card.lights, pixel_pitch_mm=0.05,
                                     kind="flatfield", bit_depth=10, dark=card.dark, card_albedo=0.8))
    out = tmp_path / "reference"
    assert main(["calibrate", "flatfield", *map(str, folders), "--out", str(out), "--json"]) == 0
    report = _last_json(capsys)
    assert report["frames"] == 2 and report["trusted_fraction"] > 0.8
    capture = read_capture(out)
    assert capture.kind == "flatfield" and capture.card_albedo == 0.8 and capture.mask is not None


def test_bad_input_fails_cleanly(tmp_path, capsys, spheres):
    folder = _write_rgb8(tmp_path / "sphere", spheres[0])
    assert main(["calibrate", "sphere", str(folder), "--leds", "6", "--out", str(tmp_path / "x.json")]) == 1
    assert "8 LED images but 6 LEDs" in capsys.readouterr().err
    names = (folder / "filenames.txt").read_text().split()
    (folder / "filenames.txt").write_text("\n".join(names + ["missing.png"]))
    assert main(["calibrate", "sphere", str(folder), "--out", str(tmp_path / "x.json")]) == 1
    assert "missing.png" in capsys.readouterr().err
    (folder / "filenames.txt").write_text("\n".join(names[:3] + ["007.png"]))
    dark = np.zeros((200, 200, 3), np.uint8)
    write_image(folder / "007.png", dark)
    assert main(["calibrate", "sphere", str(folder), "--mask", str(folder / "mask.png"),
                 "--out", str(tmp_path / "x.json")]) == 1
    assert "LED 3" in capsys.readouterr().err and not (tmp_path / "x.json").exists()
    assert (
        main(["reconstruct", str(folder), "--lights", str(tmp_path / "none.json"), "--out", str(tmp_path / "o")]) == 1
    )
