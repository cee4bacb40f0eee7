"""The noise estimate: robust per-pixel standard deviation from second differences.

Smooth kernels have tiny second differences; white noise of standard deviation s has
second differences of variance 6 s^2.  So s = MAD_TO_SIGMA * median|d2| / sqrt(6), with the
median over the second differences whose three samples are all fitted.  Two variants:

* :func:`noise_sigma` over the whole profile (the first estimate of every pixel);
* :func:`signal_noise_sigma` over the samples where a fitted model is above
  SIGNAL_REGION_FRACTION of its peak, from the second differences of the *residual*: photon
  noise grows with the signal, so the whole-profile value, dominated by the quiet part of the
  window, is too low there.  Differencing the residual, not the data, leaves no peak
  curvature in it, and a smooth misfit (an offset) is removed by the differencing too.

Both are the only home of this rule in the package.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from .constants import MAD_TO_SIGMA, MIN_NOISE_SAMPLES, SIGNAL_REGION_FRACTION

__all__ = ["noise_sigma", "signal_noise_sigma"]


def _usable(fit: np.ndarray) -> np.ndarray:
    """(P, L - 2) bool: second differences whose three samples are all fitted."""
    return fit[:, 2:] & fit[:, 1:-1] & fit[:, :-2]


def _mad_sigma(d2: np.ndarray, ok: np.ndarray | None) -> np.ndarray:
    """MAD_TO_SIGMA * median over ``ok`` of |d2| / sqrt(6) per row (0 for rows without one)."""
    if ok is None or ok.all():
        med = np.median(d2, axis=1)
    else:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN rows: no usable samples
            med = np.nanmedian(np.where(ok, d2, np.nan), axis=1)
        med = np.where(np.isfinite(med), med, 0.0)
    return MAD_TO_SIGMA * med / math.sqrt(6.0)


def noise_sigma(profiles: np.ndarray, fit: np.ndarray | None = None) -> np.ndarray:
    """Noise standard deviation of each profile, from all its usable second differences.

    Parameters
    ----------
    profiles : ndarray (P, L)
    fit : ndarray (P, L) bool, optional
        Samples that are fitted; second differences touching another sample are ignored.

    Returns
    -------
    ndarray (P,), in the units of ``profiles``; 0 where no second difference is usable.
    """
    p = profiles
    d2 = np.abs(p[:, 2:] - 2.0 * p[:, 1:-1] + p[:, :-2])
    return _mad_sigma(d2, None if fit is None else _usable(fit))


def signal_noise_sigma(residual: np.ndarray, model: np.ndarray, fit: np.ndarray,
                       min_samples: int = MIN_NOISE_SAMPLES) -> np.ndarray:
    """Noise standard deviation where the signal is (see the module docstring).

    Parameters
    ----------
    residual, model : ndarray (P, L)
        Data minus model, and the model.
    fit : ndarray (P, L) bool
        Samples fitted exactly (not excluded, not censored).
    min_samples : int
        Rows with fewer usable second differences in the signal region get 0.

    Returns
    -------
    ndarray (P,), in the units of ``residual``.
    """
    mag = np.abs(model)
    region = mag >= SIGNAL_REGION_FRACTION * mag.max(axis=1, keepdims=True)
    r = residual
    d2 = np.abs(r[:, 2:] - 2.0 * r[:, 1:-1] + r[:, :-2])
    ok = region[:, 1:-1] & _usable(fit)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.where(ok, d2, np.nan), axis=1)
    med = np.where(np.isfinite(med) & (ok.sum(axis=1) >= min_samples), med, 0.0)
    return MAD_TO_SIGMA * med / math.sqrt(6.0)
