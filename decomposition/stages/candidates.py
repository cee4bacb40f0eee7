"""Candidate component sets after the detection: polish one, and run a step block by block.

The search stage's starts (:mod:`decomposition.stages.search`) and the steps after it
(:mod:`decomposition.stages.grow`, :mod:`decomposition.stages.prune`) each
build an alternative slot state for some pixels, polish it with the solver's compiled LM and
keep it where the search's penalised objective is lower.  :func:`polish_candidate` is that
polish, exactly as the search stage scores its starts (amplitudes by NNLS, the LM on the data
term, zero atoms emptied, thresholded and merged as the labels will); :func:`each_block` runs a
step over the live pixels, ``opts.block_size`` at a time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..constants import (SIGNAL_NOISE_FLOOR_FRACTION, SIGNAL_NOISE_LAG_RATIO, SIGNAL_NOISE_PEAK_RATIO,
                         SIGNAL_NOISE_POOL_FRACTION, SIGNAL_NOISE_POOL_MIN, SIGNAL_NOISE_POOL_Z, SIGNAL_NOISE_Z,
                         SIGNIFICANCE_LAG_BINS, WHITE_LAG_RATIO)
from .detect import solver_inputs
from .label import final_atoms
from ..noise import count_variance, lagged_noise_sigma, periodogram, residual_spectrum, signal_variance
from ..methods.polish import refit_amplitudes
from ..model.slots import drop_zero, parameter_bounds, put, refine_atoms, render

__all__ = ["polish_candidate", "each_block", "residual_significance_noise", "signal_weights",
           "detector_variance", "correlated_noise_spectrum"]


def polish_candidate(t_ps, p, mask, st, noise, dic, opts, significance_sigma, weights=None):
    """Polish the slot state ``st`` (n, K) of profiles ``p`` (n, L) -> the polished state.

    ``noise`` (n,) is the solver's noise (its penalty scale), ``significance_sigma`` (n,) the
    noise of the labels' in-window test; ``opts`` a resolved :class:`SolverOptions`;
    ``weights`` (n, L) the samples' relative least-squares weights (default: all alike).
    """
    refit_amplitudes(p, mask, st, dic)
    st, _, _ = refine_atoms(t_ps, p, mask, st, np.zeros(p.shape[0]), opts.eps_rel * np.asarray(noise),
                            parameter_bounds(dic, opts.bound_factor), opts.n_polish, None, opts.shared_sigma,
                            opts.sss_after_direct, opts.lm_tol, weights=weights, response=dic.response)
    drop_zero(st)
    return final_atoms(st, t_ps, dic.time_bin_ps, opts, significance_sigma, weights, irf=dic.response)


def each_block(samples, det, opts, step, pixels: bool = False, weights: bool = False):
    """Run ``step(p, mask, state, noise, significance_sigma) -> (state, hit)`` on the detected
    atoms of the live pixels, block by block (normalised profiles and masks of
    :func:`decomposition.stages.detect.solver_inputs`) -> (state of all live pixels, hit (n_live,) bool).
    With ``pixels`` the step also gets the block's pixel indices into ``samples`` (its sixth
    argument), for what else it reads of them; with ``weights`` the block's rows of
    ``det.weights`` (None where the detection has none) as the keyword ``weights``, and
    ``det.noise_spectrum`` as the keyword ``spectrum``."""
    live = samples.live
    state = {k: v.copy() for k, v in det.state.items()}
    hit = np.zeros(live.size, bool)
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        p, mask = solver_inputs(samples, live[rows])
        noise = det.noise_eff[live[rows]]
        args = (p, mask, {k: v[rows] for k, v in state.items()}, noise, samples.significance_sigma(live[rows], noise))
        kw = ({"weights": None if det.weights is None else det.weights[rows], "spectrum": det.noise_spectrum}
              if weights else {})
        st, hit[rows] = step(*args, live[rows], **kw) if pixels else step(*args, **kw)
        put(state, rows, st)
    return state, hit



def residual_significance_noise(samples, det, dic, opts) -> np.ndarray:
    """The significance noise of the steps after the search, from the detected fit's residual.

    :meth:`Samples.significance_sigma` weighs an atom's energy with the larger of the solver's
    noise and the profile's noise across ``SIGNIFICANCE_LAG_BINS`` samples
    (:func:`decomposition.noise.lagged_noise_sigma`), a guard against correlated noise.  On the
    profile that lagged noise also holds the components' own slopes: on the paper's scenes
    under white noise it is 1.45x the true noise (median; 2x at the 90th percentile, NSR
    0.055), so a component of energy 25 true sigma^2 -- the detectable ceiling's rule -- is
    judged at 12.  Across the same lag on the residual the slopes are gone; where the
    residual's lagged noise is at most ``WHITE_LAG_RATIO`` times the solver's (sample-to-sample)
    noise the noise is white at the component scale and the residual's value replaces the
    profile's; elsewhere (pink noise: 1.4-2.6 x) the profile's stays.

    Parameters
    ----------
    samples : Samples      the prepared samples (their ``lagged_noise`` is the default)
    det : Detection        the detected (and searched) atoms of the live pixels
    dic, opts              the dictionary and the resolved :class:`SolverOptions`

    Returns
    -------
    ndarray (P,)
        The lagged noise to use, normalised units (``samples.lagged_noise`` for count data and
        for pixels that are not live).
    """
    out = np.array(samples.lagged_noise, np.float64, copy=True)
    if samples.noise_model == "poisson":
        return out
    live = samples.live
    L = samples.n_bins
    lag = min(SIGNIFICANCE_LAG_BINS, max(1, L // 4))
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        px = live[rows]
        p, mask = solver_inputs(samples, px)
        model = render(t, {k: v[rows] for k, v in det.state.items()}, dic.response)
        lagged = lagged_noise_sigma(mask.residual(p, model), mask.fit, lag)
        white = lagged <= WHITE_LAG_RATIO * det.noise_eff[px]
        out[px] = np.where(white, lagged, out[px])
    return out


def correlated_noise_spectrum(samples, det, dic, opts, lagged) -> np.ndarray | None:
    """The power spectrum of the noise of a call whose noise is correlated (pink), for the
    penalised objectives of the stages after the detection -> (L // 2 + 1,) per unit of a pixel's
    noise variance (``det.noise_eff`` squared), or None.

    The noise is judged correlated where the median over the live pixels (at least
    SIGNAL_NOISE_POOL_MIN of them) of ``lagged`` (P,), the noise at the components' scale
    (:func:`residual_significance_noise`), over the solver's sample-to-sample noise exceeds
    WHITE_LAG_RATIO: a detector's noise spectrum is the detector's, not a pixel's.  The
    spectrum is then :func:`decomposition.noise.residual_spectrum` of the detected fits'
    residuals, each divided by its pixel's noise.  A penalised objective reads its data term as
    the residual whitened by it (:func:`decomposition.noise.whitened_chi2`): a bump of
    low-frequency noise costs what its power in that noise says, not what a white noise of the
    lagged level says.  Float data only (None for counts), and not where most pixels are
    weighted for noise that follows the signal (:func:`signal_weights`: such noise is not
    stationary; on the paper's scenes photon noise is never judged correlated anyway, its
    lagged noise, a median over mostly dark samples, reading near zero).
    """
    live = samples.live
    if samples.noise_model == "poisson" or live.size < SIGNAL_NOISE_POOL_MIN:
        return None
    if det.weights is not None and (det.weights != 1).any(axis=1).mean() >= SIGNAL_NOISE_POOL_FRACTION:
        return None         # noise that follows the signal: not stationary, its weights say more
    noise = np.maximum(det.noise_eff[live], 1e-300)
    if not np.median(np.asarray(lagged, np.float64)[live] / noise) > WHITE_LAG_RATIO:
        return None
    L = samples.n_bins
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    power = np.empty((live.size, L // 2 + 1))      # block by block: no (pixels, L) residual held
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        p, mask = solver_inputs(samples, live[rows])
        model = render(t, {k: v[rows] for k, v in det.state.items()}, dic.response)
        resid = mask.residual(p, model) / noise[rows, None]
        power[rows] = periodogram(resid)
    return residual_spectrum(power=power)


def signal_weights(samples, det, dic, opts, info=None):
    """Relative least-squares weights of the stages after the detection, where the noise
    follows the signal (photon noise) -> (n_live, L) float64, or None where no pixel's does.

    Count data (``noise="poisson"``): every pixel, from the Poisson law at the detected model
    (:func:`decomposition.noise.count_variance`, floored at SIGNAL_NOISE_FLOOR_FRACTION of the
    peak's count).  Float data (the Gaussian noise model), as follows.

    A pixel has one noise level, ``det.noise_eff``; under shot noise the variance is largest
    at the components' peaks, so a fit weighing every sample alike there takes the noise for
    structure (a wide direct split into two or three narrow Gaussians).  The variance law
    ``floor + gain * model`` of every pixel is fitted to its detected fit's residual
    (:func:`decomposition.noise.signal_variance`).  A pixel passes its own tests where the gain
    is significant (more than SIGNAL_NOISE_Z standard errors), the variance at the model's peak
    is more than SIGNAL_NOISE_PEAK_RATIO times the floor above it and the law read at a lag of
    two samples is not SIGNAL_NOISE_LAG_RATIO times larger (a misfit, not noise).  The verdict
    is pooled over the live pixels of the call: where at least SIGNAL_NOISE_POOL_FRACTION of
    them (and SIGNAL_NOISE_POOL_MIN or more) pass, or where the median of their gains'
    significance is at least SIGNAL_NOISE_POOL_Z and the median of their lag ratios below
    SIGNAL_NOISE_LAG_RATIO (read noise hides each pixel's gain, not the call's), the noise is a
    detector's shot noise.  Then,
    by ``opts.signal_noise_law``:

    ``"auto"`` (the default): every pixel is weighted by the detector's law, one law in the
    data's units for the whole call: the medians over the live pixels of their laws' floors
    and gains, each converted to the data's units (floor x scale^2, gain x scale,
    ``samples.scale`` the pixel's normalisation) -- a detector's read noise and conversion gain
    are the detector's, not a pixel's, and the median of hundreds of pixels is far more precise
    than a pixel's own gain, read off the few dozen samples under its signal.  Where the verdict
    is not pooled, only the pixels that pass their own tests are weighted, each by its own law.

    ``"pixel"``: each pixel by its own law -- where the verdict is pooled, every pixel whose
    fitted gain is positive; else those that pass their own tests.

    ``"detector"``: the detector's law for every pixel, whatever the verdict (the caller knows
    that one detector's shot noise lies behind the data); no weights where its gain is not
    positive.

    With ``info`` (a dict) the detector's law, where one was used, is recorded there as
    ``signal_noise_law_fit``: ``{"floor": variance, "gain": variance per unit of signal}`` in the
    data's units.  The floor is kept at least SIGNAL_NOISE_FLOOR_FRACTION of the peak's variance
    (no sample weighs without bound where no light arrives).  Weight = noise_eff^2 / variance:
    the search's data term becomes the sum of residual^2 / variance, 1 per sample for a fit at
    the noise.  Other pixels get 1.
    """
    live = samples.live
    L = samples.n_bins
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    counts = samples.noise_model == "poisson"
    law = opts.signal_noise_law
    out = np.ones((live.size, L)) if counts else None      # float data: once a pixel has a law
    passed = np.zeros(live.size, bool)       # the pixel's own tests
    z = np.full(live.size, np.nan)           # the pooled verdict's statistics
    lag_ratio = np.full(live.size, np.nan)
    usable = np.zeros(live.size, bool)       # its own law to weigh by (a positive gain)
    read = np.zeros(live.size, bool)         # a law could be read (the detector law's inputs)
    floors = np.zeros(live.size)             # each pixel's law in the data's units
    gains = np.zeros(live.size)
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        p, mask = solver_inputs(samples, live[rows])
        model = np.maximum(render(t, {k: v[rows] for k, v in det.state.items()}, dic.response), 0.0)
        noise2 = det.noise_eff[live[rows]][:, None] ** 2
        if counts:
            out[rows] = noise2 / _count_law(samples, live[rows], p, mask, model)
            continue
        fitted = _fitted_law(p, mask, model)
        passed[rows], usable[rows], read[rows] = fitted.passed, fitted.usable, fitted.read
        z[rows], lag_ratio[rows] = fitted.z, fitted.lag_ratio
        s = samples.scale[live[rows]]
        floors[rows], gains[rows] = fitted.floor * s * s, fitted.gain * s
        if fitted.usable.any():
            out = np.ones((live.size, L)) if out is None else out
            out[rows[fitted.usable]] = noise2[fitted.usable] / fitted.variance[fitted.usable]
    if counts:
        return out
    pooled = (passed.sum() >= max(SIGNAL_NOISE_POOL_FRACTION * live.size, SIGNAL_NOISE_POOL_MIN)
              or _pooled_law_holds(z, lag_ratio))
    if law == "detector" or (law == "auto" and pooled):
        return _detector_weights(samples, det, dic, opts, floors, gains, read, info, out)
    keep = usable if pooled else passed
    if out is None or not keep.any():
        return None
    out[~keep] = 1.0
    return out


def _pooled_law_holds(z, lag_ratio) -> bool:
    """The pooled verdict read off the call's statistics rather than its pixels' own tests: the
    median over the pixels of their gain's significance ``z`` at least SIGNAL_NOISE_POOL_Z and the
    median of their ``lag_ratio`` below SIGNAL_NOISE_LAG_RATIO (see the constants: read noise
    can hide each pixel's gain, not the call's)."""
    zs, ratios = z[np.isfinite(z)], lag_ratio[np.isfinite(lag_ratio)]
    if zs.size < SIGNAL_NOISE_POOL_MIN or ratios.size < SIGNAL_NOISE_POOL_MIN:
        return False
    return bool(np.median(zs) >= SIGNAL_NOISE_POOL_Z and np.median(ratios) < SIGNAL_NOISE_LAG_RATIO)


def _detector_weights(samples, det, dic, opts, floors, gains, read, info, out=None):
    """The weights of one variance law for every live pixel (see :func:`signal_weights`):
    ``floors``, ``gains`` (n_live,) each pixel's law in the data's units, ``read`` the pixels
    whose law could be read; the detected models rendered again block by block; ``out``
    (n_live, L), if given, is overwritten with the weights."""
    # (a pixel's fitted floor may be slightly negative under pure shot noise; a variance is not)
    floor = max(float(np.median(floors[read])), 0.0) if read.any() else 0.0
    gain = float(np.median(gains[read])) if read.any() else 0.0
    if info is not None:
        info["signal_noise_law_fit"] = {"floor": floor, "gain": gain}
    if not gain > 0:
        return None
    live, L = samples.live, samples.n_bins
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    out = np.empty((live.size, L)) if out is None else out
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        model = np.maximum(render(t, {k: v[rows] for k, v in det.state.items()}, dic.response), 0.0)
        out[rows] = det.noise_eff[live[rows]][:, None] ** 2 / detector_variance(floor, gain, model,
                                                                                samples.scale[live[rows]])
    return out


def detector_variance(floor: float, gain: float, model: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(n, L) the variance of one detector's law, ``floor`` + ``gain`` x signal (both in the
    data's units, as :func:`signal_weights` records them), at the models ``model`` (n, L, >= 0)
    of pixels normalised by ``scale`` (n,), in those normalised units; the floor kept at least
    SIGNAL_NOISE_FLOOR_FRACTION of the variance at each model's peak (:func:`_kept_floor`)."""
    s = np.maximum(scale, 1e-300)
    g = gain / s                                       # each pixel's share, normalised units
    f = _kept_floor(floor / (s * s), g * model.max(axis=1))
    return f[:, None] + g[:, None] * model


def _kept_floor(floor, peak_var):
    """A variance law's floor (n,) kept at least SIGNAL_NOISE_FLOOR_FRACTION of the variance at
    the model's peak (``peak_var`` (n,), the gain times the peak): no sample weighs without bound
    where no light arrives."""
    return np.maximum(floor, SIGNAL_NOISE_FLOOR_FRACTION * (np.maximum(floor, 0.0) + peak_var))


@dataclass(frozen=True)
class _FittedLaw:
    """Each pixel's variance law read off its residual (:func:`_fitted_law`): ``floor``,
    ``gain`` (n,) as fitted, in normalised units; ``read`` (n,) where they could be read;
    ``passed`` (n,) the pixel's own tests; ``usable`` (n,) a positive gain, and ``variance``
    (n, L) its law, floored (1 where not usable); ``z`` (n,) the gain over its error (NaN where
    not read) and ``lag_ratio`` (n,) the gain read at a lag of two samples over it (NaN where
    the gain is not positive)."""

    floor: np.ndarray
    gain: np.ndarray
    read: np.ndarray
    passed: np.ndarray
    usable: np.ndarray
    variance: np.ndarray
    z: np.ndarray
    lag_ratio: np.ndarray


def _fitted_law(p, mask, model) -> _FittedLaw:
    """The variance law of normalised profiles ``p`` (n, L) read off their residual from
    ``model`` (>= 0); see :func:`signal_weights`."""
    floor, gain, se = signal_variance(p - model, model, mask.fit, floor_fraction=SIGNAL_NOISE_FLOOR_FRACTION)
    peak_var = gain * model.max(axis=1)
    follows = (gain > SIGNAL_NOISE_Z * se) & (peak_var > SIGNAL_NOISE_PEAK_RATIO * np.maximum(floor, 0.0))
    # a misfit (structure wider than a bin) grows with the lag, independent noise does not
    lag_ratio = np.full(gain.shape, np.nan)
    c = np.flatnonzero(gain > 0)
    if c.size:
        _, gain2, _ = signal_variance(p[c] - model[c], model[c], mask.fit[c], lag=2,
                                      floor_fraction=SIGNAL_NOISE_FLOOR_FRACTION)
        lag_ratio[c] = gain2 / gain[c]
    follows &= lag_ratio < SIGNAL_NOISE_LAG_RATIO
    kept = _kept_floor(floor, peak_var)
    usable = (gain > 0) & (peak_var > 0) & np.isfinite(kept) & (kept > 0)
    variance = np.where(usable[:, None], kept[:, None] + gain[:, None] * model, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(np.isfinite(se), gain / se, np.nan)
    return _FittedLaw(floor=floor, gain=gain, read=np.isfinite(se), passed=follows & usable, usable=usable,
                      variance=variance, z=z, lag_ratio=lag_ratio)


def _count_law(samples, px, p, mask, model):
    """(n, L) Poisson variance of count pixels ``px`` at ``model`` (>= 0), in the units of their
    normalised profiles (:func:`decomposition.noise.count_variance`)."""
    scale = np.maximum(samples.scale[px], 1e-300)
    disp = None if samples.dispersion is None else samples.dispersion[px]
    return count_variance(model * scale[:, None], disp, SIGNAL_NOISE_FLOOR_FRACTION) / scale[:, None] ** 2
