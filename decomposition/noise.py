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

Photon noise on float data (the Gaussian noise model) also has a law, variance = floor +
gain * signal, but of unknown scale: :func:`signal_variance` fits it to a fitted profile's
residual (the stages after the detection weigh their samples with it where it is
significant; :func:`decomposition.stages.candidates.signal_weights`).

Count data (``noise="poisson"``, photon counting) have a known noise law instead: the
variance of a sample is its expected count.  :func:`is_count_data` is the rule that
``noise="auto"`` applies to recognise them, :func:`anscombe` stabilises their variance to ~1
(the spike test works there), :func:`count_dispersion` measures the noise in that domain (1
for pure Poisson counts, more with read noise or a gain above one count per unit),
:func:`count_signal_sigma` gives the noise at the signal of a normalised count profile,
:func:`poisson_weights` the least-squares weights 1 / variance for a model,
:func:`fit_dispersion` the noise scale of a fitted count profile (the standard errors' one),
:func:`poisson_deviance` / :func:`count_deviance` the likelihood-ratio statistic of a model
(the one home of the deviance), :func:`removal_deviance` each atom's share of it, :func:`atom_gain` what one more atom would
remove, and
:func:`anscombe_residual` the residual in noise sigmas where the counts are.
"""

# One module over 600 lines on purpose: it is the one home of every noise estimate of the package
# (whole profile, at the signal, lagged, count data, the variance laws of noise that follows the
# signal), so that a rule about the noise is written once.
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .constants import (MAD_TO_SIGMA, MIN_NOISE_SAMPLES, PEARSON_MIN_COUNTS, POISSON_VARIANCE_FLOOR,
                        SIGNAL_REGION_FRACTION)
from .kernels.countlm import deviance_row
from .kernels.jit import njit
from .options import parse_noise_model

#: bisection steps of :func:`atom_gain` (the amplitude to 2^-40 of its bracket)
ATOM_GAIN_BISECTIONS = 40

__all__ = ["masked_median", "noise_sigma", "lagged_noise_sigma", "SpectralNoise", "periodogram", "residual_spectrum",
           "whitened_chi2", "signal_noise_sigma", "is_count_data", "resolve_noise_model", "anscombe",
           "count_dispersion", "count_signal_sigma", "poisson_weights", "fit_dispersion", "poisson_deviance",
           "count_deviance", "removal_deviance", "atom_gain", "anscombe_residual"]


def _usable(fit: np.ndarray) -> np.ndarray:
    """(P, L - 2) bool: second differences whose three samples are all fitted."""
    return fit[:, 2:] & fit[:, 1:-1] & fit[:, :-2]


@njit
def _select_in_place(a, m, k):
    """Reorder ``a[:m]`` (no NaN) so that ``a[k]`` is its k-th smallest value, every value before
    it no larger and every one after it no smaller (quickselect, median-of-three pivots) -> a[k]."""
    lo, hi = 0, m - 1
    while hi > lo:
        mid = (lo + hi) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@njit
def _median_of_first(buf, m):
    """Median of ``buf[:m]`` by selection in place (the middle value, or the mean of the two
    middle ones, as ``np.median``); NaN for m = 0.  ``buf[:m]`` is reordered."""
    if m == 0:
        return np.nan
    k = m // 2
    hi = _select_in_place(buf, m, k)
    lo = hi
    if m % 2 == 0:
        lo = buf[0]
        for j in range(1, k):
            lo = max(lo, buf[j])
    return (lo + hi) / 2.0


@njit
def _masked_medians(values, ok, out):
    P, N = values.shape
    buf = np.empty(N)
    for i in range(P):
        m = 0
        for j in range(N):
            v = values[i, j]
            if ok[i, j] and not math.isnan(v):
                buf[m] = v
                m += 1
        out[i] = _median_of_first(buf, m)


def masked_median(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Median of each row of ``values`` (P, N) over its entries where ``ok`` (P, N) is True.

    The value ``np.nanmedian`` gives for the row with every other entry (and every NaN) set to
    NaN -- the middle sample, or the mean of the two middle ones -- by a compiled selection per
    row (no sort, and none of the masked arrays ``np.nanmedian`` builds along an axis).

    Returns
    -------
    ndarray (P,), NaN for rows without an entry.
    """
    values = np.ascontiguousarray(values, np.float64)
    out = np.empty(values.shape[0])
    if values.shape[0]:
        _masked_medians(values, np.ascontiguousarray(ok, np.bool_), out)
    return out


def _d2_sigma(med: np.ndarray) -> np.ndarray:
    """The noise sigma of white noise whose |second differences| have the median ``med``
    (a second difference has variance 6 sigma^2)."""
    return MAD_TO_SIGMA * med / math.sqrt(6.0)


def _mad_sigma(d2: np.ndarray, ok: np.ndarray | None) -> np.ndarray:
    """MAD_TO_SIGMA * median over ``ok`` of |d2| / sqrt(6) per row (0 for rows without one)."""
    if ok is None or ok.all():
        med = np.median(d2, axis=1)
    else:
        med = masked_median(d2, ok)
        med = np.where(np.isfinite(med), med, 0.0)
    return _d2_sigma(med)


def noise_sigma(profiles: np.ndarray, fit: np.ndarray | None = None, order: int = 2) -> np.ndarray:
    """Noise standard deviation of each profile, from all its usable differences of ``order``.

    Parameters
    ----------
    profiles : ndarray (P, L)
    fit : ndarray (P, L) bool, optional
        Samples that are fitted; differences touching another sample are ignored.
    order : {2, 1}
        2 (the solver's estimate): the MAD of the second differences, over sqrt(6); a smooth
        kernel's curvature barely moves them.  1: the MAD of the first differences about their
        median (which takes out a constant slope), over sqrt(2): the estimate of
        :func:`decomposition.stages.search.structured_search`.  Both give sigma for white noise.

    Returns
    -------
    ndarray (P,), in the units of ``profiles``; 0 where no difference is usable.
    """
    p = profiles
    if order == 1:
        d = np.diff(p, axis=-1)
        if fit is None:
            return MAD_TO_SIGMA * np.median(np.abs(d - np.median(d, axis=-1, keepdims=True)), axis=-1) / np.sqrt(2.0)
        ok = fit[:, 1:] & fit[:, :-1]
        centre = masked_median(d, ok)
        sigma = MAD_TO_SIGMA * masked_median(np.abs(d - centre[:, None]), ok) / np.sqrt(2.0)
        return np.where(np.isfinite(sigma), sigma, 0.0)
    if order != 2:
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    d2 = np.abs(p[:, 2:] - 2.0 * p[:, 1:-1] + p[:, :-2])
    return _mad_sigma(d2, None if fit is None else _usable(fit))


@dataclass(frozen=True)
class SpectralNoise:
    """Correlated noise: the call's ``spectrum`` (L // 2 + 1,) per unit variance
    (:func:`residual_spectrum`; :attr:`decomposition.stages.detect.Detection.noise_spectrum`) and each
    pixel's ``variance`` (n,).  A data term in it is the residual whitened by the spectrum
    (:func:`whitened_chi2`, :func:`decomposition.stages.selection.penalised_objective`)."""

    spectrum: np.ndarray
    variance: np.ndarray


def periodogram(rows: np.ndarray) -> np.ndarray:
    """|rfft|^2 of each row of ``rows`` (P, L) -> (P, L // 2 + 1)."""
    return np.abs(np.fft.rfft(np.asarray(rows, np.float64), axis=1)) ** 2


def residual_spectrum(residual: np.ndarray | None = None, *, power: np.ndarray | None = None) -> np.ndarray:
    """The power spectrum shared by the rows of ``residual`` (P, L), per unit of their variance:
    (L // 2 + 1,), the median over the rows of |rfft|^2 divided by ln 2 (the mean of an
    exponentially distributed periodogram value is its median / ln 2; the median ignores the
    rows where a misfit adds power), floored at 1e-12 of its largest value.  White noise of
    variance 1 gives L at every frequency; a whitened data term is then
    sum_f c_f |R_f|^2 / S_f, c_f = 1 at 0 and L/2 and 2 elsewhere (:func:`whitened_chi2`).
    ``power`` (P, L // 2 + 1): the rows' :func:`periodogram` instead of the residual.
    """
    if (residual is None) == (power is None):
        raise ValueError("residual_spectrum takes the residual or its periodogram, one of them")
    p = periodogram(residual) if power is None else np.asarray(power, np.float64)
    s = np.median(p, axis=0) / math.log(2.0)
    return np.maximum(s, 1e-12 * max(float(s.max()), 1e-300))


def whitened_chi2(residual: np.ndarray, spectrum: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """(P,) the data term of rows ``residual`` (P, L) in noise of power ``spectrum`` per unit
    variance (:func:`residual_spectrum`) scaled by each row's ``variance`` (P,): the sum of
    squares of the residual whitened by that spectrum, whose expectation is L for such noise."""
    r = np.asarray(residual, np.float64)
    power = periodogram(r)
    c = np.full(power.shape[1], 2.0)
    c[0] = 1.0
    if r.shape[1] % 2 == 0:
        c[-1] = 1.0
    return power @ (c / np.asarray(spectrum, np.float64)) / np.asarray(variance, np.float64)


def lagged_noise_sigma(profiles: np.ndarray, fit: np.ndarray | None = None, lag_bins: int = 4) -> np.ndarray:
    """Noise standard deviation of each profile at a scale of ``lag_bins`` samples.

    MAD of the differences p[i + lag] - p[i], over sqrt(2) (for white noise the same sigma as
    :func:`noise_sigma`).  Correlated noise (pink: most of its power at low frequencies) is
    underestimated by second differences, which see only its high frequencies; across a lag
    of a few samples, the scale of a component, these differences see what a component-sized
    bump of noise looks like.  The signal's own slopes raise it a little where the components
    cover much of the window (the median is robust to the rest).

    Parameters
    ----------
    profiles : ndarray (P, L)
    fit : ndarray (P, L) bool, optional
        Samples that are fitted; differences touching another sample are ignored.
    lag_bins : int
        The lag, >= 1.

    Returns
    -------
    ndarray (P,), in the units of ``profiles``; 0 where no difference is usable.
    """
    lag = int(lag_bins)
    if lag < 1:
        raise ValueError(f"lag_bins must be >= 1, got {lag_bins!r}")
    if profiles.shape[1] <= lag:
        return np.zeros(profiles.shape[0])
    d = np.abs(profiles[:, lag:] - profiles[:, :-lag])
    ok = None if fit is None else fit[:, lag:] & fit[:, :-lag]
    # _mad_sigma divides by sqrt(6), the scale of a second difference; a first difference has sqrt(2)
    return _mad_sigma(d, ok) * math.sqrt(3.0)


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
    r = np.ascontiguousarray(residual, np.float64)
    P = r.shape[0]
    med = np.empty(P)
    n_ok = np.zeros(P, np.int64)
    if P and r.shape[1] > 2:
        _signal_d2_medians(r, np.ascontiguousarray(model, np.float64), np.ascontiguousarray(fit, np.bool_),
                           SIGNAL_REGION_FRACTION, med, n_ok)
    else:
        med[:] = np.nan
    med = np.where(np.isfinite(med), med, 0.0)
    return np.where(n_ok >= min_samples, _d2_sigma(med), 0.0)


@njit
def _signal_d2_medians(r, model, fit, frac, med, n_ok):
    """Per row: the median of |second difference| of ``r`` over the second differences whose
    three samples are fitted and whose middle sample's |model| is at least ``frac`` of the row's
    largest (NaN where none), and how many such differences there are -- in one pass, without
    the (P, L) temporaries of the array form."""
    P, L = r.shape
    buf = np.empty(L)
    for i in range(P):
        top = 0.0
        has_nan = False
        for j in range(L):
            a = abs(model[i, j])
            if math.isnan(a):
                has_nan = True
            elif a > top:
                top = a
        thr = frac * top
        m = 0
        n = 0
        for j in range(L - 2):
            if has_nan or not (fit[i, j] and fit[i, j + 1] and fit[i, j + 2]):
                continue
            if not abs(model[i, j + 1]) >= thr:
                continue
            n += 1
            v = abs(r[i, j + 2] - 2.0 * r[i, j + 1] + r[i, j])
            if not math.isnan(v):
                buf[m] = v
                m += 1
        n_ok[i] = n
        med[i] = _median_of_first(buf, m)


def is_count_data(values: np.ndarray) -> bool:
    """The ``noise="auto"`` rule: are these photon counts?

    True for an integer (or boolean) dtype, and for floating-point input whose finite samples
    are all non-negative whole numbers (counts stored as float) with at least one non-zero;
    False otherwise (negative values, e.g. background-subtracted data, or any fractional
    sample).  Non-finite samples are ignored (they are excluded from the fit anyway).
    """
    v = np.asarray(values)
    if np.issubdtype(v.dtype, np.integer) or v.dtype == np.bool_:
        return True
    if not np.issubdtype(v.dtype, np.floating):
        return False
    f = v[np.isfinite(v)]
    return bool(f.size) and bool(np.all(f >= 0)) and bool(np.any(f > 0)) and bool(np.all(f == np.floor(f)))


def resolve_noise_model(noise: str, values) -> str:
    """``"auto"`` -> "poisson" for count data (:func:`is_count_data`), else
    "gaussian"; "gaussian" and "poisson" are kept."""
    noise = parse_noise_model(noise)
    if noise == "auto":
        return "poisson" if is_count_data(values) else "gaussian"
    return noise


def anscombe(counts: np.ndarray) -> np.ndarray:
    """2 sqrt(x + 3/8): Poisson counts of any mean above ~1 get variance ~1 (less below)."""
    return 2.0 * np.sqrt(np.maximum(counts, 0.0) + 0.375)


def count_dispersion(counts: np.ndarray, fit: np.ndarray, min_samples: int = MIN_NOISE_SAMPLES) -> np.ndarray:
    """(P,) noise standard deviation of the count profiles in the Anscombe domain, at least 1.

    The robust second-difference estimate (as :func:`noise_sigma`) of the stabilised profile
    over the samples above SIGNAL_REGION_FRACTION of the peak (where the counts are large
    enough for the stabilisation to hold), kept only where it exceeds the Poisson law's own
    value 1: read noise, or a gain above one unit per photon.  1 for rows with fewer than
    ``min_samples`` usable second differences there.
    """
    x = np.maximum(counts, 0.0)
    region = fit & (x >= SIGNAL_REGION_FRACTION * x.max(axis=1, keepdims=True))
    a = anscombe(x)
    d2 = np.abs(a[:, 2:] - 2.0 * a[:, 1:-1] + a[:, :-2])
    ok = _usable(region)
    s = _mad_sigma(d2, ok)
    s = np.where(ok.sum(axis=1) >= min_samples, s, 0.0)
    return np.maximum(s, 1.0)


def count_signal_sigma(counts: np.ndarray, fit: np.ndarray, scale: np.ndarray,
                       dispersion: np.ndarray | None = None) -> np.ndarray:
    """(P,) Poisson noise at the signal of count profiles, in units of the normalised profile.

    sqrt(median count over the fitted samples above SIGNAL_REGION_FRACTION of the peak)
    / scale, times the dispersion (its square is the variance per count) where given: the
    value :func:`signal_noise_sigma` measures on the residual of a good fit, known here from
    the counts before any fit.  0 for rows without a positive scale.
    """
    region = fit & (counts >= SIGNAL_REGION_FRACTION * scale[:, None])
    med = masked_median(counts, region)
    with np.errstate(all="ignore"):
        s = np.sqrt(np.where(np.isfinite(med), med, 0.0)) / scale
    s = np.where(scale > 0, s, 0.0)
    return s if dispersion is None else s * dispersion


def count_variance(model_counts: np.ndarray, dispersion=None, floor_fraction: float = 0.0,
                   floor_counts: float = POISSON_VARIANCE_FLOOR) -> np.ndarray:
    """(P, L) variance of count data under a model: its model count (times dispersion^2 where
    given), floored at ``floor_counts`` (POISSON_VARIANCE_FLOOR) and at ``floor_fraction`` of
    the row's largest model count."""
    m = np.asarray(model_counts, np.float64)
    floor = np.maximum(floor_counts, floor_fraction * np.max(m, axis=1, initial=0.0))
    var = np.maximum(m, floor[:, None])
    if dispersion is not None:
        var = var * np.square(dispersion)[:, None]
    return var


def poisson_weights(model_counts: np.ndarray, fit: np.ndarray, dispersion=None,
                    floor_counts: float = POISSON_VARIANCE_FLOOR) -> np.ndarray:
    """Least-squares weights 1 / variance of count data for a model, 0 off the fitted samples
    (the variance of :func:`count_variance`, floored at ``floor_counts``)."""
    return np.where(fit, 1.0 / count_variance(model_counts, dispersion, floor_counts=floor_counts), 0.0)


def fit_dispersion(counts: np.ndarray, model_counts: np.ndarray, fit: np.ndarray,
                   min_samples: int = MIN_NOISE_SAMPLES) -> np.ndarray:
    """(P,) noise scale of count profiles from their fit: sqrt(Pearson chi^2 / n), at least 1.

    Over the fitted samples whose model is at least PEARSON_MIN_COUNTS counts (there each
    (y - mu)^2 / mu averages 1 for Poisson counts, and the variance floor plays no part);
    1 (the Poisson law) for rows with fewer than ``min_samples`` such samples, and wherever
    the estimate is below 1.  Unlike :func:`count_dispersion` it sees no curvature of the
    profile, so it stays at 1 for pure counts however high the peak.
    """
    ok = fit & (model_counts >= PEARSON_MIN_COUNTS)
    mu = np.where(ok, model_counts, 1.0)
    chi2 = np.where(ok, (counts - mu) ** 2 / mu, 0.0).sum(axis=1)
    n = ok.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(n >= min_samples, np.sqrt(chi2 / np.maximum(n, 1)), 1.0)
    return np.maximum(d, 1.0)


def _deviance_terms(y: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Per-sample Poisson deviance 2 [y log(y / mu) - (y - mu)] (y >= 0, mu > 0; 0 log 0 = 0)."""
    ratio = np.where(y > 0, y / np.where(y > 0, mu, 1.0), 1.0)
    return 2.0 * (np.where(y > 0, y * np.log(ratio), 0.0) - (y - mu))


def poisson_deviance(counts, expected) -> np.ndarray:
    """Poisson deviance 2 sum [y log(y / mu) - (y - mu)] over the last axis, shape S.

    ``counts`` y >= 0 and ``expected`` mu > 0 broadcast to S + (L,); y log(y / mu) is 0 at y = 0.
    """
    y = np.asarray(counts, np.float64)
    mu = np.asarray(expected, np.float64)
    return np.sum(_deviance_terms(y, mu), axis=-1)


@njit
def _masked_deviance_rows(y, mu, fit, floor, out):
    """out[p] = the Poisson deviance of row p over its fitted samples
    (:func:`decomposition.kernels.countlm.deviance_row`, the terms of :func:`_deviance_terms`)."""
    for p in range(y.shape[0]):
        out[p] = deviance_row(y[p], mu[p], fit[p], floor)


def _masked_deviance(counts, model_counts, fit, dispersion, floor_counts=POISSON_VARIANCE_FLOOR):
    y, mu = np.broadcast_arrays(np.asarray(counts, np.float64), np.asarray(model_counts, np.float64))
    fit = np.broadcast_to(np.asarray(fit, np.bool_), y.shape)
    shape = y.shape[:-1]
    L = y.shape[-1] if y.ndim else 1
    dev = np.empty(int(np.prod(shape)))
    _masked_deviance_rows(np.ascontiguousarray(y.reshape(-1, L)), np.ascontiguousarray(mu.reshape(-1, L)),
                          np.ascontiguousarray(fit.reshape(-1, L)), float(floor_counts), dev)
    dev = dev.reshape(shape)
    if dispersion is not None:
        dev = dev / np.square(np.asarray(dispersion, np.float64))
    return dev


def count_deviance(counts: np.ndarray, model_counts: np.ndarray, fit: np.ndarray, dispersion=None,
                   floor_counts: float = POISSON_VARIANCE_FLOOR) -> np.ndarray:
    """(P,) Poisson deviance of count profiles under a model, over the fitted samples, in chi2 units.

    Twice the log-likelihood ratio of the saturated model to this one: the difference of two
    models' deviances is their likelihood-ratio statistic, which a component must lower it by
    (``significance_chi2``) to be kept.

    Parameters
    ----------
    counts : ndarray (P, L)          the counts (read on the fitted samples only)
    model_counts : ndarray (P, L)    expected counts, floored at ``floor_counts`` as the
                                     weights are (NaN read as 0)
    fit : ndarray (P, L) bool        samples that count
    dispersion : ndarray (P,), optional
        Noise scale of the counts (1: the Poisson law); the deviance is divided by its square.
    floor_counts : float
        Least expected count read (POISSON_VARIANCE_FLOOR: the weights' floor, and the
        significance tests'; a fit's objective may read the likelihood closer, see
        :data:`~decomposition.constants.POISSON_FIT_FLOOR`).
    """
    return _masked_deviance(counts, model_counts, fit, dispersion, floor_counts)


def removal_deviance(counts: np.ndarray, model_counts: np.ndarray, atoms_counts: np.ndarray, fit: np.ndarray,
                     dispersion=None) -> np.ndarray:
    """(P, K) increase of the count deviance when each atom alone is taken out of the model.

    The others held as they are: for Gaussian noise at the least-squares amplitudes this is
    the atom's energy sum c_i^2 / s^2; for counts it is the same likelihood-ratio statistic
    with the Poisson law where the atom lies (a faint atom far from a bright one is weighed
    with the few counts there, not with the noise at the bright one).

    Parameters
    ----------
    counts, model_counts : ndarray (P, L)
        Counts and the full model's expected counts.
    atoms_counts : ndarray (P, K, L)
        Each atom's expected counts (zero rows for empty slots: 0 there).
    fit : ndarray (P, L) bool
    dispersion : ndarray (P,), optional
    """
    base = _masked_deviance(counts, model_counts, fit, dispersion)
    K = atoms_counts.shape[1]
    out = np.zeros(atoms_counts.shape[:2])
    for k in range(K):
        on = np.any(atoms_counts[:, k] != 0, axis=-1)
        if on.any():
            out[on, k] = _masked_deviance(counts[on], model_counts[on] - atoms_counts[on, k], fit[on],
                                          None if dispersion is None else np.asarray(dispersion)[on]) - base[on]
    return out


def atom_gain(counts: np.ndarray, model_counts: np.ndarray, atom: np.ndarray, fit: np.ndarray, dispersion=None):
    """The count deviance one more atom removes, its amplitude at its best, the rest held.

    Maximises D(a) = D(mu) - D(mu + a phi) = 2 sum [y log(1 + a phi / mu) - a phi] over a >= 0,
    with mu floored at POISSON_VARIANCE_FLOOR first (the atom added to the floored model; the
    deviance floors the sum, which differs by at most the floor where the atom is ~0): D is
    concave, its maximum the root of the score sum y phi / (mu + a phi) - sum phi, decreasing in
    a, found by bisection on [0, sum y / sum phi] over the atom's support (past that bound the
    score is negative).

    Parameters
    ----------
    counts, model_counts : ndarray (P, L)
        Counts and the model's expected counts.
    atom : ndarray (P, L)
        The atom's shape (non-negative; a its amplitude in counts per unit of it).
    fit : ndarray (P, L) bool
    dispersion : ndarray (P,), optional
        The gain is divided by its square (chi2 units).

    Returns
    -------
    gain : ndarray (P,)        >= 0 (0 where the best amplitude is 0)
    amplitude : ndarray (P,)   counts per unit of ``atom``
    """
    y = np.ascontiguousarray(counts, np.float64)
    gain = np.zeros(y.shape[0])
    amp = np.zeros(y.shape[0])
    if y.shape[0]:
        _atom_gains(y, np.ascontiguousarray(model_counts, np.float64), np.ascontiguousarray(atom, np.float64),
                    np.ascontiguousarray(fit, np.bool_), ATOM_GAIN_BISECTIONS, POISSON_VARIANCE_FLOOR, gain, amp)
    if dispersion is not None:
        gain = gain / np.square(np.asarray(dispersion, np.float64))
    return gain, amp


@njit
def _atom_gains(counts, model_counts, atom, fit, n_bisect, floor, gain, amp):
    """:func:`atom_gain`'s bisection and gain, one pixel at a time over the atom's support (the
    samples where the atom is above 1e-12 of its peak)."""
    P, L = counts.shape
    on = np.empty(L, np.int64)
    for i in range(P):
        top = 0.0
        for j in range(L):
            if fit[i, j]:
                top = max(top, atom[i, j])
        cut = 1e-12 * max(top, 1e-300)
        m = 0
        sp = 0.0
        sy = 0.0
        for j in range(L):
            if fit[i, j] and atom[i, j] > cut:
                on[m] = j
                m += 1
                sp += atom[i, j]
                sy += counts[i, j]
        lo = 0.0
        hi = sy / max(sp, 1e-300)
        for _ in range(n_bisect):
            mid = 0.5 * (lo + hi)
            score = 0.0
            for q in range(m):
                j = on[q]
                mc = model_counts[i, j]
                mu = max(mc if math.isfinite(mc) else (0.0 if math.isnan(mc) else mc), floor)
                score += counts[i, j] * (atom[i, j] / (mu + mid * atom[i, j]))
            if score - sp > 0.0:
                lo = mid
            else:
                hi = mid
        g = 0.0
        for q in range(m):
            j = on[q]
            yj = counts[i, j]
            if yj > 0.0:
                mc = model_counts[i, j]
                mu = max(mc if math.isfinite(mc) else (0.0 if math.isnan(mc) else mc), floor)
                g += yj * math.log1p(lo * atom[i, j] / mu)
        gain[i] = max(2.0 * (g - lo * sp), 0.0)
        amp[i] = lo


def anscombe_residual(counts: np.ndarray, model_counts: np.ndarray, fit: np.ndarray, dispersion=None) -> np.ndarray:
    """(P, L) residual of count profiles in noise sigmas, in the variance-stabilised domain:
    :func:`anscombe` (y) - :func:`anscombe` (mu), 0 off the fitted samples, divided by the
    dispersion where given.

    Its variance is ~1 wherever mu is above ~1 count and less below, and it stays bounded where
    the model is ~0: a single stray count there reads 1.1 sigma, where the Pearson residual
    (y - mu) / sqrt(max(mu, POISSON_VARIANCE_FLOOR)) reads 7 -- so that a few stray counts far
    in a tail do not outrank a component's cluster of counts.
    """
    mu = np.maximum(np.nan_to_num(np.asarray(model_counts, np.float64)), 0.0)
    z = np.where(fit, anscombe(np.asarray(counts, np.float64)) - anscombe(mu), 0.0)
    if dispersion is not None:
        z = z / np.asarray(dispersion, np.float64)[:, None]
    return z


def signal_variance(residual: np.ndarray, model: np.ndarray, fit: np.ndarray, lag: int = 1,
                    floor_fraction: float = 0.01):
    """Per-sample noise variance ``floor + gain * max(model, 0)`` fitted to a residual.

    Photon (shot) noise has a variance proportional to the signal: largest at a direct's peak,
    nothing where no light arrives.  A single noise level per pixel then understates the noise
    where the components are, and the fit takes noise at the peak for structure.  Here the
    variance law of each row is read off the residual itself: half the squared first
    difference of the residual, ``(r[i+1] - r[i])^2 / 2``, has expectation
    ``floor + gain * (m[i] + m[i+1]) / 2`` for independent noise of that law; ``floor`` and
    ``gain`` are its weighted least-squares fit (two passes, the second with weights
    1 / variance^2, the variance of a squared Gaussian difference, the variance kept at least
    ``floor_fraction`` of its value at the model's peak).  ``lag``: differences across that
    many samples instead (a misfit wider than a sample grows with the lag; noise does not).

    Parameters
    ----------
    residual, model : ndarray (P, L)
        Data minus model, and the model (same units).
    fit : ndarray (P, L) bool
        Samples that count.

    Returns
    -------
    floor, gain : ndarray (P,)
        Fitted intercept (may be slightly negative for pure shot noise) and slope (>= 0).
    gain_stderr : ndarray (P,)
        Standard error of ``gain`` (inf where it cannot be estimated).
    """
    residual = np.ascontiguousarray(residual, np.float64)
    P = residual.shape[0]
    floor, gain, se = np.empty(P), np.empty(P), np.empty(P)
    _signal_variance_rows(residual, np.ascontiguousarray(model, np.float64), np.ascontiguousarray(fit, np.bool_),
                          int(lag), float(floor_fraction), floor, gain, se)
    return floor, gain, se


@njit
def _signal_variance_rows(residual, model, fit, lag, floor_fraction, floor_out, gain_out, se_out):
    """:func:`signal_variance` row by row: both weighted least-squares passes over the lagged
    pairs whose samples both count (y = (r[i+lag] - r[i])^2 / 2, x = the mean of max(model, 0)
    at the two), without a full-size temporary."""
    P, L = residual.shape
    for p in range(P):
        xmax = 0.0
        ymax = 0.0
        for i in range(L - lag):
            if fit[p, i] and fit[p, i + lag]:
                d = residual[p, i + lag] - residual[p, i]
                ymax = max(ymax, 0.5 * d * d)
                xmax = max(xmax, 0.5 * (max(model[p, i + lag], 0.0) + max(model[p, i], 0.0)))
        gain = 0.0
        floor = 0.0
        se = math.inf
        for second in (False, True):
            g = max(gain, 0.0)
            least = 0.0
            if second:      # weights 1 / variance^2 of the first pass's law
                top = max(floor, 0.0) + g * xmax
                least = max(floor_fraction * top, max(1e-12 * ymax, 1e-150))
            n = 0.0
            sx = 0.0
            sxx = 0.0
            sy = 0.0
            sxy = 0.0
            for i in range(L - lag):
                if not (fit[p, i] and fit[p, i + lag]):
                    continue
                d = residual[p, i + lag] - residual[p, i]
                y = 0.5 * d * d
                x = 0.5 * (max(model[p, i + lag], 0.0) + max(model[p, i], 0.0))
                w = 1.0
                if second:
                    v = max(floor + g * x, least)
                    w = 1.0 / (v * v)
                n += w
                sx += w * x
                sxx += w * x * x
                sy += w * y
                sxy += w * x * y
            det = n * sxx - sx * sx
            good = det > 1e-12 * max(n * sxx, 1e-300) and n > 2
            gain = (n * sxy - sx * sy) / det if good else 0.0
            floor = (sy - gain * sx) / max(n, 1e-300) if n > 0 else 0.0
            se = math.sqrt(n / det) if good else math.inf
        # the weights are relative; var(y) = 2 variance^2 (half the square of a Gaussian
        # difference of variance 2 v), so the information of y at variance v is 1 / (2 v^2)
        floor_out[p] = floor
        gain_out[p] = max(gain, 0.0)
        se_out[p] = se * math.sqrt(2.0)
