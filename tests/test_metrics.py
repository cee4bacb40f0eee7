"""Decomposition fidelity and parameter errors on hand-computed cases."""
import numpy as np
import pytest

from decomposition.model.fidelity import fidelity
from decomposition.evaluation.metrics import delay_error_ps, delay_rmse_ps, detection_counts, mean_fidelity, parameter_error
from core.model import render_components
from decomposition.evaluation.synthetic import make_profiles


def _comps(d, s, ir):
    return {"direct": np.asarray(d, float), "sss": np.asarray(s, float), "interreflections": np.asarray(ir, float)}


def test_perfect_estimate_has_fidelity_one():
    d = make_profiles(9, 128, seed=0)
    f = fidelity(d.components, d.components)
    np.testing.assert_array_equal(f, np.ones(9))
    assert mean_fidelity(d.components, d.components) == 1.0


def test_missing_and_spurious_classes_cost_their_norm():
    # One pixel, L = 2.  Truth: d = [3, 4] (norm 5), s = [0, 1] (norm 1), r2 = [1, 0] (norm 1).
    truth = _comps([3, 4], [0, 1], [[1, 0]])
    # Estimate misses r2 entirely: error 1 of 7.
    est = _comps([3, 4], [0, 1], np.zeros((0, 2)))
    assert fidelity(truth, est) == pytest.approx(1 - 1 / 7)
    # Spurious r3 of norm 2 on top of a perfect estimate: error 2 of 7.
    est = _comps([3, 4], [0, 1], [[1, 0], [0, 2]])
    assert fidelity(truth, est) == pytest.approx(1 - 2 / 7)
    # Missed sss and a wrong direct ([0, 4] vs [3, 4]): error 1 + 3 of 7.
    est = _comps([0, 4], [0, 0], [[1, 0]])
    assert fidelity(truth, est) == pytest.approx(1 - 4 / 7)
    # Direct taken as sss (class confusion): costs twice.
    est = _comps([0, 0], [3, 5], [[1, 0]])
    assert fidelity(truth, est) == pytest.approx(1 - (5 + 5) / 7)
    # Empty estimate: fidelity 0.
    est = _comps([0, 0], [0, 0], np.zeros((0, 2)))
    assert fidelity(truth, est) == pytest.approx(0.0)


def test_matched_pairing_charges_a_missed_first_echo_once():
    # One pixel, L = 4.  Truth: d = [3, 4, 0, 0] (norm 5), no sss, a faint r2 = [0, 0, 0.1, 0]
    # (norm 0.1) and a strong r3 = [0, 0, 0, 2] (norm 2).
    truth = _comps([3, 4, 0, 0], [0, 0, 0, 0], [[0, 0, 0.1, 0], [0, 0, 0, 2]])
    # The faint first echo missed; the strong one found and (by arrival) labelled r2.
    est = _comps([3, 4, 0, 0], [0, 0, 0, 0], [[0, 0, 0, 2], [0, 0, 0, 0]])
    total = 5 + 0.1 + 2
    # By order: r2 compared with the faint echo (error |(0,0,0.1,-2)| = sqrt(4.01)) and r3 with
    # nothing (error 2).
    assert fidelity(truth, est) == pytest.approx(1 - (np.sqrt(4.01) + 2) / total)
    # Matched: the strong echo paired with the strong one; only the faint one's norm is lost.
    assert fidelity(truth, est, ir_pairing="matched") == pytest.approx(1 - 0.1 / total)
    # In the right order both pairings agree, and the pairing never makes an estimate worse.
    right = _comps([3, 4, 0, 0], [0, 0, 0, 0], [[0, 0, 0.1, 0], [0, 0, 0, 1.5]])
    assert fidelity(truth, right, ir_pairing="matched") == pytest.approx(fidelity(truth, right))
    # Two-echo scenes with their echoes listed in reverse: wrong by order, exact when matched.
    d = make_profiles(30, 128, seed=1, kinds=("c",))
    swapped = {"direct": d.components["direct"], "sss": d.components["sss"],
               "interreflections": d.components["interreflections"][:, ::-1]}
    assert np.all(fidelity(d.components, swapped) < 1.0)
    np.testing.assert_allclose(fidelity(d.components, swapped, ir_pairing="matched"), 1.0, atol=1e-12)
    with pytest.raises(ValueError, match="ir_pairing"):
        fidelity(truth, est, ir_pairing="nearest")


def test_batched_pixels_and_undefined_truth():
    truth = _comps([[1, 0], [0, 0]], [[0, 0], [0, 0]], np.zeros((2, 0, 2)))
    est = _comps([[0.5, 0], [0, 0]], [[0, 0], [0, 1]], np.zeros((2, 0, 2)))
    f = fidelity(truth, est)
    assert f[0] == pytest.approx(0.5)
    assert np.isnan(f[1])  # nothing to recover: undefined, and left out of the mean
    assert mean_fidelity(truth, est) == pytest.approx(0.5)


def test_result_objects_and_missing_keys():
    class Result:
        def __init__(self, c):
            self.direct, self.sss, self.interreflections = c["direct"], c["sss"], c["interreflections"]

    truth = _comps([[1.0, 0.0]], [[0.0, 1.0]], np.zeros((1, 0, 2)))
    assert fidelity(truth, Result(truth))[0] == 1.0
    assert fidelity(truth, {"direct": truth["direct"]})[0] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="shape"):
        fidelity(truth, _comps(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 0, 3))))


def test_parameter_errors_match_by_presence():
    truth = {"direct_delay_ps": np.array([10.0, 20.0, np.nan]),
             "ir_delay_ps": np.array([[50.0], [60.0], [np.nan]])}
    est = {"direct_delay_ps": np.array([11.0, np.nan, 30.0]),
           "ir_delay_ps": np.array([[49.0, 80.0], [62.0, np.nan], [np.nan, np.nan]])}
    e = delay_error_ps(truth, est)
    assert e[0] == 1.0 and np.isnan(e[1]) and np.isnan(e[2])
    assert delay_rmse_ps(truth, est) == 1.0
    assert delay_rmse_ps(truth, est, "ir") == pytest.approx(np.sqrt((1 + 4) / 2))
    assert detection_counts(truth, est) == {"matched": 1, "missed": 1, "spurious": 1}
    assert detection_counts(truth, est, "ir") == {"matched": 2, "missed": 0, "spurious": 1}
    rel = parameter_error(truth, est, "direct_delay_ps", relative=True)
    assert rel[0] == pytest.approx(0.1)


def test_fidelity_of_a_shifted_direct_component():
    # Render by the model: a one-bin shift of a sigma = 3 ps direct costs a known amount.
    p = {"direct_delay_ps": np.array([50.0]), "direct_amplitude": np.array([1.0]),
         "direct_sigma_ps": np.array([3.0])}
    q = dict(p, direct_delay_ps=np.array([52.0]))
    a, b = render_components(p, 64), render_components(q, 64)
    expect = 1 - np.linalg.norm(a["direct"] - b["direct"]) / np.linalg.norm(a["direct"])
    assert fidelity(a, b)[0] == pytest.approx(expect)
    assert 0.5 < expect < 0.9
