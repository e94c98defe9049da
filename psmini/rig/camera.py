"""The rig's camera over OpenCV: explicit backend, locked and recorded settings, gray centre crop, fresh frames.

:class:`RigCamera` drives anything shaped like :class:`cv2.VideoCapture` (``isOpened``, ``read``, ``grab``,
``set``, ``get``, ``release``): the real webcam through ``cv2.VideoCapture(index, backend)``, the simulated
camera of :mod:`data_synth.simulated_rig`, or a test's fake, all through the ``open_capture`` argument.

OpenCV's exposure, gain and white-balance controls are backend-specific (V4L2 takes ``AUTO_EXPOSURE = 1`` for
manual, DirectShow 0.25) and a camera may ignore a value silently, so every setting is set, read back and
recorded as both. Webcams buffer several frames: after an LED switch the frames already queued show the
previous LED, so :meth:`RigCamera.read_fresh` discards the buffered frames and then reads until a frame
passes the caller's freshness test (:class:`FrameCheck`: new, and brighter on the side where the LED shines).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from psmini.errors import RigError

__all__ = ["BACKENDS", "CameraSettings", "FrameCheck", "RigCamera", "default_backend", "to_gray", "centre_crop"]

logger = logging.getLogger(__name__)

#: OpenCV capture backends by name.
BACKENDS = {
    "any": cv2.CAP_ANY,
    "v4l2": cv2.CAP_V4L2,
    "dshow": cv2.CAP_DSHOW,
    "msmf": cv2.CAP_MSMF,
    "avfoundation": cv2.CAP_AVFOUNDATION,
    "gstreamer": cv2.CAP_GSTREAMER,
}

# CAP_PROP_AUTO_EXPOSURE values meaning "manual" and "auto": V4L2 uses its menu (1 manual, 3 aperture
# priority), DirectShow and most others 0.25 / 0.75.
_MANUAL_EXPOSURE = {cv2.CAP_V4L2: (1.0, 3.0)}
_DEFAULT_MANUAL_EXPOSURE = (0.25, 0.75)
# Gray weights of the capture format (the same as the readers': MATLAB's rgb2gray).
_GRAY_BGR = np.array([0.1140, 0.5870, 0.2989], dtype=np.float32)


def default_backend() -> str:
    """The backend name that exposes manual controls on this platform: v4l2, dshow or avfoundation."""
    # a table, not sys.platform tests in turn: mypy evaluates those for the platform it checks on, and would
    # call every branch after the first unreachable
    platforms = (("linux", "v4l2"), ("win", "dshow"), ("darwin", "avfoundation"))
    return next((backend for prefix, backend in platforms if sys.platform.startswith(prefix)), "any")


@dataclass(frozen=True)
class CameraSettings:
    """Camera controls to lock for photometric stereo (None: leave the camera's value).

    Attributes:
        exposure: ``CAP_PROP_EXPOSURE`` in the backend's unit (V4L2: 100 µs steps; DirectShow: log2 s).
        gain: ``CAP_PROP_GAIN``.
        white_balance: ``CAP_PROP_WB_TEMPERATURE``, kelvin (automatic white balance is switched off).
        focus: ``CAP_PROP_FOCUS`` (autofocus is switched off when given).
        buffer_size: ``CAP_PROP_BUFFERSIZE``: frames the driver queues (1 keeps them fresh where honoured).

    Raises:
        RigError: a control that is not a finite number (NaN, infinite, text), or a buffer size below 1.
    """

    exposure: float | None = None
    gain: float | None = None
    white_balance: float | None = None
    focus: float | None = None
    buffer_size: int | None = 1

    def __post_init__(self) -> None:
        # checked here, not at the first frame: a NaN set on the camera reached the manifest, and the capture
        # failed to write only after the whole acquisition
        for name in ("exposure", "gain", "white_balance", "focus"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not math.isfinite(value)):
                raise RigError(f"camera {name} must be a finite number (negative is valid: DirectShow's exposure is "
                               f"log2 s) or None, got {value!r}")
        if self.buffer_size is not None and (isinstance(self.buffer_size, bool) or not isinstance(self.buffer_size, int)
                                             or self.buffer_size < 1):
            raise RigError(f"camera buffer_size must be an integer >= 1 or None, got {self.buffer_size!r}")


class FrameCheck:
    """Is a frame the one taken under the LED just switched on? New, and brighter where that LED shines.

    A near LED lights the side of the field facing it more. So when the light moves from LED ``j`` to LED ``i``,
    the change ``frame - previous`` is positive toward LED ``i`` and negative toward LED ``j``: its first moment
    along ``u_i - u_j`` (the azimuth unit vectors), normalised by its total absolute change, is positive; the
    cloth's own texture, common to both frames, cancels in the difference. From the dark frame, the moment of
    ``frame - dark`` along ``u_i`` is positive the same way. A frame under LED ``i`` must (1) differ from the
    previous frame (a frozen camera repeats the very same pixels), (2) carry light (mean above the dark
    frame's by ``min_signal``), and (3) have that normalised moment above ``margin`` (above 0 after the dark
    frame, where (2) already separates lit from stale frames); a stale frame, the
    previous LED's again, changes only by noise and scores about 0. A dark frame taken after lit ones must be
    darker than the last lit frame by ``min_signal`` (:meth:`dark_reason`).

    Args:
        azimuths_rad: LED azimuths, counter-clockwise from +x (image right), y up, length K.
        min_signal: minimum mean of ``frame - dark`` for a lit frame, fraction of full scale.
        margin: smallest normalised moment of the change toward the new LED (half-width units; a full-field
            brightness ramp gives about 0.3, noise about 0).

    Example:
        >>> check = FrameCheck([0.0, math.pi])
        >>> ramp = np.tile(np.linspace(0.1, 0.9, 16, dtype=np.float32), (16, 1))  # brighter to the right
        >>> check.accepts(ramp, led=0, previous=ramp[:, ::-1].copy(), dark=np.zeros_like(ramp), previous_led=1)
        True
        >>> check.reason(ramp[:, ::-1] + 0.001, led=0, previous=ramp[:, ::-1].copy(), dark=np.zeros_like(ramp),
        ...              previous_led=1)[:34]
        'not brighter toward LED 0 than LED'
    """

    def __init__(self, azimuths_rad: list[float] | np.ndarray, min_signal: float = 0.01, margin: float = 0.05) -> None:
        azimuths = np.asarray(azimuths_rad, dtype=np.float64).ravel()
        if azimuths.size == 0 or not np.isfinite(azimuths).all():
            raise RigError(f"FrameCheck needs finite LED azimuths, got {azimuths_rad!r}")
        self.directions = np.stack([np.cos(azimuths), np.sin(azimuths)], axis=1)
        self.min_signal, self.margin = float(min_signal), float(margin)

    @staticmethod
    def moment(change: np.ndarray, direction: np.ndarray) -> float:
        """First moment of ``change`` along ``direction`` (x right, y up, half-width units) over its total
        absolute value: in about [-1, 1], 0 for a change without a side."""
        change = change.astype(np.float64)
        height, width = change.shape
        x = (np.arange(width) - (width - 1) / 2) / (width / 2)
        y = -(np.arange(height) - (height - 1) / 2) / (height / 2)
        total = np.abs(change).sum()
        if total <= 0:
            return 0.0
        return float(((change.sum(0) * x).sum() * direction[0] + (change.sum(1) * y).sum() * direction[1]) / total)

    def reason(self, frame: np.ndarray, led: int, previous: np.ndarray, dark: np.ndarray,
               previous_led: int | None = None) -> str | None:
        """Why ``frame`` is not LED ``led``'s fresh frame after ``previous`` (None when it is).

        Args:
            frame: the candidate, :math:`(H, W)`.
            led: the LED just switched on.
            previous: the frame before the switch: the previous LED's, or the dark frame.
            dark: the dark frame.
            previous_led: the LED lit in ``previous``, or None when ``previous`` is the dark frame.
        """
        if np.array_equal(frame, previous):
            return "the frame repeats the previous one exactly"
        level = float((frame.astype(np.float64) - dark).mean())
        if level < self.min_signal:
            return f"too dark (mean {level:.4f} above the dark frame, expected >= {self.min_signal:g})"
        toward = self.directions[led].copy()
        if previous_led is not None and previous_led != led:
            toward -= self.directions[previous_led]
        toward /= np.linalg.norm(toward)
        score = self.moment(frame.astype(np.float64) - previous, toward)
        # From the dark frame the level test already tells lit from stale; the side only has to be right (a
        # small field sees little of the LED's fall-off). Between LEDs the side is the test.
        needed = self.margin if previous_led is not None else 0.0
        if score <= needed:
            source = "the dark frame" if previous_led is None else f"LED {previous_led}"
            return (f"not brighter toward LED {led} than {source} (normalised moment of the change {score:.4f}, "
                    f"expected > {needed:g})")
        return None

    def dark_reason(self, frame: np.ndarray, lit: np.ndarray) -> str | None:
        """Why ``frame`` is not a fresh all-LEDs-off frame after ``lit``, the last frame taken with an LED on
        (None when it is: darker than ``lit`` by ``min_signal`` on average)."""
        drop = float(lit.astype(np.float64).mean() - frame.astype(np.float64).mean())
        if drop < self.min_signal:
            return (f"not darker than the last lit frame (mean lower by {drop:.4f}, expected >= "
                    f"{self.min_signal:g}): the LEDs still seem on")
        return None

    def accepts(self, frame: np.ndarray, led: int, previous: np.ndarray, dark: np.ndarray,
                previous_led: int | None = None) -> bool:
        """True when ``frame`` passes (see :meth:`reason`)."""
        return self.reason(frame, led, previous, dark, previous_led) is None


def to_gray(frame: np.ndarray) -> np.ndarray:
    """A camera frame (BGR or gray, 8- or 16-bit) as gray float32 in [0, 1] (0.2989/0.5870/0.1140 weights).

    Raises:
        RigError: for an empty frame, an unexpected shape or dtype.

    Example:
        >>> round(float(to_gray(np.full((2, 2, 3), 255, np.uint8)).max()), 3)
        1.0
    """
    if frame is None or not isinstance(frame, np.ndarray) or frame.size == 0:
        raise RigError(f"the camera returned no image data (got {type(frame).__name__})")
    if frame.dtype == np.uint8:
        top = 255.0
    elif frame.dtype == np.uint16:
        top = 65535.0
    else:
        raise RigError(f"camera frames must be 8- or 16-bit, got {frame.dtype}")
    if frame.ndim == 3 and frame.shape[2] == 3:
        gray = frame.astype(np.float32) @ _GRAY_BGR
    elif frame.ndim == 2:
        gray = frame.astype(np.float32)
    else:
        raise RigError(f"camera frames must be (H, W) gray or (H, W, 3) BGR, got shape {frame.shape}")
    return np.clip(gray / top, 0.0, 1.0)


def centre_crop(image: np.ndarray, size: int) -> tuple[np.ndarray, list[int]]:
    """The centred ``size``×``size`` crop of ``image`` and its ``[x, y, w, h]`` (640×480 → x 120, y 40).

    Raises:
        RigError: when the image is smaller than the crop.

    Example:
        >>> centre_crop(np.zeros((480, 640)), 400)[1]
        [120, 40, 400, 400]
    """
    height, width = image.shape[:2]
    if height < size or width < size:
        raise RigError(f"the camera frame is {width}x{height}, smaller than the {size}x{size} crop")
    x, y = (width - size) // 2, (height - size) // 2
    return image[y : y + size, x : x + size], [x, y, size, size]


class RigCamera:
    """The rig's webcam: settings locked and recorded, gray centre crops, stale frames refused.

    Args:
        source: camera index or device path/URL for OpenCV.
        backend: OpenCV backend name (a key of :data:`BACKENDS`); default: :func:`default_backend`.
        settings: controls to lock (:class:`CameraSettings`).
        frame_size: ``(width, height)`` to ask for, pixels.
        crop_size: side of the centre crop, pixels.
        flush_frames: frames discarded after each LED switch (what the driver may have queued).
        max_stale_frames: frames read after the flush before a frame that is still stale is an error.
        read_retries: reads that may fail in a row before "no frame" is an error.
        open_capture: ``open_capture(source, backend_id) -> capture`` (default :class:`cv2.VideoCapture`);
            the simulator and tests inject theirs here.

    Raises:
        RigError: for an unknown backend or bad sizes.

    Example:
        >>> from data_synth.simulated_rig import SimulatedRig
        >>> with SimulatedRig(size=32) as rig, RigCamera(0, open_capture=rig.open_capture,
        ...                                                frame_size=rig.frame_size, crop_size=32) as camera:
        ...     camera.read().shape
        (32, 32)
    """

    def __init__(
        self,
        source: int | str = 0,
        *,
        backend: str | None = None,
        settings: CameraSettings | None = None,
        frame_size: tuple[int, int] = (640, 480),
        crop_size: int = 400,
        flush_frames: int = 4,
        max_stale_frames: int = 10,
        read_retries: int = 3,
        open_capture: Callable[[int | str, int], Any] | None = None,
    ) -> None:
        backend = backend or default_backend()
        if backend not in BACKENDS:
            raise RigError(f"unknown camera backend {backend!r}; expected one of {', '.join(BACKENDS)}")
        if not (isinstance(frame_size, (tuple, list)) and len(frame_size) == 2
                and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in frame_size)):
            raise RigError(f"frame_size must be a (width, height) pair of positive integers, got {frame_size!r}")
        width, height = frame_size
        if not (isinstance(crop_size, int) and 0 < crop_size <= min(width, height)):
            raise RigError(f"crop_size must be an integer in 1..{min(width, height)} for {width}x{height} frames, "
                           f"got {crop_size!r}")
        for name, value in (("flush_frames", flush_frames), ("max_stale_frames", max_stale_frames),
                            ("read_retries", read_retries)):
            if not isinstance(value, int) or value < 0:
                raise RigError(f"{name} must be an integer >= 0, got {value!r}")
        self.source, self.backend = source, backend
        self.settings = settings or CameraSettings()
        self.frame_size, self.crop_size = (int(width), int(height)), crop_size
        self.flush_frames, self.max_stale_frames, self.read_retries = flush_frames, max_stale_frames, read_retries
        self._open_capture = open_capture or cv2.VideoCapture
        self._capture: Any = None
        self.report: dict[str, Any] = {}
        self.crop: list[int] | None = None
        self.frames_read = 0  # every frame taken from the camera, discarded ones included

    # ---------------------------------------------------------------------------------------- life cycle

    def open(self) -> dict[str, Any]:
        """Open the camera, ask for the frame size, lock the settings and read them back.

        Returns:
            the settings report recorded in capture metadata: backend, requested and read-back values, which
            controls took, the frame size delivered.

        Raises:
            RigError: the camera cannot be opened, or delivers frames of another size than asked.
        """
        if self._capture is not None:
            return self.report
        backend_id = BACKENDS[self.backend]
        try:
            capture = self._open_capture(self.source, backend_id)
        except cv2.error as error:
            raise RigError(f"cannot open camera {self.source!r} with backend {self.backend}: {error}") from error
        if capture is None or not capture.isOpened():
            raise RigError(f"cannot open camera {self.source!r} with backend {self.backend} (is it connected, "
                           "and free of other programs?)")
        self._capture = capture
        try:
            self.report = self._configure()
            frame = self._read_raw()
            height, width = frame.shape[:2]
            if (width, height) != self.frame_size:
                raise RigError(f"camera {self.source!r} delivers {width}x{height} frames, asked for "
                               f"{self.frame_size[0]}x{self.frame_size[1]}")
        except BaseException:
            self.close()
            raise
        self.report["frame_size"] = [width, height]
        logger.info("camera %r (%s): %s", self.source, self.backend, self.report["read_back"])
        return self.report

    def close(self) -> None:
        """Release the camera (never raises)."""
        capture, self._capture = self._capture, None
        if capture is not None:
            try:
                capture.release()
            except cv2.error as error:
                logger.debug("releasing camera %r: %s", self.source, error)

    def __enter__(self) -> RigCamera:
        self.open()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()

    def _configure(self) -> dict[str, Any]:
        manual, _ = _MANUAL_EXPOSURE.get(BACKENDS[self.backend], _DEFAULT_MANUAL_EXPOSURE)
        width, height = self.frame_size
        requested: dict[str, float] = {"frame_width": width, "frame_height": height}
        s = self.settings
        if s.buffer_size is not None:
            requested["buffer_size"] = s.buffer_size
        if s.exposure is not None:
            requested["auto_exposure"] = manual
            requested["exposure"] = s.exposure
        if s.gain is not None:
            requested["gain"] = s.gain
        if s.white_balance is not None:
            requested["auto_wb"] = 0
            requested["wb_temperature"] = s.white_balance
        if s.focus is not None:
            requested["autofocus"] = 0
            requested["focus"] = s.focus
        accepted, read_back = {}, {}
        for name, value in requested.items():
            accepted[name] = bool(self._capture.set(_PROPS[name], float(value)))
        for name in _PROPS:  # read everything back, also what was left alone: the record says what the camera had
            read_back[name] = float(self._capture.get(_PROPS[name]))
        took = {name: accepted[name] and math.isclose(read_back[name], float(value), rel_tol=1e-3, abs_tol=1e-6)
                for name, value in requested.items()}
        for name, ok in took.items():
            if not ok:
                logger.warning("camera %r (%s): %s = %g did not take (read back %g)", self.source, self.backend,
                               name, requested[name], read_back[name])
        backend_name = self._capture.getBackendName() if hasattr(self._capture, "getBackendName") else self.backend
        return {"source": self.source, "backend": self.backend, "backend_name": str(backend_name),
                "requested": requested, "read_back": read_back, "took": took,
                "settings": dataclasses.asdict(self.settings)}

    # -------------------------------------------------------------------------------------------- frames

    def _read_raw(self) -> np.ndarray:
        for _ in range(self.read_retries + 1):
            ok, frame = self._cap().read()
            if ok and frame is not None and getattr(frame, "size", 0):
                self.frames_read += 1
                return frame
        raise RigError(f"camera {self.source!r} ({self.backend}) returned no frame in {self.read_retries + 1} reads "
                       "(disconnected, or in use by another program?)")

    def _cap(self) -> Any:
        if self._capture is None:
            raise RigError(f"camera {self.source!r} is not open; call open() or use it in a with block")
        return self._capture

    def read(self) -> np.ndarray:
        """The next frame as a gray centre crop.

        Returns:
            shape ``(crop_size, crop_size)``, float32 in [0, 1].

        Raises:
            RigError: no frame (after ``read_retries`` more tries), a frame of the wrong size or type.
        """
        frame = self._read_raw()
        height, width = frame.shape[:2]
        if (width, height) != self.frame_size:
            raise RigError(f"camera {self.source!r} delivered a {width}x{height} frame, expected "
                           f"{self.frame_size[0]}x{self.frame_size[1]}")
        crop, self.crop = centre_crop(to_gray(frame), self.crop_size)
        return np.ascontiguousarray(crop)

    def flush(self) -> None:
        """Discard the frames the driver may have queued (``flush_frames`` grabs)."""
        for _ in range(self.flush_frames):
            if not self._cap().grab():
                raise RigError(f"camera {self.source!r} returned no frame while discarding buffered frames")
            self.frames_read += 1

    def read_fresh(self, reason: Callable[[np.ndarray], str | None], what: str,
                   keepalive: Callable[[], None] | None = None) -> tuple[np.ndarray, float]:
        """Discard buffered frames, then read until ``reason(frame)`` is None (the frame is fresh).

        Args:
            reason: returns why a frame is stale, or None to accept it.
            what: what the frame should show, for the error message (``"LED 3"``).
            keepalive: called before each read (e.g. :meth:`LEDController.keepalive`).

        Returns:
            the frame (gray crop, float32 in [0, 1]) and the host's time when it was read
            (:func:`time.time`, s).

        Raises:
            RigError: no frame; still stale after ``max_stale_frames`` reads (the last reason is named).
        """
        self.flush()
        why: str | None = "no frame read"
        for _ in range(self.max_stale_frames + 1):
            if keepalive is not None:
                keepalive()
            frame = self.read()
            why = reason(frame)
            if why is None:
                return frame, time.time()
            logger.debug("camera %r: discarding a stale frame for %s: %s", self.source, what, why)
        raise RigError(f"camera {self.source!r}: stale frame for {what}: after discarding {self.flush_frames} buffered "
                       f"frames, {self.max_stale_frames + 1} more were still stale ({why})")


_PROPS = {
    "frame_width": cv2.CAP_PROP_FRAME_WIDTH,
    "frame_height": cv2.CAP_PROP_FRAME_HEIGHT,
    "buffer_size": cv2.CAP_PROP_BUFFERSIZE,
    "auto_exposure": cv2.CAP_PROP_AUTO_EXPOSURE,
    "exposure": cv2.CAP_PROP_EXPOSURE,
    "gain": cv2.CAP_PROP_GAIN,
    "auto_wb": cv2.CAP_PROP_AUTO_WB,
    "wb_temperature": cv2.CAP_PROP_WB_TEMPERATURE,
    "autofocus": cv2.CAP_PROP_AUTOFOCUS,
    "focus": cv2.CAP_PROP_FOCUS,
}
