"""Per-line corrections of raw streak images: dark, flat field, and the time-axis calibration.

The streak sweep is not linear in the pixel row, so row ``r`` records the light
that arrived at ``t(r) = sum_k c_k r**k + trigger_delay_ps`` (ps after the laser
pulse).  The counts of a row are treated as a sample of the pixel's time profile
at ``t(r)``; :func:`resample_uniform` interpolates those samples onto the uniform
grid ``t0_ps + i * time_bin_ps`` the rest of streaklab works with.  Everything
works on whole lines (x, t) or blocks of lines at once: no Python loop per pixel.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from core import limits as L
from core.errors import StreaklabError

__all__ = ["CalibrationError", "dark_image", "dark_noise_variance", "load_flat", "uniform_grid", "resample_uniform", "correct_frames"]


class CalibrationError(StreaklabError, ValueError):
    """A dark, flat or time calibration that cannot be applied (says why)."""


def dark_image(dark_frames: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """Mean dark image.

    Parameters
    ----------
    dark_frames : ndarray, shape (n_dark, x, t), uint16
        Frames taken with no light.  ``n_dark = 0`` gives a zero dark image.
    image_shape : (x, t)

    Returns
    -------
    ndarray, shape (x, t), float64, counts.
    """
    dark_frames = np.asarray(dark_frames)
    if dark_frames.ndim != 3 or tuple(dark_frames.shape[1:]) != tuple(image_shape):
        raise CalibrationError(f"dark frames must have shape (n, {image_shape[0]}, {image_shape[1]}), "
                               f"got {dark_frames.shape}")
    if dark_frames.shape[0] == 0:
        return np.zeros(image_shape, dtype=np.float64)
    return dark_frames.mean(axis=0, dtype=np.float64)


#: rows pooled into one group by :func:`dark_noise_variance` before the median over the groups
DARK_NOISE_GROUP_ROWS = 16


def dark_noise_variance(dark_frames: np.ndarray) -> np.ndarray | None:
    """Variance of the mean dark image's noise per slit pixel, (x,) counts^2; None from fewer
    than two frames.

    Each sample's scatter over the ``n`` dark frames (``ddof=1``) is averaged over groups of
    :data:`DARK_NOISE_GROUP_ROWS` rows, and the median over the groups is divided by the median
    of the scaled chi-square law of a group mean, ``(1 - 2 / (9 k))**3`` with ``k = rows * (n - 1)``
    degrees of freedom (Wilson-Hilferty), then by ``n``.  A median of single samples' scatters
    would sit far below their mean (with two frames, at 0.45 of it, the median of chi-square with
    one degree of freedom); the group means are close to normal, and the median over them still
    ignores a hot sample's group.

    Parameters
    ----------
    dark_frames : ndarray, shape (n_dark, x, t)
    """
    frames = np.asarray(dark_frames, np.float64)
    n, _, n_rows = frames.shape
    if n < 2:
        return None
    scatter = np.var(frames, axis=0, ddof=1)                       # (x, t), unit: counts^2 per frame
    group = min(DARK_NOISE_GROUP_ROWS, n_rows)
    n_groups = n_rows // group
    means = scatter[:, :n_groups * group].reshape(scatter.shape[0], n_groups, group).mean(axis=2)
    k = group * (n - 1)
    return np.median(means, axis=1) / (1.0 - 2.0 / (9.0 * k)) ** 3 / n


def load_flat(path, image_shape: tuple[int, int]) -> tuple[np.ndarray, str]:
    """Read a flat-field image from a ``.npy`` file and normalise it to mean 1.

    Parameters
    ----------
    path : str or Path
        ``.npy`` holding shape (x, t) (per pixel and row) or (x,) (per slit pixel).
    image_shape : (x, t)

    Returns
    -------
    flat : ndarray, shape (x, t), float64
        Relative sensitivity, mean 1; corrected = (raw - dark) / flat.
    sha256 : str
        Digest of the file, for provenance.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise CalibrationError(f"flat field {path}: cannot read it: {exc.strerror or exc}") from None
    try:
        flat = np.load(p, allow_pickle=False)
    except Exception as exc:
        raise CalibrationError(f"flat field {path}: not a .npy array: {exc}") from None
    nx, nt = image_shape
    if flat.shape == (nx,):
        flat = np.broadcast_to(flat[:, None], (nx, nt))
    if flat.shape != (nx, nt):
        raise CalibrationError(f"flat field {path}: shape {flat.shape} does not fit the images; "
                               f"expected ({nx}, {nt}) or ({nx},)")
    if not np.issubdtype(flat.dtype, np.number) or np.issubdtype(flat.dtype, np.complexfloating):
        raise CalibrationError(f"flat field {path}: must be real numbers, got dtype {flat.dtype}")
    flat = flat.astype(np.float64)
    if not np.all(np.isfinite(flat)) or np.any(flat <= 0):
        n_bad = int(np.count_nonzero(~np.isfinite(flat) | (flat <= 0)))
        raise CalibrationError(f"flat field {path}: {n_bad} values are not positive and finite")
    return flat / flat.mean(), hashlib.sha256(raw).hexdigest()


def uniform_grid(row_times_ps: np.ndarray, time_bin_ps: float, t0_ps: float | None = None) -> tuple[float, int]:
    """The uniform time grid covered by the calibrated rows.

    Parameters
    ----------
    row_times_ps : ndarray, shape (n_rows,)
        Strictly monotonic time of each row, ps.
    time_bin_ps : float
        Bin width, ps.
    t0_ps : float, optional
        Time of bin 0.  Default: the first multiple of ``time_bin_ps`` at or after
        the earliest row time (so grids of different runs line up).

    Returns
    -------
    t0_ps : float
    n_bins : int
        Bins ``t0_ps + i * time_bin_ps`` that lie inside [min, max] of the row times.
    """
    lo, hi = float(np.min(row_times_ps)), float(np.max(row_times_ps))
    T = float(time_bin_ps)
    if t0_ps is None:
        t0_ps = np.ceil(lo / T - 1e-9) * T
    t0_ps = float(t0_ps)
    if t0_ps < lo - 1e-9 * T or t0_ps > hi:
        raise CalibrationError(f"t0_ps = {t0_ps} ps lies outside the calibrated window [{lo:.6g}, {hi:.6g}] ps")
    n = np.floor((hi - t0_ps) / T + 1e-9) + 1
    refused = L.time_bin_message(T, hi - lo, n)
    if refused:
        raise CalibrationError(refused)
    return t0_ps, int(n)


def resample_uniform(profiles: np.ndarray, row_times_ps: np.ndarray, *, time_bin_ps: float, t0_ps: float,
                     n_bins: int) -> np.ndarray:
    """Linearly interpolate profiles sampled at the row times onto a uniform grid.

    Parameters
    ----------
    profiles : ndarray, shape (..., n_rows)
        Samples at ``row_times_ps`` (any leading shape: a line (x, n_rows) or a block).
    row_times_ps : ndarray, shape (n_rows,)
        Strictly monotonic (increasing or decreasing) row times, ps.
    time_bin_ps, t0_ps : float
        Output grid ``t0_ps + i * time_bin_ps``, ps.
    n_bins : int
        Output bins; every grid time must lie inside the row-time range.

    Returns
    -------
    ndarray, shape (..., n_bins), float64.
    """
    t = np.asarray(row_times_ps, dtype=np.float64)
    profiles = np.asarray(profiles, dtype=np.float64)
    if profiles.shape[-1] != t.size:
        raise CalibrationError(f"profiles have {profiles.shape[-1]} rows but the calibration {t.size}")
    d = np.diff(t)
    if d.size and d[0] < 0:
        t = t[::-1]
        profiles = profiles[..., ::-1]
        d = -d[::-1]
    if not np.all(d > 0):
        raise CalibrationError("row times must be strictly monotonic")
    grid = float(t0_ps) + float(time_bin_ps) * np.arange(int(n_bins), dtype=np.float64)
    span = 1e-9 * max(abs(t[0]), abs(t[-1]), 1.0)
    if grid[0] < t[0] - span or grid[-1] > t[-1] + span:
        raise CalibrationError(f"grid [{grid[0]:.6g}, {grid[-1]:.6g}] ps leaves the calibrated window "
                               f"[{t[0]:.6g}, {t[-1]:.6g}] ps")
    # One set of indices and weights for every profile: the rows share their times.
    j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 2)
    w = np.clip((grid - t[j]) / (t[j + 1] - t[j]), 0.0, 1.0)
    lo = np.take(profiles, j, axis=-1)
    hi = np.take(profiles, j + 1, axis=-1)
    return lo + w * (hi - lo)


def correct_frames(frames: np.ndarray, dark: np.ndarray, flat: np.ndarray | None = None) -> np.ndarray:
    """Average the frames of each line, subtract the dark image, divide by the flat.

    Parameters
    ----------
    frames : ndarray, shape (..., n_frames, x, t), uint16
    dark : ndarray, shape (x, t), float64
    flat : ndarray, shape (x, t), optional (mean 1)

    Returns
    -------
    ndarray, shape (..., x, t), float64, counts per frame.
    """
    out = np.asarray(frames).mean(axis=-3, dtype=np.float64) - dark
    if flat is not None:
        out /= flat
    return out
