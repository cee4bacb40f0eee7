"""Chunked decomposition: the dask mapping gives exactly the in-memory API's results."""
import threading

import numpy as np
import pytest

from core import model
from decomposition import decompose
from decomposition.store.chunked import chunk_tasks, fit_ir_slots, rechunk_pixels, run_tasks, solve_block

from _cubes import TB, small_cube as _cube




def _assert_same_as_api(result, profiles, n_ir, exact=True):
    """``result`` (chunk layout flattened over pixels) equals decompose() on ``profiles`` (n, L).

    ``exact``: bit for bit (the same batch of pixels).  Otherwise the batches differ, and the
    solver's batched linear algebra and iteration stops depend slightly on a pixel's batch-mates:
    the same components and flags, values equal well within the solver's convergence.
    """
    res = decompose(profiles, time_bin_ps=TB, method="convscd", max_reflections=n_ir)

    def same(a, b, msg, rtol):
        a, b = np.asarray(a), np.asarray(b)
        if exact:
            np.testing.assert_array_equal(a, b, err_msg=msg)
        else:
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=msg)
            np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * np.nanmax(np.abs(b), initial=1.0), err_msg=msg)

    for k, v in res.params.items():
        v = np.asarray(v, np.float64)
        if v.ndim == 2:
            v = fit_ir_slots(v, n_ir, axis=1, fill=np.nan)
        same(result["params"][k], v, k, 1e-6)
    np.testing.assert_array_equal(result["flags"], res.flags)
    # components in the solver's own precision (the store casts them to its float32 arrays)
    same(result["direct"], np.asarray(res.direct), "direct", 1e-6)
    same(result["sss"], np.asarray(res.sss), "sss", 1e-6)
    same(result["ir"], fit_ir_slots(np.asarray(res.interreflections), n_ir, 1, 0.0), "ir", 1e-6)
    np.testing.assert_allclose(result["rms_residual"], np.sqrt(np.mean(np.square(res.residual), axis=-1)),
                               rtol=1e-12 if exact else 1e-5)


def test_solve_block_equals_the_api_and_marks_nonfinite_pixels():
    cube = _cube(3, 4, seed=1)
    cube[1, 2, 7] = np.nan
    cube[0, 3, 0] = np.inf
    out = solve_block(cube, time_bin_ps=TB, method="convscd", n_ir=3, options={"max_reflections": 3})
    valid = np.isfinite(cube).all(-1)
    np.testing.assert_array_equal(out["valid"], valid)
    assert out["stats"]["invalid"] == 2 and out["stats"]["pixels"] == 12
    flat = {k: (v[valid] if k != "params" else {p: a[valid] for p, a in v.items()})
            for k, v in out.items() if k not in ("valid", "stats")}
    _assert_same_as_api(flat, cube[valid], n_ir=3)
    for k, v in out["params"].items():
        assert np.isnan(v[~valid]).all(), k
    from decomposition import NONFINITE
    np.testing.assert_array_equal(out["flags"][~valid], NONFINITE)
    assert np.isnan(out["direct"][~valid]).all() and np.isnan(out["rms_residual"][~valid]).all()
    assert out["params"]["ir_delay_ps"].shape == (3, 4, 3)


def test_fit_ir_slots_pads_and_truncates():
    a = np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(fit_ir_slots(a, 2, 1, np.nan), [[0, 1], [3, 4]])
    padded = fit_ir_slots(a, 5, 1, np.nan)
    assert padded.shape == (2, 5) and np.isnan(padded[:, 3:]).all()
    np.testing.assert_array_equal(padded[:, :3], a)
    comp = np.ones((2, 1, 4))
    assert fit_ir_slots(comp, 3, 1, 0.0).sum() == 8 and fit_ir_slots(comp, 3, 1, 0.0).shape == (2, 3, 4)


def test_chunks_cover_the_cube_once_and_equal_the_in_memory_api():
    cube = _cube(5, 7, seed=2)
    sunk, lock = {}, threading.Lock()

    def sink(iy, ix, result):
        with lock:
            assert (iy, ix) not in sunk
            sunk[(iy, ix)] = result

    shapes = {k: () for k in model.DIRECT_KEYS + model.SSS_KEYS}
    shapes.update({k: (2,) for k in model.IR_KEYS})
    seen = []
    tasks = chunk_tasks(cube, chunks=(2, 3), sink=sink, param_shapes=shapes, time_bin_ps=TB, method="convscd",
                        n_ir=2, options={"max_reflections": 2})
    summaries = run_tasks(tasks, num_workers=2, on_done=seen.append)
    assert sorted(sunk) == [(i, j) for i in range(3) for j in range(3)]
    assert len(seen) == 9 and sum(s["pixels"] for s in summaries) == 35
    # assemble the chunk results into whole-cube arrays and compare with one in-memory call
    whole = {"params": {}}
    for key in ("flags", "direct", "sss", "ir", "rms_residual"):
        whole[key] = np.concatenate([np.concatenate([sunk[(i, j)][key] for j in range(3)], axis=1)
                                     for i in range(3)], axis=0).reshape((35,) + sunk[(0, 0)][key].shape[2:])
    for key in sunk[(0, 0)]["params"]:
        whole["params"][key] = np.concatenate(
            [np.concatenate([sunk[(i, j)]["params"][key] for j in range(3)], axis=1) for i in range(3)],
            axis=0).reshape((35,) + sunk[(0, 0)]["params"][key].shape[2:])
    # each chunk is bit for bit the API on that chunk's pixels ...
    for (iy, ix), r in sunk.items():
        block = cube[2 * iy:2 * iy + 2, 3 * ix:3 * ix + 3]
        flat = {k: (v.reshape((-1,) + v.shape[2:]) if k != "params" else
                    {p: a.reshape((-1,) + a.shape[2:]) for p, a in v.items()})
                for k, v in r.items() if k != "valid"}
        _assert_same_as_api(flat, block.reshape(-1, block.shape[-1]), n_ir=2)
    # ... and the assembled cube is the API on all pixels at once, to the solver's convergence
    _assert_same_as_api(whole, cube.reshape(35, -1), n_ir=2, exact=False)


def test_only_pending_chunks_run_and_rechunking_follows_the_request():
    cube = _cube(4, 4, nt=96, seed=3)
    arr = rechunk_pixels(cube, (3, 2))
    assert arr.chunks == ((3, 1), (2, 2), (96,))
    sunk = []
    tasks = chunk_tasks(arr, chunks=(3, 2), sink=lambda iy, ix, r: sunk.append((iy, ix)), param_shapes={},
                        pending=[(1, 0), (0, 1)], time_bin_ps=TB)
    run_tasks(tasks)
    assert sorted(sunk) == [(0, 1), (1, 0)]


def test_an_all_nan_chunk_gets_nan_parameters_of_every_name():
    cube = _cube(2, 2, nt=64, seed=4)
    cube[:, :, 3] = np.nan
    got = {}
    shapes = {"direct_delay_ps": (), "ir_delay_ps": (2,)}
    run_tasks(chunk_tasks(cube, chunks=(2, 2), sink=lambda iy, ix, r: got.update(r), param_shapes=shapes,
                          time_bin_ps=TB, n_ir=2))
    assert got["params"]["ir_delay_ps"].shape == (2, 2, 2) and np.isnan(got["params"]["ir_delay_ps"]).all()
    assert not got["valid"].any() and got["ir"].shape == (2, 2, 2, 64)


def test_a_failing_chunk_stops_the_run_but_keeps_finished_chunks():
    cube = _cube(2, 6, nt=64, seed=5)
    sunk = []

    def sink(iy, ix, result):
        if ix == 2:
            raise OSError("disk full")
        sunk.append(ix)

    tasks = chunk_tasks(cube, chunks=(2, 1), sink=sink, param_shapes={}, pending=[(0, 0), (0, 1), (0, 2)],
                        time_bin_ps=TB)
    with pytest.raises(OSError, match="disk full"):
        run_tasks(tasks, num_workers=1)
    assert 2 not in sunk and len(set(sunk)) == len(sunk)


def test_pixels_with_more_interreflections_than_kept_are_counted():
    p = model.empty_params((1, 2), 3)
    p["direct_delay_ps"][:] = 40.0
    p["direct_amplitude"][:] = 1.0
    p["direct_sigma_ps"][:] = 3.0
    p["ir_delay_ps"][0, 0] = [100.0, 160.0, 220.0]  # pixel 0: three inter-reflections; pixel 1: none
    p["ir_amplitude"][0, 0] = [0.6, 0.4, 0.3]
    p["ir_sigma_ps"][0, 0] = 3.0
    cube = model.render_profile(p, 160, TB)
    out = solve_block(cube, time_bin_ps=TB, n_ir=1, options={"max_reflections": 1})
    assert out["stats"]["ir_truncated"] == 1
    assert out["stats"]["poor_fit"] == int(np.count_nonzero(out["flags"] & 4))      # POOR_FIT's bit
    assert out["params"]["ir_delay_ps"].shape == (1, 2, 1)
    np.testing.assert_allclose(out["params"]["ir_delay_ps"][0, 0, 0], 100.0, atol=1.0)  # the earliest is kept
    assert np.isnan(out["params"]["ir_delay_ps"][0, 1, 0])


def test_a_local_run_leaves_dask_distributed_unimported(tmp_path):
    """The threaded scheduler is handed to dask as a function: given its name, dask imports
    dask.distributed to look for a client (0.2 s of every ``streaklab decompose``)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    np.save(tmp_path / "c.npy", _cube(2, 3, seed=1))
    code = ("import sys, numpy as np\n"
            "from decomposition.store.pipeline import decompose_to_store\n"
            f"s = decompose_to_store({str(tmp_path / 'c.npy')!r}, {str(tmp_path / 'r.zarr')!r}, "
            f"time_bin_ps={TB}, progress=False)\n"
            "print(s['chunks_done'], 'distributed' in sys.modules)\n")
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    chunks, imported = out.stdout.split()
    assert int(chunks) >= 1 and imported == "False"
