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
  :mod:`decomposition.refit`);
* standard errors (``stderr``): the Fisher information of the response's atoms
  (:mod:`decomposition.response_fisher`).

The refinement always runs here (``n_polish`` iterations): the detection's relocation is short
(``n_lm`` iterations per added atom) and there is no grid to snap to.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, empty_params, render_profile
from .constants import BOUND_TOL, FAM_NONE, FAM_SSS, POISSON_REFITS, SSS_SLOT
from .flags import AT_BOUND, FLAG_DTYPE, MAX_ITER, TRUNCATED, mark
from .noise import fit_dispersion, poisson_weights
from .options import GridSpec, SolverOptions
from .prepare import Samples
from .response_detect import RESPONSE_PHASES, detect_response, response_dictionary
from .response_fisher import slot_standard_errors
from .response_label import label_response, param_slots, slots_to_params
from .response_refine import fit_slots

__all__ = ["ResponseOutcome", "decompose_with_response"]


@dataclass(frozen=True)
class ResponseOutcome:
    """``params`` (P-shaped, keys of :mod:`core.model`, ``<key>_stderr`` too with ``stderr``),
    ``flags`` (P,) (MAX_ITER, AT_BOUND, TRUNCATED), ``info`` (dict)."""

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
                                   sss_after_direct=opts.sss_after_direct)

    fam, delay, lalp = param_slots(params, R)
    y = samples.profiles[live]
    fit_mask = samples.fit[live]
    counts = samples.noise_model == "poisson"
    disp = samples.dispersion[live] if counts else None
    iterations = np.zeros(live.size, np.int64)
    amp = np.zeros(fam.shape)
    sw = fit_mask.astype(np.float64)
    for _ in range(POISSON_REFITS if counts else 1):
        if counts:
            model = np.nan_to_num(render_profile(params, L, ax.time_bin_ps, ax.t0_ps, irf=irf))
            sw = np.sqrt(poisson_weights(model, fit_mask, disp)) * scale[:, None]
        f = fit_slots(irf, t, y, sw, fam, delay, lalp, n_iter=opts.n_polish, lm_tol=opts.lm_tol,
                      delay_bounds_ps=bounds["delay_ps"], lalp_bounds=bounds["lalp"],
                      sss_after_direct=opts.sss_after_direct, first_is_direct=True)
        iterations += f.iterations
        delay, lalp, amp = np.nan_to_num(f.delay), np.nan_to_num(f.lalp), f.amp
        bad = (fam != FAM_NONE) & ~(amp > 0)
        if bad.any():
            fam = fam.copy()
            fam[bad] = FAM_NONE
            r = np.flatnonzero(bad.any(axis=1))
            g = fit_slots(irf, t, y[r], sw[r], fam[r], delay[r], lalp[r], n_iter=0, lm_tol=opts.lm_tol,
                          delay_bounds_ps=bounds["delay_ps"], lalp_bounds=bounds["lalp"],
                          sss_after_direct=opts.sss_after_direct, first_is_direct=True)
            amp[r] = g.amp
        params = slots_to_params(fam, delay, lalp, amp, scale, sigma_eq, R)

    flags = np.zeros(P, FLAG_DTYPE)
    mark(flags, live[~det.converged], MAX_ITER)
    mark(flags, live[trunc], TRUNCATED)
    sss = fam[:, SSS_SLOT] == FAM_SSS
    lo, hi = bounds["lalp"]
    at_b = sss & ((lalp[:, SSS_SLOT] <= lo + BOUND_TOL) | (lalp[:, SSS_SLOT] >= hi - BOUND_TOL))
    mark(flags, live[at_b], AT_BOUND)

    out = empty_params((P,), n_ir=R)
    for k, v in params.items():
        out[k][live] = v
    if opts.stderr:
        out.update(_errors(samples, irf, t, params, fam, delay, lalp, amp, R, opts.sss_after_direct))
    info = {"response_phases": RESPONSE_PHASES, "response_sss_start": det.sss_start, "n_atoms": int(dic.n_atoms),
            "response_alphas_per_ps": [float(a) for a in np.geomspace(a_lo, a_hi, grid.coarse_alpha)]
            if "s" in components else [],
            "n_iter": _scatter(P, live, det.n_iter, 0).reshape(samples.lead),
            "refine_iterations": _scatter(P, live, iterations, 0).reshape(samples.lead)}
    return ResponseOutcome(params=out, flags=flags, info=info)


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
