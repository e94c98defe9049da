"""Capture sessions on the rig: dark frame and one guarded frame per LED, written as a capture folder atomically.

A :class:`CaptureSession` drives an open :class:`~psmini.rig.controller.LEDController` and
:class:`~psmini.rig.camera.RigCamera`: switch the LEDs off and take the dark frame, then for each LED switch
it on, discard the frames the driver had queued and read until a frame passes the
:class:`~psmini.rig.camera.FrameCheck` (new, lit, brighter toward that LED than the previous frame), averaging
``frames_per_led`` frames; then switch off. Nothing touches the disk until every frame is in memory, and the
folder is written with :func:`psmini.io.write_capture` (temporary sibling, renamed into place), so a failure
leaves no capture folder behind. The manifest records the firmware identity, the camera settings as read back,
the timing of every frame and the light model.

Calibration captures are the same acquisition of another target (``kind="flatfield"`` for the matte card,
``"sphere"`` for the mirror sphere); :func:`write_with_card` writes a sample with its card capture inside it,
so that the one folder reconstructs as it is. :meth:`CaptureSession.focus_sweep` runs the focus issue's stop
rule (:func:`psmini.autofocus.autofocus_sweep`) with the robot's ``move_to(z)``.
"""

from __future__ import annotations

import datetime
import logging
import math
import secrets
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from psmini.errors import DataFormatError, RigError
from psmini.lights import LEDLights, LightModel
from psmini.rig.camera import FrameCheck, RigCamera
from psmini.rig.controller import LEDController

__all__ = ["Acquisition", "CaptureSession", "led_azimuths", "nominal_ring_lights", "write_with_card"]

logger = logging.getLogger(__name__)

_KINDS = ("sample", "flatfield", "sphere")


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


def nominal_ring_lights(led_count: int = 8, ring_diameter_mm: float = 31.6, led_height_mm: float = 10.0,
                        azimuth_offset_deg: float = 0.0) -> LEDLights:
    """The rig's LEDs as built: evenly spaced on a ring above the card, each aimed at the field centre.

    LED ``i`` sits at azimuth ``azimuth_offset_deg + 360 i / led_count`` (counter-clockwise from +x, the image's
    right), the order of the firmware's pins D2, D3, ... ; ``mu = 1`` (Lambertian LED), unit intensities.
    A calibration (mirror sphere, card) refines these nominal values.

    Raises:
        RigError: for fewer than 3 LEDs or non-positive sizes.

    Example:
        >>> nominal_ring_lights().positions_mm[2].tolist()
        [0.0, 15.800000190734863, 10.0]
    """
    if not isinstance(led_count, int) or led_count < 3:
        raise RigError(f"a ring needs at least 3 LEDs to span 3D, got {led_count!r}")
    if not (ring_diameter_mm > 0 and led_height_mm > 0):
        raise RigError(f"ring diameter and LED height must be positive, got {ring_diameter_mm!r}, {led_height_mm!r}")
    azimuth = (torch.arange(led_count, dtype=torch.float64) * (2 * math.pi / led_count)
               + math.radians(azimuth_offset_deg))
    radius = ring_diameter_mm / 2
    positions = torch.stack([radius * azimuth.cos(), radius * azimuth.sin(),
                             torch.full_like(azimuth, float(led_height_mm))], dim=-1)
    positions = positions.where(positions.abs() > 1e-12, torch.zeros_like(positions))
    aim = -positions / positions.norm(dim=-1, keepdim=True)
    return LEDLights(positions.float(), aim.float(), torch.ones(led_count), torch.ones(led_count))


def led_azimuths(lights: nn.Module) -> np.ndarray:
    """Azimuth of each light around the optical axis, radians counter-clockwise from +x: that of its light vector at
    the field centre (the model is asked, so a user's light model works as the built-ins do).

    Raises:
        RigError: for anything that is not a light model of :mod:`psmini.lights`, or a light on the axis.

    Example:
        >>> led_azimuths(nominal_ring_lights(4)).round(3).tolist()
        [0.0, 1.571, 3.142, -1.571]
    """
    if not isinstance(lights, LightModel):
        raise RigError(f"lights must be a psmini.lights model, got {type(lights).__name__}")
    with torch.no_grad():  # models convert their tensors to the points' device and dtype
        directions, _ = lights(torch.zeros(1, 3, 1, 1, dtype=torch.float64))  # (1, K, 3, 1, 1)
    xy = directions[0, :, :2, 0, 0].detach().cpu().double().numpy()
    if (np.hypot(xy[:, 0], xy[:, 1]) < 1e-9).any():
        raise RigError("a light on the optical axis has no azimuth; the stale-frame check needs a ring of LEDs")
    return np.arctan2(xy[:, 1], xy[:, 0])


@dataclass
class Acquisition:
    """The frames of one capture, in memory.

    Attributes:
        kind: ``"sample"``, ``"flatfield"`` or ``"sphere"``.
        images: one frame per LED (each the mean of ``frames_per_led``), shape :math:`(K, S, S)`, float32 in [0, 1].
        dark: the all-LEDs-off frame, shape :math:`(S, S)`.
        bit_depth: 8 for single 8-bit frames, 16 for averages (their extra precision is kept).
        timing: per frame, seconds since the start: ``{"led": i, "switched_s", "frames_s": [...], "discarded"}``.
        started, finished: ISO 8601 times.
    """

    kind: str
    images: np.ndarray
    dark: np.ndarray
    bit_depth: int
    timing: list[dict[str, Any]] = field(default_factory=list)
    started: str = ""
    finished: str = ""


class CaptureSession:
    """One photometric-stereo capture after another on an open LED controller and camera.

    Args:
        leds: the open LED controller.
        camera: the open camera.
        lights: the light model written into the manifest (:func:`nominal_ring_lights` or a calibration); its
            K must equal the firmware's LED count.
        pixel_pitch_mm: size of a pixel on the cloth, mm.
        frames_per_led: frames averaged per LED (and for the dark frame).
        check: the stale-frame test; default :class:`FrameCheck` on the lights' azimuths.
        metadata: recorded in every manifest (operator, sample id...).

    Raises:
        RigError: when the light model's K differs from the firmware's LED count, or bad arguments.

    Example:
        >>> from data_synth.simulated_rig import SimulatedRig
        >>> with (SimulatedRig(size=32, pixel_pitch_mm=0.1) as rig,
        ...       LEDController(rig.port, handshake_timeout_s=1) as leds,
        ...       RigCamera(0, open_capture=rig.open_capture, frame_size=rig.frame_size, crop_size=32) as camera):
        ...     CaptureSession(leds, camera, rig.lights, pixel_pitch_mm=0.025).acquire().images.shape
        (8, 32, 32)
    """

    def __init__(self, leds: LEDController, camera: RigCamera, lights: nn.Module, *, pixel_pitch_mm: float = 0.025,
                 frames_per_led: int = 1, check: FrameCheck | None = None,
                 metadata: Mapping[str, Any] | None = None) -> None:
        if not isinstance(frames_per_led, int) or frames_per_led < 1:
            raise RigError(f"frames_per_led must be an integer >= 1, got {frames_per_led!r}")
        if not (isinstance(pixel_pitch_mm, (int, float)) and pixel_pitch_mm > 0):
            raise RigError(f"pixel_pitch_mm must be a positive number, got {pixel_pitch_mm!r}")
        if lights.count != leds.led_count:
            raise RigError(f"the light model has {lights.count} lights but the firmware drives {leds.led_count} LEDs")
        self.leds, self.camera, self.lights = leds, camera, lights
        self.pixel_pitch_mm, self.frames_per_led = float(pixel_pitch_mm), frames_per_led
        self.check = check or FrameCheck(led_azimuths(lights))
        self.metadata = dict(metadata or {})
        self._last_lit: np.ndarray | None = None  # the last frame taken with an LED on (stale-frame guard)

    def _mean_frames(self, first: np.ndarray, times: list[float], start: float) -> np.ndarray:
        total = first.astype(np.float64)
        for _ in range(self.frames_per_led - 1):
            self.leds.keepalive()
            total += self.camera.read()
            times.append(round(time.time() - start, 4))
        return (total / self.frames_per_led).astype(np.float32)

    def acquire(self, kind: str = "sample") -> Acquisition:
        """Take the dark frame and one guarded frame (or average) per LED; LEDs off at the end.

        Args:
            kind: what is under the camera: ``"sample"``, ``"flatfield"`` (the card) or ``"sphere"``.

        Returns:
            the :class:`Acquisition`.

        Raises:
            RigError: from the controller (timeouts, garbage, disconnect, refusals) or the camera (no frame,
                stale frames).
        """
        if kind not in _KINDS:
            raise RigError(f"kind must be one of {', '.join(_KINDS)}, got {kind!r}")
        started, start = _now(), time.time()
        timing: list[dict[str, Any]] = []
        self.leds.off()
        read_before = self.camera.frames_read
        # After OFF the driver's queue may still hold frames lit by this session's previous capture: they must
        # give way to a darker frame. A session's first dark frame has nothing lit to compare with: the board
        # reset when its port opened, so only frames queued before that could be stale, and the flush drops them.
        last_lit = self._last_lit

        def dark_reason(frame: np.ndarray) -> str | None:
            return None if last_lit is None else self.check.dark_reason(frame, last_lit)

        first, when = self.camera.read_fresh(dark_reason, "the dark frame", self.leds.keepalive)
        times = [round(when - start, 4)]
        dark = self._mean_frames(first, times, start)
        timing.append({"led": None, "switched_s": 0.0, "frames_s": times,
                       "discarded": self.camera.frames_read - read_before - self.frames_per_led})
        previous, previous_led, images = first, None, []
        for led in range(self.leds.led_count):
            self.leds.on(led)
            switched = round(time.time() - start, 4)
            read_before = self.camera.frames_read

            def reason(frame: np.ndarray, led: int = led, previous: np.ndarray = previous,
                       previous_led: int | None = previous_led) -> str | None:
                return self.check.reason(frame, led, previous, first, previous_led)

            frame, when = self.camera.read_fresh(reason, f"LED {led}", self.leds.keepalive)
            times = [round(when - start, 4)]
            images.append(self._mean_frames(frame, times, start))
            timing.append({"led": led, "switched_s": switched, "frames_s": times,
                           "discarded": self.camera.frames_read - read_before - self.frames_per_led})
            previous, previous_led = frame, led
        self.leds.off()
        self._last_lit = previous
        logger.info("acquired %s: %d LEDs x %d frames in %.2f s", kind, len(images), self.frames_per_led,
                    time.time() - start)
        return Acquisition(kind, np.stack(images), dark, 8 if self.frames_per_led == 1 else 16, timing, started, _now())

    def manifest_fields(self, acquisition: Acquisition) -> dict[str, Any]:
        """The keyword arguments of :func:`psmini.io.write_capture` that describe this rig and acquisition."""
        metadata = {
            "rig": "psmini",
            "firmware": str(self.leds.identity),
            "port": self.leds.name,
            "frames_per_led": self.frames_per_led,
            "started": acquisition.started,
            "finished": acquisition.finished,
            "timing": acquisition.timing,
            **self.metadata,
        }
        return {"lights": self.lights, "pixel_pitch_mm": self.pixel_pitch_mm, "kind": acquisition.kind,
                "bit_depth": acquisition.bit_depth, "dark": acquisition.dark, "crop": self.camera.crop,
                "camera": self.camera.report, "metadata": metadata}

    def write(self, folder: str | Path, acquisition: Acquisition, *, flatfield: Mapping[str, Any] | None = None,
              card_albedo: float | None = None, mask: Any = None, gt: Mapping[str, Any] | None = None,
              metadata: Mapping[str, Any] | None = None, overwrite: bool = False) -> Path:
        """Write ``acquisition`` as a capture folder (atomically, with :func:`psmini.io.write_capture`).

        Args:
            folder: the capture folder to create.
            acquisition: from :meth:`acquire`.
            flatfield: ``{"path": ..., "albedo": ...}``: the card capture these frames are flat-fielded by.
            card_albedo: for a ``flatfield`` acquisition: the card's albedo.
            mask: optional pixels to reconstruct, :math:`(S, S)`.
            gt: ground truth (simulated rigs).
            metadata: added to the session's metadata.
            overwrite: replace an existing folder.

        Returns:
            the folder.
        """
        from psmini.io import write_capture

        fields = self.manifest_fields(acquisition)
        fields["metadata"].update(metadata or {})
        return write_capture(folder, acquisition.images, flatfield=flatfield, card_albedo=card_albedo, mask=mask,
                             gt=gt, overwrite=overwrite, **fields)

    def capture(self, folder: str | Path, kind: str = "sample", **write_args: Any) -> Path:
        """:meth:`acquire` then :meth:`write`; nothing is written when the acquisition fails."""
        return self.write(folder, self.acquire(kind), **write_args)

    def focus_sweep(self, move_to: Callable[[float], object], positions: Sequence[float] | None = None, *,
                    folder: str | Path | None = None, overwrite: bool = False, full_sweep: bool = False,
                    **autofocus: Any) -> Any:
        """Find focus with the robot: all LEDs on, ``move_to(z)``, a fresh frame, the stop rule; LEDs off after.

        Uses :func:`psmini.autofocus.autofocus_sweep` (the seed's rule: stop once the Brenner maximum is followed
        by five smaller values; the robot ends at the best position).

        Args:
            move_to: moves the stage to ``z`` mm and returns when it is there.
            positions: the sweep's positions, mm (or ``start``, ``stop``, ``step`` in ``autofocus``).
            folder: when given, the frames taken are written there as a ``kind: "focus"`` capture.
            overwrite: replace an existing ``folder``.
            full_sweep: visit every position (no early stop) so the frames in ``folder`` cover the whole range:
                the stack for shape from focus (``psmini sff FOLDER``, :func:`psmini.sff.depth_from_focus`).
            autofocus: more arguments of :func:`~psmini.autofocus.autofocus_sweep` (``start``, ``stop``,
                ``step``, ``bounds``, ``measure``, ``roi``, ``patience``, ...).

        Returns:
            the :class:`psmini.autofocus.AutofocusResult`.

        Raises:
            RigError: from the controller or the camera; InputError: bad sweep parameters.
        """
        from psmini.autofocus import autofocus_sweep

        frames: list[np.ndarray] = []
        visited: list[float] = []
        stage = {"z": math.nan}

        def move(z: float) -> None:
            move_to(z)
            stage["z"] = float(z)

        def grab() -> torch.Tensor:
            # The stage moved, not the light: any frame after the flush shows the new position.
            frame, _ = self.camera.read_fresh(lambda frame: None, f"focus position {stage['z']:g} mm",
                                              self.leds.keepalive)
            frames.append(frame)
            visited.append(stage["z"])
            return torch.from_numpy(frame)

        if full_sweep:
            autofocus["patience"] = 1 << 30  # the stop rule never fires: the sweep ends at its last position
        self.leds.all_on()
        try:
            result = autofocus_sweep(move, grab, positions, **autofocus)
        finally:
            self.leds.off()
            if frames:
                self._last_lit = frames[-1]
        logger.info("focus sweep: best %.4f mm after %d frames", result.best_position, len(frames))
        if folder is not None:
            from psmini.io import write_capture

            write_capture(folder, np.stack(frames), None, kind="focus", positions_mm=visited,
                          pixel_pitch_mm=self.pixel_pitch_mm, bit_depth=8, crop=self.camera.crop,
                          camera=self.camera.report,
                          metadata={"rig": "psmini", "firmware": str(self.leds.identity), "autofocus": result.to_dict(),
                                    **self.metadata}, overwrite=overwrite)
        return result


def write_with_card(folder: str | Path, session: CaptureSession, sample: Acquisition, card: Acquisition, *,
                    card_albedo: float, gt: Mapping[str, Any] | None = None, metadata: Mapping[str, Any] | None = None,
                    overwrite: bool = False) -> Path:
    """Write a sample capture with its card capture inside it (``folder/card``), as one atomic folder.

    Both are written into a hidden staging folder beside ``folder`` and the sample is renamed into place last,
    so ``folder`` appears complete, card included, or not at all. The sample's manifest refers to the card as
    ``card``: the folder reconstructs as it is (``psmini reconstruct folder``).

    Args:
        folder: the sample folder to create.
        session: the session that took both (its rig metadata is recorded).
        sample: the sample's acquisition (``kind="sample"``).
        card: the card's acquisition (``kind="flatfield"``).
        card_albedo: the card's albedo.
        gt: ground truth of the sample (simulated rigs).
        metadata: more metadata for both manifests.
        overwrite: replace an existing ``folder``.

    Returns:
        the folder.

    Raises:
        DataFormatError: ``folder`` exists (without ``overwrite``) or cannot be written.
        RigError: acquisitions of the wrong kinds.
    """
    if sample.kind != "sample" or card.kind != "flatfield":
        raise RigError(f"expected a 'sample' and a 'flatfield' acquisition, got {sample.kind!r} and {card.kind!r}")
    folder = Path(folder)
    if folder.exists() and not overwrite:
        raise DataFormatError(f"{folder} already exists; pass overwrite=True (--overwrite) to replace it")
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        staging = folder.parent / f".{folder.name}.staging-{secrets.token_hex(4)}"
        staging.mkdir()
    except OSError as error:  # a file where a folder of the path should be, a read-only folder
        raise DataFormatError(f"cannot create a folder beside {folder}: {error}") from error
    try:
        staged = staging / folder.name
        session.write(staged, sample, flatfield={"path": "card", "albedo": card_albedo}, gt=gt, metadata=metadata)
        session.write(staged / "card", card, card_albedo=card_albedo, metadata=metadata)
        from psmini.io._atomic import swap_in

        try:
            swap_in(staged, folder)  # the old folder moved back should this rename fail
        except OSError as error:
            raise DataFormatError(f"cannot move the capture into {folder}: {error}") from error
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder

