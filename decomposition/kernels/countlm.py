"""The count fit's damped loop, compiled: an instrument's atoms fitted to Poisson counts, one pixel at a time.

:func:`count_lm` is the loop of :func:`decomposition.response.refine.fit_slots` for count data:
Levenberg-Marquardt on the Poisson deviance by Fisher scoring over every parameter at once (the
slots' delays, the sss log decay rate, the amplitudes and the offset's correction), from the
amplitudes of one weighted least-squares solve at the starting delays.  The same steps, bounds,
ordering constraints, sign rule and stopping rules as the NumPy loop there, which stays the
reference; here each atom is rendered on its own support by
:func:`decomposition.kernels.projected.atom_rows` and a pixel runs to convergence before the next
starts, so nothing of size (pixels, parameters, samples) is allocated and the loop releases the
interpreter lock for its whole length.  The two agree to rounding (a different order of
summation, and :func:`~decomposition.kernels.projected.lu_solve` for LAPACK's solve).

:func:`deviance_row` is the one home of the deviance's arithmetic: :mod:`decomposition.noise`
sums its rows with it too.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from .jit import njit
from .projected import atom_rows, atom_scratch, lu_solve, uniform_step

__all__ = ["deviance_row", "count_lm"]

_BIG = np.finfo(np.float64).max


@njit
def deviance_row(y, mu, fit, floor):
    """sum over the fitted samples of 2 [y log(y / m) - (y - m)] (0 log 0 = 0), m = max(mu,
    ``floor``) with a NaN ``mu`` read as 0 and an infinite one as the largest finite value of its
    sign (``np.nan_to_num``): the Poisson deviance of one row, ``y``, ``mu``, ``fit`` (L,)."""
    s = 0.0
    for i in range(y.shape[0]):
        if not fit[i]:
            continue
        m = mu[i]
        if m != m:
            m = 0.0
        elif m > _BIG:
            m = _BIG
        elif m < -_BIG:
            m = -_BIG
        m = max(m, floor)
        v = y[i]
        if v > 0.0:
            s += 2.0 * (v * math.log(v / m) - (v - m))
        else:
            s += 2.0 * (0.0 - (v - m))
    return s


@njit
def _render(t, m, lo, hi, fam, delay, lalp, lsig, inst, increasing, step_t, scratch):
    """The pixel's atoms with their derivative rows into ``m`` (the layout of
    :func:`~decomposition.kernels.projected.atom_rows`; ``lsig`` the slots' Gaussian log widths,
    unread for a response's table), each slot's support into ``lo``, ``hi``."""
    K = fam.shape[0]
    for k in range(K):
        if fam[k] == FAM_NONE:
            lo[k] = 0
            hi[k] = 0
            continue
        sss = fam[k] == FAM_SSS
        a = math.exp(lalp[k]) if sss else 0.0
        j0, j1 = atom_rows(t, m, K, k, sss, delay[k], math.exp(lsig[k]), a, inst, t, False, True, increasing, step_t,
                           scratch)
        lo[k] = j0
        hi[k] = j1


@njit
def _model(m, lo, hi, amp, has_bg, scale, held, mu):
    """Expected counts ``mu`` (L,) of the amplitudes ``amp`` on the rendered atoms (and the offset
    column, amp[K], where ``has_bg``): held + scale * model."""
    K = lo.shape[0]
    base = held + (scale * amp[K] if has_bg else 0.0)
    for i in range(mu.shape[0]):
        mu[i] = 0.0
    for k in range(K):
        a = amp[k]
        for i in range(lo[k], hi[k]):
            mu[i] += a * m[k, i]
    for i in range(mu.shape[0]):
        mu[i] = base + scale * mu[i]


@njit
def _column_on(fam, has_bg, c):
    """Amplitude column ``c`` is fitted: an active slot's atom, or (c == K) the offset where ``has_bg``."""
    return (fam[c] != FAM_NONE) if c < fam.shape[0] else has_bg


@njit
def _column(m, lo, hi, has_bg, c, i):
    """Sample ``i`` of amplitude column ``c``: the rendered atom on its support (0 off it), or
    (c == K) the offset's column of ones where ``has_bg``."""
    K = lo.shape[0]
    if c < K:
        return m[c, i] if lo[c] <= i < hi[c] else 0.0
    return 1.0 if has_bg else 0.0


@njit
def _start_amplitudes(m, lo, hi, fam, has_bg, y, sw, amp, mat, rhs, piv):
    """:func:`decomposition.response.refine.solve_amplitudes` for one pixel: the weighted
    least-squares amplitudes of its atoms (and the offset column where ``has_bg``) under the
    square-root weights ``sw``, ridge 1e-12 of the largest diagonal on the active columns, 0 in
    empty slots and where the solve is not finite.  Into ``amp`` (Kc,)."""
    Kc = amp.shape[0]
    L = y.shape[0]
    for a in range(Kc):
        rhs[a, 0] = 0.0
        for b in range(Kc):
            mat[a, b] = 0.0
    for a in range(Kc):
        for i in range(L):
            wa = _column(m, lo, hi, has_bg, a, i) * sw[i]
            if wa == 0.0:
                continue
            rhs[a, 0] += wa * (y[i] * sw[i])
            for b in range(a, Kc):
                wb = _column(m, lo, hi, has_bg, b, i) * sw[i]
                mat[a, b] += wa * wb
    for a in range(Kc):
        for b in range(a):
            mat[a, b] = mat[b, a]
    top = mat[0, 0]
    for a in range(Kc):
        top = max(top, mat[a, a])
    ridge = 1e-12 * max(top, 1e-300)
    for a in range(Kc):
        mat[a, a] += ridge if _column_on(fam, has_bg, a) else 1.0
    lu_solve(mat, rhs, Kc, 1, piv)
    for a in range(Kc):
        v = rhs[a, 0]
        amp[a] = v if (_column_on(fam, has_bg, a) and math.isfinite(v)) else 0.0


@njit
def _project(fam, delay, lalp, d_lo, d_hi, l_lo, l_hi, sss_after_direct, first_is_direct):
    """:func:`decomposition.model.slotfit.project_slots` for one pixel, in place."""
    K = fam.shape[0]
    for k in range(K):
        delay[k] = min(max(delay[k], d_lo), d_hi)
        lalp[k] = min(max(lalp[k], l_lo), l_hi)
    if first_is_direct and fam[0] == FAM_GAUSS:
        for k in range(1, K):
            if fam[k] == FAM_GAUSS:
                delay[k] = max(delay[k], delay[0])
    if sss_after_direct:
        first = math.inf
        for k in range(K):
            if fam[k] == FAM_GAUSS:
                first = min(first, delay[k])
        if math.isfinite(first):
            for k in range(K):
                if fam[k] == FAM_SSS:
                    delay[k] = max(delay[k], first)


@njit
def _no_light_turned_negative(fam, a_cur, a_new):
    """The sign rule: where every active slot's amplitude is positive, a step keeps them so."""
    K = fam.shape[0]
    for k in range(K):
        if fam[k] != FAM_NONE and not (a_cur[k] > 0.0):
            return True
    for k in range(K):
        if fam[k] != FAM_NONE and not (a_new[k] > 0.0):
            return False
    return True


@njit
def count_lm(t, counts, y, sw0, scale, held, fit, disp2, floor, fam, delay, lalp, lsig, amp, bg, held_d, held_l,
             d_lo, d_hi, l_lo, l_hi, sss_after_direct, first_is_direct, n_iter, lm_tol, lam0, lam_max,
             inst, cost_out, mu_out, iters, converged):
    """Fisher scoring of n pixels' slots on their Poisson deviance, each to its own convergence.

    Parameters
    ----------
    t : float64 (L,)                     sample times, ps
    counts : float64 (n, L)              the counts
    y : float64 (n, L)                   the normalised profiles (counts - held) / scale
    sw0 : float64 (n, L)                 square-root weights of the starting amplitudes' solve
    scale, held : float64 (n,)           counts per unit of ``y``; the offset already subtracted
    fit : bool (n, L)                    the samples that count
    disp2 : float64 (n,)                 the counts' noise scale squared (1: the Poisson law)
    floor : float                        the least expected count read (POISSON_FIT_FLOOR)
    fam : int8 (n, K)                    slot families
    delay, lalp : float64 (n, K)         the start, projected (and held values put in);
                                         overwritten by the fit
    lsig : float64 (n, K)                the slots' log widths (ln ps) for the Gaussian PSF's
                                         atoms, held (unread for a response's table atoms)
    amp : float64 (n, Kc)                written: the amplitudes (Kc = K + 1: with the offset's
                                         correction in column K, fitted where ``bg``)
    bg : bool (n,)                       the pixels that fit an offset correction
    held_d, held_l : bool (n, K)         the delays and log decay rates held
    d_lo, d_hi, l_lo, l_hi : float       the bounds of the delays (ps) and log decay rates
    sss_after_direct, first_is_direct : bool
                                         the ordering constraints (:func:`_project`)
    n_iter : int                         the most iterations per pixel
    lm_tol : float                       relative gain per fitted sample that ends a pixel
    lam0, lam_max : float                the starting damping; the damping that ends a pixel
    inst : tuple                         the atoms (:func:`decomposition.kernels.projected.instrument`)

    Outputs (written): ``cost_out`` (n,) the deviance (chi2 units), ``mu_out`` (n, L) the expected
    counts, ``iters`` (n,), ``converged`` (n,).

    Each step solves ``(J^T W J + lambda diag(J^T W J)) delta = J^T W (counts - mu)`` over the free
    parameters, W = 1 / the Poisson variance at the current model (floored at ``floor``, times the
    dispersion squared), the gradient nothing where the model is below the floor; it is kept where
    it lowers the deviance, is finite and turns no positive amplitude non-positive (the damping
    then shrinks by 3, else grows by 4).
    """
    n, L = counts.shape
    K = fam.shape[1]
    Kc = amp.shape[1]
    npar = 2 * K + Kc
    increasing = True
    for i in range(1, L):
        if not t[i] > t[i - 1]:
            increasing = False
    step_t = uniform_step(t, increasing)
    scratch = atom_scratch(inst)
    m_s = np.zeros((2, 3 * K + 2, L))
    lo_s = np.zeros((2, K), np.int64)
    hi_s = np.zeros((2, K), np.int64)
    mu_s = np.zeros((2, L))
    amp_s = np.zeros((2, Kc))
    th_d = np.zeros((2, K))
    th_l = np.zeros((2, K))
    mat = np.zeros((Kc, Kc))
    rhs1 = np.zeros((Kc, 1))
    piv = np.zeros(max(npar, Kc), np.int64)
    jac = np.zeros((npar, L))
    wr = np.zeros(L)
    w = np.zeros(L)
    lhs = np.zeros((npar, npar))
    rhs = np.zeros((npar, 1))
    free = np.zeros(npar, np.bool_)
    order = np.zeros(npar, np.int64)
    jlo = np.zeros(npar, np.int64)
    jhi = np.zeros(npar, np.int64)
    step = np.zeros(npar)
    lhs0 = np.zeros((npar, npar))
    rhs0 = np.zeros(npar)
    for p in range(n):
        f = fam[p]
        has_bg = Kc > K and bg[p]
        now = 0
        for k in range(K):
            th_d[now, k] = delay[p, k]
            th_l[now, k] = lalp[p, k]
        _render(t, m_s[now], lo_s[now], hi_s[now], f, th_d[now], th_l[now], lsig[p], inst, increasing, step_t,
                scratch)
        _start_amplitudes(m_s[now], lo_s[now], hi_s[now], f, has_bg, y[p], sw0[p], amp_s[now], mat, rhs1, piv)
        if Kc > K:
            # an offset of counts is light or dark counts: never below 0
            amp_s[now, K] = max(amp_s[now, K], -held[p] / scale[p])
        _model(m_s[now], lo_s[now], hi_s[now], amp_s[now], has_bg, scale[p], held[p], mu_s[now])
        dev = deviance_row(counts[p], mu_s[now], fit[p], floor) / disp2[p]
        nf = 0
        for k in range(K):
            free[k] = f[k] != FAM_NONE and not held_d[p, k]
            free[K + k] = f[k] == FAM_SSS and not held_l[p, k]
        for c in range(Kc):
            free[2 * K + c] = _column_on(f, has_bg, c)
        for j in range(npar):
            if free[j]:
                order[nf] = j
                nf += 1
        n_used = 0
        for i in range(L):
            if fit[p, i]:
                n_used += 1
        n_used = max(n_used, 1)
        lam = lam0
        it = 0
        conv = nf == 0
        fresh = False               # lhs0, rhs0 hold the normal equations at the current parameters
        while not conv and it < n_iter:
            m = m_s[now]
            lo = lo_s[now]
            hi = hi_s[now]
            mu = mu_s[now]
            a_cur = amp_s[now]
            sc = scale[p]
            if fresh:
                # a rejected step leaves the parameters, and so the equations, as they were: only
                # the damping changes
                for a in range(nf):
                    rhs[a, 0] = rhs0[a]
                    for b in range(nf):
                        lhs[a, b] = lhs0[a, b]
            else:
                for i in range(L):
                    if fit[p, i]:
                        w[i] = 1.0 / (max(mu[i], floor) * disp2[p])
                        wr[i] = w[i] * (counts[p, i] - mu[i]) if mu[i] >= floor else 0.0
                    else:
                        w[i] = 0.0
                        wr[i] = 0.0
                # the free parameters' Jacobian rows of the expected counts, each on its atom's
                # support [jlo, jhi) (the offset's on the whole axis); the products summed over
                # the overlap of two rows' supports
                for q in range(nf):
                    j = order[q]
                    k = j % K if j < 3 * K else K
                    jlo[q] = lo[k] if k < K else 0
                    jhi[q] = hi[k] if k < K else L
                    if j < K:
                        for i in range(jlo[q], jhi[q]):
                            jac[q, i] = a_cur[k] * m[K + k, i] * sc
                    elif j < 2 * K:
                        for i in range(jlo[q], jhi[q]):
                            jac[q, i] = a_cur[k] * m[3 * K, i] * sc
                    elif j < 3 * K:
                        for i in range(jlo[q], jhi[q]):
                            jac[q, i] = m[k, i] * sc
                    else:
                        for i in range(L):
                            jac[q, i] = sc
                for a in range(nf):
                    s = 0.0
                    for i in range(jlo[a], jhi[a]):
                        s += jac[a, i] * wr[i]
                    rhs[a, 0] = s
                    for b in range(a, nf):
                        s = 0.0
                        for i in range(max(jlo[a], jlo[b]), min(jhi[a], jhi[b])):
                            s += jac[a, i] * w[i] * jac[b, i]
                        lhs[a, b] = s
                        lhs[b, a] = s
                for a in range(nf):
                    rhs0[a] = rhs[a, 0]
                    for b in range(nf):
                        lhs0[a, b] = lhs[a, b]
                fresh = True
            top = 0.0
            for a in range(nf):
                top = max(top, lhs[a, a])
            for a in range(nf):
                # Marquardt's scaling, floored at 1e-12 of the largest (an atom that has left
                # the window has no column to scale by)
                dg = max(lhs[a, a], 1e-12 * top) + 1e-300
                lhs[a, a] += lam * dg
            lu_solve(lhs, rhs, nf, 1, piv)
            finite = True
            for j in range(npar):
                step[j] = 0.0
            for q in range(nf):
                step[order[q]] = rhs[q, 0]
                finite = finite and math.isfinite(rhs[q, 0])
            if not finite:
                for j in range(npar):
                    step[j] = 0.0
            nxt = 1 - now
            for k in range(K):
                th_d[nxt, k] = th_d[now, k] + step[k]
                th_l[nxt, k] = th_l[now, k] + step[K + k]
            _project(f, th_d[nxt], th_l[nxt], d_lo, d_hi, l_lo, l_hi, sss_after_direct, first_is_direct)
            for k in range(K):
                if held_d[p, k]:
                    th_d[nxt, k] = th_d[now, k]
                if held_l[p, k]:
                    th_l[nxt, k] = th_l[now, k]
            for c in range(Kc):
                amp_s[nxt, c] = a_cur[c] + step[2 * K + c] if free[2 * K + c] else 0.0
            if Kc > K:
                amp_s[nxt, K] = max(amp_s[nxt, K], -held[p] / sc)
            _render(t, m_s[nxt], lo_s[nxt], hi_s[nxt], f, th_d[nxt], th_l[nxt], lsig[p], inst, increasing, step_t,
                    scratch)
            _model(m_s[nxt], lo_s[nxt], hi_s[nxt], amp_s[nxt], has_bg, sc, held[p], mu_s[nxt])
            t_dev = deviance_row(counts[p], mu_s[nxt], fit[p], floor) / disp2[p]
            ok = finite and math.isfinite(t_dev) and t_dev < dev and _no_light_turned_negative(f, a_cur, amp_s[nxt])
            gain = dev - t_dev
            it += 1
            if ok:
                now = nxt
                fresh = False
                dev = t_dev
                lam /= 3.0
                if gain < lm_tol * t_dev / n_used:
                    conv = True
            else:
                lam *= 4.0
                if lam > lam_max:
                    conv = True
        for k in range(K):
            delay[p, k] = th_d[now, k]
            lalp[p, k] = th_l[now, k]
        for c in range(Kc):
            amp[p, c] = amp_s[now, c]
        for i in range(L):
            mu_out[p, i] = mu_s[now, i]
        cost_out[p] = dev
        iters[p] = it
        converged[p] = conv
