"""A simulated Hamamatsu streak camera speaking RemoteEx over TCP.

The server binds 127.0.0.1 only, on a command port and the data port right
above it (as RemoteEx does), and serves one client at a time from a background
thread.  Frames are rendered from a :class:`~drivers.sim.scene.VirtualScene`
and the shared :class:`~drivers.sim.state.LabState`:

* the line shown is the scene line whose angle is nearest the mirror angle;
* no light when the laser-sync output is off (dark level and read noise only);
* the time window opens ``sync_delay_ps`` plus the delay-box delay later;
* counts follow :meth:`VirtualScene.render_frame` (Poisson photon noise,
  Gaussian read noise, clipped to uint16).

Noise is seeded per frame from ``(seed, mirror angle, total delay, output
state, index)``, where ``index`` counts the frames taken since any of those (or
the exposure, gain or time range) last changed, for example since the mirror
last moved.  The same seed and the same sequence of commands therefore give the
same bytes, and a capture resumed after a crash reproduces an uninterrupted one.

Protocol state (application started, settings, the current image) belongs to
the server, not to a connection: a client that reconnects finds it unchanged,
like a RemoteEx server whose application keeps running.

Faults for tests (one-shot, see :mod:`drivers.sim.faults`)::

    sim.inject("drop_reply" | "delay" | "garbage" | "close" | "error" | "notify" | "short_data",
               command="AcqStatus", code=8, delay_s=1.0, times=1)

``notify`` sends unsolicited code-4 and code-5 messages before the real reply;
``short_data`` sends the ``ImgDataGet`` reply but only half of the pixel bytes.
"""
from __future__ import annotations

import collections
import logging
import re
import select
import socket
import threading
import time

import numpy as np

from drivers.remoteex import COMMAND_BANNER, DATA_BANNER, format_exposure, format_seconds, parse_exposure

from .faults import COMMON_KINDS, FaultInjector
from .scene import TIME_RANGE_SCALE, VirtualScene
from .state import LabState

__all__ = ["RemoteExSimulator", "bind_port_pair", "frame_seed"]

log = logging.getLogger(__name__)

_CMD_RE = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_]*)\s*\((.*)\)\s*$", re.S)
_STREAK_NAMES = {"streak", "streakcamera", "td"}
_DELAY_NAMES = {"delaybox", "del", "delay", "del1"}
_EXPOSURE_LOCATIONS = {"acquire", "live", "ai", "pc"}
_GAIN_RANGE = (0, 63)
_EXPOSURE_RANGE_S = (1e-6, 10.0)
_DELAY_RANGE_S = (0.0, 1e-6)
GARBAGE = b"\x15\xfe\xff#garbage, not RemoteEx\r"


def bind_port_pair(host: str = "127.0.0.1", port: int = 0, attempts: int = 64):
    """Listening sockets on ``port`` and ``port + 1``.

    With ``port=0`` an ephemeral command port is chosen whose successor is
    free too (retrying with fresh ephemeral ports); returns
    ``(command_socket, data_socket)``.

    Raises
    ------
    OSError
        If a fixed pair is taken, or no free pair was found in ``attempts`` tries.
    """

    def listener(p):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, p))
            s.listen(4)
        except OSError:
            s.close()
            raise
        return s

    if port:
        c = listener(int(port))
        try:
            return c, listener(int(port) + 1)
        except OSError:
            c.close()
            raise
    for _ in range(attempts):
        c = listener(0)
        p = c.getsockname()[1]
        if p + 1 > 65535:
            c.close()
            continue
        try:
            return c, listener(p + 1)
        except OSError:
            c.close()
    raise OSError(f"no free pair of adjacent ports on {host} after {attempts} attempts")


def _zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def frame_seed(seed: int, angle_deg: float, delay_ps: float, output: bool, index: int) -> np.random.SeedSequence:
    """Seed sequence of one frame's noise (angle quantised to 1e-6 deg, delay to 1e-3 ps)."""
    return np.random.SeedSequence([_zigzag(int(seed)), _zigzag(int(round(angle_deg * 1e6))),
                                   _zigzag(int(round(delay_ps * 1e3))), int(bool(output)), int(index)])


class _Reply(Exception):
    """Internal: a handler's error reply."""

    def __init__(self, code: int):
        self.code = code


class _Gone(Exception):
    """Internal: the client connection is finished."""


class RemoteExSimulator:
    """RemoteEx TCP server in a thread.

    Parameters
    ----------
    state : LabState, optional
        Shared virtual-lab state (a fresh one if omitted).
    scene : VirtualScene, optional
        What the camera sees (``VirtualScene.default(seed=seed)`` if omitted).
    seed : int
        Noise seed.
    host : str
        Bind address; loopback only by default.
    port : int
        Command port; 0 picks a free ephemeral pair.  The data port is ``port + 1``.
    frame_time_s : float
        Simulated duration of one acquisition (``AcqStatus`` reports busy meanwhile).
    app_type, app_version : str
        Reported by ``AppInfo(Type)`` and ``AppInfo(Version)``.
    """

    FAULT_KINDS = COMMON_KINDS | {"notify", "short_data"}

    def __init__(self, state: LabState | None = None, scene: VirtualScene | None = None, *, seed: int = 0,
                 host: str = "127.0.0.1", port: int = 0, frame_time_s: float = 0.002,
                 app_type: str = "HPD-TA", app_version: str = "9.5 (simulated)",
                 data_accept_timeout_s: float = 5.0):
        self.state = state if state is not None else LabState()
        self.scene = scene if scene is not None else VirtualScene.default(seed=seed)
        self.seed = int(seed)
        self.host = host
        self._requested_port = int(port)
        self.frame_time_s = float(frame_time_s)
        self.app_type = app_type
        self.app_version = app_version
        self.data_accept_timeout_s = float(data_accept_timeout_s)
        self.faults = FaultInjector(self.FAULT_KINDS)
        self.received: collections.deque[str] = collections.deque(maxlen=4096)
        self.connections = 0
        self.frames_rendered = 0
        # Device state (outlives connections).
        self.app_started = False
        self.exposure_s = self.scene.reference_exposure_s
        self.gain = int(self.scene.reference_gain)
        self.time_range = int(self.scene.time_range)
        self.delaybox_s = 0.0
        self._busy_until = 0.0
        self._acquiring = False
        self._image: np.ndarray | None = None          # (n_t, n_x) uint16, rows = time
        self._image_meta: dict = {}
        self._view_key = None
        self._view_index = -1
        self._dev_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listeners: tuple[socket.socket, socket.socket] | None = None
        self._conns: list[socket.socket] = []

    # --------------------------------------------------------------- control
    @property
    def port(self) -> int:
        if self._listeners is None:
            raise RuntimeError("simulator not started")
        return self._listeners[0].getsockname()[1]

    @property
    def data_port(self) -> int:
        if self._listeners is None:
            raise RuntimeError("simulator not started")
        return self._listeners[1].getsockname()[1]

    @property
    def address(self) -> tuple[str, int]:
        """``(host, command_port)``; the data port is ``command_port + 1``."""
        return (self.host, self.port)

    def inject(self, kind: str, command: str | None = None, **kw) -> None:
        """Arm a one-shot fault (see the module docstring)."""
        self.faults.inject(kind, command, **kw)

    def start(self) -> "RemoteExSimulator":
        if self._thread is not None:
            raise RuntimeError("simulator already started")
        self._listeners = bind_port_pair(self.host, self._requested_port)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve_forever, name=f"remoteex-sim:{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop serving and close every socket; returns once the thread ended (bounded)."""
        self._stop.set()
        for c in list(self._conns):
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("RemoteEx simulator thread did not stop within %s s", timeout_s)
        self._thread = None
        if self._listeners is not None:
            for s in self._listeners:
                s.close()
        self._listeners = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ----------------------------------------------------------- networking
    def _wait_readable(self, s: socket.socket, timeout_s: float) -> bool:
        """Wait until ``s`` is readable, the stop flag is set, or the timeout expires."""
        end = time.monotonic() + timeout_s
        while not self._stop.is_set():
            left = end - time.monotonic()
            if left <= 0:
                return False
            try:
                r, _, _ = select.select([s], [], [], min(0.05, left))
            except (OSError, ValueError):
                return False
            if r:
                return True
        return False

    def _serve_forever(self) -> None:
        cmd_l, data_l = self._listeners
        while not self._stop.is_set():
            if not self._wait_readable(cmd_l, 3600.0):
                continue
            try:
                conn, _ = cmd_l.accept()
            except OSError:
                continue
            data = None
            try:
                self._drain_stale(data_l)
                conn.sendall(COMMAND_BANNER)
                if not self._wait_readable(data_l, self.data_accept_timeout_s):
                    log.info("RemoteEx simulator: client never opened the data port")
                    continue
                data, _ = data_l.accept()
                data.sendall(DATA_BANNER)
                self.connections += 1
                self._conns = [conn, data]
                self._serve_client(conn, data)
            except (_Gone, OSError) as exc:
                log.debug("RemoteEx simulator: client gone (%s)", exc)
            except Exception:
                log.exception("RemoteEx simulator: internal error; dropping the client")
            finally:
                self._conns = []
                for s in (conn, data):
                    if s is not None:
                        try:
                            s.close()
                        except OSError:
                            pass

    @staticmethod
    def _drain_stale(listener: socket.socket) -> None:
        # A data-port connection queued before the command banner was sent belongs to an
        # earlier client that gave up; a new client connects only after reading the banner.
        while True:
            r, _, _ = select.select([listener], [], [], 0)
            if not r:
                return
            try:
                stale, _ = listener.accept()
                stale.close()
            except OSError:
                return

    def _serve_client(self, conn: socket.socket, data: socket.socket) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            i = buf.find(b"\r")
            if i < 0:
                if not self._wait_readable(conn, 3600.0):
                    continue
                chunk = conn.recv(4096)
                if not chunk:
                    raise _Gone("client closed the command connection")
                buf += chunk
                if len(buf) > 1 << 16:
                    raise _Gone("command line too long")
                continue
            line = bytes(buf[:i]).lstrip(b"\n")
            del buf[: i + 1]
            if line.strip():
                self._handle_line(conn, data, line)

    def _client_gone(self, conn: socket.socket) -> bool:
        try:
            r, _, _ = select.select([conn], [], [], 0)
            return bool(r) and conn.recv(1, socket.MSG_PEEK) == b""
        except OSError:
            return True

    def _sleep(self, conn: socket.socket, delay_s: float) -> None:
        end = time.monotonic() + delay_s
        while time.monotonic() < end:
            if self._stop.is_set() or self._client_gone(conn):
                raise _Gone("client left during a delayed reply")
            time.sleep(min(0.02, max(0.0, end - time.monotonic())))

    # --------------------------------------------------------------- protocol
    def _handle_line(self, conn, data, line: bytes) -> None:
        text = line.decode("ascii", errors="replace")
        self.received.append(text)
        m = _CMD_RE.match(text)
        if not m:
            name = text.split("(")[0].strip() or "?"
            conn.sendall(f"1,{name}\r".encode("ascii", "replace"))
            return
        name, argtext = m.group(1), m.group(2)
        args = [a.strip() for a in argtext.split(",")] if argtext.strip() else []
        fault = self.faults.take(name)
        if fault is not None:
            log.info("RemoteEx simulator: injecting %s on %s", fault.kind, name)
            if fault.kind == "close":
                raise _Gone("fault: close")
            if fault.kind == "garbage":
                conn.sendall(GARBAGE)
                return
            if fault.kind == "error":
                conn.sendall(f"{fault.code},{name}\r".encode("ascii"))
                return
            if fault.kind == "delay":
                self._sleep(conn, fault.delay_s)
            if fault.kind == "notify":
                conn.sendall(b"4,Livemonitor,1\r5,Message,simulated status notification\r")
        try:
            values, payload = self._execute(name, args)
            reply = ",".join(["0", name] + [str(v) for v in values]) + "\r"
        except _Reply as r:
            values, payload = None, None
            reply = f"{r.code},{name}\r"
        if fault is not None and fault.kind == "drop_reply":
            return
        conn.sendall(reply.encode("ascii"))
        if payload is not None:
            if fault is not None and fault.kind == "short_data":
                data.sendall(payload[: len(payload) // 2])
            else:
                data.sendall(payload)

    def _execute(self, name: str, args: list[str]):
        """Run one command; returns ``(reply values, data-port payload or None)``."""
        key = name.lower()
        handler = getattr(self, f"_cmd_{key}", None)
        if handler is None:
            raise _Reply(2)
        with self._dev_lock:
            return handler(args)

    @staticmethod
    def _need(args, n):
        if len(args) < n:
            raise _Reply(6)

    def _need_app(self):
        if not self.app_started:
            raise _Reply(3)

    def _poll(self):
        if self._acquiring and time.monotonic() >= self._busy_until:
            self._acquiring = False

    # Application
    def _cmd_appstart(self, args):
        self.app_started = True
        return [], None

    def _cmd_append(self, args):
        self._need_app()
        self.app_started = False
        self._acquiring = False
        return [], None

    def _cmd_appinfo(self, args):
        self._need(args, 1)
        info = {"type": self.app_type, "version": self.app_version, "title": "streaklab RemoteEx simulator"}
        value = info.get(args[0].lower())
        if value is None:
            raise _Reply(2)
        return [value], None

    # Acquisition
    def _cmd_acqstart(self, args):
        self._need_app()
        self._need(args, 1)
        if args[0].lower() != "acquire":
            raise _Reply(2)
        self._poll()
        if self._acquiring:
            raise _Reply(7)
        self._image, self._image_meta = self._render()
        self._acquiring = True
        self._busy_until = time.monotonic() + self.frame_time_s
        return [], None

    def _cmd_acqstatus(self, args):
        self._need_app()
        self._poll()
        return (["busy", "Acquire"] if self._acquiring else ["idle"]), None

    def _cmd_acqstop(self, args):
        self._acquiring = False
        return [], None

    def _cmd_imgdataget(self, args):
        self._need_app()
        self._need(args, 2)
        if args[0].lower() != "current" or args[1].lower() != "data":
            raise _Reply(2)
        self._poll()
        if self._acquiring:
            raise _Reply(3)
        if self._image is None:
            raise _Reply(7)
        img = self._image
        return [img.shape[1], img.shape[0], 2, "Data"], img.astype("<u2").tobytes()

    # Camera
    def _cmd_camparamget(self, args):
        self._need_app()
        self._need(args, 2)
        if args[0].lower() not in _EXPOSURE_LOCATIONS or args[1].lower() != "exposure":
            raise _Reply(2)
        return [format_exposure(self.exposure_s)], None

    def _cmd_camparamset(self, args):
        self._need_app()
        self._need(args, 3)
        if args[0].lower() not in _EXPOSURE_LOCATIONS or args[1].lower() != "exposure":
            raise _Reply(2)
        try:
            value = parse_exposure(args[2])
        except ValueError:
            raise _Reply(1) from None
        if not _EXPOSURE_RANGE_S[0] <= value <= _EXPOSURE_RANGE_S[1]:
            raise _Reply(10)
        self.exposure_s = value
        return [], None

    # External devices
    def _device(self, args):
        dev = args[0].lower()
        if dev in _STREAK_NAMES:
            return "streak"
        if dev in _DELAY_NAMES:
            return "delay"
        raise _Reply(2)

    def _cmd_devparamget(self, args):
        self._need_app()
        self._need(args, 2)
        dev, param = self._device(args), args[1].lower()
        if dev == "streak":
            values = {"time range": str(self.time_range), "mcp gain": str(self.gain),
                      "devicename": "C5680 streak unit (simulated)"}
        else:
            values = {"delay a": format_seconds(self.delaybox_s), "devicename": "delay generator (simulated)"}
        if param not in values:
            raise _Reply(2)
        return [values[param]], None

    def _cmd_devparamset(self, args):
        self._need_app()
        self._need(args, 3)
        dev, param, raw = self._device(args), args[1].lower(), args[2]
        try:
            number = float(raw)
        except ValueError:
            raise _Reply(1) from None
        if dev == "streak" and param == "time range":
            if number != int(number) or int(number) not in TIME_RANGE_SCALE:
                raise _Reply(10)
            self.time_range = int(number)
        elif dev == "streak" and param == "mcp gain":
            if number != int(number) or not _GAIN_RANGE[0] <= number <= _GAIN_RANGE[1]:
                raise _Reply(10)
            self.gain = int(number)
        elif dev == "delay" and param == "delay a":
            if not _DELAY_RANGE_S[0] <= number <= _DELAY_RANGE_S[1]:
                raise _Reply(10)
            self.delaybox_s = number
        else:
            raise _Reply(2)
        return [], None

    # -------------------------------------------------------------- frames
    def _render(self):
        with self.state.lock:
            angle = float(self.state.mirror_angle_deg)
            light = bool(self.state.sync_output_enabled)
            sync_delay_ps = float(self.state.sync_delay_ps)
        delay_ps = sync_delay_ps + self.delaybox_s * 1e12
        key = (round(angle, 6), round(delay_ps, 3), light, self.exposure_s, self.gain, self.time_range)
        if key == self._view_key:
            self._view_index += 1
        else:
            self._view_key, self._view_index = key, 0
        rng = np.random.default_rng(frame_seed(self.seed, angle, delay_ps, light, self._view_index))
        line = self.scene.line_index(angle)
        frame = self.scene.render_frame(line, rng, delay_ps=delay_ps, exposure_s=self.exposure_s, gain=self.gain,
                                        time_range=self.time_range, light=light)
        self.frames_rendered += 1
        meta = {"line": line, "angle_deg": angle, "delay_ps": delay_ps, "light": light, "index": self._view_index}
        return np.ascontiguousarray(frame.T), meta     # (n_t, n_x): image rows are the sweep direction

    @property
    def last_frame_info(self) -> dict:
        """Line, angle, delay, light and noise index of the most recent frame."""
        return dict(self._image_meta)
