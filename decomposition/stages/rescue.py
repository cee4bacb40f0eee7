"""A second, differently started pass for the pixels whose fit still misfits (``rescue``).

A pixel flagged POOR_FIT at the end of the path (either instrument) misfits its data by more than
``poor_fit`` times its noise: a better split exists, and the path that led here did not find
it.  So does a pixel whose data term (:func:`data_term`, in the noise the first pass weighed it
with) lies more than RESCUE_MISFIT_Z standard deviations of a chi-square above its expectation
(:func:`decomposition.stages.selection.misfit_beyond_noise`): POOR_FIT's bar, a residual RMS of 3 noise sigmas, forgives a
wide direct that took in an echo, unflagged (``tests/test_rescue.py`` holds one).
Which path finds it is a matter of where the detection started: the same profiles decomposed without the detection's
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

Left out: pixels weighted by a signal variance law (photon noise on float data) and count data
(``noise="poisson"``, whose misfit is read on the Poisson law): on the benchmark's scenes the
second pass found nothing better there.  The second pass is the whole path, search included
(the search is where its gain comes from).  The call's ``info`` arrays of the detection
(``objective``, ``n_iter``) stay the first pass's.  Measurements: docs/history.md.
"""
from __future__ import annotations

import numpy as np

from ..noise import SpectralNoise
from .selection import data_term as _chi2, families, free_parameters, log_samples, penalised

__all__ = ["RESCUE_OPTIONS", "rescue_rows", "data_term", "penalised_misfit", "take_rescued"]

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


def data_term(residual: np.ndarray, fit: np.ndarray, noise: np.ndarray,
              spectrum: np.ndarray | None = None) -> np.ndarray:
    """(n,) the sum over the ``fit`` (n, L) samples of (``residual`` / ``noise``)^2, ``residual``
    (n, L) and ``noise`` (n,) in the same units.  With the call's correlated-noise ``spectrum``
    (:attr:`Detection.noise_spectrum`) the residual whitened by it, as the search reads it
    (:func:`decomposition.noise.whitened_chi2`)."""
    var = np.maximum(np.asarray(noise, np.float64), 1e-300) ** 2
    return _chi2(np.where(fit, residual, 0.0), var if spectrum is None else SpectralNoise(spectrum, var))


def penalised_misfit(residual: np.ndarray, fit: np.ndarray, noise: np.ndarray, params: dict,
                     spectrum: np.ndarray | None = None) -> np.ndarray:
    """(n,) J = :func:`data_term` + k ln n_fit, k :func:`decomposition.stages.selection.free_parameters`
    and n_fit the number of ``fit`` samples."""
    return penalised(data_term(residual, fit, noise, spectrum), free_parameters(families(params), "shared"),
                     log_samples(fit.sum(axis=1)))


def take_rescued(j_first: np.ndarray, j_second: np.ndarray, margin: float) -> np.ndarray:
    """(n,) bool: the second answer is taken where its J is lower than the first's by at least
    ``margin`` (finite values only)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(j_second) & (j_second <= j_first - float(margin))

