"""Scan-mirror driver: a Newport SMC100-style single-axis controller over a serial line.

Wire protocol (Newport SMC100CC/PP User's Manual, "Command set"): ASCII lines
``{address}{command}{value}\\r\\n``, 57600 baud, 8 data bits, no parity, one
stop bit, no flow control.  Commands used here:

=========  ==========================  ======================================
command    meaning                     reply
=========  ==========================  ======================================
``xxID?``  stage identifier            ``xxID<text>``
``xxOR``   execute home search         none (check with ``TE``)
``xxPA<v>``move absolute to ``v``      none (check with ``TE``)
``xxST``   stop motion                 none
``xxTE``   last command error          ``xxTE<letter>`` (``@`` = no error)
``xxTP``   current position            ``xxTP<float>``
``xxTS``   positioner error and state  ``xxTS<4 hex digits><2-char state>``
=========  ==========================  ======================================

``TE``, ``TP`` and ``TS`` are "get" commands without a ``?`` in the manual's
syntax tables (``xxTE``, ``xxTP``, ``xxTS``); ``ID`` can also be set, so its
query form carries the ``?``.  Commands that change something never answer;
the manual's advice is to read ``TE`` afterwards, which this driver does after
every ``PA`` and ``OR``.  Reading ``TE`` clears the controller's error register.

Thread safety: one lock per connection; a command and its reply are exchanged
under it, and every reply is checked to start with the address and command
echo that was sent, so two threads sharing a driver never see each other's
replies.  Every wait has a timeout.  No pyserial or OS exception leaves this
module: they become :class:`~drivers.errors.ConnectionLost`.
"""
from __future__ import annotations

import math
import threading
import time

import serial

try:  # pyserial's POSIX backend lets termios.error (not an OSError) out of flush()/tcdrain
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - not POSIX
    class _TermiosError(Exception):
        pass

from .errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError

# SMC100 manual, TE command: the documented command error letters.
COMMAND_ERRORS = {
    "@": "No error.",
    "A": "Unknown message code or floating point controller address.",
    "B": "Controller address not correct.",
    "C": "Parameter missing or out of range.",
    "D": "Command not allowed.",
    "E": "Home sequence already started.",
    "F": "ESP stage name unknown.",
    "G": "Displacement out of limits.",
    "H": "Command not allowed in NOT REFERENCED state.",
    "I": "Command not allowed in CONFIGURATION state.",
    "J": "Command not allowed in DISABLE state.",
    "K": "Command not allowed in READY state.",
    "L": "Command not allowed in HOMING state.",
    "M": "Command not allowed in MOVING state.",
    "N": "Current position out of software limit.",
    "S": "Communication Time Out.",
    "U": "Error during EEPROM access.",
    "V": "Error during command execution.",
    "W": "Command not allowed for PP version.",
    "X": "Command not allowed for CC version.",
}

# SMC100 manual, TS command: controller state codes (last two characters of the reply).
CONTROLLER_STATES = {
    "0A": ("not_referenced", "NOT REFERENCED from reset"),
    "0B": ("not_referenced", "NOT REFERENCED from HOMING"),
    "0C": ("not_referenced", "NOT REFERENCED from CONFIGURATION"),
    "0D": ("not_referenced", "NOT REFERENCED from DISABLE"),
    "0E": ("not_referenced", "NOT REFERENCED from READY"),
    "0F": ("not_referenced", "NOT REFERENCED from MOVING"),
    "10": ("not_referenced", "NOT REFERENCED ESP stage error"),
    "11": ("not_referenced", "NOT REFERENCED from JOGGING"),
    "14": ("configuration", "CONFIGURATION"),
    "1E": ("homing", "HOMING commanded from RS-232-C"),
    "1F": ("homing", "HOMING commanded by SMC-RC"),
    "28": ("moving", "MOVING"),
    "32": ("ready", "READY from HOMING"),
    "33": ("ready", "READY from MOVING"),
    "34": ("ready", "READY from DISABLE"),
    "35": ("ready", "READY from JOGGING"),
    "3C": ("disabled", "DISABLE from READY"),
    "3D": ("disabled", "DISABLE from MOVING"),
    "3E": ("disabled", "DISABLE from JOGGING"),
    "46": ("jogging", "JOGGING from READY"),
    "47": ("jogging", "JOGGING from DISABLE"),
}

# SMC100 manual, TS command: positioner error bits (first four hex characters).
POSITIONER_ERRORS = {
    0x0200: "80W output power exceeded",
    0x0100: "DC voltage too low",
    0x0080: "Wrong ESP stage",
    0x0040: "Homing time out",
    0x0020: "Following error",
    0x0010: "Short circuit detection",
    0x0008: "RMS current limit",
    0x0004: "Peak current limit",
    0x0002: "Positive end of run",
    0x0001: "Negative end of run",
}

BAUDRATE = 57600
TERMINATOR = b"\r\n"
_MAX_LINE = 256  # no SMC100 reply comes near this; longer means a garbled line
_READ_SLICE_S = 0.05  # one blocking read; the reply deadline is checked between reads
_IO_ERRORS = (serial.SerialException, OSError, _TermiosError)


def format_value(value: float) -> str:
    """Decimal text for a command value: no exponent, no trailing zeros (``12.5``, ``-3``, ``0``)."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"value must be finite, got {value!r}")
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def decode_positioner_errors(bits: int) -> list[str]:
    """Names of the positioner error bits set in ``bits`` (the TS error word)."""
    return [name for mask, name in POSITIONER_ERRORS.items() if bits & mask]


class SMC100Mirror:
    """Scan mirror on an SMC100-style controller (implements :class:`drivers.interfaces.ScanMirror`).

    Parameters
    ----------
    port : str
        Serial port name (``/dev/ttyUSB0``, a pseudo-terminal path) or any
        pyserial URL (``loop://``, ``rfc2217://host:port``).
    address : int
        Controller address on the RS-485 chain, 1..31 (default 1).
    timeout_s : float
        Time to wait for one reply, seconds.
    poll_interval_s : float
        Period of ``TS`` polling while waiting for motion or homing to end, seconds.

    Notes
    -----
    Angles are in degrees (the rotation stage's native unit).  On a dropped
    connection the driver reopens the port once and repeats the exchange; if
    that fails it raises :class:`~drivers.errors.ConnectionLost`.
    """

    def __init__(self, port: str, *, address: int = 1, timeout_s: float = 1.0,
                 poll_interval_s: float = 0.02):
        if not isinstance(address, int) or not 1 <= address <= 31:
            raise ValueError(f"controller address must be an integer 1..31, got {address!r}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if not poll_interval_s > 0:
            raise ValueError(f"poll_interval_s must be > 0, got {poll_interval_s!r}")
        self.port = str(port)
        self.address = address
        self.timeout_s = float(timeout_s)
        self.poll_interval_s = float(poll_interval_s)
        self._lock = threading.RLock()
        self._serial = None
        self._stale = False  # a reply may still be in flight from a timed-out exchange
        self._closed = False
        with self._lock:
            self._serial = self._open()

    # ------------------------------------------------------------------ transport
    def _open(self):
        try:
            return serial.serial_for_url(
                self.port, baudrate=BAUDRATE, bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                xonxoff=False, rtscts=False, timeout=_READ_SLICE_S,
                write_timeout=self.timeout_s)
        except (*_IO_ERRORS, ValueError) as exc:
            raise ConnectionLost(f"cannot open serial port {self.port!r}: {exc}") from exc

    def _reopen(self) -> None:
        self._drop_serial()
        self._serial = self._open()
        self._stale = False

    def _drop_serial(self) -> None:
        ser, self._serial = self._serial, None
        if ser is not None:
            try:
                ser.close()
            except _IO_ERRORS:
                pass

    def _write_line(self, text: str) -> None:
        data = text.encode("ascii") + TERMINATOR
        if self._stale:
            # Whatever a timed-out exchange left behind must not be taken as this reply.
            self._serial.reset_input_buffer()
            self._stale = False
        self._serial.write(data)
        self._serial.flush()

    def _read_line(self, deadline: float) -> bytes:
        buf = bytearray()
        ser = self._serial
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._stale = True
                raise DeviceTimeout(
                    f"{self.port}: no complete reply within {self.timeout_s:g} s (got {bytes(buf)!r})")
            chunk = ser.read(max(1, min(ser.in_waiting, _MAX_LINE)))
            if not chunk:
                continue
            buf += chunk
            end = buf.find(b"\n")
            if end >= 0:
                line, rest = bytes(buf[:end + 1]), buf[end + 1:]
                if rest:
                    # The controller answers one line per query; more means noise.
                    self._stale = True
                return line
            if len(buf) > _MAX_LINE:
                self._stale = True
                raise ProtocolError(f"{self.port}: reply line too long", bytes(buf))

    def _exchange(self, command: str, *, reply: bool):
        """Send ``command`` (without address); return the reply payload after the echo, or None."""
        echo = f"{self.address}{command.rstrip('?')}"
        attempt = 0
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"{self.port}: driver is closed")
            while True:
                try:
                    if self._serial is None:
                        self._serial = self._open()
                    self._write_line(f"{self.address}{command}")
                    if not reply:
                        return None
                    deadline = time.monotonic() + self.timeout_s
                    raw = self._read_line(deadline)
                    break
                except (DeviceTimeout, ProtocolError):
                    self._stale = True
                    raise
                except serial.SerialTimeoutException as exc:  # output blocked (flow control)
                    self._stale = True
                    raise DeviceTimeout(f"{self.port}: write not done within {self.timeout_s:g} s") from exc
                except _IO_ERRORS as exc:
                    if attempt == 0:
                        attempt += 1
                        try:
                            self._reopen()
                            continue
                        except ConnectionLost:
                            pass
                    self._drop_serial()
                    raise ConnectionLost(f"{self.port}: connection lost ({exc})") from exc
            try:
                text = raw.decode("ascii")
            except UnicodeDecodeError:
                text = None
            if text is None or not text.endswith("\r\n") or not text.startswith(echo):
                self._stale = True  # resynchronise before the next command
                raise ProtocolError(f"{self.port}: reply to {command!r} is not "
                                    f"'{echo}<value>' + CR LF", raw)
        return text[len(echo):-2], raw

    def _query(self, command: str):
        return self._exchange(command, reply=True)

    def _command_checked(self, command: str) -> None:
        """Send a setting command, then read TE and raise :class:`DeviceError` if it failed."""
        with self._lock:  # no other thread's command may come between the command and its TE
            self._exchange(command, reply=False)
            code = self.last_error()
        if code != "@":
            raise DeviceError(code, COMMAND_ERRORS.get(code, "undocumented error code"),
                              command=f"{self.address}{command}", device=self.port)

    # ------------------------------------------------------------------ protocol
    def last_error(self) -> str:
        """Read (and thereby clear) the controller's last command error letter; ``@`` = none."""
        payload, raw = self._query("TE")
        if len(payload) != 1 or payload not in COMMAND_ERRORS:
            raise ProtocolError(f"{self.port}: malformed TE reply", raw)
        return payload

    def status(self) -> tuple[int, str]:
        """Positioner error bits and the two-character controller state code (``TS``).

        Returns
        -------
        error_bits : int
            16-bit positioner error word; see :func:`decode_positioner_errors`.
        state_code : str
            Controller state, e.g. ``"0A"`` (not referenced), ``"28"`` (moving), ``"33"`` (ready).
        """
        payload, raw = self._query("TS")
        if len(payload) != 6:
            raise ProtocolError(f"{self.port}: malformed TS reply", raw)
        try:
            bits = int(payload[:4], 16)
        except ValueError:
            raise ProtocolError(f"{self.port}: malformed TS error word", raw) from None
        code = payload[4:].upper()
        if code not in CONTROLLER_STATES:
            raise ProtocolError(f"{self.port}: unknown controller state {code!r}", raw)
        return bits, code

    # ------------------------------------------------------------------ ScanMirror
    def identify(self) -> str:
        """Stage identifier reported by ``ID?``."""
        payload, raw = self._query("ID?")
        if not payload.strip():
            raise ProtocolError(f"{self.port}: empty ID reply", raw)
        return payload.strip()

    def state(self) -> str:
        """Controller state as a word: not_referenced, homing, moving, ready, disabled, configuration, jogging."""
        return CONTROLLER_STATES[self.status()[1]][0]

    def position(self) -> float:
        """Current mirror angle in degrees (``TP``)."""
        payload, raw = self._query("TP")
        try:
            angle = float(payload)
        except ValueError:
            raise ProtocolError(f"{self.port}: malformed TP reply", raw) from None
        if not math.isfinite(angle):
            raise ProtocolError(f"{self.port}: non-finite position", raw)
        return angle

    def move_to(self, angle_deg: float) -> None:
        """Start an absolute move to ``angle_deg`` (degrees); returns once the controller accepted it.

        Raises :class:`DeviceError` (e.g. code ``C``: out of the travel range,
        ``H``: not referenced yet) when the controller refuses the move.
        """
        self._command_checked(f"PA{format_value(angle_deg)}")

    def stop(self) -> None:
        """Stop any motion (``ST``)."""
        self._exchange("ST", reply=False)

    def wait_settled(self, *, timeout_s: float = 10.0) -> float:
        """Poll ``TS`` until the controller is READY; return the final angle in degrees.

        Raises :class:`DeviceTimeout` if it is still moving after ``timeout_s``
        and :class:`DeviceError` if the controller drops to a state from which
        it will not become ready by itself (not referenced, disabled).
        """
        return self._wait_for_ready(timeout_s, waiting_for="motion")

    def home(self, *, timeout_s: float = 30.0) -> None:
        """Reference the stage and leave it at the home position (0 degrees).

        Not referenced: send ``OR`` and wait for the HOMING state to end.
        Already referenced (the controller refuses ``OR`` in READY): move to 0.
        Moving: wait for the move to end, then move to 0.  Homing: wait for it.
        ``timeout_s`` bounds the whole operation.
        """
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        deadline = time.monotonic() + timeout_s
        _, code = self.status()
        word = CONTROLLER_STATES[code][0]
        if word == "moving":
            self._wait_for_ready(deadline - time.monotonic(), waiting_for="motion")
            word = "ready"
        if word == "ready":
            self.move_to(0.0)
        elif word == "not_referenced":
            self._command_checked("OR")
        elif word != "homing":
            raise DeviceError(code, f"cannot home in state {CONTROLLER_STATES[code][1]}",
                              command="OR", device=self.port)
        self._wait_for_ready(max(deadline - time.monotonic(), 1e-3), waiting_for="homing")

    def _wait_for_ready(self, timeout_s: float, *, waiting_for: str) -> float:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        deadline = time.monotonic() + timeout_s
        while True:
            bits, code = self.status()
            word, meaning = CONTROLLER_STATES[code]
            if word == "ready":
                return self.position()
            if word in ("not_referenced", "disabled", "configuration"):
                errors = decode_positioner_errors(bits)
                detail = f" ({', '.join(errors)})" if errors else ""
                raise DeviceError(code, f"{meaning}{detail}", command=f"wait for {waiting_for}",
                                  device=self.port)
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.port}: {waiting_for} not finished within {timeout_s:g} s "
                                    f"(state {meaning})")
            time.sleep(min(self.poll_interval_s, max(0.0, deadline - time.monotonic())))

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Close the serial port (idempotent).  Does not move the stage."""
        with self._lock:
            self._closed = True
            self._drop_serial()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        # Leave the stage safe: stop motion, whatever happened in the body.
        try:
            if not self._closed:
                self.stop()
        except (ConnectionLost, DeviceTimeout, ProtocolError, DeviceError):
            pass
        finally:
            self.close()

    def __repr__(self) -> str:
        return f"SMC100Mirror(port={self.port!r}, address={self.address})"
