"""Structured alternative starts: physics relabelling and recovery of the sss-absorbs-direct split."""
import numpy as np
import pytest

from decomposition.metrics import fidelity
from core.model import empty_params, render_components, render_profile
from decomposition.search import STARTS, SearchOptions, relabel, structured_search


def test_relabel_puts_the_earliest_gaussian_first_and_no_sss_before_it():
    p = empty_params((2,), n_ir=2)
    p["direct_delay_ps"][:] = [80.0, 50.0]
    p["direct_amplitude"][:] = [0.3, 1.0]
    p["direct_sigma_ps"][:] = 3.0
    p["ir_delay_ps"][:] = [[60.0, 120.0], [90.0, np.nan]]
    p["ir_amplitude"][:] = [[0.9, 0.2], [0.4, np.nan]]
    p["ir_sigma_ps"][:] = [[3.0, 3.0], [3.0, np.nan]]
    p["sss_delay_ps"][:] = [55.0, 52.0]
    p["sss_amplitude"][:] = 0.01
    p["sss_alpha_per_ps"][:] = 0.03
    p["sss_sigma_ps"][:] = 3.0
    r = relabel(p)
    np.testing.assert_array_equal(r["direct_delay_ps"], [60.0, 50.0])
    np.testing.assert_array_equal(r["direct_amplitude"], [0.9, 1.0])
    np.testing.assert_array_equal(r["ir_delay_ps"], [[80.0, 120.0], [90.0, np.nan]])
    np.testing.assert_array_equal(r["sss_delay_ps"], [60.0, 52.0])  # onset moved to the new direct
    # The rendered total is unchanged by relabelling (only the sss onset moved, in pixel 0).
    np.testing.assert_allclose(render_profile(relabel(r), 256), render_profile(r, 256))


def test_search_recovers_a_direct_absorbed_by_the_sss():
    # d + s with the sss peak twice the direct's and its onset one sigma after it.
    n, L, T = 4, 256, 2.0
    truth = empty_params((n,), n_ir=2)
    truth["direct_delay_ps"][:] = [100.0, 120.0, 90.0, 150.0]
    truth["direct_amplitude"][:] = 1.0
    truth["direct_sigma_ps"][:] = [4.0, 5.0, 3.0, 6.0]
    truth["sss_delay_ps"][:] = truth["direct_delay_ps"] + truth["direct_sigma_ps"]
    truth["sss_amplitude"][:] = 2.0 * 0.03 / 0.6  # roughly twice the direct peak
    truth["sss_alpha_per_ps"][:] = 0.03
    truth["sss_sigma_ps"][:] = truth["direct_sigma_ps"]
    y = render_profile(truth, L, T) + np.random.default_rng(0).normal(0, 1e-3, (n, L))
    # The typical wrong split: the sss starts before the true direct, a "direct" on its hump.
    wrong = {k: v.copy() for k, v in truth.items()}
    wrong["sss_delay_ps"] = truth["direct_delay_ps"] - truth["direct_sigma_ps"]
    wrong["direct_delay_ps"] = truth["direct_delay_ps"] + 6 * truth["direct_sigma_ps"]
    wrong["direct_amplitude"][:] = 0.2
    comps = render_components(truth, L, T)
    assert fidelity(comps, render_components(wrong, L, T)).max() < 0.5
    p, info = structured_search(y, wrong, time_bin_ps=T)
    f = fidelity(comps, render_components(p, L, T))
    assert f.min() > 0.95
    # Pixel 3 (sss peak about the direct's) is only recovered by a start without the spurious Gaussian.
    assert info["start"][3] == STARTS.index("edge bare") or info["start"][3] == STARTS.index("peak bare")
    assert np.all(info["objective"] <= info["objective_solver"])
    np.testing.assert_allclose(p["direct_delay_ps"], truth["direct_delay_ps"], atol=0.5)


def test_search_options_are_validated():
    with pytest.raises(ValueError, match="penalty"):
        SearchOptions(penalty=-1)
    with pytest.raises(ValueError, match="edge_level"):
        SearchOptions(edge_level=1.5)
