"""RemoteEx driver against the simulated camera, through real loopback TCP."""
import logging
import socket
import threading
import time

import numpy as np
import pytest

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.remoteex import ERROR_MEANINGS, RemoteExCamera
from drivers.sim.camera import RemoteExSimulator, bind_port_pair
from drivers.sim.scene import VirtualScene
from drivers.sim.state import LabState

pytestmark = pytest.mark.timeout(30)

SCENE = VirtualScene.default(n_lines=8, n_x=32, n_t=128, seed=0)


def lit_state(angle_deg=0.0, delay_ps=0.0, output=True):
    return LabState(mirror_angle_deg=angle_deg, sync_output_enabled=output, sync_delay_ps=delay_ps)


@pytest.fixture
def lab():
    state = lit_state(angle_deg=float(SCENE.angle_deg[3]))
    with RemoteExSimulator(state, SCENE, seed=7) as sim:
        with RemoteExCamera(*sim.address, timeout_s=1.0, connect_timeout_s=2.0) as cam:
            yield sim, cam, state


def frames(sim_seed, steps, scene=SCENE):
    """Run the same command sequence on a fresh simulator; ``steps`` is a list of LabState updates."""
    state = lit_state()
    out = []
    with RemoteExSimulator(state, scene, seed=sim_seed) as sim:
        with RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
            cam.configure(exposure_s=0.01, gain=30, time_range=2)
            for step in steps:
                for k, v in step.items():
                    setattr(state, k, v)
                out.append(cam.acquire().data.tobytes())
    return out


# ------------------------------------------------------------------ imaging
def test_acquire_shape_dtype_and_signal_matches_scene(lab):
    sim, cam, state = lab
    img = cam.acquire(timeout_s=5)
    assert img.data.shape == (SCENE.n_x, SCENE.n_t) and img.data.dtype == np.uint16
    expected = SCENE.expected_counts(3, exposure_s=0.01, gain=30)
    resid = (img.data.astype(float) - expected) / np.sqrt(expected - SCENE.dark_level + SCENE.read_noise**2)
    assert abs(resid.mean()) < 0.1 and 0.85 < resid.std() < 1.15
    assert img.data.max() > SCENE.dark_level + 300        # there is real signal in the frame
    assert sim.last_frame_info["line"] == 3


def test_same_seed_same_bytes_and_noise_index_semantics():
    a0, a1 = SCENE.angle_deg[2], SCENE.angle_deg[5]
    steps = [{"mirror_angle_deg": a0}, {}, {"mirror_angle_deg": a1}, {"mirror_angle_deg": a0}, {}]
    run1 = frames(11, steps)
    run2 = frames(11, steps)
    assert run1 == run2                        # same seed, same commands: same bytes
    assert run1[0] != run1[1]                  # a second frame at the same view has fresh noise
    assert run1[3] == run1[0] and run1[4] == run1[1]   # the index restarts when the mirror moves
    assert frames(12, steps[:1]) != run1[:1]   # another seed, other noise


def test_resumed_sequence_reproduces_uninterrupted_one():
    a = SCENE.angle_deg
    full = frames(3, [{"mirror_angle_deg": a[i]} for i in (0, 0, 1, 1, 2, 2)])
    # A "crash" after line 1, then a fresh lab that homes (angle 0) and continues with line 2.
    resumed = frames(3, [{"mirror_angle_deg": 0.0}, {"mirror_angle_deg": a[2]}, {}])
    assert resumed[1:] == full[4:]


def test_dark_when_sync_output_off(lab):
    sim, cam, state = lab
    state.sync_output_enabled = False
    img = cam.acquire().data.astype(float)
    assert img.mean() == pytest.approx(SCENE.dark_level, abs=0.2)
    assert img.std() == pytest.approx(SCENE.read_noise, rel=0.1)
    state.sync_output_enabled = True
    assert cam.acquire().data.max() > SCENE.dark_level + 300


def test_line_follows_mirror_angle_and_window_follows_delay(lab):
    sim, cam, state = lab
    for line in (0, 6):
        state.mirror_angle_deg = float(SCENE.angle_deg[line]) + 0.1   # nearest line wins
        img = cam.acquire().data.astype(float)
        assert sim.last_frame_info["line"] == line
        expected = SCENE.expected_counts(line)
        other = SCENE.expected_counts(7 - line if line == 0 else 0)
        assert np.abs(img - expected).mean() < np.abs(img - other).mean()
    state.mirror_angle_deg = float(SCENE.angle_deg[4])
    peak0 = np.argmax(cam.acquire().data.astype(float).sum(axis=0))
    state.sync_delay_ps = 60.0
    img = cam.acquire().data.astype(float)
    peak1 = np.argmax(img.sum(axis=0))
    assert peak1 < peak0 - 10                                  # later window: light arrives at earlier rows
    expected = SCENE.expected_counts(4, delay_ps=60.0)
    assert np.abs(img - expected).mean() < 5.0


def test_exposure_and_gain_scale_the_signal(lab):
    sim, cam, state = lab
    cam.configure(exposure_s=0.02, gain=40)
    img = cam.acquire().data.astype(float)
    assert cam.exposure_s() == pytest.approx(0.02) and cam.gain() == 40
    signal = img - SCENE.dark_level
    ref = SCENE.expected_counts(3) - SCENE.dark_level
    assert signal.sum() / ref.sum() == pytest.approx(4.0, rel=0.02)   # 2x exposure, +10 gain steps = 2x


def test_out_of_range_settings_are_device_errors(lab):
    sim, cam, state = lab
    with pytest.raises(DeviceError) as info:
        cam.configure(exposure_s=60.0)
    assert info.value.code == 10 and info.value.meaning == ERROR_MEANINGS[10]
    with pytest.raises(DeviceError) as info:
        cam.configure(time_range=9)
    assert info.value.code == 10
    with pytest.raises(DeviceError) as info:
        cam.command("NoSuchCommand")
    assert info.value.code == 2
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)


def test_acquisition_left_running_is_stopped_and_restarted(lab):
    sim, cam, state = lab
    sim.inject("error", command="AcqStart", code=7)
    n = len(sim.received)
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)
    assert [c for c in list(sim.received)[n:] if c.startswith("Acq")][:3] == \
        ["AcqStart(Acquire)", "AcqStop()", "AcqStart(Acquire)"]


def test_a_status_query_cut_short_by_the_acquisition_deadline_reports_the_acquisition_timeout():
    """The last status query before the deadline gets only what is left of it; when the reply
    misses that, the error is the acquisition's timeout, not a missing reply (and the
    acquisition is stopped)."""
    with RemoteExSimulator(lit_state(), SCENE, frame_time_s=30.0) as sim, \
            RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
        sim.inject("delay", command="AcqStatus", delay_s=0.6)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="acquisition not finished within 0.3 s"):
            cam.acquire(timeout_s=0.3)
        assert time.monotonic() - t0 < 2.0
        assert list(sim.received)[-1] == "AcqStop()"


def test_acquisition_timeout_stops_the_acquisition():
    with RemoteExSimulator(lit_state(), SCENE, frame_time_s=30.0) as sim, \
            RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="not finished within 0.3 s"):
            cam.acquire(timeout_s=0.3)
        assert time.monotonic() - t0 < 2.0
        assert list(sim.received)[-1] == "AcqStop()"
        assert cam.acq_status()[0] == "idle"


# ------------------------------------------------------------------- faults
def test_dropped_reply_times_out_then_recovers(lab):
    sim, cam, state = lab
    sim.inject("drop_reply", command="AcqStatus")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        cam.acq_status()
    assert time.monotonic() - t0 < 3.0
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)


def test_delayed_reply_times_out_then_recovers(lab):
    sim, cam, state = lab
    sim.inject("delay", command="CamParamGet", delay_s=2.0)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        cam.exposure_s()
    assert time.monotonic() - t0 < 3.0
    assert cam.exposure_s() == pytest.approx(0.01)   # the late reply never answers this one


def test_garbage_is_a_protocol_error_then_recovers(lab):
    sim, cam, state = lab
    sim.inject("garbage", command="AcqStart")
    with pytest.raises(ProtocolError) as info:
        cam.acquire()
    assert b"garbage" in info.value.raw
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)


def test_device_error_code_is_reported_then_recovers(lab):
    sim, cam, state = lab
    sim.inject("error", command="ImgDataGet", code=9)
    with pytest.raises(DeviceError) as info:
        cam.acquire()
    assert info.value.code == 9 and info.value.meaning == ERROR_MEANINGS[9]
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)


def test_notifications_from_the_simulator_do_not_disturb(lab):
    sim, cam, state = lab
    sim.inject("notify", command="AcqStatus", times=3)
    sim.inject("notify", command="ImgDataGet")
    for _ in range(3):   # each acquisition polls AcqStatus at least once
        assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)
    assert not sim.faults.pending()


def test_short_image_data_times_out_then_recovers(lab):
    sim, cam, state = lab
    sim.inject("short_data", command="ImgDataGet")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        cam.acquire(timeout_s=0.8)
    assert time.monotonic() - t0 < 3.0
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)


def test_closed_connection_is_reestablished_once_transparently(lab):
    sim, cam, state = lab
    before = sim.connections
    sim.inject("close", command="AcqStatus")
    assert cam.acquire().data.shape == (SCENE.n_x, SCENE.n_t)
    assert sim.connections == before + 1 and cam.reconnects >= 1


def test_connection_closed_twice_is_connection_lost_then_usable_again(lab):
    sim, cam, state = lab
    sim.inject("close", command="CamParamGet", times=2)
    t0 = time.monotonic()
    with pytest.raises(ConnectionLost):
        cam.exposure_s()
    assert time.monotonic() - t0 < 5.0
    assert cam.exposure_s() == pytest.approx(0.01)


def test_server_gone_is_connection_lost():
    state = lit_state()
    sim = RemoteExSimulator(state, SCENE).start()
    cam = RemoteExCamera(*sim.address, timeout_s=1.0, connect_timeout_s=1.0)
    sim.stop()
    t0 = time.monotonic()
    with pytest.raises(ConnectionLost):
        cam.acquire()
    assert time.monotonic() - t0 < 5.0
    cam.close()


# ---------------------------------------------------------------- threading
def test_two_threads_never_get_each_others_replies(lab):
    sim, cam, state = lab
    cam.configure(time_range=3, gain=17)
    errors, n = [], 150

    def worker(param, expected):
        try:
            for _ in range(n):
                got = cam.command("DevParamGet", "Streak", param)
                if got != [expected]:
                    errors.append((param, got))
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=a) for a in (("Time Range", "3"), ("MCP Gain", "17"))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert not any(t.is_alive() for t in threads)
    assert errors == []


def test_two_threads_acquiring_each_get_whole_frames(lab):
    sim, cam, state = lab
    results, errors = [], []

    def worker():
        try:
            for _ in range(5):
                results.append(cam.acquire(timeout_s=5).data)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert errors == [] and len(results) == 10
    expected = SCENE.expected_counts(3)
    for img in results:
        assert img.shape == (SCENE.n_x, SCENE.n_t)
        assert np.abs(img - expected).mean() < 5.0
    assert len({r.tobytes() for r in results}) == 10   # ten distinct noise draws, none duplicated


# ------------------------------------------------------------------ server
def test_simulator_binds_loopback_adjacent_ports_and_stops_cleanly():
    sims = [RemoteExSimulator(lit_state(), SCENE).start() for _ in range(3)]
    try:
        for s in sims:
            assert s.address[0] == "127.0.0.1" and s.data_port == s.port + 1
        assert len({s.port for s in sims}) == 3
    finally:
        t0 = time.monotonic()
        for s in sims:
            s.stop()
        assert time.monotonic() - t0 < 3.0


def test_fixed_port_pair_in_use_is_refused():
    c, d = bind_port_pair()
    try:
        with pytest.raises(OSError):
            RemoteExSimulator(lit_state(), SCENE, port=c.getsockname()[1]).start()
    finally:
        c.close()
        d.close()


def test_fault_kinds_are_checked():
    sim = RemoteExSimulator(lit_state(), SCENE)
    with pytest.raises(ValueError, match="unknown fault kind"):
        sim.inject("explode")
    with pytest.raises(ValueError, match="code"):
        sim.inject("error")


# ------------------------------------------------------------------- scene
def test_scene_rendering_equals_render_profile_on_a_linear_sweep():
    from dataclasses import replace

    from core.model import render_profile

    linear = replace(SCENE, time_calibration=np.array([2.0, 2.0]))
    for line in (0, 4):
        got = linear.clean_line(line)
        ref = render_profile(linear.line_params(line), SCENE.n_t, time_bin_ps=2.0, t0_ps=2.0)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
        shifted = linear.clean_line(line, delay_ps=30.0)
        ref = render_profile(linear.line_params(line), SCENE.n_t, time_bin_ps=2.0, t0_ps=32.0)
        np.testing.assert_allclose(shifted, ref, rtol=1e-12, atol=1e-15)


def test_scene_sweep_times_delay_and_time_range():
    t = SCENE.row_times_ps()
    assert t[0] == pytest.approx(2.0) and np.all(np.diff(t) > 0)
    assert np.all(np.diff(t, 2) > 0)                       # the sweep slows down: not linear
    np.testing.assert_allclose(SCENE.row_times_ps(25.0), t + 25.0)
    np.testing.assert_allclose(SCENE.row_times_ps(0.0, time_range=3), 2.0 * t)
    with pytest.raises(ValueError, match="time_range"):
        SCENE.row_times_ps(0.0, time_range=7)


def test_default_scene_has_every_component_inside_the_window():
    p, window = SCENE.params, SCENE.row_times_ps()[-1]
    has_sss = np.isfinite(p["sss_amplitude"])
    has_ir = np.isfinite(p["ir_amplitude"]).any(axis=-1)
    assert has_sss.sum() > 10 and has_ir.sum() > 10 and np.all(np.isfinite(p["direct_delay_ps"]))
    for key in ("direct_delay_ps", "sss_delay_ps", "ir_delay_ps"):
        d = p[key][np.isfinite(p[key])]
        assert d.min() > 20.0 and d.max() < 0.85 * window


@pytest.mark.parametrize("change,message", [
    ({"time_calibration": np.array([0.0, 2.0, -0.05])}, "not strictly increasing"),
    ({"angle_deg": np.zeros(8)}, "strictly increasing"),
    ({"angle_deg": np.arange(5.0)}, "n_lines"),
    ({"photon_scale": -1.0}, "photon_scale"),
    ({"time_range": 9}, "time_range"),
])
def test_scene_validation_names_the_problem(change, message):
    fields = dict(params=SCENE.params, angle_deg=SCENE.angle_deg, n_t=SCENE.n_t,
                  time_calibration=SCENE.time_calibration)
    fields.update(change)
    with pytest.raises(ValueError, match=message):
        VirtualScene(**fields)


# ----------------------------------------------------------- data-port hygiene
def test_stray_bytes_on_the_data_port_do_not_reach_the_next_image():
    def run(stray):
        with RemoteExSimulator(lit_state(angle_deg=float(SCENE.angle_deg[2])), SCENE, seed=4) as sim, \
                RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
            if stray:
                sim.inject("stray_data", command="AcqStatus")
            return cam.acquire().data, cam.stray_data_bytes

    clean, _ = run(False)
    dirty, discarded = run(True)
    assert discarded == 3
    np.testing.assert_array_equal(dirty, clean)          # the first pixels are not 257, nothing is shifted


def test_a_flood_of_replies_for_another_command_is_skipped_with_few_warnings(lab, caplog):
    sim, cam, state = lab
    sim.inject("wrong_name", command="AcqStatus")
    with caplog.at_level(logging.WARNING, logger="drivers.remoteex"):
        assert cam.acq_status()[0] == "idle"
    assert len([r for r in caplog.records if "skipping reply" in r.getMessage()]) <= 2
    assert cam._warnings.counts["foreign-reply"] == 20000


def test_a_transfer_without_a_data_connection_is_code_9():
    with RemoteExSimulator(lit_state(), SCENE) as sim:
        cmd = socket.create_connection(sim.address, timeout=5)
        try:
            assert cmd.recv(64) == b"RemoteEx Ready\r"
            cmd.sendall(b"AppStart()\rAcqStart(Acquire)\rAcqStop()\rImgDataGet(Current,Data)\r")
            buf = b""
            while buf.count(b"\r") < 4:
                buf += cmd.recv(4096)
            assert buf.split(b"\r")[3] == b"9,ImgDataGet"
        finally:
            cmd.close()


# ----------------------------------------------------------- handbook commands
@pytest.mark.parametrize("command,args,expected", [
    ("AppLicenceGet", (), ["1", "1", "1", "0", "1", "0"]),
    ("AsyncCommandStatus", (), ["0", "0", "0"]),
    ("DevParamInfoEx", ("Streak", "MCP Gain"), ["1", "1", "MCP Gain", "30", "1", "0", "63"]),
    ("DevParamInfoEx", ("Streak", "Mode"), ["1", "1", "Mode", "Operate", "2", "2", "Focus", "Operate"]),
    ("DevParamInfoEx", ("Streak", "Time Range"), ["1", "1", "Time Range", "2", "2", "4", "1", "2", "3", "4"]),
    ("DevParamInfo", ("Delaybox", "Delay A"), ["Delay A", "0", "1", "0", "1e-06"]),
    ("DevParamGet", ("TD", "DeviceName"), ["C5680 streak unit (simulated)"]),
    ("CamParamInfo", ("Acquire", "Exposure"), ["Exposure time", "10 ms", "4"]),
    ("CamParamInfoEx", ("Setup", "Binning"), ["Binning factor", "1 x 1", "2", "3", "1 x 1", "2 x 2", "4 x 4"]),
    ("CamParamsList", ("AI",), ["3", "Exposure", "Gain", "NrExposures"]),
])
def test_handbook_commands_answer_on_the_simulator(lab, command, args, expected):
    sim, cam, state = lab
    assert cam.command(command, *args) == expected


def test_dev_params_list_names_every_streak_parameter(lab):
    sim, cam, state = lab
    values = cam.command("DevParamsList", "Streak")
    assert int(values[0]) == len(values) - 1 == 9
    assert values[1:4] == ["Time Range", "Mode", "Gate Mode"]
    assert cam.command("DevParamsList", "Delaybox")[0] == "6"


@pytest.mark.parametrize("command,args,code", [
    ("AcqStart", ("Sweep",), 2),
    ("AcqLiveMonitor", ("Sometimes",), 2),
    ("DevParamSet", ("Streak", "Mode", "Sweep"), 10),
    ("DevParamSet", ("Streak", "MCP Gain", "many"), 1),
    ("DevParamSet", ("Streak", "Time Range", "1 ns"), 10),          # a synchroscan unit takes setting numbers
    ("DevParamSet", ("Delaybox", "Delay A", "2e-6"), 10),
    ("CamParamSet", ("Setup", "Binning", "3 x 3"), 10),
    ("CamParamSet", ("Setup", "CameraInfo", "x"), 7),
    ("CamParamGet", ("Nowhere", "Exposure"), 2),
    ("DevParamInfoEx", ("Streak",), 6),
    ("ImgDataGet", ("current", "ScalingTable", "Horizontal"), 7),
    ("ImgRingBufferGet", ("Data", "1"), 7),
])
def test_handbook_error_codes_on_the_simulator(lab, command, args, code):
    sim, cam, state = lab
    cam.acquire()                                   # there is a current image
    with pytest.raises(DeviceError) as info:
        cam.command(command, *args)
    assert info.value.code == code


def test_list_valued_device_parameters_accept_their_entries(lab):
    sim, cam, state = lab
    cam.set_streak_mode("Focus")
    assert cam.streak_mode() == "Focus"
    cam.command("DevParamSet", "Streakcamera", "Trig. slope", "falling")
    assert cam.command("DevParamGet", "Streak", "Trig. slope") == ["Falling"]
    cam.command("DevParamSet", "Del", "Trig. Mode", "Ext. rising")
    assert cam.command("DevParamGet", "Delaybox", "Trig. Mode") == ["Ext. rising"]


def test_focus_mode_puts_the_time_integrated_slit_image_on_the_middle_rows(lab):
    sim, cam, state = lab
    cam.set_streak_mode("Focus")
    assert sim.gain == 0                                  # the driver's focus-mode gain interlock
    img = cam.acquire().data.astype(float)
    expected = SCENE.expected_focus_counts(3, gain=0)
    assert np.abs(img - expected).mean() < 5.0
    row = int(np.argmax(img.sum(axis=0)))
    assert abs(row - (SCENE.n_t - 1) / 2) <= 1
    assert cam.scaling_table_ps() is None                # no sweep: no time scaling
    cam.set_streak_mode("Operate")
    cam.configure(gain=SCENE.reference_gain)
    assert np.abs(cam.acquire().data - SCENE.expected_counts(3)).mean() < 5.0


def test_analog_integration_sums_and_photon_counting_drops_the_dark_level(lab):
    sim, cam, state = lab
    cam.command("CamParamSet", "AI", "NrExposures", "3")
    cam.command("CamParamSet", "PC", "NrExposures", "2")
    means = {}
    for mode in ("Acquire", "AI", "PC"):
        cam.acquire_mode = mode
        means[mode] = cam.acquire().data.astype(float)
        assert sim.last_frame_info["mode"] == mode
    signal = SCENE.expected_counts(3) - SCENE.dark_level
    assert means["AI"].mean() == pytest.approx(3 * means["Acquire"].mean(), rel=0.02)
    assert means["PC"].mean() == pytest.approx(2 * signal.mean(), rel=0.03)
    assert means["PC"].min() == 0.0                      # photon counting: no offset, no read noise


def test_image_display_and_profiles(lab):
    sim, cam, state = lab
    data = cam.acquire().data
    values, payload = cam.transaction("ImgDataGet", ("current", "Display"), data=lambda v: int(v[0]) * int(v[1]))
    disp = np.frombuffer(payload, np.uint8).reshape(SCENE.n_t, SCENE.n_x).T
    assert values[2:] == ["1", "Display"] and disp.max() == 255 and disp.min() == 0
    assert np.argmax(disp) == np.argmax(data)
    values, payload = cam.transaction("ImgDataGet", ("current", "Profile", "3", "0", "0", str(SCENE.n_x),
                                                     str(SCENE.n_t)), data=lambda v: 4 * int(v[0]))
    np.testing.assert_allclose(np.frombuffer(payload, "<f4"), data.sum(axis=0), rtol=1e-6)


def test_single_sweep_unit_takes_time_strings_and_its_scaling_table_is_the_sweep():
    with RemoteExSimulator(lit_state(angle_deg=float(SCENE.angle_deg[3])), SCENE, single_sweep=True) as sim, \
            RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
        assert cam.time_range() == "1 ns"
        cam.configure(time_range="2ns")
        assert cam.time_range() == "2 ns"
        cam.configure(time_range="1 ns")
        with pytest.raises(DeviceError) as info:
            cam.configure(time_range=3)
        assert info.value.code == 10
        img = cam.acquire()
        assert img.metadata["time_range"] == "1 ns"
        assert np.abs(img.data - SCENE.expected_counts(3, time_range="1 ns")).mean() < 5.0
        np.testing.assert_allclose(cam.scaling_table_ps(), SCENE.row_times_ps(0.0, "1 ns"), rtol=1e-6)


def test_synchroscan_scaling_table_and_a_camera_without_one():
    with RemoteExSimulator(lit_state(), SCENE) as sim, RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
        cam.configure(time_range=3)
        cam.acquire()
        np.testing.assert_allclose(cam.scaling_table_ps(), SCENE.row_times_ps(0.0, 3), rtol=1e-6)
    with RemoteExSimulator(lit_state(), SCENE, scaling_table=False) as sim, \
            RemoteExCamera(*sim.address, timeout_s=1.0) as cam:
        cam.acquire()
        assert cam.scaling_table_ps() is None


def test_live_mode_announces_each_image_and_stops(lab):
    sim, cam, state = lab
    cam.set_exposure_s(0.02, "Live")
    cam.start_live(ring_buffers=3)
    assert cam.acq_status() == ("busy", "Live")
    assert cam.command("AsyncCommandStatus")[0] == "1"
    seqs = []
    for _ in range(3):
        img, seq = cam.live_image(timeout_s=5.0)
        seqs.append(seq)
        assert np.abs(img - SCENE.expected_counts(3, exposure_s=0.02)).mean() < 6.0
    assert seqs == sorted(seqs) and len(set(seqs)) == 3
    cam.stop_live()
    assert cam.acq_status() == ("idle", "")
    assert cam.command("AsyncCommandStatus") == ["0", "0", "0"]


def test_single_live_takes_one_image(lab):
    sim, cam, state = lab
    cam.command("AcqLiveMonitor", "NotifyTimeStamp")
    cam.command("AcqStart", "SingleLive")
    event = cam.wait_live_event(5.0)
    assert event[0] == "NotifyTimeStamp" and float(event[1]) >= 0
    assert cam.acq_status()[0] == "idle"
    assert cam.read_image().shape == (SCENE.n_x, SCENE.n_t)
    cam.command("AcqLiveMonitor", "Off")


@pytest.mark.parametrize("monitor,compute", [
    (("Average", "Subarray", "2", "10", "4", "8"), lambda img: [float(f"{img[10:18, 2:6].mean():.6g}")]),
    (("Maximum", "FullArea"), lambda img: [float(img.max())]),
    (("Minimum",), lambda img: [float(img.min())]),
    (("Profile", "3", "FullArea"), lambda img: [img.shape[0]] + [float(f"{v:.6g}") for v in img.sum(axis=1)]),
    (("Profile", "2", "Subarray", "0", "0", "5", "3"), lambda img: [5] + [float(f"{v:.6g}") for v in
                                                                        img[0:3, 0:5].sum(axis=0)]),
])
def test_live_monitoring_values_describe_the_live_image(lab, monitor, compute):
    sim, cam, state = lab
    cam.command("AcqLiveMonitor", *monitor)
    cam.command("AcqStart", "SingleLive")
    event = cam.wait_live_event(5.0)
    image = cam.read_image().T.astype(np.float64)                   # (rows = t, columns = x), as sent
    assert event[0] == monitor[0]
    assert [float(v) for v in event[1:]] == pytest.approx(compute(image), rel=1e-6)
    cam.command("AcqLiveMonitor", "Off")


@pytest.mark.parametrize("args,code", [
    (("Profile", "4", "FullArea"), 10), (("Profile", "2"), 6), (("Average", "Somewhere"), 2),
    (("Maximum", "Subarray", "0", "0", "999", "1"), 10), (("RingBuffer", "0"), 10),
])
def test_live_monitoring_arguments_are_checked(lab, args, code):
    sim, cam, state = lab
    with pytest.raises(DeviceError) as info:
        cam.command("AcqLiveMonitor", *args)
    assert info.value.code == code
