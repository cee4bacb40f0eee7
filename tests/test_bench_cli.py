"""``streaklab bench``: dispatch to benchmark modules, and the accuracy benchmark's outputs."""
import csv
import json
import sys
import types

import numpy as np
import pytest

from streaklab.bench.accuracy import largest_nsr_at_level, nsr_grid
from streaklab.cli import main


def test_unknown_and_missing_benchmarks_are_clear_errors(capsys):
    assert main(["bench", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert "unknown benchmark 'nosuch'" in err and "accuracy" in err


def test_dispatches_options_to_the_benchmark_module(monkeypatch):
    seen = {}
    fake = types.ModuleType("streaklab.bench.stability")
    fake.add_arguments = lambda p: p.add_argument("--repeats", type=int, default=1)
    fake.run = lambda args: seen.setdefault("repeats", args.repeats) and 0
    monkeypatch.setitem(sys.modules, "streaklab.bench.stability", fake)
    assert main(["bench", "stability", "--repeats", "7"]) == 0
    assert seen["repeats"] == 7


def test_benchmark_help_lists_its_options(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "accuracy", "--help"])
    assert exc.value.code == 0
    assert "--pixels" in capsys.readouterr().out


def test_nsr_grid_is_log_spaced_with_reference_points():
    g = nsr_grid(10)
    assert g[0] == pytest.approx(0.001) and g[-1] == pytest.approx(0.2)
    assert np.any(np.isclose(g, 0.005)) and np.any(np.isclose(g, 0.055))
    assert np.all(np.diff(g) > 0)
    with pytest.raises(ValueError):
        nsr_grid(1)


def test_largest_nsr_at_level():
    nsr = [0.001, 0.01, 0.1]
    # Crosses 0.9 halfway (in fidelity) between 0.01 and 0.1: log-midpoint sqrt(0.01 * 0.1).
    value, note = largest_nsr_at_level(nsr, [0.99, 0.95, 0.85])
    assert note == "interpolated" and value == pytest.approx(np.sqrt(0.001), rel=1e-9)
    assert largest_nsr_at_level(nsr, [0.8, 0.95, 0.99]) == (None, "below grid")
    assert largest_nsr_at_level(nsr, [0.99, 0.95, 0.91]) == (0.1, "above grid")
    # "Stays": a later recovery above the level does not count.
    value, _ = largest_nsr_at_level(nsr, [0.95, 0.85, 0.95])
    assert 0.001 < value < 0.01


@pytest.mark.timeout(60)
def test_accuracy_quick_writes_csv_png_and_summary(tmp_path, capsys):
    out = tmp_path / "acc"
    assert main(["bench", "accuracy", "--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    with open(out / "accuracy.csv") as fh:
        rows = list(csv.DictReader(fh))
    keys = {(r["method"], r["noise"], float(r["nsr"])) for r in rows}
    assert keys == {(m, n, x) for m in ("convscd", "gradbm") for n in ("white", "pink", "photon")
                    for x in (0.001, 0.055, 0.2)}
    for r in rows:
        f = float(r["mean_fidelity"])
        assert np.isfinite(f) and f <= 1.0
        assert int(r["pixels"]) == 12 and float(r["seconds_per_pixel"]) > 0
        assert {"mean_fidelity[d+s]", "mean_fidelity[d+s+r2]", "mean_fidelity[d+s+r2+r3]"} <= set(r)
    # Nearly clean data decompose well; heavy noise costs fidelity.
    by = {(r["method"], r["noise"], float(r["nsr"])): float(r["mean_fidelity"]) for r in rows}
    for m in ("convscd", "gradbm"):
        assert by[(m, "white", 0.001)] > 0.7 and by[(m, "white", 0.2)] < by[(m, "white", 0.001)]
    assert (out / "accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["largest_nsr_at_level"]) == {f"{m}/{n}" for m in ("convscd", "gradbm")
                                                    for n in ("white", "pink", "photon")}
    assert set(summary["seconds_per_pixel"]) == {"convscd", "gradbm"}
    for m in ("convscd", "gradbm"):
        for n in ("white", "pink", "photon"):
            assert any(line.split()[:2] == [m, n] for line in text.splitlines())
    assert "run time per pixel" in text and "ms" in text


def test_accuracy_bad_options(tmp_path, capsys):
    assert main(["bench", "accuracy", "--quick", "--noise", "brown", "--out", str(tmp_path / "a")]) == 2
    assert "--noise" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert main(["bench", "accuracy", "--quick", "--out", str(tmp_path / "file")]) == 2
    assert "not a folder" in capsys.readouterr().err
