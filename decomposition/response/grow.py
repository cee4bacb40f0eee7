"""Forward steps of the response path: the components its detection's single noise level misses.

On float data the grow stage (:mod:`decomposition.stages.grow`) has already added echoes and
swapped late sss peaks over the response's atoms, before the labels, as for the Gaussian PSF;
here only the direct's steps (0, 0b) run for them.  Count data take every step below.  The
instrument is a measured response or the Gaussian PSF of each pixel's width
(:class:`decomposition.model.atoms.GaussianPSF`, ``likelihood_counts``); "widths" below are each
pixel's (the response's Gaussian-equivalent one).

The detection (:func:`decomposition.stages.detect.detect_components`) weighs every sample with
one noise; for count data that is the Poisson noise at the signal, i.e. at the direct's peak.  A
component where the counts are few never pays its penalty there: at ~100 photons per pixel an
sss tail, and at any level a faint echo far after the direct (a 1 % echo 5 sigma above its own
Poisson noise is 1 sigma of the noise at the direct's peak).  After the refinement
(:func:`grow_response`):

0. **A direct** ("d" asked): a pixel whose fit has no direct, or one that explains next to
   nothing (taken out alone it raises the deviance by less than ``significance_chi2``), while
   other atoms hold light, is refitted with a direct started at its sss onset and at the peak
   of its data smoothed over the response's width (there also with the sss restarted at the
   direct with each coarse alpha): at few counts the detection's first atom can be a fast sss
   whose onset lies before the direct and which takes the direct's light.  The best trial
   that keeps a direct is taken where that direct is significant in it; where the fit without
   it lies within ``ambiguity_sigma`` sqrt(2 n) with a split more than ``ambiguity_split``
   away, or where a direct that explains nothing stays, the pixel is AMBIGUOUS (the search
   stage's rule, :mod:`decomposition.stages.search`); a direct that explains nothing where no sample
   sees it, far before its sss, is not reported (:func:`_unseen_direct`).  A pixel left with
   an sss and no direct is AMBIGUOUS unless ``sss_alone`` (:mod:`decomposition.response.path`).
0b. **A direct before the window** ("d" asked; its delay before the first sample, so only its
   falling edge is seen): refitted with the direct started at the window's edge and at
   EARLY_DIRECT_STARTS_SIGMA response widths before it, the pixel keeping the lowest deviance
   (its own fit included; a refit whose direct slid out to where no sample sees it, far
   before its sss, is not taken: :func:`_unseen_direct`).  From the edge alone the fit can slide the direct out with its
   amplitude growing to match what it leaves, and stop there: on ``bench realism``'s
   truncated rows at 10,000 photons the worst fits lay 13-17 ps early with a deviance 2-36
   above the reference's.
0c. **An sss onset far after its direct** (count data, "d" and "s" asked; after step 1): an sss whose
   onset lies more than ONSET_RESTART_SIGMA response widths after a direct inside the window
   is refitted with the onset started at the direct, and takes that refit where it keeps
   every atom and the direct inside the window and lowers the deviance.  At few counts the fit
   can stop with the onset 3-9 widths late and the direct moved later to fill the gap.  A
   direct before the window is left to step 0b: there the onset started at it let the direct
   slide out, its amplitude grown tenfold or more, for small deviance gains.  Gaussian data are
   not refitted: no pixel took the refit there (docs/history.md).
1. **Far sss** (count data, "r" and "s" asked, a free inter-reflection slot): an sss whose onset lies more
   than NEAR_SIGMA widths after the direct (sss is light entering where the direct is
   reflected; one far after it, alpha at its bound, is an echo the detection took for an sss --
   about half of the pixels of a 5-sigma echo in white noise) is replaced by a shifted copy at
   its peak where that lowers the penalised deviance, deviance + ``search_penalty`` x ln(n)
   per free parameter (the search stage's objective; the copy has one parameter fewer).
2. **Rounds**, on the pixels with a direct, repeated on those that grew until none does:

   * an sss (count data, "s" asked, none yet): started at the direct delay, once per coarse
     alpha, the best alpha's refit kept where its sss survives (as the trial always was);
   * an echo, a shifted copy of the response (count data, "r" asked, a free slot): at the largest
     residual in noise sigmas after the direct -- on the variance-stabilised scale,
     :func:`decomposition.noise.anscombe_residual` (bounded where the model is ~0, where the
     Pearson residual makes one stray count a 7-sigma event) -- smoothed over the response's width and more
     than GROW_EXCLUDE_SIGMA widths from the pixel's shifted atoms
     (:func:`decomposition.stages.grow.residual_peak`, the Gaussian path's rule); refitted only where
     :func:`decomposition.stages.grow.worth_refitting` says so, and kept only where the refit lost no
     atom and the shifted atoms stay resolved (RESOLVED_SIGMA widths apart, or no closer than
     before: an atom that slid onto the direct splits its peak).

   Each trial is refitted with the rest (:func:`decomposition.response.refine.refit_slots`,
   the Poisson likelihood for counts), and a pixel takes the trial of lowest deviance where it lowers
   its deviance (:func:`deviance`: the Poisson deviance for counts, RSS / s^2 with the
   significance noise otherwise) by at least ``significance_chi2`` -- the likelihood-ratio
   statistic of the added component, the threshold the in-window rule applies to every atom.
3. **Weak echoes**: an echo added above that, taken out of the final model alone, raises the
   deviance by less than ``significance_chi2`` (:func:`decomposition.noise.removal_deviance`)
   is dropped and its pixel refitted without it (an echo can let the refit move the direct onto
   light it had missed, and then explain next to nothing itself).

The echo steps need count data, ``grow=True`` and ``significance_chi2 > 0`` (they find what only
the significance rule keeps).  ``info``: ``response_direct_restored``, ``response_early_direct_moved``,
``response_onset_restarted``, ``response_sss_added``,
``response_echo_added``, ``response_sss_swapped``.
"""

# One module over 600 lines on purpose: the response path's forward steps share one context
# (GrowContext) and its refit helpers, and each step is a function here in the order grow_response
# runs them.
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import convolve1d

from core.model import BACKGROUND_KEY, DIRECT_KEYS
from ..constants import (EARLY_DIRECT_NEAR_SIGMA, EARLY_DIRECT_STARTS_SIGMA, FAM_GAUSS, FAM_NONE, FAM_SSS,
                         GROW_BROAD_FACTOR, GROW_TRIAL_FRACTION, NEAR_SIGMA, ONSET_RESTART_SIGMA, PRE_DIRECT_LEVEL,
                         RESOLVED_SIGMA, SSS_SLOT, UNSEEN_DIRECT_LEAD_SIGMA)
from ..stages.grow import min_gaussian_gap_sigma, residual_peak, worth_refitting
from ..stages.selection import ambiguity_tolerance, free_parameters, is_ambiguous, log_samples, penalised
from ..noise import anscombe_residual, atom_gain, count_deviance, removal_deviance
from ..model.atoms import (GaussianPSF, instrument_rows, params_components, params_profile, shifted_slot_atoms,
                           slot_atoms, sss_slot_atoms)
from .refine import Slots, pixel_widths, refine_rows, refit_slots
from ..model.slots import select_rows
from ..model.fidelity import fidelity

__all__ = ["GrowContext", "deviance", "grow_response"]


class GrowContext:
    """What the forward steps need of the response path for its n live pixels.

    Parameters
    ----------
    samples : decomposition.stages.prepare.Samples
    irf : InstrumentResponse or GaussianPSF
                                       the instrument: a measured response on the samples'
                                       step, or the Gaussian PSF of each pixel's held width
                                       (:class:`decomposition.model.atoms.GaussianPSF`)
    held : ndarray (n,)                the offset already subtracted from the profiles, units
    fit_bg : bool                      the offset is fitted jointly (the ``b`` family)
    refine_kw : dict                   keywords of :func:`refit_slots` for all n pixels
    opts : SolverOptions

    ``width`` (n,): each pixel's (Gaussian-equivalent) width, ps (``refine_kw["sigma_eq"]``), the
    unit of every distance rule here.
    """

    def __init__(self, samples, irf, held, fit_bg, refine_kw, opts):
        self.samples, self.irf, self.held, self.fit_bg = samples, irf, held, bool(fit_bg)
        self.refine_kw, self.opts = refine_kw, opts
        self.counts = samples.noise_model == "poisson"
        live = samples.live
        # the widths the refit writes into the parameters (one for a response, one per pixel for
        # the Gaussian PSF)
        self.width, self.log_width = pixel_widths(refine_kw["sigma_eq"], live.size)
        self.values = np.asarray(samples.values[live], np.float64)
        self.fit = samples.fit[live]
        self.t = refine_kw["t"]
        # Gaussian data: the noise (units of the samples) of the in-window significance test
        self.sigma = samples.significance_sigma(live, samples.noise_eff[live]) * samples.scale[live]

    def model(self, params, background) -> np.ndarray:
        """(m, L) the model of m pixels' ``params`` plus ``background`` (m,), units of the samples
        (the response's table atoms, :func:`decomposition.model.atoms.params_profile`)."""
        p = dict(params)
        p[BACKGROUND_KEY] = background
        return params_profile(self.irf, self.t, p)

    def atoms(self, rows, fam, delay, lalp) -> np.ndarray:
        """(m, K, L) the atoms of the pixels ``rows``' slot arrays (m, K)
        (:func:`decomposition.model.atoms.slot_atoms`)."""
        return slot_atoms(instrument_rows(self.irf, rows), self.t, fam, delay, lalp)

    def refit(self, rows, fam, delay, lalp, params, background) -> Slots:
        """:func:`refit_slots` of the pixels ``rows`` from the slots given (``params`` and
        ``background`` the model of the first weights)."""
        kw = refine_rows(self.refine_kw, rows)
        p0 = dict(params)
        p0[BACKGROUND_KEY] = background
        y = self.samples.profiles[self.samples.live[rows]]
        return refit_slots(y, fam, delay, lalp, self.held[rows], self.fit_bg, p0, **kw)


def deviance(ctx: GrowContext, rows, params, background) -> np.ndarray:
    """(m,) the deviance of the pixels ``rows`` under ``params`` plus ``background``, in chi2
    units: the Poisson deviance over the dispersion squared for counts
    (:func:`decomposition.noise.count_deviance`), the residual sum of squares over the
    significance noise squared otherwise (each sample weighed by the signal-noise stage's
    weights where the noise follows the signal); over the fitted samples."""
    return _model_deviance(ctx, rows, ctx.model(params, background))


def _model_deviance(ctx: GrowContext, rows, mu) -> np.ndarray:
    """:func:`deviance` of a model ``mu`` (m, L)."""
    if ctx.counts:
        return count_deviance(ctx.values[rows], mu, ctx.fit[rows], ctx.samples.dispersion[ctx.samples.live[rows]])
    r = np.where(ctx.fit[rows], ctx.values[rows] - mu, 0.0)
    w = ctx.refine_kw.get("weights")
    rw = r if w is None else r * w[rows]
    return np.einsum("pl,pl->p", rw, r) / np.square(np.maximum(ctx.sigma[rows], 1e-300))


def _removal_deviance(ctx: GrowContext, rows, sub: Slots, slots=slice(None)) -> np.ndarray:
    """(m, K') how much the deviance of the pixels ``rows`` rises when each atom of ``sub`` alone
    is taken out, the others held (:func:`decomposition.noise.removal_deviance` for counts; the
    atom's energy over s^2 for Gaussian data at the least-squares amplitudes); 0 for empty slots.
    ``slots``: the slots asked about (a slice of the K; default all), each atom's answer the same
    whichever others are asked."""
    mu = ctx.model(sub.params, sub.background)
    scale = ctx.samples.scale[ctx.samples.live[rows]]
    fam, delay, lalp, amp = sub.fam[:, slots], sub.delay[:, slots], sub.lalp[:, slots], sub.amp[:, slots]
    atoms = ctx.atoms(rows, fam, delay, lalp) * (amp * scale[:, None])[:, :, None]
    if ctx.counts:
        return removal_deviance(ctx.values[rows], mu, atoms, ctx.fit[rows],
                                ctx.samples.dispersion[ctx.samples.live[rows]])
    base = _model_deviance(ctx, rows, mu)
    out = np.zeros(fam.shape)
    for k in range(fam.shape[1]):
        on = fam[:, k] != FAM_NONE
        if on.any():
            out[on, k] = _model_deviance(ctx, rows[on], mu[on] - atoms[on, k]) - base[on]
    return out


def _drop_weak_echoes(ctx: GrowContext, slots: Slots, grown: np.ndarray) -> tuple[Slots, np.ndarray]:
    """The echoes the rounds added (``grown`` (n, K) bool) that are no longer significant in
    the final model -- taken out alone, the others held, the deviance rises by less than
    ``significance_chi2`` -- dropped, and their pixels refitted without them.  (An echo can let
    the refit move the direct onto light it had missed, and then explain next to nothing
    itself.)  -> (slots, grown echoes kept)."""
    rows = np.flatnonzero(grown.any(axis=1))
    if rows.size == 0:
        return slots, grown
    sub = _sub(slots, rows)
    weak = grown[rows] & (_removal_deviance(ctx, rows, sub) < ctx.opts.significance_chi2)
    w = np.flatnonzero(weak.any(axis=1))
    if w.size == 0:
        return slots, grown
    f = sub.fam[w].copy()
    f[weak[w]] = FAM_NONE
    t_w = ctx.refit(rows[w], f, sub.delay[w], sub.lalp[w], {k: v[w] for k, v in sub.params.items()},
                    sub.background[w])
    its = slots.iterations.copy()
    its[rows[w]] += t_w.iterations
    slots = _put(slots, rows[w], t_w, np.ones(w.size, bool))._replace(iterations=its)
    grown = grown.copy()
    grown[rows[w]] &= slots.fam[rows[w]] == FAM_GAUSS
    return slots, grown


def _residual_sigmas(ctx: GrowContext, rows, mu) -> np.ndarray:
    """(m, L) residual of the counts of the pixels ``rows`` from their model ``mu`` (m, L) in
    noise sigmas (Anscombe's)."""
    return anscombe_residual(ctx.values[rows], mu, ctx.fit[rows], ctx.samples.dispersion[ctx.samples.live[rows]])


def _sub(slots: Slots, rows) -> Slots:
    return Slots(*(({k: v[rows] for k, v in x.items()} if isinstance(x, dict) else x[rows]) for x in slots))


def _unseen_direct(ctx: GrowContext, slots: Slots, rows) -> np.ndarray:
    """(rows.size,) bool: the direct (slot 0) of the pixels ``rows`` lies where no sample sees it
    -- before the window, its response at the first sample below PRE_DIRECT_LEVEL of its peak --
    and more than UNSEEN_DIRECT_LEAD_SIGMA Gaussian-equivalent widths before the light it would
    lead (the sss onset; the first sample without an sss).  Nothing in the data places it there:
    a direct that explains nothing went to 195 ps before the window under a tailed response
    (53 widths before its sss), where the response's tail leaves it no trace."""
    rows = np.asarray(rows, np.int64)
    if rows.size == 0:
        return np.zeros(0, bool)
    d = slots.delay[rows, 0]
    lag = ctx.t[0] - d
    width = ctx.width[rows]
    with np.errstate(invalid="ignore"):
        if isinstance(ctx.irf, GaussianPSF):
            faint = np.exp(-0.5 * np.square(np.maximum(lag, 0.0) / width)) < PRE_DIRECT_LEVEL
        else:
            faint = ctx.irf.evaluate(np.maximum(lag, 0.0)) < PRE_DIRECT_LEVEL * ctx.irf.peak_per_ps
        unseen = (lag > 0) & faint
        led = np.where(slots.fam[rows, SSS_SLOT] == FAM_SSS, slots.delay[rows, SSS_SLOT], ctx.t[0])
        return unseen & (led - d > UNSEEN_DIRECT_LEAD_SIGMA * width)


def _without_direct(slots: Slots, rows) -> Slots:
    """``slots`` with the direct (slot 0) of the pixels ``rows`` removed."""
    if np.size(rows) == 0:
        return slots
    fam, amp = slots.fam.copy(), slots.amp.copy()
    fam[rows, 0], amp[rows, 0] = FAM_NONE, 0.0
    params = {k: v.copy() for k, v in slots.params.items()}
    for k in DIRECT_KEYS:
        if k in params:
            params[k][rows] = np.nan
    return slots._replace(fam=fam, amp=amp, params=params)


def _put(slots: Slots, rows, new: Slots, take) -> Slots:
    """``slots`` with the pixels ``rows[take]`` replaced by the rows ``take`` of ``new``."""
    if not np.any(take):
        return slots
    r = rows[take]
    out = []
    for x, y in zip(slots, new):
        if isinstance(x, dict):
            x = {k: v.copy() for k, v in x.items()}
            for k in x:
                x[k][r] = y[k][take]
        else:
            x = x.copy()
            x[r] = y[take]
        out.append(x)
    return Slots(*out)


def _pick_rows(win, a: Slots, b: Slots) -> Slots:
    """The rows of ``a`` where ``win``, of ``b`` elsewhere."""
    return Slots(*(select_rows(win, x, y) for x, y in zip(a, b)))


def _gap_sigma(fam, delay, log_width) -> np.ndarray:
    """(m,) the least gap between two shifted atoms of slot arrays (m, K), in the pixels' widths
    (``log_width`` (m,), ln ps)."""
    st = {"fam": fam, "delay": delay, "lsig": np.broadcast_to(log_width[:, None], fam.shape)}
    return min_gaussian_gap_sigma(st)


def _all_kept(fam_trial, fam_refit) -> np.ndarray:
    """(m,) the refit kept every atom of the trial (the echo step adds one, it loses none)."""
    return np.all(fam_refit == fam_trial, axis=1)


def _gate(ctx: GrowContext) -> float:
    """The held gain a trial needs before it is refitted."""
    return GROW_TRIAL_FRACTION * ctx.opts.significance_chi2


def _sss_trial(ctx: GrowContext, cur: Slots, rows, mu, alphas_per_ps):
    """The best sss trial of the pixels ``rows`` (their model ``mu`` (m, L)) over
    ``alphas_per_ps`` -> (slots, deviance).  Pixels where no alpha's atom at the direct would
    remove :func:`_gate` of the deviance with the rest held are not refitted (deviance inf)."""
    sub = _sub(cur, rows)
    m = rows.size
    gain = np.zeros(m)
    for alpha in alphas_per_ps:
        phi = sss_slot_atoms(instrument_rows(ctx.irf, rows), ctx.t, sub.delay[:, 0], np.full(m, alpha))
        gain = np.maximum(gain, _held_gain(ctx, rows, mu, phi)[0])
    i = np.flatnonzero(gain >= _gate(ctx))
    dev = np.full(m, np.inf)
    spent = np.zeros(m, np.int64)
    if i.size == 0:
        return sub._replace(iterations=spent), dev
    base = _sub(sub, i)
    trial, dev_i = None, None
    for alpha in alphas_per_ps:
        f, d, la = base.fam.copy(), base.delay.copy(), base.lalp.copy()
        f[:, SSS_SLOT], d[:, SSS_SLOT], la[:, SSS_SLOT] = FAM_SSS, d[:, 0], math.log(alpha)
        t_a = ctx.refit(rows[i], f, d, la, base.params, base.background)
        spent[i] += t_a.iterations
        dev_a = np.where(t_a.fam[:, SSS_SLOT] == FAM_SSS, deviance(ctx, rows[i], t_a.params, t_a.background),
                         np.inf)
        if trial is None:
            trial, dev_i = t_a, dev_a
        else:
            win = dev_a < dev_i
            trial, dev_i = _pick_rows(win, t_a, trial), np.where(win, dev_a, dev_i)
    dev[i] = dev_i
    return _put(sub, i, trial, np.ones(i.size, bool))._replace(iterations=spent), dev


def _held_gain(ctx: GrowContext, rows, mu, phi):
    """The Poisson deviance one more atom of shape ``phi`` (m, L) would remove from the model
    ``mu`` (m, L) of the counts of the pixels ``rows``, its amplitude at its best (>= 0), the
    rest held (:func:`decomposition.noise.atom_gain`) -> (gain (m,), amplitude (m,) counts per
    unit of ``phi``)."""
    fit = ctx.fit[rows]
    return atom_gain(ctx.values[rows], mu, np.where(fit, phi, 0.0), fit, ctx.samples.dispersion[ctx.samples.live[rows]])


def _echo_trial(ctx: GrowContext, cur: Slots, rows, mu):
    """The echo trial of the pixels ``rows`` (their model ``mu`` (m, L)) -> (slots, deviance,
    tried (m,) bool).  Pixels
    whose trial :func:`decomposition.stages.grow.worth_refitting` turns down (its atom at the trial
    position with the rest held, :func:`_held_gain`) are not refitted (deviance inf)."""
    sub = _sub(cur, rows)
    m, K = sub.fam.shape
    z = _residual_sigmas(ctx, rows, mu)
    shifted = sub.fam == FAM_GAUSS
    # an echo comes after the direct (slot 0; the refit keeps every shifted atom after it)
    after = ctx.fit[rows] & (ctx.t[None, :] > sub.delay[:, :1])
    at_ps, score = residual_peak(ctx.t, z, after, np.where(shifted, sub.delay, np.nan), ctx.width[rows])
    free = sub.fam[:, 2:] == FAM_NONE
    tried = np.isfinite(score) & free.any(axis=1)
    dev = np.full(m, np.inf)
    if tried.any():
        i = np.flatnonzero(tried)
        gain, amp = _held_gain(ctx, rows[i], mu[i], shifted_slot_atoms(instrument_rows(ctx.irf, rows[i]), ctx.t,
                                                                      at_ps[i]))
        # the wider atom: a Gaussian GROW_BROAD_FACTOR response widths wide (unit peak)
        wide = np.exp(-0.5 * np.square((ctx.t[None, :] - at_ps[i, None])
                                       / (GROW_BROAD_FACTOR * ctx.width[rows[i], None])))
        gain_wide, _ = _held_gain(ctx, rows[i], mu[i], wide)
        tried[i] = worth_refitting(gain, gain_wide, amp, sub.params["direct_amplitude"][i], ctx.opts.significance_chi2)
    if not tried.any():
        return sub._replace(iterations=np.zeros(m, np.int64)), dev, tried
    i = np.flatnonzero(tried)
    slot = 2 + np.argmax(free[i], axis=1)
    f, d, la = sub.fam[i].copy(), sub.delay[i].copy(), sub.lalp[i].copy()
    f[np.arange(i.size), slot] = FAM_GAUSS
    d[np.arange(i.size), slot] = at_ps[i]
    t_i = ctx.refit(rows[i], f, d, la, {k: v[i] for k, v in sub.params.items()}, sub.background[i])
    kept = _all_kept(f, t_i.fam)
    before = _gap_sigma(sub.fam[i], sub.delay[i], ctx.log_width[rows[i]])
    resolved = _gap_sigma(t_i.fam, t_i.delay, ctx.log_width[rows[i]]) >= np.minimum(RESOLVED_SIGMA, before)
    dev[i] = np.where(kept & resolved, deviance(ctx, rows[i], t_i.params, t_i.background), np.inf)
    spent = np.zeros(m, np.int64)
    spent[i] = t_i.iterations
    trial = _put(sub, i, t_i, np.ones(i.size, bool))
    return trial._replace(iterations=spent), dev, tried


def _direct_starts(ctx: GrowContext, sub: Slots, rows) -> list:
    """Where a direct trial of the pixels ``rows`` starts: the sss onset (an sss that took the
    direct's light starts before it), and the peak of the data smoothed over the response's
    width (the brightest return; at the window's first sample for a direct before the window)."""
    starts = []
    has_sss = sub.fam[:, SSS_SLOT] == FAM_SSS
    if has_sss.any():
        starts.append(np.where(has_sss, sub.delay[:, SSS_SLOT], np.nan))
    y = np.where(ctx.fit[rows], ctx.values[rows], 0.0) - ctx.held[rows, None] * ctx.fit[rows]
    smooth = _smooth(ctx, rows, y)
    starts.append(ctx.t[np.argmax(np.where(ctx.fit[rows], smooth, -np.inf), axis=1)])
    return starts


def _smooth(ctx: GrowContext, rows, y) -> np.ndarray:
    """(m, L) the rows ``y`` of the pixels ``rows`` smoothed by a Gaussian of each one's width
    (out to 3 widths, zero beyond the window's ends)."""
    T = ctx.t[1] - ctx.t[0] if ctx.t.size > 1 else 1.0
    width = ctx.width[rows]
    if not isinstance(ctx.irf, GaussianPSF):
        # one width for every pixel: one kernel
        s = float(width[0]) if width.size else 1.0
        half = max(int(math.ceil(3.0 * s / T)), 1)
        kernel = np.exp(-0.5 * np.square(np.arange(-half, half + 1) * T / s))
        return convolve1d(y, kernel, axis=1, mode="constant")
    half = max(int(math.ceil(3.0 * float(width.max(initial=0.0)) / T)), 1)
    lag = np.arange(-half, half + 1) * T
    own = np.ceil(3.0 * width / T)[:, None] * T
    kernels = np.where(np.abs(lag) <= np.maximum(own, T), np.exp(-0.5 * np.square(lag / width[:, None])), 0.0)
    padded = np.pad(y, ((0, 0), (half, half)))
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1, axis=1)
    return np.einsum("plk,pk->pl", windows, kernels[:, ::-1])


def _restore_direct(ctx: GrowContext, cur: Slots, alphas_per_ps) -> tuple[Slots, np.ndarray, np.ndarray]:
    """A direct for the pixels ("d" asked) whose fit has none, or one that explains next to
    nothing (taken out alone it raises the deviance by less than ``significance_chi2``), while
    other atoms hold their light (see the module docstring, step 0).

    A direct is tried at each of :func:`_direct_starts` with the rest (from the data's peak
    also with the sss restarted at the direct with each of ``alphas_per_ps``); the trial of
    lowest deviance that keeps a direct is taken where its direct is significant in it (taken
    out alone, the others held, the deviance rises by ``significance_chi2`` or more: the rule
    every kept atom meets) and its deviance is at most ``ambiguity_sigma`` sqrt(2 n) above the
    fit it replaces.  A taken trial whose deviance lies within ``ambiguity_sigma``
    sqrt(2 n) of the fit it replaces, with a split more than ``ambiguity_split`` (1 - fidelity)
    away, is ambiguous: the data do not determine it (the search stage's rule); so is a pixel
    whose direct explains nothing and that no trial replaced.  -> (slots, restored (n,) bool,
    ambiguous (n,) bool).
    """
    n = cur.fam.shape[0]
    restored, ambiguous = np.zeros(n, bool), np.zeros(n, bool)
    fam = cur.fam
    other = (fam[:, 1:] != FAM_NONE).any(axis=1)
    cand = np.flatnonzero(other & (fam[:, 0] != FAM_GAUSS))
    with_d = np.flatnonzero(other & (fam[:, 0] == FAM_GAUSS))
    if with_d.size:
        weak = _removal_deviance(ctx, with_d, _sub(cur, with_d), slice(0, 1))[:, 0] < ctx.opts.significance_chi2
        cand = np.union1d(cand, with_d[weak])
    if cand.size == 0:
        return cur, restored, ambiguous
    opts = ctx.opts
    sub = _sub(cur, cand)
    d_cur = deviance(ctx, cand, sub.params, sub.background)
    best, d_best = sub, np.full(cand.size, np.inf)
    spent = np.zeros(cand.size, np.int64)
    starts = _direct_starts(ctx, sub, cand)
    # the sss that took the direct's light is fast; from the peak it is also restarted at the
    # direct with each coarse alpha, as the dictionary's own sss atoms are
    trials = [(x, None) for x in starts] + [(starts[-1], a) for a in alphas_per_ps]
    for start, alpha in trials:
        i = np.flatnonzero(np.isfinite(start))
        if alpha is not None:
            i = i[sub.fam[i, SSS_SLOT] == FAM_SSS]
        if i.size == 0:
            continue
        f, d, la = sub.fam[i].copy(), sub.delay[i].copy(), sub.lalp[i].copy()
        f[:, 0], d[:, 0] = FAM_GAUSS, start[i]
        if alpha is not None:
            d[:, SSS_SLOT], la[:, SSS_SLOT] = start[i], math.log(alpha)
        t_i = ctx.refit(cand[i], f, d, la, {k: v[i] for k, v in sub.params.items()}, sub.background[i])
        spent[i] += t_i.iterations
        dev = np.where(t_i.fam[:, 0] == FAM_GAUSS, deviance(ctx, cand[i], t_i.params, t_i.background), np.inf)
        win = dev < d_best[i]
        best = _put(best, i, t_i, win)
        d_best[i[win]] = dev[win]
    tried = np.isfinite(d_best)
    n_fit = ctx.fit[cand].sum(axis=1)
    # a direct significant where it lies (taken out alone, the others held, the deviance rises
    # by significance_chi2: the rule every kept atom meets)
    # and a fit no worse than the one it replaces beyond the noise (ambiguity_sigma sqrt(2 n))
    tol = ambiguity_tolerance("noise", opts, n_fit)
    take = np.zeros(cand.size, bool)
    if tried.any():
        r = np.flatnonzero(tried)
        take[r] = ((_removal_deviance(ctx, cand[r], _sub(best, r), slice(0, 1))[:, 0] >= opts.significance_chi2)
                   & (d_best[r] - d_cur[r] <= tol[r]))
    out = _put(cur, cand, best, take)
    its = cur.iterations.copy()
    its[cand] += spent
    restored[cand[take]] = True
    # a direct that explains nothing and found no better place: no direct to speak of (a pixel
    # left with none is the caller's to judge: with sss_alone an sss may stand alone)
    phantom = cand[~take & (sub.fam[:, 0] == FAM_GAUSS)]
    ambiguous[phantom] = True
    out = _without_direct(out, phantom[_unseen_direct(ctx, out, phantom)])

    def split_distance(r):
        split_new = params_components(ctx.irf, ctx.t, {k: v[r] for k, v in best.params.items()})
        split_old = params_components(ctx.irf, ctx.t, {k: v[r] for k, v in sub.params.items()})
        return 1.0 - fidelity(split_new, split_old)

    ambiguous[cand] |= is_ambiguous(d_best - d_cur, tol, split_distance, opts.ambiguity_split, where=take)
    return out._replace(iterations=its), restored, ambiguous


def _swap_far_sss(ctx: GrowContext, cur: Slots):
    """An sss far after the direct replaced by a shifted copy at its peak where the penalised
    deviance is lower (see the module docstring) -> (slots, pixels swapped)."""
    fam, delay = cur.fam, cur.delay
    has = (fam[:, SSS_SLOT] == FAM_SSS) & (fam[:, 0] == FAM_GAUSS) & (fam[:, 2:] == FAM_NONE).any(axis=1)
    far = has & (delay[:, SSS_SLOT] > delay[:, 0] + NEAR_SIGMA * ctx.width)
    rows = np.flatnonzero(far)
    if rows.size == 0:
        return cur, 0
    sub = _sub(cur, rows)
    m = rows.size
    phi = ctx.atoms(rows, sub.fam[:, SSS_SLOT:SSS_SLOT + 1], sub.delay[:, SSS_SLOT:SSS_SLOT + 1],
                    sub.lalp[:, SSS_SLOT:SSS_SLOT + 1])[:, 0]
    peak_ps = ctx.t[np.argmax(phi, axis=1)]
    slot = 2 + np.argmax(sub.fam[:, 2:] == FAM_NONE, axis=1)
    f, d, la = sub.fam.copy(), sub.delay.copy(), sub.lalp.copy()
    f[:, SSS_SLOT] = FAM_NONE
    f[np.arange(m), slot] = FAM_GAUSS
    d[np.arange(m), slot] = peak_ps
    trial = ctx.refit(rows, f, d, la, sub.params, sub.background)
    log_n, weight = log_samples(ctx.fit[rows].sum(axis=1)), ctx.opts.search_penalty
    j_cur = penalised(deviance(ctx, rows, sub.params, sub.background), free_parameters(sub.fam, "fixed"), log_n, weight)
    j_new = penalised(deviance(ctx, rows, trial.params, trial.background), free_parameters(trial.fam, "fixed"), log_n,
                      weight)
    before = _gap_sigma(sub.fam, sub.delay, ctx.log_width[rows])
    resolved = _gap_sigma(trial.fam, trial.delay, ctx.log_width[rows]) >= np.minimum(RESOLVED_SIGMA, before)
    take = (j_new < j_cur) & resolved & (trial.fam[np.arange(m), slot] == FAM_GAUSS)
    out = _put(cur, rows, trial, take)
    its = cur.iterations.copy()
    its[rows] += trial.iterations
    return out._replace(iterations=its), int(take.sum())


def _restart_early_direct(ctx: GrowContext, cur: Slots) -> tuple[Slots, int]:
    """A direct before the window (its delay before the first sample) refitted from the
    window's edge and from EARLY_DIRECT_STARTS_SIGMA response widths before it, the rest as
    they are (a start within EARLY_DIRECT_NEAR_SIGMA widths of the fitted direct is skipped);
    each pixel keeps the lowest deviance, its own fit included, among the refits that keep
    every atom and whose direct some sample still sees (:func:`_unseen_direct`) (see the
    module docstring, step 0b) -> (slots, pixels moved)."""
    fam, delay = cur.fam, cur.delay
    rows = np.flatnonzero((fam[:, 0] == FAM_GAUSS) & (delay[:, 0] < ctx.t[0]))
    if rows.size == 0:
        return cur, 0
    sub = _sub(cur, rows)
    d_best = deviance(ctx, rows, sub.params, sub.background)
    best = sub
    spent = np.zeros(rows.size, np.int64)
    width = ctx.width[rows]
    for widths in EARLY_DIRECT_STARTS_SIGMA:
        start = ctx.t[0] - widths * width
        i = np.flatnonzero(np.abs(sub.delay[:, 0] - start) > EARLY_DIRECT_NEAR_SIGMA * width)
        if i.size == 0:
            continue
        d = sub.delay[i].copy()
        d[:, 0] = start[i]
        trial = ctx.refit(rows[i], sub.fam[i], d, sub.lalp[i], {k: v[i] for k, v in sub.params.items()},
                          sub.background[i])
        spent[i] += trial.iterations
        # every atom kept, and the direct not slid out to where no sample sees it
        kept = _all_kept(sub.fam[i], trial.fam) & ~_unseen_direct(ctx, trial, np.arange(i.size))
        dev = np.where(kept, deviance(ctx, rows[i], trial.params, trial.background), np.inf)
        win = dev < d_best[i]
        best = _put(best, i, trial, win)
        d_best[i] = np.where(win, dev, d_best[i])
    moved = np.any(best.delay != sub.delay, axis=1)
    out = _put(cur, rows, best, np.ones(rows.size, bool))
    its = cur.iterations.copy()
    its[rows] += spent
    return out._replace(iterations=its), int(moved.sum())


def _restart_onset_at_direct(ctx: GrowContext, cur: Slots) -> tuple[Slots, int]:
    """An sss whose onset lies more than ONSET_RESTART_SIGMA response widths after its direct,
    the direct inside the window, refitted with the onset started at the direct, the rest as
    they are; a pixel takes the refit where it keeps every atom and the direct inside the
    window and lowers the deviance (see the module docstring, step 0c) -> (slots, pixels
    moved)."""
    fam, delay = cur.fam, cur.delay
    both = (fam[:, 0] == FAM_GAUSS) & (fam[:, SSS_SLOT] == FAM_SSS) & (delay[:, 0] >= ctx.t[0])
    rows = np.flatnonzero(both & (delay[:, SSS_SLOT] > delay[:, 0] + ONSET_RESTART_SIGMA * ctx.width))
    if rows.size == 0:
        return cur, 0
    sub = _sub(cur, rows)
    d = sub.delay.copy()
    d[:, SSS_SLOT] = d[:, 0]
    trial = ctx.refit(rows, sub.fam, d, sub.lalp, sub.params, sub.background)
    kept = _all_kept(sub.fam, trial.fam) & (trial.delay[:, 0] >= ctx.t[0])
    dev = np.where(kept, deviance(ctx, rows, trial.params, trial.background), np.inf)
    win = dev < deviance(ctx, rows, sub.params, sub.background)
    out = _put(cur, rows, trial, win)
    its = cur.iterations.copy()
    its[rows] += trial.iterations
    return out._replace(iterations=its), int(win.sum())


def grow_response(ctx: GrowContext, slots: Slots, *, alphas_per_ps,
                  components) -> tuple[Slots, dict, np.ndarray]:
    """The forward steps (see the module docstring) on the refined slots of the n live pixels.

    Returns the slots, ``{"response_direct_restored", "response_early_direct_moved",
    "response_onset_restarted", "response_sss_added", "response_echo_added",
    "response_sss_swapped"}`` -- the pixels given a direct, the pixels whose direct before the
    window moved to a better start, the pixels whose late sss onset moved to the direct, the pixels
    given an sss, the echoes in the answer that it did not have before (far sss turned echoes
    included), and the pixels whose far sss became an echo -- and (n,) bool: the pixels whose
    restored direct the data do not determine (AMBIGUOUS).
    """
    info = {"response_sss_added": 0, "response_echo_added": 0, "response_sss_swapped": 0,
            "response_direct_restored": 0, "response_early_direct_moved": 0, "response_onset_restarted": 0}
    opts = ctx.opts
    # the echo is found by its significance alone: no trial without the rule (or with grow=False);
    # float data had theirs from the grow stage
    with_r = ctx.counts and "r" in components and slots.fam.shape[1] > 2 and opts.grow and opts.significance_chi2 > 0
    with_s = "s" in components and ctx.counts
    ambiguous = np.zeros(slots.fam.shape[0], bool)
    if "d" in components:
        slots, restored, ambiguous = _restore_direct(ctx, slots, alphas_per_ps)
        info["response_direct_restored"] = int(restored.sum())
        slots, info["response_early_direct_moved"] = _restart_early_direct(ctx, slots)
    fam0 = slots.fam.copy()
    if with_r and "s" in components:
        slots, info["response_sss_swapped"] = _swap_far_sss(ctx, slots)
    if "d" in components and "s" in components and ctx.counts:
        slots, info["response_onset_restarted"] = _restart_onset_at_direct(ctx, slots)
    if not (with_r or with_s):
        return slots, info, ambiguous
    active = np.flatnonzero(slots.fam[:, 0] == FAM_GAUSS)
    chi2 = opts.significance_chi2
    for _ in range(slots.fam.shape[1]):
        if active.size == 0:
            break
        sub = _sub(slots, active)
        mu = ctx.model(sub.params, sub.background)
        d_cur = _model_deviance(ctx, active, mu)
        best, d_best = sub, np.full(active.size, np.inf)
        is_sss = np.zeros(active.size, bool)
        its = np.zeros(active.size, np.int64)
        if with_s:
            c = np.flatnonzero(sub.fam[:, SSS_SLOT] == FAM_NONE)
            if c.size:
                t_s, d_s = _sss_trial(ctx, slots, active[c], mu[c], alphas_per_ps)
                its[c] += t_s.iterations
                best = _put(best, c, t_s, np.ones(c.size, bool))
                d_best[c], is_sss[c] = d_s, True
        if with_r:
            t_e, d_e, tried = _echo_trial(ctx, slots, active, mu)
            its += t_e.iterations
            win = tried & (d_e < d_best)
            best = _pick_rows(win, t_e, best)
            d_best = np.where(win, d_e, d_best)
            is_sss &= ~win
        take = d_cur - d_best >= chi2
        total = slots.iterations.copy()
        total[active] += its
        slots = _put(slots, active, best, take)._replace(iterations=total)
        info["response_sss_added"] += int((take & is_sss).sum())
        active = active[take]
    if with_r:
        grown = (slots.fam == FAM_GAUSS) & (fam0 != FAM_GAUSS)
        grown[:, :2] = False
        slots, grown = _drop_weak_echoes(ctx, slots, grown)
        info["response_echo_added"] = int(grown.sum())
    return slots, info, ambiguous

