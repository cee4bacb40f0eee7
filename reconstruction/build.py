"""Run store -> calibrated (y, x, t) cube.

For every finished scan line: average its frames, subtract the mean dark frame,
divide by the flat field (optional), and resample each slit pixel's profile from
the calibrated row times onto the uniform grid of ``calibration.time_bin_ps``.
The row times are the camera's own scaling table (recorded at capture) or the
configured polynomial, see :func:`row_times`; the provenance says which.
Lines are placed along y in order of their target mirror angle (scene order),
whatever order they were acquired in.  The cube is written through
:mod:`reconstruction.cubestore`, beside three per-y arrays that tie it to the run:

    line_index  (y,)  int64    run line that fills this y
    line_valid  (y,)  bool     False where the line was unfinished (--allow-partial; cube is NaN there)
    angle_deg   (y,)  float64  mirror angle reached for the line, deg (NaN if unfinished)

Everything is checked before anything is written, and the cube is built in a
temporary directory beside ``out`` and renamed into place only when complete, so
an error never leaves a half-written cube or destroys an existing one.
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from acquisition.config import TIME_SOURCES, ConfigError, check_calibration, check_row_times
from core import limits as L
from acquisition.runstore import describe_absent, open_run
from core.errors import StreaklabError
from core.integrity import create_array, read_checked
from core.staging import check_output_path, staged_output

from .calibrate import correct_frames, dark_image, dark_noise_variance, load_flat, resample_uniform, uniform_grid
from .cubestore import CUBE_KIND, create_cube, open_cube

__all__ = ["ReconstructionError", "reconstruct", "row_times", "TIME_AGREEMENT_PS", "LineCalibration",
           "ALIGN_REFERENCES", "line_calibration", "run_dark", "mean_line_images", "scan_order"]


class ReconstructionError(StreaklabError, ValueError):
    """The run cannot be reconstructed as asked (says why)."""


def _describe_lines(idx) -> str:
    idx = [int(i) for i in idx]
    shown = ", ".join(map(str, idx[:10]))
    return shown + (f", ... ({len(idx)} in all)" if len(idx) > 10 else "")


# Camera table and configured polynomial may differ this much (ps, any row) before the cube's
# provenance flags the difference as a disagreement.
TIME_AGREEMENT_PS = 1.0


def row_times(run, n_rows: int, time_source: str | None = None) -> tuple[np.ndarray, dict]:
    """The row times (ps after the trigger, before the trigger delay) a reconstruction uses, and why.

    ``time_source`` (default: the run's ``calibration.time_source``, else ``auto``):
    ``camera`` the camera's scaling table recorded at capture, ``config`` the configured
    polynomial, ``auto`` the table when the run has one, else the polynomial.  When both
    exist they are compared; the provenance records the largest difference.
    """
    cal = run.config["calibration"]
    source = time_source or cal.get("time_source", "auto")
    if source not in TIME_SOURCES:
        raise ReconstructionError(f"time source must be one of {', '.join(TIME_SOURCES)}, got {source!r}")
    table = run.camera_row_times_ps()
    poly = None
    if "time_poly_ps" in cal:
        poly = check_calibration(cal["time_poly_ps"], n_rows, key=f"{run.path}: calibration.time_poly_ps")
    if table is not None:
        try:
            table = check_row_times(table, n_rows, key=f"{run.path}: camera_row_times_ps")
        except ConfigError as exc:
            raise ReconstructionError(str(exc)) from None
    if source == "camera" and table is None:
        raise ReconstructionError(f"{run.path}: time source 'camera', but the camera offered no scaling table "
                                  f"when this run was captured; use the configured polynomial (time source 'config')")
    if source == "config" and poly is None:
        raise ReconstructionError(f"{run.path}: time source 'config', but the run's configuration has no "
                                  f"calibration.time_poly_ps")
    use_table = table is not None and source in ("camera", "auto")
    info = {
        "time_calibration_source": "camera scaling table" if use_table else "config polynomial",
        "time_calibration_requested": source,
        "camera_scaling_table": table is not None,
        "camera_vs_config_max_diff_ps": None,
        "camera_and_config_agree": None,
    }
    if table is not None and poly is not None:
        diff = float(np.max(np.abs(table - poly)))
        info["camera_vs_config_max_diff_ps"] = diff
        info["camera_and_config_agree"] = diff <= TIME_AGREEMENT_PS
    if use_table:
        info["time_calibration_row_times_ps"] = [float(v) for v in table]
    return (table if use_table else poly), info


def reconstruct(run_path, out_path, *, chunks: tuple[int, int] | None = None, flat_path=None,
                allow_partial: bool = False, overwrite: bool = False, progress=None,
                time_source: str | None = None, align: bool | None = None, sweep_path=None,
                fiducial_min_snr: float = 5.0, align_on: str | None = None):
    """Reconstruct the calibrated cube of a run store.

    Parameters
    ----------
    run_path : path of the run store (``streaklab capture`` output).
    out_path : path of the cube store to write.
    chunks : (by, bx), optional
        Cube chunk size in pixels (time is never split); default (min(ny, 16), min(nx, 64)).
    flat_path : path of a ``.npy`` flat field, shape (x, t) or (x,), optional.
    allow_partial : bool
        Reconstruct a run with unfinished lines; their cube rows are NaN and
        ``line_valid`` is False there.  Without it unfinished lines are an error.
    overwrite : bool
        Replace an existing ``out_path`` (only after the new cube is complete).
    progress : callable(done_lines, total_lines), optional
    time_source : {"auto", "camera", "config"}, optional
        Where the row times come from (see :func:`row_times`); default: the run's
        ``calibration.time_source``, else ``auto``.  The cube's provenance records which
        was used (``time_calibration_source``) and how far the two differ.
    align : bool, optional
        Align every frame on the run's time reference before the frames are averaged
        (:mod:`reconstruction.align`); default: when the run records one (its ``fiducial``
        attribute, or its ``trigger_interval_ps``).  The corrections go into the cube's
        ``fiducial_correction_ps`` (y, frame), ps.
    align_on : {"pulse", "sync"}, optional
        The reference: the fiducial pulse in the frames (``pulse``) or the laser sync's measured
        trigger intervals (``sync``, :func:`reconstruction.align.reference_correction_ps`); default
        the one the run records, the pulse where it records both.
    sweep_path : path of a sweep calibration (``streaklab calibrate-sweep``), optional
        Its row times replace the camera table and the polynomial; it must have been made for
        the run's time range and row count.  The cube keeps a copy in its ``sweep`` group.
    fiducial_min_snr : float
        Peak-to-noise ratio the fiducial must reach in every frame.

    Returns
    -------
    reconstruction.cubestore.Cube
        The written cube, opened read-only.

    Raises
    ------
    acquisition.runstore.RunStoreError, acquisition.config.ConfigError,
    reconstruction.calibrate.CalibrationError, ReconstructionError, FileExistsError
        With a message naming the problem; nothing has been written then.
    """
    from core.provenance import __version__

    run = open_run(run_path, mode="r")
    out = Path(out_path)
    if out.resolve() == Path(run.path).resolve():
        raise ReconstructionError(f"--out {out_path} is the run store itself; choose another path")
    inputs = [run.path] + [p for p in (flat_path, sweep_path) if p is not None]
    check_output_path(out, overwrite=overwrite, inputs=inputs, kind=CUBE_KIND)

    cfg = run.config
    nx, n_rows = run.image_shape
    n_lines = run.n_lines
    row_times_ps, time_bin_ps, t0_ps, n_bins, time_info, sweep_cal = _time_grid(run, time_source, sweep_path)
    fid_attr = run.attrs.get("fiducial")
    align_on = _align_on(run, align, align_on)
    align = align_on is not None
    fiducial = _fiducial(run, align_on == "pulse", n_rows, nx)

    by = min(n_lines, 16) if chunks is None else min(int(chunks[0]), n_lines)
    try:
        # one block of lines in memory: raw frames (uint16), their float64 mean, the resampled block
        per_frame = run.frames_per_line * n_rows * (2 + (8 * 4 if align else 0))   # raw, and the aligned copies
        L.check_memory("--chunks", by * nx * (per_frame + n_rows * 8 + n_bins * (8 + 4)),
                       L.MAX_CHUNK_BYTES, what=f"to reconstruct {by} lines at a time")
        L.check_disk("cube", n_lines * nx * n_bins * 4, L.MAX_CUBE_BYTES, out.parent,
                     what=f"for a {n_lines} x {nx} x {n_bins} float32 cube (limits.MAX_CUBE_BYTES)")
    except L.LimitError as exc:
        raise ReconstructionError(f"{run.path}: {exc}") from None

    done = run.done_mask()
    missing = np.flatnonzero(~done)
    if done.sum() == 0:
        raise ReconstructionError(f"{run.path}: no line has been acquired yet; nothing to reconstruct")
    if missing.size and not allow_partial:
        raise ReconstructionError(
            f"{run.path}: {missing.size} of {n_lines} lines are unfinished (lines {_describe_lines(missing)}); "
            f"finish the run with 'streaklab capture --resume', or pass --allow-partial to fill them with NaN")
    if not run.dark_done():
        raise ReconstructionError(f"{run.path}: the dark frames were never recorded; the run is damaged")
    absent = run.absent_chunks()
    if absent:
        raise ReconstructionError(describe_absent(run, absent))
    flat, flat_sha = (None, None)
    if flat_path is not None:
        flat, flat_sha = load_flat(flat_path, (nx, n_rows))
    calib = line_calibration(run, flat=flat, time_source=time_source, sweep_path=sweep_path, align=align,
                             fiducial_min_snr=fiducial_min_snr, align_on=align_on)

    reached = np.asarray(read_checked(run["angle_deg"], slice(None), store=run.path), dtype=np.float64)
    order, target = scan_order(run)
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    provenance = {
        "producer": "streaklab reconstruct",
        "software_version": __version__,
        "created_utc": now,
        "run_path": str(Path(run.path).resolve()),
        "run_config_hash": run.config_hash,
        "run_created_utc": run.attrs.get("created_utc"),
        "run_software_version": run.attrs.get("software_version"),
        "run_devices": run.attrs.get("devices", {}),
        "lines_used": [int(i) for i in order if done[i]],
        "lines_missing": [int(i) for i in missing],
        "line_order": "y sorted by target mirror angle; line_index maps y -> run line",
        "frames_per_line": int(run.frames_per_line),
        "dark_frames": int(run["dark"].shape[0]),
        "flat_field": None if flat_path is None else str(Path(flat_path).resolve()),
        "flat_field_sha256": flat_sha,
        "time_calibration_poly_ps": [float(c) for c in cfg["calibration"].get("time_poly_ps", [])] or None,
        **time_info,
        "trigger_delay_ps": float(cfg["sync"]["trigger_delay_ps"]),
        "time_range": cfg["camera"]["time_range"],
        "exposure_s": float(cfg["camera"]["exposure_s"]),
        "resampling": ("each frame moved onto its time reference by Lanczos interpolation from calibrated row times"
                       if align else "linear interpolation from calibrated row times"),
        "aligned_on_fiducial": bool(align),
        "alignment_reference": ALIGN_REFERENCES.get(align_on),
        "fiducial": None if fiducial is None else dict(fid_attr),
        "sync_reference_nominal_ps": calib.sync_nominal_ps,
        "signal": "mean counts per frame, dark subtracted" + (", flat-field corrected" if flat is not None else ""),
    }

    with staged_output(out, overwrite=overwrite, inputs=inputs, kind=CUBE_KIND) as tmp:
        # one camera's dark-subtracted mean counts: one read noise and one gain for every pixel,
        # unless a flat field has scaled each pixel (and each row) by its own factor
        cube = create_cube(tmp, (n_lines, nx, n_bins), time_bin_ps=time_bin_ps, t0_ps=t0_ps, chunks=chunks,
                           units="counts", provenance=provenance, y_coord=target[order], y_units="deg",
                           noise_law=calib.noise_law,
                           long_name="mean counts per frame, dark-subtracted, in uniform time bins")
        g = cube.group
        create_array(g, "line_index", shape=(n_lines,), dtype="int64", dimension_names=["y"],
                     attributes={"units": "1", "long_name": "run line filling this y"})[:] = order
        create_array(g, "line_valid", shape=(n_lines,), dtype="bool", dimension_names=["y"],
                     attributes={"units": "1", "long_name": "line acquired (False: unfinished, cube is NaN)",
                                 "flag_values": [0, 1],
                                 "flag_meanings": "unfinished acquired"})[:] = done[order]
        corr_arr = None
        if align:
            what = ("its fiducial at the reference" if align_on == "pulse" else
                    "its trigger at the nominal interval after its laser pulse (the laser sync's measurement)")
            corr_arr = create_array(g, "fiducial_correction_ps", shape=(n_lines, run.frames_per_line),
                                    dtype="float64", fill_value=np.nan, dimension_names=["y", "frame"],
                                    attributes={"units": "ps", "long_name": f"time each frame was moved by to put "
                                                f"{what} (NaN: unfinished line)"})
            uncovered_arr = create_array(g, "uncovered_bins", shape=(n_lines,), dtype="int32", fill_value=0,
                                         dimension_names=["y"],
                                         attributes={"units": "1", "long_name": "time bins no frame of the line "
                                                     "covered once moved (0 there: the window saw nothing)"})
        if sweep_cal is not None:
            from .sweep import SWEEP_GROUP, write_sweep_group
            write_sweep_group(g.create_group(SWEEP_GROUP), sweep_cal)
        create_array(g, "angle_deg", shape=(n_lines,), dtype="float64", dimension_names=["y"],
                     attributes={"units": "deg", "long_name": "mirror angle reached"})[:] = reached[order]
        by = cube.array.chunks[0]
        streaks = run["streaks"]
        taken = run.frames_taken()             # adaptive accumulation: only these frames of each line
        for y0 in range(0, n_lines, by):
            ys = order[y0:y0 + by]
            block = np.full((ys.size, nx, n_bins), np.nan, dtype=np.float32)
            ok = done[ys]
            if ok.any():
                raw = np.stack([read_checked(streaks, int(i), store=run.path)
                                for i in ys[ok]])                             # (b, frame, x, rows) uint16
                try:
                    intervals = run.trigger_intervals_ps(ys[ok]) if calib.sync_nominal_ps is not None else None
                    rows, corr = calib.correct(raw, line_ids=ys[ok], frames_taken=None if taken is None
                                               else taken[ys[ok]], trigger_interval_ps=intervals)
                except StreaklabError as exc:                     # the fiducial not found in a frame
                    raise ReconstructionError(f"{run.path}: {exc}") from None
                block[ok] = rows
                if corr is not None:
                    corr_block = np.full((ys.size, run.frames_per_line), np.nan)
                    corr_block[ok] = corr
                    corr_arr[y0:y0 + ys.size] = corr_block
                    from .align import uncovered_bins
                    uncovered_arr[y0:y0 + ys.size] = uncovered_bins(calib.row_times_ps, corr_block,
                                                                   time_bin_ps=time_bin_ps, t0_ps=t0_ps, n_bins=n_bins)
            cube.array[y0:y0 + ys.size] = block
            if progress is not None:
                progress(min(y0 + by, n_lines), n_lines)
    return open_cube(out.resolve())


def _time_grid(run, time_source=None, sweep_path=None):
    """-> (row_times_ps (n_rows,), time_bin_ps, t0_ps, n_bins, time_info, sweep calibration or None):
    the cube's time axis, from the sweep calibration at ``sweep_path`` where given (checked against
    the run's time range and rows), else from :func:`row_times`."""
    cfg = run.config
    n_rows = run.image_shape[1]
    sweep_cal = None
    if sweep_path is not None:
        from .sweep import check_sweep, load_sweep
        sweep_cal = load_sweep(sweep_path)
        check_sweep(sweep_cal, time_range=cfg["camera"]["time_range"], n_rows=n_rows, where=str(run.path))
        sweep_ps = sweep_cal.row_times_ps
        time_info = {"time_calibration_source": "sweep calibration",
                     "time_calibration_requested": "sweep",
                     "sweep_calibration": str(Path(sweep_path).resolve()),
                     "sweep_calibration_residual_rms_ps": sweep_cal.residual_rms_ps}
    else:
        sweep_ps, time_info = row_times(run, n_rows, time_source)
    row_times_ps = sweep_ps + float(cfg["sync"]["trigger_delay_ps"])
    time_bin_ps = float(cfg["calibration"]["time_bin_ps"])
    t0_ps, n_bins = uniform_grid(row_times_ps, time_bin_ps, cfg["calibration"].get("t0_ps"))
    if n_bins < 2:
        raise ReconstructionError(f"{run.path}: time_bin_ps = {time_bin_ps} ps leaves fewer than 2 bins in the "
                                  f"calibrated window of {np.ptp(row_times_ps):.6g} ps")
    return row_times_ps, time_bin_ps, t0_ps, n_bins, time_info, sweep_cal


#: the time references a reconstruction aligns frames on (``align_on``), as the provenance names them
ALIGN_REFERENCES = {"pulse": "fiducial pulse", "sync": "laser sync trigger intervals"}


def _align_on(run, align, align_on):
    """The reference the frames are aligned on ("pulse", "sync") or None (not aligned), from
    ``align`` (None: when the run records a reference) and ``align_on`` (None: the run's, the
    pulse where it records both); a reference the run lacks is an error."""
    if align_on is not None and align_on not in ALIGN_REFERENCES:
        raise ReconstructionError(f"align_on must be one of {', '.join(ALIGN_REFERENCES)}, got {align_on!r}")
    has = {"pulse": run.attrs.get("fiducial") is not None, "sync": run.has_sync_reference}
    if align is False:
        if align_on is not None:
            raise ReconstructionError(f"{run.path}: --no-align with --align-on {align_on}; give one of them")
        return None
    if align_on is None:
        align_on = "pulse" if has["pulse"] or not has["sync"] else "sync"
        if align is None and not has[align_on]:
            return None
    if align_on == "sync" and not has["sync"]:
        raise ReconstructionError(f"{run.path}: --align-on sync, but the run records no trigger intervals "
                                  f"(captured without sync.reference); align on the pulse or reconstruct with "
                                  f"--no-align")
    return align_on


def _fiducial(run, align, n_rows: int, nx: int):
    """The run's fiducial (:class:`reconstruction.align.Fiducial`) where frames are to be aligned
    on it (``align``), else None; ``align`` without a recorded fiducial is an error."""
    if not align:
        return None
    from .align import parse_fiducial
    fid_attr = run.attrs.get("fiducial")
    if fid_attr is None:
        raise ReconstructionError(f"{run.path}: --align, but the run records no fiducial "
                                  f"(no 'fiducial' attribute); reconstruct with --no-align")
    return parse_fiducial(fid_attr, n_rows, nx, where=str(run.path))


@dataclass(frozen=True)
class LineCalibration:
    """How a run's scan lines become rows of its cube: dark subtraction, flat field, time axis.

    Attributes
    ----------
    row_times_ps : ndarray (n_rows,)   calibrated row times (trigger delay included), ps
    time_bin_ps, t0_ps : float         the cube's uniform time axis (bin i at t0_ps + i * time_bin_ps)
    n_bins : int                       time bins of the cube
    dark : ndarray (x, n_rows)         mean dark image, counts
    flat : ndarray (x, n_rows) or None flat field (mean 1)
    time_info : dict                   where the row times came from (the cube's provenance)
    fiducial : Fiducial or None        align every frame on the run's fiducial before the mean
    fiducial_min_snr : float           peak-to-noise ratio the fiducial must reach in every frame
    dark_noise_var : ndarray (x,) or None  variance of the mean dark's noise per slit pixel, counts^2
                                       (None: a single dark frame); what of the dark moves with
                                       aligned frames (:func:`reconstruction.align.split_dark`)
    sync_nominal_ps : float or None    align every frame on the laser sync's measured trigger
                                       interval instead, this being the nominal one (ps,
                                       :func:`reconstruction.align.reference_correction_ps`)
    """

    row_times_ps: np.ndarray
    time_bin_ps: float
    t0_ps: float
    n_bins: int
    dark: np.ndarray
    flat: np.ndarray | None
    time_info: dict
    fiducial: object = None
    fiducial_min_snr: float = 5.0
    dark_noise_var: np.ndarray | None = None
    sync_nominal_ps: float | None = None

    @cached_property
    def _dark_split(self):
        """The dark for aligned frames, split once per calibration (:func:`reconstruction.align.split_dark`):
        its structure (x, n_rows), subtracted from each frame before it moves; its noise (x, n_rows),
        flat corrected; and that noise on the cube's bins (x, n_bins), subtracted once after the
        move (moved, it would repeat at the frames' lags)."""
        from .align import split_dark
        structure, noise = split_dark(self.dark, noise_var=self.dark_noise_var)
        if self.flat is not None:
            noise = noise / self.flat
        bins = resample_uniform(noise, self.row_times_ps, time_bin_ps=self.time_bin_ps, t0_ps=self.t0_ps,
                                n_bins=self.n_bins)
        return structure, noise, bins

    @property
    def aligned(self) -> bool:
        """Frames are moved onto a time reference (the fiducial pulse or the sync's) before the mean."""
        return self.fiducial is not None or self.sync_nominal_ps is not None

    @property
    def noise_law(self) -> str | None:
        """The cube's ``noise_law``: "detector" (one camera's read-out) unless a flat field rescaled pixels."""
        return "detector" if self.flat is None else None

    def rows(self, raw, line_ids=None, frames_taken=None, trigger_interval_ps=None) -> np.ndarray:
        """Raw frames of lines, (b, frame, x, n_rows) uint16 -> their cube rows, (b, x, n_bins) float32
        (mean counts per frame, dark subtracted, flat corrected, aligned on the fiducial where the
        run has one, on the uniform time axis); ``line_ids`` (b,) name the lines in errors;
        ``frames_taken`` (b,) int, optional: only the first ``frames_taken[i]`` frames of line i
        are used (adaptive accumulation; the run store's ``frames_taken``); ``trigger_interval_ps``
        (b, frame) ps: the lines' recorded trigger intervals, needed where the frames are aligned on
        the sync reference (the run store's ``trigger_interval_ps``)."""
        return self.correct(raw, line_ids, frames_taken, trigger_interval_ps)[0]

    def correct(self, raw, line_ids=None, frames_taken=None, trigger_interval_ps=None):
        """-> (rows (b, x, n_bins) float32 as :meth:`rows`, corrections (b, frame) ps or None): each
        frame's shift onto the reference time, where frames are aligned (NaN for the frames not
        taken)."""
        if self.sync_nominal_ps is not None and trigger_interval_ps is None:
            raise ReconstructionError("frames aligned on the sync reference need their trigger intervals")
        if frames_taken is not None:
            raw = np.asarray(raw)
            taken = np.asarray(frames_taken, dtype=np.int64).reshape(-1)
            if taken.shape != raw.shape[:1] or (taken < 1).any() or (taken > raw.shape[1]).any():
                raise ReconstructionError(f"frames_taken {taken.tolist()} do not fit {raw.shape[0]} lines of "
                                          f"{raw.shape[1]} frames")
            if (taken < raw.shape[1]).any():      # lines of unequal length: one at a time
                ids = [None] * taken.size if line_ids is None else list(np.asarray(line_ids).reshape(-1))
                intervals = None if trigger_interval_ps is None else np.asarray(trigger_interval_ps, np.float64)
                parts = [self.correct(raw[i:i + 1, :k], None if ids[i] is None else [ids[i]], None,
                                      None if intervals is None else intervals[i:i + 1, :k])
                         for i, k in enumerate(taken)]
                rows = np.concatenate([r for r, _ in parts])
                if not self.aligned:
                    return rows, None
                corr = np.full(raw.shape[:2], np.nan)
                for i, (_, c) in enumerate(parts):
                    corr[i, :taken[i]] = c[0]
                return rows, corr
        if not self.aligned:
            corrected, corr = correct_frames(raw, self.dark, self.flat), None     # (b, x, rows)
        else:
            from .align import fiducial_correction_ps, mean_of_covering, reference_correction_ps, resample_aligned
            structure, dark_noise, dark_noise_bins = self._dark_split
            frames = raw - structure                                           # (b, frame, x, rows) float64
            if self.flat is not None:
                frames /= self.flat
            if self.sync_nominal_ps is not None:
                corr = reference_correction_ps(np.asarray(trigger_interval_ps, np.float64).reshape(frames.shape[:2]),
                                               self.sync_nominal_ps, line_ids=line_ids)
            else:
                corr = fiducial_correction_ps(frames - dark_noise, self.row_times_ps, self.fiducial,
                                              min_snr=self.fiducial_min_snr, line_ids=line_ids)
            rows = mean_of_covering(resample_aligned(frames, self.row_times_ps, corr, time_bin_ps=self.time_bin_ps,
                                                     t0_ps=self.t0_ps, n_bins=self.n_bins))
            rows -= dark_noise_bins
            return rows.astype(np.float32), corr
        rows = resample_uniform(corrected, self.row_times_ps, time_bin_ps=self.time_bin_ps, t0_ps=self.t0_ps,
                                n_bins=self.n_bins).astype(np.float32)
        return rows, corr


def line_calibration(run, *, flat=None, time_source: str | None = None, sweep_path=None, align: bool | None = None,
                     fiducial_min_snr: float = 5.0, align_on: str | None = None) -> LineCalibration:
    """The :class:`LineCalibration` :func:`reconstruct` applies to ``run`` (an opened run store whose
    dark frames are recorded); ``flat`` an already loaded flat field (x, n_rows) or None;
    ``sweep_path``, ``align``, ``fiducial_min_snr`` and ``align_on`` as :func:`reconstruct` takes them."""
    nx, n_rows = run.image_shape
    row_times_ps, time_bin_ps, t0_ps, n_bins, time_info, _ = _time_grid(run, time_source, sweep_path)
    align_on = _align_on(run, align, align_on)
    fiducial = _fiducial(run, align_on == "pulse", n_rows, nx)
    sync_nominal_ps = float(run.config["sync"]["trigger_delay_ps"]) if align_on == "sync" else None
    dark, noise_var = run_dark(run, with_noise=True)
    return LineCalibration(row_times_ps, time_bin_ps, t0_ps, n_bins, dark, flat, time_info, fiducial,
                           fiducial_min_snr, noise_var, sync_nominal_ps)


def run_dark(run, *, with_noise: bool = False):
    """The run's mean dark image, (x, n_rows) float64 counts per frame; ``with_noise``: and the
    variance of its noise per slit pixel, (x,) counts^2 (:func:`.calibrate.dark_noise_variance`;
    None from fewer than two frames)."""
    frames = read_checked(run["dark"], slice(None), store=run.path)
    mean = dark_image(frames, run.image_shape)
    if not with_noise:
        return mean
    return mean, dark_noise_variance(frames)


def mean_line_images(run, lines):
    """Yield ``(line, image)`` for each of ``lines``: the line's mean frame, dark subtracted,
    (x, n_rows) float64 counts per frame, over the frames it took (``frames_taken`` of an adaptive
    run), one line in memory at a time -- the raw rows a calibration capture is read from."""
    dark = run_dark(run)
    taken = run.frames_taken()
    for i in lines:
        raw = np.asarray(read_checked(run["streaks"], int(i), store=run.path))
        yield int(i), correct_frames(raw if taken is None else raw[:int(taken[i])], dark)


def scan_order(run) -> tuple[np.ndarray, np.ndarray]:
    """-> (order, target_angle_deg): ``order[y]`` is the run line that fills cube row y (lines sorted by
    target mirror angle, stable), ``target_angle_deg`` (line,) the angles the config asked for, deg."""
    target = np.asarray(read_checked(run["target_angle_deg"], slice(None), store=run.path), dtype=np.float64)
    return np.argsort(target, kind="stable"), target

