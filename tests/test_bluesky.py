"""The Bluesky plan and ophyd-async devices: same run store as ``streaklab capture``, valid documents,
pause / resume / abort without a lost or a duplicated line."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from acquisition.runstore import open_run
from acquisition.session import CaptureError, CaptureSession

import bluesky.plan_stubs as bps
from bluesky import RunEngine
from bluesky.utils import RunEngineInterrupted
from event_model import DocumentNames, schema_validators
from ophyd_async.core import NotConnectedError, get_mock_put, init_devices, set_mock_value

from streaklab.bluesky import scan
from streaklab.bluesky.devices import LaserSyncDevice, ScanMirrorMotor, StreakCameraDetector
from test_capture_resume import write_config

ROOT = Path(__file__).resolve().parents[1]
N_LINES = 4


def assert_same_arrays_but_timestamps(a, b):
    """Every array of two run stores equal, byte for byte, except ``timestamp``."""
    ga, gb = open_run(a).group, open_run(b).group
    names = sorted(ga.array_keys())
    assert names == sorted(gb.array_keys())
    assert {"streaks", "done", "angle_deg", "dark", "time_ps"} <= set(names)
    for name in names:
        if name == "timestamp":
            continue
        x, y = np.asarray(ga[name][...]), np.asarray(gb[name][...])
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), f"{name} differs"


@pytest.fixture
def lab_run(tmp_path):
    """(config path, reference store written by ``streaklab capture --simulate``, new store path)."""
    from streaklab.cli import main

    write_config(tmp_path / "scan.toml", n_lines=N_LINES)
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "reference.zarr"),
                 "--simulate", "--quiet"]) == 0
    return tmp_path / "scan.toml", tmp_path / "reference.zarr", tmp_path / "bluesky.zarr"


def recording_engine():
    RE = RunEngine({})
    docs = []
    RE.subscribe(lambda name, doc: docs.append((name, doc)))
    return RE, docs


def ctrl_c_during_line(monkeypatch, RE, at_line):
    """Press Ctrl-C (SIGINT to this process) while line ``at_line`` is being taken; the line goes on
    once the RunEngine's handler has turned it into a deferred pause (waited for, 5 s at most)."""
    take_line = CaptureSession.take_line

    def take(self, line):
        if line == at_line:
            os.kill(os.getpid(), signal.SIGINT)
            deadline = time.monotonic() + 5.0
            while not RE.deferred_pause_requested and time.monotonic() < deadline:
                time.sleep(0.005)
            assert RE.deferred_pause_requested, "the RunEngine did not take Ctrl-C as a pause request"
        take_line(self, line)
    monkeypatch.setattr(CaptureSession, "take_line", take)


def event_lines(docs):
    return [doc["data"]["streak_camera-line"] for name, doc in docs if name == "event"]


def validate(docs):
    for name, doc in docs:
        schema_validators[DocumentNames(name)].validate(doc)


@pytest.mark.timeout(30)
def test_devices_work_under_mock_init_devices():
    RE = RunEngine({}, call_returns_result=True)
    with init_devices(mock=True):
        camera = StreakCameraDetector(exposure_s=0.01, gain=30, time_range="2")
        mirror = ScanMirrorMotor()
        sync = LaserSyncDevice(repetition_rate_hz=80e6, trigger_delay_ps=100.0, channel=1)
    assert (camera.name, mirror.name, sync.name) == ("camera", "mirror", "sync")

    def plan():
        yield from bps.mv(mirror, 3.5, camera.line, 2, sync.trigger_delay_ps, 250.0)
        yield from bps.trigger(camera, wait=True)
        return {**(yield from bps.read(camera)), **(yield from bps.read(mirror))}

    reading = RE(plan()).plan_result
    assert reading["mirror-user_readback"]["value"] == 3.5
    assert reading["camera-line"]["value"] == 2
    get_mock_put(sync.trigger_delay_ps).assert_called_once_with(250.0)
    set_mock_value(camera.angle_deg, 3.49)
    assert RE(bps.rd(camera.angle_deg)).plan_result == 3.49
    assert set(RE(bps.read(sync)).plan_result) == {"sync-output_enabled"}
    assert RE(bps.rd(sync.repetition_rate_hz)).plan_result == 80e6
    with pytest.raises(NotConnectedError):
        with init_devices():
            without_driver = ScanMirrorMotor()
    assert without_driver.name == "without_driver"


@pytest.mark.timeout(60)
def test_plan_store_equals_capture_and_documents_validate(lab_run):
    config, reference, out = lab_run
    RE, docs = recording_engine()
    RE(scan(config=config, out=out, simulate=True))
    assert_same_arrays_but_timestamps(reference, out)
    assert [name for name, _ in docs] == ["start", "descriptor"] + ["event"] * N_LINES + ["stop"]
    validate(docs)
    start, stop = docs[0][1], docs[-1][1]
    assert start["lines_todo"] == list(range(N_LINES)) and start["run_store"] == str(out)
    assert stop["exit_status"] == "success" and stop["num_events"] == {"primary": N_LINES}
    assert event_lines(docs) == list(range(N_LINES))
    angles = [doc["data"]["streak_camera-angle_deg"] for name, doc in docs if name == "event"]
    np.testing.assert_array_equal(angles, open_run(out)["angle_deg"][...])
    (session,) = open_run(out).attrs["sessions"]
    assert session["status"] == "complete" and session["lines_acquired"] == N_LINES
    assert session["client"] == "bluesky"


@pytest.mark.timeout(60)
def test_ctrl_c_pauses_between_lines_and_resume_completes(lab_run, monkeypatch):
    config, reference, out = lab_run
    RE, docs = recording_engine()

    ctrl_c_during_line(monkeypatch, RE, 1)
    with pytest.raises(RunEngineInterrupted):
        RE(scan(config=config, out=out, simulate=True))
    assert RE.state == "paused"
    assert open_run(out).done_mask().tolist() == [True, True, False, False]
    RE.resume()
    assert RE.state == "idle"
    assert event_lines(docs) == list(range(N_LINES))
    validate(docs)
    assert_same_arrays_but_timestamps(reference, out)
    (session,) = open_run(out).attrs["sessions"]
    assert session["status"] == "complete" and session["lines_acquired"] == N_LINES


@pytest.mark.timeout(60)
def test_a_pause_inside_a_line_neither_loses_nor_repeats_it(lab_run, monkeypatch):
    """An immediate pause while line 2 is being taken: the line still lands once; the replay
    after resume finds it on disk and reports it in one event."""
    config, reference, out = lab_run
    RE, docs = recording_engine()
    take_line = CaptureSession.take_line
    taken = []

    def pause_inside_line_2(self, line):
        if line == 2 and RE.state == "running":
            RE.request_pause(defer=False)            # from the driver thread, as another thread would
        taken.append(line)
        take_line(self, line)
    monkeypatch.setattr(CaptureSession, "take_line", pause_inside_line_2)
    with pytest.raises(RunEngineInterrupted):
        RE(scan(config=config, out=out, simulate=True))
    assert RE.state == "paused"
    RE.resume()
    assert taken == list(range(N_LINES))
    assert event_lines(docs) == list(range(N_LINES))
    assert [doc["seq_num"] for name, doc in docs if name == "event"] == list(range(1, N_LINES + 1))
    validate(docs)
    assert_same_arrays_but_timestamps(reference, out)


@pytest.mark.timeout(60)
def test_abort_then_resumed_scan_takes_only_the_missing_lines(lab_run, monkeypatch):
    config, reference, out = lab_run
    RE, docs = recording_engine()

    ctrl_c_during_line(monkeypatch, RE, 1)
    with pytest.raises(RunEngineInterrupted):
        RE(scan(config=config, out=out, simulate=True))
    RE.abort("operator")
    monkeypatch.undo()
    assert docs[-1][0] == "stop" and docs[-1][1]["exit_status"] == "abort"
    validate(docs)
    run = open_run(out)
    assert run.done_mask().tolist() == [True, True, False, False]
    assert run.attrs["sessions"][0]["status"] == "aborted"

    with pytest.raises(CaptureError, match="already exists; pass --resume"):
        RE(scan(config=config, out=out, simulate=True))
    docs.clear()
    RE(scan(config=config, out=out, simulate=True, resume=True))
    assert docs[0][1]["lines_todo"] == [2, 3]
    assert event_lines(docs) == [2, 3]
    validate(docs)
    assert_same_arrays_but_timestamps(reference, out)
    sessions = open_run(out).attrs["sessions"]
    assert [s["status"] for s in sessions] == ["aborted", "complete"]
    assert sessions[-1]["lines_acquired"] == 2 and sessions[-1]["lines_done_at_start"] == 2


def test_the_core_packages_and_the_cli_load_without_bluesky_or_ophyd_async():
    """The core install stays lean: importing the CLI, every command and every package leaves them
    unloaded (tests/test_layers.py: no module outside streaklab/bluesky imports them)."""
    from test_layers import project_packages

    commands = sorted(p.stem for p in (ROOT / "streaklab" / "commands").glob("*.py") if p.stem != "__init__")
    code = ("import importlib, sys\n"
            f"for name in {project_packages()!r} + ['streaklab.cli'] + "
            f"['streaklab.commands.' + c for c in {commands!r}]:\n"
            "    importlib.import_module(name)\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('bluesky', 'ophyd_async')))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
