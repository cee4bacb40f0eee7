"""``streaklab bench tradeoff --quick``: runs end to end and writes the CSV and the PNG it promises."""
import argparse
import csv

import pytest

from _timing import first_call_costs_a_second
from streaklab.bench import tradeoff


@pytest.mark.timeout(90)
def test_quick_tradeoff_writes_csv_and_png(tmp_path, capsys, monkeypatch):
    first_call_costs_a_second(monkeypatch)  # as compiling the kernels does on a fresh install
    parser = argparse.ArgumentParser()
    tradeoff.add_arguments(parser)
    args = parser.parse_args(["--quick", "--out", str(tmp_path)])
    assert tradeoff.run(args) == 0
    rows = list(csv.DictReader(open(tmp_path / "tradeoff.csv")))
    fig3 = [r for r in rows if r["scene"] == "fig3"]
    settings = {r["setting"] for r in fig3}
    # quick: one on-grid density with and without refinement, the default with and without, GradBM
    assert settings == {"convscd grid 10x10 on-grid", "convscd grid 10x10 on-grid + refine",
                        "convscd default, refine off", "convscd default, refine on", "gradbm"}
    assert len(fig3) == len(settings) * 3  # three NSRs, white noise only
    assert {float(r["nsr"]) for r in fig3} == {0.01, 0.055, 0.11}
    assert sum(r["default"] == "True" for r in fig3) == 3  # exactly one default setting per NSR
    iso = [r for r in rows if r["scene"] == "isolated_direct"]
    assert len(iso) == 2 and all(float(r["nsr"]) == 0.05 for r in iso)
    for r in rows:
        assert 0 < float(r["time_per_pixel_s"]) < 1.0 / 12 / 2  # no point carries the first call's second
        assert -1.0 <= float(r["mean_fidelity"]) <= 1.0
        assert float(r["direct_delay_crb_median_ps"]) > 0
        # Every setting beside the oracle on the same data (one oracle value per scene and NSR).
        assert float(r["gap_to_oracle"]) == pytest.approx(float(r["mean_fidelity"]) - float(r["oracle_mean_fidelity"]),
                                                          abs=1e-5)
    for nsr in (0.01, 0.055, 0.11):
        assert len({r["oracle_mean_fidelity"] for r in fig3 if float(r["nsr"]) == nsr}) == 1
    assert float(next(r for r in fig3 if float(r["nsr"]) == 0.01)["oracle_mean_fidelity"]) > 0.95
    # Per regime: the default setting and GradBM beside the oracle; each variable partitions the pixels.
    reg = list(csv.DictReader(open(tmp_path / "regimes.csv")))
    assert {"fidelity[default]", "fidelity[gradbm]", "fidelity[oracle]", "gap[default]", "gap[gradbm]"} <= set(reg[0])
    at = [r for r in reg if float(r["nsr"]) == 0.055]
    for regime in {r["regime"] for r in at}:
        assert sum(int(r["n"]) for r in at if r["regime"] == regime) == 12
    # Refinement of grid-snapped parameters cannot leave the delays on the 2 ps grid.
    on = {float(r["nsr"]): float(r["direct_delay_rmse_ps"]) for r in fig3 if r["setting"] == "convscd grid 10x10 on-grid"}
    ref = {float(r["nsr"]): float(r["direct_delay_rmse_ps"]) for r in fig3
           if r["setting"] == "convscd grid 10x10 on-grid + refine"}
    assert ref[0.01] < on[0.01]
    png = (tmp_path / "tradeoff.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    out = capsys.readouterr().out
    assert "\ntargets:\n" in out and "isolated direct" in out
