"""Shading along time: a known 10 % row sensitivity measured from uniform light and divided out."""
import numpy as np
import pytest

from acquisition.config import parse_config
from acquisition.runstore import create_run
from reconstruction.build import reconstruct
from reconstruction.shading import ShadingError, shading_flat
from streaklab.cli import main

N_ROWS, NX, DARK = 200, 8, 100.0
U = np.linspace(-1.0, 1.0, N_ROWS)
SHADING = 1.0 + 0.1 * (0.6 * U - 0.8 * U ** 2 + 0.3 * np.sin(2.0 * U))   # 10 % variation along time
SHADING = SHADING / SHADING.mean()
COLUMNS = np.linspace(0.9, 1.1, NX)                                       # slit pixels differ too


def test_ten_percent_shading_leaves_under_half_a_percent():
    rng = np.random.default_rng(7)
    assert np.ptp(SHADING) > 0.09
    sens = COLUMNS[:, None] * SHADING[None, :]
    # uniform light: 64 frames of ~500 counts per pixel and row, Poisson noise
    uniform = rng.poisson(500.0 * sens, size=(64, NX, N_ROWS)).mean(axis=0)
    flat, rows = shading_flat(uniform * 64)
    np.testing.assert_allclose(rows.mean(), 1.0)
    # a signal of known amplitude seen through the shading (noise-free: the error measured is the
    # correction's, from the photon noise of the uniform-light capture), then corrected
    signal = 1000.0 * (1.0 + 0.5 * np.cos(3.0 * U))[None, :] * np.ones((NX, 1))
    seen = signal * sens
    corrected = seen / flat
    scale = (corrected.sum() / signal.sum())
    amp_err = np.abs(corrected.mean(axis=0) / scale / signal[0] - 1.0)
    raw_err = np.abs(seen.mean(axis=0) / (seen.sum() / signal.sum()) / signal[0] - 1.0)
    assert raw_err.max() > 0.05                                           # uncorrected: the shading shows
    assert amp_err.max() < 0.005
    assert np.abs(rows / SHADING - 1.0).max() < 0.005


@pytest.mark.parametrize("image, kwargs, match", [
    (np.full((4, 50), 0.1), {}, "too dim: row 0 holds"),
    (np.full((4, 50), 100.0), {"degree": 0}, "degree must be an integer from 1 to 20"),
    (np.full((50,), 100.0), {}, "must be 2-D"),
    (np.where(np.eye(4, 50) > 0, np.nan, 100.0), {}, "4 non-finite values"),
])
def test_bad_uniform_light_images(image, kwargs, match):
    with pytest.raises(ShadingError, match=match):
        shading_flat(image, **kwargs)


def make_run(path, profile, frames=8):
    raw = {"scan": {"angles_deg": [0.0, 1.0]}, "camera": {"frames_per_line": frames}, "dark": {"frames": 1},
           "calibration": {"time_poly_ps": [0.0, 2.0], "time_bin_ps": 2.0}}
    run = create_run(path, parse_config(raw), image_shape=(NX, N_ROWS))
    run.write_dark(np.full((1, NX, N_ROWS), DARK, dtype=np.uint16))
    rng = np.random.default_rng(8)
    sens = COLUMNS[:, None] * SHADING[None, :]
    for i in range(2):
        f = rng.poisson(np.broadcast_to(profile * sens, (frames, NX, N_ROWS))) + DARK
        run.write_line(i, f.astype(np.uint16), angle_deg=float(i), timestamp=1.7e9 + i)


def test_calibrate_shading_then_reconstruct_with_the_flat(tmp_path, capsys):
    make_run(tmp_path / "uniform.zarr", np.full(N_ROWS, 2000.0), frames=16)
    assert main(["calibrate-shading", str(tmp_path / "uniform.zarr"), "--out", str(tmp_path / "flat.npy")]) == 0
    assert "wrote the flat field" in capsys.readouterr().err
    assert np.load(tmp_path / "flat.npy").shape == (NX, N_ROWS)
    signal = 20000.0 * (1.0 + 0.5 * np.cos(3.0 * U))                     # photon noise well below 0.5 %
    make_run(tmp_path / "scene.zarr", signal)
    cube = reconstruct(tmp_path / "scene.zarr", tmp_path / "cube.zarr", flat_path=tmp_path / "flat.npy")
    got = cube.array[...].astype(np.float64).mean(axis=(0, 1))           # bins fall on the rows (2 ps each)
    ratio = got / signal[:got.size]
    assert np.abs(ratio / ratio.mean() - 1.0).max() < 0.005
    assert main(["calibrate-shading", str(tmp_path / "uniform.zarr"), "--out", str(tmp_path / "flat.txt")]) == 2
    assert "name it *.npy" in capsys.readouterr().err
    assert not (tmp_path / "flat.txt").exists()


@pytest.mark.timeout(60)
def test_a_uniform_light_capture_from_the_simulated_lab_gives_its_ten_percent_shading_to_half_a_percent(tmp_path, capsys):
    # end to end through the camera's wire protocol: the simulated camera's sensitivity ramps
    # 0.9 -> 1.1 along the time axis (drivers.sim.timebase), the scene is one level of light
    from acquisition.rig import run_capture
    from drivers.sim.timebase import TimeBase
    from test_capture import sim_config

    cfg = sim_config(n_lines=4, n_x=8, n_t=256, camera={"frames_per_line": 4},
                     simulation={"scene": "uniform", "shading": 0.1})
    assert run_capture(cfg, tmp_path / "uniform.zarr", simulate=True).status == "complete"
    assert main(["calibrate-shading", str(tmp_path / "uniform.zarr"), "--out", str(tmp_path / "flat.npy")]) == 0
    true = TimeBase(shading=0.1).sensitivity(256)
    ratio = np.load(tmp_path / "flat.npy") / true[None, :]
    assert np.abs(true / true.mean() - 1.0).max() > 0.09                 # what the shading does uncorrected
    assert np.abs(ratio / ratio.mean() - 1.0).max() < 0.005
