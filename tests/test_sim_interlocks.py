"""MCP gain interlocks (focus mode, end of acquisition, fault, Ctrl-C, shutdown) and the
``[simulation]`` time-base keys, against the simulated lab that logs its gain."""
import numpy as np
import pytest

from acquisition.config import ConfigError, parse_config
from acquisition.live import LiveOptions, LiveView
from acquisition.rig import run_capture, start_simulated_lab
from acquisition.runstore import open_run
from acquisition.session import CaptureFailed
from drivers.remoteex import RemoteExCamera
from drivers.sim import SimulatedLab
from drivers.sim.timebase import FIDUCIAL_PIXELS, TimeBase
from test_capture import sim_config, start_lab

pytestmark = pytest.mark.timeout(60)
GAIN = 30


def gains(lab):
    return [g for _, g, _ in lab.gain_log()]


# ------------------------------------------------------------------ capture
def test_the_gain_is_zero_after_a_capture_ends_and_was_the_configured_one_while_it_ran(tmp_path):
    cfg = sim_config(camera={"gain": 37})
    seen = []
    with start_lab(cfg) as lab:
        result = run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=lambda s, line: seen.append(lab.camera.gain))
        assert result.status == "complete"
        assert seen == [37] * cfg.n_lines
        assert lab.camera.gain == 0 and gains(lab)[-1] == 0


def test_the_gain_is_zero_after_a_fault_and_set_again_before_the_next_frames(tmp_path):
    cfg = sim_config(n_lines=3)
    seen = []
    with start_lab(cfg) as lab:
        def arm(session, line):
            seen.append(lab.camera.gain)
            if line == 0:
                lab.camera.inject("drop_reply", "AcqStatus", times=1)       # one fault in line 1, retried

        assert run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=arm).status == "complete"
        # the simulated camera starts at the configured gain: on during the lines, 0 after the
        # fault, on again for the retried line, 0 at the end
        assert lab.scene.reference_gain == GAIN
        assert gains(lab) == [GAIN, 0, GAIN, 0]
        assert seen == [GAIN] * 3


def test_the_gain_is_zero_after_a_capture_fails(tmp_path):
    cfg = sim_config(session={"retries": 1})
    with start_lab(cfg) as lab:
        def arm(session, line):
            if line == 1:
                lab.camera.inject("close", "AcqStart", times=50)

        with pytest.raises(CaptureFailed):
            run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=arm)
        lab.camera.faults.clear()
        assert lab.camera.gain == 0 and GAIN in gains(lab)


def test_the_gain_is_zero_after_ctrl_c(tmp_path):
    cfg = sim_config()
    with start_lab(cfg) as lab:
        def interrupt(session, line):
            if line == 1:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            run_capture(cfg, tmp_path / "run.zarr", lab=lab, on_line=interrupt)
        assert lab.camera.gain == 0 and GAIN in gains(lab)


def test_a_capture_without_a_configured_gain_refuses_a_camera_left_at_zero(tmp_path):
    raw_cfg = sim_config()
    data = {k: dict(v) for k, v in raw_cfg.data.items()}
    del data["camera"]["gain"]
    data["scan"] = {"angles_deg": data["scan"]["angles_deg"]}
    cfg = parse_config(data)
    with start_lab(cfg) as lab:
        assert run_capture(cfg, tmp_path / "a.zarr", lab=lab).status == "complete"     # the camera's own 30
        with pytest.raises(Exception, match="camera.gain: not set, and the camera's MCP gain is 0"):
            run_capture(cfg, tmp_path / "b.zarr", lab=lab)


# ------------------------------------------------------------------ driver and live view
def test_the_driver_sets_the_gain_to_zero_on_shutdown_and_before_focus_mode():
    with SimulatedLab(seed=0, mirror=False, sync=False) as lab:
        with RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
            cam.configure(gain=45)
            assert lab.camera.gain == 45
        assert lab.camera.gain == 0 and gains(lab)[-2:] == [45, 0]
        with RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
            cam.configure(gain=45)
            cam.set_streak_mode("Focus")
            assert lab.camera.focus and lab.camera.gain == 0
        # every logged moment in Focus mode has the gain at 0
        assert all(g == 0 for _, g, mode in lab.gain_log() if mode == "Focus")


def test_the_live_view_in_focus_mode_runs_at_gain_zero_and_leaves_it_there():
    with SimulatedLab(seed=0, mirror=False, sync=False) as lab:
        lab.state.sync_output_enabled = True
        with RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
            cam.configure(gain=GAIN)
            during = []
            LiveView(cam, LiveOptions(frames=2, rate_hz=50.0, focus=True)).run(
                lambda frame: during.append((lab.camera.gain, lab.camera.focus)))
            assert during == [(0, True), (0, True)]
            assert lab.camera.gain == 0 and not lab.camera.focus
            LiveView(cam, LiveOptions(frames=1, rate_hz=50.0)).run(lambda frame: None)
            assert lab.camera.gain == 0                                  # 0 after the live acquisition ends
        assert all(g == 0 for _, g, mode in lab.gain_log() if mode == "Focus")


# ------------------------------------------------------------------ config
def test_simulation_time_base_keys_are_parsed_and_start_the_lab_with_them(tmp_path):
    cfg = sim_config(simulation={"jitter_ps": 2, "drift_ps_per_min": -5.0, "sweep_nonlinearity": 0.02,
                                 "shading": 0.1, "clock_speed": 60, "fiducial": True})
    assert cfg["simulation"]["jitter_ps"] == 2.0 and cfg["simulation"]["fiducial"] is True
    lab = start_simulated_lab(cfg)
    try:
        assert lab.timebase == TimeBase(jitter_ps=2.0, drift_ps_per_min=-5.0, sweep_nonlinearity=0.02,
                                        shading=0.1, clock_speed=60.0, fiducial=True)
        assert run_capture(cfg, tmp_path / "run.zarr", lab=lab).status == "complete"
        n_frames = len(lab.camera.frame_shifts)
    finally:
        lab.close()
    run = open_run(tmp_path / "run.zarr")
    where = run.attrs["fiducial"]
    assert where == lab.fiducial_nominal() and (where["x_start"], where["x_stop"]) == (0, FIDUCIAL_PIXELS)
    assert n_frames == cfg.n_lines                  # one shift per lit frame (the dark frames have no light)
    # the fiducial is in the captured lines where recorded
    lines = run["streaks"][:, 0].astype(np.float64)                   # (line, x, t)
    profile = lines[:, :FIDUCIAL_PIXELS].mean(axis=(0, 1))
    assert abs(int(np.argmax(profile[: lines.shape[-1] // 4])) - where["row"]) <= 1.5


def test_a_plain_config_keeps_its_hash_and_records_no_fiducial(tmp_path):
    cfg = sim_config()
    assert "fiducial" not in cfg["simulation"]
    assert sim_config(simulation={"fiducial": False}).hash != cfg.hash      # named keys are part of the data
    with start_lab(cfg) as lab:
        run_capture(cfg, tmp_path / "run.zarr", lab=lab)
    assert "fiducial" not in open_run(tmp_path / "run.zarr").attrs


@pytest.mark.parametrize("key, value, message", [
    ("jitter", 1.0, r"^simulation\.jitter: unknown key \(known keys: "),
    ("jitter_ps", -1.0, r"^simulation\.jitter_ps: must be a jitter RMS in ps"),
    ("drift_ps_per_min", "fast", r"^simulation\.drift_ps_per_min: must be a drift"),
    ("sweep_nonlinearity", 0.3, r"^simulation\.sweep_nonlinearity: must be a fraction of the window in \(-0.25, 0.25\)"),
    ("shading", 1.0, r"^simulation\.shading: must be a number in \[0, 1\), got 1.0$"),
    ("clock_speed", 0, r"^simulation\.clock_speed: must be a positive clock speed"),
    ("fiducial", "yes", r"^simulation\.fiducial: must be true or false"),
])
def test_bad_simulation_keys_get_one_line_naming_the_key(key, value, message):
    with pytest.raises(ConfigError, match=message) as info:
        sim_config(simulation={key: value})
    assert "\n" not in str(info.value)


def test_the_capture_command_reports_a_bad_simulation_key_in_one_line(tmp_path, capsys):
    from streaklab.cli import main

    (tmp_path / "scan.toml").write_text(
        '[scan]\nangles_deg = [0.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n[simulation]\nshading = 2.0\n')
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "r.zarr"),
                 "--simulate"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "simulation.shading: must be a number in [0, 1)" in err[0]
