"""The ``quality`` stage of :func:`decomposition.decompose`: the rendered fit and its quality flags.

POOR_FIT: the residual RMS over the fitted samples (censored samples count only where the
model lies above them) exceeds ``poor_fit`` x the noise -- the larger of the solver's
estimate and the noise at the signal, since noise that grows with the signal (photon noise)
is not a misfit; the whole-profile noise alone for pixels whose noise was judged not to follow
the signal (``flat_noise``: there both of the others can be the misfit itself) -- or where the
residual RMS over the direct's own samples (its delay +- POOR_FIT_DIRECT_SIGMA fitted widths,
widened by one bin) exceeds ``poor_fit`` x the same noise (photon counts: in noise sigmas of
the variance-stabilised domain).  The second test sees a direct of the
wrong shape: its misfit lies on a few samples, diluted in the whole window's RMS, and being
on the scale of a bin it also raises the noise estimated at the signal (second differences of
the residual) that the first test forgives.  For photon counts POOR_FIT also marks light
before the direct (:func:`light_before_direct`): more counts before the direct's leading edge
than the model expects there, at PRE_DIRECT_SIGMA on the Poisson law -- nothing arrives
before the direct reflection, so a direct placed after light is not the direct (at 100
photons per pixel, a weak direct put on a noise peak 20-30 ps late under an sss).  EMPTY: a
finite pixel with no component at all.

AMBIGUOUS (also set by the search, :mod:`decomposition.stages.search`): the direct is weak and just
before a much larger onset -- its rendered peak below WEAK_DIRECT_FRACTION of the peak of the
other light (sss and inter-reflections) over the direct's delay + (WEAK_DIRECT_ONSET_SIGMA + 2)
widths + 1 bin, an sss onset or an inter-reflection within WEAK_DIRECT_ONSET_SIGMA widths plus
one bin after it (:func:`weak_direct`).  Such a Gaussian can be the direct or a bump on the
onset of the larger light, with the true direct inside that light: the data often fit both
equally well.
Also an inter-reflection whose peak is more than BRIGHT_ECHO_RATIO times the direct's
(:func:`bright_echo`): every bounce loses light, and on the paper's scenes such an echo is the
direct's or the sss's light split off.  And two Gaussian components (the direct and the
inter-reflections) less than RESOLVED_SIGMA of their width apart (:func:`unresolved_gaussians`):
their sum is one hump whose split between them (and so which of them is the direct or which
bounce) the data hardly fix.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model import components as comp
from ..constants import (BRIGHT_ECHO_RATIO, POOR_FIT_DIRECT_SIGMA, PRE_DIRECT_LEVEL, PRE_DIRECT_SIGMA, RESOLVED_SIGMA,
                         WEAK_DIRECT_FRACTION, WEAK_DIRECT_ONSET_SIGMA)
from ..flags import AMBIGUOUS, EMPTY, FLAG_DTYPE, POOR_FIT, mark
from ..noise import anscombe_residual, signal_noise_sigma
from .prepare import Samples

__all__ = ["Fit", "assess_fit", "direct_samples", "direct_misfit", "weak_direct", "bright_echo",
           "unresolved_gaussians", "light_before_direct", "direct_lead_ps"]


@dataclass(frozen=True)
class Fit:
    """Rendered components (``direct``, ``sss`` (P, L), ``interreflections`` (P, R, L)), the
    ``residual`` (P, L) = values - all components, and ``flags`` (P,) (POOR_FIT, EMPTY,
    AMBIGUOUS)."""

    direct: np.ndarray
    sss: np.ndarray
    interreflections: np.ndarray
    residual: np.ndarray
    flags: np.ndarray


def assess_fit(samples: Samples, params: dict, noise_eff: np.ndarray, poor_fit: float, irf=None,
               flat_noise=None) -> Fit:
    """Render ``params`` (P-shaped; with the instrument response ``irf`` when given, else the
    Gaussian PSF), form the residual, flag poor fits and empty pixels.

    ``flat_noise`` (n_live,) bool over ``samples.live``, optional: the pixels whose noise has
    been judged not to follow the signal (float data that
    :func:`decomposition.stages.candidates.signal_weights` left unweighted).  Their misfit is read
    against the whole-profile noise ``samples.noise_eff`` alone, not against ``noise_eff`` (which
    the detection's second noise pass may have raised) or the noise at the signal: both are read
    off the residual, and where the model is wrong on the scale of a bin they are the misfit
    itself (4 ps bins, white NSR 0.001: a 1.9 ps direct and its echo fitted as one Gaussian 8 ps
    wide, the noise raised to 0.16 of the peak, the residual RMS 400 times the true noise).
    """
    L = samples.n_bins
    axis = samples.axis
    P = samples.values.shape[0]
    live, scale, sat = samples.live, samples.scale, samples.censored
    flags = np.zeros(P, FLAG_DTYPE)
    rend = comp.render_params(params, L, axis.time_bin_ps, axis.t0_ps, irf=irf)
    total = rend["direct"] + rend["sss"] + rend["interreflections"].sum(axis=-2)
    if "background" in rend:
        total = total + rend["background"]
    residual = samples.values - total
    if live.size:
        rr = residual[live]
        w = samples.fit[live].astype(np.float64)
        rw = np.where(sat[live], np.maximum(rr, 0.0), rr * w) / scale[live, None]
        nw = np.maximum((samples.fit[live] | sat[live]).sum(axis=1), 1.0)
        rms = np.sqrt(np.einsum("pl,pl->p", rw, rw) / nw)
        s_sig = signal_noise_sigma(rr / scale[live, None], total[live] / scale[live, None], samples.fit[live])
        flat = np.zeros(live.size, bool) if flat_noise is None else np.asarray(flat_noise, bool)
        s_signal = np.where(flat, samples.noise_eff[live], np.maximum(noise_eff[live], s_sig))
        bad = rms > poor_fit * s_signal
        # where the noise at the signal could not be measured (too few samples in the signal
        # region), the direct's samples are not judged on their own: the whole-profile noise
        # can be far below theirs (photon noise on a dark baseline)
        measured = (s_sig > 0) | flat | (samples.noise_model == "poisson")
        bad |= measured & (direct_misfit(samples, params, residual, total, s_signal) > poor_fit)
        if samples.noise_model == "poisson":
            bad |= light_before_direct(samples, params, total, irf)
        mark(flags, live[bad], POOR_FIT)
    has_any = np.isfinite(params["direct_delay_ps"]) | np.isfinite(params["sss_delay_ps"])
    if params["ir_delay_ps"].shape[-1]:
        has_any |= np.isfinite(params["ir_delay_ps"]).any(axis=1)
    mark(flags, samples.finite & ~has_any, EMPTY)
    t = axis.t0_ps + axis.time_bin_ps * np.arange(L)
    mark(flags, weak_direct(params, rend, t) | bright_echo(params) | unresolved_gaussians(params), AMBIGUOUS)
    return Fit(direct=rend["direct"], sss=rend["sss"], interreflections=rend["interreflections"],
               residual=residual, flags=flags)


def direct_samples(t_ps: np.ndarray, time_bin_ps: float, delay_ps: np.ndarray, sigma_ps: np.ndarray,
                   used: np.ndarray) -> np.ndarray:
    """(n, L) bool: the ``used`` samples (n, L) within POOR_FIT_DIRECT_SIGMA widths ``sigma_ps``
    (n,) plus one bin (``time_bin_ps``) of the direct's ``delay_ps`` (n,; NaN: none, no sample)
    on the axis ``t_ps`` (L,): where a direct of the wrong shape misfits (this module's second
    POOR_FIT test, and the search's near-direct doubt)."""
    w_ps = POOR_FIT_DIRECT_SIGMA * sigma_ps + time_bin_ps
    with np.errstate(invalid="ignore"):
        return (np.abs(t_ps[None, :] - delay_ps[:, None]) <= w_ps[:, None]) & used


def direct_misfit(samples: Samples, params: dict, residual: np.ndarray, total: np.ndarray,
                  noise: np.ndarray) -> np.ndarray:
    """(n,) over ``samples.live``: the residual RMS over the fitted samples within
    POOR_FIT_DIRECT_SIGMA fitted widths (plus one bin) of the direct's delay, in units of the
    noise of those samples (0 for pixels without a direct).

    The noise (normalised units) is ``noise`` (n,) -- the larger of the solver's and the one
    at the signal, as in the whole-window test.  For photon counts: the residual in noise
    sigmas of the variance-stabilised domain (:func:`decomposition.noise.anscombe_residual`).
    """
    live = samples.live
    axis = samples.axis
    t = axis.t0_ps + axis.time_bin_ps * np.arange(samples.n_bins)
    near = direct_samples(t, axis.time_bin_ps, np.asarray(params["direct_delay_ps"], np.float64)[live],
                          np.asarray(params["direct_sigma_ps"], np.float64)[live], samples.fit[live])
    if samples.noise_model == "poisson":
        z = anscombe_residual(samples.values[live], total[live], near, samples.dispersion[live])
        chi2 = np.einsum("pl,pl->p", z, z)
    else:
        r = np.where(near, residual[live], 0.0) / samples.scale[live, None]
        chi2 = np.einsum("pl,pl->p", r, r) / np.maximum(noise, 1e-300) ** 2
    return np.sqrt(chi2 / np.maximum(near.sum(axis=1), 1))


def direct_lead_ps(sigma_ps, irf=None) -> np.ndarray:
    """How long before its delay a direct's response rises from PRE_DIRECT_LEVEL of its peak,
    ps, shape of ``sigma_ps``: sqrt(2 ln(1 / level)) widths ``sigma_ps`` for the Gaussian PSF,
    the response's own leading edge with a measured one (``irf``)."""
    w = np.asarray(sigma_ps, np.float64)
    if irf is None:
        return math.sqrt(2.0 * math.log(1.0 / PRE_DIRECT_LEVEL)) * w
    step = min(irf.time_step_ps, 1.0) / 4.0
    t = -np.arange(0.0, -irf.window_start_ps + step, step)[::-1]
    shape = irf.evaluate(t) / irf.peak_per_ps
    return np.full(w.shape, -float(t[np.argmax(shape >= PRE_DIRECT_LEVEL)]))


def light_before_direct(samples: Samples, params: dict, total: np.ndarray, irf=None) -> np.ndarray:
    """(n,) over ``samples.live``, photon counts: more counts on the fitted samples before the
    direct's leading edge (its delay less :func:`direct_lead_ps`) than the model ``total``
    (P, L, counts) expects there, by at least PRE_DIRECT_SIGMA on the Poisson law (upper tail
    P(N >= n | model) below the one-sided normal tail at that many sigma).  False for pixels
    without a direct or without a sample there."""
    from scipy.stats import norm, poisson

    live = samples.live
    axis = samples.axis
    t = axis.t0_ps + axis.time_bin_ps * np.arange(samples.n_bins)
    d = np.asarray(params["direct_delay_ps"], np.float64)[live]
    edge = d - direct_lead_ps(np.asarray(params["direct_sigma_ps"], np.float64)[live], irf)
    with np.errstate(invalid="ignore"):
        before = samples.fit[live] & (t[None, :] < edge[:, None])
    n = np.where(before, samples.values[live], 0.0).sum(axis=1)
    m = np.where(before, np.maximum(total[live], 0.0), 0.0).sum(axis=1)
    p = poisson.sf(n - 1.0, np.maximum(m, 1e-12))
    return np.isfinite(d) & before.any(axis=1) & (p < norm.sf(PRE_DIRECT_SIGMA))


def bright_echo(params: dict) -> np.ndarray:
    """(P,) bool: an inter-reflection's amplitude (peak height) is more than BRIGHT_ECHO_RATIO
    times the direct's (``direct_amplitude`` (P,), ``ir_amplitude`` (P, R); NaN: absent)."""
    d = np.asarray(params["direct_amplitude"], np.float64)
    ir = np.asarray(params["ir_amplitude"], np.float64)
    if ir.shape[-1] == 0:
        return np.zeros(d.shape, bool)
    top = np.max(np.where(np.isfinite(ir), ir, -np.inf), axis=-1)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d) & (top > BRIGHT_ECHO_RATIO * d)


def unresolved_gaussians(params: dict) -> np.ndarray:
    """(P,) bool: two of a pixel's Gaussian components (the direct and the inter-reflections:
    ``direct_delay_ps`` (P,), ``ir_delay_ps`` (P, R), NaN absent) lie less than RESOLVED_SIGMA
    of the direct's width (``direct_sigma_ps``; one width per pixel) apart.

    Two equal Gaussians less than two widths apart add up to a single hump; the solver's own
    rules keep its Gaussians RESOLVED_SIGMA widths apart where it adds one, but a polish can
    draw two together.
    """
    d = np.asarray(params["direct_delay_ps"], np.float64)
    ir = np.asarray(params["ir_delay_ps"], np.float64)
    if ir.shape[-1] == 0:
        return np.zeros(d.shape, bool)
    delays = np.sort(np.concatenate([d[..., None], ir], axis=-1), axis=-1)       # NaN last
    with np.errstate(invalid="ignore"):
        gaps = np.diff(delays, axis=-1)
        sigma = np.asarray(params["direct_sigma_ps"], np.float64)
        return np.any(gaps < RESOLVED_SIGMA * sigma[..., None], axis=-1)


def weak_direct(params: dict, rendered: dict, t_ps: np.ndarray) -> np.ndarray:
    """(P,) bool: the direct is weak and just before a much larger onset (see the module
    docstring).

    Parameters
    ----------
    params : dict of ndarray
        ``direct_delay_ps``, ``direct_sigma_ps``, ``sss_delay_ps`` (P,) and ``ir_delay_ps``
        (P, R), in ps.
    rendered : dict of ndarray
        The rendered ``direct``, ``sss`` (P, L) and ``interreflections`` (P, R, L).
    t_ps : ndarray (L,)
        Sample times in ps.
    """
    d = np.asarray(params["direct_delay_ps"], np.float64)
    w = np.asarray(params["direct_sigma_ps"], np.float64)
    ir = np.asarray(params["ir_delay_ps"], np.float64)
    first_ir = np.min(np.where(np.isfinite(ir), ir, np.inf), axis=1) if ir.shape[-1] else np.full(d.shape, np.inf)
    onset = np.fmin(np.asarray(params["sss_delay_ps"], np.float64), first_ir)
    T = t_ps[1] - t_ps[0] if t_ps.size > 1 else 1.0
    other = rendered["sss"] + rendered["interreflections"].sum(axis=-2)
    with np.errstate(invalid="ignore"):
        near = (onset - d) <= WEAK_DIRECT_ONSET_SIGMA * w + T
        window = (t_ps[None, :] >= d[:, None]) & (t_ps[None, :] <= (d + (WEAK_DIRECT_ONSET_SIGMA + 2.0) * w + T)[:, None])
    h_other = np.where(window, other, 0.0).max(axis=1)
    h_direct = rendered["direct"].max(axis=1)
    return near & (h_other > 0) & (h_direct < WEAK_DIRECT_FRACTION * h_other)
