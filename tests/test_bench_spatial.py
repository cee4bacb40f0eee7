"""``streaklab bench spatial`` on a tiny scene: its named columns, its targets, its table."""
import csv
import json

import pytest

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


#: the smallest bench: 12 x 12 scenes of 200 bins, the per-pixel column, no demo
TINY = ["--methods", "per_pixel", "--size", "12", "--bins", "200", "--demo-lines", "0"]


def _seed_blocks(text):
    """seed -> its printed target lines, from a ``--seeds`` run's output (blocks "seed N:")."""
    blocks, seed = {}, None
    for line in text.splitlines():
        if line.startswith("seed ") and line.endswith(":"):
            seed = int(line[5:-1])
            blocks[seed] = []
        elif line.startswith("targets over"):
            seed = None
        elif seed is not None and line.startswith("  ["):
            blocks[seed].append(line)
    return blocks


def _without_timings(rows):
    return [{k: v for k, v in r.items() if "px_per_s" not in k} for r in rows]


def test_bench_spatial_grades_each_seed_apart_and_tables_the_targets_over_them(tmp_path, capsys):
    both, one = tmp_path / "both", tmp_path / "one"
    assert main(["bench", "spatial", *TINY, "--seeds", "0-1", "--out", str(both)]) == 0
    text = capsys.readouterr().out
    assert main(["bench", "spatial", *TINY, "--seed", "1", "--out", str(one)]) == 0
    single = capsys.readouterr().out
    rows = list(csv.DictReader(open(both / "spatial.csv")))
    by_seed = {s: [r for r in rows if r["seed"] == s] for s in ("0", "1")}
    assert len(by_seed["0"]) == len(by_seed["1"]) > 0 and len(rows) == 2 * len(by_seed["0"])
    # each seed is its own draw, and seed 1's is the one --seed 1 gives, wherever it comes in the list
    assert _without_timings(by_seed["0"]) != _without_timings(by_seed["1"])
    assert _without_timings(by_seed["1"]) == _without_timings(csv.DictReader(open(one / "spatial.csv")))
    blocks = _seed_blocks(text)
    assert sorted(blocks) == [0, 1]
    assert blocks[1] == [line for line in single.splitlines() if line.startswith("  [")]
    assert "seed 1:" not in single and "targets over" not in single
    # the table over the seeds: each target's figure and verdict per seed, and on how many it is met
    summary = json.loads((both / "summary.json").read_text())
    assert summary["options"]["seeds"] == [0, 1] and [r["seed"] for r in summary["rows"]] == [int(r["seed"]) for r in rows]
    table = text[text.index("targets over 2 seeds"):].splitlines()[2:]
    targets = summary["targets"]
    assert len(targets) == len(blocks[0]) == len(table)
    measured = 0
    for t, line, lines in zip(targets, table, zip(blocks[0], blocks[1])):
        assert [p["seed"] for p in t["seeds"]] == [0, 1]
        marks = [ln.split("]")[0].strip(" [") for ln in lines]
        assert [{True: "met", False: "NOT met", None: "not measured"}[p["met"]] for p in t["seeds"]] == marks
        assert all(f"{t['text']}: {p['detail']}" in ln for p, ln in zip(t["seeds"], lines))
        assert line.strip().startswith(t["text"])
        if t["measured_on"]:
            measured += 1
            k = marks.count("met")
            assert t["met_on"] == k and line.endswith(f"  {k} of 2 seeds")
            for p in t["seeds"]:
                assert f"{p['value']} {'met' if p['met'] else 'NOT'}" in line
        else:
            assert line.endswith("  not measured") and line.count("n/m") == 2
    assert measured == 4      # the pooled echoes and the spikes: the per-pixel column's targets


@pytest.mark.parametrize("given, said", [
    (["--seeds", "2-1"], "--seeds: the range 2-1 runs backwards (give 1-2)"),
    (["--seeds", ""], "--seeds must be comma-separated non-negative integers or ranges a-b"),
    (["--seeds", "0,a"], "--seeds must be comma-separated non-negative integers or ranges a-b (e.g. 1-8 or 1,2,5), "
                         "got '0,a'"),
    (["--seeds", "0-2,1"], "--seeds: seed 1 given more than once in '0-2,1'"),
    (["--seed", "0", "--seeds", "0-1"], "give --seed or --seeds, not both (--seed 0 is --seeds 0), got --seed 0 --seeds 0-1"),
    (["--seed", "-1"], "--seed must be a non-negative integer, got -1"),
])
def test_bench_spatial_names_bad_seeds_in_one_line(tmp_path, capsys, given, said):
    out = tmp_path / "spatial"
    assert main(["bench", "spatial", *TINY, *given, "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert said in captured.err and captured.err.strip().count("\n") == 0
    assert captured.out == "" and not out.exists()
