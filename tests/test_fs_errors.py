"""File-system trouble and damaged stores: one line naming the problem, and the resume command where data are safe."""
import errno
from pathlib import Path

import numpy as np
import pytest

from _cubes import TB, small_cube
from acquisition.config import parse_config
from acquisition.runstore import RunStore, create_run, open_run
from decomposition.store.resultstore import ResultStore, open_result_store
from reconstruction.cubestore import write_cube
from streaklab.cli import main

SCAN = ("[scan]\nangles_deg = [0.0, 1.0, 2.0, 3.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n"
        "[simulation]\nn_x = 4\nn_t = 32\n[session]\nretry_backoff_s = 0.0\n")


def _lines(capsys):
    return capsys.readouterr().err.strip().splitlines()


@pytest.fixture
def cube(tmp_path):
    write_cube(tmp_path / "cube.zarr", small_cube(3, 3, seed=1), time_bin_ps=TB, chunks=(1, 3))
    return tmp_path / "cube.zarr"


def test_outputs_that_cannot_be_written_are_one_line(tmp_path, cube, capsys, monkeypatch):
    (tmp_path / "afile").write_text("x")
    assert main(["decompose", str(cube), "--out", str(tmp_path / "afile" / "r.zarr"), "--quiet"]) == 2
    assert _lines(capsys) == [f"streaklab decompose: error: cannot write {tmp_path / 'afile' / 'r.zarr'}: "
                              f"a file stands where a folder should be"]
    assert main(["decompose", str(cube), "--out", "/proc/r.zarr", "--quiet"]) == 2
    assert _lines(capsys) == ["streaklab decompose: error: cannot write /proc/r.zarr: No such file or directory"]
    assert main(["export", str(cube), "--out", "/proc/c.h5"]) == 2
    assert _lines(capsys) == ["streaklab export: error: cannot write /proc/c.h5: No such file or directory"]
    (tmp_path / "scan.toml").write_text(SCAN)
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--simulate", "--quiet",
                 "--out", str(tmp_path / "afile" / "run.zarr")]) == 2
    assert _lines(capsys)[-1] == (f"streaklab capture: error: cannot write the run store "
                                  f"{tmp_path / 'afile' / 'run.zarr'}: a file stands where a folder should be")

    import decomposition.store.resultstore as rs

    def read_only(path, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(Path(path).parent / ".r.zarr.partial-0123abcd"))

    monkeypatch.setattr(rs, "create_result_store", read_only)
    assert main(["decompose", str(cube), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 2
    assert _lines(capsys) == [f"streaklab decompose: error: cannot write {tmp_path / 'r.zarr'}: Read-only file system"]


def _full_disk_on_call(real, n):
    """``real``, failing with ENOSPC from its n-th call on."""
    calls = []

    def fail(*args, **kwargs):
        calls.append(1)
        if len(calls) >= n:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    return fail


@pytest.mark.timeout(60)
def test_a_full_disk_during_capture_keeps_the_lines_and_says_how_to_resume(tmp_path, capsys, monkeypatch):
    real = RunStore.write_line
    (tmp_path / "scan.toml").write_text(SCAN)
    out = tmp_path / "run.zarr"
    monkeypatch.setattr(RunStore, "write_line", _full_disk_on_call(real, 3))
    argv = ["capture", "--config", str(tmp_path / "scan.toml"), "--simulate", "--quiet", "--out", str(out)]
    assert main(argv) == 1
    err = _lines(capsys)
    assert f"streaklab capture: error: line 2: cannot write it to {out}: no space left on the device" in err
    assert "streaklab capture: 2 of 4 lines are safely in" in err[-2] and "free space on that disk and resume" in err[-2]
    assert err[-1].strip().endswith(f"--out {out} --simulate --resume")
    assert open_run(out).done_mask().tolist() == [True, True, False, False]
    monkeypatch.setattr(RunStore, "write_line", real)
    assert main(argv + ["--resume"]) == 0
    assert open_run(out).done_mask().all()


def test_a_full_disk_during_decompose_counts_the_chunks_and_says_how_to_resume(tmp_path, cube, capsys,
                                                                               monkeypatch):
    real = ResultStore.write_chunk
    out = tmp_path / "r.zarr"
    monkeypatch.setattr(ResultStore, "write_chunk", _full_disk_on_call(real, 2))
    assert main(["decompose", str(cube), "--out", str(out), "--threads", "1"]) == 2
    err = _lines(capsys)
    n_done = int(open_result_store(out).done_chunks().sum())
    assert n_done == 1
    assert f"decompose: stopped; 1/3 chunks are on disk in {out}; fix the problem below and rerun with --resume" \
           in err[-2]
    assert err[-1] == "streaklab decompose: error: cannot write: no space left on the device"
    monkeypatch.setattr(ResultStore, "write_chunk", real)
    assert main(["decompose", str(cube), "--out", str(out), "--resume", "--quiet"]) == 0
    assert open_result_store(out).done_mask().all()


def test_damaged_array_metadata_is_named_in_one_line(tmp_path, capsys):
    raw = {"scan": {"angles_deg": [0.0, 1.0]}, "dark": {"frames": 1}, "calibration": {"time_poly_ps": [0.0, 2.0]}}
    run = create_run(tmp_path / "run.zarr", parse_config(raw), image_shape=(4, 32))
    run.write_dark(np.full((1, 4, 32), 100, np.uint16))
    for i in range(2):
        run.write_line(i, np.random.default_rng(i).integers(0, 4000, (1, 4, 32)).astype(np.uint16),
                       angle_deg=float(i), timestamp=0.0)
    (tmp_path / "run.zarr" / "done" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "arr')
    assert main(["reconstruct", str(tmp_path / "run.zarr"), "--out", str(tmp_path / "c.zarr")]) == 2
    assert _lines(capsys) == [f"streaklab reconstruct: error: {tmp_path / 'run.zarr'}/done: unreadable array "
                              f"metadata (JSONDecodeError: Unterminated string starting at: line 1 column 33 "
                              f"(char 32)); the store is damaged"]
    assert not (tmp_path / "c.zarr").exists()


def test_damaged_cube_and_result_metadata_are_named_in_one_line(tmp_path, cube, capsys):
    out = tmp_path / "r.zarr"
    assert main(["decompose", str(cube), "--out", str(out), "--quiet"]) == 0
    (out / "valid" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "arr')
    for argv in (["decompose", str(cube), "--out", str(out), "--resume", "--quiet"],
                 ["report", str(out), "--out", str(tmp_path / "figs")]):
        assert main(argv) == 2
        err = _lines(capsys)
        assert len(err) == 1 and err[0].endswith(f"{out}/valid: unreadable array metadata (JSONDecodeError: "
                                                 f"Unterminated string starting at: line 1 column 33 (char 32)); "
                                                 f"the store is damaged"), err
    (cube / "cube" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "arr')
    assert main(["decompose", str(cube), "--out", str(tmp_path / "r2.zarr"), "--quiet"]) == 2
    assert _lines(capsys) == [f"streaklab decompose: error: not a usable cube: {cube}/cube: unreadable array "
                              f"metadata (JSONDecodeError: Unterminated string starting at: line 1 column 33 "
                              f"(char 32)); the store is damaged"]
    assert not (tmp_path / "r2.zarr").exists()
