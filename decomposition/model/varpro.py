"""Variable projection with Levenberg-Marquardt damping, batched over pixels (the engine of refinement).

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
(kernels, derivatives, one Gram product of the stacked rows [Phi; dPhi; y], the
amplitudes and the normal equations) is compiled for point-sampled kernels, one pixel
at a time over the rows' supports (:mod:`decomposition.kernels.projected`, the same
numbers to rounding); bin-integrated kernels (and :data:`COMPILED` off, the reference)
take the NumPy path, in cache-sized chunks of pixels.  Where the evaluation is compiled the
damped loop is too, one pixel at a time (:mod:`decomposition.kernels.projlm`); elsewhere the only
Python loops are over LM iterations, blocks and chunks of pixels, and the quadrature nodes of
bin-integrated sampling.
Damping follows the gain ratio (Nielsen 1999); a pixel stops when an accepted
step lowers its RSS by less than ``ftol`` relative, or when no step helps.

Background: a constant offset per pixel (the ``b`` family) is one more linear parameter
with no nonlinear one.  It is eliminated exactly by projecting every stacked row (basis,
derivatives and data, each weighted) onto the complement of the weighted constant
u = sqrt(w): with P_u = I - u u^T / (u^T u), the projector of [Phi, u] is that of
P_u Phi times P_u, so the amplitudes, the residual and Kaufman's Jacobian of the joint fit
are those of the projected rows, and the offset follows from the residual
(:func:`background_level`).  Pixels without the flag are untouched.

Priors: ``slots`` may carry Gaussian pseudo-observations (weight 0: none for that pixel) of the
direct delay (``delay_prior_mean`` / ``_weight``, ps), of the sss onset after the direct
(``onset_prior_...``, ps), of the sss decay rate's logarithm (``alpha_prior_...``) and of the sss-to-direct amplitude ratio
(``ratio_prior_mean`` / ``_weight``), each (n,).  A prior on v . theta (one parameter, or the
difference of two) has the residual sqrt(w) (v . theta - mean), one more row of the
least-squares problem, so the normal equations gain w v v^T and the gradient w (v . theta -
mean) v (:func:`_with_prior`).  The ratio's residual
sqrt(w) (c_sss - rho c_direct) is linear in the amplitudes: one more sample of the linear
problem whose basis values are sqrt(w) (-rho, 1, 0, ...) and whose data value is 0
(:func:`_amplitude_prior`), so the amplitudes are still solved exactly and Kaufman's Jacobian
holds as it is.  The objective the LM lowers (and the never-worse rule compares) is the RSS plus
every prior's term.

See :mod:`decomposition.model.refine` for the public function and its options.
"""

# One module over 600 lines on purpose: the layout of the parameters, the evaluation of the projected
# model (NumPy, the reference of the compiled one) and the damped loop over it are one algorithm;
# split, each part would read the others' private layout.
from __future__ import annotations

import numpy as np

from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, SSS_SLOT
from ..kernels.response import slot_rows
from ..kernels.derivatives import _Z_NEGLIGIBLE, kernel_derivatives
from ..kernels.projected import GAUSSIAN_PSF, given_rss, instrument, projected_normal_equations
from ..kernels.projlm import projected_lm
from ..kernels.jit import kernel_array

__all__ = ["Layout", "design_rows", "kernel_windows", "refine_block", "background_level", "rss_at", "CHUNK_PIXELS"]


def _support(t, delay, sigma, tb, tail):
    """Where each of A kernels is not negligible on the time axis ``t`` (L,, increasing).

    Outside ``|t - delay| <= Z sigma + tb / 2`` (Z = ``_Z_NEGLIGIBLE`` of
    :mod:`decomposition.kernels.derivatives`, where exp(-z^2/2) reaches the exp floor,
    exp(-700) ~ 1e-304) a Gaussian and all its derivatives are below 1e-300 of their
    peaks, and so is the sss kernel's rising edge before its onset (the kernel itself is
    exactly zero there); ``tail`` keeps every sample after the onset (the decay).
    Returns the first and one-past-last sample (A,) each and ``whole`` (A,) bool: the kernels
    that keep the whole axis, those whose delay or width is not finite and those wholly off
    the axis (every value at the floor: they keep them, as all their amplitude has to go on).
    """
    L = t.size
    half = _Z_NEGLIGIBLE * sigma + (0.5 * tb if tb is not None else 0.0)
    ok = np.isfinite(delay) & np.isfinite(half)
    d, h = np.where(ok, delay, 0.0), np.where(ok, half, 0.0)
    j0 = np.searchsorted(t, d - h, side="left")
    j1 = np.full(delay.size, L) if tail else np.searchsorted(t, d + h, side="right")
    return j0, j1, ~ok | (j1 <= j0)


def kernel_windows(t, delay, sigma, alpha, present, tb, derivatives):
    """The present kernels on their supports (:func:`_support`): the Gaussians, then the sss.

    ``delay``, ``sigma`` (n, K), ``alpha`` (n,) and ``present`` (n, K) bool as in
    :func:`design_rows`.  Yields groups ``(pix, slot, idx, vals)``: the A kernels' pixels and
    slots (A,), their sample indices (A, W) and
    :func:`decomposition.kernels.derivatives.kernel_derivatives` there (each (A, W)).  The
    windows of a group have one width W, the widest (shifted to stay on the axis); kernels
    that keep the whole axis (and every kernel where the axis is not increasing) come in a
    group of their own with W = L.
    """
    L = t.size
    increasing = L >= 2 and bool(np.all(t[1:] > t[:-1]))
    gmask = present.copy()
    gmask[:, SSS_SLOT] = False
    gpix, gslot = np.nonzero(gmask)
    spix = np.flatnonzero(present[:, SSS_SLOT])
    for pix, slot, tail in ((gpix, gslot, False), (spix, np.full(spix.size, SSS_SLOT), True)):
        if not pix.size:
            continue
        d, s = delay[pix, slot], sigma[pix, slot]
        a = None if not tail else alpha[pix][:, None]
        if increasing:
            j0, j1, whole = _support(t, d, s, tb, tail)
        else:
            j0, j1, whole = None, None, np.ones(pix.size, bool)
        for part in (~whole, whole):
            if not part.any():
                continue
            w = L if part is whole else int(np.max(j1[part] - j0[part]))
            start = np.zeros(int(part.sum()), np.int64) if w >= L else np.minimum(j0[part], L - w)
            idx = start[:, None] + np.arange(min(w, L))
            vals = kernel_derivatives(t[idx] - d[part][:, None], s[part][:, None],
                                      None if a is None else a[part], time_bin_ps=tb, derivatives=derivatives)
            yield pix[part], slot[part], idx, vals


def design_rows(t, y, delay, sigma, alpha, present, tb, jac, sw=None):
    """Stacked design rows M (n, Q, L) for one batched Gram product.

    Rows: [0, K) basis phi_k; if ``jac``, [K, 2K) d phi_k / d delay_k,
    [2K, 3K) d phi_k / d log sigma_k, 3K the sss d h / d log alpha; the last
    row is the data y.  Absent slots are zero rows.  With ``sw`` (n, L), the
    square roots of the sample weights, the model rows are weighted (``y``
    must already be).  Each kernel is evaluated on its support only
    (:func:`_support`) and is exactly zero outside it, as in the forward model's
    exp floor (:func:`core.model.sss_kernel`); inside it the values are those of
    :func:`decomposition.kernels.derivatives.kernel_derivatives` on the whole axis.
    """
    n, k = delay.shape
    L = t.size
    q = (3 * k + 2) if jac else (k + 1)
    m = np.zeros((n, q, L))
    m[:, -1] = y
    flat = m.reshape(-1)
    # Weights multiply the kernels' windows only (zero stays zero where they are finite);
    # unit weights change nothing.
    if sw is not None and bool(np.all(sw == 1.0)):
        sw = None
    windowed_sw = sw is not None and bool(np.all(np.isfinite(sw)))

    def put(pix, row, idx, v):
        if windowed_sw:
            v = v * sw[pix[:, None], idx]
        flat[((pix * q + row) * L)[:, None] + idx] = v

    for pix, slot, idx, vals in kernel_windows(t, delay, sigma, alpha, present, tb, jac):
        put(pix, slot, idx, vals[0])
        if jac:
            s = sigma[pix, slot][:, None]
            put(pix, k + slot, idx, vals[1])
            put(pix, 2 * k + slot, idx, vals[2] * s)
            if len(vals) == 4:
                put(pix, np.full_like(slot, 3 * k), idx, vals[3] * alpha[pix][:, None])
    if sw is not None and not windowed_sw:
        m[:, :-1] *= sw[:, None, :]
    return m


def _project_constant(m, bg, sw):
    """Project the rows of the pixels ``bg`` (n,) bool of ``m`` (n, Q, L) onto the complement
    of the weighted constant sqrt(w) (``sw`` (n, L); all ones without weights), in place."""
    if bg is None or not bg.any():
        return m
    u = np.ones((int(bg.sum()), m.shape[-1])) if sw is None else sw[bg]
    uu = np.einsum("nl,nl->n", u, u)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = u / np.sqrt(np.where(uu > 0, uu, 1.0))[:, None]
    sub = m[bg]
    sub -= np.einsum("nql,nl->nq", sub, u)[..., None] * u[:, None, :]
    m[bg] = sub
    return m


def background_level(t, y, delay, sigma, alpha, present, c, tb, sw=None, table=None):
    """Least-squares offset (n,) given the amplitudes ``c`` (n, K) at the nonlinear parameters:
    b = u . (y - Phi c) / (u . u) with u = sqrt(w) (``y`` weighted like the rows, as in
    :func:`design_rows`; ``table``: a response's atoms, as :func:`refine_block`); 0 for a pixel
    without weighted samples."""
    k = present.shape[1]
    if table is None:
        m = design_rows(t, y, delay, sigma, alpha, present, tb, False, sw)
        r = m[:, -1] - np.einsum("nk,nkl->nl", c, m[:, :k])
    else:
        fam = np.where(present, FAM_GAUSS, FAM_NONE).astype(np.int8)
        fam[:, SSS_SLOT] = np.where(present[:, SSS_SLOT], FAM_SSS, FAM_NONE)
        phi = slot_rows(table, t, fam, np.where(present, delay, 0.0),
                        np.where(fam == FAM_SSS, alpha[:, None], 0.0))
        if sw is not None:
            phi = phi * sw[:, None, :]
        r = y - np.einsum("nk,nkl->nl", c, phi)
    u = np.ones_like(r) if sw is None else sw
    uu = np.einsum("nl,nl->n", u, u)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(uu > 0, np.einsum("nl,nl->n", u, r) / np.where(uu > 0, uu, 1.0), 0.0)


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


class Layout:
    """Nonlinear parameters theta (n, P) and how they map onto the derivative rows.

    Derivative rows (Q = 2K + 1): d/d delay_k, d/d log sigma_k (k < K), d/d log alpha.
    Independent widths: theta = [delay_0..K-1, log sigma_0..K-1, log alpha], P = Q.
    Shared width (``shared_sigma``, one PSF per pixel as in eq. (2) of the paper):
    theta = [delay_0..K-1, log sigma, log alpha], P = K + 2, and the sigma
    parameter moves every present component's width together.
    No widths (``widths`` False, a measured response's atoms, which have none):
    theta = [delay_0..K-1, log alpha], P = K + 1; the width rows stay in the derivative rows,
    no parameter maps onto them (``sigma`` is ignored by :meth:`pack` and :meth:`held`,
    :meth:`unpack` gives ones).
    """

    def __init__(self, k, shared_sigma=False, widths=True):
        self.k = k
        self.q = 2 * k + 1
        self.shared = bool(shared_sigma)
        self.widths = bool(widths)
        if self.shared and not self.widths:
            raise ValueError("a shared width (shared_sigma) needs the width parameters (widths=True)")
        self.dslot = np.concatenate([np.arange(k), np.arange(k), [SSS_SLOT]])
        if not self.widths:
            self.p = k + 1
            assign = np.zeros((self.p, self.q))
            assign[np.arange(k), np.arange(k)] = 1.0
            assign[k, 2 * k] = 1.0
        elif self.shared:
            self.p = k + 2
            assign = np.zeros((self.p, self.q))
            assign[np.arange(k), np.arange(k)] = 1.0
            assign[k, k:2 * k] = 1.0
            assign[k + 1, 2 * k] = 1.0
        else:
            self.p = self.q
            assign = np.eye(self.q)
        self.assign = assign
        self._sub = {}             # truncated(): layouts of the first k_eff slots, built on demand

    def free_rows(self, present):
        return np.concatenate([present, present, present[:, SSS_SLOT:SSS_SLOT + 1]], axis=1)

    def free(self, present):
        return (self.free_rows(present).astype(np.float64) @ self.assign.T) > 0

    def pack(self, delay, sigma, alpha, present):
        with np.errstate(divide="ignore", invalid="ignore"):
            logs = np.log(sigma)
            loga = np.log(alpha)[:, None]
        if not self.widths:
            return np.concatenate([delay, loga], axis=1)
        if not self.shared:
            return np.concatenate([delay, logs, loga], axis=1)
        # Start the shared width from the direct component's, else the mean over present ones.
        npres = present.sum(axis=1)
        mean = np.where(present, logs, 0.0).sum(axis=1) / np.maximum(npres, 1)
        shared = np.where(present[:, 0], logs[:, 0], mean)[:, None]
        return np.concatenate([delay, shared, loga], axis=1)

    def unpack(self, theta):
        k = self.k
        if not self.widths:
            sigma = np.ones((theta.shape[0], k))
        elif self.shared:
            sigma = np.repeat(np.exp(theta[:, k:k + 1]), k, axis=1)
        else:
            sigma = np.exp(theta[:, k:2 * k])
        return theta[:, :k], sigma, np.exp(theta[:, -1])

    def held(self, delay, sigma, alpha):
        """(n, P) bool: the parameters held, from ``delay`` (n, K) bool (each slot's delay),
        ``sigma`` (n,) bool (every width of the pixel) and ``alpha`` (n,) bool."""
        n_sig = self._n_sigma()
        sig = np.repeat(np.asarray(sigma, bool)[:, None], n_sig, axis=1)
        return np.concatenate([np.asarray(delay, bool), sig, np.asarray(alpha, bool)[:, None]], axis=1)

    def truncated(self, k_eff):
        """Layout of the first ``k_eff`` slots and the indices of its parameters in this one."""
        key = (k_eff, self.shared)
        cache = self._sub
        if key not in cache:
            k = self.k
            if not self.widths:
                cols = np.concatenate([np.arange(k_eff), [k]])
            elif self.shared:
                cols = np.concatenate([np.arange(k_eff), [k, k + 1]])
            else:
                cols = np.concatenate([np.arange(k_eff), k + np.arange(k_eff), [2 * k]])
            cache[key] = (self if k_eff == k else Layout(k_eff, self.shared, self.widths), cols)
        return cache[key]

    def _n_sigma(self):
        return 0 if not self.widths else 1 if self.shared else self.k

    def bounds(self, delay_lim, logsigma_lim, logalpha_lim):
        n_sig = self._n_sigma()
        lo = np.concatenate([np.full(self.k, delay_lim[0]), np.full(n_sig, logsigma_lim[0]), [logalpha_lim[0]]])
        hi = np.concatenate([np.full(self.k, delay_lim[1]), np.full(n_sig, logsigma_lim[1]), [logalpha_lim[1]]])
        return lo, hi


# Pixels per chunk of the L-length work: keeps the temporaries of the kernel
# evaluation within the CPU caches (a whole block at once is several times slower).
CHUNK_PIXELS = 48


#: Point-sampled kernels (no ``tb``) take the compiled evaluation
#: (:func:`decomposition.kernels.projected.projected_normal_equations`, the same numbers to
#: rounding); False: always the NumPy path below (the reference the compiled one is tested against).
COMPILED = True


def _compiled(inst, tb) -> bool:
    """Whether the compiled evaluation (and damped loop) applies: point samples (``tb`` None) of
    the Gaussian PSF with :data:`COMPILED` on, or of a response's table atoms (``inst`` not
    :data:`~decomposition.kernels.projected.GAUSSIAN_PSF`), which have no NumPy path."""
    return (COMPILED or inst is not GAUSSIAN_PSF) and tb is None


def _evaluate(lay, t, y, theta, present, free, tb, jac, sw=None, bg=None, amp=None, inst=GAUSSIAN_PSF, r_out=None,
              r_row=None, rows=None):
    """Amplitudes, RSS and (``jac``) the normal equations of the pixels at ``theta``
    (:func:`_evaluate_chunk`): compiled for point-sampled kernels (:data:`COMPILED`) and for a
    response's table atoms (``inst``, :func:`decomposition.kernels.projected.instrument`), else
    :func:`_evaluate_numpy`.  Compiled path only: ``rows`` (n,) where given, pixel i's data and
    weights are row ``rows[i]`` of ``y`` and ``sw`` (m, L) (not copied out of them); pixel i's
    weighted residual into row ``r_row[i]`` of ``r_out`` (m, L) where given."""
    if not _compiled(inst, tb):
        if r_out is not None:
            raise ValueError("the weighted residual comes from the compiled evaluation only (point samples)")
        if rows is not None:
            y, sw = y[rows], None if sw is None else sw[rows]
        return _evaluate_numpy(lay, t, y, theta, present, free, tb, jac, sw, bg, amp)
    n = theta.shape[0]
    k, p = lay.k, lay.p
    c = np.zeros((n, k))
    rss = np.empty(n)
    a = np.zeros((n, p, p) if jac else (0, p, p))
    g = np.zeros((n, p) if jac else (0, p))
    if n:
        t = np.ascontiguousarray(t, np.float64)
        increasing = t.size >= 2 and bool(np.all(t[1:] > t[:-1]))
        projected_normal_equations(
            t, np.ascontiguousarray(y, np.float64),
            np.arange(n) if rows is None else np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(theta, np.float64),
            np.ascontiguousarray(present, np.bool_), np.ascontiguousarray(free, np.bool_),
            np.zeros((0, t.size)) if sw is None else np.ascontiguousarray(sw, np.float64),
            np.zeros(n, np.bool_) if bg is None else np.ascontiguousarray(bg, np.bool_),
            np.zeros((0, k)) if amp is None else np.ascontiguousarray(amp, np.float64),
            np.ascontiguousarray(lay.assign, np.float64), np.ascontiguousarray(lay.dslot, np.int64),
            lay.shared, increasing, bool(jac), c, rss, a, g,
            np.zeros((0, t.size)) if r_out is None else r_out,
            np.zeros(0, np.int64) if r_out is None else np.ascontiguousarray(r_row, np.int64), inst)
    return (c, rss, a, g) if jac else (c, rss, None, None)


def rss_at(t, y, delay, sigma, alpha, present, amplitude, offset, tb, sw=None, inst=GAUSSIAN_PSF):
    """(n,) weighted RSS of the weighted data ``y`` (n, L) at the given parameters (``delay``,
    ``sigma`` (n, K), ``alpha`` (n,), ``present`` (n, K)) and amplitudes (n, K), less a constant
    ``offset`` (n,), the model and the offset weighted by ``sw`` (n, L; None: unweighted) as
    :func:`design_rows` weighs its rows: compiled for point-sampled kernels (:data:`COMPILED`)
    and for a response's table atoms (``inst``, :func:`decomposition.kernels.projected.instrument`)."""
    n = y.shape[0]
    out = np.empty(n)
    if _compiled(inst, tb):
        if n:
            t = np.ascontiguousarray(t, np.float64)
            given_rss(t, np.ascontiguousarray(y, np.float64), np.ascontiguousarray(delay, np.float64),
                      np.ascontiguousarray(sigma, np.float64), np.ascontiguousarray(alpha, np.float64),
                      np.ascontiguousarray(present, np.bool_), np.ascontiguousarray(amplitude, np.float64),
                      np.ascontiguousarray(offset, np.float64),
                      np.zeros((0, t.size)) if sw is None else np.ascontiguousarray(sw, np.float64),
                      t.size >= 2 and bool(np.all(t[1:] > t[:-1])), out, inst)
        return out
    for i in range(0, n, CHUNK_PIXELS):
        ch = slice(i, i + CHUNK_PIXELS)
        phi0 = design_rows(t, y[ch], delay[ch], sigma[ch], alpha[ch], present[ch], tb, False,
                           None if sw is None else sw[ch])[:, :present.shape[1]]
        r0 = y[ch] - np.einsum("nk,nkl->nl", amplitude[ch], phi0)
        u0 = np.ones_like(r0) if sw is None else sw[ch]
        r0 = r0 - offset[ch][:, None] * u0
        out[ch] = np.einsum("nl,nl->n", r0, r0)
    return out


def _evaluate_numpy(lay, t, y, theta, present, free, tb, jac, sw=None, bg=None, amp=None):
    """:func:`_evaluate_chunk` over cache-sized chunks of pixels (``amp`` (n, K): the
    amplitude prior's rows, :func:`_amplitude_prior`).

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
    for i in range(0, n, CHUNK_PIXELS):
        sel = order[i:i + CHUNK_PIXELS]
        k_eff = int(last[sel].max()) + 1
        sub_lay, cols = lay.truncated(k_eff)
        c, rss, a, g = _evaluate_chunk(sub_lay, t, y[sel], theta[np.ix_(sel, cols)], present[sel, :k_eff],
                                       free[np.ix_(sel, cols)], tb, jac, None if sw is None else sw[sel],
                                       None if bg is None else bg[sel],
                                       None if amp is None else amp[sel, :k_eff])
        c_out[sel, :k_eff] = c
        rss_out[sel] = rss
        if jac:
            a_out[sel[:, None, None], cols[None, :, None], cols[None, None, :]] = a
            g_out[np.ix_(sel, cols)] = g
    return c_out, rss_out, a_out, g_out


def _evaluate_chunk(lay, t, y, theta, present, free, tb, jac, sw=None, bg=None, amp=None):
    """Amplitudes, residual sum of squares and (if jac) the LM normal equations at theta.

    With V = W dPhi (rows; W carries the amplitudes c and the parameter
    mapping of the layout), G = Phi Phi^T and B = Phi V^T, Kaufman's projected
    Jacobian J = Phi^T G^-1 B - V^T gives J^T J = V V^T - B^T G^-1 B and
    J^T r = -V r (because Phi r = 0), so one batched Gram product of the
    stacked rows [Phi; dPhi; y] is all the L-length work.  Pixels ``bg`` (n,) bool also
    fit a constant offset (rows projected, :func:`_project_constant`).  ``amp`` (n, K): the
    amplitude prior's row (:func:`_amplitude_prior`), one more sample of the linear problem
    whose basis values are ``amp``, whose data value is 0 and which no nonlinear parameter
    moves (it is not projected with the offset).
    """
    k, q = lay.k, lay.q
    delay, sigma, alpha = lay.unpack(theta)
    m = _project_constant(design_rows(t, y, delay, sigma, alpha, present, tb, jac, sw), bg, sw)
    if amp is not None:
        extra = np.zeros(m.shape[:2] + (1,))
        extra[:, :k, 0] = amp
        m = np.concatenate([m, extra], axis=-1)
    mm = m @ m.swapaxes(-1, -2)
    gram = _regularise(mm[:, :k, :k], present)
    c = np.linalg.solve(gram, mm[:, :k, -1][..., None])[..., 0]
    c = np.where(present, c, 0.0)
    r = m[:, -1] - np.einsum("nk,nkl->nl", c, m[:, :k])      # the data row (projected where bg)
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


def _onset_after_direct(theta, present, earliest=False):
    """Project sss onsets onto delay >= direct delay where a pixel has both (theta[:, 0] / [:, 1]);
    ``earliest``: onto delay >= the earliest present shifted component's (slot 0 or any other)."""
    if not earliest:
        both = present[:, 0] & present[:, SSS_SLOT]
        theta[:, SSS_SLOT] = np.where(both, np.maximum(theta[:, SSS_SLOT], theta[:, 0]), theta[:, SSS_SLOT])
        return theta
    shifted = present.copy()
    shifted[:, SSS_SLOT] = False
    k = present.shape[1]
    first = np.where(shifted, theta[:, :k], np.inf).min(axis=1)
    ok = present[:, SSS_SLOT] & np.isfinite(first)
    theta[:, SSS_SLOT] = np.where(ok, np.maximum(theta[:, SSS_SLOT], first), theta[:, SSS_SLOT])
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


def _theta_priors(slots, present, lay):
    """The Gaussian pseudo-observations of nonlinear parameters in ``slots``: a list of
    (v (P,), mean (n,), weight (n,)), each a prior on v . theta, weight 0 where the pixel has
    none (a component absent or a value not finite): the direct delay (``delay_prior_mean`` /
    ``_weight``, ps), the sss onset after the direct (``onset_prior_...``, ps) and the sss decay
    rate's logarithm (``alpha_prior_...``, ln(1/ps))."""
    out = []
    for name, terms, slots_needed in (("delay", ((0, 1.0),), (0,)),
                                      ("onset", ((SSS_SLOT, 1.0), (0, -1.0)), (0, SSS_SLOT)),
                                      ("alpha", ((lay.p - 1, 1.0),), (SSS_SLOT,))):
        if f"{name}_prior_weight" not in slots:
            continue
        mean = np.asarray(slots[f"{name}_prior_mean"], np.float64)
        weight = np.asarray(slots[f"{name}_prior_weight"], np.float64)
        ok = np.isfinite(mean) & np.isfinite(weight) & (weight > 0)
        for slot in slots_needed:
            ok &= present[:, slot]
        if ok.any():
            v = np.zeros(lay.p)
            for col, coef in terms:
                v[col] = coef
            out.append((v, np.where(ok, mean, 0.0), np.where(ok, weight, 0.0)))
    return out


def _amplitude_prior(slots, present):
    """(n, K) the row of the sss-to-direct amplitude ratio's pseudo-observation in ``slots``
    (``ratio_prior_mean`` rho, ``ratio_prior_weight`` w): sqrt(w) (c_sss - rho c_direct) is one
    more residual, linear in the amplitudes, so the row is sqrt(w) (-rho, 1, 0, ...); zero
    where a pixel lacks the direct or the sss or a finite positive weight.  None: no prior."""
    if "ratio_prior_weight" not in slots:
        return None
    rho = np.asarray(slots["ratio_prior_mean"], np.float64)
    weight = np.asarray(slots["ratio_prior_weight"], np.float64)
    ok = present[:, 0] & present[:, SSS_SLOT] & np.isfinite(rho) & np.isfinite(weight) & (weight > 0)
    if not ok.any():
        return None
    row = np.zeros(present.shape)
    root = np.sqrt(np.where(ok, weight, 0.0))
    row[:, 0] = -root * np.where(ok, rho, 0.0)
    row[:, SSS_SLOT] = root
    return row


def _with_prior(priors, theta, rss, a=None, g=None, rows=None):
    """Add the pseudo-observations ``priors`` (:func:`_theta_priors`; their pixels ``rows`` of
    them, default all) at ``theta`` to the RSS and, where given, to the normal equations ``a``
    (n, P, P) and the gradient ``g`` (n, P) (in place)."""
    for v, mean, weight in priors:
        if rows is not None:
            mean, weight = mean[rows], weight[rows]
        dd = theta @ v - mean
        if a is not None:
            a += weight[:, None, None] * np.outer(v, v)[None]
            g += (weight * dd)[:, None] * v[None]
        rss = rss + weight * dd * dd
    return rss


def _steps_numpy(lay, t, y, theta, present, free, tb, sw, bg, amp, inst, prior, bounds, ftol, lam0, max_iter,
                 positive, sss_after_direct, onset_after_earliest, keep_order, residual):
    """The damped loop of :func:`refine_block` over a block's active pixels at once (NumPy; the
    reference of :func:`_steps_compiled`).  -> theta, amplitudes, objective, amplitude violations,
    iterations, converged, and the residual rows with the current row of each pixel (``residual``)."""
    n = y.shape[0]
    lo, hi = bounds
    # the residuals in two rows per pixel, i and n + i: the current one in row i + n cur[i], a
    # trial's into the other, so that an accepted step flips cur and copies nothing
    resid = np.empty((2 * n, y.shape[1])) if residual else None
    cur = np.zeros(n, np.int64)
    c, rss, a, g = _evaluate(lay, t, y, theta, present, free, tb, True, sw, bg, amp, inst, resid, np.arange(n))
    rss = _with_prior(prior, theta, rss, a, g)
    viol = _amp_violations(c, present) if positive else np.zeros(n, np.int64)
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
            trial = _onset_after_direct(trial, present[idx], onset_after_earliest)
        if keep_order:
            trial = _keep_order(trial, present[idx])
        trial = np.where(fr, trial, theta[idx])     # absent: 0, held: the held value
        c_t, rss_t, a_t, g_t = _evaluate(lay, t, y, trial, present[idx], fr, tb, True, sw,
                                         None if bg is None else bg[idx], None if amp is None else amp[idx], inst,
                                         resid, idx + n * (1 - cur[idx]), idx)
        rss_t = _with_prior(prior, trial, rss_t, a_t, g_t, idx)
        viol_t = _amp_violations(c_t, present[idx]) if positive else np.zeros(idx.size, np.int64)
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
        cur[acc] = 1 - cur[acc]
        lam[acc] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * np.clip(rho[accept], 0.0, 1.0) - 1.0) ** 3)
        lam[acc] = np.maximum(lam[acc], 1e-12)
        nu[acc] = 2.0
        rej = idx[~accept]
        lam[rej] *= nu[rej]
        nu[rej] *= 2.0

        # Converged: an accepted step that no longer lowers the RSS noticeably,
        # a fit that is exact to rounding, or damping so large that no step helps.
        done = np.zeros(idx.size, bool)
        done |= accept & (gain < ftol[idx])
        done |= rss[idx] <= 1e-26 * ynorm2[idx]
        stalled = ~accept & (lam[idx] > 1e12)
        converged[idx[done | stalled]] = True
        active[idx[done | stalled]] = False

    return theta, c, rss, viol, iters, converged, resid, cur


def _steps_compiled(lay, t, y, theta, present, free, tb, sw, bg, amp, inst, prior, bounds, ftol, lam0, max_iter,
                    positive, sss_after_direct, onset_after_earliest, keep_order, residual):
    """:func:`_steps_numpy` compiled, one pixel at a time (:func:`decomposition.kernels.projlm.projected_lm`;
    point-sampled atoms of either instrument), the same numbers to rounding."""
    n, L = y.shape
    k, p = lay.k, lay.p
    theta = np.array(theta, np.float64, order="C")
    c = np.zeros((n, k))
    rss = np.empty(n)
    viol = np.zeros(n, np.int64)
    iters = np.zeros(n, np.int64)
    converged = np.zeros(n, bool)
    cur = np.zeros(n, np.int64)
    resid = np.empty((2 * n, L)) if residual else np.zeros((0, L))
    pv = np.array([v for v, _, _ in prior], np.float64).reshape(len(prior), p)
    pm = np.array([m for _, m, _ in prior], np.float64).reshape(len(prior), n)
    pw = np.array([w for _, _, w in prior], np.float64).reshape(len(prior), n)
    if n:
        t = kernel_array(t, np.float64)
        lo, hi = (kernel_array(np.broadcast_to(b, (p,)), np.float64) for b in bounds)
        projected_lm(
            t, kernel_array(y, np.float64), theta, kernel_array(present, np.bool_), kernel_array(free, np.bool_),
            np.zeros((0, L)) if sw is None else kernel_array(sw, np.float64),
            np.zeros(n, np.bool_) if bg is None else kernel_array(bg, np.bool_),
            np.zeros((0, k)) if amp is None else kernel_array(amp, np.float64),
            kernel_array(lay.assign, np.float64), kernel_array(lay.dslot, np.int64), lay.shared,
            L >= 2 and bool(np.all(t[1:] > t[:-1])), lo, hi, kernel_array(ftol, np.float64), float(lam0),
            int(max_iter),
            bool(positive), bool(sss_after_direct), bool(onset_after_earliest), bool(keep_order), pv, pm, pw,
            c, rss, viol, iters, converged, cur, resid, inst)
    return theta, c, rss, viol, iters, converged, resid if residual else None, cur


def refine_block(t, y, slots, lay, bounds, tb, max_iter, ftol, lam0, sw=None, sss_after_direct=False,
                  keep_order=True, held=None, table=None, positive=True, onset_after_earliest=False, residual=False):
    """LM over theta for one block (normalised, weighted profiles ``y`` (n, L)); see the module
    docstring.  ``slots`` may carry ``fit_background`` (n,) bool, the pixels that also fit a
    constant offset, and ``background`` (n,), their input offsets (normalised units; the
    never-worse reference uses them); the returned ``background`` is the fitted offset there
    (the input where the refined values were not kept) and 0 elsewhere.  With priors (module
    docstring) ``rss`` includes their terms.
    ``held`` (n, P) bool
    (P of ``lay``): parameters kept at their input value, outside the bounds too (no
    derivative column, no step); the amplitudes are still solved.  ``table``: a response's
    table (:class:`decomposition.kernels.response.ResponseTable`) whose atoms replace the
    Gaussian PSF's (point-sampled only: ``tb`` None); the widths are then not parameters: a
    layout without them (``Layout(widths=False)``, as the callers give it), or held whatever
    ``held`` says.  ``ftol`` a scalar or (n,) per pixel.  ``positive``: a step
    may not turn a positive amplitude non-positive and a fit with one is not kept (False: plain
    least squares, the amplitudes of any sign).  ``onset_after_earliest``: ``sss_after_direct``
    keeps the onset at or after the earliest shifted component, whichever slot holds it.
    ``residual`` (point samples only): ``info`` also carries ``residual`` (n, L), the weighted
    residual ``y`` - Phi c of the refined fit (less its offset) where ``refined``, NaN elsewhere."""
    n = y.shape[0]
    if table is not None and tb is not None:
        raise ValueError("a response's table atoms are point samples of the response resolved on the time "
                         "axis; bin integration (bin_integrated=True) applies to the Gaussian PSF only")
    if table is None and not lay.widths:
        raise ValueError("the Gaussian PSF's atoms have widths: a layout without them (widths=False) is for a "
                         "response's table atoms")
    inst = instrument(table, t)
    present = slots["present"]
    prior = _theta_priors(slots, present, lay)
    amp = _amplitude_prior(slots, present)
    bg = slots.get("fit_background")
    if bg is not None:
        bg = np.asarray(bg, bool)
        if not bg.any():
            bg = None
    used = lay.free(present)
    free = used if held is None else used & ~np.asarray(held, bool)
    if table is not None:
        free = free & ~lay.held(np.zeros(present.shape, bool), np.ones(n, bool), np.zeros(n, bool))
    lo, hi = bounds
    theta = lay.pack(slots["delay"], slots["sigma"], slots["alpha"], present)
    theta = np.where(used, theta, 0.0)
    given = theta
    theta = np.where(free, np.clip(theta, lo, hi), theta)
    if sss_after_direct:
        theta = _onset_after_direct(theta, present, onset_after_earliest)
    if keep_order:
        theta = _keep_order(theta, present)
    theta = np.where(free, theta, given)
    ftol = np.broadcast_to(np.asarray(ftol, np.float64), (n,))

    # RSS of the input exactly as given (input amplitudes), the never-worse reference.
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = np.where(present, slots["sigma"], 1.0)
        a0 = np.where(present[:, SSS_SLOT], slots["alpha"], 1.0)
    d0 = np.where(present, slots["delay"], 0.0)
    amp_in = np.where(present, slots["amplitude"], 0.0)
    offset = np.zeros(n) if bg is None else np.where(bg, np.nan_to_num(slots["background"]), 0.0)
    if table is None or amp_in.any():
        rss_input = rss_at(t, y, d0, s0, a0, present, amp_in, offset, tb, sw, inst)
    else:       # no model given (the response path's fits from delays alone): the data's own sum of squares
        r_in = y - offset[:, None] * (1.0 if sw is None else sw)
        rss_input = np.einsum("nl,nl->n", r_in, r_in)
    if amp is not None:
        rss_input += np.einsum("nk,nk->n", amp, amp_in) ** 2
    theta_in = lay.pack(np.where(present, slots["delay"], 0.0), s0, a0, present)
    rss_input = _with_prior(prior, theta_in, rss_input)

    steps = _steps_compiled if _compiled(inst, tb) else _steps_numpy
    theta, c, rss, viol, iters, converged, resid, cur = steps(
        lay, t, y, theta, present, free, tb, sw, bg, amp, inst, prior, (lo, hi), ftol, lam0, max_iter, positive,
        sss_after_direct, onset_after_earliest, keep_order, residual)

    delay, sigma, alpha = lay.unpack(theta)
    kept = (rss < rss_input) & (viol == 0) & np.isfinite(rss)
    out = {
        "delay": np.where(kept[:, None], delay, slots["delay"]),
        "sigma": np.where(kept[:, None], sigma, slots["sigma"]),
        "alpha": np.where(kept & present[:, SSS_SLOT], alpha, slots["alpha"]),
        "amplitude": np.where(kept[:, None], c, slots["amplitude"]),
        "background": np.zeros(n),
    }
    if bg is not None:
        b_fit = background_level(t, y, delay, sigma, alpha, present, c, tb, sw, table)
        b_in = np.nan_to_num(slots["background"])
        out["background"] = np.where(bg, np.where(kept, b_fit, b_in), 0.0)
    info = {
        "iterations": iters,
        "converged": converged,
        "refined": kept,
        "rss_input": rss_input,
        "rss": np.where(kept, rss, rss_input),
    }
    if residual:
        info["residual"] = np.where(kept[:, None], resid[np.arange(n) + n * cur], np.nan)
    return out, info


