"""Forward step of a decomposition: add a Gaussian where a fit leaves a resolved bump.

The sparse coding can stop with a component missing: an inter-reflection a few widths after
the direct whose rise the sss and a wide neighbour share, or a weak first inter-reflection
before a strong one, left as a residual bump.  :func:`grow_components` takes every pixel with
a free slot whose largest smoothed residual more than ``GROW_EXCLUDE_SIGMA`` widths from every
Gaussian it has is significant -- its matched-filter z (:func:`residual_peak`, in the
significance noise, :meth:`Samples.significance_sigma`, read against the spread of the smoothed
residual itself so that correlated noise does not pass for a component) squared at least
GROW_TRIAL_FRACTION x ``significance_chi2`` -- or whose data term exceeds ``search_doubt_chi2``
times its expected value, puts a Gaussian at that residual bump, polishes all atoms
with the solver's compiled LM, and keeps the grown answer where it lowers the search's
penalised objective (:func:`decomposition.stages.selection.penalised_objective`) and every pair of
Gaussians stays resolved (``RESOLVED_SIGMA`` widths apart, or no closer than before: a
Gaussian that slid onto the direct splits a peak, it is not a component).

Why both tests: the data-term test alone misses a component of energy E sigma^2 unless E is
about half the window's samples, and the weak first inter-reflections the solver misses carry
far less; the bump's z is read in the significance noise and against the smoothed residual's own
spread, so that correlated noise does not pass for a component; the resolution rule keeps
trial Gaussians from splitting the direct's peak, where photon noise is largest.

An sss whose onset the fit moved late can take in a weak first inter-reflection instead,
leaving no bump: :func:`swap_block` tries a Gaussian at the peak of every sss that peaks more
than ``SWAP_MODE_GAP_SIGMA`` widths after the direct, with the sss onset moved next to the
direct.

Count data (``noise="poisson"``) have a forward step of their own, :func:`grow_counts`, after the
Poisson polish and the threshold: the pursuit, the search and the test above weigh every sample
with the Poisson noise at the direct's peak, in which a faint echo where the counts are few is
invisible, and so is an sss tail at ~100 photons per pixel.  Its trials -- an echo at the
residual's peak (:func:`residual_peak`, tested before the refit by :func:`worth_refitting`) and
an sss at the direct -- and their deviance test are those of the response path's count steps
(:mod:`decomposition.response.grow`, step 2).
"""
from __future__ import annotations

import math

import numpy as np

from .candidates import each_block, polish_candidate
from ..constants import (BOUND_TOL, FAM_GAUSS, FAM_NONE, FAM_SSS, GROW_BROAD_FACTOR, GROW_EXCLUDE_SIGMA,
                         GROW_TRIAL_FRACTION, NEAR_SIGMA, PRUNE_ONSET_SIGMA, RESOLVED_SIGMA, SWAP_MIN_ALPHA_SIGMA,
                         SWAP_MODE_GAP_SIGMA)

from .countpolish import polish_count_state
from ..noise import MAD_TO_SIGMA, anscombe_residual, atom_gain, count_deviance, masked_median
from .objective import _smooth, objective_variance
from .selection import log_samples, penalised_objective
from ..model.slots import eval_atoms, parameter_bounds, put, render, take

__all__ = ["min_gaussian_gap_sigma", "with_atom", "with_gaussian", "late_fast_sss", "near_centres", "masked_spread", "residual_peak", "worth_refitting",
           "grow_block", "grow_components", "swap_block", "swap_components", "grow_count_block", "grow_counts"]


def min_gaussian_gap_sigma(st) -> np.ndarray:
    """Smallest distance between two Gaussians of each pixel, in the pixel's (widest) PSF
    widths; inf where a pixel has fewer than two."""
    g = st["fam"] == FAM_GAUSS
    d = np.where(g, st["delay"], np.nan)
    K = d.shape[1]
    gap = np.abs(d[:, :, None] - d[:, None, :])
    gap[:, np.arange(K), np.arange(K)] = np.nan
    gap = np.where(np.isfinite(gap), gap, np.inf).min(axis=(1, 2))
    with np.errstate(invalid="ignore", over="ignore"):
        return gap / np.exp(np.where(g, st["lsig"], -np.inf).max(axis=1))


def near_centres(t_ps, centres_ps, half_width_ps):
    """(n, L) bool: samples of the uniform axis ``t_ps`` (L,) closer than ``half_width_ps`` (n,)
    to one of the ``centres_ps`` (n, K) of their row (NaN: none), by interval edges and one
    cumulative sum (no (n, L, K) array)."""
    n, L = centres_ps.shape[0], t_ps.size
    c = np.where(np.isfinite(centres_ps), centres_ps, np.inf)
    h = np.asarray(half_width_ps, np.float64)[:, None]
    with np.errstate(invalid="ignore"):
        lo = np.searchsorted(t_ps, c - h, side="right")
        hi = np.maximum(np.searchsorted(t_ps, c + h, side="left"), lo)
    edges = np.zeros((n, L + 1), np.int64)
    rows = np.repeat(np.arange(n), c.shape[1])
    np.add.at(edges, (rows, lo.ravel()), 1)
    np.add.at(edges, (rows, hi.ravel()), -1)
    return np.cumsum(edges[:, :L], axis=1) > 0


def masked_spread(values, used):
    """(n,) robust standard deviation about zero of each row of ``values`` (n, L) over the
    samples ``used`` (n, L): MAD_TO_SIGMA x the median of |value| (0 where none is used)."""
    med = masked_median(np.abs(values), used)
    return MAD_TO_SIGMA * np.where(np.isfinite(med), med, 0.0)


def residual_peak(t_ps, residual, used, centres_ps, width_ps, spread: bool = False):
    """Where a forward step puts its trial atom: the largest smoothed residual more than
    ``GROW_EXCLUDE_SIGMA`` widths from every peaked atom a pixel has.

    Parameters
    ----------
    t_ps : ndarray (L,)           sample times, ps (uniform)
    residual : ndarray (n, L)     data minus model (any units; in noise sigmas for the score)
    used : ndarray (n, L) bool    samples that may hold the trial's position
    centres_ps : ndarray (n, K)   delays of the atoms to stay away from, ps (NaN: none)
    width_ps : ndarray (n,)       the pixel's PSF width, ps (the smoothing's and the exclusion's)

    Returns
    -------
    at_ps : ndarray (n,)
        The trial delay, ps (the first sample where no sample is allowed).
    score : ndarray (n,)
        The smoothed residual there times sqrt(2 sqrt(pi) w), w the smoothing width in bins:
        for a residual in noise sigmas, the matched-filter z of a Gaussian of that width
        (its square the chi2 such an atom would gain, its amplitude free, the rest held);
        -inf where no sample is allowed.
    spread : ndarray (n,), with ``spread=True`` only
        The robust standard deviation of the smoothed residual over the allowed samples on the
        same scale (:func:`masked_spread`): 1 for white noise in noise sigmas, more where the
        noise is correlated at the atom's scale.
    """
    T = float(t_ps[1] - t_ps[0])
    w = np.maximum(np.asarray(width_ps, np.float64) / T, 0.5)
    smooth = _smooth(residual, w)
    res = np.where(used, smooth, -np.inf)
    res = np.where(near_centres(t_ps, centres_ps, GROW_EXCLUDE_SIGMA * np.asarray(width_ps, np.float64)), -np.inf, res)
    i = np.argmax(res, axis=1)
    peak = res[np.arange(res.shape[0]), i]
    gain = np.sqrt(2.0 * np.sqrt(np.pi) * w)
    if not spread:
        return t_ps[i], peak * gain
    return t_ps[i], peak * gain, masked_spread(smooth, used) * gain


def worth_refitting(gain, gain_wide, amplitude, direct_amplitude, significance_chi2: float) -> np.ndarray:
    """(n,) bool: the forward steps' test of an echo trial before its refit, on the trial atom
    at its position with the rest held (:func:`decomposition.noise.atom_gain` for counts).

    It must remove at least GROW_TRIAL_FRACTION x ``significance_chi2`` of the deviance
    (``gain``; the refit's deviance drop decides, this only spares refits where there is
    nothing to find), more than an atom GROW_BROAD_FACTOR times wider at the same place would
    (``gain_wide``: an echo is a bump of the PSF's width; a broad excess -- an sss tail the fit
    lacks, an offset it does not model -- is none), and its ``amplitude`` must stay below the
    direct's (``direct_amplitude``, same units: an echo brighter than the direct it echoes has
    found light the direct missed, a wrong split that one more atom does not mend).
    """
    return ((gain >= GROW_TRIAL_FRACTION * significance_chi2) & (gain > gain_wide)
            & (amplitude < direct_amplitude))


def with_atom(st, fam, delay_ps, lsig, amp=1.0, lalp=None):
    """A forward step's trial: a copy of the slot state ``st`` (n, K) with an atom of family
    ``fam`` and log width ``lsig`` (n,) at ``delay_ps`` (n,), amplitude ``amp`` (scalar or
    (n,)), log alpha ``lalp`` (scalar or (n,); None: the free slot's left as it is), penalty
    scale 1, in each row's first free slot (every row must have one) -> (state, slot (n,))."""
    n = st["fam"].shape[0]
    alt = take(st, np.arange(n))
    r = np.arange(n)
    slot = np.argmax(alt["fam"] == FAM_NONE, axis=1)
    alt["fam"][r, slot] = fam
    alt["delay"][r, slot] = delay_ps
    alt["lsig"][r, slot] = lsig
    alt["amp"][r, slot] = amp
    if lalp is not None:
        alt["lalp"][r, slot] = lalp
    alt["pen"][r, slot] = 1.0
    return alt, slot


def with_gaussian(st, delay_ps, lsig, amp=1.0):
    """:func:`with_atom` with a Gaussian."""
    return with_atom(st, FAM_GAUSS, delay_ps, lsig, amp)


def _keep_if_better(t, p, mask, out, idx, cur, alt, s_eff, s_sig, dic, opts, weights=None, spectrum=None):
    """Polish the trials ``alt`` of rows ``idx`` (whose state is ``cur``) and put those into
    ``out`` whose penalised objective (over :func:`decomposition.stages.search.objective_variance`) is
    lower and whose Gaussians stay resolved (RESOLVED_SIGMA widths apart, or no closer than
    before) -> the rows of ``idx`` taken.  ``weights`` (n, L): the samples' relative
    least-squares weights (default: all alike); ``spectrum``: the call's correlated noise
    (:attr:`Detection.noise_spectrum`), by which the objectives whiten their residuals."""
    pb, mb = p[idx], mask[idx]
    log_n = log_samples(mb.used.sum(axis=1))
    wb = None if weights is None else weights[idx]
    alt = polish_candidate(t, pb, mb, alt, np.maximum(s_eff[idx], 1e-300), dic, opts, s_sig[idx], wb)
    s2 = objective_variance(np.maximum(s_eff[idx], 1e-300), s_sig[idx], wb, spectrum)
    resolved = min_gaussian_gap_sigma(alt) >= np.minimum(RESOLVED_SIGMA, min_gaussian_gap_sigma(cur))
    better = (penalised_objective(t, pb, mb, alt, s2, log_n, opts, dic.response)
              < penalised_objective(t, pb, mb, cur, s2, log_n, opts, dic.response))
    w = np.flatnonzero(resolved & better)
    if w.size:
        put(out, idx[w], take(alt, w))
    return idx[w]


def grow_block(p, mask, st, s_eff, dic, opts, significance_sigma=None, bump_test: bool = True, weights=None,
               spectrum=None):
    """The forward step on one block (normalised profiles ``p`` (n, L), their masks, slot state
    ``st`` (n, K) and noise ``s_eff`` (n,); ``significance_sigma`` (n,) the noise of the
    in-window test and of the candidate test, default ``s_eff``) -> (state, grown (n,) bool).

    ``bump_test``: a pixel is tried where its largest resolved residual bump is significant, or
    its data term is high; False: the data term alone (count data, whose faint echoes
    :func:`grow_counts` tests with Poisson weights and against a broad excess: with a response
    tail the Gaussian model lacks, the bump test put a Gaussian on the tail's misfit in 21 % of
    the pixels of ``tests/test_echo.py``'s d+s scene at 100 photons).  ``weights`` (n, L): the
    samples' relative least-squares weights (:attr:`Detection.weights`): the trial is polished and
    scored with them and, with ``bump_test``, the residual read in each sample's noise sigmas
    (count data keep the unweighted data term as their trigger: weighted, the misfit of a
    response tail the Gaussian model lacks set it off, and a false echo was kept in 42 % of
    ``tests/test_echo.py``'s tailed d+s pixels at 100 photons, 2.5 % unweighted)."""
    n, L = p.shape
    T = dic.time_bin_ps
    t = dic.t0_ps + T * np.arange(L)
    out = {k: v.copy() for k, v in st.items()}
    grown = np.zeros(n, bool)
    s_sig = s_eff if significance_sigma is None else significance_sigma
    nfit = np.maximum(mask.used.sum(axis=1), 1)
    g = out["fam"] == FAM_GAUSS
    free = np.nonzero((out["fam"] == FAM_NONE).any(axis=1) & g.any(axis=1))[0]
    if free.size == 0:
        return out, grown
    cur = take(out, free)
    gc = cur["fam"] == FAM_GAUSS
    sigma_ps = np.exp(np.where(gc, cur["lsig"], -np.inf).max(axis=1))
    # the largest smoothed residual away from the Gaussians the pixel has, and its matched-filter z
    sig_f = np.maximum(s_sig[free], 1e-300)
    resid = mask[free].residual(p[free], render(t, cur, dic.response))
    if weights is not None and bump_test:       # in the noise sigmas of each sample
        resid = resid * np.sqrt(weights[free])
    at_ps, z, spread = residual_peak(t, resid / sig_f[:, None], mask[free].used,
                                     np.where(gc, cur["delay"], np.nan), sigma_ps, spread=True)
    # noise that is correlated at the atom's scale (pink) makes the smoothed residual spread
    # more than white noise of the same sample sigma would: z is read against the spread seen
    z = z / np.maximum(spread, 1.0)
    chi2 = np.einsum("pl,pl->p", resid, resid) / sig_f ** 2
    keep = chi2 > opts.search_doubt_chi2 * nfit[free]
    if bump_test:
        keep |= np.isfinite(z) & (z > 0) & (z ** 2 >= GROW_TRIAL_FRACTION * opts.significance_chi2)
    idx, cur, at_ps, sigma_ps = free[keep], take(cur, np.nonzero(keep)[0]), at_ps[keep], sigma_ps[keep]
    if idx.size == 0:
        return out, grown
    alt, _ = with_gaussian(cur, at_ps, np.log(sigma_ps))
    grown[_keep_if_better(t, p, mask, out, idx, cur, alt, s_eff, s_sig, dic, opts, weights, spectrum)] = True
    return out, grown


def grow_components(samples, det, dic, opts):
    """The ``grow`` stage of :func:`decomposition.decompose` (``grow=True``): :func:`grow_block` on the
    detected (and searched) atoms of the live pixels, block by block -> (state, grown (n_live,))."""
    bump = samples.noise_model != "poisson"
    return each_block(samples, det, opts,
                      lambda p, mask, st, noise, sig, weights, spectrum: grow_block(p, mask, st, noise, dic, opts, sig,
                                                                                    bump, weights, spectrum),
                      weights=True)


def late_fast_sss(t_ps, st, d0_ps, sigma_ps, response=None):
    """The sss swap's rule on slot states ``st`` (n, K) whose direct lies at ``d0_ps`` (n,), of
    width ``sigma_ps`` (n,): -> (the sss's slot (n,), its hump's mode in ps (n,), passes (n,)
    bool): the hump peaks more than ``SWAP_MODE_GAP_SIGMA`` widths after the direct and decays
    fast enough against the PSF to pass for a Gaussian (alpha sigma >= ``SWAP_MIN_ALPHA_SIGMA``).
    A pixel without an sss does not pass (its mode NaN, its slot the first).  ``response``: the
    atoms are a measured response's."""
    n = st["fam"].shape[0]
    r = np.arange(n)
    ss = np.argmax(st["fam"] == FAM_SSS, axis=1)
    has = (st["fam"] == FAM_SSS).any(axis=1)
    h, sh = np.flatnonzero(has), ss[has]
    mode_ps = np.full(n, np.nan)
    if h.size:
        hump = eval_atoms(t_ps, np.full(h.size, FAM_SSS, np.int8), st["delay"][h, sh], st["lsig"][h, sh],
                          st["lalp"][h, sh], response)
        mode_ps[h] = t_ps[np.argmax(hump, axis=1)]
    # an sss decaying slowly against the PSF (small alpha sigma) has a hump far broader than a
    # Gaussian's: it takes in none
    with np.errstate(invalid="ignore"):
        steep = np.exp(st["lalp"][r, ss]) * sigma_ps >= SWAP_MIN_ALPHA_SIGMA
        return ss, mode_ps, has & steep & (mode_ps - d0_ps > SWAP_MODE_GAP_SIGMA * sigma_ps)


def swap_block(p, mask, st, s_eff, dic, opts, significance_sigma=None, weights=None, spectrum=None):
    """The sss swap on one block (arguments of :func:`grow_block`) -> (state, swapped (n,) bool).

    An sss whose onset the fit moved late takes in a weak inter-reflection after the direct: its
    hump sits where the Gaussian is and no residual bump is left for :func:`grow_block` to
    find.  Every pixel with a Gaussian, an sss and a free slot whose sss peaks more than
    ``SWAP_MODE_GAP_SIGMA`` widths after the direct (the earliest Gaussian) and decays fast
    enough against the PSF to pass for a Gaussian (alpha sigma >= ``SWAP_MIN_ALPHA_SIGMA``) gets
    the start: a Gaussian of the pixel's width at the sss's peak and the sss onset moved to
    ``PRUNE_ONSET_SIGMA`` widths after the direct; all atoms are polished and the start kept
    where the penalised objective is lower and every pair of Gaussians stays resolved (the rule
    of :func:`grow_block`).
    """
    n, L = p.shape
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    out = {k: v.copy() for k, v in st.items()}
    swapped = np.zeros(n, bool)
    g = out["fam"] == FAM_GAUSS
    s = out["fam"] == FAM_SSS
    cand = np.flatnonzero((out["fam"] == FAM_NONE).any(axis=1) & g.any(axis=1) & s.any(axis=1))
    if cand.size == 0:
        return out, swapped
    cur = take(out, cand)
    gc = cur["fam"] == FAM_GAUSS
    d0_ps = np.where(gc, cur["delay"], np.inf).min(axis=1)
    sigma_ps = np.exp(np.where(gc, cur["lsig"], -np.inf).max(axis=1))
    ss, mode_ps, passes = late_fast_sss(t, cur, d0_ps, sigma_ps, dic.response)
    late = np.flatnonzero(passes)
    if late.size == 0:
        return out, swapped
    idx, cur = cand[late], take(cur, late)
    alt, _ = with_gaussian(cur, mode_ps[late], np.log(sigma_ps[late]))
    alt["delay"][np.arange(late.size), ss[late]] = d0_ps[late] + PRUNE_ONSET_SIGMA * sigma_ps[late]
    s_sig = s_eff if significance_sigma is None else significance_sigma
    swapped[_keep_if_better(t, p, mask, out, idx, cur, alt, s_eff, s_sig, dic, opts, weights, spectrum)] = True
    return out, swapped


def swap_components(samples, det, dic, opts):
    """The ``grow`` stage of :func:`decomposition.decompose`, second step (``grow=True``, after
    :func:`grow_components`): :func:`swap_block` on the live pixels, block by block
    -> (state, swapped (n_live,))."""
    # count data swap unweighted: their Poisson weights make a response tail the Gaussian model
    # lacks significant, and the trial Gaussian on the sss hump took it (tests/test_echo.py's d+s
    # scene with a 30 ps tail at 100 photons: a false echo in 10 % of the pixels, 2.5 % without;
    # fidelity of paper scenes at 300-10,000 photons -0.002..-0.008 for it)
    return each_block(samples, det, opts,
                      lambda p, mask, st, noise, sig, weights=None, spectrum=None: swap_block(p, mask, st, noise, dic,
                                                                                              opts, sig, weights,
                                                                                              spectrum),
                      weights=samples.noise_model != "poisson")


def grow_count_block(counts, fit, p, mask, st, scale, noise, dispersion, background, dic, opts):
    """The forward step of count data on one block (see :func:`grow_counts`) -> (state, grown (n,)).

    Parameters
    ----------
    counts : ndarray (n, L)       the counts (background included)
    fit : ndarray (n, L) bool     samples fitted
    p, mask                       normalised profiles and their SampleMask (the solver's inputs)
    st : dict                     slot state (n, K), normalised units
    scale, noise : ndarray (n,)   counts per normalised unit; the solver's noise
    dispersion, background : ndarray (n,) or None
    """
    n, L = p.shape
    T = dic.time_bin_ps
    blk = _CountBlock(dic.t0_ps + T * np.arange(L), counts, fit, p, mask, scale, noise, dispersion, background, dic,
                      opts)
    out = {k: v.copy() for k, v in st.items()}
    grown = np.zeros(n, bool)
    active = np.arange(n)
    for _ in range(out["fam"].shape[1]):
        cand = active[(out["fam"][active] == FAM_NONE).any(axis=1) & (out["fam"][active] == FAM_GAUSS).any(axis=1)]
        if cand.size == 0:
            break
        cur = take(out, cand)
        mu = blk.model(cur, cand)
        dev_cur = blk.deviance(cand, mu)
        best, dev_best = take(cur, np.arange(cand.size)), np.full(cand.size, np.inf)
        for trial in (_echo_trial_counts, _sss_trial_counts):
            rows, alt, dev = trial(blk, cand, cur, mu)
            win = dev < dev_best[rows]
            if win.any():
                put(best, rows[win], take(alt, np.flatnonzero(win)))
                dev_best[rows[win]] = dev[win]
        w = np.flatnonzero(dev_cur - dev_best >= opts.significance_chi2)
        if w.size:
            put(out, cand[w], take(best, w))
            grown[cand[w]] = True
        active = cand[w]
    return out, grown


class _CountBlock:
    """What the count trials of one block read (see :func:`grow_count_block`)."""

    def __init__(self, t, counts, fit, p, mask, scale, noise, dispersion, background, dic, opts):
        n = p.shape[0]
        self.t, self.counts, self.fit, self.p, self.mask = t, counts, fit, p, mask
        self.scale, self.noise, self.dic, self.opts = scale, noise, dic, opts
        self.dispersion, self.background = dispersion, background
        self.bg = np.zeros(n) if background is None else np.asarray(background, np.float64)
        self.disp = np.ones(n) if dispersion is None else np.asarray(dispersion, np.float64)
        self.bounds = parameter_bounds(dic, opts.bound_factor)

    def model(self, st, rows):
        """(m, L) expected counts of the slot state ``st`` of the block's pixels ``rows``."""
        return render(self.t, st, self.dic.response) * self.scale[rows, None] + self.bg[rows, None]

    def deviance(self, rows, mu):
        """(m,) the Poisson deviance of the pixels ``rows`` under expected counts ``mu``."""
        return count_deviance(self.counts[rows], mu, self.fit[rows], self.disp[rows])

    def polish(self, rows, st):
        """The trial state ``st`` of the pixels ``rows`` polished with Poisson weights."""
        return polish_count_state(self.t, self.p[rows], self.mask[rows], st, self.scale[rows], self.noise[rows],
                                  None if self.dispersion is None else self.disp[rows],
                                  None if self.background is None else self.bg[rows], self.bounds, self.opts,
                                  self.dic.response)

    def gain(self, rows, mu, phi):
        """:func:`decomposition.noise.atom_gain` of one more atom ``phi`` (m, L) on the model
        ``mu`` of the pixels ``rows`` -> (gain (m,), amplitude (m,) counts per unit of ``phi``)."""
        return atom_gain(self.counts[rows], mu, phi, self.fit[rows], self.disp[rows])


def _echo_trial_counts(blk, cand, cur, mu):
    """The echo trial of the pixels ``cand`` of a block (state ``cur``, expected counts ``mu``)
    -> (rows of ``cand`` tried, their polished trials, deviance (inf where refused))."""
    t, dic, opts = blk.t, blk.dic, blk.opts
    none = (np.zeros(0, np.int64), take(cur, np.zeros(0, np.int64)), np.zeros(0))
    if opts.max_reflections == 0:
        return none
    gc = cur["fam"] == FAM_GAUSS
    # a pixel whose Gaussian is wider than the grid (WIDE_PSF: an sss hump or a truncated direct
    # taken for one broad atom) leaves residual bumps that are that atom's misfit, not echoes
    narrow = ~(gc & (cur["lsig"] > math.log(dic.grid.sigma_range_ps[1]) + BOUND_TOL)).any(axis=1)
    lsig = np.where(gc, cur["lsig"], -np.inf).max(axis=1)
    sigma_ps = np.exp(lsig)
    y, f = blk.counts[cand], blk.fit[cand]
    # an echo comes after the direct (the earliest Gaussian)
    d0 = np.where(gc, cur["delay"], np.inf).min(axis=1)
    after = f & (t[None, :] > d0[:, None])
    z = anscombe_residual(y, mu, f, blk.disp[cand])
    at_ps, score = residual_peak(t, z, after, np.where(gc, cur["delay"], np.nan), sigma_ps)
    phi = eval_atoms(t, np.full(cand.size, FAM_GAUSS, np.int8), at_ps, lsig, np.zeros(cand.size), dic.response)
    # (the broad excess is a Gaussian GROW_BROAD_FACTOR widths wide for either instrument)
    gain, a_counts = blk.gain(cand, mu, phi)
    wide = eval_atoms(t, np.full(cand.size, FAM_GAUSS, np.int8), at_ps, lsig + np.log(GROW_BROAD_FACTOR),
                      np.zeros(cand.size))
    gain_wide, _ = blk.gain(cand, mu, wide)
    a_direct = np.take_along_axis(cur["amp"], np.argmin(np.where(gc, cur["delay"], np.inf), axis=1)[:, None],
                                  axis=1)[:, 0] * blk.scale[cand]
    tried = np.flatnonzero(narrow & np.isfinite(score) & worth_refitting(gain, gain_wide, a_counts, a_direct,
                                                                        opts.significance_chi2))
    if tried.size == 0:
        return none
    idx = cand[tried]
    base = take(cur, tried)
    alt, _ = with_atom(base, FAM_GAUSS, at_ps[tried], lsig[tried], a_counts[tried] / blk.scale[idx], lalp=0.0)
    fam_trial = alt["fam"].copy()
    alt = blk.polish(idx, alt)
    kept = np.all(alt["fam"] == fam_trial, axis=1)
    resolved = min_gaussian_gap_sigma(alt) >= np.minimum(RESOLVED_SIGMA, min_gaussian_gap_sigma(base))
    dev = np.where(kept & resolved, blk.deviance(idx, blk.model(alt, idx)), np.inf)
    return tried, alt, dev


def _sss_trial_counts(blk, cand, cur, mu):
    """The sss trial of the pixels ``cand`` of a block that have none: an sss at the direct (the
    earliest Gaussian) with its width, at the coarse alpha whose atom removes the most deviance
    with the rest held -> as :func:`_echo_trial_counts`."""
    t, dic, opts = blk.t, blk.dic, blk.opts
    none = (np.zeros(0, np.int64), take(cur, np.zeros(0, np.int64)), np.zeros(0))
    alphas = dic.sss_alphas_per_ps
    gc = cur["fam"] == FAM_GAUSS
    rows = np.flatnonzero(~(cur["fam"] == FAM_SSS).any(axis=1))
    if alphas.size == 0 or rows.size == 0:
        return none
    first = np.argmin(np.where(gc[rows], cur["delay"][rows], np.inf), axis=1)
    d0 = cur["delay"][rows, first]
    ls0 = cur["lsig"][rows, first]
    gains = np.zeros((alphas.size, rows.size))
    amps = np.zeros((alphas.size, rows.size))
    for j, a in enumerate(alphas):
        phi = eval_atoms(t, np.full(rows.size, FAM_SSS, np.int8), d0, ls0, np.full(rows.size, math.log(a)),
                         dic.response)
        gains[j], amps[j] = blk.gain(cand[rows], mu[rows], phi)
    pick = np.argmax(gains, axis=0)
    m = np.arange(rows.size)
    tried = np.flatnonzero(gains[pick, m] >= GROW_TRIAL_FRACTION * opts.significance_chi2)
    if tried.size == 0:
        return none
    r, idx, j = rows[tried], cand[rows[tried]], pick[tried]
    alt, slot = with_atom(take(cur, r), FAM_SSS, d0[tried], ls0[tried],
                          np.maximum(amps[j, tried], 1e-12) / blk.scale[idx], lalp=np.log(alphas[j]))
    m = np.arange(tried.size)
    alt = blk.polish(idx, alt)
    # kept where its sss survives at the direct: an onset the polish moved more than NEAR_SIGMA
    # widths after it is an echo taken for an sss (the response path's far sss), not this trial's
    at_direct = alt["delay"][m, slot] - d0[tried] <= NEAR_SIGMA * np.exp(ls0[tried])
    dev = np.where((alt["fam"][m, slot] == FAM_SSS) & at_direct, blk.deviance(idx, blk.model(alt, idx)), np.inf)
    return r, alt, dev


def grow_counts(samples, det, dic, opts):
    """The forward step of count data on the Gaussian path (``grow=True``, ``noise="poisson"``,
    after the Poisson polish and the threshold): the rules of the response path's trials
    (:mod:`decomposition.response.grow`, step 2) on the Gaussian dictionary's atoms.

    The pursuit and the search weigh every sample with the Poisson noise at the direct's peak;
    a faint Gaussian where the counts are few (a 1 % echo 5 sigma above its own noise is 1 sigma
    of that) never pays there, and :func:`grow_block`'s test of the data term, in the same
    noise, never looks; nor does an sss tail at ~100 photons per pixel.  Every pixel with a
    Gaussian and a free slot gets, in rounds repeated on the pixels that grew:

    * an echo (``max_reflections`` > 0; no Gaussian wider than the grid): a trial Gaussian of
      the pixel's width at its largest smoothed residual on the Anscombe scale
      (:func:`residual_peak`) after its earliest Gaussian and more than GROW_EXCLUDE_SIGMA
      widths from its Gaussians, refitted where :func:`worth_refitting` says so (with the rest
      held, :func:`decomposition.noise.atom_gain`), kept where no atom was lost and the
      Gaussians stay resolved;
    * an sss (the dictionary has sss atoms; the pixel has none): started at the earliest
      Gaussian's delay with its width and the coarse alpha whose atom, with the rest held,
      removes the most deviance, refitted where that is GROW_TRIAL_FRACTION x
      ``significance_chi2`` at least, kept where its sss survives with its onset within
      NEAR_SIGMA widths of that delay (one the polish moved further is an echo taken for an
      sss, the response path's far sss).  The response path refits every coarse alpha, where
      the held gains pick worse; here the pick loses nothing and saves two thirds of the
      refits (docs/history.md, "The count forward step tries an sss on the Gaussian path").

    Each trial is polished with the rest (Poisson weights,
    :func:`decomposition.stages.countpolish.polish_count_state`); a pixel takes the trial of lowest
    Poisson deviance where it drops the deviance by ``significance_chi2``.
    -> (state, grown (n_live,) bool).
    """
    if samples.noise_model != "poisson" or not opts.grow or opts.significance_chi2 <= 0:
        return {k: v.copy() for k, v in det.state.items()}, np.zeros(samples.live.size, bool)

    def step(p, mask, st, noise, _, px):
        return grow_count_block(np.where(samples.fit[px], samples.values[px], 0.0), samples.fit[px], p, mask, st,
                                samples.scale[px], noise,
                                None if samples.dispersion is None else samples.dispersion[px],
                                None if samples.background is None else samples.background[px], dic, opts)

    return each_block(samples, det, opts, step, pixels=True)
