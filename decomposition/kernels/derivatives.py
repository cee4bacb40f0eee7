"""Kernel values with their analytic parameter derivatives, batched (for refinement and Fisher information).

The value forms are those of the forward model (:func:`core.model.sss_kernel`, the
reference; :func:`decomposition.kernels.jit.sss_value` is its compiled twin): the same stable
branches in u, so nothing overflows for any alpha sigma.  This evaluation carries the
derivatives along, sharing g and the tail exponential between value and derivatives, and
skips the special functions where erfc(u) is exactly 2 in float64; its values agree with the
reference to rounding (tests check 1e-13 relative), and refinement results depend on its
exact arithmetic, so it is kept as it is rather than rebuilt on the value-only form.

Analytic derivatives (t relative to the component's delay, s = sigma, a = alpha)
-------------------------------------------------------------------------------
Gaussian g = exp(-t^2 / (2 s^2)):

    dg/d delay = g t / s^2,      dg/ds = g t^2 / s^3.

sss kernel h = integral_0^inf exp(-a tau) g(t - tau) d tau (the closed form in
model.py).  Differentiating under the integral, or the closed form, gives
expressions in h and g alone, both of which model.py evaluates without
overflow for any a*s:

    dh/dt       = g - a h                       (so dh/d delay = a h - g)
    dh/da       = (a s^2 - t) h - s^2 g
    dh/ds       = h (1/s + a^2 s) - g (a s + t/s)

(for dh/da: d/da of a^2 s^2 / 2 - a t is a s^2 - t, and d erfc(u)/da with
u = (a s^2 - t)/(s sqrt 2) contributes -s^2 exp(a^2 s^2/2 - a t - u^2) = -s^2 g).
The cancellation between the two terms for large a*s costs at most about
eps * (a s)^2 relative to the size of the derivative column, far below what
the fit needs; tests check all of them against finite differences.
"""
from __future__ import annotations

import numpy as np
from scipy import special

from core.model import _GL_NODES, _GL_WEIGHTS

__all__ = ["kernel_derivatives"]

_SQRT_PI_2 = np.sqrt(np.pi / 2.0)
_SQRT_2 = np.sqrt(2.0)

# exp() of arguments below about -708 underflows through a slow path (10x);
# exp(-700) = 1e-304 is already zero for every purpose here.
_EXP_FLOOR = -700.0


def _gauss_point(t, s, deriv=True):
    z = t / s
    g = np.exp(np.maximum(-0.5 * z * z, _EXP_FLOOR))
    if not deriv:
        return (g,)
    gz = g * z
    return g, gz / s, gz * z / s


# erfc(u) rounds to exactly 2.0 for u <= -6 (erfc(6) = 2.2e-17 < half an ulp of 2).
_ERFC_IS_TWO = -6.0
# exp(-z^2/2) is below the exp floor for |z| > 37.5: the rising edge is zero there.
_Z_NEGLIGIBLE = 37.5


def _sss_point(t, s, a, deriv=True):
    """sss kernel and its derivatives (see module docstring) with the stable branches of model.py.

    u = (a s^2 - t) / (s sqrt 2);  u >= 0: h = c g erfcx(u);  u < 0: h = c exp(-a (t - a s^2/2)) erfc(u),
    c = s sqrt(pi/2).  The special functions are evaluated only where they are not
    exactly 2 (erfc, u > -6) or multiplied by an underflowed g (erfcx, t far before
    the onset), which is a few dozen samples per profile.
    """
    t, s, a = np.broadcast_arrays(np.asarray(t, np.float64), np.asarray(s, np.float64),
                                  np.asarray(a, np.float64))
    z = t / s
    q = a * s
    u = (q - z) * (1.0 / _SQRT_2)
    g = np.exp(np.maximum(-0.5 * z * z, _EXP_FLOOR))
    # Tail branch everywhere first; its exponent is negative wherever u < 0 (clamped elsewhere).
    e = np.exp(np.clip(q * (0.5 * q - z), _EXP_FLOOR, 0.0))
    h = 2.0 * e
    fix = np.nonzero((u > _ERFC_IS_TWO) & (z > -_Z_NEGLIGIBLE))
    uf = u[fix]
    pos = uf >= 0
    hf = np.empty_like(uf)
    hf[pos] = g[fix][pos] * special.erfcx(uf[pos])
    neg = ~pos
    hf[neg] = e[fix][neg] * special.erfc(uf[neg])
    h[u >= 0] = 0.0  # rising edge far before the onset (g underflowed); overwritten below where not
    h[fix] = hf
    h *= _SQRT_PI_2 * s
    if not deriv:
        return (h,)
    d_delay = a * h - g
    d_sigma = h * ((1.0 + q * q) / s) - g * (q + z)
    d_alpha = s * ((q - z) * h - s * g)
    return h, d_delay, d_sigma, d_alpha


def kernel_derivatives(t_rel_ps, sigma_ps, alpha_per_ps=None, *, time_bin_ps=None, derivatives=True):
    """Kernel values and analytic derivatives with respect to its parameters.

    Parameters
    ----------
    t_rel_ps : array_like
        Sample times minus the component's delay, in ps.
    sigma_ps : array_like
        Gaussian width in ps (> 0); broadcasts against ``t_rel_ps``.
    alpha_per_ps : array_like, optional
        sss attenuation in 1/ps (>= 0).  ``None`` selects the unit-peak Gaussian.
    time_bin_ps : float, optional
        If given, values and derivatives are averaged over a bin of this width
        (matches ``bin_integrated=True`` rendering in :mod:`core.model`).
    derivatives : bool
        ``False`` returns the 1-tuple ``(k,)`` only (cheaper).

    Returns
    -------
    tuple of ndarray, float64, broadcast shape of the inputs:
        ``(k, dk_ddelay, dk_dsigma)`` for the Gaussian and
        ``(k, dk_ddelay, dk_dsigma, dk_dalpha)`` for the sss kernel; the delay
        derivative is with respect to the component's delay (= -dk/dt), units
        1/ps for delay and sigma, ps for alpha.
    """
    t = np.asarray(t_rel_ps, np.float64)
    s = np.asarray(sigma_ps, np.float64)

    def point(tt):
        if alpha_per_ps is None:
            return _gauss_point(tt, s, derivatives)
        return _sss_point(tt, s, np.asarray(alpha_per_ps, np.float64), derivatives)

    if time_bin_ps is None:
        return point(t)
    acc = None
    for x, w in zip(_GL_NODES, _GL_WEIGHTS):
        vals = point(t + x * float(time_bin_ps))
        acc = [w * v for v in vals] if acc is None else [a + w * v for a, v in zip(acc, vals)]
    return tuple(acc)

