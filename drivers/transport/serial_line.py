"""Serial lines through pyserial (see :mod:`drivers.transport`)."""
from __future__ import annotations

import time

import serial

from .base import LineTransport

__all__ = ["SerialLineTransport"]


class SerialLineTransport(LineTransport):
    """A serial line through pyserial.

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyUSB0``, a pty's ``/dev/pts/N``, a stable link) or
        any pyserial URL (``loop://``, ``rfc2217://host:port``).
    baudrate, bytesize, parity, stopbits
        Line settings (pyserial values).
    xonxoff, rtscts : bool
        Software / hardware flow control.
    timeout_s : float
        Default reply timeout and write timeout, seconds.
    read_slice_s : float
        Longest single blocking read; the reply deadline is checked between reads.
    **kwargs
        ``terminator``, ``max_line``, ``reconnect_attempts`` (see :class:`LineTransport`).
    """

    def __init__(self, port: str, *, baudrate: int = 9600, bytesize: int = serial.EIGHTBITS,
                 parity: str = serial.PARITY_NONE, stopbits: float = serial.STOPBITS_ONE,
                 xonxoff: bool = False, rtscts: bool = False, timeout_s: float = 1.0,
                 read_slice_s: float = 0.05, **kwargs):
        super().__init__(timeout_s=timeout_s, name=str(port), **kwargs)
        if not read_slice_s > 0:
            raise ValueError(f"read_slice_s must be > 0, got {read_slice_s!r}")
        self.port = str(port)
        self.settings = dict(baudrate=int(baudrate), bytesize=bytesize, parity=parity, stopbits=stopbits,
                             xonxoff=bool(xonxoff), rtscts=bool(rtscts))
        self.read_slice_s = float(read_slice_s)
        self.serial = None
        self.connect()

    def _open(self) -> None:
        self.serial = serial.serial_for_url(self.port, timeout=self.read_slice_s,
                                            write_timeout=self.timeout_s, **self.settings)

    def _close_link(self) -> None:
        ser, self.serial = self.serial, None
        if ser is not None:
            ser.close()

    def _send(self, data: bytes) -> None:
        self.serial.write(data)
        self.serial.flush()

    def _receive(self, max_bytes: int, deadline: float) -> bytes:
        ser = self.serial
        while time.monotonic() < deadline:
            chunk = ser.read(max(1, min(ser.in_waiting, max_bytes)))
            if chunk:
                return chunk
        return b""

    def _discard_input(self) -> bytes:
        ser = self.serial
        pending = ser.read(ser.in_waiting) if ser.in_waiting else b""
        ser.reset_input_buffer()
        return pending
