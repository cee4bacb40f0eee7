"""The ``irf=`` argument of :func:`decomposition.decompose`: accepted forms, checks, resampling.

An instrument response may be given as an :class:`core.irf.InstrumentResponse`, a tuple
``(samples, time_step_ps)`` (samples at ``j * time_step_ps`` relative to the first, any
positive scale; the peak becomes the reference instant), or a path to a stored response
(:func:`core.irfstore.load_response`: a ``.npz``, a response store, or a cube store's ``irf``
group).  The response is moved onto streaklab's convention (peak at t = 0, ``centred()``).

Time step: the solver renders atoms on the profiles' bins.  A response sampled at another
step is **resampled** onto the bin width by evaluating its band-limited interpolant every
``time_bin_ps`` (exact when the response is band-limited at the coarser of the two steps);
it is refused when its FWHM is below two bins (sampled that coarsely the response aliases and
sub-bin delays lose their meaning).  ``provenance["resampled_from_step_ps"]`` records it.

Refused, each with a :class:`core.irf.ResponseError` naming the problem: an unknown type, a
path that holds no response, non-finite or otherwise invalid samples (the checks of
:class:`core.irf.InstrumentResponse`), and a response whose samples span more than the
profiles' window (after cropping the leading and trailing samples below TRIM_REL of the peak).
"""
from __future__ import annotations

import math
import os

import numpy as np

from core.irf import InstrumentResponse, ResponseError
from core.irfstore import load_response

__all__ = ["resolve_response", "stretched_response", "response_record", "spike_neighbour_ratio", "spike_settings",
           "STEP_RTOL",
           "TRIM_REL",
           "SPIKE_PHASES"]

#: sub-bin positions of the peak at which :func:`spike_neighbour_ratio` samples the response
SPIKE_PHASES = 32
#: time steps that differ by less than this (relative) are the same step
STEP_RTOL = 1e-9
#: leading and trailing samples below this fraction of the peak are cropped before use: far
#: below any noise (a model response's tail is sampled down to 1e-15 of its peak); an
#: exponential tail cropped there loses ~1e-7 x its decay time x the peak rate, under 1e-5 of
#: the response's area for tails up to 100 widths
TRIM_REL = 1e-7


def _coerce(irf) -> InstrumentResponse:
    if isinstance(irf, InstrumentResponse):
        return irf
    if isinstance(irf, (str, os.PathLike)):
        return load_response(irf)
    if isinstance(irf, tuple):
        if len(irf) != 2:
            raise ResponseError(f"irf as a tuple must be (samples_array, time_step_ps), got {len(irf)} items")
        samples, step = irf
        step = float(step) if np.isscalar(step) else np.nan
        if not (math.isfinite(step) and step > 0):
            raise ResponseError(f"irf time_step_ps must be a positive finite number, got {irf[1]!r}")
        return InstrumentResponse(np.asarray(samples, dtype=np.float64), step, 0.0,
                                  {"source": "samples passed to decompose"})
    raise ResponseError(f"irf must be an InstrumentResponse, a (samples, time_step_ps) tuple or a path "
                        f"to a stored response; got {type(irf).__name__}")


def stretched_response(irf: InstrumentResponse, factor: float) -> InstrumentResponse:
    """The response ``irf`` (peak at t = 0) stretched in time by ``factor`` s: r(t / s) / s (same
    area, every width times s, the peak still at t = 0), sampled on its own step from its
    band-limited interpolant.  ``provenance["stretch"]`` records s; the model's closed form is
    dropped (the samples are the response).  A shared instrument's time scale
    (:func:`decomposition.image.shared.estimate_shared`) is held this way."""
    s = float(factor)
    if not (math.isfinite(s) and s > 0):
        raise ResponseError(f"response stretch must be a finite number > 0, got {factor!r}")
    T = irf.time_step_ps
    lo = math.floor(irf.t0_ps * s / T)
    hi = math.ceil((irf.t0_ps + (irf.n_samples - 1) * T) * s / T)
    t = T * np.arange(lo, hi + 1)
    prov = dict(irf.provenance, stretch=s)
    return InstrumentResponse(np.maximum(irf.evaluate(t / s), 0.0) / s + 0.0, T, float(t[0]), prov, None).centred()


def resolve_response(irf, time_bin_ps: float, n_bins: int) -> InstrumentResponse:
    """The response ``irf`` ready for profiles of ``n_bins`` bins of ``time_bin_ps`` ps.

    Returns an :class:`InstrumentResponse` with its peak at t = 0 and its time step equal to
    ``time_bin_ps`` (resampled when it was not; see the module docstring).
    """
    r = _coerce(irf).centred()
    T = float(time_bin_ps)
    if abs(r.time_step_ps - T) > STEP_RTOL * T:
        fwhm = r.fwhm_ps()
        if fwhm < 2.0 * T:
            raise ResponseError(
                f"the response's time step {r.time_step_ps:g} ps differs from time_bin_ps {T:g} ps and its "
                f"FWHM {fwhm:.3g} ps is under two bins: resampled onto the bins it would alias")
        lo = math.floor(r.t0_ps / T)
        hi = math.ceil((r.t0_ps + (r.n_samples - 1) * r.time_step_ps) / T)
        t = T * np.arange(lo, hi + 1)
        prov = dict(r.provenance, resampled_from_step_ps=r.time_step_ps)
        r = InstrumentResponse(np.maximum(r.evaluate(t), 0.0) + 0.0, T, float(t[0]), prov, r.model).centred()
    r = _trimmed(r)
    span_ps = r.n_samples * r.time_step_ps
    window_ps = n_bins * T
    if span_ps > window_ps:
        raise ResponseError(
            f"the response spans {span_ps:g} ps ({r.n_samples} samples of {r.time_step_ps:g} ps), longer than "
            f"the profiles' window of {window_ps:g} ps ({n_bins} bins); crop the response or use longer profiles")
    return r


def _trimmed(r: InstrumentResponse) -> InstrumentResponse:
    """``r`` without its leading and trailing samples below TRIM_REL of the peak."""
    keep = np.flatnonzero(np.abs(r.samples) >= TRIM_REL * r.peak_per_ps)
    lo, hi = int(keep[0]), int(keep[-1]) + 1
    if lo == 0 and hi == r.n_samples:
        return r
    prov = dict(r.provenance, cropped_below_peak_fraction=TRIM_REL)
    return InstrumentResponse(r.samples[lo:hi], r.time_step_ps, r.t0_ps + lo * r.time_step_ps, prov, r.model).centred()


def response_record(irf: InstrumentResponse) -> dict:
    """What a result records about the response that made it: ``describe()``, the
    Gaussian-equivalent sigma, a checksum of the samples and the provenance (JSON-able)."""
    from core.irf_components import gaussian_equivalent_sigma_ps
    from core.irfstore import samples_sha256

    rec = dict(irf.describe())
    rec["gaussian_equivalent_sigma_ps"] = gaussian_equivalent_sigma_ps(irf)
    rec["samples_sha256"] = samples_sha256(irf)
    rec["provenance"] = irf.provenance
    return rec


def spike_neighbour_ratio(irf: InstrumentResponse, time_bin_ps: float, min_rel: float) -> float:
    """r_min of the spike test for components shaped like ``irf``: the smallest ratio of the
    larger neighbour to a sample, max(c(u - T), c(u + T)) / c(u), over every sample u of a
    shifted copy of the response (SPIKE_PHASES sub-bin shifts) that reaches ``min_rel`` of its
    peak -- a smaller sample is no spike candidate (:func:`decomposition.stages.prepare.find_spikes`
    leaves spikes under ``min_rel`` of the pixel's peak alone).  The counterpart of the Gaussian
    path's exp(-T^2 / (2 sigma_min^2)); in [0, 1], 0 for a response with no neighbour above zero
    (a single sample: no spike can be told from it).

    Parameters
    ----------
    irf : InstrumentResponse
        Sampled at ``time_bin_ps`` (:func:`resolve_response`).
    time_bin_ps : float
        T, ps.
    min_rel : float
        Fraction of the peak below which a sample is not considered.
    """
    from core.irf import render_shifted

    T = float(time_bin_ps)
    j = np.arange(-1, int(math.ceil(irf.window_ps / T)) + 2)
    t = irf.window_start_ps + T * j
    c = render_shifted(irf, t, -T * np.arange(SPIKE_PHASES) / SPIKE_PHASES)      # (phases, n), unit peak
    mid, nb = c[:, 1:-1], np.maximum(c[:, :-2], c[:, 2:])
    top = c.max(axis=1, keepdims=True)
    cand = mid >= max(float(min_rel), 1e-6) * top
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(cand, np.maximum(nb, 0.0) / mid, np.inf)
    return float(np.clip(ratio.min(), 0.0, 1.0))


def spike_settings(irf: InstrumentResponse | None, time_bin_ps: float, spike_sigma: float, rel_threshold: float,
                   ratio: float | None = None) -> dict:
    """The keywords of :func:`decomposition.stages.prepare.prepare_samples`'s spike test for
    components shaped like ``irf`` (None: the Gaussian PSF's, ``spike_sigma`` as given):
    ``spike_sigma`` (0 where no sample can be told from the response: its ratio is 0) and
    ``spike_neighbour_ratio`` (:func:`spike_neighbour_ratio`, or ``ratio`` where the caller has
    it; None for the Gaussian PSF)."""
    if irf is None:
        return {"spike_sigma": spike_sigma, "spike_neighbour_ratio": None}
    if ratio is None:
        ratio = spike_neighbour_ratio(irf, time_bin_ps, rel_threshold)
    return {"spike_sigma": spike_sigma if ratio > 0 else 0.0, "spike_neighbour_ratio": ratio if ratio > 0 else None}
