"""Structured alternative starts for a decomposition (a prototype, not used by ``decompose``).

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
:func:`decomposition.refine.refine` (one PSF width per pixel, sss onset at or after the
direct, inter-reflections in order), scored by a penalised objective

    J = RSS / s^2 + penalty * k * ln(L),

s the pixel's noise estimated from first differences, k the number of free parameters and L
the number of bins (the Bayesian information criterion for ``penalty = 1``), and the lowest J
is kept.  All work is on blocks of pixels: one refine call per kind of start.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.model import IR_KEYS, SSS_KEYS, render_profile, time_axis_ps
from .refine import refine

__all__ = ["SearchOptions", "relabel", "structured_search"]

STARTS = ("solver", "edge", "edge2", "peak", "edge bare", "peak bare")


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
    ir_gap_sigma: float = 3.0
    edge_level: float = 0.1
    peak_level: float = 0.2
    default_sigma_ps: float = 3.0
    default_alpha_per_ps: float = 0.03
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


def _smooth(y, width_bins):
    """Gaussian smoothing along the last axis with a per-pixel width (bins), via FFT."""
    n = y.shape[-1]
    f = np.fft.rfftfreq(2 * n)
    h = np.exp(-2.0 * (np.pi * f[None, :] * width_bins[:, None]) ** 2)
    pad = np.concatenate([y, np.zeros_like(y)], axis=-1)
    return np.fft.irfft(np.fft.rfft(pad, axis=-1) * h, n=2 * n, axis=-1)[:, :n]


def _noise_sigma(y):
    """Per-pixel white-noise level from the median absolute first difference."""
    d = np.diff(y, axis=-1)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=-1, keepdims=True)), axis=-1) / np.sqrt(2.0)


def _n_params(params):
    has_d = np.isfinite(params["direct_delay_ps"])
    has_s = np.isfinite(params["sss_delay_ps"])
    n_ir = np.isfinite(params["ir_delay_ps"]).sum(axis=1)
    # delays and amplitudes; one shared sigma; alpha for the sss.
    return 2 * has_d + 3 * has_s + 2 * n_ir + 1


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
    is_peak = np.zeros_like(ys, dtype=bool)
    is_peak[:, 1:-1] = (ys[:, 1:-1] >= ys[:, :-2]) & (ys[:, 1:-1] > ys[:, 2:]) & (ys[:, 1:-1] >= opt.peak_level * top)
    has_peak = is_peak.any(axis=1)
    t_peak = np.where(has_peak, t[np.argmax(is_peak, axis=1)], t[np.argmax(ys, axis=1)])

    starts = {"solver": relabel(params, n_ir)}
    for name, d_delay, s_delay, keep in (("edge", t_edge + sigma, t_edge + sigma, True),
                                         ("edge2", t_edge + 2 * sigma, t_edge + 2 * sigma, True),
                                         ("peak", t_peak, t_peak + sigma, True),
                                         ("edge bare", t_edge + sigma, t_edge + sigma, False),
                                         ("peak bare", t_peak, t_peak + sigma, False)):
        later = keep & (gd > d_delay[:, None] + opt.ir_gap_sigma * sigma[:, None])
        starts[name] = _assemble(d_delay, sigma, s_delay, alpha, np.where(later, gd, np.nan),
                                 np.where(later, ga, np.nan), n_ir)

    s2 = np.maximum(_noise_sigma(y), 1e-12 * np.abs(y).max(axis=1)) ** 2
    best, best_j, j_solver, which = None, None, None, np.zeros(n, np.int64)
    for k, name in enumerate(STARTS):
        start = starts[name]
        fit, _ = refine(y, start, time_bin_ps=T, t0_ps=t0_ps, max_iter=int(opt.max_iter), shared_sigma=True,
                        sss_after_direct=True, keep_order=True)
        rss = np.sum((y - render_profile(fit, n_bins, T, t0_ps)) ** 2, axis=1)
        j = rss / s2 + opt.penalty * _n_params(fit) * np.log(n_bins)
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
