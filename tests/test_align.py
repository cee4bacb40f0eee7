"""Fiducial alignment: known per-frame shifts recovered, frames moved onto the time grid, every bad input."""
import numpy as np
import pytest
from scipy.special import erf

from acquisition.config import parse_config
from acquisition.runstore import create_run
from reconstruction.align import (AlignmentError, Fiducial, fiducial_correction_ps, mean_of_covering, parse_fiducial,
                                  resample_aligned, row_edges_ps, split_dark)
from reconstruction.build import ReconstructionError, reconstruct
from streaklab.cli import main

N_ROWS, NX, DARK = 160, 4, 100.0
ROW_TIMES_PS = 2.0 * np.arange(N_ROWS)          # linear sweep, 2 ps per row
FID = {"row_start": 2, "row_stop": 40, "nominal_ps": 40.0}


def pulse_counts(centre_ps, sigma_ps, total, row_times_ps=ROW_TIMES_PS):
    """Counts per row of a Gaussian pulse of ``total`` counts (integrated over each row's extent)."""
    e = row_edges_ps(row_times_ps)
    return total * np.diff(0.5 * (1.0 + erf((e - np.asarray(centre_ps)[..., None]) / (np.sqrt(2) * sigma_ps))))


def frames_with_jitter(jitter_ps, *, fiducial=True, scene_ps=200.0):
    """(line, frame, x, row) counts: the fiducial at 40 ps and a scene pulse at ``scene_ps``, each
    frame late by its jitter (ps)."""
    j = np.asarray(jitter_ps, dtype=np.float64)
    prof = pulse_counts(scene_ps + j, 6.0, 20000.0)
    if fiducial:
        prof = prof + pulse_counts(40.0 + j, 3.0, 8000.0)
    return np.broadcast_to(prof[:, :, None, :], j.shape + (NX, N_ROWS)).copy()


def _moved(frames, shifts_ps):
    """Frames moved by ``shifts_ps`` onto the rows' own 2 ps grid."""
    return resample_aligned(frames, ROW_TIMES_PS, shifts_ps, time_bin_ps=2.0, t0_ps=0.0, n_bins=N_ROWS)


def test_known_shifts_are_recovered_and_undone():
    rng = np.random.default_rng(3)
    jitter = rng.normal(0.0, 5.0, (3, 8))                          # ps, 2.5 rows RMS
    noisy = rng.poisson(frames_with_jitter(jitter)).astype(np.float64)
    corr = fiducial_correction_ps(noisy, ROW_TIMES_PS, Fiducial(**FID))
    assert corr.shape == (3, 8)
    assert np.abs(corr + jitter).max() < 0.15                      # ps
    aligned = np.nan_to_num(_moved(noisy, corr))                    # the bins a frame missed: 0
    truth = frames_with_jitter(np.zeros((1, 1)))[0, 0]
    mean_aligned = aligned.mean(axis=(0, 1))
    mean_raw = noisy.mean(axis=(0, 1))
    peak = truth.max()
    # averaging unaligned frames smears the pulses; aligned, they match the unshifted truth (to
    # linear interpolation's loss between 2 ps samples: 1.4 % of a 6 ps pulse, 5.4 % at 3 ps)
    assert np.abs(mean_raw - truth).max() > 0.1 * peak
    err = np.abs(mean_aligned - truth)
    assert err[..., 50:].max() < 0.02 * peak and err.max() < 0.06 * peak
    # the counts are kept, save what left the ends
    np.testing.assert_allclose(aligned.sum(axis=(-1, -2)), noisy.sum(axis=(-1, -2)), rtol=1e-3)


def test_fiducial_time_is_the_pulse_centre_on_a_sweep_whose_rows_differ_in_length():
    # the simulated camera's sweep (rows 1.8 ps long at the start, 2.6 ps at the end); its rows are
    # samples of the time profile at the row times.  A pulse at a known centre, anywhere in the band
    # and at any phase between rows, is found at that centre: no bias from the rows' unequal length
    # (the centroid in row numbers, mapped to time, is up to 0.02 ps early here).
    rows = np.arange(256, dtype=np.float64)
    row_times = 2.0 + 1.8 * rows + 0.0015625 * rows ** 2
    centres = np.array([[35.63, 36.1, 37.05, 41.9], [80.3, 120.77, 200.5, 260.2]])           # ps
    frames = 1500.0 * np.exp(-0.5 * ((row_times - centres[..., None]) / 4.0) ** 2)
    frames = np.broadcast_to(frames[:, :, None, :], centres.shape + (2, rows.size)).copy()
    fid = Fiducial(0, 256, 35.63, 0, 2)
    corr = fiducial_correction_ps(frames, row_times, fid)
    np.testing.assert_allclose(corr, 35.63 - centres, atol=0.002)


def test_whole_row_shift_is_exact_and_uncovered_bins_are_empty():
    rng = np.random.default_rng(0)
    f = np.zeros((2, 1, 3, N_ROWS))
    f[..., 50:90] = rng.uniform(1, 100, (2, 1, 3, 40))
    f[..., :3] = 7.0                                                 # light at the window's start
    out = _moved(f, np.array([[6.0], [-4.0]]))                       # +3 rows, -2 rows
    np.testing.assert_allclose(out[0, 0, :, 53:93], f[0, 0, :, 50:90], atol=1e-9)
    np.testing.assert_allclose(out[1, 0, :, 48:88], f[1, 0, :, 50:90], atol=1e-9)
    assert np.isnan(out[0, 0, :, :3]).all() and np.isnan(out[1, 0, :, -2:]).all()   # the frame did not see there
    assert np.isfinite(out[0, 0, :, 3:]).all() and np.isfinite(out[1, 0, :, :-2]).all()
    # a sub-row shift moves the centroid by the shift (the pulse alone, away from the ends)
    g = np.where(np.arange(N_ROWS) < 10, 0.0, f)
    sub = np.nan_to_num(_moved(g, np.array([[0.7], [-1.3]])))
    c = lambda a: (a * ROW_TIMES_PS).sum(-1) / a.sum(-1)
    np.testing.assert_allclose(c(sub) - c(g), np.array([[[0.7] * 3], [[-1.3] * 3]]), atol=0.05)


def test_missing_fiducial_names_line_and_frame():
    jitter = np.zeros((2, 3))
    f = frames_with_jitter(jitter)
    f[1, 2] = frames_with_jitter(np.zeros((1, 1)), fiducial=False)[0, 0]
    f = np.random.default_rng(1).poisson(f + 5.0).astype(np.float64)
    with pytest.raises(AlignmentError, match=r"^line 7 frame 2: no usable fiducial pulse in rows 2\.\.40"):
        fiducial_correction_ps(f, ROW_TIMES_PS, Fiducial(**FID), line_ids=[4, 7])


@pytest.mark.parametrize("attr, match", [
    ({"row_start": 2}, "lacks 'row_stop'"),
    ({"row_start": 30, "row_stop": 20}, "band of at least 5"),
    ({"row_start": 0, "row_stop": 500}, "band of at least 5"),
    ({"row_start": 0, "row_stop": 20, "nominal_ps": "soon"}, "nominal_ps must be a finite number"),
    ({"row_start": 0.5, "row_stop": 20}, "row_start must be an integer"),
    ([1, 2], "must be a mapping"),
])
def test_bad_fiducial_attribute(attr, match):
    with pytest.raises(AlignmentError, match=match):
        parse_fiducial(attr, N_ROWS, NX)


def make_run(path, jitter_ps, *, fiducial=True, record=True):
    raw = {"scan": {"angles_deg": [0.0, 1.0, 2.0]}, "camera": {"frames_per_line": jitter_ps.shape[1]},
           "dark": {"frames": 1}, "sync": {"trigger_delay_ps": 0.0},
           "calibration": {"time_poly_ps": [0.0, 2.0], "time_bin_ps": 2.0}}
    run = create_run(path, parse_config(raw), image_shape=(NX, N_ROWS))
    if record:
        run.group.attrs["fiducial"] = FID
    run.write_dark(np.full((1, NX, N_ROWS), DARK, dtype=np.uint16))
    rng = np.random.default_rng(5)
    frames = rng.poisson(frames_with_jitter(jitter_ps, fiducial=fiducial)) + DARK
    for i in range(jitter_ps.shape[0]):
        run.write_line(i, frames[i].astype(np.uint16), angle_deg=float(i), timestamp=1.7e9 + i)
    return run


def test_reconstruct_aligns_by_default_and_records_corrections(tmp_path, capsys):
    jitter = np.random.default_rng(2).normal(0.0, 6.0, (3, 5))
    jitter[1] = np.abs(jitter[1]) + 4.0                    # every frame of run line 1 late: its window's end unseen
    make_run(tmp_path / "run.zarr", jitter)
    assert main(["reconstruct", str(tmp_path / "run.zarr"), "--out", str(tmp_path / "cube.zarr")]) == 0
    err = capsys.readouterr().err
    assert "aligned 15 frames on the fiducial: corrections" in err
    from reconstruction.cubestore import open_cube
    cube = open_cube(tmp_path / "cube.zarr")
    corr = cube.group["fiducial_correction_ps"]
    assert corr.attrs["units"] == "ps" and tuple(corr.metadata.dimension_names) == ("y", "frame")
    np.testing.assert_allclose(corr[...], -jitter[cube.group["line_index"][...]], atol=0.2)
    assert cube.attrs["provenance"]["aligned_on_fiducial"] is True
    # the bins no moved frame reaches: counted per line, said in one line where there are any
    from reconstruction.align import uncovered_bins
    gap = cube.group["uncovered_bins"][...]
    assert tuple(cube.group["uncovered_bins"].metadata.dimension_names) == ("y",)
    expect = uncovered_bins(ROW_TIMES_PS, corr[...], time_bin_ps=cube.time_bin_ps, t0_ps=cube.t0_ps,
                            n_bins=cube.shape[2])
    assert gap.tolist() == expect.tolist() and gap.any()
    assert f"lines were moved so far that up to {int(gap.max())} bins at the window's ends" in err
    t = cube.time_axis_ps()
    # 2 ps bins on the 2 ps rows: the same numbers as the rows
    truth = pulse_counts(200.0, 6.0, 20000.0, t) + pulse_counts(40.0, 3.0, 8000.0, t)
    peak = truth.max()
    # each moved frame is sampled onto the bins by linear interpolation, as an unaligned cube is:
    # a pulse of width sigma loses at most 1 - exp(-(1 ps)^2 / (2 sigma^2)) of its peak between
    # 2 ps samples (1.4 % at 6 ps, 5.4 % at the fiducial's 3 ps)
    err = np.abs(cube.array[...] - truth)
    assert err[..., t > 100].max() < 0.03 * peak and err.max() < 0.06 * peak
    assert main(["reconstruct", str(tmp_path / "run.zarr"), "--out", str(tmp_path / "plain.zarr"), "--no-align"]) == 0
    plain = open_cube(tmp_path / "plain.zarr")
    assert "fiducial_correction_ps" not in plain.group
    assert np.abs(plain.array[...] - truth).max() > 0.1 * peak


def test_align_refused_without_fiducial_and_nothing_written(tmp_path, capsys):
    make_run(tmp_path / "run.zarr", np.zeros((3, 2)), record=False)
    with pytest.raises(ReconstructionError, match="records no fiducial"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr", align=True)
    assert not (tmp_path / "cube.zarr").exists()
    make_run(tmp_path / "weak.zarr", np.zeros((3, 2)), fiducial=False)
    assert main(["reconstruct", str(tmp_path / "weak.zarr"), "--out", str(tmp_path / "cube.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "weak.zarr: line 0 frame 0: no usable fiducial pulse in rows 2..40" in err[0]
    assert not (tmp_path / "cube.zarr").exists()


def test_split_dark_keeps_the_sensors_structure_and_separates_its_noise():
    rng = np.random.default_rng(11)
    ramp = 100.0 + 0.05 * np.arange(N_ROWS)                      # slow offset along the rows
    noise = rng.normal(0.0, 2.0, (NX, N_ROWS))
    dark = ramp + noise
    dark[1, 70] += 400.0                                         # a hot sample of the sensor
    structure, rest = split_dark(dark)
    np.testing.assert_allclose(structure + rest, dark)
    assert structure[1, 70] == dark[1, 70] and rest[1, 70] == 0.0   # structure: moves with the frames
    off = structure - ramp
    off[1, 70] = 0.0
    assert np.abs(off[:, 20:-20]).max() < 2.0                    # the ramp, to the median's noise
    assert np.corrcoef(rest.ravel(), noise.ravel())[0, 1] > 0.95
    with pytest.raises(AlignmentError, match="2-D"):
        split_dark(dark[0])


def test_aligned_line_carries_the_dark_noise_once_and_white():
    # two frames 6 ps (3 rows) apart; the frames noiseless, the dark image the only noise: an
    # aligned line's noise is then the dark's, subtracted once on the bins, not one copy per shift
    from reconstruction.build import LineCalibration

    rng = np.random.default_rng(4)
    shifts = np.array([[0.0, 6.0]])
    frames = frames_with_jitter(shifts) + DARK
    noise = rng.normal(0.0, 3.0, (NX, N_ROWS))
    calib = LineCalibration(ROW_TIMES_PS, 2.0, 0.0, N_ROWS, DARK + noise, None, {}, Fiducial(**FID))
    rows, corr = calib.correct(frames)
    np.testing.assert_allclose(corr, -shifts, atol=0.05)
    clean = mean_of_covering(_moved(frames_with_jitter(shifts), -shifts))
    cube_noise = (rows - clean)[0, :, 6:-6].ravel()
    assert np.corrcoef(cube_noise, -noise[:, 6:-6].ravel())[0, 1] > 0.97
    n = (rows - clean)[0, :, 6:-6]
    lag3 = (n[:, 3:] * n[:, :-3]).mean() / (n * n).mean()
    assert abs(lag3) < 0.15                                      # a copy at the frames' lag: 0.5


def test_a_dark_of_noise_alone_moves_next_to_none_of_it_with_the_frames():
    # a dark image of white noise about a level: its structure is the level alone.  What of the
    # noise the running median keeps would be subtracted twice from moved frames (once moved,
    # once unmoved), a bump at a pulse's scale; at the ends a median padded with the end sample
    # is that sample's noise over several rows (0.7 of the noise variance at the first rows)
    rng = np.random.default_rng(21)
    noise = rng.normal(0.0, 2.0, (400, N_ROWS))
    for noise_var in (np.full(400, 4.0), None):
        structure, rest = split_dark(DARK + noise, noise_var=noise_var)
        np.testing.assert_allclose(structure + rest, DARK + noise)
        moved = structure - np.median(structure, axis=1, keepdims=True)
        assert np.mean(moved[:, :8] ** 2) < 0.05 * 4.0           # the first rows: nearest padding 0.7 * 4
        assert np.mean(moved[:, -8:] ** 2) < 0.05 * 4.0
        assert np.mean(moved ** 2) < 0.02 * 4.0                  # a 31-row median alone: 0.05 * 4


def test_frames_moved_far_carry_the_darks_noise_once_and_white_from_the_window_start():
    # two noiseless frames late by 60 ps (30 rows; the dark image the only noise): the aligned line
    # is the clean one less the dark's noise on the bins unmoved, from the first bin on.  A running
    # median of the noise moved with the frames would add itself at two places 30 rows apart
    from reconstruction.build import LineCalibration

    nx, rng = 200, np.random.default_rng(22)
    shifts = np.array([[60.0, 61.0]])
    prof = pulse_counts(200.0 + shifts, 6.0, 20000.0) + pulse_counts(40.0 + shifts, 3.0, 8000.0)
    frames = np.broadcast_to(prof[:, :, None, :], (1, 2, nx, N_ROWS)).copy()
    noise = rng.normal(0.0, 2.0, (nx, N_ROWS))
    fid = Fiducial(row_start=2, row_stop=70, nominal_ps=40.0)
    calib = LineCalibration(ROW_TIMES_PS, 2.0, 0.0, N_ROWS, DARK + noise, None, {}, fid,
                            dark_noise_var=np.full(nx, 4.0))
    rows, corr = calib.correct(frames + DARK)
    np.testing.assert_allclose(corr, -shifts, atol=0.05)
    clean = mean_of_covering(resample_aligned(frames, ROW_TIMES_PS, corr, time_bin_ps=2.0, t0_ps=0.0,
                                              n_bins=N_ROWS))
    extra = (rows - clean + noise)[0, :, :N_ROWS - 32]          # the bins both frames cover
    # at a pulse's scale (means of 8 bins), beside the dark noise's own 2 / sqrt(8) = 0.71 counts
    scale = np.sqrt(np.mean(extra.reshape(nx, -1, 8).mean(axis=2) ** 2, axis=0))
    assert scale[0] < 0.35                                       # median padded with the end sample: 1.4
    assert np.sqrt(np.mean(scale ** 2)) < 0.3                    # a 31-row median twice: 0.73


def test_a_sensors_fine_fixed_pattern_moves_with_the_frames_and_cancels():
    # a fixed pattern of 10 counts RMS from sample to sample (far above the mean dark's own noise,
    # 0.5 counts RMS from 16 frames of read noise 2): it is in every frame at the same rows, so it
    # must be subtracted before the frames move; subtracted after, it would be left moved
    from reconstruction.build import LineCalibration

    rng = np.random.default_rng(5)
    shifts = np.array([[0.0, 6.0]])
    pattern = rng.normal(0.0, 10.0, (NX, N_ROWS))
    dark_noise = rng.normal(0.0, 0.5, (NX, N_ROWS))
    frames = frames_with_jitter(shifts) + DARK + pattern
    clean = mean_of_covering(_moved(frames_with_jitter(shifts), -shifts))

    def error(noise_var):
        calib = LineCalibration(ROW_TIMES_PS, 2.0, 0.0, N_ROWS, DARK + pattern + dark_noise, None, {},
                                Fiducial(**FID), dark_noise_var=noise_var)
        rows, _ = calib.correct(frames)
        return float(np.std((rows - clean)[0, :, 6:-6]))

    assert error(np.full(NX, 0.25)) < 1.0                       # the pattern cancels; the dark's noise is left
    assert error(None) > 5.0                                    # taken for noise, it is left moved
    structure, rest = split_dark(DARK + pattern + dark_noise, noise_var=0.25)
    assert np.std(rest) < 0.1                                   # the pattern's share: (100 - 0.25) / 100


def test_moved_noise_keeps_its_variance_and_whiteness_at_any_fraction_of_a_row():
    # white noise of unit variance on 2 ps rows, moved by a whole row (2 ps) and by half a row
    # (1 ps) onto the 2 ps grid: the Lanczos move keeps 0.79 of the variance at half a row (linear
    # interpolation 0.5) and correlates neighbouring bins 0.25 (linear 0.5)
    noise = np.random.default_rng(8).normal(0.0, 1.0, (1, 2, 400, N_ROWS))
    out = _moved(noise, np.array([[2.0, 1.0]]))[0][..., 10:-10]            # away from the ends
    whole, half = out[0], out[1]
    assert abs(whole.var() - 1.0) < 0.02                                      # a whole row: the rows
    assert 0.74 < half.var() < 0.84
    lag1 = (half[:, 1:] * half[:, :-1]).mean() / half.var()
    assert 0.15 < lag1 < 0.35


@pytest.mark.parametrize("shift_ps", [0.5, 0.7, 1.0, -1.3])
def test_a_pulse_moved_by_a_fraction_of_a_row_keeps_its_shape_and_lands_at_its_centre(shift_ps):
    # a Gaussian of sigma 4 ps sampled on 2 ps rows, moved by a fraction of a row: the moved
    # samples are the pulse at its moved centre to 0.3 % of its peak (linear interpolation loses
    # up to 1 - exp(-(1 ps)^2 / (2 sigma^2)) = 3 % half way between rows), its centroid the
    # moved centre to 0.01 ps, and its counts kept
    centre = 150.0
    pulse = 1000.0 * np.exp(-0.5 * ((ROW_TIMES_PS - centre) / 4.0) ** 2)
    out = np.nan_to_num(_moved(pulse[None, None, None, :], np.array([[shift_ps]]))[0, 0, 0])
    truth = 1000.0 * np.exp(-0.5 * ((ROW_TIMES_PS - centre - shift_ps) / 4.0) ** 2)
    assert np.abs(out - truth).max() < 0.005 * 1000.0
    centroid = (out * ROW_TIMES_PS).sum() / out.sum()
    assert abs(centroid - (centre + shift_ps)) < 0.01
    np.testing.assert_allclose(out.sum(), pulse.sum(), rtol=1e-6)



@pytest.mark.parametrize("n_frames", [2, 5])
def test_the_dark_noise_variance_is_the_mean_scatter_not_its_median_and_ignores_hot_samples(n_frames):
    # whole-number dark frames of read noise 3 counts RMS (variance 9 + 1/12 with the rounding):
    # the mean dark's noise variance is that over the frames' number.  A median over single
    # samples' scatters reads 0.45 of it from two frames; a hot sample (scatter 10^4) changes nothing.
    from reconstruction.calibrate import dark_noise_variance

    rng = np.random.default_rng(11)
    frames = np.round(100.0 + rng.normal(0.0, 3.0, (n_frames, 32, 256)))
    frames[0, :, 40] += 200.0                                       # a hot row in one frame
    truth = (9.0 + 1.0 / 12.0) / n_frames
    est = dark_noise_variance(frames)
    assert est.shape == (32,)
    assert abs(np.median(est) / truth - 1.0) < 0.05
    assert np.all(np.abs(est / truth - 1.0) < 0.35)
    assert dark_noise_variance(frames[:1]) is None


def test_a_lines_mean_near_the_windows_ends_is_over_the_frames_that_saw_there():
    # light of 40 counts per frame all over the window, two frames moved by +6 and -6 ps (3 rows):
    # the first 3 bins are seen by one frame only, as are the last 3; their mean is still 40
    # (a plain mean over both frames, one of them missing there, read 20)
    f = np.full((1, 2, 3, N_ROWS), 40.0)
    moved = _moved(f, np.array([[6.0, -6.0]]))
    line = mean_of_covering(moved)
    np.testing.assert_allclose(line, 40.0, atol=1e-9)
    both = np.full((1, 2, 1, 4), np.nan)
    both[0, 0, 0, :2] = [1.0, 3.0]
    np.testing.assert_array_equal(mean_of_covering(both)[0, 0], [1.0, 3.0, 0.0, 0.0])   # no frame: 0


def test_uncovered_bins_count_what_no_moved_frame_of_a_line_reaches():
    from reconstruction.align import uncovered_bins

    # rows 0..198 ps every 2 ps onto the same grid: a frame moved by -6 ps leaves the last 3 bins,
    # one moved by +4 ps the first 2; a line holding both covers everything, a line of the first
    # alone lacks 3, an untaken frame (NaN) counts for nothing
    rows_ps = np.arange(100) * 2.0
    corr = np.array([[-6.0, 4.0], [-6.0, np.nan], [np.nan, np.nan], [-6.0, -6.0]])
    got = uncovered_bins(rows_ps, corr, time_bin_ps=2.0, t0_ps=0.0, n_bins=100)
    assert got.tolist() == [0, 3, 0, 3]
    moved = resample_aligned(np.ones((4, 2, 1, 100)), rows_ps, np.nan_to_num(corr), time_bin_ps=2.0, t0_ps=0.0,
                             n_bins=100)
    assert int((mean_of_covering(moved[3:4]) == 0).sum()) == 3      # the same bins the line's mean sets to 0
