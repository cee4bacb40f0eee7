"""``streaklab report``: PNGs and a summary from a small result store."""
import shutil

import numpy as np
import pytest

from core import model
from decomposition.store.pipeline import decompose_to_store
from decomposition.store.resultstore import create_result_store, open_result_store
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


def _copy(result, tmp_path, name="copy.zarr"):
    dst = tmp_path / name
    shutil.copytree(result / "res.zarr", dst)
    return dst


def _panel(fig, title_start):
    (ax,) = [a for a in fig.axes if a.get_title().startswith(title_start)]
    (mesh,) = ax.collections
    return ax, mesh


def test_an_all_but_empty_frame_panel_shows_flat_not_its_rounding_noise(result, tmp_path):
    import zarr

    from streaklab.report import frames_figure

    path = _copy(result, tmp_path)
    g = zarr.open_group(str(path), mode="r+")
    rng = np.random.default_rng(0)
    g["ir"][...] = (7e-19 * rng.random(g["ir"].shape)).astype(np.float32)  # numerical noise, no signal
    store = open_result_store(path)
    t_ps = choose_time_ps(store)
    fig = frames_figure(store, t_ps)
    _, measured = _panel(fig, "measured")
    ax, ir = _panel(fig, "inter-reflections")
    scale = np.nanpercentile(np.abs(measured.get_array().filled(np.nan)), 99)
    vmin, vmax = ir.get_clim()
    assert vmin == 0 and vmax >= 1e-3 * scale > 1e-6  # the noise sits at the bottom of the colour map
    assert np.nanmax(ir.norm(ir.get_array())) < 1e-12  # every cell drawn in the colour of zero
    assert "none at this time" in ax.get_title()
    # a panel with signal keeps its own robust limits
    ax, direct = _panel(fig, "direct")
    lo, hi = np.nanpercentile(direct.get_array().filled(np.nan), [1, 99])
    assert direct.get_clim() == pytest.approx((lo, hi)) and "none" not in ax.get_title()


def test_maps_are_oriented_as_xarray_plots_them(result, tmp_path):
    """y upwards and x to the right, cells centred on the coordinates: increasing and decreasing y."""
    import matplotlib.pyplot as plt
    import xarray as xr
    import zarr

    from streaklab.report import maps_figure

    for y in (None, np.array([10.0, 5.0, 0.0, -7.5])):  # line index; mirror angles scanned downwards
        path = _copy(result, tmp_path, f"y{y is None}.zarr")
        if y is not None:
            g = zarr.open_group(str(path), mode="r+")
            g["y"][...] = y
            g["y"].attrs["units"] = "deg"
        store = open_result_store(path)
        fig = maps_figure(store)
        ax, mesh = _panel(fig, "direct delay")
        delay = np.asarray(store.group["direct_delay_ps"][...])
        da = xr.DataArray(delay, dims=("y", "x"), coords={"y": store.group["y"][...], "x": store.group["x"][...]})
        ref_fig, ref_ax = plt.subplots()
        ref = da.plot(ax=ref_ax, add_colorbar=False)
        np.testing.assert_allclose(mesh.get_coordinates(), ref.get_coordinates())
        np.testing.assert_array_equal(mesh.get_array(), ref.get_array())
        assert ax.get_ylim() == pytest.approx(ref_ax.get_ylim()) and ax.get_ylim()[0] < ax.get_ylim()[1]
        assert ax.get_xlim() == pytest.approx(ref_ax.get_xlim()) and ax.get_xlim()[0] < ax.get_xlim()[1]
        assert ax.get_ylabel() == ("y (deg)" if y is not None else "y (pixel)")
        plt.close(fig)
        plt.close(ref_fig)


def test_profile_titles_give_the_maps_coordinates_and_flag_names(result, tmp_path):
    import zarr

    from decomposition import FLAG_NAMES
    from streaklab.report import profiles_figure

    path = _copy(result, tmp_path)
    g = zarr.open_group(str(path), mode="r+")
    g["y"][...] = [-9.0, -3.0, 3.0, 9.0]
    g["y"].attrs["units"] = "deg"
    by_name = {name: bit for bit, name in FLAG_NAMES.items()}
    flags = g["flags"][...]
    flags[2, 4] = by_name["POOR_FIT"] | by_name["SPIKE"]
    flags[0, 1] = 0
    g["flags"][...] = flags
    fig = profiles_figure(open_result_store(path), [(2, 4), (0, 1)])
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[0] == "y = 3 deg, x = 4 (--pixels 2,4); flags: POOR_FIT, SPIKE"
    assert titles[1] == "y = -9 deg, x = 1 (--pixels 0,1); flags: none"


def test_flag_text_names_solver_and_store_bits():
    """The solver's bits and the store's own OUT_OF_RANGE by name; unknown bits in hex."""
    from decomposition.flags import POOR_FIT, SPIKE
    from decomposition.store.resultstore import OUT_OF_RANGE
    from streaklab.report import flag_text

    assert flag_text(0) == "none"
    assert flag_text(int(POOR_FIT) | int(SPIKE)) == "POOR_FIT, SPIKE"
    assert flag_text(int(POOR_FIT) | OUT_OF_RANGE) == "POOR_FIT, OUT_OF_RANGE"
    assert flag_text(1 << 15) == "bits 0x8000"
