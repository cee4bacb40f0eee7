"""The Gauss-Southwell pick of ConvSCD: the best new coordinate of every pixel of a block.

For a zero coordinate with column norm n and correlation c the one-dimensional problem is
(n/2)(z - u)^2 + mu log(1 + z/eps), u = c/n; its exact minimiser and the objective decrease
are evaluated by the compiled selection (:func:`decomposition.kernels.pick.select`).  Correlations
come from the coarse dictionary by FFT for a pixel's first atom (:func:`score_coarse`), and
at the pixel's own PSF width from compiled direct correlations afterwards
(:func:`score_pixel`, :mod:`decomposition.kernels.pickcorr`).
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import DICT_SUPPORT_SIGMA, FAM_GAUSS, FAM_SSS
from .dictionary import Dictionary
from ..kernels.pick import select as _select
from ..kernels.pickcorr import PickWorkspace, pixel_correlations

__all__ = ["score_coarse", "score_pixel"]


def score_coarse(r, fit, weighted, dic: Dictionary, mu, eps, allow_g, allow_s, min_s, by_size=None):
    """Best coordinate of the coarse dictionary per pixel (Gauss-Southwell, largest decrease)."""
    # only the families some pixel may take are correlated (the first pick of the primary
    # start allows Gaussians only: 4 of the 13 default atoms)
    is_s = dic.fam == FAM_SSS
    atoms = np.flatnonzero(np.where(is_s, bool(allow_s.any()), bool(allow_g.any())))
    if atoms.size == 0:
        atoms = np.arange(dic.fam.size)
    norm2 = dic.norm2[atoms]
    is_s = is_s[atoms]
    c = dic.correlate(r, atoms=atoms)                      # (n, A', S)
    if weighted:
        n2 = dic.correlate(fit.astype(np.float64), squared=True, atoms=atoms)
        n2 = np.where(n2 > 1e-12 * norm2[None], n2, 0.0)
    else:
        n2 = norm2[None]
    allow = np.where(is_s[None, :], allow_s[:, None], allow_g[:, None])[..., None]
    delay = dic.t0_ps + dic.shifts * dic.time_bin_ps
    allow = allow & ~(is_s[None, :, None] & (delay[None, None, :] < min_s[:, None, None]))
    eligible = (dic.shifts >= 0)[None, None, :] & (n2 >= 0.5 * norm2[None])
    best, zb, db = _select(c, n2, mu, eps, allow, by_size, eligible)
    a_i, j_i = np.divmod(best, dic.shifts.size)
    a_i = atoms[a_i]
    fam = dic.fam[a_i]
    alpha = np.where(fam == FAM_SSS, dic.alpha_per_ps[a_i], 1.0)
    cand = {"fam": fam, "amp": zb / dic.peak[a_i], "pen": dic.peak[a_i].copy(),
            "delay": dic.t0_ps + dic.shifts[j_i] * dic.time_bin_ps,
            "lsig": np.log(dic.sigma_ps[a_i]), "lalp": np.where(fam == FAM_SSS, np.log(alpha), 0.0)}
    return cand, db


def score_pixel(r, fit, weighted, dic: Dictionary, sig, mu, eps, allow_g, allow_s, min_s, bound_factor,
                workspace: PickWorkspace | None = None):
    """Best coordinate per pixel among atoms at the pixel's own PSF width ``sig`` (n,).

    Atoms: the Gaussian and the sss kernel at each coarse alpha, all with the
    pixel's sigma, at every integer-bin shift; correlations and exact
    window-truncated norms come from compiled per-pixel FIR passes and one-pole
    recursions (:func:`decomposition.kernels.pickcorr.pixel_correlations`), written into
    ``workspace`` when one is given (the caller's: it is overwritten by the next call).
    """
    n = r.shape[0]
    T = dic.time_bin_ps
    pre = dic.pre
    # the coarse alphas: the dictionary's first sss sigma carries each of them once, in order
    alphas = dic.alpha_per_ps[dic.fam == FAM_SSS][:dic.grid.coarse_alpha]
    kf = [FAM_GAUSS] + [FAM_SSS] * alphas.size
    ka = np.concatenate([[np.nan], alphas])
    H = int(math.ceil(DICT_SUPPORT_SIGMA * float(sig.max()) / T)) + 1
    delay = dic.t0_ps + dic.shifts * T
    # only what each pixel may take is correlated: no sss kernel once it has its sss atom, no sss
    # onset before its direct
    c, n2, peak = pixel_correlations(r, sig, alphas, time_bin_ps=T, pre=pre, half_bins=H,
                                     w1=fit.astype(np.float64) if weighted else None,
                                     out=workspace,   # consumed by _select below
                                     need_gauss=allow_g, need_sss=allow_s,
                                     sss_from=np.searchsorted(delay, min_s, side="left"))
    if weighted:
        n2 = np.where(n2 > 1e-12, n2, 0.0)
    is_s = np.array(kf) == FAM_SSS
    allow = np.where(is_s[None, :], allow_s[:, None], allow_g[:, None])[..., None]
    allow = allow & ~(is_s[None, :, None] & (delay[None, None, :] < min_s[:, None, None]))
    best, zb, db = _select(c, n2, mu, eps, allow)
    a_i, j_i = np.divmod(best, dic.shifts.size)
    rows = np.arange(n)
    fam = np.array(kf, np.int8)[a_i]
    cand = {"fam": fam, "amp": zb / peak[rows, a_i], "pen": peak[rows, a_i],
            "delay": dic.t0_ps + dic.shifts[j_i] * T, "lsig": np.log(sig),
            "lalp": np.where(fam == FAM_SSS, np.log(np.where(np.isfinite(ka[a_i]), ka[a_i], 1.0)), 0.0)}
    return cand, db

