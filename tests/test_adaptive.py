"""Adaptive accumulation (``streaklab capture --target-delay-error-ps E``) against the simulated lab."""

import numpy as np
import pytest

from acquisition.rig import run_capture
from acquisition.runstore import open_run
from reconstruction.build import line_calibration, reconstruct, scan_order
from reconstruction.calibrate import correct_frames, resample_uniform
from streaklab.adaptive import DelayErrorRule, line_delay_error_ps
from test_capture_resume import write_config as resume_config

MAX_FRAMES = 6


def write_config(path, n_lines=4):
    """The scan of tests/test_capture_resume.py with up to MAX_FRAMES frames per line."""
    return resume_config(path, n_lines, scan={"start_deg": -6.0, "stop_deg": 6.0},
                         camera={"frames_per_line": MAX_FRAMES, "acquire_timeout_s": 3.0},
                         devices={"timeout_s": 0.25}, session={"retries": 2, "retry_backoff_s": 0.0},
                         simulation={"seed": 3, "n_t": 128})


def adaptive_capture(cfg, out, target_ps):
    rule = DelayErrorRule(target_ps)
    result = run_capture(cfg, out, simulate=True, on_start=lambda s: rule.start(s.store), line_good_enough=rule)
    assert result.status == "complete"
    return rule


@pytest.mark.timeout(60)
def test_lines_stop_once_their_offline_error_reaches_the_target(tmp_path):
    cfg = write_config(tmp_path / "scan.toml")
    target = 0.03
    rule = adaptive_capture(cfg, tmp_path / "run.zarr", target)
    run = open_run(tmp_path / "run.zarr")
    taken, reached = run.frames_taken(), run.target_reached()
    assert taken.shape == (4,) and ((2 <= taken) & (taken <= MAX_FRAMES)).all()
    assert (taken < MAX_FRAMES).any()                   # some line stopped early
    assert run["frames_taken"].attrs["units"] == "1" and "long_name" in run["frames_taken"].attrs
    calib = line_calibration(run)
    streaks = run["streaks"][...]
    for line in range(4):
        k = int(taken[line])
        # the slots after the frames taken are unused (zero); the frames taken are images
        assert not streaks[line, k:].any() and streaks[line, :k].min(axis=(1, 2)).all()
        # the error the capture saw is the one computed offline from the stored frames
        offline = line_delay_error_ps(calib, streaks[line, :k])
        assert offline == rule.errors_ps[line]
        assert reached[line] == (offline <= target)
        if reached[line]:
            for fewer in range(2, k):                   # it stopped at the first count that reached it
                assert line_delay_error_ps(calib, streaks[line, :fewer]) > target
        else:
            assert k == MAX_FRAMES


@pytest.mark.timeout(60)
def test_reconstruct_averages_only_the_frames_taken(tmp_path):
    cfg = write_config(tmp_path / "scan.toml")
    adaptive_capture(cfg, tmp_path / "run.zarr", 0.03)
    run = open_run(tmp_path / "run.zarr")
    taken = run.frames_taken()
    assert (taken < MAX_FRAMES).any()
    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    calib = line_calibration(run)
    order, _ = scan_order(run)
    dark = run["dark"][...].mean(axis=0)
    for y, line in enumerate(order):
        frames = run["streaks"][int(line), :int(taken[line])]
        mean = correct_frames(frames, dark)                              # (x, rows)
        by_hand = resample_uniform(mean, calib.row_times_ps, time_bin_ps=cube.time_bin_ps, t0_ps=cube.t0_ps,
                                   n_bins=cube.array.shape[-1]).astype(np.float32)
        np.testing.assert_array_equal(cube.array[y], by_hand)


@pytest.mark.timeout(60)
def test_an_unreachable_target_stops_at_the_maximum_flags_the_lines_and_says_so(tmp_path, capsys):
    from streaklab.cli import main

    write_config(tmp_path / "scan.toml", n_lines=2)
    out = tmp_path / "run.zarr"
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(out), "--simulate",
                 "--quiet", "--target-delay-error-ps", "1e-9"]) == 0
    run = open_run(out)
    assert run.frames_taken().tolist() == [MAX_FRAMES, MAX_FRAMES]
    assert run.target_reached().tolist() == [False, False]
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "missed the target" in ln]
    assert lines == ["streaklab capture: adaptive accumulation (target 1e-09 ps): 12 frames in 2 lines "
                     "(at most 6 each); 2 line(s) missed the target at the maximum: [0, 1]"]


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "abc"])
def test_bad_target_values_are_refused_in_one_line_before_anything_is_written(tmp_path, capsys, value):
    from streaklab.cli import main

    (tmp_path / "scan.toml").write_text("[scan]\nangles_deg = [0.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n")
    out = tmp_path / "run.zarr"
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(out), "--simulate",
                 f"--target-delay-error-ps={value}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"streaklab capture: error: --target-delay-error-ps must be a positive number of ps, got '{value}'"
    assert not out.exists()


@pytest.mark.timeout(60)
def test_an_adaptive_run_resumes_and_a_fixed_run_can_resume_adaptive(tmp_path):
    import threading

    cfg = write_config(tmp_path / "scan.toml")
    out = tmp_path / "run.zarr"
    stop = threading.Event()
    first = run_capture(cfg, out, simulate=True, stop_event=stop, on_line=lambda s, line: stop.set())
    assert first.status == "interrupted" and first.acquired == [0]
    assert open_run(out).frames_taken() is None                     # a fixed accumulation so far
    rule = DelayErrorRule(0.03)
    result = run_capture(cfg, out, simulate=True, resume=True, on_start=lambda s: rule.start(s.store),
                         line_good_enough=rule)
    assert result.status == "complete" and result.acquired == [1, 2, 3]
    run = open_run(out)
    taken, reached = run.frames_taken(), run.target_reached()
    assert taken[0] == MAX_FRAMES and not reached[0]               # taken before, without the option
    assert ((2 <= taken[1:]) & (taken[1:] <= MAX_FRAMES)).all()
    assert sorted(rule.errors_ps) == [1, 2, 3]
    assert reached[1:].tolist() == [rule.errors_ps[i] <= 0.03 for i in (1, 2, 3)]
    assert np.isfinite(reconstruct(out, tmp_path / "cube.zarr").array[...]).all()


@pytest.mark.timeout(120)
def test_live_decomposition_of_an_adaptive_run_equals_the_offline_one(tmp_path, capsys,
                                                                      live_worker_at_normal_priority):
    from streaklab.cli import main
    from tests.test_live_decompose import _assert_same_arrays

    write_config(tmp_path / "scan.toml")
    run, live = tmp_path / "run.zarr", tmp_path / "live.zarr"
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(run), "--simulate", "--quiet",
                 "--target-delay-error-ps", "0.03", "--live", str(live)]) == 0
    assert (open_run(run).frames_taken() < MAX_FRAMES).any()
    assert main(["reconstruct", str(run), "--out", str(tmp_path / "cube.zarr")]) == 0
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "offline.zarr"),
                 "--chunks", "1", "16", "--quiet", "--per-pixel"]) == 0
    _assert_same_arrays(live, tmp_path / "offline.zarr")


@pytest.mark.timeout(60)
def test_bench_adaptive_reports_both_frame_counts_and_the_targets(tmp_path, capsys):
    import csv

    from streaklab.cli import main

    assert main(["bench", "adaptive", "--lines", "3", "--max-frames", "4", "--n-x", "16",
                 "--target-ps", "1e-9", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = list(csv.DictReader(open(tmp_path / "adaptive.csv")))
    assert [r["frames_taken"] for r in rows] == ["4", "4", "4"]       # unreachable: every line at the maximum
    assert "adaptive: 12 frames (per line [4, 4, 4]); 0% of lines reached the target" in out
    assert "fixed: no frame count up to 4 brings every line to the target" in out
    assert "  [NOT met] at least 95% of lines reach the target: 0% (0 of 3)" in out
    assert "  [not measured] at least 30% fewer frames than the fixed accumulation whose worst line reaches it: " \
           "no fixed frame count reaches it" in out
    assert main(["bench", "adaptive", "--max-frames", "1"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.timeout(60)
def test_a_missing_frames_taken_chunk_is_named_as_damage(tmp_path):
    from reconstruction.build import ReconstructionError

    cfg = write_config(tmp_path / "scan.toml", n_lines=2)
    adaptive_capture(cfg, tmp_path / "run.zarr", 1e-9)
    assert open_run(tmp_path / "run.zarr").absent_chunks() == []
    chunk = [p for p in (tmp_path / "run.zarr" / "frames_taken").rglob("*") if p.is_file() and p.name == "1"]
    assert len(chunk) == 1
    chunk[0].unlink()
    damage = open_run(tmp_path / "run.zarr").absent_chunks()
    assert [(d.array, d.coords) for d in damage] == [("frames_taken", (1,))]
    with pytest.raises(ReconstructionError, match="frames_taken"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")


class _RowsCalibration:
    """A line calibration whose rows are given profiles (x, n_bins), 2 ps bins from 2 ps."""
    time_bin_ps, t0_ps = 2.0, 2.0

    def __init__(self, profiles):
        self.profiles = profiles

    def rows(self, raw):
        return self.profiles[None].astype(np.float32)


def test_the_line_error_is_the_largest_delay_error_of_its_lit_pixels():
    # 20 pixels of one direct each; pixel 7 is the dimmest lit one (0.55 of the brightest), pixel 3
    # is below half the brightest (not lit): the line's error is pixel 7's, the largest of the lit
    rng = np.random.default_rng(5)
    t = 2.0 + 2.0 * np.arange(128)
    amp = np.full(20, 2000.0)
    amp[7], amp[3] = 0.55 * 2000.0, 0.3 * 2000.0
    profiles = amp[:, None] * np.exp(-0.5 * ((t - 100.0) / 6.0) ** 2) + rng.normal(0.0, 20.0, (20, t.size))
    from decomposition import decompose
    res = decompose(profiles.astype(np.float32), 2.0, t0_ps=2.0, stderr=True, nan_policy="omit")
    se = np.asarray(res.params["direct_delay_ps_stderr"], np.float64)
    assert not np.asarray(res.flags).any() and np.argmax(np.where(np.arange(20) == 3, 0, se)) == 7
    err = line_delay_error_ps(_RowsCalibration(profiles), np.zeros((2, 20, 128), np.uint16))
    assert err == se[7] and se[3] > err


def test_lit_pixels_are_the_trusted_bright_ones():
    from decomposition.flags import AMBIGUOUS, SPIKE
    from streaklab.adaptive import lit_pixels
    amp = np.array([10.0, 6.0, 4.0, 100.0, np.nan, 8.0, 9.0])
    se = np.array([0.1, 0.2, 0.3, 0.05, 0.1, np.nan, 0.1])
    flags = np.array([0, 0, 0, AMBIGUOUS, 0, 0, SPIKE])
    # pixel 3 (the brightest, but AMBIGUOUS) neither counts nor sets the brightness scale; pixel 2
    # is below half of the brightest trusted (10); 4 and 5 have no amplitude or error; a SPIKE is harmless
    np.testing.assert_array_equal(lit_pixels(amp, se, flags), [True, True, False, False, False, False, True])
    assert not lit_pixels(amp[4:6], se[4:6], flags[4:6]).any()
