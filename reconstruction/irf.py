"""Estimating the instrument response from a capture of a direct reflection (a calibration target).

A mirror or a thin diffuser in the scene returns, at every pixel, one copy of the instrument
response, delayed by the pixel's path length, scaled, on a background, with noise:

    p_i(t) = a_i c(t - tau_i) + b_i + n_i(t)

:func:`fit_response` recovers c, tau_i and a_i:

1. per pixel, the background b_i is the median of the samples well before the peak (more
   than ``background_guard_ps`` before it; default three times the median half-maximum
   width plus two bins), and the noise the scaled median absolute deviation of the same
   samples.  A pixel is left out when it has non-finite samples, is saturated (a sample at
   ``saturation_level``, or a flat top of three or more samples at the maximum), has fewer
   than ``min_background_bins`` samples before its peak (a return cut off at the window's
   start), or its peak is below ``min_snr`` times its noise;
2. a first template: each pixel aligned on its parabolic peak, averaged;
3. alignment: for every pixel, amplitude and delay are fitted to the template by
   Gauss-Newton least squares (the template's continuous, exactly shifted copies from
   :func:`core.irf.render_shifted`; all pixels at once), which is the matched-filter
   estimate of the delay, accurate to a small fraction of a bin;
4. averaging: every pixel is resampled on the template's grid relative to its delay
   (Fourier shift of its zero-padded profile), and the template is the amplitude-weighted
   least-squares average ``c_k = sum_i w_ik a_i y_ik / sum_i w_ik a_i**2`` (``w_ik`` = 0 where
   the pixel's window does not cover the sample), the optimal average under white noise;
   pixels whose residual (in units of their noise) is more than ``outlier_factor`` times the
   median residual, or than its noise when the median is below it (another reflection in the
   pixel, a hot pixel), are dropped;
5. steps 3-4 are repeated ``iterations`` times, moving the template's reference onto its
   peak each time; the result is normalised to unit area with its peak at t = 0.

The estimate is the response of the whole chain up to the cube, including the camera's bin
integration and the reconstruction's resampling onto uniform bins; a cube reconstructed the
same way is decomposed with exactly that response.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

from core.errors import StreaklabError
from core.irf import InstrumentResponse, ResponseError, render_shifted
from core.irf_models import gaussian_fit
from core.provenance import __version__

from .cubestore import Cube

__all__ = ["ResponseEstimateError", "ResponseEstimateOptions", "ResponseFit", "fit_response", "estimate_response"]


class ResponseEstimateError(StreaklabError, ValueError):
    """The data cannot give an instrument response (too few usable pixels, no signal, ...); says why."""


@dataclass(frozen=True)
class ResponseEstimateOptions:
    """Settings of :func:`fit_response` (validated on creation).

    Attributes
    ----------
    pre_peak_ps, post_peak_ps : float or None
        Extent of the estimated response before and after its peak, ps.  Defaults: the
        background guard before; after, the span that at least three quarters of the pixels
        cover.
    background_guard_ps : float or None
        Samples closer than this before a pixel's peak are not background (default: three
        times the median half-maximum width plus two bins).
    min_background_bins : int
        Background samples a pixel needs before its peak.
    min_snr : float
        Smallest peak-to-noise ratio of a usable pixel.
    saturation_level : float or None
        Samples at or above this level mark a pixel saturated (in the data's units).
    min_pixels : int
        Usable pixels needed.
    max_pixels : int
        At most this many pixels are aligned and averaged: those with the highest
        peak-to-noise ratio (bounds time and memory on a large cube; the others add little).
    iterations : int
        Alignment-and-average rounds.
    outlier_factor : float
        Pixels whose residual exceeds this multiple of the median residual are dropped.
    """

    pre_peak_ps: float | None = None
    post_peak_ps: float | None = None
    background_guard_ps: float | None = None
    min_background_bins: int = 8
    min_snr: float = 10.0
    saturation_level: float | None = None
    min_pixels: int = 8
    max_pixels: int = 4096
    iterations: int = 3
    outlier_factor: float = 4.0

    def __post_init__(self):
        for name in ("pre_peak_ps", "post_peak_ps", "background_guard_ps", "saturation_level"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ResponseEstimateError(f"{name} must be positive and finite, got {v!r}")
        for name, lo in (("min_background_bins", 1), ("min_pixels", 1), ("max_pixels", 1), ("iterations", 1)):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ResponseEstimateError(f"{name} must be an integer >= {lo}, got {v!r}")
        for name in ("min_snr", "outlier_factor"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ResponseEstimateError(f"{name} must be positive and finite, got {v!r}")


@dataclass(frozen=True, eq=False)
class ResponseFit:
    """What :func:`fit_response` found.

    Attributes
    ----------
    response : InstrumentResponse
        Unit area, peak at t = 0, step = the data's bin.
    delay_ps : ndarray, shape (...,)
        Time of each pixel's response peak on the data's time axis, ps; NaN where unused.
    amplitude : ndarray, shape (...,)
        Peak height of each pixel's return above its background (data units); NaN where unused.
    background : ndarray, shape (...,)
        Pre-peak median of each pixel (data units); NaN where it could not be measured.
    used : ndarray of bool, shape (...,)
    dropped : dict
        Pixels left out, by reason.
    """

    response: InstrumentResponse
    delay_ps: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    used: np.ndarray
    dropped: dict


def _fourier_resample(y: np.ndarray, start: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Band-limited samples of each profile at ``start_i + k`` bins, k = 0 .. m-1.

    Returns the samples (P, m) and a mask of those inside the measured range [0, L - 1].
    """
    p, n_bins = y.shape
    n = n_bins + m + 16
    n += 1 - n % 2
    spec = sp_fft.rfft(y, n=n, axis=1)
    whole = np.floor(start)
    frac = start - whole
    ramp = np.exp(2j * np.pi * np.arange(spec.shape[1])[None, :] * frac[:, None] / n)
    grid = sp_fft.irfft(spec * ramp, n=n, axis=1)
    idx = whole[:, None].astype(np.int64) + np.arange(m)[None, :]
    pos = idx + frac[:, None]
    inside = (pos >= 0) & (pos <= n_bins - 1)
    vals = np.take_along_axis(grid, np.clip(idx, 0, n - 1), axis=1)
    return np.where(inside, vals, 0.0), inside


def _average(y, delay_bins, amp, pre, m):
    """Amplitude-weighted least-squares average of the aligned profiles on k = -pre .. m - pre - 1."""
    aligned, w = _fourier_resample(y, delay_bins - pre, m)
    num = np.sum(w * amp[:, None] * aligned, axis=0)
    den = np.sum(w * amp[:, None] ** 2, axis=0)
    if np.any(den <= 0):
        raise ResponseEstimateError("no usable pixel covers part of the requested response window; "
                                    "shorten pre_peak_ps / post_peak_ps")
    return num / den, aligned, w


def _template(c, time_bin_ps, pre):
    try:
        return InstrumentResponse(c, time_bin_ps, -pre * time_bin_ps)
    except ResponseError as exc:
        raise ResponseEstimateError(f"the averaged response is unusable: {exc} (noisy data: use more pixels "
                                    f"or more frames, or a shorter post_peak_ps / --post-ps)") from None


def fit_response(data, time_bin_ps: float | None = None, *, t0_ps: float | None = None,
                 options: ResponseEstimateOptions | None = None, source: dict | None = None) -> ResponseFit:
    """Estimate the instrument response from profiles of a direct reflection (see the module docstring).

    Parameters
    ----------
    data : Cube or array_like, shape (..., L)
        A cube store of the calibration target, or its profiles (any leading shape).
    time_bin_ps : float
        Bin width, ps (taken from the cube when ``data`` is one).
    t0_ps : float, optional
        Time of bin 0, ps (default: the cube's, or 0); only the reported delays depend on it.
    options : ResponseEstimateOptions, optional
    source : dict, optional
        Extra provenance (e.g. the store it came from).

    Returns
    -------
    ResponseFit
    """
    opts = options or ResponseEstimateOptions()
    prov_source = dict(source or {})
    if isinstance(data, Cube):
        time_bin_ps = data.time_bin_ps if time_bin_ps is None else time_bin_ps
        t0_ps = data.t0_ps if t0_ps is None else t0_ps
        prov_source.setdefault("store", data.path)
        prov_source.setdefault("shape", list(data.shape))
        data = data.array[...]
    if time_bin_ps is None or not (math.isfinite(float(time_bin_ps)) and float(time_bin_ps) > 0):
        raise ResponseEstimateError(f"time_bin_ps must be positive and finite, got {time_bin_ps!r}")
    dt = float(time_bin_ps)
    t0_ps = 0.0 if t0_ps is None else float(t0_ps)
    x = np.asarray(data, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] < 16:
        raise ResponseEstimateError(f"profiles need at least 16 time bins, got shape {x.shape}")
    lead, n_bins = x.shape[:-1], x.shape[-1]
    x = x.reshape(-1, n_bins)
    n_pix = x.shape[0]
    dropped = {"non_finite": 0, "saturated": 0, "no_baseline": 0, "low_signal": 0, "outlier": 0,
               "beyond_max_pixels": 0}

    finite = np.all(np.isfinite(x), axis=1)
    dropped["non_finite"] = int(np.sum(~finite))
    x = np.where(finite[:, None], x, 0.0)
    j = np.argmax(x, axis=1)
    peak = x[np.arange(n_pix), j]
    flat_top = np.sum(x >= peak[:, None] - 1e-9 * np.abs(peak[:, None]), axis=1) >= 3
    saturated = flat_top
    if opts.saturation_level is not None:
        saturated = saturated | np.any(x >= opts.saturation_level, axis=1)
    saturated &= finite
    dropped["saturated"] = int(np.sum(saturated))
    ok = finite & ~saturated

    # A first, whole-profile look at the signal (median and MAD): pure-noise pixels go first.
    med = np.median(x, axis=1)
    mad = 1.4826 * np.median(np.abs(x - med[:, None]), axis=1)
    faint = ok & ~(peak - med > opts.min_snr * np.maximum(mad, 1e-300))
    dropped["low_signal"] += int(np.sum(faint))
    ok &= ~faint

    # Widths against a rough baseline set the guard before the peak that is not background.
    rough = np.percentile(x, 20, axis=1)
    above = x - rough[:, None] > 0.5 * (peak - rough)[:, None]
    width_bins = np.median(np.sum(above[ok], axis=1)) if ok.any() else 1.0
    guard_ps = opts.background_guard_ps if opts.background_guard_ps is not None else (3 * width_bins + 2) * dt
    guard = int(math.ceil(guard_ps / dt))
    before = np.arange(n_bins)[None, :] < (j - guard)[:, None]
    has_base = np.sum(before, axis=1) >= opts.min_background_bins
    dropped["no_baseline"] = int(np.sum(ok & ~has_base))
    ok &= has_base
    masked = np.where(before, x, np.nan)
    background = np.full(n_pix, np.nan)
    noise = np.full(n_pix, np.nan)
    if ok.any():
        background[ok] = np.nanmedian(masked[ok], axis=1)
        noise[ok] = 1.4826 * np.nanmedian(np.abs(masked[ok] - background[ok, None]), axis=1)
    amp0 = peak - background
    snr_ok = np.zeros(n_pix, bool)
    snr_ok[ok] = amp0[ok] > opts.min_snr * np.maximum(noise[ok], 1e-300)
    snr_ok[ok] &= amp0[ok] > 0
    dropped["low_signal"] += int(np.sum(ok & ~snr_ok))
    ok &= snr_ok

    def refuse(extra=""):
        why = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in dropped.items() if v and k != "beyond_max_pixels")
        raise ResponseEstimateError(
            f"only {int(ok.sum())} of {n_pix} pixels have a usable direct return (need at least {opts.min_pixels})"
            f"{': ' + why if why else ''}{extra}; a calibration capture needs a single bright return per pixel "
            f"(peak >= {opts.min_snr:g} x noise) with baseline before it")

    if ok.sum() < opts.min_pixels:
        refuse()
    idx = np.flatnonzero(ok)
    if idx.size > opts.max_pixels:
        snr = amp0[idx] / np.maximum(noise[idx], 1e-300)
        chosen = np.sort(idx[np.argsort(-snr, kind="stable")[:opts.max_pixels]])
        dropped["beyond_max_pixels"] = int(idx.size - chosen.size)
        ok[np.setdiff1d(idx, chosen)] = False
        idx = chosen
    y = x[idx] - background[idx, None]
    jj = j[idx]
    amp = amp0[idx]

    # Parabolic peak: the first delays (in bins from bin 0).
    lo, hi = np.clip(jj - 1, 0, n_bins - 1), np.clip(jj + 1, 0, n_bins - 1)
    ym, y0, yp = y[np.arange(idx.size), lo], y[np.arange(idx.size), jj], y[np.arange(idx.size), hi]
    curv = ym - 2 * y0 + yp
    delta = np.where(curv < 0, 0.5 * (ym - yp) / np.where(curv < 0, curv, -1.0), 0.0)
    delay = jj + np.clip(delta, -0.5, 0.5)

    pre = int(math.ceil((opts.pre_peak_ps if opts.pre_peak_ps is not None else guard * dt) / dt))
    if opts.post_peak_ps is not None:
        post = int(math.ceil(opts.post_peak_ps / dt))
    else:
        post = int(np.floor(np.quantile(n_bins - 1 - delay, 0.25)))
    if post < 2:
        raise ResponseEstimateError("the returns sit at the end of the window: no samples after the peak")
    m = pre + post + 1
    t_axis = dt * np.arange(n_bins)
    keep = np.ones(idx.size, bool)
    c, _, _ = _average(y, delay, amp, pre, m)
    for _ in range(opts.iterations):
        tpl = _template(c, dt, pre)
        # Gauss-Newton on (amplitude, delay) of each pixel against the template's shifted copies.
        d_ps = delay * dt
        for _ in range(3):
            atom, d_atom = render_shifted(tpl, t_axis, d_ps, derivative=True)
            h11 = np.sum(atom * atom, axis=1)
            h12 = np.sum(atom * d_atom, axis=1)
            h22 = np.sum(d_atom * d_atom, axis=1)
            a_ls = np.sum(atom * y, axis=1) / h11
            g2 = np.sum(d_atom * (y - a_ls[:, None] * atom), axis=1)
            # Delay step at the least-squares amplitude: the Schur complement of the 2 x 2 system.
            step = g2 / (a_ls * (h22 - h12 * h12 / h11))
            d_ps = d_ps + np.clip(step, -dt, dt)
        amp = a_ls
        # Move every delay onto the template's peak, so the next template peaks at its sample `pre`.
        delay = (d_ps + tpl.peak_time_ps) / dt
        res_all, w_all = _fourier_resample(y, delay - pre, m)
        c, _, _ = _average(y[keep], delay[keep], amp[keep], pre, m)
        # Residual of each pixel against the amplitude-scaled template; drop the outliers.
        rms = np.sqrt(np.sum(w_all * (res_all - amp[:, None] * c[None, :]) ** 2, axis=1)
                      / np.maximum(np.sum(w_all, axis=1), 1))
        rel = rms / np.maximum(noise[idx], 1e-6 * np.abs(amp))          # in units of the pixel's noise
        keep = rel <= opts.outlier_factor * max(float(np.median(rel)), 1.0)
        if keep.sum() < opts.min_pixels:
            ok[idx[~keep]] = False
            dropped["outlier"] = int(np.sum(~keep))
            refuse(" after dropping pixels that do not look like the others")
        c, _, _ = _average(y[keep], delay[keep], amp[keep], pre, m)
    dropped["outlier"] = int(np.sum(~keep))
    ok[idx[~keep]] = False

    raw = _template(c, dt, pre)
    used_idx = idx[keep]
    delay_ps = np.full(n_pix, np.nan)
    amplitude = np.full(n_pix, np.nan)
    delay_ps[used_idx] = t0_ps + delay[keep] * dt + raw.peak_time_ps
    # The template has (nearly) unit peak; the fitted amplitudes are peak heights of the returns.
    amplitude[used_idx] = amp[keep]
    d_atom = render_shifted(raw, t_axis, delay[keep] * dt + raw.peak_time_ps, derivative=True)[1]
    fisher = np.sum(d_atom ** 2, axis=1)
    align_sd = noise[used_idx] / (np.abs(amplitude[used_idx]) * np.sqrt(np.maximum(fisher, 1e-300)))
    provenance = {
        "method": "calibration target: least-squares alignment to the template, amplitude-weighted average",
        **prov_source,
        "pixels_total": n_pix,
        "pixels_used": int(used_idx.size),
        "pixels_dropped": dropped,
        "time_bin_ps": dt,
        "pre_peak_ps": pre * dt,
        "post_peak_ps": post * dt,
        "background_guard_ps": guard * dt,
        "delay_spread_ps": float(np.std(delay_ps[used_idx])),
        "delay_range_ps": [float(np.min(delay_ps[used_idx])), float(np.max(delay_ps[used_idx]))],
        "alignment_sd_ps": float(np.median(align_sd)) if np.all(np.isfinite(align_sd)) else None,
        "median_snr": float(np.median(amplitude[used_idx] / np.maximum(noise[used_idx], 1e-300))),
        "software_version": __version__,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    provenance["gaussian_fit"] = gaussian_fit(raw)
    response = InstrumentResponse(raw.samples, dt, raw.t0_ps, provenance).centred()
    return ResponseFit(response, delay_ps.reshape(lead), amplitude.reshape(lead), background.reshape(lead),
                       ok.reshape(lead), dropped)


def estimate_response(data, time_bin_ps: float | None = None, **kwargs) -> InstrumentResponse:
    """The instrument response of :func:`fit_response` (same arguments), without the per-pixel fit."""
    return fit_response(data, time_bin_ps, **kwargs).response
