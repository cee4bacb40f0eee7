"""``streaklab bench tradeoff --quick``: runs end to end and writes the CSV and the PNG it promises."""
import argparse
import csv

import numpy as np
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


def _points_under_legends(fig):
    """(legend entry count, point) for every plotted point whose drawn position lies inside a legend."""
    renderer = fig.canvas.get_renderer()
    hidden = []
    for leg_ax in fig.axes:
        leg = leg_ax.get_legend()
        if leg is None:
            continue
        box = leg.get_window_extent(renderer)
        for ax in fig.axes:
            for line in ax.get_lines():
                xy = line.get_xydata()
                if not len(xy) or line.get_marker() in (None, "None", "", " "):
                    continue
                for px, py in ax.transData.transform(xy):
                    if box.contains(px, py):
                        hidden.append((line.get_label(), (px, py)))
    return hidden


def test_the_legends_hide_no_point():
    """Fidelity and error against time for the ConvSCD settings and GradBM's single point: the
    legends sit outside the panels, so every point -- GradBM's among them -- is drawn clear of them."""
    import matplotlib.pyplot as plt

    rows = []
    curves = ("ConvSCD on grid", "ConvSCD on grid + refine", "ConvSCD off-grid", "ConvSCD default",
              "ConvSCD default + refine")
    for nsr in (0.01, 0.05):
        base = {"scene": "fig3", "noise": "white", "nsr": nsr, "oracle_mean_fidelity": 0.97,
                "direct_delay_crb_median_ps": 0.3}
        for c, curve in enumerate(curves):   # the curves fill the panels, from fast and rough to slow and good
            for grid, ms in ((5, 0.3), (10, 0.8), (20, 2.0), (40, 5.0)):
                rows.append(dict(base, method=curve, setting=f"{curve} {grid}", grid=grid,
                                 time_per_pixel_s=ms * (1 + 0.2 * c) / 1e3,
                                 mean_fidelity=0.6 + 0.3 * np.log(ms * 4) / np.log(20) + 0.01 * c,
                                 direct_delay_median_abs_error_ps=0.08 + 0.4 / ms - 0.01 * c,
                                 default=curve == "ConvSCD default" and grid == 10))
        # GradBM: slow and about as good, at the top right, where a legend placed 'best' lands
        rows.append(dict(base, method="GradBM", setting="gradbm", grid=0, time_per_pixel_s=4e-3,
                         mean_fidelity=0.9, direct_delay_median_abs_error_ps=0.2, default=False))
    fig = tradeoff.figure(rows, [0.01, 0.05])
    fig.canvas.draw()
    assert any(line.get_label() == "GradBM" for ax in fig.axes for line in ax.get_lines())
    assert _points_under_legends(fig) == []
    renderer = fig.canvas.get_renderer()
    legends = [ax.get_legend().get_window_extent(renderer) for ax in fig.axes if ax.get_legend()]
    assert len(legends) == 2
    for box in legends:                       # beside the panels, never over one
        assert not any(box.overlaps(ax.get_window_extent(renderer)) for ax in fig.axes)
        assert box.x1 <= fig.bbox.width and box.y0 >= 0
    title = fig.texts[0].get_window_extent(renderer)   # the figure's title is not cut off either
    assert title.x0 >= 0 and title.x1 <= fig.bbox.width
    plt.close(fig)
