"""What a new user meets first: inputs named for what they are, the packaged example config,
and messages that say what to do."""
import numpy as np
import pytest

from reconstruction.cubestore import write_cube
from streaklab.cli import main


def test_decompose_names_an_hdf5_input_and_how_to_convert_it(tmp_path, capsys):
    from reconstruction.nexus import export_cube

    write_cube(tmp_path / "cube.zarr", np.ones((1, 2, 32), np.float32), time_bin_ps=2.0)
    export_cube(tmp_path / "cube.zarr", tmp_path / "cube.h5")
    assert main(["decompose", str(tmp_path / "cube.h5"), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "HDF5" in err and "--time-bin-ps" not in err and ".npy" not in err
    assert f"streaklab import {tmp_path / 'cube.h5'} --out cube.zarr" in err
    (tmp_path / "notes.txt").write_text("not data")
    assert main(["decompose", str(tmp_path / "notes.txt"), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "neither a cube store" in err and "--time-bin-ps" not in err
    assert not (tmp_path / "r.zarr").exists()


def test_a_taken_output_path_is_refused_in_the_command_lines_words(tmp_path, capsys):
    from reconstruction.nexus import export_cube

    write_cube(tmp_path / "cube.zarr", np.ones((1, 2, 32), np.float32), time_bin_ps=2.0)
    export_cube(tmp_path / "cube.zarr", tmp_path / "cube.h5")
    taken = tmp_path / "taken.zarr"
    taken.mkdir()
    (taken / "notes.txt").write_text("keep me")
    for argv in (["simulate", "--shape", "1", "2", "32", "--out", str(taken)],
                 ["export", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "cube.h5")],
                 ["import", str(tmp_path / "cube.h5"), "--out", str(taken)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.endswith("already exists; pass --overwrite to replace it"), err
        assert "overwrite=True" not in err and len(err.splitlines()) == 1
    assert (taken / "notes.txt").read_text() == "keep me"


def _parser(module, prog):
    import argparse

    parser = argparse.ArgumentParser(prog=prog)
    module.add_arguments(parser)
    return parser


def _benchmark_parsers():
    import importlib

    from streaklab.commands.bench import BENCHMARKS

    return {name: _parser(importlib.import_module(f"streaklab.bench.{name}"), f"streaklab bench {name}")
            for name in BENCHMARKS}


def test_every_option_of_demo_and_the_benchmarks_says_what_it_does():
    from streaklab.commands import demo

    parsers = {"demo": _parser(demo, "streaklab demo"), **_benchmark_parsers()}
    for name, parser in parsers.items():
        for action in parser._actions:
            if action.dest == "help":
                continue
            assert action.help and len(action.help) > 10, (name, action.option_strings or action.dest)


def test_benchmarks_write_under_one_output_folder():
    outs = {name: p.get_default("out") for name, p in _benchmark_parsers().items() if p.get_default("out")}
    assert {"accuracy", "speed", "tradeoff"} <= set(outs)
    assert outs == {name: f"bench-output/{name}" for name in outs}


def test_bench_descriptions_are_not_circular(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    text = capsys.readouterr().out
    lines = {ln.split()[0]: ln.split(None, 1)[1] for ln in text.split("benchmarks:\n", 1)[1].splitlines() if ln.strip()}
    assert set(lines) == {"accuracy", "speed", "tradeoff", "stability", "realism", "counts", "timebase", "adaptive", "spatial",
                          "live"}
    for name, desc in lines.items():
        assert name not in desc and "--help" not in desc, (name, desc)


def test_no_issue_numbers_in_code_output_or_docs():
    import io
    import re
    import tokenize
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pattern = re.compile(r"\bissue[- ]?#?\d|\bissue's\b", re.IGNORECASE)
    found = []
    for pkg in ("acquisition", "reconstruction", "decomposition", "drivers", "streaklab"):
        for path in (root / pkg).rglob("*.py"):
            for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
                if tok.type in (tokenize.STRING, tokenize.COMMENT) or tok.type == getattr(tokenize, "FSTRING_MIDDLE", -1):
                    if pattern.search(tok.string):
                        found.append(f"{path.relative_to(root)}:{tok.start[0]}")
    for path in [root / "README.md", *(root / "docs").glob("*.md")]:
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line):
                found.append(f"{path.relative_to(root)}:{i}")
    assert not found


def test_the_license_is_an_spdx_string_with_a_backend_that_reads_it():
    import re
    import tomllib
    from pathlib import Path

    meta = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    assert meta["project"]["license"] == "BSD-3-Clause"  # PEP 639: a string, not the deprecated table
    (req,) = [r for r in meta["build-system"]["requires"] if r.startswith("setuptools")]
    major = int(re.fullmatch(r"setuptools>=(\d+).*", req).group(1))
    assert major >= 77  # the first setuptools that reads license expressions


def test_the_packaged_example_config_is_reachable_from_any_folder(tmp_path, monkeypatch, capsys):
    from acquisition.config import example_config_path, load_config

    monkeypatch.chdir(tmp_path)
    packaged = example_config_path("sim")
    assert load_config("sim").source == str(packaged)
    assert main(["example-config"]) == 0
    assert capsys.readouterr().out == packaged.read_text()
    assert main(["example-config", "--out", "scan.toml"]) == 0
    assert "streaklab capture --config scan.toml" in capsys.readouterr().err
    assert load_config("scan.toml").data == load_config("sim").data
    assert main(["example-config", "--out", "scan.toml"]) == 2
    assert "already exists; pass --overwrite" in capsys.readouterr().err
    # a missing file says where a configuration can come from
    assert main(["capture", "--config", "nosuch.toml", "--out", "run.zarr", "--simulate"]) == 2
    err = capsys.readouterr().err
    assert "nosuch.toml: cannot read" in err and "example-config" in err and len(err.strip().splitlines()) == 1
    # a file of that name in the folder is what the user means
    (tmp_path / "sim").write_text("[scan]\ncount = 0\n")
    assert main(["capture", "--config", "sim", "--out", "run.zarr", "--simulate"]) == 2
    assert "scan.count" in capsys.readouterr().err


def _readme_session():
    """The commands of the README's "A capture session, end to end" block, as argument lists."""
    import shlex
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = text.split("## A capture session, end to end", 1)[1].split("```", 2)[1]
    commands = []
    for line in block.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            argv = shlex.split(line)
            assert argv[0] == "streaklab", line
            commands.append(argv[1:])
    return commands


def test_the_readme_session_runs_as_written_from_an_empty_folder(tmp_path, monkeypatch, capsys):
    from decomposition.store.resultstore import open_result_store

    session = _readme_session()
    assert [argv[0] for argv in session] == ["capture", "reconstruct", "decompose", "report", "verify"]
    monkeypatch.chdir(tmp_path)
    for argv in session:
        assert main(argv) == 0, (argv, capsys.readouterr().err)
    store = open_result_store(tmp_path / "result.zarr")
    assert store.shape[0] == 16 and store.done_mask().all()
    assert {"frames.png", "maps.png", "profiles.png", "summary.txt"} <= {p.name for p in (tmp_path / "figs").iterdir()}
    assert "pixels: 1024; done 1024 (100.0%); decomposed 1024" in (tmp_path / "figs" / "summary.txt").read_text()


def test_compile_notice_speaks_only_when_numba_compiles():
    import io

    from decomposition.kernels import jit

    ns = {"jit": jit}
    exec("@jit.njit\ndef thrice(x):\n    return 3.0 * x\n", ns)  # no source file: compiled, not cached
    first, second = io.StringIO(), io.StringIO()
    with jit.compile_notice(first, label="test") as watch:
        assert ns["thrice"](2.0) == 6.0
    assert watch.started is not None
    lines = first.getvalue().splitlines()
    assert len(lines) == 2 and lines[0] == f"test: {jit.COMPILE_NOTICE} ..."
    assert lines[1].startswith("test: kernels compiled and cached in ") and lines[1].endswith(" s")
    with jit.compile_notice(second, label="test") as watch:
        assert ns["thrice"](4.0) == 12.0  # already compiled in this process
    assert watch.started is None and second.getvalue() == ""

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    exec("@jit.njit\ndef twice(x):\n    return 2.0 * x\n", ns)
    term = Terminal()
    with jit.compile_notice(term, label="test"):
        assert ns["twice"](2.0) == 4.0
    notice, rest = term.getvalue().split("\n", 1)
    assert notice == f"test: {jit.COMPILE_NOTICE} ..."  # a whole line, whatever the terminal's width
    assert rest.startswith("\rtest: kernels compiled and cached in ")  # drawn over the seconds count


def _seed_cache_without_one_kernel(cache_dir, *, left_out: str) -> int:
    """Copy this process's numba cache of ``decomposition`` into ``cache_dir`` (where a run with
    ``NUMBA_CACHE_DIR=cache_dir`` looks), all but the files of kernel ``left_out``; -> files copied.

    A run on that cache compiles one kernel instead of all of them (a full compile is 30-40 s of
    CPU, and the suite already pays for one): the same first-run path, the notice and the
    caching, for a fraction of the time.  Where the layout cannot be found nothing is copied and
    the run compiles everything, which the test accepts just as well.
    """
    import shutil
    from pathlib import Path

    import numba
    from numba.core import caching

    from decomposition import noise, warmup

    warmup.warm_up(quiet=True)                    # this process's cache is complete (usually it already is)
    pkg = Path(noise.__file__).resolve().parent
    n = 0
    # every folder of the package that holds kernels (the package itself, kernels/, ...)
    for folder in sorted({p.parent for p in pkg.rglob("*.py")}):
        try:
            sub = caching._CacheLocator.get_suitable_cache_subpath(str(folder / "x.py"))
        except AttributeError:
            return n
        source = Path(numba.config.CACHE_DIR) / sub if numba.config.CACHE_DIR else folder / "__pycache__"
        target = Path(cache_dir) / sub
        for f in source.glob("*.nb[ic]"):
            if not f.name.startswith(left_out + "-"):
                target.mkdir(parents=True, exist_ok=True)
                shutil.copy2(f, target / f.name)
                n += 1
    return n


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_the_first_decompose_says_it_compiles_once_and_later_runs_do_not(tmp_path):
    """A numba cache that lacks a kernel (a new install lacks them all): the notice, then
    progress; the next run is silent about it."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from decomposition.evaluation.synthetic import make_cube
    from decomposition.kernels import jit

    root = Path(__file__).resolve().parents[1]
    np.save(tmp_path / "c.npy", make_cube(1, 8, 96, nsr=0.05, seed=1).noisy)
    _seed_cache_without_one_kernel(tmp_path / "numba-cache", left_out="noise._masked_medians")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache"),
           "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "streaklab", "decompose", str(tmp_path / "c.npy"), "--time-bin-ps", "2",
           "--components", "d", "--out", str(tmp_path / "r.zarr"), "--overwrite"]
    first = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    assert first.returncode == 0, first.stderr
    lines = first.stderr.splitlines()
    notice = [i for i, ln in enumerate(lines) if jit.COMPILE_NOTICE in ln]
    done = [i for i, ln in enumerate(lines) if "kernels compiled and cached in" in ln]
    progress = [i for i, ln in enumerate(lines) if "1/1 chunks (100%)" in ln]
    assert len(notice) == 1 and len(done) == 1 and progress, first.stderr
    assert notice[0] < done[0] < progress[0]
    assert "compiled the solver's kernels, once" in first.stdout
    second = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    assert second.returncode == 0, second.stderr
    assert "compil" not in second.stderr + second.stdout and "1/1 chunks (100%)" in second.stderr


def test_accuracy_timings_leave_out_the_first_calls_one_time_cost(monkeypatch):
    from streaklab.bench.accuracy import measure
    from _timing import first_call_costs_a_second

    calls = first_call_costs_a_second(monkeypatch)
    rows, per_pixel, _ = measure(pixels=3, n_bins=64, time_bin_ps=2.0, nsrs=[0.01], noises=["white"],
                                 methods=["convscd"], kinds="a,b,c", seed=0, scenes="legacy", bin_integrated=False)
    # 1 s over 3 pixels would be 0.33 s per pixel
    assert rows[0]["seconds_per_pixel"] < 0.1 and per_pixel["convscd"] < 0.1
    assert len(calls) >= 2  # the slow first call happened, untimed


def test_warm_up_suits_any_time_axis_and_reports_no_compile_once_cached():
    from decomposition.warmup import warm_up

    # a window far too short for its synthetic scenes (0.1 ps bins): the default axis is used instead
    assert warm_up(time_bin_ps=0.1, n_bins=4096, quiet=True) >= 0.0
    assert warm_up(time_bin_ps=50.0, n_bins=16, components=("d", "s"), quiet=True) >= 0.0
    assert warm_up(time_bin_ps=2.0, n_bins=256, quiet=True) == 0.0  # everything is loaded by now


def test_commands_run_with_one_blas_thread_unless_the_user_says_otherwise(monkeypatch, capsys):
    """Beside dask's own threads an idle BLAS pool spins on the same cores; the command sets the
    BLAS pools to one thread before numpy loads, and leaves a user's own setting alone."""
    import os
    import subprocess
    import sys

    from streaklab import cli

    for name in cli.BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert main(["example-config"]) == 0
    capsys.readouterr()
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1" and os.environ["MKL_NUM_THREADS"] == "1"
    assert os.environ["OMP_NUM_THREADS"] == "3"
    # numpy reads the variables once, as it loads: the dispatcher itself must not load it
    probe = subprocess.run([sys.executable, "-c", "import sys, streaklab.cli; print('numpy' in sys.modules)"],
                           capture_output=True, text=True, timeout=60)
    assert probe.stdout.strip() == "False", probe.stderr


def test_counts_are_worded_with_their_plurals():
    from core.words import counted, plural

    assert [counted(n, "pixel") for n in (0, 1, 2, 1024)] == ["0 pixels", "1 pixel", "2 pixels", "1,024 pixels"]
    assert counted(np.int64(1), "pixel chunk") == "1 pixel chunk" and plural(3, "was", "were") == "were"


def test_decompose_words_one_pixel_as_one(tmp_path, capsys):
    from decomposition.evaluation.synthetic import make_cube

    cube = make_cube(1, 2, 128, nsr=0.01, seed=2, kinds="a").noisy
    cube[0, 1, 5] = np.nan
    np.save(tmp_path / "c.npy", cube)
    assert main(["decompose", str(tmp_path / "c.npy"), "--time-bin-ps", "2", "--nan-policy", "omit",
                 "--no-components", "--quiet", "--out", str(tmp_path / "r.zarr")]) == 0
    out = capsys.readouterr().out
    assert "decomposed 1 pixel of a 1 x 2 x 128 cube" in out
    assert "note: 1 pixel had NaN/inf samples and was not decomposed (valid = False)" in out



def test_capturing_the_example_config_without_simulate_says_to_add_it(tmp_path, monkeypatch, capsys):
    """The example's device addresses are placeholders: a capture that cannot reach them says to
    add --simulate; a rig's own address gets no such hint."""
    import contextlib

    import drivers.remoteex
    import drivers.smc100
    from drivers.errors import DriverError

    def refused(host, port, **kw):
        raise DriverError(f"cannot connect to RemoteEx at {host}:{port}: [Errno 111] Connection refused")

    def absent(port, **kw):
        raise DriverError(f"cannot open {port}: no such device")

    monkeypatch.chdir(tmp_path)
    assert main(["example-config", "--out", "scan.toml"]) == 0
    text = (tmp_path / "scan.toml").read_text()
    (tmp_path / "rig.toml").write_text(text.replace('"127.0.0.1:1001"', '"192.168.7.2:1001"'))
    capsys.readouterr()

    def capture(config):
        assert main(["capture", "--config", config, "--out", "run.zarr", "--quiet"]) == 2, config
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and not (tmp_path / "run.zarr").exists(), err
        return err

    monkeypatch.setattr(drivers.remoteex, "RemoteExCamera", refused)
    for config, hint in (("sim", True), ("scan.toml", True), ("rig.toml", False)):
        err = capture(config)
        assert "cannot open the camera at " in err and "Connection refused" in err, err
        assert ("add --simulate to capture from a simulated lab" in err) == hint, (config, err)
    # the camera answers (a sim-lab on the example's port); the example's mirror port does not
    monkeypatch.setattr(drivers.remoteex, "RemoteExCamera", lambda host, port, **kw: contextlib.nullcontext())
    monkeypatch.setattr(drivers.smc100, "SMC100Mirror", absent)
    assert "add --simulate" in capture("sim")
    assert "add --simulate" not in capture("scan.toml")       # a copy's /dev/ttyUSB0 may well be the rig's



def test_an_image_run_warms_up_the_image_stages_before_its_notice_ends(tmp_path, monkeypatch):
    """The command's default run on an image shares the PSF and couples the pixels: its warm-up (before any chunk,
    inside the compile notice) decomposes the warm-up's profiles as one small image with those
    settings too, so the kernels of the image-level stages compile there and not, unannounced,
    in the first chunk (on a fresh install that was about 20 s after "kernels compiled and
    cached in ..." had been printed).  The warm-up is watched, not replaced: the real
    decompositions run."""
    from decomposition import warmup
    from decomposition.evaluation.synthetic import make_cube

    seen = {"warm_up": [], "decompose_image": []}
    real_warm_up, real_image = warmup.warm_up, warmup.decompose_image

    def watched_warm_up(**kw):
        seen["warm_up"].append(kw.get("image"))
        return real_warm_up(**kw)

    def watched_image(cube, *a, **kw):
        seen["decompose_image"].append((np.shape(cube), kw.get("shared"), kw.get("spatial")))
        return real_image(cube, *a, **kw)

    monkeypatch.setattr(warmup, "warm_up", watched_warm_up)
    monkeypatch.setattr(warmup, "decompose_image", watched_image)
    np.save(tmp_path / "c.npy", make_cube(2, 8, 96, nsr=0.05, seed=1).noisy)
    assert main(["decompose", str(tmp_path / "c.npy"), "--time-bin-ps", "2", "--out", str(tmp_path / "r.zarr"),
                 "--quiet"]) == 0
    (image,) = seen["warm_up"]                      # an image's default: the PSF shared, pixels coupled
    assert image["shared"] == ("psf",) and image["psf_map"] is False and image["spatial"]
    assert seen["decompose_image"] and all(len(shape) == 3 and shape[0] == 2 and shared == ("psf",) and spatial
                                          for shape, shared, spatial in seen["decompose_image"])
    # every pixel on its own: no image in the warm-up
    seen["warm_up"].clear()
    seen["decompose_image"].clear()
    assert main(["decompose", str(tmp_path / "c.npy"), "--time-bin-ps", "2", "--out", str(tmp_path / "p.zarr"),
                 "--per-pixel", "--quiet"]) == 0
    assert seen["warm_up"] == [None] and not seen["decompose_image"]
    # a PSF map: the warm-up's few pixels cannot determine one, and it needs no kernels of its own
    assert real_warm_up(image={"shared": ("psf",), "psf_map": True, "spatial": False}, quiet=True) >= 0.0
