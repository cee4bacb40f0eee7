"""The variable-projection refine's damped loop, compiled: one pixel at a time, every iteration.

:func:`projected_lm` is the loop of :func:`decomposition.model.varpro.refine_block` for
point-sampled atoms of either instrument (the Gaussian PSF's kernels, a response's table): the
same damped Gauss-Newton steps on the projected normal equations (Levenberg-Marquardt with
Nielsen's gain-ratio damping), the same bounds, ordering constraints, priors, amplitude-sign
rule and stopping rules, with :func:`decomposition.kernels.projected.pixel_equations` evaluating
each trial.  The NumPy loop there steps every active pixel of a block at once and is the
reference; here a pixel runs to convergence before the next starts, so no interpreted work is
done per iteration and the loop releases the interpreter lock for its whole length.  The two
agree to rounding: the step's small linear solve is :func:`~decomposition.kernels.projected.lu_solve`
here, LAPACK's there.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import SSS_SLOT
from .jit import njit
from .projected import lu_solve, equation_scratch, pixel_equations, uniform_step

__all__ = ["projected_lm"]


@njit
def _larger(a, b):
    """np.maximum(a, b): the larger, NaN where either is NaN."""
    if a != a or b != b:
        return a + b
    return a if a >= b else b


@njit
def _onset_after_direct(theta, present, earliest):
    """varpro._onset_after_direct for one pixel's ``theta`` (P,), in place."""
    K = present.shape[0]
    if not earliest:
        if present[0] and present[SSS_SLOT]:
            theta[SSS_SLOT] = _larger(theta[SSS_SLOT], theta[0])
        return
    first = math.inf
    for slot in range(K):
        if slot != SSS_SLOT and present[slot]:
            v = theta[slot]
            if v != v:
                first = v
                break
            first = min(first, v)
    if present[SSS_SLOT] and math.isfinite(first):
        theta[SSS_SLOT] = _larger(theta[SSS_SLOT], first)


@njit
def _keep_order(theta, present):
    """varpro._keep_order for one pixel's ``theta`` (P,), in place."""
    K = present.shape[0]
    prev = theta[0] if present[0] else -math.inf
    for slot in range(2, K):
        if present[slot]:
            d = _larger(theta[slot], prev)
            theta[slot] = d
            prev = d


@njit
def _with_prior(p, theta, rss, a, g, prior_v, prior_mean, prior_weight):
    """varpro._with_prior for pixel ``p``: its pseudo-observations' terms added to ``rss`` (returned)
    and to ``a`` (P, P) and ``g`` (P,) in place."""
    P = theta.shape[0]
    for k in range(prior_v.shape[0]):
        w = prior_weight[k, p]
        dd = -prior_mean[k, p]
        for j in range(P):
            dd += theta[j] * prior_v[k, j]
        for i in range(P):
            for j in range(P):
                a[i, j] += w * (prior_v[k, i] * prior_v[k, j])
            g[i] += (w * dd) * prior_v[k, i]
        rss = rss + w * dd * dd
    return rss


@njit
def _violations(c, present):
    """varpro._amp_violations for one pixel: its present slots whose amplitude is not positive."""
    v = 0
    for k in range(present.shape[0]):
        if present[k] and not (c[k] > 0.0):
            v += 1
    return v


@njit
def _all_finite(a):
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            if not math.isfinite(a[i, j]):
                return False
    return True


@njit
def projected_lm(t, y, theta, present, free, sw, bg, amp, assign, dslot, shared, increasing, lo, hi, ftol, lam0,
                 max_iter, positive, sss_after_direct, earliest, keep_order, prior_v, prior_mean, prior_weight,
                 c_out, rss_out, viol_out, iters, converged, cur, r_out, inst):
    """Levenberg-Marquardt over n pixels' nonlinear parameters, each to its own convergence.

    Parameters
    ----------
    t : float64 (L,)                 sample times, ps
    y : float64 (n, L)               normalised, weighted data
    theta : float64 (n, P)           the starting parameters, feasible (clipped, ordered);
                                     overwritten by the refined ones
    present, free, sw, bg, amp, assign, dslot, shared, increasing, inst
                                     as :func:`decomposition.kernels.projected.projected_normal_equations`
    lo, hi : float64 (P,)            the bounds of the free parameters
    ftol : float64 (n,)              relative RSS decrease below which an accepted step ends a pixel
    lam0 : float                     the starting damping
    max_iter : int                   the most iterations per pixel
    positive : bool                  a step may not add a non-positive amplitude
    sss_after_direct, earliest, keep_order : bool
                                     the ordering constraints of varpro.refine_block
    prior_v : float64 (m, P)         the m pseudo-observations on v . theta ...
    prior_mean, prior_weight : float64 (m, n)
                                     ... their means and weights per pixel (weight 0: none)

    Outputs (written): ``c_out`` (n, K) the amplitudes at the final parameters, ``rss_out`` (n,)
    their objective (RSS and priors' terms), ``viol_out`` (n,) their non-positive amplitudes,
    ``iters`` (n,) the iterations run, ``converged`` (n,); with ``r_out`` (2n, L) (else (0, L)) the
    weighted residual of the final parameters in row p + n ``cur[p]`` (the other row holds the
    last trial's), as varpro.refine_block keeps them.
    """
    n, P = theta.shape
    L = y.shape[1]
    K = present.shape[1]
    has_amp = amp.shape[0] == n
    has_r = r_out.shape[0] == 2 * n
    work = equation_scratch(L, K, P, True, inst)
    step_t = uniform_step(t, increasing)
    no_amp = np.zeros(K)
    r_own = np.empty(L)
    cs = np.zeros((2, K))
    a_s = np.zeros((2, P, P))
    g_s = np.zeros((2, P))
    trial = np.empty(P)
    step = np.empty(P)
    dscale = np.empty(P)
    lhs = np.empty((P, P))
    rhs = np.empty((P, 1))
    piv = np.zeros(P, np.int64)
    for p in range(n):
        amp_p = amp[p] if has_amp else no_amp
        th = theta[p]
        fr = free[p]
        ynorm2 = 0.0
        for i in range(L):
            ynorm2 += y[p, i] * y[p, i]
        now = 0                                  # the buffers (cs, a_s, g_s) of the current fit
        cur[p] = 0
        rss = pixel_equations(t, y, p, th, present[p], fr, sw, bg[p], amp_p, has_amp, assign, dslot, shared,
                              increasing, True, cs[now], a_s[now], g_s[now], r_out[p] if has_r else r_own, inst,
                              step_t, work)
        rss = _with_prior(p, th, rss, a_s[now], g_s[now], prior_v, prior_mean, prior_weight)
        viol = _violations(cs[now], present[p]) if positive else 0
        lam = lam0
        nu = 2.0
        it = 0
        any_free = False
        for j in range(P):
            any_free = any_free or fr[j]
        done = not (any_free and math.isfinite(rss))
        while not done and it < max_iter:
            a = a_s[now]
            g = g_s[now]
            top = a[0, 0]
            for j in range(P):
                top = _larger(top, a[j, j])
            for j in range(P):
                dscale[j] = _larger(a[j, j], 1e-12 * top + 1e-300)
            for i in range(P):
                for j in range(P):
                    lhs[i, j] = a[i, j] if (fr[i] and fr[j]) else 0.0
                lhs[i, i] = (a[i, i] + lam * dscale[i]) if fr[i] else 1.0
                rhs[i, 0] = -g[i] if fr[i] else 0.0
            lu_solve(lhs, rhs, P, 1, piv)
            for j in range(P):
                step[j] = rhs[j, 0]
                v = th[j] + step[j]
                if v < lo[j]:
                    v = lo[j]
                if v > hi[j]:
                    v = hi[j]
                trial[j] = v
            if sss_after_direct:
                _onset_after_direct(trial, present[p], earliest)
            if keep_order:
                _keep_order(trial, present[p])
            for j in range(P):
                if not fr[j]:
                    trial[j] = th[j]
            nxt = 1 - now
            rss_t = pixel_equations(t, y, p, trial, present[p], fr, sw, bg[p], amp_p, has_amp, assign, dslot, shared,
                                    increasing, True, cs[nxt], a_s[nxt], g_s[nxt],
                                    r_out[p + n * (1 - cur[p])] if has_r else r_own, inst, step_t, work)
            rss_t = _with_prior(p, trial, rss_t, a_s[nxt], g_s[nxt], prior_v, prior_mean, prior_weight)
            viol_t = _violations(cs[nxt], present[p]) if positive else 0
            ok = math.isfinite(rss_t) and _all_finite(a_s[nxt]) and viol_t <= viol
            accept = ok and rss_t < rss
            it += 1
            gain = (rss - rss_t) / _larger(rss, 1e-300)
            pred = 0.0
            damp = 0.0
            for j in range(P):
                pred -= step[j] * g[j]
                damp += step[j] * dscale[j] * step[j]
            pred += lam * damp
            rho = (rss - rss_t) / _larger(pred, 1e-300)
            if accept:
                for j in range(P):
                    th[j] = trial[j]
                rss = rss_t
                viol = viol_t
                now = nxt
                cur[p] = 1 - cur[p]
                q = min(max(rho, 0.0), 1.0) if rho == rho else rho
                lam *= _larger(1.0 / 3.0, 1.0 - (2.0 * q - 1.0) ** 3)
                lam = _larger(lam, 1e-12)
                nu = 2.0
            else:
                lam *= nu
                nu *= 2.0
            # converged: an accepted step that no longer lowers the RSS noticeably, a fit exact to
            # rounding, or damping so large that no step helps
            if (accept and gain < ftol[p]) or rss <= 1e-26 * ynorm2 or (not accept and lam > 1e12):
                done = True
        converged[p] = done
        iters[p] = it
        for k in range(K):
            c_out[p, k] = cs[now, k]
        rss_out[p] = rss
        viol_out[p] = viol

