"""The raw run store: every streak image of a capture session, exactly as acquired.

One Zarr v3 directory store per run (see ``docs/layout.md`` for the full table)::

    streaks           (line, frame, x, row)  uint16   counts as read from the camera, one chunk per line
    done              (line,)                bool     True once the line's data is on disk
    angle_deg         (line,)                float64  mirror angle reached (deg), NaN until done
    timestamp         (line,)                float64  acquisition end, seconds since 1970-01-01 UTC
    target_angle_deg  (line,)                float64  the angle the config asked for (deg)
    dark              (dark_frame, x, row)   uint16   frames taken with the sync output off
    dark_done         ()                     bool     True once the dark frames are on disk
    line, x, row      coordinates; time_ps (row,) the row's calibrated time (ps)
    camera_row_times_ps (row,)               float64  the camera's own sweep calibration (its scaling
                                                      table, ps after the trigger); only where the
                                                      camera offers one
    trigger_interval_ps (line, frame)        float64  the laser sync's measured interval of each frame's
                                                      camera trigger after its laser pulse, ps; only
                                                      where the config sets ``sync.reference``

Every array is checksummed (:mod:`core.integrity`); :func:`verify_run` reads every chunk
and reports damage by line.

Every frame of a line is kept (``frame`` axis) instead of their mean or sum: the data
stay the camera's own uint16 counts, a reconstruction can reject a bad frame (a
cosmic-ray hit, a missed trigger) after the fact, and the average is one ``mean``
away.

Durability.  ``streaks``, ``done``, ``angle_deg``, ``timestamp`` (and ``trigger_interval_ps``)
are chunked one line per chunk, so writing a line never rewrites another line's bytes.  A line is
written data first (``streaks``, ``angle_deg``, ``timestamp``, ``trigger_interval_ps``), fsync'd, and only
then marked in ``done`` (fsync'd too).  zarr-python 3.1's LocalStore writes each
chunk to a temporary file and renames it into place, so a chunk file is either the
old or the new version, never a torn one; an interrupted write leaves at most a
``*.partial`` file, which :func:`open_run` removes when resuming.  Readers trust
``done`` only: a line whose flag is not set is treated as never acquired.
"""
from __future__ import annotations

import datetime as _dt
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

from core.durable import fsync_path, sync_chunk, sync_chunks
from core.errors import StreaklabError
from core.integrity import (ChunkDamage, consolidate, create_array, has_checksums, missing_chunks, read_checked,
                            open_member, scan_array, writable)
from core.staging import OutputPathError, check_no_links, staged_output

from .config import ConfigError, ScanConfig, calibration_times_ps, parse_config

__all__ = ["RUN_KIND", "TRIGGER_INTERVALS", "RunStoreError", "RunStore", "create_run", "open_run", "config_differences"]

RUN_KIND = "run"
LINE_ARRAYS = ("streaks", "angle_deg", "timestamp", "done")
#: the laser sync's measured trigger interval of every frame (a run with ``sync.reference``)
TRIGGER_INTERVALS = "trigger_interval_ps"


class RunStoreError(StreaklabError, ValueError):
    """The path is not a usable run store, or does not fit the session (says exactly why)."""


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def config_differences(stored: dict, current: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two (normalised) config dicts."""
    out = []
    for key in sorted(set(stored) | set(current)):
        a, b = stored.get(key, "<absent>"), current.get(key, "<absent>")
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out.extend(config_differences(a, b, name + "."))
        elif a != b:
            out.append(f"{name} ({a!r} -> {b!r})")
    return out


@dataclass
class RunStore:
    """An opened run store.

    Attributes
    ----------
    path : str
    group : zarr.Group
    config : ScanConfig
        The configuration the run was captured with (from the store's attributes).
    """

    path: str
    group: zarr.Group
    config: ScanConfig
    _arrays: dict = field(default_factory=dict, repr=False)

    def __getitem__(self, name) -> zarr.Array:
        if name not in self._arrays:
            self._arrays[name] = writable(self.group[name])
        return self._arrays[name]

    @property
    def attrs(self) -> dict:
        return dict(self.group.attrs)

    @property
    def n_lines(self) -> int:
        return self["streaks"].shape[0]

    @property
    def frames_per_line(self) -> int:
        return self["streaks"].shape[1]

    @property
    def image_shape(self) -> tuple[int, int]:
        """(x, t) pixels of one streak image."""
        return tuple(self["streaks"].shape[2:])

    @property
    def config_hash(self) -> str:
        return str(self.group.attrs["config_hash"])

    def done_mask(self) -> np.ndarray:
        """Per-line done flags, shape (line,), bool."""
        return np.asarray(read_checked(self["done"], slice(None), store=self.path), dtype=bool)

    def dark_done(self) -> bool:
        return bool(read_checked(self["dark_done"], (), store=self.path))

    def camera_row_times_ps(self) -> np.ndarray | None:
        """The camera's scaling table recorded at capture, shape (row,), ps; None if the camera had none."""
        if "camera_row_times_ps" not in self.group:
            return None
        return np.asarray(read_checked(self["camera_row_times_ps"], slice(None), store=self.path),
                          dtype=np.float64)

    @property
    def has_sync_reference(self) -> bool:
        """The run records the laser sync's trigger interval of every frame (``sync.reference``)."""
        return TRIGGER_INTERVALS in self.group

    def trigger_intervals_ps(self, lines) -> np.ndarray:
        """The recorded trigger intervals of ``lines`` (a sequence of line indices), shape
        (len(lines), frame), float64 ps (NaN for the frames a line did not take).

        Raises
        ------
        RunStoreError
            The run records none (captured without ``sync.reference``).
        """
        if not self.has_sync_reference:
            raise RunStoreError(f"{self.path}: the run records no trigger intervals (captured without "
                                f"sync.reference)")
        arr = self[TRIGGER_INTERVALS]
        return np.stack([np.asarray(read_checked(arr, int(i), store=self.path), dtype=np.float64)
                         for i in lines]).reshape(len(lines), self.frames_per_line)

    # -- integrity -------------------------------------------------------------------------
    def absent_chunks(self) -> list[ChunkDamage]:
        """Chunks the store says were written (lines marked done, the dark frames) whose files are gone.

        Only a stat per chunk; arrays of earlier releases (no checksums) are not judged.
        """
        done = [int(i) for i in np.flatnonzero(self.done_mask())]
        out = []
        # (target_reached is not judged: a False flag may be stored as no chunk, the fill value)
        names = ("streaks", "angle_deg", "timestamp") + tuple(
            name for name in ("frames_taken", TRIGGER_INTERVALS) if name in self.group)
        for name in names:
            arr = self[name]
            for coords in missing_chunks(self.path, arr, [(i,) + (0,) * (arr.ndim - 1) for i in done]):
                out.append(ChunkDamage(name, coords, "missing"))
        if self.dark_done() and self["dark"].shape[0]:
            out.extend(ChunkDamage("dark", c, "missing") for c in missing_chunks(self.path, self["dark"], [(0, 0, 0)]))
        return out

    def verify(self) -> "RunCheck":
        """Read every chunk the store says holds data; see :class:`RunCheck`."""
        return verify_run(self)

    def mark_lines_not_done(self, lines) -> None:
        """Clear the done flag of ``lines`` (durably), so ``capture --resume`` takes them again."""
        for line in lines:
            self["done"][int(line)] = False
            self._sync_chunk("done", (int(line),))

    def mark_dark_not_done(self) -> None:
        self["dark_done"][...] = False
        self._sync_chunk("dark_done", ())

    # -- writing ---------------------------------------------------------------------------
    def _sync_chunk(self, name: str, coords: tuple[int, ...]) -> None:
        sync_chunk(self.path, name, coords)

    def frames_taken(self) -> np.ndarray | None:
        """Frames each line took, shape (line,), int64 (0: line not acquired), where the run was
        captured with adaptive accumulation; None for a fixed accumulation (every line took
        ``frames_per_line``).  Only ``streaks[line, :frames_taken[line]]`` hold frames."""
        if "frames_taken" not in self.group:
            return None
        return np.asarray(read_checked(self["frames_taken"], slice(None), store=self.path), dtype=np.int64)

    def target_reached(self) -> np.ndarray | None:
        """Per-line flag of an adaptive run, shape (line,), bool: the stopping target was met
        (False: the line stopped at the maximum without it, or was not acquired); None otherwise."""
        if "target_reached" not in self.group:
            return None
        return np.asarray(read_checked(self["target_reached"], slice(None), store=self.path), dtype=bool)

    def add_adaptive_arrays(self) -> None:
        """Create ``frames_taken`` and ``target_reached`` (line,) if absent (the first adaptive
        session of a run; lines acquired before it took every frame)."""
        if "frames_taken" in self.group:
            return
        n = self.n_lines
        done = self.done_mask()
        taken = create_array(self.group, "frames_taken", shape=(n,), chunks=(1,), dtype="int64", fill_value=0,
                             dimension_names=["line"],
                             attributes={"units": "1", "long_name": "frames the line took (adaptive "
                                         "accumulation; the frame slots after them are unused)"})
        create_array(self.group, "target_reached", shape=(n,), chunks=(1,), dtype="bool",
                     fill_value=False, dimension_names=["line"],
                     attributes={"units": "1", "long_name": "adaptive accumulation reached its target",
                                 "flag_values": [0, 1], "flag_meanings": "missed_or_fixed reached"})
        if done.any():
            taken[:] = np.where(done, self.frames_per_line, 0)
        for name in ("frames_taken", "target_reached"):
            fsync_path(Path(self.path) / name / "zarr.json")
        consolidate(self.path)
        self._arrays.pop("frames_taken", None)
        self._arrays.pop("target_reached", None)
        sync_chunks(self.path, [("frames_taken", (i,)) for i in np.flatnonzero(done)])

    def write_line(self, line: int, frames: np.ndarray, *, angle_deg: float, timestamp: float,
                   frames_taken: int | None = None, target_reached: bool | None = None,
                   trigger_interval_ps=None) -> None:
        """Store one scan line durably, then mark it done.

        Parameters
        ----------
        line : int
            Line index (acquisition order, as in the config).
        frames : ndarray, shape (frame, x, t), uint16
            The line's frames exactly as acquired.
        angle_deg : float
            Mirror angle reached, degrees.
        timestamp : float
            Acquisition end time, seconds since 1970-01-01 UTC.
        frames_taken, target_reached : int, bool, optional
            Adaptive accumulation: the frames the line took (the first ``frames_taken`` of
            ``frames``) and whether it met its target.  Where the store records them and these
            are not given, the line took every frame and the flag is False.
        trigger_interval_ps : sequence of float, optional
            The laser sync's measured trigger interval of each frame taken, ps, in order (one
            per frame taken); required where the store records them, refused where it does not.
        """
        frames = np.asarray(frames)
        expect = self["streaks"].shape[1:]
        if frames.shape != expect or frames.dtype != np.uint16:
            raise RunStoreError(f"line {line}: expected uint16 frames of shape {expect}, got "
                                f"{frames.dtype} {frames.shape}")
        n_taken = frames.shape[0] if frames_taken is None else int(frames_taken)
        intervals = None
        if self.has_sync_reference:
            if trigger_interval_ps is None:
                raise RunStoreError(f"line {line}: the store records trigger intervals, none given")
            measured = np.asarray(trigger_interval_ps, dtype=np.float64).reshape(-1)
            if measured.size != n_taken:
                raise RunStoreError(f"line {line}: {measured.size} trigger intervals for {n_taken} frames")
            intervals = np.full(frames.shape[0], np.nan)
            intervals[:n_taken] = measured
        elif trigger_interval_ps is not None:
            raise RunStoreError(f"line {line}: trigger intervals given, but the store has no "
                                f"{TRIGGER_INTERVALS} array")
        self["streaks"][line] = frames
        self["angle_deg"][line] = float(angle_deg)
        self["timestamp"][line] = float(timestamp)
        written = [("streaks", (line, 0, 0, 0)), ("angle_deg", (line,)), ("timestamp", (line,))]
        if intervals is not None:
            self[TRIGGER_INTERVALS][line] = intervals
            written.append((TRIGGER_INTERVALS, (line, 0)))
        if frames_taken is not None and not 1 <= int(frames_taken) <= frames.shape[0]:
            raise RunStoreError(f"line {line}: frames_taken {frames_taken} outside 1..{frames.shape[0]}")
        if "frames_taken" in self.group:
            self["frames_taken"][line] = frames.shape[0] if frames_taken is None else int(frames_taken)
            self["target_reached"][line] = bool(target_reached)
            written += [("frames_taken", (line,)), ("target_reached", (line,))]
        elif frames_taken is not None:
            raise RunStoreError(f"line {line}: frames_taken given, but the store has no frames_taken array")
        sync_chunks(self.path, written)
        self["done"][line] = True
        self._sync_chunk("done", (line,))

    def write_dark(self, frames: np.ndarray) -> None:
        """Store the dark frames (dark_frame, x, t) uint16 durably, then mark them done."""
        frames = np.asarray(frames)
        expect = self["dark"].shape
        if frames.shape != expect or frames.dtype != np.uint16:
            raise RunStoreError(f"dark: expected uint16 frames of shape {expect}, got {frames.dtype} {frames.shape}")
        if frames.shape[0]:
            self["dark"][...] = frames
            self._sync_chunk("dark", (0, 0, 0))
        self["dark_done"][...] = True
        self._sync_chunk("dark_done", ())

    def add_session(self, info: dict) -> None:
        """Append one entry (start time, device identities, ...) to the ``sessions`` attribute."""
        sessions = list(self.group.attrs.get("sessions", []))
        sessions.append(dict(info))
        self.set_sessions(sessions)

    def set_sessions(self, sessions: list) -> None:
        """Replace the ``sessions`` attribute and consolidate the metadata again (rewriting the root
        document drops its consolidated part)."""
        self.group.attrs["sessions"] = list(sessions)
        consolidate(self.path)


@dataclass
class RunCheck:
    """What :func:`verify_run` found.

    Attributes
    ----------
    checksums : bool
        The data arrays carry crc32c checksums (False for stores of earlier releases, where
        only undecodable chunks can be found, not changed bytes).
    lines : dict line -> list of ChunkDamage
        Lines marked done with a damaged chunk (``streaks``, ``angle_deg``, ``timestamp`` or
        the line's ``done`` flag itself).
    dark : list of ChunkDamage
        Damage to the dark frames (or their flag).
    other : list of ChunkDamage
        Damage that a recapture does not mend (``target_angle_deg``, coordinates).
    lines_done : int
        Lines whose ``done`` flag is set (and readable), damaged or not.
    n_lines : int
        Lines of the scan.
    dark_pending : bool
        The run takes dark frames and they are not marked done (the capture stopped before them).
    """

    checksums: bool
    lines: dict
    dark: list
    other: list
    lines_done: int = 0
    n_lines: int = 0
    dark_pending: bool = False

    @property
    def complete(self) -> bool:
        """Every line (and the dark frames) was captured; damage aside."""
        return self.lines_done + sum(1 for d in self.lines.values()
                                     if any(x.array == "done" for x in d)) >= self.n_lines and not self.dark_pending

    @property
    def ok(self) -> bool:
        return not (self.lines or self.dark or self.other)


def verify_run(run: RunStore) -> RunCheck:
    """Read every chunk of ``run`` that should hold data and report the damaged ones by line."""
    path = run.path
    lines: dict[int, list] = {}
    n = run.n_lines
    done_arr = run["done"]
    done = np.zeros(n, bool)
    for line in range(n):                                   # the flags one by one: one may be damaged itself
        bad = list(scan_array(path, done_arr, [(line,)], must_exist=lambda c: False))
        if bad:
            lines.setdefault(line, []).extend(bad)
        else:
            done[line] = bool(done_arr[line])
    ok_lines = [(int(i),) for i in np.flatnonzero(done)]
    for name in ("streaks", "angle_deg", "timestamp") + ((TRIGGER_INTERVALS,) if run.has_sync_reference else ()):
        arr = run[name]
        for d in scan_array(path, arr, [c + (0,) * (arr.ndim - 1) for c in ok_lines]):
            lines.setdefault(d.coords[0], []).append(d)
    dark = list(scan_array(path, run["dark_done"], must_exist=lambda c: False))
    dark_pending = False
    if not dark:
        if run.dark_done():
            dark = list(scan_array(path, run["dark"]))
        else:
            dark_pending = run["dark"].shape[0] > 0
    other = []
    for name in sorted(run.group.array_keys()):
        if name not in LINE_ARRAYS + ("dark", "dark_done", TRIGGER_INTERVALS):
            other.extend(scan_array(path, run[name]))
    return RunCheck(checksums=has_checksums(run["streaks"]), lines=dict(sorted(lines.items())), dark=dark,
                    other=other, lines_done=int(done.sum()), n_lines=n, dark_pending=dark_pending)


def describe_absent(run: RunStore, absent: list[ChunkDamage]) -> str:
    """One line: which lines (and dark frames) are marked done but lack their chunks, and the fix."""
    lines = sorted({d.coords[0] for d in absent if d.array != "dark"})
    parts = []
    if lines:
        shown = ", ".join(map(str, lines[:10])) + (f", ... ({len(lines)} in all)" if len(lines) > 10 else "")
        parts.append(f"line{'s' if len(lines) > 1 else ''} {shown} {'are' if len(lines) > 1 else 'is'} marked done "
                     f"but {', '.join(sorted({d.array for d in absent if d.array != 'dark'}))} chunks are missing")
    if any(d.array == "dark" for d in absent):
        parts.append("the dark frames are marked done but their chunk is missing")
    return (f"{run.path}: {'; '.join(parts)}; run 'streaklab verify {run.path} --mark-for-resume', then "
            f"'streaklab capture ... --resume' to recapture just those")


def create_run(path, config: ScanConfig, *, image_shape: tuple[int, int], devices: dict | None = None,
               software_version: str | None = None, camera_row_times_ps=None,
               camera_time_info: dict | None = None) -> RunStore:
    """Create an empty run store laid out for ``config`` and images of ``image_shape`` = (x, t).

    ``camera_row_times_ps`` (row,) is the camera's own sweep calibration, if it has one;
    ``camera_time_info`` says where it came from (stored as the array's attributes).

    The path must not exist or be an empty directory (resuming goes through :func:`open_run`).
    The store is built beside ``path`` and renamed into place once every array exists, so a
    killed creation never leaves a half store at ``path``.
    """
    from core.provenance import __version__

    p = Path(path)
    if p.exists() and (p.is_file() or any(p.iterdir())):
        raise RunStoreError(f"{path} already exists; pass --resume to continue that run, or choose another --out")
    nx, nt = (int(s) for s in image_shape)
    if nx <= 0 or nt <= 0:
        raise RunStoreError(f"image shape must be positive, got {image_shape}")
    n_lines = config.n_lines
    n_frames = int(config["camera"]["frames_per_line"])
    n_dark = int(config["dark"]["frames"])
    table = None
    if camera_row_times_ps is not None:
        table = np.asarray(camera_row_times_ps, dtype=np.float64)
        if table.shape != (nt,):
            raise RunStoreError(f"camera_row_times_ps has shape {table.shape}, the images {nt} rows")
    with staged_output(p, kind=RUN_KIND) as tmp:
        _write_skeleton(tmp, config, n_lines=n_lines, n_frames=n_frames, n_dark=n_dark, nx=nx, nt=nt,
                        devices=devices, software_version=software_version or __version__,
                        camera_table=table, camera_time_info=camera_time_info)
    fsync_path(p.parent)
    return open_run(p, mode="r+")


def _write_skeleton(p: Path, config: ScanConfig, *, n_lines, n_frames, n_dark, nx, nt, devices,
                    software_version, camera_table=None, camera_time_info=None) -> None:
    g = zarr.open_group(str(p), mode="w")
    # Marked uninitialised until every array exists (earlier releases built the store in place, and
    # --resume recreates a store they left so marked).
    g.attrs.update({"streaklab_kind": RUN_KIND, "initialised": False})
    create_array(g, "streaks", shape=(n_lines, n_frames, nx, nt), chunks=(1, n_frames, nx, nt), dtype="uint16",
                 fill_value=0, dimension_names=["line", "frame", "x", "row"],
                 attributes={"units": "counts", "long_name": "streak images as acquired",
                             "coordinates": "time_ps"})
    create_array(g, "done", shape=(n_lines,), chunks=(1,), dtype="bool", fill_value=False,
                 dimension_names=["line"],
                 attributes={"units": "1", "long_name": "line acquired and on disk", "flag_values": [0, 1],
                             "flag_meanings": "not_acquired acquired",
                             "comment": "readers trust only this flag: a line without it is treated as never "
                                        "acquired, whatever bytes its chunk holds"})
    create_array(g, "angle_deg", shape=(n_lines,), chunks=(1,), dtype="float64", fill_value=np.nan,
                 dimension_names=["line"], attributes={"units": "deg", "long_name": "mirror angle reached"})
    create_array(g, "timestamp", shape=(n_lines,), chunks=(1,), dtype="float64", fill_value=np.nan,
                 dimension_names=["line"],
                 attributes={"units": "seconds since 1970-01-01", "calendar": "proleptic_gregorian",
                             "long_name": "end of the line's acquisition (UTC)"})
    target = create_array(g, "target_angle_deg", shape=(n_lines,), dtype="float64", dimension_names=["line"],
                          attributes={"units": "deg", "long_name": "mirror angle requested by the config"})
    target[:] = config.angles_deg
    if config["sync"].get("reference"):
        create_array(g, TRIGGER_INTERVALS, shape=(n_lines, n_frames), chunks=(1, n_frames), dtype="float64",
                     fill_value=np.nan, dimension_names=["line", "frame"],
                     attributes={"units": "ps", "long_name": "camera trigger's interval after its laser pulse, "
                                 "as the laser sync measured it (NaN: frame not taken)"})
    create_array(g, "dark", shape=(n_dark, nx, nt), chunks=(max(n_dark, 1), nx, nt), dtype="uint16", fill_value=0,
                 dimension_names=["dark_frame", "x", "row"],
                 attributes={"units": "counts", "long_name": "dark frames (sync output off)",
                             "coordinates": "time_ps"})
    create_array(g, "dark_done", shape=(), dtype="bool", fill_value=False, dimension_names=[],
                 attributes={"units": "1", "long_name": "dark frames on disk", "flag_values": [0, 1],
                             "flag_meanings": "not_taken taken"})
    # coordinates, so that xarray gives labelled axes
    create_array(g, "line", shape=(n_lines,), dtype="int64", dimension_names=["line"],
                 attributes={"units": "1", "long_name": "scan line, in acquisition order (scan.angles_deg)"})[:] = \
        np.arange(n_lines)
    create_array(g, "x", shape=(nx,), dtype="float64", dimension_names=["x"],
                 attributes={"units": "pixel", "long_name": "slit position"})[:] = np.arange(nx, dtype=np.float64)
    create_array(g, "row", shape=(nt,), dtype="int64", dimension_names=["row"],
                 attributes={"units": "1", "long_name": "streak pixel row (the sweep direction)"})[:] = np.arange(nt)
    cal = config["calibration"]
    if camera_table is not None:
        create_array(g, "camera_row_times_ps", shape=(nt,), dtype="float64", dimension_names=["row"],
                     attributes={"units": "ps", "long_name": "row times from the camera's scaling table "
                                                             "(after the trigger)",
                                 **dict(camera_time_info or {})})[:] = camera_table
    # time_ps follows the row times a reconstruction uses by default (calibration.time_source)
    if camera_table is not None and cal.get("time_source", "auto") != "config":
        time_ps, origin = camera_table, "the camera's scaling table (camera_row_times_ps)"
    else:
        time_ps = calibration_times_ps(cal["time_poly_ps"], nt)
        origin = "calibration.time_poly_ps at the row"
    create_array(g, "time_ps", shape=(nt,), dtype="float64", dimension_names=["row"],
                 attributes={"units": "ps", "long_name": "time of the row after the laser pulse",
                             "comment": f"{origin} plus sync.trigger_delay_ps, as known when the run was "
                                        f"created; not uniform in general"})[:] = \
        time_ps + float(config["sync"]["trigger_delay_ps"])
    g.attrs.update({
        "streaklab_kind": RUN_KIND,
        "config": config.data,
        "config_hash": config.hash,
        "config_source": config.source,
        "software_version": software_version,
        "devices": dict(devices or {}),
        "created_utc": _utc_now(),
        "sessions": [],
        "initialised": True,
    })
    for name in g.array_keys():
        fsync_path(p / name / "zarr.json")
    fsync_path(p / "zarr.json")
    fsync_path(p)


def _remove_partials(path: Path) -> int:
    n = 0
    for f in path.rglob("*.partial"):
        f.unlink(missing_ok=True)
        n += 1
    return n


def is_uninitialised_run(path) -> bool:
    """True for a run store whose creation was interrupted (no line can be in it).

    That is only a group that streaklab itself marked as a run still being created
    (``streaklab_kind = "run"``, ``initialised = False``; earlier releases created the store
    in place).  Nothing else is ever taken for one, whatever files it holds: a folder of
    ``*.partial`` files may be anybody's.
    """
    p = Path(path)
    if not (p / "zarr.json").is_file():
        return False
    try:
        g = zarr.open_group(str(path), mode="r")
    except Exception:
        return False
    return g.attrs.get("streaklab_kind") == RUN_KIND and g.attrs.get("initialised") is False


def remove_uninitialised_run(path) -> None:
    if not is_uninitialised_run(path):
        raise RunStoreError(f"{path} is not an interrupted, empty run store; refusing to delete it")
    shutil.rmtree(path)


def open_run(path, *, mode: str = "r") -> RunStore:
    """Open and validate a run store.

    Parameters
    ----------
    mode : "r" or "r+"
        ``r+`` (for resuming) also removes ``*.partial`` files left by an interrupted write.

    Raises
    ------
    RunStoreError
        Naming what is wrong: missing path, not a Zarr group, not a run, missing arrays.
    """
    p = Path(path)
    if not p.exists():
        raise RunStoreError(f"{path}: no such file or directory")
    if p.is_dir() and not (p / "zarr.json").exists():
        raise RunStoreError(f"{path} is not a Zarr group (it has no zarr.json); streaklab did not create it as "
                            f"a run store, so it neither resumes nor removes it: choose another --out, or remove "
                            f"it yourself")
    try:
        g = zarr.open_group(str(p), mode=mode, use_consolidated=False)
    except Exception as exc:
        raise RunStoreError(f"{path} is not a Zarr group: {exc}") from None
    kind = g.attrs.get("streaklab_kind")
    if kind != RUN_KIND:
        what = f"a streaklab {kind!r} store" if kind else "not a streaklab store"
        raise RunStoreError(f"{path} is not a run store (it is {what})")
    if g.attrs.get("initialised") is not True:
        raise RunStoreError(f"{path}: the run store's creation was interrupted before any line was taken")
    for name in ("streaks", "done", "angle_deg", "timestamp", "target_angle_deg", "dark", "dark_done"):
        if not isinstance(open_member(g, name, path, RunStoreError), zarr.Array):
            raise RunStoreError(f"{path}: run store lacks the {name!r} array")
    try:
        config = parse_config(g.attrs["config"], source=g.attrs.get("config_source"))
    except (KeyError, ConfigError) as exc:
        raise RunStoreError(f"{path}: the stored configuration is unusable: {exc}") from None
    s = g["streaks"]
    if s.ndim != 4 or s.dtype != np.uint16:
        raise RunStoreError(f"{path}/streaks must be uint16 (line, frame, x, t); it is {s.dtype} {s.shape}")
    if s.shape[0] != config.n_lines or g["done"].shape != (s.shape[0],):
        raise RunStoreError(f"{path}: {s.shape[0]} lines in streaks, {g['done'].shape} done flags, "
                            f"{config.n_lines} lines in the stored config")
    if mode != "r":
        try:
            check_no_links(p)
        except OutputPathError as exc:
            raise RunStoreError(str(exc)) from None
        _remove_partials(p)
    return RunStore(str(p), g, config)
