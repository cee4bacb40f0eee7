"""Run store: layout, per-line durability bookkeeping, validation, xarray."""
import numpy as np
import pytest
import zarr

from acquisition.config import parse_config
from acquisition.runstore import RunStoreError, config_differences, create_run, open_run

RAW = {"scan": {"angles_deg": [1.0, -1.0, 0.0]}, "camera": {"frames_per_line": 2}, "dark": {"frames": 3},
       "calibration": {"time_poly_ps": [0.0, 2.0]}}


def make(tmp_path, raw=RAW):
    return create_run(tmp_path / "run.zarr", parse_config(raw), image_shape=(4, 8), devices={"camera": "sim"})


def test_layout_and_line_writes(tmp_path):
    run = make(tmp_path)
    assert run["streaks"].shape == (3, 2, 4, 8) and run["streaks"].dtype == np.uint16
    assert run["streaks"].chunks == (1, 2, 4, 8)
    assert run["done"].chunks == (1,)
    assert run["dark"].shape == (3, 4, 8)
    assert not run.done_mask().any() and not run.dark_done()
    frames = np.arange(64, dtype=np.uint16).reshape(2, 4, 8)
    run.write_line(1, frames, angle_deg=-0.999, timestamp=1.7e9)
    run.write_dark(np.full((3, 4, 8), 100, np.uint16))
    again = open_run(tmp_path / "run.zarr")
    np.testing.assert_array_equal(again.done_mask(), [False, True, False])
    np.testing.assert_array_equal(again["streaks"][1], frames)
    assert again["angle_deg"][1] == -0.999 and np.isnan(again["angle_deg"][0])
    np.testing.assert_array_equal(again["target_angle_deg"][...], [1.0, -1.0, 0.0])
    assert again.dark_done() and again["dark"][0, 0, 0] == 100
    assert again.attrs["config"]["camera"]["frames_per_line"] == 2
    assert again.attrs["devices"] == {"camera": "sim"}
    assert again.config_hash == parse_config(RAW).hash
    # Only the line's own chunk files exist: one chunk per line, nothing shared.
    assert (tmp_path / "run.zarr/streaks/c/1/0/0/0").is_file()
    assert not (tmp_path / "run.zarr/streaks/c/0").exists()
    with pytest.raises(RunStoreError, match=r"expected uint16 frames of shape \(2, 4, 8\)"):
        run.write_line(0, frames.astype(np.float32), angle_deg=0, timestamp=0)


def test_xarray_opens_run_with_dims(tmp_path):
    xr = pytest.importorskip("xarray")
    run = make(tmp_path)
    run.write_line(0, np.ones((2, 4, 8), np.uint16), angle_deg=1.0, timestamp=1.7e9)
    ds = xr.open_zarr(tmp_path / "run.zarr")
    assert ds["streaks"].dims == ("line", "frame", "x", "row")
    assert ds["dark"].dims == ("dark_frame", "x", "row")
    # labelled axes: line index, slit pixel, streak row and its calibrated time (poly [0, 2] ps)
    assert set(ds["streaks"].coords) == {"line", "x", "row", "time_ps"}
    np.testing.assert_array_equal(ds["line"], [0, 1, 2])
    np.testing.assert_array_equal(ds["time_ps"], 2.0 * np.arange(8))
    assert ds["time_ps"].attrs["units"] == "ps" and ds["x"].attrs["units"] == "pixel"
    assert ds["done"].attrs["flag_meanings"] == "not_acquired acquired"
    assert ds["done"].dims == ("line",) and bool(ds["done"][0])
    assert ds["timestamp"].dtype.kind == "M"  # decoded as UTC datetimes
    assert ds.attrs["streaklab_kind"] == "run"


def test_refuses_existing_and_bad_stores(tmp_path):
    make(tmp_path)
    with pytest.raises(RunStoreError, match="already exists; pass --resume"):
        make(tmp_path)
    with pytest.raises(RunStoreError, match="no such file"):
        open_run(tmp_path / "nothing.zarr")
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain/file.txt").write_text("x")
    with pytest.raises(RunStoreError, match="not a Zarr group"):
        open_run(tmp_path / "plain")
    g = zarr.open_group(str(tmp_path / "cube.zarr"), mode="w")
    g.attrs["streaklab_kind"] = "cube"
    with pytest.raises(RunStoreError, match="not a run store .*'cube'"):
        open_run(tmp_path / "cube.zarr")


def test_partial_files_removed_on_resume_open(tmp_path):
    make(tmp_path)
    stray = tmp_path / "run.zarr/streaks/c/0/0/0/0.0123abcd.partial"
    stray.parent.mkdir(parents=True)
    stray.write_bytes(b"torn")
    open_run(tmp_path / "run.zarr")                 # read-only open leaves it
    assert stray.exists()
    open_run(tmp_path / "run.zarr", mode="r+")
    assert not stray.exists()


def test_config_differences_lists_keys():
    a = parse_config(RAW).hashed_part()
    b = parse_config({**RAW, "camera": {"frames_per_line": 3}}).hashed_part()
    assert config_differences(a, b) == ["camera.frames_per_line (2 -> 3)"]


def test_interrupted_creation_is_recognised(tmp_path):
    from acquisition.runstore import is_uninitialised_run, remove_uninitialised_run

    torn = tmp_path / "torn.zarr"            # not marked by streaklab: never taken for a torn run
    torn.mkdir()
    (torn / "zarr.json.1234.partial").write_text("{")
    assert not is_uninitialised_run(torn)
    with pytest.raises(RunStoreError, match="no zarr.json.*neither resumes nor removes it"):
        open_run(torn, mode="r+")
    assert (torn / "zarr.json.1234.partial").exists()
    g = zarr.open_group(str(tmp_path / "half.zarr"), mode="w")
    g.attrs.update({"streaklab_kind": "run", "initialised": False})
    assert is_uninitialised_run(tmp_path / "half.zarr")
    with pytest.raises(RunStoreError, match="creation was interrupted"):
        open_run(tmp_path / "half.zarr")
    remove_uninitialised_run(tmp_path / "half.zarr")
    assert not (tmp_path / "half.zarr").exists()
    run = make(tmp_path)                                   # a real run is never taken for a torn one
    assert not is_uninitialised_run(run.path)
    with pytest.raises(RunStoreError, match="refusing to delete"):
        remove_uninitialised_run(run.path)
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes/a.txt").write_text("mine")
    assert not is_uninitialised_run(tmp_path / "notes")


def test_stores_carry_consolidated_metadata_through_resumed_sessions(tmp_path):
    import warnings

    xr = pytest.importorskip("xarray")
    run = make(tmp_path)
    run.add_session({"started_utc": "now"})                  # an attribute rewrite keeps it consolidated
    with warnings.catch_warnings():
        warnings.simplefilter("error")                       # no "consolidated metadata not found" warning
        ds = xr.open_zarr(tmp_path / "run.zarr")
    assert ds.attrs["sessions"] == [{"started_utc": "now"}]
    meta = zarr.open_group(str(tmp_path / "run.zarr"), mode="r").metadata.consolidated_metadata
    assert meta is not None and "streaks" in meta.metadata
