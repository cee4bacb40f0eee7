"""The best-found fit of the true component set: the truth's start and an answer's, the lower cost kept.

A fit of the true component set started at the true parameters (the oracle,
:mod:`decomposition.evaluation.oracle`; the Poisson reference, :mod:`decomposition.evaluation.poisson_reference`)
stays in the optimum nearest the truth.  Where the data leave a valley of nearly equal cost
(a direct and an sss onset trading light, a direct narrower than a bin) or a second, lower
optimum, that fit is closer to the truth than any method that must find its own start can be
told to be.  The same fit started from a method's answer mapped onto the true component set
(:func:`answer_start`), and per pixel the fit of lower cost (:func:`lowest_cost`), is the best
fit of that component set the two starts find: its distance from the truth is what the data's
cost function allows, and a method's distance from it what the method's search costs.

Used by ``streaklab bench accuracy`` (the ``best-found`` ceiling: least-squares cost) and
``streaklab bench realism`` (the ``best`` variant: Poisson deviance).
"""
from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["MATCH_WIDTHS", "answer_start", "lowest_cost"]

#: An answer's inter-reflection is matched to a true one within this many PSF widths of it (the
#: ``match_ps`` both benches give :func:`answer_start`, in the widths of their scenes).
MATCH_WIDTHS = 2.0


def answer_start(truth: dict, est: dict, *, delay_range_ps: tuple, match_ps, widths: bool = False) -> dict:
    """A start on the true component set from a method's answer.

    Each true component takes the answer's values where it found that component: the
    direct's delay and amplitude, the sss's onset, amplitude and alpha, and for each true
    inter-reflection the answer's nearest one within ``match_ps`` of its delay; the truth's
    values elsewhere, and wherever the answer's delay lies outside ``delay_range_ps`` or its
    amplitude is not positive.

    Parameters
    ----------
    truth, est : dict of ndarray
        True and estimated parameters (keys of :mod:`core.model`; shapes (N,) and (N, R)).
    delay_range_ps : (float, float)
        The delays a start may hold (the fit's window).
    match_ps : float or array_like (N,)
        Largest distance between a true inter-reflection and the answer's nearest one, in ps
        (per pixel where an array).
    widths : bool
        Also take the answer's PSF width (its ``direct_sigma_ps``, one width per pixel) for
        every component, where it is finite and positive (the Gaussian PSF's fits, whose width
        is free; a fit with a fixed response leaves ``False``).

    Returns
    -------
    dict of ndarray, the truth's keys and shapes (the truth itself is not modified).
    """
    lo, hi = delay_range_ps
    start = {k: np.array(v, np.float64, copy=True) for k, v in truth.items()}

    def est_of(key, shape):
        return np.asarray(est.get(key, np.full(shape, np.nan)), np.float64)

    def usable(delay, amp):
        return np.isfinite(delay) & (delay >= lo) & (delay <= hi) & (amp > 0)

    t_d = start["direct_delay_ps"]
    e_d, e_a = est_of("direct_delay_ps", t_d.shape), est_of("direct_amplitude", t_d.shape)
    take = np.isfinite(t_d) & usable(e_d, e_a)
    start["direct_delay_ps"][take], start["direct_amplitude"][take] = e_d[take], e_a[take]
    t_s = start["sss_alpha_per_ps"]
    e_sd, e_sa, e_al = (est_of(k, t_s.shape) for k in ("sss_delay_ps", "sss_amplitude", "sss_alpha_per_ps"))
    take = np.isfinite(t_s) & usable(e_sd, e_sa) & np.isfinite(e_al) & (e_al > 0)
    for key, v in (("sss_delay_ps", e_sd), ("sss_amplitude", e_sa), ("sss_alpha_per_ps", e_al)):
        start[key][take] = v[take]
    t_r = start["ir_delay_ps"]
    e_r, e_ra = est_of("ir_delay_ps", (t_r.shape[0], 0)), est_of("ir_amplitude", (t_r.shape[0], 0))
    if t_r.shape[1] and e_r.shape[1]:
        ok = usable(e_r, e_ra)
        dist = np.where(ok[:, None, :], np.abs(e_r[:, None, :] - t_r[:, :, None]), np.inf)     # (N, Rt, Re)
        k = np.argmin(dist, axis=2)
        reach = np.broadcast_to(np.asarray(match_ps, np.float64), t_d.shape)[:, None]
        near = np.isfinite(t_r) & (np.take_along_axis(dist, k[..., None], axis=2)[..., 0] <= reach)
        start["ir_delay_ps"] = np.where(near, np.take_along_axis(e_r, k, axis=1), t_r)
        start["ir_amplitude"] = np.where(near, np.take_along_axis(e_ra, k, axis=1), start["ir_amplitude"])
    if widths:
        w = est_of("direct_sigma_ps", t_d.shape)
        ok = np.isfinite(w) & (w > 0)
        for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"):
            if key in start:
                v = start[key]
                wk = w.reshape(w.shape + (1,) * (v.ndim - w.ndim))
                start[key] = np.where(np.isfinite(v) & ok.reshape(wk.shape), wk, v)
    return start


def lowest_cost(fits, *, cost: str, tie_tolerance: float = 1e-6):
    """Per pixel, the fit of lowest cost among ``fits``.

    Parameters
    ----------
    fits : sequence of dataclass instances of one type
        Fits of the same data and component set from different starts (an ``OracleFit``, a
        ``PoissonReferenceFit``): every field an array with the pixels leading (shape S + ...)
        or a dict of such arrays, and ``info[cost]`` (S) the objective each minimised.
    cost : str
        The key of that objective in ``info`` (``"rss"``, ``"deviance"``).
    tie_tolerance : float
        A fit replaces an earlier one only where its cost is lower by more than
        ``tie_tolerance`` x max(cost, 1): two starts that converge to the same optimum stop a
        convergence tolerance apart, and the earlier fit is kept there.

    Returns
    -------
    The type of the fits, every field taken per pixel from the winning fit; ``info`` gains
    ``start`` (S, int): the index in ``fits`` of the fit kept.
    """
    if not (np.isfinite(tie_tolerance) and tie_tolerance >= 0):
        raise ValueError(f"tie_tolerance must be finite and >= 0, got {tie_tolerance}")
    fits = list(fits)
    if not fits:
        raise ValueError("lowest_cost needs at least one fit")
    first = fits[0]
    if any(type(f) is not type(first) for f in fits):
        raise ValueError("lowest_cost: the fits are of different kinds")
    if any(cost not in f.info for f in fits):
        raise ValueError(f"lowest_cost: a fit's info holds no {cost!r}")
    costs = [np.asarray(f.info[cost], np.float64) for f in fits]
    names = [fl.name for fl in dataclasses.fields(first)]

    def layout(f):
        return {n: ({k: np.shape(v) for k, v in getattr(f, n).items()} if isinstance(getattr(f, n), dict)
                    else np.shape(getattr(f, n))) for n in names if n != "info"}

    if any(layout(f) != layout(first) for f in fits[1:]) or any(c.shape != costs[0].shape for c in costs):
        raise ValueError("lowest_cost: the fits differ in their component set or shape")
    win = np.zeros(costs[0].shape, np.int64)
    kept = np.where(np.isfinite(costs[0]), costs[0], np.inf)
    for i, c in enumerate(costs[1:], start=1):
        scale = np.maximum(np.where(np.isfinite(kept), kept, 1.0), 1.0)
        better = np.isfinite(c) & (c < kept - tie_tolerance * scale)
        win = np.where(better, i, win)
        kept = np.where(better, c, kept)
    lead = win.shape

    def pick(arrays):
        a = np.stack([np.asarray(x) for x in arrays])
        idx = win.reshape((1,) + lead + (1,) * (a.ndim - 1 - len(lead)))
        return np.take_along_axis(a, idx, axis=0)[0]

    out = {}
    for n in names:
        v = getattr(first, n)
        if isinstance(v, dict):
            out[n] = {k: pick([getattr(f, n)[k] for f in fits]) for k in v}
        else:
            out[n] = pick([getattr(f, n) for f in fits])
    out["info"]["start"] = win
    return type(first)(**out)
