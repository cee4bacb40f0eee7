"""The simulators driven by client libraries the project did not write (test-only dependencies).

* laser sync: python-usbtmc and pyvisa + pyvisa-py, through pyusb with the
  simulator as the pyusb backend (python-usbtmc takes the ``usb.core.Device``;
  pyvisa-py finds devices with pyusb's default backend lookup, which is
  pointed at the simulator, as libusb would be on the rig);
* scan mirror: the yaqd-newport SMC100 daemon, on the pty that
  ``streaklab sim-lab`` prints, started against an already homed controller
  (its start-up resets with ``RS`` and homes with ``OR``), then moving the
  mirror through a short scan while the camera shows the line at each angle.

None of the clients is modified or wrapped.
"""
from __future__ import annotations

import asyncio
import pathlib
import signal
import time

import numpy as np
import pytest
import pyvisa                    # test extra: pyvisa + pyvisa-py (loaded by ResourceManager("@py"))
import usb.backend.libusb1
import usb.core
import usbtmc                    # test extra: python-usbtmc
from yaqd_newport._newport_smc100 import NewportSMC100   # test extra: yaqd-newport

from drivers.remoteex import RemoteExCamera
from drivers.sim import SimulatedLab
from drivers.sim.scene import VirtualScene
from drivers.smc100 import SMC100Mirror

from _simlab_process import start_sim_lab, stop_sim_lab

pytestmark = pytest.mark.timeout(60)

ROOT = pathlib.Path(__file__).resolve().parents[1]

SMALL = VirtualScene.default(n_lines=4, n_x=16, n_t=64, seed=2)


def test_python_usbtmc_runs_a_delay_scan_on_the_simulated_sync():
    with SimulatedLab(seed=1, scene=SMALL, mirror=False) as lab:
        sim = lab.usb_backend
        dev = usb.core.find(backend=sim, idVendor=sim.vendor_id, idProduct=sim.product_id)
        instr = usbtmc.Instrument(dev)
        instr.timeout = 2.0
        try:
            assert instr.ask("*IDN?") == "STREAKLAB,SLS-575SIM,SLS0001,1.0"
            instr.write("*RST")
            instr.write(":PULS0:PER 1.25e-08")
            instr.write(":PULS0:STAT ON")
            assert instr.ask("SYST:ERR?") == '0,"No error"'
            assert instr.read_stb() == 0                     # USB488 READ_STATUS_BYTE, interrupt-IN
            lab.state.mirror_angle_deg = float(SMALL.angle_deg[1])
            with RemoteExCamera(*lab.camera_address, timeout_s=2.0) as cam:
                for delay_ps in (0.0, 40.0):
                    instr.write(f":PULS1:DEL {delay_ps * 1e-12!r}")
                    assert float(instr.ask(":PULS1:DEL?")) == pytest.approx(delay_ps * 1e-12, abs=1e-16)
                    img = cam.acquire().data
                    assert np.abs(img - SMALL.expected_counts(1, delay_ps=delay_ps)).mean() < 5.0
            instr.write(":PULS9:DEL 0")                      # no channel 9
            assert instr.ask("SYST:ERR?") == '-113,"Undefined header"'
            instr.clear()                                    # INITIATE_CLEAR / CHECK_CLEAR_STATUS
            assert instr.ask("*OPC?") == "1"
        finally:
            instr.close()
        assert lab.state.sync_delay_ps == 40.0 and lab.state.sync_output_enabled is True


@pytest.mark.filterwarnings("ignore:.*hislip resource discovery:UserWarning")
def test_pyvisa_py_finds_and_drives_the_simulated_sync(monkeypatch):
    with SimulatedLab(seed=1, scene=SMALL, mirror=False) as lab:
        sim = lab.usb_backend
        # pyusb's default backend lookup (what pyvisa-py uses) answers with the simulator
        monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *args, **kwargs: sim)
        rm = pyvisa.ResourceManager("@py")
        try:
            name = f"USB0::{sim.vendor_id}::{sim.product_id}::SLS0001::0::INSTR"
            assert name in rm.list_resources("USB?*")
            inst = rm.open_resource(name, timeout=2000)
            assert inst.query("*IDN?").strip() == "STREAKLAB,SLS-575SIM,SLS0001,1.0"
            inst.write(":PULS0:PER 1.3e-08")
            inst.write(":PULS1:DEL 2.5e-10")
            inst.write(":PULS0:STAT ON")
            assert inst.query("SYST:ERR?").strip() == '0,"No error"'
            assert inst.query(":PULS0:STAT?;:PULS1:DEL?").strip() == "1;2.5000000000000E-10"
            inst.close()   # (pyvisa-py 0.8 supports neither clear() nor read_stb() on USB sessions)
        finally:
            rm.close()
        assert lab.state.sync_rate_hz == pytest.approx(1 / 1.3e-08)
        assert (lab.state.sync_delay_ps, lab.state.sync_output_enabled) == (250.0, True)


@pytest.mark.slow   # the daemon's own start-up waits 5 s after its RS
def test_yaqd_newport_daemon_on_sim_lab_homes_an_already_homed_controller_and_scans(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))       # the daemon's state file goes here

    async def until(condition, timeout_s):
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, "the daemon did not get there in time"
            await asyncio.sleep(0.02)

    async def scan(port, cam):
        config = NewportSMC100._parse_config(
            {"mirror": {"serial_port": port, "port": 0, "host": "127.0.0.1"}}, "mirror")
        daemon = NewportSMC100("mirror", config, pathlib.Path(tmp_path / "config.toml"))
        try:
            await until(lambda: not daemon.busy(), 20)       # RS, NOT REFERENCED, OR, READY
            assert daemon._state["status"].startswith("READY")
            assert daemon._state["hw_limits"] == [-45.0, 45.0]   # read with SL? / SR?
            for line in (3, 0, 2):
                daemon.set_position(float(SMALL.angle_deg[line]))
                await until(lambda: not daemon.busy(), 10)
                assert daemon.get_position() == pytest.approx(SMALL.angle_deg[line], abs=1e-6)
                img = await asyncio.to_thread(lambda: cam.acquire().data)
                assert np.abs(img - SMALL.expected_counts(line)).mean() < 5.0   # the camera shows that line
        finally:
            daemon.close()
            await asyncio.sleep(0.05)
            daemon._serial.port.close()

    proc, info = start_sim_lab("--lines", "4", "--x", "16", "--t", "64", "--seed", "2")
    try:
        with SMC100Mirror(info["mirror-stable"]) as mirror:   # leave the controller homed, off zero
            mirror.home(timeout_s=5)
            mirror.move_to(4.0)
            mirror.wait_settled(timeout_s=5)
        host, port = info["camera"].rsplit(":", 1)
        with RemoteExCamera(host, int(port), timeout_s=2.0) as cam:
            asyncio.run(scan(info["mirror-stable"], cam))
        with SMC100Mirror(info["mirror-stable"]) as mirror:
            assert mirror.position() == pytest.approx(SMALL.angle_deg[2], abs=1e-6)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        stop_sim_lab(proc)


def test_pyvisa_py_serial_session_with_xonxoff_drives_the_mirror_as_sim_lab_help_says(capsys):
    from drivers.sim.mirror import MirrorSimulator
    from streaklab.cli import main
    from streaklab.commands.simlab import CONNECTING

    with pytest.raises(SystemExit) as info:
        main(["sim-lab", "--help"])
    assert info.value.code == 0
    assert CONNECTING in capsys.readouterr().out and "VI_ASRL_FLOW_XON_XOFF" in CONNECTING
    with MirrorSimulator(velocity_deg_per_s=100.0, min_home_s=0.01) as sim:
        rm = pyvisa.ResourceManager("@py")
        try:
            inst = rm.open_resource("ASRL" + sim.stable_port + "::INSTR", baud_rate=57600,
                                    read_termination="\r\n", write_termination="\r\n",
                                    flow_control=pyvisa.constants.VI_ASRL_FLOW_XON_XOFF, timeout=2000)
            assert inst.query("1ID?") == "1IDSLAB-GALVO-SIM"
            inst.write("1OR")
            deadline = time.monotonic() + 5
            while inst.query("1TS") != "1TS000032":
                assert time.monotonic() < deadline
            inst.write("1PA2.5")
            while inst.query("1TS") != "1TS000033":
                assert time.monotonic() < deadline
            assert inst.query("1TP") == "1TP2.500000" and inst.query("1TE") == "1TE@"
            inst.close()
        finally:
            rm.close()
        assert sim.lab_state.mirror_angle_deg == 2.5
