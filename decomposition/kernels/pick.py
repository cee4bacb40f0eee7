"""Gauss-Southwell selection of each pixel's next coordinate, compiled (ConvSCD step 1).

Given the correlations ``c`` of a pixel's residual with every atom at every shift and the
atoms' (window-truncated) squared norms ``n``, a zero coefficient's one-dimensional problem

    (n/2) (z - u)^2 + mu log(1 + z/eps),   u = c/n,  z >= 0

has the closed-form minimiser of :func:`closed_form`.  :func:`select` picks per pixel

- Gauss-Southwell-q (default): the coordinate with the largest exact objective decrease among
  the ``TOP_K`` best by the unpenalised decrease c^2/n (the ranking barely differs and the
  exact decrease keeps the descent monotone);
- Gauss-Southwell-r (rows with ``by_size``): the first coordinate, in order of decreasing
  coefficient u, among the ``TOP_K`` largest that decreases the objective, restricted to
  ``eligible`` coordinates (atoms mostly outside the window or on excluded samples have tiny
  norms that make any coefficient possible).

One pass per pixel over its (atoms x shifts) coordinates keeps the ``TOP_K`` best keys (ties
go to the lower flat index); nothing of the block's size is allocated.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import AMP_MAX
from .jit import njit

__all__ = ["closed_form", "select", "TOP_K"]

TOP_K = 3


@njit
def _closed_form1(u, n, mu, eps):
    if not (n > 0.0 and u > 0.0):
        return 0.0, 0.0
    disc = (u + eps) ** 2 - 4.0 * mu / n
    if not disc >= 0.0:
        return 0.0, 0.0
    z = 0.5 * ((u - eps) + math.sqrt(disc))
    if not z > 0.0:
        return 0.0, 0.0
    dec = 0.5 * n * (u * u - (z - u) ** 2) - mu * math.log1p(z / eps)
    if not (math.isfinite(dec) and dec > 0.0):    # a positive stationary point may lose to z = 0
        return 0.0, 0.0
    return z, dec


def closed_form(u, n, mu, eps):
    """Minimiser on z >= 0 of (n/2)(z-u)^2 + mu log(1 + z/eps) and its decrease vs z = 0.

    Element-wise over broadcast arrays; (0, 0) where z = 0 is the minimiser.
    """
    u, n, mu, eps = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (u, n, mu, eps)))
    z = np.zeros(u.shape)
    dec = np.zeros(u.shape)
    _closed_form_many(u.ravel(), n.ravel(), mu.ravel(), eps.ravel(), z.reshape(-1), dec.reshape(-1))
    return z, dec


@njit
def _closed_form_many(u, n, mu, eps, z, dec):
    for i in range(u.size):
        z[i], dec[i] = _closed_form1(u[i], n[i], mu[i], eps[i])


@njit
def _select_rows(c, n2, mu, eps, allow, by_size, eligible, use_eligible, best, zb, db):
    P, A, S = c.shape
    shared_norm = n2.shape[0] == 1
    kv = np.empty(TOP_K)
    kj = np.empty(TOP_K, np.int64)
    for i in range(P):
        ni = 0 if shared_norm else i
        by_coef = by_size[i]
        m = 0
        for a in range(A):
            for s in range(S):
                if not allow[i, a, s]:
                    continue
                if by_coef and use_eligible and not eligible[i, a, s]:
                    continue
                nn = n2[ni, a, s]
                u = c[i, a, s] / nn if nn > 0.0 else 0.0
                if not (u > 0.0 and u <= AMP_MAX):
                    continue
                key = u if by_coef else c[i, a, s] * u
                # insert into the descending top-K list (a later equal key ranks after)
                if m < TOP_K:
                    pos = m
                    m += 1
                elif key > kv[TOP_K - 1]:
                    pos = TOP_K - 1
                else:
                    continue
                while pos > 0 and kv[pos - 1] < key:
                    kv[pos] = kv[pos - 1]
                    kj[pos] = kj[pos - 1]
                    pos -= 1
                kv[pos] = key
                kj[pos] = a * S + s
        best[i] = 0
        zb[i] = 0.0
        db[i] = 0.0
        for r in range(m):
            j = kj[r]
            a = j // S
            s = j - a * S
            nn = n2[ni, a, s]
            z, dec = _closed_form1(c[i, a, s] / nn, nn, mu[i], eps[i])
            if not z <= AMP_MAX:
                dec = 0.0
            if by_coef:
                if dec > 0.0:                # first decreasing coordinate in coefficient order
                    best[i], zb[i], db[i] = j, z, dec
                    break
            elif dec > db[i]:                # best exact decrease among the top candidates
                best[i], zb[i], db[i] = j, z, dec


def select(c, n2, mu, eps, allow, by_size=None, eligible=None):
    """Per-pixel best coordinate of correlations ``c`` (n, A, S) with squared norms ``n2``.

    Parameters
    ----------
    c : ndarray (n, A, S)
        Correlations of each pixel's residual with atom a at shift s.
    n2 : ndarray (n, A, S) or (1, A, S)
        Squared norms of the atoms as seen by each pixel (or shared).
    mu, eps : ndarray (n,)
        Penalty weight and scale.
    allow : bool array broadcastable to (n, A, S)
        Coordinates a pixel may take.
    by_size : bool ndarray (n,), optional
        Rows that select by coefficient (Gauss-Southwell-r) instead of by decrease.
    eligible : bool array broadcastable to (n, A, S), optional
        For ``by_size`` rows: the coordinates that may be taken.

    Returns
    -------
    best : ndarray (n,) int64       flat index a * S + s (0 where nothing decreases F)
    z : ndarray (n,)                coefficient of the pick (0 where nothing decreases F)
    dec : ndarray (n,)              objective decrease of the pick (0 where nothing does)
    """
    n = c.shape[0]
    shape = c.shape
    # writable C-ordered copies (a few kB): one compiled signature, whether the masks came
    # whole or broadcast (a broadcast view is typed apart, and was compiled a second time)
    al = np.array(np.broadcast_to(np.asarray(allow, bool), shape), order="C")
    el = np.array(np.broadcast_to(np.asarray(True if eligible is None else eligible, bool), shape), order="C")
    bs = np.zeros(n, bool) if by_size is None else np.asarray(by_size, bool)
    best = np.zeros(n, np.int64)
    zb = np.zeros(n)
    db = np.zeros(n)
    if n:
        _select_rows(np.asarray(c, np.float64), np.asarray(n2, np.float64), np.asarray(mu, np.float64),
                     np.asarray(eps, np.float64), al, bs, el, eligible is not None, best, zb, db)
    return best, zb, db
