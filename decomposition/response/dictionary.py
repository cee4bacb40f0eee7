"""A convolutional dictionary built from a measured instrument response (not yet used by the solver).

The Gaussian dictionary of :mod:`decomposition.methods.convscd` has one kernel per PSF width (and
per width and alpha for sss), placed at every whole-bin shift.  A measured response has no
width parameter; instead its kernels are the response at a few sub-bin *phases*, so that the
detection step already sees delays at a fraction of a bin:

    shifted family   k[m] = c((m - phi) T)                       one kernel per phase phi
    sss family       k[m] = s_alpha((m - phi) T)                  one per (alpha, phi)

The atom of kernel ``a`` at shift ``j`` (``j = -pre .. L - 1``) is ``k_a[i - j]`` on bin ``i``: a
component with delay ``t0_ps + (j + phi_a) * time_bin_ps`` (the response's reference instant,
its peak, at that time).  Kernels are rendered by :func:`core.irf.render_shifted` and
:func:`core.irf.render_sss` (exact sub-bin shifts, stable sss for any alpha), normalised to
unit peak.  :meth:`ResponseDictionary.correlate` correlates a block of profiles with every
atom at every shift by FFT, as the Gaussian dictionary does; ``norm2`` holds each atom's
squared norm truncated to the window, for normalised scores.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import fft as sp_fft

from core.irf import InstrumentResponse, render_shifted, render_sss

__all__ = ["FAM_SHIFTED", "FAM_SSS", "ResponseDictionary"]

FAM_SHIFTED = 0
FAM_SSS = 1


class ResponseDictionary:
    """Kernels of one response on one time axis, at every whole-bin shift.

    Parameters
    ----------
    irf : InstrumentResponse
    n_bins : int
        Profile length L.
    time_bin_ps, t0_ps : float
        Time axis: bin i at ``t0_ps + i * time_bin_ps``.
    phases : int
        Sub-bin phases per family (phi = 0, 1/phases, ...); 1 is whole-bin delays only.
    alphas_per_ps : sequence of float
        Attenuations of the sss kernels (empty: no sss family).
    shifted : bool
        Include the shifted family (direct and inter-reflections).
    pre_bins : int, optional
        Shifts before the window's first bin (atoms whose peak lies before it, their rest
        inside); default 1.5 response FWHM plus one bin.

    Attributes
    ----------
    fam : ndarray (A,) int8            FAM_SHIFTED or FAM_SSS
    phase : ndarray (A,)               sub-bin phase phi of each kernel, bins
    alpha_per_ps : ndarray (A,)        NaN for the shifted family
    shifts : ndarray (S,) int          whole-bin shifts j
    norm2 : ndarray (A, S)             squared norm of each atom inside the window
    n_fft : int
    """

    def __init__(self, irf: InstrumentResponse, n_bins: int, time_bin_ps: float, t0_ps: float, *,
                 phases: int = 4, alphas_per_ps=(), shifted: bool = True, pre_bins: int | None = None):
        L, T = int(n_bins), float(time_bin_ps)
        if L < 2 or not (math.isfinite(T) and T > 0):
            raise ValueError(f"need n_bins >= 2 and a positive time_bin_ps, got {n_bins}, {time_bin_ps}")
        phases = int(phases)
        if phases < 1:
            raise ValueError(f"phases must be >= 1, got {phases}")
        alphas = np.asarray(alphas_per_ps, dtype=np.float64).reshape(-1)
        if np.any(~np.isfinite(alphas)) or np.any(alphas < 0):
            raise ValueError("alphas_per_ps must be non-negative and finite")
        if not shifted and alphas.size == 0:
            raise ValueError("no component family selected")
        self.irf, self.n_bins, self.time_bin_ps, self.t0_ps = irf, L, T, float(t0_ps)
        self.pre = int(pre_bins) if pre_bins is not None else int(math.ceil(1.5 * irf.fwhm_ps() / T)) + 1
        phi = np.arange(phases) / phases
        fam, ph, al = [], [], []
        if shifted:
            fam += [FAM_SHIFTED] * phases
            ph += list(phi)
            al += [np.nan] * phases
        for a in alphas:
            fam += [FAM_SSS] * phases
            ph += list(phi)
            al += [a] * phases
        self.fam = np.array(fam, np.int8)
        self.phase = np.array(ph)
        self.alpha_per_ps = np.array(al)
        self.shifts = np.arange(-self.pre, L)
        # Kernel support in bins relative to the shift: the response's window, and for sss on to
        # the end of the profile from the earliest shift.
        lo = int(math.floor(irf.window_start_ps / T)) - 1
        hi_shift = int(math.ceil((irf.window_start_ps + irf.window_ps) / T)) + 1
        hi_sss = L + self.pre
        m_shift = np.arange(lo, hi_shift + 1)
        m_sss = np.arange(lo, max(hi_sss, hi_shift) + 1)
        kernels = []
        sh = self.fam == FAM_SHIFTED
        if sh.any():
            k = render_shifted(irf, m_shift * T, self.phase[sh] * T)                # (phases, M)
            kernels += [(m_shift, row) for row in k]
        ss = ~sh
        if ss.any():
            k = render_sss(irf, m_sss * T, self.phase[ss] * T, self.alpha_per_ps[ss])
            kernels += [(m_sss, row) for row in k]
        A, S = self.fam.size, self.shifts.size
        need = max(max(int(m[-1]) + L, L + self.pre - int(m[0])) for m, _ in kernels) + 1
        self.n_fft = N = sp_fft.next_fast_len(need, real=True)
        kp = np.zeros((A, N))
        self.norm2 = np.zeros((A, S))
        for a, (m, k) in enumerate(kernels):
            kp[a, m % N] = k
            c = np.concatenate([[0.0], np.cumsum(k * k)])
            # Atom at shift j covers bins i = j + m; inside the window: 0 <= j + m <= L - 1.
            first = np.clip(-self.shifts - m[0], 0, k.size)
            last = np.clip(L - 1 - self.shifts - m[0] + 1, 0, k.size)
            self.norm2[a] = c[last] - c[np.minimum(first, last)]
        self._kernels = kernels
        self.spec_conj = np.conj(sp_fft.rfft(kp, axis=-1))
        self.gather = self.shifts % N

    @property
    def n_atoms(self) -> int:
        return int(self.fam.size * self.shifts.size)

    def delay_ps(self, a, j) -> np.ndarray:
        """Delay (ps) of kernel ``a`` at shift ``j`` (broadcasting index arrays)."""
        return self.t0_ps + (np.asarray(j) + self.phase[a]) * self.time_bin_ps

    def atom(self, a: int, j: int) -> np.ndarray:
        """The atom of kernel ``a`` at shift ``j`` on the profile's bins, shape (L,)."""
        m, k = self._kernels[a]
        out = np.zeros(self.n_bins)
        i = j + m
        inside = (i >= 0) & (i < self.n_bins)
        out[i[inside]] = k[inside]
        return out

    def correlate(self, x: np.ndarray) -> np.ndarray:
        """Inner products of rows of ``x`` (P, L) with every atom at every shift, shape (P, A, S)."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.n_bins:
            raise ValueError(f"profiles must have shape (P, {self.n_bins}), got {x.shape}")
        X = sp_fft.rfft(x, n=self.n_fft, axis=-1)
        c = sp_fft.irfft(X[:, None, :] * self.spec_conj[None], n=self.n_fft, axis=-1)
        return np.take(c, self.gather, axis=-1)

    def best_atoms(self, x: np.ndarray):
        """Best-matching atom per profile by normalised correlation (matched filter).

        Returns
        -------
        kernel : (P,) int, shift : (P,) int, delay_ps : (P,), amplitude : (P,)
            amplitude = the least-squares scale of the unit-peak atom.
        """
        c = self.correlate(x)
        score = np.where(self.norm2 > 0, c * np.abs(c) / np.where(self.norm2 > 0, self.norm2, 1.0), -np.inf)
        flat = np.argmax(score.reshape(score.shape[0], -1), axis=1)
        a, s = np.unravel_index(flat, score.shape[1:])
        amp = c[np.arange(c.shape[0]), a, s] / self.norm2[a, s]
        return a, self.shifts[s], self.delay_ps(a, self.shifts[s]), amp
