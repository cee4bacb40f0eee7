"""Detection with a measured response: ConvSCD over the response's dictionary.

The Gaussian PSF's detection (:mod:`decomposition.stages.detect`) and this one run the same
sparse coding, :func:`decomposition.methods.convscd.solve_multistart`: Gauss-Southwell picks
over a coarse convolutional dictionary with the paper's log-sum penalty, the first atom a
shifted copy by largest coefficient, every pick followed by a short refinement of the pixel's
atoms, and the unrestricted start where the first leaves the data term above its noise.  Here
the dictionary's kernels are the response and the response convolved with the sss exponential
at the coarse alphas (:class:`decomposition.methods.dictionary.Dictionary` with ``response=``),
and the refinement fits the response's table atoms
(:func:`decomposition.model.slots.refine_penalised`).  What follows -- the labels, the
refinement with the offset, the forward steps -- is the response path's
(:mod:`decomposition.response.path`).
"""
from __future__ import annotations

import numpy as np

from ..constants import FAM_NONE, FAM_SSS
from ..kernels.pickcorr import PickWorkspace
from ..methods import convscd as cs
from ..methods.dictionary import Dictionary, get_dictionary
from ..options import GridSpec, SolverOptions
from ..stages.detect import Detection, solver_inputs, solver_options
from ..stages.prepare import Samples

__all__ = ["detect_response", "response_dictionary"]


def response_dictionary(irf, samples: Samples, grid: GridSpec, components) -> Dictionary:
    """The coarse dictionary of ``irf`` on the samples' axis (families as ``components``)."""
    ax = samples.axis
    return get_dictionary(samples.n_bins, ax.time_bin_ps, ax.t0_ps, grid, "d" in components, "s" in components,
                          response=irf)


def detect_response(samples: Samples, dic: Dictionary, opts: SolverOptions, components) -> Detection:
    """ConvSCD's detection for every live pixel, ``opts.block_size`` at a time: the
    :class:`~decomposition.stages.detect.Detection` the stages over the slot state read (the
    search), its slots' delays and log alphas NaN where a slot is empty or not an sss."""
    live = samples.live
    n, K = live.size, opts.max_components
    st = {"fam": np.zeros((n, K), np.int8), "delay": np.full((n, K), np.nan), "lsig": np.zeros((n, K)),
          "lalp": np.full((n, K), np.nan), "amp": np.zeros((n, K)), "pen": np.ones((n, K))}
    P = samples.values.shape[0]
    hist = np.full((P, opts.max_iter + 1), np.nan)
    n_iter = np.zeros(P, np.int64)
    conv = np.zeros(n, bool)
    lm_total = 0
    solve_opts = solver_options(opts, components, PickWorkspace())
    restarted = 0
    for lo in range(0, n, opts.block_size):
        rows = live[lo:lo + opts.block_size]
        p, mask = solver_inputs(samples, rows)
        got, info = cs.solve_multistart(p, mask.uncensored(), samples.noise_eff[rows], dic, sss_alone=opts.sss_alone,
                                        restart=opts.multistart, **solve_opts)
        fam = got["fam"]
        sl = slice(lo, lo + rows.size)
        st["fam"][sl] = fam
        st["delay"][sl] = np.where(fam != FAM_NONE, got["delay"], np.nan)
        st["lalp"][sl] = np.where(fam == FAM_SSS, got["lalp"], np.nan)
        st["amp"][sl] = np.where(fam != FAM_NONE, got["amp"], 0.0)
        st["lsig"][sl] = got["lsig"]
        st["pen"][sl] = got["pen"]
        hist[rows] = info["objective"]
        n_iter[rows] = info["n_iter"]
        conv[sl] = info["converged"]
        lm_total += info["lm_iterations"]
        restarted += int(info["restarted"])
    return Detection(state=st, converged=conv, objective=hist, n_iter=n_iter, noise_eff=samples.noise_eff,
                     lm_iterations=lm_total, restarted=restarted)
