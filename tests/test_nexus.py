"""NeXus/HDF5 export and import: NXdata conventions and a lossless round trip."""
import h5py
import numpy as np
import pytest
import zarr

from reconstruction.cubestore import create_cube, open_cube, write_cube
from reconstruction.nexus import NexusError, export_cube, import_cube
from streaklab.cli import main


def make_cube(path):
    rng = np.random.default_rng(1)
    data = rng.normal(size=(5, 6, 40)).astype(np.float32)
    data[1, 2, :] = np.nan                                   # a missing pixel survives
    cube = create_cube(path, data.shape, time_bin_ps=2.0, t0_ps=12.0, chunks=(2, 4),
                       provenance={"producer": "test", "lines_used": [4, 0, 1, 2, 3], "nested": {"a": None}},
                       y_coord=[-2.0, -1.0, 0.0, 1.0, 2.0], y_units="deg")
    cube.array[...] = data
    g = cube.group
    g.create_array("line_valid", shape=(5,), dtype="bool", dimension_names=["y"],
                   attributes={"long_name": "ok"})[:] = [True, False, True, True, True]
    truth = g.create_group("truth", attributes={"note": "ground truth"})
    truth.create_array("direct_delay_ps", shape=(5, 6), dtype="float64", dimension_names=["y", "x"],
                       attributes={"units": "ps"})[...] = rng.random((5, 6))
    return data


def assert_groups_equal(a: zarr.Group, b: zarr.Group):
    assert dict(a.attrs) == dict(b.attrs)
    assert sorted(n for n, _ in a.arrays()) == sorted(n for n, _ in b.arrays())
    assert sorted(n for n, _ in a.groups()) == sorted(n for n, _ in b.groups())
    for name, arr in a.arrays():
        other = b[name]
        assert other.dtype == arr.dtype and other.shape == arr.shape and other.chunks == arr.chunks, name
        assert tuple(other.metadata.dimension_names) == tuple(arr.metadata.dimension_names), name
        assert dict(other.attrs) == dict(arr.attrs), name
        np.testing.assert_array_equal(other[...], arr[...])   # NaN == NaN here, bit-exact otherwise
        assert np.asarray(other[...]).tobytes() == np.asarray(arr[...]).tobytes(), name
    for name, sub in a.groups():
        assert_groups_equal(sub, b[name])


def test_nexus_layout(tmp_path):
    make_cube(tmp_path / "c.zarr")
    export_cube(tmp_path / "c.zarr", tmp_path / "c.h5")
    with h5py.File(tmp_path / "c.h5", "r") as f:
        assert f.attrs["default"] == "entry" and f["entry"].attrs["NX_class"] == "NXentry"
        d = f["entry/data"]
        assert d.attrs["NX_class"] == "NXdata" and d.attrs["signal"] == "cube"
        assert list(d.attrs["axes"]) == ["y", "x", "t"]
        assert (d.attrs["y_indices"], d.attrs["x_indices"], d.attrs["t_indices"]) == (0, 1, 2)
        assert d["t"].attrs["units"] == "ps" and d["y"].attrs["units"] == "deg" and d["x"].attrs["units"] == "pixel"
        np.testing.assert_allclose(d["t"][:3], [12.0, 14.0, 16.0])
        assert d["cube"].dtype == np.float32 and d["cube"].shape == (5, 6, 40)
        assert d.attrs["time_bin_ps"] == 2.0 and '"producer": "test"' in d.attrs["provenance"]
        assert f["entry/truth"].attrs["NX_class"] == "NXcollection"


def test_round_trip_is_lossless(tmp_path):
    data = make_cube(tmp_path / "c.zarr")
    export_cube(tmp_path / "c.zarr", tmp_path / "c.h5")
    import_cube(tmp_path / "c.h5", tmp_path / "back.zarr")
    a = zarr.open_group(str(tmp_path / "c.zarr"), mode="r")
    b = zarr.open_group(str(tmp_path / "back.zarr"), mode="r")
    assert_groups_equal(a, b)
    back = open_cube(tmp_path / "back.zarr")
    assert back.time_bin_ps == 2.0 and back.t0_ps == 12.0
    np.testing.assert_array_equal(back.array[...], data)
    assert np.isnan(back.array.metadata.fill_value)


def test_foreign_nxdata_imports_and_bad_files_are_named(tmp_path):
    with h5py.File(tmp_path / "other.h5", "w") as f:
        e = f.create_group("scan1")
        e.attrs["NX_class"] = "NXentry"
        d = e.create_group("plot")
        d.attrs.update({"NX_class": "NXdata", "signal": "counts", "axes": ["row", "col", "time"]})
        d["counts"] = np.arange(2 * 3 * 4, dtype=np.float64).reshape(2, 3, 4)
        d["row"], d["col"] = np.arange(2.0), np.arange(3.0)
        d["time"] = np.array([5.0, 7.0, 9.0, 11.0])
        d["time"].attrs["units"] = "ps"
    import_cube(tmp_path / "other.h5", tmp_path / "other.zarr")
    c = open_cube(tmp_path / "other.zarr")
    assert c.time_bin_ps == 2.0 and c.t0_ps == 5.0 and c.array[1, 2, 3] == 23.0
    with h5py.File(tmp_path / "other.h5", "a") as f:
        f["scan1/plot/time"][...] = [5.0, 7.0, 10.0, 11.0]
    with pytest.raises(NexusError, match="must be uniform"):
        import_cube(tmp_path / "other.h5", tmp_path / "o2.zarr")
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["x"] = [1, 2]
    with pytest.raises(NexusError, match="no NXentry"):
        import_cube(tmp_path / "plain.h5", tmp_path / "o2.zarr")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(NexusError, match="not an HDF5 file"):
        import_cube(tmp_path / "text.h5", tmp_path / "o2.zarr")
    assert not (tmp_path / "o2.zarr").exists()


def test_command_line_round_trip_and_refusals(tmp_path, capsys):
    write_cube(tmp_path / "c.zarr", np.ones((2, 3, 4)), time_bin_ps=2.0)
    assert main(["export", str(tmp_path / "c.zarr"), "--out", str(tmp_path / "c.h5")]) == 0
    assert main(["export", str(tmp_path / "c.zarr"), "--out", str(tmp_path / "c.h5")]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["import", str(tmp_path / "c.h5"), "--out", str(tmp_path / "back.zarr")]) == 0
    np.testing.assert_array_equal(open_cube(tmp_path / "back.zarr").array[...], np.ones((2, 3, 4)))
    assert main(["export", str(tmp_path / "missing.zarr"), "--out", str(tmp_path / "m.h5")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_declared_sizes_and_damaged_metadata_are_refused_before_writing(tmp_path, capsys, monkeypatch):
    from core import limits
    # a tiny file declaring a 20000 x 20000 x 512 signal (chunks never written read as the fill value)
    with h5py.File(tmp_path / "huge.h5", "w") as f:
        e = f.create_group("entry")
        e.attrs["NX_class"] = "NXentry"
        d = e.create_group("data")
        d.attrs.update({"NX_class": "NXdata", "signal": "s", "axes": ["y", "x", "t"]})
        d.create_dataset("s", shape=(20000, 20000, 512), dtype="float32", chunks=(1, 100, 512))
        d["y"], d["x"], d["t"] = np.arange(20000.0), np.arange(20000.0), 2.0 * np.arange(512)
    assert (tmp_path / "huge.h5").stat().st_size < 1_000_000
    out = tmp_path / "huge.zarr"
    monkeypatch.setattr(limits.shutil, "disk_usage", lambda p: type("Usage", (), {"free": 79 << 30})())
    assert main(["import", str(tmp_path / "huge.h5"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # 20000 x 20000 x 512 float32 = 762.9 GiB: within the 1 TiB limit for cubes, but not on a 79 GiB disk
    assert len(err) == 1 and err[0].startswith(f"streaklab import: error: {tmp_path / 'huge.h5'}: ") and \
        "/entry/data/s: needs 762.94 GiB to import it (limits.MAX_CUBE_BYTES), but only 79.00 GiB are free" in err[0], err
    assert not out.exists() and not list(tmp_path.glob(".huge.zarr*"))
    with h5py.File(tmp_path / "long.h5", "w") as f:
        e = f.create_group("entry")
        e.attrs["NX_class"] = "NXentry"
        d = e.create_group("data")
        d.attrs.update({"NX_class": "NXdata", "signal": "s", "axes": ["y", "x", "t"]})
        d.create_dataset("s", shape=(1, 1, 10**8), dtype="float32", chunks=(1, 1, 10**6))
    with pytest.raises(NexusError, match=r"long\.h5: /entry/data/s \(t\): 100000000 time bins exceeds the limit "
                                         r"of 65536 time bins$"):
        import_cube(tmp_path / "long.h5", out)
    # an exported file whose metadata JSON was damaged
    make_cube(tmp_path / "c.zarr")
    export_cube(tmp_path / "c.zarr", tmp_path / "c.h5")
    with h5py.File(tmp_path / "c.h5", "a") as f:
        f["entry/data/cube"].attrs["streaklab_zarr"] = '{"chunks": [2, 4, 40], "attributes": {'
    with pytest.raises(NexusError, match=r"c\.h5: /entry/data/cube@streaklab_zarr is not valid JSON "
                                         r"\(JSONDecodeError: .*\); the file is damaged$"):
        import_cube(tmp_path / "c.h5", out)
    assert not out.exists()
