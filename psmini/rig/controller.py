"""The host side of the LED controller: the psmini-leds protocol over any pyserial transport.

:class:`LEDController` opens its port with :func:`serial.serial_for_url`, so a real port (``/dev/ttyUSB0``,
``COM3``), a pseudo-terminal, the simulator's URL (``psminisim://``) and pyserial's own test URLs
(``loop://``) all work; an already-open pyserial object can be passed instead. Everything written is bytes.

Opening the port resets most Arduino boards (DTR), so the handshake waits for the READY banner with a timeout
rather than sleeping a fixed time; a board that does not reset (DTR disabled) is asked ``ID?`` instead. Each
command waits for its own reply (stale replies to earlier commands are skipped) within a per-command timeout,
is sent once more on a timeout or a garbled reply, then fails with a :class:`~psmini.errors.RigError` naming
the cause. The LEDs are switched off when the controller closes, whatever ended the session (error, Ctrl-C);
if even that fails, the firmware's watchdog switches them off after its timeout.
"""

from __future__ import annotations

import importlib.metadata
import logging
import math
import time
from types import TracebackType
from typing import Any, Protocol

import serial

from psmini.errors import RigError
from psmini.rig.protocol import (
    BAUDRATE,
    FIRMWARE_NAME,
    WATCHDOG_RANGE_MS,
    DeviceState,
    Identity,
    Reply,
    encode_command,
    parse_banner,
    parse_identity,
    parse_reply,
    parse_state,
)

__all__ = ["LEDController", "open_port"]

logger = logging.getLogger(__name__)

# Other packages serve URL schemes of their own (the simulated rig of data_synth: psminisim://) by naming a
# pyserial handler package in the "psmini.serial_url_handlers" entry-point group; the rig adapter itself
# depends on none of them.
for _entry in importlib.metadata.entry_points(group="psmini.serial_url_handlers"):
    if _entry.value not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(_entry.value)

class SerialPort(Protocol):
    """What the controller asks of an open pyserial port. Every port class that :func:`serial.serial_for_url` returns
    (pyserial's own, ``loop://``, a URL handler's) has it; their common base ``SerialBase`` declares neither
    ``in_waiting`` nor ``reset_input_buffer``."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1, /) -> bytes: ...

    def write(self, data: bytes, /) -> int | None: ...

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


#: Read slice, s: how long one read of the port may block while a deadline is watched.
_POLL_S = 0.01

try:  # pyserial's POSIX ports let termios errors through from tcdrain and tcflush on a vanished device
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # Windows
    _PORT_ERRORS = (serial.SerialException, OSError)


def open_port(url: str, baudrate: int = BAUDRATE, write_timeout_s: float = 1.0) -> SerialPort:
    """Open ``url`` with :func:`serial.serial_for_url` (short read timeout: the controller keeps deadlines).

    Raises:
        RigError: when the port cannot be opened (missing device, permissions, unknown URL scheme).

    Example:
        >>> port = open_port("loop://")
        >>> port.is_open
        True
    """
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=_POLL_S, write_timeout=write_timeout_s)
    except (serial.SerialException, ValueError, OSError) as error:
        raise RigError(f"cannot open the LED controller port {url!r}: {error}") from error


class LEDController:
    """The rig's LED controller (psmini-leds firmware) over a pyserial port.

    Use it as a context manager: the handshake runs on entry, and the LEDs are switched off on exit whatever
    happened inside (an error, Ctrl-C).

    Args:
        port: a port name or URL for :func:`serial.serial_for_url`, or an open pyserial object (closed with the
            controller).
        baudrate: serial speed (the firmware's is 115200).
        handshake_timeout_s: how long to wait for the READY banner after opening, s (a Nano's bootloader
            takes about 1.6 s after the reset that opening the port causes).
        command_timeout_s: how long to wait for the reply to one command, s.
        retries: how many times a command is sent again after a timeout or a garbled reply.
        watchdog_ms: set the firmware's watchdog to this timeout after the handshake (None: keep its own).

    Raises:
        RigError: for bad arguments: a port that is neither a name nor a port object, timeouts that are not
            positive and finite, negative retries, a watchdog out of range.

    Example:
        >>> from data_synth.simulated_rig import SimulatedDevice, serve_url
        >>> with LEDController(serve_url(SimulatedDevice()), handshake_timeout_s=0.5) as leds:
        ...     leds.on(3)
        ...     leds.state().lit
        3
    """

    def __init__(
        self,
        port: str | SerialPort,
        *,
        baudrate: int = BAUDRATE,
        handshake_timeout_s: float = 3.0,
        command_timeout_s: float = 0.5,
        retries: int = 1,
        watchdog_ms: int | None = None,
    ) -> None:
        if not isinstance(port, str) and not all(hasattr(port, name) for name in ("read", "write", "close")):
            raise RigError(f"port must be a port name or URL (a str such as '/dev/ttyUSB0', 'COM3') or an open "
                           f"pyserial port, got {port!r}")
        for name, value in (("handshake_timeout_s", handshake_timeout_s), ("command_timeout_s", command_timeout_s)):
            # finite: an infinite deadline waits forever on a silent device instead of naming the timeout
            if not (isinstance(value, (int, float)) and 0 < value < math.inf):
                raise RigError(f"{name} must be a positive, finite number of seconds, got {value!r}")
        if not isinstance(retries, int) or retries < 0:
            raise RigError(f"retries must be an integer >= 0, got {retries!r}")
        low, high = WATCHDOG_RANGE_MS
        if watchdog_ms is not None and not (isinstance(watchdog_ms, int) and low <= watchdog_ms <= high):
            raise RigError(f"watchdog_ms must be an integer in {low}..{high}, got {watchdog_ms!r}")
        self._port_arg = port
        self.name = port if isinstance(port, str) else str(getattr(port, "port", None) or type(port).__name__)
        self.baudrate = baudrate
        self.handshake_timeout_s = float(handshake_timeout_s)
        self.command_timeout_s = float(command_timeout_s)
        self.retries = retries
        self.watchdog_ms = watchdog_ms
        self.identity: Identity | None = None
        self.lit: int | str | None = None
        self._serial: SerialPort | None = None
        self._buffer = bytearray()
        self._last_sent = 0.0

    # ---------------------------------------------------------------------------------------- life cycle

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    @property
    def led_count(self) -> int:
        """LEDs the firmware drives (from its banner)."""
        return self._identity().led_count

    def open(self) -> Identity:
        """Open the port and shake hands: wait for READY (or ask ``ID?``), then set the watchdog.

        Returns:
            the firmware's :class:`~psmini.rig.protocol.Identity`.

        Raises:
            RigError: the port cannot be opened; no banner within the handshake timeout and no answer to
                ``ID?``; a firmware other than psmini-leds.
        """
        if self._serial is not None:
            return self._identity()
        self._serial = open_port(self._port_arg, self.baudrate) if isinstance(self._port_arg, str) else self._port_arg
        try:
            self.identity = self._handshake()
            if self.watchdog_ms is not None:
                self.set_watchdog(self.watchdog_ms)
        except BaseException:
            self._close_port()
            raise
        logger.info("LED controller on %s: %s", self.name, self.identity)
        return self.identity

    def close(self) -> None:
        """Switch the LEDs off and close the port. Never raises: a failure to switch off is logged (the
        firmware's watchdog then switches them off)."""
        if self._serial is None:
            return
        try:
            self.off()
        except RigError as error:
            watchdog = self.identity.watchdog_ms if self.identity else None
            logger.warning("could not switch the LEDs off on %s (%s); the firmware watchdog switches them off after "
                           "%s ms of silence", self.name, error, watchdog)
        finally:
            self._close_port()

    def __enter__(self) -> LEDController:
        self.open()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()

    def _close_port(self) -> None:
        port, self._serial = self._serial, None
        if port is None:
            return
        try:
            port.close()
        except _PORT_ERRORS as error:  # a vanished device: nothing left to close
            logger.debug("closing %s: %s", self.name, error)

    def _identity(self) -> Identity:
        if self.identity is None:
            raise RigError(f"the LED controller on {self.name} is not open; call open() or use it in a with block")
        return self.identity

    # ------------------------------------------------------------------------------------------ commands

    def ping(self) -> None:
        """``PING``: check the firmware answers (and feed its watchdog)."""
        self.command("PING")

    def identify(self) -> Identity:
        """``ID?``: the firmware's identity."""
        reply = self.command("ID?")
        identity = parse_identity(reply.text)
        if identity is None:
            raise RigError(f"LED controller on {self.name}: cannot parse the identity in {reply.line!r}")
        return identity

    def on(self, led: int) -> None:
        """``ON i``: light exactly LED ``led`` (0-based)."""
        count = self.led_count
        if isinstance(led, bool) or not isinstance(led, int) or not 0 <= led < count:
            raise RigError(f"LED index must be an integer in 0..{count - 1}, got {led!r}")
        self.command("ON", led)
        self.lit = led

    def all_on(self) -> None:
        """``ALL``: light every LED (focus sweeps, alignment)."""
        self.command("ALL")
        self.lit = "all"

    def off(self) -> None:
        """``OFF``: switch every LED off."""
        self.command("OFF")
        self.lit = None

    def state(self) -> DeviceState:
        """``STATE?``: what is lit, the watchdog timeout and how often it tripped."""
        return parse_state(self.command("STATE?").text)

    def set_watchdog(self, timeout_ms: int) -> None:
        """``WDT ms``: switch the LEDs off after ``timeout_ms`` without a command line."""
        low, high = WATCHDOG_RANGE_MS
        if isinstance(timeout_ms, bool) or not isinstance(timeout_ms, int) or not low <= timeout_ms <= high:
            raise RigError(f"watchdog timeout must be an integer in {low}..{high} ms, got {timeout_ms!r}")
        self.command("WDT", timeout_ms)
        self.identity = Identity(self._identity().name, self._identity().version, self._identity().led_count,
                                 timeout_ms)

    def keepalive(self) -> None:
        """``PING`` when a third of the watchdog timeout has passed since the last command, so that a lit LED
        stays lit through long camera reads."""
        if time.monotonic() - self._last_sent > self._identity().watchdog_ms / 3000:
            self.ping()

    def command(self, verb: str, *args: int) -> Reply:
        """Send one command and return its ``OK`` reply; send it again once after a timeout or garbled reply.

        Args:
            verb: the command (``PING``, ``ID?``, ``ON``, ``ALL``, ``OFF``, ``STATE?``, ``WDT``).
            args: its integer arguments.

        Returns:
            the :class:`~psmini.rig.protocol.Reply`.

        Raises:
            RigError: the firmware answered ``ERR`` (its message is quoted); no reply within the command
                timeout on every try; garbled replies on every try; the board reset (a READY banner); the port
                failed (disconnected).
        """
        line = encode_command(verb, *args)
        text = line.decode().strip()
        port = self._port()
        cause = ""
        for attempt in range(1 + self.retries):
            if attempt:
                logger.warning("LED controller on %s: %s; sending %r again", self.name, cause, text)
                self._discard_input(port)
            self._write(port, line)
            try:
                return self._await_reply(port, verb.rstrip("?"), text)
            except _Retry as retry:
                cause = str(retry)
        raise RigError(f"LED controller on {self.name}: command {text!r} failed after {1 + self.retries} tries: "
                       f"{cause}")

    # ------------------------------------------------------------------------------------------ plumbing

    def _port(self) -> SerialPort:
        if self._serial is None:
            raise RigError(f"the LED controller on {self.name} is not open; call open() or use it in a with block")
        return self._serial

    def _handshake(self) -> Identity:
        port = self._port()
        deadline = time.monotonic() + self.handshake_timeout_s
        seen: list[bytearray] = []
        while True:
            raw = self._read_line(port, deadline)
            if raw is None:
                break
            identity = parse_banner(_text(raw) or "")
            if identity is not None:
                self._check_firmware(identity)
                self._discard_input(port)
                return identity
            seen.append(raw)  # bootloader noise or line junk before the banner
        # A board whose DTR reset is disabled does not print the banner again: ask it.
        logger.info("no READY banner from %s within %.2f s; asking ID?", self.name, self.handshake_timeout_s)
        self._discard_input(port)
        self._write(port, encode_command("ID?"))
        try:
            reply = self._await_reply(port, "ID", "ID?")
        except _Retry as retry:
            got = f"; before it: {seen[:3]!r}" if seen else ""
            raise RigError(f"LED controller on {self.name}: no READY banner within {self.handshake_timeout_s:g} s "
                           f"and no answer to ID? ({retry}){got}; is the psmini-leds firmware flashed and the "
                           "port right?") from None
        identity = parse_identity(reply.text)
        if identity is None:
            raise RigError(f"LED controller on {self.name}: cannot parse the identity in {reply.line!r}")
        self._check_firmware(identity)
        return identity

    def _check_firmware(self, identity: Identity) -> None:
        if identity.name != FIRMWARE_NAME:
            raise RigError(f"the device on {self.name} runs {identity.name!r}, expected the {FIRMWARE_NAME!r} firmware")
        if identity.version.split(".")[0] != "1":
            raise RigError(f"the device on {self.name} runs {identity}, a protocol version this host does not speak "
                           "(1.x)")
        low, high = WATCHDOG_RANGE_MS
        if not low <= identity.watchdog_ms <= high:
            # psmini-leds keeps its watchdog in this range; outside it (0: none) a crashed host leaves the LEDs lit
            raise RigError(f"the device on {self.name} reports a watchdog of {identity.watchdog_ms} ms, outside the "
                           f"protocol's {low}..{high} ms: not the psmini-leds firmware, or a damaged build of it")

    def _await_reply(self, port: SerialPort, expected: str, text: str) -> Reply:
        deadline = time.monotonic() + self.command_timeout_s
        while True:
            raw = self._read_line(port, deadline)
            if raw is None:
                raise _Retry(f"no reply within {self.command_timeout_s:g} s")
            line = _text(raw)
            if line is None:
                raise _Retry(f"garbled reply {bytes(raw)!r}")
            if parse_banner(line) is not None:
                self.lit = None
                raise RigError(f"LED controller on {self.name}: the board reset during the session (READY banner in "
                               f"reply to {text!r}); check its power supply and USB cable")
            if line == text:
                raise _Retry(f"the port echoed {text!r} back (a loopback or a terminal with echo, not the firmware)")
            reply = parse_reply(line)
            if reply is None:
                raise _Retry(f"garbled reply {line!r}")
            if not reply.ok:
                raise RigError(f"LED controller on {self.name} refused {text!r}: {reply.line}")
            if reply.verb == expected:
                return reply
            logger.debug("skipping a stale reply %r while waiting for %r", line, text)

    def _read_line(self, port: SerialPort, deadline: float) -> bytearray | None:
        """The next line without its end (``\\r`` removed), or None at the deadline."""
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                raw = self._buffer[:end].replace(b"\r", b"")
                del self._buffer[: end + 1]
                return raw
            if time.monotonic() >= deadline:
                return None
            self._buffer += self._read(port)

    def _read(self, port: SerialPort) -> bytes:
        try:
            return port.read(max(1, port.in_waiting))
        except _PORT_ERRORS as error:
            raise RigError(f"LED controller on {self.name} disconnected: {error}") from error

    def _write(self, port: SerialPort, line: bytes) -> None:
        try:
            port.write(line)
            port.flush()
        except serial.SerialTimeoutException as error:
            raise RigError(f"LED controller on {self.name}: writing {line!r} timed out ({error})") from error
        except _PORT_ERRORS as error:
            raise RigError(f"LED controller on {self.name} disconnected: {error}") from error
        self._last_sent = time.monotonic()

    def _discard_input(self, port: SerialPort) -> None:
        self._buffer.clear()
        try:
            port.reset_input_buffer()
        except _PORT_ERRORS as error:
            raise RigError(f"LED controller on {self.name} disconnected: {error}") from error

    def __repr__(self) -> str:
        state: Any = self.identity if self.identity is not None else "closed"
        return f"LEDController({self.name!r}, {state})"


class _Retry(Exception):
    """A failure worth sending the command again for (timeout, garbled reply); internal."""


def _text(raw: bytes | bytearray) -> str | None:
    """The line as printable ASCII text, or None when it holds any other byte."""
    try:
        text = bytes(raw).decode("ascii")
    except UnicodeDecodeError:
        return None
    return text if text.isprintable() else None
