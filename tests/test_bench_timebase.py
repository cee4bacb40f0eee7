"""``streaklab bench timebase``: a tiny simulated scan under jitter and drift, aligned and not."""
import csv
import json
import math

import numpy as np
import pytest

from streaklab.cli import main

pytestmark = pytest.mark.timeout(120)

TINY = ["--lines", "4", "--x", "16", "--t", "256", "--frames", "2"]


def _read(out, seed="pooled"):
    """The CSV's rows of one seed (or the pooled ones) by case, and summary.json."""
    with open(out / "timebase.csv") as fh:
        rows = {r["case"]: r for r in csv.DictReader(fh) if r["seed"] == str(seed)}
    return rows, json.loads((out / "summary.json").read_text())


def test_aligned_direct_delays_beat_unaligned_ones(tmp_path, capsys):
    out = tmp_path / "tb"
    # 10 ps/min over 5 simulated minutes: the fiducial stays in its band
    assert main(["bench", "timebase", *TINY, "--minutes", "5", "--seed", "3", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows, summary = _read(out)
    assert set(rows) == {"steady", "aligned", "unaligned", "steady_aligned"}
    # one seed: its rows are the pooled ones
    assert _read(out, 3)[0] == {c: {**r, "seed": "3"} for c, r in rows.items()}
    rmse = {c: float(r["direct_delay_rmse_ps"]) for c, r in rows.items()}
    assert all(math.isfinite(v) and v > 0 for v in rmse.values()) and not any(r["failure"] for r in rows.values())
    (seed,) = summary["seeds"]
    assert seed["seed"] == 3 and summary["options"]["seeds"] == [3]
    assert seed["lit_exposures"] == 8 and seed["simulated_span_min"] == pytest.approx(5.0)
    # the drift spans ~50 ps: without alignment the delays are off by tens of ps
    assert seed["shift_range_ps"] > 40
    # aligned: most pixels as in the steady scan (a wrong peak taken for the direct in a few can
    # still lift the RMSE); unaligned: every pixel off by the drift
    med = {c: float(r["median_abs_ratio_to_steady"]) for c, r in rows.items()}
    assert med["aligned"] < 3 and med["unaligned"] > 50
    assert med["steady_aligned"] < 3                             # the steady scan moved by ~0: as steady
    assert int(rows["unaligned"]["pixels_off_by_over_50ps"]) == 0
    assert summary["ratio_aligned"] == pytest.approx(rmse["aligned"] / rmse["steady"])
    assert summary["target"]["met"] == (summary["ratio_aligned"] <= 1.1)
    assert ("  [met] aligned direct-delay RMSE at most 1.1 x the steady scan's: x" in text) == summary["target"]["met"]
    assert ("  [NOT met] aligned direct-delay RMSE at most 1.1 x the steady scan's: x" in text) != summary["target"]["met"]
    assert "without alignment x" in text
    for name in ("steady.result.zarr", "aligned.result.zarr", "unaligned.result.zarr"):
        assert (out / "seed-3" / name).is_dir()


def test_a_fiducial_that_leaves_its_band_is_reported_not_met(tmp_path, capsys):
    out = tmp_path / "tb"
    # 100 ps/min over 10 minutes moves the pulse ~1,000 ps: out of the whole window
    assert main(["bench", "timebase", *TINY, "--drift-ps-per-min", "100", "--seed", "3", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows, summary = _read(out)
    assert "no usable fiducial pulse" in rows["aligned"]["failure"]
    assert summary["ratio_aligned"] is None and summary["target"]["met"] is False
    assert math.isfinite(float(rows["unaligned"]["direct_delay_rmse_ps"]))
    assert ("  [NOT met] aligned direct-delay RMSE at most 1.1 x the steady scan's: the aligned reconstruction failed "
            "(seed 3: ") in text


def test_bad_options_are_named(tmp_path, capsys):
    assert main(["bench", "timebase", "--time-range", "7", "--out", str(tmp_path / "tb")]) == 2
    assert "--time-range must be a synchroscan setting 1..4" in capsys.readouterr().err
    assert main(["bench", "timebase", "--minutes", "0", "--out", str(tmp_path / "tb")]) == 2
    assert "--minutes must be positive" in capsys.readouterr().err
    assert main(["bench", "timebase", "--reference-noise-ps", "-1", "--out", str(tmp_path / "tb")]) == 2
    assert "--reference-noise-ps must be a finite number >= 0, got -1.0" in capsys.readouterr().err


def test_the_sync_reference_undoes_the_drift_as_the_pulse_does(tmp_path, capsys):
    from acquisition.runstore import open_run
    from reconstruction.cubestore import open_cube

    out = tmp_path / "tb"
    assert main(["bench", "timebase", *TINY, "--minutes", "5", "--reference", "sync", "--seed", "3",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows, summary = _read(out)
    assert "aligned on the laser sync's trigger intervals (0.5 ps RMS measurement noise)" in text
    assert summary["options"]["reference"] == "sync" and summary["options"]["reference_noise_ps"] == 0.5
    assert open_run(out / "seed-3" / "moving.run.zarr").has_sync_reference
    prov = open_cube(out / "seed-3" / "aligned.cube.zarr").attrs["provenance"]
    assert prov["alignment_reference"] == "laser sync trigger intervals"
    med = {c: float(r["median_abs_ratio_to_steady"]) for c, r in rows.items()}
    assert med["aligned"] < 3 and med["unaligned"] > 50 and not any(r["failure"] for r in rows.values())
    assert "without alignment x" in text


def test_pooled_figures_are_those_of_all_the_seeds_pixels_together():
    from streaklab.bench.timebase import delay_errors, direct_delay_errors, pooled_stats

    # two draws of different sizes; each estimate's NaN drops that pixel in every case of its draw
    truth_a = np.array([[100.0, 200.0, 300.0], [400.0, 500.0, 600.0]])
    est_a = {"steady": truth_a + [[3.0, -4.0, 0.0], [1.0, np.nan, 2.0]],
             "aligned": truth_a + [[0.0, 0.0, 80.0], [-1.0, 5.0, 2.0]]}
    mask_a = np.array([[True, True, True], [True, True, False]])
    truth_b = np.array([[10.0, 20.0], [30.0, 40.0]])
    est_b = {"steady": truth_b + [[-60.0, 1.0], [2.0, 0.0]], "aligned": truth_b + [[1.0, np.nan], [-2.0, 0.0]]}
    mask_b = np.ones((2, 2), bool)
    errs = [delay_errors(truth_a, est_a, mask_a)[1], delay_errors(truth_b, est_b, mask_b)[1]]
    pooled = pooled_stats(errs)
    # known answer: steady errors 3, -4, 0, 1 | -60, 2, 0 ; aligned 0, 0, 80, -1 | 1, -2, 0
    assert pooled["steady"]["rmse_ps"] == pytest.approx(math.sqrt((9 + 16 + 0 + 1 + 3600 + 4 + 0) / 7))
    assert pooled["steady"]["median_abs_ps"] == 2.0 and pooled["steady"]["gross"] == 1
    assert pooled["aligned"]["rmse_ps"] == pytest.approx(math.sqrt((6400 + 1 + 1 + 4) / 7))
    assert pooled["aligned"]["median_abs_ps"] == 1.0 and pooled["aligned"]["gross"] == 1
    # the same as one scene made of both draws side by side
    pad = np.full((2, 1), np.nan)
    side = {k: np.hstack([est_a[k], pad, est_b[k]]) for k in est_a}
    _, together = direct_delay_errors(np.hstack([truth_a, pad, truth_b]), side,
                                      np.hstack([mask_a, np.zeros((2, 1), bool), mask_b]))
    for case in ("steady", "aligned"):
        assert pooled[case] == pytest.approx(together[case])
    # a case missing from one draw (its aligned reconstruction failed) has no pooled figure
    partial = pooled_stats([errs[0], {"steady": errs[1]["steady"]}])
    assert math.isnan(partial["aligned"]["rmse_ps"]) and partial["aligned"]["gross"] == -1
    assert partial["steady"] == pytest.approx(pooled["steady"])


def test_each_seed_is_its_own_draw_in_its_own_folder_and_the_grade_pools_them(tmp_path, capsys):
    out = tmp_path / "tb"
    assert main(["bench", "timebase", "--lines", "2", "--x", "16", "--minutes", "5", "--seeds", "1-2",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    pooled, summary = _read(out)
    per_seed = {s: _read(out, s)[0] for s in (1, 2)}
    for s in (1, 2):
        for case in ("steady", "aligned", "unaligned"):
            assert (out / f"seed-{s}" / f"{case}.result.zarr").is_dir()
        assert f"  seed {s}: aligned RMSE x{float(per_seed[s]['aligned']['ratio_to_steady']):.3f} of steady" in text
    assert [e["seed"] for e in summary["seeds"]] == [1, 2] and summary["options"]["seeds"] == [1, 2]
    # two draws: different scenes and noise
    assert per_seed[1]["steady"]["direct_delay_rmse_ps"] != per_seed[2]["steady"]["direct_delay_rmse_ps"]
    n = {s: int(per_seed[s]["steady"]["pixels_counted"]) for s in (1, 2)}
    assert int(pooled["steady"]["pixels_counted"]) == n[1] + n[2] == summary["pixels_counted"]
    for case in ("steady", "aligned", "unaligned"):
        # the pooled RMSE: every pixel weighs the same, whichever draw it came from
        ms = sum(n[s] * float(per_seed[s][case]["direct_delay_rmse_ps"]) ** 2 for s in (1, 2)) / (n[1] + n[2])
        assert float(pooled[case]["direct_delay_rmse_ps"]) == pytest.approx(math.sqrt(ms), rel=1e-9)
        assert int(pooled[case]["pixels_off_by_over_50ps"]) == sum(
            int(per_seed[s][case]["pixels_off_by_over_50ps"]) for s in (1, 2))
    assert summary["ratio_aligned"] == pytest.approx(
        float(pooled["aligned"]["direct_delay_rmse_ps"]) / float(pooled["steady"]["direct_delay_rmse_ps"]))
    assert f"pooled over 2 seeds: direct delay against the scenes' truth over {n[1] + n[2]} lit pixels" in text
    assert f"x{summary['ratio_aligned']:.3f} pooled over 2 seeds" in text
    # a later run over a seed already there is refused before anything is written
    assert main(["bench", "timebase", "--lines", "2", "--x", "16", "--seeds", "3,2", "--out", str(out)]) == 2
    assert f"{out / 'seed-2' / 'steady.run.zarr'} exists" in capsys.readouterr().err
    assert not (out / "seed-3").exists()


@pytest.mark.parametrize("given, said", [
    (["--seeds", "3-1"], "--seeds: the range 3-1 runs backwards (give 1-3)"),
    (["--seeds", "1,x"], "--seeds must be comma-separated non-negative integers or ranges a-b (e.g. 1-8 or 1,2,5), "
                         "got '1,x'"),
    (["--seeds", ""], "--seeds must be comma-separated non-negative integers or ranges a-b"),
    (["--seeds", "1,-2"], "--seeds must be comma-separated non-negative integers or ranges a-b"),
    (["--seeds", "1-3,2"], "--seeds: seed 2 given more than once in '1-3,2'"),
    (["--seed", "3", "--seeds", "1-2"], "give --seed or --seeds, not both (--seed 3 is --seeds 3), got --seed 3 --seeds 1-2"),
    (["--seed", "-1"], "--seed must be a non-negative integer, got -1"),
])
def test_bad_seeds_are_named_in_one_line(tmp_path, capsys, given, said):
    out = tmp_path / "tb"
    assert main(["bench", "timebase", *given, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert said in err and err.strip().count("\n") == 0
    assert not any(out.glob("seed-*"))


def test_seed_lists_keep_their_order():
    from streaklab.bench.arguments import seed_list

    assert seed_list("1-4") == [1, 2, 3, 4]
    assert seed_list(" 7, 0-2 ,5") == [7, 0, 1, 2, 5]
    assert seed_list("3") == [3] and seed_list("4-4") == [4]
