"""Adaptive accumulation (``streaklab capture --target-delay-error-ps E``): the stopping rule.

A line's frames so far are calibrated as :func:`reconstruction.build.reconstruct` calibrates a
finished line (dark subtraction, frame mean, uniform time axis) and decomposed with standard
errors (:func:`decomposition.decompose` with ``stderr=True``).  The line's error is the largest
``direct_delay_ps_stderr`` over its lit pixels (:func:`lit_pixels`): the pixels whose direct the
fit trusts (a finite amplitude and delay error, none of the flags :data:`UNRELIABLE` that say the
direct's parameters are not determined by the data) with a direct amplitude at least
``LIT_FRACTION`` of the largest such amplitude in the line.  A flagged pixel's standard error
does not measure its delay error (two splits of the light fit equally well, the fit stopped at a
bound, ...), and more frames do not bring it down, so it is left out rather than let it make
every target unreachable; no lit pixel: infinite.  The capture session
(:class:`acquisition.session.CaptureSession`, ``line_good_enough``) stops the line once its
error is at most the target.
"""
from __future__ import annotations

import math

import numpy as np


from decomposition.flags import AMBIGUOUS, AT_BOUND, MAX_ITER, OFF_WINDOW, POOR_FIT, WIDE_PSF

#: A trusted pixel is lit when its direct amplitude is at least this fraction of the line's
#: largest trusted direct amplitude.
LIT_FRACTION = 0.5
#: Flags whose pixels' direct-delay standard errors are not their errors: the fit does not
#: explain the data (POOR_FIT), did not converge (MAX_ITER), ended at a bound of its grid
#: (AT_BOUND, WIDE_PSF), cannot tell the direct from the rest (AMBIGUOUS) or runs off the window.
UNRELIABLE = POOR_FIT | MAX_ITER | AT_BOUND | AMBIGUOUS | WIDE_PSF | OFF_WINDOW


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


def lit_pixels(amplitude, stderr_ps, flags) -> np.ndarray:
    """The pixels whose direct-delay standard error counts in a line's error.

    Parameters
    ----------
    amplitude : ndarray (x,)
        Direct amplitudes of the line's pixels (NaN: no direct).
    stderr_ps : ndarray (x,)
        Their ``direct_delay_ps_stderr``, ps.
    flags : ndarray (x,) of int
        Their decomposition flags.

    Returns
    -------
    ndarray (x,) of bool: trusted (amplitude and standard error finite, no flag of
    :data:`UNRELIABLE`) and bright (amplitude at least ``LIT_FRACTION`` of the largest trusted
    one); all False where no pixel is trusted.
    """
    amp = np.asarray(amplitude, dtype=np.float64)
    se = np.asarray(stderr_ps, dtype=np.float64)
    trusted = np.isfinite(amp) & np.isfinite(se) & ((np.asarray(flags).astype(np.int64) & int(UNRELIABLE)) == 0)
    if not trusted.any():
        return trusted
    return trusted & (amp >= LIT_FRACTION * amp[trusted].max())


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
    float : the largest ``direct_delay_ps_stderr`` over the line's lit pixels (:func:`lit_pixels`),
    ps; ``inf`` where none is lit.
    """
    from decomposition import decompose

    rows = calib.rows(np.asarray(frames)[None])[0]                           # (x, n_bins) float32
    res = decompose(rows, calib.time_bin_ps, t0_ps=calib.t0_ps, stderr=True, nan_policy="omit")
    se = np.asarray(res.params["direct_delay_ps_stderr"], dtype=np.float64)
    lit = lit_pixels(res.params["direct_amplitude"], se, res.flags)
    return float(se[lit].max()) if lit.any() else math.inf


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
