"""The ``label`` stage of :func:`decomposition.decompose`: from atoms to named components.

Optionally snaps the atoms to the reference grid (``off_grid=False``, the paper's discrete
setting), applies the 5 % threshold and merging once more (refinement can bring two atoms
together), flags atoms whose refined width or decay ended at a bound, and names the atoms
(earliest Gaussian: direct; later ones: r2, r3, ... in delay order; the sss atom, its onset
not before the direct with ``sss_after_direct``) with
:func:`decomposition.model.components.classify`.  With ``shared_sigma`` every atom of a pixel
leaves with the same width.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model import components as comp
from ..methods import convscd as cs
from ..constants import BOUND_TOL, FAM_NONE, FAM_SSS
from .detect import Detection, solver_inputs
from ..flags import AT_BOUND, FLAG_DTYPE, MAX_ITER, OFF_WINDOW, TRUNCATED, WIDE_PSF, mark
from core.model import empty_params
from ..options import SolverOptions
from .prepare import Samples
from ..model.slots import parameter_bounds, tie_widths

__all__ = ["Labels", "final_state", "label_components", "at_bound", "params_at_bound"]


@dataclass(frozen=True)
class Labels:
    """Named components of every pixel: ``params`` (keys of :mod:`core.model`, shapes
    (P,) and (P, R), NaN where absent) and ``flags`` (P,) (MAX_ITER, AT_BOUND, WIDE_PSF,
    TRUNCATED, OFF_WINDOW)."""

    params: dict
    flags: np.ndarray


def at_bound(state: dict, bounds: dict) -> np.ndarray:
    """(n,) bool: some atom's log sigma, or the sss atom's log alpha, is at its bound."""
    act = state["fam"] != FAM_NONE
    hit = act & _at_limit(state["lsig"], bounds["lsig"])
    hit |= (state["fam"] == FAM_SSS) & _at_limit(state["lalp"], bounds["lalp"])
    return hit.any(axis=1)


def _at_limit(x, limits) -> np.ndarray:
    """Values ``x`` (log units) within BOUND_TOL of either of ``limits`` (lo, hi) or beyond
    (False for NaN)."""
    return (x <= limits[0] + BOUND_TOL) | (x >= limits[1] - BOUND_TOL)


def params_at_bound(params: dict, bounds: dict) -> np.ndarray:
    """(P,) bool: :func:`at_bound`'s rule on named parameters (P-shaped ``params``, NaN where
    absent; ``bounds`` with "lsig" and "lalp", log sigma_ps and log alpha_per_ps): a present
    component's width, or the sss attenuation, at its bound."""
    with np.errstate(divide="ignore", invalid="ignore"):
        widths = [np.log(np.asarray(params[k], np.float64)).reshape(len(params[k]), -1)
                  for k in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps")]
        hit = _at_limit(np.concatenate(widths, axis=1), bounds["lsig"]).any(axis=1)
        hit |= _at_limit(np.log(np.asarray(params["sss_alpha_per_ps"], np.float64)), bounds["lalp"])
    return hit


def final_atoms(st: dict, t_ps: np.ndarray, time_bin_ps: float, opts: SolverOptions, noise=None,
                weights=None, irf=None) -> dict:
    """The atoms a pixel keeps, as every output reports them (in place): the in-window threshold
    (relative, or significant against the pixel's ``noise`` (n,), normalised units;
    :func:`decomposition.model.components.threshold`), Gaussians merged (refinement can bring two
    together), one width per pixel with ``shared_sigma`` (a merge leaves the merged atom wider),
    no sss onset before the direct with ``sss_after_direct``.  The search stage scores its
    starts through the same rule, and a measured response's labels (``irf``: its atoms' heights
    and energies, the larger of two close shifted copies kept, no width to share)."""
    comp.threshold(st, t_ps, opts.rel_threshold, noise, opts.significance_chi2, weights, irf=irf)
    comp.merge_gaussians(st, time_bin_ps, opts.merge_tol_bins, widths=irf is None)
    if opts.shared_sigma and irf is None:
        tie_widths(st)
    if opts.sss_after_direct:
        comp.clip_sss_onset(st)
    return st


def final_state(samples: Samples, det: Detection, dic: cs.Dictionary, opts: SolverOptions) -> dict:
    """The detected atoms of the live pixels as every output reports them: snapped
    (``off_grid=False``), thresholded and merged (:func:`final_atoms`); slot state (n, K)."""
    live = samples.live
    st = {k: v.copy() for k, v in det.state.items()}
    if not opts.off_grid:
        cs.snap_to_grid(st, dic)
        p, mask = solver_inputs(samples, live)
        cs.refit_amplitudes(p, mask, st, dic)
    t = dic.t0_ps + dic.time_bin_ps * np.arange(samples.n_bins)
    return final_atoms(st, t, dic.time_bin_ps, opts, samples.significance_sigma(live, det.noise_eff[live]),
                       det.weights, irf=dic.response)


def label_components(samples: Samples, det: Detection, dic: cs.Dictionary, opts: SolverOptions,
                     state: dict | None = None) -> Labels:
    """Snap (``off_grid=False``), threshold, merge and classify the detected atoms; ``state``:
    the final atoms already (:func:`final_state`, and a later step's additions), classified as
    they are."""
    P = samples.values.shape[0]
    live = samples.live
    R = opts.max_reflections
    flags = np.zeros(P, FLAG_DTYPE)
    params = empty_params((P,), n_ir=R)
    mark(flags, live[~det.converged], MAX_ITER)
    st = final_state(samples, det, dic, opts) if state is None else {k: v.copy() for k, v in state.items()}
    t = dic.t0_ps + dic.time_bin_ps * np.arange(samples.n_bins)
    mark(flags, live[comp.off_window(st, t).any(axis=1)], OFF_WINDOW)
    mark(flags, live[at_bound(st, parameter_bounds(dic, opts.bound_factor))], AT_BOUND)
    wide = ((st["fam"] != FAM_NONE) & (st["lsig"] > math.log(dic.grid.sigma_range_ps[1]) + BOUND_TOL)).any(axis=1)
    mark(flags, live[wide], WIDE_PSF)
    got, trunc = comp.classify(st, samples.scale[live], R)
    mark(flags, live[trunc], TRUNCATED)
    for k, v in got.items():
        params[k][live] = v
    return Labels(params=params, flags=flags)
