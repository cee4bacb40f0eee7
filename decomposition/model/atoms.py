"""Atoms of a measured response for blocks of slot arrays, with their derivatives.

The response path of :func:`decomposition.decompose` keeps each pixel's components in slot
arrays of shape (P, K): ``fam`` (FAM_NONE, FAM_GAUSS for a shifted copy of the response --
direct or inter-reflection --, FAM_SSS), ``delay`` (ps), ``lalp`` (log alpha, alpha in 1/ps;
sss slots only).  :func:`slot_atoms` renders every active slot at once with the compiled
:func:`decomposition.kernels.response.slot_rows` (the atoms of
:func:`~decomposition.kernels.response.shifted_atoms` / :func:`~decomposition.kernels.response.sss_atoms`,
unit peak; :func:`core.irf.render_shifted` / :func:`core.irf.render_sss` to within their
stated table error), and optionally the derivatives with respect to the delay and to log alpha.
"""
from __future__ import annotations

import numpy as np

from core.irf import InstrumentResponse
from core.irf_components import render_components_response
from core.model import BACKGROUND_KEY, params_shape
from ..constants import FAM_SSS
from ..kernels.response import response_table, shifted_atoms, slot_rows, sss_atoms

__all__ = ["params_components", "params_profile", "slot_atoms"]


def slot_atoms(irf: InstrumentResponse, t_ps: np.ndarray, fam: np.ndarray, delay: np.ndarray,
               lalp: np.ndarray, *, derivatives: bool = False):
    """Unit-peak atoms of every slot, zeros for empty ones.

    Parameters
    ----------
    irf : InstrumentResponse
    t_ps : ndarray (L,)          time axis, ps
    fam : ndarray (P, K) int8    slot families
    delay : ndarray (P, K)       delays, ps (read where the slot is active)
    lalp : ndarray (P, K)        log alpha (read in sss slots)
    derivatives : bool
        Also return d atom / d delay (per ps) and d atom / d log alpha (dimensionless;
        zero outside sss slots).

    Returns
    -------
    phi : ndarray (P, K, L)
    d_delay, d_lalp : ndarray (P, K, L) (only with ``derivatives=True``)
    """
    ss = fam == FAM_SSS
    alpha = np.zeros(fam.shape)
    alpha[ss] = np.exp(lalp[ss])
    out = slot_rows(response_table(irf), t_ps, fam, delay, alpha, derivatives=derivatives)
    if derivatives:
        phi, dd, da = out
        da[ss] *= alpha[ss][:, None]            # d / d log alpha = alpha d / d alpha
        return phi, dd, da
    return out


def params_components(irf: InstrumentResponse, t_ps: np.ndarray, params: dict) -> dict:
    """The components of ``params`` rendered with the response's table atoms
    (:mod:`decomposition.kernels.response`): :func:`core.irf_components.render_components_response`
    (and the ``background`` of :func:`core.model.render_components` where ``params`` has the
    key) to within the table's error, at most :data:`~decomposition.kernels.response.TABLE_REL_ERROR`
    of each atom's peak times its amplitude.  The response path's trial models at every forward
    step, and the components it reports (:func:`decomposition.model.components.render_params`):
    the model it fitted, and far cheaper than the exact interpolant's FFT rendering.

    Parameters
    ----------
    irf : InstrumentResponse
    t_ps : ndarray (L,)        time axis, ps
    params : dict of ndarray   keys of :mod:`core.model` (shapes (...,) and (..., R)); NaN
                               entries and missing families render as zeros

    Returns
    -------
    dict with ``direct`` (..., L), ``sss`` (..., L), ``interreflections`` (..., R, L), and
    ``background`` (..., L) (0 where NaN) where ``params`` has :data:`core.model.BACKGROUND_KEY`.
    """
    t = np.ascontiguousarray(t_ps, np.float64)
    tab = response_table(irf)
    shape = params_shape(params)
    out = render_components_response(params, t, irf, shifted=lambda tt, d: shifted_atoms(tab, tt, d),
                                     sss=lambda tt, d, a: sss_atoms(tab, tt, d, a))
    if BACKGROUND_KEY in params:
        b = np.asarray(params[BACKGROUND_KEY], np.float64)
        out["background"] = np.broadcast_to(np.where(np.isfinite(b), b, 0.0)[..., None], shape + (t.size,)).copy()
    return out


def params_profile(irf: InstrumentResponse, t_ps: np.ndarray, params: dict) -> np.ndarray:
    """(..., L) the model of ``params``: the sum of :func:`params_components` (background
    included where ``params`` has one); :func:`core.model.render_profile` with ``irf`` to
    within the table's error."""
    c = params_components(irf, t_ps, params)
    total = c["direct"] + c["sss"] + c["interreflections"].sum(axis=-2)
    if "background" in c:
        total += c["background"]
    return total
