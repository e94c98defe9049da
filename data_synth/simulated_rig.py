"""A simulated rig: the psmini-leds firmware behind a pseudo-terminal or a pyserial URL, and a camera that
renders a :mod:`data_synth` fabric under whichever LED is lit, with faults to inject.

- :class:`SimulatedDevice` is the firmware's logic (the same protocol as the sketch, watchdog included) as a
  thread-safe state machine on a clock. The board resets when a host opens the port (DTR) and prints the
  READY banner after ``boot_s``.
- :class:`PtyLink` serves a device on a real pseudo-terminal (``pty.openpty`` and a thread), so the host goes
  through the operating system's serial path; :func:`serve_url` serves it as ``psminisim://NAME`` for
  :func:`serial.serial_for_url` (handled by :mod:`data_synth.urlhandler.protocol_psminisim`).
- :class:`SimulatedCapture` looks like :class:`cv2.VideoCapture` to :class:`~psmini.rig.camera.RigCamera`:
  640×480 BGR frames whose centre 400×400 is :func:`data_synth.rig.render_capture`'s image for the lit LED
  (each LED rendered once and cached), delayed by a driver queue of ``buffer_frames`` frames like a webcam's.
- :class:`SimulatedRig` puts them together with a movable scene: the fabric, the flat-field card, the mirror
  sphere.

Faults (:data:`FAULTS`), starting after ``fault_after`` command lines (device) or frames (camera):
``no-banner`` (dead firmware: no banner, no replies), ``timeout`` (replies lost: they come ``slow_s`` late),
``garbage`` (replies replaced by noise bytes), ``disconnect`` (the board vanishes; its LEDs lose power),
``no-frame`` (the camera returns nothing), ``stale-frame`` (the camera repeats its last frame forever).
"""

from __future__ import annotations

import argparse
import collections
import itertools
import logging
import os
import pty
import select
import threading
import time
import tty
from collections.abc import Callable
from types import TracebackType
from typing import Any

import cv2
import numpy as np
import torch

from psmini.errors import RigError
from psmini.rig.protocol import (
    FIRMWARE_NAME,
    FIRMWARE_VERSION,
    LED_COUNT,
    MAX_LINE,
    WATCHDOG_DEFAULT_MS,
    WATCHDOG_RANGE_MS,
)

__all__ = [
    "simulated_capture",
    "FAULTS",
    "DEVICE_FAULTS",
    "CAMERA_FAULTS",
    "SimulatedDevice",
    "PtyLink",
    "serve_url",
    "device_for_url",
    "SimulatedScene",
    "SimulatedCapture",
    "SimulatedRig",
]

logger = logging.getLogger(__name__)

DEVICE_FAULTS = ("no-banner", "timeout", "garbage", "disconnect")
CAMERA_FAULTS = ("no-frame", "stale-frame")
FAULTS = DEVICE_FAULTS + CAMERA_FAULTS


def _check_fault(fault: str | None, allowed: tuple[str, ...]) -> None:
    if fault is not None and fault not in allowed:
        raise RigError(f"unknown fault {fault!r}; expected one of {', '.join(allowed)}")


class SimulatedDevice:
    """The psmini-leds firmware as a state machine (see ``docs/rig-protocol.md``).

    Bytes go in with :meth:`receive`; reply bytes come out of :meth:`output` when due. Time comes from
    ``clock``; the watchdog is applied whenever the state is looked at.

    Args:
        led_count: LEDs driven.
        boot_s: delay between a reset and the READY banner, s (a Nano's bootloader: about 1.6 s).
        watchdog_ms: initial watchdog timeout, ms.
        fault: one of :data:`DEVICE_FAULTS`, or None.
        fault_after: command lines answered normally before the fault starts (``no-banner``: from reset).
        slow_s: how late replies come under the ``timeout`` fault, s.
        seed: seed of the ``garbage`` bytes.
        clock: monotonic time source, s.

    Example:
        >>> device = SimulatedDevice(boot_s=0.0)
        >>> device.reset(); device.output()
        b'READY psmini-leds 1.0.0 leds=8 wdt=2000\\r\\n'
        >>> device.receive(b"ON 2\\n"); device.output(), device.lit
        (b'OK ON 2\\r\\n', 2)
    """

    def __init__(self, led_count: int = LED_COUNT, *, boot_s: float = 0.05, watchdog_ms: int = WATCHDOG_DEFAULT_MS,
                 fault: str | None = None, fault_after: int = 4, slow_s: float = 5.0, seed: int = 0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        _check_fault(fault, DEVICE_FAULTS)
        if not isinstance(led_count, int) or not 1 <= led_count <= 99:
            raise RigError(f"led_count must be an integer in 1..99, got {led_count!r}")
        self.led_count, self.boot_s, self.initial_watchdog_ms = led_count, float(boot_s), int(watchdog_ms)
        self.fault, self.fault_after, self.slow_s = fault, int(fault_after), float(slow_s)
        self.clock = clock
        self.connected = True
        self.watchdog_trips = 0
        self.resets = 0
        self.history: list[str] = []  # every command line received, for tests and logs
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._lit: int | str | None = None
        self._pending: list[tuple[float, bytes]] = []
        self._line = bytearray()
        self._too_long = self._bad_byte = False
        self._commands = 0
        self.watchdog_ms = self.initial_watchdog_ms
        self._last_line = clock()

    # ------------------------------------------------------------------------------------------- state

    @property
    def lit(self) -> int | str | None:
        """The LED lit (index), ``"all"``, or None; the watchdog is applied first."""
        with self._lock:
            self._watchdog()
            return self._lit

    def reset(self) -> None:
        """What the board does when the host opens the port: restart with LEDs off, banner after ``boot_s``."""
        with self._lock:
            self.resets += 1
            self._lit = None
            self._line.clear()
            self._too_long = self._bad_byte = False
            self._pending.clear()
            self.watchdog_ms = self.initial_watchdog_ms
            self._last_line = self.clock()
            if self.fault != "no-banner" and self.connected:
                self._pending.append((self.clock() + self.boot_s, f"READY {self._identity()}\r\n".encode()))

    def unplug(self) -> None:
        """The board vanishes (USB pulled): its LEDs lose power, nothing more is received or sent."""
        with self._lock:
            self.connected = False
            self._lit = None
            self._pending.clear()

    def _identity(self) -> str:
        return f"{FIRMWARE_NAME} {FIRMWARE_VERSION} leds={self.led_count} wdt={self.watchdog_ms}"

    def _watchdog(self) -> None:
        # whole milliseconds, as millis() counts them
        if self._lit is not None and round((self.clock() - self._last_line) * 1000, 6) >= self.watchdog_ms:
            logger.info("simulated device: watchdog switched the LEDs off after %d ms of silence", self.watchdog_ms)
            self._lit = None
            self.watchdog_trips += 1

    # -------------------------------------------------------------------------------------------- bytes

    def receive(self, data: bytes) -> None:
        """Bytes from the host (any chunking), parsed like the firmware's loop() does."""
        with self._lock:
            if not self.connected or self.fault == "no-banner":
                return
            self._watchdog()
            for byte in data:
                if byte == 0x0A:
                    self._end_of_line()
                elif byte == 0x0D:
                    continue
                elif byte < 0x20 or byte > 0x7E:
                    self._bad_byte = True
                elif len(self._line) < MAX_LINE:
                    self._line.append(byte)
                else:
                    self._too_long = True
                if not self.connected:
                    return

    def output(self) -> bytes:
        """The reply bytes due by now."""
        with self._lock:
            now = self.clock()
            due = [chunk for when, chunk in self._pending if when <= now]
            self._pending = [(when, chunk) for when, chunk in self._pending if when > now]
            return b"".join(due)

    def replies_due(self) -> bool:
        """Whether a reply is due now that :meth:`output` has not handed over yet."""
        with self._lock:
            now = self.clock()
            return any(when <= now for when, _ in self._pending)

    def _end_of_line(self) -> None:
        self._last_line = self.clock()
        line = self._line.decode("ascii")
        self._line.clear()
        too_long, bad_byte = self._too_long, self._bad_byte
        self._too_long = self._bad_byte = False
        self.history.append(line)
        if too_long:
            reply = "ERR 3 line too long"
        elif bad_byte:
            reply = "ERR 4 non-ASCII byte"
        elif not line:
            return
        else:
            self._commands += 1
            if self.fault == "disconnect" and self._commands > self.fault_after:
                logger.info("simulated device: disconnecting (fault) at %r", line)
                self.unplug()
                return
            reply = self._execute(line)
        self._send(reply)

    def _send(self, reply: str) -> None:
        delay = 0.0
        data = (reply + "\r\n").encode("ascii")
        if self._commands > self.fault_after and self.fault == "timeout":
            delay = self.slow_s
        elif self._commands > self.fault_after and self.fault == "garbage":
            data = bytes(self._rng.integers(128, 256, size=12, dtype=np.uint8)) + b"\r\n"
        self._pending.append((self.clock() + delay, data))

    def _execute(self, line: str) -> str:
        argument = line.partition(" ")[2]
        if line == "PING":
            return "OK PING"
        if line == "ID?":
            return f"OK ID {self._identity()}"
        if line.startswith("ON "):
            if not (argument.isdigit() and len(argument) <= 5 and int(argument) < self.led_count):
                return "ERR 2 led index out of range"
            self._lit = int(argument)
            return f"OK ON {int(argument)}"
        if line == "ALL":
            self._lit = "all"
            return "OK ALL"
        if line == "OFF":
            self._lit = None
            return "OK OFF"
        if line == "STATE?":
            on = "-" if self._lit is None else str(self._lit)
            return f"OK STATE on={on} wdt={self.watchdog_ms} trips={self.watchdog_trips}"
        if line.startswith("WDT "):
            low, high = WATCHDOG_RANGE_MS
            if not (argument.isdigit() and len(argument) <= 5 and low <= int(argument) <= high):
                return "ERR 2 watchdog ms out of range 100..60000"
            self.watchdog_ms = int(argument)
            return f"OK WDT {self.watchdog_ms}"
        return "ERR 1 unknown command"


class PtyLink:
    """A :class:`SimulatedDevice` on a pseudo-terminal: the host opens :attr:`path` like a USB serial port.

    A thread moves bytes between the pty's master side and the device. Opening the slave side (seen as the
    end of the master's hang-up) resets the device, as DTR resets a Nano; an unplugged device closes the
    master, so the host's next read or write fails as with a pulled cable. The thread polls every ``poll_s``:
    a port closed and reopened faster than that may not reset the device (the host's ``ID?`` fallback still
    finds it).

    Example:
        >>> with PtyLink(SimulatedDevice()) as link:
        ...     link.path.startswith("/dev/")
        True
    """

    def __init__(self, device: SimulatedDevice, poll_s: float = 0.002) -> None:
        self.device, self.poll_s = device, poll_s
        self._master, slave = pty.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)  # held open, the slave would hide the host's open and close from the master
        self._stop = threading.Event()
        self._cycle = threading.Lock()  # held from a poll's wake-up until its replies are written
        self._thread = threading.Thread(target=self._serve, name=f"psmini-sim-pty {self.path}", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        host_open = False
        try:
            while not self._stop.is_set():
                events = dict(poller.poll(self.poll_s * 1000))
                hung_up = bool(events.get(self._master, 0) & select.POLLHUP)
                if hung_up:
                    host_open = False
                    time.sleep(self.poll_s)
                    continue
                with self._cycle:
                    if not host_open:
                        host_open = True
                        self.device.reset()
                    if events.get(self._master, 0) & select.POLLIN:
                        self.device.receive(os.read(self._master, 4096))
                    if not self.device.connected:
                        return
                    data = self.device.output()
                    if data:
                        os.write(self._master, data)
        except OSError as error:  # the host went away mid-transfer
            logger.debug("pty link %s: %s", self.path, error)
        finally:
            self._close_master()

    def idle(self) -> bool:
        """Whether the device has parsed every byte the host wrote and every reply due is written to the host's
        side: what a test waits for before it reads what a command brought, however late this thread runs."""
        with self._cycle:
            if self._master < 0:
                return True
            unread = bool(select.select([self._master], [], [], 0)[0])
            return not unread and not self.device.replies_due()

    def _close_master(self) -> None:
        master, self._master = self._master, -1
        if master >= 0:
            os.close(master)

    def close(self) -> None:
        """Stop the thread and close the pty."""
        self._stop.set()
        self._thread.join(timeout=2.0)

    def __enter__(self) -> PtyLink:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()


_URL_DEVICES: dict[str, SimulatedDevice] = {}
_URL_NAMES = itertools.count()


def serve_url(device: SimulatedDevice, name: str | None = None) -> str:
    """Make ``device`` reachable as ``psminisim://NAME`` through :func:`serial.serial_for_url`.

    Example:
        >>> serve_url(SimulatedDevice(), "doc")
        'psminisim://doc'
    """
    name = name or f"device{next(_URL_NAMES)}"
    _URL_DEVICES[name] = device
    return f"psminisim://{name}"


def device_for_url(url: str) -> SimulatedDevice:
    """The device behind a ``psminisim://`` URL: a served one by name, else a new one from the query.

    ``psminisim://?leds=8&fault=garbage&after=4&boot=0.05`` makes a fresh device with those settings.

    Raises:
        RigError: for another scheme, an unknown name, or bad query values.
    """
    from urllib.parse import parse_qs, urlsplit

    parts = urlsplit(url)
    if parts.scheme != "psminisim":
        raise RigError(f"expected a psminisim:// URL, got {url!r}")
    if parts.netloc:
        if parts.netloc not in _URL_DEVICES:
            raise RigError(f"no simulated device is served as {url!r}; served: {sorted(_URL_DEVICES)}")
        return _URL_DEVICES[parts.netloc]
    query = {key: values[-1] for key, values in parse_qs(parts.query).items()}
    unknown = set(query) - {"leds", "fault", "after", "boot", "wdt"}
    if unknown:
        raise RigError(f"unknown psminisim:// options {sorted(unknown)}; expected leds, fault, after, boot, wdt")
    try:
        return SimulatedDevice(int(query.get("leds", LED_COUNT)), fault=query.get("fault"),
                               fault_after=int(query.get("after", 4)), boot_s=float(query.get("boot", 0.05)),
                               watchdog_ms=int(query.get("wdt", WATCHDOG_DEFAULT_MS)))
    except ValueError as error:
        raise RigError(f"bad psminisim:// option in {url!r}: {error}") from error


class SimulatedScene:
    """What the simulated camera sees: a fabric, the flat-field card or the mirror sphere, under each LED.

    Each target is rendered once (all LEDs and the dark frame, :func:`data_synth.rig.render_capture`,
    :func:`~data_synth.rig.render_card`, :func:`~data_synth.rig.render_sphere`) and cached as 8-bit codes
    (a webcam's). The fabric and its noise use ``seed``, the card ``seed + 1`` (as
    :func:`data_synth.rig.write_synthetic_capture` does), so both match data_synth's own rendering.

    Args:
        fabric: a key of :data:`data_synth.FABRICS`.
        seed: seed of the fabric and its sensor noise.
        config: the rig (:class:`data_synth.rig.RigConfig`); its ``bit_depth`` is forced to 8.
        target: ``"sample"``, ``"card"`` or ``"sphere"``: what lies under the camera.
    """

    TARGETS = ("sample", "card", "sphere")

    def __init__(self, fabric: str = "jute", seed: int = 0, config: Any = None, target: str = "sample") -> None:
        from data_synth import FABRICS
        from data_synth.rig import RigConfig

        if fabric not in FABRICS:
            raise RigError(f"unknown fabric {fabric!r}; expected one of {', '.join(FABRICS)}")
        self.fabric_name, self.seed = fabric, int(seed)
        self.config = (config or RigConfig()).replace(bit_depth=8)
        self.target = target
        self.stage_z = 0.0  # lift of the cloth by the robot's stage, mm (focus sweeps)
        self._renders: dict[str, dict[str, Any]] = {}
        self._focus_frames: dict[float, np.ndarray] = {}
        self._lock = threading.RLock()

    @property
    def target(self) -> str:
        return self._target

    @target.setter
    def target(self, value: str) -> None:
        if value not in self.TARGETS:
            raise RigError(f"the simulated scene holds one of {', '.join(self.TARGETS)}, got {value!r}")
        self._target = value

    @property
    def lights(self) -> torch.nn.Module:
        """The rig's true LED model."""
        from data_synth.rig import rig_lights

        return rig_lights(self.config)

    def render(self, target: str | None = None) -> dict[str, Any]:
        """The cached render of ``target`` (default: the current one): ``codes`` (K, S, S) uint8, ``dark``
        (S, S) uint8, and for the sample ``gt`` (normals, depth, albedo, mask as tensors) and ``fabric``."""
        target = target or self.target
        with self._lock:
            if target not in self._renders:
                self._renders[target] = self._render(target)
            return self._renders[target]

    def _render(self, target: str) -> dict[str, Any]:
        from data_synth import CARD_ALBEDO, make_fabric
        from data_synth.rig import render_capture, render_card, render_sphere

        start = time.perf_counter()
        result: dict[str, Any] = {}
        if target == "sample":
            fabric = make_fabric(self.fabric_name, size=self.config.size, pixel_pitch_mm=self.config.pixel_pitch_mm,
                                 seed=self.seed)
            capture = render_capture(fabric, self.config, self.seed)
            result["gt"] = {"normals": capture.normals, "depth": capture.depth_mm, "albedo": capture.albedo,
                            "mask": capture.mask, "lights": capture.lights}
            result["fabric"] = {"name": fabric.name, "params": fabric.params}
            result["fabric_object"] = fabric
        elif target == "card":
            capture = render_card(self.config, CARD_ALBEDO, self.seed + 1)
            result["card_albedo"] = CARD_ALBEDO
        else:
            capture = render_sphere(self.config, seed=self.seed + 2)
        result["codes"] = _codes(capture.images)
        result["dark"] = _codes(capture.dark)[0]
        logger.info("simulated scene: rendered %s (%d LEDs, %d px) in %.1f s", target, len(result["codes"]),
                    self.config.size, time.perf_counter() - start)
        return result

    def image(self, lit: int | str | None) -> np.ndarray:
        """The gray 8-bit image of the current target with ``lit`` lit (index, ``"all"`` or None)."""
        render = self.render()
        if lit is None:
            return render["dark"]
        if lit == "all" and self.target == "sample":
            return self._focus_frame()
        if lit == "all":  # light adds up: the sum of each LED's contribution above the dark frame
            total = (render["codes"].astype(np.int32).sum(0)
                     - (len(render["codes"]) - 1) * render["dark"].astype(np.int32))
            return np.clip(total, 0, 255).astype(np.uint8)
        return render["codes"][int(lit)]


    def _focus_frame(self) -> np.ndarray:
        """The cloth under all LEDs at the stage's height, blurred away from the focal plane
        (:func:`data_synth.rig.focus_stack`; depth of field 2 mm unless the config sets one)."""
        from data_synth.rig import focus_stack

        z = round(float(self.stage_z), 6)
        with self._lock:
            if z not in self._focus_frames:
                fabric = self.render("sample")["fabric_object"]
                frames = focus_stack(fabric, [z], self.config.focal_plane_mm, self.config.depth_of_field_mm or 2.0,
                                     seed=self.seed, config=self.config)
                self._focus_frames[z] = _codes(frames)[0]
            return self._focus_frames[z]


def _codes(images: torch.Tensor) -> np.ndarray:
    return np.rint(images.detach().cpu().double().numpy() * 255).clip(0, 255).astype(np.uint8)


class SimulatedCapture:
    """A :class:`cv2.VideoCapture` look-alike showing a :class:`SimulatedScene` lit by a :class:`SimulatedDevice`.

    Frames are BGR ``uint8`` of ``frame_size``, the scene's image in the centre and reflected around it. Each
    read exposes a frame with the device's current LED state and returns the one exposed ``buffer_frames``
    reads earlier, as a webcam's driver queue does; ``grab`` discards one.

    Args:
        device: the LED controller whose state lights the scene.
        scene: what the camera sees.
        frame_size: ``(width, height)``.
        buffer_frames: frames queued in the driver.
        fault: one of :data:`CAMERA_FAULTS`, or None.
        fault_after: frames delivered normally before the fault.
    """

    def __init__(self, device: SimulatedDevice, scene: SimulatedScene, frame_size: tuple[int, int],
                 buffer_frames: int = 2, fault: str | None = None, fault_after: int = 4) -> None:
        _check_fault(fault, CAMERA_FAULTS)
        self.device, self.scene = device, scene
        self.frame_size, self.fault, self.fault_after = frame_size, fault, int(fault_after)
        self.props: dict[int, float] = {cv2.CAP_PROP_FRAME_WIDTH: float(frame_size[0]),
                                        cv2.CAP_PROP_FRAME_HEIGHT: float(frame_size[1])}
        self.delivered = 0
        self._opened = True
        self._queue: collections.deque[np.ndarray] = collections.deque(
            [self._expose() for _ in range(buffer_frames)])
        self._last: np.ndarray | None = None

    def _expose(self) -> np.ndarray:
        image = self.scene.image(self.device.lit)
        width, height = self.frame_size
        size = image.shape[0]
        left, top = (width - size) // 2, (height - size) // 2
        frame = cv2.copyMakeBorder(image, top, height - size - top, left, width - size - left, cv2.BORDER_REFLECT)
        return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)

    def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
        return self._opened

    def grab(self) -> bool:
        return self.read()[0]

    def read(self) -> tuple[bool, np.ndarray | None]:
        if not self._opened:
            return False, None
        faulty = self.delivered >= self.fault_after
        if self.fault == "no-frame" and faulty:
            return False, None
        if self.fault == "stale-frame" and faulty and self._last is not None:
            return True, self._last.copy()
        self._queue.append(self._expose())
        self._last = self._queue.popleft()
        self.delivered += 1
        return True, self._last.copy()

    def set(self, prop: int, value: float) -> bool:
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return float(value) == self.props[prop]  # the simulated sensor has one mode
        self.props[prop] = float(value)
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def getBackendName(self) -> str:  # noqa: N802 - cv2.VideoCapture's name
        return "psmini-simulator"

    def release(self) -> None:
        self._opened = False


class SimulatedRig:
    """LED controller, camera and scene of a simulated rig, ready for :class:`~psmini.rig.session.CaptureSession`.

    Args:
        fabric: the fabric under the camera (a key of :data:`data_synth.FABRICS`).
        seed: seed of the fabric and the noise.
        size: side of the rendered crop, pixels (frames are ``size`` × 1.6 by ``size`` × 1.2, 640×480 for 400).
        fault: one of :data:`FAULTS`, or None.
        fault_after: command lines (device faults) or frames (camera faults) before the fault.
        transport: ``"pty"`` (a real pseudo-terminal; :attr:`port` is its path) or ``"url"``
            (:attr:`port` is a ``psminisim://`` URL).
        boot_s: the simulated bootloader's delay before the banner, s.
        buffer_frames: frames the simulated camera driver queues.
        pixel_pitch_mm: pixel size on the cloth, mm (default: the config's, 0.025); small test rigs see more
            of the cloth with a larger pitch.
        config: a :class:`data_synth.rig.RigConfig` (its ``size`` is replaced by ``size``).

    Example:
        >>> with SimulatedRig(size=32) as rig:
        ...     rig.port.startswith("/dev/")
        True
    """

    def __init__(self, fabric: str = "jute", seed: int = 0, size: int = 400, *, fault: str | None = None,
                 fault_after: int = 4, transport: str = "pty", boot_s: float = 0.05, buffer_frames: int = 2,
                 pixel_pitch_mm: float | None = None, config: Any = None) -> None:
        from data_synth.rig import RigConfig

        _check_fault(fault, FAULTS)
        if transport not in ("pty", "url"):
            raise RigError(f"transport must be 'pty' or 'url', got {transport!r}")
        self.fault = fault
        config = (config or RigConfig()).replace(size=size)
        if pixel_pitch_mm is not None:
            config = config.replace(pixel_pitch_mm=pixel_pitch_mm)
        self.scene = SimulatedScene(fabric, seed, config)
        self.device = SimulatedDevice(LED_COUNT, boot_s=boot_s, fault=fault if fault in DEVICE_FAULTS else None,
                                      fault_after=fault_after)
        self.camera_fault = fault if fault in CAMERA_FAULTS else None
        self.fault_after, self.buffer_frames = fault_after, buffer_frames
        self.frame_size = (size + 2 * round(0.3 * size), size + 2 * round(0.1 * size))
        self._link = PtyLink(self.device) if transport == "pty" else None
        self.port = self._link.path if self._link is not None else serve_url(self.device)
        self.captures: list[SimulatedCapture] = []

    @property
    def size(self) -> int:
        return self.scene.config.size

    @property
    def pixel_pitch_mm(self) -> float:
        return self.scene.config.pixel_pitch_mm

    @property
    def lights(self) -> torch.nn.Module:
        """The rig's LED model (what a calibration would give)."""
        return self.scene.lights

    @property
    def stage_z(self) -> float:
        """The stage's position, mm (the cloth's lift toward the camera)."""
        return self.scene.stage_z

    def move_to(self, z: float) -> None:
        """The robot's ``move_to(z)``: lift the cloth to ``z`` mm (what the camera sees under all LEDs changes
        focus; the per-LED renders stay those at the reference height)."""
        self.scene.stage_z = float(z)

    def place(self, target: str) -> None:
        """Put ``"sample"``, ``"card"`` or ``"sphere"`` under the camera."""
        self.scene.target = target

    def open_capture(self, source: int | str, backend: int) -> SimulatedCapture:
        """``open_capture`` for :class:`~psmini.rig.camera.RigCamera`: a camera on this rig's scene."""
        capture = SimulatedCapture(self.device, self.scene, self.frame_size, self.buffer_frames,
                                   self.camera_fault, self.fault_after)
        self.captures.append(capture)
        return capture

    def idle(self) -> bool:
        """Whether the board has answered everything the host sent so far (:meth:`PtyLink.idle`; over a URL, where
        the host's own thread runs the device, always)."""
        return self._link.idle() if self._link is not None else True

    def close(self) -> None:
        if self._link is not None:
            self._link.close()

    def __enter__(self) -> SimulatedRig:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()


def simulated_capture(args: argparse.Namespace) -> dict:
    """``psmini capture --simulate``: capture the card, then the fabric, on a :class:`SimulatedRig`; write OUT.

    Args:
        args: the parsed ``psmini capture`` command line (``out``, ``fabric``, ``seed``, ``size``, ``fault``,
            ``pixel_pitch``, ``frames``, timeouts, ``overwrite``).

    Returns:
        the command's summary (``out``, ``kind``, ``leds``, ``firmware``, ``simulated``, ``fabric``, ``camera``).
    """
    from data_synth import CARD_ALBEDO
    from psmini.rig import CaptureSession, LEDController, RigCamera, write_with_card

    with SimulatedRig(args.fabric, args.seed, args.size, fault=args.fault, pixel_pitch_mm=args.pixel_pitch) as rig, \
            LEDController(rig.port, handshake_timeout_s=args.handshake_timeout,
                          command_timeout_s=args.command_timeout) as leds, \
            RigCamera(0, open_capture=rig.open_capture, frame_size=rig.frame_size, crop_size=rig.size) as camera:
        session = CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=rig.pixel_pitch_mm,
                                 frames_per_led=args.frames, metadata={"simulated": True, "fault": args.fault})
        rig.place("card")
        card = session.acquire("flatfield")
        rig.place("sample")
        sample = session.acquire("sample")
        render = rig.scene.render("sample")
        write_with_card(args.out, session, sample, card, card_albedo=CARD_ALBEDO, gt=render["gt"],
                        metadata={"fabric": render["fabric"], "seed": args.seed}, overwrite=args.overwrite)
        return {"out": str(args.out), "kind": "sample", "leds": leds.led_count, "firmware": str(leds.identity),
                "simulated": True, "fabric": args.fabric, "camera": camera.report}
