"""Neighbours' answers as starts: the first step of the spatial coupling (:mod:`decomposition.image.spatial`).

A pixel is *in doubt* when it is flagged AMBIGUOUS or POOR_FIT, or when its component set or its
direct delay agrees with fewer than half of its 8 neighbours (a neighbour shares the delay where the two lie within
``doubt_delay_ps``, or where the pixel's lies between that neighbour's and the opposite
neighbour's: an inclined surface, an object's edge).  Each pixel in doubt is refitted
(:func:`decomposition.model.refine.refine`) from each neighbour's parameter set (its
components and their parameters), and the fits are compared on the penalised objective J
(:func:`decomposition.stages.selection.penalised`) with the data term read as the per-pixel
search read it (:func:`objective_weights`: where the noise follows the signal, in the
detector's variance law).  A refit replaces the pixel's own fit where its J is lower by more
than the evidence tolerance (``ambiguity_chi2``,
:func:`decomposition.stages.selection.ambiguity_tolerance`), or lower by less and shared by
as many neighbours as the own fit; among those, within the tolerance of the lowest J, the
fit most neighbours share is kept (the data do not choose there; the neighbours do).  A start
is refitted only where it could compete: its J with only the amplitudes re-solved at its
own shapes (:func:`_screen`, one render and a small linear solve) must lie within
:data:`_SCREEN_MARGIN` times the pixel's own J of that J; a neighbour on another surface or
of an unrelated scene is not refitted.  The
search's AMBIGUOUS is resolved (cleared, unless the final fit's own quality test sets it
again) where a neighbour's start was taken or where the pixel's answer agrees with its
neighbours'.
"""
from __future__ import annotations

import numpy as np

from core.model import BACKGROUND_KEY, time_axis_ps
from ..flags import AMBIGUOUS, POOR_FIT
from ..kernels.screen import screened_rss
from ..model.refine import hold_params, slot_arrays, unit_widths
from ..stages.selection import ambiguity_tolerance, families, free_parameters, log_samples, penalised
from .spatial import (NEIGHBOURS_8, Coupling, SpatialOptions, noise_variance, objective, objective_weights, refit,
                      shifted, take_rows)

__all__ = ["in_doubt", "neighbour_starts"]


#: A neighbour's start is refitted only where its J at its own shapes, the amplitudes re-solved
#: (:func:`_screen`), exceeds the pixel's own J by less than this many times the own J's
#: magnitude: a refit moves the shapes from there, but a start whose shapes leave a misfit many
#: times the pixel's own is another scene's answer, not its neighbourhood's (on the spatial
#: bench's scenes every start taken lay within 15 times)
_SCREEN_MARGIN = 20.0


def _screen(c: Coupling, rows: np.ndarray, start: dict, weights: np.ndarray) -> np.ndarray:
    """(n,) J (:func:`objective`) of the starts ``start`` (n-shaped) on the pixels ``rows``
    (``weights`` (P, L) every pixel's sample weights) with
    only their amplitudes (and the offset, where :func:`refit` fits it) re-solved by weighted
    linear least squares at the starts' shapes (delays, widths, decay rates; the held values put
    in), without a sign constraint: one render and a small linear solve per start, compiled
    (:func:`decomposition.kernels.screen.screened_rss`).
    A refit from the start (:func:`refit`) moves the shapes too and keeps the amplitudes
    positive; the screen's J is its J before the shapes move."""
    s = c.samples
    n = rows.size
    out = np.empty(n)
    if n == 0:
        return out
    hold = {k: v[rows] for k, v in c.hold.items()}
    start = hold_params(start, hold, (n,)) if hold else start
    slots = slot_arrays(start if c.irf is None else unit_widths(start), (n,))
    present = slots["present"]
    if BACKGROUND_KEY in start:
        b = np.asarray(start[BACKGROUND_KEY], np.float64)
        fit_bg = np.isfinite(b) & (b != 0)
        held_bg = np.where(fit_bg | ~np.isfinite(b), 0.0, b)
    else:
        fit_bg, held_bg = np.zeros(n, bool), np.zeros(n)
    t = time_axis_ps(s.n_bins, s.axis.time_bin_ps, s.axis.t0_ps)
    k_free = free_parameters(families(start), c.widths)
    noise2 = noise_variance(c)[rows]
    log_n = log_samples(s.fit.sum(axis=1))[rows]
    # in order of pixel: the starts of one pixel share its weighted data in the kernel
    order = np.argsort(rows, kind="stable")
    rss = np.empty(n)
    rss[order] = screened_rss(s.values, np.asarray(weights, np.float64), rows[order], held_bg[order], t,
                              slots["delay"][order], slots["sigma"][order], slots["alpha"][order], present[order],
                              fit_bg[order], c.inst)
    out[:] = penalised(rss / noise2, k_free, log_n, c.opts.search_penalty)
    return out


def _signature(params: dict) -> np.ndarray:
    """(P,) int: the component set (direct, sss, number of inter-reflections) as one code."""
    fam = families(params) != 0
    return fam[:, 0] + 2 * fam[:, 1] + 4 * fam[:, 2:].sum(axis=1)


def _neighbour_counts(c: Coupling, params: dict, pix: np.ndarray, sig: np.ndarray, d: np.ndarray,
                      doubt_delay_ps: float):
    """How many of the decomposed 8 neighbours of the pixels ``pix`` (n,) share an answer of
    component set ``sig`` (n,, :func:`_signature`) and direct delay ``d`` (n,, ps; NaN: none),
    the neighbours read in ``params`` -> (n,) each: the neighbours, those with the same set,
    those with the same delay, those with both.

    A neighbour shares the delay where the two lie within ``doubt_delay_ps`` (or neither has a
    direct), or where ``d`` lies between that neighbour's delay and the opposite neighbour's
    (to within ``doubt_delay_ps``): on a surface inclined to the scan, neighbours' delays
    differ by the slope, and at an object's edge a pixel lies between the two surfaces."""
    live_i = np.where(c.live, np.arange(c.live.size), -1)
    nsig = np.where(c.live, _signature(params), -1)
    nd_all = params["direct_delay_ps"]
    n, same_set, same_delay, same = (np.zeros(pix.size, np.int64) for _ in range(4))
    for dy, dx in NEIGHBOURS_8:
        nb = shifted(live_i, c.shape, dy, dx, -1)[pix]
        ok = nb >= 0
        nb = np.where(ok, nb, 0)
        ns, nd = nsig[nb], nd_all[nb]
        op = shifted(live_i, c.shape, -dy, -dx, -1)[pix]
        od = np.where(op >= 0, nd_all[np.where(op >= 0, op, 0)], np.nan)
        with np.errstate(invalid="ignore"):
            set_ok = ok & (ns == sig)
            between = (d >= np.fmin(nd, od) - doubt_delay_ps) & (d <= np.fmax(nd, od) + doubt_delay_ps)
            delay_ok = ok & (between | (np.isnan(nd) & np.isnan(d)))
        n += ok
        same_set += set_ok
        same_delay += delay_ok
        same += set_ok & delay_ok
    return n, same_set, same_delay, same


def _agreement(c: Coupling, params: dict, doubt_delay_ps: float):
    """(P,) bool each: whether a pixel's component set, and its direct delay, agree with at
    least half of its decomposed 8 neighbours (:func:`_neighbour_counts`; a pixel without any
    neighbour agrees)."""
    pix = np.arange(c.live.size)
    n, same_set, same_delay, _ = _neighbour_counts(c, params, pix, _signature(params), params["direct_delay_ps"],
                                                   doubt_delay_ps)
    live = c.live
    return ~live | (2 * same_set >= n), ~live | (2 * same_delay >= n)


def in_doubt(c: Coupling, options: SpatialOptions) -> np.ndarray:
    """(P,) bool: decomposed pixels flagged AMBIGUOUS or POOR_FIT, or whose component set or
    direct delay disagrees with most of their 8 neighbours."""
    agree_set, agree_delay = _agreement(c, c.params, options.doubt_delay_ps)
    flagged = (c.flags & (AMBIGUOUS | POOR_FIT)) != 0
    return c.live & (flagged | ~agree_set | ~agree_delay)


def neighbour_starts(c: Coupling, options: SpatialOptions) -> None:
    """Step 1 (module docstring): the pixels in doubt refitted from their neighbours' answers,
    each keeping its own fit or the one of those that the rule of the module docstring picks (a
    lower J, the neighbours deciding within the evidence tolerance); ``c`` updated in place."""
    doubt = in_doubt(c, options)
    c.info["spatial_doubt"] = int(doubt.sum())
    c.info["spatial_starts_screened"] = 0
    taken = np.zeros(c.live.size, bool)
    rows = np.flatnonzero(doubt)
    if rows.size and options.neighbour_starts:
        idx = np.arange(c.live.size)
        live_i = np.where(c.live, idx, -1)
        sig = _signature(c.params)
        d = c.params["direct_delay_ps"]
        pix, src = [], []
        for dy, dx in NEIGHBOURS_8:
            nb = shifted(live_i, c.shape, dy, dx, -1)[rows]
            ok = nb >= 0
            nb_ok = np.where(ok, nb, 0)
            # a start is a different answer: another component set or another direct delay
            # (refitted, one that agrees with the pixel's own would end where that did)
            with np.errstate(invalid="ignore"):
                other = (sig[nb_ok] != sig[rows]) | ~(np.abs(d[nb_ok] - d[rows]) <= options.doubt_delay_ps)
            ok &= other & (sig[nb_ok] > 0)
            pix.append(rows[ok])
            src.append(nb[ok])
        pix, src = np.concatenate(pix), np.concatenate(src)
        # one start per pixel for each answer (component set, delay to within doubt_delay_ps)
        bucket = np.nan_to_num(np.floor(d[src] / options.doubt_delay_ps), nan=-1).astype(np.int64)
        _, first = np.unique(np.stack([pix, sig[src], bucket]), axis=1, return_index=True)
        first.sort()
        pix, src = pix[first], src[first]
        if pix.size:
            own = take_rows(c.params, rows)
            weights = objective_weights(c, c.params)
            j_best = objective(c, rows, own, weights[rows])
            start = take_rows(c.params, src)
            if BACKGROUND_KEY in start:         # the pixel's own offset, fitted again
                start[BACKGROUND_KEY] = c.params[BACKGROUND_KEY][pix]
            # a start whose misfit at its own shapes (the amplitudes re-solved) is many times the
            # pixel's own J is not refitted (module docstring)
            j_own = j_best[np.searchsorted(rows, pix)]
            near = _screen(c, pix, start, weights) - j_own < _SCREEN_MARGIN * np.abs(j_own)
            c.info["spatial_starts_screened"] = int(pix.size - near.sum())
            pix, src, start = pix[near], src[near], take_rows(start, near)
            fits = refit(c, pix, start, weights[pix]) if pix.size else start
            j = objective(c, pix, fits, weights[pix]) if pix.size else np.zeros(0)
            # the candidates: each pixel's own fit (index -1) and its refits from the starts
            cand_pos = np.concatenate([np.arange(rows.size), np.searchsorted(rows, pix)])
            cand_j = np.concatenate([j_best, j])
            cand_fit = np.concatenate([np.full(rows.size, -1), np.arange(pix.size)])
            cand_sig = np.concatenate([_signature(own), _signature(fits) if pix.size else np.zeros(0, np.int64)])
            cand_d = np.concatenate([own["direct_delay_ps"], fits["direct_delay_ps"]])
            *_, agree = _neighbour_counts(c, c.params, rows[cand_pos], cand_sig, cand_d, options.doubt_delay_ps)
            # a start replaces the pixel's own fit where its J is lower: by more than the
            # evidence tolerance, or by less and it agrees with as many neighbours as the own
            # (within the tolerance the data do not choose, and the neighbours veto); among
            # those, within the tolerance of the lowest J, the fit most neighbours share, then
            # the lower J
            tol = ambiguity_tolerance("evidence", c.opts)
            is_own = cand_fit < 0
            own_agree = agree[:rows.size][cand_pos]
            ok = is_own | ((cand_j < j_best[cand_pos]) &
                           ((cand_j < j_best[cand_pos] - tol) | (agree >= own_agree)))
            j_min = np.full(rows.size, np.inf)
            np.minimum.at(j_min, cand_pos[ok], cand_j[ok])
            tie = ok & (cand_j <= j_min[cand_pos] + tol)
            order = np.lexsort((cand_j, -agree, ~tie, ~ok, cand_pos))
            first = order[np.r_[True, cand_pos[order][1:] != cand_pos[order][:-1]]]
            first = first[cand_fit[first] >= 0]
            win, from_row = rows[cand_pos[first]], cand_fit[first]
            for k in c.params:
                c.params[k][win] = fits[k][from_row]
            taken[win] = True
    c.info["spatial_starts_taken"] = int(taken.sum())
    agree_set, agree_delay = _agreement(c, c.params, options.doubt_delay_ps)
    c.resolved = taken | (agree_set & agree_delay)
