"""The background family ``b``: a constant offset per pixel (the dark level of TCSPC, SPAD
and lidar data).

Two rules live here and nowhere else, for every path that fits a background:

* :func:`estimate_background` -- the first, robust estimate of the offset from the samples
  that sit at the noise level (before any component is known);
* :func:`background_significant` -- whether a fitted offset is significant: the increase of
  the data term when it is removed and the amplitudes are re-fitted (the likelihood-ratio
  statistic for one linear parameter, :func:`background_test`), at least
  ``significance_chi2`` (the same threshold a component must pass,
  :func:`decomposition.components.threshold`).

The joint fit of the offset with the amplitudes is the refinement's
(:func:`decomposition.refine.refine` with ``fit_background``; a constant column of the linear
solve, :mod:`decomposition.varpro`).
"""
from __future__ import annotations

import warnings

import numpy as np

from core.model import BACKGROUND_KEY, render_components
from .constants import BACKGROUND_CLIP_SIGMA, BACKGROUND_ITERATIONS, BACKGROUND_START_QUANTILE
from .noise import noise_sigma

__all__ = ["estimate_background", "background_test", "background_significant"]


def _masked(fn, v, ok):
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # rows without any sample
        out = fn(np.where(ok, v, np.nan), axis=1)
    return out


def estimate_background(values, fit=None, *, counts: bool = False) -> np.ndarray:
    """Robust constant offset of each profile, from the samples at the noise level.

    Components only ever add light, so the samples left at the noise level are the lowest
    ones.  Start at the BACKGROUND_START_QUANTILE quantile of the fitted samples, then
    BACKGROUND_ITERATIONS times take the mean of the samples within BACKGROUND_CLIP_SIGMA
    noise sigmas of the current value (:mod:`decomposition.constants`).  The noise is the
    second-difference estimate of :func:`decomposition.noise.noise_sigma`, for count data
    (``counts``) at least the Poisson sqrt(max(b, 1)) of the current level.  Light of the
    components within the clip (a faint tail) biases the estimate up; the joint fit of the
    refinement removes that.

    Parameters
    ----------
    values : ndarray (P, L)
        Profiles in their own units (counts for count data).
    fit : ndarray (P, L) bool, optional
        Samples to use (default all).
    counts : bool
        The samples are photon counts.

    Returns
    -------
    ndarray (P,), units of ``values``; 0 for a profile without fitted samples.
    """
    v = np.asarray(values, np.float64)
    if v.ndim != 2:
        raise ValueError(f"values must have shape (P, L), got {v.shape}")
    ok = np.isfinite(v) if fit is None else (np.asarray(fit, bool) & np.isfinite(v))
    if ok.shape != v.shape:
        raise ValueError(f"fit must have the shape of values {v.shape}, got {ok.shape}")
    s = noise_sigma(np.where(ok, v, 0.0), ok)
    b = _masked(lambda a, axis: np.nanquantile(a, BACKGROUND_START_QUANTILE, axis=axis), v, ok)
    b = np.where(np.isfinite(b), b, 0.0)
    for _ in range(BACKGROUND_ITERATIONS):
        si = np.maximum(s, np.sqrt(np.maximum(b, 1.0))) if counts else s
        near = ok & (np.abs(v - b[:, None]) <= BACKGROUND_CLIP_SIGMA * si[:, None])
        m = _masked(np.nanmean, v, near)
        b = np.where(np.isfinite(m), m, b)
    return b


def background_test(values, params: dict, weights, noise_sigma_units, *, time_bin_ps: float,
                    t0_ps: float | None = None, irf=None):
    """Likelihood-ratio statistic and standard error of each pixel's fitted offset.

    With the components' nonlinear parameters fixed, the model is linear in the amplitudes
    and the offset b: y ~ A c with A = [unit components..., 1].  Removing b and re-fitting
    the amplitudes raises the weighted data term by b^2 / [(A^T W A)^-1]_bb (in units of the
    noise variance ``noise_sigma_units``^2): the likelihood-ratio statistic of the offset,
    chi-square with one degree of freedom where there is none.

    Parameters
    ----------
    values : ndarray (P, L)
        The profiles (unused but for their shape: the statistic needs only the fitted b).
    params : dict
        P-shaped parameters (keys of :mod:`core.model`) with ``background`` (P,).
    weights : ndarray (P, L)
        Least-squares weights (the fit mask, or 1 / Poisson variance for count data).
    noise_sigma_units : ndarray (P,)
        Noise standard deviation at unit weight, units of the profiles (1 for count data
        weighted by their Poisson variance).
    irf : core.irf.InstrumentResponse, optional
        The components are the response's atoms (the response path of
        :func:`decomposition.decompose`) instead of Gaussians.

    Returns
    -------
    delta_chi2 : ndarray (P,)     0 where the offset is 0 or NaN
    stderr : ndarray (P,)         standard error of b, units of the profiles (NaN where
                                  the design is singular or the pixel has no weight)
    """
    v = np.asarray(values)
    P, L = v.shape
    b = np.asarray(params[BACKGROUND_KEY], np.float64).reshape(P)
    unit = {k: (np.where(np.isfinite(val), 1.0, np.nan) if k.endswith("amplitude") else val)
            for k, val in params.items() if k != BACKGROUND_KEY and not k.endswith("_stderr")}
    with np.errstate(invalid="ignore"):
        comps = render_components(unit, L, time_bin_ps, t0_ps, irf=irf)
    rows = [comps["direct"], comps["sss"]] + [comps["interreflections"][:, j] for j in
                                              range(comps["interreflections"].shape[1])]
    A = np.stack(rows + [np.ones((P, L))], axis=1)                         # (P, K + 1, L)
    A = np.where(np.isfinite(A), A, 0.0)
    w = np.asarray(weights, np.float64)
    G = np.einsum("pkl,pl,pjl->pkj", A, w, A)
    diag = np.einsum("pkk->pk", G)
    absent = ~(diag > 0)
    k = np.arange(G.shape[1])
    G[:, k, k] = np.where(absent, 1.0, diag * (1.0 + 1e-12))
    e_b = np.zeros((P, G.shape[1]))
    e_b[:, -1] = 1.0
    with np.errstate(all="ignore"):
        inv_bb = np.linalg.solve(G, e_b[..., None])[:, -1, 0]
    ok = (inv_bb > 0) & ~absent[:, -1] & np.isfinite(inv_bb)
    s = np.asarray(noise_sigma_units, np.float64).reshape(P)
    with np.errstate(all="ignore"):
        stderr = np.where(ok, s * np.sqrt(np.where(ok, inv_bb, 1.0)), np.nan)
        dchi2 = np.where(ok & np.isfinite(b) & (s > 0), np.nan_to_num(b) ** 2 / np.where(ok, inv_bb, 1.0)
                         / np.where(s > 0, s, 1.0) ** 2, 0.0)
    return dchi2, stderr


def background_significant(delta_chi2, significance_chi2: float) -> np.ndarray:
    """The offset is kept where its likelihood-ratio statistic (:func:`background_test`) is at
    least ``significance_chi2``; (P,) bool."""
    return np.asarray(delta_chi2, np.float64) >= float(significance_chi2)
