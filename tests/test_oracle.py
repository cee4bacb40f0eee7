"""The oracle: the true component set fitted from the truth reaches what the data allow."""
import numpy as np
import pytest

from decomposition.model.fidelity import fidelity
from decomposition.evaluation.oracle import OracleOptions, oracle_fit, significant_truth
from decomposition.evaluation.synthetic import make_profiles


@pytest.mark.parametrize("T, bin_integrated", [(2.0, True), (4.0, False)])
def test_oracle_is_near_perfect_on_noiseless_scenes(T, bin_integrated):
    d = make_profiles(30, 512, seed=7, time_bin_ps=T, ranges="paper", bin_integrated=bin_integrated)
    o = oracle_fit(d.noisy, d.params, time_bin_ps=T, bin_integrated=bin_integrated)
    f = fidelity(d.components, o)
    assert f.min() > 0.9999
    # Started a little away from the truth it walks back to it, except where a direct and an sss
    # with nearly the same onset are all but indistinguishable even without noise.
    start = {k: v.copy() for k, v in d.params.items()}
    start["direct_delay_ps"] += 0.3
    start["sss_alpha_per_ps"] *= 1.1
    o = oracle_fit(d.noisy, start, time_bin_ps=T, bin_integrated=bin_integrated)
    f = fidelity(d.components, o)
    assert np.median(f) > 0.9999 and f.mean() > 0.995
    close = f > 0.9999
    np.testing.assert_allclose(o.params["direct_delay_ps"][close], d.params["direct_delay_ps"][close], atol=0.01)
    # The component set is the true one.
    for key in ("direct_delay_ps", "sss_delay_ps", "ir_delay_ps"):
        np.testing.assert_array_equal(np.isfinite(o.params[key]), np.isfinite(d.params[key]))


def test_oracle_under_noise_is_close_to_but_below_one():
    d = make_profiles(60, 512, nsr=0.055, seed=8, ranges="paper", bin_integrated=True)
    o = oracle_fit(d.noisy, d.params, bin_integrated=True)
    f = fidelity(d.components, o)
    assert 0.9 < f.mean() < 0.999
    # The fit lowers the residual below that of the truth itself (it fits the noise a little).
    assert np.all(o.info["rss"] <= o.info["rss_input"] * (1 + 1e-9))


def test_oracle_options_are_validated():
    with pytest.raises(ValueError, match="max_iter"):
        OracleOptions(max_iter=0)
    with pytest.raises(ValueError, match="ftol"):
        OracleOptions(ftol=0.0)


def test_significant_truth_drops_what_the_noise_hides_and_keeps_the_order():
    d = make_profiles(60, 512, seed=9, ranges="paper", bin_integrated=True, kinds=("c",))   # d+s+r2+r3
    ir_e = np.sum(d.components["interreflections"] ** 2, axis=-1)                          # (60, 2)
    s_e = np.sum(d.components["sss"] ** 2, axis=-1)
    # a noise level between the two inter-reflections' energies of every pixel: the weaker one hides
    lo, hi = ir_e.min(axis=1), ir_e.max(axis=1)
    sigma = np.sqrt(np.sqrt(lo * hi) / 25.0)
    seen = significant_truth(d.params, d.components, sigma)
    np.testing.assert_array_equal(seen["direct_delay_ps"], d.params["direct_delay_ps"])
    weak_first = ir_e[:, 0] < ir_e[:, 1]
    assert weak_first.any() and (~weak_first).any()
    # one inter-reflection left, moved to the front, with its own parameters
    np.testing.assert_array_equal(np.isfinite(seen["ir_delay_ps"]), [[True, False]] * 60)
    kept = np.where(weak_first, 1, 0)
    for k in ("ir_delay_ps", "ir_amplitude", "ir_sigma_ps"):
        np.testing.assert_array_equal(seen[k][:, 0], d.params[k][np.arange(60), kept])
    # the sss hides where its energy is below 25 sigma^2
    np.testing.assert_array_equal(np.isfinite(seen["sss_delay_ps"]), s_e >= 25.0 * sigma ** 2)
    # no noise: nothing hides; the input is not modified
    same = significant_truth(d.params, d.components, np.zeros(60))
    for k, v in d.params.items():
        np.testing.assert_array_equal(same[k], v)
    with pytest.raises(ValueError, match="significance_chi2"):
        significant_truth(d.params, d.components, sigma, significance_chi2=-1.0)
    with pytest.raises(ValueError, match="noise_sigma"):
        significant_truth(d.params, d.components, np.full(60, np.nan))


def test_significant_truth_reads_each_sample_in_its_own_variance():
    # photon counts: the same echo is visible on a dark baseline and hidden under a bright sss
    d = make_profiles(40, 256, seed=4, kinds="d+s+r2", photons_per_pixel=300.0)
    comps = d.components
    var = np.maximum(np.asarray(d.clean, np.float64), 0.0)                 # Poisson: variance = mean
    seen = significant_truth(d.params, comps, np.sqrt(var))
    # against a hand computation of each component's chi2 (sum of c^2 / var over its samples)
    with np.errstate(divide="ignore", invalid="ignore"):
        ir_chi2 = np.nansum(np.where(var[:, None, :] > 0, comps["interreflections"] ** 2 / var[:, None, :], 0.0),
                            axis=-1)
        s_chi2 = np.nansum(np.where(var > 0, comps["sss"] ** 2 / var, 0.0), axis=-1)
    has_ir = np.isfinite(d.params["ir_delay_ps"])
    n_kept = ((ir_chi2 >= 25.0) & has_ir).sum(axis=1)
    np.testing.assert_array_equal(np.isfinite(seen["ir_delay_ps"]).sum(axis=1), n_kept)
    np.testing.assert_array_equal(np.isfinite(seen["sss_delay_ps"]), np.isfinite(d.params["sss_delay_ps"]) & (s_chi2 >= 25.0))
    assert 0 < n_kept.sum() < has_ir.sum()                     # some echoes hide at 300 photons, some not
    # a sample of no variance: a component there is infinitely significant, zero there adds nothing
    one = {"direct": np.zeros((1, 4)), "sss": np.array([[0.0, 1e-9, 0.0, 0.0]]),
           "interreflections": np.zeros((1, 1, 4))}
    p1 = {"direct_delay_ps": np.array([1.0]), "sss_delay_ps": np.array([2.0]), "ir_delay_ps": np.array([[3.0]])}
    out = significant_truth(p1, one, np.array([[1.0, 0.0, 1.0, 1.0]]))
    assert np.isfinite(out["sss_delay_ps"][0]) and np.isnan(out["ir_delay_ps"][0, 0])
    # a scalar noise is every pixel's; a shape of neither kind is refused
    np.testing.assert_array_equal(significant_truth(d.params, comps, 0.0)["ir_delay_ps"], d.params["ir_delay_ps"])
    with pytest.raises(ValueError, match="pixels' shape"):
        significant_truth(d.params, comps, np.ones(7))
