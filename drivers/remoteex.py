"""Hamamatsu streak camera over RemoteEx (the TCP remote control of HPD-TA / HiPic).

Wire protocol, as publicly described for RemoteEx (Hamamatsu's RemoteEx
programmer's handbook; the same facts are visible in the open-source RemoteEx
clients of Odemis, ``odemis/driver/hamamatsurx.py``, and of the ``hamamatsu``
simulator by T. Coutinho):

* Two TCP connections: the command port (default 1001) and the data port
  (command port + 1).  Right after connecting the server sends
  ``RemoteEx Ready\\r`` on the command port and ``RemoteEx Data Ready\\r`` on
  the data port.
* A command is ASCII ``Name(arg1,arg2,...)\\r``.  Its reply is
  ``code,Name,ret1,ret2,...\\r`` where ``Name`` repeats the command name (compared
  case-insensitively).  Codes: 0 OK, 1 invalid syntax, 2 unknown command or
  parameter, 3 not possible now, 6 missing parameter, 7 cannot execute,
  8 execution error, 9 data cannot be sent via TCP, 10 parameter out of range.
  Codes 4 and 5 are unsolicited messages (monitoring, status) that can arrive at
  any time, including between a command and its reply; they are never a reply.
* ``ImgDataGet(Current,Data)`` replies ``0,ImgDataGet,width,height,bytes_per_pixel,type``
  and the raw little-endian pixels (row-major, ``height`` rows of ``width``
  pixels) follow on the data port.  On a streak camera the rows are the sweep
  (time) direction and the columns the slit (space) direction.
* ``AcqStatus()`` replies ``idle`` or ``busy`` followed by the mode.
* ``CamParamGet/Set(Location,Exposure[,value])`` take exposure times such as
  ``10 ms``; ``DevParamGet/Set(Streak,Time Range[,value])`` and
  ``DevParamGet/Set(Delaybox,Delay A[,seconds])`` address the streak unit and
  the delay generator.

Everything that waits has a deadline; every socket failure is mapped to the
:mod:`drivers.errors` hierarchy.  One lock per connection serialises whole
transactions (command, reply and data-port transfer), so a reply always goes
back to the thread that sent its command.  A connection that dropped is
re-established once (and the interrupted command re-sent); if that fails the
driver raises :class:`~drivers.errors.ConnectionLost`.  After a timeout or a
malformed reply the connection is closed and a fresh one is opened by the next
command, so a late or partial reply can never be taken for a later answer.
"""
from __future__ import annotations

import logging
import math
import re
import socket
import threading
import time

import numpy as np

from .errors import ConnectionLost, DeviceError, DeviceTimeout, DriverError, ProtocolError
from .interfaces import StreakImage

__all__ = [
    "RemoteExCamera",
    "ERROR_MEANINGS",
    "NOTIFICATION_CODES",
    "COMMAND_BANNER",
    "DATA_BANNER",
    "DEFAULT_PORT",
    "format_command",
    "parse_reply",
    "format_exposure",
    "parse_exposure",
    "format_seconds",
]

log = logging.getLogger(__name__)

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
_TIME_UNITS = {"ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
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


class _Dropped(Exception):
    """Internal: the connection broke (EOF, reset, refused); the caller may reconnect once."""


# --------------------------------------------------------------------- driver
class RemoteExCamera:
    """Streak camera driven through RemoteEx; implements :class:`drivers.interfaces.StreakCamera`.

    Parameters
    ----------
    host : str
        RemoteEx server address.
    port : int
        Command port (RemoteEx default 1001).
    data_port : int, optional
        Data port; defaults to ``port + 1`` as RemoteEx does.
    timeout_s : float
        Default time allowed for one command's reply (seconds).
    connect_timeout_s : float
        Time allowed to connect and receive both banners.
    start_app : bool
        Send ``AppStart()`` after the first connection (starts HPD-TA/HiPic
        if it is not running yet).
    app_start_timeout_s : float
        Timeout for ``AppStart`` (the application may take a while to come up).
    acquire_mode : str
        Acquisition mode passed to ``AcqStart`` (``Acquire``: one image per start).
    exposure_location : str
        ``CamParamSet`` location holding the exposure of ``acquire_mode``.
    streak_device, delay_device, delay_parameter : str
        ``DevParam*`` names of the streak unit, the delay generator and its delay.
    poll_interval_s : float
        Pause between ``AcqStatus`` polls while an acquisition runs.
    connect : bool
        Connect in the constructor (default).  Otherwise the first command does.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, data_port: int | None = None,
                 timeout_s: float = 5.0, connect_timeout_s: float = 5.0, start_app: bool = True,
                 app_start_timeout_s: float = 30.0, acquire_mode: str = "Acquire",
                 exposure_location: str = "Acquire", streak_device: str = "Streak",
                 delay_device: str = "Delaybox", delay_parameter: str = "Delay A",
                 poll_interval_s: float = 0.005, connect: bool = True):
        for name, v in (("timeout_s", timeout_s), ("connect_timeout_s", connect_timeout_s),
                        ("app_start_timeout_s", app_start_timeout_s)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {v!r}")
        if not (0 < int(port) < 65536):
            raise ValueError(f"port must be in 1..65535, got {port!r}")
        self.host = host
        self.port = int(port)
        self.data_port = int(data_port) if data_port is not None else self.port + 1
        self.timeout_s = float(timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.app_start_timeout_s = float(app_start_timeout_s)
        self.acquire_mode = acquire_mode
        self.exposure_location = exposure_location
        self.streak_device = streak_device
        self.delay_device = delay_device
        self.delay_parameter = delay_parameter
        self.poll_interval_s = float(poll_interval_s)
        self._start_app = bool(start_app)
        self._app_started = False
        self._lock = threading.RLock()
        self._cmd: socket.socket | None = None
        self._data: socket.socket | None = None
        self._buf = bytearray()
        self._closed = False
        self.reconnects = 0  # connections a command had to (re)open after a drop or a reset
        self._settings: dict = {}
        if connect:
            try:
                self.open()
            except BaseException:
                self.close()
                raise

    def __repr__(self):
        return f"RemoteExCamera({self.host!r}, {self.port}, data_port={self.data_port})"

    @property
    def address(self) -> tuple[str, int]:
        return (self.host, self.port)

    # ------------------------------------------------------------ connection
    def open(self) -> None:
        """Connect (if not connected) and start the application if asked to."""
        with self._lock:
            self._closed = False
            if self._cmd is None:
                try:
                    self._connect()
                except _Dropped as exc:
                    raise ConnectionLost(f"cannot connect to RemoteEx at {self.host}:{self.port}: {exc}") from None
            if self._start_app and not self._app_started:
                self.command("AppStart", timeout_s=self.app_start_timeout_s)
                self._app_started = True

    def _connect(self) -> None:
        deadline = time.monotonic() + self.connect_timeout_s
        cmd = data = None
        try:
            cmd = self._open_socket(self.port, deadline)
            self._expect_banner(cmd, COMMAND_BANNER, deadline, "command")
            data = self._open_socket(self.data_port, deadline)
            self._expect_banner(data, DATA_BANNER, deadline, "data")
        except BaseException:
            for s in (cmd, data):
                if s is not None:
                    s.close()
            raise
        self._cmd, self._data = cmd, data
        self._buf.clear()

    def _open_socket(self, port: int, deadline: float) -> socket.socket:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise _Dropped(f"connect timeout ({self.connect_timeout_s} s)")
        try:
            s = socket.create_connection((self.host, port), timeout=remaining)
        except (socket.timeout, TimeoutError):
            raise _Dropped(f"connect to port {port} timed out") from None
        except OSError as exc:
            raise _Dropped(f"connect to port {port}: {exc}") from None
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return s

    def _expect_banner(self, s: socket.socket, banner: bytes, deadline: float, which: str) -> None:
        got = bytearray()
        while not got.endswith(TERMINATOR):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise _Dropped(f"no RemoteEx banner on the {which} port within {self.connect_timeout_s} s "
                               f"(got {bytes(got)!r})")
            try:
                s.settimeout(remaining)
                chunk = s.recv(len(banner) - len(got) if len(got) < len(banner) else 1)
            except (socket.timeout, TimeoutError):
                continue
            except OSError as exc:
                raise _Dropped(f"{which} port: {exc}") from None
            if not chunk:
                raise _Dropped(f"{which} port closed before the RemoteEx banner")
            got += chunk
            if len(got) > len(banner):
                break
        if bytes(got) != banner:
            raise ProtocolError(f"unexpected RemoteEx banner on the {which} port (expected {banner!r})", bytes(got))

    def _disconnect(self) -> None:
        for s in (self._cmd, self._data):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self._cmd = self._data = None
        self._buf.clear()

    def close(self) -> None:
        """Close both connections (does not end the remote application; see :meth:`app_end`)."""
        with self._lock:
            self._disconnect()
            self._closed = True

    # -------------------------------------------------------------- commands
    def command(self, name: str, *args, timeout_s: float | None = None) -> list[str]:
        """Send one command and return the values of its reply.

        Parameters
        ----------
        name : str
            Command name, e.g. ``"CamParamGet"``.
        *args
            Arguments; converted with ``str``.
        timeout_s : float, optional
            Time allowed for the reply (default: ``self.timeout_s``).

        Returns
        -------
        list of str
            The fields after ``code,Name``.

        Raises
        ------
        DeviceError
            The reply carries a non-zero code (``.code``, ``.meaning``).
        DeviceTimeout, ProtocolError, ConnectionLost
        """
        values, _ = self._transaction(name, args, timeout_s=timeout_s)
        return values

    def _transaction(self, name: str, args, *, timeout_s: float | None = None, data=None):
        """Command, reply and (if ``data`` is a callable) the data-port payload, under the lock.

        ``data(values) -> int`` returns the byte count announced by the reply.
        Returns ``(values, payload_bytes_or_None)``.
        """
        wire = format_command(name, *args)
        timeout_s = self.timeout_s if timeout_s is None else float(timeout_s)
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"{self!r} is closed")
            last_drop = None
            for attempt in range(2):
                deadline = time.monotonic() + timeout_s
                try:
                    if self._cmd is None:
                        log.info("RemoteEx: (re)connecting to %s:%s for %s", self.host, self.port, name)
                        self._connect()
                        self.reconnects += 1
                    self._send(wire)
                    values = self._read_reply(name, wire, deadline)
                    payload = None
                    if data is not None:
                        payload = self._recv_data(data(values), deadline)
                    return values, payload
                except _Dropped as exc:
                    self._disconnect()
                    last_drop = exc
                    log.warning("RemoteEx: connection dropped during %s: %s", name, exc)
                    continue
                except (DeviceTimeout, ProtocolError):
                    # The stream is in an unknown state: start afresh on the next command.
                    self._disconnect()
                    raise
            raise ConnectionLost(f"RemoteEx connection to {self.host}:{self.port} lost during {name} "
                                 f"and could not be re-established: {last_drop}")

    def _send(self, wire: bytes) -> None:
        try:
            self._cmd.settimeout(self.timeout_s)
            self._cmd.sendall(wire)
        except (socket.timeout, TimeoutError):
            raise DeviceTimeout(f"RemoteEx: sending {wire!r} timed out") from None
        except OSError as exc:
            raise _Dropped(f"send: {exc}") from None

    def _read_line(self, deadline: float, wire: bytes) -> bytes:
        while True:
            i = self._buf.find(TERMINATOR)
            if i >= 0:
                line = bytes(self._buf[:i])
                del self._buf[: i + 1]
                return line.lstrip(b"\n")
            if len(self._buf) > _MAX_LINE:
                raise ProtocolError("RemoteEx reply line too long", bytes(self._buf[:200]))
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"RemoteEx: no reply to {wire.decode('ascii').strip()!r} "
                                    f"within the timeout (partial: {bytes(self._buf)!r})")
            try:
                self._cmd.settimeout(remaining)
                chunk = self._cmd.recv(4096)
            except (socket.timeout, TimeoutError):
                continue
            except OSError as exc:
                raise _Dropped(f"receive: {exc}") from None
            if not chunk:
                raise _Dropped("server closed the command connection")
            self._buf += chunk

    def _read_reply(self, name: str, wire: bytes, deadline: float) -> list[str]:
        while True:
            line = self._read_line(deadline, wire)
            if not line.strip():
                continue
            code, rname, values = parse_reply(line)
            if code in NOTIFICATION_CODES:
                log.debug("RemoteEx notification: %r", line)
                continue
            if rname.lower() != name.lower():
                log.warning("RemoteEx: skipping reply %r while waiting for %s", line, name)
                continue
            if code != 0:
                raise DeviceError(code, ERROR_MEANINGS.get(code, "unknown RemoteEx error code"),
                                  command=wire.decode("ascii").strip(), device="RemoteEx")
            return values

    def _recv_data(self, nbytes: int, deadline: float) -> bytes:
        out = bytearray()
        while len(out) < nbytes:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"RemoteEx: received {len(out)} of {nbytes} image bytes within the timeout")
            try:
                self._data.settimeout(remaining)
                chunk = self._data.recv(min(nbytes - len(out), 1 << 20))
            except (socket.timeout, TimeoutError):
                continue
            except OSError as exc:
                raise _Dropped(f"data port: {exc}") from None
            if not chunk:
                raise _Dropped("server closed the data connection")
            out += chunk
        return bytes(out)

    # --------------------------------------------------------- device calls
    def identify(self) -> str:
        """Application type and version, e.g. ``'Hamamatsu HPD-TA 9.5 (RemoteEx at host:1001)'``."""
        with self._lock:
            app = ",".join(self.command("AppInfo", "Type")).strip()
            version = ",".join(self.command("AppInfo", "Version")).strip()
        return f"Hamamatsu {app} {version} (RemoteEx at {self.host}:{self.port})"

    def app_end(self) -> None:
        """Close the remote application (HPD-TA/HiPic)."""
        self.command("AppEnd")
        self._app_started = False

    def configure(self, *, time_range: int | None = None, exposure_s: float | None = None,
                  gain: int | None = None) -> None:
        """Set the streak time range (setting number), exposure (s) and MCP gain (setting)."""
        for name, v in (("time_range", time_range), ("gain", gain)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))):
                raise ValueError(f"{name} must be an integer setting, got {v!r}")
        if time_range is not None and time_range < 1:
            raise ValueError(f"time_range must be >= 1, got {time_range}")
        if gain is not None and gain < 0:
            raise ValueError(f"gain must be >= 0, got {gain}")
        exposure_text = format_exposure(exposure_s) if exposure_s is not None else None
        with self._lock:
            if time_range is not None:
                self.command("DevParamSet", self.streak_device, "Time Range", int(time_range))
                self._settings["time_range"] = int(time_range)
            if exposure_text is not None:
                self.command("CamParamSet", self.exposure_location, "Exposure", exposure_text)
                self._settings["exposure_s"] = parse_exposure(exposure_text)
            if gain is not None:
                self.command("DevParamSet", self.streak_device, "MCP Gain", int(gain))
                self._settings["gain"] = int(gain)

    def exposure_s(self) -> float:
        """Exposure time read back from the camera, seconds."""
        values = self.command("CamParamGet", self.exposure_location, "Exposure")
        try:
            value = parse_exposure(values[0])
        except (IndexError, ValueError):
            raise ProtocolError("CamParamGet(Exposure) reply has no time value", ",".join(values).encode()) from None
        self._settings["exposure_s"] = value
        return value

    def _dev_int(self, parameter: str) -> int:
        values = self.command("DevParamGet", self.streak_device, parameter)
        try:
            return int(float(values[0]))
        except (IndexError, ValueError):
            raise ProtocolError(f"DevParamGet({parameter}) reply is not a number", ",".join(values).encode()) from None

    def time_range(self) -> int:
        """Streak time-range setting read back from the streak unit."""
        self._settings["time_range"] = v = self._dev_int("Time Range")
        return v

    def gain(self) -> int:
        """MCP gain setting read back from the streak unit."""
        self._settings["gain"] = v = self._dev_int("MCP Gain")
        return v

    def set_delay_ps(self, delay_ps: float) -> None:
        """Set the delay generator's delay (``Delay A``), picoseconds."""
        delay_ps = float(delay_ps)
        if not math.isfinite(delay_ps) or delay_ps < 0:
            raise ValueError(f"delay_ps must be finite and >= 0, got {delay_ps!r}")
        self.command("DevParamSet", self.delay_device, self.delay_parameter, format_seconds(delay_ps * 1e-12))
        self._settings["delay_ps"] = delay_ps

    def delay_ps(self) -> float:
        """Delay generator's delay read back, picoseconds."""
        values = self.command("DevParamGet", self.delay_device, self.delay_parameter)
        try:
            v = float(values[0]) * 1e12
        except (IndexError, ValueError):
            raise ProtocolError("DevParamGet(delay) reply is not a number", ",".join(values).encode()) from None
        self._settings["delay_ps"] = v
        return v

    def settings(self) -> dict:
        """All settings read back from the device: time_range, exposure_s, gain, delay_ps."""
        with self._lock:
            return {"time_range": self.time_range(), "exposure_s": self.exposure_s(),
                    "gain": self.gain(), "delay_ps": self.delay_ps()}

    def _refresh_settings(self) -> None:
        # Settings a rig may lack (no delay generator, no MCP gain control) are recorded as None.
        for key, getter in (("time_range", self.time_range), ("exposure_s", self.exposure_s),
                            ("gain", self.gain), ("delay_ps", self.delay_ps)):
            if key not in self._settings:
                try:
                    getter()
                except DeviceError as exc:
                    log.info("RemoteEx: %s not readable (%s); recorded as None", key, exc)
                    self._settings[key] = None

    def acq_status(self) -> tuple[str, str]:
        """``(status, mode)``: status ``'idle'`` or ``'busy'``; mode may be empty."""
        values = self.command("AcqStatus")
        if not values:
            raise ProtocolError("AcqStatus reply has no status", b"")
        return values[0].strip().lower(), (values[1].strip() if len(values) > 1 else "")

    def start(self, mode: str | None = None) -> None:
        """Start an acquisition in ``mode`` (default ``acquire_mode``)."""
        self.command("AcqStart", mode or self.acquire_mode)

    def stop(self) -> None:
        """Stop any running acquisition."""
        self.command("AcqStop")

    def read_image(self, *, timeout_s: float | None = None) -> np.ndarray:
        """Transfer the current image.

        Returns
        -------
        ndarray, shape (x, t), uint16
            Axis 0 along the slit (image columns), axis 1 along the sweep (image rows).
        """
        shape = {}

        def announced(values):
            try:
                w, h, bpp = int(values[0]), int(values[1]), int(values[2])
            except (IndexError, ValueError):
                raise ProtocolError("ImgDataGet reply lacks width,height,bytes-per-pixel",
                                    ",".join(values).encode()) from None
            if w <= 0 or h <= 0 or bpp not in _BPP_DTYPE or w * h > 1 << 28:
                raise ProtocolError(f"ImgDataGet announced an impossible image {w}x{h}x{bpp}",
                                    ",".join(values).encode())
            shape.update(w=w, h=h, bpp=bpp, type=values[3].strip() if len(values) > 3 else "")
            return w * h * bpp

        _, payload = self._transaction("ImgDataGet", ("Current", "Data"), timeout_s=timeout_s, data=announced)
        img = np.frombuffer(payload, dtype=_BPP_DTYPE[shape["bpp"]]).reshape(shape["h"], shape["w"])
        if shape["bpp"] == 4 and img.size and img.max() > np.iinfo(np.uint16).max:
            raise ProtocolError("32-bit image holds values beyond the uint16 range", b"")
        self._last_image_info = shape
        return np.ascontiguousarray(img.T).astype(np.uint16, copy=False)

    def acquire(self, *, timeout_s: float = 10.0) -> StreakImage:
        """Take one streak image: start, wait until idle, transfer.

        The whole sequence runs under the connection lock, so concurrent callers
        each get a complete image of their own.

        Parameters
        ----------
        timeout_s : float
            Bound on the whole acquisition, seconds.

        Returns
        -------
        StreakImage with ``data`` of shape (x, t), uint16.
        """
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
        deadline = time.monotonic() + timeout_s

        def late():
            return DeviceTimeout(f"RemoteEx: acquisition not finished within {timeout_s} s")

        def remaining():
            r = deadline - time.monotonic()
            if r <= 0:
                raise late()
            return min(r, self.timeout_s)

        with self._lock:
            try:
                self._start_acquisition(remaining)
                while True:
                    try:
                        values = self.command("AcqStatus", timeout_s=remaining())
                    except DeviceTimeout:
                        # a status query started just before the deadline gets only what is left
                        # of it: its timeout is the acquisition's, and is reported as such
                        if time.monotonic() >= deadline:
                            raise late() from None
                        raise
                    if values and values[0].strip().lower() == "idle":
                        break
                    if deadline - time.monotonic() <= 0:
                        raise late()
                    time.sleep(min(self.poll_interval_s, max(0.0, deadline - time.monotonic())))
            except DeviceTimeout:
                self._abort_acquisition()
                raise
            taken = time.time()
            data = self.read_image(timeout_s=remaining())
            if not {"time_range", "exposure_s", "gain", "delay_ps"} <= self._settings.keys():
                self._refresh_settings()
            meta = {"time_range": self._settings.get("time_range"),
                    "exposure_s": self._settings.get("exposure_s"),
                    "gain": self._settings.get("gain"),
                    "delay_ps": self._settings.get("delay_ps"),
                    "acquired_unix_s": taken,
                    "image_type": self._last_image_info.get("type", ""),
                    "bytes_per_pixel": self._last_image_info["bpp"]}
        return StreakImage(data=data, metadata=meta)

    def _start_acquisition(self, remaining) -> None:
        try:
            self.command("AcqStart", self.acquire_mode, timeout_s=remaining())
        except DeviceError as exc:
            # 7 (cannot execute): an acquisition is still running, e.g. one left over
            # from an interrupted session.  Stop it and start ours once more.
            if exc.code != 7:
                raise
            log.warning("RemoteEx: AcqStart refused (%s); stopping the running acquisition and retrying", exc)
            self.command("AcqStop", timeout_s=remaining())
            self.command("AcqStart", self.acquire_mode, timeout_s=remaining())

    def _abort_acquisition(self) -> None:
        try:
            self.command("AcqStop", timeout_s=min(self.timeout_s, 2.0))
        except DriverError as exc:
            log.warning("RemoteEx: AcqStop after an acquisition timeout failed: %s", exc)

    # ------------------------------------------------------- context manager
    def __enter__(self):
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.stop()
        except DriverError:
            if exc_type is None:
                self.close()
                raise
            log.exception("RemoteEx: could not stop the acquisition while leaving after an error")
        finally:
            self.close()
