"""Adaptive accumulation (``streaklab capture --target-delay-error-ps E``): the stopping rule.

A line's frames so far are calibrated as :func:`reconstruction.build.reconstruct` calibrates a
finished line (dark subtraction, frame mean, uniform time axis) and decomposed with standard
errors (:func:`decomposition.decompose` with ``stderr=True``).  The line's lit pixels are those
whose direct amplitude is at least ``LIT_FRACTION`` of the line's largest, with a finite
direct-delay standard error; the line's direct-delay error is the ``ERROR_QUANTILE`` quantile of
``direct_delay_ps_stderr`` over them (none lit: infinite).  A quantile, not the largest: a few
pixels per line (direct and sss overlapping, a fit in a poor local optimum) carry errors of
tenths of a ps to hundreds that do not shrink with more frames, and would make every target
below them unreachable.  The capture session (:class:`acquisition.session.CaptureSession`,
``line_good_enough``) stops the line once its error is at most the target.
"""
from __future__ import annotations

import math

import numpy as np


#: A pixel is lit when its direct amplitude is at least this fraction of the line's largest.
LIT_FRACTION = 0.5
#: The line's error is this quantile of the direct-delay standard errors of its lit pixels.
ERROR_QUANTILE = 0.9


def parse_target_error_ps(value, where: str = "--target-delay-error-ps") -> float:
    """``value`` as a positive finite target error in ps, else a one-line :class:`CommandError`."""
    from streaklab.cli import CommandError

    try:
        e = float(value)
    except (TypeError, ValueError):
        raise CommandError(f"{where} must be a positive number of ps, got {value!r}") from None
    if not math.isfinite(e) or e <= 0:
        raise CommandError(f"{where} must be a positive number of ps, got {value!r}")
    return e


def line_delay_error_ps(calib, frames) -> float:
    """The direct-delay error of one line, ps.

    Parameters
    ----------
    calib : reconstruction.build.LineCalibration
        The run's line calibration.
    frames : ndarray (frame, x, t) uint16
        The line's frames so far.

    Returns
    -------
    float : the ``ERROR_QUANTILE`` quantile of ``direct_delay_ps_stderr`` over the lit pixels
    (direct amplitude at least ``LIT_FRACTION`` of the line's largest, delay error finite), ps;
    ``inf`` where none is lit.
    """
    from decomposition import decompose

    rows = calib.rows(np.asarray(frames)[None])[0]                           # (x, n_bins) float32
    res = decompose(rows, calib.time_bin_ps, t0_ps=calib.t0_ps, stderr=True, nan_policy="omit")
    se = np.asarray(res.params["direct_delay_ps_stderr"], dtype=np.float64)
    amp = np.asarray(res.params["direct_amplitude"], dtype=np.float64)
    if not np.isfinite(amp).any():
        return math.inf
    with np.errstate(invalid="ignore"):
        lit = np.isfinite(se) & (amp >= LIT_FRACTION * np.nanmax(amp))
    return float(np.quantile(se[lit], ERROR_QUANTILE)) if lit.any() else math.inf


class DelayErrorRule:
    """``line_good_enough(line, frames) -> bool`` for a capture session: the line's direct-delay
    error (:func:`line_delay_error_ps`) is at most ``target_ps``.

    The line calibration is read from the run store at :meth:`start` (once the session has opened
    the store and recorded its dark frames); ``errors_ps`` keeps each line's last error, ps.
    """

    def __init__(self, target_ps: float):
        self.target_ps = float(target_ps)
        self.calib = None
        self.errors_ps: dict[int, float] = {}

    def start(self, run) -> None:
        from reconstruction.build import line_calibration
        self.calib = line_calibration(run)

    def __call__(self, line: int, frames) -> bool:
        err = line_delay_error_ps(self.calib, frames)
        self.errors_ps[int(line)] = err
        return err <= self.target_ps
