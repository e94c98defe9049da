"""The simulated device speaks the firmware's protocol; its pty link and URL behave like a port."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
import serial

from data_synth.simulated_rig import (
    PtyLink,
    SimulatedCapture,
    SimulatedDevice,
    SimulatedScene,
    device_for_url,
    serve_url,
)
from psmini.errors import RigError
from psmini.rig.protocol import MAX_LINE


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def booted(**kwargs) -> tuple[SimulatedDevice, Clock]:
    clock = Clock()
    device = SimulatedDevice(boot_s=0.5, clock=clock, **kwargs)
    device.reset()
    assert device.output() == b""  # the bootloader is still running
    clock.now = 0.5
    assert device.output() == b"READY psmini-leds 1.0.0 leds=8 wdt=2000\r\n"
    return device, clock


def ask(device: SimulatedDevice, line: bytes) -> bytes:
    device.receive(line)
    return device.output()


def test_every_command_gets_one_reply_line():
    device, _ = booted()
    assert ask(device, b"PING\n") == b"OK PING\r\n"
    assert ask(device, b"ID?\n") == b"OK ID psmini-leds 1.0.0 leds=8 wdt=2000\r\n"
    assert ask(device, b"ON 5\r\n") == b"OK ON 5\r\n" and device.lit == 5
    assert ask(device, b"ON 2\n") == b"OK ON 2\r\n" and device.lit == 2  # exactly one LED
    assert ask(device, b"STATE?\n") == b"OK STATE on=2 wdt=2000 trips=0\r\n"
    assert ask(device, b"ALL\n") == b"OK ALL\r\n" and device.lit == "all"
    assert ask(device, b"OFF\n") == b"OK OFF\r\n" and device.lit is None
    assert ask(device, b"WDT 500\n") == b"OK WDT 500\r\n"
    assert ask(device, b"ID?\n").endswith(b"wdt=500\r\n")


def test_errors():
    device, _ = booted()
    assert ask(device, b"ON 8\n") == b"ERR 2 led index out of range\r\n"
    assert ask(device, b"ON -1\n") == b"ERR 2 led index out of range\r\n"
    assert ask(device, b"WDT 5\n") == b"ERR 2 watchdog ms out of range 100..60000\r\n"
    assert ask(device, b"BLINK\n") == b"ERR 1 unknown command\r\n"
    assert ask(device, b"X" * (MAX_LINE + 1) + b"\n") == b"ERR 3 line too long\r\n"
    assert ask(device, b"ON \xff1\n") == b"ERR 4 non-ASCII byte\r\n"
    assert ask(device, b"\n") == b""  # an empty line is no command
    assert device.lit is None


def test_bytes_in_any_chunks():
    device, _ = booted()
    for byte in b"ON 3\n":
        device.receive(bytes([byte]))
    assert device.output() == b"OK ON 3\r\n" and device.lit == 3


def test_watchdog_switches_off_after_silence():
    device, clock = booted()
    ask(device, b"WDT 200\n")
    ask(device, b"ON 1\n")
    clock.now += 0.19
    assert device.lit == 1
    ask(device, b"PING\n")  # any line feeds the watchdog
    clock.now += 0.19
    assert device.lit == 1
    clock.now += 0.02
    assert device.lit is None
    assert ask(device, b"STATE?\n") == b"OK STATE on=- wdt=200 trips=1\r\n"


def test_reset_switches_off_and_prints_the_banner_again():
    device, clock = booted()
    ask(device, b"ON 4\n")
    device.reset()
    assert device.lit is None
    clock.now += 0.5
    assert device.output().startswith(b"READY ")


@pytest.mark.parametrize("fault", ["timeout", "garbage", "disconnect"])
def test_device_faults_start_after_some_commands(fault):
    device, clock = booted(fault=fault, fault_after=1)
    assert ask(device, b"ON 1\n") == b"OK ON 1\r\n"
    reply = ask(device, b"ON 2\n")
    if fault == "timeout":
        assert reply == b"" and device.lit == 2  # obeyed, reply lost (late)
        clock.now += 10
        assert device.output() == b"OK ON 2\r\n"
    elif fault == "garbage":
        assert reply.endswith(b"\r\n") and not reply[:-2].isascii() and device.lit == 2
    else:
        assert reply == b"" and not device.connected and device.lit is None  # power lost with the cable


def test_no_banner_fault_is_a_dead_board():
    device = SimulatedDevice(boot_s=0.0, clock=Clock(), fault="no-banner")
    device.reset()
    assert device.output() == b""
    assert ask(device, b"ID?\n") == b""


def test_unknown_fault():
    with pytest.raises(RigError, match="unknown fault"):
        SimulatedDevice(fault="smoke")


def test_pty_link_is_a_serial_port():
    device = SimulatedDevice(boot_s=0.05)  # pyserial flushes its input on open: the banner comes after that
    with PtyLink(device) as link:
        assert os.path.exists(link.path)
        with serial.serial_for_url(link.path, 115200, timeout=1.0) as port:
            assert port.readline() == b"READY psmini-leds 1.0.0 leds=8 wdt=2000\r\n"
            port.write(b"ON 6\n")
            assert port.readline() == b"OK ON 6\r\n"
        assert device.resets == 1
        time.sleep(0.05)  # the link sees the hang-up between the two opens
        with serial.serial_for_url(link.path, 115200, timeout=1.0) as port:  # reopening resets the board (DTR)
            assert port.readline().startswith(b"READY ")
        assert device.resets == 2 and device.lit is None


def test_replies_due_follow_the_clock():
    device, clock = booted(fault="timeout", fault_after=0, slow_s=2.0)
    device.receive(b"PING\n")
    assert not device.replies_due()  # the slow board answers in 2 s
    clock.now += 2.0
    assert device.replies_due()
    assert device.output() == b"OK PING\r\n" and not device.replies_due()


def test_pty_link_idle_once_the_board_answered():
    device = SimulatedDevice(boot_s=0.0)
    with PtyLink(device) as link, serial.serial_for_url(link.path, 115200, timeout=1.0) as port:
        assert port.readline().startswith(b"READY ")
        port.write(b"ON 2\nPING\n")
        deadline = time.monotonic() + 5.0
        while not (link.idle() and device.history[-1:] == ["PING"]) and time.monotonic() < deadline:
            time.sleep(0.001)
        assert link.idle() and device.lit == 2  # both lines parsed, both replies written to the host's side
        assert port.readline() == b"OK ON 2\r\n" and port.readline() == b"OK PING\r\n"
    assert link.idle()  # a closed link has nothing left to answer


def test_url_devices():
    device = SimulatedDevice(boot_s=0.0)
    url = serve_url(device, "test-url-devices")
    assert device_for_url(url) is device
    fresh = device_for_url("psminisim://?leds=4&fault=garbage&after=2")
    assert (fresh.led_count, fresh.fault, fresh.fault_after) == (4, "garbage", 2)
    with pytest.raises(RigError, match="no simulated device"):
        device_for_url("psminisim://nobody")
    with pytest.raises(RigError, match="unknown psminisim:// options"):
        device_for_url("psminisim://?colour=red")
    with serial.serial_for_url(url, timeout=0.5) as port:
        assert port.readline().startswith(b"READY ")
        port.write(b"ALL\n")
        assert port.readline() == b"OK ALL\r\n"


def test_simulated_camera_queues_frames_like_a_webcam():
    scene = SimulatedScene("cotton", config=None)
    scene.config = scene.config.replace(size=16, pixel_pitch_mm=0.1, noise=False)
    device, _ = booted()
    capture = SimulatedCapture(device, scene, (24, 20), buffer_frames=2)
    ok, dark = capture.read()
    assert ok and dark.shape == (20, 24, 3) and dark.dtype == np.uint8
    ask(device, b"ON 0\n")
    stale = [capture.read()[1] for _ in range(2)]
    fresh = capture.read()[1]
    assert all(np.array_equal(frame, dark) for frame in stale)
    assert fresh[2:18, 4:20, 0].mean() > dark.mean() + 20
    np.testing.assert_array_equal(fresh[2:18, 4:20, 1], scene.render()["codes"][0])
