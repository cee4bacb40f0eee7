"""Levenberg-Marquardt refinement of each pixel's atoms, compiled (ConvSCD step 2).

After every pick, and once more after thresholding, the active atoms of a pixel -- Gaussians
(direct, inter-reflections) and at most one sss kernel -- have their amplitudes, delays, widths
and decay rates refined continuously, each step accepted only where the pixel's objective

    F = 1/2 ||residual||^2 + mu sum_k log(1 + pen_k |amp_k| / eps)

decreases (see :mod:`decomposition.methods.convscd` for the objective, the sample masks and the
constraints).  This module is that loop, one pixel at a time in compiled code
(:mod:`decomposition.kernels.jit`): a pixel's atoms are evaluated on their own support only (a Gaussian
within +-8 sigma of its delay, an sss kernel from 8 sigma before its onset; its exponential
tail by a one-pole recursion), and the normal equations sum only over the overlap of two
atoms' supports -- over the sss tail past every other atom, where each column is h times a
polynomial of degree <= 1 in t, in closed form from five sums (:func:`_tail_sums`; the
derivative columns are not even written there).  Nothing of size (pixels, atoms, parameters,
time) is ever allocated.

Parameters per slot: (amp, delay_ps, log sigma_ps, log alpha_per_ps), columns 4k..4k+3.
Options as in the solver: ``tie_sigma`` keeps one width for pixels whose atoms share it
(slot 0's width column carries all of them); ``sss_after_direct`` parametrises an sss onset
within 3 PSF widths before the earliest Gaussian as direct delay + gap, gap >= 0 by an active
set, and keeps onsets at or after that Gaussian.
"""

# One module over 600 lines on purpose: the LM loop, the atom values and derivatives it evaluates,
# the models, the NNLS amplitudes and the window sums are compiled functions that call one another;
# numba compiles and caches them together, and the one-pixel loop reads as one piece.
from __future__ import annotations

import math

import numpy as np

from ..constants import AMP_MAX, FAM_GAUSS, FAM_NONE, FAM_SSS, GAUSS_SUPPORT_SIGMA, NEAR_SIGMA, TAIL_SIGMA
from .jit import SQRT_PI_2, njit, sss_erfc_part
from ..masks import SampleMask, check_mask
from .onsets import onset_link
from .projected import GAUSSIAN_PSF, atom_scratch, table_rows, table_window

__all__ = ["lm_refine", "atom_profiles", "atom_window_sums", "atom_weighted_squares", "state_models", "nnls_amplitudes"]

_SQRT_2PI = math.sqrt(2.0 * math.pi)
_SQRT_2 = math.sqrt(2.0)
_TINY = 1e-290                        # tail values below this are exact zeros (no subnormals)
_RESTART = 8                          # bins between fresh evaluations of the stepped factors


@njit
def _tail_start(t0, T, L, lo, delay, sig, alp):
    """First sample of an sss atom's exponential tail (where erfc(u) is 2 to double precision, so
    every column of the atom is h times a polynomial in t of degree <= 1): the atom's samples
    from ``lo`` up to the last bin within alpha sigma^2 + TAIL_SIGMA sigma of its onset are
    evaluated exactly, the later ones by the one-pole recursion."""
    we = int(math.ceil((delay + alp * sig * sig + TAIL_SIGMA * sig - t0) / T))
    return min(max(lo, we + 1), L)


@njit
def _gauss_support(t0, T, L, delay, sig):
    """[lo, hi) of a Gaussian atom: the bins within GAUSS_SUPPORT_SIGMA widths of its delay."""
    lo = min(max(int(math.floor((delay - GAUSS_SUPPORT_SIGMA * sig - t0) / T)), 0), L)
    hi = max(min(int(math.ceil((delay + GAUSS_SUPPORT_SIGMA * sig - t0) / T)) + 1, L), lo)
    return lo, hi


@njit
def _pure_tail(t0, T, L, K, fam, delay, lsig, lalp, lo, hi):
    """(sss slot, first sample of its pure tail) of one pixel: the samples of its sss atom's
    exponential tail past the support of every other atom, where the normal equations are
    summed in closed form (:func:`_tail_sums`); (-1, L) without one sss atom.
    ``lo``, ``hi`` (K,): the supports of the slots (only the other atoms' are read)."""
    s_k = -1
    for k in range(K):
        if fam[k] == FAM_SSS:
            if s_k >= 0:
                return -1, L                 # two sss atoms: no closed form
            s_k = k
    if s_k < 0:
        return -1, L
    sig = math.exp(lsig[s_k])
    lo_s = max(int(math.floor((delay[s_k] - GAUSS_SUPPORT_SIGMA * sig - t0) / T)), 0)
    if lo_s >= L:
        return -1, L
    p_tail = _tail_start(t0, T, L, lo_s, delay[s_k], sig, math.exp(lalp[s_k]))
    for k in range(K):
        if k != s_k and fam[k] != FAM_NONE and hi[k] > lo[k]:
            p_tail = max(p_tail, hi[k])
    return s_k, p_tail


@njit
def _gauss_columns(J, row, i, aph, x, sig):
    """A Gaussian atom's derivative columns at sample i: ``aph`` its value times its amplitude,
    ``x`` the time from its delay in widths ``sig``."""
    J[row + 1, i] = aph * x / sig
    J[row + 2, i] = aph * x * x
    J[row + 3, i] = 0.0


@njit
def _sss_columns(J, row, i, amp, h, g, x, sig, alp, s2):
    """An sss atom's derivative columns at sample i before its tail: ``h`` its kernel, ``g`` the
    Gaussian factor, ``x`` the time after its onset (ps), ``s2`` = sig^2."""
    J[row + 1, i] = -amp * (g - alp * h)
    J[row + 2, i] = amp * sig * (h * (1.0 / sig + alp * alp * sig) - g * (alp * sig + x / sig))
    J[row + 3, i] = amp * alp * ((alp * s2 - x) * h - s2 * g)


@njit
def _tail_columns(J, row, i, h, x, c1, c2, alp, s2):
    """An sss atom's derivative columns in its exponential tail, multiples of its kernel ``h``
    (c1 = amp alpha, c2 = amp (1 + alpha^2 sigma^2))."""
    J[row + 1, i] = c1 * h
    J[row + 2, i] = c2 * h
    J[row + 3, i] = c1 * (alp * s2 - x) * h


@njit
def _eval_slot(t0, T, L, fam, amp, delay, lsig, lalp, J, row, deriv_end, model, keep_g=False):
    """Atom ``amp * phi`` and its 4 derivative columns into J[row:row+4, lo:hi]; returns (lo, hi).

    Columns: d/d amp (= phi), d/d delay_ps, d/d log sigma, d/d log alpha; the derivative
    columns only before ``deriv_end`` (0: the atom's values alone).  Outside [lo, hi) every
    column is zero (and J is not written there).  ``model`` (L,): amp * phi is added to it, sample
    by sample (an empty array: nothing is added).  ``keep_g`` (with ``deriv_end`` 0): an sss
    atom also leaves its Gaussian factor g in J[row + 3] before its tail, from which
    :func:`_fill_slot` forms the derivative columns later.
    """
    add = model.size > 0
    sig = math.exp(lsig)
    # Gaussian factors g(x) = exp(-x^2 / 2), x in widths, stepped from bin to bin as
    # g(x + b) = g(x) e(x), e(x + b) = e(x) exp(-b^2), b = T / sigma: two products instead of an
    # exponential per bin, evaluated afresh every _RESTART bins (the rounding stays below ~30 ulp);
    # for narrow atoms (b > 1, a few bins each) every bin is evaluated afresh
    b = T / sig
    step = _RESTART if b <= 1.0 else 1
    cb = math.exp(-b * b)
    if fam == FAM_GAUSS:
        lo, hi = _gauss_support(t0, T, L, delay, sig)
        ph = 0.0
        e = 0.0
        for i in range(lo, hi):
            x = (t0 + i * T - delay) / sig
            if (i - lo) % step == 0:
                ph = math.exp(-0.5 * x * x)
                e = math.exp(-x * b - 0.5 * b * b)
            J[row, i] = ph
            if add:
                model[i] += amp * ph
            if i < deriv_end:
                _gauss_columns(J, row, i, amp * ph, x, sig)
            ph *= e
            e *= cb
        return lo, hi
    alp = math.exp(lalp)
    lo = max(int(math.floor((delay - GAUSS_SUPPORT_SIGMA * sig - t0) / T)), 0)
    if lo >= L:
        return L, L
    hi = L
    s2 = sig * sig
    i = lo
    i_tail = _tail_start(t0, T, L, lo, delay, sig, alp)
    # h = sqrt(pi/2) sigma f(x) erfc(u), u = (alpha sigma^2 - x) / (sigma sqrt 2), in the stable
    # form of jit.sss_erfc_part: g(x) erfcx(u) where u >= 0, 2 f(x) - g(x) erfcx(-u) elsewhere,
    # with g stepped as above and f(x) = g(x) exp(u^2) = exp(alpha^2 sigma^2 / 2 - alpha x) <= 1
    # (u < 0) stepped by exp(-alpha T) per bin: one polynomial of erfcx's table per bin, and no
    # other transcendental function
    rho = math.exp(-alp * T)
    scale = SQRT_PI_2 * sig
    g = 0.0
    e = 0.0
    f = 0.0
    f_on = False
    while i < i_tail:
        x = t0 + i * T - delay
        if (i - lo) % step == 0:
            xs = x / sig
            g = math.exp(-0.5 * xs * xs)
            e = math.exp(-xs * b - 0.5 * b * b)
            f_on = False
        u = (alp * s2 - x) / (sig * _SQRT_2)
        if u < 0.0 and not f_on:
            f = math.exp(0.5 * alp * alp * s2 - alp * x)      # = g exp(u^2) <= 1 where u < 0
            f_on = True
        h = scale * sss_erfc_part(u, g, f)
        J[row, i] = h
        if add:
            model[i] += amp * h
        if i < deriv_end:
            _sss_columns(J, row, i, amp, h, g, x, sig, alp, s2)
        elif keep_g:
            J[row + 3, i] = g
        g *= e
        e *= cb
        f *= rho
        i += 1
    if i < L:
        # exponential tail (g = 0 there): h = sqrt(2 pi) sigma exp(alpha^2 sigma^2 / 2 - alpha x),
        # stepped by exp(-alpha T) per bin; all three derivative columns are multiples of h
        x = t0 + i * T - delay
        h = _SQRT_2PI * sig * math.exp(min(0.5 * alp * alp * s2 - alp * x, 0.0))
        c1 = amp * alp
        c2 = amp * (1.0 + alp * alp * s2)
        while i < L:
            if h < _TINY:
                hi = i
                break
            J[row, i] = h
            if add:
                model[i] += amp * h
            if i < deriv_end:
                _tail_columns(J, row, i, h, x, c1, c2, alp, s2)
            h *= rho
            x += T
            i += 1
    return lo, hi


@njit
def _fill_slot(t0, T, L, fam, amp, delay, lsig, lalp, J, row, lo, hi, deriv_end):
    """The derivative columns J[row + 1:row + 4] of a slot rendered by :func:`_eval_slot` with
    ``keep_g`` and no derivatives (its values in J[row], an sss atom's g in J[row + 3] before
    its tail), on [lo, min(hi, deriv_end)): the same numbers :func:`_eval_slot` writes with
    derivatives, from the same values and the same times."""
    end = min(hi, deriv_end)
    sig = math.exp(lsig)
    if fam == FAM_GAUSS:
        for i in range(lo, end):
            x = (t0 + i * T - delay) / sig
            _gauss_columns(J, row, i, amp * J[row, i], x, sig)
        return
    alp = math.exp(lalp)
    s2 = sig * sig
    i_tail = _tail_start(t0, T, L, lo, delay, sig, alp)
    for i in range(lo, min(i_tail, end)):
        x = t0 + i * T - delay
        _sss_columns(J, row, i, amp, J[row, i], J[row + 3, i], x, sig, alp, s2)
    if i_tail < end:
        x = t0 + i_tail * T - delay
        c1 = amp * alp
        c2 = amp * (1.0 + alp * alp * s2)
        for i in range(i_tail, end):
            _tail_columns(J, row, i, J[row, i], x, c1, c2, alp, s2)
            x += T


@njit
def _profiles(t0, T, fam, delay, lsig, lalp, out):
    n, L = out.shape
    J = np.empty((4, L))
    none = np.empty(0)
    for i in range(n):
        if fam[i] == FAM_GAUSS or fam[i] == FAM_SSS:
            lo, hi = _eval_slot(t0, T, L, fam[i], 1.0, delay[i], lsig[i], lalp[i], J, 0, 0, none)
            for m in range(lo, hi):
                out[i, m] = J[0, m]


@njit
def _window_sums(t0, T, L, fam, delay, lsig, lalp, out):
    J = np.empty((4, L))
    none = np.empty(0)
    for i in range(fam.size):
        if fam[i] == FAM_GAUSS or fam[i] == FAM_SSS:
            lo, hi = _eval_slot(t0, T, L, fam[i], 1.0, delay[i], lsig[i], lalp[i], J, 0, 0, none)
            top = 0.0
            s1 = 0.0
            s2 = 0.0
            for m in range(lo, hi):
                v = J[0, m]
                top = max(top, v)
                s1 += v
                s2 += v * v
            out[i, 0] = top
            out[i, 1] = s1
            out[i, 2] = s2


def atom_window_sums(t0_ps, time_bin_ps, n_bins, fam, delay_ps, lsig, lalp):
    """Largest value, sum and sum of squares over the window of every unit atom of
    :func:`atom_profiles` (the same atoms, without the (n, n_bins) array).

    Returns
    -------
    ndarray (n, 3) float64: max_i phi(t_i), sum_i phi(t_i), sum_i phi(t_i)^2; zeros for
    FAM_NONE rows.
    """
    fam = np.ascontiguousarray(fam, np.int8)
    out = np.zeros((fam.size, 3))
    if fam.size:
        _window_sums(float(t0_ps), float(time_bin_ps), int(n_bins), fam, np.ascontiguousarray(delay_ps, np.float64),
                     np.ascontiguousarray(lsig, np.float64), np.ascontiguousarray(lalp, np.float64), out)
    return out


@njit
def _weighted_squares(t0, T, L, fam, delay, lsig, lalp, w, rows, cap, out):
    J = np.empty((4, L))
    none = np.empty(0)
    for i in range(fam.size):
        if fam[i] == FAM_GAUSS or fam[i] == FAM_SSS:
            lo, hi = _eval_slot(t0, T, L, fam[i], 1.0, delay[i], lsig[i], lalp[i], J, 0, 0, none)
            wr = w[rows[i]]
            s = 0.0
            for m in range(lo, hi):
                v = J[0, m]
                s += min(wr[m], cap) * v * v
            out[i] = s


def atom_weighted_squares(t0_ps, time_bin_ps, n_bins, fam, delay_ps, lsig, lalp, weights, rows, cap=np.inf):
    """Weighted sum of squares over the window of every unit atom of :func:`atom_profiles`:
    sum_i min(w_i, cap) phi(t_i)^2, with w the row ``rows[j]`` of ``weights`` (P, n_bins) for
    atom j (the same atoms, without the (n, n_bins) array).

    Returns
    -------
    ndarray (n,) float64; zeros for FAM_NONE rows.
    """
    fam = np.ascontiguousarray(fam, np.int8)
    w = np.ascontiguousarray(weights, np.float64)
    if w.ndim != 2 or w.shape[1] != int(n_bins):
        raise ValueError(f"weights have shape {w.shape}; expected (pixels, {int(n_bins)})")
    out = np.zeros(fam.size)
    if fam.size:
        _weighted_squares(float(t0_ps), float(time_bin_ps), int(n_bins), fam, np.ascontiguousarray(delay_ps, np.float64),
                          np.ascontiguousarray(lsig, np.float64), np.ascontiguousarray(lalp, np.float64), w,
                          np.ascontiguousarray(rows, np.int64), float(cap), out)
    return out


def atom_profiles(t0_ps, time_bin_ps, n_bins, fam, delay_ps, lsig, lalp):
    """Unit-amplitude atoms on the time axis, one row per atom (the solver's own evaluation).

    Parameters
    ----------
    t0_ps, time_bin_ps : float
        Bin i at t0_ps + i * time_bin_ps.
    n_bins : int
    fam : int array (n,)
        FAM_GAUSS, FAM_SSS or FAM_NONE (a zero row).
    delay_ps, lsig, lalp : arrays (n,)
        Delay (ps), log sigma_ps and log alpha_per_ps (ignored for Gaussians).

    Returns
    -------
    ndarray (n, n_bins) float64: unit-peak Gaussians exp(-(t - d)^2 / (2 sigma^2)) within
    +-8 sigma, sss kernels (core.model.sss_kernel, not normalised) from 8 sigma before
    their onset; exact zeros elsewhere.
    """
    fam = np.ascontiguousarray(fam, np.int8)
    out = np.zeros((fam.size, int(n_bins)))
    if fam.size:
        _profiles(float(t0_ps), float(time_bin_ps), fam, np.ascontiguousarray(delay_ps, np.float64),
                  np.ascontiguousarray(lsig, np.float64), np.ascontiguousarray(lalp, np.float64), out)
    return out


@njit
def _models(t0, T, fam, amp, delay, lsig, lalp, out):
    P, L = out.shape
    K = fam.shape[1]
    J = np.empty((4, L))
    for pi in range(P):
        for k in range(K):
            if fam[pi, k] == FAM_GAUSS or fam[pi, k] == FAM_SSS:
                _eval_slot(t0, T, L, fam[pi, k], amp[pi, k], delay[pi, k], lsig[pi, k], lalp[pi, k], J, 0, 0, out[pi])


def state_models(t0_ps, time_bin_ps, n_bins, fam, amp, delay_ps, lsig, lalp):
    """Model of every pixel of a slot state: the sum of its active atoms, in slot order.

    Parameters
    ----------
    t0_ps, time_bin_ps : float
        Bin i at t0_ps + i * time_bin_ps.
    n_bins : int
    fam : int array (P, K)
        FAM_GAUSS, FAM_SSS or FAM_NONE (adds nothing).
    amp, delay_ps, lsig, lalp : arrays (P, K)
        Amplitude, delay (ps), log sigma_ps and log alpha_per_ps of every slot.

    Returns
    -------
    ndarray (P, n_bins) float64: sum over k of amp[:, k] times the unit atom of
    :func:`atom_profiles`, accumulated in slot order (the same values as adding those rows).
    """
    fam = np.ascontiguousarray(fam, np.int8)
    out = np.zeros((fam.shape[0], int(n_bins)))
    if fam.size:
        _models(float(t0_ps), float(time_bin_ps), fam, np.ascontiguousarray(amp, np.float64),
                np.ascontiguousarray(delay_ps, np.float64), np.ascontiguousarray(lsig, np.float64),
                np.ascontiguousarray(lalp, np.float64), out)
    return out


@njit
def _nnls_pixels(t0, T, t, p, fit, fam, amp, delay, lsig, lalp, sweeps, inst):
    P, L = p.shape
    K = fam.shape[1]
    J = np.zeros((K + 3, L))
    lo = np.zeros(K, np.int64)
    hi = np.zeros(K, np.int64)
    G = np.zeros((K, K))
    b = np.zeros(K)
    a = np.zeros(K)
    w = np.zeros(L)
    none = np.empty(0)
    table = inst[0].size > 0
    scratch = atom_scratch(inst)
    for pi in range(P):
        for i in range(L):
            w[i] = 1.0 if fit[pi, i] else 0.0
        for k in range(K):
            if (fam[pi, k] == FAM_GAUSS or fam[pi, k] == FAM_SSS) and table:
                # a response's table atom (unit peak) on its window
                sss = fam[pi, k] == FAM_SSS
                lo[k], hi[k] = table_window(t, delay[pi, k], sss, inst, True)
                table_rows(t, J, K, k, sss, delay[pi, k], math.exp(lalp[pi, k]) if sss else 0.0, inst, t, False,
                           False, lo[k], hi[k], scratch[0], scratch[1], scratch[2])
            elif fam[pi, k] == FAM_GAUSS or fam[pi, k] == FAM_SSS:
                lo[k], hi[k] = _eval_slot(t0, T, L, fam[pi, k], 1.0, delay[pi, k], lsig[pi, k], lalp[pi, k], J, k, 0,
                                          none)
            else:
                lo[k] = hi[k] = 0
        for k in range(K):
            s = 0.0
            for i in range(lo[k], hi[k]):
                s += J[k, i] * w[i] * (p[pi, i] * w[i])
            b[k] = s
            for j in range(k, K):
                s = 0.0
                for i in range(max(lo[k], lo[j]), min(hi[k], hi[j])):
                    s += J[k, i] * w[i] * (J[j, i] * w[i])
                G[k, j] = s
                G[j, k] = s
            a[k] = amp[pi, k] if fam[pi, k] != FAM_NONE else 0.0
        for _ in range(sweeps):
            for k in range(K):
                if fam[pi, k] == FAM_NONE:
                    a[k] = 0.0
                    continue
                gkk = G[k, k]
                r = b[k]
                for j in range(K):
                    r -= G[k, j] * a[j]
                r += gkk * a[k]
                a[k] = max(r / gkk, 0.0) if gkk > 0.0 else 0.0
        for k in range(K):
            amp[pi, k] = a[k]


def nnls_amplitudes(t0_ps, time_bin_ps, p, fit, fam, amp, delay_ps, lsig, lalp, sweeps=20, inst=GAUSSIAN_PSF):
    """Non-negative least-squares amplitudes of fixed atoms, every pixel of a block.

    Exact coordinate descent on the convex problem min_a ||w (p - sum_k a_k phi_k)||^2, a >= 0
    (``sweeps`` sweeps over the slots, starting from ``amp``), with the unit atoms phi_k of
    :func:`atom_profiles` -- or of a response's table (``inst``) -- and w the fitted samples.

    Parameters
    ----------
    t0_ps, time_bin_ps : float
        Bin i at t0_ps + i * time_bin_ps.
    p : ndarray (P, L)
        Profiles (unit peak).
    fit : ndarray (P, L) bool
        Samples that count.
    fam, delay_ps, lsig, lalp : arrays (P, K)
        The atoms (FAM_NONE slots get amplitude 0; ``lsig`` is not read with a response).
    amp : ndarray (P, K)
        Starting amplitudes.
    sweeps : int
    inst : tuple
        The atoms' instrument (:func:`decomposition.kernels.projected.instrument`): the Gaussian
        PSF's (:data:`~decomposition.kernels.projected.GAUSSIAN_PSF`, the default) or a response's
        table atoms on the axis t0_ps + i * time_bin_ps.

    Returns
    -------
    ndarray (P, K): the amplitudes (0 for empty slots and atoms the data do not support).
    """
    P, L = np.shape(p)
    out = np.array(amp, np.float64, order="C", copy=True)
    if P:
        _nnls_pixels(float(t0_ps), float(time_bin_ps), float(t0_ps) + float(time_bin_ps) * np.arange(L),
                     np.ascontiguousarray(p, np.float64), np.ascontiguousarray(fit, np.bool_),
                     np.ascontiguousarray(fam, np.int8), out, np.ascontiguousarray(delay_ps, np.float64),
                     np.ascontiguousarray(lsig, np.float64), np.ascontiguousarray(lalp, np.float64), int(sweeps), inst)
    return out


@njit
def _render(t0, T, L, K, fam, amp, delay, lsig, lalp, J, lo, hi, model, derivs=True):
    """Evaluate the pixel's K active slots into J and sum their model into ``model`` (L,).

    The sss atom's derivative columns are left out in its pure tail (:func:`_pure_tail`), which
    the normal equations sum in closed form from its values.  Without ``derivs`` only the
    values (and an sss atom's Gaussian factor) are written: a trial step is judged by its
    objective alone, and :func:`_fill_derivatives` completes J where it is accepted (in the
    search's polish about 40 % of the trials are rejected).
    """
    for i in range(L):
        model[i] = 0.0
    for k in range(K):
        if fam[k] == FAM_GAUSS:
            lo[k], hi[k] = _gauss_support(t0, T, L, delay[k], math.exp(lsig[k]))
        else:
            lo[k] = hi[k] = 0
    s_k, p_tail = _pure_tail(t0, T, L, K, fam, delay, lsig, lalp, lo, hi)
    for k in range(K):
        end = (p_tail if k == s_k else L) if derivs else 0
        lo[k], hi[k] = _eval_slot(t0, T, L, fam[k], amp[k], delay[k], lsig[k], lalp[k], J, 4 * k, end, model,
                                  not derivs)


@njit
def _fill_derivatives(t0, T, L, K, fam, amp, delay, lsig, lalp, J, lo, hi):
    """The derivative columns of a state that :func:`_render` evaluated without them (its
    supports ``lo``, ``hi``): afterwards J is what a render with derivatives writes."""
    s_k, p_tail = _pure_tail(t0, T, L, K, fam, delay, lsig, lalp, lo, hi)
    for k in range(K):
        _fill_slot(t0, T, L, fam[k], amp[k], delay[k], lsig[k], lalp[k], J, 4 * k, lo[k], hi[k],
                   p_tail if k == s_k else L)


@njit
def _penalty(K, fam, amp, pen, eps):
    """sum_k log(1 + pen_k |amp_k| / eps) over the pixel's active slots."""
    pensum = 0.0
    for k in range(K):
        if fam[k] != FAM_NONE:
            pensum += math.log1p(pen[k] * abs(amp[k]) / eps)
    return pensum


@njit
def _objective(L, K, p, fit, cens, w, model, fam, amp, pen, mu, eps, r, jw):
    """F of one pixel; fills the weighted residual ``r`` (w * (p - model)) and the Jacobian
    row weights ``jw`` (w on the samples that count, 0 elsewhere)."""
    ss = 0.0
    for i in range(L):
        d = p[i] - model[i]
        if fit[i] or (cens[i] and d > 0.0):   # censored from below: only a model under the data misfits
            r[i] = w[i] * d
            jw[i] = w[i]
            ss += r[i] * d
        else:
            r[i] = 0.0
            jw[i] = 0.0
    return 0.5 * ss + mu * _penalty(K, fam, amp, pen, eps)


@njit
def _objective_plain(L, K, p, wf, model, fam, amp, pen, mu, eps, r):
    """:func:`_objective` of a pixel without censored samples (and with finite values where its
    samples do not count), ``wf`` its weights with 0 on the samples that do not count (then also
    its Jacobian row weights, which stay as they are): the same sums without a branch per
    sample, about 8 % of the LM's time less."""
    s0 = 0.0             # four sums side by side (a fixed order: the same bits on every machine)
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    L4 = L - L % 4
    for i in range(0, L4, 4):
        d0 = p[i] - model[i]
        d1 = p[i + 1] - model[i + 1]
        d2 = p[i + 2] - model[i + 2]
        d3 = p[i + 3] - model[i + 3]
        r0 = wf[i] * d0
        r1 = wf[i + 1] * d1
        r2 = wf[i + 2] * d2
        r3 = wf[i + 3] * d3
        r[i] = r0
        r[i + 1] = r1
        r[i + 2] = r2
        r[i + 3] = r3
        s0 += r0 * d0
        s1 += r1 * d1
        s2 += r2 * d2
        s3 += r3 * d3
    for i in range(L4, L):
        d = p[i] - model[i]
        ri = wf[i] * d
        r[i] = ri
        s0 += ri * d
    ss = (s0 + s1) + (s2 + s3)
    return 0.5 * ss + mu * _penalty(K, fam, amp, pen, eps)


@njit
def _links(K, fam, delay, lsig, tie_sigma, sss_after_direct):
    """(tied, linked, direct slot, sss slot) of one pixel: one width for all atoms, and the
    onset-tie rule (:func:`onset_link`) where ``sss_after_direct``."""
    tied = False
    if tie_sigma and K > 0:
        lo = lsig[0]
        hi = lsig[0]
        for k in range(1, K):
            lo = min(lo, lsig[k])
            hi = max(hi, lsig[k])
        tied = hi - lo <= 1e-12
    linked, dsl, ssl = onset_link(K, fam, delay, lsig, NEAR_SIGMA)
    return tied, sss_after_direct and linked, dsl, ssl


@njit
def _merge_column(J, dst, src, lo_d, hi_d, lo_s, hi_s, stop):
    """J[dst] += J[src] over their supports, written for samples before ``stop`` only; returns the
    new support of dst (zero-extended; the union of both, ``stop`` notwithstanding)."""
    a = min(lo_d, lo_s)
    b = max(hi_d, hi_s)
    for i in range(a, min(b, stop)):
        if i < lo_d or i >= hi_d:
            J[dst, i] = 0.0
    for i in range(lo_s, min(hi_s, stop)):
        J[dst, i] += J[src, i]
    return a, b


@njit
def _normal_equations(t0, T, K, fam, amp, delay, lsig, lalp, J, lo, hi, r, jw, tied, linked, dsl, ssl, JtJ, g, free,
                      clo, chi, act, bp, pa, pb):
    """J^T J and J^T r over the free columns, summing over support overlaps only.

    The samples are swept once, segment by segment (between the supports' ends), updating every
    pair of columns that both cover the segment, four sums side by side.  The segment where only
    an sss atom's exponential tail is left (after its exactly evaluated part and past every other
    atom) is summed in closed form instead: there every covering column is (a + b x) h, h the
    tail and x the time after the onset less alpha sigma^2, so each entry is a combination of
    sum h^2 w, sum x h^2 w, sum x^2 h^2 w (and sum h r, sum x h r for J^T r) -- five sums
    instead of one per pair.  ``act`` (4K,), ``bp`` (8K + 2,), ``pa`` and ``pb`` (4K (4K + 1) / 2,)
    int64 are scratch.
    """
    n = 4 * K
    for c in range(n):
        k = c // 4
        q = c % 4
        clo[c] = lo[k]
        chi[c] = hi[k]
        free[c] = fam[k] != FAM_NONE and (q != 3 or fam[k] == FAM_SSS)
    # the sss atom's pure tail [p_tail, hi[s]): its exponential tail past every other atom
    L_END = J.shape[1]
    s_k, p_tail = _pure_tail(t0, T, L_END, K, fam, delay, lsig, lalp, lo, hi)
    sig = math.exp(lsig[s_k]) if s_k >= 0 else 1.0
    alp = math.exp(lalp[s_k]) if s_k >= 0 else 1.0
    if s_k < 0 or p_tail >= hi[s_k]:
        p_tail = L_END
    if tied:
        for k in range(1, K):
            if hi[k] > lo[k]:
                clo[2], chi[2] = _merge_column(J, 2, 4 * k + 2, clo[2], chi[2], lo[k], hi[k], p_tail)
            free[4 * k + 2] = False
    if linked:
        dc = 4 * dsl + 1
        sc = 4 * ssl + 1
        clo[dc], chi[dc] = _merge_column(J, dc, sc, clo[dc], chi[dc], clo[sc], chi[sc], p_tail)
    for a in range(n):
        g[a] = 0.0
        for b in range(n):
            JtJ[a, b] = 0.0
    # segment ends: every free column's support ends and the pure tail's start, sorted, once each
    nb = 0
    for a in range(n + 1):
        if a < n and not (free[a] and chi[a] > clo[a]):
            continue
        for e in ((clo[a], chi[a]) if a < n else (p_tail, p_tail)):
            j = 0
            while j < nb and bp[j] < e:
                j += 1
            if j < nb and bp[j] == e:
                continue
            for q in range(nb, j, -1):
                bp[q] = bp[q - 1]
            bp[j] = e
            nb += 1
    for sgi in range(nb - 1):
        u = bp[sgi]
        v = bp[sgi + 1]
        na = 0
        for a in range(n):
            if free[a] and clo[a] <= u and chi[a] >= v:
                act[na] = a
                na += 1
        if na == 0:
            continue
        if u >= p_tail:
            _tail_sums(t0, T, J, r, jw, u, v, s_k, amp[s_k], delay[s_k], sig, alp, act, na, JtJ, g)
            continue
        # J^T r: four columns at a time
        for x0 in range(0, na, 4):
            a0 = act[x0]
            a1 = act[min(x0 + 1, na - 1)]
            a2 = act[min(x0 + 2, na - 1)]
            a3 = act[min(x0 + 3, na - 1)]
            s0 = g[a0]
            s1 = g[a1]
            s2 = g[a2]
            s3 = g[a3]
            for i in range(u, v):
                ri = r[i]
                s0 += J[a0, i] * ri
                s1 += J[a1, i] * ri
                s2 += J[a2, i] * ri
                s3 += J[a3, i] * ri
            g[a0] = s0
            if x0 + 1 < na:
                g[a1] = s1
            if x0 + 2 < na:
                g[a2] = s2
            if x0 + 3 < na:
                g[a3] = s3
        # J^T J: the pairs (a <= b) of the covering columns, four at a time
        m = 0
        for x in range(na):
            for y in range(x, na):
                pa[m] = act[x]
                pb[m] = act[y]
                m += 1
        for c0 in range(0, m, 4):
            a0 = pa[c0]
            b0 = pb[c0]
            a1 = pa[min(c0 + 1, m - 1)]
            b1 = pb[min(c0 + 1, m - 1)]
            a2 = pa[min(c0 + 2, m - 1)]
            b2 = pb[min(c0 + 2, m - 1)]
            a3 = pa[min(c0 + 3, m - 1)]
            b3 = pb[min(c0 + 3, m - 1)]
            s0 = JtJ[a0, b0]
            s1 = JtJ[a1, b1]
            s2 = JtJ[a2, b2]
            s3 = JtJ[a3, b3]
            for i in range(u, v):
                wi = jw[i]
                s0 += J[a0, i] * J[b0, i] * wi
                s1 += J[a1, i] * J[b1, i] * wi
                s2 += J[a2, i] * J[b2, i] * wi
                s3 += J[a3, i] * J[b3, i] * wi
            JtJ[a0, b0] = s0
            if c0 + 1 < m:
                JtJ[a1, b1] = s1
            if c0 + 2 < m:
                JtJ[a2, b2] = s2
            if c0 + 3 < m:
                JtJ[a3, b3] = s3
    for a in range(n):
        for b in range(a + 1, n):
            JtJ[b, a] = JtJ[a, b]


@njit
def _tail_sums(t0, T, J, r, jw, u, v, s_k, amp, delay, sig, alp, act, na, JtJ, g):
    """Add the samples [u, v) of the sss atom's pure tail (slot ``s_k``) to J^T J and J^T r.

    There the covering columns are the atom's own and the merged width and delay columns, each
    (a + b x) h with h = J[4 s_k] and x = t - delay - alpha sigma^2: amplitude (1, 0), delay
    (c1, 0), width (c2, 0), log alpha (0, -c1), c1 = amp alpha, c2 = amp (1 + alpha^2 sigma^2)
    (the columns :func:`_eval_slot` writes there).
    """
    s2 = sig * sig
    c1 = amp * alp
    c2 = amp * (1.0 + alp * alp * s2)
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    n0 = 0.0
    n1 = 0.0
    row = 4 * s_k
    xs = t0 - delay - alp * s2
    for i in range(u, v):
        h = J[row, i]
        x = xs + i * T
        hw = h * h * jw[i]
        hr = h * r[i]
        m0 += hw
        m1 += x * hw
        m2 += x * x * hw
        n0 += hr
        n1 += x * hr
    for xa in range(na):
        a = act[xa]
        aa, ba = _tail_coef(a, row, c1, c2)
        g[a] += aa * n0 + ba * n1
        for xb in range(xa, na):
            b = act[xb]
            ab, bb = _tail_coef(b, row, c1, c2)
            JtJ[a, b] += aa * ab * m0 + (aa * bb + ba * ab) * m1 + ba * bb * m2


@njit
def _tail_coef(col, row, c1, c2):
    """(a, b) of column ``col`` in the pure tail of the sss atom whose columns start at ``row``:
    its own amplitude, delay, width and decay columns, or a merged width (column 2, tied widths)
    or delay (the direct's, linked onsets) column."""
    q = col - row
    if q == 0:
        return 1.0, 0.0
    if q == 3:
        return 0.0, -c1
    if q == 2 or col % 4 == 2:
        return c2, 0.0
    return c1, 0.0          # the atom's delay, or the direct's delay merged with it


@njit
def _damped_step(n, JtJ, g, fixed, lam, A, x, idx):
    """Marquardt step (JtJ + lam diag(JtJ)) x = g over the non-fixed parameters (0 elsewhere).

    The damped matrix is symmetric and positive definite (a Gram matrix plus a positive
    diagonal; the caller fixes every column whose diagonal is not positive): Cholesky
    factorisation, then two triangular solves.  A pivot that is not positive (a Gram matrix
    singular to rounding) or a non-finite result gives a zero step.
    """
    m = 0
    for a in range(n):
        x[a] = 0.0
        if not fixed[a]:
            idx[m] = a
            m += 1
    if m == 0:
        return
    # lower triangle of A = L (in place), column m = the right-hand side
    for i in range(m):
        ii = idx[i]
        for j in range(i):
            A[i, j] = JtJ[ii, idx[j]]
        A[i, i] = JtJ[ii, ii] * (1.0 + lam)
        A[i, m] = g[ii]
    for j in range(m):
        d = A[j, j]
        for k in range(j):
            d -= A[j, k] * A[j, k]
        if not d > 0.0:
            return
        d = math.sqrt(d)
        A[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, m):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s * inv
    # L y = g (y over column m), then L^T x = y
    for i in range(m):
        s = A[i, m]
        for k in range(i):
            s -= A[i, k] * A[k, m]
        A[i, m] = s / A[i, i]
    for i in range(m - 1, -1, -1):
        s = A[i, m]
        for k in range(i + 1, m):
            s -= A[k, i] * x[idx[k]]
        x[idx[i]] = s / A[i, i]
    for i in range(m):
        if not math.isfinite(x[idx[i]]):
            for a in range(n):
                x[a] = 0.0
            return


@njit
def _lm_pixels(t0, T, p, fit, cens, wts, fam, amp, delay, lsig, lalp, pen, mu, eps, obj, model, n_iter, tie_sigma,
               sss_after_direct, tol, d_lo, d_hi, s_lo, s_hi, a_lo, a_hi, iters):
    P, L = p.shape
    KA = fam.shape[1]
    nmax = 4 * KA
    J = np.empty((nmax, L))
    Jt = np.empty((nmax, L))
    tmodel = np.empty(L)
    cmodel = np.empty(L)                # the current state's model (swapped with tmodel on accept)
    r = np.empty(L)
    jw = np.empty(L)
    lo = np.zeros(KA, np.int64)
    hi = np.zeros(KA, np.int64)
    tlo = np.zeros(KA, np.int64)
    thi = np.zeros(KA, np.int64)
    clo = np.zeros(nmax, np.int64)
    chi = np.zeros(nmax, np.int64)
    JtJ = np.zeros((nmax, nmax))
    gv = np.zeros(nmax)
    free = np.zeros(nmax, np.bool_)
    fixed = np.zeros(nmax, np.bool_)
    step = np.zeros(nmax)
    A = np.zeros((nmax, nmax + 1))
    idx = np.zeros(nmax, np.int64)
    act = np.zeros(nmax, np.int64)
    bp = np.zeros(2 * nmax + 2, np.int64)
    pa = np.zeros(nmax * (nmax + 1) // 2, np.int64)
    pb = np.zeros(nmax * (nmax + 1) // 2, np.int64)
    sf = np.zeros(KA, np.int8)
    sv = np.zeros((5, KA))
    tf = np.zeros(KA)
    td = np.zeros(KA)
    ts = np.zeros(KA)
    tl = np.zeros(KA)
    for pi in range(P):
        # active slots first, in their order (the inactive ones keep theirs, after them)
        K = 0
        for k in range(KA):
            if fam[pi, k] != FAM_NONE:
                K += 1
        c_act = 0
        c_in = K
        for k in range(KA):
            dst = c_act if fam[pi, k] != FAM_NONE else c_in
            if fam[pi, k] != FAM_NONE:
                c_act += 1
            else:
                c_in += 1
            sf[dst] = fam[pi, k]
            sv[0, dst] = amp[pi, k]
            sv[1, dst] = delay[pi, k]
            sv[2, dst] = lsig[pi, k]
            sv[3, dst] = lalp[pi, k]
            sv[4, dst] = pen[pi, k]
        for k in range(KA):
            fam[pi, k] = sf[k]
            amp[pi, k] = sv[0, k]
            delay[pi, k] = sv[1, k]
            lsig[pi, k] = sv[2, k]
            lalp[pi, k] = sv[3, k]
            pen[pi, k] = sv[4, k]
        f = fam[pi]
        wp = wts[pi] if wts.shape[0] == P else wts[0]     # one row of ones when unweighted
        am = amp[pi]
        de = delay[pi]
        ls = lsig[pi]
        la = lalp[pi]
        pe = pen[pi]
        md = model[pi]
        if K == 0:
            for i in range(L):
                md[i] = 0.0
            obj[pi] = _objective(L, 0, p[pi], fit[pi], cens[pi], wp, md, f, am, pe, mu[pi], eps[pi], r, jw)
            iters[pi] = 0
            continue
        nw = 0.0
        plain = True        # no censored sample, nothing unfitted non-finite: the branch-free objective
        for i in range(L):
            if fit[pi, i] or cens[pi, i]:
                nw += 1.0
            if cens[pi, i] or not (fit[pi, i] or math.isfinite(p[pi, i])):
                plain = False
        nw = max(nw, 1.0)
        n = 4 * K
        _render(t0, T, L, K, f, am, de, ls, la, J, lo, hi, cmodel)
        # (also sets jw, which the branch-free objective then reads as its weights)
        cur = _objective(L, K, p[pi], fit[pi], cens[pi], wp, cmodel, f, am, pe, mu[pi], eps[pi], r, jw)
        if math.isnan(obj[pi]):
            obj[pi] = cur
        level = obj[pi]                  # what a step must beat
        tied, linked, dsl, ssl = _links(K, f, de, ls, tie_sigma, sss_after_direct)
        _normal_equations(t0, T, K, f, am, de, ls, la, J, lo, hi, r, jw, tied, linked, dsl, ssl, JtJ, gv, free, clo, chi,
                          act, bp, pa, pb)
        lam = 1e-3
        it = 0
        while it < n_iter:
            it += 1
            for c in range(n):
                fixed[c] = not free[c] or not JtJ[c, c] > 0.0
            _damped_step(n, JtJ, gv, fixed, lam, A, step, idx)
            if linked:
                # active set for gap >= 0: a gap at 0 whose step points below it is pinned
                col = 4 * ssl + 1
                if de[ssl] - de[dsl] <= 1e-9 and step[col] < 0.0:
                    fixed[col] = True
                    _damped_step(n, JtJ, gv, fixed, lam, A, step, idx)
            for k in range(K):
                tf[k] = min(max(am[k] + step[4 * k], 0.0), AMP_MAX / pe[k])
                td[k] = min(max(de[k] + step[4 * k + 1], d_lo), d_hi)
                ts[k] = min(max(ls[k] + step[4 * k + 2], s_lo), s_hi)
                if f[k] == FAM_SSS:
                    tl[k] = min(max(la[k] + step[4 * k + 3], a_lo), a_hi)
                else:
                    tl[k] = la[k]
            if tied:
                for k in range(1, K):
                    ts[k] = ts[0]
            if linked:
                td[ssl] = min(max(td[ssl] + step[4 * dsl + 1], d_lo), d_hi)
            if sss_after_direct:    # a near onset never moves before the direct (a pixel has one sss atom)
                near, d_k, s_k = onset_link(K, f, td, ts, NEAR_SIGMA)
                if near:
                    td[s_k] = max(td[s_k], td[d_k])
            _render(t0, T, L, K, f, tf, td, ts, tl, Jt, tlo, thi, tmodel, False)
            if plain:
                tobj = _objective_plain(L, K, p[pi], jw, tmodel, f, tf, pe, mu[pi], eps[pi], r)
            else:
                tobj = _objective(L, K, p[pi], fit[pi], cens[pi], wp, tmodel, f, tf, pe, mu[pi], eps[pi], r, jw)
            if tobj < level:
                old = level
                level = tobj
                cur = tobj
                for k in range(K):
                    am[k] = tf[k]
                    de[k] = td[k]
                    ls[k] = ts[k]
                    la[k] = tl[k]
                    lo[k] = tlo[k]
                    hi[k] = thi[k]
                J, Jt = Jt, J
                cmodel, tmodel = tmodel, cmodel
                if old - tobj <= tol * old / nw:
                    break                # converged: this state's normal equations are not needed
                _fill_derivatives(t0, T, L, K, f, am, de, ls, la, J, lo, hi)
                tied, linked, dsl, ssl = _links(K, f, de, ls, tie_sigma, sss_after_direct)
                _normal_equations(t0, T, K, f, am, de, ls, la, J, lo, hi, r, jw, tied, linked, dsl, ssl, JtJ, gv, free, clo, chi,
                          act, bp, pa, pb)
                lam = max(lam / 3.0, 1e-9)
            else:
                lam *= 4.0
                if lam > 1e8:
                    break
        for i in range(L):
            md[i] = cmodel[i]
        obj[pi] = cur
        iters[pi] = it


def lm_refine(t0_ps, time_bin_ps, p, mask: SampleMask, st, mu, eps, bounds, n_iter, obj=None, *, tie_sigma=False,
              sss_after_direct=False, tol=0.0, weights=None):
    """Refine the active atoms of every pixel by Levenberg-Marquardt; F never increases.

    Parameters
    ----------
    t0_ps, time_bin_ps : float
        Time axis: bin i at t0_ps + i * time_bin_ps.
    p : ndarray (P, L) float64
        Profiles (unit peak).
    mask : SampleMask
        Fitted and censored samples (:mod:`decomposition.masks`).
    st : dict of (P, K) arrays
        Slot state: fam (int8), amp, delay (ps), lsig (log sigma_ps), lalp (log alpha_per_ps),
        pen (penalty scale).  Not modified.
    mu, eps : ndarray (P,)
        Penalty weight and scale.
    bounds : dict
        (lo, hi) for "delay", "lsig", "lalp".
    n_iter : int
        Largest number of LM iterations per pixel.
    obj : ndarray (P,), optional
        F at the start state, the level a step must beat (default: computed exactly here;
        NaN entries are computed too).
    tie_sigma, sss_after_direct : bool
        See the module docstring.
    tol : float
        A pixel stops once an accepted step gains less than ``tol`` * F / (fitted samples).
    weights : ndarray (P, L), optional
        Least-squares weights of the samples the masks let count (relative inverse variances,
        finite and >= 0): the data term becomes 1/2 sum w (p - model)^2.  Default: 1 for all
        (the unweighted objective, exactly).

    Returns
    -------
    state : dict of (P, K) arrays, active slots first in their original order.
    obj : ndarray (P,)
        F at the returned state, evaluated exactly.
    iterations : ndarray (P,) int64
        LM iterations run per pixel.
    model : ndarray (P, L)
        Model of the returned state.
    """
    P, L = p.shape
    check_mask(mask, p.shape)
    out = {k: np.array(v, dtype=np.int8 if k == "fam" else np.float64, order="C", copy=True)
           for k, v in st.items()}
    o = np.full(P, np.nan) if obj is None else np.array(obj, np.float64, copy=True)
    model = np.empty((P, L))
    iters = np.zeros(P, np.int64)
    if weights is None:
        wts = np.ones((1, L))                # one row serves every pixel
    else:
        wts = np.ascontiguousarray(weights, np.float64)
        if wts.shape != (P, L):
            raise ValueError(f"weights have shape {wts.shape}, the profiles {(P, L)}")
        if not (np.isfinite(wts).all() and (wts >= 0).all()):
            raise ValueError("weights must be finite and >= 0")
    if P:
        _lm_pixels(float(t0_ps), float(time_bin_ps), np.ascontiguousarray(p, np.float64),
                   np.ascontiguousarray(mask.fit), np.ascontiguousarray(mask.censored), wts, out["fam"], out["amp"],
                   out["delay"], out["lsig"], out["lalp"], out["pen"], np.asarray(mu, np.float64), np.asarray(eps, np.float64), o, model,
                   int(n_iter), bool(tie_sigma), bool(sss_after_direct), float(tol),
                   float(bounds["delay"][0]), float(bounds["delay"][1]), float(bounds["lsig"][0]),
                   float(bounds["lsig"][1]), float(bounds["lalp"][0]), float(bounds["lalp"][1]), iters)
    return out, o, iters, model
