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

    from streaklab.report import EMPTY_PANEL_FRACTION, frames_figure

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
    assert vmin == 0 and vmax >= EMPTY_PANEL_FRACTION * scale > 1e6 * 7e-19  # the noise at the bottom of the map
    assert np.nanmax(ir.norm(ir.get_array())) < 1e-6  # every cell drawn in the colour of zero (1/256 a step)
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


def test_summary_explains_each_flag_that_occurs(result, tmp_path):
    """After the counts, one line per flag present: what it means and what to do; none for the rest."""
    import zarr

    from decomposition.flags import AMBIGUOUS, FLAG_HELP, Flag, OFF_WINDOW
    from decomposition.store.resultstore import OUT_OF_RANGE
    from streaklab.report import flag_help, summary_text

    assert set(flag_help()) == {f.name for f in Flag} | {"OUT_OF_RANGE"} and set(FLAG_HELP) == set(Flag)
    assert all(len(text) > 40 and "\n" not in text for text in flag_help().values())
    shutil.copytree(result / "res.zarr", tmp_path / "res.zarr")
    flags = zarr.open_group(str(tmp_path / "res.zarr"), mode="r+")["flags"]
    marked = np.zeros(flags.shape, np.uint16)
    marked[0, :3] = int(AMBIGUOUS)
    marked[1, 0] = int(AMBIGUOUS) | int(OFF_WINDOW)
    marked[3, 5] = OUT_OF_RANGE
    flags[...] = marked
    text = summary_text(open_result_store(tmp_path / "res.zarr")).splitlines()
    at = next(i for i, line in enumerate(text) if line.startswith("flagged pixels: "))
    assert text[at] == "flagged pixels: 5 (OUT_OF_RANGE 1, AMBIGUOUS 4, OFF_WINDOW 1)"   # bit order
    assert text[at + 1:] == [f"  OUT_OF_RANGE: {flag_help()['OUT_OF_RANGE']}",
                             f"  AMBIGUOUS: {FLAG_HELP[Flag.AMBIGUOUS]}",
                             f"  OFF_WINDOW: {FLAG_HELP[Flag.OFF_WINDOW]}"]
    assert "uncertain" in text[at + 2] and "trigger_delay_ps" in text[at + 3]


def _constructed(tmp_path, ny=12, nx=12, nt=64, name="built.zarr"):
    """A finished result store written directly (no decomposition): a direct reflection in every
    pixel at bin 20, nothing else; the measured frames are rebuilt from components + residual."""
    store = create_result_store(tmp_path / name, shape=(ny, nx, nt), chunks=(ny, nx), n_ir=1, time_bin_ps=TB,
                                t0_ps=TB)
    g = store.group
    t = TB + TB * np.arange(nt)
    g["direct_delay_ps"][...] = np.full((ny, nx), t[20])
    g["direct_amplitude"][...] = np.full((ny, nx), 1000.0)
    g["direct"][...] = (1000.0 * np.exp(-0.5 * ((t - t[20]) / 3.0) ** 2) * np.ones((ny, nx, 1))).astype(np.float32)
    for k in ("sss", "residual"):
        g[k][...] = np.zeros((ny, nx, nt), np.float32)
    g["ir"][...] = np.zeros((ny, nx, 1, nt), np.float32)
    g["rms_residual"][...] = np.ones((ny, nx))
    g["valid"][...] = np.ones((ny, nx), bool)
    g["done"][...] = np.ones((ny, nx), bool)
    return open_result_store(tmp_path / name)


def test_an_inter_reflection_in_one_pixel_alone_is_shown_not_called_none(tmp_path):
    """One pixel of 144 holds an inter-reflection (a fifth of the direct's height): its panel is
    titled without "none" and its colour range reaches that pixel's value."""
    import zarr

    from streaklab.report import frames_figure

    store = _constructed(tmp_path)
    g = zarr.open_group(str(store.path), mode="r+")
    ir = g["ir"][...]
    ir[2, 7, 0, 20] = 200.0
    g["ir"][...] = ir
    fig = frames_figure(open_result_store(store.path), float(store.time_axis_ps()[20]))
    ax, mesh = _panel(fig, "inter-reflections")
    assert "none" not in ax.get_title()
    vmin, vmax = mesh.get_clim()
    assert vmin == 0 and vmax == pytest.approx(200.0)
    assert mesh.norm(200.0) == pytest.approx(1.0)      # drawn at the top of the colour map
    for name in ("subsurface scattering", "residual"):  # exactly zero: none
        assert "(none at this time)" in _panel(fig, name)[0].get_title()


def test_coordinates_print_alike_along_an_axis(result, tmp_path):
    """Mirror angles 4/3 deg apart print with one decimal each ("-0.7 deg" beside "6.0 deg"), whole
    pixels with none; never "-0.0"."""
    import zarr

    from streaklab.report import coordinate_text, profiles_figure

    path = _copy(result, tmp_path)
    g = zarr.open_group(str(path), mode="r+")
    angles = np.linspace(-10.0, 10.0, 16)
    assert coordinate_text(angles, 7, "deg") == "-0.7 deg" and coordinate_text(angles, 12, "deg") == "6.0 deg"
    assert coordinate_text(angles, 2, "deg") == "-7.3 deg"
    assert coordinate_text(np.array([-0.01, 1.0, 2.0]), 0, "deg") == "0 deg"
    assert coordinate_text(np.arange(64.0), 29, "pixel") == "29"
    g["y"][...] = [-0.6667, 0.6667, 6.0, 7.3333]
    g["y"].attrs["units"] = "deg"
    fig = profiles_figure(open_result_store(path), [(0, 1), (2, 4)])
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert titles[0].startswith("y = -0.7 deg, x = 1 (") and titles[1].startswith("y = 6.0 deg, x = 4 (")


def test_profiles_zoom_to_the_signal(tmp_path):
    """A direct reflection (sigma 3 ps) at 42 ps in a 128-ps window: the time axis spans it with a
    margin, not the whole window."""
    from streaklab.report import profiles_figure

    store = _constructed(tmp_path)
    t = store.time_axis_ps()
    fig = profiles_figure(store, [(0, 0), (5, 5)])
    lo, hi = fig.axes[0].get_xlim()
    assert lo <= t[20] - 4 * 3.0 and hi >= t[20] + 4 * 3.0        # the whole peak, with a margin
    assert lo >= t[0] - TB and hi < t[20] + 0.5 * (t[-1] - t[20])  # not the empty rest of the window


def _with_truth(tmp_path):
    """A simulated cube with its truth, and a result store 'decomposed' from it holding the truth's
    own parameters and components (written directly)."""
    from decomposition.evaluation.synthetic import make_cube
    from streaklab.commands.simulate import write_simulation

    data = make_cube(3, 4, 96, seed=1)
    write_simulation(tmp_path / "sim.zarr", data)
    store = create_result_store(tmp_path / "fromsim.zarr", shape=(3, 4, 96), chunks=(3, 4), n_ir=2, time_bin_ps=TB,
                                t0_ps=data.t0_ps, attrs={"source": {"path": str(tmp_path / "sim.zarr"),
                                                                    "kind": "cube", "shape": [3, 4, 96]}})
    g = store.group
    for k in ("direct_delay_ps", "sss_alpha_per_ps", "sss_amplitude", "direct_amplitude"):
        g[k][...] = 0.9 * np.asarray(data.params[k])   # an estimate 10 % off the truth
    g["direct"][...] = 0.9 * data.components["direct"]
    g["sss"][...] = 0.9 * data.components["sss"]
    g["ir"][...] = 0.9 * data.components["interreflections"]
    g["residual"][...] = np.zeros((3, 4, 96), np.float32)
    g["rms_residual"][...] = np.ones((3, 4))
    g["valid"][...] = np.ones((3, 4), bool)
    g["done"][...] = np.ones((3, 4), bool)
    return open_result_store(store.path), data


def test_a_synthetic_cubes_truth_is_shown_beside_the_estimate(tmp_path):
    from streaklab.report import maps_figure, profiles_figure

    store, data = _with_truth(tmp_path)
    fig = maps_figure(store)
    ax, mesh = _panel(fig, "true direct delay")
    np.testing.assert_allclose(mesh.get_array().reshape(3, 4), data.params["direct_delay_ps"])
    _, est = _panel(fig, "estimated direct delay")
    assert est.get_clim() == mesh.get_clim()                          # one colour scale for both
    _, err = _panel(fig, "direct delay error")
    np.testing.assert_allclose(err.get_array().reshape(3, 4), -0.1 * data.params["direct_delay_ps"])
    for name in ("true subsurface attenuation alpha", "true subsurface amplitude b"):
        _panel(fig, name)
    fig = profiles_figure(store, [(1, 2)])
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    np.testing.assert_allclose(lines["true direct"].get_ydata(), data.components["direct"][1, 2].astype(np.float32))
    # without its truth (the source moved) the maps are the plain four
    shutil.move(tmp_path / "sim.zarr", tmp_path / "gone.zarr")
    store = open_result_store(store.path)
    titles = [a.get_title() for a in maps_figure(store).axes if a.get_title()]
    assert len(titles) == 4 and not any("true" in t for t in titles)
    assert not any(ln.get_label().startswith("true") for ln in profiles_figure(store, [(1, 2)]).axes[0].get_lines())


def test_the_summary_of_a_store_whose_spatial_options_hold_one_no_longer_known(result, tmp_path):
    """A store written by an older version records its spatial options as they were then; its
    summary still says the coupling and the halo (the options it names that this version has)."""
    import dataclasses

    import zarr

    from decomposition.image import halo_pixels
    from decomposition.image.spatial import SpatialOptions
    from streaklab.report import summary_text

    shutil.copytree(result / "res.zarr", tmp_path / "res.zarr")
    group = zarr.open_group(str(tmp_path / "res.zarr"), mode="r+")
    job = dict(group.attrs["job"])
    job["spatial"] = dataclasses.asdict(SpatialOptions(sweeps=2)) | {"stray_share": 0.1}
    group.attrs["job"] = job
    text = summary_text(open_result_store(tmp_path / "res.zarr"))
    assert "2 sweeps" in text and f"a halo of {halo_pixels(SpatialOptions(sweeps=2))} pixels" in text
