"""Structured alternative starts for a decomposition.

Two entry points share the starts below.  :func:`search_components` is the search stage of
``decompose`` (``search=True``, the default): on the solver's slot states, for the pixels whose
answer is in doubt only, with the solver's compiled LM, AMBIGUOUS flags and per-start counters
(see :func:`search_block`).  :func:`structured_search` is the earlier stand-alone form on a
finished decomposition's parameters (every pixel, six variable-projection refines; ``streaklab
bench accuracy --methods search``), kept for comparison.

The sparse-coding step can settle on a wrong split that still fits the data: its typical
failure is an sss atom whose onset sits before the true direct reflection and absorbs it,
with the next Gaussian in time (an inter-reflection, or a bump on the sss hump) labelled
"direct".  :func:`structured_search` takes the profiles and a decomposition's parameters and
tries, for every pixel, a few starts built from physics:

``solver``
    the decomposition itself, relabelled by physics (:func:`relabel`);
``edge``
    a direct and an sss sharing the profile's leading edge (direct delay one and two PSF
    widths after the first crossing of 10 % of the smoothed peak, sss onset at the direct);
``peak``
    the earliest significant local maximum of the smoothed profile (>= 20 % of its peak) as
    the direct, the sss onset one PSF width after it;

each with the decomposition's Gaussians that lie more than ``ir_gap_sigma`` PSF widths after
the new direct as inter-reflections, and (``edge bare``, ``peak bare``) the first and the last
of them without any (a refine never changes a start's component set, so a spurious Gaussian
of the decomposition can only be dropped by a start without it).  Every start is refined by
:func:`decomposition.model.refine.refine` (one PSF width per pixel, sss onset at or after the
direct, inter-reflections in order), scored by a penalised objective

    J = RSS / s^2 + penalty * k * ln(L),

s the pixel's noise estimated from first differences, k the number of free parameters and L
the number of bins (the Bayesian information criterion for ``penalty = 1``), and the lowest J
is kept.  All work is on blocks of pixels: one refine call per kind of start.
"""

# One module over 600 lines on purpose: the search stage and the stand-alone structured_search share
# the start builders and the scoring of the starts; apart they would import each other.
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.model import IR_KEYS, SSS_KEYS, render_profile, time_axis_ps
from ..constants import (FAM_GAUSS, FAM_NONE, FAM_SSS, NARROW_FRACTION, NEAR_SIGMA, RISE_10_50_SIGMA,
                         SEARCH_DEFAULT_ALPHA_PER_PS, SEARCH_DEFAULT_SIGMA_PS, SEARCH_EDGE_GAP_SIGMA, SEARCH_EDGE_LEVEL,
                         SEARCH_IR_GAP_SIGMA, SEARCH_NEAR_DIRECT_CHI2, SEARCH_PEAK_LEVEL, SEARCH_RISE_MIN_BINS,
                         SEARCH_WIDE_FACTOR)
from ..noise import noise_sigma
from .objective import _smooth, objective_variance
from .selection import (ambiguity_tolerance, data_term, families, free_parameters, log_samples, penalised,
                        is_ambiguous, penalised_objective, penalty)
from ..model.refine import refine
from ..model import components as comp
from .candidates import polish_candidate
from ..model.components import classify, render_params
from .detect import solver_inputs
from .grow import grow_block
from .quality import direct_samples, weak_direct
from ..model.slots import new_state, put, render, take

__all__ = ["SearchOptions", "relabel", "structured_search", "STAGE_STARTS", "SearchStage", "search_block",
           "search_components", "weak_leading_gaussian"]

STARTS = ("solver", "edge", "edge2", "peak", "edge bare", "peak bare")

#: the starts of :func:`search_block` that also get the forward step of
#: :func:`decomposition.stages.grow.grow_block` (the ``rise`` start always gets it) where the best
#: start still misfits (only there: on every pixel in doubt the step gained more but cost
#: 8-10 % of the speed; measured: docs/history.md).
MISFIT_GROWN_STARTS = ("edge", "peak", "wide")


@dataclass(frozen=True)
class SearchOptions:
    """Settings of :func:`structured_search`.

    Attributes
    ----------
    penalty : float
        Weight of the parameter-count term of the objective (1 = BIC).
    ir_gap_sigma : float
        Solver Gaussians more than this many PSF widths after a start's direct become its
        inter-reflections; closer ones are dropped (the start's direct replaces them).
    edge_level, peak_level : float
        Fractions of the smoothed peak that define the leading edge and a significant peak.
    default_sigma_ps, default_alpha_per_ps : float
        Width and attenuation of a start where the decomposition has none.
    max_iter : int
        Levenberg-Marquardt iterations per refine.
    """

    penalty: float = 1.0
    ir_gap_sigma: float = SEARCH_IR_GAP_SIGMA
    edge_level: float = SEARCH_EDGE_LEVEL
    peak_level: float = SEARCH_PEAK_LEVEL
    default_sigma_ps: float = SEARCH_DEFAULT_SIGMA_PS
    default_alpha_per_ps: float = SEARCH_DEFAULT_ALPHA_PER_PS
    max_iter: int = 30

    def __post_init__(self):
        if not self.penalty >= 0:
            raise ValueError("SearchOptions.penalty must be >= 0")
        if not self.ir_gap_sigma > 0:
            raise ValueError("SearchOptions.ir_gap_sigma must be positive")
        if not (0 < self.edge_level < 1 and 0 < self.peak_level < 1):
            raise ValueError("SearchOptions.edge_level and peak_level must lie in (0, 1)")
        if not (self.default_sigma_ps > 0 and self.default_alpha_per_ps > 0):
            raise ValueError("SearchOptions defaults must be positive")
        if int(self.max_iter) < 1:
            raise ValueError("SearchOptions.max_iter must be >= 1")


def _gaussians(params):
    """All Gaussian components of each pixel (direct first, then inter-reflections): delays,
    amplitudes and widths, (N, 1 + R)."""
    d = np.concatenate([np.asarray(params["direct_delay_ps"], float)[:, None],
                        np.asarray(params["ir_delay_ps"], float)], axis=1)
    a = np.concatenate([np.asarray(params["direct_amplitude"], float)[:, None],
                        np.asarray(params["ir_amplitude"], float)], axis=1)
    s = np.concatenate([np.asarray(params["direct_sigma_ps"], float)[:, None],
                        np.asarray(params["ir_sigma_ps"], float)], axis=1)
    on = np.isfinite(d) & np.isfinite(a) & np.isfinite(s)
    return np.where(on, d, np.nan), np.where(on, a, np.nan), np.where(on, s, np.nan)


def _assemble(direct_delay, sigma, sss_delay, alpha, gd, ga, n_ir):
    """A start: a direct (NaN = none), an sss, and Gaussians ``gd`` / ``ga`` (N, G) as
    inter-reflections in delay order, at most ``n_ir`` of them."""
    order = np.argsort(np.where(np.isfinite(gd), gd, np.inf), axis=1, kind="stable")
    gd = np.take_along_axis(gd, order, axis=1)[:, :n_ir]
    ga = np.take_along_axis(ga, order, axis=1)[:, :n_ir]
    if gd.shape[1] < n_ir:
        pad = n_ir - gd.shape[1]
        gd = np.pad(gd, ((0, 0), (0, pad)), constant_values=np.nan)
        ga = np.pad(ga, ((0, 0), (0, pad)), constant_values=np.nan)
    has_d = np.isfinite(direct_delay)
    has_s = np.isfinite(sss_delay)
    return {
        "direct_delay_ps": direct_delay.copy(),
        "direct_amplitude": np.where(has_d, 1.0, np.nan),
        "direct_sigma_ps": np.where(has_d, sigma, np.nan),
        "sss_delay_ps": sss_delay.copy(),
        "sss_amplitude": np.where(has_s, 1.0, np.nan),
        "sss_alpha_per_ps": np.where(has_s, alpha, np.nan),
        "sss_sigma_ps": np.where(has_s, sigma, np.nan),
        "ir_delay_ps": gd,
        "ir_amplitude": np.where(np.isfinite(gd), np.where(np.isfinite(ga), np.abs(ga), 1.0), np.nan),
        "ir_sigma_ps": np.where(np.isfinite(gd), sigma[:, None], np.nan),
    }


def relabel(params: dict, n_ir: int | None = None) -> dict:
    """Labels by physics: the earliest Gaussian is the direct, the later ones inter-reflections
    in delay order; an sss onset before the direct is moved to the direct's delay.

    Parameters
    ----------
    params : dict of ndarray, shapes (N,) and (N, R)
    n_ir : int, optional
        Inter-reflection slots of the output (default R).

    Returns
    -------
    dict of ndarray, same keys, shapes (N,) and (N, n_ir).
    """
    gd, ga, gs = _gaussians(params)
    n_ir = gd.shape[1] - 1 if n_ir is None else int(n_ir)
    order = np.argsort(np.where(np.isfinite(gd), gd, np.inf), axis=1, kind="stable")
    gd, ga, gs = (np.take_along_axis(v, order, axis=1) for v in (gd, ga, gs))
    out = {k: np.asarray(params[k], float).copy() for k in SSS_KEYS}
    out["direct_delay_ps"], out["direct_amplitude"], out["direct_sigma_ps"] = gd[:, 0], ga[:, 0], gs[:, 0]
    for key, v in zip(IR_KEYS, (gd, ga, gs)):
        r = v[:, 1:1 + n_ir]
        out[key] = np.pad(r, ((0, 0), (0, n_ir - r.shape[1])), constant_values=np.nan)
    early = np.isfinite(out["sss_delay_ps"]) & np.isfinite(gd[:, 0]) & (out["sss_delay_ps"] < gd[:, 0])
    out["sss_delay_ps"] = np.where(early, gd[:, 0], out["sss_delay_ps"])
    return out


def _first_peak(ys, level):
    """Index of each profile's earliest significant local maximum (at least ``level`` x its
    peak), or of its maximum where it has none.  ys: (n, L) -> (n,) int."""
    top = ys.max(axis=1, keepdims=True)
    is_peak = np.zeros_like(ys, dtype=bool)
    is_peak[:, 1:-1] = (ys[:, 1:-1] >= ys[:, :-2]) & (ys[:, 1:-1] > ys[:, 2:]) & (ys[:, 1:-1] >= level * top)
    return np.where(is_peak.any(axis=1), np.argmax(is_peak, axis=1), np.argmax(ys, axis=1))


def structured_search(profiles, params: dict, *, time_bin_ps: float = 2.0, t0_ps: float | None = None,
                      options: SearchOptions | None = None):
    """Try structured alternative starts for each pixel and keep the lowest penalised objective.

    Parameters
    ----------
    profiles : array_like, (N, L)
        Measured profiles.
    params : dict of ndarray, shapes (N,) and (N, R)
        A decomposition's parameters (``DecompositionResult.params``).
    time_bin_ps, t0_ps : float
        Time axis in ps.
    options : SearchOptions, optional

    Returns
    -------
    params : dict of ndarray, shapes (N,) and (N, R)
        The chosen decomposition of each pixel, labelled by physics.
    info : dict of ndarray, (N,)
        ``start`` (index into :data:`STARTS` of the kept start), ``objective`` (its J) and
        ``objective_solver`` (J of the relabelled, refined input).
    """
    opt = options or SearchOptions()
    y = np.asarray(profiles, dtype=np.float64)
    if y.ndim != 2:
        raise ValueError(f"profiles must have shape (N, L), got {y.shape}")
    n, n_bins = y.shape
    T = float(time_bin_ps)
    t = time_axis_ps(n_bins, T, t0_ps)
    n_ir = int(np.shape(params["ir_delay_ps"])[-1])

    gd, ga, gs = _gaussians(params)
    sigma = np.asarray(params["direct_sigma_ps"], float)
    first_ir = np.take_along_axis(gs, np.argmax(np.isfinite(gs), axis=1)[:, None], axis=1)[:, 0]
    for alt in (first_ir, np.asarray(params["sss_sigma_ps"], float)):
        sigma = np.where(np.isfinite(sigma), sigma, alt)
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, opt.default_sigma_ps)
    alpha = np.asarray(params["sss_alpha_per_ps"], float)
    alpha = np.where(np.isfinite(alpha) & (alpha > 0), alpha, opt.default_alpha_per_ps)

    # Leading edge and the earliest significant peak of the smoothed profile.
    ys = _smooth(y, np.maximum(sigma / T, 0.5))
    top = ys.max(axis=1, keepdims=True)
    above = ys >= opt.edge_level * top
    i_edge = np.argmax(above, axis=1)
    t_edge = t[i_edge]
    t_peak = t[_first_peak(ys, opt.peak_level)]

    starts = {"solver": relabel(params, n_ir)}
    for name, d_delay, s_delay, keep in (("edge", t_edge + sigma, t_edge + sigma, True),
                                         ("edge2", t_edge + 2 * sigma, t_edge + 2 * sigma, True),
                                         ("peak", t_peak, t_peak + sigma, True),
                                         ("edge bare", t_edge + sigma, t_edge + sigma, False),
                                         ("peak bare", t_peak, t_peak + sigma, False)):
        later = keep & (gd > d_delay[:, None] + opt.ir_gap_sigma * sigma[:, None])
        starts[name] = _assemble(d_delay, sigma, s_delay, alpha, np.where(later, gd, np.nan),
                                 np.where(later, ga, np.nan), n_ir)


    s2 = np.maximum(noise_sigma(y, order=1), 1e-12 * np.abs(y).max(axis=1)) ** 2
    best, best_j, j_solver, which = None, None, None, np.zeros(n, np.int64)
    for k, name in enumerate(STARTS):
        start = starts[name]
        fit, _ = refine(y, start, time_bin_ps=T, t0_ps=t0_ps, max_iter=int(opt.max_iter), shared_sigma=True,
                        sss_after_direct=True, keep_order=True)
        rss = np.sum((y - render_profile(fit, n_bins, T, t0_ps)) ** 2, axis=1)
        j = penalised(rss / s2, free_parameters(families(fit), "shared"), log_samples(n_bins), opt.penalty)
        if best is None:
            best, best_j, j_solver = {key: v.copy() for key, v in fit.items()}, j, j.copy()
            continue
        better = j < best_j
        which = np.where(better, k, which)
        best_j = np.where(better, j, best_j)
        for key in best:
            m = better if best[key].ndim == 1 else better[:, None]
            best[key] = np.where(m, fit[key], best[key])
    return relabel(best, n_ir), {"start": which, "objective": best_j, "objective_solver": j_solver}


# ==========================================================================================
# The search stage of ``decompose`` (between detection and labelling), on slot states
# ==========================================================================================

#: starts of the search stage, in the order of ``info["search_wins"]``
STAGE_STARTS = ("solver", "edge", "peak", "peak bare", "rise", "wide")


@dataclass(frozen=True)
class SearchStage:
    """What :func:`search_components` hands on: the chosen atoms of the live pixels and, per
    pixel, the kept start (index into :data:`STAGE_STARTS`), whether it was searched at all
    (``doubt``) and whether the data leave its split undetermined (``ambiguous``)."""

    state: dict
    start: np.ndarray
    doubt: np.ndarray
    ambiguous: np.ndarray


def _stage_state(n, K, direct_ps, lsig, sss_ps, lalp, later_ps):
    """Slot state (n, K) of a start: a direct Gaussian (NaN = none) in slot 0, an sss (NaN =
    none) in slot 1, the Gaussians ``later_ps`` (n, G) after them, all with width exp(lsig)."""
    st = new_state(n, K)
    st["lsig"][:] = lsig[:, None]
    st["lalp"][:] = lalp[:, None]
    cols = [(direct_ps, FAM_GAUSS), (sss_ps, FAM_SSS)] + [(later_ps[:, j], FAM_GAUSS) for j in range(later_ps.shape[1])]
    slot = np.zeros(n, np.int64)
    rows = np.arange(n)
    for d, fam in cols:
        on = np.isfinite(d) & (slot < K)
        st["fam"][rows[on], slot[on]] = fam
        st["delay"][rows[on], slot[on]] = d[on]
        st["amp"][rows[on], slot[on]] = 1.0
        slot += on
    return st


def _same_start(built, direct_ps, sss_ps, later_ps):
    """(m,) int: for each pixel the first of the ``built`` starts (1-based; 0: none) whose direct
    delay, sss onset (m,) and later Gaussians (m, G) are the ones given (NaN matching NaN)."""
    same = np.zeros(direct_ps.size, np.int64)
    for j, (d, s, later) in enumerate(built, start=1):
        eq = (d == direct_ps) & (s == sss_ps) & np.all((later == later_ps) | (np.isnan(later) & np.isnan(later_ps)),
                                                       axis=1)
        same[(same == 0) & eq] = j
    return same


def _near_direct_chi2(t, residual, mask, st, s2):
    """(n,) the data term per sample, over the used samples within POOR_FIT_DIRECT_SIGMA widths
    (plus one bin) of each pixel's earliest Gaussian, in units of the noise variance ``s2``
    (n,); 0 for a pixel without a Gaussian.  ``residual`` (n, L): of the state ``st`` under the
    masks (:meth:`SampleMask.residual`).  A direct of the wrong width misfits there while
    the whole window's data term, over hundreds of quiet samples, stays near its expectation."""
    g = st["fam"] == FAM_GAUSS
    rows = np.arange(g.shape[0])
    k0 = np.argmin(np.where(g, st["delay"], np.inf), axis=1)
    has = g[rows, k0]
    d0 = np.where(has, st["delay"][rows, k0], np.nan)
    T = t[1] - t[0] if t.size > 1 else 1.0
    near = direct_samples(t, T, d0, np.exp(st["lsig"][rows, k0]), mask.used)
    r = np.where(near, residual, 0.0)
    return data_term(r, s2) / np.maximum(near.sum(axis=1), 1)


def _split(t, st, response=None):
    """Rendered split of a slot state: earliest Gaussian (direct), sss, later Gaussians
    (summed), each (n, L) (``response``: the atoms are a measured response's)."""
    g = st["fam"] == FAM_GAUSS
    d0 = np.argmin(np.where(g, st["delay"], np.inf), axis=1)
    first = np.zeros_like(g)
    first[np.arange(g.shape[0]), d0] = g[np.arange(g.shape[0]), d0]
    parts = []
    for keep in (first, st["fam"] == FAM_SSS, g & ~first):
        sub = dict(st)
        sub["fam"] = np.where(keep, st["fam"], FAM_NONE).astype(st["fam"].dtype)
        parts.append(render(t, sub, response))
    return parts


def weak_leading_gaussian(t_ps, st, response=None) -> np.ndarray:
    """(n,) bool: slot states whose earliest Gaussian is weak and just before a much larger
    onset -- the geometry :func:`decomposition.stages.quality.weak_direct` flags AMBIGUOUS in the
    output, read on a slot state labelled and rendered as the output is (``t_ps`` (L,) the
    sample times).  Such a Gaussian is often not the direct but a patch on its leading edge
    (4 ps bins, PSFs narrower than a bin: a Gaussian one bin before the true direct, at 10-15 %
    of its height, the direct labelled an inter-reflection).  ``response``: the atoms are a
    measured response's."""
    n, K = st["fam"].shape
    params, _ = classify(st, np.ones(n), max(K - 1, 0))      # every later Gaussian an inter-reflection
    T = float(t_ps[1] - t_ps[0]) if t_ps.size > 1 else 1.0
    return weak_direct(params, render_params(params, t_ps.size, T, float(t_ps[0]), irf=response), t_ps)


def _split_distance(a, b):
    """1 - fidelity of split ``a`` against split ``b`` (lists of (n, L) parts)."""
    num = sum(np.linalg.norm(x - y, axis=1) for x, y in zip(a, b))
    den = sum(np.linalg.norm(y, axis=1) for y in b)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, 0.0)


def _crossing(t, y, level, allowed):
    """First time (linearly interpolated) where ``y`` (n, L) reaches ``level`` (n,) among the
    ``allowed`` samples; the first allowed sample where none does."""
    up = (y >= level[:, None]) & allowed
    i = np.argmax(up, axis=1)
    rows = np.arange(y.shape[0])
    j = np.maximum(i - 1, 0)
    y0, y1 = y[rows, j], y[rows, i]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where((i > 0) & (y1 > y0), (level - y0) / (y1 - y0), 1.0)
    T = t[1] - t[0] if t.size > 1 else 1.0
    return t[j] + np.clip(frac, 0.0, 1.0) * T * (i > 0)


#: the measured noise below which :func:`_floor_hidden_misfit` stops reading a misfit larger,
#: as a fraction of the noise floor (a noiseless profile's second differences read ~0)
FLOOR_HIDDEN_MIN_FRACTION = 0.01


def _floor_hidden_misfit(chi2, s_eff, measured, noise_floor, limit):
    """(n,) bool: pixels whose noise ``s_eff`` (n,) is the floor ``noise_floor`` and not the
    data's, and whose data term ``chi2`` (n,), read in the ``measured`` noise (n,) instead (x
    (s_eff / measured)^2, the measured noise not below FLOOR_HIDDEN_MIN_FRACTION of the floor),
    exceeds ``limit`` (n,).

    The floor (``noise_floor`` x the peak) gives nearly noiseless data a finite detection limit;
    it also hides a wrong split that misfits the data several times their noise but far less
    than the floor's.
    """
    floored = (measured < noise_floor) & (s_eff <= noise_floor * (1.0 + 1e-9))
    seen = np.maximum(measured, FLOOR_HIDDEN_MIN_FRACTION * noise_floor)
    return floored & (chi2 * (s_eff / seen) ** 2 > limit)


def search_block(p, mask, st, s_eff, dic, opts, components, significance_sigma=None, bump_test: bool = True,
                 weights=None, objective_sigma=None, wide_start: bool = True, noise_spectrum=None,
                 weighted_doubt: bool = False, measured_noise=None):
    """The search on one block of pixels (normalised profiles ``p`` (n, L), their masks, the
    detected slot state ``st`` (n, K) and noise ``s_eff`` (n,); ``significance_sigma`` (n,), the
    noise of the in-window significance test (:meth:`Samples.significance_sigma`), default
    ``s_eff``; ``bump_test``: the forward step on the rise start tries significant residual
    bumps too (:func:`decomposition.stages.grow.grow_block`; False for count data); ``weights``
    (n, L): relative least-squares weights of the samples (:attr:`Detection.weights`): every
    data term below is then the sum of residual^2 / (s_eff^2 / weight), and every polish weighs
    the samples so); ``objective_sigma`` (n,): the noise at the components' scale
    (:func:`decomposition.stages.candidates.residual_significance_noise` of the detected fit); where it
    marks the noise as correlated (:func:`objective_variance`) the starts' objectives, and so the
    ambiguity test, read the data term in its variance instead of ``s_eff``'s; ``noise_spectrum``
    (:attr:`Detection.noise_spectrum`, the call's correlated noise): they whiten it by that
    spectrum instead (:class:`SpectralNoise`), and so does the whole-window doubt test below;
    ``wide_start``: try the ``wide`` start (False
    for count data, see below); ``weighted_doubt``: every pixel that ``weights`` weigh (noise
    that follows the signal) is in doubt (float data: there the tests below, read in the
    weighted data term, miss wrong splits whose misfit lies where the noise is largest);
    ``measured_noise`` (n,): the noise
    the data show before the floor (:attr:`Samples.noise`), read by the misfit test below where
    the floor, not the data, set ``s_eff``.

    A pixel is in doubt when it has an sss whose onset lies more than half a width before the
    earliest Gaussian or more than ``NEAR_SIGMA`` widths after it, an sss without a Gaussian,
    two or more Gaussians without an sss, a leading edge that rises faster than the start width
    (``SEARCH_DEFAULT_SIGMA_PS``) allows, a data term above ``search_doubt_chi2`` times its expected value, or a data
    term per sample above ``SEARCH_NEAR_DIRECT_CHI2`` (in noise variances) over the samples within
    POOR_FIT_DIRECT_SIGMA widths (plus one bin) of the earliest Gaussian (a direct of the
    wrong width: its misfit is diluted in the whole window's), or an earliest Gaussian that is
    weak and just before a much larger onset (:func:`weak_leading_gaussian`).  Only
    those pixels get the starts of :data:`STAGE_STARTS` (``edge``: a direct one width after the
    leading edge and an sss ``SEARCH_EDGE_GAP_SIGMA`` widths after it; ``peak``: the earliest significant peak as the
    direct, the sss one width later; both with the detected Gaussians more than
    ``SEARCH_IR_GAP_SIGMA`` widths after the new direct; ``peak bare``: without them; ``rise``:
    the peak start at the grid's narrowest width, at least ``SEARCH_RISE_MIN_BINS`` bins (the sss one such width after the direct,
    later Gaussians more than SEARCH_IR_GAP_SIGMA such widths after it), followed by the
    forward step of :func:`decomposition.stages.grow.grow_block` where ``opts.grow``; ``wide``: the
    peak start at the detected direct's width where that exceeds ``SEARCH_WIDE_FACTOR`` times
    the default (the sss ``SEARCH_EDGE_GAP_SIGMA`` such widths after the direct, later
    Gaussians more than SEARCH_IR_GAP_SIGMA such widths after it), elsewhere the peak start; amplitudes by NNLS, then the solver's
    polish: shared width, sss onset at or after the direct, data term only; thresholded,
    merged and relabelled as :mod:`decomposition.stages.label` will), scored by
    ``chi2 + search_penalty * k * ln(n_fit)``; the lowest is kept (ties keep the solver's).
    Where even the lowest leaves a data term above ``search_doubt_chi2`` times its expected
    value, the starts of :data:`MISFIT_GROWN_STARTS` get the forward step too, and are scored
    again, before the choice (where ``opts.grow``); where ``opts.noise_floor`` set ``s_eff``
    above ``measured_noise``, that data term is read in the measured noise
    (:func:`_floor_hidden_misfit`).

    -> (state, start (n,) int, doubt (n,) bool, ambiguous (n,) bool).
    """
    n, L = p.shape
    K = st["fam"].shape[1]
    T = dic.time_bin_ps
    t = dic.t0_ps + T * np.arange(L)
    out = {k: v.copy() for k, v in st.items()}
    start = np.zeros(n, np.int64)
    ambiguous = np.zeros(n, bool)
    if n == 0 or not ("d" in components and "s" in components):
        return out, start, np.zeros(n, bool), ambiguous
    s2 = objective_variance(np.maximum(s_eff, 1e-300), None, weights)
    nfit = np.maximum(mask.used.sum(axis=1), 1)
    log_l = log_samples(nfit)

    base = {k: v.copy() for k, v in st.items()}
    s_sig = s_eff if significance_sigma is None else significance_sigma
    comp.threshold(base, t, opts.rel_threshold, s_sig, opts.significance_chi2, weights, irf=dic.response)
    r0 = mask.residual(p, render(t, base, dic.response))
    # read in the call's correlated noise where it has one, as the objectives below (pink: in
    # sample variances nearly every pixel's data term is above its expectation, and in doubt)
    chi0 = data_term(r0, s2 if noise_spectrum is None
                       else objective_variance(np.maximum(s_eff, 1e-300), spectrum=noise_spectrum))

    # Pixels in doubt (see the docstring).

    g = base["fam"] == FAM_GAUSS
    s_at = base["fam"] == FAM_SSS
    has_s = s_at.any(axis=1)
    d0 = np.where(g, base["delay"], np.inf).min(axis=1)
    s_on = np.where(has_s, np.where(s_at, base["delay"], -np.inf).max(axis=1), np.nan)
    # Every start begins at the default width, not at the solver's: from a narrow start the
    # polish grows the width to the data's, while the solver's widths on a pixel in doubt are
    # often an sss hump's (too wide) and trap it.  Paper scenes, 300 px, 2 ps bins, white
    # noise, mean fidelity at NSR 0.001 / 0.055 / 0.11: default width 0.904 / 0.861 / 0.850;
    # the largest atom width 0.885 / 0.820 / 0.798; the narrowest Gaussian's 0.888 / 0.828 /
    # 0.809; the width from the leading edge's rise 0.895 / 0.854 / 0.835.
    lsig = np.full(n, np.log(SEARCH_DEFAULT_SIGMA_PS))
    sig = np.exp(lsig)
    lalp = np.where(has_s, np.where(s_at, base["lalp"], -np.inf).max(axis=1),
                    np.log(SEARCH_DEFAULT_ALPHA_PER_PS))
    # PSF width from the rise of the earliest significant peak (10 % to 50 % of its height
    # takes 0.97 sigma for a Gaussian), from a profile smoothed by one bin only
    y1 = _smooth(p, np.ones(n))
    i_pk = _first_peak(y1, SEARCH_PEAK_LEVEL)
    h_pk = y1[np.arange(n), i_pk]
    before = np.arange(L)[None, :] <= i_pk[:, None]
    t10 = _crossing(t, y1, 0.1 * h_pk, before)
    t50 = _crossing(t, y1, 0.5 * h_pk, before)
    sig_edge = np.clip((t50 - t10) / RISE_10_50_SIGMA, dic.grid.sigma_range_ps[0], dic.grid.sigma_range_ps[1])
    narrow_all = sig_edge < NARROW_FRACTION * sig
    with np.errstate(invalid="ignore"):
        doubt = narrow_all | (~has_s & (g.sum(axis=1) >= 2))
        doubt |= has_s & (~g.any(axis=1) | (s_on < d0 - 0.5 * sig) | (s_on > d0 + NEAR_SIGMA * sig))
        doubt |= chi0 > opts.search_doubt_chi2 * nfit
        doubt |= _near_direct_chi2(t, r0, mask, base, s2) > SEARCH_NEAR_DIRECT_CHI2
    # an earliest Gaussian weak and just before a much larger onset (the output's AMBIGUOUS
    # rule; measured: docs/history.md)
    rest = np.nonzero(~doubt)[0]
    if rest.size:
        doubt[rest] |= weak_leading_gaussian(t, take(base, rest), dic.response)
    if weighted_doubt and weights is not None:
        doubt |= (weights != 1).any(axis=1)
    idx = np.nonzero(doubt)[0]
    if idx.size == 0:
        return out, start, doubt, ambiguous

    # Starts for the pixels in doubt.
    pb, mb = p[idx], mask[idx]
    sg, ls, la = sig[idx], lsig[idx], lalp[idx]
    ys = _smooth(pb, np.maximum(sg / T, 0.5))
    top = ys.max(axis=1, keepdims=True)
    t_edge = t[np.argmax(ys >= SEARCH_EDGE_LEVEL * top, axis=1)]
    t_peak = t[_first_peak(ys, SEARCH_PEAK_LEVEL)]
    gd = np.where(g[idx], base["delay"][idx], np.nan)
    allow_later = "r" in components
    noise_b = np.maximum(s_eff[idx], 1e-300)
    wb = None if weights is None else weights[idx]

    def refined(state, rows=slice(None)):                  # scored as it will be labelled
        return polish_candidate(t, pb[rows], mb[rows], state, noise_b[rows], dic, opts, s_sig[idx][rows],
                                None if wb is None else wb[rows])

    # the solver's own answer, its sss onset not before its direct (as labelled), re-polished
    cand = [take(base, idx)]
    if opts.sss_after_direct:
        moved = comp.clip_sss_onset(cand[0])
        if moved.any():
            m = np.nonzero(moved)[0]
            put(cand[0], m, refined(take(cand[0], m), m))
    # ("edge bare" and a start at the rise's narrower width never won on the paper's scenes
    # at 2 ps bins: a pixel whose rise is too steep is in doubt, and the peak start takes it;
    # at 4 ps the rise reads too wide, hence the ``rise`` start at the grid's narrowest width)
    specs = (("edge", t_edge + sg, t_edge + (1.0 + SEARCH_EDGE_GAP_SIGMA) * sg, True), ("peak", t_peak, t_peak + sg, True),
             ("peak bare", t_peak, t_peak + sg, False))
    built = []                  # (direct, sss onset, later Gaussians) of the starts so far
    # ``rise``: a direct at the earliest significant peak at the grid's narrowest width (not
    # below SEARCH_RISE_MIN_BINS bins: point samples do not see a narrower width), the
    # sss onset one such width after it, the detected Gaussians more than SEARCH_IR_GAP_SIGMA
    # of those widths later -- the split of a direct narrower than the detection's width,
    # whose wide direct swallowed the sss rise (and often an inter-reflection, hence the
    # forward step on this start below)
    narrow = np.full(idx.size, max(float(dic.grid.sigma_range_ps[0]), SEARCH_RISE_MIN_BINS * T))
    specs = specs + (("rise", t_peak, t_peak + narrow, True),)
    widths = {"rise": narrow}
    # ``wide``: the peak start at the detected direct's own width where that is more than
    # SEARCH_WIDE_FACTOR times the default (a wide direct whose small sss every start at the
    # default width lost to Gaussians); elsewhere the peak start itself, polished once
    k_d = np.argmin(np.where(g[idx], base["delay"][idx], np.inf), axis=1)
    w_det = np.clip(np.exp(base["lsig"][idx][np.arange(idx.size), k_d]), *dic.grid.sigma_range_ps)
    # (not for count data: with a tailed response it added false echoes on d+s scenes)
    wide = (w_det > SEARCH_WIDE_FACTOR * sg) & bool(wide_start)
    widths["wide"] = np.where(wide, w_det, sg)
    specs = specs + (("wide", t_peak, np.where(wide, t_peak + SEARCH_EDGE_GAP_SIGMA * w_det, t_peak + sg), True),)
    for name, d_ps, s_ps, keep in specs:
        w_ps = widths.get(name, sg)
        ls = np.log(w_ps)
        later = np.where(keep & allow_later & (gd > d_ps[:, None] + SEARCH_IR_GAP_SIGMA * w_ps[:, None]), gd, np.nan)
        later = np.sort(later, axis=1)[:, :max(K - 2, 0)]
        # a start identical to an earlier one (``peak bare`` where the peak start has no later
        # Gaussians) has that start's result: polished once
        same = _same_start(built, d_ps, s_ps, later)
        built.append((d_ps, s_ps, later))
        if not same.any():
            cand.append(refined(_stage_state(idx.size, K, d_ps, ls, s_ps, la, later)))
            continue
        c = new_state(idx.size, K)
        for j in range(1, len(cand)):
            rows = np.nonzero(same == j)[0]
            if rows.size:
                put(c, rows, take(cand[j], rows))
        new = np.nonzero(same == 0)[0]
        if new.size:
            put(c, new, refined(_stage_state(new.size, K, d_ps[new], ls[new], s_ps[new], la[new], later[new]), new))
        cand.append(c)
    if allow_later and opts.grow:
        # the forward step of decomposition.stages.grow on the rise start: an inter-reflection the
        # wide direct had absorbed is no detected Gaussian, and without it the narrow split
        # loses to the wide one it would beat
        i_rise = 1 + [spec[0] for spec in specs].index("rise")
        cand[i_rise], _ = grow_block(pb, mb, cand[i_rise], noise_b, dic, opts, s_sig[idx], bump_test, weights=wb,
                                     spectrum=noise_spectrum)
    js = []
    sj2 = objective_variance(noise_b, None if objective_sigma is None else objective_sigma[idx], wb, noise_spectrum)
    for c in cand:
        js.append(penalised_objective(t, pb, mb, c, sj2, log_l[idx], opts, dic.response))
    js = np.stack(js)                                   # (starts, m)
    if allow_later and opts.grow:
        # where even the best start still misfits (its data term above search_doubt_chi2 times
        # its expected value), the forward step on the starts of MISFIT_GROWN_STARTS too: their
        # later Gaussians are the detection's, and an inter-reflection the detection missed
        # (absorbed by a wide direct or by an sss hump) is none of them; without it the right
        # split loses to a wrong one that spreads over the missing echo
        widths = "shared" if opts.shared_sigma else "per_atom"
        chi = js - np.stack([penalty(free_parameters(c["fam"], widths), log_l[idx], opts.search_penalty) for c in cand])
        chi_best = chi[np.argmin(js, axis=0), np.arange(idx.size)]
        misfit = chi_best > opts.search_doubt_chi2 * nfit[idx]
        if measured_noise is not None:
            misfit |= _floor_hidden_misfit(chi_best, noise_b, measured_noise[idx], opts.noise_floor,
                                           opts.search_doubt_chi2 * nfit[idx])
        names = [spec[0] for spec in specs]
        for name in MISFIT_GROWN_STARTS:
            i = 1 + names.index(name)
            rows = np.nonzero(misfit & wide if name == "wide" else misfit)[0]   # (else the peak start)
            if rows.size == 0:
                continue
            grown, _ = grow_block(pb[rows], mb[rows], take(cand[i], rows), noise_b[rows], dic, opts, s_sig[idx][rows],
                                  bump_test, weights=None if wb is None else wb[rows], spectrum=noise_spectrum)
            put(cand[i], rows, grown)
            s2_rows = objective_variance(noise_b[rows], None if objective_sigma is None else objective_sigma[idx][rows],
                                         None if wb is None else wb[rows], noise_spectrum)
            js[i, rows] = penalised_objective(t, pb[rows], mb[rows], grown, s2_rows, log_l[idx][rows], opts,
                                              dic.response)
    if not opts.sss_alone:
        # the paper's model gives every pixel a direct: a start that lost it competes only
        # where every start did
        has_d = np.stack([(c["fam"] == FAM_GAUSS).any(axis=1) for c in cand])
        js_pick = np.where(has_d | ~has_d.any(axis=0), js, np.inf)
    else:
        js_pick = js
    best = np.argmin(js_pick, axis=0)
    # ties keep the solver's answer
    best = np.where(js_pick[0] <= js_pick[best, np.arange(idx.size)], 0, best)
    chosen = take(cand[0], np.arange(idx.size))
    for k in range(1, len(cand)):
        rows = np.nonzero(best == k)[0]
        if rows.size:
            put(chosen, rows, take(cand[k], rows))
    put(out, idx, chosen)
    start[idx] = best

    # Ambiguity: another start whose objective (chi2 + k ln n: a BIC, with search_penalty 1) is
    # within ambiguity_chi2 of the best one's, and whose split differs from the best's by more
    # than ambiguity_split (1 - fidelity between the two).  Both objectives are read on the same
    # data, so the noise they share cancels in their difference: what is left is the evidence
    # for one over the other, read on Kass and Raftery's scale (J. Am. Stat. Assoc. 90, 773
    # (1995): a difference in BIC above 10 is "very strong").
    j_best = js[best, np.arange(idx.size)]
    split_best = _split(t, chosen, dic.response)
    amb = np.zeros(idx.size, bool)
    tol = ambiguity_tolerance("evidence", opts)
    for k, c in enumerate(cand):
        amb |= is_ambiguous(js[k] - j_best, tol,
                            lambda r, c=c: _split_distance(_split(t, take(c, r), dic.response),
                                                           [x[r] for x in split_best]),
                            opts.ambiguity_split, where=best != k)
    if not opts.sss_alone:
        amb |= ~(chosen["fam"] == FAM_GAUSS).any(axis=1) & (chosen["fam"] == FAM_SSS).any(axis=1)
    ambiguous[idx] = amb
    return out, start, doubt, ambiguous


def search_components(samples, det, dic, opts, components, objective_lagged_noise=None) -> SearchStage:
    """The ``search`` stage of :func:`decomposition.decompose`: structured alternative starts for the
    detected pixels in doubt, block by block (``opts.block_size``); see :func:`search_block`
    (``objective_lagged_noise`` (P,): the lagged noise of its ``objective_sigma``, in place of
    ``samples.lagged_noise``)."""
    live = samples.live
    state = {k: v.copy() for k, v in det.state.items()}
    n = live.size
    start = np.zeros(n, np.int64)
    doubt = np.zeros(n, bool)
    amb = np.zeros(n, bool)
    float_data = samples.noise_model != "poisson"      # the bump test, the wide start and the weighted doubt
    for b0 in range(0, n, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, n))
        px = live[rows]
        p, mask = solver_inputs(samples, px)
        sub = {k: v[rows] for k, v in state.items()}
        noise = det.noise_eff[px]
        objective_sigma = (None if objective_lagged_noise is None
                           else samples.significance_sigma(px, noise, objective_lagged_noise))
        st, start[rows], doubt[rows], amb[rows] = search_block(
            p, mask, sub, noise, dic, opts, components, samples.significance_sigma(px, noise), bump_test=float_data,
            weights=None if det.weights is None else det.weights[rows], objective_sigma=objective_sigma,
            wide_start=float_data, noise_spectrum=det.noise_spectrum, weighted_doubt=float_data,
            measured_noise=samples.noise[px])
        put(state, rows, st)
    return SearchStage(state=state, start=start, doubt=doubt, ambiguous=amb)
