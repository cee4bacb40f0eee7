"""The noise a penalised objective reads its data term in, and the smoothing its tests share.

The search, grow and prune stages score a pixel's alternative slot states by
J = chi2 + search_penalty * k * ln(n) (:mod:`decomposition.stages.selection`, the one home of
that measure); :func:`objective_variance` says which noise variance chi2 divides by: per
pixel, per sample, or the call's noise spectrum (pink noise).
"""
from __future__ import annotations

import numpy as np

from ..constants import WHITE_LAG_RATIO
from ..noise import SpectralNoise

__all__ = ["objective_variance"]


def _smooth(y, width_bins):
    """Gaussian smoothing along the last axis with a per-pixel width (bins), via FFT (zero-padded
    to twice the length: no wrap-around); the filter is built and applied in place."""
    n = y.shape[-1]
    f = np.fft.rfftfreq(2 * n)
    h = np.pi * f[None, :] * np.asarray(width_bins, np.float64)[:, None]
    h *= h
    h *= -2.0
    np.exp(h, out=h)                          # exp(-2 (pi f w)^2)
    spec = np.fft.rfft(np.asarray(y, np.float64), n=2 * n, axis=-1)
    spec *= h
    return np.fft.irfft(spec, n=2 * n, axis=-1)[:, :n]


def _per_sample(s2):
    """A noise variance of one value per pixel (n,) or per sample (n, L), as (n, 1) or (n, L)."""
    s2 = np.asarray(s2, np.float64)
    return s2[:, None] if s2.ndim == 1 else s2


def objective_variance(s_eff, significance_sigma=None, weights=None, spectrum=None):
    """The noise variance a penalised objective divides its data term by: (n,), or (n, L) with
    ``weights``.  The solver's ``s_eff`` (n,) squared, or the significance noise's
    (``significance_sigma`` (n,), :meth:`Samples.significance_sigma` after
    :func:`decomposition.stages.candidates.residual_significance_noise`; None: not used) where that
    exceeds WHITE_LAG_RATIO x ``s_eff``, i.e. where the noise is correlated at the components'
    scale (pink noise); divided by the samples' relative least-squares ``weights`` (n, L)
    (:attr:`Detection.weights`) where given.  There a component fitted to the noise lowers the data term by about
    (lagged / sample noise)^2 times what white noise would, and a parameter-count penalty read in
    sample variances lets noise bumps through as inter-reflections.

    With the call's noise ``spectrum`` (:attr:`Detection.noise_spectrum`, where its noise is
    correlated): a :class:`SpectralNoise` of that spectrum and ``s_eff``'s variances instead,
    whatever the rest -- the residual whitened by the noise's own spectrum rather than read in
    one lagged level."""
    s_eff = np.asarray(s_eff, np.float64)
    if spectrum is not None:
        return SpectralNoise(np.asarray(spectrum, np.float64), s_eff ** 2)
    if significance_sigma is None:
        var = s_eff ** 2
    else:
        sig = np.asarray(significance_sigma, np.float64)
        var = np.where(sig > WHITE_LAG_RATIO * s_eff, sig, s_eff) ** 2
    return var if weights is None else var[:, None] / np.maximum(weights, 1e-300)

