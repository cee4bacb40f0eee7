"""Staged writes: what killed runs leave beside an output is cleaned by the next run, and only that."""
import subprocess
import sys
from pathlib import Path

from reconstruction.cubestore import open_cube, write_cube
from core.staging import clean_stale_staging, staged_output

ROOT = Path(__file__).resolve().parents[1]

KILLED_WRITER = """
import os, signal, sys
import core.staging as staging
from reconstruction.cubestore import write_cube
import numpy as np
out, where = sys.argv[1], sys.argv[2]
real = os.replace
def replace(a, b):
    real(a, b)
    if where == "between" and ".old-" in str(b):    # the old output moved aside, the new one not yet in
        os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
with staging.staged_output(out, overwrite=True) as tmp:
    write_cube(tmp, np.full((2, 2, 4), 7.0), time_bin_ps=1.0)
    if where == "writing":
        os.kill(os.getpid(), signal.SIGKILL)
"""


def _killed_write(out, where):
    proc = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(out), where], cwd=ROOT,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, capture_output=True)
    assert proc.returncode == -9, proc.stderr.decode()


def _hidden(d):
    return sorted(p.name for p in d.iterdir() if p.name.startswith("."))


def test_the_next_run_cleans_what_killed_runs_left(tmp_path):
    out = tmp_path / "cube.zarr"
    write_cube(out, [[[1.0, 2.0]]], time_bin_ps=1.0)
    for _ in range(3):
        _killed_write(out, "writing")
    left = _hidden(tmp_path)          # each run cleaned the one before: only the last one's pair is left
    assert len(left) == 2 and any(".partial-" in n for n in left) and any(n.endswith(".json") for n in left)
    assert open_cube(out).array[0, 0, 1] == 2.0                     # the old cube is untouched
    foreign = tmp_path / ".cube.zarr.partial-0badc0de"               # no marker: not ours to delete
    foreign.mkdir()
    (foreign / "keep.txt").write_text("x")
    write_cube(tmp_path / "other.zarr", [[[3.0, 4.0]]], time_bin_ps=1.0, overwrite=True)  # no staging
    with staged_output(tmp_path / "another.zarr") as tmp:
        write_cube(tmp, [[[5.0, 6.0]]], time_bin_ps=1.0)
    assert _hidden(tmp_path) == [foreign.name]


def test_a_kill_between_the_renames_gives_the_old_output_back(tmp_path):
    out = tmp_path / "cube.zarr"
    write_cube(out, [[[1.0, 2.0]]], time_bin_ps=1.0)
    _killed_write(out, "between")
    assert not out.exists() and any(".old-" in n for n in _hidden(tmp_path))
    clean_stale_staging(tmp_path)
    assert open_cube(out).array[0, 0, 1] == 2.0 and _hidden(tmp_path) == []


def test_a_running_owner_is_left_alone(tmp_path):
    with staged_output(tmp_path / "a.zarr") as tmp:
        tmp.mkdir()
        (tmp / "x").write_text("in progress")
        assert clean_stale_staging(tmp_path) == [] and (tmp / "x").exists()   # this process owns it
    assert _hidden(tmp_path) == []
