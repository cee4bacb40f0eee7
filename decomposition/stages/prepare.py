"""The ``prepare`` stage of :func:`decomposition.decompose`: prepare the samples.

Input check, per-pixel normalisation to unit peak, the masks of the samples that are fitted
and of those that are censored (saturated), the noise model (Gaussian, or Poisson for photon
counts), single-sample spikes (tested in the noise model's own terms), and the noise estimate.
Nothing here depends on the solver; every later stage reads the :class:`Samples` it returns.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from statistics import NormalDist

from ..constants import DICT_SUPPORT_SIGMA, SIGNIFICANCE_LAG_BINS, SPIKE_FALSE_ALARM
from ..masks import SampleMask
from ..flags import EMPTY, FLAG_DTYPE, NONFINITE, SATURATED, SPIKE, mark
from .background import estimate_background
from ..noise import (anscombe, count_dispersion, count_signal_sigma, lagged_noise_sigma, noise_sigma,
                     resolve_noise_model)
from ..options import GridSpec, parse_nan_policy

__all__ = ["Samples", "TimeAxis", "prepare_samples", "time_axis", "find_spikes", "find_count_spikes",
           "min_neighbour_ratio"]


@dataclass(frozen=True)
class TimeAxis:
    """Bin i at ``t0_ps + i * time_bin_ps`` (ps)."""

    time_bin_ps: float
    t0_ps: float


def time_axis(time_bin_ps, t0_ps=None) -> TimeAxis:
    """Validated time axis; ``t0_ps`` defaults to one bin (the paper's t = T..LT)."""
    T = float(time_bin_ps) if np.isscalar(time_bin_ps) else np.nan
    if not (np.isfinite(T) and T > 0):
        raise ValueError(f"time_bin_ps must be a positive finite number, got {time_bin_ps!r}")
    t0 = T if t0_ps is None else float(t0_ps)
    if not np.isfinite(t0):
        raise ValueError(f"t0_ps must be finite, got {t0_ps!r}")
    return TimeAxis(T, t0)


@dataclass(frozen=True)
class Samples:
    """Profiles ready for the solver, flattened to P pixels of L samples.

    Attributes
    ----------
    values : ndarray (P, L) float64     the input samples
    profiles : ndarray (P, L) float64   values / scale on fitted samples, 0 elsewhere
    scale : ndarray (P,)                peak magnitude over the fitted samples (0: empty)
    fit : ndarray (P, L) bool           samples fitted (finite, not saturated, not a spike)
    censored : ndarray (P, L) bool      saturated samples: the true value is at least this
    finite : ndarray (P,) bool          pixels without NaN/inf samples
    live : ndarray (n,) int             pixels to decompose (finite, not empty)
    noise : ndarray (P,)                whole-profile noise estimate of ``profiles`` (before
                                        spikes were removed)
    noise_eff : ndarray (P,)            the noise the solver uses: after spike removal,
                                        floored at ``noise_floor``
    lagged_noise : ndarray (P,)         noise across SIGNIFICANCE_LAG_BINS samples
                                        (:func:`decomposition.noise.lagged_noise_sigma`; correlated
                                        noise makes component-sized bumps), 0 for pixels not
                                        decomposed; see :meth:`significance_sigma`
    flags : ndarray (P,) uint16         NONFINITE, SATURATED, SPIKE, EMPTY as found here
    lead : tuple                        leading shape of the input
    axis : TimeAxis
    saturation_level : float or None
    noise_model : {"gaussian", "poisson"}    resolved (``"auto"`` decided by the count rule)
    dispersion : ndarray (P,) or None      count data: noise std in the Anscombe domain (>= 1)
    background : ndarray (P,) or None      the background family: the first estimate of each
                                        pixel's constant offset, units of ``values``
                                        (:func:`decomposition.stages.background.estimate_background`),
                                        already subtracted from ``profiles``; None without it
    """

    values: np.ndarray
    profiles: np.ndarray
    scale: np.ndarray
    fit: np.ndarray
    censored: np.ndarray
    finite: np.ndarray
    live: np.ndarray
    noise: np.ndarray
    noise_eff: np.ndarray
    lagged_noise: np.ndarray
    flags: np.ndarray
    lead: tuple
    axis: TimeAxis
    saturation_level: float | None
    noise_model: str = "gaussian"
    dispersion: np.ndarray | None = None
    background: np.ndarray | None = None

    @property
    def n_bins(self) -> int:
        return self.values.shape[1]

    @property
    def mask(self) -> SampleMask:
        """The fit and censored masks (:class:`~decomposition.masks.SampleMask`)."""
        return SampleMask(self.fit, self.censored)

    def significance_sigma(self, rows, noise, lagged_noise=None) -> np.ndarray:
        """(n,) the noise the in-window significance test weighs an atom's energy with, for the
        pixels ``rows`` whose solver noise is ``noise`` (n,): the larger of the two noises
        (``lagged_noise`` (P,): another estimate of the lagged noise in place of this one's)."""
        lagged = self.lagged_noise if lagged_noise is None else lagged_noise
        return np.maximum(noise, lagged[rows])

    @property
    def weights(self) -> np.ndarray:
        """(P, L) float64 least-squares weights: 1 on fitted samples, 0 elsewhere."""
        return self.fit.astype(np.float64)


def _as_profiles(profiles):
    arr = np.asarray(profiles)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
                                   or arr.dtype == np.bool_):
        raise ValueError(f"profiles must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim == 0:
        raise ValueError("profiles must have at least one dimension (..., L); got a 0-d scalar")
    return arr


def check_window(n_bins: int, axis: TimeAxis, grid: GridSpec) -> None:
    """Refuse windows shorter than the widest dictionary kernel."""
    T = axis.time_bin_ps
    min_bins = max(8, int(math.ceil(DICT_SUPPORT_SIGMA * grid.sigma_range_ps[1] / T)) + 1)
    if n_bins < min_bins:
        raise ValueError(
            f"profiles have L={n_bins} time bins; the kernels need at least {min_bins} "
            f"({DICT_SUPPORT_SIGMA:g} x sigma_max {grid.sigma_range_ps[1]:g} ps / time_bin_ps {T:g} ps + 1)")


def prepare_samples(profiles, axis: TimeAxis, grid: GridSpec, *, nan_policy: str = "raise",
                    saturation_level: float | None = None, spike_sigma: float = 8.0,
                    noise_floor: float = 1e-3, rel_threshold: float = 0.05,
                    noise: str = "gaussian", background: bool = False,
                    spike_neighbour_ratio: float | None = None) -> Samples:
    """Validate, mask and normalise profiles (..., L); estimate their noise.

    Parameters
    ----------
    profiles : array_like (..., L), any real dtype
    axis : TimeAxis
    grid : GridSpec
        For the shortest window and the narrowest kernel (spike test, unless
        ``spike_neighbour_ratio`` is given).
    nan_policy : {"raise", "omit"}
    saturation_level : float, optional
        Samples >= this are censored.  Default: the dtype maximum for integer input.
    spike_sigma : float
        Spike threshold in noise sigmas (0: no spike test).
    noise_floor : float
        Floor of the noise estimate relative to the pixel's peak.
    rel_threshold : float
        Spikes below this fraction of the peak are left alone (see :func:`find_spikes`).
    noise : {"gaussian", "poisson", "auto"}
        Noise model.  "poisson": the samples are counts; spikes are tested against the
        counting statistics (:func:`find_count_spikes`, ``spike_sigma`` only switches the
        test on or off) and the solver's noise is the Poisson noise at the signal.  "auto":
        "poisson" for count data (:func:`resolve_noise_model`).
    background : bool
        The background family: estimate each pixel's constant offset
        (:func:`decomposition.stages.background.estimate_background`, on the finite unsaturated
        samples) and subtract it from the normalised ``profiles`` the solver sees
        (``values`` keep it; counting statistics use the raw counts).
    spike_neighbour_ratio : float, optional
        The smallest ratio of a real component's larger neighbour sample to the sample itself,
        in (0, 1] (:func:`min_neighbour_ratio`); default that of a centred Gaussian of the
        grid's narrowest sigma.  With a measured response the response's own
        (:func:`decomposition.response.resolve.spike_neighbour_ratio`).
    """
    nan_policy = parse_nan_policy(nan_policy)
    arr = _as_profiles(profiles)
    lead, L = arr.shape[:-1], arr.shape[-1]
    check_window(L, axis, grid)
    P = int(np.prod(lead, dtype=np.int64))
    raw = arr.reshape(P, L)
    if saturation_level is None and np.issubdtype(arr.dtype, np.integer):
        saturation_level = float(np.iinfo(arr.dtype).max)
    noise_model = resolve_noise_model(noise, raw)
    x = raw.astype(np.float64)

    flags = np.zeros(P, FLAG_DTYPE)
    finite = np.isfinite(x).all(axis=1)
    n_bad = int(P - finite.sum())
    if n_bad and nan_policy == "raise":
        raise ValueError(f"profiles contain NaN or inf samples in {n_bad} of {P} pixels "
                         f"(use nan_policy='omit' to flag and skip them)")
    mark(flags, ~finite, NONFINITE)

    fit = np.ones((P, L), bool)
    sat = np.zeros((P, L), bool)
    if saturation_level is not None:
        sat = x >= float(saturation_level)
        fit[sat] = False
        mark(flags, sat.any(axis=1), SATURATED)
    fit[~finite] = False
    b_est = None
    if background:
        b_est = np.zeros(P)
        if finite.any():
            b_est[finite] = estimate_background(x[finite], fit[finite], counts=noise_model == "poisson")
    xb = x if b_est is None else x - b_est[:, None]      # what the components must explain
    xs = np.where(fit, xb, 0.0)
    scale = np.abs(xs).max(axis=1)
    live = finite & (scale > 0)
    mark(flags, finite & ~(scale > 0), EMPTY)

    idx_live = np.nonzero(live)[0]
    pn = np.zeros((P, L))
    pn[idx_live] = xs[idx_live] / scale[idx_live, None]
    s_est = np.zeros(P)
    if idx_live.size:
        s_est[idx_live] = noise_sigma(pn[idx_live], fit[idx_live])
    s_eff = np.maximum(s_est, noise_floor)

    counts = noise_model == "poisson"
    disp = np.ones(P) if counts else None
    raw = np.where(fit, x, 0.0) if counts else None     # counting statistics see the raw counts
    if counts and idx_live.size:
        disp[idx_live] = count_dispersion(raw[idx_live], fit[idx_live])
    if spike_sigma and idx_live.size:
        if counts:
            sp = find_count_spikes(raw[idx_live], fit[idx_live], axis.time_bin_ps, grid.sigma_range_ps[0],
                                   disp[idx_live], min_rel=rel_threshold, neighbour_ratio=spike_neighbour_ratio)
        else:
            sp = find_spikes(pn[idx_live], fit[idx_live], s_eff[idx_live], axis.time_bin_ps, grid.sigma_range_ps[0],
                             spike_sigma, rel_threshold, neighbour_ratio=spike_neighbour_ratio)
        hit = idx_live[sp.any(axis=1)]
        mark(flags, hit, SPIKE)
        fit[idx_live] = fit[idx_live] & ~sp
        # re-normalise without the spikes (a pixel without one keeps its samples, scale and noise)
        xs[hit] = np.where(fit[hit], xb[hit], 0.0)
        scale[hit] = np.abs(xs[hit]).max(axis=1)
        ok = scale[hit] > 0
        mark(flags, hit[~ok], EMPTY)
        idx_live = np.setdiff1d(idx_live, hit[~ok], assume_unique=True)
        hit = hit[ok]
        pn[hit] = xs[hit] / scale[hit, None]
        s_eff[hit] = np.maximum(noise_sigma(pn[hit], fit[hit]), noise_floor)
    if counts and idx_live.size:
        # the noise the solver weighs its sparsity with is the noise at the components
        s_sig = count_signal_sigma(np.where(fit, x, 0.0)[idx_live], fit[idx_live], scale[idx_live], disp[idx_live])
        s_eff[idx_live] = np.maximum(s_eff[idx_live], s_sig)
    s_lag = np.zeros(P)
    if idx_live.size:
        lag = min(SIGNIFICANCE_LAG_BINS, max(1, L // 4))
        s_lag[idx_live] = lagged_noise_sigma(pn[idx_live], fit[idx_live], lag)
    return Samples(values=x, profiles=pn, scale=scale, fit=fit, censored=sat, finite=finite, live=idx_live,
                   noise=s_est, noise_eff=s_eff, lagged_noise=s_lag, flags=flags, lead=lead, axis=axis,
                   saturation_level=saturation_level, noise_model=noise_model, dispersion=disp,
                   background=b_est)


def min_neighbour_ratio(time_bin_ps: float, sigma_min_ps: float, given: float | None = None) -> float:
    """r_min of the spike tests: the smallest ratio of a real component's larger neighbour to a
    sample -- exp(-T^2 / (2 sigma_min^2)) for Gaussians of sigma >= sigma_min (the neighbours of
    a centred peak), or ``given`` (another kernel's, e.g. a measured response's), in (0, 1]."""
    if given is None:
        return math.exp(-0.5 * (time_bin_ps / sigma_min_ps) ** 2)
    r = float(given)
    if not (0.0 < r <= 1.0):
        raise ValueError(f"the spike test's neighbour ratio must lie in (0, 1], got {given!r}")
    return r


def find_spikes(profiles, fit, noise, time_bin_ps, sigma_min_ps, k_sigma, min_rel=0.05, *, neighbour_ratio=None):
    """Single-sample spikes: too narrow for the narrowest kernel and far above the noise.

    A component with sigma >= sigma_min has neighbours at least
    r_min = exp(-T^2 / (2 sigma_min^2)) of a centred peak (``neighbour_ratio``: another
    kernel's r_min, :func:`min_neighbour_ratio`); a sample whose larger
    neighbour is below half of that (plus a noise margin) and which exceeds
    both neighbours by ``k_sigma`` noise sigmas is a spike.  The half keeps the rule true for
    any sum of such components with non-negative amplitudes: the larger of two sums of
    neighbours is at least half their total.

    Parameters
    ----------
    profiles : ndarray (P, L)     normalised profiles
    fit : ndarray (P, L) bool     fitted samples (only those can be spikes)
    noise : ndarray (P,)          noise sigma, units of ``profiles``
    time_bin_ps, sigma_min_ps : float
    k_sigma : float
    min_rel : float
        Spikes must also exceed this fraction of the pixel's peak: a smaller one could never
        become a reported component (and isolated counts of photon-limited data are no spikes).
    neighbour_ratio : float, optional
        r_min in place of the Gaussian's (``sigma_min_ps`` is then not used).

    Returns
    -------
    ndarray (P, L) bool
    """
    pn, s, T = profiles, noise, time_bin_ps
    P, L = pn.shape
    out = np.zeros((P, L), bool)
    if L < 3:
        return out
    r_min = min_neighbour_ratio(T, sigma_min_ps, neighbour_ratio)
    c = pn[:, 1:-1]
    nb = np.maximum(pn[:, :-2], pn[:, 2:])
    big = np.maximum(k_sigma * s[:, None], min_rel * np.abs(pn).max(axis=1, keepdims=True))
    sp = (c - nb > big) & (nb < 0.5 * r_min * c + 3.0 * s[:, None]) & fit[:, 1:-1]
    out[:, 1:-1] = sp
    return out


def _count_threshold(n_bins: int) -> float:
    """Per-sample threshold (standard deviations) for SPIKE_FALSE_ALARM per profile of n_bins."""
    return NormalDist().inv_cdf(1.0 - SPIKE_FALSE_ALARM / max(n_bins - 2, 1))


def find_count_spikes(counts, fit, time_bin_ps, sigma_min_ps, dispersion=None, min_rel=0.05, *,
                      neighbour_ratio=None):
    """Single-sample spikes of count profiles, tested against the counting statistics.

    The rule of :func:`find_spikes` in Poisson terms, on the variance-stabilised profile
    a = 2 sqrt(x + 3/8) (:func:`decomposition.noise.anscombe`; variance ~1 per sample, the
    ``dispersion`` squared where larger).  With c the sample, n the larger neighbour and
    r = exp(-T^2 / (2 sigma_min^2)) the smallest neighbour-to-peak ratio a real component has
    (``neighbour_ratio`` when given, :func:`min_neighbour_ratio`),
    a sample is a spike when both

    * it is significantly above the neighbour: a(c) - a(n) > z sqrt(2) dispersion, and
    * the neighbour is significantly below what the narrowest kernel would leave there:
      a(r c) - a(n) > z sqrt(1 + r) dispersion (a(r c) has variance ~r),

    and c - n exceeds ``min_rel`` of the pixel's peak, as for Gaussian data.  z is the normal
    quantile for the false-alarm rate SPIKE_FALSE_ALARM per profile
    (:mod:`decomposition.constants`), whatever the count level: a profile without spikes is
    flagged with about that probability.

    Parameters
    ----------
    counts : ndarray (P, L)       counts (0 on samples that are not fitted)
    fit : ndarray (P, L) bool     fitted samples (only those can be spikes)
    time_bin_ps, sigma_min_ps : float
    dispersion : ndarray (P,), optional
        Noise std in the Anscombe domain (default 1, pure Poisson).
    min_rel : float
    neighbour_ratio : float, optional
        r in place of the Gaussian's (``sigma_min_ps`` is then not used).

    Returns
    -------
    ndarray (P, L) bool
    """
    x = np.asarray(counts, np.float64)
    P, L = x.shape
    out = np.zeros((P, L), bool)
    if L < 3:
        return out
    disp = np.ones(P) if dispersion is None else np.asarray(dispersion, np.float64)
    r_min = min_neighbour_ratio(time_bin_ps, sigma_min_ps, neighbour_ratio)
    z = _count_threshold(L) * disp[:, None]
    c = x[:, 1:-1]
    nb = np.maximum(x[:, :-2], x[:, 2:])
    a_c, a_nb, a_rc = anscombe(c), anscombe(nb), anscombe(r_min * c)
    above = a_c - a_nb > z * math.sqrt(2.0)
    narrow = a_rc - a_nb > z * math.sqrt(1.0 + r_min)
    big = c - nb > min_rel * np.abs(x).max(axis=1, keepdims=True)
    out[:, 1:-1] = above & narrow & big & fit[:, 1:-1]
    return out
