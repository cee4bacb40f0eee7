"""The variable-projection refine's L-length work, compiled: amplitudes, RSS and normal equations.

:func:`projected_normal_equations` is :func:`decomposition.model.varpro._evaluate_chunk` for
point-sampled kernels, one pixel at a time: the stacked rows [Phi; dPhi; y] of
:func:`decomposition.model.varpro.design_rows` (each kernel on its support only, the values and
derivatives of :func:`decomposition.kernels.derivatives.kernel_derivatives`, weighted), the rows
projected onto the complement of the weighted constant where a pixel fits an offset, the
amplitude prior's extra sample, one Gram product summed over the overlap of the rows' supports,
the amplitudes from the ridge-regularised Gram matrix, the weighted residual and its sum of
squares, and Kaufman's normal equations J^T J and gradient J^T r over the layout's nonlinear
parameters.  The same arithmetic as the NumPy reference path to rounding (a different order of
summation, and the erfcx of :func:`decomposition.kernels.jit.erfcx`); nothing of size
(pixels, rows, time) is allocated.
"""

# One module over 600 lines on purpose: the refine's evaluation, its never-worse reference and the
# Fisher information's Gram product render the same rows on the same supports, for either
# instrument's atoms (the Gaussian PSF's analytic kernels, a response's table).
from __future__ import annotations

import math

import numpy as np

from ..constants import SSS_SLOT
from .jit import erfcx, njit
from .response import ResponseTable, polyphase, response_table, shifted_row, sss_row, uniform_stride

__all__ = ["projected_normal_equations", "pixel_equations", "equation_scratch", "lu_solve", "given_rss",
           "SUPPORT_WIDTHS", "support_window", "kernel_rows", "uniform_step", "row_dot", "fisher_gram", "instrument",
           "response_instrument", "GAUSSIAN_PSF", "atom_rows", "atom_scratch"]

#: widths from its centre (or before the sss onset) beyond which a kernel is taken as zero: every
#: value and derivative there is below 1e-29 of its peak (exp(-72) times a power of 12), nothing
#: any sum of the refine or of the neighbour screen could carry to rounding
SUPPORT_WIDTHS = 12.0

_SQRT_PI_2 = math.sqrt(math.pi / 2.0)
_INV_SQRT_2 = 1.0 / math.sqrt(2.0)
# as kernels.derivatives: the exp floor, where erfc(u) is exactly 2, where g is at the floor
_EXP_FLOOR = -700.0
_ERFC_IS_TWO = -6.0
_Z_NEGLIGIBLE = 37.5
_G_FLOOR = math.exp(_EXP_FLOOR)
#: samples between fresh evaluations of the sss tail's stepped exponential
_RESTART = 8


def _readonly(a):
    v = np.ascontiguousarray(a, np.float64).view()
    v.setflags(write=False)
    return v


def instrument(table: ResponseTable | None, t) -> tuple:
    """The instrument argument of :func:`projected_normal_equations` and :func:`given_rss`: the
    atoms they render.  ``table`` None: the Gaussian PSF's analytic kernels (:data:`GAUSSIAN_PSF`);
    a :class:`decomposition.kernels.response.ResponseTable`: the response's table atoms
    (:func:`~decomposition.kernels.response.shifted_row` / :func:`~decomposition.kernels.response.sss_row`,
    unit peak) on the time axis ``t`` (L,) -- (value, slope, polyphase values, polyphase slopes,
    start ps, node step ps, window ps, 1 / peak, nodes, the axis' stride in nodes)."""
    if table is None:
        return GAUSSIAN_PSF
    stride = int(uniform_stride(np.ascontiguousarray(t, np.float64), table.step_ps))
    vpp, spp = polyphase(table, stride)
    return (_readonly(table.value), _readonly(table.slope), _readonly(vpp), _readonly(spp), float(table.start_ps),
            float(table.step_ps), float(table.n_steps * table.step_ps), 1.0 / float(table.peak_per_ps),
            int(table.n_steps), stride)


def response_instrument(irf, t) -> tuple:
    """:func:`instrument` of a measured response ``irf`` (a :class:`core.irf.InstrumentResponse`;
    its :func:`~decomposition.kernels.response.response_table`) on the time axis ``t`` (L,); None:
    the Gaussian PSF's (:data:`GAUSSIAN_PSF`)."""
    return instrument(None if irf is None else response_table(irf), t)


#: the instrument argument of the Gaussian PSF: no table (the analytic kernels of :func:`kernel_rows`)
GAUSSIAN_PSF = (_readonly(np.zeros(0)), _readonly(np.zeros(0)), _readonly(np.zeros((1, 1))),
                _readonly(np.zeros((1, 1))), 0.0, 0.0, 0.0, 0.0, 0, 0)


@njit
def _first_at_least(t, v):
    """np.searchsorted(t, v, "left") for increasing ``t``."""
    lo, hi = 0, t.size
    while lo < hi:
        mid = (lo + hi) // 2
        if t[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit
def _first_above(t, v):
    """np.searchsorted(t, v, "right") for increasing ``t``."""
    lo, hi = 0, t.size
    while lo < hi:
        mid = (lo + hi) // 2
        if t[mid] <= v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit
def row_dot(m, a, b, i0, i1):
    """sum_i m[a, i] m[b, i] over [i0, i1), in four interleaved partial sums (four independent
    chains of additions instead of one)."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    i = i0
    while i + 4 <= i1:
        s0 += m[a, i] * m[b, i]
        s1 += m[a, i + 1] * m[b, i + 1]
        s2 += m[a, i + 2] * m[b, i + 2]
        s3 += m[a, i + 3] * m[b, i + 3]
        i += 4
    while i < i1:
        s0 += m[a, i] * m[b, i]
        i += 1
    return (s0 + s1) + (s2 + s3)


@njit
def lu_solve(a, b, n, m, piv):
    """Solve a x = b in place (``a`` (n, n) overwritten by its LU factors, ``b`` (n, m) by x):
    Gaussian elimination with partial pivoting, as LAPACK's gesv (a few rows, a plain loop)."""
    for j in range(n):
        p = j
        big = abs(a[j, j])
        for i in range(j + 1, n):
            if abs(a[i, j]) > big:
                big = abs(a[i, j])
                p = i
        piv[j] = p
        if p != j:
            for k in range(n):
                tmp = a[j, k]
                a[j, k] = a[p, k]
                a[p, k] = tmp
            for k in range(m):
                tmp = b[j, k]
                b[j, k] = b[p, k]
                b[p, k] = tmp
        d = a[j, j]
        for i in range(j + 1, n):
            f = a[i, j] / d
            a[i, j] = f
            for k in range(j + 1, n):
                a[i, k] -= f * a[j, k]
            for k in range(m):
                b[i, k] -= f * b[j, k]
    for k in range(m):
        for i in range(n - 1, -1, -1):
            s = b[i, k]
            for q in range(i + 1, n):
                s -= a[i, q] * b[q, k]
            b[i, k] = s / a[i, i]


@njit
def uniform_step(t, increasing):
    """The bin width of a uniform increasing axis ``t`` (to 1e-9 of it), else 0: a uniform axis
    steps the sss tail's exponential (:func:`kernel_rows`)."""
    L = t.size
    if not increasing or L < 2:
        return 0.0
    step = (t[L - 1] - t[0]) / (L - 1)
    for i in range(1, L):
        if abs((t[i] - t[i - 1]) - step) > 1e-9 * step:
            return 0.0
    return step


@njit
def support_window(t, d, s, sss, increasing):
    """[j0, j1) of a kernel at delay ``d``, width ``s``: within :data:`SUPPORT_WIDTHS` widths
    of the delay (of the onset and after it for the sss), where every value and derivative
    is below 1e-29 of its peak and adds nothing to any sum to rounding; the whole axis where
    that is empty, the parameters are not finite or ``t`` is not increasing."""
    L = t.size
    half = SUPPORT_WIDTHS * s
    if not (increasing and math.isfinite(d) and math.isfinite(half)):
        return 0, L
    j0 = _first_at_least(t, d - half)
    j1 = L if sss else _first_above(t, d + half)
    if j1 <= j0:
        return 0, L
    return j0, j1


@njit
def kernel_rows(t, m, K, slot, sss, d, s, a, sw, has_sw, jac, j0, j1, step_t, log_scale=True):
    """Write slot ``slot``'s kernel (and with ``jac`` its derivative rows: K + slot the delay's,
    2K + slot the log width's, 3K the sss log decay rate's; without ``log_scale`` the width's
    and the decay rate's own) on [j0, j1) into ``m``, each times ``sw`` where ``has_sw``.

    The sss kernel's tail factor e = exp(alpha^2 sigma^2 / 2 - alpha x) is evaluated afresh
    every :data:`_RESTART` samples and stepped by exp(-alpha ``step_t``) in between (``step_t``
    the axis' bin width; 0: always afresh): a few ulp, not an exponential per sample."""
    rho = math.exp(-a * step_t) if step_t > 0.0 else 0.0
    fs = s if log_scale else 1.0
    fa = a if log_scale else 1.0
    e = 0.0
    stepped = _RESTART           # samples since e was evaluated afresh (_RESTART: evaluate now)
    for i in range(j0, j1):
        w = sw[i] if has_sw else 1.0
        x = t[i] - d
        z = x / s
        if not sss:
            g = math.exp(max(-0.5 * z * z, _EXP_FLOOR))
            m[slot, i] = g * w
            if jac:
                gz = g * z
                m[K + slot, i] = (gz / s) * w
                m[2 * K + slot, i] = ((gz * z / s) * fs) * w
            continue
        q = a * s
        u = (q - z) * _INV_SQRT_2
        zz = -0.5 * z * z
        g = math.exp(zz) if zz > _EXP_FLOOR else _G_FLOOR
        ez = q * (0.5 * q - z)
        if ez >= 0.0:
            e = 1.0
            stepped = _RESTART
        elif ez <= _EXP_FLOOR:
            e = _G_FLOOR
            stepped = _RESTART
        elif stepped < _RESTART - 1 and rho > 0.0:
            e *= rho
            stepped += 1
        else:
            e = math.exp(ez)
            stepped = 0
        h = 2.0 * e
        if u > _ERFC_IS_TWO and z > -_Z_NEGLIGIBLE:
            if u >= 0.0:
                h = g * erfcx(u)
            else:
                h = e * math.erfc(u)
        elif u >= 0.0:
            h = 0.0
        h *= _SQRT_PI_2 * s
        m[slot, i] = h * w
        if jac:
            m[K + slot, i] = (a * h - g) * w
            m[2 * K + slot, i] = ((h * ((1.0 + q * q) / s) - g * (q + z)) * fs) * w
            m[3 * K, i] = ((s * ((q - z) * h - s * g)) * fa) * w


@njit
def table_window(t, d, sss, inst, increasing):
    """[j0, j1) of a table atom at delay ``d`` (:func:`instrument`): the response's padded window
    shifted by ``d`` (from its start to the end of the axis for the sss); the whole axis where
    ``t`` is not increasing or ``d`` not finite."""
    L = t.size
    start = inst[4]
    span = inst[6]
    if not (increasing and math.isfinite(d)):
        return 0, L
    j0 = _first_at_least(t, d + start)
    j1 = L if sss else _first_at_least(t, d + start + span)
    if j1 <= j0:
        return 0, 0
    return j0, j1


@njit
def table_rows(t, m, K, slot, sss, d, a, inst, sw, has_sw, jac, j0, j1, s_buf, r_buf, E):
    """:func:`kernel_rows` for a response's table atoms (:func:`instrument`): slot ``slot``'s atom
    into row ``slot`` and, with ``jac``, its delay derivative into K + slot (the width's row 2K +
    slot is left alone: a response has no width, and the caller gives it no support), the sss
    log decay rate's derivative into 3K; each
    times ``sw`` on [j0, j1) where ``has_sw``.  ``s_buf``, ``r_buf`` (nodes + 1,) and ``E`` (5,)
    are the sss recursion's scratch."""
    value, slope, vpp, spp, start, h, _, scale, n_steps, stride = inst
    if not sss:
        if jac:
            shifted_row(value, slope, start, h, n_steps, t, stride, vpp, spp, d, scale, True, m[slot], m[K + slot])
        else:
            shifted_row(value, slope, start, h, n_steps, t, stride, vpp, spp, d, scale, False, m[slot], m[slot])
    elif jac:
        sss_row(value, slope, start, h, n_steps, t, stride, vpp, spp, d, a, scale, True, m[slot], m[K + slot],
                m[3 * K], s_buf, r_buf, E)
        for i in range(j0, j1):
            m[3 * K, i] *= a
    else:
        sss_row(value, slope, start, h, n_steps, t, stride, vpp, spp, d, a, scale, False, m[slot], m[slot], m[slot],
                s_buf, r_buf, E)
    if has_sw:
        for i in range(j0, j1):
            w = sw[i]
            m[slot, i] *= w
            if jac:
                m[K + slot, i] *= w
                if sss:
                    m[3 * K, i] *= w


@njit
def atom_scratch(inst):
    """The scratch of :func:`atom_rows` for the instrument ``inst`` (:func:`instrument`): the table
    sss recursion's two (nodes + 1,) buffers and its (5,) moments."""
    return np.empty(inst[8] + 1), np.empty(inst[8] + 1), np.empty(5)


@njit
def atom_rows(t, m, K, slot, sss, d, s, a, inst, sw, has_sw, jac, increasing, step_t, scratch):
    """Slot ``slot``'s atom, and with ``jac`` its derivative rows, into ``m`` on its support, for
    either instrument (:func:`instrument`): the Gaussian PSF's kernel of width ``s``
    (:func:`kernel_rows` on :func:`support_window`) or a response's table atom, whose ``s`` is not
    read (:func:`table_rows` on :func:`table_window`); ``scratch`` of :func:`atom_scratch`.
    -> the support [j0, j1)."""
    if inst[0].size > 0:
        j0, j1 = table_window(t, d, sss, inst, increasing)
        table_rows(t, m, K, slot, sss, d, a, inst, sw, has_sw, jac, j0, j1, scratch[0], scratch[1], scratch[2])
    else:
        j0, j1 = support_window(t, d, s, sss, increasing)
        kernel_rows(t, m, K, slot, sss, d, s, a, sw, has_sw, jac, j0, j1, step_t)
    return j0, j1


@njit
def projected_normal_equations(t, y, rows, theta, present, free, sw, bg, amp, assign, dslot, shared, increasing, jac,
                               c_out, rss_out, a_out, g_out, r_out, r_row, inst):
    """Amplitudes, RSS and (``jac``) the LM normal equations of n pixels at ``theta``.

    Parameters
    ----------
    t : float64 (L,)            sample times, ps
    y : float64 (m, L)          normalised, weighted data: pixel p's in row ``rows[p]``
    rows : int (n,)             the pixels' rows of ``y`` and ``sw``
    theta : float64 (n, P)      the layout's nonlinear parameters (delays, log widths, log alpha)
    present : bool (n, K)       the slots each pixel has
    free : bool (n, P)          the parameters each pixel moves
    sw : float64 (m, L)         square roots of the sample weights, rows as ``y`` ((0, L): none)
    bg : bool (n,)              the pixels that fit a constant offset too
    amp : float64 (n, K)        the amplitude prior's row ((0, K): none)
    assign : float64 (P, 2K+1)  the layout's map of parameters onto derivative rows
    dslot : int (2K+1,)         the slot of each derivative row
    shared : bool               one width per pixel (theta[:, K])
    increasing : bool           ``t`` increasing (else every kernel on the whole axis)
    jac : bool                  compute the normal equations too
    inst : tuple                the atoms (:func:`instrument`): the Gaussian PSF's (the widths
                                ``theta``'s) or a response's table atoms (the widths unused)

    Outputs (written): ``c_out`` (n, K) the amplitudes (0 where absent), ``rss_out`` (n,),
    ``a_out`` (n, P, P) J^T J and ``g_out`` (n, P) J^T r (with ``jac``), and pixel p's
    weighted residual (projected where it fits an offset) into row ``r_row[p]`` of ``r_out``
    (m, L) (``r_row`` (0,): not written).
    """
    n = theta.shape[0]
    L = y.shape[1]
    K = present.shape[1]
    has_amp = amp.shape[0] == n
    has_r = r_row.shape[0] == n
    P = theta.shape[1]
    work = equation_scratch(L, K, P, jac, inst)
    r_own = np.empty(L)
    no_amp = np.zeros(K)
    no_a = np.zeros((P, P))
    no_g = np.zeros(P)
    step_t = uniform_step(t, increasing)
    for p in range(n):
        rss_out[p] = pixel_equations(t, y, rows[p], theta[p], present[p], free[p], sw, bg[p],
                                     amp[p] if has_amp else no_amp, has_amp, assign, dslot, shared, increasing, jac,
                                     c_out[p], a_out[p] if jac else no_a, g_out[p] if jac else no_g,
                                     r_out[r_row[p]] if has_r else r_own, inst, step_t, work)


@njit
def equation_scratch(L, K, P, jac, inst):
    """The scratch of :func:`pixel_equations` for profiles of ``L`` samples, ``K`` slots and ``P``
    nonlinear parameters (``jac``: with the derivative rows), atoms ``inst`` (:func:`instrument`)."""
    Q = 2 * K + 1
    R = 3 * K + 2 if jac else K + 1
    return (np.zeros((R, L)), np.zeros(R, np.int64), np.zeros(R, np.int64), np.zeros((R, R)), np.zeros((K, K)),
            np.zeros((K, 1 + P)), np.zeros(K, np.int64), np.empty(L), np.zeros((P, Q)), np.zeros(Q), np.zeros((Q, P)),
            np.zeros((K, K)), np.zeros((K, P)), np.zeros(P, np.int64), np.zeros(Q, np.int64), atom_scratch(inst),
            np.empty(0))


@njit
def pixel_equations(t, y, yp, theta_p, present_p, free_p, sw, bg_p, amp_p, has_amp, assign, dslot, shared, increasing,
                    jac, c_p, a_p, g_p, r, inst, step_t, work):
    """One pixel of :func:`projected_normal_equations`: its data row ``yp`` of ``y`` (and ``sw``),
    its parameters ``theta_p`` (P,), slots ``present_p`` (K,), free parameters ``free_p`` (P,),
    offset flag ``bg_p`` and amplitude prior row ``amp_p`` (K,, read where ``has_amp``).  Writes
    its amplitudes into ``c_p`` (K,), with ``jac`` J^T J into ``a_p`` (P, P) and J^T r into ``g_p``
    (P,), its weighted residual into ``r`` (L,); ``step_t`` of :func:`uniform_step`, ``work`` of
    :func:`equation_scratch`.  -> the RSS."""
    m, lo, hi, mm, gram, rhs, piv, u, w, dr, vw, g2, bx, jl, ql, scratch, dummy = work
    L = y.shape[1]
    K = present_p.shape[0]
    P = theta_p.shape[0]
    Q = 2 * K + 1
    R = 3 * K + 2 if jac else K + 1
    has_sw = sw.shape[0] > 0
    table = inst[0].size > 0
    swp = sw[yp] if has_sw else dummy
    for row in range(R):
        lo[row] = 0
        hi[row] = 0
    lo[R - 1] = 0
    hi[R - 1] = L
    for i in range(L):
        m[R - 1, i] = y[yp, i]
    alpha_p = math.exp(theta_p[P - 1])
    for slot in range(K):
        if not present_p[slot]:
            continue
        d = theta_p[slot]
        sss = slot == SSS_SLOT
        s = 1.0 if table else math.exp(theta_p[K] if shared else theta_p[K + slot])
        j0, j1 = atom_rows(t, m, K, slot, sss, d, s, alpha_p, inst, swp, has_sw, jac, increasing, step_t, scratch)
        rows_here = (slot, K + slot, 2 * K + slot) if jac else (slot, slot, slot)
        for row in rows_here:
            lo[row] = j0
            hi[row] = j1
        if jac and table:
            # a response has no width: its row is empty (no sum reads it)
            lo[2 * K + slot] = 0
            hi[2 * K + slot] = 0
        if jac and sss:
            lo[3 * K] = j0
            hi[3 * K] = j1
    if bg_p:
        uu = 0.0
        for i in range(L):
            u[i] = swp[i] if has_sw else 1.0
            uu += u[i] * u[i]
        norm = math.sqrt(uu if uu > 0.0 else 1.0)
        for i in range(L):
            u[i] = u[i] / norm
        for row in range(R):
            if hi[row] <= lo[row]:
                continue
            acc = 0.0
            for i in range(lo[row], hi[row]):
                acc += m[row, i] * u[i]
            if row < R - 1:
                for i in range(0, lo[row]):
                    m[row, i] = 0.0
                for i in range(hi[row], L):
                    m[row, i] = 0.0
            for i in range(L):
                m[row, i] -= acc * u[i]
            lo[row] = 0
            hi[row] = L
    # the Gram product of the stacked rows over the overlaps of their supports
    for a in range(R):
        for b in range(a, R):
            if b == R - 1 and a >= K:
                # the derivative rows' products with the data are never read (J^T r is
                # taken against the residual below)
                continue
            acc = row_dot(m, a, b, max(lo[a], lo[b]), min(hi[a], hi[b]))
            if has_amp and a < K and b < K:
                acc += amp_p[a] * amp_p[b]
            mm[a, b] = acc
            mm[b, a] = acc
    # the amplitudes: the regularised Gram matrix (an identity row for an absent slot)
    top = 0.0
    for k in range(K):
        if present_p[k]:
            top = max(top, mm[k, k])
    for k in range(K):
        for j in range(K):
            gram[k, j] = mm[k, j] if (present_p[k] and present_p[j]) or k != j else 0.0
        gram[k, k] = (mm[k, k] + (1e-13 * top + 1e-300)) if present_p[k] else 1.0
        rhs[k, 0] = mm[k, R - 1]
    for k in range(K):
        for j in range(K):
            g2[k, j] = gram[k, j]
    lu_solve(g2, rhs, K, 1, piv)
    for k in range(K):
        c_p[k] = rhs[k, 0] if present_p[k] else 0.0
    # the residual, in its row of r_out where it is kept
    for i in range(L):
        r[i] = m[R - 1, i]
    for k in range(K):
        if present_p[k]:
            ck = c_p[k]
            for i in range(lo[k], hi[k]):
                r[i] -= ck * m[k, i]
    rss = 0.0
    for i in range(L):
        rss += r[i] * r[i]
    if has_amp:
        v = 0.0
        for k in range(K):
            v -= c_p[k] * amp_p[k]
        rss += v * v
    if not jac:
        return rss
    # the parameters the normal equations carry (jl, nj of them) and the derivative rows those
    # read (ql, nq): all of them for the Gaussian PSF's atoms; for a response's table atoms the
    # free parameters only (its widths are always held), whose rows and columns are the only
    # non-zero ones, and the rows that some free parameter maps onto
    nj = 0
    for j in range(P):
        if free_p[j] or not table:
            jl[nj] = j
            nj += 1
    nq = 0
    for qq in range(Q):
        live = not table
        for jj in range(nj):
            if assign[jl[jj], qq] != 0.0:
                live = True
        if live:
            ql[nq] = qq
            nq += 1
    for a in range(nq):
        qq = ql[a]
        sl = dslot[qq]
        fr = present_p[sl] if qq < 2 * K else present_p[SSS_SLOT]
        cq = c_p[sl] if fr else 0.0
        for jj in range(nj):
            j = jl[jj]
            w[j, qq] = assign[j, qq] * cq * (1.0 if free_p[j] else 0.0)
    # dPhi r over the derivative rows (the residual's extra sample has no derivative)
    for a in range(nq):
        row = K + ql[a]
        acc = 0.0
        for i in range(lo[row], hi[row]):
            acc += m[row, i] * r[i]
        dr[ql[a]] = acc
    # B W^T (rhs[:, 1 + j]) and its solve against the Gram matrix (bx[:, jj])
    for k in range(K):
        for jj in range(nj):
            j = jl[jj]
            acc = 0.0
            for b in range(nq):
                qq = ql[b]
                acc += mm[k, K + qq] * w[j, qq]
            rhs[k, 1 + j] = acc
            bx[k, jj] = acc
    for k in range(K):
        for j in range(K):
            g2[k, j] = gram[k, j]
    lu_solve(g2, bx, K, nj, piv)
    for a in range(nq):
        qa = ql[a]
        for jj in range(nj):
            j = jl[jj]
            acc = 0.0
            for b in range(nq):
                qb = ql[b]
                acc += mm[K + qa, K + qb] * w[j, qb]
            vw[qa, j] = acc
    if table:
        for i in range(P):
            g_p[i] = 0.0
            for j in range(P):
                a_p[i, j] = 0.0
    for ii in range(nj):
        i = jl[ii]
        acc = 0.0
        for a in range(nq):
            acc += w[i, ql[a]] * dr[ql[a]]
        g_p[i] = -acc
        for jj in range(nj):
            j = jl[jj]
            s = 0.0
            for a in range(nq):
                s += w[i, ql[a]] * vw[ql[a], j]
            for k in range(K):
                s -= rhs[k, 1 + i] * bx[k, jj]
            a_p[i, j] = s
    return rss


@njit
def given_rss(t, y, delay, sigma, alpha, present, amplitude, offset, sw, increasing, out, inst):
    """(n,) weighted RSS of the pixels' data at given parameters and amplitudes (the refine's
    never-worse reference): sum_i (y_i - sum_k amplitude_k phi_k(t_i) sw_i - offset sw_i)^2,
    the kernels on the supports of :func:`projected_normal_equations`.

    ``y`` (n, L) weighted data; ``delay``, ``sigma``, ``amplitude`` (n, K), ``alpha`` (n,),
    ``present`` (n, K); ``offset`` (n,) a constant subtracted (0: none); ``sw`` (n, L) or
    (0, L): the square roots of the sample weights; ``inst`` the atoms (:func:`instrument`)."""
    n, L = y.shape
    K = present.shape[1]
    has_sw = sw.shape[0] == n
    m = np.zeros((K, L))
    r = np.empty(L)
    dummy = np.empty(0)
    step_t = uniform_step(t, increasing)
    scratch = atom_scratch(inst)
    for p in range(n):
        swp = sw[p] if has_sw else dummy
        for i in range(L):
            r[i] = y[p, i] - offset[p] * (swp[i] if has_sw else 1.0)
        for slot in range(K):
            if not present[p, slot]:
                continue
            d = delay[p, slot]
            sss = slot == SSS_SLOT
            j0, j1 = atom_rows(t, m, K, slot, sss, d, sigma[p, slot], alpha[p], inst, swp, has_sw, False, increasing,
                               step_t, scratch)
            c = amplitude[p, slot]
            for i in range(j0, j1):
                r[i] -= c * m[slot, i]
        acc = 0.0
        for i in range(L):
            acc += r[i] * r[i]
        out[p] = acc


@njit
def fisher_gram(t, delay, sigma, alpha, amplitude, present, sw, offset, tied, onset, fixed, out):
    """J^T W J of the Fisher information's Jacobian rows (:func:`decomposition.model.fisher._jacobian`,
    point-sampled kernels on their supports), n pixels.

    Rows per slot k: 3k the delay's (amplitude times the kernel's delay derivative), 3k + 1 the
    amplitude's (the kernel), 3k + 2 the width's (amplitude times d/d sigma); 3K the sss decay
    rate's; with ``offset`` (n,) given (else (0,)) row 3K + 1 the offset's (ones, where the
    pixel has one).  Each row times ``sw`` (n, L) where given ((0, L): none).  Then, as the
    NumPy path: ``tied`` (n,) >= 0 the slot whose width row carries the sum of every width row
    (one width per pixel; -1: none), ``onset`` (n,) the pixels whose sss onset rides on the
    direct's delay (the sss delay row added to the direct's and zeroed), ``fixed`` (n, p) the
    rows zeroed (held parameters).  ``out`` (n, p, p), p = 3K + 1 (+ 1 with ``offset``).
    """
    n, K = present.shape
    L = t.size
    p = out.shape[1]
    has_sw = sw.shape[0] == n
    has_off = offset.shape[0] == n
    increasing = L >= 2
    for i in range(1, L):
        if not t[i] > t[i - 1]:
            increasing = False
    step_t = uniform_step(t, increasing)
    m = np.zeros((3 * K + 1, L))
    J = np.zeros((p, L))
    lo = np.zeros(p, np.int64)
    hi = np.zeros(p, np.int64)
    dummy = np.empty(0)
    for q in range(n):
        swq = sw[q] if has_sw else dummy
        for row in range(p):
            lo[row] = 0
            hi[row] = 0
        for k in range(K):
            if not present[q, k]:
                continue
            sss = k == SSS_SLOT
            j0, j1 = support_window(t, delay[q, k], sigma[q, k], sss, increasing)
            kernel_rows(t, m, K, k, sss, delay[q, k], sigma[q, k], alpha[q], swq, has_sw, True, j0, j1, step_t,
                        False)
            c = amplitude[q, k]
            for i in range(j0, j1):
                J[3 * k, i] = c * m[K + k, i]
                J[3 * k + 1, i] = m[k, i]
                J[3 * k + 2, i] = c * m[2 * K + k, i]
            for row in range(3 * k, 3 * k + 3):
                lo[row] = j0
                hi[row] = j1
            if sss:
                for i in range(j0, j1):
                    J[3 * K, i] = c * m[3 * K, i]
                lo[3 * K] = j0
                hi[3 * K] = j1
        if has_off and offset[q]:
            for i in range(L):
                J[3 * K + 1, i] = swq[i] if has_sw else 1.0
            lo[3 * K + 1] = 0
            hi[3 * K + 1] = L
        if tied[q] >= 0:
            # the sum of the width rows over the union of their supports, in the tied slot's row
            dst = 3 * tied[q] + 2
            a0, a1 = L, 0
            for k in range(K):
                if hi[3 * k + 2] > lo[3 * k + 2]:
                    a0 = min(a0, lo[3 * k + 2])
                    a1 = max(a1, hi[3 * k + 2])
            if a1 > a0:
                tot = np.zeros(L)
                for k in range(K):
                    row = 3 * k + 2
                    for i in range(lo[row], hi[row]):
                        tot[i] += J[row, i]
                    lo[row] = 0
                    hi[row] = 0
                for i in range(a0, a1):
                    J[dst, i] = tot[i]
                lo[dst] = a0
                hi[dst] = a1
        if onset[q]:
            src = 3 * SSS_SLOT
            if hi[src] > lo[src]:
                b0 = min(lo[0], lo[src]) if hi[0] > lo[0] else lo[src]
                b1 = max(hi[0], hi[src]) if hi[0] > lo[0] else hi[src]
                for i in range(b0, b1):
                    v0 = J[0, i] if lo[0] <= i < hi[0] else 0.0
                    vs = J[src, i] if lo[src] <= i < hi[src] else 0.0
                    J[0, i] = v0 + vs
                lo[0] = b0
                hi[0] = b1
            lo[src] = 0
            hi[src] = 0
        for row in range(p):
            if fixed[q, row]:
                lo[row] = 0
                hi[row] = 0
        for a in range(p):
            for b in range(a, p):
                v = row_dot(J, a, b, max(lo[a], lo[b]), min(hi[a], hi[b]))
                out[q, a, b] = v
                out[q, b, a] = v
