"""Compiled atoms of a sampled instrument response for blocks of atoms, with derivatives.

:func:`core.irf.render_shifted` and :func:`core.irf.render_sss` evaluate the response's exact
(band-limited) interpolant with an inverse FFT of its padded window per atom; the response
path of :func:`decomposition.decompose` renders atoms at every Levenberg-Marquardt trial, and
there the FFTs and their array temporaries cost most of its time.  This module renders the
same atoms from a table, in compiled loops (:func:`decomposition.kernels.jit.njit`, no fastmath: the
results are the same bits on every run):

table
    :func:`response_table`: the exact interpolant c and its derivative c' at the nodes
    ``start_ps + j * step_ps``, j = 0 .. n_steps, over the response's padded window
    [A, A + B) (A = ``irf.window_start_ps``, B = ``irf.window_ps``), ``step_ps`` = the
    response's step / ``substeps`` (a power of two, 4 to 64); both from one inverse FFT of
    the zero-padded spectrum, so the nodes hold the interpolant itself.  Between nodes c is
    the cubic Hermite interpolant of those values and slopes (C1, exact for cubics).
shifted atom
    c(t - d) from the table, and d/dd = -(the Hermite cubic's derivative): the derivative of
    the rendered atom itself, so a Levenberg-Marquardt step sees a consistent model.  Zero
    outside the padded window, as :func:`core.irf.render_shifted`.
sss atom
    s(D) = integral_0^D exp(-alpha (D - u)) c(A + u) du on the window, with c the piecewise
    cubic above; s at the nodes by the one-pole recursion
        s_{j+1} = exp(-alpha h) s_j + h [c_j a0 + h c'_j a1 + c_{j+1} a2 + h c'_{j+1} a3]
    whose weights a_i(alpha h) are the exact integrals of exp(-alpha h sigma) against the
    Hermite basis (combinations of E_n(beta) = int_0^1 exp(-beta x) x^n dx, by their power
    series for beta < 1 and the upward recurrence above), so the recursion is exact for the
    piecewise cubic c; between nodes, the Hermite cubic of s_j and its exact slope
    s'_j = c_j - alpha s_j.  After the window s(D) = s(B) exp(-alpha (D - B)), before it 0.
    d/dalpha s: the same recursion differentiated (exact for the discrete scheme) and
    interpolated with its slope -s_j - alpha r_j; d/dd: alpha s - c, the exact relation, with
    c the shifted atom's table value at the same instant -- so that, as for the exact atoms,
    an sss whose onset coincides with a shifted atom has its onset derivative in the span of
    the two atoms (the Levenberg-Marquardt projection then sees the degeneracy, not an O(h^3)
    remainder that Marquardt's column scaling would blow up into a step).

Error against the exact interpolant (:func:`core.irf.render_shifted` / :func:`core.irf.render_sss`,
unit-peak atoms): ``substeps`` is the smallest power of two (>= 4) for which the Hermite bound
h^4 / 384 max|c''''| (max|c''''| bounded by the spectrum, (2/N) sum |X_k| w_k^4) is at most
:data:`TABLE_REL_ERROR` of the peak, capped at 64.  Measured (tests/test_response_kernels.py)
on the simulated tailed and afterpulse responses and Gaussians of 1 and 3 bins (2 ps bins; 8,
8, 32 and 8 substeps), delays on and between bins, partly or wholly off the time axis, alpha
1e-4 to 1 per ps (alpha sigma from 1e-4 to 6): the shifted and sss atoms within 3.4e-8 of
their peak (the test holds them to 1e-7), the alpha derivatives within 3.1e-8 of their largest
value, the delay derivatives -- of the shifted atom the derivative of the cubic, one order
lower -- within 1.7e-6 of their largest (the test: 5e-6).  The shifted atom's delay derivative
and the alpha derivative equal finite differences of the rendered atoms to the differences' own
error; the sss delay derivative equals them within 5e-6 of its largest value.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

from core.irf import InstrumentResponse, ResponseError
from .jit import njit

__all__ = ["ResponseTable", "response_table", "shifted_atoms", "sss_atoms", "TABLE_REL_ERROR"]

#: the table's Hermite interpolation error bound, relative to the response's peak
TABLE_REL_ERROR = 1e-7
_MIN_SUBSTEPS = 4
_MAX_SUBSTEPS = 64
_SERIES_BELOW = 1.0          # beta = alpha h under which E_n(beta) is summed as a power series
_SERIES_TERMS = 20           # 1 / 20! < 1e-18: the series' remainder for beta < 1


@dataclass(frozen=True, eq=False)
class ResponseTable:
    """The response's interpolant at the nodes ``start_ps + j * step_ps``, j = 0 .. n_steps.

    ``value`` (n_steps + 1,) 1/ps and ``slope`` (n_steps + 1,) 1/ps^2, read-only;
    ``substeps`` nodes per sample of the response; ``peak_per_ps`` the response's peak (the
    unit-peak atoms are divided by it)."""

    start_ps: float
    step_ps: float
    n_steps: int
    substeps: int
    value: np.ndarray
    slope: np.ndarray
    peak_per_ps: float


_TABLES: "weakref.WeakKeyDictionary[InstrumentResponse, ResponseTable]" = weakref.WeakKeyDictionary()


def _substeps(irf: InstrumentResponse) -> int:
    w = irf.angular_frequencies()
    c4 = 2.0 / irf.n_padded * float(np.sum(np.abs(irf.spectrum[1:]) * w[1:] ** 4))
    s = _MIN_SUBSTEPS
    while s < _MAX_SUBSTEPS and (irf.time_step_ps / s) ** 4 / 384.0 * c4 > TABLE_REL_ERROR * irf.peak_per_ps:
        s *= 2
    return s


def response_table(irf: InstrumentResponse) -> ResponseTable:
    """The table of ``irf`` (built once per response object and kept while it lives)."""
    if not isinstance(irf, InstrumentResponse):
        raise ResponseError(f"a response table needs an InstrumentResponse, got {type(irf).__name__}")
    tab = _TABLES.get(irf)
    if tab is not None:
        return tab
    s = _substeps(irf)
    n = irf.n_padded
    spec = irf.spectrum
    m = n * s
    # the trigonometric interpolant at every node: the spectrum zero-padded to n * s points
    # (n is odd: no Nyquist term to split), scaled by s for the longer inverse transform
    padded = np.zeros(m // 2 + 1, np.complex128)
    padded[:spec.size] = spec
    value = sp_fft.irfft(padded, n=m) * s
    padded[:spec.size] = spec * (1j * irf.angular_frequencies())
    slope = sp_fft.irfft(padded, n=m) * s
    value = np.append(value, value[0])          # the node at A + B: the periodic interpolant's limit
    slope = np.append(slope, slope[0])
    value.setflags(write=False)
    slope.setflags(write=False)
    tab = ResponseTable(float(irf.window_start_ps), irf.time_step_ps / s, m, s, value, slope, float(irf.peak_per_ps))
    _TABLES[irf] = tab
    return tab


def _axis(t_ps, delay_ps):
    t = np.ascontiguousarray(t_ps, dtype=np.float64)
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise ResponseError(f"t_ps must be a non-empty finite 1-D time axis, got shape {t.shape}")
    d = np.asarray(delay_ps, dtype=np.float64)
    if not np.all(np.isfinite(d)):
        raise ResponseError("delay_ps must be finite")
    return t, d


def shifted_atoms(table: ResponseTable, t_ps, delay_ps, *, derivative: bool = False):
    """Unit-peak shifted atoms c(t - d) / peak, as :func:`core.irf.render_shifted`.

    Parameters
    ----------
    table : ResponseTable
    t_ps : array_like (L,)              time axis, ps (any spacing)
    delay_ps : array_like (...,)        delays, ps
    derivative : bool                   also return d atom / d delay (per ps)

    Returns
    -------
    atoms : ndarray (..., L); d_delay : ndarray (..., L) with ``derivative``
    """
    t, d = _axis(t_ps, delay_ps)
    flat = np.ascontiguousarray(d.reshape(-1))
    out = np.empty((flat.size, t.size))
    dout = np.empty((flat.size, t.size) if derivative else (0, 0))
    _shifted_kernel(table.value, table.slope, table.start_ps, table.step_ps, table.n_steps, t, flat,
                    1.0 / table.peak_per_ps, derivative, out, dout)
    shape = d.shape + (t.size,)
    if derivative:
        return out.reshape(shape), dout.reshape(shape)
    return out.reshape(shape)


def sss_atoms(table: ResponseTable, t_ps, delay_ps, alpha_per_ps, *, derivatives: bool = False):
    """Unit-peak sss atoms (the response convolved with exp(-alpha t) u(t), shifted by d, over the
    response's peak), as :func:`core.irf.render_sss`.

    Parameters
    ----------
    table : ResponseTable
    t_ps : array_like (L,)                       time axis, ps (any spacing)
    delay_ps, alpha_per_ps : array_like (...,)   onsets (ps) and attenuations (1/ps, >= 0), broadcast
    derivatives : bool                           also return d / d delay (per ps) and d / d alpha (ps)

    Returns
    -------
    atoms : ndarray (..., L); d_delay, d_alpha : ndarray (..., L) with ``derivatives``
    """
    d, a = np.broadcast_arrays(np.asarray(delay_ps, np.float64), np.asarray(alpha_per_ps, np.float64))
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ResponseError("alpha_per_ps must be non-negative and finite")
    t, d = _axis(t_ps, d)
    flat_d = np.ascontiguousarray(d.reshape(-1))
    flat_a = np.ascontiguousarray(a.reshape(-1))
    n = flat_d.size
    out = np.empty((n, t.size))
    dd = np.empty((n, t.size) if derivatives else (0, 0))
    da = np.empty((n, t.size) if derivatives else (0, 0))
    _sss_kernel(table.value, table.slope, table.start_ps, table.step_ps, table.n_steps, t, flat_d, flat_a,
                1.0 / table.peak_per_ps, derivatives, out, dd, da)
    shape = d.shape + (t.size,)
    if derivatives:
        return out.reshape(shape), dd.reshape(shape), da.reshape(shape)
    return out.reshape(shape)


@njit
def _shifted_kernel(value, slope, start, h, n_steps, t, delay, scale, want_d, out, dout):
    for a in range(delay.size):
        if want_d:
            shifted_row(value, slope, start, h, n_steps, t, delay[a], scale, True, out[a], dout[a])
        else:
            shifted_row(value, slope, start, h, n_steps, t, delay[a], scale, False, out[a], out[a])


@njit
def shifted_row(value, slope, start, h, n_steps, t, delay, scale, want_d, out, dout):
    """One shifted atom into ``out`` (L,) (and its delay derivative into ``dout`` (L,) with
    ``want_d``): the body of :func:`shifted_atoms` for one delay, for compiled callers."""
    L = t.size
    inv_h = 1.0 / h
    base = start + delay
    for i in range(L):
        x = (t[i] - base) * inv_h
        if x >= 0.0 and x < n_steps:
            j = int(x)
            u = x - j
            c0 = value[j]
            c1 = value[j + 1]
            m0 = h * slope[j]
            m1 = h * slope[j + 1]
            u2 = u * u
            u3 = u2 * u
            out[i] = scale * ((2.0 * u3 - 3.0 * u2 + 1.0) * c0 + (u3 - 2.0 * u2 + u) * m0
                              + (3.0 * u2 - 2.0 * u3) * c1 + (u3 - u2) * m1)
            if want_d:
                dout[i] = -scale * inv_h * ((6.0 * u2 - 6.0 * u) * (c0 - c1) + (3.0 * u2 - 4.0 * u + 1.0) * m0
                                            + (3.0 * u2 - 2.0 * u) * m1)
        else:
            out[i] = 0.0
            if want_d:
                dout[i] = 0.0


@njit
def _moments(beta, e, out):
    """E_n(beta) = int_0^1 exp(-beta x) x^n dx, n = 0 .. 4, into ``out`` (``e`` = exp(-beta))."""
    if beta < _SERIES_BELOW:
        for n in range(5):
            acc = 0.0
            term = 1.0
            for k in range(_SERIES_TERMS):
                acc += term / (n + k + 1.0)
                term *= -beta / (k + 1.0)
            out[n] = acc
    else:
        out[0] = -math.expm1(-beta) / beta
        for n in range(1, 5):
            out[n] = (n * out[n - 1] - e) / beta


@njit
def _sss_kernel(value, slope, start, h, n_steps, t, delay, alpha, scale, want_d, out, dd, da):
    s = np.empty(n_steps + 1)
    r = np.empty(n_steps + 1)
    E = np.empty(5)
    for a in range(delay.size):
        if want_d:
            sss_row(value, slope, start, h, n_steps, t, delay[a], alpha[a], scale, True, out[a], dd[a], da[a], s, r, E)
        else:
            sss_row(value, slope, start, h, n_steps, t, delay[a], alpha[a], scale, False, out[a], out[a], out[a],
                    s, r, E)


@njit
def sss_row(value, slope, start, h, n_steps, t, delay, al, scale, want_d, out, dd, da, s, r, E):
    """One sss atom into ``out`` (L,) (and its delay and alpha derivatives into ``dd``, ``da``
    (L,) with ``want_d``): the body of :func:`sss_atoms` for one onset and alpha, for compiled
    callers; ``s``, ``r`` (n_steps + 1,) and ``E`` (5,) are scratch."""
    L = t.size
    inv_h = 1.0 / h
    base = start + delay
    x_max = -1.0
    for i in range(L):
        x = (t[i] - base) * inv_h
        if x > x_max:
            x_max = x
    if x_max < 0.0:
        for i in range(L):
            out[i] = 0.0
            if want_d:
                dd[i] = 0.0
                da[i] = 0.0
        return
    j_top = n_steps if x_max >= n_steps else int(x_max) + 1
    beta = al * h
    e = math.exp(-beta)
    _moments(beta, e, E)
    # exact integrals of exp(-beta (1 - tau)) against the Hermite basis (sigma = 1 - tau)
    w0 = h * (3.0 * E[2] - 2.0 * E[3])
    w1 = h * h * (E[2] - E[3])
    w2 = h * (E[0] - 3.0 * E[2] + 2.0 * E[3])
    w3 = h * h * (-E[1] + 2.0 * E[2] - E[3])
    # their alpha derivatives (dE_n / dbeta = -E_{n+1}, dbeta / dalpha = h)
    v0 = -h * h * (3.0 * E[3] - 2.0 * E[4])
    v1 = -h * h * h * (E[3] - E[4])
    v2 = -h * h * (E[1] - 3.0 * E[3] + 2.0 * E[4])
    v3 = -h * h * h * (-E[2] + 2.0 * E[3] - E[4])
    s[0] = 0.0
    r[0] = 0.0
    he = h * e
    # the brackets g_j (and their alpha derivatives q_j) first, into s[j + 1] (r[j + 1]): a loop
    # with no dependence between nodes, which the compiler runs on vector registers; the
    # recursion below reads each before it writes its node
    for j in range(j_top):
        c0 = value[j]
        c1 = value[j + 1]
        m0 = slope[j]
        m1 = slope[j + 1]
        s[j + 1] = w0 * c0 + w1 * m0 + w2 * c1 + w3 * m1
    if want_d:
        for j in range(j_top):
            c0 = value[j]
            c1 = value[j + 1]
            m0 = slope[j]
            m1 = slope[j + 1]
            r[j + 1] = v0 * c0 + v1 * m0 + v2 * c1 + v3 * m1
    # two nodes per step: s_{j+2} = e^2 s_j + (e g_j + g_{j+1}) (r likewise), which halves the
    # chain of dependent multiply-adds the loop waits on; the same recursion to rounding (1e-15
    # relative)
    e2 = e * e
    he2 = 2.0 * he * e
    sj = 0.0
    rj = 0.0
    j = 0
    if want_d:
        while j + 2 <= j_top:
            g0 = s[j + 1]
            g1 = s[j + 2]
            q0 = r[j + 1]
            q1 = r[j + 2]
            s[j + 1] = e * sj + g0
            r[j + 1] = e * rj - he * sj + q0
            s2 = e2 * sj + (e * g0 + g1)
            rj = e2 * rj - he2 * sj + (e * q0 - he * g0 + q1)
            sj = s2
            s[j + 2] = sj
            r[j + 2] = rj
            j += 2
        if j < j_top:
            g0 = s[j + 1]
            s[j + 1] = e * sj + g0
            r[j + 1] = e * rj - he * sj + r[j + 1]
    else:
        while j + 2 <= j_top:
            g0 = s[j + 1]
            g1 = s[j + 2]
            s[j + 1] = e * sj + g0
            sj = e2 * sj + (e * g0 + g1)
            s[j + 2] = sj
            j += 2
        if j < j_top:
            s[j + 1] = e * sj + s[j + 1]
    s_b = s[n_steps] if j_top == n_steps else 0.0
    r_b = r[n_steps] if j_top == n_steps else 0.0
    for i in range(L):
        x = (t[i] - base) * inv_h
        if x < 0.0:
            out[i] = 0.0
            if want_d:
                dd[i] = 0.0
                da[i] = 0.0
        elif x >= n_steps:
            past = (x - n_steps) * h
            tail = math.exp(-al * past)
            out[i] = scale * s_b * tail
            if want_d:
                dd[i] = scale * al * s_b * tail
                da[i] = scale * tail * (r_b - past * s_b)
        else:
            j = int(x)
            u = x - j
            u2 = u * u
            u3 = u2 * u
            h00 = 2.0 * u3 - 3.0 * u2 + 1.0
            h10 = u3 - 2.0 * u2 + u
            h01 = 3.0 * u2 - 2.0 * u3
            h11 = u3 - u2
            s0 = s[j]
            s1 = s[j + 1]
            p0 = h * (value[j] - al * s0)          # h s'(node): the exact slope s' = c - alpha s
            p1 = h * (value[j + 1] - al * s1)
            out[i] = scale * (h00 * s0 + h10 * p0 + h01 * s1 + h11 * p1)
            if want_d:
                # d/dd s(t - d) = alpha s - c, with c the shifted atom's own value here (the
                # same expression as _shifted_kernel): where a shifted atom shares the onset,
                # this column lies in the span of the two atoms, as it does exactly
                c0 = value[j]
                c1 = value[j + 1]
                m0 = h * slope[j]
                m1 = h * slope[j + 1]
                c = (2.0 * u3 - 3.0 * u2 + 1.0) * c0 + (u3 - 2.0 * u2 + u) * m0 \
                    + (3.0 * u2 - 2.0 * u3) * c1 + (u3 - u2) * m1
                dd[i] = al * out[i] - scale * c
                r0 = r[j]
                r1 = r[j + 1]
                q0 = h * (-s0 - al * r0)           # h r'(node): d/dalpha of h s'(node)
                q1 = h * (-s1 - al * r1)
                da[i] = scale * (h00 * r0 + h10 * q0 + h01 * r1 + h11 * q1)
