"""Correlations of residuals with atoms at each pixel's own PSF width (compiled, per pixel).

Once a pixel has an atom, ConvSCD picks its next one among atoms that share the pixel's
width sigma (``tie_sigma``): the unit-peak Gaussian and the sss kernel at each coarse alpha,
at every integer-bin shift.  Per pixel and kernel k_a this needs

    c[a, j]  = sum_{m=0}^{L-1} r[m] k_a(m - s_j)          correlation with the residual r
    n2[a, j] = sum_{m=0}^{L-1} w[m] k_a(m - s_j)^2        squared norm on the fitted samples

for the shifts s_j = j - pre (j = 0 .. L + pre - 1), where k_a(d) is the kernel sampled at
d * T, divided by its largest sample over d in [-H, L + pre), and zero before d = -H.
Evaluating and transforming a kernel per pixel costs more than the correlation itself, so
this module uses the structure of the kernels instead of FFTs:

* Gaussian: exp(-32) below the unit peak beyond 8 sigma, so a direct FIR correlation over
  its +-8 sigma support.
* sss kernel: h = g * [exp(-alpha t) u(t)] sampled at m T obeys h_m = rho h_{m-1} + q_m
  with rho = exp(-alpha T) and q_m = integral_0^T g(m T - tau) exp(-alpha tau) dtau, a bump
  below g((m - 1) T) T, i.e. negligible past 8 sigma + T.  So the correlation with h is a
  backward one-pole recursion over the FIR correlation with the short q:

      c_h(s) = c_q(s) + rho c_h(s + 1),   c_h(s) = 0 for s >= L - d_lo,

  and likewise for the norms with h^2 = rho^2 h_{m-1}^2 + q2_m, q2_m = q_m (h_m + rho h_{m-1}):
  a FIR of the weights with q2, or, unweighted, window sums of q2 from its cumulative sum.
  Gaussian norms: the same FIR or window sums of k^2.

q is computed from exact kernel values on its support (:func:`decomposition.jit.sss_value`,
the forward model's stable forms), so the recursion reproduces the sampled kernel up to
rounding (relative 1e-13 over thousands of bins).  Cost per pixel and kernel: one
O(S * 16 sigma / T) FIR pass (two when weighted), O(S) for the recursions.
"""
from __future__ import annotations

import math
import threading

import numpy as np

from .jit import njit, sss_value

__all__ = ["pixel_correlations"]

_HALF_SIGMA = 8.0   # kernel support (Gaussian) and q support (sss) in sigma: exp(-32) beyond
_scratch = threading.local()   # per-thread output buffers (reuse_buffers=True)


@njit
def _fir(xp, x_off, k, k_n, d_lo, s_lo, n_s, out):
    """out[j] = sum_{t < k_n} k[t] * x(s_lo + j + d_lo + t) for j < n_s; x(i) = xp[x_off + i].

    Four taps per pass over ``out`` (a quarter of its loads and stores); slices indexed by the
    range variable carry no wrap-around checks, so the inner loops compile to SIMD.
    """
    o = out[:n_s]
    o[:] = 0.0
    base = x_off + s_lo + d_lo
    t = 0
    while t + 4 <= k_n:
        k0, k1, k2, k3 = k[t], k[t + 1], k[t + 2], k[t + 3]
        b = base + t
        x0 = xp[b: b + n_s]
        x1 = xp[b + 1: b + 1 + n_s]
        x2 = xp[b + 2: b + 2 + n_s]
        x3 = xp[b + 3: b + 3 + n_s]
        for j in range(n_s):
            o[j] += (k0 * x0[j] + k1 * x1[j]) + (k2 * x2[j] + k3 * x3[j])
        t += 4
    while t < k_n:
        kt = k[t]
        xs = xp[base + t: base + t + n_s]
        for j in range(n_s):
            o[j] += kt * xs[j]
        t += 1


@njit
def _window_sums(k2, kn, d_lo, L, pre, cs, out):
    """out[j] = sum of k2 over d in [-s_j, L - 1 - s_j], s_j = j - pre, j < out.size.

    ``k2[t]`` is the value at d = d_lo + t (zero outside t in [0, kn)); ``cs`` is scratch.
    """
    cs[0] = 0.0
    for t in range(kn):
        cs[t + 1] = cs[t] + k2[t]
    for j in range(out.size):
        sh = j - pre
        a = min(max(-sh - d_lo, 0), kn)
        b = min(max(L - sh - d_lo, 0), kn)
        out[j] = cs[b] - cs[min(a, b)]


@njit
def _block(r, w1, weighted, sig, alphas, T, pre, H, c, n2, peak):
    n, L = r.shape
    S = L + pre
    na = alphas.size
    smax = 0.0
    for i in range(n):
        smax = max(smax, sig[i])
    D = min(int(math.ceil(_HALF_SIGMA * smax / T)) + 2, H + L + pre)   # |d_lo|, q support bound
    off = pre + D + 1                                                 # left padding of r
    xp = np.zeros(off + L + 2 * D + 4)
    wp = np.zeros(off + L + 2 * D + 4)
    kbuf = np.empty(2 * D + 4)
    hbuf = np.empty(2 * D + 4)
    k2buf = np.empty(2 * D + 4)
    ext = np.empty(S + D + 8)
    extn = np.empty(S + D + 8)
    cs = np.empty(2 * D + 5)
    for i in range(n):
        s = sig[i]
        half = int(math.ceil(_HALF_SIGMA * s / T))
        d_lo = max(-H, -half)
        for m in range(L):
            xp[off + m] = r[i, m]
        if weighted:
            for m in range(L):
                wp[off + m] = w1[i, m]
        # ---- Gaussian: FIR over [d_lo, d_hi]
        d_hi = min(half, L + pre - 1)
        kn = d_hi - d_lo + 1
        for t in range(kn):
            x = (d_lo + t) * T / s
            kbuf[t] = math.exp(-0.5 * x * x)
            k2buf[t] = kbuf[t] * kbuf[t]
        peak[i, 0] = 1.0
        _fir(xp, off, kbuf, kn, d_lo, -pre, S, c[i, 0])
        if weighted:
            _fir(wp, off, k2buf, kn, d_lo, -pre, S, n2[i, 0])
        else:
            _window_sums(k2buf, kn, d_lo, L, pre, cs, n2[i, 0])
        # ---- sss kernels: q on [d_lo, q_hi], backward one-pole recursions beyond
        q_hi = min(half + 1, L + pre - 1)
        kn = q_hi - d_lo + 1
        n_ext = L - d_lo + pre          # shifts -pre .. L - 1 - d_lo; zero from s = L - d_lo on
        for a in range(na):
            al = alphas[a]
            rho = math.exp(-al * T)
            pk = 0.0
            for t in range(kn):
                h = sss_value((d_lo + t) * T, s, al)[0]
                hbuf[t] = h
                pk = max(pk, h)
            if not pk > 0.0:
                pk = 1.0
            peak[i, 1 + a] = pk
            inv = 1.0 / pk
            prev = 0.0
            for t in range(kn):
                h = hbuf[t] * inv
                q = h - rho * prev
                kbuf[t] = q                         # h_m = rho h_{m-1} + q_m
                k2buf[t] = q * (h + rho * prev)     # h_m^2 = rho^2 h_{m-1}^2 + q2_m
                prev = h
            _fir(xp, off, kbuf, kn, d_lo, -pre, n_ext, ext)
            if weighted:
                _fir(wp, off, k2buf, kn, d_lo, -pre, n_ext, extn)
            else:
                _window_sums(k2buf, kn, d_lo, L, pre, cs, extn[:n_ext])
            _recurse(ext, extn, n_ext, rho, c[i, 1 + a], n2[i, 1 + a])


@njit
def _recurse(e, en, n_e, rho, c_out, n_out):
    """c(j) = e(j) + rho c(j + 1) and n(j) = en(j) + rho^2 n(j + 1), backwards from c = n = 0 at
    j = n_e; written for j < c_out.size.  ``e``, ``en`` are overwritten (and need n_e + 8 room).

    Unrolled by four: with e4(j) = e(j) + rho e(j+1) + rho^2 e(j+2) + rho^3 e(j+3),
    c(j) = e4(j) + rho^4 c(j + 4), i.e. four independent chains (eight with the norms) instead
    of one long chain of dependent multiply-adds.
    """
    S = c_out.size
    nb = (n_e + 3) // 4 * 4
    for j in range(n_e, nb + 4):
        e[j] = 0.0
        en[j] = 0.0
    r1, r2 = rho, rho * rho
    r4 = r2 * r2
    r8 = r4 * r4
    for j in range(nb + 3):                     # e2(j) = e(j) + rho e(j+1)
        e[j] += r1 * e[j + 1]
        en[j] += r2 * en[j + 1]
    for j in range(nb + 2):                     # e4(j) = e2(j) + rho^2 e2(j+2)
        e[j] += r2 * e[j + 2]
        en[j] += r4 * en[j + 2]
    c0 = c1 = c2 = c3 = 0.0
    n0 = n1 = n2 = n3 = 0.0
    for jb in range(nb // 4):
        b = nb - 4 - 4 * jb
        c0 = e[b] + r4 * c0
        c1 = e[b + 1] + r4 * c1
        c2 = e[b + 2] + r4 * c2
        c3 = e[b + 3] + r4 * c3
        n0 = en[b] + r8 * n0
        n1 = en[b + 1] + r8 * n1
        n2 = en[b + 2] + r8 * n2
        n3 = en[b + 3] + r8 * n3
        if b + 3 < S:
            c_out[b], c_out[b + 1], c_out[b + 2], c_out[b + 3] = c0, c1, c2, c3
            n_out[b], n_out[b + 1], n_out[b + 2], n_out[b + 3] = n0, n1, n2, n3
        else:
            if b < S:
                c_out[b], n_out[b] = c0, n0
            if b + 1 < S:
                c_out[b + 1], n_out[b + 1] = c1, n1
            if b + 2 < S:
                c_out[b + 2], n_out[b + 2] = c2, n2


def pixel_correlations(r, sig_ps, alphas_per_ps, *, time_bin_ps, pre, half_bins, w1=None,
                       reuse_buffers=False):
    """Correlations and window-truncated squared norms of atoms at each pixel's own width.

    Parameters
    ----------
    r : ndarray (n, L) float64
        Residuals (zero on samples that are not fitted).
    sig_ps : ndarray (n,)
        PSF width sigma of each pixel in ps (> 0).
    alphas_per_ps : ndarray (na,)
        sss attenuations in 1/ps (> 0); kernel 0 is the Gaussian, kernel 1 + a the sss
        kernel at (sigma, alphas_per_ps[a]).
    time_bin_ps : float
        Bin width T.
    pre : int
        Shifts run from -pre to L - 1 bins (S = L + pre).
    half_bins : int
        H: kernels are sampled over d in [-H, L + pre) (zero before -H) and each is divided
        by its largest sample there.
    w1 : ndarray (n, L), optional
        Weights of the squared norms (1 fitted, 0 excluded); None: all samples fitted
        (norms from cumulative sums).
    reuse_buffers : bool
        Write ``c`` and ``n2`` into buffers kept per thread and reused by the next call with
        this option (for callers that consume them at once): fresh multi-megabyte arrays per
        call cost more in page faults than the correlations themselves.

    Returns
    -------
    c : ndarray (n, 1 + na, S)      sum_m r[m] k(m - s_j)
    n2 : ndarray (n, 1 + na, S)     sum_m w1[m] k(m - s_j)^2 (m in [0, L))
    peak : ndarray (n, 1 + na)      the sampled kernels' largest values (1 for the Gaussian)
    """
    r = np.ascontiguousarray(r, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"r must be (n, L), got shape {r.shape}")
    n, L = r.shape
    sig = np.ascontiguousarray(sig_ps, dtype=np.float64).reshape(-1)
    if sig.size != n:
        raise ValueError(f"sig_ps must have one width per pixel ({n}), got {sig.size}")
    if n and not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
        raise ValueError("sig_ps must be finite and positive")
    alphas = np.ascontiguousarray(alphas_per_ps, dtype=np.float64).reshape(-1)
    if not (np.all(np.isfinite(alphas)) and np.all(alphas > 0)):
        raise ValueError("alphas_per_ps must be finite and positive")
    T = float(time_bin_ps)
    if not (math.isfinite(T) and T > 0):
        raise ValueError(f"time_bin_ps must be finite and positive, got {time_bin_ps!r}")
    pre, H = int(pre), int(half_bins)
    if pre < 0 or H < 1:
        raise ValueError(f"pre must be >= 0 and half_bins >= 1, got {pre}, {H}")
    weighted = w1 is not None
    if weighted:
        w1 = np.ascontiguousarray(w1, dtype=np.float64)
        if w1.shape != r.shape:
            raise ValueError(f"w1 must have the shape of r {r.shape}, got {w1.shape}")
    else:
        w1 = np.zeros((0, L))
    nk = 1 + alphas.size
    if reuse_buffers:
        need = n * nk * (L + pre)
        buf = getattr(_scratch, "buf", None)
        if buf is None or buf.shape[1] < need:
            buf = _scratch.buf = np.empty((2, need))
        c = buf[0, :need].reshape(n, nk, L + pre)
        n2 = buf[1, :need].reshape(n, nk, L + pre)
    else:
        c = np.empty((n, nk, L + pre))
        n2 = np.empty((n, nk, L + pre))
    peak = np.empty((n, nk))
    if n:
        _block(r, w1, weighted, sig, alphas, T, pre, H, c, n2, peak)
    return c, n2, peak
