"""The ``detect`` stage of :func:`decomposition.decompose`: detect the components by sparse coding.

For every block of live pixels: the multi-start greedy ConvSCD solve
(:func:`decomposition.methods.convscd.solve_multistart`), the 5 % threshold and merging, and the
polish of the kept atoms on the data term (:func:`decomposition.methods.convscd.polish_block`).
Where the noise at the signal turns out larger than the whole-profile estimate (photon
noise), those pixels are solved again with the sparsity weight of that noise: the weight must
follow the noise at the components, not in the quiet tail.  On float data this second pass
runs only where most of the call's pixels show such noise (RESTART_POOL_FRACTION): shot noise
is the detector's, while a few pixels' larger "noise at the signal" is their misfit.

The GradBM baseline (:func:`detect_gradbm`) takes the place of this stage for
``method="gradbm"``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import components as comp
from ..methods import convscd as cs
from ..constants import FAM_NONE, FAM_SSS, RESTART_FACTOR, RESTART_POOL_FRACTION
from ..masks import SampleMask
from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, empty_params
from ..noise import signal_noise_sigma
from ..options import SolverOptions
from ..kernels.pickcorr import PickWorkspace
from .prepare import Samples
from ..model.slots import new_state, put
from ..methods.gradbm import gradbm

__all__ = ["Detection", "detect_components", "detect_gradbm", "solver_inputs", "solver_options"]


@dataclass(frozen=True)
class Detection:
    """Atoms found for the live pixels of a :class:`~decomposition.stages.prepare.Samples`.

    Attributes
    ----------
    state : dict of (n, K) slot arrays       rows follow ``samples.live``
    converged : ndarray (n,) bool            the greedy solve stopped before ``max_iter``
    objective : ndarray (P, max_iter + 1)    per-pixel objective after every outer iteration
                                             (NaN after a pixel stopped, and for pixels not solved)
    n_iter : ndarray (P,) int
    noise_eff : ndarray (P,)                 the noise used in the end (second pass included)
    lm_iterations : int                      LM iterations of the slowest pixel, summed over calls
    restarted : int                          pixels that ran the second (unrestricted) start
    weights : ndarray (n, L) or None         relative least-squares weights (noise_eff^2 /
                                             variance) of the stages after the detection, where
                                             the noise follows the signal
                                             (:func:`decomposition.stages.candidates.signal_weights`);
                                             None: every sample weighs the same
    noise_spectrum : ndarray (L // 2 + 1,) or None
                                             the power spectrum of the call's noise per unit of
                                             a pixel's noise variance where that noise is
                                             correlated (pink), read off the detected residuals
                                             (:func:`decomposition.stages.candidates.correlated_noise_spectrum`):
                                             the penalised objectives of the stages after the
                                             detection whiten their residuals by it; None: they
                                             do not
    """

    state: dict
    converged: np.ndarray
    objective: np.ndarray
    n_iter: np.ndarray
    noise_eff: np.ndarray
    lm_iterations: int
    restarted: int
    weights: np.ndarray | None = None
    noise_spectrum: np.ndarray | None = None


def solver_inputs(samples: Samples, rows: np.ndarray):
    """Profiles and sample masks of ``rows`` for the solver.

    Saturated samples keep their (normalised, background-subtracted) recorded value and are
    censored (only a model below them is a misfit).  Returns (p (n, L), :class:`SampleMask`).
    """
    sat = samples.censored[rows]
    v = samples.values[rows]
    if samples.background is not None:
        v = v - samples.background[rows, None]
    p = np.where(sat, v / samples.scale[rows, None], samples.profiles[rows])
    return p, samples.mask[rows]


def solver_options(opts: SolverOptions, components, workspace: PickWorkspace) -> dict:
    """The keywords of :func:`decomposition.methods.convscd.solve_block` for these options and families."""
    max_gauss = (opts.max_components if "r" in components else 1) if "d" in components else 0
    return dict(workspace=workspace, max_components=opts.max_components, max_gauss=max_gauss,
                allow_sss="s" in components, sparsity=opts.sparsity, eps_rel=opts.eps_rel,
                max_iter=opts.max_iter, n_lm=opts.n_lm, bound_factor=opts.bound_factor,
                tie_sigma=opts.shared_sigma, sss_after_direct=opts.sss_after_direct, lm_tol=opts.lm_tol)


def _solve(p, mask: SampleMask, noise, dic, t, opts: SolverOptions, solve_opts: dict, significance_sigma):
    """Sparse solve (no censored sample), threshold (``significance_sigma``: the noise of its
    significance test, :meth:`Samples.significance_sigma`), merge and polish (censored samples too)."""
    st, si = cs.solve_multistart(p, mask.uncensored(), noise, dic, sss_alone=opts.sss_alone,
                                 restart=opts.multistart, **solve_opts)
    # (every larger atom hides a faint one here: kept near an sss onset before the polish, the
    # greedy's faint atoms led it astray; docs/history.md)
    comp.threshold(st, t, opts.rel_threshold, significance_sigma, opts.significance_chi2, sss_factor=None)
    comp.merge_gaussians(st, dic.time_bin_ps, opts.merge_tol_bins)
    st, model, nl = cs.polish_block(p, mask, st, noise, dic, sparsity=opts.sparsity, eps_rel=opts.eps_rel,
                                    n_lm=opts.n_polish, bound_factor=opts.bound_factor,
                                    tie_sigma=opts.shared_sigma, sss_after_direct=opts.sss_after_direct,
                                    lm_tol=opts.lm_tol)
    return st, si, model, nl


def detect_components(samples: Samples, dic: cs.Dictionary, opts: SolverOptions, components, *,
                      polish: bool = True) -> Detection:
    """Sparse coding of every live pixel, block by block (``opts.block_size`` pixels).

    ``opts`` must be resolved (:meth:`SolverOptions.resolved`).  Each block is solved as one
    batch (the block-wide choice between the plain and the masked pick follows its samples).
    The second noise pass (the module docstring) runs where the noise at the signal exceeds
    RESTART_FACTOR x the pixel's noise, on float data only where that holds for at least
    RESTART_POOL_FRACTION of the call's live pixels (see there).

    ``polish=False``: the sparse coding's atoms as they are, without the threshold, merge and
    polish and without the second noise pass -- a measured response's detection, whose refit
    relocates every atom after the labels; there each of those steps cost fidelity
    (docs/history.md).  Empty slots then carry NaN delays, and slots other than an sss NaN
    log alphas.
    """
    P = samples.values.shape[0]
    live = samples.live
    t = dic.t0_ps + dic.time_bin_ps * np.arange(samples.n_bins)
    solve_opts = solver_options(opts, components, PickWorkspace())   # one scratch space for all blocks
    noise_eff = samples.noise_eff.copy()
    hist = np.full((P, opts.max_iter + 1), np.nan)
    n_iter = np.zeros(P, np.int64)
    blocks = []
    lm_total, restarted = 0, 0
    for b0 in range(0, live.size, opts.block_size):
        bi = live[b0:b0 + opts.block_size]
        pb, mb = solver_inputs(samples, bi)
        if not polish:
            st, sinfo = cs.solve_multistart(pb, mb.uncensored(), noise_eff[bi], dic, sss_alone=opts.sss_alone,
                                            restart=opts.multistart, **solve_opts)
            lm_total += sinfo["lm_iterations"]
            blocks.append((bi, _unused_nan(st), sinfo, np.zeros(0, np.int64), None))
            continue
        st, sinfo, model_b, nl = _solve(pb, mb, noise_eff[bi], dic, t, opts, solve_opts,
                                        samples.significance_sigma(bi, noise_eff[bi]))
        lm_total += sinfo["lm_iterations"] + nl
        s_sig = signal_noise_sigma(pb - model_b, model_b, mb.fit)
        blocks.append((bi, st, sinfo, np.nonzero(s_sig > RESTART_FACTOR * noise_eff[bi])[0], s_sig))
    raised = sum(b[3].size for b in blocks)
    second = polish and (samples.noise_model == "poisson" or raised >= RESTART_POOL_FRACTION * live.size)
    states, converged = [], []
    for bi, st, sinfo, again, s_sig in blocks:
        if second and again.size:
            pb, mb = solver_inputs(samples, bi[again])
            sb = s_sig[again]
            st2, sinfo2, _, nl2 = _solve(pb, mb, sb, dic, t, opts, solve_opts, samples.significance_sigma(bi[again], sb))
            lm_total += sinfo2["lm_iterations"] + nl2
            put(st, again, st2)
            for key in ("objective", "n_iter", "converged"):
                sinfo[key][again] = sinfo2[key]
            restarted += sinfo2.get("restarted", 0)
            noise_eff[bi[again]] = sb
        hist[bi] = sinfo["objective"]
        n_iter[bi] = sinfo["n_iter"]
        restarted += sinfo.get("restarted", 0)
        states.append(st)
        converged.append(sinfo["converged"])
    if states:
        state = {k: np.concatenate([s[k] for s in states]) for k in states[0]}
        conv = np.concatenate(converged)
    else:
        state = new_state(0, opts.max_components)
        conv = np.zeros(0, bool)
    return Detection(state=state, converged=conv, objective=hist, n_iter=n_iter, noise_eff=noise_eff,
                     lm_iterations=lm_total, restarted=restarted)


def _unused_nan(st: dict) -> dict:
    """Slot state ``st`` with NaN delays in empty slots, NaN log alphas outside sss slots and 0
    amplitudes in empty slots (in place)."""
    fam = st["fam"]
    st["delay"] = np.where(fam != FAM_NONE, st["delay"], np.nan)
    st["lalp"] = np.where(fam == FAM_SSS, st["lalp"], np.nan)
    st["amp"] = np.where(fam != FAM_NONE, st["amp"], 0.0)
    return st


def detect_gradbm(samples: Samples, n_ir: int, components, options: dict) -> dict:
    """The GradBM baseline on every live pixel -> parameters (P-shaped, NaN where absent)."""
    live, scale = samples.live, samples.scale
    params = empty_params((samples.values.shape[0],), n_ir=n_ir)
    if live.size == 0:
        return params
    T, t0 = samples.axis.time_bin_ps, samples.axis.t0_ps
    got = gradbm(samples.profiles[live], T, t0, components=tuple(sorted(components)), max_interreflections=n_ir,
                 **options)
    for k in DIRECT_KEYS + SSS_KEYS:
        if k in got:
            v = np.asarray(got[k], np.float64).reshape(live.size)
            if k in ("direct_amplitude", "sss_amplitude"):
                v = v * scale[live]
            params[k][live] = v
    if n_ir and "ir_delay_ps" in got:
        for k in IR_KEYS:
            v = np.asarray(got[k], np.float64).reshape(live.size, -1)[:, :n_ir]
            if k == "ir_amplitude":
                v = v * scale[live, None]
            params[k][live, : v.shape[1]] = v
    return params
