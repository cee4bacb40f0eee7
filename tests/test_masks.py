import numpy as np
import pytest

from decomposition.kernels import atomlm
from decomposition.methods import convscd as cs
from decomposition import decompose
from decomposition.masks import SampleMask
from decomposition.model.slots import new_state, parameter_bounds


def test_masks_are_masks_and_never_both():
    fit = np.ones((2, 8), bool)
    cens = np.zeros((2, 8), bool)
    cens[0, 3] = True
    with pytest.raises(ValueError, match="both fitted and censored"):
        SampleMask(fit, cens)
    with pytest.raises(TypeError, match="boolean array"):
        SampleMask(fit.astype(float), cens)
    m = SampleMask(fit & ~cens, cens)
    p = np.linspace(-1.0, 1.0, 16).reshape(2, 8)
    r = m.residual(p, 0.5)
    assert r[0, 3] == 0.0                       # censored, model above the data: no misfit
    np.testing.assert_array_equal(r[1], p[1] - 0.5)
    assert m[1:].shape == (1, 8) and not m.uncensored().censored.any()


def test_a_real_valued_weight_is_refused_by_the_solver_with_a_clear_error(default_dictionary):
    """0.5 once meant "excluded" to the solver; now the solver takes masks and says so."""
    L, T = 128, 2.0
    p = np.zeros((2, L))
    w = np.full((2, L), 0.5)
    dic = default_dictionary(L, T)
    s = np.full(2, 0.01)
    for call in (lambda: cs.solve_block(p, w, s, dic),
                 lambda: cs.solve_multistart(p, w, s, dic),
                 lambda: cs.polish_block(p, w, new_state(2, 2), s, dic),
                 lambda: atomlm.lm_refine(T, T, p, w, new_state(2, 2), s, s, parameter_bounds(dic, 4.0), 3)):
        with pytest.raises(TypeError, match="SampleMask.*no per-sample weights"):
            call()


def test_real_weights_work_as_weights_in_the_refinement():
    """The stage that takes weights treats 0.5 as a weight: halving every weight changes nothing,
    down-weighting one sample moves the fit less than excluding it."""
    from core.model import empty_params, render_profile
    from decomposition.model.refine import refine

    L, T = 128, 2.0
    truth = empty_params((1,), 0)
    truth.update(direct_delay_ps=np.array([100.0]), direct_amplitude=np.array([1.0]),
                 direct_sigma_ps=np.array([3.0]))
    y = render_profile(truth, L, T)
    y[0, 52] += 0.3                                              # one bad sample at the peak's flank
    start = {k: v.copy() for k, v in truth.items()}
    start["direct_delay_ps"] = start["direct_delay_ps"] + 0.7
    ones = np.ones_like(y)
    a, _ = refine(y, start, time_bin_ps=T, weights=ones)
    b, _ = refine(y, start, time_bin_ps=T, weights=0.5 * ones)
    np.testing.assert_allclose(a["direct_delay_ps"], b["direct_delay_ps"], rtol=1e-9)
    half, zero = ones.copy(), ones.copy()
    half[0, 52], zero[0, 52] = 0.5, 0.0
    c, _ = refine(y, start, time_bin_ps=T, weights=half)
    d, _ = refine(y, start, time_bin_ps=T, weights=zero)
    err = [abs(x["direct_delay_ps"][0] - 100.0) for x in (a, c, d)]
    assert err[0] > err[1] > err[2]


def test_saturated_samples_are_censored_end_to_end():
    from decomposition.evaluation.synthetic import make_profiles

    y = make_profiles(6, 256, nsr=0.01, noise="white", seed=2).noisy
    level = 0.8 * np.abs(y).max(axis=1, keepdims=True)
    clipped = np.minimum(y, level)
    res = decompose(clipped, 2.0, saturation_level=float(level.min()))
    assert np.all(res.flags & 2)                               # SATURATED
    # a censored sample may sit under the model, never above it by more than the noise
    model = clipped - res.residual
    sat = clipped >= level.min()
    assert np.all(model[sat] >= clipped[sat] - 0.05 * level.max())
