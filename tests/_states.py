"""Slot states polished by the solver's LM, shared by the tests of the steps after the search."""
import numpy as np


def solver_setup(n_bins, time_bin_ps=2.0, components="drs"):
    """(dictionary, resolved SolverOptions) of the default solver for ``n_bins`` bins, on the
    time axis of :func:`core.model.render_profile` (:func:`core.model.time_axis_ps`)."""
    from core.model import time_axis_ps
    from decomposition.methods.dictionary import get_dictionary
    from decomposition.options import GridSpec, SolverOptions

    opts = SolverOptions().resolved(components)
    t0_ps = float(time_axis_ps(n_bins, time_bin_ps)[0])
    return get_dictionary(n_bins, time_bin_ps, t0_ps, GridSpec(), True, True), opts


def polished(y, st, dic, opts, noise=1e-3):
    """The state's amplitudes solved (NNLS) and all its atoms polished by the solver's LM."""
    from decomposition.masks import SampleMask
    from decomposition.methods.polish import refit_amplitudes
    from decomposition.model.slots import parameter_bounds, refine_atoms

    n, L = y.shape
    mask = SampleMask.all_fitted(y.shape)
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    refit_amplitudes(y, mask, st, dic)
    st, _, _ = refine_atoms(t, y, mask, st, np.zeros(n), np.full(n, opts.eps_rel * noise),
                            parameter_bounds(dic, opts.bound_factor), opts.n_polish, None, True, True, opts.lm_tol)
    return st
