"""Candidate component sets after the detection: polish one, and run a step block by block.

The search stage's starts (:mod:`decomposition.search`) and the steps after it
(:mod:`decomposition.grow`, :mod:`decomposition.prune`) each
build an alternative slot state for some pixels, polish it with the solver's compiled LM and
keep it where the search's penalised objective is lower.  :func:`polish_candidate` is that
polish, exactly as the search stage scores its starts (amplitudes by NNLS, the LM on the data
term, zero atoms emptied, thresholded and merged as the labels will); :func:`each_block` runs a
step over the live pixels, ``opts.block_size`` at a time.
"""
from __future__ import annotations

import numpy as np

__all__ = ["polish_candidate", "each_block", "residual_significance_noise", "signal_weights"]


def polish_candidate(t_ps, p, mask, st, noise, dic, opts, significance_sigma, weights=None):
    """Polish the slot state ``st`` (n, K) of profiles ``p`` (n, L) -> the polished state.

    ``noise`` (n,) is the solver's noise (its penalty scale), ``significance_sigma`` (n,) the
    noise of the labels' in-window test; ``opts`` a resolved :class:`SolverOptions`;
    ``weights`` (n, L) the samples' relative least-squares weights (default: all alike).
    """
    from .label import final_atoms
    from .polish import refit_amplitudes
    from .slots import drop_zero, parameter_bounds, refine_atoms

    refit_amplitudes(p, mask, st, dic)
    st, _, _ = refine_atoms(t_ps, p, mask, st, np.zeros(p.shape[0]), opts.eps_rel * np.asarray(noise),
                            parameter_bounds(dic, opts.bound_factor), opts.n_polish, None, opts.shared_sigma,
                            opts.sss_after_direct, opts.lm_tol, weights=weights)
    drop_zero(st)
    return final_atoms(st, t_ps, dic.time_bin_ps, opts, significance_sigma, weights)


def each_block(samples, det, opts, step, pixels: bool = False, weights: bool = False):
    """Run ``step(p, mask, state, noise, significance_sigma) -> (state, hit)`` on the detected
    atoms of the live pixels, block by block (normalised profiles and masks of
    :func:`decomposition.detect.solver_inputs`) -> (state of all live pixels, hit (n_live,) bool).
    With ``pixels`` the step also gets the block's pixel indices into ``samples`` (its sixth
    argument), for what else it reads of them; with ``weights`` the block's rows of
    ``det.weights`` (None where the detection has none) as the keyword ``weights``."""
    from .detect import solver_inputs
    from .slots import put

    live = samples.live
    state = {k: v.copy() for k, v in det.state.items()}
    hit = np.zeros(live.size, bool)
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        p, mask = solver_inputs(samples, live[rows])
        noise = det.noise_eff[live[rows]]
        args = (p, mask, {k: v[rows] for k, v in state.items()}, noise, samples.significance_sigma(live[rows], noise))
        kw = {"weights": None if det.weights is None else det.weights[rows]} if weights else {}
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
    from .constants import SIGNIFICANCE_LAG_BINS, WHITE_LAG_RATIO
    from .detect import solver_inputs
    from .noise import lagged_noise_sigma
    from .slots import render

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
        lagged = lagged_noise_sigma(mask.residual(p, render(t, {k: v[rows] for k, v in det.state.items()})),
                                    mask.fit, lag)
        white = lagged <= WHITE_LAG_RATIO * det.noise_eff[px]
        out[px] = np.where(white, lagged, out[px])
    return out


def signal_weights(samples, det, dic, opts):
    """Relative least-squares weights of the stages after the detection, where the noise
    follows the signal (photon noise) -> (n_live, L) float64, or None where no pixel's does.

    Count data (``noise="poisson"``): every pixel, from the Poisson law at the detected model
    (:func:`decomposition.noise.count_variance`, floored at SIGNAL_NOISE_FLOOR_FRACTION of the
    peak's count).  Float data (the Gaussian noise model), as follows.

    A pixel has one noise level, ``det.noise_eff``; under shot noise the variance is largest
    at the components' peaks, so a fit weighing every sample alike there takes the noise for
    structure (a wide direct split into two or three narrow Gaussians).  The variance law
    ``floor + gain * model`` of every pixel is fitted to its detected fit's residual
    (:func:`decomposition.noise.signal_variance`).  It is used where the gain is significant
    (more than SIGNAL_NOISE_Z standard errors), the variance at the model's peak is more
    than SIGNAL_NOISE_PEAK_RATIO times the floor above it and the law read at a lag of two
    samples is not SIGNAL_NOISE_LAG_RATIO times larger (a misfit, not noise).  The verdict is
    then pooled over the live pixels of the call: where at least SIGNAL_NOISE_POOL_FRACTION of
    them (and SIGNAL_NOISE_POOL_MIN or more) pass, the noise is the detector's shot noise and
    every pixel whose fitted gain is positive is weighted by its own law (see the constants).
    The floor is kept at least SIGNAL_NOISE_FLOOR_FRACTION of the peak's variance (no sample
    weighs without bound where no light arrives).  Weight = noise_eff^2 / variance: the
    search's data term becomes the sum of residual^2 / variance, 1 per sample for a fit at the
    noise.  Other pixels get 1.
    """
    from .constants import SIGNAL_NOISE_POOL_FRACTION, SIGNAL_NOISE_POOL_MIN
    from .detect import solver_inputs
    from .slots import render

    live = samples.live
    L = samples.n_bins
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    counts = samples.noise_model == "poisson"
    out = np.ones((live.size, L))
    passed = np.zeros(live.size, bool)       # the pixel's own tests (all of them for counts)
    usable = np.zeros(live.size, bool)       # a law to weigh by (positive gain; counts: all)
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        p, mask = solver_inputs(samples, live[rows])
        model = np.maximum(render(t, {k: v[rows] for k, v in det.state.items()}), 0.0)
        if counts:
            var = _count_law(samples, live[rows], p, mask, model)
            passed[rows] = usable[rows] = True
        else:
            var, passed[rows], usable[rows] = _fitted_law(p, mask, model)
        out[rows[usable[rows]]] = (det.noise_eff[live[rows[usable[rows]]]][:, None] ** 2
                                   / var[usable[rows]])
    pooled = passed.sum() >= max(SIGNAL_NOISE_POOL_FRACTION * live.size, SIGNAL_NOISE_POOL_MIN)
    keep = usable if pooled else passed
    out[~keep] = 1.0
    return out if keep.any() else None


def _fitted_law(p, mask, model):
    """The variance law of normalised profiles ``p`` (n, L) whose residual from ``model`` (>= 0)
    is read (see :func:`signal_weights`) -> (variance (n, L), passed (n,) bool: the pixel's own
    tests, usable (n,) bool: a positive gain, so a law to weigh by)."""
    from .constants import SIGNAL_NOISE_FLOOR_FRACTION, SIGNAL_NOISE_LAG_RATIO, SIGNAL_NOISE_PEAK_RATIO, SIGNAL_NOISE_Z
    from .noise import signal_variance

    floor, gain, se = signal_variance(p - model, model, mask.fit, floor_fraction=SIGNAL_NOISE_FLOOR_FRACTION)
    peak_var = gain * model.max(axis=1)
    follows = (gain > SIGNAL_NOISE_Z * se) & (peak_var > SIGNAL_NOISE_PEAK_RATIO * np.maximum(floor, 0.0))
    # a misfit (structure wider than a bin) grows with the lag, independent noise does not
    c = np.flatnonzero(follows)
    if c.size:
        _, gain2, _ = signal_variance(p[c] - model[c], model[c], mask.fit[c], lag=2,
                                      floor_fraction=SIGNAL_NOISE_FLOOR_FRACTION)
        follows[c] = gain2 < SIGNAL_NOISE_LAG_RATIO * gain[c]
    floor = np.maximum(floor, SIGNAL_NOISE_FLOOR_FRACTION * (np.maximum(floor, 0.0) + peak_var))
    usable = (gain > 0) & (peak_var > 0) & np.isfinite(floor) & (floor > 0)
    var = np.where(usable[:, None], floor[:, None] + gain[:, None] * model, 1.0)
    return var, follows & usable, usable


def _count_law(samples, px, p, mask, model):
    """(n, L) Poisson variance of count pixels ``px`` at ``model`` (>= 0), in the units of their
    normalised profiles (:func:`decomposition.noise.count_variance`)."""
    from .constants import SIGNAL_NOISE_FLOOR_FRACTION
    from .noise import count_variance

    scale = np.maximum(samples.scale[px], 1e-300)
    disp = None if samples.dispersion is None else samples.dispersion[px]
    return count_variance(model * scale[:, None], disp, SIGNAL_NOISE_FLOOR_FRACTION) / scale[:, None] ** 2
