"""``streaklab report``: PNGs and a summary from a small result store."""
import shutil

import numpy as np
import pytest

from core import model
from decomposition.pipeline import decompose_to_store
from decomposition.resultstore import create_result_store, open_result_store
from reconstruction.cubestore import write_cube
from streaklab.cli import main
from streaklab.report import choose_pixels, choose_time_ps, measured_profiles

TB = 2.0
PNG = b"\x89PNG\r\n\x1a\n"


def _cube(ny=4, nx=6, nt=128):
    p = model.empty_params((ny, nx), 1)
    yy, xx = np.mgrid[0:ny, 0:nx]
    p["direct_delay_ps"] = 40.0 + 2.0 * xx + 1.0 * yy
    p["direct_amplitude"] = 1.0 + 0.1 * xx
    p["direct_amplitude"][2, 4] = 5.0  # the brightest direct reflection
    p["direct_sigma_ps"] = np.full((ny, nx), 3.0)
    p["sss_delay_ps"] = np.where(xx < 3, p["direct_delay_ps"], np.nan)
    p["sss_amplitude"] = np.where(xx < 3, 0.04, np.nan)
    p["sss_alpha_per_ps"] = np.where(xx < 3, 0.03, np.nan)
    p["sss_sigma_ps"] = np.where(xx < 3, 3.0, np.nan)
    return model.render_profile(p, nt, TB).astype(np.float32)


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    write_cube(tmp / "cube.zarr", _cube(), time_bin_ps=TB, chunks=(2, 3), units="photons")
    decompose_to_store(tmp / "cube.zarr", tmp / "res.zarr", progress=False)
    return tmp


def _is_png(path):
    return path.exists() and path.stat().st_size > 2000 and path.read_bytes()[:8] == PNG


def test_report_writes_pngs_and_a_summary(result, capsys):
    figs = result / "figs"
    assert main(["report", str(result / "res.zarr"), "--out", str(figs)]) == 0
    out = capsys.readouterr().out
    for name in ("frames.png", "maps.png", "profiles.png"):
        assert _is_png(figs / name), name
        assert f"wrote {figs / name}" in out
    summary = (figs / "summary.txt").read_text()
    assert summary in out
    assert "pixels: 24; done 24 (100.0%); decomposed 24" in summary
    assert "method: convscd" in summary and "cube: 4 x 6 pixels x 128 bins of 2 ps" in summary
    import matplotlib.image as mpimg

    assert mpimg.imread(figs / "maps.png").shape[0] > 400  # a readable size, not a thumbnail


def test_automatic_choices_follow_the_data(result):
    store = open_result_store(result / "res.zarr")
    delay = store.group["direct_delay_ps"][...]
    t = store.time_axis_ps()
    expected = t[np.argmin(np.abs(t - np.nanmedian(delay)))]
    assert choose_time_ps(store) == expected
    picks = choose_pixels(store, n=3)
    assert picks[0] == (2, 4) and len(set(picks)) == 3


def test_chosen_pixels_and_time_and_a_moved_source(result, capsys):
    store = open_result_store(result / "res.zarr")
    measured = measured_profiles(store, slice(0, 2), slice(0, 3))
    np.testing.assert_array_equal(measured, _cube()[0:2, 0:3])
    moved = result / "moved.zarr"
    shutil.move(result / "cube.zarr", moved)
    try:  # source gone: the profile is rebuilt from components + residual
        np.testing.assert_allclose(measured_profiles(store, slice(0, 2), slice(0, 3)), _cube()[0:2, 0:3],
                                   atol=1e-5)
        np.testing.assert_allclose(measured_profiles(store, slice(None), slice(None), 20), _cube()[:, :, 20],
                                   atol=1e-5)
        figs = result / "figs2"
        assert main(["report", str(result / "res.zarr"), "--out", str(figs), "--time-ps", "50",
                     "--pixels", "0,0", "3,5"]) == 0
        assert "frames at t = 50.0 ps; profiles of pixels [(0, 0), (3, 5)]" in (figs / "summary.txt").read_text()
        assert _is_png(figs / "profiles.png")
    finally:
        shutil.move(moved, result / "cube.zarr")
    capsys.readouterr()


def test_store_without_components_is_rendered_from_parameters(result, capsys):
    decompose_to_store(result / "cube.zarr", result / "nocomp.zarr", write_components=False, progress=False)
    assert main(["report", str(result / "nocomp.zarr"), "--out", str(result / "figs3")]) == 0
    assert all(_is_png(result / "figs3" / n) for n in ("frames.png", "maps.png", "profiles.png"))
    capsys.readouterr()


def test_bad_requests_are_named(result, tmp_path, capsys):
    assert main(["report", str(result / "res.zarr"), "--out", str(tmp_path / "f"), "--pixels", "9,9"]) == 2
    assert "outside the 4 x 6 image" in capsys.readouterr().err
    assert main(["report", str(result / "res.zarr"), "--out", str(tmp_path / "f"), "--time-ps", "1e6"]) == 2
    assert "outside the cube" in capsys.readouterr().err
    assert main(["report", str(result / "cube.zarr"), "--out", str(tmp_path / "f")]) == 2
    assert "not a decomposition result store" in capsys.readouterr().err
    create_result_store(tmp_path / "empty.zarr", shape=(2, 2, 8), chunks=(1, 1), n_ir=1, time_bin_ps=2.0, t0_ps=2.0)
    assert main(["report", str(tmp_path / "empty.zarr"), "--out", str(tmp_path / "f")]) == 2
    assert "no finished chunk" in capsys.readouterr().err


def test_measured_frame_reads_one_bin(result):
    store = open_result_store(result / "res.zarr")
    np.testing.assert_array_equal(measured_profiles(store, slice(None), slice(None), 20), _cube()[:, :, 20])
