"""Compiled choice of each pixel's best response atom from its correlations (the detection's pick).

:func:`decomposition.response.detect._pick` scores every atom of a
:class:`~decomposition.response.dictionary.ResponseDictionary` (kernel a at whole-bin shift s)
for a block of pixels by the decrease of the residual sum of squares it buys,
c^2 / ||atom||^2 with c the atom's correlation with the pixel's residual, among the atoms
that are allowed: positive amplitude c / ||atom||^2 no larger than ``amp_max``, inside the
window (norm > 0), of a family the pixel may still take (shifted copies up to
``n_shift_max``, one sss where ``allow_sss``), and for shifted kernels not within ``tol_ps``
of a shifted atom the pixel already has.  As block arrays this builds and masks several
(pixels, kernels, shifts) temporaries; here one compiled pass per pixel keeps the running
best (the first of equal gains in kernel-major order, as ``argmax`` of the flattened block).
"""
from __future__ import annotations

import numpy as np

from ..constants import FAM_GAUSS, FAM_SSS
from .jit import njit

__all__ = ["pick_atoms"]


def pick_atoms(c, gather, norm2, shifted, grid_ps, fam, delay, n_shift_max: int, allow_sss: bool, tol_ps: float,
               amp_max: float):
    """Best allowed atom per pixel.

    Parameters
    ----------
    c : ndarray (P, A, N)        circular correlations of the residuals with kernel a
    gather : ndarray (S,) int    the entry of ``c``'s last axis that holds shift s
    norm2 : ndarray (A, S)       squared norms of the atoms inside the window
    shifted : ndarray (A,) bool  kernels of the shifted family (else sss)
    grid_ps : ndarray (A, S)     the atoms' delays, ps
    fam, delay : ndarray (P, K)  the pixels' slots (FAM_GAUSS slots' delays read)
    n_shift_max : int            shifted atoms a pixel may hold
    allow_sss : bool             an sss may be added (to a pixel without one)
    tol_ps : float               no shifted atom within this of a shifted slot
    amp_max : float              largest amplitude accepted

    Returns
    -------
    gain : ndarray (P,)          c^2 / norm2 of the best atom; -inf where none is allowed
    amp : ndarray (P,)           its amplitude c / norm2 (0 where none)
    kernel, shift : ndarray (P,) int64  its indices (0 where none)
    """
    c = np.ascontiguousarray(c, np.float64)
    P = c.shape[0]
    gain = np.empty(P)
    amp = np.empty(P)
    a_idx = np.zeros(P, np.int64)
    s_idx = np.zeros(P, np.int64)
    _pick_pixels(c, np.ascontiguousarray(gather, np.int64), np.ascontiguousarray(norm2, np.float64), np.ascontiguousarray(shifted, np.bool_),
                 np.ascontiguousarray(grid_ps, np.float64), np.ascontiguousarray(fam, np.int8),
                 np.ascontiguousarray(delay, np.float64), int(n_shift_max), bool(allow_sss), float(tol_ps),
                 float(amp_max), gain, amp, a_idx, s_idx)
    return gain, amp, a_idx, s_idx


@njit
def _pick_pixels(c, gather, norm2, shifted, grid, fam, delay, n_shift_max, allow_sss, tol, amp_max, gain, amp, a_idx, s_idx):
    P, A = c.shape[0], c.shape[1]
    S = gather.size
    K = fam.shape[1]
    for p in range(P):
        n_sh = 0
        has_s = False
        for k in range(K):
            if fam[p, k] == FAM_GAUSS:
                n_sh += 1
            elif fam[p, k] == FAM_SSS:
                has_s = True
        best = -np.inf
        best_amp = 0.0
        ba = 0
        bs = 0
        for a in range(A):
            if shifted[a]:
                if n_sh >= n_shift_max:
                    continue
            elif has_s or not allow_sss:
                continue
            for s in range(S):
                n2 = norm2[a, s]
                cv = c[p, a, gather[s]]
                if not (n2 > 0.0 and cv > 0.0):
                    continue
                am = cv / n2
                if not (am <= amp_max):
                    continue
                g = cv * am
                if not (g > best):
                    continue
                if shifted[a]:
                    near = False
                    for k in range(K):
                        if fam[p, k] == FAM_GAUSS and abs(grid[a, s] - delay[p, k]) < tol:
                            near = True
                    if near:
                        continue
                best = g
                best_amp = am
                ba = a
                bs = s
        gain[p] = best
        amp[p] = best_amp
        a_idx[p] = ba
        s_idx[p] = bs
