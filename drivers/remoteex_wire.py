"""RemoteEx wire format: greetings, reply codes, command and reply lines, time values.

Facts from Hamamatsu's RemoteEx programmer's handbook (the same facts are visible
in the open-source RemoteEx clients of Odemis, ``odemis/driver/hamamatsurx.py``):

* the command port (default 1001) greets with ``RemoteEx Ready\\r``, the data
  port (command port + 1) with ``RemoteEx Data Ready\\r``;
* a command is ASCII ``Name(arg1,arg2,...)\\r``; its reply is
  ``code,Name,ret1,ret2,...\\r`` (``Name`` compared case-insensitively);
* codes 0 OK, 1 invalid syntax, 2 unknown command or parameter, 3 not possible
  now, 6 missing parameter, 7 cannot execute, 8 execution error, 9 data cannot
  be sent via TCP, 10 parameter out of range; 4 and 5 are unsolicited messages
  (live monitoring, status) that can arrive at any time and are never a reply;
* times are written ``<value> <unit>`` (``10 ms``, ``1 ns``); the streak unit's
  ``Time Range`` of a single-sweep unit is such a time (``1 ns``), that of a
  synchroscan unit a setting number (``2``).  A sweep's scaling table
  (``ImgDataGet(current,ScalingTable,Vertical)``) is given in the unit of the
  time range's engineering prefix (ps for ``500 ps``, ns for ``1 ns``).
"""
from __future__ import annotations

import math
import re

from .errors import ProtocolError

__all__ = [
    "DEFAULT_PORT", "COMMAND_BANNER", "DATA_BANNER", "TERMINATOR", "NOTIFICATION_CODES", "ERROR_MEANINGS",
    "format_command", "parse_reply", "format_exposure", "parse_exposure", "format_seconds",
    "normalize_time_range", "time_range_seconds", "scaling_table_unit_ps",
]

DEFAULT_PORT = 1001
COMMAND_BANNER = b"RemoteEx Ready\r"
DATA_BANNER = b"RemoteEx Data Ready\r"
TERMINATOR = b"\r"
NOTIFICATION_CODES = (4, 5)
ERROR_MEANINGS = {
    1: "invalid syntax (a command needs parentheses and the right number and type of parameters)",
    2: "command or parameter unknown",
    3: "command not possible now",
    6: "parameter missing",
    7: "command cannot be executed",
    8: "error during execution",
    9: "data cannot be sent via TCP/IP",
    10: "parameter value out of range",
}
_MAX_LINE = 1 << 16
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_BPP_DTYPE = {1: "<u1", 2: "<u2", 4: "<u4"}
_TIME_UNITS = {"ps": 1e-12, "ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
_TIME_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµ]*)\s*$")


# ---------------------------------------------------------------- wire format
def format_command(name: str, *args) -> bytes:
    """Encode ``Name(arg1,arg2)\\r``.

    Raises
    ------
    ValueError
        If the name is not an identifier or an argument contains a character
        that would break the framing (``,``, ``(``, ``)``, CR, LF) or is not ASCII.
    """
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f"invalid RemoteEx command name {name!r}")
    parts = []
    for a in args:
        s = str(a)
        if any(c in s for c in ",()\r\n") or not s.isascii():
            raise ValueError(f"RemoteEx argument {s!r} of {name} contains a forbidden character")
        parts.append(s)
    return f"{name}({','.join(parts)})\r".encode("ascii")


def parse_reply(line: bytes) -> tuple[int, str, list[str]]:
    """Split one reply line (without its CR) into ``(code, name, values)``.

    Raises
    ------
    ProtocolError
        If the line is not ASCII ``code,Name[,values...]`` with an integer code.
    """
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("RemoteEx reply is not ASCII", line) from None
    fields = text.split(",")
    if len(fields) < 2 or not fields[1].strip():
        raise ProtocolError("RemoteEx reply is not 'code,Name,...'", line)
    try:
        code = int(fields[0].strip())
    except ValueError:
        raise ProtocolError("RemoteEx reply does not start with an integer code", line) from None
    return code, fields[1].strip(), fields[2:]


def format_exposure(exposure_s: float) -> str:
    """Exposure time as RemoteEx writes it: ``<value> <unit>`` with unit s, ms, us or ns.

    ``0.0125`` -> ``'12.5 ms'``; ``2`` -> ``'2 s'``.
    """
    exposure_s = float(exposure_s)
    if not (math.isfinite(exposure_s) and exposure_s > 0):
        raise ValueError(f"exposure_s must be positive and finite, got {exposure_s!r}")
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9)):
        if exposure_s >= scale * (1 - 1e-12) or unit == "ns":
            value = exposure_s / scale
            return f"{value:.6g} {unit}"
    raise AssertionError("unreachable")


def parse_exposure(text: str) -> float:
    """Parse a RemoteEx time such as ``10 ms``, ``5ms``, ``1 s``, ``1h`` into seconds.

    A bare number is taken as milliseconds (RemoteEx's default exposure unit).
    """
    m = _TIME_RE.match(str(text))
    if not m:
        raise ValueError(f"not a RemoteEx time: {text!r}")
    value, unit = float(m.group(1)), m.group(2) or "ms"
    if unit not in _TIME_UNITS:
        raise ValueError(f"unknown time unit {unit!r} in {text!r}")
    return value * _TIME_UNITS[unit]


def format_seconds(value_s: float) -> str:
    """Fixed-point seconds with trailing zeros removed (``1.5e-10`` -> ``'0.00000000015'``).

    Delay-generator values are written in plain decimal seconds; exponent
    notation is avoided because RemoteEx device controls parse plain decimals.
    """
    value_s = float(value_s)
    if not math.isfinite(value_s):
        raise ValueError(f"value must be finite, got {value_s!r}")
    s = f"{value_s:.15f}".rstrip("0").rstrip(".")
    return "0" if s in ("", "-0") else s




# ------------------------------------------------------------------ time range
_RANGE_RE = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(ps|ns|us|µs|ms|s)\s*$")
_RANGE_UNITS_S = {"ps": 1e-12, "ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}


def normalize_time_range(value) -> int | str:
    """The streak ``Time Range`` as RemoteEx writes it.

    A synchroscan setting number stays an int (``2``); a single-sweep time is
    written ``<value> <unit>`` with one space (``"1ns"`` -> ``"1 ns"``); an all-digit
    string is a setting number.

    Raises
    ------
    ValueError
        Neither a positive integer setting nor a positive time with unit ps, ns, us, ms or s.
    """
    if isinstance(value, bool):
        raise ValueError(f"time range must be a setting number or a time such as '1 ns', got {value!r}")
    if isinstance(value, int) or (hasattr(value, "__index__") and not isinstance(value, str)):
        if int(value) < 0:
            raise ValueError(f"time range setting must be >= 0, got {value!r}")
        return int(value)
    if isinstance(value, str):
        text = value.strip()
        if text.isdigit():
            return int(text)
        m = _RANGE_RE.match(text)
        if m and float(m.group(1)) > 0:
            unit = "us" if m.group(2) == "µs" else m.group(2)
            return f"{float(m.group(1)):g} {unit}"
    raise ValueError(f"time range must be a setting number or a time such as '1 ns' (ps, ns, us, ms, s), "
                     f"got {value!r}")


def time_range_seconds(value) -> float | None:
    """Sweep duration of a single-sweep time range in seconds; None for a synchroscan setting number."""
    tr = normalize_time_range(value)
    if isinstance(tr, int):
        return None
    number, unit = tr.split(" ")
    return float(number) * _RANGE_UNITS_S[unit]


def scaling_table_unit_ps(value) -> float | None:
    """Picoseconds per scaling-table unit for this time range (the range's engineering prefix).

    ``"500 ps"`` -> 1, ``"1 ns"`` and ``"20 ns"`` -> 1000, ``"1 us"`` -> 1e6.  None for a
    synchroscan setting number (the table's unit is then a property of the unit's calibration).
    """
    seconds = time_range_seconds(value)
    if seconds is None:
        return None
    exponent = math.floor(math.log10(seconds) / 3 + 1e-9) * 3
    return 10.0 ** exponent * 1e12
