"""Simulated SMC100-style scan-mirror controller on a pseudo-terminal.

The simulator owns the master side of a pty pair (``os.openpty``) and serves
the SMC100 ASCII protocol on it from a thread; a driver opens the slave side's
``/dev/pts/N`` path exactly as it would open ``/dev/ttyUSB0``.  A stable
symbolic link to the current slave (``stable_port``, like a udev
``/dev/serial/by-id`` link) survives a simulated re-plug.

Behaviour follows the Newport SMC100CC/PP User's Manual (EDH0206En), section
6.3 "Command syntax" and section 6.5 "Command set":

* syntax (6.3): ``{address}{command}{value}``, upper or lower case, blanks
  allowed and ignored anywhere (``2P A1.43 6`` is ``2PA1.436``); the line ends
  at CR LF (CR or LF alone is accepted too).  A line for another address is
  ignored; ``ST`` without an address stops every controller on the line, so
  this one too; any other command without an address is ignored;
* states (``TS``): power-up NOT REFERENCED (``0A``); ``OR`` is HOMING
  (``1E``) for a time proportional to the distance to 0, then READY from
  HOMING (``32``); a move is MOVING (``28``) for ``distance / velocity``
  seconds of wall-clock time, then READY from MOVING (``33``); ``MM0`` enters
  DISABLE (``3C`` from READY, ``3D`` from MOVING, stopping there), ``MM1``
  leaves it (READY from DISABLE, ``34``); ``RS`` resets the controller to
  NOT REFERENCED from reset (``0A``) where the stage is, with the power-up
  velocity and acceleration;
* moves: ``PA`` absolute, ``PR`` relative to the current target; a target
  outside the software travel limits (``SL``/``SR``) is refused with ``C``;
  moves are refused with the state's letter (``H`` not referenced, ``L``
  homing, ``J`` disabled, ``I`` configuration); ``ST`` stops where the stage
  is (``33``; ``0B`` during homing);
* queries: ``ID?``, ``PA?`` (target), ``TP`` (position), ``TH`` (set-point;
  the same as ``TP`` in this ideal motion model), ``TS``, ``TE`` (returns and
  clears the last error letter), ``VA?``, ``AC?``, ``SL?``, ``SR?``,
  ``HT?`` (home search type), ``VE`` (firmware text).  ``VA``/``AC`` can be
  set (refused with ``C`` unless > 0, with ``M``/``L`` while moving/homing);
  ``HT`` can only be set in CONFIGURATION, which this simulator does not
  enter, so setting it is refused with the state's letter.  Setting commands
  never answer; an unknown command sets ``A``.

Fault injection (one-shot, see :mod:`drivers.sim.faults`)::

    sim.inject("drop_reply", command="TP")   # next TP is executed, no answer
    sim.inject("delay", command="TS", delay_s=1.0)
    sim.inject("garbage")                    # next query answered with noise
    sim.inject("error", command="PA", code="V")  # next PA fails with TE = V
    sim.inject("close")                      # port vanishes, reappears at stable_port (re-plug)
    sim.inject("power_cycle")                # re-plug, and the controller restarts NOT REFERENCED
    sim.inject("unplug")                     # port vanishes until sim.replug()

The link folder (``/tmp/streaklab-mirror-*``) is marked with its owner's pid;
:meth:`MirrorSimulator.start` removes the folders of earlier simulators whose
process has gone (see :mod:`drivers.sim.linkdir`).
"""
from __future__ import annotations

import collections
import logging
import os
import re
import select
import threading
import time
import tty

from .faults import COMMON_KINDS, FaultInjector
from .linkdir import make_link_dir, remove_link_dir, remove_stale_link_dirs
from .state import LabState

log = logging.getLogger(__name__)

_LINE = re.compile(r"^(\d{0,2})([A-Za-z]{2})(.*)$")
_BLANKS = re.compile(r"[ \t]")
# manual syntax xxTE / xxTP / xxTS / xxTH / xxVE: "get" commands without a value (a "?" is tolerated)
_GET_ALWAYS = {"TE", "TP", "TS", "TH", "VE"}
_READY_STATES = {"32", "33", "34", "35"}
_DISABLE_STATES = {"3C", "3D", "3E"}
_NOT_REFERENCED = {"0A", "0B", "0C", "0D", "0E", "0F", "10", "11"}
_MAX_RATE = 1e12  # manual, VA/AC: upper end of the accepted range


def _state_letter(state: str) -> str:
    """The TE letter for "command not allowed in this state" (manual, TE command)."""
    if state in _NOT_REFERENCED:
        return "H"
    if state == "14":
        return "I"
    if state in _DISABLE_STATES:
        return "J"
    if state in _READY_STATES:
        return "K"
    if state in ("1E", "1F"):
        return "L"
    if state == "28":
        return "M"
    return "D"


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
    acceleration_deg_per_s2 : float
        Reported by ``AC?`` (stored, not used: the motion model is constant-velocity).
    firmware : str
        Text answered to ``VE``.
    home_type : int
        Answered to ``HT?`` (0..4, manual HT command).

    Use as a context manager, or call :meth:`start` and :meth:`close`.
    """

    def __init__(self, lab_state: LabState | None = None, *, address: int = 1,
                 velocity_deg_per_s: float = 100.0, travel_deg: tuple[float, float] = (-45.0, 45.0),
                 initial_angle_deg: float = 0.0, stage_id: str = "SLAB-GALVO-SIM",
                 min_home_s: float = 0.05, acceleration_deg_per_s2: float = 400.0,
                 firmware: str = "SMC100CC streaklab simulator 1.0", home_type: int = 0):
        if not 1 <= int(address) <= 31:
            raise ValueError(f"address must be 1..31, got {address!r}")
        if not velocity_deg_per_s > 0:
            raise ValueError(f"velocity_deg_per_s must be > 0, got {velocity_deg_per_s!r}")
        if not acceleration_deg_per_s2 > 0:
            raise ValueError(f"acceleration_deg_per_s2 must be > 0, got {acceleration_deg_per_s2!r}")
        if int(home_type) not in range(5):
            raise ValueError(f"home_type must be 0..4, got {home_type!r}")
        lo, hi = (float(v) for v in travel_deg)
        if not lo < hi:
            raise ValueError(f"travel_deg must be (low, high) with low < high, got {travel_deg!r}")
        self.lab_state = lab_state if lab_state is not None else LabState()
        self.address = int(address)
        self.velocity_deg_per_s = self._power_up_velocity = float(velocity_deg_per_s)
        self.acceleration_deg_per_s2 = self._power_up_acceleration = float(acceleration_deg_per_s2)
        self.travel_deg = (lo, hi)
        self.stage_id = stage_id
        self.firmware = str(firmware)
        self.home_type = int(home_type)
        self.min_home_s = float(min_home_s)
        self.faults = FaultInjector(COMMON_KINDS | {"unplug", "power_cycle"})
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
        for stale in remove_stale_link_dirs():
            log.info("removed the link folder %s left by an earlier run", stale)
        self._linkdir = make_link_dir()
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
        port = os.ttyname(slave)
        tmp = self.stable_port + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(port, tmp)
        os.replace(tmp, self.stable_port)
        # published last: whoever sees the new port finds stable_port already pointing at it (a
        # client reconnecting in between would open a link still pointing at the dead pty)
        self._master, self._slave = master, slave
        self.port = port

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
            remove_link_dir(self._linkdir)
            self._linkdir = None

    def replug(self) -> None:
        """Plug the port back in after an ``unplug`` fault: a new pty behind ``stable_port``."""
        with self._lock:
            if self._stop.is_set() or self._linkdir is None:
                raise RuntimeError("simulator is not running")
            if self._master is None:
                self._open_pty()

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
            self.lab_state.mirror_referenced = self._state not in _NOT_REFERENCED | {"14", "1E", "1F"}

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
                    try:
                        self._handle(line)
                    except Exception:  # noqa: BLE001 - one bad line must not end the controller
                        log.exception("mirror simulator: handling %r failed", line)
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
            line = raw.decode("ascii")
        except UnicodeDecodeError:
            return  # noise on the line: the controller ignores it
        line = _BLANKS.sub("", line)   # manual 6.3: blanks are allowed and ignored in any position
        self.received.append(line)
        m = _LINE.match(line)
        if m is None:
            return
        addr_text, cmd, arg = m.group(1), m.group(2).upper(), m.group(3)
        if not addr_text:
            if cmd != "ST":   # manual, ST: without an address it stops all controllers
                return
        elif int(addr_text) != self.address:
            return  # another controller on the chain would answer
        fault = self.faults.take(cmd)
        if fault is not None and fault.kind in ("close", "unplug", "power_cycle"):
            self._disconnect(replug=fault.kind != "unplug", reset=fault.kind == "power_cycle")
            return
        if fault is not None and fault.kind == "error":
            if cmd != "TE":
                with self._lock:
                    self._error = str(fault.code)
                return
            fault = None
        with self._lock:
            self._execute(cmd, arg, fault, addressed=bool(addr_text))

    def _disconnect(self, *, replug: bool, reset: bool = False) -> None:
        with self._lock:
            old = [fd for fd in (self._master, self._slave) if fd is not None]
            if replug:
                self._open_pty()  # the new port exists (and stable_port points at it) before the old one dies
            else:
                self._master = self._slave = None
            for fd in old:
                try:
                    os.close(fd)
                except OSError:
                    pass
            if reset:
                self._reset()

    def _reset(self) -> None:
        """Power-up state where the stage is: NOT REFERENCED from reset, power-up VA and AC."""
        pos = self._advance()
        self._error = "@"
        self.velocity_deg_per_s = self._power_up_velocity
        self.acceleration_deg_per_s2 = self._power_up_acceleration
        self._halt(pos, "0A")

    def _halt(self, pos: float, state: str) -> None:
        self._from_deg = self._to_deg = pos
        self._t0 = self._t1 = time.monotonic()
        self._state = state
        self._publish(pos)

    def _execute(self, cmd: str, arg: str, fault, addressed: bool = True) -> None:
        """Run one command (manual, section 6.5); replies start with the address and command."""
        a = self.address
        query = arg == "?"
        if not addressed and (cmd != "ST" or arg):
            return
        if cmd in _GET_ALWAYS and arg not in ("", "?"):
            self._error = "A"
            return
        pos = self._advance()
        state = self._state
        if cmd == "TE":
            err, self._error = self._error, "@"
            self._send(f"{a}TE{err}", fault)
        elif cmd == "TP":
            self._send(f"{a}TP{pos:.6f}", fault)
        elif cmd == "TH":
            self._send(f"{a}TH{pos:.6f}", fault)
        elif cmd == "TS":
            self._send(f"{a}TS0000{state}", fault)
        elif cmd == "VE":
            self._send(f"{a}VE {self.firmware}", fault)
        elif cmd == "ID" and query:
            self._send(f"{a}ID{self.stage_id}", fault)
        elif cmd == "PA" and query:
            self._send(f"{a}PA{self._to_deg:.6f}", fault)
        elif cmd == "VA" and query:
            self._send(f"{a}VA{self.velocity_deg_per_s:g}", fault)
        elif cmd == "AC" and query:
            self._send(f"{a}AC{self.acceleration_deg_per_s2:g}", fault)
        elif cmd == "SL" and query:
            self._send(f"{a}SL{self.travel_deg[0]:g}", fault)
        elif cmd == "SR" and query:
            self._send(f"{a}SR{self.travel_deg[1]:g}", fault)
        elif cmd == "HT" and query:
            self._send(f"{a}HT{self.home_type}", fault)
        elif cmd == "HT":
            self._error = _state_letter(state)   # settable in CONFIGURATION only
        elif cmd in ("VA", "AC"):
            self._set_rate(cmd, arg, state)
        elif cmd == "OR" and not arg:
            if state in ("1E", "1F"):
                self._error = "E"
            elif state in _NOT_REFERENCED:
                self._start_motion(0.0, "1E", self.min_home_s)
            else:
                self._error = _state_letter(state)
        elif cmd in ("PA", "PR"):
            self._move(cmd, arg, state)
        elif cmd == "MM" and arg in ("0", "1"):
            self._disable(arg == "0", pos, state)
        elif cmd == "MM":
            self._error = "C"
        elif cmd == "RS" and not arg:
            self._reset()
        elif cmd == "ST" and not arg:
            if state == "28":
                self._halt(pos, "33")
            elif state in ("1E", "1F"):
                self._halt(pos, "0B")
            self._publish(pos)
        else:
            self._error = "A"

    @staticmethod
    def _number(arg: str) -> float | None:
        try:
            value = float(arg)
        except ValueError:
            return None
        return value if value == value and abs(value) != float("inf") else None

    def _move(self, cmd: str, arg: str, state: str) -> None:
        value = self._number(arg)
        if value is None:
            self._error = "C"
            return
        if not (state in _READY_STATES or state == "28"):
            self._error = _state_letter(state)
            return
        target = value if cmd == "PA" else self._to_deg + value
        lo, hi = self.travel_deg
        if not lo <= target <= hi:
            self._error = "C"
            return
        self._after_motion = "33"
        self._start_motion(target, "28")

    def _set_rate(self, cmd: str, arg: str, state: str) -> None:
        value = self._number(arg)
        if value is None or not 1e-6 <= value <= _MAX_RATE:
            self._error = "C"
        elif state in ("28", "1E", "1F"):
            self._error = _state_letter(state)
        elif cmd == "VA":
            self.velocity_deg_per_s = value
        else:
            self.acceleration_deg_per_s2 = value

    def _disable(self, enter: bool, pos: float, state: str) -> None:
        if enter:
            if state in _READY_STATES:
                self._halt(pos, "3C")
            elif state == "28":
                self._halt(pos, "3D")         # DISABLE from MOVING: the stage stops where it is
            elif state in ("46", "47"):
                self._halt(pos, "3E")
            elif state not in _DISABLE_STATES:
                self._error = _state_letter(state)
        else:
            if state in _DISABLE_STATES:
                self._halt(pos, "34")         # READY from DISABLE
            elif state not in _READY_STATES:
                self._error = _state_letter(state)
