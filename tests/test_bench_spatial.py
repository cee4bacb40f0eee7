"""``streaklab bench spatial`` on a tiny scene: its named columns, its targets, its table."""
import csv

from streaklab.cli import main


def test_bench_spatial_reports_its_columns_and_targets(tmp_path, capsys):
    out = tmp_path / "spatial"
    assert main(["bench", "spatial", "--methods", "per_pixel,oracle", "--size", "12", "--bins", "200",
                 "--demo-lines", "0", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows = list(csv.DictReader(open(out / "spatial.csv")))
    fid = [r for r in rows if r["method"] in ("per_pixel", "oracle")]
    assert {(r["condition"], r["method"]) for r in fid} == \
        {(c, m) for c in ("white NSR 0.11", "white NSR 0.22", "100 photons", "1000 photons") for m in ("per_pixel", "oracle")}
    for r in fid:
        assert 0.0 < float(r["fidelity"]) <= 1.0 and 0.0 < float(r["edges"]) <= 1.0
    # more photons, a better per-pixel answer
    per = {r["condition"]: float(r["fidelity"]) for r in fid if r["method"] == "per_pixel"}
    assert per["1000 photons"] > per["100 photons"]
    # the spatial spike test finds the 10x spikes the per-pixel one misses; none on pure draws
    spikes = next(r for r in rows if r["condition"] == "spikes")
    assert float(spikes["spatial_recall"]) >= 0.9 > float(spikes["per_pixel_recall"])
    assert float(spikes["spatial_false_pure"]) == 0.0
    echo = next(r for r in rows if r["condition"] == "pooled echoes")
    assert float(echo["recall"]) > float(echo["per_pixel_recall"])
    # the spatial column was not asked for: its targets are not measured, every line says which
    assert "[not measured] white NSR 0.11: spatial >= oracle + 0.02" in text
    assert "[met] spikes flagged in >= 90%" in text


def test_bench_spatial_names_bad_options(tmp_path, capsys):
    assert main(["bench", "spatial", "--methods", "per_pixel,nosuch", "--demo-lines", "0"]) == 2
    assert "--methods" in capsys.readouterr().err
    assert main(["bench", "spatial", "--size", "4"]) == 2
    assert "--size" in capsys.readouterr().err
