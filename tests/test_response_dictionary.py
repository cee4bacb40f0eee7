"""ConvSCD's dictionary and detection over a measured response (methods/dictionary.py with
``response=``, model/slots.refine_penalised, stages/detect.detect_components(polish=False))."""
import numpy as np
import pytest

from core.irf import render_shifted, render_sss
from core.irf_components import gaussian_equivalent_sigma_ps
from core.irf_models import tailed_response
from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from decomposition.masks import SampleMask
from decomposition.methods import convscd as cs
from decomposition.methods.dictionary import Dictionary
from decomposition.model.slots import refine_penalised
from decomposition.options import GridSpec

T, L, T0 = 2.0, 160, 2.0
AXIS = T0 + T * np.arange(L)
IRF = tailed_response(4.0, 0.25, 20.0, time_step_ps=T)


@pytest.fixture(scope="module")
def dic():
    return Dictionary(L, T, T0, GridSpec(coarse_alpha=2, alpha_range_per_ps=(0.01, 0.05)), True, True, response=IRF)


def _atom(dic, a, j):
    d = np.array([T0 + j * T])
    ref = (render_shifted(IRF, AXIS, d) if dic.fam[a] == FAM_GAUSS
           else render_sss(IRF, AXIS, d, np.array([dic.alpha_per_ps[a]])))[0]
    return ref / dic.peak[a]


def test_kernels_are_the_response_and_its_sss_atoms(dic):
    assert dic.fam.tolist() == [FAM_GAUSS, FAM_SSS, FAM_SSS] and dic.response is IRF
    np.testing.assert_allclose(dic.alpha_per_ps[1:], [0.01, 0.05])
    np.testing.assert_allclose(dic.sigma_ps, gaussian_equivalent_sigma_ps(IRF))
    assert dic.peak[0] == pytest.approx(1.0, abs=1e-12)      # the response's peak at the delay
    x = np.random.default_rng(0).standard_normal((3, L))
    c = dic.correlate(x)
    for a in range(3):
        for j in (-dic.pre, -3, 0, 57, L - 1):
            ref = _atom(dic, a, j)
            np.testing.assert_allclose(c[:, a, j + dic.pre], x @ ref, rtol=1e-10, atol=1e-10)
            assert dic.norm2[a, j + dic.pre] == pytest.approx(np.sum(ref ** 2), rel=1e-10, abs=1e-14)


def test_the_penalised_refinement_never_raises_the_objective(dic):
    """From a start 3 ps off, the refinement lands on the true delay where F falls; a start
    given an ``obj`` below what any fit reaches keeps the state it was given."""
    y = 2.0 * render_shifted(IRF, AXIS, np.array([61.0]))[0] + 0.7 * render_sss(IRF, AXIS, np.array([61.0]),
                                                                               np.array([0.03]))[0]
    p = np.vstack([y, y])
    st = {"fam": np.array([[FAM_GAUSS, FAM_SSS]] * 2, np.int8), "delay": np.array([[64.0, 64.0]] * 2),
          "lalp": np.log(np.array([[1.0, 0.02]] * 2)), "amp": np.array([[1.5, 0.5]] * 2),
          "lsig": np.zeros((2, 2)), "pen": np.ones((2, 2))}
    mask = SampleMask(np.ones(p.shape, bool), np.zeros(p.shape, bool))
    mu, eps = np.full(2, 1e-6), np.full(2, 1e-3)
    out, f, _, model = refine_penalised(IRF, AXIS, p, mask, st, mu, eps, {"delay": (-30.0, 400.0),
                                        "lalp": (np.log(1e-3), 0.0)}, 30, np.array([np.inf, -1.0]),
                                        sss_after_direct=True)
    np.testing.assert_allclose(out["delay"][0], [61.0, 61.0], atol=1e-3)
    np.testing.assert_allclose(out["amp"][0], [2.0, 0.7], rtol=1e-3)
    np.testing.assert_allclose(model[0], y, atol=1e-5)
    assert f[1] == -1.0 and np.array_equal(out["delay"][1], st["delay"][1])     # nothing beat it


def test_convscd_over_the_response_finds_a_direct_and_its_sss(dic):
    rng = np.random.default_rng(3)
    d_ps = np.array([41.3, 80.6, 120.2])
    y = render_shifted(IRF, AXIS, d_ps) + 0.3 * render_sss(IRF, AXIS, d_ps, np.full(3, 0.03))     # onset at the direct
    noise = 0.005
    y = y / y.max(axis=1, keepdims=True) + noise * rng.standard_normal(y.shape)
    mask = SampleMask(np.ones(y.shape, bool), np.zeros(y.shape, bool))
    st, info = cs.solve_multistart(y, mask, np.full(3, noise), dic, max_components=4, max_gauss=1, max_iter=6, n_lm=10)
    assert np.all(info["converged"])
    assert np.all((st["fam"] == FAM_GAUSS).sum(axis=1) == 1) and np.all((st["fam"] == FAM_SSS).sum(axis=1) == 1)
    direct = np.where(st["fam"] == FAM_GAUSS, st["delay"], 0.0).sum(axis=1)
    onset = np.where(st["fam"] == FAM_SSS, st["delay"], 0.0).sum(axis=1)
    np.testing.assert_allclose(direct, d_ps, atol=0.3)
    np.testing.assert_allclose(onset, d_ps, atol=0.5)
    hist = info["objective"]
    diffs = np.diff(hist, axis=1)
    assert np.all(diffs[np.isfinite(diffs)] <= 1e-12)     # monotone
    assert np.all(st["fam"][st["amp"] <= 0] == FAM_NONE)


def test_families_left_out_are_not_built():
    grid = GridSpec(coarse_alpha=3)
    only_s = Dictionary(L, T, T0, grid, False, True, response=IRF)
    assert only_s.fam.tolist() == [FAM_SSS] * 3 and only_s.norm2.shape == (3, only_s.shifts.size)
    only_d = Dictionary(L, T, T0, grid, True, False, response=IRF)
    assert only_d.fam.tolist() == [FAM_GAUSS] and np.all(np.isnan(only_d.alpha_per_ps))
    with pytest.raises(ValueError, match="no component family selected"):
        Dictionary(L, T, T0, grid, False, False, response=IRF)


def test_a_state_with_the_onset_before_its_direct_takes_the_fit():
    """A detected state whose sss onset lies before a shifted atom picked after it breaks
    ``sss_after_direct``: the refinement's answer, the onset moved to the direct, is taken even
    where its objective is above the given one; without the rule the state is kept."""
    y = 2.0 * render_shifted(IRF, AXIS, np.array([61.0]))[0] + 0.7 * render_sss(IRF, AXIS, np.array([61.0]),
                                                                               np.array([0.03]))[0]
    st = {"fam": np.array([[FAM_GAUSS, FAM_SSS]], np.int8), "delay": np.array([[61.0, 40.0]]),
          "lalp": np.log(np.array([[1.0, 0.03]])), "amp": np.array([[2.0, 0.7]]), "lsig": np.zeros((1, 2)),
          "pen": np.ones((1, 2))}
    mask = SampleMask(np.ones((1, L), bool), np.zeros((1, L), bool))
    args = (IRF, AXIS, y[None], mask, st, np.full(1, 1e-6), np.full(1, 1e-3),
            {"delay": (-30.0, 400.0), "lalp": (np.log(1e-3), 0.0)}, 10, np.array([-1.0]))
    out, f, _, _ = refine_penalised(*args, sss_after_direct=True)
    assert out["delay"][0, 1] >= out["delay"][0, 0] and f[0] > -1.0
    kept, f_kept, _, _ = refine_penalised(*args, sss_after_direct=False)
    assert kept["delay"][0, 1] == 40.0 and f_kept[0] == -1.0
