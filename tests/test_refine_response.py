"""The variable-projection refinement over a measured response's atoms (decomposition.model.refine,
``irf=``): the Gaussian path's engine (decomposition.model.varpro, decomposition.kernels.projected)
rendering the response's table atoms instead of Gaussians.

Known answers: noise-free profiles rendered with the response's exact interpolant
(decomposition.model.atoms.params_profile) are fitted back to their parameters from perturbed starts;
an offset and zero-weight samples are handled as with the Gaussian PSF.
"""
import numpy as np
import pytest

from core.irf_models import tailed_response
from decomposition.model.atoms import params_profile
from decomposition.model.refine import refine

T = 2.0
L = 200
T_PS = T + T * np.arange(L)


@pytest.fixture(scope="module")
def irf():
    return tailed_response(4.0, 0.2, 30.0, time_step_ps=T)


def _scene(n, seed, onset_ps=(3.0, 8.0)):
    rng = np.random.default_rng(seed)
    nan = np.full(n, np.nan)
    d = rng.uniform(60, 120, n)
    truth = {"direct_delay_ps": d, "direct_amplitude": rng.uniform(0.5, 1.0, n), "direct_sigma_ps": nan.copy(),
             "sss_delay_ps": d + rng.uniform(*onset_ps, n), "sss_amplitude": rng.uniform(0.1, 0.4, n),
             "sss_sigma_ps": nan.copy(), "sss_alpha_per_ps": rng.uniform(0.02, 0.1, n),
             "ir_delay_ps": (d + rng.uniform(30, 60, n))[:, None], "ir_amplitude": rng.uniform(0.1, 0.3, (n, 1)),
             "ir_sigma_ps": np.full((n, 1), np.nan)}
    start = {k: v.copy() for k, v in truth.items()}
    start["direct_delay_ps"] = d + rng.normal(0, 0.5, n)
    start["sss_delay_ps"] = np.maximum(truth["sss_delay_ps"] + rng.normal(0, 0.5, n), start["direct_delay_ps"])
    start["ir_delay_ps"] = truth["ir_delay_ps"] + rng.normal(0, 0.5, (n, 1))
    start["sss_alpha_per_ps"] = truth["sss_alpha_per_ps"] * np.exp(rng.normal(0, 0.1, n))
    start["direct_amplitude"] = truth["direct_amplitude"] * 1.1
    return truth, start


def test_clean_profiles_are_fitted_back_to_their_parameters(irf):
    truth, start = _scene(24, 0)
    y = params_profile(irf, T_PS, truth)
    out, info = refine(y, start, time_bin_ps=T, irf=irf, max_iter=60, ftol=1e-15, sss_after_direct=True)
    assert info["refined"].all()
    for key, tol in (("direct_delay_ps", 1e-5), ("sss_delay_ps", 1e-4), ("ir_delay_ps", 1e-5),
                     ("sss_alpha_per_ps", 1e-6), ("direct_amplitude", 1e-6), ("sss_amplitude", 1e-5),
                     ("ir_amplitude", 1e-6)):
        np.testing.assert_allclose(out[key], truth[key], atol=tol, err_msg=key)
    # a response has no width: the width keys come back NaN
    for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"):
        assert np.isnan(out[key]).all()


def test_the_truth_is_the_fit_of_its_own_profile(irf):
    truth, _ = _scene(8, 1)
    y = params_profile(irf, T_PS, truth)
    out, info = refine(y, truth, time_bin_ps=T, irf=irf, max_iter=5)
    # the compiled table atoms are the exact interpolant's to the table's error
    assert np.all(info["rss_input"] < 1e-20 * np.sum(y * y, axis=-1))
    np.testing.assert_allclose(out["direct_delay_ps"], truth["direct_delay_ps"], atol=1e-9)


def test_an_offset_and_zero_weight_samples(irf):
    truth, start = _scene(12, 2)
    y = params_profile(irf, T_PS, truth) + 0.05
    w = np.ones_like(y)
    w[:, 150:160] = 0.0
    y[:, 150:160] = np.nan          # ignored where the weight is 0
    start["background"] = np.zeros(12)
    out, info = refine(y, start, time_bin_ps=T, irf=irf, weights=w, fit_background=True, max_iter=60, ftol=1e-15,
                       sss_after_direct=True)
    np.testing.assert_allclose(out["background"], 0.05, atol=1e-7)
    np.testing.assert_allclose(out["direct_delay_ps"], truth["direct_delay_ps"], atol=1e-5)


def test_held_onset_stays_and_the_rest_is_fitted_around_it(irf):
    truth, start = _scene(10, 3)
    y = params_profile(irf, T_PS, truth)
    out, _ = refine(y, start, time_bin_ps=T, irf=irf, max_iter=60, ftol=1e-15,
                    hold={"direct_delay_ps": truth["direct_delay_ps"]})
    assert np.array_equal(out["direct_delay_ps"], truth["direct_delay_ps"])
    np.testing.assert_allclose(out["ir_delay_ps"], truth["ir_delay_ps"], atol=1e-5)


def test_bad_combinations_are_refused(irf):
    truth, start = _scene(2, 4)
    y = params_profile(irf, T_PS, truth)
    with pytest.raises(ValueError, match="bin_integrated"):
        refine(y, start, time_bin_ps=T, irf=irf, bin_integrated=True)
    with pytest.raises(ValueError, match="sigma_ps"):
        refine(y, start, time_bin_ps=T, irf=irf, hold={"sigma_ps": 3.0})
