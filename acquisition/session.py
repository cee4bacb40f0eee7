"""The capture session: check the rig, take darks, then scan line by line into a run store.

The session drives the devices only through the :mod:`drivers.interfaces`
protocols, so the same code runs on the real rig and on ``drivers.sim``::

    check    identify camera, mirror and laser sync; configure them (the streak unit in
             Operate mode, sweeping); home the mirror
    dark     sync output off, ``dark.frames`` frames at the home position (skipped if on disk);
             a new run also records the camera's own sweep calibration (its scaling table)
             where the camera offers one
    lines    sync output on; for every line not yet done: move the mirror, wait until it
             settles, take ``frames_per_line`` frames, check the sync's error queue, write
             the frames durably, mark the line done; with ``sync.reference`` the sync unit's
             trigger-interval buffer is emptied before the frames and read after them: one
             measured interval per frame, written with the frames
    finally  sync output off and the camera's MCP gain 0 (the drivers' context managers do the rest)

The gain interlock: the camera's MCP gain is set to 0 when the session ends (complete,
stopped, failed, Ctrl-C) and after every device fault (the operating gain is set again
before the next frames); the streak unit is put in Operate mode before the gain is raised.

A device fault (:class:`~drivers.errors.DeviceTimeout`, ``ConnectionLost``,
``DeviceError``, ``ProtocolError``) during a step is retried ``session.retries``
times (the line restarts from the mirror move), waiting ``retry_backoff_s * 2**k``
before retry k, at most ``limits.MAX_BACKOFF_WAIT_S`` each and
``limits.MAX_BACKOFF_TOTAL_S`` in all; after that the session stops with
:class:`CaptureFailed`, every finished line intact and resumable.  A device that
answers a configured setting with an error rejects it: that is not retried, the
session stops at once with :class:`SettingRejected` naming the config key.  A stop request
(Ctrl-C, see :func:`capture`) ends the session after the current line; a
KeyboardInterrupt (a second Ctrl-C) gives up the current line at once.  Either way the
session's entry in the store's ``sessions`` attribute gets its end time and status
(``interrupted``, ``aborted``); the finished lines stay on disk and resumable.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from core.errors import StreaklabError
from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, DriverError, ProtocolError

from core import limits as L

from .config import ConfigError, ScanConfig, check_calibration, check_row_times
from .runstore import (RunStore, RunStoreError, config_differences, create_run, describe_absent,
                       is_uninitialised_run, open_run, remove_uninitialised_run)

__all__ = ["CaptureError", "CaptureFailed", "SettingRejected", "TriggerCountMismatch", "check_trigger_count",
           "SessionResult", "CaptureSession", "RETRYABLE"]

log = logging.getLogger(__name__)


class CaptureError(StreaklabError, RuntimeError):
    """The session cannot start or continue (bad store, device check failed, config mismatch)."""


class CaptureFailed(CaptureError):
    """A device kept failing after the retries; the finished lines are on disk and resumable."""

    def __init__(self, message: str, *, cause: BaseException, lines_done: int, n_lines: int,
                 store_created: bool = True, remedy: str = "fix the device"):
        super().__init__(message)
        self.remedy = remedy        # what to do before resuming
        self.cause = cause
        self.lines_done = lines_done
        self.n_lines = n_lines
        self.store_created = store_created  # False: it failed before the run store existed


class TriggerCountMismatch(DriverError):
    """The laser sync measured another number of trigger intervals than the line took frames
    (a missed or extra trigger): the line is taken again, as after any device fault
    (:data:`RETRYABLE`)."""


#: the device faults after which a line is taken again
RETRYABLE = (DeviceTimeout, ConnectionLost, DeviceError, ProtocolError, TriggerCountMismatch)


def check_trigger_count(line: int, measured, n_frames: int) -> list[float]:
    """``measured`` (the trigger intervals read after line ``line``'s frames) when it holds one per
    frame, else :class:`TriggerCountMismatch` naming the line and the first frame without its own."""
    measured = list(measured)
    m = len(measured)
    if m < n_frames:
        raise TriggerCountMismatch(f"line {line} frame {m}: no trigger interval measured (the laser sync "
                                   f"measured {m} for the line's {n_frames} frames)")
    if m > n_frames:
        raise TriggerCountMismatch(f"line {line} frame {n_frames - 1}: the laser sync measured {m} trigger "
                                   f"intervals for the line's {n_frames} frames (more triggers than frames)")
    return measured


class SettingRejected(CaptureError):
    """A device refused a configured setting: retrying cannot help; nothing has been acquired."""

    def __init__(self, key: str, value, device: str, cause: DeviceError):
        super().__init__(f"{key} = {value!r}: the {device} rejects this setting ({cause}); "
                         f"nothing was acquired; change {key} in the configuration")
        self.key = key
        self.cause = cause


@dataclass
class SessionResult:
    """How a session ended.

    Attributes
    ----------
    status : "complete" or "interrupted"
    lines_done, n_lines : int
        Lines on disk (all sessions together) and lines in the scan.
    acquired : list of int
        Lines taken by this session, in order.
    devices : dict
        Device identities.
    """

    status: str
    lines_done: int
    n_lines: int
    acquired: list = field(default_factory=list)
    devices: dict = field(default_factory=dict)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@contextlib.contextmanager
def _ctrl_c_held():
    """Hold Ctrl-C (SIGINT) while the block runs and hand it on afterwards.

    A store's attributes are rewritten as a whole; held, a further Ctrl-C cannot cut that
    write in half.  Only the main thread can handle signals: elsewhere nothing is held.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
        if held and callable(previous):
            previous(signal.SIGINT, None)


class CaptureSession:
    """One capture session over three connected drivers.

    Parameters
    ----------
    config : ScanConfig
    out : path of the run store.
    camera, mirror, sync : StreakCamera, ScanMirror, LaserSync
        Open drivers (the caller owns them and closes them, normally with ``with``).
    resume : bool
        Continue an existing run store (its config hash must match).  Without it an
        existing non-empty ``out`` is an error.
    stop_event : threading.Event, optional
        Set it to stop after the current line.
    on_line : callable(session, line_index), optional
        Called after each line is on disk (progress display, tests).
    on_start : callable(session), optional
        Called once the devices are checked and the store is open, before the first line.
    sleep : callable(seconds)
        Used for the retry back-off.
    session_info : dict, optional
        Extra fields for this session's entry in the store's ``sessions`` attribute.
    line_good_enough : callable(line, frames) -> bool, optional
        Adaptive accumulation: frames are taken one at a time and, from the second on, the
        line's frames so far (frame, x, t) uint16 are passed to it; the line stops when it
        answers True, or at ``camera.frames_per_line`` frames (the maximum).  The store then
        records each line's ``frames_taken`` and ``target_reached``.  None: every line takes
        ``camera.frames_per_line`` frames.
    """

    def __init__(self, config: ScanConfig, out, camera, mirror, sync, *, resume: bool = False,
                 stop_event: threading.Event | None = None,
                 on_line: Callable[["CaptureSession", int], None] | None = None,
                 on_start: Callable[["CaptureSession"], None] | None = None,
                 sleep: Callable[[float], None] = time.sleep, session_info: dict | None = None,
                 line_good_enough: Callable[[int, np.ndarray], bool] | None = None):
        self.config = config
        self.out = Path(out)
        self.camera, self.mirror, self.sync = camera, mirror, sync
        self.resume = bool(resume)
        self.stop_event = stop_event or threading.Event()
        self.on_line = on_line
        self.on_start = on_start
        self.sleep = sleep
        self.session_info = dict(session_info or {})
        self.line_good_enough = line_good_enough
        self.store: RunStore | None = None
        self.devices: dict = {}
        self.acquired: list[int] = []
        self.retries_used = 0
        self._entry: int | None = None          # index of this session's entry in ``sessions``
        self.operating_gain: int | None = None  # the MCP gain the frames are taken at (None: not controlled)
        self._gain_is_off = False               # the gain interlock set it to 0 since it was last set
        s = config["session"]
        self.retries = int(s["retries"])
        self.backoff_s = float(s["retry_backoff_s"])

    # ------------------------------------------------------------------ helpers
    @property
    def n_lines(self) -> int:
        return self.config.n_lines

    def lines_done(self) -> int:
        return 0 if self.store is None else int(self.store.done_mask().sum())

    def _attempt(self, what: str, fn):
        """Run ``fn()``; on a device fault retry up to ``retries`` times, then raise CaptureFailed.

        The waits between attempts are :func:`core.limits.backoff_waits` (each capped), and
        all of them together stop at ``limits.MAX_BACKOFF_TOTAL_S``.
        """
        waits = L.backoff_waits(self.retries, self.backoff_s)
        waited = 0.0
        for attempt in range(self.retries + 1):
            try:
                return fn()
            except RETRYABLE as exc:
                if attempt >= self.retries:
                    done = self.lines_done()
                    raise CaptureFailed(
                        f"{what} failed after {attempt + 1} attempts: {type(exc).__name__}: {exc}",
                        cause=exc, lines_done=done, n_lines=self.n_lines,
                        store_created=self.store is not None) from exc
                self.retries_used += 1
                log.warning("%s: %s: %s (attempt %d of %d; retrying)", what, type(exc).__name__, exc,
                            attempt + 1, self.retries + 1)
                self._recover()
                wait = min(waits[attempt], L.MAX_BACKOFF_TOTAL_S - waited)
                if wait > 0:
                    self.sleep(wait)
                    waited += wait

    def _setting(self, key: str, value, device: str, fn) -> None:
        """Apply one configured setting: faults are retried, a device error (a rejection) is not."""
        def apply():
            try:
                fn()
            except DeviceError as exc:
                raise SettingRejected(key, value, device, exc) from None

        self._attempt(f"{device} setting {key}", apply)

    def _recover(self) -> None:
        """Best effort after a fault: stop any acquisition still running on the camera, and
        home the mirror again if it lost its reference (a power cycle, a reset, a re-plug)."""
        try:
            self.camera.stop()
        except DriverError as exc:
            log.info("camera stop after a fault failed too: %s", exc)
        self.gain_off("after a fault")
        try:
            state = self.mirror.state()
            if state in ("not_referenced", "disabled"):
                log.warning("mirror is %s after the fault; homing it again", state.replace("_", " "))
                self.mirror.home(timeout_s=max(30.0, self.config["scan"]["settle_timeout_s"]))
        except DriverError as exc:
            log.info("mirror check after a fault failed too: %s", exc)

    # ------------------------------------------------------------------ steps
    def check_devices(self) -> dict:
        """Identify, configure and home every device; returns their identities."""
        cfg = self.config
        ids = {}
        for name, dev in (("camera", self.camera), ("mirror", self.mirror), ("sync", self.sync)):
            ids[name] = str(self._attempt(f"{name} check (identify)", dev.identify))

        def reset_sync():
            self.sync.set_output(False)
            self.sync.read_errors()                                       # clear stale errors

        def sync_setting(fn):
            def apply():
                fn()
                errors = self.sync.read_errors()
                if errors:
                    raise DeviceError(errors[0][0], errors[0][1], device="laser sync")
            return apply

        sync = cfg["sync"]
        self._attempt("laser-sync setup", reset_sync)
        self._setting("sync.repetition_rate_hz", sync["repetition_rate_hz"], "laser sync",
                      sync_setting(lambda: self.sync.set_repetition_rate(sync["repetition_rate_hz"])))
        self._setting("sync.trigger_delay_ps", sync["trigger_delay_ps"], "laser sync",
                      sync_setting(lambda: self.sync.set_trigger_delay(sync["trigger_delay_ps"],
                                                                       channel=sync["channel"])))
        if sync.get("reference"):
            def probe_reference():
                # a unit without the time-interval counter leaves the query unanswered and says
                # why in its error queue (-113, undefined header): refused here, not after a line
                try:
                    self.sync.fetch_trigger_intervals()           # also forgets triggers so far
                except DeviceTimeout:
                    errors = self.sync.read_errors()
                    if errors:
                        raise DeviceError(errors[0][0], errors[0][1], command=":TINT:FETC?",
                                          device="laser sync") from None
                    raise
            self._setting("sync.reference", True, "laser sync", probe_reference)
        cam = cfg["camera"]
        for key in ("time_range", "exposure_s"):
            if cam.get(key) is not None:
                self._setting(f"camera.{key}", cam[key], "camera",
                              lambda key=key: self.camera.configure(**{key: cam[key]}))
        operate = getattr(self.camera, "operate", None)
        if operate is not None:
            # the sweep on before the gain is raised (RemoteExCamera.operate)
            self._attempt("camera streak mode", operate)
        if cam.get("gain") is not None:
            self._setting("camera.gain", cam["gain"], "camera", lambda: self.camera.configure(gain=cam["gain"]))
        self.operating_gain = cam.get("gain")
        read_gain = getattr(self.camera, "gain", None)
        if self.operating_gain is None and callable(read_gain):
            def read():
                try:
                    return read_gain()
                except DeviceError as exc:
                    if exc.code != 2:        # 2: no MCP gain control on this unit: nothing to guard
                        raise
                    return None

            gain = self._attempt("camera gain read-back", read)
            if gain == 0:
                raise CaptureError("camera.gain: not set, and the camera's MCP gain is 0 (the gain interlock "
                                   "sets it to 0 after every acquisition); set camera.gain in the config")
            self.operating_gain = gain
        self._gain_is_off = False
        self._attempt("mirror homing", lambda: self.mirror.home(timeout_s=max(30.0, cfg["scan"]["settle_timeout_s"])))
        self.devices = ids
        return ids

    def _acquire_frames(self, n: int, what: str, key: str, also=()) -> np.ndarray:
        """``n`` frames (frame, x, t) uint16; ``key`` is the config key that asks for ``n``.

        The first frame tells the image size: the memory for all ``n`` (and for each ``(count,
        key)`` of ``also``) is checked against ``limits.MAX_LINE_BYTES`` and the available
        memory before the second is taken.
        """
        timeout_s = self.config["camera"]["acquire_timeout_s"]
        if self._gain_is_off and self.operating_gain is not None:
            self.camera.configure(gain=int(self.operating_gain))     # back from the interlock after a fault
            self._gain_is_off = False
        frames = []
        for i in range(n):
            img = self.camera.acquire(timeout_s=timeout_s)
            data = np.asarray(img.data)
            if data.ndim != 2 or data.dtype != np.uint16:
                raise ProtocolError(f"{what}: camera returned a {data.dtype} image of shape {data.shape}, "
                                    f"expected uint16 (x, t)")
            if frames and data.shape != frames[0].shape:
                raise ProtocolError(f"{what}: image shape changed from {frames[0].shape} to {data.shape}")
            if i == 0:
                for count, k in ((n, key), *also):
                    self._check_frame_memory(count, data, k)
            frames.append(data)
        return np.stack(frames) if frames else np.zeros((0, 0, 0), np.uint16)

    def _check_frame_memory(self, n: int, image: np.ndarray, key: str) -> None:
        pixels = int(image.size)
        if pixels > L.MAX_IMAGE_PIXELS:
            raise CaptureError(f"the camera delivers {image.shape[0]} x {image.shape[1]} images ({pixels} pixels), "
                               f"above the limit of {L.MAX_IMAGE_PIXELS} pixels (limits.MAX_IMAGE_PIXELS)")
        try:
            # the frames and their stacked copy
            L.check_memory(key, 2 * n * image.nbytes, L.MAX_LINE_BYTES,
                           what=f"for {n} frames of {image.shape[0]} x {image.shape[1]} pixels "
                                f"(limits.MAX_LINE_BYTES)")
        except L.LimitError as exc:
            raise CaptureError(f"{exc}; take fewer frames") from None

    def _take_dark(self) -> tuple[np.ndarray, tuple[int, int]]:
        """Dark frames (sync output off), shape (dark_frame, x, t), and the image shape (x, t).

        At least one frame is taken, to learn the image shape, even with ``dark.frames = 0``.
        """
        n = max(1, int(self.config["dark"]["frames"]))

        def take():
            self.sync.set_output(False)
            # the lines' frames must fit too: checked as soon as the first frame gives the image size
            return self._acquire_frames(n, "dark frames", "dark.frames",
                                        also=[(int(self.config["camera"]["frames_per_line"]),
                                               "camera.frames_per_line")])

        frames = self._attempt("dark frames", take)
        return frames[: int(self.config["dark"]["frames"])], tuple(frames.shape[1:])

    def open_store(self) -> None:
        """Open (resume) or create the run store; create takes the dark frames first to learn the image shape."""
        out = self.out
        exists = out.exists() and (out.is_file() or any(out.iterdir()))
        if exists and not self.resume:
            raise CaptureError(f"{out} already exists; pass --resume to continue that run, or choose another --out")
        if exists and is_uninitialised_run(out):
            log.info("%s: creation was interrupted before any line; starting it again", out)
            remove_uninitialised_run(out)
            exists = False
        if exists:
            try:
                store = open_run(out, mode="r+")
            except RunStoreError as exc:
                raise CaptureError(f"cannot resume: {exc}") from None
            if store.config_hash != self.config.hash:
                diffs = config_differences(store.config.hashed_part(), self.config.hashed_part())
                raise CaptureError(
                    f"cannot resume {out}: it was captured with a different configuration "
                    f"({'; '.join(diffs) or 'hash differs'}). Resume with the original configuration, "
                    f"or start a new run with another --out")
            absent = store.absent_chunks()
            if absent:
                raise CaptureError(f"cannot resume: {describe_absent(store, absent)}")
            self.store = store
            if not store.dark_done():
                dark, shape = self._take_dark()
                self._check_shape(shape)
                store.write_dark(dark)
            return
        dark, shape = self._take_dark()
        table = self._camera_row_times(shape[1])
        self._check_shape(shape, camera_table=table is not None)
        info = {"source": "ImgDataGet(Current,ScalingTable,Vertical)",
                "time_range": str(self.config["camera"]["time_range"])}
        store = create_run(out, self.config, image_shape=shape, devices=self.devices, camera_row_times_ps=table,
                           camera_time_info=info)
        store.write_dark(dark)
        self.store = store

    def _camera_row_times(self, n_rows: int):
        """The camera's scaling table for the current image (ps, one per row), or None if it has none."""
        reader = getattr(self.camera, "scaling_table_ps", None)
        if reader is None:
            return None
        table = self._attempt("camera scaling table", reader)
        if table is None:
            if self.config["calibration"].get("time_source") == "camera":
                raise CaptureError("calibration.time_source = \"camera\", but the camera offers no scaling table "
                                   "for this time range; set time_source = \"config\" and give time_poly_ps")
            return None
        try:
            return check_row_times(table, n_rows, key="the camera's scaling table")
        except ConfigError as exc:
            raise CaptureError(str(exc)) from None

    def _check_shape(self, shape, *, camera_table: bool = False) -> None:
        if self.store is not None and tuple(self.store.image_shape) != tuple(shape):
            raise CaptureError(f"the camera delivers {shape} images but the run store holds "
                               f"{self.store.image_shape}; was the camera binning changed?")
        if "time_poly_ps" not in self.config["calibration"]:
            if not camera_table and (self.store is None or self.store.camera_row_times_ps() is None):
                raise CaptureError("calibration.time_poly_ps is not given and the camera has no scaling table")
            return
        try:
            t = check_calibration(self.config["calibration"]["time_poly_ps"], shape[1])
        except ConfigError as exc:
            raise CaptureError(f"{exc} (the camera has {shape[1]} streak rows)") from None
        # the cube's time grid must stay within the limit too: refuse now, not after the scan
        tb = float(self.config["calibration"]["time_bin_ps"])
        refused = L.time_bin_message(tb, float(np.ptp(t)), float(np.ptp(t)) / tb + 1)
        if refused:
            raise CaptureError(f"{refused} (the camera has {shape[1]} streak rows)")

    def take_line(self, line: int) -> None:
        """Acquire scan line ``line`` into the store: move, settle, frames, sync check, durable write.

        A device fault restarts the line from the mirror move (see :meth:`_attempt`); the
        one home of the line logic, for :meth:`run` and for ``streaklab.bluesky``.
        """
        angle = float(self.config.angles_deg[line])
        settle_s = self.config["scan"]["settle_timeout_s"]
        n = self.config["camera"]["frames_per_line"]

        reference = bool(self.config["sync"].get("reference"))

        def acquire():
            self.mirror.move_to(angle)
            reached = float(self.mirror.wait_settled(timeout_s=settle_s))
            if reference:
                self.sync.fetch_trigger_intervals()      # forget triggers before this line's frames
            if self.line_good_enough is None:
                frames, taken, good = self._acquire_frames(n, f"line {line}", "camera.frames_per_line"), None, None
            else:
                frames, taken, good = self._accumulate(line, n)
            intervals = check_trigger_count(line, self.sync.fetch_trigger_intervals(),
                                            n if taken is None else taken) if reference else None
            if frames.shape[1:] != self.store.image_shape:
                raise CaptureError(f"line {line}: the camera delivers {frames.shape[1:]} images, the run store "
                                   f"holds {self.store.image_shape}")
            # A laser-sync error while the frames were taken (lost lock, trigger fault) spoils the line.
            errors = self.sync.read_errors()
            if errors:
                raise DeviceError(errors[0][0], errors[0][1], command=f"line {line}", device="laser sync")
            return reached, frames, taken, good, intervals

        reached, frames, taken, good, intervals = self._attempt(f"line {line} (mirror {angle:g} deg)", acquire)
        try:
            self.store.write_line(line, frames, angle_deg=reached, timestamp=time.time(),
                                  frames_taken=taken, target_reached=good, trigger_interval_ps=intervals)
        except OSError as exc:  # a full or read-only disk: the lines before this one are safe
            full = exc.errno == errno.ENOSPC
            raise CaptureFailed(f"line {line}: cannot write it to {self.out}: "
                                f"{'no space left on the device' if full else exc.strerror or exc}",
                                cause=exc, lines_done=self.lines_done(), n_lines=self.n_lines,
                                remedy="free space on that disk" if full else "make the run store writable") from None
        self.acquired.append(line)

    def _accumulate(self, line: int, n: int) -> tuple[np.ndarray, int, bool]:
        """Adaptive accumulation of one line: frames one at a time until :attr:`line_good_enough`
        says yes (asked from the second frame on, or after the only one when ``n`` is 1) or ``n``
        frames are taken -> (frames (n, x, t) uint16, the unused slots zero; frames taken;
        whether the target was reached)."""
        frames: list[np.ndarray] = []
        good = False
        while len(frames) < n:
            frames.append(self._acquire_frames(1, f"line {line}", "camera.frames_per_line")[0])
            if len(frames) >= min(2, n):
                good = bool(self.line_good_enough(line, np.stack(frames)))
                if good:
                    break
        taken = len(frames)
        out = np.zeros((n,) + frames[0].shape, np.uint16)
        out[:taken] = frames
        return out, taken, good

    # ------------------------------------------------------------------ run
    def run(self) -> SessionResult:
        """Run the session to completion, a stop request, or a failure.

        Returns
        -------
        SessionResult (status ``complete`` or ``interrupted``).

        Raises
        ------
        KeyboardInterrupt
            Passed on after the session's entry is closed with status ``aborted``.
        CaptureFailed
            A device kept failing; the finished lines are on disk.
        CaptureError
            The session could not start (store, config mismatch, calibration).
        """
        try:
            ids = self.begin()
            status = "interrupted"
            todo = self.lines_todo()
            if todo and not self.stop_event.is_set():
                self.output_on()
                for line in todo:
                    if self.stop_event.is_set():
                        break
                    self.take_line(line)
                    if self.on_line is not None:
                        self.on_line(self, line)
            if self.store.done_mask().all():
                status = "complete"
            self.end(status)
            return SessionResult(status, self.lines_done(), self.n_lines, list(self.acquired), dict(ids))
        except CaptureFailed as exc:
            self.end("failed", error=str(exc))
            raise
        except KeyboardInterrupt:               # the current line is given up; the finished ones are on disk
            self.end("aborted")
            raise
        except OSError as exc:  # creating the run store: read-only, full, a file where a folder should be
            reason = "a file stands where a folder should be" if exc.errno == errno.ENOTDIR else \
                "no space left on the device" if exc.errno == errno.ENOSPC else exc.strerror or str(exc)
            raise CaptureError(f"cannot write the run store {self.out}: {reason}") from None
        finally:
            self.make_safe()

    def begin(self) -> dict:
        """Check and configure the devices, open (or create) the store, open this session's entry.

        The steps before the first line, shared by :meth:`run` and by other drivers of the
        line loop (``streaklab.bluesky``); returns the device identities.
        """
        if self.config["sync"].get("reference") and not callable(getattr(self.sync, "fetch_trigger_intervals",
                                                                         None)):
            raise CaptureError("sync.reference = true, but this laser-sync driver measures no trigger intervals "
                               "(fetch_trigger_intervals); set sync.reference = false")
        ids = self.check_devices()
        self.open_store()
        if self.line_good_enough is not None:
            with _ctrl_c_held():
                self.store.add_adaptive_arrays()
        entry = {"started_utc": _utc_now(), "resumed": self.resume, "devices": ids,
                 "lines_done_at_start": self.lines_done(), **self.session_info}
        with _ctrl_c_held():
            self.store.add_session(entry)
            self._entry = len(self.store.group.attrs.get("sessions", [])) - 1
        if self.on_start is not None:
            self.on_start(self)
        return ids

    def lines_todo(self) -> list[int]:
        """Indices of the lines not yet on disk, in scan order."""
        return [int(i) for i in np.flatnonzero(~self.store.done_mask())]

    def line_done(self, line: int) -> bool:
        """True once ``line`` is on disk (its ``done`` flag is set)."""
        return bool(self.store.done_mask()[line])

    def output_on(self) -> None:
        """Laser-sync output on, before the first line (retried like every device step)."""
        self._attempt("laser-sync output on", lambda: self.sync.set_output(True))

    def end(self, status: str, error: str | None = None) -> None:
        """Close this session's entry in ``sessions``: end time, status, lines and retries (once)."""
        if self.store is None or self._entry is None:
            return
        try:
            with _ctrl_c_held():
                sessions = list(self.store.group.attrs.get("sessions", []))
                if self._entry < len(sessions):
                    sessions[self._entry] = {**sessions[self._entry], "ended_utc": _utc_now(), "status": status,
                                             "lines_acquired": len(self.acquired),
                                             "retries_used": self.retries_used, **({"error": error} if error else {})}
                    self.store.set_sessions(sessions)
                self._entry = None
        except Exception as exc:  # bookkeeping must never mask the session's outcome
            log.warning("could not record the session's end in %s: %s", self.out, exc)

    def make_safe(self) -> None:
        """Laser-sync output off and MCP gain 0 (best effort; the drivers' context managers also do it).

        Runs when the session ends however it ends: complete, stopped, failed, Ctrl-C.
        """
        try:
            self.sync.set_output(False)
        except DriverError as exc:
            log.warning("could not switch the laser-sync output off: %s", exc)
        self.gain_off("at the end of the acquisition")

    def gain_off(self, when: str) -> None:
        """The gain interlock: MCP gain 0 (best effort, logged when it fails).

        Cameras without the call (test doubles, units without MCP gain control) are left alone.
        """
        off = getattr(self.camera, "gain_off", None)
        if off is None:
            return
        try:
            off()
            self._gain_is_off = True
        except DriverError as exc:
            log.warning("could not set the camera's MCP gain to 0 %s: %s", when, exc)
