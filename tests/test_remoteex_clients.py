"""The RemoteEx simulator driven by a client that is not streaklab's driver.

No RemoteEx client is published on a package registry (PyPI's ``hamamatsu``
holds a DCAM binding and a RemoteEx *server* simulator), so the client here is
written from the handbook alone and behaves like Odemis' ``hamamatsurx``
driver: it opens the command and the data port first and reads both greetings
afterwards, runs Odemis' start-up sequence (camera info, Setup parameters, the
live ring buffer, the streak unit and the delay generator, their info and
parameter lists, the licence query) and an acquisition cycle (live image from
the ring buffer, the sweep's scaling table, stop, wait for the asynchronous
command to end).  It shares no code with :mod:`drivers.remoteex`.
"""
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.sim.camera import RemoteExSimulator
from drivers.sim.scene import VirtualScene
from drivers.sim.state import LabState

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]
SCENE = VirtualScene.default(n_lines=4, n_x=16, n_t=64, seed=5)


class HandbookClient:
    """A plain-socket RemoteEx client: both ports opened, then both greetings read."""

    def __init__(self, host, port, timeout_s=5.0):
        self.cmd = socket.create_connection((host, port), timeout=timeout_s)
        self.data = socket.create_connection((host, port + 1), timeout=timeout_s)
        self.greetings = (self.cmd.recv(64), self.data.recv(64))
        self.buf = b""
        self.live = []           # sequence numbers announced by 4,Livemonitor,RingBuffer,<seq>
        self.timeout_s = timeout_s

    def _line(self):
        while b"\r" not in self.buf:
            chunk = self.cmd.recv(4096)
            if not chunk:
                raise ConnectionError("server closed the command port")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\r")
        return line.lstrip(b"\n").decode("latin1")

    def _handle_unsolicited(self, fields):
        if fields[0] == "4" and fields[1] == "Livemonitor" and len(fields) > 3:
            self.live.append(int(fields[3]))

    def send(self, func, *args):
        """Returns (code, values); unsolicited 4/5 messages are set aside."""
        self.cmd.sendall(f"{func}({','.join(args)})\r".encode("ascii"))
        while True:
            fields = self._line().split(",")
            if fields[0] in ("4", "5"):
                self._handle_unsolicited(fields)
                continue
            if fields[1].lower() == func.lower():
                return int(fields[0]), fields[2:]

    def ok(self, func, *args):
        code, values = self.send(func, *args)
        assert code == 0, f"{func}({','.join(args)}) answered code {code}"
        return values

    def camera_info(self):
        values = self.ok("CamParamGet", "Setup", "CameraInfo")
        extra = []
        self.cmd.settimeout(0.3)
        try:
            while True:
                extra.append(self._line())
        except socket.timeout:
            pass
        finally:
            self.cmd.settimeout(self.timeout_s)
        return values + extra

    def wait_live(self):
        end = time.monotonic() + self.timeout_s
        while not self.live:
            assert time.monotonic() < end, "no live image announced"
            self._handle_unsolicited(self._line().split(","))
        return self.live.pop()

    def receive(self, n):
        out = b""
        while len(out) < n:
            chunk = self.data.recv(n - len(out))
            assert chunk, "data port closed"
            out += chunk
        return out

    def close(self):
        self.cmd.close()
        self.data.close()


def odemis_start_up(c: HandbookClient) -> dict:
    """Odemis' hamamatsurx start-up sequence; returns what it learned."""
    info = {}
    c.ok("AppStart")
    info["licence"] = c.ok("AppLicenceGet")
    info["camera"] = c.camera_info()
    for name, value in (("TimingMode", "Internal timing"), ("ScanMode", "Subarray"), ("Binning", "2 x 2"),
                        ("VWidth", "1016"), ("HWidth", "1344"), ("ShowGainOffset", "True")):
        c.ok("CamParamSet", "Setup", name, value)
    info["hwidth"] = int(c.ok("CamParamGet", "Setup", "HWidth")[0])
    info["binning"] = c.ok("CamParamGet", "Setup", "Binning")[0]
    info["binning_choices"] = c.ok("CamParamInfoEx", "Setup", "Binning")[4:]
    exp = c.ok("CamParamInfoEx", "Live", "Exposure")
    info["exposure_range"] = (exp[4], exp[-1])
    info["exposure"] = c.ok("CamParamGet", "Live", "Exposure")[0]
    c.ok("acqLiveMonitor", "RingBuffer", "10")
    info["streak_name"] = c.ok("DevParamGet", "Streakcamera", "DeviceName")[0]
    info["streak_params"] = c.ok("DevParamsList", "Streakcamera")
    for name, value in (("Time Range", "1 ns"), ("MCP Gain", "0"), ("Mode", "Focus"), ("Trig. Mode", "Cont"),
                        ("Trig. level", "1"), ("Trig. slope", "Rising")):
        c.ok("DevParamSet", "Streakcamera", name, value)
    info["mode"] = c.ok("DevParamGet", "Streakcamera", "Mode")[0]
    info["time_range"] = c.ok("DevParamGet", "Streakcamera", "Time Range")[0]
    info["gain_range"] = c.ok("DevParamInfoEx", "Streakcamera", "MCP Gain")[5:7]
    info["time_ranges"] = c.ok("DevParamInfoEx", "Streakcamera", "Time Range")[6:]
    c.ok("DevParamGet", "Delaybox", "DeviceName")
    for name, value in (("Setting", "M1"), ("Trig. Mode", "Ext. rising"), ("Repetition Rate", "1000000"),
                        ("Delay A", "0"), ("Delay B", "0.00000002"), ("Burst Mode", "Off")):
        c.ok("DevParamSet", "Delaybox", name, value)
    info["delay"] = float(c.ok("DevParamGet", "Delaybox", "Delay A")[0])
    info["delay_max"] = float(c.ok("DevParamInfoEx", "Delaybox", "Delay A")[-1])
    info["async"] = c.ok("AsyncCommandStatus")
    return info


def odemis_acquire(c: HandbookClient):
    """One live image from the ring buffer in Operate mode, with its scaling table; then stop."""
    c.ok("DevParamSet", "Streakcamera", "Mode", "Operate")
    c.ok("DevParamSet", "Streakcamera", "MCP Gain", str(SCENE.reference_gain))
    c.ok("CamParamSet", "Live", "Exposure", "10 ms")
    c.ok("AcqStart", "Live")
    seq = c.wait_live()
    w, h, bpp, kind, got_seq = c.ok("ImgRingBufferGet", "Data", str(seq))[:5]
    img = np.frombuffer(c.receive(int(w) * int(h) * int(bpp)), dtype="<u2").reshape(int(h), int(w))
    n = int(c.ok("ImgDataGet", "current", "ScalingTable", "Vertical")[0])
    table = np.frombuffer(c.receive(4 * n), dtype="<f4")
    c.ok("AcqStop", "1000")
    end = time.monotonic() + 5
    while int(c.ok("AsyncCommandStatus")[0]):
        assert time.monotonic() < end, "asynchronous command never ended"
    return img, int(got_seq), table


def check_start_up(info):
    assert info["licence"] == ["1", "1", "1", "0", "1", "0"]
    assert info["camera"][0] == "C13440 (simulated)" and len(info["camera"]) == 5
    assert info["camera"][1].startswith("Product number")
    assert info["hwidth"] == 1344 and info["binning"] == "2 x 2"
    assert {(int(b[0]), int(b[4])) for b in info["binning_choices"]} == {(1, 1), (2, 2), (4, 4)}
    assert info["exposure_range"] == ("1 us", "10 s")
    assert int(info["streak_params"][0]) == len(info["streak_params"]) - 1
    assert {"Time Range", "Mode", "MCP Gain"} <= set(info["streak_params"][1:])
    assert info["mode"] == "Focus" and info["time_range"] == "1 ns"
    assert info["gain_range"] == ["0", "63"] and "1 ns" in info["time_ranges"]
    # Odemis converts every entry with the units s, ms, us, ns (and fails on anything else).
    assert all(e.split(" ")[1] in ("s", "ms", "us", "ns") for e in info["time_ranges"])
    assert info["delay"] == 0.0 and info["delay_max"] == pytest.approx(1e-6)
    assert info["async"][0] == "0"


def check_image(img, table, state_line):
    assert img.shape == (SCENE.n_t, SCENE.n_x)
    expected = SCENE.expected_counts(state_line, exposure_s=0.01, time_range="1 ns").T
    assert np.abs(img - expected).mean() < 5.0 and img.max() > SCENE.dark_level + 50
    np.testing.assert_allclose(table * 1e3, SCENE.row_times_ps(0.0, "1 ns"), rtol=1e-6)   # ns -> ps


def test_handbook_client_starts_up_and_acquires_on_the_simulator():
    state = LabState(mirror_angle_deg=float(SCENE.angle_deg[1]), sync_output_enabled=True)
    with RemoteExSimulator(state, SCENE, seed=3, single_sweep=True) as sim:
        c = HandbookClient(*sim.address)
        try:
            assert c.greetings == (b"RemoteEx Ready\r", b"RemoteEx Data Ready\r")
            check_start_up(odemis_start_up(c))
            img, seq, table = odemis_acquire(c)
            assert seq >= 1
            check_image(img, table, 1)
            c.ok("AppEnd")
        finally:
            c.close()


def test_the_data_port_may_be_opened_first_and_greetings_read_late():
    with RemoteExSimulator(LabState(sync_output_enabled=True), SCENE) as sim:
        for _ in range(3):          # the same client order, again and again: never a stale-connection drop
            data = socket.create_connection((sim.host, sim.data_port), timeout=5)
            cmd = socket.create_connection(sim.address, timeout=5)
            assert data.recv(64) == b"RemoteEx Data Ready\r" and cmd.recv(64) == b"RemoteEx Ready\r"
            cmd.sendall(b"AppStart()\rAcqStart(Acquire)\r")
            buf = b""
            while buf.count(b"\r") < 2:
                buf += cmd.recv(64)
            assert buf == b"0,AppStart\r0,AcqStart\r"
            cmd.close()
            data.close()


def test_handbook_client_against_the_sim_lab_command():
    proc = subprocess.Popen([sys.executable, "-m", "streaklab", "sim-lab", "--lines", "4", "--x", "16", "--t", "64",
                             "--seed", "5", "--single-sweep", "--no-mirror"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        sel = selectors.DefaultSelector()
        sel.register(proc.stdout, selectors.EVENT_READ)
        buf, end = b"", time.monotonic() + 20
        while b"ready" not in buf:
            assert time.monotonic() < end and sel.select(end - time.monotonic()), f"sim-lab not ready: {buf!r}"
            chunk = os.read(proc.stdout.fileno(), 4096)
            assert chunk, proc.stderr.read()
            buf += chunk
        info = dict(line.split(" ", 1) for line in buf.decode().splitlines() if " " in line)
        assert info["streak-unit"] == "single-sweep"
        host, port = info["camera"].rsplit(":", 1)
        c = HandbookClient(host, int(port))
        try:
            check_start_up(odemis_start_up(c))
            img, seq, table = odemis_acquire(c)
            check_image(img, table, SCENE.line_index(0.0))     # sim-lab: laser on, mirror at 0 deg
        finally:
            c.close()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
