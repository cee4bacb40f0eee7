"""The background family ``b``: a constant offset per pixel (the dark level of TCSPC, SPAD
and lidar data).

Three rules live here and nowhere else, for every path that fits a background:

* :func:`estimate_background` -- the first, robust estimate of the offset from the samples
  that sit at the noise level (before any component is known);
* :func:`background_significant` -- whether a fitted offset is significant: the increase of
  the data term when it is removed and the amplitudes are re-fitted (the likelihood-ratio
  statistic for one linear parameter, :func:`background_test`), at least the threshold of
  :func:`background_threshold` (``background_chi2``; by default ln(n) of the pixel's n
  fitted samples, the information criterion's price of one parameter);
* :func:`light_test` -- whether a pixel holds any light above its offset at all: the increase
  of the data term when every component is removed and the offset alone re-fitted, which
  ``decompose`` requires to be at least ``significance_chi2`` (an atom's own price) before it
  reports a component on a background.

The joint fit of the offset with the amplitudes is the refinement's
(:func:`decomposition.model.refine.refine` with ``fit_background``; a constant column of the linear
solve, :mod:`decomposition.model.varpro`).
"""
from __future__ import annotations

import warnings

import numpy as np

from core.model import BACKGROUND_KEY, render_components
from ..constants import (BACKGROUND_CLIP_SIGMA, BACKGROUND_COUNT_WINDOW_BINS, BACKGROUND_ITERATIONS,
                         BACKGROUND_START_QUANTILE)
from ..noise import count_deviance, noise_sigma
from .selection import log_samples

__all__ = ["estimate_background", "background_test", "background_threshold", "background_significant", "offset_alone",
           "light_test"]


def _masked(fn, v, ok):
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # rows without any sample
        out = fn(np.where(ok, v, np.nan), axis=1)
    return out


def estimate_background(values, fit=None, *, counts: bool = False) -> np.ndarray:
    """Robust constant offset of each profile, from the samples at the noise level.

    Components only ever add light, so the samples left at the noise level are the lowest
    ones.  Start at the BACKGROUND_START_QUANTILE quantile, then BACKGROUND_ITERATIONS times
    take the mean of the samples at the current level, within BACKGROUND_CLIP_SIGMA noise
    sigmas of it (:mod:`decomposition.constants`):

    * profiles in their own units: each sample against the noise of one sample, the
      second-difference estimate of :func:`decomposition.noise.noise_sigma`;
    * count data (``counts``): the mean count m_i of the BACKGROUND_COUNT_WINDOW_BINS fitted
      samples centred on each sample against the Poisson noise of such a mean,
      sqrt(max(b, 1 / n_i) / n_i) for n_i samples (the floor keeps one count in the window
      distinguishable from none at b = 0).  Below a few counts per bin one sample's Poisson
      noise is as large as a faint component's level, so the per-sample clip would take the
      whole of a faint sss tail for background (at 100 photons per pixel that nearly doubled
      an offset of 0.2 counts per bin and put 0.2 counts per bin where there was none).

    Light of the components within the clip (a faint tail) still biases the estimate up a
    little; the joint fit of the refinement removes that.

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
    if counts:
        level, n_level = _local_mean(np.where(ok, v, 0.0), ok, BACKGROUND_COUNT_WINDOW_BINS)
        ok = ok & (n_level > 0)
    else:
        level = v
        s = noise_sigma(np.where(ok, v, 0.0), ok)
    b = _masked(lambda a, axis: np.nanquantile(a, BACKGROUND_START_QUANTILE, axis=axis), level, ok)
    b = np.where(np.isfinite(b), b, 0.0)
    for _ in range(BACKGROUND_ITERATIONS):
        if counts:
            n = np.maximum(n_level, 1)
            clip = BACKGROUND_CLIP_SIGMA * np.sqrt(np.maximum(b[:, None], 1.0 / n) / n)
        else:
            clip = BACKGROUND_CLIP_SIGMA * s[:, None]
        near = ok & (np.abs(level - b[:, None]) <= clip)
        m = _masked(np.nanmean, v, near)
        b = np.where(np.isfinite(m), m, b)
    return b


def _local_mean(v, ok, width: int):
    """Mean of the ``ok`` samples of ``v`` (P, L) in the ``width`` bins centred on each sample
    (fewer at the ends), and their number; both (P, L), the mean 0 where there are none."""
    P, L = v.shape
    half = width // 2
    c_v = np.concatenate([np.zeros((P, 1)), np.cumsum(np.where(ok, v, 0.0), axis=1)], axis=1)
    c_n = np.concatenate([np.zeros((P, 1), np.int64), np.cumsum(ok, axis=1)], axis=1)
    i = np.arange(L)
    lo, hi = np.maximum(i - half, 0), np.minimum(i - half + width, L)
    n = c_n[:, hi] - c_n[:, lo]
    total = c_v[:, hi] - c_v[:, lo]
    return np.where(n > 0, total / np.maximum(n, 1), 0.0), n


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


def background_threshold(fit, background_chi2: float | None = None) -> np.ndarray:
    """(P,) threshold of each pixel's offset statistic (:func:`background_test`).

    ``background_chi2`` itself where given; by default (None) ln(n) for a pixel of n fitted
    samples (``fit`` (P, L) bool), the Bayesian information criterion's price of one more
    parameter: the offset is kept when it raises the log-likelihood by more than ln(n) / 2.
    A family the user asked for is one parameter to judge, not a detection among many
    candidates (the 5-sigma energy ``significance_chi2`` of an atom): left out where it is
    present, the sss absorbs it (a lifetime biased by tens of %), kept where it is absent, it
    only widens the other errors a little.  For 256 samples ln(n) = 5.5; a pixel without an
    offset then keeps one with probability P(chi2_1 >= 5.5) = 1.9 %.
    """
    n = np.asarray(fit, bool).sum(axis=-1)
    if background_chi2 is not None:
        return np.full(n.shape, float(background_chi2))
    return log_samples(n).astype(np.float64)


def background_significant(delta_chi2, threshold) -> np.ndarray:
    """The offset is kept where its likelihood-ratio statistic (:func:`background_test`) is at
    least ``threshold`` (a number or (P,), :func:`background_threshold`); (P,) bool."""
    return np.asarray(delta_chi2, np.float64) >= np.asarray(threshold, np.float64)


def offset_alone(values, fit) -> np.ndarray:
    """(P,) the best offset of a model that is nothing but an offset: the mean of each row's
    fitted samples (``fit`` (P, L) bool), for least squares and the Poisson likelihood alike;
    NaN for a row without one."""
    return _masked(np.nanmean, np.asarray(values, np.float64), np.asarray(fit, bool))


def light_test(values, model, fit, *, counts: bool, noise=None, dispersion=None) -> np.ndarray:
    """(P,) likelihood-ratio statistic of all of a pixel's components against its offset alone.

    The data term of the offset alone (its best value: the mean of the fitted samples, for
    least squares as for the Poisson likelihood) less that of ``model`` -- the components and
    the offset fitted with them.  On a pure background every component is fitted noise, and the
    statistic is that of noise: a pixel whose light does not raise it to ``significance_chi2``
    holds nothing above its offset.  (At 5 counts per bin and no signal, the largest atom --
    always kept by the relative threshold, being the largest -- was a "direct" of 1-2 bins in
    more than half the pixels, unflagged.)

    Parameters
    ----------
    values, model : ndarray (P, L)
        Data and full model (components plus offset), same units.
    fit : ndarray (P, L) bool
        Samples that count.
    counts : bool
        Photon counts: Poisson deviances (:func:`decomposition.noise.count_deviance`, over the
        squared ``dispersion`` (P,)); else sums of squares over ``noise`` (P,)^2.
    """
    v = np.asarray(values, np.float64)
    ok = np.asarray(fit, bool)
    flat = np.broadcast_to(offset_alone(v, ok)[:, None], v.shape)
    if counts:
        return count_deviance(v, flat, ok, dispersion) - count_deviance(v, model, ok, dispersion)
    s2 = np.asarray(noise, np.float64) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        rss0 = np.where(ok, (v - flat) ** 2, 0.0).sum(axis=1)
        rss = np.where(ok, (v - np.nan_to_num(model)) ** 2, 0.0).sum(axis=1)
        return np.where(s2 > 0, (rss0 - rss) / s2, np.inf)
