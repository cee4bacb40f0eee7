"""Atoms of an instrument for blocks of slot arrays: a measured response's, or the Gaussian PSF's.

The response path of :func:`decomposition.decompose` keeps each pixel's components in slot
arrays of shape (P, K): ``fam`` (FAM_NONE, FAM_GAUSS for a shifted copy of the response --
direct or inter-reflection --, FAM_SSS), ``delay`` (ps), ``lalp`` (log alpha, alpha in 1/ps;
sss slots only).  :func:`slot_atoms` renders every active slot at once with the compiled
:func:`decomposition.kernels.response.slot_rows` (the atoms of
:func:`~decomposition.kernels.response.shifted_atoms` / :func:`~decomposition.kernels.response.sss_atoms`,
unit peak; :func:`core.irf.render_shifted` / :func:`core.irf.render_sss` to within their
stated table error), and optionally the derivatives with respect to the delay and to log alpha.

The response path's stages take either instrument: a measured response
(:class:`core.irf.InstrumentResponse`, the same for every pixel) or :class:`GaussianPSF`, the
Gaussian PSF of one known width per pixel (the Gaussian kernels of
:func:`decomposition.kernels.atomlm.atom_profiles`, the Gaussian path's own).
:func:`instrument_rows` takes an instrument's pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.irf import InstrumentResponse
from core.irf_components import render_components_response
from core.model import BACKGROUND_KEY, params_shape, render_components
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from ..kernels.atomlm import atom_profiles
from ..kernels.response import response_table, shifted_atoms, slot_rows, sss_atoms

__all__ = ["GaussianPSF", "instrument_rows", "params_components", "params_profile", "slot_atoms",
           "shifted_slot_atoms", "sss_slot_atoms"]


@dataclass(frozen=True)
class GaussianPSF:
    """The Gaussian PSF as an instrument of the response path's stages: ``sigma_ps`` (n,), each
    pixel's width (ps, finite and positive), held.  Its atoms are the Gaussian path's kernels
    (unit peak for a shifted atom; the sss the Gaussian convolved with the exponential, in the
    amplitude convention of :func:`core.model.render_components`)."""

    sigma_ps: np.ndarray

    def __post_init__(self):
        s = np.asarray(self.sigma_ps, np.float64)
        if s.ndim != 1 or not np.all(np.isfinite(s) & (s > 0)):
            raise ValueError("GaussianPSF needs one finite positive width per pixel, shape (n,)")
        object.__setattr__(self, "sigma_ps", s)

    def rows(self, idx) -> "GaussianPSF":
        """The instrument of the pixels ``idx``."""
        return GaussianPSF(self.sigma_ps[idx])


def instrument_rows(inst, idx):
    """The instrument of the pixels ``idx``: a measured response is every pixel's."""
    return inst.rows(idx) if isinstance(inst, GaussianPSF) else inst


def _gaussian_atoms(inst: GaussianPSF, t_ps, fam, delay, lalp) -> np.ndarray:
    """(P, K, L) the Gaussian PSF's atoms of slot arrays (P, K) on the uniform axis ``t_ps``,
    zeros in empty slots."""
    t = np.asarray(t_ps, np.float64)
    fam = np.asarray(fam)
    P, K = fam.shape
    lsig = np.broadcast_to(np.log(inst.sigma_ps)[:, None], (P, K))
    on = fam != FAM_NONE
    out = np.zeros((P, K, t.size))
    if on.any():
        step = t[1] - t[0] if t.size > 1 else 1.0
        out[on] = atom_profiles(float(t[0]), float(step), t.size, fam[on], np.asarray(delay, np.float64)[on],
                                lsig[on], np.where(fam == FAM_SSS, lalp, 0.0)[on])
    return out


def shifted_slot_atoms(inst, t_ps, delay) -> np.ndarray:
    """(m, L) the instrument's shifted atoms (unit peak) of m pixels at ``delay`` (m,), ps."""
    if isinstance(inst, GaussianPSF):
        d = np.asarray(delay, np.float64)[:, None]
        return _gaussian_atoms(inst, t_ps, np.full(d.shape, FAM_GAUSS, np.int8), d, np.zeros(d.shape))[:, 0]
    return shifted_atoms(response_table(inst), t_ps, delay)


def sss_slot_atoms(inst, t_ps, delay, alpha_per_ps) -> np.ndarray:
    """(m, L) the instrument's sss atoms of m pixels with onsets ``delay`` and decay rates
    ``alpha_per_ps`` (m,)."""
    if isinstance(inst, GaussianPSF):
        d = np.asarray(delay, np.float64)[:, None]
        la = np.log(np.asarray(alpha_per_ps, np.float64))[:, None]
        return _gaussian_atoms(inst, t_ps, np.full(d.shape, FAM_SSS, np.int8), d, la)[:, 0]
    return sss_atoms(response_table(inst), t_ps, delay, alpha_per_ps)


def slot_atoms(irf: InstrumentResponse, t_ps: np.ndarray, fam: np.ndarray, delay: np.ndarray,
               lalp: np.ndarray, *, derivatives: bool = False):
    """Unit-peak atoms of every slot, zeros for empty ones.

    Parameters
    ----------
    irf : InstrumentResponse or GaussianPSF (of the P pixels)
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
    if isinstance(irf, GaussianPSF):
        if derivatives:
            raise ValueError("the Gaussian PSF's slot atoms have no derivatives here: its count fit is the "
                             "compiled one (decomposition.kernels.countlm)")
        return _gaussian_atoms(irf, t_ps, fam, delay, lalp)
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
    irf : InstrumentResponse or GaussianPSF (its widths are those of ``params``)
    t_ps : ndarray (L,)        time axis, ps
    params : dict of ndarray   keys of :mod:`core.model` (shapes (...,) and (..., R)); NaN
                               entries and missing families render as zeros

    Returns
    -------
    dict with ``direct`` (..., L), ``sss`` (..., L), ``interreflections`` (..., R, L), and
    ``background`` (..., L) (0 where NaN) where ``params`` has :data:`core.model.BACKGROUND_KEY`.
    """
    t = np.ascontiguousarray(t_ps, np.float64)
    shape = params_shape(params)
    if isinstance(irf, GaussianPSF):
        # the parameters carry each pixel's width: the Gaussian path's own rendering
        step = t[1] - t[0] if t.size > 1 else 1.0
        return render_components(params, t.size, float(step), float(t[0]))
    tab = response_table(irf)
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
