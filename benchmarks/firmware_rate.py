"""The psmini-leds sketch's limits, measured on the emulated ATmega328P (simavr, 16 MHz) at 115200 baud.

Times are emulated: the AVR's cycle counter / 16 MHz, i.e. the board's own, whatever the load of this machine.

- Round trip per command through psmini's LEDController (pyserial on the bridge's pseudo-terminal): from the start
  bit of the command's first byte to the stop bit of the reply's last byte, and what it allows: commands/s when
  each command waits for its reply (the LEDController's way, host latency excluded).
- Sustained rate of pipelined commands (sent in one write, not waiting for replies), and the most commands a host
  may pipeline before the 64-byte receive buffer overflows (bytes are then lost).
- The longest line accepted, and the watchdog's timing, beside the protocol's documented timeouts.

Run: ``python benchmarks/firmware_rate.py`` (needs arduino-builder, gcc-avr, simavr, libsimavr-dev; a few minutes).
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import serial  # noqa: E402

from benchmarks._ledger import append_results, table  # noqa: E402
from psmini.rig import LEDController  # noqa: E402
from psmini.rig.protocol import BAUDRATE, MAX_LINE, WATCHDOG_DEFAULT_MS  # noqa: E402
from tests.rig._avr_emulator import HZ, EmulatedBoard, build_bridge, build_firmware, emulator_missing, ms  # noqa: E402

BYTE_CYCLES = HZ * 10 / BAUDRATE  # one 8N1 frame from the host


def read_all(link: serial.Serial, board: EmulatedBoard) -> bytes:
    board.settle()
    data = b""
    while True:
        chunk = link.read(4096)
        if not chunk:
            return data
        data += chunk


def round_trips(board: EmulatedBoard, count: int = 200) -> tuple[list[float], float, float]:
    """Per command: emulated round trip, ms; the emulated and wall time of the whole run, s."""
    with LEDController(board.port, handshake_timeout_s=5.0, command_timeout_s=1.0) as leds:
        start, wall = board.sync(), time.perf_counter()
        for index in range(count):
            leds.on(index % 8)
        wall = time.perf_counter() - wall
        end = board.sync()
    received = [cycle for cycle, line in board.received_lines(start)][:count]  # the command's stop bit
    replies = [line for line in board.lines(start) if line.data.startswith(b"OK ON")][:count]
    trips = []
    # at most count of each; a command the board did not echo is not timed (stops at the shortest)
    for cycle, line, reply in zip(received, range(count), replies, strict=False):
        command_bytes = len(b"ON %d\n" % (line % 8))
        first_start_bit = cycle - command_bytes * BYTE_CYCLES
        trips.append(ms(reply.end + 10 * HZ / 117647 - first_start_bit))  # the reply's stop bit, at the AVR's baud
    return trips, (end - start) / HZ, wall


def pipelined(board: EmulatedBoard, link: serial.Serial, command: bytes, count: int) -> tuple[int, float]:
    """``count`` copies of ``command`` in one write: how many were answered correctly, and commands/s."""
    start = board.sync()
    link.write(command * count)
    replies = read_all(link, board)
    link.write(b"\n")  # end any partial line a lost line end left behind
    read_all(link, board)
    verb = command.split()[0].rstrip(b"?")
    good = [line for line in board.lines(start) if line.data.startswith(b"OK " + verb)]
    answered = sum(line.startswith(b"OK " + verb) for line in replies.split(b"\n"))
    received = board.received_lines(start)
    first = received[0][0] - len(command) * BYTE_CYCLES if received else start
    rate = len(good) / ((good[-1].end - first) / HZ) if good else 0.0
    return answered, rate


def main() -> None:
    reason = emulator_missing()
    if reason:
        sys.exit(reason)
    with tempfile.TemporaryDirectory() as tmp:
        bridge, elf = build_bridge(Path(tmp) / "bridge"), build_firmware(Path(tmp) / "firmware")
        with EmulatedBoard(bridge, elf) as board:
            trips, emulated_s, wall_s = round_trips(board)
        rows = []
        best = min(trips)
        rows.append(["round trip ON i via LEDController (emulated), ms", f"median {statistics.median(trips):.3f}, "
                     f"min {best:.3f}, max {max(trips):.3f}"])
        rows.append(["commands/s, each waiting for its reply (wire + firmware, host latency excluded)",
                     f"{1000 / statistics.median(trips):.0f}"])
        rows.append(["commands/s through LEDController here (emulated clock / wall clock)",
                     f"{len(trips) / emulated_s:.0f} / {len(trips) / wall_s:.0f}"])
        with EmulatedBoard(bridge, elf) as board, serial.Serial(board.port, BAUDRATE, timeout=0.01) as link:
            link.write(b"WDT 60000\n")  # no watchdog trip while the limits are measured
            read_all(link, board)  # the banner and OK WDT
            limits = {}
            for command in (b"PING\n", b"ON 3\n", b"STATE?\n"):
                largest = 0
                for count in range(8, 90):
                    answered, _ = pipelined(board, link, command, count)
                    if answered < count:
                        break
                    largest = count
                _, rate = pipelined(board, link, command, largest)
                limits[command] = largest
                rows.append([f"pipelined {command.decode().strip()!r}: most answered in full (bytes), sustained/s",
                             f"{largest} ({largest * len(command)} B), {rate:.0f}/s"])
            lengths = {}
            for length in (MAX_LINE - 1, MAX_LINE, MAX_LINE + 1):
                link.write(b"X" * length + b"\n")
                lengths[length] = read_all(link, board).strip().decode()
            longest = max((n for n, reply in lengths.items() if "too long" not in reply), default=0)
            rows.append(["longest line accepted (characters before the line end)",
                         f"{longest} ({MAX_LINE + 1}: {lengths[MAX_LINE + 1]!r})"])
            for timeout_ms in (100, 500, WATCHDOG_DEFAULT_MS):
                link.write(b"WDT %d\nON 1\n" % timeout_ms)
                read_all(link, board)
                quiet = board.received_lines()[-1][0]
                board.wait_ms(timeout_ms * 1.1)
                dark = board.dark_since(quiet)
                rows.append([f"watchdog {timeout_ms} ms: LEDs off after the last line, ms",
                             f"{ms(dark - quiet):.2f}" if dark else "never"])
        body = table(["measure (115200 baud, 8N1, emulated ATmega328P at 16 MHz)", "value"], rows)
        body += ("\n\nDocumented timeouts beside them: LEDController waits 0.5 s per command and 3 s for the banner; "
                 f"the watchdog's default is {WATCHDOG_DEFAULT_MS} ms. simavr ran this sketch at "
                 f"{emulated_s / wall_s:.2f}x real time here (the bridge never lets it run ahead of the wall "
                 "clock).")
        print(body)
        append_results("Firmware on the emulated Nano (simavr): round trip, sustained rate, limits", body)


if __name__ == "__main__":
    main()
