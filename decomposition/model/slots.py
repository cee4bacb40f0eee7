"""Slot state of a block of pixels and the operations on it shared by the solver's steps.

A block's atoms live in "slot" arrays of shape (P, K): ``fam`` (int8, :mod:`decomposition.constants`),
``amp`` (model amplitude, units of the normalised profile), ``delay`` (ps), ``lsig``
(log sigma_ps), ``lalp`` (log alpha_per_ps) and ``pen`` (the penalty's amplitude scale).
Here: creating, slicing and merging states, rendering them, the objective, the parameter
bounds, the sss-onset link and the compiled Levenberg-Marquardt refinement
(:func:`decomposition.kernels.atomlm.lm_refine`) behind :func:`refine_atoms`, or with a measured
response's atoms its least squares (:func:`refine_penalised`).

Which samples count: a :class:`~decomposition.masks.SampleMask` (fitted, censored).
"""
from __future__ import annotations

import math

import numpy as np

from ..kernels.atomlm import atom_profiles, lm_refine, state_models
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, NEAR_SIGMA
from ..masks import SampleMask
from ..kernels.onsets import onset_links
from .atoms import slot_atoms
from .slotfit import least_squares

__all__ = ["new_state", "take", "put", "select_rows", "drop_zero", "eval_atoms", "render",
           "objective", "penalty",
           "linked_onsets", "refine_atoms", "refine_penalised", "parameter_bounds", "shape_bounds", "axis_of",
           "tie_widths"]


def axis_of(t):
    """(t0_ps, time_bin_ps) of a uniform time axis t (L,)."""
    return float(t[0]), float(t[1] - t[0]) if t.size > 1 else 1.0


def eval_atoms(t, fam, delay, lsig, lalp, response=None):
    """Unit-amplitude atoms (n, L) with flat parameter arrays (n,) on the uniform time axis t (L,);
    with a measured ``response`` its own atoms (:func:`decomposition.model.atoms.slot_atoms`;
    ``lsig`` is not read)."""
    if response is not None:
        return slot_atoms(response, t, np.asarray(fam)[:, None], np.asarray(delay, np.float64)[:, None],
                          np.asarray(lalp, np.float64)[:, None])[:, 0]
    return atom_profiles(*axis_of(t), t.size, fam, delay, lsig, lalp)


def render(t, st, response=None):
    """Model (P, L) of the slot state ``st`` (compiled: :func:`decomposition.kernels.atomlm.state_models`;
    with a measured ``response``, the sum of its atoms, :func:`decomposition.model.atoms.slot_atoms`)."""
    if response is not None:
        return _render(response, t, st)
    return state_models(*axis_of(t), t.size, st["fam"], st["amp"], st["delay"], st["lsig"], st["lalp"])


def objective(p, mask: SampleMask, model, st, mu, eps):
    """F per pixel (P,): 1/2 ||residual||^2 (:meth:`SampleMask.residual`) + :func:`penalty`."""
    r = mask.residual(p, model)
    return 0.5 * np.einsum("pl,pl->p", r, r) + penalty(st, mu, eps)


def penalty(st, mu, eps):
    """The log-sum penalty per pixel (P,): mu sum over the active slots of log(1 + pen_scale*amp/eps)."""
    pen = np.where(st["fam"] != FAM_NONE, np.log1p(st["pen"] * np.abs(st["amp"]) / eps[:, None]), 0.0)
    return mu * pen.sum(axis=1)


def take(st, idx):
    """The rows ``idx`` of a state (copies)."""
    return {k: v[idx] for k, v in st.items()}


def put(st, idx, sub):
    """Write the state ``sub`` into rows ``idx`` of ``st`` in place."""
    for k, v in sub.items():
        st[k][idx] = v


def select_rows(take, a, b):
    """The rows of ``a`` where ``take`` (n,), of ``b`` elsewhere (arrays, or dicts of them)."""
    if isinstance(a, dict):
        return {k: select_rows(take, a[k], b[k]) for k in a}
    return np.where(take.reshape((-1,) + (1,) * (np.ndim(a) - 1)), a, b)


def linked_onsets(st, near_sigma=None):
    """Pixels whose sss onset is tied to the direct (earliest Gaussian) delay.

    Returns (linked (P,), direct slot (P,), sss slot (P,)); the rule is
    :func:`decomposition.kernels.onsets.onset_link` (the one the compiled refinement applies), with
    ``near_sigma`` PSF widths (default :data:`~decomposition.constants.NEAR_SIGMA`).
    """
    return onset_links(st["fam"], st["delay"], st["lsig"], NEAR_SIGMA if near_sigma is None else near_sigma)


def refine_atoms(t, p, mask: SampleMask, st, mu, eps, bounds, n_iter, obj, tie_sigma=False, sss_after_direct=False,
                 tol=None, return_model=False, weights=None, response=None):
    """Levenberg-Marquardt on all active slots of the pixels in ``st``; monotone in F.

    ``obj`` is F at the current state (P,), the level a step must beat (None: computed
    exactly); returns (state, F, iterations run by the slowest pixel) and, with
    ``return_model``, the model (P, L) of the returned state.  The loop itself is
    :func:`decomposition.kernels.atomlm.lm_refine` (compiled, one pixel at a time): a pixel stops when
    an accepted step lowers F by less than ``tol`` times F per fitted sample (a change far
    below what one sample's misfit can resolve; it shrinks as the fit improves, so noiseless
    data converge fully), or when its damping has grown past 1e8.  With ``tie_sigma`` pixels
    whose atoms already share one sigma keep sharing it; with ``sss_after_direct`` a near sss
    onset moves with the direct and its gap stays >= 0.  ``weights`` (P, L): least-squares
    weights of the samples (relative inverse variances; default 1).  With a measured
    ``response`` (an :class:`~core.irf.InstrumentResponse`) the atoms are its own and the loop is
    :func:`refine_penalised` (no width to fit or tie).
    """
    if response is not None:
        out, o, it, model = refine_penalised(response, t, p, mask, st, mu, eps, bounds, n_iter, obj,
                                             sss_after_direct, 0.0 if tol is None else tol, weights)
        return (out, o, it, model) if return_model else (out, o, it)
    out, o, iters, model = lm_refine(*axis_of(t), p, mask, st, mu, eps, bounds, n_iter, obj, tie_sigma=tie_sigma,
                                     sss_after_direct=sss_after_direct, tol=0.0 if tol is None else tol,
                                     weights=weights)
    it = int(iters.max(initial=0))
    return (out, o, it, model) if return_model else (out, o, it)


def new_state(P, K):
    """Empty slot state of P pixels with K slots."""
    return {
        "fam": np.zeros((P, K), np.int8),
        "amp": np.zeros((P, K)),
        "delay": np.zeros((P, K)),
        "lsig": np.zeros((P, K)),
        "lalp": np.zeros((P, K)),
        "pen": np.ones((P, K)),
    }


def parameter_bounds(dic, bound_factor: float):
    """Bounds of delay (ps), log sigma and log alpha of a :class:`~decomposition.methods.dictionary.Dictionary`'s
    atoms: the window widened by ``pre`` bins, the grid ranges widened by ``bound_factor``."""
    T = dic.time_bin_ps
    return {"delay": (dic.t0_ps - dic.pre * T, dic.t0_ps + (dic.n_bins - 1 + dic.pre) * T),
            **shape_bounds(dic.grid, bound_factor)}


def shape_bounds(grid, bound_factor: float):
    """{"lsig": (lo, hi), "lalp": (lo, hi)}: log sigma_ps and log alpha_per_ps bounds of a
    :class:`~decomposition.options.GridSpec`'s ranges widened by ``bound_factor``."""
    return {
        "lsig": (math.log(grid.sigma_range_ps[0] / bound_factor), math.log(grid.sigma_range_ps[1] * bound_factor)),
        "lalp": (math.log(grid.alpha_range_per_ps[0] / bound_factor),
                 math.log(grid.alpha_range_per_ps[1] * bound_factor)),
    }



def drop_zero(st):
    """Empty the slots of atoms whose amplitude is not positive (in place)."""
    dead = (st["fam"] != FAM_NONE) & ~(st["amp"] > 0)
    st["fam"][dead] = FAM_NONE
    st["amp"][dead] = 0.0



def tie_widths(st):
    """One PSF width per pixel (in place): every active atom's log sigma set to the
    area-weighted mean of the pixel's active atoms (area = amplitude x sigma).

    The compiled refinement keeps a shared width shared (``tie_sigma``) only where all atoms
    already have it; merging two Gaussians, or atoms picked at different grid widths, can
    leave a pixel with a small split that an untied polish then amplifies.
    """
    act = st["fam"] != FAM_NONE
    w = np.where(act, np.abs(st["amp"]) * np.exp(st["lsig"]), 0.0)
    tot = w.sum(axis=1)
    n_act = act.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(tot > 0, (w * st["lsig"]).sum(axis=1) / tot,
                        np.where(act, st["lsig"], 0.0).sum(axis=1) / np.maximum(n_act, 1))
    st["lsig"] = np.where(act, mean[:, None], st["lsig"])
    return st


def refine_penalised(irf, t_ps, p, mask: SampleMask, st: dict, mu, eps, bounds: dict, n_iter: int, obj=None,
                     sss_after_direct: bool = False, tol: float = 0.0, weights=None):
    """ConvSCD's refinement of a slot state (:func:`refine_atoms`) over
    a measured response's atoms: :func:`least_squares` on the fitted samples (censored ones left
    out: the response's fit has no one-sided term), atoms whose amplitude ends non-positive
    emptied and the rest re-solved, and the answer kept per pixel only where the objective

        F = 1/2 sum w residual^2 + mu sum_k log(1 + pen_k amp_k / eps)

    is lower than ``obj`` (F of ``st``; None: computed here), so F never rises -- or, with
    ``sss_after_direct``, where ``st`` itself breaks that order (an sss onset before a shifted
    atom picked after it): the fit moved the onset to that atom, and F of a state the model
    does not allow is no bar.

    Parameters
    ----------
    irf : InstrumentResponse
    t_ps : ndarray (L,)
    p : ndarray (P, L)                normalised profiles
    mask : SampleMask
    st : dict of (P, K) slot arrays   (``lsig`` is carried, never read: the response has no width)
    mu, eps : ndarray (P,)            the penalty's weight and scale
    bounds : dict                     ``delay`` (ps) and ``lalp`` (low, high)
    n_iter : int                      Levenberg-Marquardt iterations at most
    obj : ndarray (P,), optional
    sss_after_direct : bool
    tol : float                       stop when a step gains less than ``tol`` x the RSS per sample
    weights : ndarray (P, L), optional   relative least-squares weights of the samples

    Returns
    -------
    (state, F (P,), iterations of the slowest pixel, model (P, L))
    """
    fam = st["fam"]
    sw = mask.fit.astype(np.float64)
    if weights is not None:
        sw = sw * np.sqrt(weights)
    kw = dict(lm_tol=tol, delay_bounds_ps=bounds["delay"], lalp_bounds=bounds["lalp"],
              sss_after_direct=sss_after_direct)
    f = least_squares(irf, t_ps, p, sw, fam, st["delay"], st["lalp"], n_iter=n_iter, **kw)
    new_fam, amp, cost = fam.copy(), f.amp, f.cost
    delay, lalp = np.nan_to_num(f.delay), np.nan_to_num(f.lalp)
    for _ in range(fam.shape[1]):          # each round empties at least one slot of the pixels it re-solves
        bad = (new_fam != FAM_NONE) & ~(amp > 0)
        if not bad.any():
            break
        new_fam[bad] = FAM_NONE
        r = np.flatnonzero(bad.any(axis=1))
        g = least_squares(irf, t_ps, p[r], sw[r], new_fam[r], delay[r], lalp[r], n_iter=0, **kw)
        amp, cost = amp.copy(), cost.copy()
        amp[r], cost[r] = g.amp, g.cost
    on = new_fam != FAM_NONE
    new = dict(st, fam=new_fam, delay=np.where(on, delay, st["delay"]),
               lalp=np.where(on & (new_fam == FAM_SSS), lalp, st["lalp"]), amp=np.where(on, amp, 0.0))
    f_new = 0.5 * cost + penalty(new, mu, eps)
    if obj is None:
        r_in = sw * (p - _render(irf, t_ps, st))
        obj = 0.5 * np.einsum("pl,pl->p", r_in, r_in) + penalty(st, mu, eps)
    keep = np.isfinite(f_new) & ((f_new < obj) | _onset_first(st, sss_after_direct))
    out = {k: np.where(keep.reshape((-1,) + (1,) * (v.ndim - 1)), new[k], v) for k, v in st.items()}
    model = _render(irf, t_ps, out)     # one render of the state returned
    return out, np.where(keep, f_new, obj), int(f.iterations.max(initial=0)), model


def _onset_first(st, sss_after_direct):
    """(P,) bool: with ``sss_after_direct``, the sss onset lies before the earliest shifted atom."""
    if not sss_after_direct:
        return np.zeros(st["fam"].shape[0], bool)
    first = np.where(st["fam"] == FAM_GAUSS, st["delay"], np.inf).min(axis=1)
    onset = np.where(st["fam"] == FAM_SSS, st["delay"], np.inf).min(axis=1)
    return np.isfinite(onset) & (onset < first)


def _render(irf, t_ps, st):
    phi = slot_atoms(irf, t_ps, st["fam"], st["delay"], st["lalp"])
    return np.einsum("pk,pkl->pl", np.where(st["fam"] != FAM_NONE, st["amp"], 0.0), phi)
