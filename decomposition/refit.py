"""Stage 3 of :func:`decomposition.decompose` (optional): off-grid refinement and standard errors.

:func:`refine_components` moves every found component's continuous parameters to the
weighted least-squares optimum of the forward model (:func:`decomposition.refine.refine`,
never worse per pixel, component set kept); :func:`component_errors` adds per-pixel standard
errors from the Fisher information at the solution (:func:`decomposition.fisher.standard_errors`).
Excluded samples (saturated, spikes, non-finite) have weight 0 in both.
"""
from __future__ import annotations

from .prepare import Samples

__all__ = ["refine_components", "component_errors"]


def refine_components(samples: Samples, params: dict, *, shared_sigma: bool, sss_after_direct: bool):
    """-> (refined params (P-shaped), {"refine_iterations", "refined"} in the input's leading shape)."""
    from .refine import refine

    axis = samples.axis
    params, rinfo = refine(samples.values, params, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                           weights=samples.weights, shared_sigma=shared_sigma, sss_after_direct=sss_after_direct)
    lead = samples.lead
    return params, {"refine_iterations": rinfo["iterations"].reshape(lead), "refined": rinfo["refined"].reshape(lead)}


def component_errors(samples: Samples, params: dict, *, shared_sigma: bool, sss_after_direct: bool) -> dict:
    """``<key>_stderr`` arrays for ``params`` (in the input's leading shape)."""
    from .fisher import standard_errors

    axis = samples.axis
    shape = samples.lead + (samples.n_bins,)
    return standard_errors(samples.values.reshape(shape), params, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                           weights=samples.weights.reshape(shape), shared_sigma=shared_sigma,
                           sss_after_direct=sss_after_direct)
