"""The line protocol of the psmini-leds firmware: constants, commands, and the parsing of its lines.

Shared by the host (:mod:`psmini.rig.controller`) and the simulated device (:mod:`data_synth.simulated_rig`), and
kept in step with the Arduino sketch ``psmini/rig/firmware/psmini_leds/psmini_leds.ino`` (a test compares the
constants). The full specification is ``docs/rig-protocol.md``; in short, ASCII lines at 115200 baud, one
reply line per command line::

    READY psmini-leds 1.0.0 leds=8 wdt=2000     after reset
    PING        -> OK PING
    ID?         -> OK ID psmini-leds 1.0.0 leds=8 wdt=2000
    ON 3        -> OK ON 3        (exactly LED 3 lit)
    ALL         -> OK ALL
    OFF         -> OK OFF
    STATE?      -> OK STATE on=3 wdt=2000 trips=0
    WDT 500     -> OK WDT 500
    FOO         -> ERR 1 unknown command
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from psmini.errors import RigError

__all__ = [
    "FIRMWARE_NAME",
    "FIRMWARE_VERSION",
    "BAUDRATE",
    "MAX_LINE",
    "LED_COUNT",
    "WATCHDOG_DEFAULT_MS",
    "WATCHDOG_RANGE_MS",
    "ERROR_CODES",
    "Identity",
    "Reply",
    "DeviceState",
    "encode_command",
    "parse_identity",
    "parse_banner",
    "parse_reply",
    "parse_state",
]

FIRMWARE_NAME = "psmini-leds"
FIRMWARE_VERSION = "1.0.0"
BAUDRATE = 115200
#: Characters of one command line, without its line end; longer lines get ``ERR 3``.
MAX_LINE = 32
#: LEDs of the sketch as shipped (pins D2..D9).
LED_COUNT = 8
WATCHDOG_DEFAULT_MS = 2000
WATCHDOG_RANGE_MS = (100, 60000)
#: ``ERR <code> <message>`` codes.
ERROR_CODES = {1: "unknown command", 2: "bad argument", 3: "line too long", 4: "non-ASCII byte"}

_IDENTITY = re.compile(r"^(?P<name>[A-Za-z0-9_.-]+) (?P<version>\d+\.\d+\.\d+) leds=(?P<leds>\d+) wdt=(?P<wdt>\d+)$")
_STATE = re.compile(r"^on=(?P<on>-|all|\d+) wdt=(?P<wdt>\d+) trips=(?P<trips>\d+)$")
_VERB = re.compile(r"^[A-Z]+\??$")


@dataclass(frozen=True)
class Identity:
    """What the firmware says about itself (READY banner, ``ID?``).

    Attributes:
        name: firmware name (``psmini-leds``).
        version: firmware version, ``MAJOR.MINOR.PATCH``.
        led_count: number of LEDs it drives.
        watchdog_ms: its watchdog timeout, ms.
    """

    name: str
    version: str
    led_count: int
    watchdog_ms: int

    def __str__(self) -> str:
        return f"{self.name} {self.version} leds={self.led_count} wdt={self.watchdog_ms}"


@dataclass(frozen=True)
class Reply:
    """One reply line.

    Attributes:
        ok: True for ``OK ...``, False for ``ERR ...``.
        verb: the command the reply answers (``PING``, ``ON``...) for ``OK``; empty for ``ERR``.
        text: what follows the verb (``OK ON 3`` → ``"3"``) or the error message.
        code: the error code of ``ERR`` (0 for ``OK``).
        line: the whole line.
    """

    ok: bool
    verb: str
    text: str
    code: int
    line: str


@dataclass(frozen=True)
class DeviceState:
    """The answer to ``STATE?``.

    Attributes:
        lit: the LED lit (index), ``None`` for none, ``"all"`` for every LED.
        watchdog_ms: the watchdog timeout, ms.
        trips: how many times the watchdog has switched the LEDs off since reset.
    """

    lit: int | str | None
    watchdog_ms: int
    trips: int


def encode_command(verb: str, *args: int) -> bytes:
    """One command line as the bytes to write (ASCII, ``\\n``-terminated).

    Args:
        verb: ``PING``, ``ID?``, ``ON``, ``ALL``, ``OFF``, ``STATE?`` or ``WDT``.
        args: integer arguments (``ON 3``, ``WDT 500``).

    Returns:
        the line, e.g. ``b"ON 3\\n"``.

    Raises:
        RigError: for a verb that is not upper-case letters (with an optional ``?``), a non-integer argument,
            or a line longer than :data:`MAX_LINE`.

    Example:
        >>> encode_command("ON", 3)
        b'ON 3\\n'
    """
    if not _VERB.match(verb):
        raise RigError(f"a command verb is upper-case letters with an optional '?', got {verb!r}")
    if any(isinstance(a, bool) or not isinstance(a, int) or a < 0 for a in args):
        raise RigError(f"command arguments must be non-negative integers, got {args!r}")
    line = " ".join([verb, *map(str, args)])
    if len(line) > MAX_LINE:
        raise RigError(f"command {line!r} is {len(line)} characters; the firmware takes at most {MAX_LINE}")
    return (line + "\n").encode("ascii")


def parse_identity(text: str) -> Identity | None:
    """The identity in ``"psmini-leds 1.0.0 leds=8 wdt=2000"``, or None when the text is not one.

    Example:
        >>> parse_identity("psmini-leds 1.0.0 leds=8 wdt=2000").led_count
        8
    """
    match = _IDENTITY.match(text)
    if match is None:
        return None
    return Identity(match["name"], match["version"], int(match["leds"]), int(match["wdt"]))


def parse_banner(line: str) -> Identity | None:
    """The identity of a ``READY ...`` banner line, or None when the line is not a banner.

    Example:
        >>> str(parse_banner("READY psmini-leds 1.0.0 leds=8 wdt=2000"))
        'psmini-leds 1.0.0 leds=8 wdt=2000'
    """
    if not line.startswith("READY "):
        return None
    return parse_identity(line[len("READY "):])


def parse_reply(line: str) -> Reply | None:
    """A reply line (``OK VERB [text]`` or ``ERR code message``), or None when the line is neither.

    Args:
        line: one line, without its line end.

    Returns:
        the :class:`Reply`, or None for anything else (noise, a banner).

    Example:
        >>> parse_reply("OK ON 3").text
        '3'
        >>> parse_reply("ERR 2 led index out of range").code
        2
    """
    if line.startswith("OK "):
        verb, _, text = line[3:].partition(" ")
        return Reply(True, verb, text, 0, line) if verb else None
    if line.startswith("ERR "):
        code, _, message = line[4:].partition(" ")
        return Reply(False, "", message, int(code), line) if code.isdigit() else None
    return None


def parse_state(text: str) -> DeviceState:
    """The state in the text of ``OK STATE on=3 wdt=2000 trips=0``.

    Raises:
        RigError: when the text does not have that form.

    Example:
        >>> parse_state("on=all wdt=2000 trips=1").lit
        'all'
    """
    match = _STATE.match(text)
    if match is None:
        raise RigError(f"expected a state 'on=<i|-|all> wdt=<ms> trips=<n>', got {text!r}")
    on = match["on"]
    lit: int | str | None = None if on == "-" else on if on == "all" else int(on)
    return DeviceState(lit, int(match["wdt"]), int(match["trips"]))
