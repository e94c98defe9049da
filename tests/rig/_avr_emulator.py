"""The psmini-leds sketch compiled for the Nano and run on an emulated ATmega328P (simavr), for the tests.

- :func:`emulator_missing` says which tool is absent (the tests skip with it).
- :func:`build_firmware` compiles the sketch with arduino-builder (as ``tests/rig/test_firmware.py`` does) and
  returns its ELF; :func:`build_bridge` compiles ``avr_bridge/avr_bridge.c`` against Debian's libsimavr.
- :class:`EmulatedBoard` runs the bridge: the AVR's UART on a pseudo-terminal (:attr:`EmulatedBoard.port`, opened
  by pyserial exactly as a board's ``/dev/ttyUSB0``; opening it resets the AVR, as DTR resets a Nano) and a
  record of every pin change of D2..D9 and every UART byte, stamped with the emulated 16 MHz cycle counter.

Times measured here are emulated (cycles / 16 MHz): they are the board's, whatever the speed of the machine
running the emulator (simavr runs this sketch at roughly 0.3-1x real time on a shared CI core).
"""

from __future__ import annotations

import bisect
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from psmini.rig import firmware_path

HZ = 16_000_000
BRIDGE_SOURCE = Path(__file__).parent / "avr_bridge" / "avr_bridge.c"
SIMAVR_INCLUDE = Path("/usr/include/simavr")
ARDUINO_HARDWARE = Path("/usr/share/arduino/hardware")
BUILDER_TOOLS = Path("/usr/share/arduino-builder")
INSTALL_HINT = ("on Debian: apt-get install arduino-builder arduino-core-avr gcc-avr avr-libc simavr libsimavr-dev "
                "(.ci/run does this when run as root)")


def emulator_missing() -> str | None:
    """Why the emulated board cannot run here (the missing tools), or None when it can."""
    missing = [name for name, ok in (
        ("arduino-builder", shutil.which("arduino-builder")),
        ("avr-g++ (gcc-avr)", shutil.which("avr-g++")),
        ("arduino-core-avr", (ARDUINO_HARDWARE / "arduino" / "avr").is_dir()),
        ("gcc", shutil.which("gcc")),
        ("libsimavr-dev", (SIMAVR_INCLUDE / "sim_avr.h").is_file()),
    ) if not ok]
    if missing:
        return f"the AVR emulator is absent ({', '.join(missing)}); {INSTALL_HINT}"
    return None


def build_firmware(build: Path) -> Path:
    """Compile the sketch for the Nano (ATmega328P, 16 MHz) into ``build``; returns the ELF."""
    build.mkdir(parents=True, exist_ok=True)
    command = ["arduino-builder", "-hardware", str(ARDUINO_HARDWARE), "-hardware", str(BUILDER_TOOLS), "-tools",
               str(BUILDER_TOOLS), "-tools", "/usr/bin", "-fqbn", "arduino:avr:nano:cpu=atmega328",
               "-prefs=compiler.cpp.extra_flags=-DDECIMAL_DIG=__DECIMAL_DIG__", "-build-path", str(build),
               str(firmware_path())]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    elf = build / "psmini_leds.ino.elf"
    if result.returncode != 0 or not elf.is_file():
        raise RuntimeError(f"arduino-builder failed: {result.stdout[-2000:]}{result.stderr[-2000:]}")
    return elf


def build_bridge(build: Path) -> Path:
    """Compile the simavr bridge into ``build``; returns the program."""
    build.mkdir(parents=True, exist_ok=True)
    program = build / "avr_bridge"
    command = ["gcc", "-O2", "-Wall", "-Wextra", "-Werror", f"-I{SIMAVR_INCLUDE}", "-o", str(program),
               str(BRIDGE_SOURCE), "-lsimavr", "-lutil"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        raise RuntimeError(f"building the simavr bridge failed: {result.stderr[-3000:]}")
    return program


@dataclass(frozen=True)
class Line:
    """A reply line the AVR sent: its bytes (with ``\\r\\n``), the cycles of its first and last byte, and the LED
    pins (bit i = LED i) when its last byte went out."""

    data: bytes
    start: int
    end: int
    pins: int


def mask_of(lit: int | str | None, led_count: int = 8) -> int:
    """The pin mask of a lit state (``None``, an LED index, ``"all"``)."""
    if lit is None:
        return 0
    if lit == "all":
        return (1 << led_count) - 1
    return 1 << int(lit)


def lit_of(mask: int, led_count: int = 8) -> int | str | None:
    """The lit state a pin mask shows; ValueError for a mask the firmware should never set (two LEDs)."""
    if mask == 0:
        return None
    if mask == (1 << led_count) - 1:
        return "all"
    if mask & (mask - 1) == 0:
        return mask.bit_length() - 1
    raise ValueError(f"LED pins {mask:08b}: neither one LED, all nor none")


class EmulatedBoard:
    """The compiled sketch on simavr behind a pseudo-terminal, with its pins and UART recorded.

    Args:
        bridge: the program from :func:`build_bridge`.
        elf: the firmware from :func:`build_firmware`.
        boot_ms: emulated time the "bootloader" holds the AVR after the reset on port open, ms.
        speed: the emulated clock never runs ahead of ``speed`` x the wall clock (0: free-running).
    """

    def __init__(self, bridge: Path, elf: Path, *, boot_ms: int = 0, speed: float = 1.0, baud: int = 115200) -> None:
        self._process = subprocess.Popen(
            [str(bridge), str(elf), "--boot-ms", str(boot_ms), "--speed", str(speed), "--baud", str(baud)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
        self.port = ""
        for _ in range(10):  # simavr's own "Loaded ..." lines come first
            line = self._process.stdout.readline()
            if line.startswith("PTY "):
                self.port = line.split()[1]
                break
        if not self.port:
            self._process.kill()
            raise RuntimeError(f"the simavr bridge did not start: {self._process.stderr.read()[-2000:]}")
        self._lock = threading.Condition()
        self.pin_events: list[tuple[int, int]] = [(0, 0)]  # (cycle, mask)
        self.rx: list[tuple[int, int]] = []  # bytes the AVR received: (cycle, byte)
        self.tx: list[tuple[int, int]] = []  # bytes the AVR sent
        self.other_pins: list[tuple[int, str, int]] = []  # writes to pins other than D2..D9: (cycle, pin, value)
        self.opens: list[int] = []
        self.closes: list[int] = []
        self.starts: list[int] = []
        self.clock = 0  # the latest cycle the bridge reported
        self.pending = 0  # host bytes not yet clocked into the AVR
        self._answers = 0
        self._thread = threading.Thread(target=self._read_events, daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------ events

    def _read_events(self) -> None:
        for line in self._process.stdout:
            kind, _, rest = line.partition(" ")
            fields = rest.split()
            with self._lock:
                if kind == "P":
                    self.pin_events.append((int(fields[0]), int(fields[1])))
                elif kind == "R":
                    self.rx.append((int(fields[0]), int(fields[1], 16)))
                elif kind == "T":
                    self.tx.append((int(fields[0]), int(fields[1], 16)))
                elif kind in ("K", "A"):
                    self.clock, self.pending = int(fields[0]), int(fields[1])
                    self._answers += kind == "A"
                elif kind == "U":
                    self.other_pins.append((int(fields[0]), fields[1], int(fields[2])))
                elif kind == "O":
                    self.opens.append(int(fields[0]))
                elif kind == "C":
                    self.closes.append(int(fields[0]))
                elif kind == "S":
                    self.starts.append(int(fields[0]))
                self._lock.notify_all()
        with self._lock:
            self._answers = -1  # ended
            self._lock.notify_all()

    def sync(self, timeout_s: float = 10.0) -> int:
        """Wait until every event up to now is recorded; returns the emulated cycle."""
        with self._lock:
            answers = self._answers
            self._process.stdin.write("t\n")
            self._process.stdin.flush()
            if not self._lock.wait_for(lambda: self._answers != answers, timeout_s) or self._answers < 0:
                raise RuntimeError(f"the simavr bridge stopped answering: {self._process.stderr.read()[-2000:]}")
            return self.clock

    def wait_cycles(self, cycles: int, timeout_s: float = 60.0) -> int:
        """Let ``cycles`` emulated cycles pass (from now); returns the cycle reached."""
        target = self.sync() + cycles
        deadline = time.monotonic() + timeout_s
        while self.clock < target:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the emulator did not reach cycle {target} within {timeout_s} s")
            time.sleep(0.002)
            self.sync()
        return self.clock

    def wait_ms(self, ms: float) -> int:
        return self.wait_cycles(round(ms * HZ / 1000))

    def settle(self, quiet_ms: float = 4.0, timeout_s: float = 60.0) -> int:
        """Wait until the host's bytes are all clocked in and the AVR has sent nothing for ``quiet_ms``
        (emulated); returns the cycle."""
        deadline = time.monotonic() + timeout_s
        quiet = round(quiet_ms * HZ / 1000)
        while time.monotonic() < deadline:
            now = self.sync()
            with self._lock:
                last = max(self.tx[-1][0] if self.tx else 0, self.rx[-1][0] if self.rx else 0)
                if self.pending == 0 and now - last >= quiet:
                    return now
            time.sleep(0.002)
        raise RuntimeError(f"the emulated board did not settle within {timeout_s} s")

    # ------------------------------------------------------------------------------------------ state

    def pins_at(self, cycle: int) -> int:
        """The LED pin mask at emulated ``cycle``."""
        with self._lock:
            index = bisect.bisect_right(self.pin_events, (cycle, 1 << 30)) - 1
            return self.pin_events[max(index, 0)][1]

    @property
    def pins(self) -> int:
        """The LED pin mask now (after a sync)."""
        self.sync()
        with self._lock:
            return self.pin_events[-1][1]

    @property
    def lit(self) -> int | str | None:
        """What the pins show, in :class:`~data_synth.simulated_rig.SimulatedDevice`'s terms (for the simulated
        camera): None, an LED index or ``"all"``."""
        return lit_of(self.pins)

    def dark_since(self, cycle: int) -> int | None:
        """The cycle from which every LED pin has stayed low, if that is after ``cycle`` (a transient low while
        the sketch switches from one LED to another does not count); None while an LED is lit."""
        self.sync()
        with self._lock:
            if self.pin_events[-1][1] != 0:
                return None
            index = len(self.pin_events) - 1
            while index > 0 and self.pin_events[index - 1][1] == 0:
                index -= 1
            return self.pin_events[index][0] if self.pin_events[index][0] > cycle else None

    def lines(self, since: int = 0) -> list[Line]:
        """The lines the AVR sent from cycle ``since`` on (a trailing incomplete line is left out)."""
        self.sync()
        with self._lock:
            sent = [(c, b) for c, b in self.tx if c >= since]
        result, current, start = [], bytearray(), 0
        for cycle, byte in sent:
            if not current:
                start = cycle
            current.append(byte)
            if byte == 0x0A:
                result.append(Line(bytes(current), start, cycle, self.pins_at(cycle)))
                current = bytearray()
        return result

    def received_lines(self, since: int = 0) -> list[tuple[int, bytes]]:
        """The lines the AVR received from cycle ``since`` on: (cycle of the ``\\n``, bytes)."""
        self.sync()
        with self._lock:
            got = [(c, b) for c, b in self.rx if c >= since]
        result, current = [], bytearray()
        for cycle, byte in got:
            current.append(byte)
            if byte == 0x0A:
                result.append((cycle, bytes(current)))
                current = bytearray()
        return result

    def close(self) -> None:
        if self._process.poll() is None:
            try:
                self._process.stdin.write("q\n")
                self._process.stdin.flush()
                self._process.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                self._process.kill()
                self._process.wait(timeout=5)
        self._thread.join(timeout=5)

    def __enter__(self) -> EmulatedBoard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def ms(cycles: int) -> float:
    """Emulated cycles in ms."""
    return cycles * 1000 / HZ
