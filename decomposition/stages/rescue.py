"""A second, differently started pass for the pixels whose fit still misfits (``rescue``).

A pixel flagged POOR_FIT at the end of the Gaussian path misfits its data by more than
``poor_fit`` times its noise: a better split exists, and the path that led here did not find
it.  So does a pixel whose data term (:func:`data_term`, in the noise the first pass weighed it
with) lies more than RESCUE_MISFIT_Z standard deviations of a chi-square above its expectation
(:func:`misfit_beyond_noise`): POOR_FIT's bar, a residual RMS of 3 noise sigmas, forgives a
wide direct that took in an echo (4 ps white NSR 0.055: a data term 1.2-1.3 times its
expectation, no flag, fidelity 0.06; ``tests/test_rescue.py``).  Which path finds it is a
matter of where the detection started: the same profiles decomposed without the detection's
Gauss-Southwell restart (``multistart=False``, :data:`RESCUE_OPTIONS`) end elsewhere, and where
they misfit less the data say so.  So those pixels, where their noise does not follow the signal
(float data left unweighted: there the misfit is the model's, not a noise law's), are decomposed
once more with those options (:func:`rescue_rows`), and a pixel takes the second answer where
its penalised objective,

    J = sum over the fitted samples of (residual / s)^2 + k ln n,

s the noise the first pass weighed the pixel with (where the call's noise is correlated, the
residual whitened by its spectrum instead, as the search reads it), k the number of free
parameters (a delay and an amplitude per component, the sss attenuation, one shared width) and
n the number of fitted samples, is lower by at least ``ambiguity_chi2`` (a difference of 10 in this BIC is
"very strong" evidence on Kass and Raftery's scale, J. Am. Stat. Assoc. 90, 773 (1995): the
search stage's own bar, :mod:`decomposition.stages.search`).  The second answer comes with its own
flags (it may still misfit).

Paper scenes (``streaklab bench accuracy``'s, 600 px, seeds 0 and 1, 2 and 4 ps bins, white /
pink / photon noise at NSR 0.001 / 0.055 / 0.11): mean fidelity +0.0016 over the 36 points, at
4 ps white NSR 0.001 0.976 -> 0.981 and 0.979 -> 0.983 (seeds 0, 1); docs/decomposition.md has
the rest.  Left out, as measured: pixels weighted by a signal variance law (photon noise on
float data; the second pass on them as well moved those points by -0.001..+0.0006) and count
data (``noise="poisson"``, the same scenes at 100 / 1,000 / 10,000 photons: 0-26 POOR_FIT
pixels of 600, and not one whose second answer was better by fidelity, let alone by J).
Adding the misfits beyond the noise (the same scenes, seeds 0, 1 and 2, 54 points): mean
fidelity +0.0004, 18 points up and 4 down (at most -0.0020, 4 ps pink NSR 0.11 on seed 2), all
six white NSR 0.055 points up by 0.0010-0.0023, pixels below fidelity 0.5 773 -> 762; 1.6 % of
the pixels tried; on ``bench speed``'s default cube about 3 % more time (1,600 / 1,634 px/s
before, 1,553 / 1,574 / 1,551 after, alternated: 2 % of its pixels tried, one more call per chunk).
The second pass is the whole path, search included: without its search (``search=False`` in
the second pass) the gain over the 36 points fell from +0.0016 to +0.0002.  The call's ``info``
arrays of the detection (``objective``, ``n_iter``) stay the first pass's.
"""
from __future__ import annotations

import numpy as np

from ..model.components import free_parameters
from ..noise import whitened_chi2

__all__ = ["RESCUE_OPTIONS", "rescue_rows", "misfit_beyond_noise", "data_term", "penalised_misfit", "take_rescued"]

#: the options of the second pass (besides ``rescue=False``: one second pass only)
RESCUE_OPTIONS = {"multistart": False}


def rescue_rows(poor: np.ndarray, flat_noise: np.ndarray | None, poisson: bool) -> np.ndarray:
    """Indices of the pixels to decompose again: ``poor`` (P,) bool (POOR_FIT), limited to those
    whose noise was judged not to follow the signal (``flat_noise`` (P,) bool, None: all) and
    none for count data (``poisson``: their misfit is read on the Poisson law, a different
    question)."""
    if poisson:
        return np.zeros(0, np.int64)
    keep = np.asarray(poor, bool)
    if flat_noise is not None:
        keep = keep & np.asarray(flat_noise, bool)
    return np.flatnonzero(keep)


def misfit_beyond_noise(chi2: np.ndarray, n_fit: np.ndarray, z: float) -> np.ndarray:
    """(n,) bool: a data term ``chi2`` above its expectation for a fit at the noise, ``n_fit``
    samples, by more than ``z`` standard deviations of a chi-square of ``n_fit`` degrees of
    freedom: chi2 > n_fit + z sqrt(2 n_fit)."""
    n = np.asarray(n_fit, np.float64)
    with np.errstate(invalid="ignore"):
        return np.asarray(chi2) > n + float(z) * np.sqrt(2.0 * n)


def data_term(residual: np.ndarray, fit: np.ndarray, noise: np.ndarray,
              spectrum: np.ndarray | None = None) -> np.ndarray:
    """(n,) the sum over the ``fit`` (n, L) samples of (``residual`` / ``noise``)^2, ``residual``
    (n, L) and ``noise`` (n,) in the same units.  With the call's correlated-noise ``spectrum``
    (:attr:`Detection.noise_spectrum`) the residual whitened by it, as the search reads it
    (:func:`decomposition.noise.whitened_chi2`)."""
    s = np.maximum(np.asarray(noise, np.float64), 1e-300)
    r = np.where(fit, residual, 0.0)
    if spectrum is None:
        return np.einsum("pl,pl->p", r / s[:, None], r / s[:, None])
    return whitened_chi2(r, spectrum, s ** 2)


def penalised_misfit(residual: np.ndarray, fit: np.ndarray, noise: np.ndarray, params: dict,
                     spectrum: np.ndarray | None = None) -> np.ndarray:
    """(n,) J = :func:`data_term` + k ln n_fit, k :func:`decomposition.model.components.free_parameters`
    and n_fit the number of ``fit`` samples."""
    n_fit = np.maximum(fit.sum(axis=1), 1)
    return data_term(residual, fit, noise, spectrum) + free_parameters(params) * np.log(n_fit)


def take_rescued(j_first: np.ndarray, j_second: np.ndarray, margin: float) -> np.ndarray:
    """(n,) bool: the second answer is taken where its J is lower than the first's by at least
    ``margin`` (finite values only)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(j_second) & (j_second <= j_first - float(margin))

