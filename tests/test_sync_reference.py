"""The laser sync's trigger-interval measurement as a time base: the bytes on the wire, the run
store's ``trigger_interval_ps`` (durable, resumable, one per frame), and ``reconstruct`` aligning
every frame on it."""
import threading

import numpy as np
import pytest

from acquisition.rig import run_capture, start_simulated_lab
from acquisition.runstore import open_run
from acquisition.session import CaptureFailed, SettingRejected, TriggerCountMismatch, check_trigger_count
from drivers.errors import ProtocolError
from drivers.scpi_sync import ScpiLaserSync
from drivers.sim.state import LabState
from drivers.sim.usbtmc import UsbtmcBackend
from drivers.transport import ScriptedTransport
from reconstruction.align import AlignmentError, reference_correction_ps
from reconstruction.build import ReconstructionError, reconstruct
from reconstruction.cubestore import open_cube
from streaklab.cli import main
from test_capture import sim_config

pytestmark = pytest.mark.timeout(60)

VID, PID = 0x1209, 0x5A17


# ---------------------------------------------------------------- the wire
def test_intervals_on_the_wire_through_the_simulated_usbtmc_unit():
    state = LabState()
    backend = UsbtmcBackend(state, reference_noise_ps=0.0)
    with ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.5) as sync:
        assert sync.fetch_trigger_intervals() == []
        state.triggers.extend([(1234.5, (1, 2)), (1230.0626, (1, 3))])
        backend.clear_log()
        assert sync.fetch_trigger_intervals() == [1234.5, 1230.063]
        assert sync.fetch_trigger_intervals() == []              # the read emptied the buffer
        bulk = [(kind, data) for kind, _, data in
                ((e[0], e[1], e[2]) for e in backend.log if e[0] in ("bulk_out", "bulk_in"))]
    # DEV_DEP_MSG_OUT (bTag 3: the first fetch took 1 and 2) with the query, REQUEST_DEV_DEP_MSG_IN
    # (bTag 4, up to 65536 bytes), DEV_DEP_MSG_IN with the reply and EOM
    reply = b"2,1234.500,1230.063\n"
    assert bulk[:3] == [("bulk_out", bytes([1, 3, 0xFC, 0, 12, 0, 0, 0, 1, 0, 0, 0]) + b":TINT:FETC?\n"),
                        ("bulk_out", bytes([2, 4, 0xFB, 0, 0, 0, 1, 0, 0, 0, 0, 0])),
                        ("bulk_in", bytes([2, 4, 0xFB, 0, len(reply), 0, 0, 0, 1, 0, 0, 0]) + reply)]
    assert bulk[5] == ("bulk_in", bytes([2, 6, 0xF9, 0, 2, 0, 0, 0, 1, 0, 0, 0]) + b"0\n\0\0")   # 4-byte alignment


def test_measurement_is_delay_less_shift_plus_seeded_noise():
    state = LabState()
    backend = UsbtmcBackend(state, reference_noise_ps=0.5)
    keys = [(7, 9, k) for k in range(400)]
    with ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, timeout_s=2.0) as sync:
        state.triggers.extend((100.0, key) for key in keys)
        first = np.array(sync.fetch_trigger_intervals())
        state.triggers.extend((100.0, key) for key in keys)
        again = np.array(sync.fetch_trigger_intervals())
    np.testing.assert_array_equal(first, again)                 # the same trigger, the same noise
    assert abs(first.mean() - 100.0) < 0.1 and 0.45 < first.std() < 0.55


@pytest.mark.parametrize("reply, match", [
    (b"2,1.5\n", "the count says 2 intervals, the reply carries 1"),
    (b"x,1.5\n", "the count 'x' is not a non-negative integer"),
    (b"2,1.5,nan\n", "interval 1 is not a finite number: 'nan'"),
    (b"1,abc\n", "interval 0 is not a finite number: 'abc'"),
])
def test_malformed_interval_replies_are_protocol_errors(reply, match):
    t = ScriptedTransport([(b":TINT:FETC?\n", reply)], terminator=b"\n", timeout_s=0.3)
    with pytest.raises(ProtocolError, match=match):
        ScpiLaserSync(transport=t).fetch_trigger_intervals()
    t.assert_done()


def test_a_count_that_does_not_match_the_frames_names_line_and_frame():
    assert check_trigger_count(4, [1.0, 2.0], 2) == [1.0, 2.0]
    with pytest.raises(TriggerCountMismatch, match=r"^line 4 frame 1: no trigger interval measured \(the laser "
                                                   r"sync measured 1 for the line's 3 frames\)$"):
        check_trigger_count(4, [1.0], 3)
    with pytest.raises(TriggerCountMismatch, match=r"^line 2 frame 1: the laser sync measured 3 trigger intervals"):
        check_trigger_count(2, [1.0, 2.0, 3.0], 2)


# ---------------------------------------------------------------- capture
def _config(**simulation):
    return sim_config(n_lines=6, n_x=16, n_t=256, camera={"frames_per_line": 2},
                      sync={"reference": True, "trigger_delay_ps": 40.0},
                      simulation={"clock_speed": 60.0, **simulation})


def _capture(path, config, **kwargs):
    lab = start_simulated_lab(config)
    try:
        result = run_capture(config, path, lab=lab, **kwargs)
        shifts = lab.frame_shifts_ps()
    finally:
        lab.close()
    return result, shifts


def test_a_missed_measurement_is_a_clear_failure_naming_line_and_frame(tmp_path):
    cfg = sim_config(n_lines=3, sync={"reference": True}, session={"retries": 1})
    lab = start_simulated_lab(cfg)
    try:
        original = lab.camera._render

        def render(mode, n):               # the sync unit misses the trigger of every frame of line 1
            out = original(mode, n)
            if out[1]["line"] == 1 and out[1]["light"]:
                lab.state.triggers.pop()
            return out
        lab.camera._render = render
        with pytest.raises(CaptureFailed, match=r"line 1 \(mirror 0 deg\) failed after 2 attempts: "
                                                r"TriggerCountMismatch: line 1 frame 0: no trigger interval"):
            run_capture(cfg, tmp_path / "run.zarr", lab=lab)
    finally:
        lab.close()
    run = open_run(tmp_path / "run.zarr")
    assert run.done_mask().tolist() == [True, False, False]
    assert np.isfinite(run.trigger_intervals_ps([0])).all() and np.isnan(run.trigger_intervals_ps([1])).all()


def test_stopped_and_resumed_capture_gives_the_same_store(tmp_path):
    cfg = sim_config(n_lines=5, camera={"frames_per_line": 2}, sync={"reference": True})
    assert _capture(tmp_path / "reference.zarr", cfg)[0].status == "complete"
    stop = threading.Event()

    def on_line(session, line):
        if line == 1:
            stop.set()
    assert _capture(tmp_path / "run.zarr", cfg, stop_event=stop, on_line=on_line)[0].status == "interrupted"
    assert open_run(tmp_path / "run.zarr").done_mask().tolist() == [True, True, False, False, False]
    assert _capture(tmp_path / "run.zarr", cfg, resume=True)[0].status == "complete"
    a, b = open_run(tmp_path / "reference.zarr"), open_run(tmp_path / "run.zarr")
    for name in ("trigger_interval_ps", "streaks", "done"):
        assert np.asarray(a[name][...]).tobytes() == np.asarray(b[name][...]).tobytes(), name
    assert np.isfinite(b.trigger_intervals_ps(range(5))).all()
    assert not b.verify().lines


# ---------------------------------------------------------------- reconstruction
@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """A steady scan and the same scan under jitter and drift (default 0.5 ps measurement noise)."""
    d = tmp_path_factory.mktemp("syncref")
    _, none = _capture(d / "steady.zarr", _config())
    _, shifts = _capture(d / "moving.zarr", _config(jitter_ps=3.0, drift_ps_per_min=10.0))
    reconstruct(d / "steady.zarr", d / "steady.cube.zarr", align=False)
    reconstruct(d / "moving.zarr", d / "raw.cube.zarr", align=False)
    assert np.all(none == 0) and shifts.size == 12 and np.std(shifts) > 1.0
    return d, shifts


def _rms_error(cube_path, d):
    ref = np.asarray(open_cube(d / "steady.cube.zarr").array[...], np.float64)
    lit = ref > 0.2 * np.nanmax(ref)
    return float(np.sqrt(np.mean((np.asarray(open_cube(cube_path).array[...], np.float64) - ref)[lit] ** 2)))


def test_jitter_and_drift_are_undone_on_the_sync_reference(captures, capsys):
    d, shifts = captures
    assert main(["reconstruct", str(d / "moving.zarr"), "--out", str(d / "aligned.cube.zarr")]) == 0
    assert "aligned 12 frames on the laser sync's trigger intervals" in capsys.readouterr().err
    cube = open_cube(d / "aligned.cube.zarr")
    prov = cube.attrs["provenance"]
    assert prov["alignment_reference"] == "laser sync trigger intervals" and prov["sync_reference_nominal_ps"] == 40.0
    # each frame moved by its measured interval less the nominal: the shift undone, to the 0.5 ps noise
    err = np.asarray(cube.group["fiducial_correction_ps"][...], np.float64).ravel() + shifts
    assert np.abs(err).max() < 2.0 and 0.2 < np.sqrt(np.mean(err ** 2)) < 1.0
    assert _rms_error(d / "aligned.cube.zarr", d) < 0.2 * _rms_error(d / "raw.cube.zarr", d)


def test_without_measurement_noise_the_alignment_is_the_true_shifts(tmp_path, captures):
    d, _ = captures
    _, shifts = _capture(tmp_path / "exact.zarr", _config(jitter_ps=3.0, drift_ps_per_min=10.0,
                                                          reference_noise_ps=0.0))
    reconstruct(tmp_path / "exact.zarr", tmp_path / "exact.cube.zarr")
    corr = np.asarray(open_cube(tmp_path / "exact.cube.zarr").group["fiducial_correction_ps"][...]).ravel()
    np.testing.assert_allclose(corr, -shifts, atol=5e-4)          # the wire's 0.001 ps resolution
    # the exact reference leaves the cube nearer the steady one than the noisy one does
    exact = _rms_error(tmp_path / "exact.cube.zarr", d)
    reconstruct(d / "moving.zarr", tmp_path / "noisy.cube.zarr")
    assert exact < _rms_error(tmp_path / "noisy.cube.zarr", d) and exact < 0.15 * _rms_error(d / "raw.cube.zarr", d)


def test_bad_references_name_line_and_frame(tmp_path, captures):
    d, _ = captures
    with pytest.raises(AlignmentError, match=r"^line 7 frame 1: no usable trigger interval from the laser sync "
                                             r"\(nan; 2 such frames in all\)$"):
        reference_correction_ps(np.array([[1.0, 2.0], [3.0, np.nan], [np.inf, 1.0]]), 0.0, line_ids=[5, 7, 9])
    # a non-finite interval on disk: reconstruct names the line and frame, writes nothing
    import shutil
    shutil.copytree(d / "moving.zarr", tmp_path / "bad.zarr")
    run = open_run(tmp_path / "bad.zarr", mode="r+")
    values = np.asarray(run["trigger_interval_ps"][3], np.float64)
    values[1] = np.nan
    run["trigger_interval_ps"][3] = values
    with pytest.raises(ReconstructionError, match=r"bad.zarr: line 3 frame 1: no usable trigger interval"):
        reconstruct(tmp_path / "bad.zarr", tmp_path / "bad.cube.zarr")
    assert not (tmp_path / "bad.cube.zarr").exists()
    # the pulse asked of a run that records only the sync reference, and the sync of one without it
    with pytest.raises(ReconstructionError, match="records no fiducial"):
        reconstruct(d / "moving.zarr", tmp_path / "p.cube.zarr", align_on="pulse")
    plain = sim_config(n_lines=2)
    assert _capture(tmp_path / "plain.zarr", plain)[0].status == "complete"
    assert not open_run(tmp_path / "plain.zarr").has_sync_reference
    with pytest.raises(ReconstructionError, match="--align-on sync, but the run records no trigger intervals"):
        reconstruct(tmp_path / "plain.zarr", tmp_path / "s.cube.zarr", align_on="sync")


def test_a_unit_without_the_interval_counter_is_refused_before_any_line(tmp_path):
    # the unit leaves :TINT:FETC? unanswered and queues -113 (undefined header), as a unit without
    # the option does: the capture stops at the setup with one line naming the setting
    cfg = sim_config(n_lines=2, sync={"reference": True})
    lab = start_simulated_lab(cfg)
    try:
        lab.sync.instrument.interval_counter = False
        with pytest.raises(SettingRejected) as err:
            run_capture(cfg, tmp_path / "run.zarr", lab=lab)
    finally:
        lab.close()
    text = str(err.value)
    assert "sync.reference = True: the laser sync rejects this setting" in text and "-113" in text
    assert "\n" not in text
    assert not (tmp_path / "run.zarr").exists() or not open_run(tmp_path / "run.zarr").done_mask().any()
