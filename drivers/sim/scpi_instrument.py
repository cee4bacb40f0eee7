"""The SCPI instrument inside the simulated laser-sync unit: no USB here.

IEEE 488.2 common commands plus a pulse/delay-generator tree in the style of
BNC 575-type units (:data:`COMMANDS_DOC`); :class:`SyncInstrument` runs one
program message at a time and keeps the error queue and the event status
register.  :mod:`drivers.sim.usbtmc` puts it behind a USBTMC interface.
"""
from __future__ import annotations

import math

import numpy as np

from .state import LabState

__all__ = ["SCPI_ERRORS", "COMMANDS_DOC", "SyncInstrument"]

# ---------------------------------------------------------------- SCPI error texts
# SCPI-99 volume 2, chapter 21 (error/event queue): standard codes and texts
SCPI_ERRORS = {
    0: "No error",
    -100: "Command error",
    -102: "Syntax error",
    -104: "Data type error",
    -108: "Parameter not allowed",
    -109: "Missing parameter",
    -113: "Undefined header",
    -200: "Execution error",
    -222: "Data out of range",
    -224: "Illegal parameter value",
    -240: "Hardware error",
    -300: "Device-specific error",
    -310: "System error",
    -350: "Queue overflow",
    -410: "Query INTERRUPTED",
    -420: "Query UNTERMINATED",
}

COMMANDS_DOC = """\
*IDN?                    -> "STREAKLAB,SLS-575SIM,<serial>,<firmware>"
*RST                     system period 12.5 ns (80 MHz), all delays 0, widths 10 ns, output off
*CLS                     clear the error queue and the event status register
*OPC? / *OPC / *WAI      operation complete ("1")
*ESR? / *STB? / *TST?    event status register / status byte / self test ("0")
SYSTem:ERRor[:NEXT]?     -> <code>,"<text>"  (0,"No error" when the queue is empty)
:PULSe0:PERiod <s> / ?   system (repetition) period, 5 ns .. 1000 s
:PULSe0:STATe ON|OFF / ? system output enable (all channels)
:PULSe<n>:DELay <s> / ?  channel n = 1..4 delay after T0, 0 .. 1 ms, 0.1 ps resolution
:PULSe<n>:WIDTh <s> / ?  channel n pulse width, 1 ns .. 1 ms
:PULSe<n>:STATe ON|OFF / ? channel n enable
:TINTerval:FETCh?        -> <count>[,<interval_ps>...]: the camera triggers' measured intervals
                         after their laser pulses since the last read, oldest first, ps with
                         3 decimals (count 0 and nothing else when there are none); the read
                         empties the buffer (65536 measurements; the oldest are lost beyond)
"""

_PERIOD_RANGE_S = (5e-9, 1000.0)
_DELAY_RANGE_S = (0.0, 1e-3)
_WIDTH_RANGE_S = (1e-9, 1e-3)
_N_CHANNELS = 4
_ERROR_QUEUE_LEN = 20
#: stream of the trigger-interval measurement noise, apart from the frames' noise streams
_REFERENCE_STREAM = 0x7111E5


class _ScpiError(Exception):
    def __init__(self, code: int):
        self.code = code


def _keyword(token: str, long_form: str) -> bool:
    """SCPI keyword match: the short form (the upper-case part) or the whole long form."""
    token = token.upper()
    short = "".join(c for c in long_form if c.isupper() or c.isdigit())
    return token in (short, long_form.upper())


class SyncInstrument:
    """The SCPI instrument behind the USB interface (no USB here).

    Parameters
    ----------
    lab_state : LabState
        Updated on every change of period, channel-1 delay and output state.
    serial_number : str
        Reported in ``*IDN?``.
    camera_channel : int
        Channel that triggers the streak camera: its delay is ``LabState.sync_delay_ps``
        and the camera sees light only while it and the system output are on.
    reference_noise_ps : float
        RMS of the Gaussian noise of each trigger-interval measurement (``:TINT:FETC?``), ps;
        each draw is seeded by its trigger's ``noise_key`` (:attr:`LabState.triggers`).

    Attributes
    ----------
    interval_counter : bool
        The unit has the time-interval counter (default True).  False: ``:TINT:FETC?`` is an
        undefined header (-113) and gets no reply, as on a unit without that option.
    """

    def __init__(self, lab_state: LabState, serial_number: str, firmware: str = "1.0",
                 camera_channel: int = 1, reference_noise_ps: float = 0.5):
        if not 1 <= int(camera_channel) <= _N_CHANNELS:
            raise ValueError(f"camera_channel must be 1..{_N_CHANNELS}, got {camera_channel!r}")
        reference_noise_ps = float(reference_noise_ps)
        if not (math.isfinite(reference_noise_ps) and reference_noise_ps >= 0):
            raise ValueError(f"reference_noise_ps must be finite and >= 0, got {reference_noise_ps!r}")
        self.reference_noise_ps = reference_noise_ps
        self.camera_channel = int(camera_channel)
        self.lab_state = lab_state
        self.serial_number = serial_number
        self.firmware = firmware
        self.errors: list[int] = []
        self.esr = 0
        self.interval_counter = True
        self.reset()

    def reset(self) -> None:
        self.period_s = 12.5e-9
        self.output = False
        self.delay_s = [0.0] * (_N_CHANNELS + 1)
        self.width_s = [10e-9] * (_N_CHANNELS + 1)
        self.channel_on = [True] * (_N_CHANNELS + 1)
        self._publish()

    def _publish(self) -> None:
        with self.lab_state.lock:
            self.lab_state.sync_rate_hz = 1.0 / self.period_s
            ch = self.camera_channel
            self.lab_state.sync_delay_ps = round(self.delay_s[ch] * 1e13) / 10.0
            self.lab_state.sync_output_enabled = bool(self.output and self.channel_on[ch])

    def push_error(self, code: int) -> None:
        if len(self.errors) >= _ERROR_QUEUE_LEN:
            self.errors[-1] = -350
        else:
            self.errors.append(int(code))
        # IEEE 488.2 event status register bits: 2 query, 3 device-dependent, 4 execution, 5 command
        if -199 <= code <= -100:
            self.esr |= 0x20
        elif -299 <= code <= -200:
            self.esr |= 0x10
        elif -399 <= code <= -300 or code > 0:
            self.esr |= 0x08
        elif -499 <= code <= -400:
            self.esr |= 0x04

    def status_byte(self, message_available: bool) -> int:
        stb = 0
        if self.errors:
            stb |= 0x04          # error/event queue not empty
        if message_available:
            stb |= 0x10          # MAV
        if self.esr:
            stb |= 0x20          # ESB (all ESR bits enabled)
        return stb

    @staticmethod
    def headers(message: str) -> list[str]:
        """SCPI headers of a program message (for fault matching), leading colon removed."""
        out = []
        for unit in message.split(";"):
            unit = unit.strip()
            if unit:
                out.append(unit.split(None, 1)[0].lstrip(":"))
        return out

    def execute(self, message: str, message_available: bool = False) -> list[str]:
        """Run one program message (units separated by ``;``); return the query responses."""
        responses = []
        for unit in message.split(";"):
            unit = unit.strip()
            if not unit:
                continue
            try:
                reply = self._unit(unit, message_available)
            except _ScpiError as exc:
                self.push_error(exc.code)
                continue
            if reply is not None:
                responses.append(reply)
        return responses

    # -- one program message unit
    def _unit(self, unit: str, message_available: bool):
        parts = unit.split(None, 1)
        header, arg = parts[0], (parts[1].strip() if len(parts) > 1 else None)
        query = header.endswith("?")
        if query and arg is not None:
            raise _ScpiError(-108)
        head = header[:-1] if query else header
        if head.startswith("*"):
            return self._common(head.upper(), query, arg, message_available)
        nodes = head.lstrip(":").split(":")
        if len(nodes) >= 2 and _keyword(nodes[0], "SYSTem") and _keyword(nodes[1], "ERRor") and \
                (len(nodes) == 2 or (len(nodes) == 3 and _keyword(nodes[2], "NEXT"))):
            if not query:
                raise _ScpiError(-113)
            code = self.errors.pop(0) if self.errors else 0
            return f'{code},"{SCPI_ERRORS.get(code, "Device-specific error")}"'
        if len(nodes) == 2 and nodes[0].upper().startswith("PULS"):
            return self._pulse(nodes[0], nodes[1], query, arg)
        if len(nodes) == 2 and _keyword(nodes[0], "TINTerval") and _keyword(nodes[1], "FETCh") \
                and self.interval_counter:
            if not query:
                raise _ScpiError(-113)
            return self._fetch_intervals()
        raise _ScpiError(-113)

    def _fetch_intervals(self) -> str:
        """``<count>[,<interval_ps>...]``: every buffered trigger measured, the buffer emptied."""
        with self.lab_state.lock:
            triggers = list(self.lab_state.triggers)
            self.lab_state.triggers.clear()
        values = []
        for interval_ps, key in triggers:
            noise = 0.0
            if self.reference_noise_ps:
                rng = np.random.default_rng([*key, _REFERENCE_STREAM])
                noise = float(rng.normal(0.0, self.reference_noise_ps))
            values.append(f"{interval_ps + noise:.3f}")
        return ",".join([str(len(values))] + values)

    def _common(self, head: str, query: bool, arg, message_available: bool):
        if arg is not None:
            raise _ScpiError(-108)
        if head == "*IDN" and query:
            return f"STREAKLAB,SLS-575SIM,{self.serial_number},{self.firmware}"
        if head == "*RST" and not query:
            self.reset()
            return None
        if head == "*CLS" and not query:
            self.errors.clear()
            self.esr = 0
            return None
        if head == "*OPC":
            if query:
                return "1"
            self.esr |= 0x01
            return None
        if head == "*WAI" and not query:
            return None
        if head == "*ESR" and query:
            value, self.esr = self.esr, 0
            return str(value)
        if head == "*STB" and query:
            return str(self.status_byte(message_available))
        if head == "*TST" and query:
            return "0"
        raise _ScpiError(-113)

    def _pulse(self, node: str, leaf: str, query: bool, arg):
        upper = node.upper()
        digits = upper[len("PULSE"):] if upper.startswith("PULSE") else upper[len("PULS"):]
        if not digits.isdigit():
            raise _ScpiError(-113)
        ch = int(digits)
        if ch > _N_CHANNELS:
            raise _ScpiError(-113)
        if _keyword(leaf, "STATe"):
            if query:
                return "1" if (self.output if ch == 0 else self.channel_on[ch]) else "0"
            value = self._boolean(arg)
            if ch == 0:
                self.output = value
            else:
                self.channel_on[ch] = value
        elif ch == 0 and _keyword(leaf, "PERiod"):
            if query:
                return f"{self.period_s:.12E}"
            self.period_s = self._number(arg, _PERIOD_RANGE_S)
        elif ch > 0 and _keyword(leaf, "DELay"):
            if query:
                return f"{self.delay_s[ch]:.13E}"
            value = self._number(arg, _DELAY_RANGE_S)
            self.delay_s[ch] = round(value * 1e13) / 1e13   # 0.1 ps resolution
        elif ch > 0 and _keyword(leaf, "WIDTh"):
            if query:
                return f"{self.width_s[ch]:.13E}"
            self.width_s[ch] = round(self._number(arg, _WIDTH_RANGE_S) * 1e13) / 1e13
        else:
            raise _ScpiError(-113)
        self._publish()
        return None

    @staticmethod
    def _boolean(arg) -> bool:
        if arg is None:
            raise _ScpiError(-109)
        text = arg.upper()
        if text in ("ON", "1"):
            return True
        if text in ("OFF", "0"):
            return False
        raise _ScpiError(-224)

    @staticmethod
    def _number(arg, bounds) -> float:
        if arg is None:
            raise _ScpiError(-109)
        try:
            value = float(arg)
        except ValueError:
            raise _ScpiError(-104) from None
        if not math.isfinite(value) or not bounds[0] <= value <= bounds[1]:
            raise _ScpiError(-222)
        return value
