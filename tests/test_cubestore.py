"""Cube store: round trip, self-description for xarray, and clear errors."""
import numpy as np
import pytest
import zarr

from reconstruction.cubestore import CubeStoreError, create_cube, open_cube, write_cube


def test_round_trip_and_layout(tmp_path):
    data = np.random.default_rng(0).random((5, 7, 33)).astype(np.float32)
    write_cube(tmp_path / "c.zarr", data, time_bin_ps=2.0, t0_ps=10.0, chunks=(2, 3), provenance={"by": "test"})
    cube = open_cube(tmp_path / "c.zarr")
    np.testing.assert_array_equal(cube.array[...], data)
    assert cube.array.chunks == (2, 3, 33)
    assert cube.time_bin_ps == 2.0 and cube.t0_ps == 10.0
    np.testing.assert_allclose(cube.time_axis_ps()[:3], [10.0, 12.0, 14.0])
    assert cube.attrs["provenance"] == {"by": "test"}


def test_xarray_opens_with_dims_and_time_coordinate(tmp_path):
    xr = pytest.importorskip("xarray")
    write_cube(tmp_path / "c.zarr", np.ones((2, 3, 4)), time_bin_ps=2.0)
    ds = xr.open_zarr(tmp_path / "c.zarr", consolidated=False)
    assert ds["cube"].dims == ("y", "x", "t")
    np.testing.assert_allclose(ds["t"].values, [2.0, 4.0, 6.0, 8.0])
    assert ds["t"].attrs["units"] == "ps"


def test_refuses_to_overwrite(tmp_path):
    write_cube(tmp_path / "c.zarr", np.ones((2, 3, 4)), time_bin_ps=2.0)
    with pytest.raises(FileExistsError, match="already exists"):
        write_cube(tmp_path / "c.zarr", np.zeros((2, 3, 4)), time_bin_ps=2.0)
    assert open_cube(tmp_path / "c.zarr").array[0, 0, 0] == 1.0  # nothing written over
    write_cube(tmp_path / "c.zarr", np.zeros((2, 3, 4)), time_bin_ps=2.0, overwrite=True)
    assert open_cube(tmp_path / "c.zarr").array[0, 0, 0] == 0.0


def test_bad_stores_are_named(tmp_path):
    with pytest.raises(CubeStoreError, match="no such file"):
        open_cube(tmp_path / "missing.zarr")
    g = zarr.open_group(str(tmp_path / "run.zarr"), mode="w")
    g.attrs["streaklab_kind"] = "run"
    with pytest.raises(CubeStoreError, match="'run' store"):
        open_cube(tmp_path / "run.zarr")
    c = create_cube(tmp_path / "nobin.zarr", (1, 1, 4), time_bin_ps=2.0, t0_ps=0.0)
    del c.array.attrs["time_bin_ps"]
    with pytest.raises(CubeStoreError, match="time_bin_ps"):
        open_cube(tmp_path / "nobin.zarr")
    with pytest.raises(CubeStoreError, match="3-D"):
        write_cube(tmp_path / "flat.zarr", np.ones((3, 4)), time_bin_ps=2.0)


def test_a_cube_says_whether_one_detector_lies_behind_it(tmp_path):
    write_cube(tmp_path / "one.zarr", np.ones((2, 3, 4)), time_bin_ps=2.0, noise_law="detector")
    write_cube(tmp_path / "any.zarr", np.ones((2, 3, 4)), time_bin_ps=2.0)
    assert open_cube(tmp_path / "one.zarr").attrs["noise_law"] == "detector"
    assert "noise_law" not in open_cube(tmp_path / "any.zarr").attrs
    with pytest.raises(CubeStoreError, match="noise_law must be one of detector, got 'camera'"):
        write_cube(tmp_path / "bad.zarr", np.ones((2, 3, 4)), time_bin_ps=2.0, noise_law="camera")
    assert not (tmp_path / "bad.zarr").exists()
