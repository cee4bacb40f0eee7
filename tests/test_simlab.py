"""SimulatedLab and the ``streaklab sim-lab`` command."""
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import ConnectionLost
from drivers.remoteex import RemoteExCamera
from drivers.scpi_sync import ScpiLaserSync
from drivers.sim import SimulatedLab
from drivers.sim.scene import VirtualScene
from drivers.smc100 import SMC100Mirror

from _simlab_process import start_sim_lab, stop_sim_lab

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]
SMALL = VirtualScene.default(n_lines=4, n_x=16, n_t=64, seed=2)


def test_lab_camera_renders_the_shared_state():
    with SimulatedLab(seed=5, scene=SMALL, mirror=False, sync=False) as lab:
        address = lab.camera_address
        assert lab.scene is SMALL and address[0] == "127.0.0.1"
        with RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
            dark = cam.acquire().data
            with lab.state.lock:
                lab.state.sync_output_enabled = True
                lab.state.mirror_angle_deg = float(SMALL.angle_deg[2])
            lit = cam.acquire().data
        assert dark.shape == lit.shape == (16, 64)
        assert abs(dark.mean() - SMALL.dark_level) < 1.0
        expected = SMALL.expected_counts(2)
        assert np.abs(lit - expected).mean() < 5.0 and lit.max() > SMALL.dark_level + 200
        with pytest.raises(RuntimeError, match="mirror"):
            lab.mirror_port
        with pytest.raises(RuntimeError, match="sync"):
            lab.usb_backend
    with pytest.raises(ConnectionLost):
        RemoteExCamera(*address, connect_timeout_s=1.0)   # closed with the lab


def test_lab_mirror_moves_select_the_scan_line_the_camera_shows():
    with SimulatedLab(seed=0, scene=SMALL, sync=False) as lab:
        assert lab.mirror_port.startswith("/dev/pts/")
        lab.state.sync_output_enabled = True
        with SMC100Mirror(lab.mirror_port) as mirror, \
                RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
            mirror.home(timeout_s=5.0)
            for line in (3, 0):
                mirror.move_to(float(SMALL.angle_deg[line]))
                reached = mirror.wait_settled(timeout_s=5.0)
                assert reached == pytest.approx(SMALL.angle_deg[line], abs=1e-4)
                img = cam.acquire().data
                assert lab.camera.last_frame_info["line"] == line
                assert np.abs(img - SMALL.expected_counts(line)).mean() < 5.0
        assert lab.describe()["mirror"] == lab.mirror_port


def test_full_lab_sync_output_and_delay_reach_the_camera():
    with SimulatedLab(seed=1, scene=SMALL) as lab:
        backend = lab.usb_backend
        with ScpiLaserSync(vendor_id=backend.vendor_id, product_id=backend.product_id, backend=backend) as sync, \
                SMC100Mirror(lab.mirror_port) as mirror, \
                RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
            assert "SLS" in sync.identify()
            mirror.home(timeout_s=5.0)
            mirror.move_to(float(SMALL.angle_deg[1]))
            mirror.wait_settled(timeout_s=5.0)
            sync.set_output(False)
            dark = cam.acquire().data
            assert abs(dark.mean() - SMALL.dark_level) < 1.0
            sync.set_output(True)
            sync.set_trigger_delay(0.0)
            at0 = cam.acquire().data
            sync.set_trigger_delay(40.0)
            at40 = cam.acquire().data
        assert lab.state.sync_delay_ps == pytest.approx(40.0)
        assert np.abs(at0 - SMALL.expected_counts(1)).mean() < 5.0
        assert np.abs(at40 - SMALL.expected_counts(1, delay_ps=40.0)).mean() < 5.0
        assert np.argmax(at40.sum(axis=0)) < np.argmax(at0.sum(axis=0))


def test_same_seed_labs_give_the_same_bytes():
    def run(seed):
        with SimulatedLab(seed=seed, scene=SMALL, mirror=False, sync=False) as lab:
            lab.state.sync_output_enabled = True
            with RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
                return [cam.acquire().data.tobytes() for _ in range(2)]

    assert run(1) == run(1)
    assert run(1) != run(2)


def test_default_scene_follows_the_seed():
    with SimulatedLab(seed=3, mirror=False, sync=False) as lab:
        assert lab.scene.n_lines == 16 and lab.scene.n_x == 64 and lab.scene.n_t == 256
        a = lab.scene.params["direct_delay_ps"]
    b = SimulatedLab(seed=3, mirror=False, sync=False).scene.params["direct_delay_ps"]
    np.testing.assert_array_equal(a, b)


def test_sim_lab_command_serves_until_sigint():
    proc, info = start_sim_lab("--lines", "4", "--x", "16", "--t", "64", "--seed", "4")
    try:
        host, port = info["camera"].rsplit(":", 1)
        assert host == "127.0.0.1" and int(info["camera-data-port"]) == int(port) + 1
        assert info["laser-output"] == "on"
        with RemoteExCamera(host, int(port), timeout_s=2.0) as cam:
            img = cam.acquire()
        assert img.data.shape == (16, 64) and img.data.max() > 300
        with SMC100Mirror(info["mirror"]) as mirror:
            mirror.home(timeout_s=5.0)
            assert mirror.position() == pytest.approx(0.0)
        assert os.path.realpath(info["mirror-stable"]) == info["mirror"]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
        assert b"stopped" in proc.stderr.read()
    finally:
        stop_sim_lab(proc)
    with pytest.raises(OSError):
        socket.create_connection((host, int(port)), timeout=1.0)


def test_sim_lab_camera_only_and_dark():
    proc, info = start_sim_lab("--lines", "4", "--x", "16", "--t", "64", "--no-mirror", "--dark")
    try:
        assert "mirror" not in info and info["laser-output"] == "off"
        host, port = info["camera"].rsplit(":", 1)
        with RemoteExCamera(host, int(port), timeout_s=2.0) as cam:
            assert abs(cam.acquire().data.mean() - SMALL.dark_level) < 1.0
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        stop_sim_lab(proc)


def test_sim_lab_reports_a_taken_port():
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen(1)
    try:
        proc = subprocess.run([sys.executable, "-m", "streaklab", "sim-lab", "--no-mirror", "--camera-port",
                               str(blocker.getsockname()[1])], cwd=ROOT, capture_output=True, timeout=30)
    finally:
        blocker.close()
    assert proc.returncode == 2
    assert b"cannot start the simulators" in proc.stderr


def test_sim_lab_time_base_options_reach_the_camera_and_the_fiducial_is_where_printed():
    proc, info = start_sim_lab("--lines", "4", "--x", "16", "--t", "128", "--no-mirror", "--fiducial",
                               "--shading", "0.1", "--clock-speed", "60")
    try:
        words = info["fiducial"].split()                      # "pixels 0..1 row R t T ps"
        assert words[:2] == ["pixels", "0..1"] and words[2] == "row" and words[4] == "t"
        row = float(words[3])
        host, port = info["camera"].rsplit(":", 1)
        with RemoteExCamera(host, int(port), timeout_s=2.0) as cam:
            img = cam.acquire().data.astype(float)
        early = img[:2, : int(row) + 6].mean(axis=0)           # the fiducial's pixels, early in the window
        assert abs(int(np.argmax(early)) - row) <= 1 and early.max() > img[2:, : int(row) + 6].max() + 100
    finally:
        stop_sim_lab(proc)


def test_sim_lab_refuses_a_bad_time_base_option_in_one_line():
    proc = subprocess.run([sys.executable, "-m", "streaklab", "sim-lab", "--no-mirror", "--shading", "1.5"],
                          cwd=ROOT, capture_output=True, timeout=30)
    assert proc.returncode == 2
    (line,) = proc.stderr.decode().strip().splitlines()
    assert "--shading: shading must be in [0, 1), got 1.5" in line
