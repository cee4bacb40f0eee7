"""A simulated Hamamatsu streak camera speaking RemoteEx over TCP.

The server binds 127.0.0.1 only, on a command port and the data port right
above it (as RemoteEx does), and serves one client at a time from a background
thread.  A client may open the two ports in either order, and read the
greetings whenever it likes: each connection is greeted as soon as it is
accepted, and a command that needs the data port uses the newest data
connection still open (code 9 if there is none).  What the commands do lives in
:mod:`drivers.sim.remoteex_commands`, the parameter tables in
:mod:`drivers.sim.remoteex_params`; this module is the networking.  Frames are rendered from a :class:`~drivers.sim.scene.VirtualScene`
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

    sim.inject("drop_reply" | "delay" | "garbage" | "close" | "error" | "notify" | "short_data"
               | "stray_data" | "wrong_name", command="AcqStatus", code=8, delay_s=1.0, times=1)

``notify`` sends unsolicited code-4 and code-5 messages before the real reply;
``short_data`` sends the ``ImgDataGet`` reply but only half of the pixel bytes;
``stray_data`` sends three stray bytes on the data port before answering;
``wrong_name`` answers 20000 times with a reply for another command, then correctly.
"""
from __future__ import annotations

import collections
import logging
import re
import select
import socket
import threading
import time

from drivers.remoteex_wire import COMMAND_BANNER, DATA_BANNER

from .faults import COMMON_KINDS, FaultInjector
from .remoteex_commands import RemoteExCommands, Reply
from .remoteex_images import frame_seed
from .scene import VirtualScene
from .state import LabState
from .timebase import SimClock, TimeBase

__all__ = ["RemoteExSimulator", "bind_port_pair", "frame_seed"]

log = logging.getLogger(__name__)

_CMD_RE = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_]*)\s*\((.*)\)\s*$", re.S)
STRAY = b"\x01\x01\x01"
WRONG_NAME_REPEATS = 20000
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


class _Gone(Exception):
    """Internal: the client connection is finished."""


class RemoteExSimulator(RemoteExCommands):
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
    single_sweep : bool
        A single-sweep streak unit (``Time Range`` such as ``1 ns``) instead of a
        synchroscan one (setting numbers 1..4).
    scaling_table : bool
        Whether images carry table scaling (``ImgDataGet(...,ScalingTable,Vertical)``).
    send_timeout_s : float
        Longest wait to hand bytes to a client that does not read them (it is then dropped).
    timebase : TimeBase, optional
        Trigger jitter, drift, sweep nonlinearity, shading and fiducial pulse
        (:mod:`drivers.sim.timebase`); all off by default.
    wall_clock : callable() -> float, optional
        Wall clock of the simulator's clock (:class:`~drivers.sim.timebase.SimClock`), for tests.
    """

    FAULT_KINDS = COMMON_KINDS | {"notify", "short_data", "stray_data", "wrong_name"}

    def __init__(self, state: LabState | None = None, scene: VirtualScene | None = None, *, seed: int = 0,
                 host: str = "127.0.0.1", port: int = 0, frame_time_s: float = 0.002,
                 app_type: str = "HPD-TA", app_version: str = "9.5 (simulated)", single_sweep: bool = False,
                 scaling_table: bool = True, send_timeout_s: float = 10.0, timebase: TimeBase | None = None,
                 wall_clock=None):
        self.timebase = timebase if timebase is not None else TimeBase()
        if not isinstance(self.timebase, TimeBase):
            raise ValueError(f"timebase must be a TimeBase, got {type(self.timebase).__name__}")
        self.clock = SimClock(self.timebase.clock_speed, wall_clock)
        self.state = state if state is not None else LabState()
        self.scene = scene if scene is not None else VirtualScene.default(seed=seed)
        self.seed = int(seed)
        self.host = host
        self._requested_port = int(port)
        self.frame_time_s = float(frame_time_s)
        self.app_type = app_type
        self.app_version = app_version
        self.single_sweep = bool(single_sweep)
        self.scaling_table = bool(scaling_table)
        if not send_timeout_s > 0:
            raise ValueError(f"send_timeout_s must be > 0, got {send_timeout_s!r}")
        self.send_timeout_s = float(send_timeout_s)
        self.faults = FaultInjector(self.FAULT_KINDS)
        self.received: collections.deque[str] = collections.deque(maxlen=4096)
        self.connections = 0
        self.frames_rendered = 0
        self._init_device()
        self._dev_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listeners: tuple[socket.socket, socket.socket] | None = None
        self._conns: list[socket.socket] = []
        self._cmd: socket.socket | None = None
        self._data_conns: list[socket.socket] = []

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
    def _serve_forever(self) -> None:
        cmd_l, data_l = self._listeners
        buf = bytearray()
        try:
            while not self._stop.is_set():
                wait = self.next_event_in_s()
                wait = 0.05 if wait is None else min(0.05, wait)
                watched = [data_l, *self._data_conns, self._cmd if self._cmd is not None else cmd_l]
                try:
                    ready, _, _ = select.select(watched, [], [], wait)
                except (OSError, ValueError):
                    self._prune()
                    continue
                if data_l in ready:
                    self._accept_data(data_l)
                for d in [c for c in ready if c in self._data_conns]:
                    self._read_data_conn(d)
                if cmd_l in ready and self._cmd is None:
                    try:
                        conn, _ = cmd_l.accept()
                        conn.settimeout(self.send_timeout_s)     # a client that stops reading is dropped
                        conn.sendall(COMMAND_BANNER)
                    except OSError:
                        continue
                    self._cmd, buf = conn, bytearray()
                    self.connections += 1
                    self._conns = [conn, *self._data_conns]
                try:
                    if self._cmd is not None and self._cmd in ready:
                        chunk = self._cmd.recv(4096)
                        if not chunk:
                            # Its data connection closes by itself; a newer client's may already be open.
                            self._drop_client(data_too=False)
                            continue
                        buf += chunk
                        if len(buf) > 1 << 16:
                            raise _Gone("command line too long")
                        while (i := buf.find(b"\r")) >= 0:
                            line = bytes(buf[:i]).lstrip(b"\n")
                            del buf[: i + 1]
                            if line.strip():
                                self._accept_data(data_l)     # a data connection opened just before the command
                                self._handle_line(self._cmd, line)
                    self._send_events()
                except (_Gone, OSError) as exc:
                    log.debug("RemoteEx simulator: client gone (%s)", exc)
                    self._drop_client()
                except Exception:
                    log.exception("RemoteEx simulator: internal error; dropping the client")
                    self._drop_client()
        finally:
            self._drop_client()

    def _accept_data(self, data_l) -> None:
        while True:
            try:
                r, _, _ = select.select([data_l], [], [], 0)
            except (OSError, ValueError):
                return
            if not r:
                return
            try:
                conn, _ = data_l.accept()
                conn.settimeout(self.send_timeout_s)
                conn.sendall(DATA_BANNER)
            except OSError:
                continue
            self._data_conns.append(conn)
            self._conns = [c for c in (self._cmd, *self._data_conns) if c is not None]

    def _read_data_conn(self, d: socket.socket) -> None:
        try:
            chunk = d.recv(4096)
        except OSError:
            chunk = b""
        if not chunk:                         # that client closed its data connection
            self._data_conns.remove(d)
            d.close()

    def _prune(self) -> None:
        for d in list(self._data_conns):
            if d.fileno() < 0:
                self._data_conns.remove(d)

    def _data_conn(self) -> socket.socket | None:
        """The newest data connection still open."""
        for d in reversed(list(self._data_conns)):
            try:
                r, _, _ = select.select([d], [], [], 0)
                if r and d.recv(1, socket.MSG_PEEK) == b"":
                    self._data_conns.remove(d)
                    d.close()
                    continue
            except OSError:
                self._data_conns.remove(d)
                continue
            return d
        return None

    def _drop_client(self, data_too: bool = True) -> None:
        for s in [self._cmd, *(self._data_conns if data_too else [])]:
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self._cmd = None
        if data_too:
            self._data_conns = []
        self._conns = list(self._data_conns)
        self.outbox.clear()

    def _send_events(self) -> None:
        with self._dev_lock:
            self.tick()
            events, self.outbox[:] = list(self.outbox), []
        if events and self._cmd is not None:
            self._cmd.sendall(b"".join(events))

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
    def _handle_line(self, conn, line: bytes) -> None:
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
            if fault.kind == "stray_data":
                d = self._data_conn()
                if d is not None:
                    d.sendall(STRAY)
            if fault.kind == "wrong_name":
                other = "AcqStatus" if name.lower() != "acqstatus" else "CamParamGet"
                conn.sendall(f"0,{other},idle\r".encode("ascii") * WRONG_NAME_REPEATS)
        with self._dev_lock:
            self.tick()
            try:
                values, payload = self.execute(name, args)
                reply = ",".join(["0", name] + [str(v) for v in values]) + "\r"
            except Reply as r:
                values, payload = None, None
                reply = f"{r.code},{name}\r"
            events, self.outbox[:] = list(self.outbox), []
        if events:
            conn.sendall(b"".join(events))
        if fault is not None and fault.kind == "drop_reply":
            return
        data = self._data_conn() if payload is not None else None
        if payload is not None and data is None:
            conn.sendall(f"9,{name}\r".encode("ascii"))     # data cannot be sent via TCP/IP
            return
        conn.sendall(reply.encode("ascii"))
        if payload is not None:
            if fault is not None and fault.kind == "short_data":
                data.sendall(payload[: len(payload) // 2])
            else:
                data.sendall(payload)
