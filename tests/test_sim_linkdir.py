"""The mirror simulator's /tmp link folders: marked with their owner, cleaned up after killed runs."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from core.owner import owner_record
from drivers.sim.linkdir import MARKER, PREFIX, make_link_dir, remove_stale_link_dirs
from drivers.sim.mirror import MirrorSimulator

pytestmark = pytest.mark.timeout(30)
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def tmpdir_here(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    return tmp_path


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def dead_owner() -> str:
    return json.dumps(dict(owner_record(), pid=dead_pid(), started=None))


def test_only_marked_folders_of_gone_processes_are_removed(tmpdir_here):
    stale = Path(make_link_dir())
    (stale / MARKER).write_text(dead_owner())
    os.symlink("/dev/pts/999", stale / "ttySMC100")
    live = Path(make_link_dir())                                  # this process: still running
    unmarked = tmpdir_here / f"{PREFIX}unmarked"
    unmarked.mkdir()
    extra = Path(make_link_dir())
    (extra / MARKER).write_text(dead_owner())
    (extra / "notes.txt").write_text("someone else's file")       # not only the simulator's entries
    garbled = Path(make_link_dir())
    (garbled / MARKER).write_text("{not json")
    foreign = Path(make_link_dir())
    (foreign / MARKER).write_text(json.dumps(dict(json.loads(dead_owner()), producer="someone-else")))
    elsewhere = Path(make_link_dir())       # another machine's process (shared /tmp): cannot tell
    (elsewhere / MARKER).write_text(json.dumps(dict(json.loads(dead_owner()), host="other-host")))
    other = tmpdir_here / "unrelated-dir"
    other.mkdir()
    os.symlink(str(other), tmpdir_here / f"{PREFIX}link")           # a link, not a folder

    assert remove_stale_link_dirs() == [str(stale)]
    assert not stale.exists()
    for kept in (live, unmarked, extra, garbled, foreign, elsewhere, other, tmpdir_here / f"{PREFIX}link"):
        assert os.path.lexists(kept), kept
    assert (extra / "notes.txt").exists()


def test_a_recycled_pid_does_not_keep_a_folder(tmpdir_here):
    folder = Path(make_link_dir())
    owner = json.loads((folder / MARKER).read_text())
    assert owner["pid"] == os.getpid()
    if owner["started"] is None:
        pytest.fail("no /proc start time on this system: the recycled-pid check cannot work")
    owner["started"] = str(int(owner["started"]) - 1)   # same pid, another (earlier) process
    (folder / MARKER).write_text(json.dumps(owner))
    assert remove_stale_link_dirs() == [str(folder)]


def test_a_killed_simulator_leaves_a_folder_the_next_one_removes(tmpdir_here):
    env = dict(os.environ, TMPDIR=str(tmpdir_here), PYTHONPATH=str(ROOT))
    child = subprocess.Popen(
        [sys.executable, "-c",
         "import sys; from drivers.sim.mirror import MirrorSimulator\n"
         "sim = MirrorSimulator().start(); print(sim.stable_port, flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, text=True)
    try:
        link = child.stdout.readline().strip()
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(10)
        child.stdin.close()
        child.stdout.close()
    left = Path(link).parent
    assert left.parent == tmpdir_here and left.exists()          # killed: nothing cleaned up
    with MirrorSimulator() as sim:
        assert not left.exists()
        mine = Path(sim.stable_port).parent
        assert mine.exists() and (mine / MARKER).exists()
    assert not mine.exists()
