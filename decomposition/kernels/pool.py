"""Neighbourhood sums aligned on the direct, compiled: the pooled-echo search's one pass.

:func:`aligned_sums` adds, for every pixel of an image, its ``window`` x ``window`` neighbours'
per-sample fields shifted in time by the whole number of bins nearest to the difference of the
two pixels' direct delays (:func:`decomposition.image.pooled.aligned_neighbours` does the same
one offset at a time in NumPy; the sums here are taken in the same order, offset by offset, so
they are the same numbers).
"""
from __future__ import annotations

import math

import numpy as np

from .jit import njit

__all__ = ["aligned_sums"]


@njit
def aligned_sums(resid, model, near, amp, delay_ps, time_bin_ps, window):
    """Aligned neighbourhood sums over the offsets (dy, dx) in row order, the centre included.

    Parameters
    ----------
    resid, model : float64 (Y, X, L)   per-sample fields summed
    near : bool (Y, X, L)              per-sample flags OR-ed
    amp : float64 (Y, X)               a per-pixel field summed
    delay_ps : float64 (Y, X)          direct delays (NaN: no direct, neither neighbour nor centre)
    time_bin_ps : float
    window : int                       neighbourhood side (odd)

    Returns
    -------
    (pooled_resid, pooled_model, pooled_near, amp_sum, n_pool)
    """
    Y, X, L = resid.shape
    h = window // 2
    pooled = np.zeros((Y, X, L))
    pooled_model = np.zeros((Y, X, L))
    pooled_near = np.zeros((Y, X, L), np.bool_)
    amp_sum = np.zeros((Y, X))
    n_pool = np.zeros((Y, X), np.int64)
    for dy in range(-h, h + 1):
        for dx in range(-h, h + 1):
            for y in range(Y):
                ny = y + dy
                if ny < 0 or ny >= Y:
                    continue
                for x in range(X):
                    nx = x + dx
                    if nx < 0 or nx >= X:
                        continue
                    d, dn = delay_ps[y, x], delay_ps[ny, nx]
                    if not (math.isfinite(d) and math.isfinite(dn)):
                        continue
                    shift = int(np.rint((dn - d) / time_bin_ps))
                    amp_sum[y, x] += amp[ny, nx]
                    n_pool[y, x] += 1
                    lo, hi = max(0, -shift), min(L, L - shift)
                    for i in range(lo, hi):
                        pooled[y, x, i] += resid[ny, nx, i + shift]
                        pooled_model[y, x, i] += model[ny, nx, i + shift]
                        if near[ny, nx, i + shift]:
                            pooled_near[y, x, i] = True
    return pooled, pooled_model, pooled_near, amp_sum, n_pool
