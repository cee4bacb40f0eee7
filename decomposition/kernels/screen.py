"""A start's misfit at its own shapes, compiled: the spatial neighbour starts' screen.

:func:`screened_rss` takes, for each pixel, a start's shapes (the slots' delays, widths and the
sss decay rate) and solves its amplitudes (and an offset where one is fitted) by weighted linear
least squares, without a sign constraint, returning the weighted residual sum of squares: the
screen of :func:`decomposition.image.spatial.neighbour_starts` that decides which starts are
worth a refit.  The atoms are the point-sampled unit-peak Gaussian and the sss kernel on their
supports, or a measured response's table atoms, as the compiled refine evaluates them (:func:`decomposition.kernels.projected.atom_rows`;
those of :func:`decomposition.model.varpro.design_rows`, to rounding); a tiny ridge keeps collinear atoms solvable, as the refinement's does, and the
normal equations are solved by a Cholesky factor.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import SSS_SLOT
from .jit import njit
from .projected import atom_rows, atom_scratch, row_dot, uniform_step

__all__ = ["screened_rss"]


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
def screened_rss(values, weights, rows, held_bg, t, delay, sigma, alpha, present, fit_bg, inst):
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
    inst : tuple              the atoms (:func:`decomposition.kernels.projected.instrument`): the
                              Gaussian PSF's, or a response's table atoms (``sigma`` unused)

    Starts of one pixel that follow one another share its weighted data (the caller may order
    them by pixel).
    """
    n = rows.size
    L = values.shape[1]
    K = delay.shape[1]
    out = np.empty(n)
    increasing = L >= 2
    for i in range(1, L):
        if not t[i] > t[i - 1]:
            increasing = False
    step_t = uniform_step(t, increasing)
    # rows 0..K-1 the slots' atoms, K the offset, K + 1 the weighted data
    m = np.zeros((K + 2, L))
    sw = np.empty(L)
    lo = np.zeros(K + 2, np.int64)          # each row's support [lo, hi): zero outside
    hi = np.zeros(K + 2, np.int64)
    use = np.zeros(K + 1, np.int64)
    r = np.empty(L)
    lo[K + 1], hi[K + 1] = 0, L
    last_row = -1
    last_bg = 0.0
    scratch = atom_scratch(inst)
    for p in range(n):
        row = rows[p]
        if row != last_row or held_bg[p] != last_bg:
            for i in range(L):
                sw[i] = math.sqrt(max(weights[row, i], 0.0))
                v = values[row, i] - held_bg[p]
                m[K + 1, i] = v * sw[i] if math.isfinite(v) else 0.0
            last_row, last_bg = row, held_bg[p]
        c = 0
        for k in range(K):
            if not present[p, k]:
                continue
            sss = k == SSS_SLOT
            j0, j1 = atom_rows(t, m, K, k, sss, delay[p, k], sigma[p, k], alpha[p], inst, sw, True, False, increasing,
                               step_t, scratch)
            lo[k], hi[k] = j0, j1
            use[c] = k
            c += 1
        if fit_bg[p]:
            for i in range(L):
                m[K, i] = sw[i]
            lo[K], hi[K] = 0, L
            use[c] = K
            c += 1
        if c == 0:
            out[p] = row_dot(m, K + 1, K + 1, 0, L)
            continue
        gram = np.zeros((c, c))
        rhs = np.zeros(c)
        for x in range(c):
            a = use[x]
            rhs[x] = row_dot(m, a, K + 1, lo[a], hi[a])
            for z in range(x + 1):
                b = use[z]
                acc = row_dot(m, a, b, max(lo[a], lo[b]), min(hi[a], hi[b]))
                gram[x, z] = acc
                gram[z, x] = acc
        top = 0.0
        for x in range(c):
            top = max(top, gram[x, x])
        for x in range(c):
            gram[x, x] += 1e-13 * top + 1e-300
        amp = _cholesky_solve(gram, rhs, c)
        for i in range(L):
            r[i] = m[K + 1, i]
        for x in range(c):
            a = use[x]
            for i in range(lo[a], hi[a]):
                r[i] -= amp[x] * m[a, i]
        rss = 0.0
        for i in range(L):
            rss += r[i] * r[i]
        out[p] = rss
    return out
