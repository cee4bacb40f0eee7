"""Material starts: an sss that one pixel's data could not justify, given by its material's neighbours.

A material has one sss-to-direct amplitude ratio, one sss decay rate and one sss onset after the
direct (the material prior of :mod:`decomposition.image.spatial`).  At a few hundred photons a
pixel of a weak, fast sss (a small ratio, a decay of a few PSF widths) is often fitted with the
direct alone: on its own the sss costs three free parameters (its amplitude, onset and decay
rate) for a few tens of counts, and the direct absorbs them, late and too wide.  Its neighbours
of the same material that did keep an sss know its shape.  Given that shape, the sss costs the
pixel one parameter (its amplitude), and the pixel's data decide on that alone.

:func:`material_round`, between the neighbour starts and the joint refinement: every decomposed
pixel with a direct and no sss whose neighbourhood (``material_radius``) is one material for all
three parameters by the majority of the neighbours' own answers
(:func:`decomposition.image.spatial.mixed_neighbourhood` with ``stray_share`` 1: the answers
beyond ``edge_sigma`` of the median left out while they are fewer than half; neighbours each of
their own material may pass it by chance, so it only proposes) is refitted with an sss started at
the neighbours' biweight means, under the material
prior at those means (:func:`decomposition.image.spatial.refine_priors`).  The refit is kept
where its penalised objective J, the sss counted as one free parameter, lies below the pixel's
own J (both with the same sample weights, :func:`decomposition.image.spatial.objective_weights`).
The joint refinement then carries the material prior on it like on any other pixel.
:func:`material_starts` runs ``material_rounds`` such rounds, each on the answers the last one
left: a pixel amid neighbours that all lacked the sss is reached once its neighbours gained it.
"""
from __future__ import annotations

import numpy as np

from ..stages.selection import families, free_parameters, log_samples, penalty
from . import spatial as sp

__all__ = ["MATERIAL_NAMES", "material_estimate", "material_round", "material_starts"]

#: the material's parameters (:func:`decomposition.image.spatial.prior_values`' names)
MATERIAL_NAMES = ("onset", "ratio", "alpha")


def material_estimate(values: dict, shape: tuple, options: sp.SpatialOptions) -> dict:
    """Each pixel's material as its neighbours within ``options.material_radius`` see it.

    Parameters
    ----------
    values : dict
        {name of :data:`MATERIAL_NAMES`: ((P,) values, (P,) standard errors, the prior's scale)}
        as :func:`decomposition.image.spatial.prior_values` gives them (NaN: no sss).
    shape : (Y, X)
    options : SpatialOptions

    Returns
    -------
    dict
        {name: ((P,) mean, (P,) precision)}: the Tukey biweight mean of the neighbours (the
        pixel itself left out) and the prior's precision 1 / (scale^2 + the mean's variance);
        precision 0 and mean NaN where the majority of the neighbourhood is not one material
        (:func:`decomposition.image.spatial.mixed_neighbourhood` with ``stray_share`` 1) or no
        neighbour has weight.
    """
    out = {}
    for name in MATERIAL_NAMES:
        v, se, scale = values[name]
        tau2 = float(scale) ** 2
        mixed = sp.mixed_neighbourhood(v, se, shape, options, scale, options.material_radius, stray_share=1.0)
        nd, ns, ok = sp._neighbourhood(v, se, shape, options.material_radius)
        mean, precision = np.full(v.size, np.nan), np.zeros(v.size)
        have = ~mixed & ok.any(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            m, w, _ = sp._biweight_mean(np.where(ok, nd, np.nan)[:, have], ns[:, have], ok[:, have], tau2,
                                        options.edge_sigma)
            wsum = w.sum(axis=0)
            on = (wsum > 0) & np.isfinite(m)
            mean[have] = np.where(on, m, np.nan)
            precision[have] = np.where(on, 1.0 / (tau2 + 1.0 / np.where(wsum > 0, wsum, 1.0)), 0.0)
        out[name] = (mean, precision)
    return out


def material_starts(c: sp.Coupling, options: sp.SpatialOptions) -> None:
    """``options.material_rounds`` rounds of :func:`material_round` (each on the answers the
    last left; they stop where a round kept none); ``c`` updated in place,
    ``c.info["spatial_material_starts"]`` the refits tried and
    ``c.info["spatial_material_taken"]`` those kept."""
    c.info["spatial_material_starts"] = c.info["spatial_material_taken"] = 0
    if not (options.material_prior and options.material_starts):
        return
    for _ in range(options.material_rounds):
        tried, taken = material_round(c, options)
        c.info["spatial_material_starts"] += tried
        c.info["spatial_material_taken"] += taken
        if taken == 0:
            break


def material_round(c: sp.Coupling, options: sp.SpatialOptions) -> tuple[int, int]:
    """One round: the pixels without an sss in a one-material neighbourhood refitted with their
    neighbours' sss and kept where the data support it (module docstring); ``c.params`` updated
    in place -> (pixels tried, pixels kept)."""
    p = c.params
    with np.errstate(invalid="ignore"):
        bare = c.live & np.isfinite(p["direct_delay_ps"]) & (p["direct_amplitude"] > 0) & ~(p["sss_amplitude"] > 0)
    if not bare.any():
        return 0, 0
    est = material_estimate(sp.prior_values(c, p, options), c.shape, options)
    rows = np.flatnonzero(bare & np.all([est[n][1] > 0 for n in MATERIAL_NAMES], axis=0))
    if rows.size == 0:
        return 0, 0
    own = sp.take_rows(p, rows)
    start = {k: np.array(v, copy=True) for k, v in own.items()}
    (onset, _), (ratio, _), (alpha, _) = (tuple(a[rows] for a in est[n]) for n in MATERIAL_NAMES)
    start["sss_delay_ps"] = own["direct_delay_ps"] + onset
    start["sss_amplitude"] = np.exp(ratio) * own["direct_amplitude"]
    start["sss_alpha_per_ps"] = np.exp(alpha)
    start["sss_sigma_ps"] = own["direct_sigma_ps"]
    priors = {n: (est[n][0][rows], est[n][1][rows]) for n in MATERIAL_NAMES}
    weights = sp.objective_weights(c, p)[rows]
    kw = sp.refine_priors(priors, sp.noise_variance(c)[rows], own["direct_amplitude"])
    fits = sp.refit(c, rows, start, weights, None, kw)
    with np.errstate(invalid="ignore"):
        kept = fits["sss_amplitude"] > 0
    # the sss's shape is the neighbours': of its free parameters only the amplitude is the pixel's
    k_extra = free_parameters(families(fits), c.widths) - free_parameters(families(own), c.widths) - 1
    log_n = log_samples(c.samples.fit[rows].sum(axis=1))
    j_new = sp.objective(c, rows, fits, weights) - penalty(np.maximum(k_extra, 0), log_n, c.opts.search_penalty)
    take = kept & (j_new < sp.objective(c, rows, own, weights))
    for k in p:
        p[k][rows[take]] = fits[k][take]
    return int(rows.size), int(take.sum())
