"""GradBM: the gradient-based decomposition baseline (Wu et al., CVPR 2012 / IJCV 2014).

The ConvSCD paper compares against this method: the time profile is modelled as a Gaussian
direct reflection, Gaussian inter-reflections and a decaying exponential for subsurface
scattering (sss), and the components are found one after another from the shape of the
profile rather than by a joint fit.  The stages, each batched over all pixels (array
operations; the only Python loop is over the few peel-off stages):

1. Direct.  The first strong rising edge of the profile, i.e. the first bin whose forward
   difference reaches ``edge_fraction`` of the largest one, followed by the first zero
   crossing of the difference (the first local maximum after the edge), locates the
   direct peak.  A Gaussian is fitted to that peak by damped Gauss-Newton on its rising
   side and top (from ``fit_rise_sigma`` widths before the peak to ``fit_fall_sigma``
   widths, at least one bin, after it; the falling side is left out because the sss tail
   lies on it), starting from the parabolic peak and the rising half-maximum width, and
   subtracted.
2. Inter-reflections.  In the remainder, later than ``ir_guard_sigma`` PSF widths after the
   previous Gaussian component, the next rising edge whose slope reaches
   ``ir_edge_fraction`` of the direct's largest slope and the zero crossing after it mark
   an inter-reflection; a Gaussian plus a straight-line background (the sss tail it sits
   on) is fitted within ``ir_fit_sigma`` widths of the peak, its sigma within a factor
   ``ir_sigma_ratio`` of the direct's (the same camera PSF blurs every bounce), and the
   Gaussian subtracted.
   Repeated up to ``max_interreflections`` times.
3. sss.  What remains from one PSF width before the direct delay on is taken as the sss:
   a straight line fitted to the logarithm of its tail (from one PSF width after its
   maximum, samples above ``tail_floor`` of that maximum only, weighted by the squared
   signal as usual for a log-linear exponential fit) gives the attenuation alpha; the onset is the best of
   ``n_onsets`` candidates between one PSF width before the direct delay and the
   remainder's maximum, each with its least-squares amplitude, for the model sss kernel
   with the direct's sigma.

Components whose peak is below ``min_fraction`` of the direct peak are dropped (the same
rule of thumb as ConvSCD's 5 % threshold).  There is no joint refit and no sparsity
prior; noise on the rising edge is taken for the direct reflection and noise bumps after
it for inter-reflections, which is how the method degrades with noise.
"""
from __future__ import annotations

import numpy as np

from core.model import IR_KEYS, empty_params, sss_kernel, time_axis_ps
from ..options import component_letters

__all__ = ["GRADBM_DEFAULTS", "gradbm"]

_FWHM_TO_SIGMA = 1.0 / np.sqrt(2.0 * np.log(2.0))  # half width at half maximum -> sigma

GRADBM_DEFAULTS = {
    "edge_fraction": 0.3,
    "ir_edge_fraction": 0.1,
    "ir_guard_sigma": 4.0,
    "fit_rise_sigma": 3.0,
    "fit_fall_sigma": 0.0,
    "ir_fit_sigma": 2.5,
    "ir_sigma_ratio": 1.5,
    "n_onsets": 16,
    "tail_floor": 0.1,
    "min_fraction": 0.05,
    "n_fit_iter": 12,
}


def _first_index(mask):
    """Index of the first True along the last axis, -1 where there is none."""
    idx = np.argmax(mask, axis=-1)
    return np.where(mask.any(axis=-1), idx, -1)


def _take(a, idx):
    return np.take_along_axis(a, np.clip(idx, 0, a.shape[-1] - 1)[:, None], axis=-1)[:, 0]


def _find_peak(y, start, edge_level):
    """First rising edge at or after ``start`` with slope >= edge_level, and the peak after it.

    Parameters
    ----------
    y : (N, L) profiles; start : (N,) first admissible bin; edge_level : (N,) slope threshold
    per bin.

    Returns
    -------
    k : (N,) int peak bin (-1 where none), found : (N,) bool
    """
    n, L = y.shape
    d = np.diff(y, axis=-1)  # d[i] = y[i+1] - y[i], (N, L-1)
    idx = np.arange(L - 1)
    edge = _first_index((d >= edge_level[:, None]) & (idx >= start[:, None]))
    # First non-rising step after the edge: y[k] is then a local maximum.
    fall = _first_index((d <= 0) & (idx > edge[:, None]))
    k = np.where(fall >= 0, fall, L - 1)  # still rising at the window end: last bin
    found = edge >= 0
    return np.where(found, k, -1), found


def _peak_and_width(y, k, t, time_bin_ps):
    """Parabolic peak time and height around bin k, and sigma from the rising half maximum."""
    n, L = y.shape
    kc = np.clip(k, 1, L - 2)
    y0, y1, y2 = _take(y, kc - 1), _take(y, kc), _take(y, kc + 1)
    den = y0 - 2.0 * y1 + y2
    delta = np.divide(0.5 * (y0 - y2), den, out=np.zeros(n), where=den < 0)
    delta = np.clip(delta, -0.5, 0.5)
    edge_bin = (k == 0) | (k == L - 1)
    delta = np.where(edge_bin, 0.0, delta)
    yk = _take(y, k)
    height = np.where(edge_bin, yk, y1 - 0.25 * (y0 - y2) * delta)
    mu = t[np.clip(k, 0, L - 1)] + delta * time_bin_ps
    # Rising half maximum: last bin before the peak below half the peak height.
    idx = np.arange(L)
    below = (idx[None, :] < k[:, None]) & (y < 0.5 * height[:, None])
    j = np.where(below, idx[None, :], -1).max(axis=-1)
    yj, yj1 = _take(y, j), _take(y, j + 1)
    frac = np.divide(0.5 * height - yj, yj1 - yj, out=np.full(n, 0.5), where=(yj1 - yj) > 0)
    t_half = t[np.clip(j, 0, L - 1)] + np.clip(frac, 0.0, 1.0) * time_bin_ps
    hwhm = np.where(j >= 0, mu - t_half, time_bin_ps)
    sigma = np.clip(hwhm * _FWHM_TO_SIGMA, 0.5 * time_bin_ps, L * time_bin_ps / 4.0)
    return mu, height, sigma


def _fit_gaussian(y, t, amp, mu, sigma, *, rise, fall, time_bin_ps, n_iter, background=False, sigma_range=None):
    """Damped Gauss-Newton fit of amp * exp(-(t-mu)^2 / (2 sigma^2)) on a per-pixel window.

    The window runs from ``rise`` sigma before the initial peak to ``fall`` sigma (at least one
    bin) after it, and stays fixed during the fit.  With ``background`` a straight line
    c0 + c1 (t - mu_initial) is fitted along with the Gaussian (a peak sitting on a sloping
    tail).  The amplitude is kept within [0, 2 max|y|] and sigma within ``sigma_range`` ((N,)
    arrays; default [T/4, L T / 8]).
    Returns (amp, mu, sigma), each (N,).
    """
    n = y.shape[0]
    lo = mu - rise * sigma
    hi = mu + np.maximum(fall * sigma, time_bin_ps)
    w = ((t[None, :] >= lo[:, None]) & (t[None, :] <= hi[:, None])).astype(np.float64)
    tc = t[None, :] - mu[:, None]
    n_par = 5 if background else 3
    x = np.zeros((n, n_par))
    x[:, 0], x[:, 1], x[:, 2] = amp, mu, sigma
    lam = np.full(n, 1e-3)
    a_max = 2.0 * np.max(np.abs(y), axis=-1)
    s_min, s_max = 0.25 * time_bin_ps, max(t.size * time_bin_ps / 8.0, time_bin_ps)
    if sigma_range is not None:
        s_min, s_max = np.maximum(sigma_range[0], s_min), np.minimum(sigma_range[1], s_max)
        x[:, 2] = np.clip(x[:, 2], s_min, s_max)
    eye = np.eye(n_par)

    def residual(x):
        e = np.exp(-0.5 * np.square((t[None, :] - x[:, 1:2]) / x[:, 2:3]))
        model = x[:, 0:1] * e
        if background:
            model = model + x[:, 3:4] + x[:, 4:5] * tc
        return w * (y - model), e

    r, e = residual(x)
    cost = np.sum(r * r, axis=-1)
    for _ in range(int(n_iter)):
        a, m, s = x[:, 0:1], x[:, 1:2], x[:, 2:3]
        dt = t[None, :] - m
        cols = [e, a * e * dt / s**2, a * e * dt**2 / s**3]
        if background:
            cols += [np.ones_like(e), tc]
        J = np.stack(cols, axis=-1) * w[..., None]  # (N, L, P)
        JTJ = np.einsum("nli,nlj->nij", J, J)
        JTr = np.einsum("nli,nl->ni", J, r)
        diag = np.einsum("nii->ni", JTJ)
        # Levenberg-Marquardt with the normal equations scaled to unit diagonal, so that the
        # step and the conditioning test do not depend on the units of the parameters or
        # on the scale of the profile.
        dsq = np.sqrt(np.where(diag > 0, diag, 1.0))
        A = JTJ / (dsq[:, :, None] * dsq[:, None, :]) + (lam[:, None] + 1e-12)[..., None] * eye
        b = JTr / dsq
        step = np.zeros_like(x)
        good = np.isfinite(A).all(axis=(1, 2)) & np.isfinite(b).all(axis=1) & (diag > 0).all(axis=1)
        if good.any():
            good[good] &= np.linalg.cond(A[good]) < 1e12
        if good.any():
            step[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0] / dsq[good]
        xn = x + np.nan_to_num(step)
        xn[:, 0] = np.clip(xn[:, 0], 0.0, a_max)
        xn[:, 2] = np.clip(xn[:, 2], s_min, s_max)
        xn[:, 1] = np.clip(xn[:, 1], lo - sigma, hi + sigma)
        rn, en = residual(xn)
        cn = np.sum(rn * rn, axis=-1)
        better = cn < cost
        x = np.where(better[:, None], xn, x)
        r = np.where(better[:, None], rn, r)
        e = np.where(better[:, None], en, e)
        cost = np.where(better, cn, cost)
        lam = np.where(better, lam * 0.3, lam * 10.0)
    return x[:, 0], x[:, 1], x[:, 2]


def _gauss(t, amp, mu, sigma):
    return amp[:, None] * np.exp(-0.5 * np.square((t[None, :] - mu[:, None]) / sigma[:, None]))


def _fit_sss(rem, t, t_direct, sigma, n_onsets, tail_floor=0.0):
    """Exponential-decay fit of the remainder after the direct onset (see the module docstring).

    Returns (delay_ps, amplitude, alpha_per_ps, peak, ok), each (N,).
    """
    n, L = rem.shape
    after = t[None, :] >= (t_direct - sigma)[:, None]
    r = np.where(after, rem, 0.0)
    kp = np.argmax(r, axis=-1)
    peak = _take(r, kp)
    tp = t[kp]
    # Tail: one PSF width past the remainder's peak, positive samples, weight r^2.
    tail = (t[None, :] >= (tp + sigma)[:, None]) & (r > tail_floor * peak[:, None]) & (r > 0)
    wt = np.where(tail, np.square(r), 0.0)
    logr = np.log(np.where(tail, r, 1.0))
    sw = wt.sum(-1)
    safe = np.where(sw > 0, sw, 1.0)
    tm = (wt * t).sum(-1) / safe
    lm = (wt * logr).sum(-1) / safe
    stt = (wt * np.square(t[None, :] - tm[:, None])).sum(-1)
    stl = (wt * (t[None, :] - tm[:, None]) * (logr - lm[:, None])).sum(-1)
    slope = np.divide(stl, stt, out=np.zeros(n), where=stt > 0)
    alpha = -slope
    ok = (tail.sum(-1) >= 3) & (alpha > 0) & np.isfinite(alpha) & (peak > 0)
    alpha = np.where(ok, alpha, 1.0)
    # Onset and amplitude: least squares of the blurred exponential (the direct's sigma, the
    # tail's alpha) over candidate onsets from one PSF width before the direct delay to the
    # remainder's peak; the amplitude of each candidate is linear and solved in closed form.
    frac = np.linspace(0.0, 1.0, int(n_onsets))
    lo_t = t_direct - sigma
    cand = lo_t[:, None] + frac[None, :] * np.maximum(tp - lo_t, 0.0)[:, None]  # (N, C)
    h = sss_kernel(t[None, None, :] - cand[..., None], sigma[:, None, None], alpha[:, None, None])  # (N, C, L)
    use = after[:, None, :]
    hh = np.sum(np.where(use, h * h, 0.0), axis=-1)
    hr = np.sum(np.where(use, h * rem[:, None, :], 0.0), axis=-1)
    amp_c = np.divide(hr, hh, out=np.zeros_like(hh), where=hh > 0)
    rr = np.sum(np.where(after, rem * rem, 0.0), axis=-1)
    cost = rr[:, None] - amp_c * hr  # residual energy of each candidate
    cost = np.where(amp_c > 0, cost, np.inf)
    best = np.argmin(cost, axis=-1)
    onset = np.take_along_axis(cand, best[:, None], axis=-1)[:, 0]
    amp = np.take_along_axis(amp_c, best[:, None], axis=-1)[:, 0]
    h = np.take_along_axis(h, best[:, None, None], axis=1)[:, 0]
    ok &= amp > 0
    model_peak = amp * h.max(axis=-1)
    return onset, amp, alpha, model_peak, ok


def gradbm(profiles, time_bin_ps: float = 2.0, t0_ps: float | None = None, *, components=("d", "r", "s"),
           max_interreflections: int = 3, **options) -> dict[str, np.ndarray]:
    """Decompose time profiles with the gradient-based method (see the module docstring).

    Parameters
    ----------
    profiles : ndarray, (N, L), float64
        Validated, finite profiles (the caller normalises them; any positive scale works).
    time_bin_ps : float
        Bin width T (ps).
    t0_ps : float, optional
        Time of bin 0 (ps); default ``time_bin_ps``.
    components : iterable of {"d", "r", "s"}
        Families to look for: direct, inter-reflections, sss.  Without "d" the first Gaussian
        peak found is reported as the first inter-reflection.
    max_interreflections : int
        Most inter-reflections per pixel (R of the output).
    **options
        Overrides of :data:`GRADBM_DEFAULTS`: ``edge_fraction``, ``ir_edge_fraction``,
        ``ir_guard_sigma``, ``ir_fit_sigma``, ``ir_sigma_ratio``, ``fit_rise_sigma``,
        ``fit_fall_sigma``, ``n_onsets``, ``tail_floor``, ``min_fraction``, ``n_fit_iter``.

    Returns
    -------
    dict of ndarray
        Parameter dict (keys of :mod:`core.model`): shapes (N,) and
        (N, max_interreflections); NaN where a component is absent.  Inter-reflections are in
        order of delay.
    """
    unknown = set(options) - set(GRADBM_DEFAULTS)
    if unknown:
        raise TypeError(f"gradbm got unknown option(s) {sorted(unknown)}; known: {sorted(GRADBM_DEFAULTS)}")
    opt = {**GRADBM_DEFAULTS, **options}
    fams = set(component_letters(components))
    p = np.asarray(profiles, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"gradbm expects profiles of shape (N, L), got {p.shape}")
    n, L = p.shape
    if L < 4:
        raise ValueError(f"profiles need at least 4 time bins, got {L}")
    R = int(max_interreflections) if "r" in fams else 0
    if R < 0:
        raise ValueError(f"max_interreflections must be >= 0, got {max_interreflections}")
    t = time_axis_ps(L, time_bin_ps, t0_ps)
    T = float(time_bin_ps)
    out = empty_params((n,), R)
    if n == 0:
        return out

    # Stage 1: the first Gaussian peak (the direct reflection, or the first inter-reflection
    # when the caller excludes "d").
    slope = np.diff(p, axis=-1)
    max_slope = slope.max(axis=-1)
    alive = max_slope > 0
    level = np.where(alive, opt["edge_fraction"] * max_slope, np.inf)
    k, found = _find_peak(p, np.zeros(n, dtype=np.int64), level)
    found &= alive
    mu0, h0, s0 = _peak_and_width(p, k, t, T)
    a1, m1, s1 = _fit_gaussian(p, t, h0, mu0, s0, rise=opt["fit_rise_sigma"], fall=opt["fit_fall_sigma"],
                               time_bin_ps=T, n_iter=opt["n_fit_iter"])
    found &= (a1 > 0) & np.isfinite(a1) & np.isfinite(m1)
    a1 = np.where(found, a1, 0.0)
    rem = p - np.where(found[:, None], _gauss(t, a1, np.where(found, m1, 0.0), np.where(found, s1, 1.0)), 0.0)
    ref_amp = np.where(found, a1, 0.0)
    min_amp = opt["min_fraction"] * ref_amp

    gauss = []  # (amp, mu, sigma, ok) in order of delay
    gauss.append((a1, m1, s1, found))

    # Stage 2: later peaks of the remainder, peeled off one at a time.
    n_more = R if "d" in fams else max(R - 1, 0)
    prev_mu, prev_s = m1, s1
    ir_level = np.where(found, opt["ir_edge_fraction"] * max_slope, np.inf)
    for _ in range(n_more):
        start_t = prev_mu + opt["ir_guard_sigma"] * prev_s
        start = np.clip(np.ceil((start_t - t[0]) / T), 0, L - 1).astype(np.int64)
        kk, ok = _find_peak(rem, start, ir_level)
        ok &= found
        if not ok.any():
            break
        mu_i, h_i, s_i = _peak_and_width(rem, kk, t, T)
        a_i, m_i, sg_i = _fit_gaussian(rem, t, h_i, mu_i, s_i, rise=opt["ir_fit_sigma"], fall=opt["ir_fit_sigma"],
                                       time_bin_ps=T, n_iter=opt["n_fit_iter"], background=True,
                                       sigma_range=(s1 / opt["ir_sigma_ratio"], s1 * opt["ir_sigma_ratio"]))
        ok &= (a_i > 0) & np.isfinite(a_i) & (m_i > prev_mu)
        rem = rem - np.where(ok[:, None], _gauss(t, np.where(ok, a_i, 0.0), np.where(ok, m_i, 0.0),
                                                  np.where(ok, sg_i, 1.0)), 0.0)
        gauss.append((a_i, m_i, sg_i, ok))
        prev_mu = np.where(ok, m_i, prev_mu)
        prev_s = np.where(ok, sg_i, prev_s)

    # Stage 3: an exponential decay fitted to what remains, as sss.
    if "s" in fams:
        onset, b, alpha, s_peak, s_ok = _fit_sss(rem, t, np.where(found, m1, t[0]), np.where(found, s1, T),
                                                 opt["n_onsets"], opt["tail_floor"])
        s_ok &= found & (s_peak >= min_amp)
        out["sss_delay_ps"] = np.where(s_ok, onset, np.nan)
        out["sss_amplitude"] = np.where(s_ok, b, np.nan)
        out["sss_alpha_per_ps"] = np.where(s_ok, alpha, np.nan)
        out["sss_sigma_ps"] = np.where(s_ok, s1, np.nan)

    # Assemble: drop weak Gaussians, then assign d / r2, r3, ... in order of delay.
    amps = np.stack([g[0] for g in gauss], axis=-1)
    mus = np.stack([g[1] for g in gauss], axis=-1)
    sigs = np.stack([g[2] for g in gauss], axis=-1)
    oks = np.stack([g[3] for g in gauss], axis=-1) & (amps >= min_amp[:, None]) & (amps > 0)
    oks[:, 0] &= found
    if "d" in fams:
        out["direct_delay_ps"] = np.where(oks[:, 0], mus[:, 0], np.nan)
        out["direct_amplitude"] = np.where(oks[:, 0], amps[:, 0], np.nan)
        out["direct_sigma_ps"] = np.where(oks[:, 0], sigs[:, 0], np.nan)
        amps, mus, sigs, oks = amps[:, 1:], mus[:, 1:], sigs[:, 1:], oks[:, 1:]
    if R:
        # Compact the accepted inter-reflections to the left, keeping their delay order.
        order = np.argsort(~oks, axis=-1, kind="stable")
        take = lambda a: np.take_along_axis(a, order, axis=-1)  # noqa: E731
        oks_s = take(oks)
        m = min(R, oks_s.shape[-1])
        for key, a in zip(IR_KEYS, (mus, amps, sigs)):
            out[key][:, :m] = np.where(oks_s[:, :m], take(a)[:, :m], np.nan)
    return out
