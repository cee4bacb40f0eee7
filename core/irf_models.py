"""Model instrument responses with closed forms, and how far a response is from a Gaussian.

:func:`gaussian_response`, :func:`tailed_response` (a Gaussian plus an exponential diffusion
tail: the exponentially modified Gaussian, via the overflow-free erfcx form of
:func:`core.model.sss_kernel`) and :func:`afterpulse_response` (a main peak plus a small
delayed copy) return :class:`core.irf.InstrumentResponse` objects whose ``model`` dict
evaluates the closed form (:func:`model_value`), which the tests and the simulated lab use as
the truth.  :func:`gaussian_fit` measures how far any response is from the paper's Gaussian PSF.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from .irf import InstrumentResponse, ResponseError
from .model import sss_kernel

__all__ = ["gaussian_response", "tailed_response", "afterpulse_response", "model_value", "gaussian_fit"]

_SQRT_2PI = math.sqrt(2.0 * math.pi)


def gaussian_fit(irf: InstrumentResponse) -> dict:
    """The best-fitting Gaussian of a response, and what it leaves: how far from the paper's PSF it is.

    Least squares of a * exp(-(t - mu)**2 / (2 sigma**2)) to the unit-peak samples over the span
    where the response exceeds 1 % of its peak (so the figure does not depend on how much empty
    window was recorded).

    Returns
    -------
    dict with ``sigma_ps``, ``center_ps``, ``amplitude`` (of the unit-peak response) and
    ``rms_misfit`` (RMS of the residual over that span, as a fraction of the peak).
    """
    t = irf.time_axis_ps()
    v = irf.samples / irf.peak_per_ps
    inside = np.flatnonzero(v >= 0.01)
    sel = slice(inside[0], inside[-1] + 1)
    t, v = t[sel], v[sel]
    sigma0 = max(irf.fwhm_ps() / (2.0 * math.sqrt(2.0 * math.log(2.0))), irf.time_step_ps)
    res = optimize.least_squares(lambda p: p[0] * np.exp(-0.5 * np.square((t - p[1]) / p[2])) - v,
                                 [1.0, irf.peak_time_ps, sigma0], x_scale=[1.0, sigma0, sigma0])
    a, mu, sigma = res.x
    return {"sigma_ps": float(abs(sigma)), "center_ps": float(mu), "amplitude": float(a),
            "rms_misfit": float(np.sqrt(np.mean(np.square(res.fun))))}


# ------------------------------------------------------------------ model responses
def _check_pos(name, v):
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ResponseError(f"{name} must be positive and finite, got {v!r}")
    return v


def _tailed_density(x, sigma, frac, tau, derivative=False):
    """(1 - f) N(x; sigma) + f EMG(x; sigma, tau), unit area; or its derivative in x."""
    x = np.asarray(x, dtype=np.float64)
    gauss = np.exp(-0.5 * np.square(x / sigma)) / (sigma * _SQRT_2PI)
    emg = 0.0
    if frac > 0:
        # EMG = (1/tau) N * exp(-x/tau) u = (1/tau) sss_kernel(x, sigma, 1/tau) / (sigma sqrt(2 pi)).
        emg = sss_kernel(x, sigma, 1.0 / tau) / (tau * sigma * _SQRT_2PI)
    if not derivative:
        return (1.0 - frac) * gauss + frac * emg
    dgauss = -x / (sigma * sigma) * gauss
    demg = (gauss - emg) / tau if frac > 0 else 0.0
    return (1.0 - frac) * dgauss + frac * demg


def _model_raw(model: dict, x, derivative=False):
    name = model["name"]
    sigma = model["sigma_ps"]
    frac = model.get("tail_fraction", 0.0)
    tau = model.get("tail_tau_ps") or 1.0
    if name in ("gaussian", "tailed"):
        return _tailed_density(x, sigma, frac, tau, derivative)
    if name == "afterpulse":
        r, delta = model["afterpulse_fraction"], model["afterpulse_delay_ps"]
        return (_tailed_density(x, sigma, frac, tau, derivative)
                + r * _tailed_density(np.asarray(x) - delta, sigma, frac, tau, derivative)) / (1.0 + r)
    raise ResponseError(f"unknown response model {name!r}")


def model_value(model: dict, t_ps, *, derivative: bool = False) -> np.ndarray:
    """Closed form of a model response (unit area, 1/ps) at times ``t_ps`` on its axis.

    ``model`` is the ``model`` dict of a response made by :func:`gaussian_response`,
    :func:`tailed_response` or :func:`afterpulse_response`; ``offset_ps`` in it moves the
    reference instant (the peak) to t = 0.
    """
    x = np.asarray(t_ps, dtype=np.float64) + float(model.get("offset_ps", 0.0))
    return _model_raw(model, x, derivative)


def _peak_offset(model: dict, lo: float, hi: float) -> float:
    """Position of the global maximum of the raw model (dense grid, then a root of c')."""
    grid = np.linspace(lo, hi, 8001)
    v = _model_raw(model, grid)
    i = int(np.argmax(v))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    fa, fb = _model_raw(model, a, True), _model_raw(model, b, True)
    if fa > 0 > fb:
        return float(optimize.brentq(lambda x: float(_model_raw(model, x, True)), a, b, xtol=1e-14, rtol=1e-15))
    return float(grid[i])


def _sampled_model(model: dict, time_step_ps: float, before_ps: float, after_ps: float, extent_lo: float,
                   extent_hi: float, provenance: dict | None) -> InstrumentResponse:
    dt = _check_pos("time_step_ps", time_step_ps)
    if model["sigma_ps"] < dt:
        raise ResponseError(f"sigma_ps ({model['sigma_ps']:g}) is below the time step ({dt:g} ps): the sampled "
                            f"response would not represent its shifts to 1 %; sample it more finely")
    peak = _peak_offset(model, extent_lo, extent_hi)
    model = dict(model, offset_ps=peak)
    n_before = int(math.ceil(before_ps / dt))
    n_after = int(math.ceil(after_ps / dt))
    t = dt * np.arange(-n_before, n_after + 1, dtype=np.float64)
    prov = {"source": "model", **model, **dict(provenance or {})}
    return InstrumentResponse(model_value(model, t), dt, float(t[0]), prov, model)


def gaussian_response(sigma_ps: float, *, time_step_ps: float, span_sigmas: float = 9.0,
                      provenance: dict | None = None) -> InstrumentResponse:
    """The paper's Gaussian PSF as a response: N(t; sigma), peak at t = 0.

    Parameters
    ----------
    sigma_ps : float
        Standard deviation, ps (>= time_step_ps).
    time_step_ps : float
        Sample spacing, ps.
    span_sigmas : float
        Samples cover +-span_sigmas * sigma (default 9: the ends are 1e-18 of the peak).
    """
    sigma = _check_pos("sigma_ps", sigma_ps)
    model = {"name": "gaussian", "sigma_ps": sigma}
    half = float(span_sigmas) * sigma
    return _sampled_model(model, time_step_ps, half, half, -sigma, sigma, provenance)


def _tail_span(sigma, frac, tau):
    # The tail falls to ~1e-15 of the peak: f exp(-x / tau) / tau relative to 1 / (sigma sqrt(2 pi)).
    if frac <= 0:
        return 9.0 * sigma
    return 9.0 * sigma + tau * max(0.0, math.log(frac * sigma * _SQRT_2PI / tau * 1e15))


def tailed_response(sigma_ps: float, tail_fraction: float, tail_tau_ps: float, *, time_step_ps: float,
                    provenance: dict | None = None) -> InstrumentResponse:
    """A Gaussian with an exponential diffusion tail (photomultiplier, SPAD, lidar pulse).

    c(t) = (1 - f) N(t'; sigma) + f EMG(t'; sigma, tau),  t' = t + offset,

    where EMG = N * [exp(-t/tau) u(t) / tau] is the exponentially modified Gaussian (the
    Gaussian convolved with the unit-area exponential tail), evaluated in the stable erfcx
    form of :func:`core.model.sss_kernel`.  ``offset`` puts the peak at t = 0.

    Parameters
    ----------
    sigma_ps : float
        Width of the Gaussian core, ps.
    tail_fraction : float
        Fraction f of the area in the tail, 0 <= f < 1.
    tail_tau_ps : float
        Decay time of the tail, ps (> 0).
    time_step_ps : float
        Sample spacing, ps.
    """
    sigma = _check_pos("sigma_ps", sigma_ps)
    tau = _check_pos("tail_tau_ps", tail_tau_ps)
    frac = float(tail_fraction)
    if not (0.0 <= frac < 1.0):
        raise ResponseError(f"tail_fraction must be in [0, 1), got {tail_fraction!r}")
    model = {"name": "tailed", "sigma_ps": sigma, "tail_fraction": frac, "tail_tau_ps": tau}
    return _sampled_model(model, time_step_ps, 9.0 * sigma, _tail_span(sigma, frac, tau), -sigma,
                          3.0 * sigma + 2.0 * tau, provenance)


def afterpulse_response(sigma_ps: float, afterpulse_fraction: float, afterpulse_delay_ps: float, *,
                        time_step_ps: float, tail_fraction: float = 0.0, tail_tau_ps: float | None = None,
                        provenance: dict | None = None) -> InstrumentResponse:
    """A main peak with a small delayed copy of itself (an afterpulse).

    c(t) = [b(t') + r b(t' - delta)] / (1 + r), b the Gaussian (or the tailed response with
    ``tail_fraction`` and ``tail_tau_ps``), peak of the whole at t = 0.

    Parameters
    ----------
    sigma_ps : float
        Width of the main peak, ps.
    afterpulse_fraction : float
        Area r of the copy relative to the main peak, 0 < r < 1.
    afterpulse_delay_ps : float
        Delay delta of the copy, ps (> 0).
    time_step_ps : float
    tail_fraction, tail_tau_ps : float, optional
        A diffusion tail on both peaks (see :func:`tailed_response`).
    """
    sigma = _check_pos("sigma_ps", sigma_ps)
    delta = _check_pos("afterpulse_delay_ps", afterpulse_delay_ps)
    r = float(afterpulse_fraction)
    if not (0.0 < r < 1.0):
        raise ResponseError(f"afterpulse_fraction must be in (0, 1), got {afterpulse_fraction!r}")
    frac = float(tail_fraction)
    if not (0.0 <= frac < 1.0):
        raise ResponseError(f"tail_fraction must be in [0, 1), got {tail_fraction!r}")
    tau = _check_pos("tail_tau_ps", tail_tau_ps) if frac > 0 else None
    model = {"name": "afterpulse", "sigma_ps": sigma, "afterpulse_fraction": r, "afterpulse_delay_ps": delta,
             "tail_fraction": frac, "tail_tau_ps": tau}
    after = delta + _tail_span(sigma, frac, tau or 1.0)
    return _sampled_model(model, time_step_ps, 9.0 * sigma, after, -sigma,
                          3.0 * sigma + (2.0 * tau if tau else 0.0), provenance)
