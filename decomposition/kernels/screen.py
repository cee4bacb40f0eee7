"""A start's misfit at its own shapes, compiled: the spatial neighbour starts' screen.

:func:`screened_rss` takes, for each pixel, a start's shapes (the slots' delays, widths and the
sss decay rate) and solves its amplitudes (and an offset where one is fitted) by weighted linear
least squares, without a sign constraint, returning the weighted residual sum of squares: the
screen of :func:`decomposition.image.spatial.neighbour_starts` that decides which starts are
worth a refit.  The atoms are the point-sampled unit-peak Gaussian and the sss kernel of
:func:`decomposition.kernels.jit.sss_value` (those of :func:`decomposition.model.varpro.design_rows`,
to rounding); a tiny ridge keeps collinear atoms solvable, as the refinement's does, and the
normal equations are solved by a Cholesky factor.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import SSS_SLOT
from .jit import njit, sss_value

__all__ = ["screened_rss"]

#: widths from its centre (or the sss onset) beyond which an atom is taken as zero: exp(-72)
_SUPPORT_WIDTHS = 12.0


@njit
def _cholesky_solve(a, b, n):
    """x with a x = b for a symmetric positive definite (n, n) ``a`` (overwritten by its Cholesky
    factor): a few atoms at most, so a plain loop, and no LAPACK to compile."""
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        d = math.sqrt(d) if d > 0.0 else 1e-150
        a[j, j] = d
        for i in range(j + 1, n):
            v = a[i, j]
            for k in range(j):
                v -= a[i, k] * a[j, k]
            a[i, j] = v / d
    x = b.copy()
    for i in range(n):                      # L y = b
        v = x[i]
        for k in range(i):
            v -= a[i, k] * x[k]
        x[i] = v / a[i, i]
    for i in range(n - 1, -1, -1):          # L^T x = y
        v = x[i]
        for k in range(i + 1, n):
            v -= a[k, i] * x[k]
        x[i] = v / a[i, i]
    return x


@njit
def screened_rss(values, weights, rows, held_bg, t, delay, sigma, alpha, present, fit_bg):
    """(n,) weighted RSS of each start's pixel's data at the start's shapes, amplitudes fitted.

    Parameters
    ----------
    values, weights : float64 (P, L)   every pixel's data and sample weights
    rows : int (n,)           the pixel of each start
    held_bg : float64 (n,)    an offset held (subtracted from the data; 0 where none)
    t : float64 (L,)          sample times, ps
    delay, sigma : float64 (n, K)   the slots' delays and widths, ps (slot SSS_SLOT the sss)
    alpha : float64 (n,)      the sss decay rate, 1/ps
    present : bool (n, K)     the slots the start has
    fit_bg : bool (n,)        an offset is fitted too
    """
    n = rows.size
    L = values.shape[1]
    K = delay.shape[1]
    out = np.empty(n)
    atoms = np.zeros((K + 1, L))
    y = np.empty(L)
    sw = np.empty(L)
    lo = np.zeros(K + 1, np.int64)          # each atom's support [lo, hi): zero outside
    hi = np.zeros(K + 1, np.int64)
    r = np.empty(L)
    for p in range(n):
        row = rows[p]
        for i in range(L):
            sw[i] = math.sqrt(max(weights[row, i], 0.0))
            v = values[row, i] - held_bg[p]
            y[i] = v * sw[i] if math.isfinite(v) else 0.0
        c = 0
        for k in range(K):
            if not present[p, k]:
                continue
            d, s = delay[p, k], sigma[p, k]
            # a Gaussian (or the sss's rising edge) is below 1e-31 of its peak 12 widths out
            a = 0
            while a < L and t[a] < d - _SUPPORT_WIDTHS * s:
                a += 1
            b = L
            if k != SSS_SLOT:
                while b > a and t[b - 1] > d + _SUPPORT_WIDTHS * s:
                    b -= 1
            for i in range(L):
                atoms[c, i] = 0.0
            for i in range(a, b):
                x = t[i] - d
                if k == SSS_SLOT:
                    v = sss_value(x, s, alpha[p])[0]
                else:
                    v = math.exp(max(-0.5 * (x / s) * (x / s), -700.0))     # the floor of kernels.derivatives
                atoms[c, i] = v * sw[i]
            lo[c], hi[c] = a, b
            c += 1
        if fit_bg[p]:
            for i in range(L):
                atoms[c, i] = sw[i]
            lo[c], hi[c] = 0, L
            c += 1
        rss = 0.0
        if c == 0:
            for i in range(L):
                rss += y[i] * y[i]
            out[p] = rss
            continue
        gram = np.zeros((c, c))
        rhs = np.zeros(c)
        for a in range(c):
            acc = 0.0
            for i in range(lo[a], hi[a]):
                acc += atoms[a, i] * y[i]
            rhs[a] = acc
            for b in range(a + 1):
                acc = 0.0
                for i in range(max(lo[a], lo[b]), min(hi[a], hi[b])):
                    acc += atoms[a, i] * atoms[b, i]
                gram[a, b] = acc
                gram[b, a] = acc
        top = 0.0
        for a in range(c):
            top = max(top, gram[a, a])
        for a in range(c):
            gram[a, a] += 1e-13 * top + 1e-300
        amp = _cholesky_solve(gram, rhs, c)
        for i in range(L):
            r[i] = y[i]
        for a in range(c):
            for i in range(lo[a], hi[a]):
                r[i] -= amp[a] * atoms[a, i]
        for i in range(L):
            rss += r[i] * r[i]
        out[p] = rss
    return out
