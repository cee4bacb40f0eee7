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

__all__ = ["polish_candidate", "each_block", "residual_significance_noise"]


def polish_candidate(t_ps, p, mask, st, noise, dic, opts, significance_sigma):
    """Polish the slot state ``st`` (n, K) of profiles ``p`` (n, L) -> the polished state.

    ``noise`` (n,) is the solver's noise (its penalty scale), ``significance_sigma`` (n,) the
    noise of the labels' in-window test; ``opts`` a resolved :class:`SolverOptions`.
    """
    from .label import final_atoms
    from .polish import refit_amplitudes
    from .slots import drop_zero, parameter_bounds, refine_atoms

    refit_amplitudes(p, mask, st, dic)
    st, _, _ = refine_atoms(t_ps, p, mask, st, np.zeros(p.shape[0]), opts.eps_rel * np.asarray(noise),
                            parameter_bounds(dic, opts.bound_factor), opts.n_polish, None, opts.shared_sigma,
                            opts.sss_after_direct, opts.lm_tol)
    drop_zero(st)
    return final_atoms(st, t_ps, dic.time_bin_ps, opts, significance_sigma)


def each_block(samples, det, opts, step, pixels: bool = False):
    """Run ``step(p, mask, state, noise, significance_sigma) -> (state, hit)`` on the detected
    atoms of the live pixels, block by block (normalised profiles and masks of
    :func:`decomposition.detect.solver_inputs`) -> (state of all live pixels, hit (n_live,) bool).
    With ``pixels`` the step also gets the block's pixel indices into ``samples`` (its sixth
    argument), for what else it reads of them."""
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
        st, hit[rows] = step(*args, live[rows]) if pixels else step(*args)
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
