"""``streaklab bench live``: a tiny capture pair with and without --live, and the live result's check."""
import csv
import json

import numpy as np
import pytest
import zarr

from streaklab.cli import main

pytestmark = pytest.mark.timeout(120)


def test_bench_live_times_a_pair_and_checks_the_live_result_byte_for_byte(tmp_path, capsys,
                                                                           live_worker_at_normal_priority):
    from acquisition.runstore import open_run
    from streaklab.bench.live import _offline_differences, last_line_on_disk

    out = tmp_path / "live"
    assert main(["bench", "live", "--lines", "2", "--pairs", "1", "--warmup", "0", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "count = 2\n" in (out / "scan.toml").read_text()
    with open(out / "live.csv") as fh:
        rows = list(csv.DictReader(fh))
    summary = json.loads((out / "summary.json").read_text())
    assert [(r["pair"], r["mode"], r["order"]) for r in rows] == [("1", "without", "1"), ("1", "with --live", "2")]
    times = {r["mode"]: float(r["capture_s"]) for r in rows}
    assert all(t > 0 for t in times.values()) and all(float(r["drain_s"]) >= 0 for r in rows)
    assert summary["ratios"] == [pytest.approx(times["with --live"] / times["without"])]
    assert summary["median_ratio"] == summary["ratios"][0]
    # the last line on disk: after the last line's acquisition ended, well before the next capture
    for name in ("pair1.plain.run.zarr", "pair1.live.run.zarr"):
        run = open_run(out / name, mode="r")
        assert run.done_mask().all() and run.n_lines == 2
        lag = last_line_on_disk(out / name) - float(np.max(run["timestamp"][...]))
        assert -0.01 <= lag < 1.0
    # printed: the pair, the median, both targets (the timing judged, whatever it is)
    lines = text.splitlines()
    pair = [ln for ln in lines if ln.split()[:1] == ["1"]]
    assert len(pair) == 1 and pair[0].endswith(f"x{summary['ratios'][0]:.3f}")
    assert any(ln.startswith(f"median ratio x{summary['median_ratio']:.3f}") for ln in lines)
    mark = "[met]" if summary["median_ratio"] <= 1.05 else "[NOT met]"
    assert f"  {mark} capture with --live at most 1.05 x the time without it" in text
    assert summary["targets"]["speed_met"] == (mark == "[met]")
    assert ("  [met] the live result equals reconstruct + decompose --per-pixel --chunks 1 NX of its run, byte for byte "
            "in every array (each of the 1 live run(s)): every array the same") in text
    assert summary["differing_arrays"] == {"1": []}

    # the check tells a live result one value off
    g = zarr.open_group(str(out / "pair1.live.result.zarr"), mode="r+")
    g["direct_amplitude"][0, 3] = np.float32(-12345.0)          # no fit gives a negative amplitude
    assert _offline_differences(out / "pair1.live.run.zarr", tmp_path / "c.zarr", tmp_path / "r.zarr",
                                out / "pair1.live.result.zarr") == ["direct_amplitude (bytes differ)"]


def test_bench_live_refuses_bad_options_and_earlier_stores(tmp_path, capsys):
    assert main(["bench", "live", "--pairs", "0", "--out", str(tmp_path / "a")]) == 2
    assert "--pairs must be at least 1, got 0" in capsys.readouterr().err
    assert main(["bench", "live", "--lines", "0", "--out", str(tmp_path / "a")]) == 2
    assert "--lines must be at least 1, got 0" in capsys.readouterr().err
    (tmp_path / "b" / "pair1.live.result.zarr").mkdir(parents=True)
    assert main(["bench", "live", "--out", str(tmp_path / "b")]) == 2
    assert "pair1.live.result.zarr exists" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["pair1.live.result.zarr"]
