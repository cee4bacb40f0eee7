"""Storing instrument responses: standalone Zarr and .npz, inside a cube store, self-describing."""
import json

import numpy as np
import pytest
import zarr

from core.errors import OutputExistsError
from core.irf import render_shifted
from core.irf_models import afterpulse_response, tailed_response
from core.irfstore import ResponseStoreError, load_response, save_response
from core.provenance import __version__
from reconstruction.cubestore import (
    CubeStoreError, open_cube, read_cube_response, verify_cube, write_cube, write_cube_response,
)


def _same(a, b):
    np.testing.assert_array_equal(a.samples, b.samples)
    assert (a.time_step_ps, a.t0_ps, a.model) == (b.time_step_ps, b.t0_ps, b.model)
    assert a.provenance == b.provenance


@pytest.mark.parametrize("name", ["irf.zarr", "irf.npz"])
def test_round_trip_is_exact_and_self_describing(tmp_path, name):
    irf = tailed_response(3.0, 0.2, 30.0, time_step_ps=2.0, provenance={"pixels_used": 12})
    path = save_response(tmp_path / name, irf)
    back = load_response(path)
    _same(back, irf)
    t = np.arange(100) * 2.0
    np.testing.assert_array_equal(render_shifted(back, t, 50.3), render_shifted(irf, t, 50.3))
    with pytest.raises(OutputExistsError, match="already exists"):
        save_response(path, irf)
    save_response(path, afterpulse_response(3.0, 0.1, 20.0, time_step_ps=2.0), overwrite=True)
    assert load_response(path).model["name"] == "afterpulse"
    if name.endswith(".zarr"):
        # Opened without streaklab: named dimension, units and provenance in plain attributes.
        g = zarr.open_group(str(path), mode="r")
        assert g.attrs["streaklab_kind"] == "instrument_response" and g.attrs["units"] == "1/ps"
        assert g.attrs["software_version"] == __version__ and "created_utc" in g.attrs
        assert tuple(g["response"].metadata.dimension_names) == ("irf_t",)
        assert g["irf_t"].attrs["units"] == "ps"
        t_axis = g["irf_t"][...]
        assert np.sum(g["response"][...]) * (t_axis[1] - t_axis[0]) == pytest.approx(1.0)
    else:
        with np.load(path) as z:
            assert json.loads(str(z["attributes"]))["normalization"] == "unit area"


def test_cube_store_holds_an_optional_response(tmp_path):
    cube = write_cube(tmp_path / "cube.zarr", np.zeros((2, 3, 40), np.float32), time_bin_ps=2.0)
    assert read_cube_response(cube) is None
    irf = tailed_response(3.0, 0.2, 30.0, time_step_ps=2.0, provenance={"source": "calibration"})
    write_cube_response(cube.path, irf)
    _same(read_cube_response(cube.path), irf)
    _same(load_response(cube.path), irf)                   # a cube path is accepted where a response is
    with pytest.raises(CubeStoreError, match="already holds an instrument response"):
        write_cube_response(cube.path, irf)
    write_cube_response(cube.path, afterpulse_response(3.0, 0.1, 20.0, time_step_ps=2.0), overwrite=True)
    assert read_cube_response(cube.path).model["name"] == "afterpulse"
    # The cube itself is untouched and still opens as a dataset without the response's dimension.
    xr = pytest.importorskip("xarray")
    ds = xr.open_zarr(cube.path, consolidated=False)
    assert "irf_t" not in ds.dims and ds.cube.shape == (2, 3, 40)
    assert xr.open_zarr(cube.path, group="irf", consolidated=False).response.dims == ("irf_t",)
    # The cube's consolidated index lists the response too, and verify reads its checksummed chunks.
    assert xr.open_zarr(cube.path, group="irf").irf_t.attrs["units"] == "ps"
    assert verify_cube(open_cube(cube.path)).ok


def test_unusable_paths_are_named(tmp_path):
    with pytest.raises(ResponseStoreError, match="no such file"):
        load_response(tmp_path / "missing.zarr")
    cube = write_cube(tmp_path / "cube.zarr", np.zeros((1, 1, 8), np.float32), time_bin_ps=2.0)
    with pytest.raises(ResponseStoreError, match="'cube' store with no 'irf' group"):
        load_response(cube.path)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ResponseStoreError, match="not an instrument response .npz"):
        load_response(tmp_path / "junk.npz")
    g = zarr.open_group(str(tmp_path / "bad.zarr"), mode="w")
    g.attrs.update({"streaklab_kind": "instrument_response", "time_step_ps": 1.0, "t0_ps": 0.0})
    g.create_array("response", shape=(20,), dtype="float64")[:] = np.ones(20)
    with pytest.raises(ResponseStoreError, match="bad.zarr: the response has not decayed"):
        load_response(tmp_path / "bad.zarr")
