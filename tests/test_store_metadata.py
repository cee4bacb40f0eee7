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


def _arrays(path):
    """(name, array) of every array of the store at ``path``, sub-groups included."""
    import zarr

    g = zarr.open_group(str(path), mode="r", use_consolidated=False)
    return [(name, obj) for name, obj in g.members(max_depth=None) if isinstance(obj, zarr.Array)]


def test_every_array_of_every_store_kind_has_units_and_a_long_name(tmp_path):
    """docs/layout.md: every array carries ``units`` (dimensionless: "1") and ``long_name``; walked
    over every array of a run store (with a camera scaling table), a reconstructed cube with an
    instrument response, a simulated cube with its truth, a result store with every optional
    array, and a standalone instrument-response store."""
    from acquisition.config import parse_config
    from acquisition.runstore import create_run
    from core.irf_models import gaussian_response
    from core.irfstore import save_response
    from decomposition.store.resultstore import CORE_IR_KEYS, CORE_MAP_KEYS, create_result_store
    from decomposition.evaluation.synthetic import make_cube
    from reconstruction.cubestore import write_cube_response
    from streaklab.commands.simulate import write_simulation

    irf = gaussian_response(3.0, time_step_ps=TB)
    run = make_run(tmp_path / "run.zarr")
    create_run(tmp_path / "table.zarr", parse_config({"scan": {"angles_deg": [0.0, 1.0]}, "calibration": {"time_source": "camera"}}), image_shape=(3, 8),
               camera_row_times_ps=np.arange(8.0), camera_time_info={"source": "scaling table"})
    reconstruct(run.path, tmp_path / "cube.zarr")
    write_cube_response(tmp_path / "cube.zarr", irf)
    write_simulation(tmp_path / "sim.zarr", make_cube(2, 3, 96, seed=0))
    create_result_store(tmp_path / "res.zarr", shape=(2, 3, 32), chunks=(1, 3), n_ir=2, time_bin_ps=TB, t0_ps=TB,
                        param_keys=CORE_MAP_KEYS + ("background", "direct_delay_ps_stderr"),
                        ir_param_keys=CORE_IR_KEYS + ("ir_amplitude_stderr",), flag_names=FLAG_NAMES, irf=irf)
    save_response(tmp_path / "irf.zarr", irf)
    stores = {"run": ("run.zarr", "table.zarr"), "cube": ("cube.zarr", "sim.zarr"), "result": ("res.zarr",),
              "response": ("irf.zarr",)}
    lacking, seen = [], set()
    for kind, names in stores.items():
        for store in names:
            for name, a in _arrays(tmp_path / store):
                seen.add(f"{store}/{name}")
                units, long_name = a.attrs.get("units"), a.attrs.get("long_name")
                if not isinstance(units, str) or not isinstance(long_name, str) or not long_name.strip():
                    lacking.append(f"{store}/{name}: units={units!r}, long_name={long_name!r}")
    # the walk reaches the arrays named in the layout, sub-groups included
    assert {"run.zarr/done", "run.zarr/dark_done", "table.zarr/camera_row_times_ps", "cube.zarr/cube",
            "cube.zarr/line_index", "cube.zarr/line_valid", "cube.zarr/irf/response", "sim.zarr/truth/ir",
            "sim.zarr/truth/direct_delay_ps", "res.zarr/background", "res.zarr/ir_amplitude_stderr",
            "res.zarr/irf/irf_t", "irf.zarr/response"} <= seen
    assert not lacking, "\n".join(lacking)
    ds = _open_quietly(tmp_path / "cube.zarr")
    assert ds["line_valid"].attrs["units"] == "1" and ds["cube"].attrs["long_name"]
    assert _open_quietly(tmp_path / "run.zarr")["done"].attrs["units"] == "1"
    res = _open_quietly(tmp_path / "res.zarr")
    assert res["direct_delay_ps_stderr"].attrs["long_name"] == "standard error of the direct reflection delay"
