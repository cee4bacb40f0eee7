"""Model selection: the rules by which the solver compares two fits of the same pixel.

Every stage that chooses between alternative fits (the search, grow and prune stages, the
second pass of :mod:`decomposition.stages.rescue`, the measured-response path's forward steps
in :mod:`decomposition.response.grow`) reads them here:

* the data term chi2 of a residual in its noise (:func:`data_term`): per pixel, per sample, or
  whitened by the call's noise spectrum (a :class:`decomposition.noise.SpectralNoise`);
* k, the free parameters of a pixel's atoms (:func:`free_parameters`), from their family codes
  (:func:`families` reads them off a parameter dict): a delay and an amplitude per atom, the
  attenuation of an sss, and the widths the fit frees (one per atom, one shared per pixel, or
  none where a measured response fixes the shape);
* ln n, n the fitted samples (:func:`log_samples`);
* the penalised objective J = chi2 + penalty * k * ln n (:func:`penalised`; with penalty 1 the
  BIC), and its slot-state form (:func:`penalised_objective`);
* the chi-square noise band z sqrt(2 n) (:func:`noise_band`): a data term of n samples at the
  noise has mean n and standard deviation sqrt(2 n), so :func:`misfit_beyond_noise` says where a
  fit misfits by more than z standard deviations;
* ambiguity (:func:`is_ambiguous`): a second fit whose objective lies within a tolerance of the
  kept one's and whose split of the light differs from it by more than ``ambiguity_split``
  leaves the split undetermined by the data.  Two criteria set the tolerance
  (:func:`ambiguity_tolerance`): ``"evidence"``, a difference of ``ambiguity_chi2`` in J (a
  BIC difference of 10 is "very strong" evidence on Kass and Raftery's scale, J. Am. Stat.
  Assoc. 90, 773 (1995)), for fits that compete on the penalised objective; ``"noise"``,
  ``ambiguity_sigma`` chi-square standard deviations (:func:`noise_band`), for a refit judged
  against the fit it replaces on its deviance.
"""
from __future__ import annotations

import numpy as np

from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from ..model.slots import render
from ..noise import SpectralNoise, whitened_chi2

__all__ = ["data_term", "families", "free_parameters", "WIDTHS", "log_samples", "penalty", "penalised",
           "penalised_objective", "noise_band", "misfit_beyond_noise", "AMBIGUITY_CRITERIA",
           "ambiguity_tolerance", "is_ambiguous"]

#: how the widths of a pixel's atoms count in k: "per_atom" (each atom its own width), "shared"
#: (one width for all of a pixel's atoms, none without an atom), "fixed" (a measured response:
#: no width is fitted)
WIDTHS = ("per_atom", "shared", "fixed")

#: the tolerances of :func:`ambiguity_tolerance`
AMBIGUITY_CRITERIA = ("evidence", "noise")


def data_term(residual: np.ndarray, variance) -> np.ndarray:
    """(n,) chi2 of residuals ``residual`` (n, L) in the noise ``variance``: the sum of
    r^2 / variance with ``variance`` (n,) per pixel or (n, L) per sample, or, with a
    :class:`SpectralNoise`, the residual whitened by its spectrum
    (:func:`decomposition.noise.whitened_chi2`).  Samples not fitted carry a zero residual."""
    if isinstance(variance, SpectralNoise):
        return whitened_chi2(residual, variance.spectrum, variance.variance)
    v = np.asarray(variance, np.float64)
    return np.einsum("pl,pl->p", residual, residual / (v[:, None] if v.ndim == 1 else v))


def families(params: dict) -> np.ndarray:
    """(n, 2 + R) int8 family codes of the components of a parameter dict (n-shaped, NaN
    absent): the direct, the sss, the R inter-reflections -- the description
    :func:`free_parameters` counts."""
    d = np.isfinite(np.asarray(params["direct_delay_ps"], np.float64)).reshape(-1)
    s = np.isfinite(np.asarray(params["sss_delay_ps"], np.float64)).reshape(-1)
    r = np.isfinite(np.asarray(params["ir_delay_ps"], np.float64)).reshape(d.size, -1)
    fam = np.full((d.size, 2 + r.shape[1]), FAM_NONE, np.int8)
    fam[:, 0] = np.where(d, FAM_GAUSS, FAM_NONE)
    fam[:, 1] = np.where(s, FAM_SSS, FAM_NONE)
    fam[:, 2:] = np.where(r, FAM_GAUSS, FAM_NONE)
    return fam


def free_parameters(fam: np.ndarray, widths: str = "per_atom") -> np.ndarray:
    """(n,) int k: the free parameters of each pixel's atoms, ``fam`` (n, K) their family codes
    (a slot state's ``fam``, the response path's, or :func:`families` of a parameter dict): a
    delay and an amplitude per atom, the attenuation of each sss, and the widths ``widths``
    (:data:`WIDTHS`) frees."""
    if widths not in WIDTHS:
        raise ValueError(f"widths must be one of {WIDTHS}, got {widths!r}")
    fam = np.asarray(fam)
    n_act = (fam != FAM_NONE).sum(axis=1)
    k = 2 * n_act + (fam == FAM_SSS).sum(axis=1)
    if widths == "fixed":
        return k
    return k + (np.minimum(n_act, 1) if widths == "shared" else n_act)


def log_samples(n_fit) -> np.ndarray:
    """ln n of the fitted samples ``n_fit`` (n,) (at least one: 0 for a pixel without any)."""
    return np.log(np.maximum(n_fit, 1))


def penalty(k, log_n, weight: float = 1.0) -> np.ndarray:
    """(n,) the parameter penalty ``weight`` * k * ln n (``weight`` the options'
    ``search_penalty``; 1: the BIC's)."""
    return weight * k * log_n


def penalised(chi2, k, log_n, weight: float = 1.0) -> np.ndarray:
    """(n,) J = ``chi2`` + :func:`penalty` (k, ln n): the objective fits of one pixel compete on."""
    return chi2 + penalty(k, log_n, weight)


def penalised_objective(t, p, mask, st, variance, log_n, opts, response=None) -> np.ndarray:
    """(n,) J of a slot state ``st`` on the data ``p`` (n, L) and its sample mask ``mask`` (a
    :class:`decomposition.model.slots`-style mask with ``residual``): the data term of the
    rendered residual in ``variance`` (:func:`data_term`), plus ``opts.search_penalty`` k ln n,
    ``log_n`` (n,) and k counting one width per pixel with ``opts.shared_sigma``, else one per
    atom; ``response``: the atoms are a measured response's (:func:`decomposition.model.slots.render`)."""
    chi2 = data_term(mask.residual(p, render(t, st, response)), variance)
    return penalised(chi2, free_parameters(st["fam"], "shared" if opts.shared_sigma else "per_atom"), log_n,
                     opts.search_penalty)


def noise_band(n_fit, z: float) -> np.ndarray:
    """(n,) ``z`` standard deviations of a chi-square of ``n_fit`` degrees of freedom:
    z sqrt(2 n_fit)."""
    return float(z) * np.sqrt(2.0 * np.asarray(n_fit, np.float64))


def misfit_beyond_noise(chi2: np.ndarray, n_fit: np.ndarray, z: float) -> np.ndarray:
    """(n,) bool: a data term ``chi2`` above its expectation for a fit at the noise, ``n_fit``
    samples, by more than ``z`` standard deviations of a chi-square of ``n_fit`` degrees of
    freedom: chi2 > n_fit + z sqrt(2 n_fit) (NaN: False)."""
    n = np.asarray(n_fit, np.float64)
    with np.errstate(invalid="ignore"):
        return np.asarray(chi2) > n + noise_band(n, z)


def ambiguity_tolerance(criterion: str, opts, n_fit=None):
    """How far above the kept fit's objective a second fit still competes with it
    (:func:`is_ambiguous`): ``"evidence"``, ``opts.ambiguity_chi2`` (a difference in the penalised
    objective); ``"noise"``, ``opts.ambiguity_sigma`` standard deviations of a chi-square of
    ``n_fit`` (n,) degrees of freedom (:func:`noise_band`)."""
    if criterion == "evidence":
        return opts.ambiguity_chi2
    if criterion == "noise":
        if n_fit is None:
            raise ValueError("the 'noise' ambiguity criterion needs the fitted samples n_fit")
        return noise_band(n_fit, opts.ambiguity_sigma)
    raise ValueError(f"criterion must be one of {AMBIGUITY_CRITERIA}, got {criterion!r}")


def is_ambiguous(delta_j, tolerance, split_distance, ambiguity_split: float, where=None) -> np.ndarray:
    """(n,) bool: the pixels a second fit leaves undetermined.  ``delta_j`` (n,) its objective
    less the kept fit's, ``tolerance`` (scalar or (n,), :func:`ambiguity_tolerance`), ``where``
    (n,) bool the pixels where the second fit is a rival at all (None: every one).  Where
    ``delta_j`` <= ``tolerance``, ``split_distance`` (a function of those pixels' indices -> their
    (m,) distance between the two fits' splits, 1 - fidelity) is read, and the pixel is
    ambiguous where it exceeds ``ambiguity_split`` (NaN: not)."""
    near = np.asarray(delta_j) <= tolerance
    if where is not None:
        near &= where
    out = np.zeros(near.shape, bool)
    if near.any():
        r = np.flatnonzero(near)
        with np.errstate(invalid="ignore"):
            out[r] = np.asarray(split_distance(r)) > ambiguity_split
    return out
