"""Compiled scalar kernels shared by the solver's per-pixel loops (numba, ``nopython`` mode).

The hot parts of ConvSCD -- refining a pixel's few atoms and correlating its residual with
kernels at its own PSF width -- do a little work on many short windows.  As array
expressions over a block of pixels they spend most of their time allocating, placing and
masking window-shaped temporaries; compiled loops over one pixel at a time do the same
arithmetic without them.  Everything here is scalar: callers loop over pixels and samples.

All functions are compiled on first use and cached on disk next to this file (numba's
``cache=True``), so later processes -- dask workers included -- load them instead of compiling
again.  ``nogil=True`` lets the threaded scheduler run them in parallel.

The forms are those of :mod:`core.model` (see its docstring): the sss kernel is
evaluated as g(x) erfcx(u) for u >= 0 and exp(-alpha (x - alpha sigma^2 / 2)) erfc(u) for
u < 0, so no exponential of a positive number is ever taken.
"""
from __future__ import annotations

import math

import numba

__all__ = ["njit", "erfcx", "sss_value"]

SQRT_PI_2 = math.sqrt(math.pi / 2.0)
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
_SQRT_2 = math.sqrt(2.0)
_ERFCX_SERIES_FROM = 10.0   # u at which the asymptotic series takes over from exp(u^2) erfc(u)


def njit(fn):
    """``numba.njit`` with the options every kernel of the solver uses.

    Compiled code is cached on disk (beside the source, else in the user's cache directory).
    Where numba finds no writable place for it, the kernel is compiled without a cache,
    once per process, instead of failing the import.
    """
    try:
        return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
    except RuntimeError:          # "cannot cache function ...: no locator available"
        return numba.njit(cache=False, nogil=True, error_model="numpy")(fn)


@njit
def erfcx(u):
    """Scaled complementary error function exp(u^2) erfc(u) for u >= 0 (float64).

    Below u = 10, exp(u^2) * erfc(u): erfc(u) >= 2e-45 there, far from underflow, and the
    rounding of u^2 costs at most ~1e-14 relative.  From u = 10 on, the asymptotic series
    1/(u sqrt(pi)) sum_n (-1)^n (2n-1)!! / (2u^2)^n (Abramowitz & Stegun 7.1.23) with 12
    terms: its next term is below 1e-15 relative.  Negative u are not used by the solver
    (its u < 0 branch uses erfc directly) and are evaluated as exp(u^2) erfc(u) as well.
    """
    if u < _ERFCX_SERIES_FROM:
        return math.exp(u * u) * math.erfc(u)
    v = 1.0 / (2.0 * u * u)
    term = 1.0
    acc = 1.0
    for n in range(1, 13):
        term *= -(2.0 * n - 1.0) * v
        acc += term
    return acc * _INV_SQRT_PI / u


@njit
def sss_value(x_ps, sigma_ps, alpha_per_ps):
    """sss kernel h(x) = (g * exp(-alpha t) u(t))(x) and the unit Gaussian g(x) at one time.

    ``x_ps`` is the time after the onset.  h = sqrt(pi/2) sigma g(x) erfcx(u) for
    u = (alpha sigma^2 - x) / (sigma sqrt 2) >= 0, and sqrt(pi/2) sigma
    exp(-alpha (x - alpha sigma^2 / 2)) erfc(u) otherwise (core.model).
    Returns (h, g).
    """
    g = math.exp(-0.5 * (x_ps / sigma_ps) ** 2)
    u = (alpha_per_ps * sigma_ps * sigma_ps - x_ps) / (sigma_ps * _SQRT_2)
    if u >= 0.0:
        h = g * erfcx(u)
    else:
        h = math.exp(-alpha_per_ps * (x_ps - 0.5 * alpha_per_ps * sigma_ps * sigma_ps)) * math.erfc(u)
    return SQRT_PI_2 * sigma_ps * h, g
