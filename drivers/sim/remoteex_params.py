"""Parameter tables of the simulated RemoteEx server: the streak unit, the delay generator, the camera.

RemoteEx exposes device and camera settings as named parameters with a type
(RemoteEx programmer's handbook, "Parameter types"): 0 boolean, 1 numeric (with
minimum and maximum), 2 list (one of its entries), 3 string, 4 exposure time
(``5 ms``, ``1 s``), 5 display (read only).  The info commands describe them:

* ``DevParamInfo(dev,param)``    -> label, value, type[, min, max]
* ``DevParamInfoEx(dev,param)``  -> control available, status available, label, value, type,
  then min, max (numeric) or the number of entries and the entries (list)
* ``CamParamInfo(loc,param)``    -> label, value, type[, min, max]
* ``CamParamInfoEx(loc,param)``  -> label, value, type, then the number of entries and the
  entries (list, exposure time) or min, max (numeric)
* ``DevParamsList(dev)`` / ``CamParamsList(loc)`` -> the number of parameters and their names

A :class:`Param` knows its type and validates what ``*ParamSet`` writes: a list
takes one of its entries (case-insensitive), a numeric value a number in range
(code 1 if it is not a number, 10 if out of range), a display parameter cannot
be set (code 7).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from drivers.remoteex_wire import format_exposure, parse_exposure

__all__ = ["Param", "Reply", "need", "BOOL", "NUMERIC", "LIST", "STRING", "EXPTIME", "DISPLAY",
           "streak_params", "delay_params", "camera_params", "EXPOSURE_CHOICES",
           "SYNCHROSCAN_RANGES", "SINGLE_SWEEP_RANGES"]

BOOL, NUMERIC, LIST, STRING, EXPTIME, DISPLAY = range(6)
_TRUE = {"true", "on", "yes"}
_FALSE = {"false", "off", "no", "0"}
# Exposure times offered by the simulated readout camera (CamParamInfoEx lists them; any time
# between the first and the last is accepted).
EXPOSURE_CHOICES = ("1 us", "10 us", "100 us", "1 ms", "10 ms", "100 ms", "1 s", "10 s")
SYNCHROSCAN_RANGES = ("1", "2", "3", "4")
# Written in ns and above: clients such as Odemis' convert time-range entries with s, ms, us and ns only.
SINGLE_SWEEP_RANGES = ("1 ns", "2 ns", "5 ns", "10 ns", "20 ns")


class Reply(Exception):
    """A command handler's error reply with a RemoteEx code (the server answers ``code,Name``)."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def need(args, n: int) -> None:
    """Code 6 (parameter missing) unless ``args`` has at least ``n`` entries."""
    if len(args) < n:
        raise Reply(6)


@dataclass
class Param:
    """One RemoteEx parameter.

    Attributes
    ----------
    name, label : str
        Name used in commands, label shown by the info commands.
    kind : int
        Parameter type (0..5, see the module docstring).
    value : str
        Current value as RemoteEx writes it.
    choices : tuple of str
        Entries of a list or exposure-time parameter.
    lo, hi : float
        Range of a numeric (or exposure-time, in seconds) parameter.
    """

    name: str
    kind: int
    value: str
    label: str = ""
    choices: tuple = ()
    lo: float | None = None
    hi: float | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.label = self.label or self.name

    def set(self, raw: str) -> None:
        """Validate and store a written value; raises :class:`Reply` with the error code."""
        raw = raw.strip()
        if self.kind == DISPLAY:
            raise Reply(7)
        if self.kind == LIST:
            for c in self.choices:
                if c.lower() == raw.lower() or c.replace(" ", "").lower() == raw.replace(" ", "").lower():
                    self.value = c
                    return
            raise Reply(10)
        if self.kind == NUMERIC:
            try:
                number = float(raw)
            except ValueError:
                raise Reply(1) from None
            if (self.lo is not None and number < self.lo) or (self.hi is not None and number > self.hi):
                raise Reply(10)
            self.value = raw
            return
        if self.kind == BOOL:
            low = raw.lower()
            if low in _TRUE:
                self.value = "1"
            elif low in _FALSE:
                self.value = "0"
            else:
                try:
                    self.value = "1" if float(raw) != 0 else "0"
                except ValueError:
                    raise Reply(1) from None
            return
        if self.kind == EXPTIME:
            try:
                seconds = parse_exposure(raw)
            except ValueError:
                raise Reply(1) from None
            if not self.lo <= seconds <= self.hi:
                raise Reply(10)
            self.value = format_exposure(seconds)
            return
        self.value = raw                                  # STRING

    def info(self) -> list[str]:
        """``*ParamInfo`` fields: label, value, type[, min, max]."""
        out = [self.label, self.value, str(self.kind)]
        if self.kind == NUMERIC:
            out += [_num(self.lo), _num(self.hi)]
        return out

    def dev_info_ex(self) -> list[str]:
        """``DevParamInfoEx`` fields: control and status available, label, value, type, details."""
        return ["1", "1", self.label, self.value, str(self.kind)] + self._details()

    def cam_info_ex(self) -> list[str]:
        """``CamParamInfoEx`` fields: label, value, type, details."""
        return [self.label, self.value, str(self.kind)] + self._details()

    def _details(self) -> list[str]:
        if self.kind in (LIST, EXPTIME):
            return [str(len(self.choices)), *self.choices]
        if self.kind == NUMERIC:
            return [_num(self.lo), _num(self.hi)]
        return []


def _num(v) -> str:
    return "" if v is None else f"{v:g}"


def streak_params(*, single_sweep: bool, time_range: str, gain: int) -> dict:
    """Parameters of the simulated streak unit (``DevParam*(Streak,...)``), keyed by lower-case name."""
    ranges = SINGLE_SWEEP_RANGES if single_sweep else SYNCHROSCAN_RANGES
    params = [
        Param("Time Range", LIST, time_range, choices=ranges),
        Param("Mode", LIST, "Operate", choices=("Focus", "Operate")),
        Param("Gate Mode", LIST, "Normal", choices=("Normal", "Gate")),
        Param("MCP Gain", NUMERIC, str(int(gain)), lo=0, hi=63),
        Param("Shutter", LIST, "Open", choices=("Open", "Closed")),
        Param("Trig. Mode", LIST, "Cont", choices=("Cont", "Single")),
        Param("Trig. level", NUMERIC, "1", lo=-10, hi=10),
        Param("Trig. slope", LIST, "Rising", choices=("Rising", "Falling")),
        Param("Trig. status", LIST, "Ready", choices=("Ready", "Fired", "Do Reset")),
    ]
    return {p.name.lower(): p for p in params}


def delay_params() -> dict:
    """Parameters of the simulated delay generator (``DevParam*(Delaybox,...)``)."""
    params = [
        Param("Setting", LIST, "M1", choices=("M1", "M2", "M3", "M4")),
        Param("Trig. Mode", LIST, "Int.", choices=("Int.", "Ext. rising", "Ext. falling")),
        Param("Repetition Rate", NUMERIC, "80000000", lo=0.001, hi=100e6),
        Param("Delay A", NUMERIC, "0", lo=0.0, hi=1e-6),
        Param("Delay B", NUMERIC, "0", lo=0.0, hi=1e-6),
        Param("Burst Mode", LIST, "Off", choices=("Off", "On")),
    ]
    return {p.name.lower(): p for p in params}


def camera_params(*, exposure_s: float, n_x: int, n_t: int) -> dict:
    """Camera parameters per location (``CamParam*(Setup|Live|Acquire|AI|PC,...)``)."""
    lo, hi = parse_exposure(EXPOSURE_CHOICES[0]), parse_exposure(EXPOSURE_CHOICES[-1])

    def exposure():
        return Param("Exposure", EXPTIME, format_exposure(exposure_s), label="Exposure time",
                     choices=EXPOSURE_CHOICES, lo=lo, hi=hi)

    setup = [
        Param("TimingMode", LIST, "Internal timing", label="Timing mode",
              choices=("Internal timing", "External timing")),
        Param("TriggerMode", LIST, "Edge trigger", label="Trigger mode", choices=("Edge trigger", "Level trigger")),
        Param("TriggerSource", LIST, "BNC", label="Trigger source", choices=("BNC", "Software")),
        Param("TriggerPolarity", LIST, "neg.", label="Trigger polarity", choices=("neg.", "pos.")),
        Param("ScanMode", LIST, "Normal", label="Scan mode", choices=("Normal", "Subarray")),
        Param("Binning", LIST, "1 x 1", label="Binning factor", choices=("1 x 1", "2 x 2", "4 x 4")),
        Param("HWidth", NUMERIC, str(int(n_x)), label="Horizontal Width (Subarray)", lo=1, hi=4096),
        Param("VWidth", NUMERIC, str(int(n_t)), label="Vertical Width (Subarray)", lo=1, hi=4096),
        Param("ShowGainOffset", BOOL, "0", label="Show Gain and Offset on acquisition dialog"),
        Param("CameraInfo", DISPLAY, "C13440 (simulated)", label="Camera info text"),
    ]
    out = {"setup": {p.name.lower(): p for p in setup}}
    for loc in ("live", "acquire", "ai", "pc"):
        params = [exposure(), Param("Gain", NUMERIC, "0", label="Analog gain", lo=0, hi=255)]
        if loc in ("ai", "pc"):
            params.append(Param("NrExposures", NUMERIC, "4", label="Number of exposures", lo=1, hi=1000))
        out[loc] = {p.name.lower(): p for p in params}
    return out
