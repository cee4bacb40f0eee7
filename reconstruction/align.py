"""Aligning streak frames on a fiducial pulse before they are averaged.

The camera's trigger jitters from frame to frame and drifts over minutes, so the same
light lands on different rows in different frames.  A capture with a fiducial records a
reference pulse at a fixed time in a fixed band of rows (``row_start`` to ``row_stop``,
the run store's ``fiducial`` attribute).  For every frame :func:`fiducial_times_ps` finds
that pulse (background-subtracted centroid in time of the pulse in the band, each row
weighted by its duration), :func:`fiducial_correction_ps` computes the correction
``reference - measured`` (ps) and :func:`resample_aligned` reads each frame's rows at their
times plus its correction and interpolates them onto the cube's uniform time grid in a single
step, with a Lanczos kernel (:data:`LANCZOS_LOBES` lobes) whose noise does not depend on the
fraction of a row a frame moves by: under linear interpolation a frame moved by half a row
has half the noise variance of one moved by whole rows, and the mean of frames moved by
different fractions is noise smoother at the scale of a pulse than its sample-to-sample
differences say, which a per-pixel decomposition reads as faint components.
:func:`split_dark` divides the mean dark image into its structure, which belongs to the sensor's
rows and is subtracted from every frame before it moves, and its read noise, subtracted once
after the frames are moved: moved with each frame, the dark's noise would enter the line's mean
once per distinct shift, a copy of the same noise at the lag between the frames' shifts, which
is noise correlated at the scale of a pulse.

A frame whose band holds no pulse (peak below ``min_snr`` times the band's noise, or a
centroid at the band's edge) is an error naming the line and frame; a frame is never
silently left unshifted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.errors import StreaklabError

__all__ = ["AlignmentError", "Fiducial", "parse_fiducial", "row_edges_ps", "fiducial_times_ps",
           "fiducial_correction_ps", "resample_aligned", "mean_of_covering", "uncovered_bins", "split_dark", "DARK_SMOOTH_ROWS", "DARK_OUTLIER_SIGMA",
           "reference_correction_ps", "LANCZOS_LOBES"]

#: rows of the running median that gives the dark image's structure along the time axis
DARK_SMOOTH_ROWS = 31
#: a dark sample this many noise sigmas off that running median is structure (a hot or cold
#: sample of the sensor), moved with the frames, not noise
DARK_OUTLIER_SIGMA = 5.0
#: variance of the median of n samples of Gaussian noise, times n over the noise's (large n)
MEDIAN_NOISE_VARIANCE = math.pi / 2.0
#: lobes of the Lanczos kernel that moves a frame (2 * LANCZOS_LOBES rows read per bin)
LANCZOS_LOBES = 3


class AlignmentError(StreaklabError, ValueError):
    """The fiducial cannot be found or used (says in which line and frame)."""


@dataclass(frozen=True)
class Fiducial:
    """Where a capture's fiducial pulse is.

    Attributes
    ----------
    row_start, row_stop : int
        Band of streak rows holding the pulse, ``row_start <= row < row_stop``.
    nominal_ps : float or None
        Time of the pulse after the laser pulse (the run's row times plus the trigger delay),
        ps: every frame is moved so that its fiducial lies there.  None: onto the median of
        the measured times.
    x_start, x_stop : int or None
        Slit pixels that see the pulse (default: all).
    """

    row_start: int
    row_stop: int
    nominal_ps: float | None = None
    x_start: int | None = None
    x_stop: int | None = None


def parse_fiducial(attr, n_rows: int, n_x: int, *, where: str = "the run") -> Fiducial:
    """Check a run store's ``fiducial`` attribute and return it as a :class:`Fiducial`.

    Parameters
    ----------
    attr : dict
        ``{"row_start": int, "row_stop": int, "nominal_ps": float (optional),
        "x_start": int, "x_stop": int (optional)}``.
    n_rows, n_x : int
        Rows and slit pixels of the run's images.
    """
    if not isinstance(attr, dict):
        raise AlignmentError(f"{where}: fiducial attribute must be a mapping with row_start and row_stop, got {attr!r}")
    for key in ("row_start", "row_stop"):
        if key not in attr:
            raise AlignmentError(f"{where}: fiducial attribute lacks {key!r}")

    def _int(key, default):
        v = attr.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise AlignmentError(f"{where}: fiducial.{key} must be an integer, got {v!r}")
        return int(v)

    r0, r1 = _int("row_start", None), _int("row_stop", None)
    x0, x1 = _int("x_start", 0), _int("x_stop", n_x)
    if not 0 <= r0 < r1 <= n_rows or r1 - r0 < 5:
        raise AlignmentError(f"{where}: fiducial rows {r0}..{r1} must be a band of at least 5 of the {n_rows} rows")
    if not 0 <= x0 < x1 <= n_x:
        raise AlignmentError(f"{where}: fiducial pixels {x0}..{x1} must lie within the {n_x} slit pixels")
    nominal = attr.get("nominal_ps")
    if nominal is not None:
        if isinstance(nominal, bool) or not isinstance(nominal, (int, float)) or not math.isfinite(nominal):
            raise AlignmentError(f"{where}: fiducial.nominal_ps must be a finite number of ps, got {nominal!r}")
        nominal = float(nominal)
    return Fiducial(r0, r1, nominal, x0, x1)


def row_edges_ps(row_times_ps: np.ndarray) -> np.ndarray:
    """Time of the boundaries between rows: midpoints, the outer two extrapolated.

    Parameters
    ----------
    row_times_ps : ndarray, shape (n_rows,), strictly increasing, ps

    Returns
    -------
    ndarray, shape (n_rows + 1,), ps.
    """
    t = np.asarray(row_times_ps, dtype=np.float64)
    mid = 0.5 * (t[1:] + t[:-1])
    return np.concatenate([[t[0] - (mid[0] - t[0])], mid, [t[-1] + (t[-1] - mid[-1])]])


def fiducial_times_ps(frames: np.ndarray, row_times_ps: np.ndarray, fiducial: Fiducial, *,
                      min_snr: float = 5.0, line_ids=None) -> np.ndarray:
    """Time of the fiducial pulse in every frame.

    Parameters
    ----------
    frames : ndarray, shape (n_lines, n_frames, x, n_rows)
        Dark-subtracted frames.
    row_times_ps : ndarray, shape (n_rows,)
        Time of each row, ps (increasing).
    fiducial : Fiducial
    min_snr : float
        The band's peak (above its background, the median of its outer sixths) must reach this
        many times the noise of those rows (their scaled median absolute deviation, at least the
        square root of the background count).
    line_ids : sequence of int, optional
        Run line of each entry of ``frames`` (for the error message; default 0, 1, ...).

    Returns
    -------
    ndarray, shape (n_lines, n_frames), ps: the background-subtracted centroid in time of the pulse
    (over the band's rows within two of its widths at half maximum of its peak, each row weighted
    by its duration: the rows are samples of the time profile at the row times, so on a sweep whose
    rows differ in length the centroid in row numbers would not be the pulse's centre in time).
    """
    f = np.asarray(frames, dtype=np.float64)
    if f.ndim != 4:
        raise AlignmentError(f"frames must be 4-D (line, frame, x, row), got shape {f.shape}")
    band = f[:, :, fiducial.x_start:fiducial.x_stop, fiducial.row_start:fiducial.row_stop].sum(axis=2)
    n = band.shape[-1]
    k = max(2, n // 6)
    edges = np.concatenate([band[..., :k], band[..., -k:]], axis=-1)
    bg = np.median(edges, axis=-1, keepdims=True)
    noise = 1.4826 * np.median(np.abs(edges - bg), axis=-1)
    prof = band - bg
    peak = prof.max(axis=-1)
    rows = np.arange(fiducial.row_start, fiducial.row_stop, dtype=np.float64)
    # the centroid of the pulse alone: rows within two of its widths at half maximum of its peak
    # (at least 3), so the noise of a wide band does not pull it
    top = rows[np.argmax(prof, axis=-1)]
    half_width = np.maximum(3.0, 2.0 * (prof >= 0.5 * peak[..., None]).sum(axis=-1))
    near = np.abs(rows - top[..., None]) <= half_width[..., None]
    pulse = np.where(near, np.maximum(prof, 0.0), 0.0)
    weight = pulse.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = (pulse * rows).sum(axis=-1) / weight
        snr = peak / np.maximum(noise, np.sqrt(np.abs(bg[..., 0]) + 1.0))
    margin = 1.0
    bad = ~(np.isfinite(snr) & (snr >= min_snr) & (weight > 0) & np.isfinite(centroid)
            & (centroid > fiducial.row_start + margin) & (centroid < fiducial.row_stop - 1 - margin))
    if bad.any():
        li, fi = np.argwhere(bad)[0]
        line = int(li) if line_ids is None else int(np.asarray(line_ids)[li])
        where = (f"peak {snr[li, fi]:.3g} times the noise, below {min_snr:g}" if not (snr[li, fi] >= min_snr)
                 else f"centroid at row {centroid[li, fi]:.4g}, at the band's edge")
        raise AlignmentError(f"line {line} frame {int(fi)}: no usable fiducial pulse in rows "
                             f"{fiducial.row_start}..{fiducial.row_stop} ({where}; {int(bad.sum())} such frames in all)")
    # the centroid in time: a row is a sample of the time profile at its row time (as
    # reconstruction.calibrate.resample_uniform reads it), so each row weighs by its duration; the
    # centroid in row numbers mapped through the row times is off wherever rows differ in length
    t = np.asarray(row_times_ps, dtype=np.float64)
    t_band = t[fiducial.row_start:fiducial.row_stop]
    duration = np.abs(np.diff(row_edges_ps(t)))[fiducial.row_start:fiducial.row_stop]
    with np.errstate(invalid="ignore", divide="ignore"):
        return (pulse * (duration * t_band)).sum(axis=-1) / (pulse * duration).sum(axis=-1)


def fiducial_correction_ps(frames: np.ndarray, row_times_ps: np.ndarray, fiducial: Fiducial, *,
                           min_snr: float = 5.0, line_ids=None) -> np.ndarray:
    """(n_lines, n_frames) the time each frame must move by, ps: the reference time
    (``fiducial.nominal_ps``, else the median measured one) minus its measured fiducial time
    (:func:`fiducial_times_ps`, whose arguments these are)."""
    measured = fiducial_times_ps(frames, row_times_ps, fiducial, min_snr=min_snr, line_ids=line_ids)
    ref = fiducial.nominal_ps if fiducial.nominal_ps is not None else float(np.median(measured))
    return ref - measured


def _covered(grid: np.ndarray, row_times_ps: np.ndarray, shift_ps: float) -> np.ndarray:
    """(n_bins,) bool: the grid times a frame's rows reach once moved by ``shift_ps``."""
    lo, hi = min(row_times_ps[0], row_times_ps[-1]), max(row_times_ps[0], row_times_ps[-1])
    return (grid >= lo + shift_ps) & (grid <= hi + shift_ps)


def resample_aligned(frames: np.ndarray, row_times_ps: np.ndarray, correction_ps: np.ndarray, *,
                     time_bin_ps: float, t0_ps: float, n_bins: int) -> np.ndarray:
    """Each frame moved by its correction and sampled onto the uniform time grid in one step.

    A frame's rows are read at their own times plus the frame's correction; every grid time
    ``t0_ps + i * time_bin_ps`` is placed among them by its fractional row number (the row
    times, moved, interpolated linearly) and its value is the Lanczos interpolation (kernel
    ``sinc(d) sinc(d / a)``, ``a =`` :data:`LANCZOS_LOBES`, over the ``2 a`` rows about it, its
    weights normalised to sum 1 and to a first moment of 0) of the frame's rows there.  Grid times the moved frame does not
    cover are NaN (that frame did not see them: a line's mean is taken over the frames that did,
    :func:`mean_of_covering`); rows beyond the frame's ends repeat its end rows.

    Why not linear interpolation: it halves a sample's noise variance half way between two rows
    and keeps it at a row, so frames moved by different fractions of a row carry noise of
    different texture, and their mean is smoother at the scale of a pulse than its
    sample-to-sample differences say.  The Lanczos kernel approximates the band-limited
    interpolation whose noise is the same at every fraction: its summed squared weights (the
    share of a row's noise variance a sample keeps) stay between 0.79 (half a row) and 1 (a whole
    row), where linear interpolation's fall to 0.5, and neighbouring samples half a row off the
    rows are correlated 0.25 (linear: 0.5).  A whole number of rows is an exact move, a
    constant or linear profile is kept, and a pulse a few rows wide is moved with its shape and
    its centroid.

    Parameters
    ----------
    frames : ndarray, shape (n_lines, n_frames, x, n_rows)
    row_times_ps : ndarray, shape (n_rows,), strictly monotonic, ps
    correction_ps : ndarray, shape (n_lines, n_frames), ps
    time_bin_ps, t0_ps : float    the grid, ps
    n_bins : int

    Returns
    -------
    ndarray, shape (n_lines, n_frames, x, n_bins), float64; NaN where a frame does not cover a bin.
    """
    f = np.asarray(frames, dtype=np.float64)
    t = np.asarray(row_times_ps, dtype=np.float64)
    c = np.asarray(correction_ps, dtype=np.float64)
    if c.shape != f.shape[:2]:
        raise AlignmentError(f"one correction per frame needed: {c.shape}, frames {f.shape[:2]}")
    if t[-1] < t[0]:
        t, f = t[::-1], f[..., ::-1]
    grid = float(t0_ps) + float(time_bin_ps) * np.arange(int(n_bins), dtype=np.float64)
    rows = np.arange(t.size, dtype=np.float64)
    taps = np.arange(1 - LANCZOS_LOBES, LANCZOS_LOBES + 1)                    # (2a,) rows about a bin
    out = np.zeros(f.shape[:3] + (grid.size,))
    for (i, k), shift in np.ndenumerate(c):          # one set of indices per frame: its pixels share them
        tt = t + shift
        covered = _covered(grid, t, shift)
        pos = np.interp(grid, tt, rows)                                        # fractional row of each bin
        j = np.floor(pos)
        d = pos[:, None] - (j[:, None] + taps)                                 # (n_bins, 2a) distance in rows
        w = np.sinc(d) * np.sinc(d / LANCZOS_LOBES)
        w /= w.sum(axis=1, keepdims=True)
        # less a ramp over the taps that zeroes their first moment: a linear profile is then
        # reproduced and a pulse's centroid moves by the shift exactly (the window alone is off
        # by up to 0.02 rows); the ramp is 0 on a row, where the weights already pick it alone
        ramp = d - d.mean(axis=1, keepdims=True)
        w -= (w * d).sum(axis=1, keepdims=True) * ramp / (ramp ** 2).sum(axis=1, keepdims=True)
        idx = np.clip(j[:, None].astype(np.int64) + taps, 0, t.size - 1)
        moved = np.einsum("xbk,bk->xb", f[i, k][:, idx], w)
        out[i, k] = np.where(covered, moved, np.nan)
    return out


def uncovered_bins(row_times_ps: np.ndarray, correction_ps: np.ndarray, *, time_bin_ps: float, t0_ps: float,
                   n_bins: int) -> np.ndarray:
    """(n_lines,) int: the grid's bins that no frame of a line covers once moved by its correction
    (:func:`resample_aligned`; the line's value there is 0, the window having seen nothing).
    Frames with a NaN correction (not taken) are left out; a line with none counts 0.

    Parameters
    ----------
    row_times_ps : ndarray, shape (n_rows,), strictly monotonic, ps
    correction_ps : ndarray, shape (n_lines, n_frames), ps
    time_bin_ps, t0_ps : float    the grid, ps
    n_bins : int
    """
    t = np.asarray(row_times_ps, dtype=np.float64)
    c = np.asarray(correction_ps, dtype=np.float64)
    grid = float(t0_ps) + float(time_bin_ps) * np.arange(int(n_bins), dtype=np.float64)
    covered = np.zeros((c.shape[0], grid.size), bool)
    for (i, _), shift in np.ndenumerate(c):
        if np.isfinite(shift):
            covered[i] |= _covered(grid, t, shift)
    taken = np.isfinite(c).any(axis=1)
    return np.where(taken, (~covered).sum(axis=1), 0)


def mean_of_covering(moved: np.ndarray) -> np.ndarray:
    """Mean over the frames (axis 1) of :func:`resample_aligned`'s output, each bin over the frames
    that cover it; 0 where none does (no frame saw that time).

    A plain mean would count a frame that did not see a bin as 0 there: near the window's ends,
    where the frames' shifts leave some of them short, the line's light would fall by the share
    of frames that missed it.
    """
    seen = np.isfinite(moved)
    n = seen.sum(axis=1)
    total = np.where(seen, moved, 0.0).sum(axis=1)
    return np.where(n > 0, total / np.maximum(n, 1), 0.0)


def split_dark(dark: np.ndarray, *, noise_var=None, smooth_rows: int = DARK_SMOOTH_ROWS,
               outlier_sigma: float = DARK_OUTLIER_SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """The mean dark image as its structure plus its noise: ``dark == structure + noise``.

    Frames aligned on a fiducial are moved by different amounts.  The dark's structure (the
    sensor's offsets, slow along the rows, its hot or cold samples and its fine fixed pattern)
    belongs to the rows, so it is subtracted from each frame before the frame moves.  The dark's
    noise (the read noise of the few dark frames averaged) is the same in every frame of a line:
    subtracted before the move, each frame would carry its own shifted copy, and the line's mean
    the same noise repeated at the lag between the frames' shifts, a correlation at the scale of
    a pulse that a per-pixel decomposition takes for one.  Subtracted once after the move (onto
    the cube's bins unmoved) it stays white, as in an unaligned cube.

    What is left about a running median along the rows is split between the two by its
    variance: the mean dark's own noise variance ``noise_var`` (the dark frames' scatter over
    their number) is noise, anything beyond it a fixed pattern of the sensor, kept with the
    structure in proportion (the least-squares, Wiener, share of each sample).  The running
    median itself (mirrored at the ends of the rows) is split the same way about each slit
    pixel's level (its median over the rows, which moves onto itself): the median of the noise
    (variance :data:`MEDIAN_NOISE_VARIANCE` over ``smooth_rows`` times the noise's) is noise,
    its variation beyond that the sensor's.  Moved with the frames and subtracted again, negated,
    on the bins unmoved, the noise it keeps would be noise at a pulse's scale at two places a
    shift apart.

    Parameters
    ----------
    dark : ndarray, shape (x, n_rows)
        Mean dark image, counts.
    noise_var : float or ndarray (x,), optional
        Variance of the mean dark's noise, counts^2, per slit pixel.  None (a single dark frame:
        its noise cannot be told from a pattern): all that is left about the running median,
        but for the outliers, is noise.
    smooth_rows : int
        Rows of the running median (along the rows, each slit pixel apart) that gives the structure.
    outlier_sigma : float
        A sample further than this many noise sigmas (each slit pixel's scaled median absolute
        deviation of the dark about its running median) from the running median is structure too.

    Returns
    -------
    (structure, noise) : two ndarrays, shape (x, n_rows), float64, counts.
    """
    from scipy.ndimage import median_filter

    d = np.asarray(dark, dtype=np.float64)
    if d.ndim != 2:
        raise AlignmentError(f"the dark image must be 2-D (x, row), got shape {d.shape}")
    size = max(1, min(int(smooth_rows), d.shape[1]))
    # mirrored at the ends: padded with the end sample, the median of the first and last rows is
    # that one sample, its noise whole, where a moved frame subtracts it at other rows
    smooth = median_filter(d, size=(1, size), mode="mirror")
    rest = d - smooth
    sigma = 1.4826 * np.median(np.abs(rest), axis=1, keepdims=True)
    outlier = np.abs(rest) > outlier_sigma * sigma
    var_noise = sigma[:, 0] ** 2 if noise_var is None else \
        np.broadcast_to(np.asarray(noise_var, np.float64), sigma.shape[:1])
    pattern = np.zeros_like(d)
    if noise_var is not None:
        var_rest = sigma[:, 0] ** 2
        keep = np.clip(1.0 - var_noise / np.where(var_rest > 0, var_rest, np.inf), 0.0, 1.0)
        pattern = keep[:, None] * rest
    # the running median about each slit pixel's level carries the noise's median too (variance
    # pi / (2 size) of the noise's): kept, it is subtracted at a moved frame's rows and again,
    # negated with the rest, at the bins unmoved, noise at a pulse's scale.  Its variation beyond
    # that variance is the sensor's, kept in proportion (a level moves onto itself)
    level = np.median(d, axis=1, keepdims=True)
    slow = smooth - level
    var_slow = np.mean(slow ** 2, axis=1)
    keep_slow = np.clip(1.0 - MEDIAN_NOISE_VARIANCE * var_noise / size
                        / np.where(var_slow > 0, var_slow, np.inf), 0.0, 1.0)
    structure = np.where(outlier, d, level + keep_slow[:, None] * slow + pattern)
    return structure, d - structure


def reference_correction_ps(trigger_interval_ps: np.ndarray, nominal_ps: float, *, line_ids=None) -> np.ndarray:
    """(n_lines, n_frames) the time each frame must move by, ps, from the laser sync's reference:
    each frame's measured trigger interval after its laser pulse minus the nominal one.

    A trigger that fires ``d`` ps late shows the light ``d`` ps early in the window, so the frame
    is read at its row times plus ``d`` (:func:`resample_aligned`): the opposite of a fiducial
    pulse, whose measured time is late when the light is (:func:`fiducial_correction_ps`).

    Parameters
    ----------
    trigger_interval_ps : ndarray, shape (n_lines, n_frames)
        The run store's ``trigger_interval_ps`` of the frames to align, ps.
    nominal_ps : float
        The trigger interval the frames' row times assume (the run's ``sync.trigger_delay_ps``), ps.
    line_ids : sequence of int, optional
        Run line of each row of ``trigger_interval_ps`` (for the error message; default 0, 1, ...).

    Raises
    ------
    AlignmentError
        A frame without a finite interval, naming its line and frame.
    """
    measured = np.asarray(trigger_interval_ps, dtype=np.float64)
    if measured.ndim != 2:
        raise AlignmentError(f"trigger intervals must be 2-D (line, frame), got shape {measured.shape}")
    bad = ~np.isfinite(measured)
    if bad.any():
        li, fi = np.argwhere(bad)[0]
        line = int(li) if line_ids is None else int(np.asarray(line_ids)[li])
        raise AlignmentError(f"line {line} frame {int(fi)}: no usable trigger interval from the laser sync "
                             f"({float(measured[li, fi])!r}; {int(bad.sum())} such frames in all)")
    return measured - float(nominal_ps)
