"""Least-squares fits of a measured response's atoms on blocks of slot arrays.

A pixel's components are slot arrays (P, K) (:mod:`decomposition.model.atoms`): ``fam``,
``delay`` (ps), ``lalp`` (log alpha, 1/ps).  :func:`least_squares` fits their delays and decay
rates by the refinement engine the Gaussian PSF's atoms take
(:func:`decomposition.model.varpro.refine_block`, rendering the response's table atoms): the
amplitudes -- and with ``fit_background`` a constant offset -- solved exactly for every set of
delays, those moved by Levenberg-Marquardt on the projected residual.  ConvSCD's detection runs
the same fit after each pick (:func:`decomposition.model.slots.refine_penalised`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, SSS_SLOT
from ..kernels.response import response_table
from .varpro import Layout, refine_block

__all__ = ["SlotFit", "LAMBDA0", "project_slots", "start_slots", "least_squares"]

#: Marquardt's starting damping
LAMBDA0 = 1e-3


@dataclass(frozen=True)
class SlotFit:
    """Result of :func:`least_squares` (and of the count fit of
    :func:`decomposition.response.refine.fit_slots`) for P pixels of K slots: ``delay``,
    ``lalp``, ``amp`` (P, K); ``background`` (P,) the fitted constant offset (units of ``y``; 0
    where it is not fitted); ``cost`` (P,) weighted residual sum of squares; ``resid`` (P, L) the
    weighted residual sw * (y - model); ``iterations`` (P,) int; ``converged`` (P,) bool."""

    delay: np.ndarray
    lalp: np.ndarray
    amp: np.ndarray
    background: np.ndarray
    cost: np.ndarray
    resid: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray


def project_slots(fam, delay, lalp, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct):
    """The slots' delays and log alphas moved into their bounds and constraints: within
    ``delay_bounds_ps`` and ``lalp_bounds``, (``first_is_direct``) no shifted atom before slot 0,
    (``sss_after_direct``) the sss onset not before the earliest shifted atom -> (delay, lalp)."""
    delay = np.clip(delay, *delay_bounds_ps)
    lalp = np.clip(lalp, *lalp_bounds)
    sh = fam == FAM_GAUSS
    if first_is_direct:
        d0 = np.where(sh[:, :1], delay[:, :1], -np.inf)
        rest = sh.copy()
        rest[:, 0] = False
        delay = np.where(rest, np.maximum(delay, d0), delay)
    if sss_after_direct:
        first = np.where(sh, delay, np.inf).min(axis=1, keepdims=True)
        delay = np.where((fam == FAM_SSS) & np.isfinite(first), np.maximum(delay, first), delay)
    return delay, lalp


def start_slots(fam, delay, lalp, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct,
                held_delay=None, held_lalp=None):
    """The start of a fit: the active slots' delays and log alphas (0 in the others) projected
    (:func:`project_slots`), the held ones (``held_delay``, ``held_lalp`` (P, K) bool) at their
    given values -> (delay, lalp, held: None or the (held delay, held lalp) masks of the active
    slots)."""
    P, K = fam.shape
    d_in, l_in = np.where(fam != FAM_NONE, delay, 0.0), np.where(fam == FAM_SSS, lalp, 0.0)
    delay, lalp = project_slots(fam, d_in, l_in, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
    held = None
    if held_delay is not None or held_lalp is not None:
        h_d = np.zeros((P, K), bool) if held_delay is None else np.asarray(held_delay, bool) & (fam != FAM_NONE)
        h_l = np.zeros((P, K), bool) if held_lalp is None else np.asarray(held_lalp, bool) & (fam == FAM_SSS)
        delay, lalp = np.where(h_d, d_in, delay), np.where(h_l, l_in, lalp)
        held = (h_d, h_l)
    return delay, lalp, held


def least_squares(irf, t_ps, y, sw, fam, delay, lalp, *, n_iter: int, lm_tol: float, delay_bounds_ps: tuple,
                  lalp_bounds: tuple, sss_after_direct: bool = True, first_is_direct: bool = False,
                  fit_background=None, held_delay=None, held_lalp=None) -> SlotFit:
    """Refine the delays (and sss log alpha) of every active slot of a block of pixels by
    weighted least squares (amplitudes of any sign).

    Parameters
    ----------
    irf : InstrumentResponse          on the axis' step
    t_ps : ndarray (L,)               time axis, ps
    y : ndarray (P, L)                profiles (any scale)
    sw : ndarray (P, L)               square-root sample weights (0 leaves a sample out)
    fam, delay, lalp : ndarray (P, K) starting slots (delays ps, log alpha of 1/ps)
    n_iter : int                      Levenberg-Marquardt iterations at most (0: amplitudes only)
    lm_tol : float
        A pixel stops when an accepted step gains less than ``lm_tol`` x its residual sum of
        squares per fitted sample.
    delay_bounds_ps, lalp_bounds : (float, float)
    sss_after_direct, first_is_direct : bool
        Constraints (:func:`project_slots`).
    fit_background : ndarray (P,) bool, optional
        Pixels that also fit a constant offset; elsewhere the model has none.
    held_delay, held_lalp : ndarray (P, K) bool, optional
        Slots whose delay / log alpha is held at the value given (a shared onset or decay
        rate): not fitted, and not moved by the constraints.

    Returns
    -------
    SlotFit
    """
    t = np.asarray(t_ps, np.float64)
    fam = np.asarray(fam)
    delay, lalp, held = start_slots(fam, delay, lalp, delay_bounds_ps, lalp_bounds, sss_after_direct,
                                    first_is_direct, held_delay, held_lalp)
    fit_bg = None if fit_background is None else np.broadcast_to(np.asarray(fit_background, bool), fam.shape[:1])
    return _least_squares(irf, t, y, sw, fam, delay, lalp, fit_bg, held, n_iter=n_iter, lm_tol=lm_tol,
                          delay_bounds_ps=delay_bounds_ps, lalp_bounds=lalp_bounds,
                          sss_after_direct=sss_after_direct, first_is_direct=first_is_direct)


def _least_squares(irf, t, y, sw, fam, delay, lalp, fit_bg, held, *, n_iter, lm_tol, delay_bounds_ps,
                   lalp_bounds, sss_after_direct, first_is_direct) -> SlotFit:
    """:func:`least_squares` from its projected start: the refinement's variable projection
    (:func:`decomposition.model.varpro.refine_block` over the response's table atoms), its slots
    laid out as that engine's (slot 0 the pixel's first shifted atom, 1 its sss, 2.. the other
    shifted atoms in their order) and back; plain least squares (amplitudes of any sign), the
    inter-reflections kept after the first shifted atom (``first_is_direct``), the onset at or
    after the earliest shifted atom (``sss_after_direct``); a pixel stops when a kept step gains
    less than ``lm_tol`` x its residual sum of squares per fitted sample."""
    P, K = fam.shape
    sh, ss = fam == FAM_GAUSS, fam == FAM_SSS
    if (ss.sum(axis=1) > 1).any():
        raise ValueError("a pixel's slots hold at most one sss atom")
    rank = np.cumsum(sh, axis=1) - 1
    pos = np.where(sh, np.where(rank == 0, 0, rank + 1), np.where(ss, SSS_SLOT, -1))       # (P, K)
    kv = max(2, 1 + int(sh.sum(axis=1).max(initial=0)))
    pix, slot = np.nonzero(pos >= 0)
    vslot = pos[pix, slot]
    present = np.zeros((P, kv), bool)
    present[pix, vslot] = True
    v_delay = np.zeros((P, kv))
    v_delay[pix, vslot] = delay[pix, slot]
    sss_lalp = np.where(ss, lalp, 0.0).sum(axis=1)
    slots = {"delay": v_delay, "sigma": np.ones((P, kv)), "amplitude": np.zeros((P, kv)), "present": present,
             "alpha": np.where(ss.any(axis=1), np.exp(sss_lalp), np.nan)}
    if fit_bg is not None and fit_bg.any():
        slots["fit_background"], slots["background"] = fit_bg, np.zeros(P)
    lay = Layout(kv, widths=False)
    lo, hi = lay.bounds(delay_bounds_ps, (0.0, 0.0), lalp_bounds)
    v_held = None
    if held is not None:
        d_held = np.zeros((P, kv), bool)
        d_held[pix, vslot] = held[0][pix, slot]
        v_held = lay.held(d_held, np.ones(P, bool), (held[1] & ss).any(axis=1))
    n_used = np.maximum((sw > 0).sum(axis=1), 1)
    yw = y * sw
    with np.errstate(under="ignore"):
        out, info = refine_block(t, yw, slots, lay, (lo, hi), None, int(n_iter), lm_tol / n_used, LAMBDA0, sw=sw,
                                 sss_after_direct=sss_after_direct, keep_order=first_is_direct, held=v_held,
                                 table=response_table(irf), positive=False, onset_after_earliest=True,
                                 residual=True)
    f_delay = np.full((P, K), np.nan)
    f_delay[pix, slot] = out["delay"][pix, vslot]
    f_amp = np.zeros((P, K))
    f_amp[pix, slot] = out["amplitude"][pix, vslot]
    f_lalp = np.where(ss, np.log(out["alpha"])[:, None], np.nan)
    background = out["background"]
    # the engine's weighted residual where it kept its fit; elsewhere the fit is its start, no
    # atom's light and no offset (amplitudes and offset 0): the weighted data
    resid = np.where(info["refined"][:, None], info["residual"], yw)
    return SlotFit(delay=f_delay, lalp=f_lalp, amp=f_amp, background=background,
                   cost=np.einsum("pl,pl->p", resid, resid), resid=resid, iterations=info["iterations"],
                   converged=info["converged"])
