"""Calibrating the streak sweep from an etalon pulse pair, and storing the calibration.

The sweep maps row ``r`` to the time ``t(r)`` (ps after the trigger, before the trigger
delay), and that map is not a straight line.  An etalon turns each laser pulse into a pair
``etalon_ps`` apart; a capture whose trigger delay steps moves the pair across the rows.
:func:`pair_rows` finds both pulses of every line's profile (background-subtracted
centroids, sub-row); :func:`fit_sweep` fits ``t(r) = sum_k c_k P_k(u)`` (Legendre
polynomials of ``u = 2 r / (n_rows - 1) - 1``) by linear least squares so that

* each pair is ``etalon_ps`` apart: ``t(r2) - t(r1) = etalon_ps``, and, with the delays known,
* each pulse arrived at one instant after the laser: ``t(r1) + delay = T``, ``t(r2) + delay = T + etalon_ps``.

An etalon capture fixes the sweep up to a constant; the constant ``c_0`` is chosen so that the
calibrated row times have the same mean as the nominal ones (the run's camera table or
polynomial), so a calibration changes the shape of the time axis, not where it lies.

A calibration is stored as a Zarr group (standalone, or the ``sweep`` group of a cube store)
or a ``.npz`` file, with the time range and row count it was made for: applying it to a run
of another time range or row count is refused (:func:`check_sweep`).
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

from core.errors import StreaklabError
from core.integrity import create_array, read_checked
from core.provenance import __version__
from core.calibfile import open_calibration, save_calibration

__all__ = ["SWEEP_KIND", "SWEEP_GROUP", "SweepError", "SweepCalibration", "pair_rows", "fit_sweep",
           "check_sweep", "write_sweep_group", "save_sweep", "load_sweep"]

SWEEP_KIND = "sweep_calibration"
SWEEP_GROUP = "sweep"
FORMAT_VERSION = 1


class SweepError(StreaklabError, ValueError):
    """A sweep calibration that cannot be made, read or applied (says why)."""


@dataclass(frozen=True, eq=False)
class SweepCalibration:
    """A calibrated sweep: the time of every row.

    Attributes
    ----------
    row_times_ps : ndarray, shape (n_rows,)
        Time of each row after the trigger (before the trigger delay), ps; strictly monotonic.
    time_range : str or int
        The camera time range the calibration was made for (``camera.time_range``).
    coefficients_ps : list of float
        Legendre coefficients of ``t`` in ``u = 2 r / (n_rows - 1) - 1``, lowest order first, ps.
    etalon_ps : float
        The pair separation it was made with, ps.
    residual_rms_ps : float
        RMS misfit of the pulse equations, ps.
    provenance : dict
    """

    row_times_ps: np.ndarray
    time_range: object
    coefficients_ps: list
    etalon_ps: float
    residual_rms_ps: float
    provenance: dict = field(default_factory=dict)

    @property
    def n_rows(self) -> int:
        return int(self.row_times_ps.size)


def _centroids(prof: np.ndarray, centre: np.ndarray, half_rows: int) -> np.ndarray:
    """Background-free centroid (rows) of ``prof`` (n, rows) in ``centre +- half_rows``."""
    n_rows = prof.shape[-1]
    offs = np.arange(-half_rows, half_rows + 1)
    idx = centre[:, None] + offs[None, :]
    ok = (idx >= 0) & (idx < n_rows)
    vals = np.where(ok, np.take_along_axis(prof, np.clip(idx, 0, n_rows - 1), axis=-1), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (vals * idx).sum(axis=-1) / vals.sum(axis=-1)


def pair_rows(profiles: np.ndarray, separation_rows: float, *, min_snr: float = 10.0) -> np.ndarray:
    """Rows of the two pulses of an etalon pair in each profile.

    Parameters
    ----------
    profiles : ndarray, shape (n, n_rows)
        Dark-subtracted counts per row (one per delay).
    separation_rows : float
        Approximate separation of the pulses, rows (from the nominal sweep); the pulses are
        measured in windows of +- 0.4 times it around their peaks.
    min_snr : float
        Each pulse's peak must reach this many times the profile's noise (scaled median
        absolute deviation about its median, at least the square root of the median count).

    Returns
    -------
    ndarray, shape (n, 2), float: earlier row first, NaN where a profile has no clear pair
    (a pulse missing, too weak or cut by the window's ends).
    """
    p = np.asarray(profiles, dtype=np.float64)
    n, n_rows = p.shape
    bg = np.median(p, axis=-1, keepdims=True)
    noise = np.maximum(1.4826 * np.median(np.abs(p - bg), axis=-1), np.sqrt(np.abs(bg[:, 0]) + 1.0))
    p = p - bg
    half = max(1, int(round(0.4 * separation_rows)))
    rows = np.arange(n_rows)
    first = np.argmax(p, axis=-1)
    masked = np.where(np.abs(rows[None, :] - first[:, None]) <= max(half, int(0.6 * separation_rows)), -np.inf, p)
    second = np.argmax(masked, axis=-1)
    peaks = np.stack([first, second], axis=-1)
    heights = np.take_along_axis(p, peaks, axis=-1)
    out = np.stack([_centroids(p, first, half), _centroids(p, second, half)], axis=-1)
    ok = ((heights >= min_snr * noise[:, None]).all(axis=-1)
          & (peaks - half >= 0).all(axis=-1) & (peaks + half < n_rows).all(axis=-1)
          & np.isfinite(out).all(axis=-1))
    ok &= np.abs(np.abs(second - first) - separation_rows) <= 0.5 * separation_rows
    out.sort(axis=-1)
    out[~ok] = np.nan
    return out


def _basis(rows: np.ndarray, n_rows: int, degree: int) -> np.ndarray:
    u = 2.0 * np.asarray(rows, dtype=np.float64) / (n_rows - 1) - 1.0
    return np.polynomial.legendre.legvander(u, degree)            # (..., degree + 1)


def fit_sweep(pulse_rows: np.ndarray, etalon_ps: float, nominal_row_times_ps: np.ndarray, *,
              delays_ps=None, degree: int = 4, time_range=None, provenance: dict | None = None
              ) -> SweepCalibration:
    """Fit the row-time curve to the pulse pairs of an etalon capture.

    Parameters
    ----------
    pulse_rows : ndarray, shape (n, 2)
        Rows of the two pulses of each pair (:func:`pair_rows`; rows of NaN are skipped).
    etalon_ps : float
        Separation of the pulses in time, ps.
    nominal_row_times_ps : ndarray, shape (n_rows,)
        The sweep as configured (camera table or polynomial), ps: gives the direction of the
        sweep and the constant the calibration keeps (its mean).
    delays_ps : ndarray, shape (n,), optional
        Trigger delay of each profile, ps; adds the equations that tie pairs at different
        delays together (without them only the separations are used).
    degree : int
        Degree of the Legendre polynomial (1 to 12).
    time_range : the camera time range it is made for (stored with it).

    Returns
    -------
    SweepCalibration
    """
    nominal = np.asarray(nominal_row_times_ps, dtype=np.float64)
    n_rows = nominal.size
    if not (isinstance(degree, int) and 1 <= degree <= 12):
        raise SweepError(f"degree must be an integer from 1 to 12, got {degree!r}")
    if not (np.isfinite(etalon_ps) and etalon_ps > 0):
        raise SweepError(f"etalon separation must be positive, got {etalon_ps!r} ps")
    pr = np.asarray(pulse_rows, dtype=np.float64)
    used = np.isfinite(pr).all(axis=-1)
    if delays_ps is not None:
        delays_ps = np.asarray(delays_ps, dtype=np.float64)
        if delays_ps.shape != (pr.shape[0],):
            raise SweepError(f"{delays_ps.size} delays given for {pr.shape[0]} profiles")
    n_used = int(used.sum())
    if n_used < degree + 2:
        raise SweepError(f"only {n_used} of {pr.shape[0]} profiles hold a clear etalon pair; "
                         f"a degree-{degree} sweep needs at least {degree + 2}")
    increasing = nominal[-1] > nominal[0]
    early, late = (pr[used, 0], pr[used, 1]) if increasing else (pr[used, 1], pr[used, 0])
    b1, b2 = _basis(early, n_rows, degree)[:, 1:], _basis(late, n_rows, degree)[:, 1:]
    if delays_ps is None:
        A = b2 - b1
        rhs = np.full(n_used, float(etalon_ps))
    else:
        d = delays_ps[used]
        ones = -np.ones((n_used, 1))
        A = np.vstack([np.hstack([b1, ones]), np.hstack([b2, ones])])
        rhs = np.concatenate([-d, float(etalon_ps) - d])
    sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    resid = A @ sol - rhs
    coef = np.concatenate([[0.0], sol[:degree]])
    t = _basis(np.arange(n_rows), n_rows, degree) @ coef
    shift = float(np.mean(nominal) - np.mean(t))
    coef[0] += shift
    t = t + shift
    dt = np.diff(t)
    if not (np.all(dt > 0) or np.all(dt < 0)):
        raise SweepError(f"the fitted sweep is not monotonic over the {n_rows} rows (degree {degree} too high "
                         f"for pairs covering rows {np.nanmin(pr):.0f}..{np.nanmax(pr):.0f}?)")
    prov = {"method": "etalon pulse pairs, Legendre least squares", "degree": degree,
            "pairs_used": n_used, "pairs_total": int(pr.shape[0]), "delays_used": delays_ps is not None,
            "rows_covered": [float(np.nanmin(pr)), float(np.nanmax(pr))],
            "max_deviation_from_nominal_ps": float(np.max(np.abs(t - nominal))),
            **dict(provenance or {})}
    return SweepCalibration(t, time_range, [float(c) for c in coef], float(etalon_ps),
                            float(np.sqrt(np.mean(resid ** 2))), prov)


def check_sweep(cal: SweepCalibration, *, time_range, n_rows: int, where: str) -> None:
    """Refuse a calibration made for another time range or row count (one line naming both)."""
    if str(cal.time_range) != str(time_range):
        raise SweepError(f"{where}: the sweep calibration was made for time range {cal.time_range!r}, "
                         f"the run uses {time_range!r}; calibrate this time range with 'streaklab calibrate-sweep'")
    if cal.n_rows != int(n_rows):
        raise SweepError(f"{where}: the sweep calibration has {cal.n_rows} rows, the run's images {n_rows}")


def _attributes(cal: SweepCalibration) -> dict:
    return {"streaklab_kind": SWEEP_KIND, "format_version": FORMAT_VERSION, "time_range": cal.time_range,
            "n_rows": cal.n_rows, "coefficients_ps": cal.coefficients_ps, "etalon_ps": cal.etalon_ps,
            "residual_rms_ps": cal.residual_rms_ps, "units": "ps",
            "reference": "ps after the trigger, before the trigger delay; Legendre in u = 2 row / (n_rows - 1) - 1",
            "provenance": cal.provenance, "software_version": __version__,
            "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}


def write_sweep_group(group: zarr.Group, cal: SweepCalibration) -> None:
    """Write ``cal`` into an empty Zarr group: array ``row_times_ps`` (row,) and the attributes."""
    group.attrs.update(_attributes(cal))
    create_array(group, "row_times_ps", shape=(cal.n_rows,), dtype="float64", dimension_names=["row"],
                 attributes={"units": "ps", "long_name": "calibrated time of the row after the trigger"}
                 )[:] = cal.row_times_ps


def _from_parts(row_times, attrs: dict, where: str) -> SweepCalibration:
    if attrs.get("streaklab_kind") != SWEEP_KIND:
        raise SweepError(f"{where} is not a sweep calibration (streaklab_kind = {attrs.get('streaklab_kind')!r})")
    t = np.asarray(row_times, dtype=np.float64)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)) or not (np.all(np.diff(t) > 0)
                                                                       or np.all(np.diff(t) < 0)):
        raise SweepError(f"{where}: row_times_ps must be finite and strictly monotonic")
    try:
        return SweepCalibration(t, attrs["time_range"], list(attrs["coefficients_ps"]), float(attrs["etalon_ps"]),
                                float(attrs["residual_rms_ps"]), dict(attrs.get("provenance") or {}))
    except KeyError as exc:
        raise SweepError(f"{where} lacks the {exc.args[0]!r} attribute") from None


def read_sweep_group(group: zarr.Group, *, where: str) -> SweepCalibration:
    """Read a calibration written by :func:`write_sweep_group`."""
    if "row_times_ps" not in group:
        raise SweepError(f"{where} has no 'row_times_ps' array")
    return _from_parts(read_checked(group["row_times_ps"], ..., store=where), dict(group.attrs), where)


def save_sweep(path, cal: SweepCalibration, *, overwrite: bool = False, inputs=()) -> Path:
    """Save as a standalone Zarr store, or a ``.npz`` file when ``path`` ends in ``.npz``
    (written beside it and renamed into place; inputs are never written over)."""
    return save_calibration(path, kind=SWEEP_KIND, arrays={"row_times_ps": cal.row_times_ps},
                            attributes=_attributes(cal), write_group=lambda g: write_sweep_group(g, cal),
                            overwrite=overwrite, inputs=inputs)


def load_sweep(path) -> SweepCalibration:
    """Read a calibration from a ``.npz`` file, a sweep store, or the ``sweep`` group of a cube store."""
    found = open_calibration(path, kind=SWEEP_KIND, group_name=SWEEP_GROUP, array_names=("row_times_ps",),
                             error=SweepError, what="sweep calibration")
    if found.group is None:
        return _from_parts(found.arrays["row_times_ps"], found.attributes, found.where)
    return read_sweep_group(found.group, where=found.where)
