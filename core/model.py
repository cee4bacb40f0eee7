"""Forward model of a transient time profile (eqs. (1)-(3) of the ConvSCD paper).

A pixel's time profile is

    p(t) = sum_r a_r * g(t - t_r; sigma_r)            direct (r = 0) and inter-reflections
         + b * h(t - t_s; sigma_s, alpha)              subsurface scattering (sss)
         + n(t)

with the unit-peak Gaussian point-spread function

    g(t; sigma) = exp(-t**2 / (2 sigma**2))

and the sss kernel, the Gaussian convolved with a causal decaying exponential,

    h(t; sigma, alpha) = integral_0^inf exp(-alpha tau) g(t - tau; sigma) dtau
                       = sigma sqrt(pi/2) exp(alpha**2 sigma**2 / 2 - alpha t)
                         * erfc((alpha sigma**2 - t) / (sigma sqrt 2)).

The closed form overflows (exp of a large number times erfc of a large number)
when alpha*sigma is large or t is far before the onset.  With
u = (alpha sigma**2 - t) / (sigma sqrt 2) and erfc(u) = erfcx(u) exp(-u**2) the
exponents combine exactly into -t**2 / (2 sigma**2), so

    u >= 0:  h = sigma sqrt(pi/2) exp(-t**2 / (2 sigma**2)) erfcx(u)
    u <  0:  h = sigma sqrt(pi/2) exp(-alpha (t - alpha sigma**2 / 2)) erfc(u)

Both branches only ever exponentiate non-positive numbers and erfcx(u) <= 1 for
u >= 0, so nothing overflows for any alpha*sigma; the first branch keeps full
relative precision deep in the rising edge, where the naive form returns 0/0.

Time axis: bin ``i`` (0-based) is centred at ``t0_ps + i * time_bin_ps``.  The
paper samples at t = T, 2T, ..., LT, which is the default ``t0_ps = time_bin_ps``.

Parameters of the components travel as a dict of arrays with the same keys
everywhere in streaklab (ground truth, solver output, result stores):

    direct_delay_ps, direct_amplitude, direct_sigma_ps            shape (...,)
    sss_delay_ps, sss_amplitude, sss_alpha_per_ps, sss_sigma_ps   shape (...,)
    ir_delay_ps, ir_amplitude, ir_sigma_ps                        shape (..., R)
    background                                                    shape (...,), optional

NaN marks an absent component.  ``background`` is a constant offset per pixel, in the
units of the profiles (the dark level of TCSPC / SPAD / lidar data): the model adds it to
every bin.  It is optional -- a dict without it, or with NaN, has no background, exactly as
before the key existed -- and it is not one of :data:`PARAM_KEYS` (every parameter dict has
those; only decompositions asked for the background family carry this one,
:data:`BACKGROUND_KEY`).
"""

from __future__ import annotations

import numpy as np
from scipy import special

__all__ = [
    "PARAM_KEYS",
    "DIRECT_KEYS",
    "SSS_KEYS",
    "IR_KEYS",
    "BACKGROUND_KEY",
    "time_axis_ps",
    "gaussian_kernel",
    "sss_kernel",
    "render_components",
    "render_profile",
    "empty_params",
    "params_shape",
]

_SQRT_PI_2 = np.sqrt(np.pi / 2.0)
_SQRT_2 = np.sqrt(2.0)

DIRECT_KEYS = ("direct_delay_ps", "direct_amplitude", "direct_sigma_ps")
SSS_KEYS = ("sss_delay_ps", "sss_amplitude", "sss_alpha_per_ps", "sss_sigma_ps")
IR_KEYS = ("ir_delay_ps", "ir_amplitude", "ir_sigma_ps")
PARAM_KEYS = DIRECT_KEYS + SSS_KEYS + IR_KEYS
#: constant offset per pixel, shape (...,), units of the profiles (optional; NaN = none)
BACKGROUND_KEY = "background"

# Gauss-Legendre nodes on [-1/2, 1/2] for bin-integrated sampling.
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(16)
_GL_NODES = _GL_NODES / 2.0
_GL_WEIGHTS = _GL_WEIGHTS / 2.0


def _check_time_bin(time_bin_ps: float) -> float:
    time_bin_ps = float(time_bin_ps)
    if not np.isfinite(time_bin_ps) or time_bin_ps <= 0:
        raise ValueError(f"time_bin_ps must be a positive finite number, got {time_bin_ps!r}")
    return time_bin_ps


def time_axis_ps(n_bins: int, time_bin_ps: float = 2.0, t0_ps: float | None = None) -> np.ndarray:
    """Bin-centre times of a profile of ``n_bins`` samples.

    Parameters
    ----------
    n_bins : int
        Number of time bins L (> 0).
    time_bin_ps : float
        Bin width T in picoseconds (> 0).
    t0_ps : float, optional
        Time of the first bin in ps.  Defaults to ``time_bin_ps`` (the paper's
        t = T, 2T, ..., LT).

    Returns
    -------
    ndarray, shape (n_bins,), float64, picoseconds.
    """
    n_bins = int(n_bins)
    if n_bins <= 0:
        raise ValueError(f"n_bins must be positive, got {n_bins}")
    time_bin_ps = _check_time_bin(time_bin_ps)
    if t0_ps is None:
        t0_ps = time_bin_ps
    return float(t0_ps) + time_bin_ps * np.arange(n_bins, dtype=np.float64)


def _check_sigma(sigma_ps):
    sigma_ps = np.asarray(sigma_ps, dtype=np.float64)
    if np.any(~np.isfinite(sigma_ps)) or np.any(sigma_ps <= 0):
        raise ValueError("sigma_ps must be positive and finite")
    return sigma_ps


# exp() of arguments below about -708 produces subnormals through a slow path (about ten
# times slower); anything below this limit is rendered as an exact zero instead.
_EXP_FLOOR = -700.0


def _exp_neg(arg):
    """exp(arg) for arg <= 0, with exp(arg) := 0 below ``_EXP_FLOOR`` (< 1e-304 of the peak)."""
    out = np.exp(np.maximum(arg, _EXP_FLOOR))
    out[arg < _EXP_FLOOR] = 0.0
    return out


def _gaussian_point(t_ps, sigma_ps):
    return _exp_neg(-0.5 * np.square(np.asarray(t_ps / sigma_ps, dtype=np.float64)))


def _sss_point(t_ps, sigma_ps, alpha_per_ps):
    t_ps, sigma_ps, alpha_per_ps = np.broadcast_arrays(
        np.asarray(t_ps, np.float64), np.asarray(sigma_ps, np.float64), np.asarray(alpha_per_ps, np.float64)
    )
    u = (alpha_per_ps * sigma_ps * sigma_ps - t_ps) / (sigma_ps * _SQRT_2)
    out = np.empty(t_ps.shape, dtype=np.float64)
    pos = u >= 0
    # u >= 0: rising edge and onset; erfcx(u) in (0, 1], exp argument <= 0.
    out[pos] = _exp_neg(-0.5 * np.square(t_ps[pos] / sigma_ps[pos])) * special.erfcx(u[pos])
    neg = ~pos
    # u < 0: t > alpha sigma^2, so alpha (t - alpha sigma^2 / 2) > 0 and the exponent is negative.
    a, s, t = alpha_per_ps[neg], sigma_ps[neg], t_ps[neg]
    out[neg] = _exp_neg(-a * (t - 0.5 * a * s * s)) * special.erfc(u[neg])
    return _SQRT_PI_2 * sigma_ps * out


def _bin_integrate(fn, t_ps, time_bin_ps, *args):
    """Mean of ``fn`` over [t - T/2, t + T/2] by 16-point Gauss-Legendre quadrature."""
    t_ps = np.asarray(t_ps, dtype=np.float64)
    acc = 0.0
    for x, w in zip(_GL_NODES, _GL_WEIGHTS):
        acc = acc + w * fn(t_ps + x * time_bin_ps, *args)
    return acc


def gaussian_kernel(t_ps, sigma_ps, *, time_bin_ps: float | None = None):
    """Unit-peak Gaussian PSF g(t) = exp(-t^2 / (2 sigma^2)).

    Parameters
    ----------
    t_ps : array_like
        Times relative to the component's delay, in ps.
    sigma_ps : array_like
        PSF standard deviation in ps (> 0); broadcasts against ``t_ps``.
    time_bin_ps : float, optional
        If given, return the mean of g over a bin of this width centred on each
        time instead of the point sample (use when sigma is comparable to a bin).

    Returns
    -------
    ndarray, float64, broadcast shape of the inputs.
    """
    sigma_ps = _check_sigma(sigma_ps)
    if time_bin_ps is None:
        return _gaussian_point(np.asarray(t_ps, np.float64), sigma_ps)
    return _bin_integrate(_gaussian_point, t_ps, _check_time_bin(time_bin_ps), sigma_ps)


def sss_kernel(t_ps, sigma_ps, alpha_per_ps, *, time_bin_ps: float | None = None):
    """Subsurface-scattering kernel h = g * [exp(-alpha t) u(t)], overflow-free.

    Parameters
    ----------
    t_ps : array_like
        Times relative to the sss onset, in ps.
    sigma_ps : array_like
        Gaussian PSF standard deviation in ps (> 0).
    alpha_per_ps : array_like
        Attenuation coefficient in 1/ps (>= 0; alpha = 0 is the blurred step).
    time_bin_ps : float, optional
        Bin-integrate instead of point-sampling (see :func:`gaussian_kernel`).

    Returns
    -------
    ndarray, float64.  Its late-time tail is exp(-alpha t); its area is
    sigma sqrt(2 pi) / alpha.
    """
    sigma_ps = _check_sigma(sigma_ps)
    alpha_per_ps = np.asarray(alpha_per_ps, dtype=np.float64)
    if np.any(~np.isfinite(alpha_per_ps)) or np.any(alpha_per_ps < 0):
        raise ValueError("alpha_per_ps must be non-negative and finite")
    if time_bin_ps is None:
        return _sss_point(t_ps, sigma_ps, alpha_per_ps)
    return _bin_integrate(_sss_point, t_ps, _check_time_bin(time_bin_ps), sigma_ps, alpha_per_ps)


def empty_params(shape=(), n_ir: int = 0) -> dict[str, np.ndarray]:
    """A parameter dict with every component absent (all NaN)."""
    shape = tuple(shape)
    out = {k: np.full(shape, np.nan) for k in DIRECT_KEYS + SSS_KEYS}
    out.update({k: np.full(shape + (int(n_ir),), np.nan) for k in IR_KEYS})
    return out


def _render_family(t, delay, amplitude, sigma, alpha=None, time_bin_ps=None):
    """Render one component per leading index; NaN parameters render as zeros."""
    delay = np.asarray(delay, np.float64)[..., None]
    amplitude = np.asarray(amplitude, np.float64)[..., None]
    sigma = np.asarray(sigma, np.float64)[..., None]
    present = np.isfinite(delay) & np.isfinite(amplitude) & np.isfinite(sigma) & (sigma > 0)
    if alpha is not None:
        alpha = np.asarray(alpha, np.float64)[..., None]
        present &= np.isfinite(alpha) & (alpha >= 0)
    shape = np.broadcast_shapes(delay.shape[:-1], amplitude.shape[:-1]) + (t.size,)
    out = np.zeros(shape, dtype=np.float64)
    pres = np.broadcast_to(present, shape[:-1] + (1,))[..., 0]
    if not pres.any():
        return out
    tt = t - np.broadcast_to(delay, shape[:-1] + (1,))[pres]
    s = np.broadcast_to(sigma, shape[:-1] + (1,))[pres]
    a = np.broadcast_to(amplitude, shape[:-1] + (1,))[pres]
    if alpha is None:
        k = gaussian_kernel(tt, s, time_bin_ps=time_bin_ps)
    else:
        al = np.broadcast_to(alpha, shape[:-1] + (1,))[pres]
        k = sss_kernel(tt, s, al, time_bin_ps=time_bin_ps)
    out[pres] = a * k
    return out


def render_components(params: dict, n_bins: int, time_bin_ps: float = 2.0, t0_ps: float | None = None,
                      *, bin_integrated: bool = False, irf=None) -> dict[str, np.ndarray]:
    """Render each component class of a parameter dict on the time axis.

    Parameters
    ----------
    params : dict of ndarray
        Keys as in the module docstring; any family may be missing from the
        dict (treated as absent).  NaN entries render as zero profiles.
    n_bins, time_bin_ps, t0_ps
        Time axis (see :func:`time_axis_ps`).
    bin_integrated : bool
        Average each kernel over its bin instead of point-sampling it.
    irf : core.irf.InstrumentResponse, optional
        Render with this instrument response instead of the Gaussian PSF
        (:func:`core.irf_components.render_components_response`; the ``*_sigma_ps`` keys are
        then unused).  Not combinable with ``bin_integrated``.

    Returns
    -------
    dict with ``direct`` (..., L), ``sss`` (..., L), ``interreflections`` (..., R, L), and
    ``background`` (..., L) (the constant offset on every bin; 0 where NaN) only when
    ``params`` has the :data:`BACKGROUND_KEY` key.
    """
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    if irf is not None:
        if bin_integrated:
            raise ValueError("bin_integrated rendering is for the Gaussian PSF; a response is point-sampled")
        from .irf_components import render_components_response
        return _with_background(render_components_response(params, t, irf), params, t)
    tb = _check_time_bin(time_bin_ps) if bin_integrated else None
    shape = params_shape(params)

    def fam(keys, alpha_key=None):
        if keys[0] not in params:
            return np.zeros(shape + (t.size,))
        alpha = params[alpha_key] if alpha_key else None
        return _render_family(t, params[keys[0]], params[keys[1]], params[keys[2]], alpha, tb)

    direct = fam(DIRECT_KEYS)
    sss = fam(("sss_delay_ps", "sss_amplitude", "sss_sigma_ps"), "sss_alpha_per_ps")
    if "ir_delay_ps" in params:
        ir = _render_family(t, params["ir_delay_ps"], params["ir_amplitude"], params["ir_sigma_ps"], None, tb)
    else:
        ir = np.zeros(shape + (0, t.size))
    return _with_background({"direct": direct, "sss": sss, "interreflections": ir}, params, t)


def params_shape(params: dict) -> tuple:
    """The pixels' shape (...,) of a parameter dict, from its first delay key."""
    shape = None
    for key in ("direct_delay_ps", "sss_delay_ps"):
        if key in params:
            shape = np.shape(params[key])
            break
    if shape is None and "ir_delay_ps" in params:
        shape = np.shape(params["ir_delay_ps"])[:-1]
    if shape is None:
        raise ValueError("params holds no component delays")
    return shape


def _with_background(out: dict, params: dict, t: np.ndarray) -> dict:
    """``out`` with the rendered ``background`` (..., L) where ``params`` has the key."""
    if BACKGROUND_KEY in params:
        shape = out["direct"].shape[:-1]
        b = np.asarray(params[BACKGROUND_KEY], np.float64)
        if b.shape != shape:
            raise ValueError(f"params[{BACKGROUND_KEY!r}] has shape {b.shape}, expected {shape}")
        out["background"] = np.broadcast_to(np.where(np.isfinite(b), b, 0.0)[..., None], shape + (t.size,)).copy()
    return out


def render_profile(params: dict, n_bins: int, time_bin_ps: float = 2.0, t0_ps: float | None = None,
                   *, bin_integrated: bool = False, irf=None) -> np.ndarray:
    """Clean (noise-free) profile: the sum of all rendered components and the background
    (if ``params`` has one), shape (..., L) (``irf``: an instrument response instead of the
    Gaussian, see :func:`render_components`)."""
    c = render_components(params, n_bins, time_bin_ps, t0_ps, bin_integrated=bin_integrated, irf=irf)
    total = c["direct"] + c["sss"] + c["interreflections"].sum(axis=-2)
    if "background" in c:
        total = total + c["background"]
    return total
