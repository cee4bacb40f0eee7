"""Reconstruction: dark, flat, time-axis calibration, scene order, and every bad input."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from acquisition.config import ConfigError, parse_config
from acquisition.runstore import RunStoreError, create_run
from reconstruction.build import ReconstructionError, reconstruct
from reconstruction.calibrate import CalibrationError, resample_uniform, uniform_grid
from reconstruction.cubestore import open_cube, write_cube
from streaklab.cli import main

ROOT = Path(__file__).resolve().parents[1]
POLY = [10.0, 1.6, 0.004]          # ps; ~1.6 ps/row at the start, ~2.1 ps/row at the end
ANGLES = [2.0, -1.0, 0.0, 3.0, 1.0, -2.0]   # acquisition order differs from scene order
NX, NROWS, DARK = 5, 64, 100.0


def truth(angle, x, t_ps):
    """Noise-free signal (counts) of pixel x of the line at ``angle``: one Gaussian pulse."""
    delay = 40.0 + 6.0 * x + 4.0 * angle
    return 1000.0 * np.exp(-0.5 * ((t_ps - delay) / 8.0) ** 2)


def make_run(path, *, poly=POLY, done=None, flat=None, delay_ps=0.0, frames=2):
    raw = {"scan": {"angles_deg": ANGLES}, "camera": {"frames_per_line": frames}, "dark": {"frames": 2},
           "sync": {"trigger_delay_ps": delay_ps},
           "calibration": {"time_poly_ps": poly, "time_bin_ps": 2.0}}
    run = create_run(path, parse_config(raw), image_shape=(NX, NROWS))
    rows = np.arange(NROWS)
    t_rows = np.polynomial.polynomial.polyval(rows, POLY) + delay_ps
    run.write_dark(np.stack([np.full((NX, NROWS), DARK - 1), np.full((NX, NROWS), DARK + 1)]).astype(np.uint16))
    sens = np.ones((NX, NROWS)) if flat is None else flat
    for i, a in enumerate(ANGLES):
        if done is not None and not done[i]:
            continue
        sig = np.stack([truth(a, x, t_rows) for x in range(NX)]) * sens
        f = np.stack([np.rint(DARK + sig + k - 0.5 * (frames - 1)) for k in range(frames)]).astype(np.uint16)
        run.write_line(i, f, angle_deg=a + 0.001, timestamp=1.7e9 + i)
    return run


def test_resample_is_exact_for_linear_profiles_and_vectorised():
    t = np.polynomial.polynomial.polyval(np.arange(50), [3.0, 2.0, 0.01])
    prof = np.stack([5.0 + 0.5 * t, -t])            # linear in t: interpolation is exact
    t0, n = uniform_grid(t, 2.0)
    assert t0 == 4.0 and t0 + (n - 1) * 2.0 <= t[-1] < t0 + n * 2.0
    out = resample_uniform(prof, t, time_bin_ps=2.0, t0_ps=t0, n_bins=n)
    grid = t0 + 2.0 * np.arange(n)
    np.testing.assert_allclose(out, np.stack([5.0 + 0.5 * grid, -grid]), rtol=1e-12)
    # Decreasing row times give the same answer as the reversed increasing ones.
    out_rev = resample_uniform(prof[:, ::-1], t[::-1], time_bin_ps=2.0, t0_ps=t0, n_bins=n)
    np.testing.assert_allclose(out_rev, out, rtol=1e-12)
    with pytest.raises(CalibrationError, match="leaves the calibrated window"):
        resample_uniform(prof, t, time_bin_ps=2.0, t0_ps=t0, n_bins=n + 5)


def test_cube_matches_signal_in_scene_order(tmp_path):
    make_run(tmp_path / "run.zarr")
    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr", chunks=(4, 2))
    g = cube.group
    assert cube.array.dtype == np.float32 and cube.array.chunks == (4, 2, cube.shape[2])
    order = np.argsort(ANGLES)
    np.testing.assert_array_equal(g["line_index"][...], order)
    np.testing.assert_array_equal(g["y"][...], np.sort(ANGLES))
    assert g["y"].attrs["units"] == "deg"
    assert g["line_valid"][...].all()
    t = cube.time_axis_ps()
    assert cube.t0_ps == 10.0 and cube.time_bin_ps == 2.0
    expect = np.stack([np.stack([truth(ANGLES[i], x, t) for x in range(NX)]) for i in order])
    # Linear interpolation of ~2 ps samples of an 8 ps Gaussian: error below 1 % of the peak.
    err = np.abs(cube.array[...] - expect)
    assert err.max() < 10.0, err.max()
    prov = cube.attrs["provenance"]
    assert prov["run_path"] == str((tmp_path / "run.zarr").resolve())
    assert prov["lines_used"] == [int(i) for i in order] and prov["lines_missing"] == []
    assert prov["run_config_hash"] == zarr.open_group(str(tmp_path / "run.zarr"), mode="r").attrs["config_hash"]


def test_trigger_delay_shifts_time_axis(tmp_path):
    make_run(tmp_path / "run.zarr", delay_ps=100.0)
    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    assert cube.t0_ps == 110.0
    t = cube.time_axis_ps()
    i = int(np.argsort(ANGLES)[0])
    expect = np.stack([truth(ANGLES[i], x, t) for x in range(NX)])
    assert np.abs(cube.array[0] - expect).max() < 10.0


def test_flat_field_is_divided_out(tmp_path):
    flat = np.linspace(0.5, 1.5, NX)[:, None] * np.ones((1, NROWS))
    make_run(tmp_path / "run.zarr", flat=flat)
    np.save(tmp_path / "flat.npy", flat[:, 0] * 3.0)         # per-pixel flat; scale does not matter
    plain_cube = reconstruct(tmp_path / "run.zarr", tmp_path / "plain.zarr")
    plain = plain_cube.array[...]
    fixed = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr", flat_path=tmp_path / "flat.npy")
    assert fixed.attrs["provenance"]["flat_field_sha256"]
    # one camera's counts have one noise law; a flat field gives every pixel its own gain
    assert plain_cube.attrs["noise_law"] == "detector" and "noise_law" not in fixed.attrs
    ratio = plain[:, :, 20] / fixed.array[:, :, 20]
    np.testing.assert_allclose(ratio, np.broadcast_to(flat[:, 0], ratio.shape), rtol=0.03)
    np.save(tmp_path / "badflat.npy", np.ones(NX + 1))
    with pytest.raises(CalibrationError, match=r"does not fit the images; expected \(5, 64\)"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "c2.zarr", flat_path=tmp_path / "badflat.npy")
    np.save(tmp_path / "zeroflat.npy", np.zeros(NX))
    with pytest.raises(CalibrationError, match="not positive and finite"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "c2.zarr", flat_path=tmp_path / "zeroflat.npy")
    assert not (tmp_path / "c2.zarr").exists()


def test_unfinished_lines_need_allow_partial(tmp_path):
    done = [True, True, False, True, False, True]
    make_run(tmp_path / "run.zarr", done=done)
    with pytest.raises(ReconstructionError, match=r"2 of 6 lines are unfinished \(lines 2, 4\).*--allow-partial"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    assert not (tmp_path / "cube.zarr").exists()
    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr", allow_partial=True)
    valid = cube.group["line_valid"][...]
    data = cube.array[...]
    idx = cube.group["line_index"][...]
    np.testing.assert_array_equal(valid, np.asarray(done)[idx])
    assert np.isnan(data[~valid]).all() and np.isfinite(data[valid]).all()
    assert cube.attrs["provenance"]["lines_missing"] == [2, 4]


def test_bad_inputs_are_named_and_nothing_is_written_over(tmp_path):
    write_cube(tmp_path / "cube.zarr", np.ones((2, 2, 4)), time_bin_ps=2.0)
    with pytest.raises(RunStoreError, match="not a run store .*'cube'"):
        reconstruct(tmp_path / "cube.zarr", tmp_path / "out.zarr")
    make_run(tmp_path / "bent.zarr", poly=[0.0, 2.0, -0.05])      # turns back at row 19
    with pytest.raises(ConfigError, match=r"calibration\.time_poly_ps: must be strictly monotonic over rows 0\.\.63"):
        reconstruct(tmp_path / "bent.zarr", tmp_path / "out.zarr")
    assert not (tmp_path / "out.zarr").exists()
    make_run(tmp_path / "run.zarr")
    with pytest.raises(FileExistsError, match="already exists"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    assert open_cube(tmp_path / "cube.zarr").array[0, 0, 0] == 1.0
    with pytest.raises(ReconstructionError, match="is the run store itself"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "run.zarr", overwrite=True)
    # A failure after validation (bad flat) with --overwrite still leaves the old cube alone.
    np.save(tmp_path / "nanflat.npy", np.full(NX, np.nan))
    with pytest.raises(CalibrationError):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr", flat_path=tmp_path / "nanflat.npy", overwrite=True)
    assert open_cube(tmp_path / "cube.zarr").array[0, 0, 0] == 1.0
    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr", overwrite=True)
    assert cube.shape[0] == len(ANGLES)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []   # no temporaries left


def test_command_line_and_xarray(tmp_path, capsys):
    xr = pytest.importorskip("xarray")
    make_run(tmp_path / "run.zarr", done=[True] * 5 + [False])
    argv = ["reconstruct", str(tmp_path / "run.zarr"), "--out", str(tmp_path / "cube.zarr"), "--chunks", "2", "3"]
    assert main(argv) == 2
    assert "1 of 6 lines are unfinished (lines 5)" in capsys.readouterr().err
    assert main(argv + ["--allow-partial"]) == 0
    assert "1 unfinished lines left NaN" in capsys.readouterr().err
    ds = xr.open_zarr(tmp_path / "cube.zarr", consolidated=False)
    assert ds["cube"].dims == ("y", "x", "t") and ds["line_valid"].dims == ("y",)
    assert ds["cube"].encoding["chunks"] == (2, 3, ds.sizes["t"])


def test_module_entry_point_runs(tmp_path):
    make_run(tmp_path / "run.zarr")
    r = subprocess.run([sys.executable, "-m", "streaklab", "reconstruct", str(tmp_path / "run.zarr"), "--out",
                        str(tmp_path / "cube.zarr")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert open_cube(tmp_path / "cube.zarr").shape[:2] == (len(ANGLES), NX)


def test_time_bins_memory_and_disk_are_checked_before_anything_is_written(tmp_path, monkeypatch):
    from core import limits

    run = make_run(tmp_path / "run.zarr")
    cfg = dict(run.group.attrs["config"])
    # 1e-6 ps bins over the 116.7 ps window: 1.17e8 bins, a 4.18 GiB-per-line-block request
    cfg["calibration"] = {**cfg["calibration"], "time_bin_ps": 1e-6}
    run.group.attrs["config"] = cfg
    with pytest.raises(CalibrationError, match=r"^calibration\.time_bin_ps = 1e-06 ps makes 1\.17e\+08 time bins "
                                               r"of the calibrated window of 116\.676 ps, above the limit of 65536"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    assert not (tmp_path / "cube.zarr").exists()
    cfg["calibration"] = {**cfg["calibration"], "time_bin_ps": 2.0}
    run.group.attrs["config"] = cfg
    monkeypatch.setattr(limits, "available_memory", lambda: 1000)
    with pytest.raises(ReconstructionError, match=r"--chunks: needs .* to reconstruct 6 lines at a time, but only "
                                                  r"1000 B of memory is available"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    monkeypatch.undo()
    monkeypatch.setattr(limits.shutil, "disk_usage", lambda p: type("U", (), {"free": 100})())
    with pytest.raises(ReconstructionError, match=r"cube: needs 6\.91 KiB for a 6 x 5 x 59 float32 cube "
                                                  r"\(limits\.MAX_CUBE_BYTES\), but only 100 B are free"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    assert not (tmp_path / "cube.zarr").exists()
