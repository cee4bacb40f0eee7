"""``streaklab bench timebase``: a tiny simulated scan under jitter and drift, aligned and not."""
import csv
import json
import math

import pytest

from streaklab.cli import main

pytestmark = pytest.mark.timeout(120)

TINY = ["--lines", "4", "--x", "16", "--t", "256", "--frames", "2"]


def _read(out):
    with open(out / "timebase.csv") as fh:
        rows = {r["case"]: r for r in csv.DictReader(fh)}
    return rows, json.loads((out / "summary.json").read_text())


def test_aligned_direct_delays_beat_unaligned_ones(tmp_path, capsys):
    out = tmp_path / "tb"
    # 10 ps/min over 5 simulated minutes: the fiducial stays in its band
    assert main(["bench", "timebase", *TINY, "--minutes", "5", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows, summary = _read(out)
    assert set(rows) == {"steady", "aligned", "unaligned"}
    rmse = {c: float(r["direct_delay_rmse_ps"]) for c, r in rows.items()}
    assert all(math.isfinite(v) and v > 0 for v in rmse.values()) and not any(r["failure"] for r in rows.values())
    assert summary["lit_exposures"] == 8 and summary["simulated_span_min"] == pytest.approx(5.0)
    # the drift spans ~50 ps: without alignment the delays are off by tens of ps
    assert summary["shift_range_ps"] > 40
    # aligned: most pixels as in the steady scan (a wrong peak taken for the direct in a few can
    # still lift the RMSE); unaligned: every pixel off by the drift
    med = {c: float(r["median_abs_ratio_to_steady"]) for c, r in rows.items()}
    assert med["aligned"] < 3 and med["unaligned"] > 50
    assert int(rows["unaligned"]["pixels_off_by_over_50ps"]) == 0
    assert summary["ratio_aligned"] == pytest.approx(rmse["aligned"] / rmse["steady"])
    assert summary["target"]["met"] == (summary["ratio_aligned"] <= 1.1)
    assert ("  [met] aligned direct-delay RMSE at most 1.1 x the steady scan's: x" in text) == summary["target"]["met"]
    assert ("  [NOT met] aligned direct-delay RMSE at most 1.1 x the steady scan's: x" in text) != summary["target"]["met"]
    assert "without alignment x" in text
    for name in ("steady.result.zarr", "aligned.result.zarr", "unaligned.result.zarr"):
        assert (out / name).is_dir()


def test_a_fiducial_that_leaves_its_band_is_reported_not_met(tmp_path, capsys):
    out = tmp_path / "tb"
    # 100 ps/min over 10 minutes moves the pulse ~1,000 ps: out of the whole window
    assert main(["bench", "timebase", *TINY, "--drift-ps-per-min", "100", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows, summary = _read(out)
    assert "no usable fiducial pulse" in rows["aligned"]["failure"]
    assert summary["ratio_aligned"] is None and summary["target"]["met"] is False
    assert math.isfinite(float(rows["unaligned"]["direct_delay_rmse_ps"]))
    assert "  [NOT met] aligned direct-delay RMSE at most 1.1 x the steady scan's: the aligned reconstruction failed (" in text


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
    assert main(["bench", "timebase", *TINY, "--minutes", "5", "--reference", "sync", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows, summary = _read(out)
    assert "aligned on the laser sync's trigger intervals (0.5 ps RMS measurement noise)" in text
    assert summary["options"]["reference"] == "sync" and summary["options"]["reference_noise_ps"] == 0.5
    assert open_run(out / "moving.run.zarr").has_sync_reference
    prov = open_cube(out / "aligned.cube.zarr").attrs["provenance"]
    assert prov["alignment_reference"] == "laser sync trigger intervals"
    med = {c: float(r["median_abs_ratio_to_steady"]) for c, r in rows.items()}
    assert med["aligned"] < 3 and med["unaligned"] > 50 and not any(r["failure"] for r in rows.values())
    assert "without alignment x" in text
