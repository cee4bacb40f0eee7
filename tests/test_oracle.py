"""The oracle: the true component set fitted from the truth reaches what the data allow."""
import numpy as np
import pytest

from decomposition.metrics import fidelity
from decomposition.oracle import OracleOptions, oracle_fit
from decomposition.synthetic import make_profiles


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
