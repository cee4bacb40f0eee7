"""Compiled variable-projection Levenberg-Marquardt of response atoms, one pixel at a time.

The least-squares fit of :func:`decomposition.response.refine.fit_slots` as one compiled loop
over pixels (:func:`decomposition.kernels.jit.njit`, no fastmath: the same bits on every run):
for each pixel its atoms and their delay / log-alpha derivatives are rendered from the
response's table (:func:`decomposition.kernels.response.shifted_row` /
:func:`~decomposition.kernels.response.sss_row`) into buffers of its own active slots only,
the amplitudes solved by the weighted normal equations of the active columns (ridge
``RIDGE`` x the largest diagonal; with a fitted offset a constant column more), and the delays
and log alphas moved by Levenberg-Marquardt on the projected residual (Kaufman's Jacobian
J = -P_perp G, G the columns a_k d phi_k / d theta_j; Marquardt's damping lambda diag(J^T J),
lambda from ``LAMBDA0``, / 3 on a kept step, x 4 on a refused one, the pixel stopped beyond
``LAMBDA_MAX`` or when a kept step gains less than ``lm_tol`` x its residual sum of squares
per fitted sample).  A step is kept only when it is finite and lowers the weighted residual
sum of squares; after each step the delays are clipped to their bounds, the shifted atoms
after slot 0 kept at or after it (``first_is_direct``) and the sss onset at or after the
earliest shifted atom (``sss_after_direct``).

These are the operations of the block-array form (a reference copy is kept by the tests), in
the same order per pixel, with the inactive slots' zero rows and columns left out; the linear
solves are Gaussian elimination with partial pivoting.  Iterates agree with the block form to
rounding (its matrix products are BLAS's, summed in another order).
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from .jit import njit
from .response import ResponseTable, polyphase, shifted_row, sss_row, uniform_stride

__all__ = ["response_lm", "RIDGE", "LAMBDA0", "LAMBDA_MAX"]

#: ridge of the amplitudes' normal matrix, relative to its largest diagonal
RIDGE = 1e-12
#: Marquardt's starting damping and the damping beyond which a pixel stops
LAMBDA0 = 1e-3
LAMBDA_MAX = 1e10


def response_lm(table: ResponseTable, t_ps, y, sw, fam, delay, lalp, fit_bg, *, n_iter: int, lm_tol: float,
                delay_bounds_ps: tuple, lalp_bounds: tuple, sss_after_direct: bool, first_is_direct: bool,
                held_delay=None, held_lalp=None):
    """Fit P pixels' slots by variable projection (see the module docstring).

    Parameters
    ----------
    table : ResponseTable              the response's table (:func:`~decomposition.kernels.response.response_table`)
    t_ps : ndarray (L,)                time axis, ps
    y, sw : ndarray (P, L)             profiles and square-root sample weights
    fam : ndarray (P, K) int8          slot families
    delay, lalp : ndarray (P, K)       starting delays (ps) and log alphas, within the constraints
    fit_bg : ndarray (P,) bool or None
        Pixels with a constant column (the offset, amplitude column K); None: no such column.
    n_iter, lm_tol, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct
        As :func:`decomposition.response.refine.fit_slots`.
    held_delay, held_lalp : ndarray (P, K) bool, optional
        Slots whose delay / log alpha is held at the value given: not a parameter of the fit,
        and left where it is by the constraints' projection.

    Returns
    -------
    delay, lalp : ndarray (P, K)   final slots (inactive slots as given)
    amp : ndarray (P, Kc)          amplitudes (Kc = K + 1 with ``fit_bg``; 0 in inactive columns)
    cost : ndarray (P,)            weighted residual sum of squares
    resid : ndarray (P, L)         weighted residual sw * (y - model)
    iterations : ndarray (P,) int64
    converged : ndarray (P,) bool
    """
    t = np.ascontiguousarray(t_ps, np.float64)
    y = np.ascontiguousarray(y, np.float64)
    sw = np.ascontiguousarray(sw, np.float64)
    fam = np.ascontiguousarray(fam, np.int8)
    P, K = fam.shape
    delay = np.array(delay, np.float64, order="C", copy=True)
    lalp = np.array(lalp, np.float64, order="C", copy=True)
    has_bg = fit_bg is not None
    bg = np.ascontiguousarray(np.broadcast_to(fit_bg, (P,)) if has_bg else np.zeros(P, bool), np.bool_)
    Kc = K + 1 if has_bg else K
    amp = np.zeros((P, Kc))
    cost = np.zeros(P)
    resid = np.zeros((P, t.size))
    iters = np.zeros(P, np.int64)
    conv = np.zeros(P, np.bool_)
    h_d = np.zeros((P, K), np.bool_) if held_delay is None else np.ascontiguousarray(held_delay, np.bool_)
    h_l = np.zeros((P, K), np.bool_) if held_lalp is None else np.ascontiguousarray(held_lalp, np.bool_)
    stride = uniform_stride(t, table.step_ps)
    vpp, spp = polyphase(table, stride)
    _lm_pixels(table.value, table.slope, table.start_ps, table.step_ps, table.n_steps, 1.0 / table.peak_per_ps,
               t, stride, vpp, spp, y, sw, fam, delay, lalp, bg, has_bg, int(n_iter), float(lm_tol),
               float(delay_bounds_ps[0]), float(delay_bounds_ps[1]), float(lalp_bounds[0]), float(lalp_bounds[1]),
               bool(sss_after_direct), bool(first_is_direct), h_d, h_l, amp, cost, resid, iters, conv)
    return delay, lalp, amp, cost, resid, iters, conv


@njit
def _clip(x, lo, hi):
    return min(max(x, lo), hi)


@njit
def _project(fam, nd, nl, K, d_lo, d_hi, l_lo, l_hi, sss_after, first_direct):
    """The constraints of one pixel's trial slots, in place (as the block form's ``_project``)."""
    for k in range(K):
        nd[k] = _clip(nd[k], d_lo, d_hi)
        nl[k] = _clip(nl[k], l_lo, l_hi)
    if first_direct and fam[0] == FAM_GAUSS:
        d0 = nd[0]
        for k in range(1, K):
            if fam[k] == FAM_GAUSS:
                nd[k] = max(nd[k], d0)
    if sss_after:
        first = np.inf
        for k in range(K):
            if fam[k] == FAM_GAUSS and nd[k] < first:
                first = nd[k]
        if first < np.inf:
            for k in range(K):
                if fam[k] == FAM_SSS:
                    nd[k] = max(nd[k], first)


@njit
def _render(value, slope, start, h, n_steps, scale, t, stride, vpp, spp, fam, cols, n_slots, nd, nl, phi, dd, dl, da, s, r, E):
    """Atoms and derivatives of the active slots ``cols[:n_slots]`` into rows 0 .. n_slots - 1."""
    L = t.size
    for i in range(n_slots):
        k = cols[i]
        if fam[k] == FAM_GAUSS:
            shifted_row(value, slope, start, h, n_steps, t, stride, vpp, spp, nd[k], scale, True, phi[i], dd[i])
            for l in range(L):
                dl[i, l] = 0.0
        else:
            alpha = math.exp(nl[k])
            sss_row(value, slope, start, h, n_steps, t, stride, vpp, spp, nd[k], alpha, scale, True, phi[i], dd[i],
                    da, s, r, E)
            for l in range(L):
                dl[i, l] = da[l] * alpha


@njit
def _invert(m, n, out, work):
    """Inverse of ``m[:n, :n]`` into ``out`` by Gauss-Jordan elimination with partial pivoting
    (a zero pivot leaves non-finite values, which the callers refuse)."""
    for i in range(n):
        for j in range(n):
            work[i, j] = m[i, j]
            out[i, j] = 1.0 if i == j else 0.0
    for c in range(n):
        piv = c
        best = abs(work[c, c])
        for i in range(c + 1, n):
            if abs(work[i, c]) > best:
                best = abs(work[i, c])
                piv = i
        if piv != c:
            for j in range(n):
                tmp = work[c, j]
                work[c, j] = work[piv, j]
                work[piv, j] = tmp
                tmp = out[c, j]
                out[c, j] = out[piv, j]
                out[piv, j] = tmp
        inv_p = 1.0 / work[c, c]
        for j in range(n):
            work[c, j] *= inv_p
            out[c, j] *= inv_p
        for i in range(n):
            if i != c:
                f = work[i, c]
                if f != 0.0:
                    for j in range(n):
                        work[i, j] -= f * work[c, j]
                        out[i, j] -= f * out[c, j]


@njit
def _solve(a, b, n, x, work):
    """x = a[:n, :n]^-1 b[:n] by Gaussian elimination with partial pivoting (``work`` (n, n + 1))."""
    for i in range(n):
        for j in range(n):
            work[i, j] = a[i, j]
        work[i, n] = b[i]
    for c in range(n):
        piv = c
        best = abs(work[c, c])
        for i in range(c + 1, n):
            if abs(work[i, c]) > best:
                best = abs(work[i, c])
                piv = i
        if piv != c:
            for j in range(n + 1):
                tmp = work[c, j]
                work[c, j] = work[piv, j]
                work[piv, j] = tmp
        for i in range(c + 1, n):
            f = work[i, c] / work[c, c]
            if f != 0.0:
                for j in range(c, n + 1):
                    work[i, j] -= f * work[c, j]
    for i in range(n - 1, -1, -1):
        acc = work[i, n]
        for j in range(i + 1, n):
            acc -= work[i, j] * x[j]
        x[i] = acc / work[i, i]


@njit
def _dot(x, y, L):
    """sum_l x[l] y[l] over l < L in eight interleaved partial sums (lane l mod 8, each in order
    of l), combined pairwise at the end: the lanes fill vector registers, and the sum is the
    same bits on every run."""
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    a4 = 0.0
    a5 = 0.0
    a6 = 0.0
    a7 = 0.0
    n8 = L - L % 8
    for l in range(0, n8, 8):
        a0 += x[l] * y[l]
        a1 += x[l + 1] * y[l + 1]
        a2 += x[l + 2] * y[l + 2]
        a3 += x[l + 3] * y[l + 3]
        a4 += x[l + 4] * y[l + 4]
        a5 += x[l + 5] * y[l + 5]
        a6 += x[l + 6] * y[l + 6]
        a7 += x[l + 7] * y[l + 7]
    for l in range(n8, L):
        a0 += x[l] * y[l]
    return ((a0 + a4) + (a1 + a5)) + ((a2 + a6) + (a3 + a7))


@njit
def _cross(x, nx, y, ny, sym, out):
    """out[i, j] = sum_l x[i, l] y[j, l] for i < nx, j < ny (with ``sym`` only j <= i, mirrored),
    each by :func:`_dot`."""
    L = x.shape[1]
    for i in range(nx):
        xi = x[i]
        for j in range(i + 1 if sym else ny):
            v = _dot(xi, y[j], L)
            out[i, j] = v
            if sym:
                out[j, i] = v


@njit
def _amplitudes(phi, n_cols, bg_col, yw, swp, pw, m, minv, work, rhs, amp, resid):
    """Weighted least-squares amplitudes of the columns ``phi[:n_cols]`` (and the constant
    column last where ``bg_col``): fills ``pw`` (the weighted columns), ``minv``, ``amp``,
    ``resid`` (``rhs`` (n, 1) scratch); returns the residual sum of squares."""
    L = yw.size
    n = n_cols + 1 if bg_col else n_cols
    for i in range(n_cols):
        for l in range(L):
            pw[i, l] = phi[i, l] * swp[l]
    if bg_col:
        for l in range(L):
            pw[n_cols, l] = swp[l]
    _cross(pw, n, pw, n, True, m)
    big = 0.0
    for i in range(n):
        if m[i, i] > big:
            big = m[i, i]
    ridge = RIDGE * max(big, 1e-300)
    for i in range(n):
        m[i, i] += ridge
    _invert(m, n, minv, work)
    _cross(pw, n, yw.reshape((1, L)), 1, False, rhs)
    for i in range(n):
        work[0, i] = rhs[i, 0]
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += minv[i, j] * work[0, j]
        amp[i] = acc if math.isfinite(acc) else 0.0
    for l in range(L):
        resid[l] = yw[l]
    for i in range(n):           # (per sample in the order of i, over whole rows: vector loops)
        a_i = amp[i]
        pw_i = pw[i]
        for l in range(L):
            resid[l] -= a_i * pw_i[l]
    return _dot(resid, resid, L)


@njit
def _normal_equations(pw, minv, amp, res, dd, dl, swp, nc, npar, par_row, par_lalp, L, g, gp, q, b, proj, jtj, rhs,
                      jtr):
    """The projected Jacobian's normal matrix ``jtj`` and right-hand side ``jtr`` of one pixel's
    current slots (scratch ``g``, ``gp``, ``q``, ``b``, ``proj``, ``rhs``).  A refused step
    leaves the slots as they were, and so these: the next trial re-solves them with the new
    damping alone."""
    # G: the columns a_k d phi_k / d theta_j, weighted
    for j in range(npar):
        i = par_row[j]
        src = dl if par_lalp[j] else dd
        a_i = amp[i]
        for l in range(L):
            g[j, l] = a_i * src[i, l] * swp[l]
    # projected columns gp = g - pw^T minv (pw g^T)
    _cross(pw, nc, g, npar, False, q)
    for j in range(npar):
        for k in range(nc):
            acc = 0.0
            for i in range(nc):
                acc += q[i, j] * minv[i, k]
            b[j, k] = acc
    # (the sum over k per sample, in the order of k, over whole rows: vector loops)
    for j in range(npar):
        for l in range(L):
            proj[l] = 0.0
        for k in range(nc):
            b_jk = b[j, k]
            pw_k = pw[k]
            for l in range(L):
                proj[l] += b_jk * pw_k[l]
        for l in range(L):
            gp[j, l] = g[j, l] - proj[l]
    _cross(gp, npar, gp, npar, True, jtj)
    _cross(g, npar, res.reshape((1, L)), 1, False, rhs)
    for j in range(npar):
        jtr[j] = rhs[j, 0]


@njit
def _lm_pixels(value, slope, start, h, n_steps, scale, t, stride, vpp, spp, y, sw, fam, delay, lalp, fit_bg, has_bg, n_iter, lm_tol,
               d_lo, d_hi, l_lo, l_hi, sss_after, first_direct, h_d, h_l, amp_out, cost_out, resid_out, iters_out,
               conv_out):
    P, K = fam.shape
    L = t.size
    nc_max = K + 1
    n_par_max = 2 * K
    # the current evaluation and a trial's (swapped on a kept step)
    phi = np.zeros((K, L))
    dd = np.zeros((K, L))
    dl = np.zeros((K, L))
    pw = np.zeros((nc_max, L))
    minv = np.zeros((nc_max, nc_max))
    amp = np.zeros(nc_max)
    res = np.zeros(L)
    t_phi = np.zeros((K, L))
    t_dd = np.zeros((K, L))
    t_dl = np.zeros((K, L))
    t_pw = np.zeros((nc_max, L))
    t_minv = np.zeros((nc_max, nc_max))
    t_amp = np.zeros(nc_max)
    t_res = np.zeros(L)
    m = np.zeros((nc_max, nc_max))
    rhs = np.zeros((max(nc_max, n_par_max), 1))
    work = np.zeros((max(nc_max, n_par_max), max(nc_max, n_par_max) + 1))
    da = np.zeros(L)
    proj = np.zeros(L)
    s = np.zeros(n_steps + 1)
    r = np.zeros(n_steps + 1)
    E = np.zeros(5)
    yw = np.zeros(L)
    cols = np.zeros(K, np.int64)
    par_row = np.zeros(n_par_max, np.int64)      # the slot row (index into cols) of each free parameter
    par_lalp = np.zeros(n_par_max, np.bool_)    # a log alpha (else a delay)
    g = np.zeros((n_par_max, L))
    gp = np.zeros((n_par_max, L))
    q = np.zeros((nc_max, n_par_max))
    b = np.zeros((n_par_max, nc_max))
    jtj = np.zeros((n_par_max, n_par_max))
    jtr = np.zeros(n_par_max)
    lhs = np.zeros((n_par_max, n_par_max))
    step = np.zeros(n_par_max)
    nd = np.zeros(K)
    nl = np.zeros(K)
    for p in range(P):
        f = fam[p]
        swp = sw[p]
        n_used = 0
        for l in range(L):
            yw[l] = y[p, l] * swp[l]
            if swp[l] > 0.0:
                n_used += 1
        n_used = max(n_used, 1)
        ns = 0
        for k in range(K):
            if f[k] != FAM_NONE:
                cols[ns] = k
                ns += 1
        npar = 0
        for i in range(ns):
            if h_d[p, cols[i]]:
                continue
            par_row[npar] = i
            par_lalp[npar] = False
            npar += 1
        for i in range(ns):
            if f[cols[i]] == FAM_SSS and not h_l[p, cols[i]]:
                par_row[npar] = i
                par_lalp[npar] = True
                npar += 1
        bg_col = has_bg and fit_bg[p]
        nc = ns + 1 if bg_col else ns
        for k in range(K):
            nd[k] = delay[p, k]
            nl[k] = lalp[p, k]
        _render(value, slope, start, h, n_steps, scale, t, stride, vpp, spp, f, cols, ns, nd, nl, phi, dd, dl, da, s,
                r, E)
        cost = _amplitudes(phi, ns, bg_col, yw, swp, pw, m, minv, work, rhs, amp, res)
        lam = LAMBDA0
        conv = npar == 0
        it = 0
        stale = True        # the Jacobian's products are those of the current slots once formed
        for _ in range(n_iter):
            if conv:
                break
            if stale:
                _normal_equations(pw, minv, amp, res, dd, dl, swp, nc, npar, par_row, par_lalp, L, g, gp, q, b,
                                  proj, jtj, rhs, jtr)
                stale = False
            for j in range(npar):
                for i in range(npar):
                    lhs[j, i] = jtj[j, i]
                lhs[j, j] += lam * (jtj[j, j] + 1e-300)
            _solve(lhs, jtr, npar, step, work)
            finite = True
            for j in range(npar):
                if not math.isfinite(step[j]):
                    finite = False
            for k in range(K):
                nd[k] = delay[p, k]
                nl[k] = lalp[p, k]
            if finite:
                for j in range(npar):
                    k = cols[par_row[j]]
                    if par_lalp[j]:
                        nl[k] += step[j]
                    else:
                        nd[k] += step[j]
            _project(f, nd, nl, K, d_lo, d_hi, l_lo, l_hi, sss_after, first_direct)
            for k in range(K):
                if h_d[p, k]:
                    nd[k] = delay[p, k]
                if h_l[p, k]:
                    nl[k] = lalp[p, k]
            _render(value, slope, start, h, n_steps, scale, t, stride, vpp, spp, f, cols, ns, nd, nl, t_phi, t_dd,
                    t_dl, da, s, r, E)
            t_cost = _amplitudes(t_phi, ns, bg_col, yw, swp, t_pw, m, t_minv, work, rhs, t_amp, t_res)
            ok = finite and math.isfinite(t_cost) and t_cost < cost
            gain = cost - t_cost
            it += 1
            if ok:
                for k in range(K):
                    delay[p, k] = nd[k]
                    lalp[p, k] = nl[k]
                cost = t_cost
                phi, t_phi = t_phi, phi
                dd, t_dd = t_dd, dd
                dl, t_dl = t_dl, dl
                pw, t_pw = t_pw, pw
                minv, t_minv = t_minv, minv
                amp, t_amp = t_amp, amp
                res, t_res = t_res, res
                stale = True
                lam /= 3.0
                if gain < lm_tol * t_cost / n_used:
                    conv = True
            else:
                lam *= 4.0
                if lam > LAMBDA_MAX:
                    conv = True
        for i in range(ns):
            amp_out[p, cols[i]] = amp[i]
        if bg_col:
            amp_out[p, K] = amp[ns]
        cost_out[p] = cost
        for l in range(L):
            resid_out[p, l] = res[l]
        iters_out[p] = it
        conv_out[p] = conv
