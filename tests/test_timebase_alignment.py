"""End to end: the simulated camera's trigger jitter and drift, recorded against its fiducial by
the capture, undone by ``streaklab reconstruct`` (alignment on by default when the run has one)."""
import numpy as np
import pytest

from acquisition.rig import run_capture, start_simulated_lab
from reconstruction.build import reconstruct
from reconstruction.cubestore import open_cube
from test_capture import sim_config

pytestmark = pytest.mark.timeout(120)


def _capture(tmp_path, name, **simulation):
    cfg = sim_config(n_lines=6, n_x=16, n_t=256, camera={"frames_per_line": 2},
                     simulation={"fiducial": True, "clock_speed": 60.0, **simulation})
    lab = start_simulated_lab(cfg)
    try:
        assert run_capture(cfg, tmp_path / name, lab=lab).status == "complete"
        shifts = lab.frame_shifts_ps()
    finally:
        lab.close()
    return tmp_path / name, shifts


def test_jitter_and_drift_are_measured_on_the_fiducial_and_undone(tmp_path):
    steady, none = _capture(tmp_path, "steady.zarr")
    moving, shifts = _capture(tmp_path, "moving.zarr", jitter_ps=3.0, drift_ps_per_min=10.0)
    assert np.all(none == 0) and shifts.size == 12 and np.std(shifts) > 1.0
    for run, out, align in ((steady, "steady.cube.zarr", None), (moving, "aligned.cube.zarr", None),
                            (moving, "raw.cube.zarr", False)):
        reconstruct(run, tmp_path / out, align=align)
    aligned = open_cube(tmp_path / "aligned.cube.zarr")
    # each frame's correction is the shift the simulator applied, undone (line-major, as captured)
    corrections = np.asarray(aligned.group["fiducial_correction_ps"][...], np.float64).ravel()
    np.testing.assert_allclose(corrections - np.mean(corrections), -(shifts - np.mean(shifts)), atol=0.5)
    # the aligned cube is the steady one's, to the noise; the unaligned one is not
    ref = np.asarray(open_cube(tmp_path / "steady.cube.zarr").array[...], np.float64)
    lit = ref > 0.2 * np.nanmax(ref)
    err_aligned = np.sqrt(np.mean((np.asarray(aligned.array[...], np.float64) - ref)[lit] ** 2))
    err_raw = np.sqrt(np.mean((np.asarray(open_cube(tmp_path / "raw.cube.zarr").array[...], np.float64) - ref)[lit] ** 2))
    assert err_aligned < 0.5 * err_raw, (err_aligned, err_raw)
