"""One error hierarchy for every driver.  No socket, pyserial or pyusb exception leaks past a driver."""
from __future__ import annotations


class DriverError(Exception):
    """Base class of every error a streaklab driver raises."""


class DeviceError(DriverError):
    """The device answered, and its answer reports an error.

    Attributes
    ----------
    code : int or str
        The device's own error code.
    meaning : str
        The documented meaning of that code.
    """

    def __init__(self, code, meaning: str, *, command: str | None = None, device: str | None = None):
        self.code = code
        self.meaning = meaning
        self.command = command
        self.device = device
        where = f"{device}: " if device else ""
        what = f" (command {command!r})" if command else ""
        super().__init__(f"{where}device error {code}: {meaning}{what}")


class DeviceTimeout(DriverError):
    """No (complete) answer within the timeout."""


class ProtocolError(DriverError):
    """A reply that does not follow the protocol.  ``raw`` holds the bytes received."""

    def __init__(self, message: str, raw: bytes = b""):
        self.raw = bytes(raw)
        super().__init__(f"{message}: {self.raw!r}")


class ConnectionLost(DriverError):
    """The connection to the device is gone and could not be re-established."""
