"""Scoring of the accuracy benchmarks: regime rows, flag precision/recall, delay failures, targets."""
import math

import numpy as np
import pytest

from streaklab.bench.scoring import (
    MIN_REGIME_PIXELS, REGIMES, check_targets, direct_delay_failures, flag_precision_recall, format_regime_table,
    gap_matrix, paired_gap_se, regime_rows, target_records, white_noise_j, within_data, worst_gap,
)


def _regimes(n, rng):
    return {"sss_peak_ratio": rng.uniform(0.05, 3, n), "onset_sigma": rng.uniform(0, 3, n),
            "sigma_bins": rng.uniform(0.25, 5, n), "n_ir": rng.integers(0, 3, n),
            "ir_min_peak_ratio": rng.uniform(0.01, 1.0, n)}


def test_regime_rows_partition_the_pixels_and_give_gaps():
    rng = np.random.default_rng(0)
    n = 200
    reg = _regimes(n, rng)
    reg["sss_peak_ratio"][:7] = np.nan  # pixels without an sss
    oracle = rng.uniform(0.9, 1.0, n)
    method = oracle - np.where(reg["n_ir"] == 2, 0.3, 0.0)
    rows = regime_rows(reg, {"convscd": method, "oracle": oracle})
    assert rows[0]["regime"] == "all" and rows[0]["n"] == n
    assert rows[0]["gap[convscd]"] == pytest.approx(method.mean() - oracle.mean())
    for title, key, bins in REGIMES:
        mine = [r for r in rows if r["regime"] == title]
        assert sum(r["n"] for r in mine) == n
    na = [r for r in rows if r["bin"] == "n/a"]
    assert len(na) == 1 and na[0]["n"] == 7
    two = next(r for r in rows if r["regime"] == "inter-reflections" and r["bin"] == ">= 2")
    assert two["n"] == int((reg["n_ir"] == 2).sum())
    assert two["gap[convscd]"] == pytest.approx(-0.3)
    zero = next(r for r in rows if r["regime"] == "inter-reflections" and r["bin"] == "0")
    assert zero["gap[convscd]"] == pytest.approx(0.0, abs=1e-12)
    assert all(r["few"] == (r["n"] < MIN_REGIME_PIXELS) for r in rows)
    # a constant difference has no spread; elsewhere the paired error of the mean difference
    assert two["gap_se[convscd]"] == pytest.approx(0.0, abs=1e-12)
    d = method - oracle
    assert rows[0]["gap_se[convscd]"] == pytest.approx(d.std(ddof=1) / np.sqrt(n))
    text = "\n".join(format_regime_table(rows, ["convscd", "oracle"]))
    assert "gap convscd +- se" in text and "-0.300 +- 0.000" in text and "fewer than" in text
    with pytest.raises(ValueError, match="reference"):
        regime_rows(reg, {"convscd": method})


def test_paired_gap_se_is_the_error_of_the_mean_difference():
    f = np.array([0.9, 0.8, 0.7, np.nan, 0.5])
    ref = np.array([1.0, 1.0, 0.8, 0.9, np.nan])
    # pairs with both finite: differences -0.1, -0.2, -0.1
    d = np.array([-0.1, -0.2, -0.1])
    assert paired_gap_se(f, ref) == pytest.approx(d.std(ddof=1) / np.sqrt(3))
    # the same fidelities shuffled between pixels have a different (unpaired) spread
    assert paired_gap_se(f[[2, 1, 0, 3, 4]], ref) != pytest.approx(paired_gap_se(f, ref))
    assert math.isnan(paired_gap_se([0.5, np.nan], [0.4, 0.3]))


def test_flag_precision_recall_on_a_constructed_case():
    fid = np.array([0.1, 0.2, 0.3, 0.9, 0.95, 0.99, 0.4, np.nan])
    flags = np.array([4, 4, 0, 4, 0, 0, 64, 4], dtype=np.uint8)
    # POOR_FIT (4): flags pixels 0, 1, 3 (7 has no truth); poor pixels are 0, 1, 2, 6.
    r = flag_precision_recall(flags, 4, fid)
    assert (r["n"], r["flagged"], r["poor"], r["flagged_poor"]) == (7, 3, 4, 2)
    assert r["precision"] == pytest.approx(2 / 3) and r["recall"] == pytest.approx(0.5)
    # Any bit: pixels 0, 1, 3, 6.
    r = flag_precision_recall(flags, 255, fid)
    assert r["precision"] == pytest.approx(3 / 4) and r["recall"] == pytest.approx(3 / 4)
    # A bit never set: precision undefined, recall zero.
    r = flag_precision_recall(flags, 128, fid)
    assert math.isnan(r["precision"]) and r["recall"] == 0.0


def test_direct_delay_failures_count_misses_and_far_delays():
    truth = {"direct_delay_ps": np.array([10.0, 10.0, 10.0, np.nan]), "direct_sigma_ps": np.array([2.0, 2.0, 2.0, 2.0])}
    est = {"direct_delay_ps": np.array([13.9, 14.1, np.nan, 5.0])}
    np.testing.assert_array_equal(direct_delay_failures(truth, est), [False, True, True, False])


def _point(noise, nsr, gap, tb=2.0, fails=0, unflagged=0, few_gap=None):
    rows = [{"regime": "all", "bin": "all", "n": 600, "few": False, "gap[convscd]": gap}]
    if few_gap is not None:
        rows.append({"regime": "sigma (bins)", "bin": "< 1", "n": 5, "few": True, "gap[convscd]": few_gap})
    return {"time_bin_ps": tb, "noise": noise, "nsr": nsr, "n": 600, "regimes": rows,
            "delay_failures[convscd]": fails, "unflagged_failures[convscd]": unflagged}


def test_check_targets_met_not_met_and_not_measured():
    points = [_point("white", 0.001, -0.01, few_gap=-0.5), _point("white", 0.055, -0.04, fails=3),
              _point("pink", 0.055, -0.04, fails=9, unflagged=1)]
    out = {text: (status, detail) for text, status, detail in check_targets(points)}
    get = lambda *words: next(v for k, v in out.items() if all(w in k for w in words))  # noqa: E731
    assert get("white noise, NSR 0.001,")[0] is True  # the row with 5 pixels does not count
    assert get("white noise, NSR 0.055,")[0] is False and "-0.040" in get("white noise, NSR 0.055,")[1]
    # with the gap's standard error the detail says how far the limit is in those errors
    points[1]["regimes"][0]["gap_se[convscd]"] = 0.004
    detail = next(d for t, s, d in check_targets(points) if "white noise, NSR 0.055," in t)
    assert "-0.040 +- 0.004" in detail and "2.5 se from the limit" in detail
    assert get("white noise, NSR 0.11,")[0] is None
    assert get("pink noise, NSR 0.055,")[0] is True  # within 0.05 under pink noise
    assert get("photon noise, NSR 0.055,")[0] is None
    # White noise, NSR <= 0.055: 3 of 1200 pixels (0.25 %) fail, all flagged -> met.
    status, detail = get("direct delay error")
    assert status is True and "3 of 1200" in detail
    points[1]["unflagged_failures[convscd]"] = 1
    status, _ = next((s, d) for t, s, d in check_targets(points) if "direct delay error" in t)
    assert status is False


def _row(regime, b, n, gaps, se=0.01):
    """A regime row of regime_rows' layout with the given gap per column."""
    out = {"regime": regime, "bin": b, "n": n, "few": n < MIN_REGIME_PIXELS}
    for m, g in gaps.items():
        out[f"gap[{m}]"], out[f"gap_se[{m}]"] = g, se
    return out


def test_each_gap_target_names_the_detectable_ceilings_own_verdict():
    # white NSR 0.055: the method misses (-0.06 where the weak echoes are) and so does the ceiling
    # (-0.042 there); white NSR 0.001: the method misses in the sub-bin row, the ceiling meets;
    # the ceiling's worst row is its own (not the method's), and a few-pixel row is not judged
    a = {"time_bin_ps": 2.0, "noise": "white", "nsr": 0.055, "n": 600, "delay_failures[convscd]": 0,
         "unflagged_failures[convscd]": 0,
         "regimes": [_row("all", "all", 600, {"convscd": -0.02, "detectable": -0.014}),
                     _row("weakest ir/direct", "< 0.05", 198, {"convscd": -0.06, "detectable": -0.042}),
                     _row("sigma (bins)", "< 1", 5, {"convscd": -0.5, "detectable": -0.5})]}
    b = {"time_bin_ps": 2.0, "noise": "white", "nsr": 0.001, "n": 600, "delay_failures[convscd]": 0,
         "unflagged_failures[convscd]": 0,
         "regimes": [_row("all", "all", 600, {"convscd": -0.01, "detectable": 0.0}),
                     _row("sigma (bins)", "< 1", 76, {"convscd": -0.036, "detectable": 0.0}),
                     _row("sss onset (sigma)", "1-2", 202, {"convscd": -0.005, "detectable": -0.002})]}
    assert worst_gap(a["regimes"], "detectable") == (-0.042, "weakest ir/direct", "< 0.05", 0.01)
    assert worst_gap(b["regimes"], "detectable")[:3] == (-0.002, "sss onset (sigma)", "1-2")
    assert worst_gap(a["regimes"], "gradbm") is None
    recs = {r["text"].split(" ps bins")[0].split(", ", 1)[1]: r for r in target_records([a, b])}
    r55, r01 = recs["white noise, NSR 0.055, 2"], recs["white noise, NSR 0.001, 2"]
    assert r55["met"] is False and r55["ceiling_met"] is False
    # beside the ceiling's verdict, the method in the rows the ceiling meets (here only "all")
    assert r55["detail"] == ("worst gap -0.060 +- 0.010 (weakest ir/direct < 0.05, 3.0 se from the limit); the "
                             "detectable ceiling: worst gap -0.042 +- 0.010 (weakest ir/direct < 0.05, 1.2 se "
                             "from the limit), not met; convscd in the rows the ceiling meets: worst gap -0.020 "
                             "+- 0.010 (overall, 1.0 se from the limit), met")
    assert r55["met_where_ceiling_meets"] is True
    a["regimes"].append(_row("sss onset (sigma)", "1-2", 200, {"convscd": -0.045, "detectable": -0.01}))
    r = next(r for r in target_records([a, b]) if "NSR 0.055, 2" in r["text"])
    assert r["met_where_ceiling_meets"] is False and r["detail"].endswith(
        "in the rows the ceiling meets: worst gap -0.045 +- 0.010 (sss onset (sigma) 1-2, 1.5 se from the limit), not met")
    a["regimes"].pop()
    assert r01["met"] is False and r01["ceiling_met"] is True and r01["detail"].endswith(", met")
    assert r01["met_where_ceiling_meets"] is None
    assert recs["white noise, NSR 0.11, 2"]["ceiling_met"] is None  # not measured
    delay = next(r for r in recs.values() if "direct delay" in r["text"])
    assert delay["met"] is True and delay["ceiling_met"] is None
    # check_targets is the same records as (text, status, detail); without the ceiling's
    # column (or asked for the ceiling itself) the detail is the method's alone
    assert check_targets([a, b]) == [(r["text"], r["met"], r["detail"]) for r in target_records([a, b])]
    for p in (a, b):
        for r in p["regimes"]:
            del r["gap[detectable]"]
    r55 = next(r for r in target_records([a, b]) if "NSR 0.055, 2" in r["text"])
    assert r55["ceiling_met"] is None and "ceiling" not in r55["detail"]


def test_the_target_header_counts_the_targets_the_ceiling_misses_too():
    from streaklab.bench.accuracy import target_header

    recs = [{"met": True, "ceiling_met": True}, {"met": False, "ceiling_met": False, "met_where_ceiling_meets": True},
            {"met": False, "ceiling_met": False, "met_where_ceiling_meets": False},
            {"met": False, "ceiling_met": True}, {"met": False, "ceiling_met": None}, {"met": None, "ceiling_met": None}]
    assert target_header(recs, "detectable") == (
        "accuracy targets against the oracle (1 met, 4 not met; 2 of the not met are missed by the detectable ceiling "
        "as well, where the components the noise hides cost more than the limit, and 1 of those are met in every row "
        "the ceiling meets):")
    assert target_header(recs[3:], "detectable") == (
        "accuracy targets against the oracle (0 met, 2 not met; none of the not met is missed by the detectable "
        "ceiling as well):")
    assert target_header(recs[:1], "detectable") == "accuracy targets against the oracle (1 met, 0 not met):"


def test_white_noise_j_is_chi2_in_the_true_noise_plus_k_ln_n():
    from core.model import render_components

    rng = np.random.default_rng(3)
    n, L, T = 4, 200, 2.0
    truth = {"direct_delay_ps": np.full(n, 60.0), "direct_sigma_ps": np.full(n, 3.0), "direct_amplitude": np.ones(n),
             "sss_delay_ps": np.full(n, 64.0), "sss_sigma_ps": np.full(n, 3.0), "sss_amplitude": np.full(n, 0.4),
             "sss_alpha_per_ps": np.full(n, 0.03), "ir_delay_ps": np.full((n, 1), 120.0),
             "ir_sigma_ps": np.full((n, 1), 3.0), "ir_amplitude": np.array([[0.5], [0.5], [0.01], [0.01]])}
    comps = render_components(truth, L, T)
    clean = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    noise = rng.normal(0, 0.01, (n, L))
    noisy = clean + noise
    sd = noise.std(axis=1)
    # the truth itself: its own chi2 plus 8 parameters (2 + 3 + 2 and one width) times ln L
    j_true = white_noise_j(noisy, clean, comps, truth)
    np.testing.assert_allclose(j_true, (noise ** 2).sum(axis=1) / sd ** 2 + 8 * np.log(L), rtol=1e-12)
    # an answer without the inter-reflection: 2 parameters fewer, the echo left in its residual
    no_ir = {**truth, "ir_delay_ps": np.full((n, 1), np.nan), "ir_amplitude": np.full((n, 1), np.nan)}
    c2 = render_components(no_ir, L, T)
    j2 = white_noise_j(noisy, clean, c2, no_ir)
    r2 = noisy - c2["direct"] - c2["sss"]
    np.testing.assert_allclose(j2, (r2 ** 2).sum(axis=1) / sd ** 2 + 6 * np.log(L), rtol=1e-12)
    # a 0.5 echo (50 noise sigmas high) missed is far out of the data's reach; a 0.01 one (one
    # sigma) is not told from the truth: its J is within 10 of the truth's
    near = within_data(j2, j_true, 10.0)
    np.testing.assert_array_equal(near, [False, False, True, True])
    assert within_data(5.0, 0.0, 10.0) and within_data(-3.0, 0.0, 10.0) and not within_data(10.5, 0.0, 10.0)


def test_the_delay_target_reads_its_unflagged_failures_against_the_data():
    pts = [_point("white", 0.001, 0.0, fails=2, unflagged=1), _point("white", 0.055, 0.0, fails=3, unflagged=2)]
    status, detail = next((s, d) for t, s, d in check_targets(pts) if "direct delay error" in t)
    assert status is False and detail == "5 of 1200 pixels (0.4%), 3 of them unflagged"
    for p, k in zip(pts, (0, 2)):
        p["unflagged_failures_within_data[convscd]"], p["within_data_margin"] = k, 10.0
    status, detail = next((s, d) for t, s, d in check_targets(pts) if "direct delay error" in t)
    assert status is False and detail == ("5 of 1200 pixels (0.4%), 3 of them unflagged (2 of those the data do "
                                          "not tell from the truth: J within 10 of the oracle's, or below it)")


def test_gap_matrix_marks_the_rows_that_fail_their_target():
    def _row(regime, b, n, gap, se):
        return {"regime": regime, "bin": b, "n": n, "few": n < MIN_REGIME_PIXELS, "gap[convscd]": gap,
                "gap_se[convscd]": se}
    white = {"time_bin_ps": 2.0, "noise": "white", "nsr": 0.055,
             "regimes": [_row("all", "all", 300, -0.02, 0.005), _row("sigma (bins)", "< 1", 40, -0.04, 0.01),
                         _row("sigma (bins)", ">= 4", 5, -0.5, 0.2)]}
    # no target is set for pink noise at NSR 0.11; this point also lacks the ">= 4" row
    pink = {"time_bin_ps": 4.0, "noise": "pink", "nsr": 0.11,
            "regimes": [_row("all", "all", 300, -0.09, 0.01), _row("sigma (bins)", "< 1", 100, -0.2, 0.02)]}
    g = gap_matrix([white, pink])
    assert g["rows"] == ["all", "sigma (bins) < 1", "sigma (bins) >= 4"]
    assert g["columns"] == ["2 ps white 0.055", "4 ps pink 0.11"]
    np.testing.assert_allclose(g["limit"], [0.03, np.nan])
    np.testing.assert_allclose(g["gap"], [[-0.02, -0.09], [-0.04, -0.2], [-0.5, np.nan]])
    np.testing.assert_allclose(g["se"][:, 0], [0.005, 0.01, 0.2])
    assert g["n"][2, 1] == 0
    # judged: enough pixels and a target at the point; failed: judged and below -limit
    np.testing.assert_array_equal(g["judged"], [[True, False], [True, False], [False, False]])
    np.testing.assert_array_equal(g["failed"], [[False, False], [True, False], [False, False]])
    assert "ceiling_failed" not in g
    # the detectable ceiling's own gap, judged on the same cells: where it fails too
    white["regimes"][0]["gap[detectable]"] = -0.01
    white["regimes"][1]["gap[detectable]"] = -0.035          # the sub-bin row: beyond 0.03 as well
    white["regimes"][2]["gap[detectable]"] = -0.4            # few pixels: not judged
    pink["regimes"][1]["gap[detectable]"] = -0.2             # no target at that point
    g = gap_matrix([white, pink], ceiling="detectable")
    np.testing.assert_array_equal(g["ceiling_failed"], [[False, False], [True, False], [False, False]])
    np.testing.assert_array_equal(g["failed"], [[False, False], [True, False], [False, False]])


def test_target_line_marks_each_status():
    from streaklab.bench.scoring import target_line

    rec = {"text": "convscd: x", "detail": "worst gap -0.010"}
    assert target_line({**rec, "met": True}) == "  [met] convscd: x: worst gap -0.010"
    assert target_line({**rec, "met": False}) == "  [NOT met] convscd: x: worst gap -0.010"
    assert target_line({**rec, "met": None}) == "  [not measured] convscd: x: worst gap -0.010"


def test_each_gap_target_reads_the_best_found_fit_and_the_methods_gap_to_it():
    """The best-found column read like the ceiling, then the method's own worst gap against it
    from the point's ``regimes_best_found`` rows; the header counts both."""
    from streaklab.bench.accuracy import target_header

    p = {"time_bin_ps": 4.0, "noise": "white", "nsr": 0.055, "n": 600, "delay_failures[convscd]": 0,
         "unflagged_failures[convscd]": 0,
         "regimes": [_row("all", "all", 600, {"convscd": -0.034, "detectable": -0.015, "best-found": -0.02}),
                     _row("inter-reflections", ">= 2", 200, {"convscd": -0.079, "detectable": -0.044,
                                                            "best-found": -0.048})],
         # against the best-found fit (its own reference): the method's gaps
         "regimes_best_found": [_row("all", "all", 600, {"convscd": -0.014}),
                                _row("inter-reflections", ">= 2", 200, {"convscd": -0.031}),
                                _row("sigma (bins)", "< 1", 12, {"convscd": -0.2})]}
    r = next(r for r in target_records([p]) if "NSR 0.055, 4" in r["text"])
    assert r["met"] is False and r["ceiling_met"] is False and r["best_met"] is False
    assert r["within_limit_of_best"] is False
    assert r["detail"].endswith(
        "; the best-found fit: worst gap -0.048 +- 0.010 (inter-reflections >= 2, 1.8 se from the limit), not met"
        "; convscd against the best-found fit: worst gap -0.031 +- 0.010 (inter-reflections >= 2, 0.1 se from the "
        "limit), beyond the limit")
    p["regimes_best_found"][1]["gap[convscd]"] = -0.029
    r = next(r for r in target_records([p]) if "NSR 0.055, 4" in r["text"])
    assert r["within_limit_of_best"] is True and r["detail"].endswith("within the limit")
    header = target_header([r, {"met": True, "ceiling_met": True, "best_met": True}], "detectable")
    assert header.endswith("; 1 of the not met are missed by the best-found fit as well, and in 1 convscd is "
                           "within the limit of the best-found fit in every row):")
    # without the column the reading is left out, and the header says nothing of it
    for x in p["regimes"]:
        del x["gap[best-found]"]
    r = next(r for r in target_records([p]) if "NSR 0.055, 4" in r["text"])
    assert r["best_met"] is None and r["within_limit_of_best"] is None and "best-found" not in r["detail"]
    assert "best-found" not in target_header([r], "detectable")
