"""Off-grid refinement of decomposed components by batched nonlinear least squares.

The sparse-coding step decides *which* components a pixel has and puts each on
a grid of delays, widths and attenuations.  This module keeps that component
set fixed and moves every present component's continuous parameters off the
grid to the least-squares optimum of the forward model of
:mod:`decomposition.model`.

Method: variable projection with Levenberg-Marquardt damping
-------------------------------------------------------------
A profile is linear in the amplitudes and nonlinear in the rest,

    y ~ Phi(theta) c,    Phi = [g(t - t_d; s_d), h(t - t_s; s_s, alpha), g(t - t_r; s_r), ...]

so for given nonlinear parameters theta the amplitudes c are solved exactly by
linear least squares, and LM only walks in theta = (delays, log sigmas,
log alpha).  This is variable projection (Golub & Pereyra 1973) with
Kaufman's (1975) approximation of the Jacobian of the projected residual,

    J_j = -P_perp(theta) (c_k d phi_k / d theta_j),   P_perp = I - Phi (Phi^T Phi)^-1 Phi^T,

which is better conditioned than LM over all parameters and cannot be led
astray by a bad amplitude start.  Widths and attenuation are refined in log
space, so sigma > 0 and alpha > 0 hold by construction; simple bounds are
enforced by projection.

Everything is batched over a block of pixels: slot arrays of shape
(pixels, K) with K = 2 + R (direct, sss, inter-reflections r2..), absent slots
masked (zero basis column, identity row in the normal equations).  Each LM
iteration works on the block's still-active pixels at once; the L-length work
(kernels, derivatives, one Gram product of the stacked rows [Phi; dPhi; y]) is
done in cache-sized chunks of pixels, which is several times faster than
whole-block temporaries.  The only Python loops are over LM iterations, blocks
and chunks of pixels, and the quadrature nodes of bin-integrated sampling.
Damping follows the gain ratio (Nielsen 1999); a pixel stops when an accepted
step lowers its RSS by less than ``ftol`` relative, or when no step helps.

Options: ``shared_sigma`` refines one PSF width per pixel for all its
components (eq. (2) has a single camera PSF); ``sss_after_direct`` keeps the
sss onset at or after the direct delay (projection); ``weights`` give per-sample
weights (0 excludes saturated or spiky samples).

Each pixel is normalised by its peak magnitude before fitting, so any overall
scale (1e-30 .. 1e30) gives the same parameters and scaled amplitudes.  A
pixel's refined parameters are kept only when they lower its residual sum of
squares below that of the input parameters (with the input amplitudes) and
keep every present amplitude positive; otherwise the input is returned as is.

Analytic derivatives (t relative to the component's delay, s = sigma, a = alpha)
-------------------------------------------------------------------------------
Gaussian g = exp(-t^2 / (2 s^2)):

    dg/d delay = g t / s^2,      dg/ds = g t^2 / s^3.

sss kernel h = integral_0^inf exp(-a tau) g(t - tau) d tau (the closed form in
model.py).  Differentiating under the integral, or the closed form, gives
expressions in h and g alone, both of which model.py evaluates without
overflow for any a*s:

    dh/dt       = g - a h                       (so dh/d delay = a h - g)
    dh/da       = (a s^2 - t) h - s^2 g
    dh/ds       = h (1/s + a^2 s) - g (a s + t/s)

(for dh/da: d/da of a^2 s^2 / 2 - a t is a s^2 - t, and d erfc(u)/da with
u = (a s^2 - t)/(s sqrt 2) contributes -s^2 exp(a^2 s^2/2 - a t - u^2) = -s^2 g).
The cancellation between the two terms for large a*s costs at most about
eps * (a s)^2 relative to the size of the derivative column, far below what
the fit needs; tests check all of them against finite differences.
"""

from __future__ import annotations

import numpy as np
from scipy import special

from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, _GL_NODES, _GL_WEIGHTS, time_axis_ps

__all__ = ["refine", "kernel_derivatives", "slot_arrays", "params_from_slots"]

# Slot layout: 0 = direct, 1 = sss, 2.. = inter-reflections.
_SSS = 1
_SQRT_PI_2 = np.sqrt(np.pi / 2.0)
_SQRT_2 = np.sqrt(2.0)


# ----------------------------------------------------------------------------------------------
# kernels and their derivatives
# ----------------------------------------------------------------------------------------------

# exp() of arguments below about -708 underflows through a slow path (10x);
# exp(-700) = 1e-304 is already zero for every purpose here.
_EXP_FLOOR = -700.0


def _gauss_point(t, s, deriv=True):
    z = t / s
    g = np.exp(np.maximum(-0.5 * z * z, _EXP_FLOOR))
    if not deriv:
        return (g,)
    gz = g * z
    return g, gz / s, gz * z / s


# erfc(u) rounds to exactly 2.0 for u <= -6 (erfc(6) = 2.2e-17 < half an ulp of 2).
_ERFC_IS_TWO = -6.0
# exp(-z^2/2) is below the exp floor for |z| > 37.5: the rising edge is zero there.
_Z_NEGLIGIBLE = 37.5


def _sss_point(t, s, a, deriv=True):
    """sss kernel and its derivatives (see module docstring) with the stable branches of model.py.

    u = (a s^2 - t) / (s sqrt 2);  u >= 0: h = c g erfcx(u);  u < 0: h = c exp(-a (t - a s^2/2)) erfc(u),
    c = s sqrt(pi/2).  The special functions are evaluated only where they are not
    exactly 2 (erfc, u > -6) or multiplied by an underflowed g (erfcx, t far before
    the onset), which is a few dozen samples per profile.
    """
    t, s, a = np.broadcast_arrays(np.asarray(t, np.float64), np.asarray(s, np.float64),
                                  np.asarray(a, np.float64))
    z = t / s
    q = a * s
    u = (q - z) * (1.0 / _SQRT_2)
    g = np.exp(np.maximum(-0.5 * z * z, _EXP_FLOOR))
    # Tail branch everywhere first; its exponent is negative wherever u < 0 (clamped elsewhere).
    e = np.exp(np.clip(q * (0.5 * q - z), _EXP_FLOOR, 0.0))
    h = 2.0 * e
    fix = np.nonzero((u > _ERFC_IS_TWO) & (z > -_Z_NEGLIGIBLE))
    uf = u[fix]
    pos = uf >= 0
    hf = np.empty_like(uf)
    hf[pos] = g[fix][pos] * special.erfcx(uf[pos])
    neg = ~pos
    hf[neg] = e[fix][neg] * special.erfc(uf[neg])
    h[u >= 0] = 0.0  # rising edge far before the onset (g underflowed); overwritten below where not
    h[fix] = hf
    h *= _SQRT_PI_2 * s
    if not deriv:
        return (h,)
    d_delay = a * h - g
    d_sigma = h * ((1.0 + q * q) / s) - g * (q + z)
    d_alpha = s * ((q - z) * h - s * g)
    return h, d_delay, d_sigma, d_alpha


def kernel_derivatives(t_rel_ps, sigma_ps, alpha_per_ps=None, *, time_bin_ps=None, derivatives=True):
    """Kernel values and analytic derivatives with respect to its parameters.

    Parameters
    ----------
    t_rel_ps : array_like
        Sample times minus the component's delay, in ps.
    sigma_ps : array_like
        Gaussian width in ps (> 0); broadcasts against ``t_rel_ps``.
    alpha_per_ps : array_like, optional
        sss attenuation in 1/ps (>= 0).  ``None`` selects the unit-peak Gaussian.
    time_bin_ps : float, optional
        If given, values and derivatives are averaged over a bin of this width
        (matches ``bin_integrated=True`` rendering in :mod:`decomposition.model`).
    derivatives : bool
        ``False`` returns the 1-tuple ``(k,)`` only (cheaper).

    Returns
    -------
    tuple of ndarray, float64, broadcast shape of the inputs:
        ``(k, dk_ddelay, dk_dsigma)`` for the Gaussian and
        ``(k, dk_ddelay, dk_dsigma, dk_dalpha)`` for the sss kernel; the delay
        derivative is with respect to the component's delay (= -dk/dt), units
        1/ps for delay and sigma, ps for alpha.
    """
    t = np.asarray(t_rel_ps, np.float64)
    s = np.asarray(sigma_ps, np.float64)

    def point(tt):
        if alpha_per_ps is None:
            return _gauss_point(tt, s, derivatives)
        return _sss_point(tt, s, np.asarray(alpha_per_ps, np.float64), derivatives)

    if time_bin_ps is None:
        return point(t)
    acc = None
    for x, w in zip(_GL_NODES, _GL_WEIGHTS):
        vals = point(t + x * float(time_bin_ps))
        acc = [w * v for v in vals] if acc is None else [a + w * v for a, v in zip(acc, vals)]
    return tuple(acc)


# ----------------------------------------------------------------------------------------------
# parameter dict <-> slot arrays
# ----------------------------------------------------------------------------------------------

def slot_arrays(params: dict, lead_shape: tuple) -> dict[str, np.ndarray]:
    """Flatten a parameter dict into per-slot arrays.

    Parameters
    ----------
    params : dict of ndarray
        Keys of :mod:`decomposition.model`; a missing family counts as absent.
    lead_shape : tuple
        Leading (pixel) shape the parameters must have.

    Returns
    -------
    dict with ``delay``, ``amplitude``, ``sigma`` (N, K) and ``alpha`` (N,),
    ``present`` (N, K) bool, and ``n_ir`` (int); N = prod(lead_shape),
    K = 2 + n_ir, slot 0 direct, 1 sss, 2.. inter-reflections in input order.
    """
    lead_shape = tuple(lead_shape)
    n = int(np.prod(lead_shape, dtype=np.int64))

    def get(key, extra=()):
        if key not in params:
            return None
        v = np.asarray(params[key], dtype=np.float64)
        if v.shape != lead_shape + extra:
            raise ValueError(f"params[{key!r}] has shape {v.shape}, expected {lead_shape + extra}")
        return v.reshape((n,) + extra)

    n_ir = 0
    if "ir_delay_ps" in params:
        shp = np.shape(params["ir_delay_ps"])
        if shp[:-1] != lead_shape or len(shp) != len(lead_shape) + 1:
            raise ValueError(f"params['ir_delay_ps'] has shape {shp}, expected {lead_shape} + (R,)")
        n_ir = shp[-1]
    k = 2 + n_ir
    out = {name: np.full((n, k), np.nan) for name in ("delay", "amplitude", "sigma")}
    out["alpha"] = np.full(n, np.nan)
    for slot, keys in ((0, DIRECT_KEYS), (_SSS, ("sss_delay_ps", "sss_amplitude", "sss_sigma_ps"))):
        vals = [get(key) for key in keys]
        if all(v is not None for v in vals):
            for name, v in zip(("delay", "amplitude", "sigma"), vals):
                out[name][:, slot] = v
    a = get("sss_alpha_per_ps")
    if a is not None:
        out["alpha"] = a
    if n_ir:
        vals = [get(key, (n_ir,)) for key in IR_KEYS]
        if any(v is None for v in vals):
            raise ValueError("params has ir_delay_ps but not all of " + ", ".join(IR_KEYS))
        for name, v in zip(("delay", "amplitude", "sigma"), vals):
            out[name][:, 2:] = v
    present = np.isfinite(out["delay"]) & np.isfinite(out["amplitude"]) & np.isfinite(out["sigma"])
    present &= out["sigma"] > 0
    present[:, _SSS] &= np.isfinite(out["alpha"]) & (out["alpha"] >= 0)
    out["present"] = present
    out["n_ir"] = n_ir
    return out


def params_from_slots(slots: dict, lead_shape: tuple) -> dict[str, np.ndarray]:
    """Inverse of :func:`slot_arrays`: absent slots become NaN; returns a full parameter dict."""
    lead_shape = tuple(lead_shape)
    pres = slots["present"]
    n_ir = slots["n_ir"]

    def col(name, sl):
        v = np.where(pres[:, sl], slots[name][:, sl], np.nan)
        return v

    out = {}
    for key, name in zip(DIRECT_KEYS, ("delay", "amplitude", "sigma")):
        out[key] = col(name, 0).reshape(lead_shape)
    for key, name in zip(("sss_delay_ps", "sss_amplitude", "sss_sigma_ps"), ("delay", "amplitude", "sigma")):
        out[key] = col(name, _SSS).reshape(lead_shape)
    out["sss_alpha_per_ps"] = np.where(pres[:, _SSS], slots["alpha"], np.nan).reshape(lead_shape)
    for key, name in zip(IR_KEYS, ("delay", "amplitude", "sigma")):
        out[key] = col(name, slice(2, None)).reshape(lead_shape + (n_ir,))
    return {key: out[key] for key in DIRECT_KEYS + SSS_KEYS + IR_KEYS}


# ----------------------------------------------------------------------------------------------
# batched basis, amplitudes, projected Jacobian
# ----------------------------------------------------------------------------------------------

def _design(t, y, delay, sigma, alpha, present, tb, jac, sw=None):
    """Stacked design rows M (n, Q, L) for one batched Gram product.

    Rows: [0, K) basis phi_k; if ``jac``, [K, 2K) d phi_k / d delay_k,
    [2K, 3K) d phi_k / d log sigma_k, 3K the sss d h / d log alpha; the last
    row is the data y.  Absent slots are zero rows.  With ``sw`` (n, L), the
    square roots of the sample weights, the model rows are weighted (``y``
    must already be).
    """
    n, k = delay.shape
    L = t.size
    q = (3 * k + 2) if jac else (k + 1)
    m = np.zeros((n, q, L))
    m[:, -1] = y
    gmask = present.copy()
    gmask[:, _SSS] = False
    rows = np.arange(k)
    if gmask.any():
        pix, slot = np.nonzero(gmask)
        s = sigma[pix, slot][:, None]
        vals = kernel_derivatives(t - delay[pix, slot][:, None], s, time_bin_ps=tb, derivatives=jac)
        m[pix, rows[slot]] = vals[0]
        if jac:
            m[pix, k + rows[slot]] = vals[1]
            m[pix, 2 * k + rows[slot]] = vals[2] * s
    pix = np.flatnonzero(present[:, _SSS])
    if pix.size:
        s = sigma[pix, _SSS][:, None]
        a = alpha[pix][:, None]
        vals = kernel_derivatives(t - delay[pix, _SSS][:, None], s, a, time_bin_ps=tb, derivatives=jac)
        m[pix, _SSS] = vals[0]
        if jac:
            m[pix, k + _SSS] = vals[1]
            m[pix, 2 * k + _SSS] = vals[2] * s
            m[pix, 3 * k] = vals[3] * a
    if sw is not None:
        m[:, :-1] *= sw[:, None, :]
    return m


def _regularise(gram, present):
    """Absent slots get an identity row; a tiny ridge keeps collinear components solvable.

    The ridge moves a well-separated amplitude by ~1e-13 relative.
    """
    k = gram.shape[-1]
    diag = np.einsum("nkk->nk", gram)
    scale = np.max(np.where(present, diag, 0.0), axis=-1, keepdims=True)
    ridge = np.where(present, 1e-13 * scale + 1e-300, 1.0)
    gram = gram.copy()
    gram[:, np.arange(k), np.arange(k)] = np.where(present, diag, 0.0) + ridge
    return gram


class _Layout:
    """Nonlinear parameters theta (n, P) and how they map onto the derivative rows.

    Derivative rows (Q = 2K + 1): d/d delay_k, d/d log sigma_k (k < K), d/d log alpha.
    Independent widths: theta = [delay_0..K-1, log sigma_0..K-1, log alpha], P = Q.
    Shared width (``shared_sigma``, one PSF per pixel as in eq. (2) of the paper):
    theta = [delay_0..K-1, log sigma, log alpha], P = K + 2, and the sigma
    parameter moves every present component's width together.
    """

    def __init__(self, k, shared_sigma=False):
        self.k = k
        self.q = 2 * k + 1
        self.shared = bool(shared_sigma)
        self.dslot = np.concatenate([np.arange(k), np.arange(k), [_SSS]])
        if self.shared:
            self.p = k + 2
            assign = np.zeros((self.p, self.q))
            assign[np.arange(k), np.arange(k)] = 1.0
            assign[k, k:2 * k] = 1.0
            assign[k + 1, 2 * k] = 1.0
        else:
            self.p = self.q
            assign = np.eye(self.q)
        self.assign = assign

    def free_rows(self, present):
        return np.concatenate([present, present, present[:, _SSS:_SSS + 1]], axis=1)

    def free(self, present):
        return (self.free_rows(present).astype(np.float64) @ self.assign.T) > 0

    def pack(self, delay, sigma, alpha, present):
        k = self.k
        with np.errstate(divide="ignore", invalid="ignore"):
            logs = np.log(sigma)
            loga = np.log(alpha)[:, None]
        if not self.shared:
            return np.concatenate([delay, logs, loga], axis=1)
        # Start the shared width from the direct component's, else the mean over present ones.
        npres = present.sum(axis=1)
        mean = np.where(present, logs, 0.0).sum(axis=1) / np.maximum(npres, 1)
        shared = np.where(present[:, 0], logs[:, 0], mean)[:, None]
        return np.concatenate([delay, shared, loga], axis=1)

    def unpack(self, theta):
        k = self.k
        if self.shared:
            sigma = np.repeat(np.exp(theta[:, k:k + 1]), k, axis=1)
        else:
            sigma = np.exp(theta[:, k:2 * k])
        return theta[:, :k], sigma, np.exp(theta[:, -1])

    def truncated(self, k_eff):
        """Layout of the first ``k_eff`` slots and the indices of its parameters in this one."""
        key = (k_eff, self.shared)
        cache = self.__dict__.setdefault("_sub", {})
        if key not in cache:
            k = self.k
            if self.shared:
                cols = np.concatenate([np.arange(k_eff), [k, k + 1]])
            else:
                cols = np.concatenate([np.arange(k_eff), k + np.arange(k_eff), [2 * k]])
            cache[key] = (self if k_eff == k else _Layout(k_eff, self.shared), cols)
        return cache[key]

    def bounds(self, delay_lim, logsigma_lim, logalpha_lim):
        n_sig = 1 if self.shared else self.k
        lo = np.concatenate([np.full(self.k, delay_lim[0]), np.full(n_sig, logsigma_lim[0]), [logalpha_lim[0]]])
        hi = np.concatenate([np.full(self.k, delay_lim[1]), np.full(n_sig, logsigma_lim[1]), [logalpha_lim[1]]])
        return lo, hi


# Pixels per chunk of the L-length work: keeps the temporaries of the kernel
# evaluation within the CPU caches (a whole block at once is several times slower).
_CHUNK = 48


def _evaluate(lay, t, y, theta, present, free, tb, jac, sw=None):
    """:func:`_evaluate_chunk` over cache-sized chunks of pixels.

    Pixels are taken in order of their last present slot, and each chunk is
    evaluated with the inter-reflection slots that none of its pixels uses cut
    off (most pixels have fewer inter-reflections than R), so the Gram products
    only carry rows that can be non-zero.  Results come back in pixel order, in
    the full layout (zeros for the cut slots, which are not free there).
    """
    n = y.shape[0]
    last = np.max(np.where(present, np.arange(lay.k), 1), axis=1)  # >= 1: direct and sss always kept
    order = np.argsort(last, kind="stable")
    c_out = np.zeros((n, lay.k))
    rss_out = np.empty(n)
    a_out = np.zeros((n, lay.p, lay.p)) if jac else None
    g_out = np.zeros((n, lay.p)) if jac else None
    for i in range(0, n, _CHUNK):
        sel = order[i:i + _CHUNK]
        k_eff = int(last[sel].max()) + 1
        sub_lay, cols = lay.truncated(k_eff)
        c, rss, a, g = _evaluate_chunk(sub_lay, t, y[sel], theta[np.ix_(sel, cols)], present[sel, :k_eff],
                                       free[np.ix_(sel, cols)], tb, jac, None if sw is None else sw[sel])
        c_out[sel, :k_eff] = c
        rss_out[sel] = rss
        if jac:
            a_out[sel[:, None, None], cols[None, :, None], cols[None, None, :]] = a
            g_out[np.ix_(sel, cols)] = g
    return c_out, rss_out, a_out, g_out


def _evaluate_chunk(lay, t, y, theta, present, free, tb, jac, sw=None):
    """Amplitudes, residual sum of squares and (if jac) the LM normal equations at theta.

    With V = W dPhi (rows; W carries the amplitudes c and the parameter
    mapping of the layout), G = Phi Phi^T and B = Phi V^T, Kaufman's projected
    Jacobian J = Phi^T G^-1 B - V^T gives J^T J = V V^T - B^T G^-1 B and
    J^T r = -V r (because Phi r = 0), so one batched Gram product of the
    stacked rows [Phi; dPhi; y] is all the L-length work.
    """
    k, q = lay.k, lay.q
    delay, sigma, alpha = lay.unpack(theta)
    m = _design(t, y, delay, sigma, alpha, present, tb, jac, sw)
    mm = m @ m.swapaxes(-1, -2)
    gram = _regularise(mm[:, :k, :k], present)
    c = np.linalg.solve(gram, mm[:, :k, -1][..., None])[..., 0]
    c = np.where(present, c, 0.0)
    r = y - np.einsum("nk,nkl->nl", c, m[:, :k])
    rss = np.einsum("nl,nl->n", r, r)
    if not jac:
        return c, rss, None, None
    w_rows = c[:, lay.dslot] * lay.free_rows(present)
    w = lay.assign[None, :, :] * w_rows[:, None, :] * free[:, :, None]  # (n, P, Q)
    b = mm[:, :k, k:k + q] @ w.swapaxes(-1, -2)  # (n, K, P)
    vv = w @ mm[:, k:k + q, k:k + q] @ w.swapaxes(-1, -2)
    vr = np.einsum("npq,nq->np", w, np.einsum("nql,nl->nq", m[:, k:k + q], r))
    x = np.linalg.solve(gram, b)
    a = vv - b.swapaxes(-1, -2) @ x
    return c, rss, a, -vr


def _amp_violations(c, present):
    return np.sum(present & ~(c > 0), axis=-1)


def _onset_after_direct(theta, present):
    """Project sss onsets onto delay >= direct delay where a pixel has both (theta[:, 0] / [:, 1])."""
    both = present[:, 0] & present[:, _SSS]
    theta[:, _SSS] = np.where(both, np.maximum(theta[:, _SSS], theta[:, 0]), theta[:, _SSS])
    return theta


def _keep_order(theta, present):
    """Keep the labels valid: the direct delay first, inter-reflections in order of delay.

    Each present inter-reflection delay is raised to at least the latest present
    Gaussian delay before it (direct, then r2, r3, ...), a feasible point of the
    ordering constraints closest to the step along each coordinate in turn.
    """
    k = present.shape[1]
    prev = np.where(present[:, 0], theta[:, 0], -np.inf)
    for slot in range(2, k):
        d = np.where(present[:, slot], np.maximum(theta[:, slot], prev), theta[:, slot])
        theta[:, slot] = d
        prev = np.where(present[:, slot], d, prev)
    return theta


def _refine_block(t, y, slots, lay, bounds, tb, max_iter, ftol, lam0, sw=None, sss_after_direct=False,
                  keep_order=True):
    n = y.shape[0]
    present = slots["present"]
    free = lay.free(present)
    lo, hi = bounds
    theta = lay.pack(slots["delay"], slots["sigma"], slots["alpha"], present)
    theta = np.where(free, theta, 0.0)
    theta = np.clip(theta, lo, hi)
    if sss_after_direct:
        theta = _onset_after_direct(theta, present)
    if keep_order:
        theta = _keep_order(theta, present)

    # RSS of the input exactly as given (input amplitudes), the never-worse reference.
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = np.where(present, slots["sigma"], 1.0)
        a0 = np.where(present[:, _SSS], slots["alpha"], 1.0)
    d0 = np.where(present, slots["delay"], 0.0)
    amp_in = np.where(present, slots["amplitude"], 0.0)
    rss_input = np.empty(n)
    for i in range(0, n, _CHUNK):
        ch = slice(i, i + _CHUNK)
        phi0 = _design(t, y[ch], d0[ch], s0[ch], a0[ch], present[ch], tb, False,
                       None if sw is None else sw[ch])[:, :lay.k]
        r0 = y[ch] - np.einsum("nk,nkl->nl", amp_in[ch], phi0)
        rss_input[ch] = np.einsum("nl,nl->n", r0, r0)

    c, rss, a, g = _evaluate(lay, t, y, theta, present, free, tb, True, sw)
    viol = _amp_violations(c, present)
    lam = np.full(n, lam0)
    nu = np.full(n, 2.0)
    iters = np.zeros(n, dtype=np.int64)
    converged = np.zeros(n, dtype=bool)
    active = free.any(axis=1) & np.isfinite(rss)
    converged[~active] = True
    ynorm2 = np.einsum("nl,nl->n", y, y)

    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        fr = free[idx]
        ai, gi = a[idx], g[idx]
        diag = np.einsum("npp->np", ai)
        dscale = np.maximum(diag, 1e-12 * np.max(diag, axis=-1, keepdims=True) + 1e-300)
        lhs = ai * fr[:, :, None] * fr[:, None, :]
        pidx = np.arange(lay.p)
        lhs[:, pidx, pidx] = np.where(fr, diag + lam[idx, None] * dscale, 1.0)
        rhs = np.where(fr, -gi, 0.0)
        step = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        trial = np.clip(theta[idx] + step, lo, hi)
        if sss_after_direct:
            trial = _onset_after_direct(trial, present[idx])
        if keep_order:
            trial = _keep_order(trial, present[idx])
        trial = np.where(fr, trial, 0.0)
        c_t, rss_t, a_t, g_t = _evaluate(lay, t, y[idx], trial, present[idx], fr, tb, True,
                                         None if sw is None else sw[idx])
        viol_t = _amp_violations(c_t, present[idx])
        ok = np.isfinite(rss_t) & np.all(np.isfinite(a_t), axis=(1, 2)) & (viol_t <= viol[idx])
        accept = ok & (rss_t < rss[idx])
        iters[idx] += 1
        gain = (rss[idx] - rss_t) / np.maximum(rss[idx], 1e-300)
        # Gain ratio against the damped Gauss-Newton model drives the damping (Nielsen 1999).
        pred = -np.einsum("np,np->n", step, gi) + lam[idx] * np.einsum("np,np,np->n", step, dscale, step)
        rho = (rss[idx] - rss_t) / np.maximum(pred, 1e-300)

        acc = idx[accept]
        theta[acc], c[acc], rss[acc], a[acc], g[acc] = trial[accept], c_t[accept], rss_t[accept], a_t[accept], g_t[accept]
        viol[acc] = viol_t[accept]
        lam[acc] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * np.clip(rho[accept], 0.0, 1.0) - 1.0) ** 3)
        lam[acc] = np.maximum(lam[acc], 1e-12)
        nu[acc] = 2.0
        rej = idx[~accept]
        lam[rej] *= nu[rej]
        nu[rej] *= 2.0

        # Converged: an accepted step that no longer lowers the RSS noticeably,
        # a fit that is exact to rounding, or damping so large that no step helps.
        done = np.zeros(idx.size, bool)
        done |= accept & (gain < ftol)
        done |= rss[idx] <= 1e-26 * ynorm2[idx]
        stalled = ~accept & (lam[idx] > 1e12)
        converged[idx[done | stalled]] = True
        active[idx[done | stalled]] = False

    delay, sigma, alpha = lay.unpack(theta)
    kept = (rss < rss_input) & (viol == 0) & np.isfinite(rss)
    out = {
        "delay": np.where(kept[:, None], delay, slots["delay"]),
        "sigma": np.where(kept[:, None], sigma, slots["sigma"]),
        "alpha": np.where(kept & present[:, _SSS], alpha, slots["alpha"]),
        "amplitude": np.where(kept[:, None], c, slots["amplitude"]),
    }
    info = {
        "iterations": iters,
        "converged": converged,
        "refined": kept,
        "rss_input": rss_input,
        "rss": np.where(kept, rss, rss_input),
    }
    return out, info



def _apply_weights(y, weights):
    """Validate per-sample weights against profiles ``y`` (..., L).

    Returns ``y`` with zero-weight samples set to 0 (they may hold anything: NaN,
    saturation) and the square-root weights as (n_pixels, L), or ``None`` without weights.
    """
    if weights is None:
        return y, None
    wts = np.asarray(weights, dtype=np.float64)
    if wts.shape != y.shape:
        raise ValueError(f"weights must have the shape of profiles {y.shape}, got {wts.shape}")
    if np.any(~np.isfinite(wts)) or np.any(wts < 0):
        raise ValueError("weights must be finite and non-negative")
    return np.where(wts > 0, y, 0.0), np.sqrt(wts).reshape(-1, y.shape[-1])

def refine(profiles, params, *, time_bin_ps: float = 2.0, t0_ps: float | None = None,
           max_iter: int = 20, ftol: float = 1e-6, block_size: int = 4096,
           sigma_bounds_ps: tuple[float, float] | None = None,
           alpha_bounds_per_ps: tuple[float, float] = (1e-7, 1e3),
           shared_sigma: bool = False, sss_after_direct: bool = False, keep_order: bool = True, weights=None,
           bin_integrated: bool = False):
    """Refine the continuous parameters of each pixel's present components.

    Parameters
    ----------
    profiles : array_like, shape (..., L)
        Measured time profiles, any real dtype; must be finite.
    params : dict of ndarray
        Starting parameters (keys of :mod:`decomposition.model`, shapes (...,)
        and (..., R)); NaN marks an absent component.  Which components are
        present is never changed.
    time_bin_ps, t0_ps : float
        Time axis (bin ``i`` at ``t0_ps + i * time_bin_ps``; t0 defaults to one bin).
    max_iter : int
        Maximum Levenberg-Marquardt iterations per pixel (each costs one model
        evaluation with its Jacobian).
    ftol : float
        A pixel has converged when an accepted step lowers its residual sum of
        squares by less than this fraction.
    block_size : int
        Pixels fitted together (memory ~ block_size * L * (2K+1) * 8 bytes * 3).
    sigma_bounds_ps : (float, float), optional
        Bounds on every sigma; default (time_bin_ps / 10, L * time_bin_ps).
    alpha_bounds_per_ps : (float, float)
        Bounds on the sss attenuation (strictly positive: refined in log space).
    shared_sigma : bool
        Fit one Gaussian width per pixel shared by all its components (the
        camera PSF of eq. (2)), started from the direct component's width (or
        the mean of the present ones).  Fewer unknowns and no width/delay
        trade-off between overlapping components; use it when the data come
        from one PSF.  Default: each component has its own width.
    sss_after_direct : bool
        Keep every sss onset at or after its pixel's direct delay (light enters
        the surface where it is directly reflected).  A pixel whose sss rising
        edge sits under its direct peak is nearly degenerate in least squares;
        the constraint (enforced by projection) removes that freedom.
    keep_order : bool
        Keep the component labels valid while refining: no inter-reflection
        moves before the direct reflection or before an earlier
        inter-reflection (enforced by projection).  Inter-reflection slots are
        assumed to be in order of delay, as decompositions report them.
    weights : array_like, shape (..., L), optional
        Non-negative per-sample weights of the least-squares fit (1 / variance
        for heteroscedastic noise; 0 excludes a sample, e.g. a saturated one,
        whose value is then ignored even if it is NaN).  Default: all ones.
    bin_integrated : bool
        Fit bin-averaged kernels instead of point samples (as in model.render_*).

    Returns
    -------
    params : dict of ndarray
        Refined parameters, same keys and shapes as a full parameter dict,
        NaN where a component is absent.  Pixels whose fit did not improve keep
        their input parameters exactly.
    info : dict of ndarray, each of the leading shape (...,)
        ``iterations`` (int), ``converged`` (bool), ``refined`` (bool: refined
        values were kept), ``rss_input`` and ``rss`` (weighted residual sums
        of squares of the input and returned parameters, in the units of
        ``profiles`` squared).
    """
    y = np.asarray(profiles)
    if y.ndim < 1 or y.shape[-1] < 2:
        raise ValueError(f"profiles must have shape (..., L) with L >= 2, got {y.shape}")
    if not np.issubdtype(y.dtype, np.number) or np.iscomplexobj(y):
        raise ValueError(f"profiles must be real numbers, got dtype {y.dtype}")
    y = y.astype(np.float64)
    y, sw = _apply_weights(y, weights)
    bad = ~np.isfinite(y).all(axis=-1)
    if bad.any():
        raise ValueError(f"profiles contain NaN or inf samples in {int(bad.sum())} pixel(s)")
    if int(max_iter) < 0:
        raise ValueError("max_iter must be >= 0")
    if int(block_size) < 1:
        raise ValueError("block_size must be >= 1")
    lead = y.shape[:-1]
    n_bins = y.shape[-1]
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    tb = float(time_bin_ps) if bin_integrated else None
    if sigma_bounds_ps is None:
        sigma_bounds_ps = (float(time_bin_ps) / 10.0, n_bins * float(time_bin_ps))
    s_lo, s_hi = map(float, sigma_bounds_ps)
    a_lo, a_hi = map(float, alpha_bounds_per_ps)
    if not (0 < s_lo < s_hi and np.isfinite(s_hi)):
        raise ValueError(f"sigma_bounds_ps must satisfy 0 < low < high < inf, got {sigma_bounds_ps}")
    if not (0 < a_lo < a_hi and np.isfinite(a_hi)):
        raise ValueError(f"alpha_bounds_per_ps must satisfy 0 < low < high < inf, got {alpha_bounds_per_ps}")

    slots = slot_arrays(params, lead)
    y = y.reshape(-1, n_bins)
    n = y.shape[0]
    k = 2 + slots["n_ir"]
    lay = _Layout(k, shared_sigma)
    span = n_bins * float(time_bin_ps)
    lo, hi = lay.bounds((t[0] - span, t[-1] + span), (np.log(s_lo), np.log(s_hi)), (np.log(a_lo), np.log(a_hi)))

    # Per-pixel normalisation: parameters are scale-free, amplitudes scale.
    scale = np.max(np.abs(y), axis=-1)
    scale = np.where(scale > 0, scale, 1.0)
    yw = y if sw is None else y * sw

    res = {name: slots[name].copy() for name in ("delay", "amplitude", "sigma", "alpha")}
    info = {"iterations": np.zeros(n, np.int64), "converged": np.zeros(n, bool),
            "refined": np.zeros(n, bool), "rss_input": np.zeros(n), "rss": np.zeros(n)}
    for start in range(0, n, int(block_size)):
        sl = slice(start, min(n, start + int(block_size)))
        sc = scale[sl]
        sub = {name: slots[name][sl] for name in ("delay", "sigma", "alpha", "present")}
        sub["amplitude"] = slots["amplitude"][sl] / sc[:, None]
        with np.errstate(under="ignore"):
            out, inf = _refine_block(t, yw[sl] / sc[:, None], sub, lay, (lo, hi), tb,
                                     int(max_iter), float(ftol), 1e-3, None if sw is None else sw[sl],
                                     bool(sss_after_direct), bool(keep_order))
        for name in ("delay", "sigma", "alpha"):
            res[name][sl] = out[name]
        res["amplitude"][sl] = np.where(inf["refined"][:, None], out["amplitude"] * sc[:, None],
                                        slots["amplitude"][sl])
        for key in ("iterations", "converged", "refined"):
            info[key][sl] = inf[key]
        info["rss_input"][sl] = inf["rss_input"] * sc * sc
        info["rss"][sl] = inf["rss"] * sc * sc
    res["present"] = slots["present"]
    res["n_ir"] = slots["n_ir"]
    out_params = params_from_slots(res, lead)
    info = {key: v.reshape(lead) for key, v in info.items()}
    return out_params, info
