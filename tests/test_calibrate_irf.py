"""The calibration target of the simulated lab and ``streaklab calibrate-irf``, end to end."""
import numpy as np
import pytest
from scipy.optimize import least_squares

from acquisition.config import ConfigError, load_config, parse_config
from acquisition.rig import simulated_scene
from core.irf import render_shifted, render_sss
from core.irf_models import gaussian_response
from core.irfstore import load_response
from drivers.sim.scene import VirtualScene, simulated_response
from reconstruction.cubestore import open_cube, read_cube_response
from reconstruction.irf import fit_response
from streaklab.cli import main

CONFIG = """
[scan]
start_deg = -3.0
stop_deg = 3.0
count = 4
[camera]
frames_per_line = 2
time_range = 2
gain = 30
[dark]
frames = 2
[calibration]
time_poly_ps = [2.0, 1.8, 0.0015625]
time_bin_ps = 2.0
[simulation]
seed = 1
n_x = 32
n_t = 256
scene = "calibration"
response = "tailed"
"""


def test_simulated_camera_renders_its_response_and_the_calibration_target():
    irf = simulated_response("tailed")
    scene = VirtualScene.calibration(n_lines=3, n_x=8, n_t=64, seed=2, response=irf)
    p = scene.params
    assert np.all(np.isnan(p["sss_delay_ps"])) and p["ir_delay_ps"].shape[-1] == 0
    times = scene.row_times_ps()
    window = times[-1]
    assert np.all((p["direct_delay_ps"] > 0.25 * window) & (p["direct_delay_ps"] < 0.34 * window))
    line = scene.clean_line(1)
    ref = 0.8 * render_shifted(irf, times, p["direct_delay_ps"][1])
    np.testing.assert_allclose(line, ref, rtol=1e-12)
    # Every family of the default scene takes the response: direct, inter-reflections, sss.
    base = VirtualScene.default(n_lines=4, n_x=16, n_t=64, seed=0)
    tailed = VirtualScene(params=base.params, angle_deg=base.angle_deg, n_t=base.n_t,
                          time_calibration=base.time_calibration, response=irf)
    q = tailed.line_params(2)
    t = tailed.row_times_ps()
    ok = np.isfinite(q["sss_delay_ps"])
    assert ok.any()
    expect = np.zeros((16, t.size))
    expect += np.nan_to_num(q["direct_amplitude"])[:, None] * render_shifted(irf, t, np.nan_to_num(q["direct_delay_ps"]))
    expect[ok] += q["sss_amplitude"][ok, None] * render_sss(irf, t, q["sss_delay_ps"][ok], q["sss_alpha_per_ps"][ok])
    for r in range(2):
        on = np.isfinite(q["ir_delay_ps"][:, r])
        expect[on] += q["ir_amplitude"][on, r, None] * render_shifted(irf, t, q["ir_delay_ps"][on, r])
    np.testing.assert_allclose(tailed.clean_line(2), expect, rtol=1e-10, atol=1e-14)
    # A Gaussian response of the scene's own sigma renders exactly the Gaussian scene: amplitudes
    # stay peak heights, the sss atom is the closed-form kernel.
    as_response = VirtualScene(params=base.params, angle_deg=base.angle_deg, n_t=base.n_t,
                               time_calibration=base.time_calibration, response=gaussian_response(6.0, time_step_ps=2.0))
    np.testing.assert_allclose(as_response.clean_line(2), base.clean_line(2), rtol=0, atol=1e-8)
    assert simulated_response("gaussian") is None
    with pytest.raises(ValueError, match="unknown simulated response"):
        simulated_response("lorentzian")


def test_config_names_scene_and_response_and_keeps_old_hashes(tmp_path):
    raw = {"scan": {"angles_deg": [0.0, 1.0]}, "calibration": {"time_poly_ps": [0.0, 2.0]}}
    plain = parse_config(raw)
    assert "scene" not in plain["simulation"] and "response" not in plain["simulation"]
    assert simulated_scene(plain).response is None
    for key, bad in (("scene", "mirror"), ("response", "lorentzian")):
        with pytest.raises(ConfigError, match=f"simulation.{key}: must be one of"):
            parse_config({**raw, "simulation": {key: bad}})
    (tmp_path / "cal.toml").write_text(CONFIG)
    cfg = load_config(tmp_path / "cal.toml")
    scene = simulated_scene(cfg)
    assert scene.response.model["name"] == "tailed" and scene.n_lines == 4 and cfg.hash != plain.hash


@pytest.mark.timeout(90)
def test_calibrate_irf_recovers_the_simulated_response_end_to_end(tmp_path, capsys):
    (tmp_path / "cal.toml").write_text(CONFIG)
    run, cube = str(tmp_path / "run.zarr"), str(tmp_path / "cube.zarr")
    assert main(["capture", "--config", str(tmp_path / "cal.toml"), "--out", run, "--simulate"]) == 0
    assert main(["reconstruct", run, "--out", cube]) == 0
    assert main(["calibrate-irf", cube]) == 0
    assert "wrote the instrument response to" in capsys.readouterr().err
    est = read_cube_response(cube)
    truth = simulated_response("tailed")
    t = est.time_axis_ps()
    tr = render_shifted(truth, t, 0.0)
    err = np.sqrt(np.mean((est.samples / est.peak_per_ps - tr) ** 2))
    # The best Gaussian is 1.3 % of the peak (RMS) away from this response; the estimate from
    # 128 pixels at SNR ~250, through the reconstruction's linear resampling, 0.14 %.
    fit = least_squares(lambda p: p[0] * np.exp(-0.5 * ((t - p[1]) / p[2]) ** 2) - tr, [1.0, 0.0, 6.0])
    gauss_err = np.sqrt(np.mean(fit.fun ** 2))
    assert gauss_err > 0.01
    assert err < 0.004 and err < 0.3 * gauss_err
    assert abs(est.fwhm_ps() - truth.fwhm_ps()) < 0.5
    prov = est.provenance
    assert prov["pixels_used"] == 128 and prov["store"].endswith("cube.zarr") and prov["software_version"]
    # Over the span above 1 % of the peak the best Gaussian misses this response by 2-3 % RMS.
    assert 0.02 < prov["gaussian_fit"]["rms_misfit"] < 0.035
    # The per-pixel delays are the mirror's known delay map (both refer to the response's peak).
    scene = simulated_scene(load_config(tmp_path / "cal.toml"))
    delays = fit_response(open_cube(cube)).delay_ps
    diff = delays - scene.params["direct_delay_ps"]
    assert np.std(diff) < 0.1 and abs(np.mean(diff)) < 0.3

    # From the run store (reconstructed on the way) into a separate .npz: the same response.
    assert main(["calibrate-irf", run]) == 2
    assert "give --out" in capsys.readouterr().err
    assert main(["calibrate-irf", run, "--out", str(tmp_path / "irf.npz")]) == 0
    np.testing.assert_array_equal(load_response(tmp_path / "irf.npz").samples, est.samples)
    assert load_response(tmp_path / "irf.npz").provenance["run_store"].endswith("run.zarr")
    # Never over the capture itself, nor over a store of another kind.
    assert main(["calibrate-irf", cube, "--out", run, "--overwrite"]) == 2
    assert "refusing to replace" in capsys.readouterr().err
    assert main(["calibrate-irf", cube, "--out", cube + "/cube"]) == 2
    assert "input" in capsys.readouterr().err
    # A stored response is kept unless --overwrite.
    assert main(["calibrate-irf", cube]) == 2
    assert "already holds an instrument response" in capsys.readouterr().err
    assert main(["calibrate-irf", cube, "--overwrite", "--post-ps", "300"]) == 0
    assert read_cube_response(cube).provenance["post_peak_ps"] == 300.0
    # The response travels with the cube through NeXus/HDF5.
    h5, back = str(tmp_path / "cube.h5"), str(tmp_path / "back.zarr")
    assert main(["export", cube, "--out", h5]) == 0 and main(["import", h5, "--out", back]) == 0
    np.testing.assert_array_equal(read_cube_response(back).samples, read_cube_response(cube).samples)


def test_simulated_lab_takes_a_response_by_name():
    from drivers.sim.lab import SimulatedLab

    lab = SimulatedLab(seed=0, response="afterpulse", mirror=False, sync=False)
    assert lab.scene.response.model["name"] == "afterpulse"
    assert SimulatedLab(seed=0, mirror=False, sync=False).scene.response is None
    with pytest.raises(ValueError, match="not both"):
        SimulatedLab(seed=0, scene=lab.scene, response="tailed", mirror=False, sync=False)
    with pytest.raises(ValueError, match="unknown simulated response"):
        SimulatedLab(seed=0, response="lorentzian", mirror=False, sync=False)
