"""Continuous refinement of response atoms on blocks of pixels.

For a pixel with K slots (:mod:`decomposition.model.atoms`) the model is
m = sum_k a_k phi_k(theta), with theta the slots' delays and the sss slot's log alpha.  Gaussian
data are fitted by the refinement the Gaussian PSF's atoms take
(:func:`decomposition.model.slotfit.least_squares`: variable projection over the response's
table atoms).  Count data (:class:`CountData`) are fitted instead to their
Poisson deviance by Fisher scoring over the delays, log alphas and amplitudes together
(:func:`_fit_counts`, compiled in :mod:`decomposition.kernels.countlm`), no step turning a
positive amplitude non-positive.  Constraints by
projection after each step: delays within ``delay_bounds_ps``, log alpha within
``lalp_bounds``, the sss onset not before the pixel's earliest shifted atom
(``sss_after_direct``), and (``first_is_direct``) no shifted atom before slot 0.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from core.irf import InstrumentResponse
from core.model import BACKGROUND_KEY
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, POISSON_FIT_FLOOR, SSS_SLOT
from ..model.slotfit import LAMBDA0, SlotFit, least_squares, project_slots, start_slots
from ..noise import count_deviance, poisson_weights
from ..kernels.countlm import count_lm
from ..kernels.jit import kernel_array
from ..kernels.projected import GAUSSIAN_PSF, response_instrument
from ..model.atoms import GaussianPSF, instrument_rows, params_profile, slot_atoms
from ..model.components import merge_gaussians
from .label import slots_to_params

#: ridge of the amplitudes' normal matrix (:func:`solve_amplitudes`), relative to its largest diagonal
RIDGE = 1e-12
#: the damping beyond which a pixel's count fit stops
LAMBDA_MAX = 1e10
#: count data take the compiled loop (:func:`_fit_counts_compiled`, the same fit to rounding);
#: False: always the NumPy loop of :func:`_fit_counts` (the reference the compiled one is tested against)
COMPILED = True

__all__ = ["SlotFit", "Slots", "solve_amplitudes", "fit_slots", "refit_slots", "held_slot_masks", "refine_rows",
           "pixel_widths"]

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
    ridge = RIDGE * np.maximum(diag.max(axis=1, keepdims=True), 1e-300)
    m += np.eye(phi.shape[1])[None] * np.where(active, ridge, 1.0)[:, :, None]
    minv = np.linalg.inv(m)
    with np.errstate(invalid="ignore", over="ignore"):
        amp = np.matmul(minv, np.matmul(pw, yw[:, :, None]))[..., 0]
    # a pixel whose every active column is zero (its atoms all outside the window) has a
    # singular matrix whatever the ridge: nothing of the data is theirs
    amp = np.where(active & np.isfinite(amp), amp, 0.0)
    resid = yw - np.matmul(amp[:, None, :], pw)[:, 0]
    return amp, resid, np.einsum("pl,pl->p", resid, resid), pw, minv


def _evaluate(irf, t, y, sw, fam, delay, lalp, fit_bg=None):
    phi, dd, dl = slot_atoms(irf, t, fam, delay, lalp, derivatives=True)
    active = fam != FAM_NONE
    if fit_bg is not None:      # the constant column (last), no nonlinear parameter
        phi = np.concatenate([phi, np.broadcast_to(fit_bg[:, None, None].astype(np.float64),
                                                   (phi.shape[0], 1, phi.shape[2]))], axis=1)
        active = np.concatenate([active, fit_bg[:, None]], axis=1)
    amp, resid, cost, pw, minv = solve_amplitudes(phi, y, sw, active)
    return {"phi": phi, "dd": dd, "dl": dl, "amp": amp, "resid": resid, "cost": cost, "pw": pw, "minv": minv}


class CountData(NamedTuple):
    """Count profiles behind a block's normalised profiles ``y = (counts - held) / scale``:
    ``counts`` (P, L), ``scale`` (P,) counts per unit of ``y``, ``held`` (P,) the offset already
    subtracted (counts), ``fit`` (P, L) bool the samples that count, ``disp`` (P,) or None the
    counts' noise scale (1: the Poisson law)."""

    counts: np.ndarray
    scale: np.ndarray
    held: np.ndarray
    fit: np.ndarray
    disp: np.ndarray | None

    def rows(self, idx) -> "CountData":
        return CountData(self.counts[idx], self.scale[idx], self.held[idx], self.fit[idx],
                         None if self.disp is None else self.disp[idx])

    def model_counts(self, ev: dict) -> np.ndarray:
        """(P, L) expected counts of an evaluation (its amplitudes on its columns)."""
        return np.einsum("pk,pkl->pl", ev["amp"], ev["phi"]) * self.scale[:, None] + self.held[:, None]

    def weights(self, mu: np.ndarray) -> np.ndarray:
        """(P, L) square-root weights of the normalised profiles under expected counts ``mu``:
        scale / Poisson standard deviation (the variance floored at POISSON_FIT_FLOOR), 0 off
        the fitted samples."""
        return np.sqrt(poisson_weights(mu, self.fit, self.disp, floor_counts=POISSON_FIT_FLOOR)) * self.scale[:, None]

    def deviance(self, mu: np.ndarray) -> np.ndarray:
        """(P,) Poisson deviance of the counts under ``mu`` (chi2 units), read at the weights'
        floor: the objective whose Fisher scoring the weights are."""
        return count_deviance(self.counts, mu, self.fit, self.disp, floor_counts=POISSON_FIT_FLOOR)


def fit_slots(irf: InstrumentResponse, t_ps: np.ndarray, y: np.ndarray, sw: np.ndarray, fam: np.ndarray,
              delay: np.ndarray, lalp: np.ndarray, *, n_iter: int, lm_tol: float,
              delay_bounds_ps: tuple, lalp_bounds: tuple, sss_after_direct: bool = True,
              first_is_direct: bool = False, fit_background=None, counts: CountData | None = None,
              held_delay=None, held_lalp=None) -> SlotFit:
    """Refine the delays (and sss log alpha) of every active slot of a block of pixels: Gaussian
    data by :func:`decomposition.model.slotfit.least_squares` (its parameters are these), count
    data by their Poisson deviance.

    Parameters
    ----------
    irf, t_ps, y, sw, fam, delay, lalp, n_iter, lm_tol, delay_bounds_ps, lalp_bounds,
    sss_after_direct, first_is_direct, fit_background, held_delay, held_lalp
        As :func:`~decomposition.model.slotfit.least_squares`.
    counts : CountData, optional
        Count data: the objective is the Poisson deviance (``cost`` is it, chi2 units), fitted
        by Fisher scoring over delays, log alpha and amplitudes together (:func:`_fit_counts`);
        ``sw`` gives only the first weights, those of the starting amplitudes.
    Returns
    -------
    SlotFit
    """
    if counts is None:
        if isinstance(irf, GaussianPSF):
            raise ValueError("float data over the Gaussian PSF take the Gaussian path's refinement; fit_slots fits "
                             "the Gaussian PSF's atoms to counts only")
        return least_squares(irf, t_ps, y, sw, fam, delay, lalp, n_iter=n_iter, lm_tol=lm_tol,
                             delay_bounds_ps=delay_bounds_ps, lalp_bounds=lalp_bounds,
                             sss_after_direct=sss_after_direct, first_is_direct=first_is_direct,
                             fit_background=fit_background, held_delay=held_delay, held_lalp=held_lalp)
    t = np.asarray(t_ps, np.float64)
    fam = np.asarray(fam)
    bounds = (delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
    delay, lalp, held = start_slots(fam, delay, lalp, *bounds, held_delay, held_lalp)
    fit_bg = None if fit_background is None else np.broadcast_to(np.asarray(fit_background, bool), fam.shape[:1])
    if COMPILED or isinstance(irf, GaussianPSF):
        return _fit_counts_compiled(irf, t, y, sw, fam, delay, lalp, fit_bg, counts, n_iter=n_iter, lm_tol=lm_tol,
                                    bounds=bounds, held=held)
    cur = _evaluate(irf, t, y, sw, fam, delay, lalp, fit_bg)
    return _fit_counts(irf, t, y, fam, delay, lalp, cur, fit_bg, counts, n_iter=n_iter, lm_tol=lm_tol, bounds=bounds,
                       held=held)


def _fit_counts_compiled(irf, t, y, sw, fam, delay, lalp, fit_bg, counts: CountData, *, n_iter, lm_tol, bounds,
                         held=None) -> SlotFit:
    """:func:`_fit_counts` by its compiled loop (:func:`decomposition.kernels.countlm.count_lm`),
    the starting amplitudes' solve (:func:`solve_amplitudes`) included: the same fit to rounding.
    The Gaussian PSF's atoms (:class:`~decomposition.model.atoms.GaussianPSF`) are fitted here
    only, each pixel's width held."""
    delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct = bounds
    P, K = fam.shape
    Kc = K + (fit_bg is not None)
    h_d, h_l = held if held is not None else (np.zeros((P, K), bool), np.zeros((P, K), bool))
    delay, lalp = kernel_array(delay, np.float64).copy(), kernel_array(lalp, np.float64).copy()
    amp = np.zeros((P, Kc))
    cost = np.empty(P)
    mu = np.empty(y.shape)
    iters = np.zeros(P, np.int64)
    conv = np.zeros(P, bool)
    disp2 = np.ones(P) if counts.disp is None else np.square(kernel_array(counts.disp, np.float64))
    bg = np.zeros(P, bool) if fit_bg is None else kernel_array(fit_bg, np.bool_)
    f64 = np.float64
    if isinstance(irf, GaussianPSF):
        inst, lsig = GAUSSIAN_PSF, np.broadcast_to(np.log(irf.sigma_ps)[:, None], (P, K))
    else:
        inst, lsig = response_instrument(irf, t), np.zeros((P, K))
    count_lm(kernel_array(t, f64), kernel_array(counts.counts, f64), kernel_array(y, f64),
             kernel_array(np.broadcast_to(sw, y.shape), f64), kernel_array(counts.scale, f64),
             kernel_array(counts.held, f64), kernel_array(counts.fit, np.bool_), disp2, float(POISSON_FIT_FLOOR),
             kernel_array(fam, np.int8), delay, lalp, kernel_array(lsig, f64), amp, bg, kernel_array(h_d, np.bool_),
             kernel_array(h_l, np.bool_),
             float(delay_bounds_ps[0]), float(delay_bounds_ps[1]), float(lalp_bounds[0]), float(lalp_bounds[1]),
             bool(sss_after_direct), bool(first_is_direct), int(n_iter), float(lm_tol), float(LAMBDA0),
             float(LAMBDA_MAX), inst, cost, mu, iters, conv)
    return _counts_answer(y, fam, delay, lalp, amp, cost, mu, iters, conv, counts, K)


def _counts_answer(y, fam, delay, lalp, amp, cost, mu, iters, conv, counts: CountData, K) -> SlotFit:
    """The :class:`SlotFit` of a count fit: its slots, offset, deviance and the weighted residual
    of the normalised profiles under the final model's weights."""
    active = fam != FAM_NONE
    sw = counts.weights(mu)
    y_model = (mu - counts.held[:, None]) / counts.scale[:, None]
    resid = sw * np.where(counts.fit, y - y_model, 0.0)
    return SlotFit(delay=np.where(active, delay, np.nan), lalp=np.where(fam == FAM_SSS, lalp, np.nan),
                   amp=np.where(active, amp[:, :K], 0.0),
                   background=amp[:, K] if amp.shape[1] > K else np.zeros(len(fam)),
                   cost=cost, resid=resid, iterations=iters, converged=conv)


def _fit_counts(irf, t, y, fam, delay, lalp, cur: dict, fit_bg, counts: CountData, *, n_iter, lm_tol,
                bounds, held=None) -> SlotFit:
    """:func:`fit_slots` for count data: Levenberg-Marquardt on the Poisson deviance by Fisher
    scoring over every parameter at once -- the delays, the sss log alpha and the amplitudes
    (and the offset's correction) -- from the amplitudes of the first weights' solve ``cur``.

    Each step solves ``(J^T W J + lambda diag(J^T W J)) delta = J^T W (counts - mu)`` with J the
    expected counts' derivatives and W = 1 / their Poisson variance at the current model
    (floored at POISSON_FIT_FLOOR, times the dispersion squared), and is kept per pixel only
    where it lowers the deviance and leaves every positive amplitude positive; the offset (the
    one held plus the fitted correction) is projected onto >= 0 counts.  The weights are
    the objective's own at every step, and the gradient is the deviance's (nothing where the
    model is below the floor, which the deviance reads as the floor), so the fixed point is the
    maximum likelihood.  Amplitudes solved by weighted least squares at each step's delays
    (variable projection, as :func:`fit_slots` does for Gaussian data) are not the deviance's
    best there unless the weights have converged too, and such a fit stalled short of the
    optimum along the valley of an sss onset and its alpha."""
    delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct = bounds
    P, K = fam.shape
    phi, dd, dl, amp = cur["phi"], cur["dd"], cur["dl"], cur["amp"]                # amp (P, Kc)
    Kc = amp.shape[1]
    active = fam != FAM_NONE
    amp_free = np.concatenate([active, np.broadcast_to(fit_bg[:, None], (P, Kc - K))], axis=1) \
        if Kc > K else active
    h_d, h_l = held if held is not None else (np.zeros((P, K), bool), np.zeros((P, K), bool))
    free = np.concatenate([active & ~h_d, (fam == FAM_SSS) & ~h_l, amp_free], axis=1)   # (P, 2K + Kc)
    n_par = free.shape[1]

    def jacobian(phi, dd, dl, amp, scale):
        a = amp[:, :K, None]
        return np.concatenate([a * dd, a * dl, phi], axis=1) * scale[:, None, None]

    if Kc > K:
        # an offset of counts is light or dark counts: never below 0 (else it would lower the
        # model under the floor where the counts are 0 and buy deviance it does not explain)
        amp = amp.copy()
        amp[:, K] = np.maximum(amp[:, K], -counts.held / counts.scale)
    mu = counts.model_counts({"amp": amp, "phi": phi})
    dev = counts.deviance(mu)
    state = {"delay": delay.copy(), "lalp": lalp.copy(), "amp": amp.copy(), "cost": dev.copy()}
    cache = {"phi": phi, "dd": dd, "dl": dl, "mu": mu}
    iters = np.zeros(P, np.int64)
    lam = np.full(P, LAMBDA0)
    conv = ~free.any(axis=1)
    n_used = np.maximum(counts.fit.sum(axis=1), 1)
    for _ in range(int(n_iter)):
        idx = np.flatnonzero(~conv)
        if idx.size == 0:
            break
        c = counts.rows(idx)
        fr = free[idx]
        a_cur = state["amp"][idx]
        jac = np.where(fr[:, :, None], jacobian(cache["phi"][idx], cache["dd"][idx], cache["dl"][idx], a_cur,
                                                     c.scale), 0.0)
        w = np.square(c.weights(cache["mu"][idx]) / c.scale[:, None])                  # 1 / variance
        jw = jac * w[:, None, :]
        jtj = np.matmul(jw, jac.transpose(0, 2, 1))
        # the deviance's gradient: nothing where the model is below the floor (read as the floor)
        mu_i = cache["mu"][idx]
        jtr = np.einsum("pil,pl->pi", jw, np.where(c.fit & (mu_i >= POISSON_FIT_FLOOR), c.counts - mu_i, 0.0))
        dg = np.einsum("pjj->pj", jtj)
        # Marquardt's scaling, floored at 1e-12 of the largest (an atom that has left the
        # window has no column to scale by)
        dg = np.maximum(dg, 1e-12 * dg.max(axis=1, keepdims=True)) + 1e-300
        lhs = jtj + (lam[idx][:, None] * np.where(fr, dg, 1.0))[:, :, None] * np.eye(n_par)[None]
        lhs += np.eye(n_par)[None] * (~fr)[:, :, None]
        step = np.where(fr, _solve_rows(lhs, np.where(fr, jtr, 0.0)), 0.0)
        # a step that is not finite (an atom whose column vanished and whose amplitude grew
        # without bound) is refused like one that raises the deviance
        finite = np.isfinite(step).all(axis=1)
        step = np.where(finite[:, None], step, 0.0)
        f = fam[idx]
        nd, nl = project_slots(f, state["delay"][idx] + step[:, :K], state["lalp"][idx] + step[:, K:2 * K],
                               delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
        if held is not None:
            nd = np.where(h_d[idx], state["delay"][idx], nd)
            nl = np.where(h_l[idx], state["lalp"][idx], nl)
        na = np.where(amp_free[idx], a_cur + step[:, 2 * K:], 0.0)
        if Kc > K:
            na[:, K] = np.maximum(na[:, K], -c.held / c.scale)
        t_phi, t_dd, t_dl = slot_atoms(irf, t, f, nd, nl, derivatives=True)
        if Kc > K:
            t_phi = np.concatenate([t_phi, np.broadcast_to(fit_bg[idx, None, None].astype(np.float64),
                                                           (idx.size, 1, t_phi.shape[2]))], axis=1)
        t_mu = c.model_counts({"amp": na, "phi": t_phi})
        t_dev = c.deviance(t_mu)
        # no step turns an atom's light negative (the counts' model is a sum of light)
        was = np.all((a_cur[:, :K] > 0) | ~active[idx], axis=1)
        ok = (finite & np.isfinite(t_dev) & (t_dev < state["cost"][idx])
              & (~was | np.all((na[:, :K] > 0) | ~active[idx], axis=1)))
        gain = state["cost"][idx] - t_dev
        iters[idx] += 1
        acc = idx[ok]
        state["delay"][acc], state["lalp"][acc], state["amp"][acc], state["cost"][acc] = nd[ok], nl[ok], na[ok], t_dev[ok]
        cache["phi"][acc], cache["dd"][acc], cache["dl"][acc], cache["mu"][acc] = t_phi[ok], t_dd[ok], t_dl[ok], t_mu[ok]
        lam[acc] /= 3.0
        lam[idx[~ok]] *= 4.0
        conv[idx[ok & (gain < lm_tol * t_dev / n_used[idx])]] = True
        conv[idx[~ok & (lam[idx] > LAMBDA_MAX)]] = True
    return _counts_answer(y, fam, state["delay"], state["lalp"], state["amp"], state["cost"], cache["mu"], iters, conv,
                          counts, K)


def _solve_rows(lhs: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(P, n) the solutions of the P damped systems; NaN for a system singular to rounding
    (its damping shrunk below the rounding of a degenerate pair of columns), which the caller
    refuses as a step, raising that pixel's damping."""
    try:
        return np.linalg.solve(lhs, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full(rhs.shape, np.nan)
        for i in range(lhs.shape[0]):      # rare: only the batch that held a singular system
            try:
                out[i] = np.linalg.solve(lhs[i], rhs[i])
            except np.linalg.LinAlgError:
                pass
        return out


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


def refine_rows(refine_kw: dict, rows) -> dict:
    """The keywords of :func:`refit_slots` (``refine_kw``, for n pixels) for the pixels ``rows``:
    the per-pixel ones (``fit_mask``, ``scale``, ``disp``, ``weights``, ``hold``'s values, and
    the instrument and its widths where they are one per pixel) taken at them."""
    out = {k: (v[rows] if k in ("fit_mask", "scale", "disp", "weights") and v is not None else v)
           for k, v in refine_kw.items()}
    out["irf"] = instrument_rows(refine_kw["irf"], rows)
    if np.ndim(refine_kw["sigma_eq"]):
        out["sigma_eq"] = refine_kw["sigma_eq"][rows]
    if refine_kw.get("hold"):
        out["hold"] = {k: v[rows] for k, v in refine_kw["hold"].items()}
    return out


def pixel_widths(sigma_eq, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each of n pixels' (Gaussian-equivalent) width, ps, and its log, (n,) each, from the
    refit's ``sigma_eq``: one width for every pixel (a measured response's) or (n,) one per pixel
    (the Gaussian PSF's)."""
    if np.ndim(sigma_eq):
        width = np.asarray(sigma_eq, np.float64)
        return width, np.log(width)
    return np.full(n, float(sigma_eq)), np.full(n, math.log(sigma_eq))


def held_slot_masks(hold, fam, delay, lalp):
    """The slots a checked ``hold`` ({key of :data:`decomposition.model.refine.HOLD_KEYS`: (n,)
    values, NaN free}, no ``sigma_ps``) holds in the refinement layout of ``fam`` (n, K) ->
    (delay, lalp, held_delay, held_lalp): the slots' delays (ps) and log alphas with the held
    values put in where the component is present, and the (n, K) bool masks of those slots."""
    n, K = fam.shape
    h_d, h_l = np.zeros((n, K), bool), np.zeros((n, K), bool)
    delay, lalp = np.array(delay, np.float64), np.array(lalp, np.float64)
    for key, slot, fams in (("direct_delay_ps", 0, (FAM_GAUSS,)), ("sss_delay_ps", SSS_SLOT, (FAM_SSS,))):
        if key in hold:
            v = np.asarray(hold[key], np.float64)
            h_d[:, slot] = np.isfinite(v) & np.isin(fam[:, slot], fams)
            delay[:, slot] = np.where(h_d[:, slot], v, delay[:, slot])
    if "sss_alpha_per_ps" in hold:
        v = np.asarray(hold["sss_alpha_per_ps"], np.float64)
        h_l[:, SSS_SLOT] = np.isfinite(v) & (fam[:, SSS_SLOT] == FAM_SSS)
        with np.errstate(invalid="ignore", divide="ignore"):
            lalp[:, SSS_SLOT] = np.where(h_l[:, SSS_SLOT], np.log(v), lalp[:, SSS_SLOT])
    return delay, lalp, h_d, h_l


def refit_slots(y, fam, delay, lalp, held, fit_bg, params, *, irf, t, ax, fit_mask, scale, opts, bounds, disp,
                sigma_eq, R, hold=None, weights=None) -> Slots:
    """Refine the slots of n live pixels (normalised profiles ``y`` (n, L), the offset ``held``
    (n,) counts / units already subtracted), with a jointly fitted constant offset where
    ``fit_bg``.  Count data (``disp`` given) are fitted to their Poisson deviance
    (:func:`fit_slots` with :class:`CountData`), the first weights those of the starting model
    ``params`` (n-shaped, units, the ``background`` key read); every step lowers the deviance,
    so the answer is never worse than the start with its amplitudes solved at its own delays.
    ``hold`` ({key: (n,) values}, :func:`held_slot_masks`): onsets and decay rates held at
    given values where the component is present.  ``weights`` (n, L): Gaussian data's relative
    sample weights where the noise follows the signal (the signal-noise stage's), by which the
    residual is weighed (count data take their Poisson weights instead).

    Returns :class:`Slots`: fam, delay, lalp, amp (n, K), params (n-shaped, units, no
    ``background`` key), background (n,) units (``held`` plus the fitted correction),
    iterations (n,).
    """
    counts = disp is not None
    n = y.shape[0]
    iterations = np.zeros(n, np.int64)
    amp = np.zeros(fam.shape)
    background = held.astype(np.float64).copy()
    sw = fit_mask.astype(np.float64)
    if weights is not None and not counts:
        sw = sw * np.sqrt(weights)
    bg_cols = np.ones(n, bool) if fit_bg else None
    fit_kw = dict(lm_tol=opts.lm_tol, delay_bounds_ps=bounds["delay_ps"], lalp_bounds=bounds["lalp"],
                  sss_after_direct=opts.sss_after_direct, first_is_direct=True)
    params = dict(params)
    params[BACKGROUND_KEY] = background

    cd = None
    if counts:
        cd = CountData(y * scale[:, None] + held[:, None], scale, held, fit_mask, disp)
        sw = cd.weights(params_profile(irf, t, params))

    if hold:
        delay, lalp, h_d, h_l = held_slot_masks(hold, np.asarray(fam), delay, lalp)
        fit_kw.update(held_delay=h_d, held_lalp=h_l)

    def solve(fam, delay, lalp, sw, n_iter):
        f = fit_slots(irf, t, y, sw, fam, delay, lalp, n_iter=n_iter, fit_background=bg_cols, counts=cd, **fit_kw)
        delay, lalp, amp, b_fit = np.nan_to_num(f.delay), np.nan_to_num(f.lalp), f.amp, f.background
        # two shifted copies the fit put on one delay are one component (the labels' merge rule)
        merged = merge_gaussians({"fam": np.array(fam), "delay": delay, "amp": amp.copy()}, ax.time_bin_ps,
                                 opts.merge_tol_bins, widths=False)
        bad = ((fam != FAM_NONE) & ~(amp > 0)) | (merged["fam"] != fam)
        if bad.any():
            fam = merged["fam"]
            fam[bad] = FAM_NONE
            r = np.flatnonzero(bad.any(axis=1))
            kw = {k: (v[r] if k.startswith("held_") else v) for k, v in fit_kw.items()}
            g = fit_slots(instrument_rows(irf, r), t, y[r], sw[r], fam[r], delay[r], lalp[r], n_iter=0,
                          fit_background=None if bg_cols is None else bg_cols[r],
                          counts=None if cd is None else cd.rows(r), **kw)
            amp[r], b_fit = g.amp, b_fit.copy()
            b_fit[r] = g.background
        background = held + b_fit * scale
        p = slots_to_params(fam, delay, lalp, amp, scale, sigma_eq, R)
        p[BACKGROUND_KEY] = background
        return [fam, delay, lalp, amp, background, p], f.iterations

    cur, iterations = solve(fam, delay, lalp, sw, opts.n_polish)
    fam, delay, lalp, amp, background, params = cur
    params = {k: v for k, v in params.items() if k != BACKGROUND_KEY}
    return Slots(fam, delay, lalp, amp, params, background, iterations)


