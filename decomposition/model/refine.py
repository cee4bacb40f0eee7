"""Off-grid refinement of decomposed components by batched nonlinear least squares.

The sparse-coding step decides *which* components a pixel has and puts each on
a grid of delays, widths and attenuations.  This module keeps that component
set fixed and moves every present component's continuous parameters off the
grid to the least-squares optimum of the forward model of
:mod:`core.model`.

Options: ``shared_sigma`` refines one PSF width per pixel for all its
components (eq. (2) has a single camera PSF); ``sss_after_direct`` keeps the
sss onset at or after the direct delay (projection); ``weights`` give per-sample
weights (0 excludes saturated or spiky samples).

Each pixel is normalised by its peak magnitude before fitting, so any overall
scale (1e-30 .. 1e30) gives the same parameters and scaled amplitudes.  A
pixel's refined parameters are kept only when they lower its residual sum of
squares below that of the input parameters (with the input amplitudes) and
keep every present amplitude positive; otherwise the input is returned as is.

A constant offset per pixel (``params["background"]``, the ``b`` family) is either held
fixed (subtracted from the profile; the default) or, with ``fit_background``, fitted jointly
with the amplitudes as one more linear parameter (:mod:`decomposition.model.varpro`).

Kernels and derivatives: :mod:`decomposition.kernels.derivatives`; the batched variable-projection
LM: :mod:`decomposition.model.varpro`.
"""

from __future__ import annotations

import numpy as np

from ..constants import SSS_SLOT
from ..kernels.derivatives import kernel_derivatives  # noqa: F401  (public here since the first release)
from ..kernels.response import response_table
from core.model import BACKGROUND_KEY, DIRECT_KEYS, IR_KEYS, SSS_KEYS, time_axis_ps
from .varpro import Layout, refine_block

__all__ = ["refine", "kernel_derivatives", "slot_arrays", "params_from_slots", "apply_weights", "HOLD_KEYS",
           "check_hold", "hold_params", "held_slots", "unit_widths"]

#: The parameters a fit can hold at given values (``hold=`` of :func:`refine`, of
#: :func:`decomposition.model.fisher.standard_errors` and of :func:`decomposition.decompose`):
#: ``sigma_ps`` every component's width (the PSF), ``direct_delay_ps`` the direct's onset,
#: ``sss_delay_ps`` the sss onset, ``sss_alpha_per_ps`` the sss decay rate.
HOLD_KEYS = ("sigma_ps", "direct_delay_ps", "sss_delay_ps", "sss_alpha_per_ps")


# ----------------------------------------------------------------------------------------------
# parameter dict <-> slot arrays
# ----------------------------------------------------------------------------------------------

def slot_arrays(params: dict, lead_shape: tuple) -> dict[str, np.ndarray]:
    """Flatten a parameter dict into per-slot arrays.

    Parameters
    ----------
    params : dict of ndarray
        Keys of :mod:`core.model`; a missing family counts as absent.
    lead_shape : tuple
        Leading (pixel) shape the parameters must have.

    Returns
    -------
    dict with ``delay``, ``amplitude``, ``sigma`` (N, K) and ``alpha`` (N,),
    ``present`` (N, K) bool, and ``n_ir`` (int); N = prod(lead_shape),
    K = 2 + n_ir, slot 0 direct, 1 sss, 2.. inter-reflections in input order.
    """
    lead_shape = tuple(lead_shape)
    n = int(np.prod(lead_shape, dtype=np.int64))

    def get(key, extra=()):
        if key not in params:
            return None
        v = np.asarray(params[key], dtype=np.float64)
        if v.shape != lead_shape + extra:
            raise ValueError(f"params[{key!r}] has shape {v.shape}, expected {lead_shape + extra}")
        return v.reshape((n,) + extra)

    n_ir = 0
    if "ir_delay_ps" in params:
        shp = np.shape(params["ir_delay_ps"])
        if shp[:-1] != lead_shape or len(shp) != len(lead_shape) + 1:
            raise ValueError(f"params['ir_delay_ps'] has shape {shp}, expected {lead_shape} + (R,)")
        n_ir = shp[-1]
    k = 2 + n_ir
    out = {name: np.full((n, k), np.nan) for name in ("delay", "amplitude", "sigma")}
    out["alpha"] = np.full(n, np.nan)
    for slot, keys in ((0, DIRECT_KEYS), (SSS_SLOT, ("sss_delay_ps", "sss_amplitude", "sss_sigma_ps"))):
        vals = [get(key) for key in keys]
        if all(v is not None for v in vals):
            for name, v in zip(("delay", "amplitude", "sigma"), vals):
                out[name][:, slot] = v
    a = get("sss_alpha_per_ps")
    if a is not None:
        out["alpha"] = a
    if n_ir:
        vals = [get(key, (n_ir,)) for key in IR_KEYS]
        if any(v is None for v in vals):
            raise ValueError("params has ir_delay_ps but not all of " + ", ".join(IR_KEYS))
        for name, v in zip(("delay", "amplitude", "sigma"), vals):
            out[name][:, 2:] = v
    present = np.isfinite(out["delay"]) & np.isfinite(out["amplitude"]) & np.isfinite(out["sigma"])
    present &= out["sigma"] > 0
    present[:, SSS_SLOT] &= np.isfinite(out["alpha"]) & (out["alpha"] >= 0)
    out["present"] = present
    out["n_ir"] = n_ir
    return out


def params_from_slots(slots: dict, lead_shape: tuple) -> dict[str, np.ndarray]:
    """Inverse of :func:`slot_arrays`: absent slots become NaN; returns a full parameter dict."""
    lead_shape = tuple(lead_shape)
    pres = slots["present"]
    n_ir = slots["n_ir"]

    def col(name, sl):
        v = np.where(pres[:, sl], slots[name][:, sl], np.nan)
        return v

    out = {}
    for key, name in zip(DIRECT_KEYS, ("delay", "amplitude", "sigma")):
        out[key] = col(name, 0).reshape(lead_shape)
    for key, name in zip(("sss_delay_ps", "sss_amplitude", "sss_sigma_ps"), ("delay", "amplitude", "sigma")):
        out[key] = col(name, SSS_SLOT).reshape(lead_shape)
    out["sss_alpha_per_ps"] = np.where(pres[:, SSS_SLOT], slots["alpha"], np.nan).reshape(lead_shape)
    for key, name in zip(IR_KEYS, ("delay", "amplitude", "sigma")):
        out[key] = col(name, slice(2, None)).reshape(lead_shape + (n_ir,))
    return {key: out[key] for key in DIRECT_KEYS + SSS_KEYS + IR_KEYS}




def check_hold(hold, lead_shape: tuple) -> dict:
    """``hold`` ({key of :data:`HOLD_KEYS`: values}) -> {key: float64 (n,)}, n = prod(lead_shape).

    Each value is a scalar or an array broadcastable to ``lead_shape``; NaN leaves that pixel's
    parameter free.  Widths and decay rates must be positive.  Raises ValueError naming the
    problem (an unknown key, a shape that does not broadcast, an inf or non-positive value).
    """
    lead_shape = tuple(lead_shape)
    n = int(np.prod(lead_shape, dtype=np.int64))
    out = {}
    for key, value in dict(hold or {}).items():
        if key not in HOLD_KEYS:
            raise ValueError(f"hold: unknown parameter {key!r}; choose from {', '.join(HOLD_KEYS)}")
        try:
            v = np.broadcast_to(np.asarray(value, dtype=np.float64), lead_shape).reshape(n)
        except ValueError:
            raise ValueError(f"hold[{key!r}]: shape {np.shape(value)} does not fit the pixels' {lead_shape}") from None
        if np.isinf(v).any():
            raise ValueError(f"hold[{key!r}]: values must be finite (NaN: free), got inf")
        if key in ("sigma_ps", "sss_alpha_per_ps") and np.any(v[np.isfinite(v)] <= 0):
            raise ValueError(f"hold[{key!r}]: values must be > 0")
        out[key] = v
    return out


def held_slots(hold: dict, n: int, k: int):
    """Per-slot masks and values of a checked ``hold`` (:func:`check_hold`, n pixels, K slots):
    -> (delay (n, K) bool, sigma (n,) bool, alpha (n,) bool): each slot's delay, every width of
    the pixel, the sss decay rate."""
    delay = np.zeros((n, k), bool)
    for slot, key in ((0, "direct_delay_ps"), (SSS_SLOT, "sss_delay_ps")):
        if key in hold:
            delay[:, slot] = np.isfinite(hold[key])
    sigma = np.isfinite(hold["sigma_ps"]) if "sigma_ps" in hold else np.zeros(n, bool)
    alpha = np.isfinite(hold["sss_alpha_per_ps"]) if "sss_alpha_per_ps" in hold else np.zeros(n, bool)
    return delay, sigma, alpha


def hold_params(params: dict, hold, lead_shape: tuple) -> dict:
    """``params`` with the held values (:func:`check_hold`) put in where the component is present
    (a new dict; absent components stay NaN)."""
    lead_shape = tuple(lead_shape)
    hold = check_hold(hold, lead_shape)
    if not hold:
        return params
    n = int(np.prod(lead_shape, dtype=np.int64))
    out = dict(params)

    def put(key, value, extra=()):
        if key not in out:
            return
        v = np.array(out[key], dtype=np.float64).reshape((n,) + extra)
        val = value.reshape((n,) + (1,) * len(extra))
        out[key] = np.where(np.isfinite(v) & np.isfinite(val), val, v).reshape(lead_shape + extra)

    if "sigma_ps" in hold:
        put("direct_sigma_ps", hold["sigma_ps"])
        put("sss_sigma_ps", hold["sigma_ps"])
        if "ir_sigma_ps" in out:
            put("ir_sigma_ps", hold["sigma_ps"], np.shape(out["ir_sigma_ps"])[len(lead_shape):])
    for key in ("direct_delay_ps", "sss_delay_ps", "sss_alpha_per_ps"):
        if key in hold:
            put(key, hold[key])
    return out


def unit_widths(params: dict) -> dict:
    """``params`` with every component's width 1 where its delay is given: a response's atoms
    have no width, and :func:`slot_arrays` reads a component as present by a finite positive
    one."""
    out = dict(params)
    for d_key, s_key in (("direct_delay_ps", "direct_sigma_ps"), ("sss_delay_ps", "sss_sigma_ps"),
                         ("ir_delay_ps", "ir_sigma_ps")):
        if d_key in out:
            out[s_key] = np.where(np.isfinite(np.asarray(out[d_key], np.float64)), 1.0, np.nan)
    return out


def apply_weights(y, weights):
    """Validate per-sample weights against profiles ``y`` (..., L).

    Returns ``y`` with zero-weight samples set to 0 (they may hold anything: NaN,
    saturation) and the square-root weights as (n_pixels, L), or ``None`` without weights.
    """
    if weights is None:
        return y, None
    wts = np.asarray(weights, dtype=np.float64)
    if wts.shape != y.shape:
        raise ValueError(f"weights must have the shape of profiles {y.shape}, got {wts.shape}")
    if np.any(~np.isfinite(wts)) or np.any(wts < 0):
        raise ValueError("weights must be finite and non-negative")
    return np.where(wts > 0, y, 0.0), np.sqrt(wts).reshape(-1, y.shape[-1])

def refine(profiles, params, *, time_bin_ps: float = 2.0, t0_ps: float | None = None,
           max_iter: int = 20, ftol: float = 1e-6, block_size: int = 4096,
           sigma_bounds_ps: tuple[float, float] | None = None,
           alpha_bounds_per_ps: tuple[float, float] = (1e-7, 1e3),
           shared_sigma: bool = False, sss_after_direct: bool = False, keep_order: bool = True, weights=None,
           bin_integrated: bool = False, fit_background=False, delay_prior=None, onset_prior=None, alpha_prior=None,
           ratio_prior=None,
           hold=None, irf=None):
    """Refine the continuous parameters of each pixel's present components.

    Parameters
    ----------
    profiles : array_like, shape (..., L)
        Measured time profiles, any real dtype; must be finite.
    params : dict of ndarray
        Starting parameters (keys of :mod:`core.model`, shapes (...,)
        and (..., R)); NaN marks an absent component.  Which components are
        present is never changed.
    time_bin_ps, t0_ps : float
        Time axis (bin ``i`` at ``t0_ps + i * time_bin_ps``; t0 defaults to one bin).
    max_iter : int
        Maximum Levenberg-Marquardt iterations per pixel (each costs one model
        evaluation with its Jacobian).
    ftol : float
        A pixel has converged when an accepted step lowers its residual sum of
        squares by less than this fraction.
    block_size : int
        Pixels fitted together (memory ~ block_size * L * (2K+1) * 8 bytes * 3).
    sigma_bounds_ps : (float, float), optional
        Bounds on every sigma; default (time_bin_ps / 10, L * time_bin_ps).
    alpha_bounds_per_ps : (float, float)
        Bounds on the sss attenuation (strictly positive: refined in log space).
    shared_sigma : bool
        Fit one Gaussian width per pixel shared by all its components (the
        camera PSF of eq. (2)), started from the direct component's width (or
        the mean of the present ones).  Fewer unknowns and no width/delay
        trade-off between overlapping components; use it when the data come
        from one PSF.  Default: each component has its own width.
    sss_after_direct : bool
        Keep every sss onset at or after its pixel's direct delay (light enters
        the surface where it is directly reflected).  A pixel whose sss rising
        edge sits under its direct peak is nearly degenerate in least squares;
        the constraint (enforced by projection) removes that freedom.
    keep_order : bool
        Keep the component labels valid while refining: no inter-reflection
        moves before the direct reflection or before an earlier
        inter-reflection (enforced by projection).  Inter-reflection slots are
        assumed to be in order of delay, as decompositions report them.
    weights : array_like, shape (..., L), optional
        Non-negative per-sample weights of the least-squares fit (1 / variance
        for heteroscedastic noise; 0 excludes a sample, e.g. a saturated one,
        whose value is then ignored even if it is NaN).  Default: all ones.
    bin_integrated : bool
        Fit bin-averaged kernels instead of point samples (as in model.render_*).
    fit_background : bool or array_like of bool, shape (...,)
        Pixels that fit a constant offset jointly with the amplitudes (started from
        ``params["background"]`` where finite, else 0).  Elsewhere an offset in ``params``
        (finite ``params["background"]``) is held fixed: subtracted before the fit and
        returned unchanged.
    delay_prior : (mean, weight) of array_like, each of shape (...,), optional
        A Gaussian pseudo-observation of each pixel's direct delay: ``weight`` * (direct delay -
        ``mean``)^2 is added to the weighted RSS the fit lowers (``mean`` in ps, ``weight`` in the
        units of ``profiles`` squared per ps^2, i.e. the RSS-units precision of the prior;
        0 or NaN: none).  A neighbourhood's estimate of the delay, weighed against the pixel's
        own samples (:mod:`decomposition.image.spatial`).
    onset_prior : (mean, weight) of array_like, each of shape (...,), optional
        The same for the sss onset after the direct: ``weight`` * (sss delay - direct delay -
        ``mean``)^2 (``mean`` in ps, ``weight`` as ``delay_prior``'s).  Pixels without both
        components have none.
    alpha_prior : (mean, weight) of array_like, each of shape (...,), optional
        The same for the sss decay rate's natural logarithm: ``weight`` * (ln alpha -
        ``mean``)^2 (``mean`` in ln(1/ps), ``weight`` in the units of ``profiles`` squared).
    ratio_prior : (mean, weight) of array_like, each of shape (...,), optional
        The same for the sss amplitude over the direct's: ``weight`` * (sss amplitude - ``mean``
        * direct amplitude)^2 (``mean`` dimensionless, ``weight`` dimensionless: the term is in
        the units of ``profiles`` squared), linear in the amplitudes.  Pixels without both
        components have none.
    hold : dict, optional
        Parameters held at given values ({key of :data:`HOLD_KEYS`: scalar or array
        broadcastable to (...,)}, NaN: free for that pixel): put into the start and never moved
        (the amplitudes and the other parameters are fitted around them), even outside the
        bounds.  Used for parameters every pixel shares (one instrument, one onset, one decay
        rate; :mod:`decomposition.image.shared`).
    irf : InstrumentResponse, optional
        A measured instrument response (resolved on ``time_bin_ps``,
        :func:`decomposition.response.resolve.resolve_response`) whose atoms replace the
        Gaussian PSF's: the shifted response for the direct and the inter-reflections, the
        response convolved with the sss exponential, unit peak
        (:mod:`decomposition.kernels.response`).  The same fit over the same parameters less
        the widths, which a response does not have (the ``*_sigma_ps`` keys are not read, and
        returned as given).  Point samples only (not with ``bin_integrated``).

    Returns
    -------
    params : dict of ndarray
        Refined parameters, same keys and shapes as a full parameter dict,
        NaN where a component is absent; with a ``background`` key (shape (...,), units
        of ``profiles``) when the input had one or ``fit_background`` is set anywhere.  Pixels whose fit did not improve keep
        their input parameters exactly.
    info : dict of ndarray, each of the leading shape (...,)
        ``iterations`` (int), ``converged`` (bool), ``refined`` (bool: refined
        values were kept), ``rss_input`` and ``rss`` (weighted residual sums
        of squares of the input and returned parameters, in the units of
        ``profiles`` squared; with the priors their terms included).
    """
    y = np.asarray(profiles)
    if y.ndim < 1 or y.shape[-1] < 2:
        raise ValueError(f"profiles must have shape (..., L) with L >= 2, got {y.shape}")
    if not np.issubdtype(y.dtype, np.number) or np.iscomplexobj(y):
        raise ValueError(f"profiles must be real numbers, got dtype {y.dtype}")
    y = y.astype(np.float64)
    y, sw = apply_weights(y, weights)
    bad = ~np.isfinite(y).all(axis=-1)
    if bad.any():
        raise ValueError(f"profiles contain NaN or inf samples in {int(bad.sum())} pixel(s)")
    if int(max_iter) < 0:
        raise ValueError("max_iter must be >= 0")
    if int(block_size) < 1:
        raise ValueError("block_size must be >= 1")
    lead = y.shape[:-1]
    n_bins = y.shape[-1]
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    tb = float(time_bin_ps) if bin_integrated else None
    if sigma_bounds_ps is None:
        sigma_bounds_ps = (float(time_bin_ps) / 10.0, n_bins * float(time_bin_ps))
    s_lo, s_hi = map(float, sigma_bounds_ps)
    a_lo, a_hi = map(float, alpha_bounds_per_ps)
    if not (0 < s_lo < s_hi and np.isfinite(s_hi)):
        raise ValueError(f"sigma_bounds_ps must satisfy 0 < low < high < inf, got {sigma_bounds_ps}")
    if not (0 < a_lo < a_hi and np.isfinite(a_hi)):
        raise ValueError(f"alpha_bounds_per_ps must satisfy 0 < low < high < inf, got {alpha_bounds_per_ps}")

    hold = check_hold(hold, lead)
    table = None
    if irf is not None:
        if bin_integrated:
            raise ValueError("bin_integrated applies to the Gaussian PSF; a response (irf=) is sampled on its bins")
        if hold and "sigma_ps" in hold:
            raise ValueError("hold['sigma_ps'] holds the Gaussian PSF's width; a measured response (irf=) has none")
        table = response_table(irf)
        given_widths = {k: params[k] for k in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps") if k in params}
        params = unit_widths(params)
    params = hold_params(params, hold, lead)
    slots = slot_arrays(params, lead)
    y = y.reshape(-1, n_bins)
    n = y.shape[0]
    fit_bg = np.broadcast_to(np.asarray(fit_background, bool), lead).reshape(n)
    has_bg = BACKGROUND_KEY in params or fit_bg.any()
    b_in = np.zeros(n)
    if BACKGROUND_KEY in params:
        b_given = np.asarray(params[BACKGROUND_KEY], np.float64)
        if b_given.shape != lead:
            raise ValueError(f"params[{BACKGROUND_KEY!r}] has shape {b_given.shape}, expected {lead}")
        b_in = np.where(np.isfinite(b_given.reshape(n)), b_given.reshape(n), 0.0)
    # a held offset is subtracted (zero-weight samples stay 0)
    held = np.where(fit_bg, 0.0, b_in)
    y = y - held[:, None] * (np.ones_like(y) if sw is None else (sw > 0))
    k = 2 + slots["n_ir"]
    # a response's atoms have no width: its layout carries none (shared_sigma has nothing to share)
    lay = Layout(k, shared_sigma and irf is None, widths=irf is None)
    span = n_bins * float(time_bin_ps)
    lo, hi = lay.bounds((t[0] - span, t[-1] + span), (np.log(s_lo), np.log(s_hi)), (np.log(a_lo), np.log(a_hi)))
    held = None
    if hold:
        d_held, s_held, a_held = held_slots(hold, n, k)
        held = lay.held(d_held, s_held, a_held)

    # Per-pixel normalisation: parameters are scale-free, amplitudes scale.
    scale = np.max(np.abs(y), axis=-1)
    scale = np.where(scale > 0, scale, 1.0)
    yw = y if sw is None else y * sw
    priors = {}        # name -> (mean, weight in normalised units), (n,) each
    for name, given, per_scale2 in (("delay", delay_prior, True), ("onset", onset_prior, True), ("alpha", alpha_prior, True),
                                    ("ratio", ratio_prior, False)):
        if given is not None:
            mean, weight = (np.broadcast_to(np.asarray(v, np.float64), lead).reshape(n) for v in given)
            priors[name] = (mean, weight / (scale * scale) if per_scale2 else weight)

    res = {name: slots[name].copy() for name in ("delay", "amplitude", "sigma", "alpha")}
    b_out = b_in.copy()
    info = {"iterations": np.zeros(n, np.int64), "converged": np.zeros(n, bool),
            "refined": np.zeros(n, bool), "rss_input": np.zeros(n), "rss": np.zeros(n)}
    for start in range(0, n, int(block_size)):
        sl = slice(start, min(n, start + int(block_size)))
        sc = scale[sl]
        sub = {name: slots[name][sl] for name in ("delay", "sigma", "alpha", "present")}
        sub["amplitude"] = slots["amplitude"][sl] / sc[:, None]
        for name, (mean, weight) in priors.items():
            sub[f"{name}_prior_mean"], sub[f"{name}_prior_weight"] = mean[sl], weight[sl]
        if fit_bg[sl].any():
            sub["fit_background"] = fit_bg[sl]
            sub["background"] = b_in[sl] / sc
        with np.errstate(under="ignore"):
            out, inf = refine_block(t, yw[sl] / sc[:, None], sub, lay, (lo, hi), tb,
                                     int(max_iter), float(ftol), 1e-3, None if sw is None else sw[sl],
                                     bool(sss_after_direct), bool(keep_order),
                                     None if held is None else held[sl], table)
        for name in ("delay", "sigma", "alpha"):
            res[name][sl] = out[name]
        res["amplitude"][sl] = np.where(inf["refined"][:, None], out["amplitude"] * sc[:, None],
                                        slots["amplitude"][sl])
        b_out[sl] = np.where(fit_bg[sl], out["background"] * sc, b_in[sl])
        for key in ("iterations", "converged", "refined"):
            info[key][sl] = inf[key]
        info["rss_input"][sl] = inf["rss_input"] * sc * sc
        info["rss"][sl] = inf["rss"] * sc * sc
    res["present"] = slots["present"]
    res["n_ir"] = slots["n_ir"]
    # held values exactly as given (the log-space round trip would move them by an ulp)
    out_params = hold_params(params_from_slots(res, lead), hold, lead)
    if irf is not None:
        # a response has no width: each component's width key as given (the response path
        # reports its Gaussian-equivalent width there), NaN where none was
        for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"):
            given = np.asarray(given_widths[key], np.float64) if key in given_widths else None
            out_params[key] = (np.full(np.shape(out_params[key]), np.nan) if given is None or
                               given.shape != np.shape(out_params[key]) else given.copy())
    if has_bg:
        b_nan = np.asarray(params[BACKGROUND_KEY], np.float64).reshape(n) if BACKGROUND_KEY in params else np.full(n, np.nan)
        # an absent (NaN) offset stays absent unless it was fitted
        out_params[BACKGROUND_KEY] = np.where(fit_bg | np.isfinite(b_nan), b_out, np.nan).reshape(lead)
    info = {key: v.reshape(lead) for key, v in info.items()}
    return out_params, info
