"""Components of a parameter dict rendered with an instrument response instead of the Gaussian.

The counterpart of :func:`core.model.render_components` when the camera's response is a
measured (or model) :class:`core.irf.InstrumentResponse`: the direct reflection and every
inter-reflection is a shifted copy of the response, ``amplitude * render_shifted(irf, t, delay)``,
the sss component the response convolved with its decaying exponential,
``amplitude * render_sss(irf, t, delay, alpha)`` (unit-peak atoms, so an amplitude is the peak
height of a direct return, as with the Gaussian).  The ``*_sigma_ps`` keys play no part in the
shape; a component is present where its delay and amplitude (and, for sss, alpha) are finite.

:func:`gaussian_equivalent_sigma_ps` is the width a decomposition with a response reports in
its ``*_sigma_ps`` keys: FWHM / (2 sqrt(2 ln 2)), the sigma of the Gaussian with the response's
full width at half maximum.
"""
from __future__ import annotations

import math

import numpy as np

from .irf import InstrumentResponse, render_shifted, render_sss
from .model import params_shape

__all__ = ["gaussian_equivalent_sigma_ps", "render_components_response"]

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def gaussian_equivalent_sigma_ps(irf: InstrumentResponse) -> float:
    """sigma (ps) of the Gaussian with the response's FWHM: ``irf.fwhm_ps() / 2.3548``."""
    return float(irf.fwhm_ps() / _FWHM_PER_SIGMA)


def _family(shifted, sss, t, delay, amplitude, alpha=None):
    """(..., L) ``amplitude`` times the unit-peak atom of each entry (``shifted(t, delays)`` or
    ``sss(t, delays, alphas)``, (n, L)); zeros where the delay or amplitude (or alpha) is not
    finite, or alpha < 0."""
    delay = np.asarray(delay, np.float64)
    amplitude = np.asarray(amplitude, np.float64)
    shape = np.broadcast_shapes(delay.shape, amplitude.shape)
    delay, amplitude = np.broadcast_to(delay, shape), np.broadcast_to(amplitude, shape)
    present = np.isfinite(delay) & np.isfinite(amplitude)
    if alpha is not None:
        alpha = np.broadcast_to(np.asarray(alpha, np.float64), shape)
        with np.errstate(invalid="ignore"):
            present &= np.isfinite(alpha) & (alpha >= 0)
    out = np.zeros(shape + (t.size,))
    if not present.any():
        return out
    if alpha is None:
        atoms = shifted(t, delay[present])
    else:
        atoms = sss(t, delay[present], alpha[present])
    out[present] = amplitude[present][:, None] * atoms
    return out


def render_components_response(params: dict, t_ps: np.ndarray, irf: InstrumentResponse, *,
                               shifted=None, sss=None) -> dict:
    """Render each component class of ``params`` on the time axis ``t_ps`` (L,) with ``irf``.

    Parameters
    ----------
    params : dict of ndarray
        Keys of :mod:`core.model` (shapes (...,) and (..., R)); missing families are absent,
        NaN entries render as zeros.
    t_ps : ndarray (L,)
        Time axis, ps.
    irf : InstrumentResponse
    shifted, sss : callable, optional
        Renderers of the unit-peak atoms, ``shifted(t_ps, delays_ps) -> (n, L)`` and
        ``sss(t_ps, delays_ps, alphas_per_ps) -> (n, L)``; default the exact
        :func:`core.irf.render_shifted` and :func:`core.irf.render_sss` of ``irf`` (a solver
        may pass faster ones of its own, such as tabulated atoms).

    Returns
    -------
    dict with ``direct`` (..., L), ``sss`` (..., L), ``interreflections`` (..., R, L).
    """
    shifted = shifted or (lambda t, d: render_shifted(irf, t, d))
    sss = sss or (lambda t, d, a: render_sss(irf, t, d, a))
    t = np.asarray(t_ps, np.float64)
    shape = params_shape(params)
    zeros = np.zeros(shape + (t.size,))
    direct = (_family(shifted, sss, t, params["direct_delay_ps"], params["direct_amplitude"])
              if "direct_delay_ps" in params else zeros)
    sss_part = (_family(shifted, sss, t, params["sss_delay_ps"], params["sss_amplitude"], params["sss_alpha_per_ps"])
                if "sss_delay_ps" in params else zeros.copy())
    if "ir_delay_ps" in params:
        ir = _family(shifted, sss, t, params["ir_delay_ps"], params["ir_amplitude"])
    else:
        ir = np.zeros(shape + (0, t.size))
    return {"direct": direct, "sss": sss_part, "interreflections": ir}
