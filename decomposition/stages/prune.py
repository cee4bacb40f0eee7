"""Backward step of a decomposition: drop a Gaussian that sits on the direct's sss onset.

A small sss whose onset lies shortly after the direct is often fitted as an sss starting too
late plus a Gaussian in the gap: the extra Gaussian (an "inter-reflection" 0.5-3 PSF widths
after the direct) and the late onset reach a data term a little below the true split's, from
which no polish returns.  :func:`prune_components` takes every pixel with an sss and a Gaussian
less than ``PRUNE_GAP_SIGMA`` widths after its direct, drops that Gaussian and polishes the rest
with the solver's compiled LM twice: from the other atoms as they are (the sss onset moves back
into the gap) and with the sss onset moved to ``PRUNE_ONSET_SIGMA`` widths after the direct (an
onset too late for the polish to bring back); the lowest penalised objective
(:func:`decomposition.stages.selection.penalised_objective`, the search stage's) of the three is kept.  A
true close inter-reflection stays: its data term pays for its three parameters.

A third trial takes the forward step (:func:`decomposition.stages.grow.grow_block`) after the moved one
-- where more than one Gaussian was close, all of them dropped first (a hump the detection
filled with several) -- so that an echo the late onset hid, or one dropped with the hump, comes
back.
A fourth reads a fast sss hump as the echo it took (:func:`hump_as_echo`).
"""
from __future__ import annotations

import numpy as np

from .candidates import each_block, polish_candidate
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, PRUNE_GAP_SIGMA, PRUNE_ONSET_SIGMA, SEARCH_DEFAULT_ALPHA_PER_PS
from .grow import grow_block, late_fast_sss, with_gaussian
from .objective import objective_variance
from .selection import log_samples, penalised_objective
from ..model.slots import put, take

__all__ = ["close_gaussian", "prune_block", "prune_components"]


def close_gaussian(st, gap_sigma: float = PRUNE_GAP_SIGMA):
    """Pixels of a slot state with an sss and a Gaussian less than ``gap_sigma`` widths after
    the earliest Gaussian (the direct) -> (candidate (n,) bool, slot of that Gaussian (n,) int)."""
    g = st["fam"] == FAM_GAUSS
    n, K = g.shape
    rows = np.arange(n)
    dg = np.where(g, st["delay"], np.inf)
    order = np.argsort(dg, axis=1, kind="stable")
    first = order[:, 0]
    second = order[:, 1] if K > 1 else order[:, 0]
    sigma_ps = np.exp(st["lsig"][rows, first])
    with np.errstate(invalid="ignore"):           # inf - inf where a pixel has no Gaussian
        gap_ps = dg[rows, second] - dg[rows, first]
        cand = (st["fam"] == FAM_SSS).any(axis=1) & (g.sum(axis=1) >= 2) & (gap_ps < gap_sigma * sigma_ps)
    return cand, second


def prune_block(p, mask, st, s_eff, dic, opts, significance_sigma=None, weights=None, spectrum=None,
                bump_test: bool = True):
    """The backward step on one block (normalised profiles ``p`` (n, L), their masks, slot state
    ``st`` (n, K) and noise ``s_eff`` (n,); ``significance_sigma`` (n,) the noise of the labels'
    in-window test, default ``s_eff``; ``weights`` and ``spectrum`` as in
    :func:`decomposition.stages.grow.grow_block`; ``bump_test``: that step's, False for count data)
    -> (state, pruned (n,) bool)."""
    n, L = p.shape
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    out = {k: v.copy() for k, v in st.items()}
    pruned = np.zeros(n, bool)
    cand, slot = close_gaussian(out)
    idx = np.nonzero(cand)[0]
    if idx.size == 0:
        return out, pruned
    s_sig = s_eff if significance_sigma is None else significance_sigma
    log_n = log_samples(mask.used.sum(axis=1)[idx])
    wb = None if weights is None else weights[idx]
    noise = np.maximum(s_eff[idx], 1e-300)
    pb, mb = p[idx], mask[idx]
    cur = take(out, idx)
    dropped = take(out, idx)
    dropped["fam"][np.arange(idx.size), slot[idx]] = FAM_NONE
    # two starts without it: the other atoms as they are, and the sss onset moved back to one
    # width after the direct (a late onset the polish would not bring back that far)
    moved = take(dropped, np.arange(idx.size))
    g = moved["fam"] == FAM_GAUSS
    d0 = np.where(g, moved["delay"], np.inf).min(axis=1)
    sigma_ps = np.exp(np.where(g, moved["lsig"], -np.inf).max(axis=1))
    moved["delay"] = np.where(moved["fam"] == FAM_SSS, (d0 + PRUNE_ONSET_SIGMA * sigma_ps)[:, None], moved["delay"])
    best = cur
    j_best = penalised_objective(t, pb, mb, cur, objective_variance(noise, s_sig[idx], wb, spectrum), log_n, opts,
                                 dic.response)
    won = np.zeros(idx.size, bool)

    def polished(state, rows):
        return polish_candidate(t, pb[rows], mb[rows], state, noise[rows], dic, opts, s_sig[idx][rows],
                                None if wb is None else wb[rows])

    def grown(state, rows):
        return grow_block(pb[rows], mb[rows], state, noise[rows], dic, opts, s_sig[idx][rows], bump_test,
                          weights=None if wb is None else wb[rows], spectrum=spectrum)[0]

    def keep_better(alt, rows):
        s2 = objective_variance(noise[rows], s_sig[idx][rows], None if wb is None else wb[rows], spectrum)
        j = penalised_objective(t, pb[rows], mb[rows], alt, s2, log_n[rows], opts, dic.response)
        w = np.nonzero(j < j_best[rows])[0]
        if w.size:
            put(best, rows[w], take(alt, w))
            j_best[rows[w]] = j[w]
            won[rows[w]] = True

    every = np.arange(idx.size)
    keep_better(polished(dropped, every), every)
    moved_polished = polished(moved, every)
    keep_better(moved_polished, every)
    if opts.grow:
        # a third trial: the moved one after the forward step, where more than one Gaussian was
        # close all of them dropped first (an sss hump the detection filled with several) --
        # either way a true echo that the late onset or the hump had hidden, or that was
        # dropped with it, comes back where the residual asks for it
        gd = np.where(g, moved["delay"], np.inf)
        close = g & (gd > d0[:, None]) & (gd - d0[:, None] < PRUNE_GAP_SIGMA * sigma_ps[:, None])
        third = take(moved_polished, every)
        rows = np.nonzero(close.any(axis=1))[0]
        if rows.size:
            cleared = take(moved, rows)
            cleared["fam"] = np.where(close[rows], FAM_NONE, cleared["fam"]).astype(cleared["fam"].dtype)
            put(third, rows, polished(cleared, rows))
        keep_better(grown(third, every), every)
        # a fourth: the sss hump as an echo (:func:`hump_as_echo`), then the forward step
        rows, trial = hump_as_echo(t, cur, moved, d0, sigma_ps, dic.response)
        if rows.size:
            keep_better(grown(polished(trial, rows), rows), rows)
    w = np.nonzero(won)[0]
    if w.size:
        put(out, idx[w], take(best, w))
        pruned[idx[w]] = True
    return out, pruned


def hump_as_echo(t_ps, cur, moved, d0_ps, sigma_ps, response=None):
    """The fourth trial of :func:`prune_block`: where the sss of ``cur`` (n, K) peaks more than
    ``SWAP_MODE_GAP_SIGMA`` widths after the direct (``d0_ps`` (n,), the pixel's width
    ``sigma_ps`` (n,)) and decays fast enough to pass for a Gaussian (the rule of
    :func:`decomposition.stages.grow.swap_block`), ``moved`` (the close Gaussian dropped, the onset one
    width after the direct) with every Gaussian between the direct and that peak dropped, a
    Gaussian of the pixel's width at the peak, and the sss at the search's default
    attenuation -> (rows (m,), their trial (m, K)).

    The sss swap of :func:`decomposition.stages.grow.swap_block` needs a free slot and keeps the
    Gaussians the detection put in the hump; a fast sss that took an echo 6 widths after the
    direct, with two Gaussians filling the true sss's hump and every slot taken, reached
    neither it nor the trials above.  ``response``: the atoms are a measured response's.
    """
    _, mode_ps, passes = late_fast_sss(t_ps, cur, d0_ps, sigma_ps, response)     # (only pixels with an sss)
    rows = np.nonzero(passes)[0]
    trial = take(moved, rows)
    g = trial["fam"] == FAM_GAUSS
    between = g & (trial["delay"] > d0_ps[rows, None]) & (trial["delay"] < mode_ps[rows, None])
    trial["fam"] = np.where(between, FAM_NONE, trial["fam"]).astype(trial["fam"].dtype)
    trial["lalp"] = np.where(trial["fam"] == FAM_SSS, np.log(SEARCH_DEFAULT_ALPHA_PER_PS), trial["lalp"])
    free = (trial["fam"] == FAM_NONE).any(axis=1)
    rows, trial = rows[free], take(trial, np.nonzero(free)[0])
    trial, _ = with_gaussian(trial, mode_ps[rows], np.log(sigma_ps[rows]))
    return rows, trial


def prune_components(samples, det, dic, opts):
    """The ``prune`` stage of :func:`decomposition.decompose` (``prune=True``): :func:`prune_block` on the
    detected (and searched) atoms of the live pixels, block by block -> (state, pruned (n_live,))."""
    float_data = samples.noise_model != "poisson"      # the forward step's bump test
    return each_block(samples, det, opts,
                      lambda p, mask, st, noise, sig, weights, spectrum: prune_block(p, mask, st, noise, dic, opts, sig,
                                                                                     weights, spectrum, float_data),
                      weights=True)
