"""``streaklab bench realism``: effects of real photon counts beside the Poisson reference."""
import csv
import json

import numpy as np
import pytest

from decomposition.synthetic import make_profiles
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
    assert keys == {(e, p, v) for e in realism.EFFECTS for p in (300.0, 10000.0) for v in ("ignored", "reference")}
    for r in rows:
        assert r["status"] == "ok"
        f = float(r["mean_fidelity"])
        assert np.isfinite(f) and f <= 1.0
        assert float(r["direct_found"]) > 0
    ref = {(r["effect"], float(r["photons_per_pixel"])): r for r in rows if r["variant"] == "reference"}
    for effect in realism.EFFECTS:
        lo, hi = ref[(effect, 300.0)], ref[(effect, 10000.0)]
        # The reference is its own yardstick, and more photons give it smaller errors.
        assert float(lo["lifetime_rmse_over_reference"]) == pytest.approx(1.0)
        assert float(hi["direct_delay_rmse_ps"]) < float(lo["direct_delay_rmse_ps"])
        assert float(hi["mean_fidelity"]) > float(lo["mean_fidelity"])
    assert np.isfinite(float(ref[("echo", 10000.0)]["echo_found"]))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["variants"] == ["ignored", "reference"] and summary["quick"]
    assert {c["met"] for c in summary["target_checks"]} <= {True, False, None}
    assert "targets (" in text and "bias within 1 %" in text


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


def test_bad_options(tmp_path):
    assert main(["bench", "realism", "--quick", "--effects", "fog", "--out", str(tmp_path / "a")]) == 2
    assert main(["bench", "realism", "--quick", "--variants", "best", "--out", str(tmp_path / "b")]) == 2
    assert main(["bench", "realism", "--photons", "100,-3", "--out", str(tmp_path / "c")]) == 2
