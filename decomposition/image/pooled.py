"""What one pixel cannot see but its neighbours together can: pooled echoes and spatial spikes.

Both tests read a pixel's spatial neighbours **aligned** (:func:`aligned_neighbours`): the
neighbour at offset o is shifted in time by the whole number of bins nearest to
``d(c + o) - d(c)``, so that light arriving at a fixed time after the direct (an echo from a
hidden surface, a narrow true component) lines up with the centre's; d is the fitted direct
delay for the pooled echoes, an onset read from the counts for the spike test.

Pooled echoes (:func:`pooled_echoes`)
    The per-pixel residuals of a ``window`` x ``window`` neighbourhood (default 5 x 5) are
    summed, aligned.  A 1 % echo at one standard deviation of one pixel's noise stands at
    about five in the sum of 25.  A matched filter (the PSF-shaped Gaussian, width the fitted
    direct's median: one instrument) scans the pooled residual after the direct, in the pooled
    noise: the sum of the members' variances, for white noise each pixel's own noise estimate
    (``info["noise_sigma"]``, else :func:`decomposition.noise.noise_sigma` of its residual; a
    noise estimate of the pooled residual itself scatters by ~8 % over its few hundred samples,
    which several times inflates how often pure noise crosses the threshold), for counts the
    pooled model (Poisson variance, at least ``POISSON_VARIANCE_FLOOR``).  Its peak,
    at ``z`` sigma or more (:data:`ECHO_Z`, 4: an echo at 5 sigma crosses a 5-sigma threshold
    only half the time), is kept where the pool's penalised objective
    (:func:`decomposition.stages.selection.penalised` of the pool's data term,
    :func:`decomposition.stages.selection.data_term`, with the echo's delay and amplitude as its
    two more free parameters) prefers it: the evidence is the pool's, since one pixel's own
    objective could never keep an echo it cannot see.  Each such pixel then gets an
    inter-reflection at the pooled delay, its amplitude fitted to its own residual by least
    squares with a Gaussian prior centred on the pool's echo-to-direct ratio times its own
    direct (width: that value), so a pixel's noise cannot flip its sign; a non-positive
    amplitude is not kept.  The pixel's other components stay as fitted (the echo lies
    several PSF widths away from them).

Spatial spikes (:func:`spatial_spikes`)
    In count data, a sample is a single-sample spike when, in the variance-stabilised domain
    (:func:`decomposition.noise.anscombe`), it lies more than z sqrt(2) above both of its time
    neighbours AND above the median of its 8 spatial neighbours' samples (each the largest
    within one bin, to allow for the alignment to whole bins), aligned on each
    pixel's onset and scaled by the ratio of brightnesses, both read from the counts so that
    the spike cannot move them (:func:`spike_free_landmarks`), z the per-profile false-alarm quantile of the
    per-pixel count test (:func:`decomposition.stages.prepare.find_count_spikes`).  A narrow
    true component is in the neighbours too, so the second condition keeps it; the per-pixel
    test must instead tell a spike from the narrowest kernel by the ratio of the sample to its
    time neighbours, which the counts resolve only at a high local level (at 2 ps bins and a
    1 ps narrowest kernel, about 400 counts under the spike).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.ndimage import correlate1d

from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import render_components

from ..api import DecompositionResult, decompose
from ..constants import POISSON_VARIANCE_FLOOR
from ..flags import SPIKE, mark
from ..noise import anscombe, noise_sigma
from ..stages.prepare import _count_threshold
from ..kernels.pool import aligned_sums
from ..kernels.response import response_table, shifted_atoms
from ..stages.selection import data_term, log_samples, penalised
from .shared import held_response

__all__ = ["pooled_echoes", "spatial_spikes", "spike_free_landmarks", "refit_spikes", "replace_pixels", "aligned_neighbours", "ECHO_Z", "ECHO_WINDOW", "SPIKE_WINDOW", "ECHO_GUARD_SIGMA"]

#: the grid the pool's PSF width is read on, ps (one matched filter per width on it)
SIGMA_STEP_PS = 0.05
#: pooled matched-filter significance an echo needs (sigma)
ECHO_Z = 4.0
#: the neighbourhood pooled (pixels a side, odd)
ECHO_WINDOW = 5
#: the neighbourhood the spike test asks (pixels a side, odd)
SPIKE_WINDOW = 3
#: an echo is searched this many PSF widths away from the pixel's fitted components and the
#: window's edges (their residuals carry the fit's own small misfits)
ECHO_GUARD_SIGMA = 4.0


def _shift_image(a: np.ndarray, dy: int, dx: int, fill) -> np.ndarray:
    """``out[y, x] = a[y + dy, x + dx]`` over the leading two axes, ``fill`` outside."""
    Y, X = a.shape[:2]
    out = np.full_like(a, fill)
    ys, yd = slice(max(dy, 0), Y + min(dy, 0)), slice(max(-dy, 0), Y + min(-dy, 0))
    xs, xd = slice(max(dx, 0), X + min(dx, 0)), slice(max(-dx, 0), X + min(-dx, 0))
    out[yd, xd] = a[ys, xs]
    return out


def aligned_neighbours(fields, direct_delay_ps: np.ndarray, time_bin_ps: float, window: int, *, centre=True):
    """Yield, for each offset of a ``window`` x ``window`` neighbourhood, the neighbours'
    ``fields`` aligned on the centre's direct delay.

    Parameters
    ----------
    fields : sequence of ndarray (Y, X, L) or (Y, X)
        Per-sample fields are shifted in time by the nearest whole number of bins to
        ``d(c + o) - d(c)`` (zero where the shift leaves the window); per-pixel fields are moved
        only in space.
    direct_delay_ps : ndarray (Y, X)
        NaN where a pixel has no direct: it is no neighbour and no centre.
    centre : bool
        Include the offset (0, 0).

    Yields
    ------
    (dy, dx), valid (Y, X) bool, list of the aligned fields.
    """
    if window < 1 or window % 2 != 1:
        raise ValueError(f"the neighbourhood must be an odd number of pixels a side, got {window}")
    d = np.asarray(direct_delay_ps, np.float64)
    has = np.isfinite(d)
    h = window // 2
    for dy in range(-h, h + 1):
        for dx in range(-h, h + 1):
            if not centre and dy == 0 and dx == 0:
                continue
            dn = _shift_image(d, dy, dx, np.nan)
            valid = has & np.isfinite(dn)
            shift = np.where(valid, np.rint((np.where(valid, dn, 0.0) - np.where(valid, d, 0.0)) / time_bin_ps),
                             0).astype(np.int64)
            out, gather = [], None
            for f in fields:
                moved = _shift_image(np.asarray(f), dy, dx, 0)
                if moved.ndim == 3:
                    if gather is None:        # the same time shift for every per-sample field
                        L = moved.shape[-1]
                        idx = np.arange(L)[None, None, :] + shift[..., None]
                        gather = ((idx >= 0) & (idx < L) & valid[..., None], np.clip(idx, 0, L - 1))
                    inside, at = gather
                    moved = np.where(inside, np.take_along_axis(moved, at, axis=-1), 0)
                else:
                    moved = np.where(valid, moved, 0)
                out.append(moved)
            yield (dy, dx), valid, out


def _pool_median(a: np.ndarray, window: int) -> np.ndarray:
    """(Y, X) the NaN-ignoring median of ``a`` (Y, X) over each pixel's ``window`` x ``window``
    neighbourhood (NaN where it holds no value)."""
    h = window // 2
    stack = [_shift_image(a, dy, dx, np.nan) for dy in range(-h, h + 1) for dx in range(-h, h + 1)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # all-NaN neighbourhoods: NaN
        return np.nanmedian(np.stack(stack), axis=0)


def _gaussian_taps(sigma_ps: float, time_bin_ps: float) -> np.ndarray:
    h = max(1, int(math.ceil(4.0 * sigma_ps / time_bin_ps)))
    k = np.arange(-h, h + 1) * time_bin_ps
    return np.exp(-0.5 * (k / sigma_ps) ** 2)


def _response_taps(irf, time_bin_ps: float) -> np.ndarray:
    """The matched filter of an echo shaped like ``irf``: its unit-peak shifted atom at the bin
    offsets -h .. h (h bins cover the response's window either side of its reference), so that
    the correlation at bin i reads an echo at delay t_i."""
    h = max(1, int(math.ceil(max(abs(irf.window_start_ps), abs(irf.window_start_ps + irf.window_ps)) / time_bin_ps)))
    k = np.arange(-h, h + 1) * float(time_bin_ps)
    return shifted_atoms(response_table(irf), k, np.zeros(1))[0]


def _window_guard(params: dict, t: np.ndarray, sigma_ps: float) -> np.ndarray:
    """(Y, X, L) bool: samples far enough after the direct and from the window's edges for an
    echo to be searched there."""
    g = ECHO_GUARD_SIGMA * sigma_ps
    d = np.asarray(params["direct_delay_ps"], np.float64)[..., None]
    return np.isfinite(d) & (t > d + g) & (t > t[0] + g) & (t < t[-1] - g)


def _near_components(params: dict, t: np.ndarray, sigma_ps: float) -> np.ndarray:
    """(Y, X, L) bool: samples within the guard of one of the pixel's fitted sss onsets or
    inter-reflections (their residuals carry the fit's own small misfits)."""
    g = ECHO_GUARD_SIGMA * sigma_ps
    s = np.asarray(params["sss_delay_ps"], np.float64)[..., None]
    near = np.abs(t - s) < g
    ir = np.asarray(params["ir_delay_ps"], np.float64)
    for r in range(ir.shape[-1]):
        near |= np.abs(t - ir[..., r, None]) < g
    return near


def pooled_echoes(profiles, result: DecompositionResult, time_bin_ps: float, t0_ps: float | None = None, *,
                  window: int = ECHO_WINDOW, z: float = ECHO_Z, counts: bool = False, irf=None):
    """Find the weak echoes a neighbourhood shares and add them to its pixels' fits.

    Parameters
    ----------
    profiles : array_like (Y, X, L)
        The image the ``result`` decomposes.
    result : DecompositionResult
        Its per-pixel (or spatial) decomposition, arrays (Y, X, ...).
    time_bin_ps, t0_ps : float
        Time axis (ps; ``t0_ps`` defaults to one bin).
    window : int
        Neighbourhood side (odd).
    z : float
        Pooled matched-filter significance an echo needs (sigma).
    counts : bool
        The profiles are photon counts: Poisson variance (the pooled model), else white noise
        at the pooled residual's :func:`decomposition.noise.noise_sigma`.
    irf : InstrumentResponse, optional
        The measured response (resolved on ``time_bin_ps``) the components are atoms of: the
        matched filter and the echo are the shifted response, and the guards are its
        Gaussian-equivalent width; default the Gaussian PSF of the pool's fitted widths.

    Returns
    -------
    result : DecompositionResult
        A new result with the pooled echoes as inter-reflections (in order of delay), the
        residual and rendered arrays updated; ``info["pooled_echoes"]`` the pixels given one.
    found : ndarray (Y, X) bool
        The pixels given an echo.
    snr : ndarray (Y, X)
        The pooled matched filter's peak significance of each pixel's neighbourhood (NaN where
        nothing was searched).
    """
    y = np.asarray(profiles, np.float64)
    if y.ndim != 3:
        raise ValueError(f"pooled_echoes: expected an image (y, x, t), got shape {y.shape}")
    Y, X, L = y.shape
    T = float(time_bin_ps)
    t0 = T if t0_ps is None else float(t0_ps)
    t = t0 + T * np.arange(L)
    params = result.params
    resid = np.nan_to_num(np.asarray(result.residual, np.float64))
    model = y - resid
    d = np.asarray(params["direct_delay_ps"], np.float64)
    a_d = np.nan_to_num(np.asarray(params["direct_amplitude"], np.float64))
    sig = np.asarray(params["direct_sigma_ps"], np.float64)
    found = np.zeros((Y, X), bool)
    snr = np.full((Y, X), np.nan)
    if irf is not None:
        # the response's own width, where the pool has a direct
        sig = np.where(np.isfinite(d), gaussian_equivalent_sigma_ps(irf), np.nan)
    if not np.isfinite(sig).any():
        return result, found, snr
    # one instrument: the PSF width is the pool's median fitted width (read in the pool alone,
    # so that a pixel's answer depends on its neighbourhood only), on a 0.05 ps grid
    sigma = _pool_median(sig, window)
    sigma = np.where(np.isfinite(sigma), np.round(sigma / SIGMA_STEP_PS) * SIGMA_STEP_PS, np.nan)

    # the search keeps away from every pool member's fitted components, aligned: the misfit
    # a neighbour leaves about its own echo must not pass for an echo the pool shares
    if counts:
        variance = np.maximum(model, 0.0)
    else:
        s_c = result.info.get("noise_sigma")
        s_c = noise_sigma(resid.reshape(-1, L)).reshape(Y, X) if s_c is None else np.asarray(s_c, np.float64)
        s_c = np.nan_to_num(s_c)
        variance = np.broadcast_to((s_c ** 2)[..., None], resid.shape)
    pooled, pooled_var, near, amp_sum, n_pool = aligned_sums(
        resid, np.ascontiguousarray(variance), _near_components(params, t, sigma[..., None]), a_d, d, T, int(window))
    var = np.maximum(pooled_var, POISSON_VARIANCE_FLOOR if counts else np.finfo(float).tiny)
    num, den = np.zeros((Y, X, L)), np.ones((Y, X, L))
    for width in np.unique(sigma[np.isfinite(sigma)]):
        at = sigma == width
        g = _gaussian_taps(float(width), T) if irf is None else _response_taps(irf, T)
        num[at] = correlate1d(pooled[at] / var[at], g, axis=-1, mode="constant")
        den[at] = correlate1d(1.0 / var[at], g * g, axis=-1, mode="constant")
    with np.errstate(invalid="ignore"):
        usable = _window_guard(params, t, sigma[..., None]) & ~near & (n_pool[..., None] > 0) \
            & np.isfinite(sigma)[..., None]
    score = np.where(usable, num / np.sqrt(den), -np.inf)
    best = np.argmax(score, axis=-1)
    peak = np.take_along_axis(score, best[..., None], axis=-1)[..., 0]
    searched = np.isfinite(peak)
    snr[searched] = peak[searched]
    cand = np.flatnonzero(searched & (peak >= z))
    if cand.size == 0:
        return _with_info(result, 0), found, snr

    # the pool's penalised objective with and without the echo (its delay and amplitude free)
    iy, ix = np.unravel_index(cand, (Y, X))
    b = best[iy, ix]
    # the peak between bins: the parabola through the score at the best bin and its two neighbours
    sc = score[iy, ix]
    lo, hi = sc[np.arange(b.size), np.maximum(b - 1, 0)], sc[np.arange(b.size), np.minimum(b + 1, L - 1)]
    curv = lo - 2.0 * peak[iy, ix] + hi
    with np.errstate(invalid="ignore"):
        frac = np.where(np.isfinite(lo) & np.isfinite(hi) & (curv < 0),
                        0.5 * (lo - hi) / np.where(curv < 0, curv, -1.0), 0.0)
    tau = t[b] + T * np.clip(frac, -0.5, 0.5)
    sigma = sigma[iy, ix]
    if irf is None:
        atom = np.exp(-0.5 * ((t[None, :] - tau[:, None]) / sigma[:, None]) ** 2)          # (n, L)
    else:
        atom = shifted_atoms(response_table(irf), t, tau)
    v = var[iy, ix]
    amp_pool = (num[iy, ix, b] / den[iy, ix, b])
    r_pool = pooled[iy, ix]
    log_n = log_samples(n_pool[iy, ix] * L)
    j0 = penalised(data_term(r_pool, v), 0, log_n)
    j1 = penalised(data_term(r_pool - amp_pool[:, None] * atom, v), 2, log_n)
    keep = (j1 < j0) & (amp_pool > 0)

    # each kept pixel's own amplitude: least squares with the pool's prior
    if counts:
        v_c = np.maximum(model[iy, ix], POISSON_VARIANCE_FLOOR)
    else:
        v_c = np.broadcast_to(np.maximum(s_c[iy, ix], np.finfo(float).tiny)[:, None] ** 2, atom.shape)
    prec = np.einsum("nl,nl->n", atom, atom / v_c)
    a_ml = np.einsum("nl,nl->n", resid[iy, ix], atom / v_c) / prec
    prior = np.where(amp_sum[iy, ix] > 0, amp_pool / np.where(amp_sum[iy, ix] > 0, amp_sum[iy, ix], 1.0), 0.0) \
        * a_d[iy, ix]
    with np.errstate(divide="ignore", invalid="ignore"):
        prior_prec = np.where(prior > 0, 1.0 / prior ** 2, 0.0)
        amp = (a_ml * prec + prior * prior_prec) / (prec + prior_prec)
    keep &= amp > 0
    if not keep.any():
        return _with_info(result, 0), found, snr
    iy, ix, tau, amp, sigma = iy[keep], ix[keep], tau[keep], amp[keep], sigma[keep]
    found[iy, ix] = True
    # (a response's echo reports the response's Gaussian-equivalent width, as the per-pixel path does)
    width = sigma if irf is None else np.full(tau.size, gaussian_equivalent_sigma_ps(irf))
    return _add_echoes(result, iy, ix, tau, amp, width, L, T, t0, irf), found, snr


def _with_info(result: DecompositionResult, n: int) -> DecompositionResult:
    info = dict(result.info)
    info["pooled_echoes"] = int(n)
    return DecompositionResult(direct=result.direct, sss=result.sss, interreflections=result.interreflections,
                               params=result.params, residual=result.residual, flags=result.flags, info=info)


def _add_echoes(result, iy, ix, tau, amp, sigma, L, T, t0, irf=None) -> DecompositionResult:
    """A copy of ``result`` with one more inter-reflection (delay ``tau``, amplitude ``amp``,
    width ``sigma``; a shifted copy of ``irf`` where given) in pixels (iy, ix), the
    inter-reflections re-ordered by delay."""
    params = {k: np.array(v, copy=True) for k, v in result.params.items()}
    irs = np.asarray(result.interreflections, np.float64)                               # (Y, X, R, L)
    Y, X, R = irs.shape[:3]
    new = {k: np.full((Y, X, 1), np.nan) for k in ("ir_delay_ps", "ir_amplitude", "ir_sigma_ps")}
    new["ir_delay_ps"][iy, ix, 0] = tau
    new["ir_amplitude"][iy, ix, 0] = amp
    new["ir_sigma_ps"][iy, ix, 0] = sigma
    # the echoes rendered in their own pixels (the others' are zero)
    n = len(iy)
    echo = np.zeros((Y, X, 1, L))
    echo[iy, ix] = render_components({**{k: np.full(n, np.nan) for k in ("direct_delay_ps", "direct_amplitude",
                                                                          "direct_sigma_ps", "sss_delay_ps",
                                                                          "sss_amplitude", "sss_alpha_per_ps",
                                                                          "sss_sigma_ps")},
                                      **{k: v[iy, ix] for k, v in new.items()}}, L, T, t0, irf=irf)["interreflections"]
    delays = np.concatenate([params["ir_delay_ps"].reshape(Y, X, R), new["ir_delay_ps"]], axis=-1)
    order = np.argsort(np.where(np.isfinite(delays), delays, np.inf), axis=-1, kind="stable")
    for k in new:
        both = np.concatenate([params[k].reshape(Y, X, R), new[k]], axis=-1)
        params[k] = np.take_along_axis(both, order, axis=-1)
    # the rendered inter-reflections re-ordered only in the pixels whose order changed
    irs = np.concatenate([irs, echo], axis=2)
    moved = np.any(order != np.arange(R + 1), axis=-1)
    irs[moved] = np.take_along_axis(irs[moved], order[moved][..., None], axis=1)
    residual = np.asarray(result.residual, np.float64) - echo[:, :, 0]
    info = dict(result.info)
    info["pooled_echoes"] = int(len(iy))
    return DecompositionResult(direct=result.direct, sss=result.sss, interreflections=irs, params=params,
                               residual=residual, flags=result.flags, info=info)


def spike_free_landmarks(counts, time_bin_ps: float) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's onset (ps from the first bin) and brightness, read so that one spike cannot
    move them: every sample clipped to the larger of its two time neighbours, then the first
    sample reaching half the clipped peak and the clipped sum.  (A fitted direct is no such
    landmark: a spike the per-pixel fit took for the direct moves its delay and amplitude.)

    Returns
    -------
    onset_ps : ndarray (Y, X), NaN for a pixel without counts
    level : ndarray (Y, X)
    """
    x = np.asarray(counts, np.float64)
    clip = x.copy()
    if x.shape[-1] >= 3:
        clip[..., 1:-1] = np.minimum(x[..., 1:-1], np.maximum(x[..., :-2], x[..., 2:]))
    top = clip.max(axis=-1)
    first = np.argmax(clip >= 0.5 * top[..., None], axis=-1)
    onset = np.where(top > 0, first * float(time_bin_ps), np.nan)
    return onset, clip.sum(axis=-1)


def spatial_spikes(counts, time_bin_ps: float, *, window: int = SPIKE_WINDOW,
                   min_neighbours: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Single-sample spikes of a count image, told from narrow true components by the neighbours.

    Parameters
    ----------
    counts : array_like (Y, X, L)
        Photon counts.
    time_bin_ps : float
        The neighbours are aligned on each pixel's onset and scaled by the ratio of the
        brightnesses (:func:`spike_free_landmarks`) before their median is taken.
    window : int
        Neighbourhood side (odd, default 3: the 8 nearest pixels).
    min_neighbours : int
        A pixel with fewer valid neighbours is not tested.

    Returns
    -------
    spikes : ndarray (Y, X, L) bool
    predicted : ndarray (Y, X, L)
        The neighbours' median aligned, scaled samples (NaN where not tested): what the
        neighbours say the pixel should hold there.
    """
    x = np.asarray(counts, np.float64)
    if x.ndim != 3:
        raise ValueError(f"spatial_spikes: expected an image (y, x, t), got shape {x.shape}")
    Y, X, L = x.shape
    out = np.zeros(x.shape, bool)
    if L < 3:
        return out, np.full(x.shape, np.nan)
    direct_delay_ps, lev = spike_free_landmarks(x, time_bin_ps)
    lev = np.where(np.isfinite(lev) & (lev > 0), lev, np.nan)
    stack, n_valid = [], np.zeros((Y, X), np.int64)
    for _, valid, (x_o, l_o) in aligned_neighbours((x, np.nan_to_num(lev)), direct_delay_ps, time_bin_ps, window,
                                                   centre=False):
        ok = valid & (l_o > 0) & np.isfinite(lev)
        scale = np.where(ok, lev / np.where(ok, l_o, 1.0), np.nan)
        # the largest of the aligned sample and its two time neighbours: a narrow true component
        # whose delay falls one bin apart in a neighbour (alignment to a whole bin) still counts
        wide = x_o.copy()
        wide[..., 1:-1] = np.maximum(np.maximum(x_o[..., :-2], x_o[..., 1:-1]), x_o[..., 2:])
        stack.append(np.where(ok[..., None], wide * scale[..., None], np.nan))
        n_valid += ok
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            predicted = np.nanmedian(np.stack(stack), axis=0)
    tested = (n_valid >= min_neighbours) & np.isfinite(np.asarray(direct_delay_ps, np.float64))
    predicted[~tested] = np.nan
    thr = _count_threshold(L) * math.sqrt(2.0)
    a = anscombe(x)
    c = a[..., 1:-1]
    above_time = c - np.maximum(a[..., :-2], a[..., 2:]) > thr
    with np.errstate(invalid="ignore"):
        above_space = c - anscombe(np.nan_to_num(predicted[..., 1:-1], nan=np.inf)) > thr
    out[..., 1:-1] = above_time & above_space & tested[..., None]
    return out, predicted


def _pad_ir(a: np.ndarray, R: int, axis: int, fill=np.nan) -> np.ndarray:
    n = a.shape[axis]
    if n >= R:
        return a
    pad = [(0, 0)] * a.ndim
    pad[axis] = (0, R - n)
    return np.pad(a, pad, constant_values=fill)


def replace_pixels(result: DecompositionResult, where: np.ndarray, sub: DecompositionResult) -> DecompositionResult:
    """A copy of ``result`` (arrays (Y, X, ...)) with the pixels ``where`` (Y, X) bool taken from
    ``sub`` (arrays (n, ...), n = where.sum(), in row-major order); the inter-reflection axis
    padded to the larger of the two."""
    R = max(result.interreflections.shape[-2], sub.interreflections.shape[-2])
    params = {}
    for k, v in result.params.items():
        v = np.asarray(v)
        s = np.asarray(sub.params[k])
        if k.startswith("ir_"):
            v, s = _pad_ir(v, R, -1), _pad_ir(s, R, -1)
        v = np.array(v, copy=True)
        v[where] = s
        params[k] = v
    irs = np.array(_pad_ir(np.asarray(result.interreflections), R, -2, 0.0), copy=True)
    irs[where] = _pad_ir(np.asarray(sub.interreflections), R, -2, 0.0)
    arrays = {}
    for name in ("direct", "sss", "residual", "flags"):
        a = np.array(getattr(result, name), copy=True)
        a[where] = getattr(sub, name)
        arrays[name] = a
    return DecompositionResult(interreflections=irs, params=params, info=dict(result.info), **arrays)


def refit_spikes(cube, result: DecompositionResult, time_bin_ps: float, method: str, keywords: dict, *,
                 hold: dict | None = None):
    """The spatial spike test (:func:`spatial_spikes`) on a count image and its decomposition:
    each spike is replaced by what the neighbours predict there (rounded: the sample then carries
    no weight of its own), the pixel is decomposed again and flagged SPIKE.

    Returns
    -------
    result : DecompositionResult
        ``info["spatial_spikes"]``: the pixels refitted.
    spikes : ndarray (Y, X, L) bool
    cleaned : ndarray (Y, X, L)
        The image with each spike replaced (``cube`` itself where there is none).
    """
    x = np.asarray(cube)
    spikes, predicted = spatial_spikes(x, time_bin_ps)
    rows = spikes.any(axis=-1)
    info = dict(result.info)
    info["spatial_spikes"] = int(rows.sum())
    if not rows.any():
        return DecompositionResult(direct=result.direct, sss=result.sss, interreflections=result.interreflections,
                                   params=result.params, residual=result.residual, flags=result.flags,
                                   info=info), spikes, x
    cleaned = np.array(x, copy=True)
    cleaned[spikes] = np.rint(predicted[spikes]).astype(cleaned.dtype) if np.issubdtype(cleaned.dtype, np.integer) \
        else np.rint(predicted[spikes])
    held = {k: np.broadcast_to(np.asarray(v, np.float64), rows.shape)[rows] for k, v in (hold or {}).items()}
    held, keywords = held_response(np.shape(cleaned)[-1], time_bin_ps, held, keywords)
    again = decompose(cleaned[rows], time_bin_ps, method, **keywords, **({"hold": held} if held else {}))
    out = replace_pixels(result, rows, again)
    mark(out.flags, rows, SPIKE)
    out.info.update(info)
    return out, spikes, cleaned
