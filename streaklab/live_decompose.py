"""Decomposition during capture: each scan line decomposed as it lands (``streaklab capture --live R.zarr``).

The capture session reports every line it has written (its ``on_line`` callback); the line's
index goes onto a queue, and a worker process takes it from there (a process of its own, at the
lowest scheduling priority, so that neither the interpreter lock nor the cores it computes on
are taken from the capture): it reads the line's frames
back from the run store, turns them into the line's row of the cube exactly as
``streaklab reconstruct`` would (:class:`reconstruction.build.LineCalibration`: dark subtracted,
frames averaged, resampled onto the uniform time axis, float32), and decomposes that row as one
chunk of a result store (:class:`decomposition.store.pipeline.StreamedDecomposition`). The
capture never waits for it: lines queue while the solver is busy and are caught up later; at the
end of the capture the queue is drained.

The result store is laid out as ``streaklab decompose`` lays out the result of the reconstructed
cube with ``--per-pixel --chunks 1 NX`` (one chunk per cube row, NX the slit pixels) and the same settings: the
cube's ``noise_law`` ("detector": one camera behind every pixel), its time axis, its y coordinate
(target mirror angle, lines sorted by it). Its arrays then equal that offline result's byte for
byte (attributes such as the source and the creation time differ).

Resume: with ``capture --resume --live R.zarr`` the store is reopened (its settings must match),
and every line already on disk in the run whose chunk is not done in R.zarr is queued before the
new ones. Chunks are written with ``done`` last, so an interrupted worker leaves only whole
chunks; a resumed live result equals an uninterrupted one.

Every ``png_every`` decomposed lines (and at the end) the maps of the direct delay and the sss
attenuation (:func:`streaklab.report.plot_maps`) are written to ``png`` when one is given; napari's
reader of result stores (:mod:`streaklab.napari`) refreshes as the chunks land.
"""
from __future__ import annotations

import importlib
import multiprocessing
import os
import queue
import signal
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["LiveDecomposition", "differing_arrays", "live_source"]

_STOP = None


def live_source(run, calib, shape) -> dict:
    """The ``source`` attribute of a live result store: the run store, and the attributes of the cube
    it would reconstruct that decide the decomposition (``noise_law``)."""
    return {"path": str(Path(run.path).resolve()), "kind": "run (decomposed live, line by line)",
            "shape": [int(v) for v in shape],
            "attrs": {"noise_law": calib.noise_law,
                      "time_calibration_source": calib.time_info["time_calibration_source"]}}


def differing_arrays(a, b) -> list[str]:
    """The arrays of two Zarr stores that are not the same byte for byte, every group included.

    The promise of ``--live``: its result store holds the same bytes in every array as
    ``streaklab decompose`` of the reconstructed cube with ``--per-pixel --chunks 1 NX`` (only attributes
    differ).  Used by the tests and by ``streaklab bench live``.

    Parameters
    ----------
    a, b : paths of the two stores.

    Returns
    -------
    list of str: the paths (``"irf/samples"``) of the arrays in one store only, or whose dtype,
    shape or bytes differ, and of the groups in one store only, each with why; empty when
    every array is the same.
    """
    import zarr

    out = []

    def walk(ga, gb, prefix):
        ka, kb = set(ga.array_keys()), set(gb.array_keys())
        out.extend(f"{prefix}{k} (only in {a if k in ka else b})" for k in sorted(ka ^ kb))
        for k in sorted(ka & kb):
            x, y = np.asarray(ga[k][...]), np.asarray(gb[k][...])
            if x.dtype != y.dtype or x.shape != y.shape:
                out.append(f"{prefix}{k} ({x.dtype} {x.shape} against {y.dtype} {y.shape})")
            elif x.tobytes() != y.tobytes():
                out.append(f"{prefix}{k} (bytes differ)")
        sa, sb = set(ga.group_keys()), set(gb.group_keys())
        out.extend(f"{prefix}{k}/ (only in {a if k in sa else b})" for k in sorted(sa ^ sb))
        for k in sorted(sa & sb):
            walk(ga[k], gb[k], f"{prefix}{k}/")

    walk(zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r"), "")
    return out


class LiveDecomposition:
    """Decompose a capture's lines in a worker process as they land.

    Parameters
    ----------
    out : path of the result store (created, or reopened with ``resume``).
    resume : continue an existing store (its done chunks are kept).
    png : path of the maps figure refreshed while lines are decomposed (None: no figure).
    png_every : decomposed lines between two refreshes of the figure.
    """

    def __init__(self, out, *, resume: bool = False, png=None, png_every: int = 4):
        self.out = str(Path(out).resolve())
        self.resume = bool(resume)
        self.png = None if png is None else str(png)
        self.png_every = max(1, int(png_every))
        self.lines_done = 0            # lines whose chunk is done in the store (earlier runs included)
        self.n_lines = None
        self.error: str | None = None
        self._ctx = multiprocessing.get_context("spawn")   # no fork of a process holding device threads
        self._inbox = self._ctx.Queue()
        self._outbox = self._ctx.Queue()
        self._abandon = self._ctx.Event()
        self._proc = None

    # -------------------------------------------------------------- capture side
    def launch(self) -> None:
        """Start the worker process: it loads the solver while the devices are being set up."""
        self._proc = self._ctx.Process(target=_worker_main, name="streaklab-live-decompose", daemon=True,
                                       args=(self.out, self.resume, self.png, self.png_every,
                                             self._inbox, self._outbox, self._abandon, os.getpid()))
        self._proc.start()
        _lowest_priority(self._proc.pid)     # at once: its interpreter's start-up is not the capture's either

    def start(self, run_path) -> None:
        """Point the worker at the run store at ``run_path`` (its dark frames recorded)."""
        if self._proc is None:
            self.launch()
        self._inbox.put(str(run_path))

    def line_landed(self, line: int) -> None:
        """Queue run line ``line`` (on disk in the run store) for decomposition; returns at once."""
        self._inbox.put(int(line))

    def _poll(self) -> None:
        while True:
            try:
                kind, *values = self._outbox.get_nowait()
            except queue.Empty:
                return
            if kind == "lines":
                self.lines_done, self.n_lines = values
            elif kind == "error":
                self.error = values[0]

    def status(self) -> str:
        """``"decomposed D/N lines"`` (or that the worker stopped on an error)."""
        self._poll()
        if self.error is not None:
            return "live decomposition stopped"
        total = "?" if self.n_lines is None else self.n_lines
        return f"decomposed {self.lines_done}/{total} lines"

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop the worker after the line in hand, without a word (a capture that failed to start)."""
        if self._proc is not None and self._proc.is_alive():
            self._abandon.set()
            self._inbox.put(_STOP)
            self._proc.join(timeout_s)

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def finish(self, *, abandon: bool = False, report=None, interval_s: float = 2.0) -> bool:
        """Wait for the worker to decompose what is queued (``abandon``: only the line in hand), calling
        ``report(status)`` every ``interval_s`` seconds -> True when the worker ended."""
        if self._proc is None:
            return True
        if abandon:
            self._abandon.set()
        self._inbox.put(_STOP)
        last = time.monotonic()
        while self._proc.is_alive():
            self._proc.join(0.1)
            self._poll()
            if report is not None and time.monotonic() - last >= interval_s:
                last = time.monotonic()
                report(self.status())
        self._poll()
        if self.error is None and self._proc.exitcode not in (0, None):
            self.error = f"the worker process ended with exit code {self._proc.exitcode}"
        return True


def _worker_main(out, resume, png, png_every, inbox, outbox, abandon, parent_pid) -> None:
    """The worker process: loads the solver, then waits for the run store's path (or the word to
    stop, from a capture that ended before its first line).  Ctrl-C is the capture's to handle
    (it tells the worker when to stop)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _lowest_priority()
    try:
        importlib.import_module("decomposition.store.pipeline")    # the solver loads while the devices are set up

        worker = _Worker(None, out, resume, png, png_every, inbox, outbox, abandon, parent_pid)
        worker.run_path = next(worker._lines([]), None)
        if worker.run_path is not None:
            worker.run()
    except BaseException as exc:  # reported by the capture at the end; the capture goes on
        outbox.put(("error", f"{type(exc).__name__}: {exc}"))


#: nice level of the live worker: the lowest, so the capture (at 0) keeps its cores
LIVE_NICE = 19


def _lowest_priority(pid: int = 0) -> None:
    """Give process ``pid`` (0: this one) the lowest nice level, :data:`LIVE_NICE`.

    Against the capture at nice 0 it gets about 1.5 % of a core they share (the kernel's weights,
    15 against 1024), so the capture keeps its rate.  Not Linux's SCHED_IDLE, which would give it
    only cores nothing else wants: on a machine whose every core is busy with other work the
    worker would never run, and the drain after the capture would wait without end; an
    unprivileged process cannot take SCHED_IDLE back when the capture is over."""
    try:
        os.setpriority(os.PRIO_PROCESS, pid, LIVE_NICE)
    except (AttributeError, OSError):
        pass


class _Worker:
    def __init__(self, run_path, out, resume, png, png_every, inbox, outbox, abandon, parent_pid):
        self.run_path, self.out, self.resume = run_path, out, resume
        self.png, self.png_every = png, png_every
        self.inbox, self.outbox, self.abandon, self.parent_pid = inbox, outbox, abandon, parent_pid
        self._since_png = 0

    def _lines(self, backlog):
        """The backlog, then the queued lines until the capture says stop (or is gone)."""
        for line in backlog:
            if os.getppid() != self.parent_pid:
                return
            yield line
        while True:
            if os.getppid() != self.parent_pid:         # the capture was killed: its resume finishes the job
                return
            try:
                line = self.inbox.get(timeout=1.0)
            except queue.Empty:
                continue
            if line is _STOP:
                return
            yield line

    def run(self) -> None:
        from acquisition.runstore import open_run
        from core.integrity import read_checked
        from decomposition.store.pipeline import StreamedDecomposition
        from reconstruction.build import line_calibration, scan_order

        run = open_run(self.run_path, mode="r")
        calib = line_calibration(run)
        order, target = scan_order(run)
        y_of_line = np.empty_like(order)
        y_of_line[order] = np.arange(order.size)
        nx = run.image_shape[0]
        shape = (run.n_lines, nx, calib.n_bins)
        live = StreamedDecomposition.open(self.out, shape=shape, chunks=(1, nx), time_bin_ps=calib.time_bin_ps,
                                          t0_ps=calib.t0_ps, source=live_source(run, calib, shape), units="counts",
                                          y_coord=target[order], y_units="deg", resume=self.resume)
        pending = {iy for iy, _ in live.pending}
        done = run.n_lines - len(pending)
        self.outbox.put(("lines", done, run.n_lines))
        # lines on disk before this session (resume), not yet decomposed: first, in scan order
        backlog = [int(i) for i in np.flatnonzero(run.done_mask()) if int(y_of_line[i]) in pending]
        streaks = run["streaks"]
        for line in self._lines(backlog):
            if self.abandon.is_set():
                break
            y = int(y_of_line[line])
            if y not in pending:
                continue
            raw = np.asarray(read_checked(streaks, line, store=run.path))[None]   # (1, frame, x, rows)
            taken = run.frames_taken()                  # adaptive accumulation: the frames the line took
            intervals = run.trigger_intervals_ps([line]) if calib.sync_nominal_ps is not None else None
            live.solve(y, 0, calib.rows(raw, frames_taken=None if taken is None else taken[[line]],
                                        trigger_interval_ps=intervals))
            pending.discard(y)
            done += 1
            self.outbox.put(("lines", done, run.n_lines))
            self._since_png += 1
            if self._since_png >= self.png_every:
                self._draw(live.store)
        if self._since_png:
            self._draw(live.store)

    def _draw(self, store) -> None:
        self._since_png = 0
        if self.png is None:
            return
        from streaklab.report import plot_maps

        try:
            tmp = f"{self.png}.tmp.png"       # replaced whole: a viewer never reads half a file
            plot_maps(store, tmp)
            os.replace(tmp, self.png)
        except Exception as exc:  # a figure never stops the decomposition
            print(f"streaklab capture: live figure {self.png} not written: {exc}", file=sys.stderr)
