"""The response dictionary: its atoms are the exact shifted and sss atoms; correlation and detection."""
import numpy as np
import pytest

from core.irf import render_shifted, render_sss
from core.irf_models import gaussian_response, tailed_response
from core.model import gaussian_kernel
from decomposition.response.dictionary import FAM_SHIFTED, FAM_SSS, ResponseDictionary

T, L, T0 = 2.0, 160, 2.0
AXIS = T0 + T * np.arange(L)
IRF = tailed_response(4.0, 0.25, 20.0, time_step_ps=T)


@pytest.fixture(scope="module")
def dic():
    return ResponseDictionary(IRF, L, T, T0, phases=4, alphas_per_ps=(0.01, 0.05))


def test_atoms_are_the_exact_shifted_and_sss_atoms(dic):
    assert dic.fam.tolist() == [FAM_SHIFTED] * 4 + [FAM_SSS] * 8
    for a in (0, 1, 3, 5, 11):
        for j in (-dic.pre, -3, 0, 57, L - 1):
            d = dic.delay_ps(a, j)
            ref = render_shifted(IRF, AXIS, d) if dic.fam[a] == FAM_SHIFTED \
                else render_sss(IRF, AXIS, d, dic.alpha_per_ps[a])
            np.testing.assert_allclose(dic.atom(a, j), ref, rtol=0, atol=1e-12)
            assert dic.norm2[a, j + dic.pre] == pytest.approx(np.sum(ref ** 2), rel=1e-12, abs=1e-15)
    # With the Gaussian as its response, the shifted kernels are the Gaussian dictionary's atoms.
    g = ResponseDictionary(gaussian_response(4.0, time_step_ps=T), L, T, T0, phases=2)
    np.testing.assert_allclose(g.atom(1, 30), gaussian_kernel(AXIS - (T0 + 30.5 * T), 4.0), atol=1e-8)


def test_correlate_is_the_inner_product_with_every_atom(dic):
    x = np.random.default_rng(0).standard_normal((3, L))
    c = dic.correlate(x)
    assert c.shape == (3, dic.fam.size, dic.shifts.size)
    for a, j in ((0, 10), (2, -dic.pre), (7, 100), (11, L - 1)):
        np.testing.assert_allclose(c[:, a, j + dic.pre], x @ dic.atom(a, j), rtol=1e-10, atol=1e-10)


def test_best_atom_finds_sub_bin_delays_and_the_family(dic):
    d = T0 + T * np.array([40.0, 40.25, 40.5, 93.75])
    direct = 3.0 * render_shifted(IRF, AXIS, d)
    a, j, delay, amp = dic.best_atoms(direct)
    np.testing.assert_allclose(delay, d, atol=1e-9)
    np.testing.assert_allclose(amp, 3.0, rtol=1e-9)
    assert np.all(dic.fam[a] == FAM_SHIFTED)
    sss = 0.5 * render_sss(IRF, AXIS, d[:2], np.array([0.05, 0.01]))
    a, j, delay, amp = dic.best_atoms(sss)
    assert np.all(dic.fam[a] == FAM_SSS)
    np.testing.assert_allclose(dic.alpha_per_ps[a], [0.05, 0.01])
    np.testing.assert_allclose(delay, d[:2], atol=1e-9)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="phases"):
        ResponseDictionary(IRF, L, T, T0, phases=0)
    with pytest.raises(ValueError, match="no component family"):
        ResponseDictionary(IRF, L, T, T0, shifted=False)
    with pytest.raises(ValueError, match="alphas_per_ps"):
        ResponseDictionary(IRF, L, T, T0, alphas_per_ps=[-1.0])
    with pytest.raises(ValueError, match="shape"):
        ResponseDictionary(IRF, L, T, T0).correlate(np.zeros((2, L + 1)))
