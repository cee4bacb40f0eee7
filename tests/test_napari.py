"""The napari plugin (streaklab/napari): manifest, reader, maps, live refresh, pixel inspector.

Headless: layers go into napari's ``ViewerModel``; the one Qt widget test runs on Qt's offscreen
platform.  The stores are a small ``streaklab demo`` (run, cube and result), made once per module.
"""
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np
import pytest
import zarr

from decomposition.store.resultstore import ResultStoreError, create_result_store, open_result_store
from reconstruction.cubestore import open_cube, write_cube
from streaklab.cli import main
from streaklab.napari._reader import get_reader, read_stores
from streaklab.napari._viewer import add_maps, add_store, pixel_at, refresh_layers
from streaklab.napari.layers import map_layer, map_names, pixel_view, store_kind
from streaklab.report import flag_names
from test_layers import EXTRAS

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "streaklab" / "napari" / "napari.yaml"
#: what only the napari extra installs (tests/test_layers.py: no module outside streaklab/napari imports them)
PLUGIN_ONLY = tuple(sorted(EXTRAS[("streaklab", "napari")]))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("napari") / "demo"
    assert main(["demo", "--out", str(out), "--lines", "3", "--nx", "4", "--nt", "128", "--quiet"]) == 0
    return out


def _viewer():
    from napari.components import ViewerModel

    return ViewerModel()


def _layer(viewer, suffix):
    (layer,) = [ly for ly in viewer.layers if ly.name.endswith(f": {suffix}")]
    return layer


def test_the_manifest_passes_npe2_validate_with_its_imports():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-m", "npe2", "validate", "--imports", str(MANIFEST)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "valid!" in out.stdout
    from npe2 import PluginManifest

    pm = PluginManifest.from_file(MANIFEST)
    (reader,) = pm.contributions.readers
    assert reader.accepts_directories and reader.filename_patterns == ["*.zarr"]
    assert {w.display_name for w in pm.contributions.widgets} == {"Pixel inspector", "Result maps", "Phasor plot"}


def test_the_reader_declines_everything_but_streaklab_run_cube_and_result_stores(tmp_path, demo):
    zarr.open_group(tmp_path / "other.zarr", mode="w").attrs["origin"] = "someone else's"
    irf = zarr.open_group(tmp_path / "irf.zarr", mode="w")
    irf.attrs["streaklab_kind"] = "instrument_response"
    (tmp_path / "plain.zarr").mkdir()
    for path in ("other.zarr", "irf.zarr", "plain.zarr", "missing.zarr"):
        assert get_reader(str(tmp_path / path)) is None, path
    assert get_reader(str(demo)) is None                      # the demo folder itself is no store
    assert [store_kind(demo / f"{k}.zarr") for k in ("run", "cube", "result")] == ["run", "cube", "decomposition"]
    assert get_reader(str(demo / "result.zarr")) is read_stores
    assert get_reader([str(demo / "cube.zarr"), str(demo / "result.zarr") + "/"]) is read_stores
    assert get_reader([str(demo / "cube.zarr"), str(tmp_path / "other.zarr")]) is None


def test_the_reader_names_a_damaged_store_of_its_kind(tmp_path):
    g = zarr.open_group(tmp_path / "res.zarr", mode="w")
    g.attrs.update({"streaklab_kind": "decomposition", "format_version": 1})
    with pytest.raises(ResultStoreError, match="res.zarr"):
        get_reader(str(tmp_path / "res.zarr"))(str(tmp_path / "res.zarr"))


def test_the_reader_gives_the_demo_stores_lazy_layers_with_scales_units_and_names(demo):
    import dask.array as da

    v = _viewer()
    for kind in ("run", "cube", "result"):
        for tup in read_stores(str(demo / f"{kind}.zarr")):
            from napari.layers import Layer

            v.add_layer(Layer.create(*tup))
            assert isinstance(tup[0], da.Array), tup[1]["name"]

    streaks = _layer(v, "streaks")
    run = zarr.open_group(demo / "run.zarr", mode="r")
    assert streaks.axis_labels == ("line", "frame", "x", "row") and type(streaks).__name__ == "Image"
    assert tuple(str(u) for u in streaks.units) == ("pixel",) * 4
    np.testing.assert_array_equal(np.asarray(streaks.data), run["streaks"][...])
    np.testing.assert_array_equal(streaks.metadata["time_ps"], run["time_ps"][...])

    cube = open_cube(str(demo / "cube.zarr"))
    y = cube.group["y"][...]
    c = _layer(v, "cube")
    assert c.axis_labels == ("t", "y", "x")
    np.testing.assert_allclose(c.scale, [cube.time_bin_ps, y[1] - y[0], 1.0])
    np.testing.assert_allclose(c.translate, [cube.t0_ps, y[0], 0.0])
    assert tuple(str(u) for u in c.units) == ("picosecond", "degree", "pixel")
    np.testing.assert_array_equal(np.asarray(c.data), np.moveaxis(cube.array[...], 2, 0))

    store = open_result_store(demo / "result.zarr")
    for name in ("direct", "sss", "residual"):
        layer = _layer(v, name)
        assert type(layer).__name__ == "Image" and layer.axis_labels == ("t", "y", "x")
        np.testing.assert_allclose(layer.scale, c.scale)
        np.testing.assert_allclose(layer.translate, c.translate)
        np.testing.assert_array_equal(np.asarray(layer.data), np.moveaxis(store.group[name][...], 2, 0))
    ir = _layer(v, "ir")
    assert ir.axis_labels == ("r", "t", "y", "x") and ir.translate[0] == 2.0
    np.testing.assert_array_equal(np.asarray(ir.data), np.transpose(store.group["ir"][...], (2, 3, 0, 1)))
    delay = _layer(v, "direct_delay_ps")
    assert delay.axis_labels == ("y", "x") and tuple(str(u) for u in delay.units) == ("degree", "pixel")
    np.testing.assert_allclose(delay.scale, c.scale[1:])
    assert delay.metadata["units"] == "ps"
    np.testing.assert_array_equal(np.asarray(delay.data), store.group["direct_delay_ps"][...])
    flags = _layer(v, "flags")
    assert type(flags).__name__ == "Labels"
    np.testing.assert_array_equal(np.asarray(flags.data), store.group["flags"][...])


def test_an_uneven_scan_axis_is_shown_by_index_and_says_so(tmp_path):
    write_cube(tmp_path / "c.zarr", np.ones((3, 2, 8), np.float32), time_bin_ps=4.0, t0_ps=10.0,
               y_coord=[0.0, 1.0, 3.0], y_units="deg")
    (tup,) = read_stores(str(tmp_path / "c.zarr"))
    assert tup[1]["scale"] == (4.0, 1.0, 1.0) and tup[1]["translate"] == (10.0, 0.0, 0.0)
    assert tup[1]["units"] == ("ps", "pixel", "pixel")
    assert "not uniform" in tup[1]["metadata"]["streaklab_axes"]["y"]


def test_maps_are_the_stores_parameters_and_component_integrals(demo):
    store = open_result_store(demo / "result.zarr")
    names = map_names(store)
    assert {"direct_delay_ps", "sss_alpha_per_ps", "ir_amplitude", "direct_integral", "valid"} <= set(names)
    v = _viewer()
    amp, integral = add_maps(v, store.path, ["ir_amplitude", "direct_integral"])
    assert amp.axis_labels == ("r", "y", "x")
    np.testing.assert_array_equal(np.asarray(amp.data), np.moveaxis(store.group["ir_amplitude"][...], 2, 0))
    np.testing.assert_allclose(np.asarray(integral.data),
                               store.group["direct"][...].sum(axis=-1) * store.attrs["time_bin_ps"], rtol=1e-6)
    assert integral.metadata["units"] == f"{store.attrs['units']} ps"
    with pytest.raises(ValueError, match="has no map 'depth'; its maps are direct_delay_ps"):
        map_layer(store, "depth")


def _strongest_pixel(store):
    amp = np.where(store.group["valid"][...], store.group["direct_amplitude"][...], -np.inf)
    return tuple(int(i) for i in np.unravel_index(np.nanargmax(amp), amp.shape))


def test_the_pixel_view_is_the_stores_profile_components_residual_and_flags(demo):
    store = open_result_store(demo / "result.zarr")
    g = store.group
    y, x = _strongest_pixel(store)
    view = pixel_view(store, y, x)
    np.testing.assert_array_equal(view["t"], g["t"][...])
    np.testing.assert_array_equal(view["measured"], open_cube(str(demo / "cube.zarr")).array[y, x])
    for name in ("direct", "sss", "residual"):
        np.testing.assert_array_equal(view[name], g[name][y, x])
    np.testing.assert_array_equal(view["ir"], g["ir"][y, x])
    np.testing.assert_allclose(view["fit"], g["direct"][y, x] + g["sss"][y, x] + g["ir"][y, x].sum(axis=0),
                               rtol=1e-6)
    # measured = fit + residual, to the float32 rounding of the stored components
    scale = np.abs(view["measured"]).max()
    np.testing.assert_allclose(view["fit"] + view["residual"], view["measured"], atol=1e-5 * scale)
    assert np.nanmax(view["direct"]) > 0
    assert view["flags"] == int(g["flags"][y, x]) and view["flag_names"] == flag_names(view["flags"])
    assert view["done"] and view["valid"] and view["units"] == "counts"
    with pytest.raises(ValueError, match=r"pixel \(y=3, x=0\) is outside"):
        pixel_view(store, 3, 0)


def _chunk(store, iy, ix, value):
    ys, xs = store.chunk_slices(iy, ix)
    shp = (ys.stop - ys.start, xs.stop - xs.start)
    nt, r = store.shape[2], store.n_ir
    params = {k: np.full(shp + ((r,) if k.startswith("ir_") else ()), value) for k in store.param_keys}
    return {"params": params, "rms_residual": np.full(shp, value), "flags": np.full(shp, 3, np.uint16),
            "valid": np.ones(shp, bool), "direct": np.full(shp + (nt,), value), "sss": np.zeros(shp + (nt,)),
            "residual": np.zeros(shp + (nt,)), "ir": np.zeros(shp + (r, nt))}


def test_layers_of_a_result_store_being_written_refresh_as_chunks_land(tmp_path):
    store = create_result_store(tmp_path / "res.zarr", shape=(2, 3, 8), chunks=(1, 3), n_ir=1, time_bin_ps=2.0,
                                t0_ps=2.0)
    store.write_chunk(0, 0, _chunk(store, 0, 0, 5.0))
    v = _viewer()
    add_store(v, store.path)
    direct, delay, flags = _layer(v, "direct"), _layer(v, "direct_delay_ps"), _layer(v, "flags")
    assert np.isnan(np.asarray(direct.data)[:, 1]).all() and (np.asarray(direct.data)[:, 0] == 5.0).all()
    assert refresh_layers(v) == 0                              # nothing new: nothing rebuilt
    # a chunk whose arrays are written but whose done flag is not yet: still not shown
    g = zarr.open_group(store.path, mode="r+")
    g["direct"][1] = 7.0
    assert refresh_layers(v) == 0 and np.isnan(np.asarray(direct.data)[:, 1]).all()
    store.write_chunk(1, 0, _chunk(store, 1, 0, 7.0))
    assert refresh_layers(v) == len(v.layers)                  # every layer of the store changed
    assert (np.asarray(direct.data)[:, 1] == 7.0).all() and (np.asarray(delay.data)[1] == 7.0).all()
    assert (np.asarray(flags.data) == 3).all()
    assert pixel_view(store.path, 1, 2)["done"] and pixel_view(store.path, 1, 2)["flag_names"] == flag_names(3)
    assert refresh_layers(v) == 0                              # complete: nothing left to refresh


def test_a_run_being_captured_refreshes_line_by_line(tmp_path):
    from test_reconstruct import ANGLES, make_run

    run = make_run(tmp_path / "run.zarr", done=[True] + [False] * (len(ANGLES) - 1))
    v = _viewer()
    add_store(v, run.path)
    streaks = _layer(v, "streaks")
    assert (np.asarray(streaks.data)[1:] == 0).all() and np.asarray(streaks.data)[0].any()
    frames = np.full(run["streaks"].shape[1:], 9, np.uint16)
    run.write_line(1, frames, angle_deg=ANGLES[1], timestamp=1.7e9)
    assert refresh_layers(v) == 1
    np.testing.assert_array_equal(np.asarray(streaks.data)[1], frames)


def test_the_pixel_inspector_widget_draws_a_clicked_pixel_offscreen(demo, qapp):
    from streaklab.napari._widgets import MapsWidget, PixelInspector

    v = _viewer()
    add_store(v, str(demo / "result.zarr"))
    w = PixelInspector(v)
    maps = MapsWidget(v)
    try:
        path = str((demo / "result.zarr").resolve())
        assert w.path == path and maps.chooser.currentText() == path
        store = open_result_store(path)
        y, x = _strongest_pixel(store)
        delay = _layer(v, "direct_delay_ps")
        world = (0.0, 0.0) + tuple(delay.data_to_world((y, x)))   # a click over the pixel (r, t, y, x)
        assert pixel_at(v, path, world) == (y, x)
        event = SimpleNamespace(position=world)
        for callback in v.mouse_drag_callbacks:
            callback(v, event)
        assert w.pixel == (y, x)
        lines = {ln.get_label(): ln.get_ydata() for ln in w.figure.axes[0].get_lines()}
        np.testing.assert_array_equal(lines["direct"], store.group["direct"][y, x])
        np.testing.assert_array_equal(lines["residual"], store.group["residual"][y, x])
        assert {"measured", "fit", "subsurface"} <= set(lines)
        names = ", ".join(flag_names(store.group["flags"][y, x])) or "none"
        assert f"flags: {names}" in w.label.text()
        maps.names.findItems("sss_delay_ps", __import__("qtpy").QtCore.Qt.MatchExactly)[0].setSelected(True)
        (added,) = maps.add_selected()
        np.testing.assert_array_equal(np.asarray(added.data), store.group["sss_delay_ps"][...])
        assert w.refresh() == 0                                # a complete store: nothing to refresh
    finally:
        w.timer.stop()
        maps.timer.stop()


@pytest.fixture(scope="module")
def qapp():
    from qtpy.QtWidgets import QApplication

    return QApplication.instance() or QApplication([])


def test_the_core_packages_and_the_cli_import_and_run_without_the_plugins_dependencies():
    code = ("import sys, importlib.abc\n"
            f"BLOCKED = {PLUGIN_ONLY!r}\n"
            "class Block(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name.split('.')[0] in BLOCKED:\n"
            "            raise ImportError(f'{name} is not installed')\n"
            "sys.meta_path.insert(0, Block())\n"
            "import core, drivers, acquisition, reconstruction, decomposition, streaklab\n"
            "import acquisition.runstore, reconstruction.cubestore, decomposition.store.resultstore\n"
            "import streaklab.report, streaklab.cli\n"
            "from streaklab.cli import main\n"
            "try:\n"
            "    main(['--help'])\n"
            "except SystemExit as exc:\n"
            "    assert exc.code == 0, exc.code\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_a_stored_background_is_part_of_the_fit_and_of_the_measured_profile_rebuilt_without_the_cube(tmp_path):
    from decomposition.store.resultstore import CORE_MAP_KEYS

    store = create_result_store(tmp_path / "res.zarr", shape=(1, 2, 8), chunks=(1, 2), n_ir=1, time_bin_ps=2.0,
                                t0_ps=2.0, param_keys=CORE_MAP_KEYS + ("background",))
    chunk = _chunk(store, 0, 0, 1.0)                  # direct 1, sss 0, ir 0, residual 0 ...
    chunk["params"]["background"] = np.array([[2.0, np.nan]])
    chunk["residual"][:] = 0.5
    store.write_chunk(0, 0, chunk)
    with_b, without = pixel_view(store.path, 0, 0), pixel_view(store.path, 0, 1)
    np.testing.assert_array_equal(with_b["background"], 2.0)
    np.testing.assert_array_equal(with_b["fit"], 3.0)
    np.testing.assert_array_equal(with_b["measured"], 3.5)          # no source cube: fit + residual
    np.testing.assert_array_equal(without["background"], 0.0)       # NaN: no background found
    np.testing.assert_array_equal(without["fit"], 1.0)
    np.testing.assert_array_equal(without["measured"], 1.5)
