"""``streaklab demo`` end to end (small settings) and ``streaklab bench speed`` on a tiny cube."""
import argparse
import json
import re

import numpy as np
import pytest

from decomposition.store.resultstore import open_result_store
from streaklab.cli import CommandError, main
from streaklab.commands.demo import class_fidelity


def test_class_fidelity_scores_each_class_against_its_truth():
    rng = np.random.default_rng(0)
    truth = {"direct": rng.random((3, 16)), "sss": np.zeros((3, 16)), "interreflections": rng.random((3, 1, 16))}
    truth["sss"][0] = 1.0
    perfect = class_fidelity(truth, {k: v.copy() for k, v in truth.items()})
    assert perfect["all"]["mean"] == 1.0 and perfect["direct"]["mean"] == 1.0
    assert perfect["sss"]["pixels"] == 1 and perfect["interreflections"]["pixels"] == 3
    no_sss = {k: v.copy() for k, v in truth.items()}
    no_sss["sss"][:] = 0.0
    f = class_fidelity(truth, no_sss)
    assert f["sss"]["mean"] == 0.0 and f["direct"]["mean"] == 1.0 and f["all"]["mean"] < 1.0


@pytest.mark.timeout(120)
def test_demo_captures_reconstructs_decomposes_and_prints_fidelities(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["demo", "--out", str(out), "--lines", "3", "--nx", "16", "--nt", "128", "--quiet"]) == 0
    printed = capsys.readouterr().out
    for step in ("[1/5] capture", "[2/5] reconstruct", "[3/5] decompose", "[4/5] report", "[5/5] fidelity"):
        assert step in printed
    for name in ("run.zarr", "cube.zarr", "result.zarr", "figs/frames.png", "figs/maps.png", "figs/profiles.png",
                 "figs/summary.txt", "fidelity.json"):
        assert (out / name).exists(), name
        assert str(out / name) in printed
    fid = json.loads((out / "fidelity.json").read_text())["fidelity"]
    for cls in ("all", "direct", "sss", "interreflections"):
        assert f"mean fidelity {fid[cls]['mean']:.3f}  ({fid[cls]['pixels']} pixels" in printed
    assert fid["direct"]["pixels"] == 48 and fid["all"]["pixels"] == 48
    assert fid["direct"]["mean"] > 0.5  # the simulated scene's wall is recovered
    store = open_result_store(out / "result.zarr")
    assert store.done_mask().all()
    assert (out / "notes.txt").read_text() == "mine"


def _tree(path):
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.timeout(120)
def test_demo_replaces_only_what_an_earlier_demo_wrote_there(tmp_path, capsys):
    import shutil

    from test_reconstruct import make_run

    out = tmp_path / "demo"
    tiny = ["--source", "simulate", "--lines", "2", "--nx", "4", "--nt", "128", "--quiet"]
    out.mkdir()
    run = make_run(out / "run.zarr")                 # a capture of one's own, where the demo puts its run
    mine = _tree(out / "run.zarr")
    assert main(["demo", "--out", str(out), *tiny]) == 2
    err = capsys.readouterr().err
    assert f"refusing to replace {out / 'run.zarr'} (a run store): an earlier 'streaklab demo' did not write it" in err
    assert not (out / "cube.zarr").exists()
    assert main(["demo", "--out", run.path, *tiny]) == 2          # nor into a store, nor inside one
    assert "refusing to write files into" in capsys.readouterr().err
    assert main(["demo", "--out", f"{run.path}/demo", *tiny]) == 2
    assert "lies inside the Zarr store" in capsys.readouterr().err
    assert _tree(out / "run.zarr") == mine and sorted(p.name for p in out.iterdir()) == ["run.zarr"]

    # its own outputs are replaced on a rerun (make demo, twice in a row); nothing else is touched
    shutil.move(out / "run.zarr", tmp_path / "mine.zarr")
    (out / "notes.txt").write_text("mine")
    assert main(["demo", "--out", str(out), *tiny]) == 0
    assert main(["demo", "--out", str(out), *tiny]) == 0
    assert (out / "notes.txt").read_text() == "mine" and open_result_store(out / "result.zarr").done_mask().all()
    # a file put into one of its products is not the demo's to delete
    (out / "result.zarr" / "look.png").write_bytes(b"png")
    (out / "figs" / "mine.png").write_bytes(b"png")
    assert main(["demo", "--out", str(out), *tiny]) == 2
    assert "look.png" in capsys.readouterr().err and (out / "result.zarr" / "look.png").exists()
    (out / "result.zarr" / "look.png").unlink()
    assert main(["demo", "--out", str(out), *tiny]) == 2
    assert "(mine.png)" in capsys.readouterr().err and (out / "figs" / "mine.png").read_bytes() == b"png"


@pytest.mark.timeout(120)
def test_demo_on_a_synthetic_cube(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--source", "simulate", "--out", str(out), "--lines", "4", "--nx", "12", "--nt", "128",
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "[1/5] simulate" in printed and not (out / "run.zarr").exists()
    fid = json.loads((out / "fidelity.json").read_text())["fidelity"]
    assert f"mean fidelity {fid['all']['mean']:.3f}" in printed
    assert fid["direct"]["pixels"] == 48 and fid["all"]["pixels"] == 48
    assert fid["all"]["mean"] > 0.7 and fid["direct"]["mean"] > 0.8
    assert open_result_store(out / "result.zarr").done_mask().all()


@pytest.mark.timeout(120)
def test_bench_speed_runs_on_a_tiny_cube(tmp_path, capsys, monkeypatch):
    from streaklab.bench import speed

    parser = argparse.ArgumentParser()
    speed.add_arguments(parser)
    # from a folder outside the repository, with a relative --out
    monkeypatch.chdir(tmp_path)
    # The paper's scenes (sigma up to 10 ps) do not fit 64 bins: a clear error; the legacy ones do.
    args = parser.parse_args(["--shape", "2", "16", "64", "--methods", "gradbm", "--workers", "threads:1",
                              "--chunks", "1", "16", "--out", "bench-rel"])
    with pytest.raises(CommandError, match="too short"):
        speed.run(args)
    args = parser.parse_args(["--shape", "2", "16", "64", "--methods", "gradbm", "--workers", "threads:1",
                              "--chunks", "1", "16", "--scenes", "legacy", "--out", "bench-rel"])
    assert speed.run(args) == 0
    printed = capsys.readouterr().out
    tmp_path = tmp_path / "bench-rel"
    report = json.loads((tmp_path / "speed.json").read_text())
    (run,) = report["runs"]
    assert run["method"] == "gradbm" and run["pixels"] == 32 and run["chunks_done"] == 2
    assert run["pixels_per_s"] > 0 and run["peak_rss_tree_mib"] > 10 and report["floor"]["pixels_per_s"] > 0
    assert "FFT floor" in printed and "paper-size 600x672x512" in printed
    assert not list(tmp_path.glob("work-*"))  # the synthetic cube and results are cleaned up
    (line,) = [ln for ln in printed.splitlines() if ln.startswith("gradbm") and "all stages" in ln]
    (stages,) = report["stages"]
    assert stages["method"] == "gradbm" and stages["pixels"] == 32 and stages["stage_seconds"]["detect"] > 0
    peak = float(re.search(r"peak memory ([\d,]+) MiB \(one process\)", line).group(1).replace(",", ""))
    assert peak == pytest.approx(run["peak_rss_mib"], abs=1) and peak >= run["peak_rss_one_process_mib"] - 1


@pytest.mark.timeout(120)
def test_bench_speed_hands_solver_options_to_every_run_and_judges_no_target_then(tmp_path, capsys):
    from streaklab.bench import speed

    parser = argparse.ArgumentParser()
    speed.add_arguments(parser)
    common = ["--shape", "2", "16", "64", "--methods", "convscd", "--workers", "threads:2", "--chunks", "1", "16",
              "--scenes", "legacy", "--out", str(tmp_path)]
    with pytest.raises(CommandError, match="no_such_option"):
        speed.run(parser.parse_args(common + ["--option", "no_such_option=1"]))
    with pytest.raises(CommandError, match="KEY=VALUE"):
        speed.run(parser.parse_args(common + ["--option", "rescue"]))
    with pytest.raises(CommandError, match="n_polish"):        # a bad value, before the cube is written
        speed.run(parser.parse_args(common + ["--option", "n_polish=-1"]))
    with pytest.raises(CommandError, match="--stage-pixels must be 0"):
        speed.run(parser.parse_args(common + ["--stage-pixels", "-1"]))
    assert not (tmp_path / "speed.json").exists() and not list(tmp_path.glob("work-*"))
    assert speed.run(parser.parse_args(common + ["--option", "rescue=false", "--option", "n_polish=10"])) == 0
    printed = capsys.readouterr().out
    report = json.loads((tmp_path / "speed.json").read_text())
    assert report["options"] == {"rescue": False, "n_polish": 10}
    # the stage breakdown runs with the same options: no second pass
    (stages,) = report["stages"]
    assert stages["pixels"] == 32 and stages["stage_seconds"]["rescue"] < 0.01 * stages["seconds"]
    (run,) = report["runs"]
    assert run["pixels"] == 32 and run["chunks_done"] == 2
    assert "target, convscd" not in printed and "the target is judged on the defaults" in printed
    # the options reached the solver: the result store records them
    assert speed.run(parser.parse_args(common + ["--option", "n_polish=10", "--keep"])) == 0
    from decomposition.store.resultstore import open_result_store
    attrs = open_result_store(tmp_path / "result-convscd-threads2.zarr").attrs
    assert attrs["options"]["n_polish"] == 10


def test_bench_speed_memory_line_states_one_peak_that_bounds_its_parts():
    from streaklab.bench.speed import memory_text

    # the 50 ms samples of the process tree missed a peak that one process's ru_maxrss saw
    s = {"scheduler": "processes", "peak_rss_tree_mib": 532.0, "peak_rss_one_process_mib": 647.0,
         "peak_rss_mib": 647.0}
    text = memory_text(s)
    total, one = (float(v) for v in re.findall(r"([\d,.]+) MiB", text))
    assert total >= one and total == 647 and "all processes" in text and "532" not in text


@pytest.mark.timeout(120)
def test_bench_speed_repeat_runs_each_configuration_in_rounds_and_judges_the_median(tmp_path, capsys):
    from streaklab.bench import speed

    parser = argparse.ArgumentParser()
    speed.add_arguments(parser)
    common = ["--shape", "2", "16", "64", "--methods", "gradbm", "--workers", "threads:1,threads:2",
              "--chunks", "1", "16", "--scenes", "legacy", "--out", str(tmp_path)]
    with pytest.raises(CommandError, match="--repeat must be at least 1"):
        speed.run(parser.parse_args(common + ["--repeat", "0"]))
    assert speed.run(parser.parse_args(common + ["--repeat", "2", "--stage-pixels", "0"])) == 0
    printed = capsys.readouterr().out
    report = json.loads((tmp_path / "speed.json").read_text())
    runs = report["runs"]
    # rounds: each configuration once per round, in the same order
    assert [(r["round"], r["workers"]) for r in runs] == [(0, 1), (0, 2), (1, 1), (1, 2)]
    assert report["repeat"] == 2 and len(report["summaries"]) == 2
    for m in report["summaries"]:
        pps = sorted(r["pixels_per_s"] for r in runs if r["workers"] == m["workers"])
        assert m["runs"] == 2 and m["pixels_per_s_min"] == pps[0] and m["pixels_per_s_max"] == pps[1]
        assert m["pixels_per_s_median"] == pytest.approx(0.5 * (pps[0] + pps[1]))
    assert "round 2 of 2" in printed and printed.count("over 2 runs: median") == 2
    assert report["stages"] == [] and "where the time goes" not in printed
    assert not (tmp_path / "stages.png").exists()
