"""Detection with a measured response: greedy sparse coding over a ResponseDictionary.

The response-path counterpart of :mod:`decomposition.stages.detect`.  For every block of live pixels,
atoms are added one at a time (orthogonal greedy pursuit with continuous relocation):

1. correlate every pixel's residual with every atom of the
   :class:`~decomposition.response.dictionary.ResponseDictionary` (the response at sub-bin phases,
   and for sss at a few alphas) of the families it may still take, by FFT on the block;
2. the best atom of each pixel (chosen in a compiled pass,
   :func:`decomposition.kernels.responsepick.pick_atoms`) is the one of largest decrease of
   the residual sum of squares, c^2 / ||atom||^2, among the positive ones (light is non-negative), the families
   still open (at most one sss; one shifted copy, or 1 + R with inter-reflections), and not
   within ``merge_tol_bins`` of a shifted atom the pixel already has;
3. it is kept only where the decrease pays for it under the paper's log-sum penalty:
   1/2 (decrease) > mu log(1 + a / eps), with mu = sparsity * s^2 and eps = eps_rel * s
   (s the pixel's noise); a pixel whose best atom does not pay stops;
4. all the kept atoms of the pixels that grew are refined together: delays and alpha by
   variable projection, amplitudes by linear least squares
   (:func:`decomposition.response.refine.fit_slots`, ``n_lm`` iterations).

Atoms whose amplitude ends non-positive are dropped at the end and the amplitudes re-solved.
Where the pursuit ends without an sss but with several shifted atoms, a second pursuit with
the sss as its second atom competes on the penalised objective (see :func:`detect_response`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

from ..constants import AMP_MAX, FAM_GAUSS, FAM_NONE, FAM_SSS
from ..kernels.responsepick import pick_atoms
from .dictionary import FAM_SHIFTED, ResponseDictionary
from ..options import SolverOptions
from ..stages.prepare import Samples
from .refine import fit_slots

__all__ = ["ResponseDetection", "detect_response", "response_dictionary", "RESPONSE_PHASES"]

#: sub-bin phases of the detection dictionary (delays found to a quarter bin before refinement)
RESPONSE_PHASES = 4
#: rows correlated at once by the pick (their spectra, rows x kernels x n_fft, stay cache-sized)
_PICK_ROWS = 32


@dataclass(frozen=True)
class ResponseDetection:
    """Atoms of the live pixels: ``state`` (n, K) slot arrays ``fam``, ``delay``, ``lalp``,
    ``amp`` (rows follow ``samples.live``), ``n_iter`` (n,) atoms tried, ``converged`` (n,)
    the pursuit stopped before ``max_components`` atoms, ``sss_start`` pixels that kept the
    sss-second start."""

    state: dict
    n_iter: np.ndarray
    converged: np.ndarray
    sss_start: int = 0


def response_dictionary(irf, samples: Samples, alphas_per_ps, components) -> ResponseDictionary:
    """The detection dictionary of ``irf`` on the samples' axis (families as ``components``)."""
    ax = samples.axis
    alphas = np.asarray(alphas_per_ps, np.float64) if "s" in components else ()
    return ResponseDictionary(irf, samples.n_bins, ax.time_bin_ps, ax.t0_ps, phases=RESPONSE_PHASES,
                              alphas_per_ps=alphas, shifted="d" in components)


def _pick(dic: ResponseDictionary, resid, fam, delay, n_shift_max, allow_sss, tol_ps):
    """Best atom per row: (gain, amplitude, kernel, shift index); gain -inf where none is allowed.

    Each row is correlated (by FFT, as :meth:`ResponseDictionary.correlate`) only with the
    kernels of the families it may still take, and the best of them chosen in a compiled pass
    (:func:`decomposition.kernels.responsepick.pick_atoms`); the shifted family first, so that
    of equal gains the earlier kernel wins, as with the argmax over all kernels."""
    n = resid.shape[0]
    gain, amp = np.full(n, -np.inf), np.zeros(n)
    a_idx, s_idx = np.zeros(n, np.int64), np.zeros(n, np.int64)
    shifted = dic.fam == FAM_SHIFTED
    want = {True: (fam == FAM_GAUSS).sum(axis=1) < n_shift_max,
            False: (~(fam == FAM_SSS).any(axis=1)) & bool(allow_sss)}
    X = None
    for is_sh in (True, False):
        rows = np.flatnonzero(want[is_sh])
        kern = np.flatnonzero(shifted == is_sh)
        if rows.size == 0 or kern.size == 0:
            continue
        if X is None:
            X = sp_fft.rfft(np.asarray(resid, np.float64), n=dic.n_fft, axis=-1)
        spec = dic.spec_conj[kern][None]
        grid = dic.delay_ps(kern[:, None], dic.shifts[None, :])                       # (A', S)
        for lo in range(0, rows.size, _PICK_ROWS):      # rows in groups: cache-sized spectra
            rr = rows[lo:lo + _PICK_ROWS]
            c = sp_fft.irfft(X[rr][:, None, :] * spec, n=dic.n_fft, axis=-1)
            g, a, ai, si = pick_atoms(c, dic.gather, dic.norm2[kern], shifted[kern], grid, fam[rr], delay[rr],
                                      n_shift_max, allow_sss, tol_ps, AMP_MAX)
            better = g > gain[rr]
            r = rr[better]
            gain[r], amp[r], a_idx[r], s_idx[r] = g[better], a[better], kern[ai[better]], si[better]
    return gain, amp, a_idx, s_idx


def _pursuit(dic, irf, t, y, sw, mu, eps, K, n_shift_max, allow_sss, tol_ps, n_lm, fit_kw, order):
    """Greedy pursuit on one block; ``order``: the family each of the first atoms must have
    ("shifted" or "sss"; free after them)."""
    n = y.shape[0]
    fam = np.zeros((n, K), np.int8)
    delay = np.zeros((n, K))
    lalp = np.zeros((n, K))
    amp = np.zeros((n, K))
    resid = y * sw
    cost = np.einsum("pl,pl->p", resid, resid)
    go = np.ones(n, bool)
    tried = np.zeros(n, np.int64)
    for k in range(K):
        g = np.flatnonzero(go)
        if g.size == 0:
            break
        want = order[k] if k < len(order) else None
        cap = 0 if want == "sss" else n_shift_max
        gain, a, a_idx, s_idx = _pick(dic, resid[g], fam[g], delay[g], cap, allow_sss and want != "shifted", tol_ps)
        tried[g] += 1
        keep = np.isfinite(gain) & (0.5 * gain > mu[g] * np.log1p(np.maximum(a, 0.0) / eps[g]))
        go[g[~keep]] = False
        g, a_idx, s_idx = g[keep], a_idx[keep], s_idx[keep]
        if g.size == 0:
            break
        is_sss = dic.fam[a_idx] != FAM_SHIFTED
        fam[g, k] = np.where(is_sss, FAM_SSS, FAM_GAUSS)
        delay[g, k] = dic.delay_ps(a_idx, dic.shifts[s_idx])
        lalp[g, k] = np.log(np.where(is_sss, dic.alpha_per_ps[a_idx], 1.0))
        f = fit_slots(irf, t, y[g], sw[g], fam[g], delay[g], lalp[g], n_iter=n_lm, **fit_kw)
        delay[g] = np.nan_to_num(f.delay)
        lalp[g] = np.nan_to_num(f.lalp)
        amp[g], resid[g], cost[g] = f.amp, f.resid, f.cost
    bad = (fam != FAM_NONE) & ~(amp > 0)
    if bad.any():
        fam[bad] = FAM_NONE
        r = np.flatnonzero(bad.any(axis=1))
        f = fit_slots(irf, t, y[r], sw[r], fam[r], delay[r], lalp[r], n_iter=0, **fit_kw)
        amp[r], cost[r] = f.amp, f.cost
    penalty = np.where(fam != FAM_NONE, mu[:, None] * np.log1p(np.maximum(amp, 0.0) / eps[:, None]), 0.0).sum(axis=1)
    return {"fam": fam, "delay": delay, "lalp": lalp, "amp": amp, "objective": 0.5 * cost + penalty,
            "tried": tried, "go": go}


def detect_response(samples: Samples, irf, dic: ResponseDictionary, opts: SolverOptions, components,
                    bounds: dict) -> ResponseDetection:
    """Greedy detection for every live pixel (blocks of ``opts.block_size``).

    The first atom is a shifted copy (every pixel of the model has a direct reflection; an
    sss atom picked first would take the direct's light too).  A greedy pursuit can explain
    an sss decay with a few shifted copies of the response after the direct; where it ends
    with no sss and more than one shifted atom, a second one whose second atom must be the
    sss is run, and each such pixel keeps the lower
    penalised objective 1/2 RSS + sum mu log(1 + a / eps).  ``info["response_sss_start"]``
    counts the pixels that kept it.

    ``bounds``: ``delay_ps`` and ``lalp`` (low, high) of the refinement.
    """
    live = samples.live
    n, L, K = live.size, samples.n_bins, opts.max_components
    st = {"fam": np.zeros((n, K), np.int8), "delay": np.full((n, K), np.nan),
          "lalp": np.full((n, K), np.nan), "amp": np.zeros((n, K))}
    n_iter = np.zeros(n, np.int64)
    conv = np.zeros(n, bool)
    n_shift_max = (1 + opts.max_reflections if "r" in components else 1) if "d" in components else 0
    allow_sss = "s" in components
    t = samples.axis.t0_ps + samples.axis.time_bin_ps * np.arange(L)
    tol_ps = opts.merge_tol_bins * samples.axis.time_bin_ps
    fit_kw = dict(lm_tol=opts.lm_tol, delay_bounds_ps=bounds["delay_ps"], lalp_bounds=bounds["lalp"],
                  sss_after_direct=opts.sss_after_direct)
    switched = 0
    for lo in range(0, n, opts.block_size):
        rows = live[lo:lo + opts.block_size]
        y = samples.profiles[rows]
        sw = samples.fit[rows].astype(np.float64)
        s = samples.noise_eff[rows]
        mu, eps = opts.sparsity * s * s, opts.eps_rel * s
        args = (dic, irf, t)
        rest = (K, n_shift_max, allow_sss, tol_ps, opts.n_lm, fit_kw)
        first = ("shifted",) if n_shift_max else ()
        best = _pursuit(*args, y, sw, mu, eps, *rest, first)
        doubt = np.flatnonzero(allow_sss & ~(best["fam"] == FAM_SSS).any(axis=1)
                               & ((best["fam"] == FAM_GAUSS).sum(axis=1) > 1)) if allow_sss and K > 1 else []
        if len(doubt):
            alt = _pursuit(*args, y[doubt], sw[doubt], mu[doubt], eps[doubt], *rest, ("shifted", "sss"))
            win = alt["objective"] < best["objective"][doubt]
            for key in best:
                best[key][doubt[win]] = alt[key][win]
            switched += int(win.sum())
        fam = best["fam"]
        sl = slice(lo, lo + rows.size)
        st["fam"][sl] = fam
        st["delay"][sl] = np.where(fam != FAM_NONE, best["delay"], np.nan)
        st["lalp"][sl] = np.where(fam == FAM_SSS, best["lalp"], np.nan)
        st["amp"][sl] = np.where(fam != FAM_NONE, best["amp"], 0.0)
        n_iter[sl] = best["tried"]
        conv[sl] = ~best["go"]
    return ResponseDetection(state=st, n_iter=n_iter, converged=conv, sss_start=switched)
