"""``psminisim://`` for :func:`serial.serial_for_url`: a :class:`~data_synth.simulated_rig.SimulatedDevice` as a port.

``psminisim://NAME`` reaches a device served with :func:`data_synth.simulated_rig.serve_url`;
``psminisim://?leds=8&fault=garbage&after=4`` makes a fresh one. Opening the port resets the device (as DTR
resets a Nano); an unplugged device makes reads and writes fail as a pulled cable does.
"""

from __future__ import annotations

import time

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from psmini.errors import RigError


class Serial(SerialBase):
    """A pyserial port whose other end is a simulated psmini-leds board."""

    def __init__(self, *args, **kwargs) -> None:
        self._device = None
        self._buffer = bytearray()
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        from data_synth.simulated_rig import device_for_url

        if self.is_open:
            raise SerialException("port already open")
        try:
            self._device = device_for_url(self.portstr)
        except RigError as error:
            raise SerialException(str(error)) from error
        self._buffer.clear()
        self.is_open = True
        self._device.reset()

    def close(self) -> None:
        self.is_open = False
        self._device = None

    def _reconfigure_port(self) -> None:
        """Nothing to configure: the simulated line has no baud rate."""

    def _alive(self):
        if not self.is_open:
            raise PortNotOpenError()
        if not self._device.connected:
            raise SerialException("device reports readiness to read but returned no data (device disconnected)")
        return self._device

    def _pull(self) -> None:
        self._buffer += self._alive().output()

    @property
    def in_waiting(self) -> int:
        self._pull()
        return len(self._buffer)

    def read(self, size: int = 1) -> bytes:
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            self._pull()
            if len(self._buffer) >= size or (deadline is not None and time.monotonic() >= deadline):
                data = bytes(self._buffer[:size])
                del self._buffer[:size]
                return data
            time.sleep(0.001)

    def write(self, data: bytes) -> int:
        device = self._alive()
        data = bytes(data)  # pyserial 3 takes bytes only, as a real port does
        device.receive(data)
        if not device.connected:
            raise SerialException("write failed: device disconnected")
        return len(data)

    def reset_input_buffer(self) -> None:
        self._pull()
        self._buffer.clear()

    def reset_output_buffer(self) -> None:
        self._alive()

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_break_state(self) -> None:
        self._alive()

    def _update_rts_state(self) -> None:
        """RTS is not wired on a Nano."""

    def _update_dtr_state(self) -> None:
        """DTR resets the board on open; open() does that."""

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
