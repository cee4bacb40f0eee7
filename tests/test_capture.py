"""Capture sessions against the simulated lab, through the real drivers and transports."""
import copy
import threading

import numpy as np
import pytest

from acquisition.config import parse_config
from acquisition.rig import run_capture, simulated_scene
from acquisition.runstore import open_run
from acquisition.session import CaptureError, CaptureFailed, SettingRejected
from core.model import render_profile
from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.sim import SimulatedLab
from reconstruction.build import reconstruct
from reconstruction.calibrate import resample_uniform


def sim_config(n_lines=4, n_x=16, n_t=64, **sections):
    """A scan of the simulated lab whose calibration is the simulated sweep."""
    raw = {"scan": {"start_deg": -6.0, "stop_deg": 6.0, "count": n_lines},
           "camera": {"frames_per_line": 1, "time_range": 2, "gain": 30, "acquire_timeout_s": 3.0},
           "dark": {"frames": 1}, "devices": {"timeout_s": 0.25},
           "session": {"retries": 2, "retry_backoff_s": 0.0},
           "simulation": {"seed": 3, "n_x": n_x, "n_t": n_t},
           "calibration": {"time_poly_ps": [0.0, 1.0]}}
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    poly = simulated_scene(parse_config(raw)).time_calibration
    raw["calibration"]["time_poly_ps"] = [float(c) for c in poly]
    return parse_config(raw)


def start_lab(config):
    lab = SimulatedLab(seed=config["simulation"]["seed"], scene=simulated_scene(config), mirror=True, sync=True)
    return lab


@pytest.mark.timeout(60)
def test_capture_then_reconstruct_matches_the_scene(tmp_path):
    cfg = sim_config(n_lines=16, n_x=64, n_t=256, camera={"frames_per_line": 2}, dark={"frames": 4})
    result = run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    assert result.status == "complete" and result.acquired == list(range(16))
    run = open_run(tmp_path / "run.zarr")
    assert run.done_mask().all() and run.dark_done()
    np.testing.assert_allclose(run["angle_deg"][...], cfg.angles_deg, atol=1e-3)
    assert set(run.attrs["devices"]) == {"camera", "mirror", "sync"}
    assert run.attrs["sessions"][0]["status"] == "complete"
    # Dark frames saw no light: dark level plus read noise only.
    scene = simulated_scene(cfg)
    assert abs(run["dark"][...].mean() - scene.dark_level) < 1.0

    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    t = cube.time_axis_ps()
    scale = scene.signal_scale(cfg["camera"]["exposure_s"], cfg["camera"]["gain"])
    truth = scale * render_profile(scene.params, t.size, cube.time_bin_ps, cube.t0_ps)      # (y, x, t)
    data = cube.array[...]
    # Noise: Poisson of the signal plus read noise, averaged over 2 frames; dark mean of 4 frames.
    sigma = np.sqrt(np.clip(truth, 0, None) / 2 + scene.read_noise ** 2 / 2 + scene.read_noise ** 2 / 4 + 1 / 12)
    # Against the same signal passed through the same linear interpolation, residuals are pure noise.
    rows = scene.row_times_ps(0.0, 2)
    at_rows = scale * np.stack([scene.clean_line(i) for i in range(scene.n_lines)])
    interp = resample_uniform(at_rows, rows, time_bin_ps=cube.time_bin_ps, t0_ps=cube.t0_ps, n_bins=t.size)
    z = (data - interp) / sigma
    assert abs(z.mean()) < 0.05 and 0.6 < z.std() < 1.1 and np.abs(z).max() < 6.5, (z.mean(), z.std())
    # Against the scene's own clean signal on the uniform grid: within the noise plus a small
    # interpolation error (2 ps rows, 6 ps pulses).
    err = np.abs(data - truth)
    assert np.median(err / sigma) < 1.0
    assert err.max() < 6.5 * sigma.max() and np.abs(data - truth).mean() < 1.5 * sigma.mean()


def test_existing_store_and_changed_config_are_refused(tmp_path):
    cfg = sim_config(n_lines=3)
    stop = threading.Event()
    result = run_capture(cfg, tmp_path / "run.zarr", simulate=True, stop_event=stop,
                         on_line=lambda s, line: stop.set())
    assert result.status == "interrupted" and result.lines_done == 1
    with pytest.raises(CaptureError, match="already exists; pass --resume"):
        run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    other = sim_config(n_lines=3, camera={"exposure_s": 0.02})
    with pytest.raises(CaptureError, match=r"different configuration \(camera\.exposure_s \(0\.01 -> 0\.02\)\)"):
        run_capture(other, tmp_path / "run.zarr", simulate=True, resume=True)
    assert open_run(tmp_path / "run.zarr").done_mask().tolist() == [True, False, False]
    result = run_capture(cfg, tmp_path / "run.zarr", simulate=True, resume=True)
    assert result.status == "complete" and result.acquired == [1, 2]
    sessions = open_run(tmp_path / "run.zarr").attrs["sessions"]
    assert [s["status"] for s in sessions] == ["interrupted", "complete"] and sessions[1]["resumed"]


def test_bad_calibration_for_the_camera_stops_before_any_line(tmp_path):
    # Monotonic over 16 rows would be fine, but the camera has 64: it turns back at row 40.
    raw = copy.deepcopy(sim_config().data)
    raw["calibration"]["time_poly_ps"] = [0.0, 8.0, -0.1]
    cfg = parse_config(raw)
    with pytest.raises(CaptureError, match=r"strictly monotonic over rows 0\.\.63.*64 streak rows"):
        run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    assert not (tmp_path / "run.zarr").exists()


# (simulator, fault kind, command, extra, expected error type)
PERSISTENT_FAULTS = [
    ("camera", "delay", "ImgDataGet", {"delay_s": 0.5}, DeviceTimeout),
    ("camera", "error", "AcqStart", {"code": 7}, DeviceError),
    ("camera", "garbage", "AcqStatus", {}, ProtocolError),
    ("camera", "close", "AcqStart", {}, ConnectionLost),
    ("mirror", "garbage", "TS", {}, ProtocolError),
    ("mirror", "error", "PA", {"code": "V"}, DeviceError),
    ("mirror", "drop_reply", "TP", {}, DeviceTimeout),
    ("sync", "drop_reply", "SYST:ERR?", {}, DeviceTimeout),
    ("sync", "garbage", "SYST:ERR?", {}, ProtocolError),
    ("sync", "close", "SYST:ERR?", {}, ConnectionLost),
]


@pytest.mark.timeout(30)
@pytest.mark.parametrize("device, kind, command, extra, error", PERSISTENT_FAULTS,
                         ids=[f"{d}-{k}-{c}" for d, k, c, _, _ in PERSISTENT_FAULTS])
def test_persistent_fault_stops_cleanly_and_resumes(tmp_path, device, kind, command, extra, error):
    cfg = sim_config(session={"retries": 1})
    retries = cfg["session"]["retries"]
    with start_lab(cfg) as lab:
        sim = {"camera": lab.camera, "mirror": lab.mirror, "sync": lab.sync}[device]

        def arm(session, line):
            if line == 1:          # two lines on disk, then the device breaks for good
                sim.inject(kind, command, times=50, **extra)

        with pytest.raises(CaptureFailed, match=f"line 2 .*failed after {retries + 1} attempts") as info:
            run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=arm)
        assert isinstance(info.value.cause, error)
        assert info.value.lines_done == 2
        run = open_run(tmp_path / "run.zarr")
        assert run.done_mask().tolist() == [True, True, False, False]
        kept = run["streaks"][:2]
        assert run.attrs["sessions"][-1]["status"] == "failed"
        assert lab.state.sync_output_enabled is False          # left safe
        # The device is repaired; the run resumes and completes without touching the finished lines.
        sim.faults.clear()
        result = run_capture(cfg, tmp_path / "run.zarr", lab=lab, resume=True)
        assert result.status == "complete" and result.acquired == [2, 3]
        np.testing.assert_array_equal(open_run(tmp_path / "run.zarr")["streaks"][:2], kept)


@pytest.mark.timeout(30)
def test_transient_faults_are_retried(tmp_path):
    cfg = sim_config()
    with start_lab(cfg) as lab:
        def arm(session, line):
            if line == 0:
                lab.camera.inject("drop_reply", "AcqStatus", times=1)
                lab.mirror.inject("garbage", "TS", times=1)

        result = run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=arm)
    assert result.status == "complete"
    sessions = open_run(tmp_path / "run.zarr").attrs["sessions"]
    assert sessions[0]["retries_used"] >= 1


def test_capture_command_rejects_bad_config_naming_the_key(tmp_path, capsys):
    from streaklab.cli import main

    (tmp_path / "scan.toml").write_text("[scan]\nstart_deg = 0.0\nstop_deg = 1.0\ncount = 0\n"
                                        "[calibration]\ntime_poly_ps = [0.0, 2.0]\n")
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "r.zarr"),
                 "--simulate"]) == 2
    assert "scan.count: must be a positive integer, got 0" in capsys.readouterr().err
    assert not (tmp_path / "r.zarr").exists()


@pytest.mark.timeout(30)
def test_a_rejected_setting_stops_at_once_naming_the_key(tmp_path):
    cfg = sim_config()
    with start_lab(cfg) as lab:
        # rejected once only: a retry would succeed, so the session must not have retried
        lab.sync.inject("error", "PULS0:PER", code=-222, times=1)
        with pytest.raises(SettingRejected, match=r"^sync\.repetition_rate_hz = 80000000\.0: the laser sync rejects "
                                                  r"this setting \(.*-222: Data out of range.*\); nothing was "
                                                  r"acquired") as info:
            run_capture(cfg, tmp_path / "run.zarr", lab=lab)
        assert isinstance(info.value.cause, DeviceError) and info.value.cause.code == -222
        assert not (tmp_path / "run.zarr").exists()
        assert lab.state.sync_output_enabled is False
        lab.camera.inject("error", "DevParamSet", code=7, times=1)
        with pytest.raises(SettingRejected, match=r"^camera\.time_range = 2: the camera rejects this setting"):
            run_capture(cfg, tmp_path / "run.zarr", lab=lab)
        assert not (tmp_path / "run.zarr").exists()


def test_a_rejected_setting_is_one_line_without_a_resume_hint(tmp_path, capsys, monkeypatch):
    from streaklab.cli import main

    cfg = sim_config()
    (tmp_path / "scan.toml").write_text(
        "[scan]\nangles_deg = [0.0, 1.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n"
        "[sync]\nrepetition_rate_hz = 1e12\n[session]\nretry_backoff_s = 0.0\n")
    with start_lab(cfg) as lab:
        import acquisition.rig as rig

        real = rig.run_capture
        monkeypatch.setattr(rig, "run_capture", lambda config, out, **kw: real(config, out, **{**kw, "lab": lab}))
        lab.sync.inject("error", "PULS0:PER", code=-222, times=50)
        assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "r.zarr"),
                     "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("streaklab capture: error: sync.repetition_rate_hz = 1000000000000.0"), err
    assert "safely in" not in err[0] and "resume" not in err[0]
    assert not (tmp_path / "r.zarr").exists()


def test_unreachable_camera_is_named(tmp_path, capsys):
    from streaklab.cli import main

    (tmp_path / "scan.toml").write_text('[devices]\ncamera = "127.0.0.1:1"\ntimeout_s = 0.5\n'
                                        "[scan]\nangles_deg = [0.0, 1.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n")
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "r.zarr")]) == 2
    assert "cannot open the camera at 127.0.0.1:1" in capsys.readouterr().err
    assert not (tmp_path / "r.zarr").exists()


def test_failed_session_tells_how_to_resume(tmp_path, capsys, monkeypatch):
    import acquisition.rig
    from streaklab.cli import main

    def failing(config, out, **kwargs):
        raise CaptureFailed("line 3 (mirror 1 deg) failed after 4 attempts: DeviceTimeout: no reply",
                            cause=DeviceTimeout("no reply"), lines_done=3, n_lines=8)

    monkeypatch.setattr(acquisition.rig, "run_capture", failing)
    (tmp_path / "scan.toml").write_text("[scan]\nangles_deg = [0.0, 1.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n")
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "r.zarr"),
                 "--simulate"]) == 1
    err = capsys.readouterr().err
    assert "failed after 4 attempts: DeviceTimeout" in err and "3 of 8 lines are safely in" in err
    assert f"--out {tmp_path / 'r.zarr'} --simulate --resume" in err


def test_a_failure_before_the_store_exists_does_not_claim_lines_are_in_it(tmp_path, capsys, monkeypatch):
    import acquisition.rig
    from streaklab.cli import main

    def failing(config, out, **kwargs):
        raise CaptureFailed("camera check (identify) failed after 4 attempts: DeviceTimeout: no reply",
                            cause=DeviceTimeout("no reply"), lines_done=0, n_lines=16, store_created=False)

    monkeypatch.setattr(acquisition.rig, "run_capture", failing)
    (tmp_path / "scan.toml").write_text("[scan]\nangles_deg = [0.0, 1.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n")
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "r.zarr")]) == 1
    err = capsys.readouterr().err
    assert "safely in" not in err and "--resume" not in err
    assert f"nothing was written to {tmp_path / 'r.zarr'}; fix the device and run again:" in err


@pytest.mark.timeout(30)
@pytest.mark.parametrize("kind", ["close", "power_cycle"])
def test_a_mirror_replug_or_power_cycle_during_a_capture_is_survived(tmp_path, kind):
    # close: the serial adapter is re-plugged (a new /dev/pts/N behind the stable link) and the
    # PA in flight is lost; power_cycle: the same, and the controller comes back NOT REFERENCED.
    cfg = sim_config(n_lines=3)
    with start_lab(cfg) as lab:
        def arm(session, line):
            if line == 0:
                lab.mirror.inject(kind, "PA")

        result = run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=arm)
        homings = list(lab.mirror.received).count("1OR")
    assert result.status == "complete" and result.acquired == [0, 1, 2]
    run = open_run(tmp_path / "run.zarr")
    np.testing.assert_allclose(run["angle_deg"][:], cfg.angles_deg, atol=1e-6)   # every line where asked
    assert run.attrs["sessions"][0]["retries_used"] >= (1 if kind == "power_cycle" else 0)
    assert homings == (2 if kind == "power_cycle" else 1)                          # re-homed after the reset


@pytest.mark.timeout(30)
@pytest.mark.parametrize("xonxoff", [True, False])
def test_the_rig_opens_the_mirror_on_the_stable_link_with_the_configured_flow_control(xonxoff):
    from acquisition.rig import open_rig

    cfg = sim_config(devices={"mirror_xonxoff": xonxoff})
    with start_lab(cfg) as lab, open_rig(cfg, lab=lab) as (camera, mirror, sync):
        assert mirror.port == lab.mirror_stable_port != lab.mirror_port
        assert mirror.transport.serial.xonxoff is xonxoff


def test_resume_never_deletes_a_folder_streaklab_did_not_mark(tmp_path):
    """A folder whose files all end in .partial is not taken for an interrupted store creation."""
    cfg = sim_config(n_lines=2)
    out = tmp_path / "run.zarr"
    (out / "sub").mkdir(parents=True)
    (out / "sub" / "thesis.tex.partial").write_text("three years of work")
    with pytest.raises(CaptureError, match="neither resumes nor removes it"):
        run_capture(cfg, out, simulate=True, resume=True)
    assert (out / "sub" / "thesis.tex.partial").read_text() == "three years of work"
    # a run store marked as being created (what earlier releases left when killed) is recreated
    import zarr

    zarr.open_group(str(tmp_path / "old.zarr"), mode="w").attrs.update({"streaklab_kind": "run", "initialised": False})
    result = run_capture(cfg, tmp_path / "old.zarr", simulate=True, resume=True)
    assert result.status == "complete" and open_run(tmp_path / "old.zarr").done_mask().all()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []   # no staging left


@pytest.mark.timeout(60)
def test_an_aborted_capture_records_its_end_and_resumes_to_the_same_bytes(tmp_path, capsys, monkeypatch):
    """Ctrl-C twice inside a line (stop, then abort): the session's entry still gets its end and status."""
    import os
    import signal

    from acquisition.session import CaptureSession
    from streaklab.cli import main
    from test_capture_resume import assert_same_data, write_config

    cfg = write_config(tmp_path / "scan.toml", n_lines=5)
    assert run_capture(cfg, tmp_path / "reference.zarr", simulate=True).status == "complete"
    acquire = CaptureSession._acquire_frames

    def ctrl_c_twice_in_line_2(self, n, what, key, also=()):
        if what == "line 2":
            os.kill(os.getpid(), signal.SIGINT)       # stop after the current line
            os.kill(os.getpid(), signal.SIGINT)       # abort it
        return acquire(self, n, what, key, also)

    monkeypatch.setattr(CaptureSession, "_acquire_frames", ctrl_c_twice_in_line_2)
    out = tmp_path / "run.zarr"
    cmd = ["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(out), "--simulate", "--quiet"]
    assert main(cmd) == 130
    assert "aborted; finished lines are safely in" in capsys.readouterr().err
    run = open_run(out)
    assert run.done_mask().tolist() == [True, True, False, False, False]
    (session,) = run.attrs["sessions"]
    assert session["status"] == "aborted" and session["ended_utc"] >= session["started_utc"]
    assert session["lines_acquired"] == 2

    monkeypatch.setattr(CaptureSession, "_acquire_frames", acquire)
    assert main(cmd + ["--resume"]) == 0
    run = open_run(out)
    assert [s["status"] for s in run.attrs["sessions"]] == ["aborted", "complete"]
    assert run.attrs["sessions"][1]["lines_done_at_start"] == 2
    assert_same_data(tmp_path / "reference.zarr", out)
