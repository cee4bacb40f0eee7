"""Continuous refinement of response atoms: variable projection on blocks of pixels.

For a pixel with K slots (:mod:`decomposition.response_atoms`) the model is
m = sum_k a_k phi_k(theta), with theta the slots' delays and the sss slot's log alpha.  The
amplitudes enter linearly and are never iterated: for any theta they are the weighted
least-squares solution ``a(theta)`` of :func:`solve_amplitudes` (the normal equations of the
columns phi_k, a K x K solve per pixel; with ``fit_background`` a constant column -- the
background family's offset -- is one more column of that solve, fitted jointly with the
amplitudes and projected out of the delays' Jacobian like them).  theta is moved by Levenberg-Marquardt on the
projected residual (variable projection with Kaufman's Jacobian J = -P_perp G, where G holds
the columns a_k d phi_k / d theta_j and P_perp projects out the span of the atoms), every
pixel of a block at once; a step is kept per pixel only when it lowers the weighted residual
sum of squares.  Constraints by projection after each step: delays within ``delay_bounds_ps``,
log alpha within ``lalp_bounds``, the sss onset not before the pixel's earliest shifted atom
(``sss_after_direct``), and (``first_is_direct``) no shifted atom before slot 0.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from core.irf import InstrumentResponse
from core.model import BACKGROUND_KEY, render_profile
from .constants import FAM_GAUSS, FAM_NONE, FAM_SSS, POISSON_REFITS
from .noise import count_deviance, poisson_weights
from .response_atoms import slot_atoms
from .response_label import slots_to_params
from .slots import select_rows

__all__ = ["SlotFit", "Slots", "solve_amplitudes", "fit_slots", "refit_slots"]

_RIDGE = 1e-12
_LAMBDA0 = 1e-3
_LAMBDA_MAX = 1e10


@dataclass(frozen=True)
class SlotFit:
    """Result of :func:`fit_slots` for P pixels of K slots: ``delay``, ``lalp``, ``amp``
    (P, K); ``background`` (P,) the fitted constant offset (units of ``y``; 0 where it is not
    fitted); ``cost`` (P,) weighted residual sum of squares; ``resid`` (P, L) the weighted
    residual sw * (y - model); ``iterations`` (P,) int; ``converged`` (P,) bool."""

    delay: np.ndarray
    lalp: np.ndarray
    amp: np.ndarray
    background: np.ndarray
    cost: np.ndarray
    resid: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray


def solve_amplitudes(phi: np.ndarray, y: np.ndarray, sw: np.ndarray, active: np.ndarray):
    """Weighted least-squares amplitudes of the columns ``phi``.

    Parameters
    ----------
    phi : ndarray (P, K, L)     unit-peak atoms (zero rows for empty slots)
    y : ndarray (P, L)          profiles
    sw : ndarray (P, L)         square-root sample weights (0 excludes a sample)
    active : ndarray (P, K) bool

    Returns
    -------
    amp : ndarray (P, K)         0 in empty slots
    resid : ndarray (P, L)       weighted residual sw * (y - sum_k amp_k phi_k)
    cost : ndarray (P,)          its sum of squares
    pw : ndarray (P, K, L)       the weighted columns sw * phi
    minv : ndarray (P, K, K)     inverse of the (regularised) normal matrix
    """
    pw = phi * sw[:, None, :]
    yw = y * sw
    m = np.matmul(pw, pw.transpose(0, 2, 1))
    diag = np.einsum("pkk->pk", m)
    ridge = _RIDGE * np.maximum(diag.max(axis=1, keepdims=True), 1e-300)
    m += np.eye(phi.shape[1])[None] * np.where(active, ridge, 1.0)[:, :, None]
    minv = np.linalg.inv(m)
    with np.errstate(invalid="ignore"):     # a trial of non-finite cost is rejected by the caller
        amp = np.matmul(minv, np.matmul(pw, yw[:, :, None]))[..., 0]
    amp = np.where(active, amp, 0.0)
    resid = yw - np.matmul(amp[:, None, :], pw)[:, 0]
    return amp, resid, np.einsum("pl,pl->p", resid, resid), pw, minv


def _project(fam, delay, lalp, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct):
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


def _evaluate(irf, t, y, sw, fam, delay, lalp, fit_bg=None):
    phi, dd, dl = slot_atoms(irf, t, fam, delay, lalp, derivatives=True)
    active = fam != FAM_NONE
    if fit_bg is not None:      # the constant column (last), no nonlinear parameter
        phi = np.concatenate([phi, np.broadcast_to(fit_bg[:, None, None].astype(np.float64),
                                                   (phi.shape[0], 1, phi.shape[2]))], axis=1)
        active = np.concatenate([active, fit_bg[:, None]], axis=1)
    amp, resid, cost, pw, minv = solve_amplitudes(phi, y, sw, active)
    return {"phi": phi, "dd": dd, "dl": dl, "amp": amp, "resid": resid, "cost": cost, "pw": pw, "minv": minv}


def fit_slots(irf: InstrumentResponse, t_ps: np.ndarray, y: np.ndarray, sw: np.ndarray, fam: np.ndarray,
              delay: np.ndarray, lalp: np.ndarray, *, n_iter: int, lm_tol: float,
              delay_bounds_ps: tuple, lalp_bounds: tuple, sss_after_direct: bool = True,
              first_is_direct: bool = False, fit_background=None) -> SlotFit:
    """Refine the delays (and sss log alpha) of every active slot of a block of pixels.

    Parameters
    ----------
    irf : InstrumentResponse          on the axis' step
    t_ps : ndarray (L,)               time axis, ps
    y : ndarray (P, L)                profiles (any scale; 0 where the weight is 0)
    sw : ndarray (P, L)               square-root sample weights
    fam, delay, lalp : ndarray (P, K) starting slots (delays ps, log alpha of 1/ps)
    n_iter : int                      Levenberg-Marquardt iterations at most (0: amplitudes only)
    lm_tol : float
        A pixel stops when an accepted step gains less than ``lm_tol`` x its residual sum of
        squares per fitted sample.
    delay_bounds_ps, lalp_bounds : (float, float)
    sss_after_direct, first_is_direct : bool
        Constraints (see the module docstring).
    fit_background : ndarray (P,) bool, optional
        Pixels that also fit a constant offset (a column of ones in the amplitudes' solve);
        elsewhere the model has none.

    Returns
    -------
    SlotFit
    """
    t = np.asarray(t_ps, np.float64)
    fam = np.asarray(fam)
    P, K = fam.shape
    delay, lalp = _project(fam, np.where(fam != FAM_NONE, delay, 0.0), np.where(fam == FAM_SSS, lalp, 0.0),
                           delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
    fit_bg = None if fit_background is None else np.broadcast_to(np.asarray(fit_background, bool), (P,))
    cur = _evaluate(irf, t, y, sw, fam, delay, lalp, fit_bg)
    amp, cost = cur["amp"], cur["cost"]
    iters = np.zeros(P, np.int64)
    conv = np.zeros(P, bool)
    lam = np.full(P, _LAMBDA0)
    n_used = np.maximum((sw > 0).sum(axis=1), 1)
    free = np.concatenate([fam != FAM_NONE, fam == FAM_SSS], axis=1)               # (P, 2K)
    conv |= ~free.any(axis=1)
    state = {"delay": delay.copy(), "lalp": lalp.copy(), "amp": amp.copy(), "cost": cost.copy()}
    cache = cur
    for _ in range(int(n_iter)):
        idx = np.flatnonzero(~conv)
        if idx.size == 0:
            break
        c = {k: v[idx] for k, v in cache.items()}
        f = fam[idx]
        a = c["amp"][:, :K]
        g = np.concatenate([a[:, :, None] * c["dd"], a[:, :, None] * c["dl"]], axis=1) * sw[idx][:, None, :]
        fr = free[idx]
        g = np.where(fr[:, :, None], g, 0.0)
        # projected columns: g - pw^T minv (pw g^T)
        proj = np.matmul(c["pw"], g.transpose(0, 2, 1))                            # (n, K, 2K)
        gp = g - np.matmul(np.matmul(proj.transpose(0, 2, 1), c["minv"]), c["pw"])
        jtj = np.matmul(gp, gp.transpose(0, 2, 1))
        jtr = np.matmul(g, c["resid"][:, :, None])[..., 0]
        dg = np.einsum("pjj->pj", jtj)
        scale_d = np.where(fr, dg + 1e-300, 1.0)
        lhs = jtj + (lam[idx][:, None] * scale_d)[:, :, None] * np.eye(2 * K)[None]
        lhs += np.eye(2 * K)[None] * (~fr)[:, :, None]
        step = np.linalg.solve(lhs, np.where(fr, jtr, 0.0)[..., None])[..., 0]
        nd = state["delay"][idx] + np.where(fr[:, :K], step[:, :K], 0.0)
        nl = state["lalp"][idx] + np.where(fr[:, K:], step[:, K:], 0.0)
        nd, nl = _project(f, nd, nl, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
        trial = _evaluate(irf, t, y[idx], sw[idx], f, nd, nl, None if fit_bg is None else fit_bg[idx])
        ok = np.isfinite(trial["cost"]) & (trial["cost"] < c["cost"])
        gain = c["cost"] - trial["cost"]
        iters[idx] += 1
        acc = idx[ok]
        state["delay"][acc], state["lalp"][acc] = nd[ok], nl[ok]
        state["amp"][acc], state["cost"][acc] = trial["amp"][ok], trial["cost"][ok]
        lam[acc] /= 3.0
        lam[idx[~ok]] *= 4.0
        small = ok & (gain < lm_tol * trial["cost"] / n_used[idx])
        conv[idx[small]] = True
        conv[idx[~ok & (lam[idx] > _LAMBDA_MAX)]] = True
        for k in cache:                    # the accepted pixels' evaluation for the next step
            cache[k][acc] = trial[k][ok]
    return SlotFit(delay=np.where(fam != FAM_NONE, state["delay"], np.nan),
                   lalp=np.where(fam == FAM_SSS, state["lalp"], np.nan),
                   amp=np.where(fam != FAM_NONE, state["amp"][:, :K], 0.0),
                   background=state["amp"][:, K] if fit_bg is not None else np.zeros(P),
                   cost=state["cost"], resid=cache["resid"],
                   iterations=iters, converged=conv)


class Slots(NamedTuple):
    """The response path's answer for n live pixels: slot arrays ``fam``, ``delay`` (ps),
    ``lalp``, ``amp`` (normalised units) (n, K) in the refinement layout (slot 0 direct, 1 sss,
    2.. inter-reflections), ``params`` (n-shaped, units of the samples, no ``background``
    key), ``background`` (n,) units, ``iterations`` (n,) LM iterations spent."""

    fam: np.ndarray
    delay: np.ndarray
    lalp: np.ndarray
    amp: np.ndarray
    params: dict
    background: np.ndarray
    iterations: np.ndarray


def refit_slots(y, fam, delay, lalp, held, fit_bg, params, *, irf, t, ax, fit_mask, scale, opts, bounds, disp,
                sigma_eq, R) -> Slots:
    """Refine the slots of n live pixels (normalised profiles ``y`` (n, L), the offset ``held``
    (n,) counts / units already subtracted), with a jointly fitted constant offset where
    ``fit_bg``; count data refitted POISSON_REFITS times with weights 1 / Poisson variance of the
    previous model (offset included), each refit kept for a pixel only where it lowers the
    Poisson deviance below the start's (its amplitudes solved at its own delays) and the
    earlier refits', and the next refit starts from the better: the weights of a model that
    lacks a component (1 / the variance floor where a missed sss tail holds counts) can pull a
    direct tens of ps onto that tail.
    ``params``: the starting model (n-shaped, units, the ``background`` key read for the first
    weights).

    Returns :class:`Slots`: fam, delay, lalp, amp (n, K), params (n-shaped, units, no
    ``background`` key), background (n,) units (``held`` plus the fitted correction),
    iterations (n,).
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

    def solve(fam, delay, lalp, sw, n_iter):
        f = fit_slots(irf, t, y, sw, fam, delay, lalp, n_iter=n_iter, fit_background=bg_cols, **fit_kw)
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
        p = slots_to_params(fam, delay, lalp, amp, scale, sigma_eq, R)
        p[BACKGROUND_KEY] = background
        return [fam, delay, lalp, amp, background, p], f.iterations

    def render(p):
        return np.nan_to_num(render_profile(p, L, ax.time_bin_ps, ax.t0_ps, irf=irf))

    if counts:
        counts_y = y * scale[:, None] + held[:, None]
        model = render(params)
    for k in range(POISSON_REFITS if counts else 1):
        if counts:
            sw = np.sqrt(poisson_weights(model, fit_mask, disp)) * scale[:, None]
            if k == 0:
                # the start with its amplitudes solved at its own delays: what a refit must beat
                best, _ = solve(fam, delay, lalp, sw, 0)
                model_best = render(best[5])
                dev_best = count_deviance(counts_y, model_best, fit_mask, disp)
        cur, its = solve(fam, delay, lalp, sw, opts.n_polish)
        iterations += its
        fam, delay, lalp, amp, background, params = cur
        if counts:
            # the Poisson deviance, the fit's own objective, decides between the start and the
            # reweighted refits; the next refit starts from the better of the two
            model_cur = render(params)
            dev = count_deviance(counts_y, model_cur, fit_mask, disp)
            better = dev < dev_best
            best = [select_rows(better, a, b) for a, b in zip(cur, best)]
            model_best = select_rows(better, model_cur, model_best)
            dev_best = np.where(better, dev, dev_best)
            fam, delay, lalp, amp, background, params = best
            model = model_best
    params = {k: v for k, v in params.items() if k != BACKGROUND_KEY}
    return Slots(fam, delay, lalp, amp, params, background, iterations)


