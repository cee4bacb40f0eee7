"""Scan-mirror driver: a Newport SMC100-style single-axis controller over a serial line.

The driver is a command table (:data:`COMMANDS`: what each command looks like on
the wire, whether it answers, whether ``TE`` is checked after it) over a
:class:`~drivers.transport.LineTransport` (by default a
:class:`~drivers.transport.SerialLineTransport`; a
:class:`~drivers.transport.ScriptedTransport` in protocol tests).

Wire protocol (Newport SMC100CC/PP User's Manual, EDH0206En, section 6.3
"Command syntax" and 6.5 "Command set"): ASCII lines
``{address}{command}{value}\\r\\n``.  Port settings (manual, sections 2.7 and
3.1): 57600 baud, 8 data bits, no parity, one stop bit, **Xon/Xoff** flow
control -- ``xonxoff=True`` by default, configurable for adapters that must not
use it.

``TE``, ``TP``, ``TS``, ``TH`` and ``VE`` are "get" commands without a ``?``
in the manual's syntax tables; settable parameters (``ID``, ``PA``, ``VA``,
``AC``, ``SL``, ``SR``) carry the ``?`` in their query form.  Commands that
change something never answer; the manual's advice is to read ``TE``
afterwards, which this driver does after ``PA``, ``PR``, ``OR`` and ``MM``.
Reading ``TE`` clears the controller's error register.

Thread safety: the transport's lock covers a command and its reply, and a
setting command and its ``TE`` read; every reply is checked to start with the
address and command echo that was sent, so two threads sharing a driver never
see each other's replies.  Every wait has a timeout.  No pyserial or OS
exception leaves this module: they become :class:`~drivers.errors.ConnectionLost`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

from .errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from .transport import LineTransport, SerialLineTransport

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
XONXOFF = True      # manual, sections 2.7 and 3.1: Xon/Xoff flow control
_MAX_LINE = 256     # no SMC100 reply comes near this; longer means a garbled line
_TARGET_TOLERANCE_DEG = 1e-6   # PA? echoes the target to 6 decimals (format_value sends at most 6)


@dataclass(frozen=True)
class Command:
    """One entry of the command table.

    Attributes
    ----------
    mnemonic : str
        The two-letter command name.
    query : bool
        Sent with a trailing ``?`` (the query form of a settable parameter).
    reply : bool
        The controller answers with ``{address}{mnemonic}{value}``.
    checked : bool
        A setting whose success is read back with ``TE`` (under the same lock).
    meaning : str
        What it does (manual, section 6.5).
    """

    mnemonic: str
    query: bool = False
    reply: bool = False
    checked: bool = False
    meaning: str = ""


# SMC100 manual, section 6.5: the commands this driver sends.
COMMANDS = {
    "ID?": Command("ID", query=True, reply=True, meaning="stage identifier"),
    "TE": Command("TE", reply=True, meaning="last command error (and clear it)"),
    "TP": Command("TP", reply=True, meaning="current (encoder) position"),
    "TH": Command("TH", reply=True, meaning="current set-point position"),
    "TS": Command("TS", reply=True, meaning="positioner error bits and controller state"),
    "VE": Command("VE", reply=True, meaning="controller revision information"),
    "PA?": Command("PA", query=True, reply=True, meaning="target position"),
    "VA?": Command("VA", query=True, reply=True, meaning="velocity"),
    "AC?": Command("AC", query=True, reply=True, meaning="acceleration"),
    "SL?": Command("SL", query=True, reply=True, meaning="negative software limit"),
    "SR?": Command("SR", query=True, reply=True, meaning="positive software limit"),
    "PA": Command("PA", checked=True, meaning="move absolute"),
    "PR": Command("PR", checked=True, meaning="move relative"),
    "OR": Command("OR", checked=True, meaning="execute home search"),
    "MM": Command("MM", checked=True, meaning="enter (0) / leave (1) DISABLE state"),
    "RS": Command("RS", meaning="reset controller (to NOT REFERENCED)"),
    "ST": Command("ST", meaning="stop motion"),
}


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


def _ascii(raw: bytes) -> str | None:
    try:
        return raw.decode("ascii")
    except UnicodeDecodeError:
        return None


class SMC100Mirror:
    """Scan mirror on an SMC100-style controller (implements :class:`drivers.interfaces.ScanMirror`).

    Parameters
    ----------
    port : str, optional
        Serial port name (``/dev/ttyUSB0``, a pseudo-terminal path, a stable
        ``/dev/serial/by-id`` link) or any pyserial URL (``loop://``,
        ``rfc2217://host:port``).  Not needed when ``transport`` is given.
    address : int
        Controller address on the RS-485 chain, 1..31 (default 1).
    timeout_s : float
        Time to wait for one reply, seconds.
    poll_interval_s : float
        Period of ``TS`` polling while waiting for motion or homing to end, seconds.
    xonxoff : bool
        Xon/Xoff flow control on the serial port (default True, as the manual specifies).
    transport : LineTransport, optional
        An already open transport (then ``port``, ``timeout_s`` and ``xonxoff`` are not used).

    Notes
    -----
    Angles are in degrees (the rotation stage's native unit).  On a dropped
    connection the transport reopens the port once and repeats the exchange; if
    that fails the driver raises :class:`~drivers.errors.ConnectionLost`.
    """

    def __init__(self, port: str | None = None, *, address: int = 1, timeout_s: float = 1.0,
                 poll_interval_s: float = 0.02, xonxoff: bool = XONXOFF,
                 transport: LineTransport | None = None):
        if isinstance(address, bool) or not isinstance(address, int) or not 1 <= address <= 31:
            raise ValueError(f"controller address must be an integer 1..31, got {address!r}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if not poll_interval_s > 0:
            raise ValueError(f"poll_interval_s must be > 0, got {poll_interval_s!r}")
        if not isinstance(xonxoff, bool):
            raise ValueError(f"xonxoff must be True or False, got {xonxoff!r}")
        if transport is None:
            if port is None:
                raise ValueError("SMC100Mirror needs a serial port (or a transport)")
            transport = SerialLineTransport(str(port), baudrate=BAUDRATE, xonxoff=xonxoff,
                                            timeout_s=timeout_s, terminator=TERMINATOR, max_line=_MAX_LINE)
        self.transport = transport
        self.port = str(port) if port is not None else transport.name
        self.address = address
        self.timeout_s = transport.timeout_s
        self.poll_interval_s = float(poll_interval_s)
        self._closed = False
        self._target_deg = None   # the last accepted PA target, checked against PA? once settled

    # ------------------------------------------------------------------ command table
    def _line(self, name: str, value: str = "") -> bytes:
        cmd = COMMANDS[name]
        return f"{self.address}{cmd.mnemonic}{value}{'?' if cmd.query else ''}".encode("ascii") + TERMINATOR

    def _check_open(self) -> None:
        if self._closed:
            raise ConnectionLost(f"{self.port}: driver is closed")

    def send(self, name: str, value: str = "") -> None:
        """Send the table command ``name`` with ``value``; check ``TE`` afterwards if the table says so."""
        cmd = COMMANDS[name]
        if cmd.reply:
            raise ValueError(f"{name} answers; use query()")
        self._check_open()
        line = self._line(name, value)
        with self.transport.lock:  # no other thread's command may come between the command and its TE
            self.transport.write(line)
            code = self.last_error() if cmd.checked else "@"
        if code != "@":
            raise DeviceError(code, COMMAND_ERRORS.get(code, "undocumented error code"),
                              command=line.decode("ascii").strip(), device=self.port)

    def query(self, name: str) -> tuple[str, bytes]:
        """Send the table query ``name``; return the reply's value (after the echo) and its raw bytes."""
        cmd = COMMANDS[name]
        if not cmd.reply:
            raise ValueError(f"{name} does not answer; use send()")
        self._check_open()
        echo = f"{self.address}{cmd.mnemonic}"
        with self.transport.lock:   # the reply, and any late one before it, belong to this exchange
            try:
                raw = self.transport.query(self._line(name))
            except ProtocolError as exc:
                raise ProtocolError(f"{self.port}: reply to {name!r} is not '{echo}<value>' + CR LF",
                                    exc.raw) from None
            text = self._reply_after_late_ones(raw, echo)
            if text is None:
                self.transport.stale = True  # resynchronise before the next command
                raise ProtocolError(f"{self.port}: reply to {name!r} is not '{echo}<value>' + CR LF", raw)
        return text[len(echo):-len(TERMINATOR)], text.encode("ascii")

    def _reply_after_late_ones(self, raw: bytes, echo: str) -> str | None:
        """The reply to this query, text, or None.  A well-formed reply of this controller to
        another command is one to an earlier exchange -- late past its timeout, or sent twice by
        an exchange repeated after the link broke -- so this query's own reply is still on its
        way: it is read on, within the timeout.  Anything else (garbage, another address), or
        no reply of ours in time, is None."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            text = _ascii(raw)
            if text is not None and text.startswith(echo):
                return text
            if not self._is_reply_to_other_command(text):
                return None
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                raw = self.transport.read_line(timeout_s=remaining)
            except (DeviceTimeout, ProtocolError):
                return None

    def _is_reply_to_other_command(self, text: str | None) -> bool:
        if text is None or not text.endswith(TERMINATOR.decode("ascii")):
            return False
        prefix = str(self.address)
        return any(c.reply and text.startswith(prefix + c.mnemonic) for c in COMMANDS.values())

    def _query_float(self, name: str) -> float:
        payload, raw = self.query(name)
        try:
            value = float(payload)
        except ValueError:
            raise ProtocolError(f"{self.port}: malformed {name} reply", raw) from None
        if not math.isfinite(value):
            raise ProtocolError(f"{self.port}: non-finite {name} reply", raw)
        return value

    # ------------------------------------------------------------------ protocol
    def last_error(self) -> str:
        """Read (and thereby clear) the controller's last command error letter; ``@`` = none."""
        payload, raw = self.query("TE")
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
        payload, raw = self.query("TS")
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

    def version(self) -> str:
        """Controller firmware revision text (``VE``)."""
        return self.query("VE")[0].strip()

    def target_position(self) -> float:
        """Target of the current or last move, degrees (``PA?``)."""
        return self._query_float("PA?")

    def setpoint_position(self) -> float:
        """Set-point (theoretical) position of the motion profile, degrees (``TH``)."""
        return self._query_float("TH")

    def velocity(self) -> float:
        """Configured velocity, degrees per second (``VA?``)."""
        return self._query_float("VA?")

    def acceleration(self) -> float:
        """Configured acceleration, degrees per second squared (``AC?``)."""
        return self._query_float("AC?")

    def travel_limits(self) -> tuple[float, float]:
        """Software travel limits (``SL?``, ``SR?``), degrees."""
        return self._query_float("SL?"), self._query_float("SR?")

    def enable(self, enabled: bool = True) -> None:
        """Leave (``MM1``) or enter (``MM0``) the DISABLE state (entering it stops motion)."""
        if not enabled:
            self._target_deg = None
        self.send("MM", "1" if enabled else "0")

    def reset(self) -> None:
        """Reset the controller (``RS``): it comes back NOT REFERENCED and needs :meth:`home`."""
        self._target_deg = None
        self.send("RS")

    # ------------------------------------------------------------------ ScanMirror
    def identify(self) -> str:
        """Stage identifier reported by ``ID?``."""
        payload, raw = self.query("ID?")
        if not payload.strip():
            raise ProtocolError(f"{self.port}: empty ID reply", raw)
        return payload.strip()

    def state(self) -> str:
        """Controller state as a word: not_referenced, homing, moving, ready, disabled, configuration, jogging."""
        return CONTROLLER_STATES[self.status()[1]][0]

    def position(self) -> float:
        """Current mirror angle in degrees (``TP``)."""
        return self._query_float("TP")

    def move_to(self, angle_deg: float) -> None:
        """Start an absolute move to ``angle_deg`` (degrees); returns once the controller accepted it.

        Raises :class:`DeviceError` (e.g. code ``C``: out of the travel range,
        ``H``: not referenced yet) when the controller refuses the move.
        """
        text = format_value(angle_deg)
        self._target_deg = None
        self.send("PA", text)
        self._target_deg = float(text)

    def move_by(self, delta_deg: float) -> None:
        """Start a relative move by ``delta_deg`` (degrees, ``PR``); refused like :meth:`move_to`."""
        text = format_value(delta_deg)
        self._target_deg = None
        self.send("PR", text)

    def stop(self) -> None:
        """Stop any motion (``ST``); the stage stays where it stopped, short of the target."""
        self._target_deg = None
        self.send("ST")

    def wait_settled(self, *, timeout_s: float = 10.0) -> float:
        """Poll ``TS`` until the controller is READY; return the final angle in degrees.

        Raises :class:`DeviceTimeout` if it is still moving after ``timeout_s``
        and :class:`DeviceError` if the controller drops to a state from which
        it will not become ready by itself (not referenced, disabled).

        After :meth:`move_to`, the controller's target (``PA?``) must be the
        angle that was sent: a move command lost with a dropped connection
        (the link was reopened, ``TE`` of the new link says ``@``) would
        otherwise look like a finished move to the old angle.  A mismatch is a
        :class:`DeviceError` with code ``"target"``.
        """
        angle = self._wait_for_ready(timeout_s, waiting_for="motion")
        self._check_target()
        return angle

    def _check_target(self) -> None:
        if self._target_deg is None:
            return
        target = self.target_position()
        if abs(target - self._target_deg) > _TARGET_TOLERANCE_DEG:
            sent, self._target_deg = self._target_deg, None
            raise DeviceError("target", f"the controller's target is {target:g} deg, not the "
                              f"{sent:g} deg sent: the move command was lost", command="PA?",
                              device=self.port)

    def home(self, *, timeout_s: float = 30.0) -> None:
        """Reference the stage and leave it at the home position (0 degrees).

        Not referenced: send ``OR`` and wait for the HOMING state to end.
        Already referenced (the controller refuses ``OR`` in READY): move to 0.
        Disabled: leave DISABLE (``MM1``), then move to 0.
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
        if word == "disabled":
            self.enable(True)
            word = "ready"
        self._target_deg = None
        if word == "ready":
            self.move_to(0.0)
        elif word == "not_referenced":
            self.send("OR")
        elif word != "homing":
            raise DeviceError(code, f"cannot home in state {CONTROLLER_STATES[code][1]}",
                              command="OR", device=self.port)
        self._wait_for_ready(max(deadline - time.monotonic(), 1e-3), waiting_for="homing")
        self._check_target()

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
        self._closed = True
        self.transport.close()

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
