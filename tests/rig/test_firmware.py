"""The psmini-leds sketch: its constants match the host's, it compiles for the Nano with Debian's AVR toolchain,
and, compiled for the host, it answers byte for byte as the simulated device does."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from data_synth.simulated_rig import SimulatedDevice
from psmini.rig import firmware_path, protocol

SKETCH = firmware_path()
HOST = Path(__file__).parent / "firmware_host"
ARDUINO_HARDWARE = Path("/usr/share/arduino/hardware")
BUILDER_TOOLS = Path("/usr/share/arduino-builder")


def code() -> str:
    """The sketch without its comments."""
    text = SKETCH.read_text(encoding="ascii")
    return re.sub(r"//[^\n]*", "", re.sub(r"/\*.*?\*/", "", text, flags=re.S))


def test_sketch_ships_with_the_package():
    assert SKETCH.is_file() and SKETCH.parent.name == SKETCH.stem  # the Arduino tools want folder = sketch name


def test_sketch_constants_match_the_host():
    source = code()

    def constant(name: str) -> str:
        return re.search(rf"\b{name}(?:\[\])?\s*=\s*([^;]+);", source).group(1).strip()

    assert constant("FIRMWARE_NAME") == f'"{protocol.FIRMWARE_NAME}"'
    assert constant("FIRMWARE_VERSION") == f'"{protocol.FIRMWARE_VERSION}"'
    assert constant("BAUD_RATE") == f"{protocol.BAUDRATE}UL"
    assert constant("MAX_LINE") == str(protocol.MAX_LINE)
    assert constant("WDT_DEFAULT_MS") == f"{protocol.WATCHDOG_DEFAULT_MS}UL"
    assert (constant("WDT_MIN_MS"), constant("WDT_MAX_MS")) == tuple(f"{v}UL" for v in protocol.WATCHDOG_RANGE_MS)
    pins = [int(p) for p in constant("LED_PINS").strip("{}").split(",")]
    assert len(pins) == protocol.LED_COUNT and pins == list(range(2, 2 + protocol.LED_COUNT))
    for code_, message in protocol.ERROR_CODES.items():
        assert re.search(rf"ERR_\w+ = {code_}\b", source), message


def test_sketch_drives_leds_at_dc_and_never_blocks():
    source = code()
    assert "analogWrite" not in source  # PWM at 490/980 Hz beats with short exposures
    for blocking in ("readString", "readBytes", "parseInt", "delay(", "Serial.find"):
        assert blocking not in source, blocking
    assert "digitalWrite" in source


# --------------------------------------------------------------------------- the sketch on the host, vs the simulator

SCRIPT: list[tuple] = [
    ("x", b"PING\n"), ("x", b"ID?\n"), ("s",),
    ("x", b"ON 3\n"), ("s",), ("x", b"ON 007\r\n"), ("s",), ("x", b"STATE?\n"),
    ("x", b"ON 8\n"), ("x", b"ON -1\n"), ("x", b"ON \n"), ("x", b"ON\n"), ("x", b"ON 123456\n"), ("x", b"ON 99999\n"),
    ("s",), ("x", b"ALL\n"), ("s",), ("x", b"OFF\n"), ("s",),
    ("x", b"WDT 99\n"), ("x", b"WDT 60001\n"), ("x", b"WDT abc\n"), ("x", b"WDT 60000\n"), ("x", b"WDT 150\n"),
    ("x", b"ping\n"), ("x", b"PING \n"), ("x", b"BLINK 3\n"), ("x", b"X" * 32 + b"\n"), ("x", b"X" * 33 + b"\n"),
    ("x", b"X" * 40 + b"\xff\n"), ("x", b"ON \xff1\n"), ("x", b"ON\t1\n"), ("x", b"\n"), ("x", b"\r\n"),
    ("x", b"O"), ("x", b"N 1"), ("s",), ("x", b"\n"), ("s",), ("x", b"PING\nON 4\nSTATE?\n"), ("s",),
    # the watchdog: 150 ms of silence switch the LEDs off, any line feeds it
    ("t", 149), ("s",), ("x", b"PING\n"), ("t", 149), ("s",), ("t", 1), ("s",), ("x", b"STATE?\n"),
    ("x", b"ALL\n"), ("t", 100), ("x", b"\n"), ("t", 100), ("s",), ("t", 60), ("s",), ("x", b"STATE?\n"),
    ("t", 100000), ("x", b"ID?\n"), ("s",),
]


def simulate(script: list[tuple]) -> list[str]:
    """The script through :class:`SimulatedDevice`, in the harness's output format."""
    now = {"ms": 0}
    device = SimulatedDevice(boot_s=0.0, clock=lambda: now["ms"] / 1000)
    device.reset()
    lines = [f"OUT {device.output().hex()}"]
    for op, *arg in script:
        if op == "x":
            device.receive(arg[0])
        elif op == "t":
            now["ms"] += arg[0]
        else:
            lit = device.lit
            lines.append("LEDS " + "".join("1" if lit in ("all", i) else "0" for i in range(device.led_count)))
        lines.append(f"OUT {device.output().hex()}")
    return lines


@pytest.fixture(scope="module")
def host_firmware(tmp_path_factory) -> Path:
    compiler = shutil.which("g++")
    if compiler is None:
        pytest.skip("g++ is absent: the sketch cannot be compiled for the host")
    binary = tmp_path_factory.mktemp("firmware") / "psmini_leds_host"
    subprocess.run([compiler, "-std=c++11", "-Wall", "-Wextra", "-Werror", "-I", str(HOST), "-I", str(SKETCH.parent),
                    str(HOST / "harness.cpp"), "-o", str(binary)], check=True, capture_output=True, timeout=120)
    return binary


def test_sketch_answers_like_the_simulated_device(host_firmware):
    commands = "".join(f"x {a[0].hex()}\n" if op == "x" else f"t {a[0]}\n" if op == "t" else "s\n"
                       for op, *a in SCRIPT)
    result = subprocess.run(
        [str(host_firmware)], input=commands, capture_output=True, text=True, check=True, timeout=30
    )
    firmware = result.stdout.splitlines()
    simulated = simulate(SCRIPT)
    assert len(firmware) == len(simulated)
    for index, (ours, theirs) in enumerate(zip(firmware, simulated, strict=True)):
        assert ours == theirs, f"step {index}: firmware {bytes.fromhex(ours[4:]) if ours.startswith('OUT') else ours!r}"
    # and the exchange itself is what the protocol says
    replies = b"".join(bytes.fromhex(line[4:]) for line in firmware if line.startswith("OUT"))
    assert replies.startswith(b"READY psmini-leds 1.0.0 leds=8 wdt=2000\r\n")
    assert b"OK STATE on=- wdt=150 trips=1\r\n" in replies and b"OK STATE on=- wdt=150 trips=2\r\n" in replies
    assert b"ERR 3 line too long\r\n" in replies and b"ERR 4 non-ASCII byte\r\n" in replies


# -------------------------------------------------------------------------------------------- the Nano build

def avr_toolchain() -> str:
    builder = shutil.which("arduino-builder")
    missing = [name for name, ok in (("arduino-builder", builder), ("avr-g++ (gcc-avr)", shutil.which("avr-g++")),
                                     ("arduino-core-avr", (ARDUINO_HARDWARE / "arduino" / "avr").is_dir()))
               if not ok]
    if missing:
        pytest.skip(f"the AVR toolchain is absent ({', '.join(missing)}); on Debian: apt-get install arduino-builder "
                    "arduino-core-avr gcc-avr avr-libc (.ci/run does this when run as root)")
    return builder


@pytest.mark.slow
def test_sketch_compiles_for_the_arduino_nano(tmp_path):
    builder = avr_toolchain()
    build = tmp_path / "build"
    build.mkdir()
    # Debian's arduino-core-avr 1.8.7 reads DECIMAL_DIG, which gcc-avr 5.4's float.h defines for C99 only.
    command = [builder, "-hardware", str(ARDUINO_HARDWARE), "-hardware", str(BUILDER_TOOLS), "-tools",
               str(BUILDER_TOOLS), "-tools", "/usr/bin", "-fqbn", "arduino:avr:nano:cpu=atmega328",
               "-prefs=compiler.cpp.extra_flags=-DDECIMAL_DIG=__DECIMAL_DIG__", "-build-path", str(build), str(SKETCH)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert (build / "psmini_leds.ino.hex").is_file()
    used = re.search(r"Sketch uses (\d+) bytes .* Maximum is (\d+) bytes", result.stdout)
    ram = re.search(r"Global variables use (\d+) bytes .* Maximum is (\d+) bytes", result.stdout)
    assert used and int(used.group(1)) < int(used.group(2)) // 2
    assert ram and int(ram.group(1)) < int(ram.group(2)) // 2
