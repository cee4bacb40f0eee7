"""The raw run store: every streak image of a capture session, exactly as acquired.

One Zarr v3 directory store per run (see ``docs/layout.md`` for the full table)::

    streaks           (line, frame, x, t)  uint16   counts as read from the camera, one chunk per line
    done              (line,)              bool     True once the line's data is on disk
    angle_deg         (line,)              float64  mirror angle reached (deg), NaN until done
    timestamp         (line,)              float64  acquisition end, seconds since 1970-01-01 UTC
    target_angle_deg  (line,)              float64  the angle the config asked for (deg)
    dark              (dark_frame, x, t)   uint16   frames taken with the sync output off
    dark_done         ()                   bool     True once the dark frames are on disk

Every frame of a line is kept (``frame`` axis) instead of their mean or sum: the data
stay the camera's own uint16 counts, a reconstruction can reject a bad frame (a
cosmic-ray hit, a missed trigger) after the fact, and the average is one ``mean``
away.

Durability.  ``streaks``, ``done``, ``angle_deg`` and ``timestamp`` are chunked one
line per chunk, so writing a line never rewrites another line's bytes.  A line is
written data first (``streaks``, ``angle_deg``, ``timestamp``), fsync'd, and only
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

from .config import ConfigError, ScanConfig, parse_config
from .durable import fsync_path, sync_chunk

__all__ = ["RUN_KIND", "RunStoreError", "RunStore", "create_run", "open_run", "config_differences"]

RUN_KIND = "run"
LINE_ARRAYS = ("streaks", "angle_deg", "timestamp", "done")


class RunStoreError(ValueError):
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
            self._arrays[name] = self.group[name]
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
        return np.asarray(self["done"][...], dtype=bool)

    def dark_done(self) -> bool:
        return bool(self["dark_done"][...])

    # -- writing ---------------------------------------------------------------------------
    def _sync_chunk(self, name: str, coords: tuple[int, ...]) -> None:
        sync_chunk(self.path, name, coords)

    def write_line(self, line: int, frames: np.ndarray, *, angle_deg: float, timestamp: float) -> None:
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
        """
        frames = np.asarray(frames)
        expect = self["streaks"].shape[1:]
        if frames.shape != expect or frames.dtype != np.uint16:
            raise RunStoreError(f"line {line}: expected uint16 frames of shape {expect}, got "
                                f"{frames.dtype} {frames.shape}")
        self["streaks"][line] = frames
        self["angle_deg"][line] = float(angle_deg)
        self["timestamp"][line] = float(timestamp)
        self._sync_chunk("streaks", (line, 0, 0, 0))
        self._sync_chunk("angle_deg", (line,))
        self._sync_chunk("timestamp", (line,))
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
        self.group.attrs["sessions"] = sessions


def create_run(path, config: ScanConfig, *, image_shape: tuple[int, int], devices: dict | None = None,
               software_version: str | None = None) -> RunStore:
    """Create an empty run store laid out for ``config`` and images of ``image_shape`` = (x, t).

    The path must not exist or be an empty directory (resuming goes through :func:`open_run`).
    """
    from streaklab import __version__

    p = Path(path)
    if p.exists() and (p.is_file() or any(p.iterdir())):
        raise RunStoreError(f"{path} already exists; pass --resume to continue that run, or choose another --out")
    nx, nt = (int(s) for s in image_shape)
    if nx <= 0 or nt <= 0:
        raise RunStoreError(f"image shape must be positive, got {image_shape}")
    n_lines = config.n_lines
    n_frames = int(config["camera"]["frames_per_line"])
    n_dark = int(config["dark"]["frames"])
    g = zarr.open_group(str(p), mode="w")
    # Marked uninitialised until every array exists: a store killed during creation is recreated on resume.
    g.attrs.update({"streaklab_kind": RUN_KIND, "initialised": False})
    g.create_array("streaks", shape=(n_lines, n_frames, nx, nt), chunks=(1, n_frames, nx, nt), dtype="uint16",
                   fill_value=0, dimension_names=["line", "frame", "x", "t"],
                   attributes={"units": "counts", "long_name": "streak images as acquired (t = streak pixel row)"})
    g.create_array("done", shape=(n_lines,), chunks=(1,), dtype="bool", fill_value=False,
                   dimension_names=["line"], attributes={"long_name": "line acquired and on disk"})
    g.create_array("angle_deg", shape=(n_lines,), chunks=(1,), dtype="float64", fill_value=np.nan,
                   dimension_names=["line"], attributes={"units": "deg", "long_name": "mirror angle reached"})
    g.create_array("timestamp", shape=(n_lines,), chunks=(1,), dtype="float64", fill_value=np.nan,
                   dimension_names=["line"],
                   attributes={"units": "seconds since 1970-01-01", "calendar": "proleptic_gregorian",
                               "long_name": "end of the line's acquisition (UTC)"})
    target = g.create_array("target_angle_deg", shape=(n_lines,), dtype="float64", dimension_names=["line"],
                            attributes={"units": "deg", "long_name": "mirror angle requested by the config"})
    target[:] = config.angles_deg
    g.create_array("dark", shape=(n_dark, nx, nt), chunks=(max(n_dark, 1), nx, nt), dtype="uint16", fill_value=0,
                   dimension_names=["dark_frame", "x", "t"],
                   attributes={"units": "counts", "long_name": "dark frames (sync output off)"})
    g.create_array("dark_done", shape=(), dtype="bool", fill_value=False, dimension_names=[],
                   attributes={"long_name": "dark frames on disk"})
    g.attrs.update({
        "streaklab_kind": RUN_KIND,
        "config": config.data,
        "config_hash": config.hash,
        "config_source": config.source,
        "software_version": software_version or __version__,
        "devices": dict(devices or {}),
        "created_utc": _utc_now(),
        "sessions": [],
        "initialised": True,
    })
    for name in ("streaks", "done", "angle_deg", "timestamp", "target_angle_deg", "dark", "dark_done"):
        fsync_path(p / name / "zarr.json")
    fsync_path(p / "zarr.json")
    fsync_path(p)
    return open_run(p, mode="r+")


def _remove_partials(path: Path) -> int:
    n = 0
    for f in path.rglob("*.partial"):
        f.unlink(missing_ok=True)
        n += 1
    return n


def is_uninitialised_run(path) -> bool:
    """True for a run store whose creation was interrupted (no line can be in it).

    That is a run group still marked ``initialised = False``, or a directory holding
    nothing but ``*.partial`` files (killed before the group's metadata was in place).
    """
    p = Path(path)
    if p.is_dir() and not (p / "zarr.json").exists():
        return all(f.name.endswith(".partial") for f in p.rglob("*") if f.is_file())
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
    try:
        g = zarr.open_group(str(p), mode=mode)
    except Exception as exc:
        raise RunStoreError(f"{path} is not a Zarr group: {exc}") from None
    kind = g.attrs.get("streaklab_kind")
    if kind != RUN_KIND:
        what = f"a streaklab {kind!r} store" if kind else "not a streaklab store"
        raise RunStoreError(f"{path} is not a run store (it is {what})")
    if g.attrs.get("initialised") is not True:
        raise RunStoreError(f"{path}: the run store's creation was interrupted before any line was taken")
    for name in ("streaks", "done", "angle_deg", "timestamp", "target_angle_deg", "dark", "dark_done"):
        try:
            ok = name in g and isinstance(g[name], zarr.Array)
        except Exception as exc:  # damaged metadata (zarr.json): JSON or zarr's own errors
            raise RunStoreError(f"{path}/{name}: unreadable array metadata ({type(exc).__name__}: "
                                f"{str(exc).splitlines()[0] if str(exc) else ''}); the run store is damaged") from None
        if not ok:
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
        _remove_partials(p)
    return RunStore(str(p), g, config)
