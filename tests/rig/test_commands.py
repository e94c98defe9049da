"""`psmini capture` (simulated rig, faults, argument errors) and `psmini rig info`."""

from __future__ import annotations

import json

import pytest

from psmini.cli import main

SMALL = ["--size", "32", "--pixel-pitch", "0.1", "--handshake-timeout", "0.5", "--command-timeout", "0.2"]


def last_json(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.mark.slow
def test_capture_simulate_then_reconstruct_and_evaluate(tmp_path, capsys):
    out = tmp_path / "cotton"
    assert main(["capture", "--simulate", "--fabric", "cotton", "--out", str(out), "--json", *SMALL]) == 0
    summary = last_json(capsys)
    assert summary["simulated"] and summary["leds"] == 8 and summary["firmware"].startswith("psmini-leds 1.0.0")
    assert (out / "card" / "capture.json").is_file() and (out / "gt" / "normals.npy").is_file()
    assert main(["reconstruct", str(out), "--out", str(tmp_path / "result")]) == 0
    assert (tmp_path / "result" / "points.ply").is_file()
    capsys.readouterr()
    assert main(["evaluate", str(out), "--json"]) == 0
    near = last_json(capsys)
    # no flag: the capture's LED model picks the near-light solver, which beats the classical one
    assert near["solver"] == "near" and near["config"]["integrator"] == "masked"
    assert main(["evaluate", str(out), "--json", "--light-model", "distant"]) == 0
    distant = last_json(capsys)
    assert distant["solver"] == "distant"
    # on this 3.2 mm crop both are within the 8-bit noise (the 10 mm field separates them: 1.7 vs 6.1 deg)
    assert near["mean_angular_error_deg"] < 2 and distant["mean_angular_error_deg"] < 2
    assert near["pixels"] == distant["pixels"]  # the one scoring rule: the ground truth's valid pixels


@pytest.mark.parametrize("fault, cause", [("garbage", "garbled reply"), ("stale-frame", "stale frame"),
                                          ("disconnect", "disconnected")])
def test_capture_faults_fail_cleanly(tmp_path, capsys, fault, cause):
    out = tmp_path / "jute"
    assert main(["capture", "--simulate", "--fault", fault, "--out", str(out), *SMALL]) == 1
    assert cause in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_capture_argument_errors(tmp_path, capsys):
    assert main(["capture", "--out", str(tmp_path / "x")]) == 1
    assert "either --simulate or --port" in capsys.readouterr().err
    assert main(["capture", "--port", "loop://", "--out", str(tmp_path / "x")]) == 1
    assert "--port needs --camera" in capsys.readouterr().err
    assert main(["capture", "--port", "loop://", "--fault", "garbage", "--out", str(tmp_path / "x")]) == 1
    assert "add --simulate" in capsys.readouterr().err
    assert (
        main(["capture", "--port", "loop://", "--camera", "0", "--kind", "flatfield", "--out", str(tmp_path / "x")])
        == 1
    )
    assert "--card-albedo" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_capture_reads_a_lights_file_before_touching_the_rig(tmp_path, capsys):
    bad = tmp_path / "lights.json"
    bad.write_text('{"format": "something-else"}')
    assert main(["capture", "--port", "psminisim://", "--camera", "0", "--lights", str(bad),
                 "--out", str(tmp_path / "x")]) == 1
    assert "format must be 'psmini-lights'" in capsys.readouterr().err


def test_capture_on_hardware_port_without_firmware(tmp_path, capsys):
    assert main(["capture", "--port", "psminisim://?fault=no-banner", "--camera", "0", "--out", str(tmp_path / "x"),
                 "--handshake-timeout", "0.2", "--command-timeout", "0.2"]) == 1
    assert "no READY banner within 0.2 s" in capsys.readouterr().err


def test_rig_info(capsys):
    assert main(["rig", "info", "--port", "psminisim://?wdt=500", "--pings", "3", "--json"]) == 0
    info = last_json(capsys)
    assert (info["firmware"], info["version"], info["leds"], info["watchdog_ms"], info["lit"]) == \
        ("psmini-leds", "1.0.0", 8, 500, None)
    assert main(["rig", "info", "--port", "loop://", "--handshake-timeout", "0.1", "--command-timeout", "0.1"]) == 1
    assert "echoed 'ID?' back" in capsys.readouterr().err
