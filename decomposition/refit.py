"""Stage 3 of :func:`decomposition.decompose` (optional): off-grid refinement and standard errors.

:func:`refine_components` moves every found component's continuous parameters to the
weighted least-squares optimum of the forward model (:func:`decomposition.refine.refine`,
never worse per pixel, component set kept); :func:`component_errors` adds per-pixel standard
errors from the Fisher information at the solution (:func:`decomposition.fisher.standard_errors`).
Excluded samples (saturated, spikes, non-finite) have weight 0 in both.

Count data (``noise="poisson"``): the weights are 1 / variance of the Poisson law at the
model (:func:`sample_weights`), and the refit is repeated POISSON_REFITS times, each with the
previous model's weights (iteratively reweighted least squares, whose fixed point is the
Poisson maximum-likelihood fit).  ``decompose`` reaches that fit without this stage, in the
compiled polish of :mod:`decomposition.countpolish`; this refit runs for count data only with
``refine=True`` (and for the GradBM baseline).  The standard errors use weights 1 / model count with the
noise scale measured on the fit (:func:`decomposition.noise.fit_dispersion`, 1 for pure
counts): the Poisson Fisher information.
"""
from __future__ import annotations

import numpy as np

from core.model import render_profile
from .constants import POISSON_REFITS
from .noise import fit_dispersion, poisson_weights
from .prepare import Samples

__all__ = ["refine_components", "component_errors", "sample_weights"]


def sample_weights(samples: Samples, params: dict) -> np.ndarray:
    """(P, L) least-squares weights: the fit mask, or for count data 1 / Poisson variance of
    the model of ``params`` (P-shaped) on the fitted samples."""
    if samples.noise_model != "poisson":
        return samples.weights
    return poisson_weights(_model(samples, params), samples.fit, samples.dispersion)


def _model(samples: Samples, params: dict) -> np.ndarray:
    """(P, L) model of P-shaped ``params`` (0 where a pixel has none)."""
    axis = samples.axis
    with np.errstate(invalid="ignore"):
        model = render_profile(params, samples.n_bins, axis.time_bin_ps, axis.t0_ps)
    return np.where(np.isfinite(model), model, 0.0)


def refine_components(samples: Samples, params: dict, *, shared_sigma: bool, sss_after_direct: bool):
    """-> (refined params (P-shaped), {"refine_iterations", "refined"} in the input's leading shape)."""
    from .refine import refine

    axis = samples.axis
    n_fits = POISSON_REFITS if samples.noise_model == "poisson" else 1
    iterations = np.zeros(samples.values.shape[0], np.int64)
    refined = np.zeros(samples.values.shape[0], bool)
    for _ in range(n_fits):
        params, rinfo = refine(samples.values, params, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                               weights=sample_weights(samples, params), shared_sigma=shared_sigma,
                               sss_after_direct=sss_after_direct)
        iterations += rinfo["iterations"].reshape(-1)
        refined |= rinfo["refined"].reshape(-1)
    lead = samples.lead
    return params, {"refine_iterations": iterations.reshape(lead), "refined": refined.reshape(lead)}


def component_errors(samples: Samples, params: dict, *, shared_sigma: bool, sss_after_direct: bool) -> dict:
    """``<key>_stderr`` arrays for ``params`` (in the input's leading shape)."""
    from .fisher import standard_errors

    axis = samples.axis
    shape = samples.lead + (samples.n_bins,)
    n_pix = samples.values.shape[0]
    flat = {k: np.reshape(v, (n_pix,) + np.shape(v)[len(samples.lead):]) for k, v in params.items()}
    noise = None
    if samples.noise_model == "poisson":
        # weights 1 / Poisson variance, the noise scale measured on the fit (1 for pure counts)
        model = _model(samples, flat)
        weights = poisson_weights(model, samples.fit)
        noise = fit_dispersion(samples.values, model, samples.fit).reshape(samples.lead)
    else:
        weights = samples.weights
    return standard_errors(samples.values.reshape(shape), params, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                           weights=weights.reshape(shape), shared_sigma=shared_sigma,
                           sss_after_direct=sss_after_direct, noise_sigma=noise)
