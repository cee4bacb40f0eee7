"""The forward step: a Gaussian where the fit leaves a resolved residual bump."""
import numpy as np

from core.model import empty_params, render_profile
from decomposition.constants import FAM_GAUSS, FAM_SSS
from decomposition.masks import SampleMask
from decomposition.slots import new_state

from _states import polished, solver_setup


def _truth(n):
    """A direct, an sss two widths later, an inter-reflection 4.5 widths after the direct at
    0.65 of it and a second one at 9 widths."""
    truth = empty_params((n,), n_ir=2)
    truth["direct_delay_ps"][:] = 30.0 + 40.0 * np.arange(n)
    truth["direct_amplitude"][:] = 1.0
    truth["direct_sigma_ps"][:] = 6.0
    truth["sss_delay_ps"][:] = truth["direct_delay_ps"] + 12.0
    truth["sss_amplitude"][:] = 0.2
    truth["sss_alpha_per_ps"][:] = 0.03
    truth["sss_sigma_ps"][:] = 6.0
    truth["ir_delay_ps"][:, 0] = truth["direct_delay_ps"] + 27.0
    truth["ir_delay_ps"][:, 1] = truth["direct_delay_ps"] + 54.0
    truth["ir_amplitude"][:] = [0.65, 0.7]
    truth["ir_sigma_ps"][:] = 6.0
    return truth


def _state(truth, n, irs, K=5):
    st = new_state(n, K)
    st["fam"][:, 0] = FAM_GAUSS
    st["delay"][:, 0] = truth["direct_delay_ps"]
    st["fam"][:, 1] = FAM_SSS
    st["delay"][:, 1] = truth["sss_delay_ps"]
    st["lalp"][:, 1] = np.log(truth["sss_alpha_per_ps"])
    for j, k in enumerate(irs):
        st["fam"][:, 2 + j] = FAM_GAUSS
        st["delay"][:, 2 + j] = truth["ir_delay_ps"][:, k]
    st["lsig"][:] = np.log(6.0)
    st["amp"][:] = 1.0
    st["pen"][:] = 1.0
    return st


def test_grow_adds_the_missing_inter_reflection():
    from decomposition.grow import grow_block

    n, L, T = 5, 512, 2.0
    truth = _truth(n)
    y = render_profile(truth, L, T) + np.random.default_rng(0).normal(0, 1e-3, (n, L))
    dic, opts = solver_setup(L, T)
    st = polished(y, _state(truth, n, irs=[1]), dic, opts)       # the first one missing
    out, grown = grow_block(y, SampleMask.all_fitted(y.shape), st, np.full(n, 1e-3), dic, opts)
    assert grown.all()
    d = np.sort(np.where(out["fam"] == FAM_GAUSS, out["delay"], np.nan), axis=1)[:, :3]
    np.testing.assert_allclose(d[:, 1], truth["ir_delay_ps"][:, 0], atol=1.0)
    np.testing.assert_allclose(d[:, 0], truth["direct_delay_ps"], atol=0.5)


def test_grow_leaves_a_fit_at_the_noise_alone():
    from decomposition.grow import grow_block

    n, L, T = 5, 512, 2.0
    truth = _truth(n)
    y = render_profile(truth, L, T) + np.random.default_rng(1).normal(0, 1e-3, (n, L))
    dic, opts = solver_setup(L, T)
    st = polished(y, _state(truth, n, irs=[0, 1]), dic, opts)
    out, grown = grow_block(y, SampleMask.all_fitted(y.shape), st, np.full(n, 1e-3), dic, opts)
    assert not grown.any()
    for k in st:
        np.testing.assert_array_equal(out[k], st[k])


def test_min_gaussian_gap_is_in_widths():
    from decomposition.grow import min_gaussian_gap_sigma

    st = new_state(3, 4)
    st["fam"][:, :3] = [[FAM_GAUSS, FAM_SSS, FAM_GAUSS], [FAM_GAUSS, FAM_GAUSS, FAM_GAUSS], [FAM_GAUSS, 0, 0]]
    st["delay"][:, :3] = [[10.0, 12.0, 40.0], [10.0, 25.0, 16.0], [10.0, 0.0, 0.0]]
    st["lsig"][:] = np.log(3.0)
    np.testing.assert_allclose(min_gaussian_gap_sigma(st), [10.0, 2.0, np.inf])
