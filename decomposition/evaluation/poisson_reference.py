"""The Poisson reference: maximum likelihood of photon counts with the true response and set.

For synthetic photon counts with known ground truth (:func:`decomposition.evaluation.synthetic.make_profiles`
with ``photons_per_pixel=``), the reference fits each pixel's *true* component set (direct,
sss, inter-reflections, and a constant background where one is given) with the *true*
instrument response, started *at the true parameters*, by maximising the Poisson likelihood
of the counts -- what the least-squares oracle (:mod:`decomposition.evaluation.oracle`) is for Gaussian
noise.  It never decides which components are there nor searches for a start, so its errors
are what the counts allow: a method's bias and RMSE are measured beside it.

Model of pixel p (expected counts per bin, bin i at t_i)::

    mu_i = a_d A(t_i - d_d) + a_s S(t_i - d_s; alpha) + sum_r a_r A(t_i - d_r) + b

with A the response's shifted copy and S the response convolved with exp(-alpha t) u(t)
(:func:`core.irf.render_shifted`, :func:`core.irf.render_sss`, peak-normalised), bin-averaged
by default (:func:`decomposition.evaluation.synthetic_effects.bin_averaged_response`).  The fit minimises
the Poisson deviance

    D = 2 sum_i [y_i log(y_i / mu_i) - (y_i - mu_i)]      (y log y = 0 at y = 0)

by Levenberg-Marquardt on the Fisher-scoring system: the step solves
``(J^T W J + lambda diag(J^T W J)) delta = J^T (y - mu) / mu`` with ``W = 1 / mu`` (the expected
information), accepted only where it lowers D; all pixels of a block at once (batched
solves), with the analytic derivatives of the two renderers.  Amplitudes stay >= 0, alpha
> 0 and delays within the window widened by a few response widths (a step leaving them is
refused); the sss onset is held at or after the direct (projected there, as the truth of every
scene is: ``PoissonReferenceOptions.sss_after_direct``; without it, at 100 photons per pixel
the onset went before the direct in a quarter of ``bench realism``'s tailed pixels, where
the lifetime came out +6 % against +0.6 % held); expected counts are floored at 1e-8 of the
pixel's largest count (the ringing of a sampled response far from it).

Started at the truth, the fit stays in the optimum nearest it; at few photons the likelihood
can have another, higher, maximum (a direct at the window's edge slid further in, an sss
onset and the direct trading light).  :func:`best_of` keeps, per pixel, the fit of lowest
deviance among fits of the same counts and component set from several starts: the maximum
likelihood as far as those starts find it.

Standard errors: the square roots of the diagonal of the inverse expected Fisher
information ``J^T diag(1 / mu) J`` over the fitted parameters, at the solution
(:func:`poisson_reference_fit`) or at any parameters (:func:`poisson_reference_bound`, the
Cramer-Rao bound at the truth).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.irf import InstrumentResponse, render_shifted, render_sss
from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, time_axis_ps

from ..noise import poisson_deviance
from .synthetic_effects import bin_averaged_response, response_sigma_ps
from .best_found import lowest_cost

__all__ = ["PoissonReferenceOptions", "PoissonReferenceFit", "poisson_reference_fit", "poisson_reference_bound",
           "best_of", "delay_window_ps", "poisson_deviance"]

# Expected counts are floored at this fraction of a pixel's largest count (at least 1).
_MU_FLOOR = 1e-8
_LAMBDA_MAX = 1e12
# Keys that get a ``_stderr`` companion.
_ERROR_KEYS = ("direct_delay_ps", "direct_amplitude", "sss_delay_ps", "sss_amplitude", "sss_alpha_per_ps",
               "ir_delay_ps", "ir_amplitude")


@dataclass(frozen=True)
class PoissonReferenceOptions:
    """Settings of the Poisson maximum-likelihood reference fit.

    Attributes
    ----------
    max_iter : int
        Levenberg-Marquardt iterations per pixel (>= 1).
    tol : float
        A pixel has converged when an accepted step lowers its deviance by less than
        ``tol`` x max(deviance, 1) (> 0).
    lambda_start : float
        Initial damping (> 0), divided by 3 after an accepted step, times 4 after a refused one.
    block_size : int
        Pixels fitted together (>= 1).
    delay_margin_widths : float
        Delays stay within the window widened on each side by this many widths of the
        response (its FWHM / 2.355; > 0): beyond that a component leaves too little of itself
        in the window to be placed (a direct before the first bin could otherwise slide away
        with its amplitude growing to match the edge it leaves).  A step leaving it is refused.
    sss_after_direct : bool
        The sss onset stays at or after the direct (the paper's model: light enters where the
        direct is reflected; every scene of :mod:`decomposition.evaluation.synthetic` holds it): a step
        that would put it before is projected onto the direct's delay, as the solver's
        refinement does.  False lets the onset go anywhere the deviance takes it.
    """

    max_iter: int = 100
    tol: float = 1e-8
    lambda_start: float = 1e-3
    block_size: int = 512
    delay_margin_widths: float = 4.0
    sss_after_direct: bool = True

    def __post_init__(self):
        if int(self.max_iter) < 1:
            raise ValueError(f"PoissonReferenceOptions.max_iter must be >= 1, got {self.max_iter}")
        if not (np.isfinite(self.tol) and self.tol > 0):
            raise ValueError(f"PoissonReferenceOptions.tol must be positive, got {self.tol}")
        if not (np.isfinite(self.lambda_start) and self.lambda_start > 0):
            raise ValueError(f"PoissonReferenceOptions.lambda_start must be positive, got {self.lambda_start}")
        if int(self.block_size) < 1:
            raise ValueError(f"PoissonReferenceOptions.block_size must be >= 1, got {self.block_size}")
        if not (np.isfinite(self.delay_margin_widths) and self.delay_margin_widths > 0):
            raise ValueError(f"PoissonReferenceOptions.delay_margin_widths must be positive, "
                             f"got {self.delay_margin_widths}")


@dataclass(frozen=True)
class PoissonReferenceFit:
    """The reference's estimate, in the layout of a decomposition result.

    Attributes
    ----------
    params : dict of ndarray
        Fitted parameters (keys of :mod:`core.model`, shapes S and S + (R,); amplitudes in
        expected counts at the peak), and ``<key>_stderr`` for the delays, amplitudes and
        alpha (NaN where absent).  The ``*_sigma_ps`` keys are the truth's, unused.
    background, background_stderr : ndarray, S
        Fitted constant background (counts per bin) and its standard error (zero and NaN
        without a background).
    direct, sss : ndarray, S + (L,)
        Rendered components (expected counts per bin).
    interreflections : ndarray, S + (R, L)
    info : dict of ndarray, S
        ``iterations``, ``converged`` (bool), ``deviance`` (at the solution),
        ``deviance_start`` (at the truth).
    """

    params: dict
    background: np.ndarray
    background_stderr: np.ndarray
    direct: np.ndarray
    sss: np.ndarray
    interreflections: np.ndarray
    info: dict


# --------------------------------------------------------------------------- layout

class _Layout:
    """Columns of the per-pixel parameter vector: d delay, d amp, s delay, s amp, s alpha,
    (r delay, r amp) per inter-reflection, background."""

    def __init__(self, n_ir: int):
        self.n_ir = int(n_ir)
        self.ir_delay = 5 + 2 * np.arange(self.n_ir)
        self.ir_amp = self.ir_delay + 1
        self.bg = 5 + 2 * self.n_ir
        self.size = self.bg + 1
        self.amplitudes = np.concatenate([[1, 3], self.ir_amp, [self.bg]]).astype(np.int64)
        self.delays = np.concatenate([[0, 2], self.ir_delay]).astype(np.int64)


def _pack(params: dict, background, lead: tuple, n: int):
    """Parameter vectors (n, P) and the mask of fitted columns from a parameter dict."""
    def get(key, extra=()):
        v = np.asarray(params[key], np.float64)
        if v.shape != lead + extra:
            raise ValueError(f"truth_params[{key!r}] has shape {v.shape}, expected {lead + extra}")
        return v.reshape((n,) + extra)

    ir_shape = np.shape(params["ir_delay_ps"])
    if len(ir_shape) != len(lead) + 1 or tuple(ir_shape[:-1]) != lead:
        raise ValueError(f"truth_params['ir_delay_ps'] has shape {ir_shape}, expected {lead} + (R,)")
    lay = _Layout(ir_shape[-1])
    theta = np.zeros((n, lay.size))
    free = np.zeros((n, lay.size), bool)
    dd, da = get("direct_delay_ps"), get("direct_amplitude")
    on = np.isfinite(dd) & np.isfinite(da)
    theta[:, 0], theta[:, 1] = np.where(on, dd, 0.0), np.where(on, da, 0.0)
    free[:, 0] = free[:, 1] = on
    sd, sa, al = get("sss_delay_ps"), get("sss_amplitude"), get("sss_alpha_per_ps")
    on = np.isfinite(sd) & np.isfinite(sa) & np.isfinite(al)
    if np.any(on & ~(al > 0)):
        raise ValueError("truth_params: sss_alpha_per_ps must be positive where an sss is present")
    theta[:, 2], theta[:, 3], theta[:, 4] = np.where(on, sd, 0.0), np.where(on, sa, 0.0), np.where(on, al, 1.0)
    free[:, 2] = free[:, 3] = free[:, 4] = on
    rd, ra = get("ir_delay_ps", (lay.n_ir,)), get("ir_amplitude", (lay.n_ir,))
    on = np.isfinite(rd) & np.isfinite(ra)
    theta[:, lay.ir_delay], theta[:, lay.ir_amp] = np.where(on, rd, 0.0), np.where(on, ra, 0.0)
    free[:, lay.ir_delay] = free[:, lay.ir_amp] = on
    if background is not None:
        b = np.broadcast_to(np.asarray(background, np.float64), lead).reshape(n)
        if not np.all(np.isfinite(b)) or np.any(b < 0):
            raise ValueError("background must be finite and >= 0")
        theta[:, lay.bg] = b
        free[:, lay.bg] = True
    amp = theta[:, lay.amplitudes]
    if np.any(free[:, lay.amplitudes] & ~(amp >= 0)):
        raise ValueError("truth_params: amplitudes of present components must be >= 0")
    return theta, free, lay


class _Model:
    """Expected counts and their Jacobian for blocks of parameter vectors."""

    def __init__(self, irf: InstrumentResponse, t: np.ndarray, lay: _Layout, bin_width_ps: float | None):
        self.irf = bin_averaged_response(irf, bin_width_ps) if bin_width_ps else irf
        self.scale = 1.0 / irf.peak_per_ps
        self.t = t
        self.lay = lay

    def __call__(self, theta: np.ndarray, free: np.ndarray, jacobian: bool = True):
        lay, t, s = self.lay, self.t, self.scale
        n, L = theta.shape[0], t.size
        mu = np.broadcast_to(theta[:, lay.bg][:, None], (n, L)).copy()
        jac = np.zeros((n, L, lay.size)) if jacobian else None
        # Direct and inter-reflections: shifted copies, all present ones at once.
        cols = [(0, 1)] + list(zip(lay.ir_delay.tolist(), lay.ir_amp.tolist()))
        rows, which = [], []
        for c_delay, c_amp in cols:
            idx = np.flatnonzero(free[:, c_amp])
            rows.append(idx)
            which.append(np.full(idx.size, c_delay))
        rows, which = np.concatenate(rows), np.concatenate(which)
        if rows.size:
            delay = theta[rows, which]
            amp = theta[rows, which + 1]
            if jacobian:
                atom, d_atom = render_shifted(self.irf, t, delay, normalization="area", derivative=True)
            else:
                atom = render_shifted(self.irf, t, delay, normalization="area")
            atom = atom * s
            np.add.at(mu, rows, amp[:, None] * atom)
            if jacobian:
                jac[rows, :, which + 1] = atom
                jac[rows, :, which] = amp[:, None] * d_atom * s
        idx = np.flatnonzero(free[:, 3])
        if idx.size:
            delay, amp, alpha = theta[idx, 2], theta[idx, 3], theta[idx, 4]
            if jacobian:
                atom, d_delay, d_alpha = render_sss(self.irf, t, delay, alpha, normalization="area", derivatives=True)
                jac[idx, :, 2] = amp[:, None] * d_delay * s
                jac[idx, :, 3] = atom * s
                jac[idx, :, 4] = amp[:, None] * d_alpha * s
            else:
                atom = render_sss(self.irf, t, delay, alpha, normalization="area")
            mu[idx] += amp[:, None] * atom * s
        if jacobian:
            jac[:, :, lay.bg] = 1.0
            jac *= free[:, None, :]
        return mu, jac


def _information(jac: np.ndarray, mu_c: np.ndarray, free: np.ndarray) -> np.ndarray:
    """J^T diag(1 / mu) J (n, P, P), identity on the fixed columns."""
    h = np.einsum("nlp,nl,nlq->npq", jac, 1.0 / mu_c, jac)
    fixed = ~free
    h[fixed, :] = 0.0
    h.transpose(0, 2, 1)[fixed, :] = 0.0
    n_idx, p_idx = np.nonzero(fixed)
    h[n_idx, p_idx, p_idx] = 1.0
    return h


def _stderr(h: np.ndarray, free: np.ndarray) -> np.ndarray:
    """sqrt(diag(inv(h))) over the fitted columns (n, P); NaN where fixed or not invertible."""
    out = np.full(free.shape, np.nan)
    diag = np.diagonal(h, axis1=1, axis2=2)
    # A fitted column without information (an amplitude at zero leaves its delay free) is
    # left out of the inversion, not allowed to make the whole pixel singular.
    blind = free & ~(diag > 0)
    if blind.any():
        h = h.copy()
        h[blind, :] = 0.0
        h.transpose(0, 2, 1)[blind, :] = 0.0
        n_idx, p_idx = np.nonzero(blind)
        h[n_idx, p_idx, p_idx] = 1.0
        free = free & ~blind
    d = np.sqrt(np.diagonal(h, axis1=1, axis2=2))
    hs = h / d[:, :, None] / d[:, None, :]                 # unit-diagonal: well scaled
    cond = np.linalg.cond(hs)
    ok = np.isfinite(cond) & (cond < 1e14)
    if ok.any():
        cov = np.linalg.inv(hs[ok])
        var = np.diagonal(cov, axis1=1, axis2=2) / np.square(d[ok])
        out[ok] = np.sqrt(np.where(var > 0, var, np.nan))
    return np.where(free, out, np.nan)


def _fit_block(y, theta, free, model: _Model, opts: PoissonReferenceOptions, delay_bounds):
    n = y.shape[0]
    lay = model.lay
    floor = _MU_FLOOR * np.maximum(y.max(axis=1), 1.0)[:, None]
    mu, jac = model(theta, free)
    dev = poisson_deviance(y, np.maximum(mu, floor))
    dev_start = dev.copy()
    lam = np.full(n, float(opts.lambda_start))
    active = np.ones(n, bool)
    converged = np.zeros(n, bool)
    iterations = np.zeros(n, np.int64)
    for _ in range(int(opts.max_iter)):
        idx = np.flatnonzero(active)
        if not idx.size:
            break
        iterations[idx] += 1
        mu_c = np.maximum(mu[idx], floor[idx])
        h = _information(jac[idx], mu_c, free[idx])
        g = np.einsum("nlp,nl->np", jac[idx], (y[idx] - mu[idx]) / mu_c) * free[idx]
        diag = np.diagonal(h, axis1=1, axis2=2).copy()
        damp = h + (lam[idx, None] * np.maximum(diag, 1e-12 * diag.max(axis=1, keepdims=True)))[:, :, None] \
            * np.eye(lay.size)[None]
        step = np.linalg.solve(damp, g[:, :, None])[..., 0] * free[idx]
        cand = theta[idx] + step
        if opts.sss_after_direct:
            both = free[idx, 0] & free[idx, 2]
            cand[:, 2] = np.where(both, np.maximum(cand[:, 2], cand[:, 0]), cand[:, 2])
        ok = np.all(np.where(free[idx][:, lay.amplitudes], cand[:, lay.amplitudes] >= 0, True), axis=1)
        ok &= np.where(free[idx, 4], cand[:, 4] > 0, True) & np.all(np.isfinite(cand), axis=1)
        dl = cand[:, lay.delays]
        ok &= np.all(~free[idx][:, lay.delays] | ((dl >= delay_bounds[0]) & (dl <= delay_bounds[1])), axis=1)
        cand = np.where(ok[:, None], cand, theta[idx])
        mu_new, jac_new = model(cand, free[idx])
        dev_new = np.where(ok, poisson_deviance(y[idx], np.maximum(mu_new, floor[idx])), np.inf)
        better = dev_new < dev[idx]
        gain = dev[idx] - dev_new
        acc = idx[better]
        theta[acc], mu[acc], jac[acc], dev[acc] = cand[better], mu_new[better], jac_new[better], dev_new[better]
        lam[acc] = np.maximum(lam[acc] / 3.0, 1e-12)
        rej = idx[~better]
        lam[rej] *= 4.0
        done = better & (gain < opts.tol * np.maximum(dev_new, 1.0))
        stuck = ~better & (lam[idx] > _LAMBDA_MAX)
        converged[idx[done | stuck]] = True
        active[idx[done | stuck]] = False
    mu_c = np.maximum(mu, floor)
    err = _stderr(_information(jac, mu_c, free), free)
    return theta, err, mu, {"iterations": iterations, "converged": converged, "deviance": dev,
                            "deviance_start": dev_start}


def _unpack(theta, err, free, lay, lead, truth_params):
    out = {k: np.array(v, dtype=np.float64, copy=True) for k, v in truth_params.items()
           if k in DIRECT_KEYS + SSS_KEYS + IR_KEYS}

    def put(key, col, present, extra=False):
        shape = lead + ((lay.n_ir,) if extra else ())
        out[key] = np.where(present, theta[:, col], np.nan).reshape(shape)
        out[key + "_stderr"] = np.where(present, err[:, col], np.nan).reshape(shape)

    put("direct_delay_ps", 0, free[:, 0])
    put("direct_amplitude", 1, free[:, 1])
    put("sss_delay_ps", 2, free[:, 2])
    put("sss_amplitude", 3, free[:, 3])
    put("sss_alpha_per_ps", 4, free[:, 4])
    put("ir_delay_ps", lay.ir_delay, free[:, lay.ir_delay], True)
    put("ir_amplitude", lay.ir_amp, free[:, lay.ir_amp], True)
    return out


def _axis(counts_shape, time_bin_ps, t0_ps):
    if len(counts_shape) < 1 or counts_shape[-1] < 2:
        raise ValueError(f"counts must have shape S + (L,) with L >= 2, got {counts_shape}")
    return time_axis_ps(counts_shape[-1], time_bin_ps, t0_ps)


def delay_window_ps(response: InstrumentResponse, t_ps, options: PoissonReferenceOptions | None = None) -> tuple:
    """(lo, hi) ps: the delays the reference fits, the window of axis ``t_ps`` widened on each
    side by ``options.delay_margin_widths`` response widths."""
    options = options or PoissonReferenceOptions()
    margin = float(options.delay_margin_widths) * response_sigma_ps(response)
    return float(t_ps[0]) - margin, float(t_ps[-1]) + margin


def poisson_reference_fit(counts, truth_params: dict, response: InstrumentResponse, *, background=None,
                          time_bin_ps: float = 2.0, t0_ps: float | None = None, bin_integrated: bool = True,
                          options: PoissonReferenceOptions | None = None) -> PoissonReferenceFit:
    """Poisson maximum likelihood of the true component set with the true response, from the truth.

    Parameters
    ----------
    counts : array_like, S + (L,)
        Photon counts (non-negative, finite; whole numbers are not required).
    truth_params : dict of ndarray
        True parameters (keys of :mod:`core.model`, shapes S and S + (R,), NaN = absent,
        amplitudes in expected counts at the peak): the start and the component set fitted.
    response : InstrumentResponse
        The true instrument response.
    background : float or array_like broadcasting to S, optional
        True constant background (counts per bin): the start of a fitted background term.
        None: no background term (fixed at zero).
    time_bin_ps, t0_ps : float
        Time axis in ps (bin ``i`` at ``t0_ps + i * time_bin_ps``; t0 defaults to one bin).
    bin_integrated : bool
        Expected counts are bin averages of the model (as photon counts are; default) or point
        samples at the bin centres.
    options : PoissonReferenceOptions, optional

    Returns
    -------
    PoissonReferenceFit
        Its ``direct`` / ``sss`` / ``interreflections`` can be given to
        :func:`decomposition.model.fidelity.fidelity` like a decomposition result.
    """
    options = options or PoissonReferenceOptions()
    if not isinstance(response, InstrumentResponse):
        raise ValueError(f"response must be a core.irf.InstrumentResponse, got {type(response).__name__}")
    y = np.asarray(counts, np.float64)
    t = _axis(y.shape, time_bin_ps, t0_ps)
    if not np.all(np.isfinite(y)) or np.any(y < 0):
        raise ValueError("counts must be finite and non-negative")
    lead, L = y.shape[:-1], y.shape[-1]
    n = int(np.prod(lead, dtype=np.int64))
    y = y.reshape(n, L)
    theta, free, lay = _pack(truth_params, background, lead, n)
    model = _Model(response, t, lay, float(time_bin_ps) if bin_integrated else None)
    err = np.full(theta.shape, np.nan)
    mu = np.zeros((n, L))
    info = {"iterations": np.zeros(n, np.int64), "converged": np.zeros(n, bool), "deviance": np.zeros(n),
            "deviance_start": np.zeros(n)}
    bounds = delay_window_ps(response, t, options)
    margin = float(t[0]) - bounds[0]
    start = theta[:, lay.delays]
    if np.any(free[:, lay.delays] & ((start < bounds[0]) | (start > bounds[1]))):
        raise ValueError(f"truth_params: a delay lies outside the window widened by {margin:.3g} ps "
                         f"({bounds[0]:.6g} .. {bounds[1]:.6g} ps); raise options.delay_margin_widths")
    bs = int(options.block_size)
    for lo in range(0, n, bs):
        sl = slice(lo, min(n, lo + bs))
        th, er, m, inf = _fit_block(y[sl], theta[sl].copy(), free[sl], model, options, bounds)
        theta[sl], err[sl], mu[sl] = th, er, m
        for k, v in inf.items():
            info[k][sl] = v
    params = _unpack(theta, err, free, lay, lead, truth_params)
    comps = _components(theta, free, model, n, L)
    has_bg = free[:, lay.bg]
    return PoissonReferenceFit(
        params=params,
        background=np.where(has_bg, theta[:, lay.bg], 0.0).reshape(lead),
        background_stderr=np.where(has_bg, err[:, lay.bg], np.nan).reshape(lead),
        direct=comps[0].reshape(lead + (L,)), sss=comps[1].reshape(lead + (L,)),
        interreflections=comps[2].reshape(lead + (lay.n_ir, L)),
        info={k: v.reshape(lead) for k, v in info.items()})


def best_of(fits, *, tie_tolerance: float = 1e-6) -> PoissonReferenceFit:
    """Per pixel, the fit of lowest Poisson deviance among ``fits``.

    Parameters
    ----------
    fits : sequence of PoissonReferenceFit
        Fits of the same counts and component set (same shapes, the same response and
        background term) from different starts; their deviances are the same objective.
    tie_tolerance : float
        A fit replaces an earlier one only where its deviance is lower by more than
        ``tie_tolerance`` x max(deviance, 1): two starts that converge to the same optimum
        stop a convergence tolerance apart (``PoissonReferenceOptions.tol``, 1e-8), and the
        earlier fit is kept there.

    Returns
    -------
    PoissonReferenceFit
        Every field taken per pixel from the winning fit; ``info`` gains ``start`` (S, int):
        the index in ``fits`` of the fit kept.
    """
    return lowest_cost(fits, cost="deviance", tie_tolerance=tie_tolerance)


def _components(theta, free, model: _Model, n, L):
    """Rendered direct (n, L), sss (n, L) and inter-reflections (n, R, L) of fitted vectors."""
    lay = model.lay
    out = []
    only = np.zeros_like(free)
    for cols in ([0, 1], [2, 3, 4]):
        only[:] = False
        only[:, cols] = free[:, cols]
        th = theta.copy()
        th[:, lay.bg] = 0.0
        out.append(model(th, only, jacobian=False)[0])
    ir = np.zeros((n, lay.n_ir, L))
    for r in range(lay.n_ir):
        only[:] = False
        cols = [lay.ir_delay[r], lay.ir_amp[r]]
        only[:, cols] = free[:, cols]
        th = theta.copy()
        th[:, lay.bg] = 0.0
        ir[:, r] = model(th, only, jacobian=False)[0]
    out.append(ir)
    return out


def poisson_reference_bound(truth_params: dict, response: InstrumentResponse, *, n_bins: int, background=None,
                            time_bin_ps: float = 2.0, t0_ps: float | None = None,
                            bin_integrated: bool = True) -> dict:
    """Cramer-Rao bound of the Poisson reference: standard errors from the expected Fisher
    information at ``truth_params`` (what :func:`poisson_reference_fit` reports at its solution).

    Parameters
    ----------
    truth_params, response, background, time_bin_ps, t0_ps, bin_integrated
        As in :func:`poisson_reference_fit`.
    n_bins : int
        Bins of the profiles (L).

    Returns
    -------
    dict with ``<key>_stderr`` for the delays, amplitudes and alpha (shapes S, S + (R,)) and
    ``background_stderr`` (S; NaN without a background).
    """
    t = _axis((int(n_bins),), time_bin_ps, t0_ps)
    lead = tuple(np.shape(truth_params["direct_delay_ps"]))
    n = int(np.prod(lead, dtype=np.int64))
    theta, free, lay = _pack(truth_params, background, lead, n)
    model = _Model(response, t, lay, float(time_bin_ps) if bin_integrated else None)
    mu, jac = model(theta, free)
    floor = _MU_FLOOR * np.maximum(mu.max(axis=1), 1.0)[:, None]
    err = _stderr(_information(jac, np.maximum(mu, floor), free), free)
    p = _unpack(theta, err, free, lay, lead, truth_params)
    out = {k: v for k, v in p.items() if k.endswith("_stderr")}
    out["background_stderr"] = np.where(free[:, lay.bg], err[:, lay.bg], np.nan).reshape(lead)
    return out
