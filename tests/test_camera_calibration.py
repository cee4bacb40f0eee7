"""The camera's own time calibration (its scaling table) from capture to the cube, and time-range strings."""
import numpy as np
import pytest

from acquisition.config import ConfigError, parse_config
from acquisition.rig import run_capture, simulated_scene
from acquisition.runstore import open_run
from acquisition.session import CaptureError
from reconstruction.build import ReconstructionError, reconstruct
from streaklab.cli import main

pytestmark = pytest.mark.timeout(60)


def config(time_range=2, poly="scene", **calibration):
    raw = {"scan": {"start_deg": -6.0, "stop_deg": 6.0, "count": 2},
           "camera": {"frames_per_line": 1, "time_range": time_range, "gain": 30, "acquire_timeout_s": 3.0},
           "dark": {"frames": 1}, "devices": {"timeout_s": 2.0},
           "session": {"retries": 1, "retry_backoff_s": 0.0},
           "simulation": {"seed": 1, "n_x": 8, "n_t": 64},
           "calibration": {"time_poly_ps": [0.0, 1.0], **calibration}}
    cfg = parse_config(raw)
    scene = simulated_scene(cfg)
    if poly == "scene":                     # the simulated sweep at this time range, as a polynomial
        scale = scene.row_times_ps(0.0, time_range)[-1] / scene.row_times_ps(0.0)[-1]
        raw["calibration"]["time_poly_ps"] = [float(c) * scale for c in scene.time_calibration]
    elif poly is None:
        del raw["calibration"]["time_poly_ps"]
    else:
        raw["calibration"]["time_poly_ps"] = poly
    return parse_config(raw), scene


def test_capture_records_the_scaling_table_and_reconstruction_uses_it(tmp_path):
    cfg, scene = config(time_range=3)
    run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    run = open_run(tmp_path / "run.zarr")
    np.testing.assert_allclose(run.camera_row_times_ps(), scene.row_times_ps(0.0, 3), rtol=1e-6)
    assert run["camera_row_times_ps"].attrs["time_range"] == "3"
    np.testing.assert_allclose(run["time_ps"][...], scene.row_times_ps(0.0, 3), rtol=1e-6)   # the table's times
    prov = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr").attrs["provenance"]
    assert prov["time_calibration_source"] == "camera scaling table"
    assert prov["camera_and_config_agree"] is True and prov["camera_vs_config_max_diff_ps"] < 1e-3
    np.testing.assert_allclose(prov["time_calibration_row_times_ps"], scene.row_times_ps(0.0, 3), rtol=1e-6)
    prov = reconstruct(tmp_path / "run.zarr", tmp_path / "cube2.zarr", time_source="config").attrs["provenance"]
    assert prov["time_calibration_source"] == "config polynomial" and prov["time_calibration_requested"] == "config"


def test_a_wrong_configured_polynomial_is_caught_by_the_camera_table(tmp_path, capsys):
    cfg, scene = config(poly=[2.0, 2.0])                # linear, but the simulated sweep slows down
    run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    np.testing.assert_allclose(open_run(tmp_path / "run.zarr")["time_ps"][...], scene.row_times_ps(), rtol=1e-6)
    cube = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr")
    prov = cube.attrs["provenance"]
    expected = float(np.max(np.abs(scene.row_times_ps() - (2.0 + 2.0 * np.arange(64)))))
    assert prov["time_calibration_source"] == "camera scaling table"
    assert prov["camera_and_config_agree"] is False
    assert prov["camera_vs_config_max_diff_ps"] == pytest.approx(expected, rel=1e-5)
    # The cube's time axis follows the camera's sweep: the last bin lies inside its window.
    assert cube.time_axis_ps()[-1] <= scene.row_times_ps()[-1] + 1e-6
    assert main(["reconstruct", str(tmp_path / "run.zarr"), "--out", str(tmp_path / "c2.zarr"),
                 "--time-source", "config"]) == 0
    err = capsys.readouterr().err
    assert "row times from the config polynomial" in err and "differ by up to" in err


def test_camera_time_source_needs_no_polynomial_but_a_table(tmp_path):
    cfg, scene = config(poly=None, time_source="camera")
    run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    prov = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr").attrs["provenance"]
    assert prov["time_calibration_source"] == "camera scaling table"
    assert prov["time_calibration_poly_ps"] is None and prov["camera_vs_config_max_diff_ps"] is None
    with pytest.raises(ReconstructionError, match="no calibration.time_poly_ps"):
        reconstruct(tmp_path / "run.zarr", tmp_path / "c2.zarr", time_source="config")
    with pytest.raises(ConfigError, match="time_poly_ps: is required"):
        config(poly=None)
    with pytest.raises(ConfigError, match="time_source: must be one of"):
        config(time_source="guess")


def test_camera_time_source_without_a_table_stops_the_capture(tmp_path, monkeypatch):
    from drivers.remoteex import RemoteExCamera

    monkeypatch.setattr(RemoteExCamera, "scaling_table_ps", lambda self, **kw: None)
    cfg, _ = config(time_source="camera")
    with pytest.raises(CaptureError, match="offers no scaling table"):
        run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    cfg, _ = config()                                    # auto: the polynomial, and the run says so
    run_capture(cfg, tmp_path / "r2.zarr", simulate=True)
    assert open_run(tmp_path / "r2.zarr").camera_row_times_ps() is None
    prov = reconstruct(tmp_path / "r2.zarr", tmp_path / "cube.zarr").attrs["provenance"]
    assert prov["time_calibration_source"] == "config polynomial" and prov["camera_scaling_table"] is False
    with pytest.raises(ReconstructionError, match="offered no scaling table"):
        reconstruct(tmp_path / "r2.zarr", tmp_path / "c2.zarr", time_source="camera")


def test_single_sweep_time_range_strings_from_config_to_cube(tmp_path):
    cfg, scene = config(time_range="1ns")
    assert cfg["camera"]["time_range"] == "1 ns"
    run_capture(cfg, tmp_path / "run.zarr", simulate=True)
    run = open_run(tmp_path / "run.zarr")
    np.testing.assert_allclose(run.camera_row_times_ps(), scene.row_times_ps(0.0, "1 ns"), rtol=1e-6)
    prov = reconstruct(tmp_path / "run.zarr", tmp_path / "cube.zarr").attrs["provenance"]
    assert prov["time_range"] == "1 ns" and prov["camera_and_config_agree"] is True
    for bad in ("fast", 2.5, True, "-1 ns"):
        with pytest.raises(ConfigError, match="camera.time_range"):
            config(time_range=bad)


def test_a_scan_puts_a_streak_unit_left_in_focus_mode_back_to_operate(tmp_path):
    from acquisition.rig import start_simulated_lab

    cfg, scene = config()
    lab = start_simulated_lab(cfg)
    try:
        lab.camera._streak["mode"].set("Focus")        # as a killed 'streaklab live --focus' leaves it
        run_capture(cfg, tmp_path / "run.zarr", lab=lab)
        assert lab.camera.focus is False
        assert "DevParamSet(Streak,Mode,Operate)" in list(lab.camera.received)
    finally:
        lab.close()
    run = open_run(tmp_path / "run.zarr")
    assert run.camera_row_times_ps() is not None         # a sweep, with its scaling table
    line0 = run["streaks"][0, 0].astype(float)
    angle = float(run["angle_deg"][0])
    assert np.abs(line0 - scene.expected_counts(scene.line_index(angle), exposure_s=0.01, gain=30)).mean() < 6.0
