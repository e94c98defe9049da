"""The rig adapter: LED controller firmware and protocol, camera and capture sessions.

The Arduino sketch ships as package data (``firmware/psmini_leds/psmini_leds.ino``, see :func:`firmware_path`);
its protocol is specified in ``docs/rig-protocol.md``. This subpackage imports pyserial and OpenCV; the core
of psmini does not import it.
"""

from __future__ import annotations

from pathlib import Path

from psmini.rig.camera import CameraSettings, FrameCheck, RigCamera
from psmini.rig.controller import LEDController, open_port
from psmini.rig.protocol import DeviceState, Identity
from psmini.rig.session import Acquisition, CaptureSession, led_azimuths, nominal_ring_lights, write_with_card

__all__ = [
    "firmware_path",
    "LEDController",
    "open_port",
    "Identity",
    "DeviceState",
    "RigCamera",
    "CameraSettings",
    "FrameCheck",
    "CaptureSession",
    "Acquisition",
    "nominal_ring_lights",
    "led_azimuths",
    "write_with_card",
]


def firmware_path() -> Path:
    """The Arduino sketch of the LED controller (psmini-leds), shipped with the package.

    Example:
        >>> firmware_path().name
        'psmini_leds.ino'
    """
    return Path(__file__).parent / "firmware" / "psmini_leds" / "psmini_leds.ino"
