"""Stage 5 of :func:`decomposition.decompose`: the rendered fit and its quality flags.

POOR_FIT: the residual RMS over the fitted samples (censored samples count only where the
model lies above them) exceeds ``poor_fit`` x the noise -- the larger of the solver's
estimate and the noise at the signal, since noise that grows with the signal (photon noise)
is not a misfit.  EMPTY: a finite pixel with no component at all.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import components as comp
from .flags import EMPTY, FLAG_DTYPE, POOR_FIT, mark
from .noise import signal_noise_sigma
from .prepare import Samples

__all__ = ["Fit", "assess_fit"]


@dataclass(frozen=True)
class Fit:
    """Rendered components (``direct``, ``sss`` (P, L), ``interreflections`` (P, R, L)), the
    ``residual`` (P, L) = values - all components, and ``flags`` (P,) (POOR_FIT, EMPTY)."""

    direct: np.ndarray
    sss: np.ndarray
    interreflections: np.ndarray
    residual: np.ndarray
    flags: np.ndarray


def assess_fit(samples: Samples, params: dict, noise_eff: np.ndarray, poor_fit: float, irf=None) -> Fit:
    """Render ``params`` (P-shaped; with the instrument response ``irf`` when given, else the
    Gaussian PSF), form the residual, flag poor fits and empty pixels."""
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
        bad = rms > poor_fit * np.maximum(noise_eff[live], s_sig)
        mark(flags, live[bad], POOR_FIT)
    has_any = np.isfinite(params["direct_delay_ps"]) | np.isfinite(params["sss_delay_ps"])
    if params["ir_delay_ps"].shape[-1]:
        has_any |= np.isfinite(params["ir_delay_ps"]).any(axis=1)
    mark(flags, samples.finite & ~has_any, EMPTY)
    return Fit(direct=rend["direct"], sss=rend["sss"], interreflections=rend["interreflections"],
               residual=residual, flags=flags)
