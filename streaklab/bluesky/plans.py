"""The Bluesky plan of a streaklab scan: the same scan as ``streaklab capture``, run by a RunEngine.

:func:`scan` opens the rig of a capture configuration (or a simulated lab started in this
process), wraps the drivers in the ophyd-async devices of :mod:`.devices`, and takes every
line not yet on disk: per line a checkpoint, the mirror move, and one trigger of the streak
camera, which writes the line's frames into the run store through the capture session's
own line step.  The run store is the one ``streaklab capture`` writes, byte for byte but
the timestamps; the documents are one start, one ``primary`` descriptor, one event per line
taken (readings: line, mirror angle reached, mean counts) and one stop.

Pause, resume and abort: a checkpoint opens every line, so a deferred pause (one Ctrl-C)
stops between lines; an immediate pause that cuts a line short lets that line's driver
call finish on the driver thread, and the replay after resume finds it on disk and emits
its event once.  An aborted scan leaves its finished lines in the store; ``scan(...,
resume=True)`` takes only the missing ones.
"""
from __future__ import annotations

import contextlib
from pathlib import Path

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
from bluesky.utils import FailedStatus, RequestAbort, RequestStop
from ophyd_async.plan_stubs import ensure_connected

from acquisition.config import ScanConfig, load_config
from acquisition.rig import open_rig, start_simulated_lab
from acquisition.session import CaptureFailed, CaptureSession
from core.errors import StreaklabError
from core.staging import check_output_location

from .devices import DriverThread, LaserSyncDevice, ScanMirrorMotor, StreakCameraDetector

__all__ = ["scan"]

#: how long opening the rig (simulated lab, three drivers) may take before the plan gives up
OPEN_TIMEOUT_S = 60.0


class _Rig:
    """The open drivers of one scan and its capture session; opened and closed on the driver thread."""

    def __init__(self, config: ScanConfig, out: Path, *, simulate: bool, resume: bool):
        self.config, self.out, self.simulate, self.resume = config, out, simulate, resume
        self.stack = contextlib.ExitStack()
        self.session: CaptureSession | None = None

    def open(self) -> None:
        lab = None
        if self.simulate:
            lab = start_simulated_lab(self.config)
            self.stack.callback(lab.close)
        camera, mirror, sync = self.stack.enter_context(open_rig(self.config, lab=lab))
        self.session = CaptureSession(self.config, self.out, camera, mirror, sync, resume=self.resume,
                                      session_info={"simulated": self.simulate, "client": "bluesky"})

    def close(self) -> None:
        self.stack.close()


def _devices(rig: _Rig, thread: DriverThread):
    cfg, session = rig.config, rig.session
    cam = cfg["camera"]
    camera = StreakCameraDetector(session.camera, thread, session=session, time_range=str(cam["time_range"]),
                                  exposure_s=cam["exposure_s"], gain=cam.get("gain") or 0,
                                  frames_per_line=cam["frames_per_line"], run_store=str(rig.out),
                                  name="streak_camera")
    mirror = ScanMirrorMotor(session.mirror, thread, settle_timeout_s=cfg["scan"]["settle_timeout_s"],
                             name="scan_mirror")
    sync = LaserSyncDevice(session.sync, thread, repetition_rate_hz=cfg["sync"]["repetition_rate_hz"],
                           trigger_delay_ps=cfg["sync"]["trigger_delay_ps"], channel=cfg["sync"]["channel"],
                           name="laser_sync")
    return camera, mirror, sync


def scan(*, config, out=None, simulate: bool = False, resume: bool = False, md: dict | None = None):
    """Plan: the capture of ``config`` into the run store ``out``, line by line.

    Parameters
    ----------
    config : path of the scan configuration (TOML), ``"sim"`` for the packaged example, or a
        :class:`~acquisition.config.ScanConfig`.
    out : path of the run store to write (default: ``output.path`` of the config).
    simulate : bool
        Start a simulated lab in this process and capture from it through the real drivers.
    resume : bool
        Continue an existing run store (its configuration must match): only the lines not on
        disk are taken.  Without it an existing non-empty ``out`` is an error.
    md : dict, optional
        Extra metadata for the start document.

    Yields
    ------
    Msg : the plan's messages, for a ``bluesky.RunEngine``.

    Raises
    ------
    acquisition.config.ConfigError, acquisition.session.CaptureError, core.staging.OutputPathError
        Bad configuration, a store that cannot be used, a device check or setting that fails,
        a device that keeps failing (:class:`~acquisition.session.CaptureFailed`: the
        finished lines are on disk).
    """
    cfg = config if isinstance(config, ScanConfig) else load_config(config)
    out = out if out is not None else cfg["output"].get("path")
    if not out:
        from acquisition.session import CaptureError
        raise CaptureError("no output: pass out= or set output.path in the config")
    out = Path(out)
    check_output_location(out)          # before any device is opened: never inside another store
    return (yield from _scan(cfg, out, simulate=bool(simulate), resume=bool(resume), md=md,
                             plan_args={"config": str(config) if not isinstance(config, ScanConfig) else str(cfg.source),
                                        "out": str(out), "simulate": bool(simulate), "resume": bool(resume)}))


def _cause(exc: FailedStatus) -> BaseException:
    """The exception a failed device status ended with (the FailedStatus itself if it names none)."""
    status = exc.args[0] if exc.args else None
    inner = status.exception() if hasattr(status, "exception") else None
    return inner if isinstance(inner, BaseException) else exc.__cause__ or exc


def _scan(cfg: ScanConfig, out: Path, *, simulate, resume, md, plan_args):
    thread = DriverThread()
    rig = _Rig(cfg, out, simulate=simulate, resume=resume)
    devices = ()
    status, error = "aborted", None
    try:
        yield from bps.wait_for([lambda: thread.call(rig.open)], timeout=OPEN_TIMEOUT_S)
        if rig.session is None:
            from acquisition.session import CaptureError
            raise CaptureError(f"opening the rig took longer than {OPEN_TIMEOUT_S:g} s")
        devices = camera, mirror, sync = _devices(rig, thread)
        yield from ensure_connected(camera, mirror, sync)
        yield from bps.stage(camera, wait=True)
        todo = camera.lines_todo
        angles = cfg.angles_deg
        start = {"plan_name": "streaklab.bluesky.scan", "plan_args": plan_args,
                 "detectors": [camera.name], "motors": [mirror.name],
                 "num_points": len(todo), "num_intervals": max(len(todo) - 1, 0),
                 "run_store": str(out), "config_hash": cfg.hash, "n_lines": int(cfg.n_lines),
                 "lines_todo": list(todo), "simulated": simulate,
                 "hints": {"dimensions": [([mirror.user_readback.name], "primary")]},
                 **(md or {})}

        def lines():
            for line in todo:
                yield from bps.checkpoint()
                yield from bps.mv(mirror, float(angles[line]), camera.line, line)
                yield from bps.trigger_and_read([camera, mirror])

        yield from bpp.run_wrapper(lines(), md=start)
        yield from bps.unstage(camera, wait=True)
        status = "complete" if not rig.session.lines_todo() else "interrupted"
    except RequestStop:
        status = "interrupted"
        raise
    except (RequestAbort, KeyboardInterrupt, GeneratorExit):
        status = "aborted"
        raise
    except FailedStatus as exc:
        cause = _cause(exc)
        status, error = "failed", f"{type(cause).__name__}: {cause}"
        if isinstance(cause, StreaklabError):
            raise cause from None           # the project's own one-line error, not the status around it
        raise
    except CaptureFailed as exc:
        status, error = "failed", str(exc)
        raise
    except Exception as exc:
        status, error = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        # Synchronous on purpose: this also runs while the RunEngine aborts.  The driver thread
        # finishes any call a pause cut short before the entry is closed and the drivers go.
        try:
            if rig.session is not None:
                for device in devices:              # the RunEngine's own unstage and stop find nothing left
                    device._thread = None
                if rig.session.store is not None and status != "complete" and not rig.session.lines_todo():
                    status = "complete"
                thread.run(rig.session.make_safe)
                thread.run(rig.session.end, status, error)
            thread.run(rig.close)
        finally:
            thread.shutdown()
