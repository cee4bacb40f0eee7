"""Crash safety: kill -9 a real `streaklab capture` process at random points, resume, compare bytes."""
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from acquisition.config import load_config
from acquisition.rig import run_capture, simulated_scene
from acquisition.runstore import open_run

ROOT = Path(__file__).resolve().parents[1]
DATA_ARRAYS = ("streaks", "done", "angle_deg", "target_angle_deg", "dark", "dark_done")


def write_config(path, n_lines=16, **overrides):
    """A TOML scan of the simulated lab at ``path`` (its calibration the simulated sweep) ->
    ScanConfig; ``overrides`` (section -> {key: value}) update the sections' keys."""
    sections = {
        "scan": {"start_deg": -8.0, "stop_deg": 8.0, "count": n_lines},
        "camera": {"frames_per_line": 2, "time_range": 2, "gain": 30},
        "dark": {"frames": 2},
        "devices": {"timeout_s": 2.0},
        "simulation": {"seed": 11, "n_x": 16, "n_t": 64},
        "calibration": {"time_poly_ps": [0.0, 1.0]},
    }
    for name, values in overrides.items():
        sections.setdefault(name, {}).update(values)
    text = lambda: "".join(f"[{name}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in sec.items())
                           for name, sec in sections.items())
    path.write_text(text())
    sections["calibration"]["time_poly_ps"] = [float(c) for c in simulated_scene(load_config(path)).time_calibration]
    path.write_text(text())
    return load_config(path)


def capture_cmd(config_path, out, *extra):
    return [sys.executable, "-m", "streaklab", "capture", "--config", str(config_path), "--out", str(out),
            "--simulate", "--resume", *extra]


def lines_on_disk(out) -> int:
    d = Path(out) / "done" / "c"
    return sum(1 for p in d.iterdir() if not p.name.endswith(".partial")) if d.is_dir() else 0


def assert_same_data(a, b):
    ra, rb = open_run(a), open_run(b)
    for name in DATA_ARRAYS:
        x, y = np.asarray(ra[name][...]), np.asarray(rb[name][...])
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), f"{name} differs"


def run_until(proc, out, lines, extra_s):
    """Wait until ``lines`` lines are on disk (or the process ended), then ``extra_s`` more seconds."""
    deadline = time.monotonic() + 30
    while lines_on_disk(out) < lines and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    time.sleep(extra_s)


@pytest.mark.timeout(90)
def test_killed_and_interrupted_captures_resume_to_identical_bytes(tmp_path):
    cfg = write_config(tmp_path / "scan.toml")
    reference = run_capture(cfg, tmp_path / "reference.zarr", simulate=True)
    assert reference.status == "complete"

    out = tmp_path / "run.zarr"
    rng = np.random.default_rng(2024)
    n = cfg.n_lines
    # SIGKILL once while the process starts up (random time), then twice at random lines, at a
    # random moment inside that line (while its frames are taken or its chunks are written).
    kill_lines = np.sort(rng.choice(np.arange(1, n - 6), 2, replace=False))
    plan = [("time", rng.uniform(0.3, 1.2))] + [("line", int(k), rng.uniform(0.0, 0.06)) for k in kill_lines]
    seen = []
    for step in plan:
        proc = subprocess.Popen(capture_cmd(tmp_path / "scan.toml", out, "--quiet"), cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            if step[0] == "time":
                time.sleep(step[1])
            else:
                run_until(proc, out, step[1], step[2])
            proc.send_signal(signal.SIGKILL)
        finally:
            proc.wait(timeout=30)
        assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()
        proc.stderr.close()
        seen.append(lines_on_disk(out))
    assert all(0 <= s < n for s in seen) and seen[1:] == sorted(seen[1:]) and seen[-1] >= plan[-1][1], seen

    # Ctrl-C: the session finishes the current line, leaves the devices safe and says how to resume.
    proc = subprocess.Popen(capture_cmd(tmp_path / "scan.toml", out), cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        run_until(proc, out, seen[-1] + 2, 0.0)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "stopping after the current line" in err and "resume with:" in err
    assert f"--out {out} --simulate --resume" in err
    assert f"resuming {out}: {seen[-1]} of {n} lines already on disk" in err
    assert f"capture: {seen[-1]}/{n} lines" in err and "lines/s" in err and "left" in err
    done = open_run(out).done_mask()
    assert seen[-1] + 2 <= done.sum() < n and done[:done.sum()].all()        # whole lines, in order
    sessions = open_run(out).attrs["sessions"]
    assert sessions[-1]["status"] == "interrupted"

    r = subprocess.run(capture_cmd(tmp_path / "scan.toml", out), cwd=ROOT, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert f"{n} lines in {out}" in r.stderr
    run = open_run(out)
    assert run.done_mask().all()
    assert run.attrs["sessions"][-1]["status"] == "complete"
    assert not list(out.rglob("*.partial"))
    assert_same_data(tmp_path / "reference.zarr", out)
