"""Laser sync driver: a SCPI pulse/delay generator on USBTMC (implements :class:`drivers.interfaces.LaserSync`).

Command set (SCPI-99 syntax, IEEE 488.2 common commands; the instrument tree
is in the style of BNC 575-type digital delay generators, where channel 0 is
the system timer ``T0``)::

    *IDN?                       identification
    *RST / *OPC? / *CLS         reset / operation complete / clear status
    SYST:ERR?                   next error, '<code>,"<text>"'; 0,"No error" when empty
    :PULS0:PER <s>              repetition period (the rate is its inverse)
    :PULS0:STAT ON|OFF          output of all channels on/off
    :PULS<n>:DEL <s>            delay of channel n after T0
    :TINT:FETC?                 the camera triggers' measured intervals after their laser
                                pulses since the last read (the read empties the unit's buffer)

The trigger-interval measurement is the unit's time-interval counter: for every camera
trigger it measures the trigger's time after the laser pulse it was derived from.  On the
wire (``<count>`` an NR1 integer, each interval an NR2 number of picoseconds, oldest first)::

    > :TINT:FETC?\n
    < 3,1234.512,1233.907,1235.020\n          three triggers since the last read
    < 0\n                                     none

The driver is a command table (:data:`COMMANDS`: header, whether it can be
set and queried, the value type on the wire) over a message transport: by
default :class:`~drivers.usbtmc.UsbtmcTransport`; anything with ``write``,
``query``, ``lock``, ``describe`` and ``close`` works, e.g. a
:class:`~drivers.transport.ScriptedTransport` with ``terminator=b"\\n"`` in
protocol tests.

Every setting command is followed by ``SYST:ERR?`` reads until the queue is
empty; an error becomes :class:`~drivers.errors.DeviceError` carrying the SCPI
code and text.  Times go over the wire in seconds, as shortest round-trip
decimal text; the driver's own units are Hz and picoseconds.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from .errors import DeviceError, DeviceTimeout, ConnectionLost, ProtocolError
from .usbtmc import UsbtmcTransport


@dataclass(frozen=True)
class ScpiCommand:
    """One entry of the command table.

    Attributes
    ----------
    header : str
        Program header; ``{channel}`` is filled in for per-channel commands.
    value : str
        Type of the value on the wire: ``"none"`` (no value), ``"seconds"``
        (NRf number), ``"bool"`` (``ON``/``OFF`` to set, ``0``/``1`` answered),
        ``"text"`` (a response only).
    settable, queryable : bool
        Sent as ``header value`` / as ``header?``.
    """

    header: str
    value: str = "none"
    settable: bool = True
    queryable: bool = False


COMMANDS = {
    "identify": ScpiCommand("*IDN", value="text", settable=False, queryable=True),
    "reset": ScpiCommand("*RST"),
    "operation_complete": ScpiCommand("*OPC", value="text", settable=False, queryable=True),
    "next_error": ScpiCommand("SYST:ERR", value="text", settable=False, queryable=True),
    "period": ScpiCommand(":PULS0:PER", value="seconds", queryable=True),
    "output": ScpiCommand(":PULS0:STAT", value="bool", queryable=True),
    "delay": ScpiCommand(":PULS{channel}:DEL", value="seconds", queryable=True),
    "trigger_intervals": ScpiCommand(":TINT:FETC", value="text", settable=False, queryable=True),
}


def program_message(name: str, value=None, *, channel: int | None = None, query: bool = False) -> str:
    """The SCPI text for table command ``name`` (without the terminator).

    ``query=True`` gives ``header?``; otherwise ``header`` plus the value in the
    table's wire format.
    """
    cmd = COMMANDS[name]
    header = cmd.header.format(channel=channel) if "{channel}" in cmd.header else cmd.header
    if query:
        if not cmd.queryable:
            raise ValueError(f"{name} cannot be queried")
        return header + "?"
    if not cmd.settable:
        raise ValueError(f"{name} cannot be set")
    if cmd.value == "none":
        return header
    if cmd.value == "seconds":
        return f"{header} {format_number(value)}"
    if cmd.value == "bool":
        return f"{header} {'ON' if value else 'OFF'}"
    raise ValueError(f"{name}: cannot send a {cmd.value} value")

_ERROR_REPLY = re.compile(r'^\s*([+-]?\d+)\s*,\s*"(.*)"\s*$', re.S)
_MAX_ERRORS = 64  # a device error queue is at most a few dozen entries; more means a broken reply loop


def format_number(value: float) -> str:
    """Shortest decimal text that reads back as the same float (SCPI NRf)."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"value must be finite, got {value!r}")
    return repr(value)


class ScpiLaserSync:
    """Laser sync / delay generator over USBTMC.

    Parameters
    ----------
    vendor_id, product_id : int, optional
        USB ids of the unit.
    serial_number : str, optional
        USB serial number (to pick one of several identical units).
    backend : usb.backend.IBackend, optional
        pyusb backend (the simulator's in tests; None: libusb).
    timeout_s : float
        Timeout of one USB write or read, seconds.
    camera_channel : int
        Channel that triggers the streak camera; the default for
        :meth:`set_trigger_delay`.
    transport : UsbtmcTransport or LineTransport, optional
        An already open transport (then the USB arguments are ignored).
    """

    def __init__(self, *, vendor_id: int | None = None, product_id: int | None = None,
                 serial_number: str | None = None, backend=None, timeout_s: float = 2.0,
                 camera_channel: int = 1, transport: UsbtmcTransport | None = None):
        self.camera_channel = self._channel(camera_channel)
        self.transport = transport if transport is not None else UsbtmcTransport(
            vendor_id=vendor_id, product_id=product_id, serial_number=serial_number,
            backend=backend, timeout_s=timeout_s)
        self._closed = False

    # ------------------------------------------------------------ SCPI plumbing
    @staticmethod
    def _channel(channel) -> int:
        if isinstance(channel, bool) or not isinstance(channel, int) or channel < 1:
            raise ValueError(f"channel must be an integer >= 1, got {channel!r}")
        return channel

    def write(self, command: str) -> None:
        """Send one program message (a newline terminator is added)."""
        self.transport.write(command.encode("ascii") + b"\n")

    def query(self, command: str) -> str:
        """Send a query and return its response without the terminator."""
        raw = self.transport.query(command.encode("ascii") + b"\n")
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError(f"non-ASCII response to {command!r}", raw) from None
        if not text.endswith("\n"):
            raise ProtocolError(f"response to {command!r} lacks the newline terminator", raw)
        return text[:-1]

    def _query_number(self, command: str) -> float:
        text = self.query(command)
        try:
            value = float(text)
        except ValueError:
            raise ProtocolError(f"non-numeric response to {command!r}", text.encode()) from None
        if not math.isfinite(value):
            raise ProtocolError(f"non-finite response to {command!r}", text.encode())
        return value

    def _set(self, command: str) -> None:
        """Send a setting command and raise :class:`DeviceError` if the device queued an error."""
        with self.transport.lock:   # nobody else's command between the setting and its error check
            self.write(command)
            errors = self.read_errors()
        if errors:
            code, text = errors[0]
            more = f" (+{len(errors) - 1} more: {errors[1:]})" if len(errors) > 1 else ""
            raise DeviceError(code, text + more, command=command, device=self.transport.describe())

    # ------------------------------------------------------------ LaserSync
    def identify(self) -> str:
        """``*IDN?``: manufacturer, model, serial number, firmware."""
        text = self.query(program_message("identify", query=True)).strip()
        if text.count(",") != 3:
            raise ProtocolError("*IDN? response is not four comma-separated fields", text.encode())
        return text

    def reset(self) -> None:
        """``*RST`` and wait for it to complete (``*OPC?``)."""
        with self.transport.lock:
            self.write(program_message("reset"))
            if self.query(program_message("operation_complete", query=True)).strip() != "1":
                raise ProtocolError("*OPC? did not answer 1", b"")

    def read_errors(self) -> list[tuple[int, str]]:
        """Drain the error queue: ``SYST:ERR?`` until ``0,"No error"``; list of (code, text)."""
        errors = []
        with self.transport.lock:
            for _ in range(_MAX_ERRORS):
                reply = self.query(program_message("next_error", query=True))
                m = _ERROR_REPLY.match(reply)
                if m is None:
                    raise ProtocolError("malformed SYST:ERR? response", reply.encode())
                code = int(m.group(1))
                if code == 0:
                    return errors
                errors.append((code, m.group(2)))
        raise ProtocolError(f"error queue did not empty after {_MAX_ERRORS} reads", b"")

    def set_repetition_rate(self, rate_hz: float) -> None:
        """Repetition rate in Hz (sent as the system period ``:PULS0:PER``, seconds)."""
        rate_hz = float(rate_hz)
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be finite and > 0, got {rate_hz!r}")
        self._set(program_message("period", 1.0 / rate_hz))

    def repetition_rate(self) -> float:
        """Current repetition rate, Hz."""
        period = self._query_number(program_message("period", query=True))
        if period <= 0:
            raise ProtocolError("non-positive period", str(period).encode())
        return 1.0 / period

    def set_trigger_delay(self, delay_ps: float, channel: int | None = None) -> None:
        """Delay of ``channel`` (default: the camera channel) after T0, picoseconds."""
        channel = self.camera_channel if channel is None else self._channel(channel)
        delay_ps = float(delay_ps)
        if not math.isfinite(delay_ps):
            raise ValueError(f"delay_ps must be finite, got {delay_ps!r}")
        self._set(program_message("delay", delay_ps * 1e-12, channel=channel))

    def trigger_delay(self, channel: int | None = None) -> float:
        """Delay of ``channel`` (default: the camera channel), picoseconds."""
        channel = self.camera_channel if channel is None else self._channel(channel)
        return round(self._query_number(program_message("delay", channel=channel, query=True)) * 1e12, 6)

    def set_output(self, enabled: bool) -> None:
        """Enable or disable the output of all channels (``:PULS0:STAT``)."""
        self._set(program_message("output", bool(enabled)))

    def output_enabled(self) -> bool:
        text = self.query(program_message("output", query=True)).strip()
        if text not in ("0", "1"):
            raise ProtocolError("malformed :PULS0:STAT? response", text.encode())
        return text == "1"

    def fetch_trigger_intervals(self) -> list[float]:
        """The camera triggers' measured intervals after their laser pulses since the last read, ps.

        ``:TINT:FETC?`` (see the module docstring); the unit forgets what it returns, so a read
        before a line's frames clears what came before them and a read after gives one interval
        per frame, oldest first.

        Raises
        ------
        ProtocolError
            A reply whose count is not a non-negative integer, whose intervals are not finite
            numbers, or whose count differs from the intervals it carries.
        """
        command = program_message("trigger_intervals", query=True)
        text = self.query(command).strip()
        fields = text.split(",")
        count = fields[0].strip()
        if not count.isdigit():
            raise ProtocolError(f"{command}: the count {count!r} is not a non-negative integer", text.encode()[:80])
        if int(count) != len(fields) - 1:
            raise ProtocolError(f"{command}: the count says {count} intervals, the reply carries "
                                f"{len(fields) - 1}", text.encode()[:80])
        out = []
        for i, field in enumerate(fields[1:]):
            try:
                value = float(field)
            except ValueError:
                value = float("nan")
            if not math.isfinite(value):
                raise ProtocolError(f"{command}: interval {i} is not a finite number: {field!r}", text.encode()[:80])
            out.append(value)
        return out

    # ------------------------------------------------------------ lifetime
    def close(self) -> None:
        self._closed = True
        self.transport.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        # Leave the unit safe: output off, whatever happened in the body.
        try:
            if not self._closed:
                self.set_output(False)
        except (ConnectionLost, DeviceTimeout, ProtocolError, DeviceError):
            pass
        finally:
            self.close()

    def __repr__(self) -> str:
        return f"ScpiLaserSync({self.transport.describe()})"
