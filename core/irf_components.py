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


def _family(irf, t, delay, amplitude, alpha=None):
    delay = np.asarray(delay, np.float64)
    amplitude = np.asarray(amplitude, np.float64)
    shape = np.broadcast_shapes(delay.shape, amplitude.shape)
    delay, amplitude = np.broadcast_to(delay, shape), np.broadcast_to(amplitude, shape)
    present = np.isfinite(delay) & np.isfinite(amplitude)
    if alpha is not None:
        alpha = np.broadcast_to(np.asarray(alpha, np.float64), shape)
        present &= np.isfinite(alpha) & (alpha >= 0)
    out = np.zeros(shape + (t.size,))
    if not present.any():
        return out
    if alpha is None:
        atoms = render_shifted(irf, t, delay[present])
    else:
        atoms = render_sss(irf, t, delay[present], alpha[present])
    out[present] = amplitude[present][:, None] * atoms
    return out


def render_components_response(params: dict, t_ps: np.ndarray, irf: InstrumentResponse) -> dict:
    """Render each component class of ``params`` on the time axis ``t_ps`` (L,) with ``irf``.

    Parameters
    ----------
    params : dict of ndarray
        Keys of :mod:`core.model` (shapes (...,) and (..., R)); missing families are absent,
        NaN entries render as zeros.
    t_ps : ndarray (L,)
        Time axis, ps.
    irf : InstrumentResponse

    Returns
    -------
    dict with ``direct`` (..., L), ``sss`` (..., L), ``interreflections`` (..., R, L).
    """
    t = np.asarray(t_ps, np.float64)
    shape = params_shape(params)
    zeros = np.zeros(shape + (t.size,))
    direct = (_family(irf, t, params["direct_delay_ps"], params["direct_amplitude"])
              if "direct_delay_ps" in params else zeros)
    sss = (_family(irf, t, params["sss_delay_ps"], params["sss_amplitude"], params["sss_alpha_per_ps"])
           if "sss_delay_ps" in params else zeros.copy())
    if "ir_delay_ps" in params:
        ir = _family(irf, t, params["ir_delay_ps"], params["ir_amplitude"])
    else:
        ir = np.zeros(shape + (0, t.size))
    return {"direct": direct, "sss": sss, "interreflections": ir}
