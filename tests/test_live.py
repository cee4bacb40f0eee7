"""``streaklab live``: live frames of the simulated camera, headless output, and Ctrl-C."""
import os
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from acquisition.config import parse_config
from acquisition.live import LiveOptions
from acquisition.rig import simulated_scene
from drivers.sim.camera import RemoteExSimulator
from drivers.sim.state import LabState
from streaklab.cli import main

pytestmark = pytest.mark.timeout(60)
ROOT = Path(__file__).resolve().parents[1]


def write_config(tmp_path, camera="127.0.0.1:1001", **camera_section):
    cam = {"exposure_s": 0.01, "time_range": 2, "gain": 30, **camera_section}
    lines = ["[scan]", "start_deg = -6.0", "stop_deg = 6.0", "count = 4", "[camera]"]
    lines += [f"{k} = {v!r}" if isinstance(v, str) else f"{k} = {v}" for k, v in cam.items()]
    lines += ["[devices]", f'camera = "{camera}"', "timeout_s = 2.0",
              "[simulation]", "seed = 1", "n_x = 16", "n_t = 64",
              "[calibration]", "time_poly_ps = [0.0, 1.0]"]
    path = tmp_path / "live.toml"
    path.write_text("\n".join(lines).replace("'", '"') + "\n")
    return path


def scene_for(path):
    import tomllib
    return simulated_scene(parse_config(tomllib.loads(Path(path).read_text())))


def test_live_shows_frames_and_time_profiles_of_the_simulated_scene(tmp_path, capsys):
    cfg = write_config(tmp_path)
    png, npz = tmp_path / "live.png", tmp_path / "live.npz"
    assert main(["live", "--config", str(cfg), "--simulate", "--frames", "3", "--fps", "50", "--no-window",
                 "--png", str(png), "--npz", str(npz)]) == 0
    out = capsys.readouterr()
    status = [line for line in out.out.splitlines() if line.startswith("live frame")]
    assert len(status) == 3 and "image 16x64" in status[0]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    shown = np.load(npz)
    scene = scene_for(cfg)
    line = scene.line_index(0.0)                            # the simulated mirror rests at 0 deg
    expected = scene.expected_counts(line, exposure_s=0.01, gain=30)
    assert shown["image"].shape == (16, 64)
    assert np.abs(shown["image"] - expected).mean() < 5.0
    np.testing.assert_allclose(shown["profile"], expected.mean(axis=0), atol=4 * 30 / np.sqrt(16))
    np.testing.assert_allclose(shown["row_times_ps"], scene.row_times_ps(0.0, 2), rtol=1e-6)   # camera's table


def test_live_focus_mode_on_one_pixel_is_undone_afterwards(tmp_path, capsys):
    scene = scene_for(write_config(tmp_path))
    with RemoteExSimulator(LabState(sync_output_enabled=True), scene, seed=1) as sim:
        cfg = write_config(tmp_path, camera=f"{sim.host}:{sim.port}")
        npz = tmp_path / "focus.npz"
        assert main(["live", "--config", str(cfg), "--frames", "2", "--fps", "50", "--focus", "--pixel", "5",
                     "--no-window", "--npz", str(npz)]) == 0
        shown = np.load(npz)
        expected = scene.expected_focus_counts(scene.line_index(0.0), exposure_s=0.01, gain=30)[5]
        assert abs(int(np.argmax(shown["profile"])) - int(np.argmax(expected))) <= 1
        assert shown["row_times_ps"].size == 0              # no sweep, no time axis
        sent = list(sim.received)
        focus, restore = sent.index("DevParamSet(Streak,Mode,Focus)"), sent.index("DevParamSet(Streak,Mode,Operate)")
        assert focus < sent.index("AcqStart(Live)") < sent.index("AcqStop()") < sent.index("AcqLiveMonitor(Off)") \
            < restore
        assert sim.last_frame_info["focus"] is True


@pytest.mark.parametrize("argv,message", [
    (["--frames", "-1"], "frames must be an integer >= 0"),
    (["--fps", "0"], "rate_hz must be a positive number"),
    (["--png", "/no/such/dir/x.png"], "its directory does not exist"),
])
def test_bad_live_options_are_named(tmp_path, capsys, argv, message):
    cfg = write_config(tmp_path)
    assert main(["live", "--config", str(cfg), "--simulate", *argv]) == 2
    assert message in capsys.readouterr().err
    with pytest.raises(ValueError, match="pixel"):
        LiveOptions(pixel=-2)


def test_ctrl_c_stops_the_live_acquisition_on_the_camera_and_exits_130(tmp_path):
    scene = scene_for(write_config(tmp_path))
    with RemoteExSimulator(LabState(sync_output_enabled=True), scene, seed=1) as sim:
        cfg = write_config(tmp_path, camera=f"{sim.host}:{sim.port}")
        proc = subprocess.Popen([sys.executable, "-m", "streaklab", "live", "--config", str(cfg), "--no-window",
                                 "--fps", "20"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            sel = selectors.DefaultSelector()
            sel.register(proc.stdout, selectors.EVENT_READ)
            buf, end = b"", time.monotonic() + 30
            while b"live frame 1 " not in buf:
                assert time.monotonic() < end and sel.select(end - time.monotonic()), f"no live frames: {buf!r}"
                chunk = os.read(proc.stdout.fileno(), 4096)
                assert chunk, proc.stderr.read()
                buf += chunk
            assert sim.acq_status_mode() == "Live"
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=15) == 130
            err = proc.stderr.read().decode()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        assert "Traceback" not in err and "live acquisition stopped on the camera" in err
        sent = list(sim.received)
        live_at = sent.index("AcqStart(Live)")
        assert "AcqStop()" in sent[live_at:] and "AcqLiveMonitor(Off)" in sent[live_at:]
        assert sim.acq_status_mode() is None


def test_laser_on_switches_the_simulated_sync_output_for_the_live_view_only(tmp_path, capsys, monkeypatch):
    from drivers.sim import SimulatedLab

    labs = []
    real_start = SimulatedLab.start

    def start(self):
        labs.append(self)
        return real_start(self)

    monkeypatch.setattr(SimulatedLab, "start", start)
    cfg = write_config(tmp_path)
    npz = tmp_path / "lit.npz"
    assert main(["live", "--config", str(cfg), "--simulate", "--laser-on", "--frames", "1", "--no-window",
                 "--npz", str(npz)]) == 0
    scene = scene_for(cfg)
    lit = np.load(npz)["image"]
    assert np.abs(lit - scene.expected_counts(scene.line_index(0.0), exposure_s=0.01, gain=30)).mean() < 5.0
    assert labs[0].state.sync_output_enabled is False            # switched off again at the end


def test_a_display_without_a_usable_window_falls_back_to_headless_output(tmp_path, capsys, monkeypatch):
    import matplotlib

    monkeypatch.setenv("DISPLAY", ":99")                      # claims a display; matplotlib has no GUI here
    monkeypatch.setattr(matplotlib, "get_backend", lambda: "agg")
    png = tmp_path / "live.png"
    assert main(["live", "--config", str(write_config(tmp_path)), "--simulate", "--frames", "1",
                 "--png", str(png)]) == 0
    assert "no window" in capsys.readouterr().err
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_the_live_figures_title_lies_inside_the_png(tmp_path):
    """The title is set before the layout is made, so it is drawn inside the figure, not cut off."""
    from types import SimpleNamespace

    from streaklab.commands.live import _Figure

    png = tmp_path / "live.png"
    fig = _Figure(window=False, png=str(png))
    img = np.arange(40 * 64, dtype=np.uint16).reshape(40, 64)
    fig.show(SimpleNamespace(image=img, profile=img.sum(axis=0).astype(float), row_times_ps=None, index=3,
                             sequence=17))
    title = fig.ax_img.title
    assert title.get_text() == "live frame 3 (camera #17)"
    box = title.get_window_extent(fig.fig.canvas.get_renderer())
    assert 0 <= box.y0 and box.y1 <= fig.fig.bbox.height and 0 <= box.x0 and box.x1 <= fig.fig.bbox.width
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig.close()


def test_a_swept_live_view_on_a_unit_left_in_focus_mode_switches_the_sweep_on_before_raising_the_gain(tmp_path):
    # a Focus-mode live view that was killed leaves the sweep off; the next live view without
    # --focus must not raise the MCP gain while the unit is still in Focus mode
    scene = scene_for(write_config(tmp_path))
    with RemoteExSimulator(LabState(sync_output_enabled=True), scene, seed=1) as sim:
        from drivers.remoteex import RemoteExCamera

        with RemoteExCamera(sim.host, sim.port, timeout_s=2.0) as cam:
            cam.set_streak_mode("Focus")
        cfg = write_config(tmp_path, camera=f"{sim.host}:{sim.port}")
        assert main(["live", "--config", str(cfg), "--frames", "1", "--fps", "50", "--no-window"]) == 0
        assert sim.gain_log and all(gain == 0 for _, gain, mode in sim.gain_log if mode == "Focus")
        assert 30 in [gain for _, gain, mode in sim.gain_log if mode == "Operate"]
        sent = list(sim.received)
        assert sent.index("DevParamSet(Streak,Mode,Operate)") < sent.index("DevParamSet(Streak,MCP Gain,30)") \
            < sent.index("AcqStart(Live)")
