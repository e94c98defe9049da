"""The LED controller over real pseudo-terminals, the psminisim:// URL and pyserial's loop://."""

from __future__ import annotations

import time

import pytest
import serial

from data_synth.simulated_rig import PtyLink, SimulatedDevice, serve_url
from psmini.errors import RigError
from psmini.rig.controller import LEDController
from psmini.rig.protocol import Identity

FAST = {"handshake_timeout_s": 0.5, "command_timeout_s": 0.2}


@pytest.fixture
def pty_device():
    device = SimulatedDevice(boot_s=0.02)
    with PtyLink(device) as link:
        yield device, link.path


def test_handshake_and_commands_over_a_pty(pty_device):
    device, path = pty_device
    with LEDController(path, **FAST) as leds:
        assert leds.identity == Identity("psmini-leds", "1.0.0", 8, 2000)
        assert leds.led_count == 8
        leds.on(7)
        assert device.lit == 7 and leds.state().lit == 7
        leds.all_on()
        assert device.lit == "all"
        leds.off()
        assert device.lit is None
        assert leds.identify().name == "psmini-leds"
        leds.ping()
    assert not leds.is_open
    assert device.history[-1] == "OFF"


def test_leds_off_on_exit_error_and_ctrl_c(pty_device):
    device, path = pty_device
    with pytest.raises(ZeroDivisionError), LEDController(path, **FAST) as leds:
        leds.on(3)
        raise ZeroDivisionError("an error inside the block")
    assert device.lit is None
    with pytest.raises(KeyboardInterrupt), LEDController(path, **FAST) as leds:
        leds.on(4)
        raise KeyboardInterrupt
    assert device.lit is None


def test_board_without_reset_is_asked_id(pty_device):
    device, path = pty_device
    device.fault = None
    device.boot_s = 60.0  # the banner never comes in time: as if DTR did not reset the board
    with LEDController(path, handshake_timeout_s=0.1, command_timeout_s=0.2) as leds:
        assert leds.identity.led_count == 8


def test_watchdog_set_on_open_and_trips_when_the_host_is_silent(pty_device):
    device, path = pty_device
    with LEDController(path, watchdog_ms=150, **FAST) as leds:
        leds.on(2)
        time.sleep(0.25)
        assert device.lit is None
        state = leds.state()
        assert (state.lit, state.watchdog_ms, state.trips) == (None, 150, 1)


def test_keepalive_keeps_an_led_lit(pty_device):
    device, path = pty_device
    with LEDController(path, watchdog_ms=300, **FAST) as leds:
        leds.on(1)
        for _ in range(8):
            time.sleep(0.05)
            leds.keepalive()
        assert device.lit == 1


def test_refused_commands_name_the_firmware_message(pty_device):
    _, path = pty_device
    with LEDController(path, **FAST) as leds:
        with pytest.raises(RigError, match="0..7"):
            leds.on(8)  # checked on the host
        with pytest.raises(RigError, match="refused 'ON 8': ERR 2 led index out of range"):
            leds.command("ON", 8)  # and by the firmware
        with pytest.raises(RigError, match="watchdog timeout must be an integer in 100..60000"):
            leds.set_watchdog(10)
        with pytest.raises(RigError, match="refused 'WDT 50': ERR 2 watchdog ms out of range"):
            leds.command("WDT", 50)
        with pytest.raises(RigError, match="refused 'BLINK': ERR 1 unknown command"):
            leds.command("BLINK")


class ScriptedPort:
    """A port whose firmware (written here, independent of psmini's simulator) answers each command line with
    ``OK VERB ...`` after the delay the script gives for that line (None: the reply is lost), so that a test
    decides which reply comes late. It records what it received and which replies it delivered."""

    def __init__(self, delays: dict[int, float | None]):
        self.delays = delays  # command number (0-based, banner excluded) -> delay in s, or None to lose it
        self.port = "scripted"
        self.is_open = True
        self.received: list[str] = []
        self.delivered: list[str] = []
        self._queue: list[tuple[float, bytes]] = [(time.monotonic(), b"READY psmini-leds 1.0.0 leds=8 wdt=2000\r\n")]
        self._incoming = b""

    def _answer(self, line: str) -> str:
        verb, _, argument = line.partition(" ")
        if verb == "STATE?":
            return "OK STATE on=2 wdt=2000 trips=0"
        return f"OK {verb} {argument}".rstrip()

    def write(self, data: bytes) -> int:
        self._incoming += data
        while b"\n" in self._incoming:
            raw, _, self._incoming = self._incoming.partition(b"\n")
            line = raw.decode().strip()
            delay = self.delays.get(len(self.received), 0.0)
            self.received.append(line)
            if delay is not None:
                self._queue.append((time.monotonic() + delay, (self._answer(line) + "\r\n").encode()))
        return len(data)

    def _due(self) -> bytes:
        now = time.monotonic()
        ready = sorted(item for item in self._queue if item[0] <= now)
        self._queue = [item for item in self._queue if item[0] > now]
        self.delivered += [data.decode().strip() for _, data in ready]
        return b"".join(data for _, data in ready)

    @property
    def in_waiting(self) -> int:
        return 0

    def read(self, size: int = 1) -> bytes:
        data = self._due()
        if not data:
            time.sleep(0.002)
        return data

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self._due()  # whatever has arrived is thrown away

    def close(self) -> None:
        self.is_open = False


def test_one_retry_recovers_from_one_lost_reply():
    port = ScriptedPort({0: None})  # the reply to the first command (ON 3) is lost
    with LEDController(port, handshake_timeout_s=0.5, command_timeout_s=0.2) as leds:
        leds.on(3)
        assert leds.lit == 3
    assert port.received[:2] == ["ON 3", "ON 3"]  # sent once more after the timeout
    assert port.delivered.count("OK ON 3") == 1


def test_stale_late_replies_are_skipped():
    """ON 2's first reply comes after its timeout: the retry is answered by that late reply, and the retry's own
    reply arrives while STATE? waits. STATE? must skip it (a stale OK ON) and return its own reply."""
    port = ScriptedPort({0: 0.3, 1: 0.3, 2: 0.0})  # ON 2 (late), ON 2 again (late), STATE? at once
    with LEDController(port, handshake_timeout_s=0.5, command_timeout_s=0.25) as leds:
        leds.on(2)
        time.sleep(0.4)  # the second OK ON 2 is now waiting in the port
        state = leds.state()
        assert state.lit == 2 and state.watchdog_ms == 2000
    assert port.received[:3] == ["ON 2", "ON 2", "STATE?"]
    # both ON replies were delivered, the second one before STATE's: it was read and skipped, not taken
    assert port.delivered[:4] == ["READY psmini-leds 1.0.0 leds=8 wdt=2000", "OK ON 2", "OK ON 2",
                                  "OK STATE on=2 wdt=2000 trips=0"]


@pytest.mark.parametrize("fault, cause", [
    ("no-banner", "no READY banner within 0.2 s and no answer to ID"),
    ("timeout", "failed after 2 tries: no reply within 0.2 s"),
    ("garbage", "failed after 2 tries: garbled reply"),
    ("disconnect", "disconnected"),
])
def test_faults_over_a_pty_end_in_a_rig_error_with_leds_off(fault, cause):
    device = SimulatedDevice(boot_s=0.02, fault=fault, fault_after=1)
    with PtyLink(device) as link:
        start = time.monotonic()
        with (pytest.raises(RigError, match=cause),
              LEDController(link.path, handshake_timeout_s=0.2, command_timeout_s=0.2) as leds):
            leds.on(0)
            leds.on(1)
        assert time.monotonic() - start < 2.0
    assert device.lit is None


def test_board_reset_mid_session_is_named():
    device = SimulatedDevice(boot_s=0.0)
    with LEDController(serve_url(device), **FAST) as leds:
        device.reset()
        with pytest.raises(RigError, match="board reset during the session"):
            leds.ping()


def test_loop_url_handshake_and_echo():
    port = serial.serial_for_url("loop://", timeout=0.01)
    port.write(b"bootloader noise\xfe\nREADY psmini-leds 1.0.0 leds=8 wdt=2000\r\n")
    leds = LEDController(port, **FAST)
    assert leds.open().led_count == 8
    with pytest.raises(RigError, match="echoed 'PING' back"):
        leds.ping()
    leds.close()
    assert not port.is_open


def test_foreign_firmware_is_refused():
    port = serial.serial_for_url("loop://", timeout=0.01)
    port.write(b"READY blinky 2.0.0 leds=8 wdt=2000\n")
    with pytest.raises(RigError, match="runs 'blinky'"):
        LEDController(port, **FAST).open()


@pytest.mark.parametrize("wdt", [0, 99, 60001])
def test_a_watchdog_outside_the_protocol_is_refused(wdt):
    """wdt=0 (no watchdog) was accepted: a crashed host would then leave an LED lit."""
    port = serial.serial_for_url("loop://", timeout=0.01)
    port.write(b"READY psmini-leds 1.0.0 leds=8 wdt=%d\n" % wdt)
    with pytest.raises(RigError, match=f"reports a watchdog of {wdt} ms, outside the protocol's 100..60000 ms"):
        LEDController(port, **FAST).open()
    assert not port.is_open


def test_port_that_cannot_be_opened():
    with pytest.raises(RigError, match="cannot open the LED controller port"):
        LEDController("/dev/psmini-no-such-port", **FAST).open()
    with pytest.raises(RigError, match="cannot open"):
        LEDController("nosuchscheme://x", **FAST).open()


@pytest.mark.parametrize("kwargs", [{"handshake_timeout_s": 0}, {"command_timeout_s": -1}, {"retries": -1},
                                    {"watchdog_ms": 50}])
def test_bad_arguments(kwargs):
    with pytest.raises(RigError):
        LEDController("loop://", **kwargs)


@pytest.mark.parametrize("kwargs, match", [
    ({"command_timeout_s": float("inf")}, "command_timeout_s must be a positive, finite number of seconds, got inf"),
    ({"handshake_timeout_s": float("nan")}, "handshake_timeout_s must be a positive, finite number"),
])
def test_timeouts_that_never_fire_are_refused(kwargs, match):
    """An infinite command timeout was taken: a silent device then hung the host instead of raising."""
    with pytest.raises(RigError, match=match):
        LEDController("loop://", **kwargs)


def test_a_port_number_is_refused_at_construction():
    """LEDController(3) (COM3's number) failed at open() with AttributeError: 'int' object has no attribute 'read'."""
    with pytest.raises(RigError, match=r"port must be a port name or URL .* got 3"):
        LEDController(3)  # type: ignore[arg-type]


def test_commands_need_an_open_controller():
    with pytest.raises(RigError, match="not open"):
        LEDController("loop://").on(1)
