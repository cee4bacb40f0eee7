"""The ``count_polish`` stage of :func:`decomposition.decompose` for count data: the atoms polished with Poisson weights.

Photon counts have a variance equal to their expected value, so the least-squares fit that
matches their statistics weighs each sample by 1 / its model count.  Detection and search fit
the atoms unweighted; for count data (``noise="poisson"``) this stage polishes every live
pixel's atoms once more with the solver's compiled Levenberg-Marquardt on the data term alone
(as the detection's own polish, :func:`decomposition.methods.polish.polish_block`), with the weights

    w_i = 1 / max(model_i, POISSON_VARIANCE_FLOOR)          (counts; times dispersion^-2)

of the current model (plus the background family's estimate, where it is fitted),
POISSON_REFITS times, each from the previous polish's model: iteratively
reweighted least squares, whose fixed point is the Poisson maximum-likelihood fit.  A pixel
keeps a polish only where it lowers the Poisson deviance below the state it started from: the
weights of a model that lacks a component -- 1 / the variance floor where a missed tail holds
counts -- can otherwise pull an atom tens of ps from the light it fits.  A pixel that kept its
state is not polished again (the next polish would start from the same state with the same
weights and end where this one did; 14 % of the pixels at 100 photons).  The weights
are rescaled by the pixel's (noise / peak)^2 so that the objective keeps the solver's units; the
scale of the weights does not move the optimum.  Work is on blocks of ``opts.block_size`` pixels.
"""
from __future__ import annotations

import numpy as np

from ..constants import POISSON_REFITS
from .detect import Detection, solver_inputs
from ..noise import count_deviance, poisson_weights
from ..options import SolverOptions
from .prepare import Samples
from ..model.slots import drop_zero, parameter_bounds, put, refine_atoms, render, take

__all__ = ["count_weights", "polish_count_state", "polish_counts"]


def count_weights(model, used, scale, noise, dispersion=None, background=None) -> np.ndarray:
    """(n, L) solver weights of count profiles for a model in the solver's units (unit peak).

    Parameters
    ----------
    model : ndarray (n, L)        model of the normalised profiles (counts / scale)
    used : ndarray (n, L) bool    samples that count (fitted or censored)
    scale : ndarray (n,)          counts per unit of the normalised profiles
    noise : ndarray (n,)          the solver's noise of each pixel, normalised units
    dispersion : ndarray (n,), optional
        Noise scale of the counts (1: the Poisson law).
    background : ndarray (n,), optional
        Counts subtracted before the normalisation (the background family's estimate): part
        of every sample's expected count, so of its variance.

    Returns
    -------
    ndarray (n, L): (scale * noise)^2 / variance of the counts; 0 where not ``used``.
    """
    counts = model * scale[:, None]
    if background is not None:
        counts = counts + background[:, None]
    w = poisson_weights(counts, used, dispersion)
    return w * np.square(scale * noise)[:, None]


def polish_count_state(t, p, mask, st, scale, noise, dispersion, background, bounds, opts: SolverOptions,
                       response=None) -> dict:
    """One block's slot state ``st`` (n, K) polished with Poisson weights, POISSON_REFITS times
    from its own model (see the module docstring); atoms whose amplitude ends non-positive
    are dropped.

    Parameters
    ----------
    t : ndarray (L,)              time axis, ps
    p, mask                       normalised profiles (n, L) and their SampleMask
    st : dict                     slot state (n, K), normalised units (not modified)
    scale, noise : ndarray (n,)   counts per normalised unit; the solver's noise
    dispersion, background : ndarray (n,) or None
    bounds : dict                 :func:`decomposition.model.slots.parameter_bounds`
    response : InstrumentResponse or None
                                  the atoms are a measured response's (None: the Gaussian PSF's)
    """
    best = {k: v.copy() for k, v in st.items()}
    mu = np.zeros(p.shape[0])
    eps = opts.eps_rel * noise
    bg = 0.0 if background is None else background[:, None]
    counts = p * scale[:, None] + bg

    def deviance(m, rows):
        """The Poisson deviance of the pixels ``rows`` for their model ``m`` (normalised)."""
        b = 0.0 if background is None else background[rows, None]
        return count_deviance(counts[rows], m * scale[rows, None] + b, mask.fit[rows],
                              None if dispersion is None else dispersion[rows])

    todo = np.arange(p.shape[0])
    model = render(t, best, response)
    dev_best = deviance(model, todo)
    for _ in range(POISSON_REFITS):
        if todo.size == 0:
            break
        sub = mask[todo]
        sc = scale[todo]
        disp = None if dispersion is None else dispersion[todo]
        bgs = None if background is None else background[todo]
        w = count_weights(model[todo], sub.used, sc, noise[todo], disp, bgs)
        start = take(best, todo)
        st, _, _, new = refine_atoms(t, p[todo], sub, start, mu[todo], eps[todo], bounds, opts.n_polish, None,
                                     opts.shared_sigma, opts.sss_after_direct, opts.lm_tol, return_model=True,
                                     weights=w, response=response)
        # the Poisson deviance, the fit's own objective, decides: the weights of a model that
        # lacks a component (1 / the floor where a missed tail holds counts) can pull an atom
        # far from the light it fits
        dev = deviance(new, todo)
        better = dev < dev_best[todo]
        rows = todo[better]
        put(best, rows, take(st, np.flatnonzero(better)))
        model[rows] = new[better]
        dev_best[rows] = dev[better]
        # a pixel that kept its state would start the next refit where this one did, with the
        # same weights, and end where this one ended: only the others are refitted
        todo = rows
    drop_zero(best)
    return best


def polish_counts(samples: Samples, det: Detection, dic, opts: SolverOptions) -> dict:
    """The slot state of ``det`` polished with Poisson weights (see the module docstring)."""
    state = {k: v.copy() for k, v in det.state.items()}
    live = samples.live
    if samples.noise_model != "poisson" or live.size == 0:
        return state
    t = dic.t0_ps + dic.time_bin_ps * np.arange(samples.n_bins)
    bounds = parameter_bounds(dic, opts.bound_factor)
    for b0 in range(0, live.size, opts.block_size):
        rows = np.arange(b0, min(b0 + opts.block_size, live.size))
        px = live[rows]
        p, mask = solver_inputs(samples, px)
        dispersion = None if samples.dispersion is None else samples.dispersion[px]
        background = None if samples.background is None else samples.background[px]
        st = polish_count_state(t, p, mask, take(state, rows), samples.scale[px], det.noise_eff[px], dispersion,
                                background, bounds, opts, dic.response)
        put(state, rows, st)
    return state
