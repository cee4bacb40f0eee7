"""Stores describe themselves: consolidated metadata (plain xr.open_zarr), units and meanings."""
import warnings

import numpy as np
import pytest

from _cubes import TB, small_cube
from decomposition.api import FLAG_NAMES
from decomposition.store.resultstore import OUT_OF_RANGE
from reconstruction.build import reconstruct
from reconstruction.cubestore import write_cube
from streaklab.cli import main
from test_reconstruct import make_run

xr = pytest.importorskip("xarray")


def _open_quietly(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return xr.open_zarr(path)


def test_a_cube_from_a_run_opens_with_plain_open_zarr(tmp_path):
    run = make_run(tmp_path / "run.zarr")
    reconstruct(run.path, tmp_path / "cube.zarr")
    ds = _open_quietly(tmp_path / "cube.zarr")
    assert ds["cube"].dims == ("y", "x", "t") and ds["t"].attrs["units"] == "ps"
    assert ds["line_valid"].attrs["flag_meanings"] == "unfinished acquired"
    assert _open_quietly(tmp_path / "run.zarr")["streaks"].dims == ("line", "frame", "x", "row")


def test_result_store_flags_and_results_too_large_for_float32(tmp_path):
    """A float64 cube of values near 1e39 decomposes to float32 components that cannot hold some of
    them: those are NaN and their pixels flagged OUT_OF_RANGE, never inf."""
    data = small_cube(1, 3, seed=2).astype(np.float64) * 1e39
    write_cube(tmp_path / "big.zarr", data, time_bin_ps=TB, dtype="float64")
    assert main(["decompose", str(tmp_path / "big.zarr"), "--out", str(tmp_path / "res.zarr"), "--quiet"]) == 0
    ds = _open_quietly(tmp_path / "res.zarr")
    flags = ds["flags"]
    table = {**FLAG_NAMES, OUT_OF_RANGE: "OUT_OF_RANGE"}      # every bit in order, the store's own among them
    assert flags.attrs["flag_masks"] == sorted(table)
    assert flags.attrs["flag_meanings"].split() == [table[b] for b in sorted(table)]
    assert ds["valid"].all()
    for name in ("direct", "sss", "residual", "ir"):
        assert not np.isinf(ds[name].values).any(), name
    too_big = (np.abs(ds["direct_amplitude"].values) > np.finfo(np.float32).max)
    assert too_big.any()
    np.testing.assert_array_equal((flags.values & OUT_OF_RANGE) != 0, too_big)
    assert np.isnan(ds["direct"].values[too_big]).any()
