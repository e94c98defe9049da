"""Capture sessions on the simulated rig: accuracy equal to data_synth's own rendering, faults, focus sweeps."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from data_synth import CARD_ALBEDO
from data_synth.rig import RigConfig, focus_stack, write_synthetic_capture
from data_synth.simulated_rig import SimulatedRig
from psmini.autofocus import best_of_scores
from psmini.errors import DataFormatError, RigError
from psmini.evaluation import evaluate_sample
from psmini.focus import brenner
from psmini.io import load_sample, read_capture
from psmini.rig import CaptureSession, LEDController, RigCamera, led_azimuths, nominal_ring_lights, write_with_card

FAST = {"handshake_timeout_s": 0.5, "command_timeout_s": 0.2}


def open_rig(rig: SimulatedRig, frames_per_led: int = 1):
    leds = LEDController(rig.port, **FAST)
    camera = RigCamera(0, open_capture=rig.open_capture, frame_size=rig.frame_size, crop_size=rig.size)
    return leds, camera


def capture_with_card(rig: SimulatedRig, out: Path, frames_per_led: int = 1) -> Path:
    """What `psmini capture --simulate` does: the card, then the sample, one folder."""
    leds, camera = open_rig(rig)
    with leds, camera:
        session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=rig.pixel_pitch_mm,
                                 frames_per_led=frames_per_led)
        rig.place("card")
        card = session.acquire("flatfield")
        rig.place("sample")
        sample = session.acquire("sample")
        return write_with_card(out, session, sample, card, card_albedo=CARD_ALBEDO, gt=rig.scene.render("sample")["gt"])


@pytest.mark.slow
def test_simulated_capture_reconstructs_like_data_synth(tmp_path):
    size, pitch, seed = 128, 0.05, 3
    with SimulatedRig("twill", seed, size, pixel_pitch_mm=pitch) as rig:
        folder = capture_with_card(rig, tmp_path / "twill")
    reference, _ = write_synthetic_capture(tmp_path / "synth", "twill", seed=seed, size=size,
                                           config=RigConfig(bit_depth=8, pixel_pitch_mm=pitch))
    captured, rendered = load_sample(folder), load_sample(reference)
    torch.testing.assert_close(captured.images, rendered.images, rtol=0, atol=0)  # same codes, same LED order
    torch.testing.assert_close(captured.reference, rendered.reference, rtol=0, atol=0)
    ours, theirs = evaluate_sample(captured), evaluate_sample(rendered)
    assert ours["mean_angular_error_deg"] == pytest.approx(theirs["mean_angular_error_deg"], abs=1e-3)
    assert ours["mean_angular_error_deg"] < 15.0

    manifest = json.loads((folder / "capture.json").read_text())
    metadata = manifest["metadata"]
    assert metadata["firmware"] == "psmini-leds 1.0.0 leds=8 wdt=2000"
    assert [entry["led"] for entry in metadata["timing"]] == [None, *range(8)]
    assert manifest["camera"]["backend_name"] == "psmini-simulator" and manifest["crop"][2:] == [size, size]
    assert manifest["lights"]["model"] == "led" and manifest["flatfield"] == {"path": "card", "albedo": CARD_ALBEDO}
    assert read_capture(folder / "card").kind == "flatfield"


def test_averaged_frames_are_kept_at_16_bits(tmp_path):
    with SimulatedRig("cotton", 0, 32, pixel_pitch_mm=0.1) as rig:
        leds, camera = open_rig(rig)
        with leds, camera:
            session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=0.1, frames_per_led=3)
            acquisition = session.acquire()
            assert acquisition.bit_depth == 16 and acquisition.images.shape == (8, 32, 32)
            assert all(len(entry["frames_s"]) == 3 for entry in acquisition.timing)
            folder = session.write(tmp_path / "cotton", acquisition)
    capture = read_capture(folder)
    np.testing.assert_allclose(capture.images.numpy(), acquisition.images, atol=1 / 65535)


def test_calibration_captures_sphere_and_card(tmp_path):
    with SimulatedRig("jute", 0, 48, pixel_pitch_mm=0.1) as rig:
        leds, camera = open_rig(rig)
        with leds, camera:
            session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=0.1)
            rig.place("sphere")
            sphere = session.capture(tmp_path / "sphere", kind="sphere")
            rig.place("card")
            card = session.capture(tmp_path / "card", kind="flatfield", card_albedo=CARD_ALBEDO)
    assert read_capture(sphere).kind == "sphere"
    assert read_capture(card).card_albedo == CARD_ALBEDO


def test_stale_frames_are_discarded_without_a_flush():
    with SimulatedRig("jute", 0, 32, pixel_pitch_mm=0.1, buffer_frames=3) as rig:
        leds, camera = open_rig(rig)
        with leds, camera:
            camera.flush_frames = 0  # only the freshness check stands between a switch and its frame
            session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=0.1)
            first = session.acquire()
            second = session.acquire()  # its dark frame follows LED 7's frames in the queue
    np.testing.assert_array_equal(first.images, second.images)
    np.testing.assert_array_equal(first.dark, second.dark)
    assert [entry["discarded"] for entry in second.timing] == [3] * 9


@pytest.mark.parametrize("fault, cause", [
    ("no-banner", "no READY banner"),
    ("timeout", "no reply within 0.2 s"),
    ("garbage", "garbled reply"),
    ("disconnect", "disconnected"),
    ("no-frame", "returned no frame"),
    ("stale-frame", "stale frame for LED"),
])
def test_every_fault_over_a_pty_is_a_named_rig_error_with_leds_off_and_no_folder(tmp_path, fault, cause):
    with SimulatedRig("jute", 0, 32, pixel_pitch_mm=0.1, fault=fault, fault_after=12) as rig:
        assert rig.port.startswith("/dev/")  # a real pseudo-terminal
        with pytest.raises(RigError, match=cause):
            capture_with_card(rig, tmp_path / "jute")
        assert rig.device.lit is None
    assert not (tmp_path / "jute").exists()
    assert list(tmp_path.iterdir()) == []  # nor any staging folder


def test_write_with_card_refuses_an_existing_folder(tmp_path):
    with SimulatedRig("jute", 0, 32, pixel_pitch_mm=0.1) as rig:
        folder = capture_with_card(rig, tmp_path / "jute")
        with pytest.raises(DataFormatError, match="already exists"):
            capture_with_card(rig, folder)
    assert load_sample(folder).reference is not None


def test_write_with_card_keeps_the_old_folder_when_the_last_rename_fails(tmp_path, monkeypatch):
    """With overwrite, the old capture was moved into the staging folder before the new one was renamed into place;
    a failure of that rename removed the staging folder, the old capture with it."""
    import os

    with SimulatedRig("jute", 0, 32, pixel_pitch_mm=0.1) as rig:
        folder = capture_with_card(rig, tmp_path / "jute")
        before = sorted(p.relative_to(folder) for p in folder.rglob("*"))
        leds, camera = open_rig(rig)
        with leds, camera:
            session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=rig.pixel_pitch_mm)
            card, sample = session.acquire("flatfield"), session.acquire("sample")
    real_replace = os.replace

    def failing_replace(source, target):
        # the new capture's rename into place fails (the old one's return is allowed)
        if Path(target) == folder and ".staging-" in Path(source).parent.name and Path(source).name == folder.name:
            raise OSError(28, "No space left on device")
        return real_replace(source, target)

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(DataFormatError, match=r"cannot move the capture into .*jute.*No space left"):
        write_with_card(folder, session, sample, card, card_albedo=CARD_ALBEDO, overwrite=True)
    assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["jute"]  # no staging folder left behind
    assert load_sample(folder).reference is not None


def test_focus_sweep_finds_the_focal_plane(tmp_path):
    config = RigConfig(shadows=False)  # shadows cost time and do not move focus
    with SimulatedRig("jute", 0, 48, pixel_pitch_mm=0.05, config=config) as rig:
        leds, camera = open_rig(rig)
        with leds, camera:
            session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=0.05)
            positions = [round(-1.2 + 0.1 * i, 2) for i in range(19)]
            result = session.focus_sweep(rig.move_to, positions, folder=tmp_path / "focus")
            assert rig.device.lit is None and rig.stage_z == pytest.approx(result.best_position)
    assert result.stopped_by_rule and len(result.positions) < len(positions)
    assert -1.2 < result.best_position < 0.0  # the cloth lies above the focal plane: the stage goes down
    # the frames the session took are data_synth's focus stack, and scored offline they give the same focus
    fabric = rig.scene.render("sample")["fabric_object"]
    stack = torch.cat([focus_stack(fabric, [z], seed=0, config=rig.scene.config) for z in result.positions])
    stack = torch.round(stack * 255) / 255  # the webcam's 8 bits
    focus = read_capture(tmp_path / "focus")
    assert focus.kind == "focus" and focus.positions_mm == result.positions
    torch.testing.assert_close(focus.images, stack, rtol=0, atol=1e-6)
    offline = best_of_scores(brenner(stack), result.positions)
    assert result.best_position == pytest.approx(offline.best_position, abs=1e-6)


def test_session_guards():
    assert led_azimuths(nominal_ring_lights(4)).tolist() == pytest.approx([0, np.pi / 2, np.pi, -np.pi / 2])
    with SimulatedRig("jute", 0, 32, pixel_pitch_mm=0.1) as rig:
        leds, camera = open_rig(rig)
        with leds, camera:
            with pytest.raises(RigError, match="6 lights but the firmware drives 8"):
                CaptureSession(leds, camera, nominal_ring_lights(6))
            with pytest.raises(RigError, match="frames_per_led"):
                CaptureSession(leds, camera, rig.lights, frames_per_led=0)
            with pytest.raises(RigError, match="kind must be one of"):
                CaptureSession(leds, camera, rig.lights).acquire("focus")
    with pytest.raises(RigError, match="at least 3 LEDs"):
        nominal_ring_lights(2)


def test_led_azimuths_misuse_raise():
    from psmini.lights import DirectionalLights

    # a (K, 3) tensor of LED positions for the light model; a light straight down the optical axis
    with pytest.raises(RigError, match="lights must be a psmini.lights model, got Tensor"):
        led_azimuths(nominal_ring_lights(4).positions_mm)
    with pytest.raises(RigError, match="a light on the optical axis has no azimuth"):
        led_azimuths(DirectionalLights(torch.tensor([[1.0, 0.0, 1.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 1.0]])))


def test_write_with_card_under_a_file_is_a_data_format_error(tmp_path):
    """A folder path under a file raised FileExistsError from mkdir: a traceback from psmini capture, after the
    whole acquisition."""
    from types import SimpleNamespace

    (tmp_path / "captures").write_text("not a folder")
    with pytest.raises(DataFormatError, match=r"cannot create a folder beside .*captures/jute"):
        write_with_card(tmp_path / "captures" / "jute", None, SimpleNamespace(kind="sample"),  # type: ignore[arg-type]
                        SimpleNamespace(kind="flatfield"), card_albedo=CARD_ALBEDO)  # type: ignore[arg-type]
    assert [p.name for p in tmp_path.iterdir()] == ["captures"]
