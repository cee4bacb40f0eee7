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

Here d_lo = max(-H, -ceil(8 sigma / T)).  q is computed from exact kernel values on its
support (the forward model's stable forms: g erfcx(u) where u >= 0, the equal 2 f - g erfcx(-u) with f
stepped from sample to sample elsewhere, :func:`_sss_samples`), so the
recursion reproduces the sampled kernel up to rounding (1e-14 of the largest value in the
tests, alpha from 1e-4 to 5 /ps, sigma from a fraction of a bin to 10 ps).

Cost per pixel: one FIR pass over the residual for all kernels together (four kernels per
load of the data), and O(S) for the recursions, which are unrolled by four (the first
three steps folded into the kernels: c(s) = c_q4(s) + rho^4 c(s + 4) with
q4(u) = sum_{k<4} rho^k q(u - k)), so they run as independent chains.  Weighted norms cost
a second FIR pass over the weights.  About 10 us per pixel for a Gaussian and three sss
kernels at L = 512, sigma ~ 4 bins (2-core test machine), against about 100 us for
evaluating, transforming and correlating the kernels per pixel by FFT.
"""
from __future__ import annotations

import math
import numpy as np

from ..constants import CORR_SUPPORT_SIGMA
from .jit import SQRT_PI_2, njit, sss_erfc_part

_SQRT_2 = math.sqrt(2.0)

__all__ = ["pixel_correlations", "PickWorkspace"]



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
    Shifts whose window holds the whole kernel get its total without a look-up.
    """
    cs[0] = 0.0
    for t in range(kn):
        cs[t + 1] = cs[t] + k2[t]
    n_out = out.size
    j1 = min(max(pre - d_lo, 0), n_out)                  # from here on the window starts before d_lo
    j2 = min(max(L - d_lo - kn + pre + 1, j1), n_out)    # ... and ends after the kernel up to here
    for j in range(j1):
        sh = j - pre
        a = min(max(-sh - d_lo, 0), kn)
        b = min(max(L - sh - d_lo, 0), kn)
        out[j] = cs[b] - cs[min(a, b)]
    out[j1:j2] = cs[kn]
    for j in range(j2, n_out):
        sh = j - pre
        a = min(max(-sh - d_lo, 0), kn)
        b = min(max(L - sh - d_lo, 0), kn)
        out[j] = cs[b] - cs[min(a, b)]


@njit
def _fir4(xp, x_off, K, row, k_n, d_lo, s_lo, n_s, O, o_off=0):
    """:func:`_fir` for the four kernels K[row:row + 4] at once (one load of x serves four
    kernels); ``K`` rows need a zero at k_n (taps go in pairs)."""
    o0 = O[row, o_off:o_off + n_s]
    o1 = O[row + 1, o_off:o_off + n_s]
    o2 = O[row + 2, o_off:o_off + n_s]
    o3 = O[row + 3, o_off:o_off + n_s]
    o0[:] = 0.0
    o1[:] = 0.0
    o2[:] = 0.0
    o3[:] = 0.0
    base = x_off + s_lo + d_lo
    for t in range(0, k_n, 2):
        b = base + t
        x0 = xp[b: b + n_s]
        x1 = xp[b + 1: b + 1 + n_s]
        a0, a1 = K[row, t], K[row, t + 1]
        b0, b1 = K[row + 1, t], K[row + 1, t + 1]
        c0, c1 = K[row + 2, t], K[row + 2, t + 1]
        e0, e1 = K[row + 3, t], K[row + 3, t + 1]
        for j in range(n_s):
            u = x0[j]
            v = x1[j]
            o0[j] += a0 * u + a1 * v
            o1[j] += b0 * u + b1 * v
            o2[j] += c0 * u + c1 * v
            o3[j] += e0 * u + e1 * v


@njit
def _fir_row0(xp, x_off, K, nk, k_n, d_lo, s_lo, n_s, O):
    """Row 0 of :func:`_fir_rows` alone, by the same arithmetic (taps in pairs as in
    :func:`_fir4` when it would take row 0 with three others, else :func:`_fir`)."""
    if nk < 4:
        _fir(xp, x_off, K[0], k_n, d_lo, s_lo, n_s, O[0])
        return
    o0 = O[0, :n_s]
    o0[:] = 0.0
    base = x_off + s_lo + d_lo
    for t in range(0, k_n, 2):
        b = base + t
        x0 = xp[b: b + n_s]
        x1 = xp[b + 1: b + 1 + n_s]
        a0, a1 = K[0, t], K[0, t + 1]
        for j in range(n_s):
            o0[j] += a0 * x0[j] + a1 * x1[j]


@njit
def _fir_rows(xp, x_off, K, nk, k_n, d_lo, s_lo, n_s, O, o_off=0):
    """O[a, o_off + j] = sum_t K[a, t] x(s_lo + j + d_lo + t) for every kernel a < nk."""
    a = 0
    while a + 4 <= nk:
        _fir4(xp, x_off, K, a, k_n, d_lo, s_lo, n_s, O, o_off)
        a += 4
    while a < nk:
        _fir(xp, x_off, K[a], k_n, d_lo, s_lo, n_s, O[a, o_off:])
        a += 1


@njit
def _block(r, w1, weighted, sig, alphas, T, pre, H, need_g, need_s, j_sss, c, n2, peak):
    n, L = r.shape
    S = L + pre
    na = alphas.size
    nk = 1 + na
    smax = 0.0
    for i in range(n):
        smax = max(smax, sig[i])
    D = min(int(math.ceil(CORR_SUPPORT_SIGMA * smax / T)) + 2, H + L + pre)   # |d_lo|, q support bound
    off = pre + D + 1                                                 # left padding of r
    xp = np.zeros(off + L + 2 * D + 8)
    wp = np.zeros(off + L + 2 * D + 8)
    K = np.zeros((nk, 2 * D + 6))        # row 0: Gaussian, 1 + a: q of sss kernel a
    K2 = np.zeros((nk, 2 * D + 6))       # squares: Gaussian^2, q2
    hbuf = np.empty(2 * D + 6)
    E = np.empty((nk, S + D + 8))
    EN = np.empty((nk, S + D + 8))
    rhos = np.empty(nk)
    cs = np.empty(2 * D + 7)
    for i in range(n):
        s = sig[i]
        for a in range(nk):
            peak[i, a] = 1.0
        if not (need_g[i] or need_s[i]):
            continue                     # nothing this pixel may take: its rows are not read
        half = int(math.ceil(CORR_SUPPORT_SIGMA * s / T))
        d_lo = max(-H, -half)            # kernels are zero before -H
        d_hi = min(half + 1, L + pre - 1)  # Gaussian and q negligible beyond (d <= L + pre - 1 anyway)
        kn = d_hi - d_lo + 1
        n_ext = L - d_lo + pre           # shifts -pre .. L - 1 - d_lo; zero from s = L - d_lo on
        for m in range(L):
            xp[off + m] = r[i, m]
        if weighted:
            for m in range(L):
                wp[off + m] = w1[i, m]
        # Gaussian samples on [d_lo, d_hi]; peak 1 at d = 0
        for t in range(kn):
            x = (d_lo + t) * T / s
            g = math.exp(-0.5 * x * x)
            K[0, t] = g
            K2[0, t] = g * g
        peak[i, 0] = 1.0
        if not need_s[i]:
            # the Gaussian alone (the pixel has its sss atom): its row by the same arithmetic
            for t in range(kn, kn + 4):
                K[0, t] = 0.0
                K2[0, t] = 0.0
            _fir_row0(xp, off, K, nk, kn + 3, d_lo, -pre, n_ext, E)
            if weighted:
                _fir_row0(wp, off, K2, nk, kn + 3, d_lo, -pre, n_ext, EN)
            else:
                _window_sums(K2[0], kn + 3, d_lo, L, pre, cs, EN[0, :n_ext])
            c[i, 0] = E[0, :S]
            n2[i, 0] = EN[0, :S]
            continue
        # sss kernels: h sampled on [d_lo, d_hi], q_m = h_m - rho h_{m-1} there
        for a in range(na):
            al = alphas[a]
            rho = math.exp(-al * T)
            rhos[1 + a] = rho
            _sss_samples(d_lo, kn, T, s, al, rho, K[0], hbuf)
            pk = 0.0
            for t in range(kn):
                pk = max(pk, hbuf[t])
            if not pk > 0.0:
                pk = 1.0
            peak[i, 1 + a] = pk
            inv = 1.0 / pk
            prev = 0.0
            for t in range(kn):
                h = hbuf[t] * inv
                q = h - rho * prev
                K[1 + a, t] = q                     # h_m = rho h_{m-1} + q_m
                K2[1 + a, t] = q * (h + rho * prev)  # h_m^2 = rho^2 h_{m-1}^2 + q2_m
                prev = h
        # fold the first three recursion steps into the sss kernels (see _recurse):
        # q4(u) = sum_{k<4} rho^k q(u - k), q2_4(u) = sum_{k<4} rho^2k q2(u - k)
        kn4 = kn + 3
        for a in range(nk):
            for t in range(kn, kn4 + 1):
                K[a, t] = 0.0
                K2[a, t] = 0.0
        for a in range(na):
            r1 = rhos[1 + a]
            _fold4(K[1 + a], kn4, r1)
            _fold4(K2[1 + a], kn4, r1 * r1)
        # shifts from j0 on only where the Gaussian is not wanted (sss onsets before j0 are not
        # allowed): every value from j0 on is computed as over all shifts
        j0 = 0 if need_g[i] else min(max(j_sss[i], 0), n_ext)
        _fir_rows(xp, off, K, nk, kn4, d_lo, -pre + j0, n_ext - j0, E, j0)
        if weighted:
            _fir_rows(wp, off, K2, nk, kn4, d_lo, -pre + j0, n_ext - j0, EN, j0)
        else:
            for a in range(nk):
                _window_sums(K2[a], kn4, d_lo, L, pre, cs, EN[a, :n_ext])
        if need_g[i]:
            c[i, 0] = E[0, :S]
            n2[i, 0] = EN[0, :S]
        for a in range(na):
            _recurse(E[1 + a], EN[1 + a], n_ext, rhos[1 + a], c[i, 1 + a], n2[i, 1 + a], j0)


@njit
def _sss_samples(d_lo, kn, T, sig, alp, rho, gauss, out):
    """out[t] = sss kernel h((d_lo + t) T) for t < kn (the values of :func:`decomposition.kernels.jit.sss_value`),
    given the unit Gaussian ``gauss`` at the same times, in the form of
    :func:`decomposition.kernels.jit.sss_erfc_part`: g erfcx(u) where u >= 0, 2 f - g erfcx(-u) elsewhere,
    f = exp(alpha^2 sigma^2 / 2 - alpha x) <= 1 stepped by ``rho`` = exp(-alpha T) (one polynomial
    of erfcx's table per sample instead of three transcendentals)."""
    scale = SQRT_PI_2 * sig
    s2 = sig * sig
    f = 0.0
    f_on = False
    for t in range(kn):
        x = (d_lo + t) * T
        u = (alp * s2 - x) / (sig * _SQRT_2)
        if u < 0.0 and not f_on:
            f = math.exp(0.5 * alp * alp * s2 - alp * x)
            f_on = True
        out[t] = scale * sss_erfc_part(u, gauss[t], f)
        f *= rho


@njit
def _fold4(k, n, rho):
    """k(u) <- k(u) + rho k(u-1) + rho^2 k(u-2) + rho^3 k(u-3) for u < n (in place, k(u<0) = 0)."""
    r2 = rho * rho
    r3 = r2 * rho
    for u in range(n - 1, -1, -1):
        v = k[u]
        if u >= 1:
            v += rho * k[u - 1]
        if u >= 2:
            v += r2 * k[u - 2]
        if u >= 3:
            v += r3 * k[u - 3]
        k[u] = v


@njit
def _recurse(e4, en4, n_e, rho, c_out, n_out, j_stop):
    """c(j) = e(j) + rho c(j + 1) and n(j) = en(j) + rho^2 n(j + 1), backwards from c = n = 0 at
    j = n_e, written for j_stop <= j < c_out.size (the blocks of four below are not computed);
    given e4(j) = sum_{k<4} rho^k e(j + k) and the same for en with rho^2 (the kernels were
    folded by :func:`_fold4`; both vanish from n_e on).

    c(j) = e4(j) + rho^4 c(j + 4): four independent chains (eight with the norms) instead of
    one chain of dependent multiply-adds.  ``e4``, ``en4`` need room for n_e + 4 values.
    """
    S = c_out.size
    nb = (n_e + 3) // 4 * 4
    for j in range(n_e, nb):
        e4[j] = 0.0
        en4[j] = 0.0
    r4 = rho ** 4
    r8 = r4 * r4
    c0 = c1 = c2 = c3 = 0.0
    n0 = n1 = n2 = n3 = 0.0
    for jb in range(nb // 4):
        b = nb - 4 - 4 * jb
        if b + 3 < j_stop:
            break
        c0 = e4[b] + r4 * c0
        c1 = e4[b + 1] + r4 * c1
        c2 = e4[b + 2] + r4 * c2
        c3 = e4[b + 3] + r4 * c3
        n0 = en4[b] + r8 * n0
        n1 = en4[b + 1] + r8 * n1
        n2 = en4[b + 2] + r8 * n2
        n3 = en4[b + 3] + r8 * n3
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


class PickWorkspace:
    """Output buffers of :func:`pixel_correlations`, owned by the caller that reuses them.

    A solver block calls :func:`pixel_correlations` once per pick; fresh multi-megabyte
    arrays per call cost more in page faults than the correlations themselves.  Passed as
    ``out=``, a workspace receives ``c`` and ``n2``: the arrays returned are views into it,
    valid until the next call with the same workspace.  Not shared between threads.
    """

    def __init__(self):
        self._buf = np.empty((2, 0))

    def arrays(self, n: int, nk: int, S: int):
        """(c, n2) views of shape (n, nk, S), growing the buffer when needed."""
        need = n * nk * S
        if self._buf.shape[1] < need:
            self._buf = np.empty((2, need))
        return self._buf[0, :need].reshape(n, nk, S), self._buf[1, :need].reshape(n, nk, S)


def pixel_correlations(r, sig_ps, alphas_per_ps, *, time_bin_ps, pre, half_bins, w1=None,
                       out: PickWorkspace | None = None, need_gauss=None, need_sss=None, sss_from=None):
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
    out : PickWorkspace, optional
        Write ``c`` and ``n2`` into this workspace (views, overwritten by its next use)
        instead of fresh arrays.
    need_gauss, need_sss : bool ndarray (n,), optional
        Pixels that may take the Gaussian / an sss kernel (default: all).  The rows a pixel may
        not take are not computed: their ``c`` and ``n2`` hold whatever the buffers held, and
        their ``peak`` is 1.
    sss_from : int ndarray (n,), optional
        Index of the first shift at which each pixel may take an sss kernel (default 0).
        Where the Gaussian is not needed, the sss rows are computed from that shift on only.
        Every value computed is the one a call without these arguments gives, bit for bit.

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
    if out is not None:
        c, n2 = out.arrays(n, nk, L + pre)
    else:
        c = np.empty((n, nk, L + pre))
        n2 = np.empty((n, nk, L + pre))
    peak = np.empty((n, nk))
    need_g = np.ones(n, np.bool_) if need_gauss is None else np.ascontiguousarray(need_gauss, np.bool_).reshape(n)
    need_s = np.ones(n, np.bool_) if need_sss is None else np.ascontiguousarray(need_sss, np.bool_).reshape(n)
    j_sss = np.zeros(n, np.int64) if sss_from is None else np.ascontiguousarray(sss_from, np.int64).reshape(n)
    if n:
        _block(r, w1, weighted, sig, alphas, T, pre, H, need_g, need_s, j_sss, c, n2, peak)
    return c, n2, peak
