"""After the sparse selection: debias the kept atoms, snap them to the grid, re-fit amplitudes.

:func:`polish_block` refines a fixed set of atoms on the data term alone (ConvSCD step 3);
with ``off_grid=False`` :func:`snap_to_grid` puts them on the paper's reference grid and
:func:`refit_amplitudes` solves the non-negative amplitudes for the snapped shapes.
"""
from __future__ import annotations

import numpy as np

from ..kernels.atomlm import nnls_amplitudes
from ..kernels.projected import response_instrument
from ..constants import FAM_NONE, FAM_SSS
from .dictionary import Dictionary
from ..masks import SampleMask, check_mask
from ..model.slots import (drop_zero, linked_onsets, parameter_bounds, put, refine_atoms, take,
                           tie_widths)

__all__ = ["polish_block", "snap_to_grid", "refit_amplitudes"]


def polish_block(p, mask: SampleMask, st, s_eff, dic: Dictionary, *, sparsity=3.0, eps_rel=0.01, n_lm=10,
                 bound_factor=4.0, tie_sigma=True, sss_after_direct=True, lm_tol=1e-6):
    """Final least-squares refinement of a fixed set of atoms (after thresholding and merging).

    The sparse step has chosen the atoms; this is the usual debiasing step
    after sparse selection: the log-sum penalty shrinks amplitudes (it favours
    a smaller direct plus a larger sss along their near-degenerate direction),
    so the kept atoms are refined on the data term alone (mu = 0), each step
    accepted only where the residual decreases.
    """
    check_mask(mask, p.shape)
    L = p.shape[1]
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    mu = np.zeros_like(s_eff)
    eps = eps_rel * s_eff
    bounds = parameter_bounds(dic, bound_factor)
    if tie_sigma:
        st = tie_widths({k: v.copy() for k, v in st.items()})
    st, obj, nl, model = refine_atoms(t, p, mask, st, mu, eps, bounds, n_lm, None, tie_sigma, sss_after_direct, lm_tol,
                                      return_model=True)
    if sss_after_direct:
        # A direct and an sss with the same onset and width are degenerate to first order
        # (dh/dt = g - alpha h), so a gap stuck near 0 is re-tried from one PSF width.
        # An sss onset far before the direct (an exponential tail alone is degenerate in
        # onset and amplitude) is re-tried the same way.
        lk, dsl, ssl = linked_onsets(st, near_sigma=np.inf)
        rows = np.arange(st["fam"].shape[0])
        gap = st["delay"][rows, ssl] - st["delay"][rows, dsl]
        sig_s = np.exp(st["lsig"][rows, ssl])
        retry = np.nonzero(lk & (gap < 0.5 * sig_s))[0]
        if retry.size:
            alt = take(st, retry)
            alt["delay"][np.arange(retry.size), ssl[retry]] = (alt["delay"][np.arange(retry.size), dsl[retry]]
                                                                + sig_s[retry])
            alt, o_alt, nl2, m_alt = refine_atoms(t, p[retry], mask[retry], alt, mu[retry], eps[retry], bounds, n_lm,
                                                  None, tie_sigma, sss_after_direct, lm_tol, return_model=True)
            better = o_alt < obj[retry]
            put(st, retry[better], take(alt, better))
            model[retry[better]] = m_alt[better]
            obj[retry[better]] = o_alt[better]
            nl += nl2
    drop_zero(st)              # zero-amplitude atoms add nothing to the model
    return st, model, nl


def snap_to_grid(st, dic: Dictionary):
    """Snap delays to integer bins and sigma/alpha to the reference grid (``off_grid=False``)."""
    act = st["fam"] != FAM_NONE
    T = dic.time_bin_ps
    st["delay"] = np.where(act, dic.t0_ps + np.round((st["delay"] - dic.t0_ps) / T) * T, st["delay"])
    fs, fa = dic.grid.fine_sigma(), dic.grid.fine_alpha()
    sig = np.exp(st["lsig"])
    si = np.abs(sig[..., None] - fs).argmin(-1)
    st["lsig"] = np.where(act, np.log(fs[si]), st["lsig"])
    alp = np.exp(st["lalp"])
    ai = np.abs(alp[..., None] - fa).argmin(-1)
    st["lalp"] = np.where(act & (st["fam"] == FAM_SSS), np.log(fa[ai]), st["lalp"])
    return st


def refit_amplitudes(p, mask: SampleMask, st, dic: Dictionary):
    """Non-negative least-squares amplitudes for fixed atom shapes (in place; compiled per pixel:
    :func:`decomposition.kernels.atomlm.nnls_amplitudes`, 20 sweeps of exact coordinate descent on the
    convex problem over the fitted samples, from the current amplitudes); atoms left at zero
    are dropped.  A dictionary over a measured response solves its own atoms' amplitudes by the
    same code, over the response's table atoms."""
    check_mask(mask, p.shape)
    t = dic.t0_ps + dic.time_bin_ps * np.arange(p.shape[1])
    st["amp"] = nnls_amplitudes(dic.t0_ps, dic.time_bin_ps, p, mask.fit, st["fam"], st["amp"], st["delay"],
                                st["lsig"], st["lalp"], sweeps=20, inst=response_instrument(dic.response, t))
    drop_zero(st)
    return st
