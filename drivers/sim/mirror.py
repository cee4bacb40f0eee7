"""Simulated SMC100-style scan-mirror controller on a pseudo-terminal.

The simulator owns the master side of a pty pair (``os.openpty``) and serves
the SMC100 ASCII protocol on it from a thread; a driver opens the slave side's
``/dev/pts/N`` path exactly as it would open ``/dev/ttyUSB0``.  A stable
symbolic link to the current slave (``stable_port``, like a udev
``/dev/serial/by-id`` link) survives a simulated re-plug.

Behaviour follows the Newport SMC100 manual: the controller starts NOT
REFERENCED (``0A``) and refuses moves (error ``H``) until ``OR`` has homed it;
``OR`` is HOMING (``1E``) for a time proportional to the distance to 0, then
READY from HOMING (``32``); ``PA`` outside the software travel limits is
refused with error ``C``; a move is MOVING (``28``) for ``distance /
velocity`` seconds of wall-clock time, then READY from MOVING (``33``);
``ST`` stops where the stage is.  Setting commands never answer; ``TE``
returns (and clears) the last error letter.

Fault injection (one-shot, see :mod:`drivers.sim.faults`)::

    sim.inject("drop_reply", command="TP")   # next TP is executed, no answer
    sim.inject("delay", command="TS", delay_s=1.0)
    sim.inject("garbage")                    # next query answered with noise
    sim.inject("error", command="PA", code="V")  # next PA fails with TE = V
    sim.inject("close")                      # port vanishes, reappears at stable_port (re-plug)
    sim.inject("unplug")                     # port vanishes for good
"""
from __future__ import annotations

import collections
import os
import re
import select
import tempfile
import threading
import time
import tty

from .faults import COMMON_KINDS, FaultInjector
from .state import LabState

_LINE = re.compile(r"^(\d{1,2})([A-Za-z]{2})(.*)$")
_GET_ALWAYS = {"TE", "TP", "TS"}  # manual syntax xxTE / xxTP / xxTS (a trailing "?" is tolerated)
_READY_STATES = {"32", "33", "34", "35"}
_GARBAGE = b"\x8f\x00\xfe#@!\x15\r\n"


class MirrorSimulator:
    """SMC100-style controller serving on a pseudo-terminal.

    Parameters
    ----------
    lab_state : LabState, optional
        Shared virtual-lab state; the simulator writes ``mirror_angle_deg`` and
        ``mirror_referenced``.  A private one is made if omitted.
    address : int
        Controller address (1..31).
    velocity_deg_per_s : float
        Speed of moves and of the home search, degrees per second.
    travel_deg : (float, float)
        Software travel limits (SL, SR), degrees.
    initial_angle_deg : float
        Where the stage sits at power-up (not referenced).
    stage_id : str
        Text answered to ``ID?``.
    min_home_s : float
        Shortest home search, seconds (the search takes at least this long even at 0).

    Use as a context manager, or call :meth:`start` and :meth:`close`.
    """

    def __init__(self, lab_state: LabState | None = None, *, address: int = 1,
                 velocity_deg_per_s: float = 100.0, travel_deg: tuple[float, float] = (-45.0, 45.0),
                 initial_angle_deg: float = 0.0, stage_id: str = "SLAB-GALVO-SIM",
                 min_home_s: float = 0.05):
        if not 1 <= int(address) <= 31:
            raise ValueError(f"address must be 1..31, got {address!r}")
        if not velocity_deg_per_s > 0:
            raise ValueError(f"velocity_deg_per_s must be > 0, got {velocity_deg_per_s!r}")
        lo, hi = (float(v) for v in travel_deg)
        if not lo < hi:
            raise ValueError(f"travel_deg must be (low, high) with low < high, got {travel_deg!r}")
        self.lab_state = lab_state if lab_state is not None else LabState()
        self.address = int(address)
        self.velocity_deg_per_s = float(velocity_deg_per_s)
        self.travel_deg = (lo, hi)
        self.stage_id = stage_id
        self.min_home_s = float(min_home_s)
        self.faults = FaultInjector(COMMON_KINDS | {"unplug"})
        self.received = collections.deque(maxlen=1000)  # the last command lines received, for tests
        self._lock = threading.RLock()
        # motion model: position moves linearly from _from_deg to _to_deg over [_t0, _t1]
        self._from_deg = self._to_deg = float(initial_angle_deg)
        self._t0 = self._t1 = time.monotonic()
        self._state = "0A"
        self._after_motion = "33"
        self._error = "@"
        self._master = self._slave = None
        self._thread = None
        self._stop = threading.Event()
        self._linkdir = None
        self.port = None
        self.stable_port = None
        self._publish()

    # ------------------------------------------------------------------ lifetime
    def start(self) -> "MirrorSimulator":
        if self._thread is not None:
            raise RuntimeError("simulator already started")
        self._linkdir = tempfile.mkdtemp(prefix="streaklab-mirror-")
        self.stable_port = os.path.join(self._linkdir, "ttySMC100")
        self._open_pty()
        self._thread = threading.Thread(target=self._serve, name="mirror-sim", daemon=True)
        self._thread.start()
        return self

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)   # no echo, no CR/LF translation: bytes pass unchanged
        tty.setraw(master)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        tmp = self.stable_port + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(self.port, tmp)
        os.replace(tmp, self.stable_port)

    def _close_pty(self) -> None:
        with self._lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            self._master = self._slave = None

    def close(self) -> None:
        """Stop serving and release the pty (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._close_pty()
        if self._linkdir is not None:
            for name in os.listdir(self._linkdir):
                os.unlink(os.path.join(self._linkdir, name))
            os.rmdir(self._linkdir)
            self._linkdir = None

    def __enter__(self):
        return self.start() if self._thread is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    def inject(self, kind: str, command: str | None = None, **kwargs) -> None:
        """Arm a one-shot fault (see the module docstring and :class:`FaultInjector`)."""
        self.faults.inject(kind, command, **kwargs)

    # ------------------------------------------------------------------ motion model
    def _advance(self, now: float | None = None) -> float:
        """Bring the motion state up to ``now``; return the current angle."""
        now = time.monotonic() if now is None else now
        with self._lock:
            if now >= self._t1:
                pos = self._to_deg
                if self._state == "28":
                    self._state = self._after_motion
                elif self._state == "1E":
                    self._state = "32"
            else:
                frac = (now - self._t0) / (self._t1 - self._t0)
                pos = self._from_deg + frac * (self._to_deg - self._from_deg)
            self._publish(pos)
            return pos

    def _publish(self, pos: float | None = None) -> None:
        if pos is None:
            pos = self._to_deg
        with self.lab_state.lock:
            self.lab_state.mirror_angle_deg = float(pos)
            self.lab_state.mirror_referenced = self._state in _READY_STATES or self._state == "28"

    def _start_motion(self, target: float, state: str, min_s: float = 0.0) -> None:
        now = time.monotonic()
        pos = self._advance(now)
        self._from_deg, self._to_deg = pos, float(target)
        self._t0 = now
        self._t1 = now + max(min_s, abs(target - pos) / self.velocity_deg_per_s)
        self._state = state

    @property
    def state_code(self) -> str:
        """Current two-character controller state."""
        with self._lock:
            self._advance()
            return self._state

    # ------------------------------------------------------------------ serving
    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            master = self._master
            if master is None:
                self._advance()
                time.sleep(0.02)
                continue
            try:
                ready, _, _ = select.select([master], [], [], 0.02)
                data = os.read(master, 4096) if ready else b""
            except (OSError, ValueError):
                data = b""
                time.sleep(0.02)
            self._advance()
            if not data:
                continue
            buf += data
            while True:
                m = re.search(rb"\r\n|\r|\n", buf)
                if m is None:
                    break
                line = bytes(buf[:m.start()])
                del buf[:m.end()]
                if line:
                    self._handle(line)
            if len(buf) > 1024:  # a line that never ends: the real controller would drop it
                buf.clear()

    def _send(self, payload: str, fault=None) -> None:
        data = payload.encode("ascii") + b"\r\n"
        if fault is not None:
            if fault.kind == "drop_reply":
                return
            if fault.kind == "garbage":
                data = _GARBAGE
            if fault.kind == "delay":
                timer = threading.Timer(fault.delay_s, self._write, args=(data, self._master))
                timer.daemon = True
                timer.start()
                return
        self._write(data)

    def _write(self, data: bytes, master: int | None = None) -> None:
        with self._lock:
            if master is None:
                master = self._master
            # a late (delayed) reply goes nowhere if its port has gone since
            if master is None or master != self._master or self._stop.is_set():
                return
            try:
                os.write(master, data)
            except OSError:
                pass

    def _handle(self, raw: bytes) -> None:
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            return  # noise on the line: the controller ignores it
        self.received.append(line)
        m = _LINE.match(line)
        if m is None:
            return
        addr, cmd, arg = int(m.group(1)), m.group(2).upper(), m.group(3).strip()
        if addr != self.address:
            return  # another controller on the chain would answer
        fault = self.faults.take(cmd)
        if fault is not None and fault.kind in ("close", "unplug"):
            self._disconnect(replug=fault.kind == "close")
            return
        if fault is not None and fault.kind == "error":
            if cmd != "TE":
                with self._lock:
                    self._error = str(fault.code)
                return
            fault = None
        with self._lock:
            self._execute(cmd, arg, fault)

    def _disconnect(self, *, replug: bool) -> None:
        with self._lock:
            old = (self._master, self._slave)
            if replug:
                self._open_pty()  # the new port exists (and stable_port points at it) before the old one dies
            else:
                self._master = self._slave = None
            for fd in old:
                try:
                    os.close(fd)
                except OSError:
                    pass

    def _execute(self, cmd: str, arg: str, fault) -> None:
        a = self.address
        query = arg == "?"
        if cmd in _GET_ALWAYS and arg not in ("", "?"):
            self._error = "A"
            return
        pos = self._advance()
        if cmd == "TE":
            err, self._error = self._error, "@"
            self._send(f"{a}TE{err}", fault)
        elif cmd == "TP":
            self._send(f"{a}TP{pos:.6f}", fault)
        elif cmd == "TS":
            self._send(f"{a}TS0000{self._state}", fault)
        elif cmd == "ID" and query:
            self._send(f"{a}ID{self.stage_id}", fault)
        elif cmd == "VA" and query:
            self._send(f"{a}VA{self.velocity_deg_per_s:g}", fault)
        elif cmd == "SL" and query:
            self._send(f"{a}SL{self.travel_deg[0]:g}", fault)
        elif cmd == "SR" and query:
            self._send(f"{a}SR{self.travel_deg[1]:g}", fault)
        elif cmd == "OR" and not arg:
            if self._state == "1E":
                self._error = "E"
            elif self._state.startswith("0") or self._state in ("10", "11"):
                self._start_motion(0.0, "1E", self.min_home_s)
            else:
                self._error = {"28": "M", "3C": "J"}.get(self._state, "K")
        elif cmd == "PA" and not query:
            try:
                target = float(arg)
            except ValueError:
                self._error = "C"
                return
            lo, hi = self.travel_deg
            if self._state in _READY_STATES or self._state == "28":
                if not lo <= target <= hi:
                    self._error = "C"
                else:
                    self._after_motion = "33"
                    self._start_motion(target, "28")
            else:
                self._error = {"1E": "L", "3C": "J", "14": "I"}.get(self._state, "H")
        elif cmd == "ST" and not arg:
            if self._state == "28":
                self._from_deg = self._to_deg = pos
                self._t0 = self._t1 = time.monotonic()
                self._state = "33"
            elif self._state == "1E":
                self._from_deg = self._to_deg = pos
                self._t0 = self._t1 = time.monotonic()
                self._state = "0B"
            self._publish(pos)
        else:
            self._error = "A"
