"""Parameters every pixel of an image shares, estimated once from all of them.

One instrument lies behind every pixel of a cube: one PSF width (or a width that varies
slowly across a streak camera's slit), and in a microscope one onset.  A material has one
sss decay rate.  A single pixel at a hundred photons cannot pin these down; pooled over the
image they are known well, and each pixel's fit is better with them held.

The estimate (:func:`estimate_shared`):

1. *Which pixels.*  Each pixel's lit score is its profile's peak above its median
   (:func:`lit_score`); of the pixels with a positive score, in every region, the brighter
   half, thinned evenly in raster order to at most ``n_pixels`` (:func:`select_pixels`): a
   deterministic subsample spread over the image.
2. *Per-pixel estimates.*  Those pixels are decomposed freely with standard errors: their
   widths and onsets.
3. *Pooled and robust* (:func:`pooled`): outliers beyond five scaled MADs of the median are
   dropped; the rest are averaged with weights 1 / (se^2 + tau^2), tau^2 the scatter beyond
   the per-pixel errors (so bright pixels' small errors do not decide alone); the standard
   error is the weighted mean's, inflated by the Birge ratio where the points scatter more
   than their errors say; widths and rates in their logarithm (:func:`pooled_positive`).
   With ``psf_map`` a quadratic surface in (y, x) is fitted the same way (:func:`fit_surface`).
4. *Pooled likelihood* for a scalar width and onset: the pixels decomposed again with the
   pooled starts held, their summed misfit (Poisson deviance or chi^2) is minimised over the
   shared values, each pixel's other parameters refitted, the errors from its curvature
   (:func:`_profile_refine`); per-pixel widths are biased where one pixel cannot tell a width
   from an onset or a decay.
5. The decay rates, pooled per region from a pass with the width and onset held.

The result, a :class:`SharedEstimate`, is a record of plain numbers (``record()``, written to
``info["shared"]`` and a result store's ``shared`` attribute, read back with
:meth:`SharedEstimate.from_record`) and gives every pixel its held values (:meth:`hold`,
the ``hold=`` of :func:`decomposition.decompose`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from core.model import render_profile
from ..api import decompose
from ..model.refine import hold_params, refine
from ..model.slots import select_rows
from ..noise import count_deviance, poisson_weights
from ..options import OptionError, parse_components
from ..model.atoms import slot_atoms
from ..response.label import param_slots
from ..response.refine import CountData, fit_slots, held_slot_masks
from ..response.resolve import resolve_response, stretched_response
from .pooling import (SURFACE_TERMS, excess_spread, fit_surface, lit_score, pooled, pooled_positive, select_pixels,
                      surface_design)

__all__ = ["SharedEstimate", "NotOneInstrument", "ONE_INSTRUMENT_SPREAD", "estimate_shared", "decompose_held", "held_response", "apply_held_stderr", "image_estimate",
           "N_LIKELIHOOD_PIXELS"]

#: at most this many of them (thinned evenly) in the pooled likelihood of the scalar width and onset
N_LIKELIHOOD_PIXELS = 128
#: the key of a measured response's shared time scale in :meth:`SharedEstimate.hold`'s values
#: (not a parameter of a pixel: :func:`decompose_held` decomposes with the stretched response)
STRETCH_KEY = "response_stretch"
@dataclass(frozen=True)
class SharedEstimate:
    """The shared parameters of one image, with their standard errors (plain numbers).

    ``psf_sigma_ps`` (ps): the PSF width (with a map, its value at the image centre);
    ``psf_map``: None or {"terms", "coefficients_ps", "covariance_ps2", "center_yx",
    "scale_yx"} (:func:`fit_surface`); ``delay_key``: the onset held ("direct_delay_ps"
    with the direct family, else "sss_delay_ps"), ``delay_ps`` its value;
    ``sss_alpha_per_ps``: {region label: decay rate, 1/ps} (label 0 without regions).
    With a measured response (``irf=``) "psf" is the response's time scale instead:
    ``response_stretch`` s, the response r(t / s) / s held in every pixel
    (:func:`decomposition.response.resolve.stretched_response`), no ``psf_sigma_ps``.
    Each value has its ``*_stderr``; ``pixels`` how many pixels each pooled; ``psf_spread`` how far
    the pixels' own widths scatter beyond their errors (relative, :func:`decomposition.image.pooling.excess_spread`).
    """

    names: tuple
    shape: tuple
    psf_sigma_ps: float | None = None
    psf_sigma_ps_stderr: float | None = None
    psf_map: dict | None = None
    delay_key: str | None = None
    delay_ps: float | None = None
    delay_ps_stderr: float | None = None
    sss_alpha_per_ps: dict = field(default_factory=dict)
    sss_alpha_per_ps_stderr: dict = field(default_factory=dict)
    regions: bool = False
    pixels: dict = field(default_factory=dict)
    response_stretch: float | None = None
    response_stretch_stderr: float | None = None
    psf_spread: float | None = None

    def record(self) -> dict:
        """A JSON-able dict (units in the names; region labels as strings) for ``info`` and a store."""
        rec = {"names": list(self.names), "shape": [int(s) for s in self.shape], "pixels": dict(self.pixels)}
        if "psf" in self.names and self.response_stretch is not None:
            rec.update(response_stretch=self.response_stretch, response_stretch_stderr=self.response_stretch_stderr)
        elif "psf" in self.names:
            rec.update(psf_sigma_ps=self.psf_sigma_ps, psf_sigma_ps_stderr=self.psf_sigma_ps_stderr,
                       psf_map=self.psf_map)
            if self.psf_spread is not None:
                rec["psf_spread"] = self.psf_spread
        if "delay" in self.names:
            rec.update(delay_key=self.delay_key, delay_ps=self.delay_ps, delay_ps_stderr=self.delay_ps_stderr)
        if "alpha" in self.names:
            rec.update(regions=self.regions,
                       sss_alpha_per_ps={str(k): v for k, v in self.sss_alpha_per_ps.items()},
                       sss_alpha_per_ps_stderr={str(k): v for k, v in self.sss_alpha_per_ps_stderr.items()})
        return rec

    @classmethod
    def from_record(cls, rec: dict) -> "SharedEstimate":
        """The estimate :meth:`record` wrote (identical values: JSON keeps every float exactly)."""
        alpha = {int(k): float(v) for k, v in rec.get("sss_alpha_per_ps", {}).items()}
        alpha_se = {int(k): float(v) for k, v in rec.get("sss_alpha_per_ps_stderr", {}).items()}
        return cls(names=tuple(rec["names"]), shape=tuple(rec["shape"]), psf_sigma_ps=rec.get("psf_sigma_ps"),
                   psf_sigma_ps_stderr=rec.get("psf_sigma_ps_stderr"), psf_map=rec.get("psf_map"),
                   delay_key=rec.get("delay_key"), delay_ps=rec.get("delay_ps"),
                   delay_ps_stderr=rec.get("delay_ps_stderr"), sss_alpha_per_ps=alpha,
                   sss_alpha_per_ps_stderr=alpha_se, regions=bool(rec.get("regions", False)),
                   pixels=dict(rec.get("pixels", {})), response_stretch=rec.get("response_stretch"),
                   response_stretch_stderr=rec.get("response_stretch_stderr"), psf_spread=rec.get("psf_spread"))

    def _psf_at(self, yy, xx):
        m = self.psf_map
        a = surface_design(yy, xx, m["center_yx"], m["scale_yx"])
        cov = np.asarray(m["covariance_ps2"])
        return a @ np.asarray(m["coefficients_ps"]), np.sqrt(np.einsum("...i,ij,...j->...", a, cov, a))

    def hold(self, regions=None, window=None) -> tuple[dict, dict]:
        """Every pixel's held values and their standard errors -> (hold, stderr), each
        {key of :data:`decomposition.model.refine.HOLD_KEYS`: (y, x) array}; a response's
        stretch under :data:`STRETCH_KEY` (one value, for :func:`decompose_held`).

        ``window`` ((y0, y1), (x0, x1)): only that part of the image (a chunk), default all of
        it; ``regions`` the labels of those pixels (the window's shape), or None.  Pixels whose label has no decay rate
        (negative labels) hold none (NaN).
        """
        Y, X = self.shape
        (y0, y1), (x0, x1) = window if window is not None else ((0, Y), (0, X))
        yy, xx = np.meshgrid(np.arange(y0, y1), np.arange(x0, x1), indexing="ij")
        shape = yy.shape
        hold, err = {}, {}
        if "psf" in self.names and self.response_stretch is not None:
            hold[STRETCH_KEY] = np.full(shape, self.response_stretch)
            err[STRETCH_KEY] = np.full(shape, self.response_stretch_stderr)
        elif "psf" in self.names:
            if self.psf_map is not None:
                hold["sigma_ps"], err["sigma_ps"] = self._psf_at(yy, xx)
            else:
                hold["sigma_ps"] = np.full(shape, self.psf_sigma_ps)
                err["sigma_ps"] = np.full(shape, self.psf_sigma_ps_stderr)
        if "delay" in self.names:
            hold[self.delay_key] = np.full(shape, self.delay_ps)
            err[self.delay_key] = np.full(shape, self.delay_ps_stderr)
        if "alpha" in self.names:
            labels = (np.zeros(shape, np.int64) if regions is None
                      else np.asarray(regions).astype(np.int64))
            value = np.full(shape, np.nan)
            se = np.full(shape, np.nan)
            for label, v in self.sss_alpha_per_ps.items():
                value[labels == label] = v
                se[labels == label] = self.sss_alpha_per_ps_stderr[label]
            hold["sss_alpha_per_ps"], err["sss_alpha_per_ps"] = value, se
        return hold, err


def _check_width_surface(coef, center, scale, shape) -> None:
    """Refuse a PSF width surface that is not a width everywhere on the image: one that falls to
    zero or below at some pixel (noisy widths on a small image, where the quadratic terms
    swing) would be held there and refused by every pixel's fit."""
    yy, xx = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    surface = surface_design(yy, xx, center, scale) @ np.asarray(coef, np.float64)
    if not np.all(np.isfinite(surface) & (surface > 0)):
        at = np.unravel_index(int(np.argmin(np.where(np.isfinite(surface), surface, -np.inf))), surface.shape)
        raise ValueError(f"psf_map: the PSF width surface fitted to the pixels' widths falls to "
                         f"{float(surface[at]):.3g} ps at pixel (y={at[0]}, x={at[1]}) of the {shape[0]} x {shape[1]} "
                         f"image: their widths do not determine a map; share one width (psf without psf_map)")


def image_estimate(cube, regions, time_bin_ps: float, method: str, names: tuple, *, psf_map: bool = False,
                   keywords: dict, score=None, gather=None, one_instrument: bool = False) -> SharedEstimate:
    """The shared parameters of an image ``cube`` (Y, X, L): :func:`select_pixels` on
    :func:`lit_score`, then :func:`estimate_shared`.  ``regions`` (Y, X) int labels or None.

    ``score`` (Y, X), the lit scores where the caller computed them already (a chunked cube),
    and ``gather(flat indices) -> (n, L)``, the selected profiles (default: read from ``cube``);
    ``one_instrument``: :func:`estimate_shared`'s.
    """
    Y, X = (int(s) for s in cube.shape[:2])
    labels = np.zeros((Y, X), np.int64) if regions is None else np.asarray(regions).astype(np.int64)
    score = lit_score(cube) if score is None else score
    idx = select_pixels(score, labels)
    if gather is None:
        profiles = np.asarray(cube).reshape(Y * X, -1)[idx]
    else:
        profiles = np.asarray(gather(idx))
    yx = np.stack(np.unravel_index(idx, (Y, X)), axis=1)
    return estimate_shared(profiles, yx, labels.reshape(-1)[idx], (Y, X), time_bin_ps, method, names,
                           psf_map=psf_map, regions=regions is not None, keywords=keywords,
                           one_instrument=one_instrument)


#: one instrument: the lit pixels' own widths scatter beyond their errors by at most this much
#: (relative; :func:`decomposition.image.pooling.excess_spread`).  Measured: 0.012 on the demo's
#: captured cube (one streak camera), 0 at white NSR 0.11-0.22 and 0.16 at 100 photons on bench
#: spatial's scenes (one PSF; errors at 100 photons fall short), 0.42 on the demo's simulated cube
#: (each pixel draws its own width).
ONE_INSTRUMENT_SPREAD = 0.25


class NotOneInstrument(ValueError):
    """The pixels' own widths are not one instrument's (:data:`ONE_INSTRUMENT_SPREAD`)."""


#: iteratively reweighted refits of count data per evaluation of the pooled likelihood
_COUNT_REFITS = 3
#: refinement iterations per pixel and evaluation of the pooled likelihood with a measured response
_RESPONSE_MISFIT_ITER = 50


def _pooled_misfit(profiles, params, hold, *, counts: bool, noise, time_bin_ps, t0_ps, shared_sigma):
    """The summed misfit (-2 log-likelihood up to a constant: Poisson deviance, or chi^2 in the
    pixels' noise) of ``profiles`` (n, L) refitted from ``params`` with ``hold``; the component
    set is kept."""
    bg = "background" in params
    n_bins = profiles.shape[-1]
    fit = np.ones(profiles.shape, bool)

    def misfits(p):
        model = np.nan_to_num(render_profile(p, n_bins, time_bin_ps, t0_ps))
        if counts:
            return count_deviance(profiles, model, fit).reshape(profiles.shape[0], -1).sum(axis=1), model
        return ((profiles - model) ** 2 / noise[:, None] ** 2).sum(axis=1), model

    cur = hold_params(params, hold, (profiles.shape[0],))
    best, model = misfits(cur)
    for _ in range(_COUNT_REFITS if counts else 1):
        weights = poisson_weights(model, fit) if counts else None
        new, _ = refine(profiles, cur, time_bin_ps=time_bin_ps, t0_ps=t0_ps, weights=weights, hold=hold,
                        shared_sigma=shared_sigma, sss_after_direct=True, fit_background=bg)
        # never worse, row by row, as the refit stage keeps its count refits: reweighted least
        # squares with 1 / model weights can step a pixel into a far worse deviance
        new_misfit, new_model = misfits(new)
        better = new_misfit < best
        cur = select_rows(better, new, cur)
        best = np.where(better, new_misfit, best)
        model = np.where(better[:, None], new_model, model)
    return float(best.sum())


def _pooled_misfit_response(profiles, params, hold, *, counts: bool, noise, time_bin_ps, t0_ps, irf, **_):
    """:func:`_pooled_misfit` with a measured response ``irf`` (resolved on ``time_bin_ps``): each
    pixel's slots (:func:`decomposition.response.label.param_slots`) refitted over the
    response's atoms with the held onsets / decay rate (:func:`decomposition.response.refine.fit_slots`,
    the same start at every evaluation; count data by Fisher scoring on their deviance)."""
    hold = dict(hold)
    if STRETCH_KEY in hold:
        irf = stretched_response(irf, hold.pop(STRETCH_KEY))
    n, n_bins = profiles.shape
    t = t0_ps + time_bin_ps * np.arange(n_bins)
    n_ir = np.shape(params["ir_delay_ps"])[-1] if "ir_delay_ps" in params else 0
    fam, delay, lalp = param_slots(params, n_ir)
    delay, lalp, h_d, h_l = held_slot_masks(hold, fam, delay, lalp)
    scale = np.maximum(np.abs(profiles).max(axis=1), 1e-300)
    y = profiles / scale[:, None]
    fit = np.ones(profiles.shape, bool)
    bg = np.ones(n, bool) if "background" in params else None
    span = n_bins * time_bin_ps
    kw = dict(n_iter=_RESPONSE_MISFIT_ITER, lm_tol=1e-6, delay_bounds_ps=(t[0] - span, t[-1] + span),
              lalp_bounds=(math.log(1e-5), math.log(10.0)), sss_after_direct=True, first_is_direct=True,
              fit_background=bg, held_delay=h_d, held_lalp=h_l)
    if counts:
        cd = CountData(profiles, scale, np.zeros(n), fit, None)
        start = fit_slots(irf, t, y, fit.astype(np.float64), fam, delay, lalp, n_iter=0, **{
            k: v for k, v in kw.items() if k != "n_iter"})
        # the first weights: those of the start's model (amplitudes solved at the held values)
        model = np.einsum("pk,pkl->pl", start.amp, slot_atoms(irf, t, fam, delay, lalp)) + start.background[:, None]
        sw = cd.weights(np.maximum(model, 0.0) * scale[:, None])
        return float(fit_slots(irf, t, y, sw, fam, delay, lalp, counts=cd, **kw).cost.sum())
    f = fit_slots(irf, t, y, fit.astype(np.float64), fam, delay, lalp, **kw)
    return float((f.cost * scale ** 2 / np.asarray(noise, np.float64) ** 2).sum())


def _minimise_1d(f, lo, hi, step):
    """Minimum of ``f`` over [lo, hi] (bounded Brent, to a quarter of ``step``) -> (argmin,
    curvature f'' there from the points ``step`` either side; nan where it does not open upwards)."""
    found = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 0.25 * step})
    x, f0 = float(found.x), float(found.fun)
    curv = (f(x + step) - 2.0 * f0 + f(x - step)) / step ** 2
    return x, (float(curv) if curv > 0 else math.nan)


#: passes of decomposition at the response's estimated time scale, each followed by the pooled
#: likelihood again
_STRETCH_ROUNDS = 2

#: the estimate's name of each scalar held in the pooled likelihood (the onset's: "delay_ps")
_EST_NAME = {"sigma_ps": "psf_sigma_ps", STRETCH_KEY: STRETCH_KEY}
#: the scalars searched in their logarithm
_LOG_SCALE = ("sigma_ps", STRETCH_KEY)


def _profile_refine(profiles, first, info, names, est, *, keywords, time_bin_ps, fixed=None):
    """The scalar shared PSF width and onset at the maximum of the pixels' pooled likelihood,
    each pixel's other parameters refitted (component set of the first pass kept), started from
    the pooled per-pixel estimates; their standard errors from its curvature (-2 log L rises by 1
    one error away), inflated where the misfit per degree of freedom exceeds 1.  Per-pixel
    estimates are biased where one pixel cannot separate a width from an onset or a decay
    (a hundred photons); the pooled likelihood is not.  ``fixed``: per-pixel values held
    throughout (the PSF map's widths, (n,) arrays).  -> (``est`` updated, the pixels pooled: at
    most :data:`N_LIKELIHOOD_PIXELS`, thinned evenly)."""
    counts = info["noise_model"] == "poisson"
    noise = np.asarray(info["noise_sigma"], np.float64).reshape(-1)
    t0 = info["t0_ps"]
    keep = np.isfinite(np.where(np.isfinite(first["direct_delay_ps"]), first["direct_delay_ps"],
                                first["sss_delay_ps"]))
    if not counts:
        keep &= np.isfinite(noise) & (noise > 0)
    if keep.sum() < 2:
        return est, 0
    idx = np.flatnonzero(keep)
    if idx.size > N_LIKELIHOOD_PIXELS:
        # thinned evenly (the selection is in raster order): the likelihood's refits are the
        # estimate's cost, and its error from this many pixels is already a small fraction of
        # the PSF width's
        keep = np.zeros_like(keep)
        keep[idx[np.linspace(0, idx.size - 1, N_LIKELIHOOD_PIXELS).round().astype(np.int64)]] = True
    prof = np.asarray(profiles, np.float64)[keep]
    params = {k: np.asarray(v)[keep] for k, v in first.items() if not k.endswith("_stderr")}
    base = {k: np.broadcast_to(np.asarray(v, np.float64), keep.shape)[keep] for k, v in (fixed or {}).items()}
    shared_sigma = bool(keywords.get("shared_sigma", True))
    kw = dict(counts=counts, noise=noise[keep], time_bin_ps=time_bin_ps, t0_ps=t0, shared_sigma=shared_sigma)
    pooled_misfit = _pooled_misfit
    if keywords.get("irf") is not None:
        kw["irf"] = resolve_response(keywords["irf"], time_bin_ps, prof.shape[-1])
        pooled_misfit = _pooled_misfit_response
    held = {}

    def misfit(hold):       # the fixed values always held
        return pooled_misfit(prof, params, dict(base, **hold), **kw)

    if "psf" in names:
        scale_key = STRETCH_KEY if "irf" in kw else "sigma_ps"
        held[scale_key] = est[_EST_NAME[scale_key]]
    if "delay" in names:
        held[est["delay_key"]] = est["delay_ps"]
    dof = max(prof.size - sum(np.isfinite(v).sum() for k, v in params.items() if np.ndim(v) == 1), 1)
    for _ in range(2 if len(held) > 1 else 1):    # coordinate-wise: the width, then the onset, twice
        for key in list(held):
            v0 = held[key]
            if key in _LOG_SCALE:
                # within a factor 1.6 of the pooled start, to 1 % (its error is a fraction of that)
                hi = math.log(v0) + 0.5
                if key == STRETCH_KEY:
                    # no longer than the window holds (the response path's own limit), less a step
                    hi = min(hi, math.log(prof.shape[-1] / kw["irf"].n_samples) - 0.02)
                x, curv = _minimise_1d(lambda x: misfit(dict(held, **{key: math.exp(x)})),
                                       math.log(v0) - 0.5, hi, step=0.01)
                if key == STRETCH_KEY and x > hi - 0.01 and hi < math.log(v0) + 0.5:
                    raise ValueError(f"shared='psf': the response's time scale reached {math.exp(hi):.3g}, the "
                                     f"most the profiles' window of {prof.shape[-1]} bins holds; use longer profiles")
                held[key] = math.exp(x)
                se = held[key] * math.sqrt(2.0 / curv) if curv > 0 else math.nan
            else:
                # three widths either side (ten errors of the pooled start, at least a bin, with a map)
                half = (3.0 * held["sigma_ps"] if "sigma_ps" in held
                        else max(10.0 * est.get("delay_ps_stderr", 0.0), float(time_bin_ps)))
                x, curv = _minimise_1d(lambda x: misfit(dict(held, **{key: x})),
                                       v0 - half, v0 + half, step=0.05 * float(time_bin_ps))
                held[key] = x
                se = math.sqrt(2.0 / curv) if curv > 0 else math.nan
            name = _EST_NAME.get(key, "delay_ps")
            est[name], est[name + "_stderr"] = held[key], se
    inflate = max(1.0, math.sqrt(misfit(held) / dof))
    names_held = [_EST_NAME.get(k, "delay_ps") for k in held]
    if len(held) == 2 and all(math.isfinite(est[n + "_stderr"]) for n in names_held):
        # the two are correlated: the marginal errors from the joint curvature (log width, onset)
        keys = list(held)
        x0 = np.array([math.log(held[k]) if k in _LOG_SCALE else held[k] for k in keys])
        h = np.array([est[_EST_NAME[k] + "_stderr"] / est[_EST_NAME[k]] if k in _LOG_SCALE
                      else est["delay_ps_stderr"] for k in keys])

        def f(x):
            return misfit({k: (math.exp(v) if k in _LOG_SCALE else v) for k, v in zip(keys, x)})

        f0 = f(x0)
        e = np.eye(2) * h
        hess = np.empty((2, 2))
        for i in range(2):
            hess[i, i] = (f(x0 + e[i]) - 2 * f0 + f(x0 - e[i])) / h[i] ** 2
        hess[0, 1] = hess[1, 0] = (f(x0 + e[0] + e[1]) - f(x0 + e[0] - e[1]) - f(x0 - e[0] + e[1])
                                   + f(x0 - e[0] - e[1])) / (4 * h[0] * h[1])
        if np.all(np.linalg.eigvalsh(hess) > 0):
            var = np.diag(np.linalg.inv(hess / 2.0))
            for k, v in zip(keys, var):
                if k in _LOG_SCALE:
                    est[_EST_NAME[k] + "_stderr"] = est[_EST_NAME[k]] * math.sqrt(v)
                else:
                    est["delay_ps_stderr"] = math.sqrt(v)
    for name, key in (("psf_sigma_ps", "sigma_ps"), (STRETCH_KEY, STRETCH_KEY), ("delay_ps", est.get("delay_key"))):
        if name + "_stderr" in est and name in est and key in held:
            est[name + "_stderr"] *= inflate
    return est, int(keep.sum())


def _width(params):
    """Per-pixel PSF width and its error: the direct's, else the sss's."""
    d, s = params["direct_sigma_ps"], params["sss_sigma_ps"]
    de = params.get("direct_sigma_ps_stderr", np.full(np.shape(d), np.nan))
    se = params.get("sss_sigma_ps_stderr", np.full(np.shape(s), np.nan))
    use_d = np.isfinite(d) & np.isfinite(de)
    return np.where(use_d, d, s), np.where(use_d, de, se)


def estimate_shared(profiles, yx, labels, shape, time_bin_ps: float, method: str, names: tuple, *,
                    psf_map: bool = False, regions: bool = False, keywords: dict,
                    one_instrument: bool = False) -> SharedEstimate:
    """The shared parameters from the selected pixels (:func:`select_pixels`).

    Parameters
    ----------
    profiles : ndarray (n, L)
        The selected pixels' profiles.
    yx : ndarray (n, 2) of int
        Their (y, x) in the image of ``shape`` (Y, X).
    labels : ndarray (n,) of int
        Their regions (all 0 without regions).
    time_bin_ps, method, keywords
        As for :func:`decomposition.decompose` (the call's own keywords).
    names : tuple
        What to estimate, of ("psf", "delay", "alpha").
    psf_map : bool
        The PSF width as a quadratic surface over the image instead of one number.
    regions : bool
        The labels are the caller's regions (recorded; else one region, label 0).
    one_instrument : bool
        Share the PSF only where the pixels' own widths are one instrument's: raise
        :class:`NotOneInstrument` where they scatter beyond their errors by more than
        :data:`ONE_INSTRUMENT_SPREAD` (the spread is recorded either way, ``psf_spread``).

    Raises ValueError (naming the parameter) where no selected pixel gives an estimate.
    """
    profiles = np.asarray(profiles)
    if profiles.shape[0] == 0:
        raise ValueError(f"shared={','.join(names)}: no lit pixel to estimate it from (every profile is flat "
                         f"or has NaN/inf samples)")
    fams = parse_components(keywords.get("components", ("d", "r", "s")))
    if "alpha" in names and "s" not in fams:
        raise OptionError("shared='alpha': the components have no sss (add 's')")
    response = keywords.get("irf") is not None
    if "psf" in names and response and psf_map:
        raise OptionError("psf_map: a measured response (irf=) is shared as one time scale over the image, "
                          "not as a map")
    kw = dict(keywords, stderr=True)
    pixels = {"selected": int(profiles.shape[0])}
    est = {"names": tuple(names), "shape": tuple(int(s) for s in shape)}
    hold = None
    first = decompose(profiles, time_bin_ps, method, **kw).params
    if "psf" in names and response:
        # the response's time scale: from 1 (the response as given), by the pooled likelihood
        est["response_stretch"], est["response_stretch_stderr"] = 1.0, math.nan
    elif "psf" in names:
        width, width_se = _width(first)
        est["psf_spread"] = excess_spread(width, width_se)
        if one_instrument and not est["psf_spread"] <= ONE_INSTRUMENT_SPREAD:
            raise NotOneInstrument(f"the lit pixels' own PSF widths scatter by {est['psf_spread']:.0%} beyond their "
                                   f"errors (one instrument: at most {ONE_INSTRUMENT_SPREAD:.0%})")
        if psf_map:
            coef, cov, center, scale, n = fit_surface(yx[:, 0], yx[:, 1], width, width_se, shape)
            est["psf_map"] = {"terms": list(SURFACE_TERMS), "coefficients_ps": coef.tolist(),
                              "covariance_ps2": cov.tolist(), "center_yx": list(center), "scale_yx": list(scale)}
            est["psf_sigma_ps"], est["psf_sigma_ps_stderr"] = float(coef[0]), float(math.sqrt(cov[0, 0]))
            _check_width_surface(coef, center, scale, shape)
            a = surface_design(yx[:, 0], yx[:, 1], center, scale)
            hold = {"sigma_ps": a @ coef}
        else:
            value, se, n = pooled_positive(width, width_se)
            if n == 0:
                raise ValueError(f"shared='psf': none of the {profiles.shape[0]} lit pixels has a component "
                                 f"whose width could be estimated")
            est["psf_sigma_ps"], est["psf_sigma_ps_stderr"] = value, se
            hold = {"sigma_ps": value}
        pixels["psf"] = n
    if "delay" in names:
        key = "direct_delay_ps" if "d" in fams else "sss_delay_ps"
        value, se, n = pooled(first[key], first[key + "_stderr"])
        if n == 0:
            raise ValueError(f"shared='delay': none of the {profiles.shape[0]} lit pixels has a "
                             f"{key.split('_')[0]} onset that could be estimated")
        est.update(delay_key=key, delay_ps=value, delay_ps_stderr=se)
        pixels["delay"] = n
    scalar = tuple(n for n in names if n == "delay" or (n == "psf" and not psf_map))
    if scalar:
        # the pixels decomposed again with the pooled starts held (a pixel whose free fit tied its
        # sss onset to the direct gets its components apart), then the pooled likelihood
        start = dict(hold or {})
        if "delay" in names:
            start[est["delay_key"]] = est["delay_ps"]
        again = decompose(profiles, time_bin_ps, method, hold=start, **kw)
        est, pixels["likelihood"] = _profile_refine(profiles, again.params, again.info, scalar, est, keywords=keywords,
                              time_bin_ps=time_bin_ps, fixed=hold if psf_map else None)
        if "psf" in scalar and response:
            base_irf = resolve_response(kw["irf"], time_bin_ps, profiles.shape[-1])
            for _ in range(_STRETCH_ROUNDS):
                if pixels["likelihood"] < 2:
                    raise ValueError(f"shared='psf': fewer than 2 of the {profiles.shape[0]} lit pixels have a "
                                     f"component to estimate the response's time scale from")
                # the pixels decomposed again with the response at the estimate (their component
                # sets found with the response as given may hold atoms its other scale needs not)
                kw["irf"] = stretched_response(base_irf, est["response_stretch"])
                start = {k: v for k, v in start.items() if k != est.get("delay_key")}
                if "delay" in names:
                    start[est["delay_key"]] = est["delay_ps"]
                again = decompose(profiles, time_bin_ps, method, hold=start, **kw)
                est, pixels["likelihood"] = _profile_refine(profiles, again.params, again.info, scalar, est,
                                                            keywords=keywords, time_bin_ps=time_bin_ps)
            kw["irf"] = stretched_response(base_irf, est["response_stretch"])
            pixels["psf"] = pixels["likelihood"]
        elif "psf" in scalar:
            hold = {"sigma_ps": est["psf_sigma_ps"]}
    if "alpha" in names and "delay" in names:
        hold = dict(hold or {}, **{est["delay_key"]: est["delay_ps"]})
    stretched = "psf" in names and response
    second = first if (hold is None and not stretched) or "alpha" not in names else \
        decompose(profiles, time_bin_ps, method, hold=hold, **kw).params
    if "alpha" in names:
        alpha, alpha_se = {}, {}
        for label in np.unique(labels):
            inside = labels == label
            value, se, n = pooled_positive(second["sss_alpha_per_ps"][inside],
                                           second["sss_alpha_per_ps_stderr"][inside])
            if n == 0:
                raise ValueError(f"shared='alpha': region {int(label)} has no lit pixel with an sss whose decay "
                                 f"rate could be estimated (label pixels to leave free with a negative number)")
            alpha[int(label)], alpha_se[int(label)] = value, se
            pixels[f"alpha_{int(label)}"] = n
        est.update(sss_alpha_per_ps=alpha, sss_alpha_per_ps_stderr=alpha_se)
    return SharedEstimate(**est, regions=bool(regions), pixels=pixels)


#: the parameter keys each held key stands for
_HELD_PARAMS = {"sigma_ps": ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"),
                "direct_delay_ps": ("direct_delay_ps",), "sss_delay_ps": ("sss_delay_ps",),
                "sss_alpha_per_ps": ("sss_alpha_per_ps",)}


def held_response(n_bins: int, time_bin_ps: float, hold: dict, keywords: dict) -> tuple[dict, dict]:
    """``hold`` without a response's shared time scale, and ``keywords`` with the response
    ``irf`` stretched by it (``hold[STRETCH_KEY]``, one value): what a call of
    :func:`decomposition.decompose` (or a refit of the image path) on profiles of ``n_bins``
    bins takes for them.  Both returned as given where there is no such scale."""
    if STRETCH_KEY not in hold:
        return hold, keywords
    hold, keywords = dict(hold), dict(keywords)
    stretch = np.asarray(hold.pop(STRETCH_KEY), np.float64)
    if keywords.get("irf") is None:
        raise OptionError("a shared response time scale needs the response (irf=)")
    if stretch.size:
        keywords["irf"] = stretched_response(resolve_response(keywords["irf"], time_bin_ps, n_bins),
                                             float(stretch.flat[0]))
    return hold, keywords


def decompose_held(profiles, time_bin_ps: float, method: str, *, hold: dict, hold_stderr: dict, **keywords):
    """:func:`decomposition.decompose` with ``hold`` (each key's values in the profiles' leading
    shape); a held parameter's ``<key>_stderr`` (where the call gives errors) is the shared
    estimate's, ``hold_stderr`` (:func:`apply_held_stderr`).  A response's shared time scale
    (``hold[STRETCH_KEY]``, one value) decomposes with the response ``irf`` stretched by it
    (:func:`held_response`)."""
    hold, keywords = held_response(np.shape(profiles)[-1], time_bin_ps, hold, keywords)
    hold_stderr = {k: v for k, v in hold_stderr.items() if k != STRETCH_KEY}
    return apply_held_stderr(decompose(profiles, time_bin_ps, method, hold=hold, **keywords), hold,
                             hold_stderr)


def apply_held_stderr(result, hold: dict, hold_stderr: dict):
    """``result`` with each held parameter's ``<key>_stderr`` set to the shared estimate's
    (``hold_stderr``) where the component is present (in place; returned)."""
    params = result.params
    for key, keys in _HELD_PARAMS.items():
        if key not in hold:
            continue
        for name in keys:
            if name + "_stderr" not in params:
                continue
            value, se = np.asarray(params[name]), np.asarray(hold_stderr[key], np.float64)
            se = se.reshape(se.shape + (1,) * (value.ndim - se.ndim))
            held = np.isfinite(value) & np.isfinite(np.asarray(hold[key], np.float64).reshape(se.shape))
            params[name + "_stderr"] = np.where(held, se, params[name + "_stderr"])
    return result
