"""The coarse convolutional dictionary of ConvSCD (unit-peak kernels at every integer shift).

With the Gaussian PSF, k1: unit-peak Gaussians g(t; sigma) over the coarse sigma grid; k2: sss
kernels h(t; sigma, alpha) = g * exp(-alpha t) u(t) over the coarse (sigma, alpha) grid, scaled
to unit peak so that every coefficient is a peak height and one penalty treats both families
alike.  With a measured response (``response=``), k1 is the response itself and k2 the response
convolved with exp(-alpha t) u(t) at the coarse alphas: the instrument's one width.  Each atom
is used at every integer-bin shift from ``pre`` bins before the window start to the window end;
column norms are the norms of the atoms truncated to the window.
Correlations with every atom at every shift are one FFT pass (:meth:`Dictionary.correlate`).
"""
from __future__ import annotations

import math
import threading

import numpy as np
from scipy import fft as sfft

from ..constants import DICT_PRE_SIGMA, DICT_SUPPORT_SIGMA, FAM_GAUSS, FAM_SSS
from core.irf import render_shifted, render_sss
from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import sss_kernel
from ..options import GridSpec

__all__ = ["Dictionary", "DictionaryCache", "DICTIONARY_CACHE", "get_dictionary", "coarse_values"]


def coarse_values(lo, hi, n):
    """``n`` log-spaced values from ``lo`` to ``hi`` (their geometric mean for n = 1)."""
    if n == 1 or lo == hi:
        return np.array([math.sqrt(lo * hi)])
    return np.geomspace(lo, hi, n)


class Dictionary:
    """Coarse convolutional dictionary for one (L, time bin, t0, grid, families).

    Attributes
    ----------
    fam : ndarray (A,) int8       FAM_GAUSS or FAM_SSS per atom
    sigma_ps, alpha_per_ps : (A,)  kernel parameters (alpha NaN for Gaussians)
    peak : (A,)                   max of the sampled kernel (atoms are stored / peak)
    shifts : (S,) int             delay bins j: delay_ps = t0_ps + j * time_bin_ps
    norm2 : (A, S)                squared norm of each atom truncated to the window
    n_fft : int                   FFT length (no circular aliasing)
    response : InstrumentResponse or None
                                  the measured response the kernels are built from (None:
                                  the Gaussian PSF); the refinement renders its atoms too
    """

    def __init__(self, n_bins, time_bin_ps, t0_ps, grid: GridSpec, gauss: bool, sss: bool, response=None):
        L, T = int(n_bins), float(time_bin_ps)
        self.n_bins, self.time_bin_ps, self.t0_ps, self.grid = L, T, float(t0_ps), grid
        self.response = response
        if response is None:
            kernels, spans = self._gaussian_kernels(gauss, sss)
        else:
            kernels, spans = self._response_kernels(response, gauss, sss)
        A = self.fam.size
        self.shifts = np.arange(-self.pre, L)
        S = self.shifts.size
        need = max(max(hi + L, L + self.pre - lo) for lo, hi in spans) + 1
        self.n_fft = N = sfft.next_fast_len(need, real=True)
        self.peak = np.array([k.max() for k in kernels])
        kp = np.zeros((A, N))
        kp2 = np.zeros((A, N))
        self.norm2 = np.zeros((A, S))
        for a, (k, (lo, hi)) in enumerate(zip(kernels, spans)):
            k = k / self.peak[a]
            m = np.arange(lo, hi + 1)
            kp[a, m % N] = k
            kp2[a, m % N] = k * k
            # window-truncated squared norm: sum over m in [-j, L-1-j] of k[m]^2
            c = np.concatenate([[0.0], np.cumsum(k * k)])
            first = np.clip(-self.shifts - lo, 0, k.size)
            last = np.clip(L - 1 - self.shifts - lo + 1, 0, k.size)
            self.norm2[a] = c[last] - c[np.minimum(first, last)]
        self.spec_conj = np.conj(sfft.rfft(kp, axis=-1))
        self.spec2_conj = np.conj(sfft.rfft(kp2, axis=-1))
        self.gather = self.shifts % N
        self.n_coordinates = A * S

    def _gaussian_kernels(self, gauss, sss):
        """The Gaussian PSF's kernels over the grid's coarse widths (and alphas): the atoms'
        families and parameters in ``fam``, ``sigma_ps``, ``alpha_per_ps``; -> (kernels, spans)."""
        L, T, grid = self.n_bins, self.time_bin_ps, self.grid
        s_lo, s_hi = grid.sigma_range_ps
        a_lo, a_hi = grid.alpha_range_per_ps
        self.pre = int(math.ceil(DICT_PRE_SIGMA * s_hi / T)) + 1
        fam, sig, alp = [], [], []
        if gauss:
            for s in coarse_values(s_lo, s_hi, grid.coarse_sigma):
                fam.append(FAM_GAUSS), sig.append(s), alp.append(np.nan)
        if sss:
            for s in coarse_values(s_lo, s_hi, grid.coarse_sss_sigma):
                for a in coarse_values(a_lo, a_hi, grid.coarse_alpha):
                    fam.append(FAM_SSS), sig.append(s), alp.append(a)
        self._families(fam, sig, alp)
        kernels, spans = [], []
        for a in range(self.fam.size):
            half = int(math.ceil(DICT_SUPPORT_SIGMA * self.sigma_ps[a] / T))
            if self.fam[a] == FAM_GAUSS:
                m = np.arange(-half, half + 1)
                k = np.exp(-0.5 * np.square(m * T / self.sigma_ps[a]))
            else:
                m = np.arange(-half, L + self.pre)
                k = sss_kernel(m * T, self.sigma_ps[a], self.alpha_per_ps[a])
            kernels.append(k)
            spans.append((m[0], m[-1]))
        return kernels, spans

    def _response_kernels(self, response, gauss, sss):
        """A measured response's kernels: its shifted copy (the direct's and the
        inter-reflections' atom, the response's peak at the delay) and its sss atoms at the
        grid's coarse alphas (:func:`core.irf.render_shifted`, :func:`core.irf.render_sss`);
        every atom's ``sigma_ps`` is the response's Gaussian-equivalent width, the one width
        the stages read; -> (kernels, spans)."""
        L, T, grid = self.n_bins, self.time_bin_ps, self.grid
        self.pre = int(math.ceil(1.5 * response.fwhm_ps() / T)) + 1
        sigma_eq = gaussian_equivalent_sigma_ps(response)
        alphas = coarse_values(*grid.alpha_range_per_ps, grid.coarse_alpha) if sss else ()
        self._families([FAM_GAUSS] * bool(gauss) + [FAM_SSS] * len(alphas), [sigma_eq] * (bool(gauss) + len(alphas)),
                       [np.nan] * bool(gauss) + list(alphas))
        lo = int(math.floor(response.window_start_ps / T)) - 1
        hi = int(math.ceil((response.window_start_ps + response.window_ps) / T)) + 1
        m_shift, m_sss = np.arange(lo, hi + 1), np.arange(lo, max(L + self.pre, hi) + 1)
        kernels, spans = [], []
        if gauss:
            kernels.append(render_shifted(response, m_shift * T, np.zeros(1))[0])
            spans.append((m_shift[0], m_shift[-1]))
        if len(alphas):
            kernels += list(render_sss(response, m_sss * T, np.zeros(len(alphas)), np.asarray(alphas)))
            spans += [(m_sss[0], m_sss[-1])] * len(alphas)
        return kernels, spans

    def _families(self, fam, sig, alp):
        """Set ``fam``, ``sigma_ps``, ``alpha_per_ps`` from the atoms' lists (none: an error)."""
        if not fam:
            raise ValueError("no component family selected")
        self.fam = np.array(fam, np.int8)
        self.sigma_ps = np.array(sig, np.float64)
        self.alpha_per_ps = np.array(alp, np.float64)

    @property
    def sss_alphas_per_ps(self) -> np.ndarray:
        """The coarse sss decay rates, each once, increasing (1/ps; none without the sss family):
        the alphas a forward step's sss trial starts from."""
        return np.unique(self.alpha_per_ps[self.fam == FAM_SSS])

    def correlate(self, x: np.ndarray, squared: bool = False, atoms=None, workers: int = 1) -> np.ndarray:
        """Correlate rows of ``x`` (P, L) with every atom (or those of index array ``atoms``, A')
        at every shift -> (P, A, S) (or (P, A', S)); ``squared``: with the squared atoms.

        ``workers``: FFT threads.  One by default: pixel blocks are parallelised by processes
        or threads (:mod:`decomposition.store.chunked`); threads inside each would oversubscribe
        the cores.  Rows go through the FFTs :data:`CORRELATE_ROWS` at a time, so that the
        (rows, A, n_fft) spectra stay in cache (the same numbers)."""
        x = np.asarray(x)
        spec = self.spec2_conj if squared else self.spec_conj
        if atoms is not None:
            spec = spec[atoms]
        out = np.empty((x.shape[0], spec.shape[0], self.gather.size))
        for r0 in range(0, x.shape[0], CORRELATE_ROWS):
            X = sfft.rfft(x[r0:r0 + CORRELATE_ROWS], n=self.n_fft, axis=-1, workers=workers)
            c = sfft.irfft(X[:, None, :] * spec[None], n=self.n_fft, axis=-1, workers=workers)
            out[r0:r0 + CORRELATE_ROWS] = np.take(c, self.gather, axis=-1)
        return out


#: rows of a block correlated together by :meth:`Dictionary.correlate`
CORRELATE_ROWS = 64


class DictionaryCache:
    """Dictionaries by their settings, the ``maxsize`` most recently used kept.

    Building a dictionary costs a few FFTs of every kernel; the chunked pipeline solves many
    blocks with the same settings in one process, so :func:`get_dictionary` keeps them in
    :data:`DICTIONARY_CACHE` (one per process, ``clear()`` empties it).  Dictionaries are
    read-only once built, so sharing one between threads is safe; the cache itself is guarded
    by a lock (the threaded scheduler solves chunks concurrently).
    """

    def __init__(self, maxsize: int = 16):
        self.maxsize = int(maxsize)
        self._items: dict = {}
        self._lock = threading.Lock()

    def get(self, n_bins, time_bin_ps, t0_ps, grid: GridSpec, gauss: bool, sss: bool) -> "Dictionary":
        key = (int(n_bins), float(time_bin_ps), float(t0_ps), grid, bool(gauss), bool(sss))
        with self._lock:
            dic = self._items.pop(key, None)
        if dic is None:
            dic = Dictionary(*key)        # built outside the lock; two threads may both build one
        with self._lock:
            self._items[key] = dic        # most recently used last
            while len(self._items) > self.maxsize:
                self._items.pop(next(iter(self._items)))
        return dic

    def clear(self) -> None:
        with self._lock:
            self._items.clear()

    def __len__(self) -> int:
        return len(self._items)


#: the process's dictionary cache (see :class:`DictionaryCache`)
DICTIONARY_CACHE = DictionaryCache()


def get_dictionary(n_bins, time_bin_ps, t0_ps, grid: GridSpec, gauss: bool, sss: bool, *,
                   cache: DictionaryCache | None = DICTIONARY_CACHE, response=None) -> "Dictionary":
    """The dictionary for these settings, from ``cache`` (built once, reused by chunked
    callers); ``cache=None`` builds a fresh one, and so does a measured ``response`` (its
    samples are no key of the cache)."""
    if cache is None or response is not None:
        return Dictionary(int(n_bins), float(time_bin_ps), float(t0_ps), grid, bool(gauss), bool(sss),
                          response=response)
    return cache.get(n_bins, time_bin_ps, t0_ps, grid, gauss, sss)

