"""Labels and the parameter layout of the response path.

:func:`label_response` turns detected slots into named components by the Gaussian path's rule
(:func:`decomposition.stages.label.final_atoms` on the response's atoms: the threshold on peak
heights inside the window, shifted atoms closer than ``merge_tol_bins`` reduced to the larger
one, the sss onset moved to the direct's delay when it lies before it with
``sss_after_direct``), then :func:`decomposition.model.components.classify`: the earliest
shifted atom is the direct reflection, later ones r2, r3, ... in delay order, the sss atom s.  Every present component's ``*_sigma_ps`` is the response's Gaussian-equivalent
sigma (:func:`core.irf_components.gaussian_equivalent_sigma_ps`).

:func:`param_slots` / :func:`slots_to_params` convert between a parameter dict and the fixed
refinement layout (slot 0 direct, 1 sss, 2.. inter-reflections).
"""
from __future__ import annotations

import math

import numpy as np

from ..model import components as comp
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, SSS_SLOT
from core.model import empty_params
from ..options import SolverOptions
from ..stages.label import final_atoms

__all__ = ["label_response", "param_slots", "slots_to_params"]


def label_response(st: dict, irf, t_ps, scale, sigma_eq_ps: float, n_ir: int, opts: SolverOptions, *,
                   time_bin_ps: float, noise=None, weights=None):
    """Slots (n, K) -> (params (n-shaped, amplitudes times ``scale``), truncated (n,) bool).

    The Gaussian path's rule of the atoms a pixel keeps
    (:func:`decomposition.stages.label.final_atoms` with ``irf``: the threshold on the
    response's own atoms, relative on in-window peaks or significant against ``noise`` (n,),
    normalised units, ``weights`` (n, L) the samples' relative least-squares weights where the
    noise follows the signal, :attr:`decomposition.stages.detect.Detection.weights`; close
    shifted copies reduced to the larger; no sss onset before the direct with
    ``sss_after_direct``), then :func:`decomposition.model.components.classify`."""
    st = {k: v.copy() for k, v in st.items()}
    st["lsig"] = np.full(st["fam"].shape, math.log(sigma_eq_ps))     # what the rule resolves by, and the output's
    final_atoms(st, t_ps, time_bin_ps, opts, noise, weights, irf=irf)
    fam = st["fam"]
    st["amp"] = np.where(fam != FAM_NONE, st["amp"], 0.0)
    st["delay"] = np.where(fam != FAM_NONE, st["delay"], 0.0)
    st["lalp"] = np.where(fam == FAM_SSS, st["lalp"], 0.0)
    return comp.classify(st, np.asarray(scale, np.float64), n_ir)


def param_slots(params: dict, n_ir: int):
    """Parameter dict (n-shaped) -> (fam, delay, lalp) (n, 2 + R) in the refinement layout."""
    n = np.shape(params["direct_delay_ps"])[0]
    fam = np.zeros((n, 2 + n_ir), np.int8)
    delay = np.zeros((n, 2 + n_ir))
    lalp = np.zeros((n, 2 + n_ir))
    d = params["direct_delay_ps"]
    fam[np.isfinite(d), 0] = FAM_GAUSS
    delay[:, 0] = np.nan_to_num(d)
    s = params["sss_delay_ps"]
    has_s = np.isfinite(s) & np.isfinite(params["sss_alpha_per_ps"])
    fam[has_s, SSS_SLOT] = FAM_SSS
    delay[:, SSS_SLOT] = np.nan_to_num(s)
    with np.errstate(divide="ignore", invalid="ignore"):
        lalp[:, SSS_SLOT] = np.where(has_s, np.log(np.where(has_s, params["sss_alpha_per_ps"], 1.0)), 0.0)
    if n_ir:
        ir = params["ir_delay_ps"]
        fam[:, 2:][np.isfinite(ir)] = FAM_GAUSS
        delay[:, 2:] = np.nan_to_num(ir)
    return fam, delay, lalp


def slots_to_params(fam, delay, lalp, amp, scale, sigma_eq_ps, n_ir: int) -> dict:
    """Inverse of :func:`param_slots` with amplitudes (normalised units, times ``scale``);
    inter-reflections sorted by delay, empty slots NaN; every component's width
    ``sigma_eq_ps`` (ps; one for all pixels, or (n,) one per pixel)."""
    n = fam.shape[0]
    out = empty_params((n,), n_ir=n_ir)
    sc = np.asarray(scale, np.float64)
    sig = np.broadcast_to(np.asarray(sigma_eq_ps, np.float64), (n,))
    d = fam[:, 0] == FAM_GAUSS
    out["direct_delay_ps"][d] = delay[d, 0]
    out["direct_amplitude"][d] = amp[d, 0] * sc[d]
    out["direct_sigma_ps"][d] = sig[d]
    s = fam[:, SSS_SLOT] == FAM_SSS
    out["sss_delay_ps"][s] = delay[s, SSS_SLOT]
    out["sss_amplitude"][s] = amp[s, SSS_SLOT] * sc[s]
    out["sss_alpha_per_ps"][s] = np.exp(lalp[s, SSS_SLOT])
    out["sss_sigma_ps"][s] = sig[s]
    if n_ir:
        pres = fam[:, 2:] == FAM_GAUSS
        key = np.where(pres, delay[:, 2:], np.inf)
        order = np.argsort(key, axis=1, kind="stable")
        rows = np.arange(n)[:, None]
        pres_o = pres[rows, order]
        out["ir_delay_ps"] = np.where(pres_o, delay[:, 2:][rows, order], np.nan)
        out["ir_amplitude"] = np.where(pres_o, amp[:, 2:][rows, order] * sc[:, None], np.nan)
        out["ir_sigma_ps"] = np.where(pres_o, sig[:, None], np.nan)
    return out
