"""The stages of :func:`decomposition.decompose` with a measured instrument response.

Same sequence as the Gaussian path -- prepare (shared), detect, label, refine, quality
(shared) -- with the response's atoms in place of the Gaussian PSF:

* detect: greedy sparse coding over the response's dictionary (:mod:`decomposition.response_detect`);
* label: threshold, merge, physics labels (:mod:`decomposition.response_label`);
* refine: every pixel's delays and sss alpha by variable projection, amplitudes by linear
  least squares (:mod:`decomposition.response_refine`), with the order kept (no
  inter-reflection before the direct, no sss onset before it with ``sss_after_direct``);
  count data (``noise="poisson"``) refitted POISSON_REFITS times with weights 1 / Poisson
  variance of the previous model (the Poisson maximum-likelihood fit, as in
  :mod:`decomposition.refit`); count data's pixels left without an sss tried again with one
  (:func:`_add_missed_sss`);
* standard errors (``stderr``): the Fisher information of the response's atoms
  (:mod:`decomposition.response_fisher`).

The refinement always runs here (``n_polish`` iterations): the detection's relocation is short
(``n_lm`` iterations per added atom) and there is no grid to snap to.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import BACKGROUND_KEY, DIRECT_KEYS, IR_KEYS, SSS_KEYS, empty_params, render_profile
from .background import background_significant, background_threshold
from .components import runs_off_window
from .constants import FAM_GAUSS, FAM_NONE, FAM_SSS, POISSON_REFITS, POISSON_VARIANCE_FLOOR, SSS_SLOT
from .flags import AT_BOUND, FLAG_DTYPE, MAX_ITER, OFF_WINDOW, TRUNCATED, mark
from .label import at_bound
from .noise import fit_dispersion, poisson_weights
from .options import GridSpec, SolverOptions
from .prepare import Samples
from .refit import background_stats
from .response_atoms import slot_window_fraction
from .response_detect import RESPONSE_PHASES, detect_response, response_dictionary
from .response_fisher import slot_standard_errors
from .response_label import label_response, param_slots, slots_to_params
from .response_refine import fit_slots

__all__ = ["ResponseOutcome", "decompose_with_response"]


@dataclass(frozen=True)
class ResponseOutcome:
    """``params`` (P-shaped, keys of :mod:`core.model`, ``<key>_stderr`` too with ``stderr``),
    ``flags`` (P,) (MAX_ITER, AT_BOUND, TRUNCATED, OFF_WINDOW), ``info`` (dict)."""

    params: dict
    flags: np.ndarray
    info: dict


def decompose_with_response(samples: Samples, irf, grid: GridSpec, opts: SolverOptions, components) -> ResponseOutcome:
    """Detect, label and refine the components of every live pixel with the response ``irf``
    (on the samples' time step, see :func:`decomposition.response_input.resolve_response`)."""
    P, L, R = samples.values.shape[0], samples.n_bins, opts.max_reflections
    ax = samples.axis
    t = ax.t0_ps + ax.time_bin_ps * np.arange(L)
    live = samples.live
    scale = samples.scale[live]
    sigma_eq = gaussian_equivalent_sigma_ps(irf)
    a_lo, a_hi = grid.alpha_range_per_ps
    span = L * ax.time_bin_ps
    bounds = {"delay_ps": (t[0] - span, t[-1] + span),
              "lalp": (math.log(a_lo / opts.bound_factor), math.log(a_hi * opts.bound_factor))}
    dic = response_dictionary(irf, samples, np.geomspace(a_lo, a_hi, grid.coarse_alpha), components)
    det = detect_response(samples, irf, dic, opts, components, bounds)
    params, trunc = label_response(det.state, irf, t, scale, sigma_eq, R, rel_threshold=opts.rel_threshold,
                                   merge_tol_ps=opts.merge_tol_bins * ax.time_bin_ps,
                                   sss_after_direct=opts.sss_after_direct,
                                   noise=samples.significance_sigma(live, samples.noise_eff[live]),
                                   significance_chi2=opts.significance_chi2)

    fam, delay, lalp = param_slots(params, R)
    fit_mask = samples.fit[live]
    counts = samples.noise_model == "poisson"
    refine_kw = dict(irf=irf, t=t, ax=ax, fit_mask=fit_mask, scale=scale, opts=opts, bounds=bounds,
                     disp=samples.dispersion[live] if counts else None, sigma_eq=sigma_eq, R=R)
    with_bg = samples.background is not None
    b_est = samples.background[live] if with_bg else np.zeros(live.size)
    # the profiles are the samples less the first estimate of the offset (0 without the family)
    slots = _refine(samples.profiles[live], fam, delay, lalp, b_est, with_bg, params, **refine_kw)
    sss_added = 0
    if counts and "s" in components:
        slots, sss_added = _add_missed_sss(samples, slots, b_est, with_bg, np.geomspace(a_lo, a_hi, grid.coarse_alpha),
                                           opts.significance_chi2, refine_kw)
    fam, delay, lalp, amp, params, background, iterations = slots
    bg_info = {}
    if with_bg:
        full = empty_params((P,), n_ir=R)
        for k, v in params.items():
            full[k][live] = v
        full[BACKGROUND_KEY] = np.zeros(P)
        full[BACKGROUND_KEY][live] = background
        chi2, stderr = background_stats(samples, full, irf)
        keep = background_significant(chi2[live], background_threshold(fit_mask, opts.background_chi2))
        drop = np.flatnonzero(~keep)
        if drop.size:
            # refit without the offset: the data themselves, the offset exactly 0
            y0 = np.where(fit_mask[drop], samples.values[live[drop]], 0.0) / scale[drop, None]
            p0 = {k: v[drop] for k, v in params.items()}
            p0[BACKGROUND_KEY] = np.zeros(drop.size)
            sub = {k: (v[drop] if k in ("fit_mask", "scale", "disp") and v is not None else v)
                   for k, v in refine_kw.items()}
            d_slots = _refine(y0, fam[drop], delay[drop], lalp[drop], np.zeros(drop.size), False, p0, **sub)
            fam, delay, lalp, amp = fam.copy(), delay.copy(), lalp.copy(), amp.copy()
            fam[drop], delay[drop], lalp[drop], amp[drop] = d_slots[:4]
            for k in params:
                params[k][drop] = d_slots[4][k]
            background[drop] = 0.0
            iterations[drop] += d_slots[6]
        params[BACKGROUND_KEY] = background
        bg_stderr = np.full(P, np.nan)
        bg_stderr[live[keep]] = stderr[live[keep]]
        chi2_out = np.zeros(P)
        chi2_out[live] = chi2[live]
        bg_info = {"background_chi2": chi2_out, "background_stderr": bg_stderr}

    flags = np.zeros(P, FLAG_DTYPE)
    mark(flags, live[~det.converged], MAX_ITER)
    mark(flags, live[trunc], TRUNCATED)
    # the Gaussian path's rules on the final atoms: alpha at its bound (the response has no width
    # to hit one), a component running off the window's edge
    state = {"fam": fam, "lsig": np.zeros(fam.shape), "lalp": lalp}
    mark(flags, live[at_bound(state, {"lsig": (-np.inf, np.inf), "lalp": bounds["lalp"]})], AT_BOUND)
    inside = slot_window_fraction(irf, t, fam, delay, lalp)
    mark(flags, live[runs_off_window(fam != FAM_NONE, fam == FAM_GAUSS, delay, inside, t).any(axis=1)], OFF_WINDOW)

    out = empty_params((P,), n_ir=R)
    if with_bg:
        out[BACKGROUND_KEY] = np.full(P, np.nan)          # NaN where not decomposed
    for k, v in params.items():
        out[k][live] = v
    if opts.stderr:
        out.update(_errors(samples, irf, t, params, fam, delay, lalp, amp, R, opts.sss_after_direct))
        if with_bg:
            out[BACKGROUND_KEY + "_stderr"] = bg_info["background_stderr"]
    info = {"response_phases": RESPONSE_PHASES, "response_sss_start": det.sss_start, "n_atoms": int(dic.n_atoms),
            "response_alphas_per_ps": [float(a) for a in np.geomspace(a_lo, a_hi, grid.coarse_alpha)]
            if "s" in components else [],
            "response_sss_added": sss_added,
            "n_iter": _scatter(P, live, det.n_iter, 0).reshape(samples.lead),
            "refine_iterations": _scatter(P, live, iterations, 0).reshape(samples.lead)}
    if with_bg:
        info["background_chi2"] = bg_info["background_chi2"].reshape(samples.lead)
    return ResponseOutcome(params=out, flags=flags, info=info)


def _refine(y, fam, delay, lalp, held, fit_bg, params, *, irf, t, ax, fit_mask, scale, opts, bounds, disp,
            sigma_eq, R):
    """Refine the slots of n live pixels (normalised profiles ``y`` (n, L), the offset ``held``
    (n,) counts / units already subtracted), with a jointly fitted constant offset where
    ``fit_bg``; count data refitted POISSON_REFITS times with weights 1 / Poisson variance of the
    previous model (offset included).  ``params``: the starting model (n-shaped, units, the
    ``background`` key read for the first weights).

    Returns fam, delay, lalp, amp (n, K), params (n-shaped, units, no ``background`` key),
    background (n,) units (``held`` plus the fitted correction), iterations (n,).
    """
    L = y.shape[1]
    counts = disp is not None
    n = y.shape[0]
    iterations = np.zeros(n, np.int64)
    amp = np.zeros(fam.shape)
    background = held.astype(np.float64).copy()
    sw = fit_mask.astype(np.float64)
    bg_cols = np.ones(n, bool) if fit_bg else None
    fit_kw = dict(lm_tol=opts.lm_tol, delay_bounds_ps=bounds["delay_ps"], lalp_bounds=bounds["lalp"],
                  sss_after_direct=opts.sss_after_direct, first_is_direct=True)
    params = dict(params)
    params[BACKGROUND_KEY] = background
    for _ in range(POISSON_REFITS if counts else 1):
        if counts:
            model = np.nan_to_num(render_profile(params, L, ax.time_bin_ps, ax.t0_ps, irf=irf))
            sw = np.sqrt(poisson_weights(model, fit_mask, disp)) * scale[:, None]
        f = fit_slots(irf, t, y, sw, fam, delay, lalp, n_iter=opts.n_polish, fit_background=bg_cols, **fit_kw)
        iterations += f.iterations
        delay, lalp, amp, b_fit = np.nan_to_num(f.delay), np.nan_to_num(f.lalp), f.amp, f.background
        bad = (fam != FAM_NONE) & ~(amp > 0)
        if bad.any():
            fam = fam.copy()
            fam[bad] = FAM_NONE
            r = np.flatnonzero(bad.any(axis=1))
            g = fit_slots(irf, t, y[r], sw[r], fam[r], delay[r], lalp[r], n_iter=0,
                          fit_background=None if bg_cols is None else bg_cols[r], **fit_kw)
            amp[r], b_fit = g.amp, b_fit.copy()
            b_fit[r] = g.background
        background = held + b_fit * scale
        params = slots_to_params(fam, delay, lalp, amp, scale, sigma_eq, R)
        params[BACKGROUND_KEY] = background
    params = {k: v for k, v in params.items() if k != BACKGROUND_KEY}
    return fam, delay, lalp, amp, params, background, iterations


def _count_deviance(samples: Samples, params: dict, background, irf) -> np.ndarray:
    """(n,) Poisson deviance of the live pixels' counts under ``params`` (n-shaped, counts)
    plus ``background`` (n,), over the fitted samples, divided by the squared dispersion."""
    live, ax = samples.live, samples.axis
    p = dict(params)
    p[BACKGROUND_KEY] = background
    with np.errstate(invalid="ignore"):
        mu = np.nan_to_num(render_profile(p, samples.n_bins, ax.time_bin_ps, ax.t0_ps, irf=irf))
    fit = samples.fit[live]
    y = np.where(fit, samples.values[live], 0.0)
    mu = np.where(fit, np.maximum(mu, POISSON_VARIANCE_FLOOR), 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        term = np.where(y > 0, y * np.log(np.where(y > 0, y, 1.0) / mu), 0.0) - (y - mu)
    return 2.0 * np.where(fit, term, 0.0).sum(axis=1) / np.square(samples.dispersion[live])


def _add_missed_sss(samples: Samples, slots, b_est, with_bg, alphas_per_ps, significance_chi2: float, refine_kw):
    """Count data: an sss for the live pixels whose detection found none (direct present).

    The pursuit weighs every sample with one noise, the Poisson noise at the signal; an sss
    tail lies where the counts, and so their noise, are far lower, and at ~100 photons per
    pixel the pursuit stopped after the direct in ~20 % of the pixels whose sss raises the
    Poisson likelihood by far more than the significance threshold.  Each such pixel is
    refined (:func:`_refine`, Poisson weights) once per alpha of ``alphas_per_ps`` with an sss
    started at its direct delay; the best trial is kept where it lowers the Poisson deviance
    (:func:`_count_deviance`, the likelihood-ratio statistic of the sss) by at least
    ``significance_chi2``, the significance an atom must have.

    Returns the slots (as :func:`_refine` returns them) and the number of pixels given an sss.
    """
    fam, delay, lalp, amp, params, background, iterations = slots
    cand = np.flatnonzero((fam[:, SSS_SLOT] == FAM_NONE) & (fam[:, 0] != FAM_NONE))
    if cand.size == 0:
        return slots, 0
    irf = refine_kw["irf"]
    sub = {k: (v[cand] if k in ("fit_mask", "scale", "disp") and v is not None else v) for k, v in refine_kw.items()}
    y = samples.profiles[samples.live[cand]]
    p0 = {k: v[cand] for k, v in params.items()}
    p0[BACKGROUND_KEY] = background[cand]
    sub_samples = _rows(samples, cand)
    d_best = _count_deviance(sub_samples, {k: v[cand] for k, v in params.items()}, background[cand], irf)
    trial, dev = None, None
    iterations = iterations.copy()
    for alpha in alphas_per_ps:
        f, d, la = fam[cand].copy(), delay[cand].copy(), lalp[cand].copy()
        f[:, SSS_SLOT], d[:, SSS_SLOT], la[:, SSS_SLOT] = FAM_SSS, d[:, 0], math.log(alpha)
        t_a = _refine(y, f, d, la, b_est[cand], with_bg, p0, **sub)
        iterations[cand] += t_a[6]
        dev_a = np.where(t_a[0][:, SSS_SLOT] == FAM_SSS, _count_deviance(sub_samples, t_a[4], t_a[5], irf), np.inf)
        if trial is None:
            trial, dev = t_a, dev_a
        else:
            win = dev_a < dev
            trial, dev = _pick_rows(win, t_a, trial), np.where(win, dev_a, dev)
    take = d_best - dev >= significance_chi2
    if not take.any():
        return (fam, delay, lalp, amp, params, background, iterations), 0
    rows = cand[take]
    fam, delay, lalp, amp, background = (a.copy() for a in (fam, delay, lalp, amp, background))
    fam[rows], delay[rows], lalp[rows], amp[rows] = (a[take] for a in trial[:4])
    params = {k: v.copy() for k, v in params.items()}
    for k in params:
        params[k][rows] = trial[4][k][take]
    background[rows] = trial[5][take]
    return (fam, delay, lalp, amp, params, background, iterations), int(rows.size)


def _pick_rows(win, a, b):
    """The slot tuple of :func:`_refine` with the rows of ``a`` where ``win``, of ``b`` elsewhere."""
    def pick(x, y):
        if isinstance(x, dict):
            return {k: pick(x[k], y[k]) for k in x}
        w = win.reshape((-1,) + (1,) * (np.ndim(x) - 1))
        return np.where(w, x, y)
    return tuple(pick(x, y) for x, y in zip(a, b))


def _rows(samples: Samples, rows) -> Samples:
    """``samples`` with only the live pixels ``rows`` (indices into ``samples.live``) live."""
    return dataclasses.replace(samples, live=samples.live[rows])


def _scatter(P, live, v, fill):
    out = np.full(P, fill, dtype=np.asarray(v).dtype)
    out[live] = v
    return out


def _errors(samples: Samples, irf, t, params, fam, delay, lalp, amp, R, sss_after_direct) -> dict:
    live, ax = samples.live, samples.axis
    P = samples.values.shape[0]
    scale = samples.scale[live]
    fit_mask = samples.fit[live]
    y = samples.profiles[live]
    if BACKGROUND_KEY in params:
        # the components' errors with the offset held at its fitted value
        y = np.where(fit_mask, samples.values[live] - params[BACKGROUND_KEY][:, None], 0.0) / scale[:, None]
    noise = None
    if samples.noise_model == "poisson":
        model = np.nan_to_num(render_profile(params, samples.n_bins, ax.time_bin_ps, ax.t0_ps, irf=irf))
        sw = np.sqrt(poisson_weights(model, fit_mask)) * scale[:, None]
        noise = fit_dispersion(samples.values[live], model, fit_mask)
    else:
        sw = fit_mask.astype(np.float64)
    tie = None
    if sss_after_direct:
        tie = np.abs(delay[:, SSS_SLOT] - delay[:, 0]) <= 1e-9 * max(ax.time_bin_ps, 1.0)
    se = slot_standard_errors(irf, t, y, sw, fam, delay, lalp, amp, noise_sigma=noise, tie_onset=tie)
    se_amp = se["amp"] * scale[:, None]
    out = {f"{k}_stderr": np.full((P,) + np.shape(params[k])[1:], np.nan) for k in DIRECT_KEYS + SSS_KEYS + IR_KEYS}
    d = fam[:, 0] != FAM_NONE
    out["direct_delay_ps_stderr"][live[d]] = se["delay"][d, 0]
    out["direct_amplitude_stderr"][live[d]] = se_amp[d, 0]
    s = fam[:, SSS_SLOT] == FAM_SSS
    out["sss_delay_ps_stderr"][live[s]] = se["delay"][s, SSS_SLOT]
    out["sss_amplitude_stderr"][live[s]] = se_amp[s, SSS_SLOT]
    out["sss_alpha_per_ps_stderr"][live[s]] = se["alpha"][s, SSS_SLOT]
    if R:
        pres = fam[:, 2:] != FAM_NONE
        order = np.argsort(np.where(pres, delay[:, 2:], np.inf), axis=1, kind="stable")
        rows = np.arange(fam.shape[0])[:, None]
        po = pres[rows, order]
        out["ir_delay_ps_stderr"][live] = np.where(po, se["delay"][:, 2:][rows, order], np.nan)
        out["ir_amplitude_stderr"][live] = np.where(po, se_amp[:, 2:][rows, order], np.nan)
    return out
