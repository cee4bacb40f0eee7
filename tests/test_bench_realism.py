"""``streaklab bench realism``: effects of real photon counts beside the Poisson reference."""
import csv
import json

import numpy as np
import pytest

from decomposition.evaluation.synthetic import make_profiles
from streaklab.bench import realism
from streaklab.cli import main


@pytest.mark.timeout(120)
def test_quick_runs_ignored_and_reference_and_writes_its_files(tmp_path, capsys):
    out = tmp_path / "realism"
    assert main(["bench", "realism", "--quick", "--variants", "ignored,reference", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    with open(out / "realism.csv") as fh:
        rows = list(csv.DictReader(fh))
    keys = {(r["effect"], float(r["photons_per_pixel"]), r["variant"]) for r in rows}
    sweep = [e for e in realism.EFFECTS if e != "echo5sigma"]
    level = {float(r["photons_per_pixel"]) for r in rows if r["effect"] == "echo5sigma"}
    assert len(level) == 1                                       # the echo target at its own level
    n_echo = level.pop()
    assert keys == ({(e, p, v) for e in sweep for p in (300.0, 10000.0) for v in ("ignored", "reference")}
                    | {("echo5sigma", n_echo, v) for v in ("ignored", "reference")})
    for r in rows:
        assert r["status"] == "ok"
        f = float(r["mean_fidelity"])
        assert np.isfinite(f) and f <= 1.0
        assert float(r["direct_found"]) > 0
    ref = {(r["effect"], float(r["photons_per_pixel"])): r for r in rows if r["variant"] == "reference"}
    for effect in sweep:
        lo, hi = ref[(effect, 300.0)], ref[(effect, 10000.0)]
        # The reference is its own yardstick, and more photons give it smaller errors.
        assert float(lo["lifetime_rmse_over_reference"]) == pytest.approx(1.0)
        assert float(hi["direct_delay_rmse_ps"]) < float(lo["direct_delay_rmse_ps"])
        assert float(hi["mean_fidelity"]) > float(lo["mean_fidelity"])
    assert np.isfinite(float(ref[("echo", 10000.0)]["echo_found"]))
    # every variant's bias beside the reference's on the same pixels; the reference's own is 0
    for r in rows:
        gaps = [float(r["direct_delay_bias_vs_reference_ps"])]
        if r["effect"] != "echo5sigma":                          # its scenes have no sss
            gaps.append(float(r["lifetime_bias_vs_reference_rel"]))
        for gap in gaps:
            assert gap == 0.0 if r["variant"] == "reference" else np.isfinite(gap)
    assert "tau-ref" in text and "beside the reference's" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["variants"] == ["ignored", "reference"] and summary["quick"]
    assert {c["met"] for c in summary["target_checks"]} <= {True, False, None}
    assert "targets (" in text and "bias within 1 %" in text
    assert "echo target (reference): a 1 % echo 5 sigma above the noise" in text


def test_a_variant_that_raises_is_reported_per_row_and_the_rest_runs(tmp_path, monkeypatch, capsys):
    def refuse(*args, **kwargs):
        raise TypeError("unknown options for method 'convscd': ['irf']")

    monkeypatch.setattr("decomposition.decompose", refuse)
    out = tmp_path / "r"
    assert main(["bench", "realism", "--quick", "--effects", "background", "--variants", "modelled,reference",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    with open(out / "realism.csv") as fh:
        rows = list(csv.DictReader(fh))
    modelled = [r for r in rows if r["variant"] == "modelled"]
    assert len(modelled) == 2
    for r in modelled:
        assert r["status"].startswith("error: TypeError") and r["mean_fidelity"] == ""
    assert all(r["status"] == "ok" for r in rows if r["variant"] == "reference")
    assert "modelled  error: TypeError" in text and "[not measured] modelled, background" in text


def test_five_sigma_photons_puts_the_echo_at_five_sigma():
    """At the level returned, the expected echo peak over the Poisson noise of its bin is 5 in
    the scenes (the generator's own counting), the direct before the window, no sss."""
    setup = realism.effect_setup("echo5sigma", 2.0)
    n = realism.five_sigma_photons(setup, 41, 256, 2.0, seed=3)
    d = make_profiles(41, 256, seed=3, kinds=setup["kinds"], time_bin_ps=2.0, photons_per_pixel=n,
                      **setup["options"])
    echo = d.components["interreflections"][:, -1]
    peak = np.argmax(echo, axis=1)
    rows = np.arange(41)
    snr = echo[rows, peak] / np.sqrt(d.clean[rows, peak])
    np.testing.assert_allclose(np.median(snr), 5.0, rtol=1e-6)
    assert np.all(np.abs(snr - 5.0) < 0.5)                      # the pixels differ by bin phase only
    assert np.all(d.params["direct_delay_ps"] == d.t0_ps - realism.ECHO_DIRECT_BEFORE_PS)
    assert np.all(np.isnan(d.params["sss_alpha_per_ps"])) and d.echo.all()
    # the echo is 1 % of the direct's amplitude
    np.testing.assert_allclose(d.params["ir_amplitude"][:, 0], 0.01 * d.params["direct_amplitude"])


def test_echo_sigma_follows_the_photon_count_and_only_a_five_sigma_echo_is_judged():
    """echo_sigma: the median echo peak over its bin's Poisson noise at any photon level (the
    generator's counting, an sss under the echo); the found-rate target is judged only where
    that is >= ECHO_SIGMA, and a weaker echo's rate is no target."""
    setup = realism.effect_setup("echo", 2.0)
    n5 = realism.five_sigma_photons(setup, 41, 256, 2.0, seed=3)
    for photons in (300.0, 10000.0):
        d = make_profiles(41, 256, seed=3, kinds=setup["kinds"], time_bin_ps=2.0, photons_per_pixel=photons,
                          **setup["options"])
        echo = d.components["interreflections"][:, -1]
        peak = np.argmax(echo, axis=1)
        snr = echo[np.arange(41), peak] / np.sqrt(d.clean[np.arange(41), peak])
        assert realism.echo_sigma(photons, n5) == pytest.approx(np.median(snr), rel=1e-6)
    assert realism.echo_sigma(n5, n5) == realism.ECHO_SIGMA
    assert np.isnan(realism.echo_sigma(300.0, float("nan")))

    base = {"variant": "modelled", "status": "ok", "lifetime_bias_rel": 0.0, "lifetime_bias_se_rel": 0.0,
            "direct_delay_bias_sigma": 0.0, "lifetime_bias_vs_reference_rel": 0.0,
            "lifetime_bias_vs_reference_se_rel": 0.0, "lifetime_rmse_over_reference": 1.0,
            "direct_delay_rmse_over_reference": 1.0, "stderr_median_z_lifetime": 0.674,
            "stderr_median_z_lifetime_se": 0.05, "stderr_median_z_delay": 0.674, "stderr_median_z_delay_se": 0.05,
            "effect": "echo", "echo_found": 0.5}
    weak = realism.check_targets([{**base, "photons_per_pixel": 300.0, "echo_sigma": 1.4}])
    strong = realism.check_targets([{**base, "photons_per_pixel": 10000.0, "echo_sigma": 7.9}])
    assert not [c for c in weak if "echo found" in c[0]]
    assert [(ok, detail) for text, ok, detail in strong if "echo found" in text] == [
        (False, "50.0% at 7.9 sigma (>= 95%)")]
    assert all(ok for _, ok, _ in weak)


def test_scores_of_the_truth_itself():
    d = make_profiles(12, 200, seed=1, kinds="d+s+r2", echo_ratio=0.01, photons_per_pixel=1000.0)
    s = realism.score(d, d.params, d.components, with_echo=True)
    assert s["direct_delay_bias_ps"] == 0 and s["lifetime_rmse_rel"] == 0 and s["mean_fidelity"] == 1.0
    assert s["echo_found"] == 1.0 and s["direct_found"] == 1.0
    # An echo estimated 3 widths off is not found; nor is a missing one.
    est = {k: v.copy() for k, v in d.params.items()}
    est["ir_delay_ps"][:6, 0] += 3 * est["ir_sigma_ps"][:6, 0]
    est["ir_amplitude"][6:9, 0] = np.nan
    est["ir_delay_ps"][6:9, 0] = np.nan
    assert realism.echo_found(d.params, est, d.echo) == pytest.approx(3 / 12)


def test_bad_options(tmp_path, capsys):
    assert main(["bench", "realism", "--quick", "--effects", "fog", "--out", str(tmp_path / "a")]) == 2
    assert main(["bench", "realism", "--quick", "--variants", "fastest", "--out", str(tmp_path / "b")]) == 2
    # the best-found maximum likelihood starts from the modelled answer and keeps the reference's
    assert main(["bench", "realism", "--quick", "--variants", "best,reference", "--out", str(tmp_path / "d")]) == 2
    assert "best needs modelled and reference" in capsys.readouterr().err
    assert main(["bench", "realism", "--photons", "100,-3", "--out", str(tmp_path / "c")]) == 2


def test_bias_beside_the_reference_and_the_median_ratio_error():
    """paired_bias: the mean of the per-pixel differences where both are finite, with its
    standard error; median_z_stderr: the spread of the median of n half-normal values."""
    a = np.array([1.0, 2.0, np.nan, 4.0, 5.0])
    b = np.array([0.5, 1.0, 3.0, np.nan, 4.0])
    diff, se = realism.paired_bias(a, b)
    assert diff == pytest.approx(np.mean([0.5, 1.0, 1.0]))
    assert se == pytest.approx(np.std([0.5, 1.0, 1.0], ddof=1) / np.sqrt(3))
    rng = np.random.default_rng(0)
    medians = np.median(np.abs(rng.standard_normal((4000, 400))), axis=1)
    assert np.median(medians) == pytest.approx(realism.HALF_NORMAL_MEDIAN, abs=0.005)
    assert np.std(medians) == pytest.approx(realism.median_z_stderr(400), rel=0.05)
    # per-pixel errors: the relative lifetime error is tau_e / tau - 1 = alpha_t / alpha_e - 1
    d = make_profiles(6, 200, seed=2, kinds="d+s", photons_per_pixel=1000.0)
    est = {k: v.copy() for k, v in d.params.items()}
    est["sss_alpha_per_ps"] = est["sss_alpha_per_ps"] * 0.8
    est["direct_delay_ps"] = est["direct_delay_ps"] + 1.5
    d_err, tau_rel = realism.pixel_errors(d.params, est)
    np.testing.assert_allclose(d_err, 1.5)
    np.testing.assert_allclose(tau_rel, 0.25)


def test_modelled_takes_the_response_as_the_bins_record_it():
    """The scenes are bin-integrated, so the response that models them is the true one averaged
    over a bin (what a calibration capture on that detector measures); the ``modelled`` variant
    takes it.  On the echo-target scenes (the direct 3 ps before the first bin, ~4,060
    photons) the continuous response, whose atoms are point samples, puts the direct
    +0.12 ps late (one standard error; median |e|/se 0.97); the recorded one leaves no bias."""
    from decomposition.evaluation.synthetic import make_profiles
    from decomposition.evaluation.synthetic_effects import bin_averaged_response

    setup = realism.effect_setup("echo5sigma", 2.0)
    box = bin_averaged_response(setup["response"], 2.0)
    np.testing.assert_allclose(setup["recorded_response"].samples, box.samples)
    seed = 1000 * realism.EFFECTS.index("echo5sigma")
    photons = realism.five_sigma_photons(setup, 300, 256, 2.0, seed)
    data = make_profiles(300, 256, seed=seed, kinds=setup["kinds"], time_bin_ps=2.0, photons_per_pixel=photons,
                         **setup["options"])
    params, _ = realism.run_variant("modelled", data, setup, 2.0)
    err = params["direct_delay_ps"] - data.params["direct_delay_ps"]
    assert abs(np.nanmean(err)) < 0.04 and np.sqrt(np.nanmean(err ** 2)) < 0.15
    setup_continuous = dict(setup, recorded_response=setup["response"])
    params_c, _ = realism.run_variant("modelled", data, setup_continuous, 2.0)
    assert np.nanmean(params_c["direct_delay_ps"] - data.params["direct_delay_ps"]) > 0.08


def test_targets_name_the_references_own_figure_where_it_is_judged_alone():
    base = {"status": "ok", "effect": "tailed", "photons_per_pixel": 100.0, "lifetime_bias_rel": -0.021,
            "lifetime_bias_se_rel": 0.004, "direct_delay_bias_sigma": 0.005, "lifetime_bias_vs_reference_rel": 0.003,
            "lifetime_bias_vs_reference_se_rel": 0.002, "lifetime_rmse_over_reference": 1.04,
            "direct_delay_rmse_over_reference": 0.9, "stderr_median_z_lifetime": 0.69,
            "stderr_median_z_lifetime_se": 0.02, "stderr_median_z_delay": 0.80, "stderr_median_z_delay_se": 0.02,
            "echo_found": float("nan")}
    ref = {**base, "variant": "reference", "lifetime_bias_rel": -0.024, "direct_delay_bias_sigma": 0.16,
           "lifetime_rmse_over_reference": 1.0, "direct_delay_rmse_over_reference": 1.0, "stderr_median_z_delay": 0.67}
    out = {text.split(": ", 1)[1]: (ok, detail)
           for text, ok, detail in realism.check_targets([{**base, "variant": "modelled"}, ref])}
    # judged alone: the reference's figure and verdict beside the variant's
    assert out["lifetime bias"] == (False, "-2.10% +- 0.40% (<= 1%); the reference: -2.40% +- 0.40%, not met")
    assert out["direct delay bias"] == (True, "+0.005 sigma (<= 0.01 sigma); the reference: +0.160 sigma, not met")
    assert out["delay stderr"][0] is False and out["delay stderr"][1].endswith("the reference: median |e|/se 0.670 +- 0.020, met")
    # judged against the reference: nothing added
    assert out["lifetime RMSE"] == (True, "1.04 x reference (<= 1.1)")
    # the reference row itself is no target, and without one nothing is added
    assert not [t for t, _, _ in realism.check_targets([ref])]
    alone = {t.split(": ", 1)[1]: d for t, _, d in realism.check_targets([{**base, "variant": "modelled"}])}
    assert alone["lifetime bias"] == "-2.10% +- 0.40% (<= 1%)"


def test_the_rmse_ratio_carries_its_standard_error():
    """rmse_ratio_se: the delta-method spread of RMSE(a) / RMSE(b) over paired pixels, against
    the spread of the ratio over many independent draws; zero for identical errors."""
    rng = np.random.default_rng(5)
    n, draws = 2000, 1000

    def pair(size):
        shared = rng.standard_normal(size)
        # the variant's errors: the reference's plus a part of its own with outliers (5 % of
        # the pixels four times wider, as a misplaced onset makes them)
        own = rng.standard_normal(size) * 0.3 * np.where(rng.random(size) < 0.05, 4.0, 1.0)
        return shared * 1.0 + own, shared * 0.95 + rng.standard_normal(size) * 0.1

    ratios, ses = [], []
    for _ in range(draws):
        a, b = pair(n)
        ratios.append(np.sqrt(np.mean(a ** 2) / np.mean(b ** 2)))
        ses.append(realism.rmse_ratio_se(a, b))
    # on average over the draws the estimate is the ratio's true spread (one draw's reads
    # within about 25 % of it: the outliers set both)
    assert np.mean(ses) == pytest.approx(np.std(ratios), rel=0.08)
    a, b = pair(n)
    b[:7] = np.nan                                       # pixels the reference lacks are left out
    keep = np.isfinite(b)
    assert realism.rmse_ratio_se(a, b) == pytest.approx(realism.rmse_ratio_se(a[keep], b[keep]), rel=1e-12)
    assert realism.rmse_ratio_se(b, b) == 0.0
    assert np.isnan(realism.rmse_ratio_se(np.array([1.0, np.nan]), np.array([np.nan, 1.0])))
    # the target line names it, and how many of them lie between the ratio and the bar
    row = {"status": "ok", "effect": "afterpulse", "photons_per_pixel": 100.0, "variant": "modelled",
           "lifetime_bias_rel": 0.0, "lifetime_bias_se_rel": 0.001, "direct_delay_bias_sigma": 0.0,
           "lifetime_bias_vs_reference_rel": 0.0, "lifetime_bias_vs_reference_se_rel": 0.001,
           "lifetime_rmse_over_reference": 1.11, "lifetime_rmse_over_reference_se": 0.025,
           "direct_delay_rmse_over_reference": 0.9, "direct_delay_rmse_over_reference_se": 0.0,
           "stderr_median_z_lifetime": 0.674, "stderr_median_z_lifetime_se": 0.02, "stderr_median_z_delay": 0.674,
           "stderr_median_z_delay_se": 0.02, "echo_found": float("nan")}
    out = {t.split(": ", 1)[1]: (ok, d) for t, ok, d in realism.check_targets([row])}
    assert out["lifetime RMSE"] == (False, "1.11 +- 0.03 x reference, 0.4 se from the limit (<= 1.1)")
    assert out["direct delay RMSE"] == (True, "0.90 x reference (<= 1.1)")


def test_the_visible_reference_leaves_out_what_the_counts_hide():
    # the echo scenes' 1 % echo on an sss tail: hidden at 100 photons, the rest visible
    setup = realism.effect_setup("echo", 2.0)
    d = make_profiles(40, 256, seed=11, kinds=setup["kinds"], time_bin_ps=2.0, photons_per_pixel=100.0,
                      **setup["options"])
    seen = realism.visible_truth(d)
    np.testing.assert_array_equal(seen["direct_delay_ps"], d.params["direct_delay_ps"])
    n_true = np.isfinite(d.params["ir_delay_ps"]).sum(axis=1)
    n_seen = np.isfinite(seen["ir_delay_ps"]).sum(axis=1)
    assert np.all(n_seen <= n_true) and np.mean(n_seen < n_true) > 0.9
    # the larger echo stays: every kept one is a true one, in order
    for i in np.flatnonzero(n_seen):
        assert set(seen["ir_delay_ps"][i][:n_seen[i]]) <= set(d.params["ir_delay_ps"][i])
    # with a million photons nothing hides
    d6 = make_profiles(10, 256, seed=11, kinds=setup["kinds"], time_bin_ps=2.0, photons_per_pixel=1e6,
                       **setup["options"])
    np.testing.assert_array_equal(np.isfinite(realism.visible_truth(d6)["ir_delay_ps"]),
                                  np.isfinite(d6.params["ir_delay_ps"]))
    # so the visible reference is the reference there, fitted once, and not at 100 photons
    assert realism.hides_nothing(d6) and not realism.hides_nothing(d)


def test_targets_name_the_visible_reference_and_the_header_counts_it():
    base = {"status": "ok", "effect": "echo", "photons_per_pixel": 100.0, "lifetime_bias_rel": 0.004,
            "lifetime_bias_se_rel": 0.004, "direct_delay_bias_sigma": 0.005, "lifetime_bias_vs_reference_rel": 0.011,
            "lifetime_bias_vs_reference_se_rel": 0.0025, "lifetime_rmse_over_reference": 1.16,
            "lifetime_rmse_over_reference_se": 0.02, "direct_delay_rmse_over_reference": 0.9,
            "stderr_median_z_lifetime": 0.69, "stderr_median_z_lifetime_se": 0.02, "stderr_median_z_delay": 0.67,
            "stderr_median_z_delay_se": 0.02, "echo_found": float("nan"), "echo_sigma": 0.2}
    ref = {**base, "variant": "reference", "lifetime_bias_vs_reference_rel": 0.0, "lifetime_bias_vs_reference_se_rel": 0.0,
           "lifetime_rmse_over_reference": 1.0, "lifetime_rmse_over_reference_se": 0.0,
           "direct_delay_rmse_over_reference": 1.0}
    vis = {**base, "variant": "visible", "lifetime_bias_vs_reference_rel": 0.0527,
           "lifetime_bias_vs_reference_se_rel": 0.0035, "lifetime_rmse_over_reference": 1.41,
           "lifetime_rmse_over_reference_se": 0.06, "direct_delay_rmse_over_reference": 1.0}
    recs = {r["text"].split(": ", 1)[1]: r for r in realism.target_records([{**base, "variant": "modelled"}, ref, vis])}
    rmse = recs["lifetime RMSE"]
    assert rmse["met"] is False and rmse["visible_met"] is False and rmse["reference_met"] is None
    assert rmse["detail"] == ("1.16 +- 0.02 x reference, 3.0 se from the limit (<= 1.1); the visible reference: "
                              "1.41 +- 0.06 x reference, 5.2 se from the limit, not met")
    bias = recs["lifetime bias beside the reference's"]
    assert bias["met"] is False and bias["visible_met"] is False
    assert bias["detail"].endswith("the visible reference: +5.27% +- 0.35%, not met")
    # judged alone: both yardsticks named, the reference first
    lb = recs["lifetime bias"]
    assert lb["detail"] == ("+0.40% +- 0.40% (<= 1%); the reference: +0.40% +- 0.40%, met; the visible reference: "
                            "+0.40% +- 0.40%, met") and lb["reference_met"] is True and lb["visible_met"] is True
    header = realism.target_header(list(recs.values()))
    n_met = sum(r["met"] is True for r in recs.values())
    assert header == (f"targets ({n_met} met, 2 not met, 0 not measured; 0 of the not met are missed by the "
                      "reference itself, 2 more by the reference on the visible components, 0 more by the "
                      "best-found maximum likelihood):")
    # a miss the best-found maximum likelihood shares, where neither reference row does, is counted last
    best = {**base, "variant": "best", "lifetime_rmse_over_reference": 1.15, "lifetime_rmse_over_reference_se": 0.02,
            "lifetime_bias_vs_reference_rel": 0.0, "lifetime_bias_vs_reference_se_rel": 0.001}
    recs_b = realism.target_records([{**base, "variant": "modelled"}, ref, best])
    assert realism.target_header(recs_b).endswith(
        "0 of the not met are missed by the reference itself, 0 more by the reference on the visible components, "
        "1 more by the best-found maximum likelihood):")
    assert next(r for r in recs_b if r["text"].endswith("lifetime RMSE"))["best_met"] is False
    # without the yardstick rows nothing is added
    alone = {r["text"].split(": ", 1)[1]: r for r in realism.target_records([{**base, "variant": "modelled"}])}
    assert alone["lifetime RMSE"]["detail"] == "1.16 +- 0.02 x reference, 3.0 se from the limit (<= 1.1)"
    assert alone["lifetime RMSE"]["visible_met"] is None


def test_quick_with_the_visible_reference(tmp_path, capsys):
    out = tmp_path / "visible"
    assert main(["bench", "realism", "--quick", "--effects", "echo,tailed", "--variants", "ignored,reference,visible",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    with open(out / "realism.csv") as fh:
        rows = {(r["effect"], float(r["photons_per_pixel"]), r["variant"]): r for r in csv.DictReader(fh)}
    for p in (300.0, 10000.0):
        # nothing hides in the tailed scenes: the visible reference is the reference itself
        t_ref, t_vis = rows[("tailed", p, "reference")], rows[("tailed", p, "visible")]
        assert float(t_vis["lifetime_rmse_rel"]) == pytest.approx(float(t_ref["lifetime_rmse_rel"]), rel=1e-9)
        assert float(t_vis["lifetime_rmse_over_reference"]) == pytest.approx(1.0)
    # every judged line names the visible reference where its row is there; the summary says it too
    judged = [x for x in text.splitlines() if x.startswith(("  [met] ignored", "  [NOT met] ignored"))]
    assert judged and all("; the visible reference: " in x for x in judged)
    summary = json.loads((out / "summary.json").read_text())
    assert {c["visible_met"] for c in summary["target_checks"]} <= {True, False, None}
    assert any(c["visible_met"] is not None for c in summary["target_checks"])
    assert "more by the reference on the visible components" in text
    assert (out / "realism.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_figure_series_lays_out_each_variants_values_by_effect_and_level():
    def row(effect, photons, variant, v, se=0.01, status="ok"):
        return {"effect": effect, "photons_per_pixel": photons, "variant": variant, "status": status,
                "lifetime_rmse_over_reference": v, "lifetime_rmse_over_reference_se": se}
    rows = [row("tailed", 100.0, "modelled", 1.04), row("tailed", 100.0, "reference", 1.0, 0.0),
            row("echo", 10000.0, "modelled", 1.16), row("echo", 10000.0, "reference", 1.0, 0.0),
            row("echo", 10000.0, "visible", 9.9, status="error: ValueError: x")]
    ser = realism.figure_series(rows, "lifetime_rmse_over_reference", "lifetime_rmse_over_reference_se")
    assert ser["columns"] == ["tailed, 100 ph", "echo, 10,000 ph"]
    np.testing.assert_allclose(ser["variants"]["modelled"][0], [1.04, 1.16])
    np.testing.assert_allclose(ser["variants"]["modelled"][1], [0.01, 0.01])
    np.testing.assert_allclose(ser["variants"]["reference"][0], [1.0, 1.0])
    # a variant without a row at a column, or whose row failed, has NaN there
    assert np.isnan(ser["variants"]["visible"][0]).all()
    assert np.isnan(realism.figure_series(rows, "lifetime_rmse_over_reference")["variants"]["modelled"][1]).all()


@pytest.mark.timeout(120)
def test_quick_with_the_best_found_maximum_likelihood(tmp_path, capsys):
    """``best`` beside ``modelled`` and ``reference``: its rows, the fraction of pixels where
    the decomposition's start won, every judged line naming it, and the header counting it."""
    out = tmp_path / "best"
    assert main(["bench", "realism", "--quick", "--effects", "truncated", "--variants", "best,modelled,reference",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    with open(out / "realism.csv") as fh:
        rows = {(float(r["photons_per_pixel"]), r["variant"]): r for r in csv.DictReader(fh)}
    for p in (300.0, 10000.0):
        best = rows[(p, "best")]
        assert best["status"] == "ok"
        assert 0.0 <= float(best["best_start_decomposition"]) <= 1.0
        # never a worse likelihood than the reference, so its fidelity is its own figure
        assert np.isfinite(float(best["mean_fidelity"]))
    judged = [x for x in text.splitlines() if x.startswith(("  [met] modelled", "  [NOT met] modelled"))]
    assert judged and all("; the best-found maximum likelihood: " in x for x in judged)
    assert "more by the best-found maximum likelihood" in text
    assert "the start from the modelled answer won in truncated 300" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["variants"] == ["modelled", "reference", "best"]


def _overlapping_labels(fig):
    """Pairs of texts (annotations) of one axes whose drawn boxes overlap."""
    renderer = fig.canvas.get_renderer()
    pairs = []
    for ax in fig.axes:
        texts = [t for t in ax.texts if t.get_text()]
        boxes = [t.get_window_extent(renderer) for t in texts]
        for i in range(len(texts)):
            for k in range(i + 1, len(texts)):
                if boxes[i].overlaps(boxes[k]):
                    pairs.append((texts[i].get_text(), texts[k].get_text()))
    return pairs


def test_off_scale_values_of_neighbouring_variants_get_labels_that_do_not_overlap():
    """Every variant far beyond the bias panels' range at one column: an open triangle each at the
    edge and a label each, none over another (they ran together as "0.2040.2529")."""
    import matplotlib.pyplot as plt

    rows = []
    columns = [(f"effect{i}", photons, 1.0 if i % 2 else -1.0) for i in range(6) for photons in (1e3, 1e4)]
    for effect, photons, sign in columns:      # 12 columns: the figure is 7.6 in wide, 0.55 in a column
        for k, variant in enumerate(realism.VARIANTS):
            rows.append({"effect": effect, "photons_per_pixel": photons, "variant": variant, "status": "ok",
                         "lifetime_rmse_over_reference": 3.0 + 0.1 * k, "lifetime_rmse_over_reference_se": 0.1,
                         "lifetime_bias_rel": sign * (0.204 + 0.0489 * k), "lifetime_bias_se_rel": 0.01,
                         "direct_delay_bias_sigma": sign * (0.9 + 0.1 * k)})
    fig = realism.figure(rows)
    fig.canvas.draw()
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert "0.204" in texts and "0.253" in texts and len(texts) == 3 * len(columns) * len(realism.VARIANTS)
    assert _overlapping_labels(fig) == []
    plt.close(fig)
