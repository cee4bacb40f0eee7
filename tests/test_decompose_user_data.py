"""What a new user meets in ``decompose`` and ``report``: damaged or unseen input stops the run in
one line (never NaN taken for data), and the command's messages count what they say."""
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from _cubes import TB, small_cube, worker_dies_at
from _runs import SLOW_SOLVE_SITE, wait_for_done_chunks
from core.integrity import create_array
from decomposition.store.resultstore import open_result_store
from reconstruction.cubestore import create_cube, open_cube, verify_cube, write_cube
from streaklab.cli import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cube(tmp_path):
    write_cube(tmp_path / "cube.zarr", small_cube(4, 6, nt=96, seed=3), time_bin_ps=TB, chunks=(2, 3))
    return tmp_path / "cube.zarr"


def test_a_missing_input_chunk_stops_decompose_and_names_it(cube, tmp_path, capsys):
    (cube / "cube" / "c" / "1" / "1" / "0").unlink()     # zarr would read the fill value, NaN
    out = tmp_path / "res.zarr"
    assert main(["decompose", str(cube), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"streaklab decompose: error: {cube}: array 'cube', chunk (1, 1, 0) is missing"), err
    assert f"run 'streaklab verify {cube}'" in err[0]
    assert not out.exists()                               # stopped before anything was written


def _partial_cube(path):
    """A 6 x 4 cube of (2, 4) chunks whose lines 2 and 3 were never captured (NaN, line_valid False)."""
    data = small_cube(6, 4, nt=96, seed=5)
    data[2:4] = np.nan
    cube = create_cube(path, data.shape, time_bin_ps=TB, t0_ps=TB, chunks=(2, 4))
    cube.array[...] = data
    valid = np.ones(6, bool)
    valid[2:4] = False
    create_array(cube.group, "line_valid", shape=(6,), dtype="bool", dimension_names=["y"])[:] = valid
    return path


def test_chunks_of_unfinished_lines_may_be_absent_any_other_may_not(tmp_path, capsys):
    cube = _partial_cube(tmp_path / "part.zarr")
    (cube / "cube" / "c" / "1" / "0" / "0").unlink()     # lines 2-3: never captured
    assert verify_cube(open_cube(cube)).ok
    out = tmp_path / "res.zarr"
    assert main(["decompose", str(cube), "--out", str(out), "--quiet"]) == 0
    store = open_result_store(out)
    valid = store.group["valid"][...]
    assert store.done_mask().all() and not valid[2:4].any() and valid[[0, 1, 4, 5]].all()
    capsys.readouterr()
    (cube / "cube" / "c" / "2" / "0" / "0").unlink()     # lines 4-5 were captured: damage
    assert [str(d) for d in verify_cube(open_cube(cube)).damaged] == ["cube chunk (2, 0, 0): missing"]
    assert main(["decompose", str(cube), "--out", str(tmp_path / "res2.zarr"), "--quiet"]) == 2
    assert "array 'cube', chunk (2, 0, 0) is missing" in capsys.readouterr().err


def test_report_refuses_a_result_store_whose_finished_chunks_lost_their_files(cube, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    assert main(["decompose", str(cube), "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    shutil.rmtree(out / "direct" / "c" / "1")             # pixel chunks (1, 0) and (1, 1) of 'direct'
    assert main(["report", str(out), "--out", str(tmp_path / "figs")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pixel chunks (1, 0), (1, 1) are marked done but direct chunk files are missing" \
        in err[0], err
    assert f"streaklab verify {out} --mark-for-resume" in err[0]
    assert not (tmp_path / "figs" / "frames.png").exists()


@pytest.fixture
def worker_elsewhere(tmp_path, monkeypatch):
    """A plain tcp:// cluster on 127.0.0.1 whose one worker process runs in another folder."""
    import logging

    from distributed import LocalCluster

    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL + 1)
    monkeypatch.chdir(tmp_path)
    try:
        yield cluster
    finally:
        cluster.close()


@pytest.mark.timeout(120)
def test_a_relative_input_reaches_a_worker_in_another_folder(cube, tmp_path, worker_elsewhere, capsys):
    from distributed import Client

    from decomposition.store.cluster import ClusterError, check_workers_see

    address = worker_elsewhere.scheduler_address
    assert main(["decompose", "cube.zarr", "--out", "r.zarr", "--quiet", "--scheduler", address]) == 0
    store = open_result_store(tmp_path / "r.zarr")
    assert store.done_mask().all() and store.group["valid"][...].all()      # not 24 "valid NaN" pixels
    assert "NaN/inf" not in capsys.readouterr().out
    # a worker that cannot open the input is named, with the path, before anything is computed
    with Client(address, timeout="10s") as client:
        worker = next(iter(client.scheduler_info()["workers"]))
        with pytest.raises(ClusterError, match=f"the dask worker {worker} cannot see {tmp_path}/gone.zarr: every "
                                               f"worker must open the input by the same absolute path"):
            check_workers_see(client, [str(tmp_path / "gone.zarr"), str(cube)], timeout_s=10)
        check_workers_see(client, [str(cube)], timeout_s=10)


def test_a_partial_cube_counts_and_times_only_the_pixels_it_decomposed(tmp_path, capsys):
    cube = _partial_cube(tmp_path / "part.zarr")          # 24 pixels, 8 on the two unfinished lines
    assert main(["decompose", str(cube), "--out", str(tmp_path / "res.zarr"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "decomposed 16 pixels of a 6 x 4 x 96 cube" in out, out
    assert "note: 8 pixels had NaN/inf samples and were not decomposed" in out
    assert "note: 8 of them lie on scan lines the capture did not finish (line_valid False in the cube)" in out


def test_after_resume_the_notes_count_the_whole_store(tmp_path, monkeypatch, capsys):
    data = small_cube(4, 6, nt=96, seed=3)
    data[0, 0, 7] = data[3, 5, 9] = data[3, 4, 9] = np.nan  # chunks (0, 0) and (1, 1) of (2, 3)
    write_cube(tmp_path / "nan.zarr", data, time_bin_ps=TB, chunks=(2, 3))
    out = tmp_path / "res.zarr"
    revive = worker_dies_at(monkeypatch, 2)
    with pytest.raises(RuntimeError, match="worker died"):
        main(["decompose", str(tmp_path / "nan.zarr"), "--out", str(out), "--threads", "1", "--quiet"])
    revive()
    first = open_result_store(out)
    assert int(first.done_chunks().sum()) == 1
    nan_before = int((first.done_mask() & ~first.group["valid"][...]).sum())
    capsys.readouterr()
    assert main(["decompose", str(tmp_path / "nan.zarr"), "--out", str(out), "--resume", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert f"decomposed {18 - (3 - nan_before)} pixels" in printed      # this run: 3 chunks, its NaN pixels skipped
    assert "the notes count the whole store: the 3 chunks of this run and the 1 chunk done before it" in printed
    assert "note: 3 pixels had NaN/inf samples" in printed, printed     # the store: all three


# every chunk's solve slowed down, so that the run is reliably still going when the signal arrives
_SLOW = ("import sys, time; import decomposition.store.chunked as c; f = c.solve_block; "
         "c.solve_block = lambda *a, **k: (time.sleep(0.3), f(*a, **k))[1]; "
         "from streaklab.cli import main; sys.exit(main(sys.argv[1:]))")


@pytest.mark.timeout(90)
def test_sigterm_keeps_the_finished_chunks_counts_them_exactly_and_prints_the_resume_command(cube, tmp_path):
    out = tmp_path / "res.zarr"
    args = ["decompose", "cube.zarr", "--out", "res.zarr", "--threads", "2", "--chunks", "1", "3",
            "--option", "sparsity=0.05"]
    proc = subprocess.Popen([sys.executable, "-c", _SLOW, *args], cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_done_chunks(out, 2, proc)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    n_done = int(open_result_store(out).done_chunks().sum())
    assert 2 <= n_done < 8
    assert f"decompose: interrupted; {n_done}/8 chunks are on disk in {out}; rerun with --resume" in err, err
    command = ("streaklab decompose cube.zarr --out res.zarr --threads 2 --chunks 1 3 --option sparsity=0.05 "
               "--resume")
    assert f"streaklab decompose: terminated; resume with:\n  {command}" in err, err
    assert "Traceback" not in err
    # the command printed continues the run
    done = subprocess.run([sys.executable, "-m", "streaklab", *command.split()[1:]], cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert f"{n_done}/8 chunks already done" in done.stderr
    assert open_result_store(out).done_mask().all()


@pytest.mark.timeout(120)
def test_ctrl_c_under_scheduler_counts_the_chunks_after_the_cluster_settles(cube, tmp_path, monkeypatch):
    import logging

    from distributed import LocalCluster

    (tmp_path / "site").mkdir()                           # the workers solve each chunk but their first slowly
    (tmp_path / "site" / "sitecustomize.py").write_text(SLOW_SOLVE_SITE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path / "site"), str(ROOT)]))
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL + 1)
    out = tmp_path / "res.zarr"
    try:
        proc = subprocess.Popen([sys.executable, "-m", "streaklab", "decompose", str(cube), "--out", str(out),
                                 "--chunks", "1", "3", "--scheduler", cluster.scheduler_address], cwd=ROOT,
                                env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            wait_for_done_chunks(out, 1, proc)
            time.sleep(0.3)                               # the workers are inside their next chunks
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 130, err
        n_done = int(open_result_store(out).done_chunks().sum())
        assert f"decompose: interrupted; {n_done}/8 chunks are on disk in {out}; rerun with --resume" in err, err
        time.sleep(2.0)                                   # longer than a chunk: nothing lands afterwards
        assert int(open_result_store(out).done_chunks().sum()) == n_done < 8
    finally:
        cluster.close()


def test_the_resume_command_repeats_the_words_typed_without_overwrite():
    from argparse import Namespace

    from streaklab.commands.decompose import resume_command

    typed = ["decompose", "my cube.zarr", "--out", "r.zarr", "--overwr", "--option", "sparsity=0.05"]
    assert resume_command(Namespace(command_words=typed)) == \
        "streaklab decompose 'my cube.zarr' --out r.zarr --option sparsity=0.05 --resume"
    again = ["decompose", "c.zarr", "--out", "r.zarr", "--resume"]
    assert resume_command(Namespace(command_words=again)) == "streaklab decompose c.zarr --out r.zarr --resume"
