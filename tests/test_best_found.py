"""The best-found fit of the true component set (decomposition.evaluation.best_found): the start mapped from
an answer, and the per-pixel choice of the lower cost."""
import numpy as np
import pytest

from decomposition.evaluation.best_found import answer_start, lowest_cost
from decomposition.evaluation.oracle import OracleFit


def test_answer_start_takes_what_the_decomposition_found():
    """The start of the best-found maximum likelihood: the truth's component set, each true
    component with the decomposition's values where it found it (an inter-reflection: its
    nearest one within ``match_ps``), the truth's elsewhere, out of the window, or where the
    decomposition's amplitude is not positive."""
    nan = np.nan
    truth = {"direct_delay_ps": np.array([50.0, 50.0, 50.0]), "direct_amplitude": np.array([10.0, 10.0, 10.0]),
             "sss_delay_ps": np.array([54.0, 54.0, nan]), "sss_amplitude": np.array([2.0, 2.0, nan]),
             "sss_alpha_per_ps": np.array([0.02, 0.02, nan]),
             "ir_delay_ps": np.array([[120.0, 200.0], [120.0, nan], [120.0, nan]]),
             "ir_amplitude": np.array([[1.0, 0.5], [1.0, nan], [1.0, nan]])}
    est = {"direct_delay_ps": np.array([51.0, -900.0, nan]), "direct_amplitude": np.array([9.0, 9.0, nan]),
           "sss_delay_ps": np.array([55.0, 56.0, 60.0]), "sss_amplitude": np.array([2.5, -1.0, 3.0]),
           "sss_alpha_per_ps": np.array([0.03, 0.03, 0.03]),
           "ir_delay_ps": np.array([[118.0, 205.0, 300.0], [140.0, nan, nan], [121.0, 122.0, nan]]),
           "ir_amplitude": np.array([[1.1, 0.6, 0.2], [0.9, nan, nan], [0.0, 0.8, nan]])}
    s = answer_start(truth, est, delay_range_ps=(0.0, 500.0), match_ps=8.0)
    # pixel 0: everything found; the second echo 5 ps off, within 8 ps
    assert s["direct_delay_ps"][0] == 51.0 and s["direct_amplitude"][0] == 9.0
    assert (s["sss_delay_ps"][0], s["sss_amplitude"][0], s["sss_alpha_per_ps"][0]) == (55.0, 2.5, 0.03)
    np.testing.assert_array_equal(s["ir_delay_ps"][0], [118.0, 205.0])
    np.testing.assert_array_equal(s["ir_amplitude"][0], [1.1, 0.6])
    # pixel 1: the direct out of the window, the sss's amplitude negative, the echo 20 ps off: the truth
    assert s["direct_delay_ps"][1] == 50.0 and s["sss_amplitude"][1] == 2.0 and s["sss_alpha_per_ps"][1] == 0.02
    assert s["ir_delay_ps"][1, 0] == 120.0 and np.isnan(s["ir_delay_ps"][1, 1])
    # pixel 2: no direct found; no true sss (none added); the nearest echo of positive amplitude
    assert s["direct_delay_ps"][2] == 50.0 and np.isnan(s["sss_alpha_per_ps"][2])
    assert s["ir_delay_ps"][2, 0] == 122.0 and s["ir_amplitude"][2, 0] == 0.8
    # the truth is not modified
    assert truth["direct_delay_ps"][0] == 50.0 and truth["ir_delay_ps"][0, 0] == 120.0


def test_answer_start_takes_the_answers_width_where_asked():
    """``widths=True``: the answer's one width for every present component of the truth, where the
    answer's width is finite and positive; absent components stay NaN."""
    nan = np.nan
    truth = {"direct_delay_ps": np.array([50.0, 50.0]), "direct_amplitude": np.array([1.0, 1.0]),
             "direct_sigma_ps": np.array([3.0, 3.0]),
             "sss_delay_ps": np.array([54.0, nan]), "sss_amplitude": np.array([0.5, nan]),
             "sss_alpha_per_ps": np.array([0.02, nan]), "sss_sigma_ps": np.array([3.0, nan]),
             "ir_delay_ps": np.array([[120.0, nan], [120.0, 160.0]]), "ir_amplitude": np.array([[0.3, nan], [0.3, 0.2]]),
             "ir_sigma_ps": np.array([[3.0, nan], [3.0, 3.0]])}
    est = {"direct_delay_ps": np.array([51.0, 50.5]), "direct_amplitude": np.array([1.1, 0.9]),
           "direct_sigma_ps": np.array([4.5, nan])}
    s = answer_start(truth, est, delay_range_ps=(0.0, 500.0), match_ps=np.array([6.0, 6.0]), widths=True)
    assert s["direct_sigma_ps"][0] == 4.5 and s["sss_sigma_ps"][0] == 4.5
    np.testing.assert_array_equal(s["ir_sigma_ps"][0], [4.5, nan])
    # no usable width in the answer: the truth's
    assert s["direct_sigma_ps"][1] == 3.0 and np.isnan(s["sss_sigma_ps"][1])
    np.testing.assert_array_equal(s["ir_sigma_ps"][1], [3.0, 3.0])
    # without widths=True the truth's widths stay
    s = answer_start(truth, est, delay_range_ps=(0.0, 500.0), match_ps=6.0)
    assert s["direct_sigma_ps"][0] == 3.0 and s["sss_sigma_ps"][0] == 3.0


def _fit(delay, rss, L=4):
    n = len(delay)
    return OracleFit(params={"direct_delay_ps": np.asarray(delay, float),
                             "ir_delay_ps": np.asarray(delay, float)[:, None] + [[10.0, 20.0]]},
                     direct=np.asarray(delay, float)[:, None] * np.ones(L), sss=np.zeros((n, L)),
                     interreflections=np.asarray(delay, float)[:, None, None] * np.ones((n, 2, L)),
                     info={"rss": np.asarray(rss, float), "iterations": np.arange(n)})


def test_lowest_cost_keeps_each_pixels_lower_cost_and_ties_the_first():
    a = _fit([1.0, 2.0, 3.0, 4.0], [10.0, 10.0, 10.0, np.nan])
    b = _fit([5.0, 6.0, 7.0, 8.0], [9.0, 10.0 - 1e-9, 11.0, 3.0])
    best = lowest_cost([a, b], cost="rss")
    assert type(best) is OracleFit
    # pixel 0: b lower; pixel 1: lower by less than the tie tolerance (1e-6 x 10): a; pixel 2: a;
    # pixel 3: a's cost is not finite: b
    np.testing.assert_array_equal(best.info["start"], [1, 0, 0, 1])
    np.testing.assert_array_equal(best.params["direct_delay_ps"], [5.0, 2.0, 3.0, 8.0])
    np.testing.assert_array_equal(best.params["ir_delay_ps"][:, 1], [25.0, 22.0, 23.0, 28.0])
    np.testing.assert_array_equal(best.direct[:, 0], [5.0, 2.0, 3.0, 8.0])
    np.testing.assert_array_equal(best.interreflections[:, 1, 2], [5.0, 2.0, 3.0, 8.0])
    np.testing.assert_array_equal(best.info["rss"][:3], [9.0, 10.0, 10.0])
    # no tolerance: the smaller cost wins even by 1e-9
    assert lowest_cost([a, b], cost="rss", tie_tolerance=0.0).info["start"][1] == 1
    # the inputs are not modified
    assert "start" not in a.info and a.params["direct_delay_ps"][0] == 1.0


def test_lowest_cost_refuses_what_it_cannot_compare():
    a = _fit([1.0, 2.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="at least one"):
        lowest_cost([], cost="rss")
    with pytest.raises(ValueError, match="differ"):
        lowest_cost([a, _fit([1.0, 2.0, 3.0], [1.0, 1.0, 1.0])], cost="rss")
    with pytest.raises(ValueError, match="tie_tolerance"):
        lowest_cost([a, a], cost="rss", tie_tolerance=np.nan)
    with pytest.raises(ValueError, match="different kinds"):
        lowest_cost([a, {"info": {"rss": np.ones(2)}}], cost="rss")
    with pytest.raises(ValueError, match="no 'deviance'"):
        lowest_cost([a, a], cost="deviance")


def test_the_best_found_ceiling_never_costs_more_than_the_detectable_one():
    """bench accuracy's best-found column on paper scenes (4 ps bins, white NSR 0.055, 60 px):
    per pixel its least-squares cost is the lower of the truth's start and ConvSCD's, and some
    pixels take ConvSCD's start (the truth's is not always the best the cost allows)."""
    from decomposition import decompose
    from decomposition.evaluation.oracle import oracle_fit, significant_truth
    from decomposition.evaluation.synthetic import make_profiles
    from streaklab.bench.accuracy import best_found_fit

    d = make_profiles(60, 256, nsr=0.055, noise="white", seed=3, kinds="a,b,c", time_bin_ps=4.0, ranges="paper",
                      bin_integrated=True)
    seen = significant_truth(d.params, d.components, np.std(d.noisy - d.clean, axis=-1))
    det = oracle_fit(d.noisy, seen, time_bin_ps=4.0, bin_integrated=True)
    answer = decompose(d.noisy, 4.0).params
    best = best_found_fit(d, seen, det, answer, 4.0, True)
    rss, rss_det = best.info["rss"], det.info["rss"]
    assert np.all(rss <= rss_det * (1 + 1e-12))
    took = best.info["start"] == 1
    assert 0 < took.sum() < 60
    assert np.all(rss[took] < rss_det[took])
    np.testing.assert_array_equal(best.params["direct_delay_ps"][~took], det.params["direct_delay_ps"][~took])
    # the component set is the detectable one: no component added or lost
    for key in ("direct_delay_ps", "sss_delay_ps", "ir_delay_ps"):
        np.testing.assert_array_equal(np.isfinite(best.params[key]), np.isfinite(seen[key]))
