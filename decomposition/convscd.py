"""ConvSCD solver: convolutional sparse coding of time profiles (eqs. (3)-(5) of the paper).

What is solved
--------------
Per pixel, with the profile normalised to unit peak (see below), the objective is

    F(z) = 1/2 || w * (p - sum_a k_a (*) z_a) ||_2^2  +  mu * sum_i log(1 + |z_i| / eps)

i.e. eq. (5) with the *squared* l2 data term (the standard form for coordinate
descent: it makes every one-dimensional sub-problem a quadratic plus a
log-sum term with a closed-form minimiser) and the log-sum sparsity penalty
written as ``log(1 + |z|/eps)`` (the paper's ``log|z|`` shifted so that a zero
coefficient costs nothing; ``eps`` keeps it finite).  ``w`` is a per-sample
code: 1 fitted, 0 excluded (detected single-sample spikes), 2 censored from
below (saturated: the true value is at least the recorded one, so only a model
*below* it is a misfit, contributing max(p - model, 0)^2; such samples are
never used to pick atoms).  Coefficients are non-negative (light adds up; this also stops noise
from being explained by negative atoms).

Dictionary.  k1: unit-peak Gaussians g(t; sigma) over a sigma grid; k2: sss
kernels h(t; sigma, alpha) = g * exp(-alpha t) u(t) over a (sigma, alpha) grid,
scaled to unit peak so that every coefficient is a peak height and one
penalty treats both families alike.  Each atom is used at every integer-bin
shift from ``pre`` bins before the window start to the window end, so
components partly outside the window are representable; column norms are the
norms of the atoms *truncated to the window*.

Adaptive sparsity weight.  The noise standard deviation ``s`` of every pixel
is estimated robustly from its second differences (MAD / 0.6745 / sqrt(6):
smooth kernels have tiny second differences, white noise has variance 6 s^2);
the caller takes the larger of the whole-profile value and the value over the
samples above 10 % of the peak (photon noise grows with the signal), floored
at ``noise_floor`` (relative to the pixel's peak, so noiseless data still have
a finite detection limit).  Then ``mu = sparsity * s^2`` and
``eps = eps_rel * s``.  With eps << s each accepted atom costs about
``mu * log(z/eps)`` ~ 6-9 mu, so an atom enters only if it explains several
times the largest correlation pure noise produces over the whole dictionary
(about 2 log(#coordinates) s^2/2 ~ 10 s^2).  Because p is normalised per pixel
and s scales with p, the decision is exactly invariant to the profile's scale.

Physics used (eq. (2)).  One camera PSF c(t) blurs every component of a
profile, so by default (``tie_sigma``) all atoms of a pixel share one sigma;
and sss light enters the surface where the direct light is reflected, so the
sss onset is kept at or after the direct delay (``sss_after_direct``).  A
direct peak and an sss rising edge with the same onset and width are
degenerate to first order (dh/dt = g - alpha h), and these two constraints are
what makes d + s with close onsets separable at all in noise.

Algorithm: batched greedy convolutional coordinate descent with local refinement
-------------------------------------------------------------------------------
1. Gauss-Southwell pick.  For a block of pixels (pixels x time array) the
   correlations of the residual with every atom at every integer shift are
   computed at once: for a pixel's first atom by FFT with the precomputed
   spectra of the coarse dictionary (only the families some pixel may take);
   once it has one, with the Gaussian and the sss kernels at the pixel's own
   sigma, by compiled direct correlations that use the sss kernel's one-pole
   structure (:mod:`decomposition.pickcorr`).  The selection is compiled too
   (:mod:`decomposition.pick`).  For a zero coordinate with column norm n and
   correlation c the one-dimensional problem is
   (n/2)(z - u)^2 + mu log(1 + z/eps), u = c/n, whose minimiser on z >= 0 is
   the larger root of z^2 + (eps - u) z + (mu/n - u eps) = 0 if it beats z = 0.
   Each pixel takes the coordinate with the largest objective decrease
   (coordinates are ranked by c^2/n and the exact decrease is evaluated for
   the best three); a pixel stops when no coordinate decreases its objective
   (or at max_iter / max_components).  The *first* atom is taken from the
   Gaussian family by largest coefficient (the atom matching the main peak):
   the largest-decrease rule would start with a narrow sss atom swallowing the
   direct peak and the tail at once, or with a broad Gaussian covering several
   components, and no local refinement separates those again.  Where that
   start leaves a data term above 1.5x its noise expectation, the
   unrestricted start is run too and the pixel keeps the lower objective.
2. Local refinement (coarse-to-fine).  The paper's reference grid (sigma
   1-10 ps and alpha 0.01-0.05 /ps, 500 samples each: 250,000 sss atoms) is
   never correlated densely.  The coarse grid only *detects* atoms; after
   every pick the active atoms' delays, shared sigma, alpha and amplitudes are
   refined jointly and continuously by a few Levenberg-Marquardt steps
   (analytic Jacobians of both kernels; near sss onsets parametrised as
   direct delay + gap with an active set for gap >= 0), a step accepted for
   a pixel only if F decreases (:mod:`decomposition.atomlm`, compiled, one
   pixel at a time, each atom evaluated on its own support).  Refining
   before the next pick matters: a coarse atom that is slightly off leaves a derivative-shaped residual that
   would otherwise be "explained" by spurious extra atoms.
3. After the 5 % threshold and merging (``decomposition.components``), the
   kept atoms are refined on the data term alone (the usual debiasing after
   sparse selection: the log-sum penalty shrinks amplitudes along the d/s
   degeneracy), with a restart of sss onsets stuck at the direct delay or far
   before it.  With ``off_grid=False`` the refined values are then snapped
   to the reference grid (integer-bin delays, the grid's sigma/alpha) and the
   amplitudes re-fitted: the paper's discrete setting.
4. The objective of steps 1-2 never increases: a pick is an exact
   coordinate minimisation, LM steps are accepted only where F, evaluated
   exactly in float64, decreases, and
   amplitude-zero atoms are dropped (no change in F).  The per-pixel
   objective after every outer iteration is returned so callers and tests
   can check it.

Why this choice: pure coordinate descent over a 250k x L dictionary is
hopeless, and over a coarse dictionary alone it leaves grid-mismatch residuals
that become false components.  Greedy Gauss-Southwell plus continuous local
refinement keeps the paper's objective and sparsity model, finds the number of
components automatically, costs a handful of FFT passes per pixel, and gives
off-grid parameters.

Performance.  Measured on the 2-core machine with 1024 synthetic pixels
(``decomposition.synthetic.make_profiles(1024, 512, nsr=0.05,
noise="white", seed=0)``, kinds a, b, c; ``decompose(profiles,
time_bin_ps=2.0)`` with default options, one process, best of 3 after a
warm-up call) and with ``streaklab bench speed --methods convscd``
(64 x 672 x 512, NSR 0.05, all stages of ``streaklab decompose``):

==========================================  =========  ==========  =========
step                                        1024 px     fidelity    bench, 2
                                            (px/s)                  workers
==========================================  =========  ==========  =========
block-wide numpy (previous release)         594        0.95189     1,051
LM compiled per pixel (atomlm)              1,019      0.95189
selection compiled (pick)                   1,082      0.95189     ~1,400*
own-width correlations compiled (pickcorr)  ~1,900     0.95189     ~2,000*
coarse pass: allowed families only          ~2,060     0.95189     2,621
==========================================  =========  ==========  =========

(* measured while other work shared the machine.)  With 2 threads instead of
2 worker processes the bench gives 2,800 px/s: the compiled kernels release
the GIL.  Where the time goes now (cProfile of the 1024 px run): the
compiled LM about a third; the own-width correlations and the selection
about 15 %; the coarse FFT pass about 8 %; the rest is block bookkeeping in
``solve_block``, noise estimates (medians), spike detection and rendering
the final components with :mod:`decomposition.model`.  Why it helped: the
numpy LM spent its time on (P, K, 4, L) float32 Jacobians, window placement
and live-set bookkeeping, and the own-width pick on per-pixel kernel
evaluation and FFTs; per pixel, compiled, each atom lives on its own
support (a Gaussian on +-8 sigma, an sss tail by a one-pole recursion) and
the normal equations sum only over overlapping supports.  The first call
in a fresh install compiles the kernels (10-15 s, once; numba caches
them next to the sources).  Tried without a measurable gain earlier: float32
FFTs for picking, blocks larger than 256 pixels.
"""
from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from .atomlm import NEAR_SIGMA as _NEAR_SIGMA
from .atomlm import atom_profiles, lm_refine
from .pick import select as _select
from core.model import sss_kernel
from .pickcorr import pixel_correlations

__all__ = [
    "GridSpec",
    "Dictionary",
    "get_dictionary",
    "estimate_noise",
    "solve_block",
    "polish_block",
    "objective",
    "FAM_NONE",
    "FAM_GAUSS",
    "FAM_SSS",
]

FAM_NONE, FAM_GAUSS, FAM_SSS = 0, 1, 2

# FFT threads per call.  One by default: pixel blocks are parallelised by processes
# (decomposition.chunked); threads inside each would oversubscribe the cores.
_WORKERS = max(1, int(os.environ.get("STREAKLAB_FFT_WORKERS", "1")))
_MIN_NOISE_SAMPLES = 12


@dataclass(frozen=True)
class GridSpec:
    """Kernel-parameter grids.

    The *reference* grid (the paper's) is sigma 1-10 ps and alpha 0.01-0.05 /ps
    with 500 equi-spaced samples each; ``coarse_*`` are the numbers of grid
    values actually correlated against (a subsample of the reference range,
    log-spaced); refined values live anywhere within ``bound_factor`` of the
    ranges (``off_grid=True``) or on the reference grid (``off_grid=False``).
    """

    sigma_range_ps: tuple = (1.0, 10.0)
    n_sigma: int = 500
    alpha_range_per_ps: tuple = (0.01, 0.05)
    n_alpha: int = 500
    coarse_sigma: int = 4
    coarse_alpha: int = 3
    coarse_sss_sigma: int = 2

    def check(self) -> "GridSpec":
        s0, s1 = map(float, self.sigma_range_ps)
        a0, a1 = map(float, self.alpha_range_per_ps)
        if not (np.isfinite([s0, s1]).all() and 0 < s0 <= s1):
            raise ValueError(f"sigma_range_ps must be 0 < lo <= hi, got {self.sigma_range_ps!r}")
        if not (np.isfinite([a0, a1]).all() and 0 < a0 <= a1):
            raise ValueError(f"alpha_range_per_ps must be 0 < lo <= hi, got {self.alpha_range_per_ps!r}")
        for name in ("n_sigma", "n_alpha", "coarse_sigma", "coarse_alpha", "coarse_sss_sigma"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1")
        return GridSpec((s0, s1), int(self.n_sigma), (a0, a1), int(self.n_alpha),
                        int(self.coarse_sigma), int(self.coarse_alpha), int(self.coarse_sss_sigma))

    def fine_sigma(self) -> np.ndarray:
        return np.linspace(*self.sigma_range_ps, self.n_sigma)

    def fine_alpha(self) -> np.ndarray:
        return np.linspace(*self.alpha_range_per_ps, self.n_alpha)


def _coarse(lo, hi, n):
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
    """

    def __init__(self, n_bins, time_bin_ps, t0_ps, grid: GridSpec, gauss: bool, sss: bool):
        L, T = int(n_bins), float(time_bin_ps)
        self.n_bins, self.time_bin_ps, self.t0_ps, self.grid = L, T, float(t0_ps), grid
        s_lo, s_hi = grid.sigma_range_ps
        a_lo, a_hi = grid.alpha_range_per_ps
        self.pre = int(math.ceil(3.0 * s_hi / T)) + 1
        fam, sig, alp = [], [], []
        if gauss:
            for s in _coarse(s_lo, s_hi, grid.coarse_sigma):
                fam.append(FAM_GAUSS), sig.append(s), alp.append(np.nan)
        if sss:
            for s in _coarse(s_lo, s_hi, grid.coarse_sss_sigma):
                for a in _coarse(a_lo, a_hi, grid.coarse_alpha):
                    fam.append(FAM_SSS), sig.append(s), alp.append(a)
        if not fam:
            raise ValueError("no component family selected")
        self.fam = np.array(fam, np.int8)
        self.sigma_ps = np.array(sig)
        self.alpha_per_ps = np.array(alp)
        A = self.fam.size
        self.shifts = np.arange(-self.pre, L)
        S = self.shifts.size
        kernels, spans = [], []
        for a in range(A):
            half = int(math.ceil(6.0 * self.sigma_ps[a] / T))
            if self.fam[a] == FAM_GAUSS:
                m = np.arange(-half, half + 1)
                k = np.exp(-0.5 * np.square(m * T / self.sigma_ps[a]))
            else:
                m = np.arange(-half, L + self.pre)
                k = sss_kernel(m * T, self.sigma_ps[a], self.alpha_per_ps[a])
            kernels.append(k)
            spans.append((m[0], m[-1]))
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

    def correlate(self, x: np.ndarray, squared: bool = False, atoms=None) -> np.ndarray:
        """Correlate rows of ``x`` (P, L) with every atom (or those of index array ``atoms``, A')
        at every shift -> (P, A, S) (or (P, A', S)); ``squared``: with the squared atoms."""
        X = sfft.rfft(x, n=self.n_fft, axis=-1, workers=_WORKERS)
        spec = self.spec2_conj if squared else self.spec_conj
        if atoms is not None:
            spec = spec[atoms]
        c = sfft.irfft(X[:, None, :] * spec[None], n=self.n_fft, axis=-1, workers=_WORKERS)
        return np.take(c, self.gather, axis=-1)   # C-contiguous (c[..., idx] is not, and slower)


@functools.lru_cache(maxsize=16)
def _cached_dictionary(n_bins, time_bin_ps, t0_ps, grid, gauss, sss):
    return Dictionary(n_bins, time_bin_ps, t0_ps, grid, gauss, sss)


def get_dictionary(n_bins, time_bin_ps, t0_ps, grid: GridSpec, gauss: bool, sss: bool) -> Dictionary:
    """The (cached) dictionary for these settings: built once, reused by chunked callers."""
    return _cached_dictionary(int(n_bins), float(time_bin_ps), float(t0_ps), grid.check(), bool(gauss), bool(sss))


def estimate_noise(p: np.ndarray, w: np.ndarray | None = None, signal_fraction: float | None = None) -> np.ndarray:
    """Robust per-pixel noise standard deviation from second differences.

    Parameters
    ----------
    p : ndarray (P, L)
    w : ndarray (P, L) of 0/1, optional; second differences touching a
        zero-weight sample are ignored.
    signal_fraction : float, optional
        Only use second differences centred on samples whose magnitude is at
        least this fraction of the pixel's largest sample: the noise *where
        the signal is*, which is what matters when the noise grows with the
        signal (photon noise).  Rows with fewer than 12 such samples get 0.

    Returns
    -------
    ndarray (P,): 1.4826 * median|d2 p| / sqrt(6)  (0 where fewer than 3 usable samples).
    """
    d2 = np.abs(p[:, 2:] - 2.0 * p[:, 1:-1] + p[:, :-2])
    ok = np.ones(d2.shape, bool) if w is None else (w[:, 2:] * w[:, 1:-1] * w[:, :-2]) > 0
    if signal_fraction is not None:
        mag = np.abs(p[:, 1:-1]) if w is None else np.abs(p[:, 1:-1]) * (w[:, 1:-1] > 0)
        ok = ok & (mag >= signal_fraction * mag.max(axis=1, keepdims=True))
    if ok.all():
        med = np.median(d2, axis=1)
    else:
        d2 = np.where(ok, d2, np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN rows: no usable samples
            med = np.nanmedian(d2, axis=1)
        med = np.where(np.isfinite(med), med, 0.0)
    if signal_fraction is not None:
        # a few samples around a narrow peak measure its curvature, not the noise
        med = np.where(ok.sum(axis=1) >= _MIN_NOISE_SAMPLES, med, 0.0)
    return 1.4826 * med / math.sqrt(6.0)


# ---------------------------------------------------------------------------
# atoms with continuous parameters (evaluated by decomposition.atomlm)


def _axis(t):
    """(t0_ps, time_bin_ps) of a uniform time axis t (L,)."""
    return float(t[0]), float(t[1] - t[0]) if t.size > 1 else 1.0


def _eval_atoms(t, fam, delay, lsig, lalp):
    """Unit-amplitude atoms (n, L) with flat parameter arrays (n,) on the uniform time axis t (L,)."""
    return atom_profiles(*_axis(t), t.size, fam, delay, lsig, lalp)


def _render(t, st):
    """Model (P, L) of the slot state ``st``."""
    act = st["fam"] != FAM_NONE
    P, K = act.shape
    model = np.zeros((P, t.size))
    if not act.any():
        return model
    pi, ki = np.nonzero(act)
    phi = _eval_atoms(t, st["fam"][pi, ki], st["delay"][pi, ki], st["lsig"][pi, ki], st["lalp"][pi, ki])
    phi *= st["amp"][pi, ki][:, None]
    np.add.at(model, pi, phi)
    return model


def _cres(p, model, w):
    """Residual under the sample codes w (1 fitted, 0 excluded, 2 censored from below)."""
    r = p - model
    return np.where(w == 2, np.maximum(r, 0.0), r * (w == 1))


def objective(p, w, model, st, mu, eps):
    """F per pixel (P,): 1/2 ||residual||^2 (see _cres) + mu sum log(1 + pen_scale*amp/eps)."""
    r = _cres(p, model, w)
    pen = np.where(st["fam"] != FAM_NONE, np.log1p(st["pen"] * np.abs(st["amp"]) / eps[:, None]), 0.0)
    return 0.5 * np.einsum("pl,pl->p", r, r) + mu * pen.sum(axis=1)


def _take(st, idx):
    return {k: v[idx] for k, v in st.items()}


def _put(st, idx, sub):
    for k, v in sub.items():
        st[k][idx] = v


def _linked(st, near_sigma=None):
    """Pixels whose sss onset is tied to the direct (earliest Gaussian) delay.

    Returns (linked (P,), direct slot (P,), sss slot (P,)).  Linked: the pixel
    has both, and the direct lies less than ``near_sigma`` PSF widths after
    the onset (the same condition as :func:`_constrain`).
    """
    near_sigma = _NEAR_SIGMA if near_sigma is None else near_sigma
    g = st["fam"] == FAM_GAUSS
    s = st["fam"] == FAM_SSS
    dg = np.where(g, st["delay"], np.inf)
    dsl = np.argmin(dg, axis=1)
    ssl = np.argmax(s, axis=1)
    rows = np.arange(st["fam"].shape[0])
    first = dg[rows, dsl]
    ts = st["delay"][rows, ssl]
    linked = s.any(axis=1) & np.isfinite(first) & (first - ts < near_sigma * np.exp(st["lsig"][rows, ssl]))
    return linked, dsl, ssl


def _lm(t, p, w, st, mu, eps, bounds, n_iter, obj, tie_sigma=False, sss_after_direct=False, tol=None,
        return_model=False):
    """Levenberg-Marquardt on all active slots of the pixels in ``st``; monotone in F.

    ``obj`` is F at the current state (P,), the level a step must beat (None: computed
    exactly); returns (state, F, iterations run by the slowest pixel) and, with
    ``return_model``, the model (P, L) of the returned state.  The loop itself is
    :func:`decomposition.atomlm.lm_refine` (compiled, one pixel at a time): a pixel stops when
    an accepted step lowers F by less than ``tol`` times F per fitted sample (a change far
    below what one sample's misfit can resolve; it shrinks as the fit improves, so noiseless
    data converge fully), or when its damping has grown past 1e8.  With ``tie_sigma`` pixels
    whose atoms already share one sigma keep sharing it; with ``sss_after_direct`` a near sss
    onset moves with the direct and its gap stays >= 0.
    """
    out, o, iters, model = lm_refine(*_axis(t), p, w, st, mu, eps, bounds, n_iter, obj, tie_sigma=tie_sigma,
                                     sss_after_direct=sss_after_direct, tol=0.0 if tol is None else tol)
    it = int(iters.max(initial=0))
    return (out, o, it, model) if return_model else (out, o, it)


def _new_state(P, K):
    return {
        "fam": np.zeros((P, K), np.int8),
        "amp": np.zeros((P, K)),
        "delay": np.zeros((P, K)),
        "lsig": np.zeros((P, K)),
        "lalp": np.zeros((P, K)),
        "pen": np.ones((P, K)),
    }


def _bounds(dic: Dictionary, bound_factor: float):
    g = dic.grid
    T = dic.time_bin_ps
    return {
        "delay": (dic.t0_ps - dic.pre * T, dic.t0_ps + (dic.n_bins - 1 + dic.pre) * T),
        "lsig": (math.log(g.sigma_range_ps[0] / bound_factor), math.log(g.sigma_range_ps[1] * bound_factor)),
        "lalp": (math.log(g.alpha_range_per_ps[0] / bound_factor), math.log(g.alpha_range_per_ps[1] * bound_factor)),
    }


def _score_coarse(r, w, weighted, dic: Dictionary, mu, eps, allow_g, allow_s, min_s, by_size=None):
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
        n2 = dic.correlate((w == 1).astype(np.float64), squared=True, atoms=atoms)
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


def _score_pixel(r, w, weighted, dic: Dictionary, sig, mu, eps, allow_g, allow_s, min_s, bound_factor):
    """Best coordinate per pixel among atoms at the pixel's own PSF width ``sig`` (n,).

    Atoms: the Gaussian and the sss kernel at each coarse alpha, all with the
    pixel's sigma, at every integer-bin shift; correlations and exact
    window-truncated norms come from compiled per-pixel FIR passes and one-pole
    recursions (:func:`decomposition.pickcorr.pixel_correlations`).
    """
    n = r.shape[0]
    T = dic.time_bin_ps
    pre = dic.pre
    # the coarse alphas: the dictionary's first sss sigma carries each of them once, in order
    alphas = dic.alpha_per_ps[dic.fam == FAM_SSS][:dic.grid.coarse_alpha]
    kf = [FAM_GAUSS] + [FAM_SSS] * alphas.size
    ka = np.concatenate([[np.nan], alphas])
    H = int(math.ceil(6.0 * float(sig.max()) / T)) + 1
    c, n2, peak = pixel_correlations(r, sig, alphas, time_bin_ps=T, pre=pre, half_bins=H,
                                     w1=(w == 1).astype(np.float64) if weighted else None,
                                     reuse_buffers=True)   # consumed by _select below
    if weighted:
        n2 = np.where(n2 > 1e-12, n2, 0.0)
    is_s = np.array(kf) == FAM_SSS
    allow = np.where(is_s[None, :], allow_s[:, None], allow_g[:, None])[..., None]
    delay = dic.t0_ps + dic.shifts * T
    allow = allow & ~(is_s[None, :, None] & (delay[None, None, :] < min_s[:, None, None]))
    best, zb, db = _select(c, n2, mu, eps, allow)
    a_i, j_i = np.divmod(best, dic.shifts.size)
    rows = np.arange(n)
    fam = np.array(kf, np.int8)[a_i]
    cand = {"fam": fam, "amp": zb / peak[rows, a_i], "pen": peak[rows, a_i],
            "delay": dic.t0_ps + dic.shifts[j_i] * T, "lsig": np.log(sig),
            "lalp": np.where(fam == FAM_SSS, np.log(np.where(np.isfinite(ka[a_i]), ka[a_i], 1.0)), 0.0)}
    return cand, db


def _drop_zero(st):
    dead = (st["fam"] != FAM_NONE) & ~(st["amp"] > 0)
    st["fam"][dead] = FAM_NONE
    st["amp"][dead] = 0.0


def solve_block(p, w, s_eff, dic: Dictionary, *, max_components=4, max_gauss=4, allow_sss=True,
                sparsity=3.0, eps_rel=0.01, max_iter=8, n_lm=8, bound_factor=4.0, first_gauss=None,
                tie_sigma=True, sss_after_direct=True, lm_tol=1e-6):
    """Greedy convolutional coordinate descent with local refinement on a block.

    Parameters
    ----------
    p : ndarray (P, L) float64
        Profiles normalised to unit peak.
    w : ndarray (P, L) float64
        Sample codes: 1 fitted, 0 excluded (spike), 2 censored from below (saturated).
    s_eff : ndarray (P,)
        Noise standard deviation per pixel (already floored, > 0).
    dic : Dictionary
    max_components, max_gauss : int
        Bounds on the number of atoms per pixel (all / Gaussian family).
    allow_sss : bool
        At most one sss atom per pixel when True, none when False.
    sparsity, eps_rel : float
        mu = sparsity * s^2, eps = eps_rel * s.
    max_iter : int
        Bound on the outer (pick + refine) iterations per pixel.
    n_lm : int
        Levenberg-Marquardt iterations after each pick.
    tie_sigma : bool
        One PSF width per pixel (eq. (2): a single c(t) blurs every component).
        A new atom takes the pixel's width when that decreases F; pixels whose
        atoms share a width keep sharing it in the refinement.
    sss_after_direct : bool
        The sss onset is kept at or after the earliest Gaussian (light enters
        the surface where it is directly reflected, so sss cannot arrive first).
    lm_tol : float
        Refinement of a pixel stops once a step gains less than lm_tol times
        the objective per fitted sample.
    first_gauss : ndarray (P,) bool, optional
        Pixels whose first pick must come from the Gaussian family (the
        second start of :func:`solve_multistart`).

    Returns
    -------
    state : dict of (P, K) arrays: fam, amp (model amplitude), delay (ps),
        lsig (log sigma_ps), lalp (log alpha_per_ps), pen (penalty scale).
    info : dict with ``objective`` (P, max_iter + 1; NaN after a pixel stopped),
        ``n_iter`` (P,), ``converged`` (P,), ``lm_iterations``, ``mu``, ``eps``.
    """
    P, L = p.shape
    K = int(max_components)
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    mu = sparsity * s_eff * s_eff
    eps = eps_rel * s_eff
    bounds = _bounds(dic, bound_factor)
    st = _new_state(P, K)
    hist = np.full((P, max_iter + 1), np.nan)
    r0 = _cres(p, 0.0, w)
    obj = 0.5 * np.einsum("pl,pl->p", r0, r0)
    hist[:, 0] = obj
    n_iter = np.zeros(P, np.int64)
    done = np.zeros(P, bool)
    converged = np.zeros(P, bool)
    first_family = np.zeros(P, np.int8)
    weighted = bool(np.any(w != 1.0))
    lm_total = 0
    model = np.zeros((P, L))
    for it in range(1, max_iter + 1):
        idx = np.nonzero(~done)[0]
        if idx.size == 0:
            break
        r = (p[idx] - model[idx]) * (w[idx] == 1)
        fam = st["fam"][idx]
        n_act = (fam != FAM_NONE).sum(1)
        room = n_act < K
        allow_g = room & ((fam == FAM_GAUSS).sum(1) < max_gauss)
        allow_s = room & allow_sss & ~(fam == FAM_SSS).any(1)
        if first_gauss is not None:
            allow_s &= ~(first_gauss[idx] & (n_act == 0))
        min_s = np.full(idx.size, -np.inf)
        if sss_after_direct:
            min_s = np.where(fam == FAM_GAUSS, st["delay"][idx], np.inf).min(axis=1)
            min_s[~np.isfinite(min_s)] = -np.inf
        cand = {k: np.zeros(idx.size, v.dtype) for k, v in st.items()}
        dec = np.zeros(idx.size)
        own = (n_act > 0) if tie_sigma else np.zeros(idx.size, bool)
        for grp, scorer in ((~own, "coarse"), (own, "pixel")):
            gsel = np.nonzero(grp & (allow_g | allow_s))[0]
            if gsel.size == 0:
                continue
            if scorer == "coarse":
                by_size = None if first_gauss is None else (first_gauss[idx[gsel]] & (n_act[gsel] == 0))
                c_, d_ = _score_coarse(r[gsel], w[idx[gsel]], weighted, dic, mu[idx[gsel]], eps[idx[gsel]],
                                       allow_g[gsel], allow_s[gsel], min_s[gsel], by_size)
            else:
                sig = np.exp(np.where(fam[gsel] != FAM_NONE, st["lsig"][idx[gsel]], -np.inf).max(axis=1))
                c_, d_ = _score_pixel(r[gsel], w[idx[gsel]], weighted, dic, sig, mu[idx[gsel]], eps[idx[gsel]],
                                      allow_g[gsel], allow_s[gsel], min_s[gsel], bound_factor)
            for k in cand:
                cand[k][gsel] = c_[k]
            dec[gsel] = d_
        stop = ~(dec > 1e-12 * np.maximum(obj[idx], 1e-300))
        converged[idx[stop]] = True
        done[idx[stop]] = True
        go = ~stop
        gi = idx[go]
        if gi.size == 0:
            break
        slot = np.argmax(st["fam"][gi] == FAM_NONE, axis=1)
        for k in st:
            st[k][gi, slot] = cand[k][go]
        if it == 1:
            first_family[gi] = cand["fam"][go]
        bdec = dec
        obj[gi] = obj[gi] - bdec[go]
        sub = _take(st, gi)
        sub, o, nl, m_sub = _lm(t, p[gi], w[gi], sub, mu[gi], eps[gi], bounds, n_lm, obj[gi].copy(),
                                tie_sigma, sss_after_direct, lm_tol, return_model=True)
        exact = o       # F evaluated exactly after refinement (not the FFT pick's estimate)
        _drop_zero(sub)
        _put(st, gi, sub)
        model[gi] = m_sub
        obj[gi] = exact
        hist[gi, it] = exact
        n_iter[gi] = it
        lm_total += nl
    info = {"objective": hist, "n_iter": n_iter, "converged": converged, "lm_iterations": lm_total,
            "mu": mu, "eps": eps, "coordinates_searched": dic.n_coordinates,
            "first_family": first_family,
            "data_term": 0.5 * np.einsum("pl,pl->p", _cres(p, model, w), _cres(p, model, w))}
    return st, info


def solve_multistart(p, w, s_eff, dic: Dictionary, sss_alone=False, restart=True, **opts):
    """Two greedy starts per pixel where needed; keep the lower objective.

    Greedy selection by largest objective decrease (Gauss-Southwell-q) tends
    to start with a narrow sss atom that swallows the direct peak together
    with the sss tail, after which local refinement cannot separate them; it
    also prefers a broad Gaussian covering several components.  The primary
    start therefore takes its *first* atom from the Gaussian family by largest
    coefficient (Gauss-Southwell-r: the atom that matches the main peak), all
    later picks by largest decrease.  Where that start does not explain the
    data down to the noise (data term above 1.5x its expected value for the
    estimated noise), the unrestricted Gauss-Southwell-q start is run as well
    and each pixel keeps the start with the lower final objective (both are
    monotone, so the kept history is too).

    ``restart=False`` keeps the primary start only.

    With ``sss_alone`` (for scenes where some pixels hold an sss component and
    no direct reflection) one unrestricted pick with its refinement is also
    tried for every pixel and kept where a single sss atom reaches a lower
    objective, and a direct sitting on an sss onset is dropped where that
    lowers the objective (:func:`_backward_direct`).  It costs about 40 % more
    time and is off by default: in the paper's model every pixel has a direct.
    """
    has_g = bool(np.any(dic.fam == FAM_GAUSS)) and opts.get("max_gauss", 1) > 0
    expected = 0.5 * (w > 0).sum(axis=1) * s_eff * s_eff
    first = np.ones(p.shape[0], bool) if has_g else None
    st, info = solve_block(p, w, s_eff, dic, first_gauss=first, **opts)
    alone = np.zeros(p.shape[0], bool)
    if sss_alone and has_g and opts.get("allow_sss", True) and np.any(dic.fam == FAM_SSS):
        # A profile that is an sss alone gets a spurious direct (and more Gaussians) from the
        # Gaussian-first start; one unrestricted pick plus refinement is tried for every
        # pixel and kept where its objective is lower
        one, info1 = solve_block(p, w, s_eff, dic, **{**opts, "max_iter": 1, "n_lm": 3 * opts.get("n_lm", 4)})
        alone = (_final(info1["objective"]) < _final(info["objective"])) & (one["fam"] == FAM_SSS).any(axis=1)
        a = np.nonzero(alone)[0]
        if a.size:
            k1 = one["fam"].shape[1]
            for key in st:
                st[key][a] = 0
                st[key][a, :k1] = one[key][a]
            st["pen"][a, k1:] = 1.0
            info["objective"][a] = np.nan
            info["objective"][a, :2] = info1["objective"][a]
            for key in ("n_iter", "converged", "first_family", "data_term"):
                info[key][a] = info1[key][a]
            info["converged"][a] = True
        info["lm_iterations"] += info1["lm_iterations"]
    info["sss_alone"] = int(alone.sum())
    redo = (np.nonzero((info["data_term"] > 1.5 * expected) & ~alone)[0] if has_g and restart
            else np.zeros(0, np.int64))
    info["restarted"] = redo.size
    if redo.size:
        st2, info2 = solve_block(p[redo], w[redo], s_eff[redo], dic, **opts)
        f1 = _final(info["objective"][redo])
        f2 = _final(info2["objective"])
        better = f2 < f1
        b = redo[better]
        _put(st, b, _take(st2, better))
        for key in ("objective", "n_iter", "converged", "first_family", "data_term"):
            info[key][b] = info2[key][better]
        info["lm_iterations"] += info2["lm_iterations"]
    if sss_alone and has_g and opts.get("allow_sss", True):
        _backward_direct(p, w, s_eff, dic, st, info, opts)
    return st, info


def _backward_direct(p, w, s_eff, dic, st, info, opts):
    """Backward step: drop a direct that sits on an sss onset where that lowers F.

    A profile that is an sss component alone is first given a Gaussian by the
    Gaussian-first start; the sss then takes the rest and both fit.  Removing
    the Gaussian, re-refining the remaining atoms and keeping the result where
    the objective (data term plus penalty) is lower undoes that.  The kept
    value replaces the pixel's last objective entry, which it lowers, so the
    history stays monotone.
    """
    lk, dsl, ssl = _linked(st)
    cand = np.nonzero(lk)[0]
    if cand.size == 0:
        return
    L = p.shape[1]
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    sp = opts.get("sparsity", 3.0)
    er = opts.get("eps_rel", 0.01)
    mu = sp * s_eff[cand] ** 2
    eps = er * s_eff[cand]
    alt = _take(st, cand)
    r_ = np.arange(cand.size)
    alt["fam"][r_, dsl[cand]] = FAM_NONE
    alt["amp"][r_, dsl[cand]] = 0.0
    alt, o, nl, m = _lm(t, p[cand], w[cand], alt, mu, eps, _bounds(dic, opts.get("bound_factor", 4.0)),
                        2 * opts.get("n_lm", 4), None, opts.get("tie_sigma", True),
                        opts.get("sss_after_direct", True), opts.get("lm_tol", 1e-2), return_model=True)
    _drop_zero(alt)
    hist = info["objective"]
    last = hist.shape[1] - 1 - np.argmax(np.isfinite(hist[cand])[:, ::-1], axis=1)
    cur = hist[cand, last]
    better = o < cur
    b = cand[better]
    _put(st, b, _take(alt, better))
    hist[b, last[better]] = o[better]
    r = _cres(p[b], m[better], w[b])
    info["data_term"][b] = 0.5 * np.einsum("pl,pl->p", r, r)
    info["lm_iterations"] += nl
    info["backward"] = int(b.size)


def _final(hist):
    """Last finite value of each row of an objective history."""
    ok = np.isfinite(hist)
    last = hist.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1)
    return hist[np.arange(hist.shape[0]), last]


def polish_block(p, w, st, s_eff, dic: Dictionary, *, sparsity=3.0, eps_rel=0.01, n_lm=10, bound_factor=4.0,
                 tie_sigma=True, sss_after_direct=True, lm_tol=1e-6):
    """Final least-squares refinement of a fixed set of atoms (after thresholding and merging).

    The sparse step has chosen the atoms; this is the usual debiasing step
    after sparse selection: the log-sum penalty shrinks amplitudes (it favours
    a smaller direct plus a larger sss along their near-degenerate direction),
    so the kept atoms are refined on the data term alone (mu = 0), each step
    accepted only where the residual decreases.
    """
    L = p.shape[1]
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    mu = np.zeros_like(s_eff)
    eps = eps_rel * s_eff
    bounds = _bounds(dic, bound_factor)
    st, obj, nl, model = _lm(t, p, w, st, mu, eps, bounds, n_lm, None, tie_sigma, sss_after_direct, lm_tol,
                             return_model=True)
    if sss_after_direct:
        # A direct and an sss with the same onset and width are degenerate to first order
        # (dh/dt = g - alpha h), so a gap stuck near 0 is re-tried from one PSF width.
        # An sss onset far before the direct (an exponential tail alone is degenerate in
        # onset and amplitude) is re-tried the same way.
        lk, dsl, ssl = _linked(st, near_sigma=np.inf)
        rows = np.arange(st["fam"].shape[0])
        gap = st["delay"][rows, ssl] - st["delay"][rows, dsl]
        sig_s = np.exp(st["lsig"][rows, ssl])
        retry = np.nonzero(lk & (gap < 0.5 * sig_s))[0]
        if retry.size:
            alt = _take(st, retry)
            alt["delay"][np.arange(retry.size), ssl[retry]] = (alt["delay"][np.arange(retry.size), dsl[retry]]
                                                                + sig_s[retry])
            alt, o_alt, nl2, m_alt = _lm(t, p[retry], w[retry], alt, mu[retry], eps[retry], bounds, n_lm, None,
                                         tie_sigma, sss_after_direct, lm_tol, return_model=True)
            better = o_alt < obj[retry]
            _put(st, retry[better], _take(alt, better))
            model[retry[better]] = m_alt[better]
            obj[retry[better]] = o_alt[better]
            nl += nl2
    _drop_zero(st)              # zero-amplitude atoms add nothing to the model
    return st, model, nl


def snap_to_grid(st, dic: Dictionary):
    """Snap delays to integer bins and sigma/alpha to the reference grid (``off_grid=False``)."""
    act = st["fam"] != FAM_NONE
    T = dic.time_bin_ps
    st["delay"] = np.where(act, dic.t0_ps + np.round((st["delay"] - dic.t0_ps) / T) * T, st["delay"])
    fs, fa = dic.grid.fine_sigma(), dic.grid.fine_alpha()
    sig = np.exp(st["lsig"])
    si = np.abs(sig[..., None] - fs).argmin(-1)
    st["lsig"] = np.where(act, np.log(fs[si]), st["lsig"])
    alp = np.exp(st["lalp"])
    ai = np.abs(alp[..., None] - fa).argmin(-1)
    st["lalp"] = np.where(act & (st["fam"] == FAM_SSS), np.log(fa[ai]), st["lalp"])
    return st


def refit_amplitudes(p, w, st, dic: Dictionary):
    """Non-negative least-squares amplitudes for fixed atom shapes (batched, small K)."""
    L = p.shape[1]
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    P, K = st["fam"].shape
    act = st["fam"] != FAM_NONE
    phi = np.zeros((P, K, L))
    if act.any():
        pi, ki = np.nonzero(act)
        phi[pi, ki] = _eval_atoms(t, st["fam"][pi, ki], st["delay"][pi, ki], st["lsig"][pi, ki],
                                  st["lalp"][pi, ki])
    w = (w == 1).astype(np.float64)
    phw = phi * w[:, None, :]
    G = np.einsum("pkl,pjl->pkj", phw, phw)
    b = np.einsum("pkl,pl->pk", phw, p * w)
    amp = np.where(act, st["amp"], 0.0)
    # a few sweeps of exact coordinate descent on the (convex) NNLS problem
    for _ in range(20):
        for k in range(K):
            gkk = G[:, k, k]
            resid = b[:, k] - np.einsum("pj,pj->p", G[:, k, :], amp) + gkk * amp[:, k]
            with np.errstate(invalid="ignore", divide="ignore"):
                newv = np.where(gkk > 0, np.maximum(resid / gkk, 0.0), 0.0)
            amp[:, k] = np.where(act[:, k], newv, 0.0)
    st["amp"] = amp
    _drop_zero(st)
    return st
