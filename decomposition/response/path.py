"""The stages of :func:`decomposition.decompose` with a measured instrument response.

Same sequence as the Gaussian path -- prepare (shared), detect, label, refine, quality
(shared) -- with the response's atoms in place of the Gaussian PSF:

* detect: greedy sparse coding over the response's dictionary (:mod:`decomposition.response.detect`);
* label: threshold, merge, physics labels (:mod:`decomposition.response.label`);
* refine: every pixel's delays and sss alpha by variable projection, amplitudes by linear
  least squares (:mod:`decomposition.response.refine`), with the order kept (no
  inter-reflection before the direct, no sss onset before it with ``sss_after_direct``);
  count data (``noise="poisson"``) fitted to their Poisson deviance instead, by Fisher
  scoring over delays, alphas and amplitudes together (the Poisson maximum-likelihood fit,
  :func:`decomposition.response.refine.fit_slots` with ``CountData``);
* forward steps (:mod:`decomposition.response.grow`): a direct where a fast sss took its
  light (AMBIGUOUS where the data do not determine it), an sss for count data's pixels left
  without one, an echo where the residual in noise sigmas holds one, an sss far after the
  direct turned into the echo it is -- each kept where the deviance drops by
  ``significance_chi2``;
* the offset's standard error (``stderr``; the components' errors are the finish stage's,
  :func:`decomposition.stages.refit.component_errors` with the response's atoms).

The refinement always runs here (``n_polish`` iterations): the detection's relocation is short
(``n_lm`` iterations per added atom) and there is no grid to snap to.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import BACKGROUND_KEY, empty_params
from ..stages.background import background_significant, background_threshold
from ..model.components import runs_off_window
from ..model.refine import hold_params
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, SSS_SLOT
from ..flags import AMBIGUOUS, AT_BOUND, FLAG_DTYPE, MAX_ITER, OFF_WINDOW, TRUNCATED, mark
from ..stages.label import at_bound
from ..options import GridSpec, SolverOptions
from ..stages.prepare import Samples
from ..stages.refit import background_stats
from ..model.atoms import slot_window_fraction
from .detect import RESPONSE_PHASES, detect_response, response_dictionary
from .label import label_response, param_slots
from .grow import GrowContext, grow_response
from .refine import refine_rows, refit_slots

__all__ = ["ResponseOutcome", "decompose_with_response"]


@dataclass(frozen=True)
class ResponseOutcome:
    """``params`` (P-shaped, keys of :mod:`core.model`, ``<key>_stderr`` too with ``stderr``),
    ``flags`` (P,) (MAX_ITER, AT_BOUND, TRUNCATED, OFF_WINDOW, AMBIGUOUS), ``info`` (dict)."""

    params: dict
    flags: np.ndarray
    info: dict


def decompose_with_response(samples: Samples, irf, grid: GridSpec, opts: SolverOptions, components,
                            hold=None) -> ResponseOutcome:
    """Detect, label and refine the components of every live pixel with the response ``irf``
    (on the samples' time step, see :func:`decomposition.response.resolve.resolve_response`).
    ``hold`` ({key of :data:`decomposition.model.refine.HOLD_KEYS` but ``sigma_ps``: (P,) values,
    NaN free}, checked): onsets and decay rates held at given values in the refinement, the
    forward steps' refits and the standard errors (their errors NaN: not fitted here)."""
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
    if hold:
        refine_kw["hold"] = {k: np.asarray(v, np.float64)[live] for k, v in hold.items()}
    with_bg = samples.background is not None
    b_est = samples.background[live] if with_bg else np.zeros(live.size)
    # the profiles are the samples less the first estimate of the offset (0 without the family)
    slots = refit_slots(samples.profiles[live], fam, delay, lalp, b_est, with_bg, params, **refine_kw)
    grow_ctx = GrowContext(samples, irf, b_est, with_bg, refine_kw, sigma_eq, opts)
    slots, grow_info, ambiguous = grow_response(grow_ctx, slots,
                                                alphas_per_ps=np.geomspace(a_lo, a_hi, grid.coarse_alpha),
                                                components=components)
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
            sub = refine_rows(refine_kw, drop)
            d_slots = refit_slots(y0, fam[drop], delay[drop], lalp[drop], np.zeros(drop.size), False, p0, **sub)
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
    mark(flags, live[runs_off_window(fam != FAM_NONE, fam == FAM_GAUSS, delay, inside, t,
                                     width_ps=sigma_eq).any(axis=1)], OFF_WINDOW)
    # the split the data do not determine: a restored direct within the noise of the fit
    # without it, or (the search stage's rule) an sss left with no direct where the paper's
    # model gives every pixel one
    if "d" in components and not opts.sss_alone:
        ambiguous = ambiguous | ((fam[:, 0] != FAM_GAUSS) & (fam[:, SSS_SLOT] == FAM_SSS))
    mark(flags, live[ambiguous], AMBIGUOUS)

    out = empty_params((P,), n_ir=R)
    if with_bg:
        out[BACKGROUND_KEY] = np.full(P, np.nan)          # NaN where not decomposed
    for k, v in params.items():
        out[k][live] = v
    if hold:
        # the held values themselves (the refinement holds log alpha: exp(log(alpha)) may differ
        # from alpha in its last bit)
        out = hold_params(out, hold, (P,))
    if opts.stderr and with_bg:
        out[BACKGROUND_KEY + "_stderr"] = bg_info["background_stderr"]
    info = {"response_phases": RESPONSE_PHASES, "response_sss_start": det.sss_start, "n_atoms": int(dic.n_atoms),
            "response_alphas_per_ps": [float(a) for a in np.geomspace(a_lo, a_hi, grid.coarse_alpha)]
            if "s" in components else [],
            **grow_info,
            "n_iter": _scatter(P, live, det.n_iter, 0).reshape(samples.lead),
            "refine_iterations": _scatter(P, live, iterations, 0).reshape(samples.lead)}
    if with_bg:
        info["background_chi2"] = bg_info["background_chi2"].reshape(samples.lead)
    return ResponseOutcome(params=out, flags=flags, info=info)


def _scatter(P, live, v, fill):
    out = np.full(P, fill, dtype=np.asarray(v).dtype)
    out[live] = v
    return out

