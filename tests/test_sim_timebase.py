"""The simulated camera's time base (jitter, drift, sweep nonlinearity, shading, fiducial) and gain log."""
import dataclasses

import numpy as np
import pytest

from drivers.remoteex import RemoteExCamera
from drivers.sim.camera import RemoteExSimulator, frame_seed
from drivers.sim.scene import VirtualScene
from drivers.sim.state import LabState
from drivers.sim.timebase import FIDUCIAL_FRACTION, FIDUCIAL_PIXELS, SimClock, TimeBase

pytestmark = pytest.mark.timeout(30)

SCENE = VirtualScene.default(n_lines=4, n_x=16, n_t=128, seed=0)
# A calibration target (one direct return per pixel at a known delay), low noise.
TARGET = dataclasses.replace(VirtualScene.calibration(n_lines=2, n_x=16, n_t=128, seed=0),
                             photon_scale=20000.0, read_noise=0.0)
# Nothing but a flat light level on every row: shows the sensitivity along the time axis.
_flat = {k: np.array(v) for k, v in TARGET.params.items()}
_flat["direct_amplitude"][:] = 0.0
FLAT = dataclasses.replace(TARGET, params=_flat, background=1.0, photon_scale=4000.0)


class FakeWall:
    """A wall clock the test moves by hand: the simulated time is exact."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def camera_frames(scene, n, *, timebase=None, wall=None, seed=3, line=0, exposure_s=0.01, before=None):
    """``n`` frames (x, t) as float, and the simulator, through the real driver over TCP."""
    state = LabState(mirror_angle_deg=float(scene.angle_deg[line]), sync_output_enabled=True)
    out = []
    with RemoteExSimulator(state, scene, seed=seed, timebase=timebase, wall_clock=wall) as sim:
        with RemoteExCamera(*sim.address, timeout_s=2.0) as cam:
            cam.configure(exposure_s=exposure_s, gain=scene.reference_gain, time_range=2)
            for i in range(n):
                if before is not None:
                    before(i)
                out.append(cam.acquire(timeout_s=5).data.astype(np.float64))
    return out, sim


def peak_times_ps(profiles, times_ps):
    """Centroid time of the peak of each profile (rows along the last axis), over +-4 rows."""
    out = []
    for p in np.atleast_2d(profiles):
        k = int(np.argmax(p))
        sl = slice(max(0, k - 4), k + 5)
        w = np.clip(p[sl], 0, None)
        out.append(float((w * times_ps[sl]).sum() / w.sum()))
    return np.array(out)


# ------------------------------------------------------------------ off by default
def test_every_effect_is_off_by_default_and_frames_are_the_scenes_own_bit_for_bit():
    angle = float(SCENE.angle_deg[1])
    plain, sim = camera_frames(SCENE, 3, line=1)
    idle, _ = camera_frames(SCENE, 3, line=1, timebase=TimeBase(clock_speed=60.0))
    assert sim.timebase == TimeBase() and not sim.timebase.active and sim.frame_shifts == []
    for k in range(3):
        rng = np.random.default_rng(frame_seed(3, angle, 0.0, True, k))
        want = SCENE.render_frame(1, rng, exposure_s=0.01, gain=SCENE.reference_gain, time_range=2)
        assert plain[k].astype(np.uint16).tobytes() == want.tobytes()
        assert idle[k].astype(np.uint16).tobytes() == want.tobytes()


@pytest.mark.parametrize("kw, message", [
    ({"jitter_ps": -1.0}, "jitter_ps must be >= 0"),
    ({"sweep_nonlinearity": 0.25}, "sweep_nonlinearity must be in"),
    ({"shading": 1.0}, "shading must be in"),
    ({"clock_speed": 0.0}, "clock_speed must be > 0"),
    ({"drift_ps_per_min": float("nan")}, "drift_ps_per_min must be a finite number"),
    ({"fiducial": 1}, "fiducial must be true or false"),
])
def test_bad_time_base_values_are_refused_naming_the_value(kw, message):
    with pytest.raises(ValueError, match=message):
        TimeBase(**kw)


# ------------------------------------------------------------------ curves
def test_sweep_bow_and_shading_follow_their_stated_curves():
    tb = TimeBase(sweep_nonlinearity=0.05, shading=0.2)
    nominal = SCENE.row_times_ps(0.0, 2)
    true = tb.true_row_times_ps(nominal)
    span = nominal[-1] - nominal[0]
    dev = true - nominal
    assert dev[0] == 0.0 and dev[-1] == 0.0
    assert dev.max() == pytest.approx(0.05 * span, rel=1e-3)                 # the bow's height at the middle
    assert int(np.argmax(dev)) in ((SCENE.n_t - 1) // 2, SCENE.n_t // 2)
    assert np.all(np.diff(true) > 0)
    s = tb.sensitivity(SCENE.n_t)
    assert s[0] == pytest.approx(0.8) and s[-1] == pytest.approx(1.2)
    np.testing.assert_allclose(np.diff(s), 0.4 / (SCENE.n_t - 1))           # a linear ramp


def test_frames_are_seen_at_the_bowed_row_times_not_the_reported_ones():
    tb = TimeBase(sweep_nonlinearity=0.04)
    frames, sim = camera_frames(TARGET, 1, timebase=tb)
    nominal = TARGET.row_times_ps(0.0, 2)
    true = tb.true_row_times_ps(nominal)
    rows = np.arange(TARGET.n_t, dtype=np.float64)
    delays = TARGET.params["direct_delay_ps"][0]                           # (n_x,), the known delay map
    seen_rows = peak_times_ps(frames[0] - TARGET.dark_level, rows)          # centroid row of each pixel
    np.testing.assert_allclose(seen_rows, np.interp(delays, true, rows), atol=0.3)
    # where the camera's own table says they are is several rows off: the capture would not notice
    assert np.all(np.abs(np.interp(delays, nominal, rows) - seen_rows) > 2.0)
    np.testing.assert_allclose(sim._scaling_table(), nominal, rtol=1e-12)    # the table is still nominal


def test_shading_multiplies_the_signal_along_the_time_axis():
    tb = TimeBase(shading=0.3)
    frames, _ = camera_frames(FLAT, 4, timebase=tb)
    plain, _ = camera_frames(FLAT, 4)
    ratio = (np.mean(frames, axis=(0, 1)) - FLAT.dark_level) / (np.mean(plain, axis=(0, 1)) - FLAT.dark_level)
    np.testing.assert_allclose(ratio, tb.sensitivity(FLAT.n_t), atol=0.03)
    assert ratio[:10].mean() < 0.75 and ratio[-10:].mean() > 1.25


# ------------------------------------------------------------------ jitter and drift
def test_jitter_per_frame_has_the_given_rms_and_moves_the_frames():
    tb = TimeBase(jitter_ps=3.0, fiducial=True)
    scene = VirtualScene.default(n_lines=2, n_x=4, n_t=64, seed=0)
    frames, sim = camera_frames(scene, 200, timebase=tb)
    shifts = np.array([f["shift_ps"] for f in sim.frame_shifts])
    assert shifts.size == 200 and np.all([f["drift_ps"] == 0.0 for f in sim.frame_shifts])
    assert np.sqrt(np.mean(shifts ** 2)) == pytest.approx(3.0, rel=0.2)
    assert abs(shifts.mean()) < 0.8
    # deterministic: the same seed gives the same draws
    assert [tb.jitter_draw_ps(3, k) for k in range(200)] == list(shifts)
    # and the frames move by them: the fiducial pulse is seen shifted by each frame's draw
    frames, sim = camera_frames(TARGET, 12, timebase=TimeBase(jitter_ps=6.0, fiducial=True))
    nominal = TARGET.row_times_ps(0.0, 2)
    seen = peak_times_ps(np.array([f[:FIDUCIAL_PIXELS].mean(axis=0) for f in frames]) - TARGET.dark_level, nominal)
    where = TimeBase().fiducial_nominal(nominal)["nominal_ps"]
    np.testing.assert_allclose(seen - where, [f["shift_ps"] for f in sim.frame_shifts], atol=1.0)


def test_drift_follows_the_simulated_clock_at_clock_speed_60():
    wall = FakeWall()
    tb = TimeBase(drift_ps_per_min=10.0, clock_speed=60.0, fiducial=True)

    def ten_wall_seconds_later(i):
        wall.t += 10.0 * (i > 0)          # each frame 10 wall seconds after the last: 10 simulated minutes

    frames, sim = camera_frames(TARGET, 3, timebase=tb, wall=wall, before=ten_wall_seconds_later)
    got = [(f["sim_time_s"], f["drift_ps"], f["shift_ps"]) for f in sim.frame_shifts]
    assert got == [(0.0, 0.0, 0.0), (600.0, 100.0, 100.0), (1200.0, 200.0, 200.0)]
    # the fiducial pulse moved by the drift in the frames themselves
    nominal = TARGET.row_times_ps(0.0, 2)
    t = peak_times_ps(np.array([f[:FIDUCIAL_PIXELS].mean(axis=0) for f in frames]) - TARGET.dark_level, nominal)
    np.testing.assert_allclose(t - t[0], [0.0, 100.0, 200.0], atol=1.0)


def test_the_real_clock_runs_clock_speed_times_the_wall_clock():
    import time

    clock = SimClock(60.0)
    t0 = time.monotonic()
    time.sleep(0.05)
    sim_s = clock.now_s()
    assert 60.0 * 0.05 <= sim_s <= 60.0 * (time.monotonic() - t0 + 1e-3)
    with pytest.raises(ValueError, match="clock speed"):
        SimClock(-1.0)


# ------------------------------------------------------------------ fiducial
def test_the_fiducial_pulse_is_where_documented():
    tb = TimeBase(fiducial=True)
    frames, sim = camera_frames(TARGET, 1, timebase=tb)
    nominal = TARGET.row_times_ps(0.0, 2)
    where = tb.fiducial_nominal(nominal)
    assert (where["x_start"], where["x_stop"]) == (0, FIDUCIAL_PIXELS)
    assert where["nominal_ps"] == pytest.approx(nominal[0] + FIDUCIAL_FRACTION * (nominal[-1] - nominal[0]))
    signal = frames[0] - TARGET.dark_level
    seen = peak_times_ps(signal[:FIDUCIAL_PIXELS], nominal)
    np.testing.assert_allclose(seen, where["nominal_ps"], atol=0.5)
    rows = np.arange(TARGET.n_t)
    assert abs(np.interp(seen[0], nominal, rows) - where["row"]) < 0.3
    # only on its pixels: the others see no light that early
    early = slice(0, int(where["row"]) + 6)
    assert signal[FIDUCIAL_PIXELS:, early].max() < 0.05 * signal[:FIDUCIAL_PIXELS, early].max()


def test_a_fiducial_off_by_default_leaves_its_pixels_dark_early_in_the_window():
    frames, _ = camera_frames(TARGET, 1)
    row = int(TimeBase().fiducial_nominal(TARGET.row_times_ps(0.0, 2))["row"])
    assert (frames[0][:FIDUCIAL_PIXELS, row - 3: row + 4] - TARGET.dark_level).max() < 50


# ------------------------------------------------------------------ gain log
def test_the_simulator_logs_gain_and_mode_changes_on_its_clock():
    wall = FakeWall()
    with RemoteExSimulator(LabState(), SCENE, timebase=TimeBase(clock_speed=2.0), wall_clock=wall) as sim:
        with RemoteExCamera(*sim.address, timeout_s=2.0) as cam:
            wall.t += 1.0
            cam.configure(gain=40)
            cam.configure(gain=40)                                  # no change: no entry
            wall.t += 1.0
            cam.set_streak_mode("Focus")
            wall.t += 1.0
        log = list(sim.gain_log)
    assert log == [(0.0, SCENE.reference_gain, "Operate"), (2.0, 40, "Operate"), (4.0, 0, "Operate"),
                   (4.0, 0, "Focus")]
