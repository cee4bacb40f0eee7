"""Result store: layout, region writes and done marks, validation, and xarray readability."""
import numpy as np
import pytest
import zarr

from decomposition.store.resultstore import (
    CORE_IR_KEYS,
    CORE_MAP_KEYS,
    ChunkWriter,
    ResultStoreError,
    create_result_store,
    open_result_store,
    prepare_output_path,
)


def _chunk_result(store, iy, ix, seed):
    ys, xs = store.chunk_slices(iy, ix)
    by, bx = ys.stop - ys.start, xs.stop - xs.start
    rng = np.random.default_rng(seed)
    nt, r = store.shape[2], store.n_ir
    params = {k: rng.random((by, bx)) for k in store.param_keys if k not in CORE_IR_KEYS}
    params.update({k: rng.random((by, bx, r)) for k in CORE_IR_KEYS})
    return {
        "params": params,
        "rms_residual": rng.random((by, bx)),
        "flags": rng.integers(0, 4, (by, bx)).astype(np.uint8),
        "valid": np.ones((by, bx), bool),
        "direct": rng.random((by, bx, nt)), "sss": rng.random((by, bx, nt)),
        "residual": rng.random((by, bx, nt)), "ir": rng.random((by, bx, r, nt)),
    }


def _store(tmp_path, **kw):
    args = dict(shape=(5, 7, 16), chunks=(2, 3), n_ir=2, time_bin_ps=2.0, t0_ps=4.0,
                attrs={"method": "convscd", "options": {"a": 1}})
    args.update(kw)
    return create_result_store(tmp_path / "res.zarr", **args)


def test_region_writes_fill_exactly_their_chunk_and_mark_it_done(tmp_path):
    store = _store(tmp_path)
    assert store.grid == (3, 3)
    assert store.pending_chunks() == [(i, j) for i in range(3) for j in range(3)]
    res = _chunk_result(store, 2, 1, seed=1)  # an edge chunk: 1 x 3 pixels
    store.write_chunk(2, 1, res)
    again = open_result_store(store.path)
    np.testing.assert_array_equal(again.group["direct_delay_ps"][4:5, 3:6], res["params"]["direct_delay_ps"])
    np.testing.assert_array_equal(again.group["ir_amplitude"][4:5, 3:6], res["params"]["ir_amplitude"])
    np.testing.assert_array_equal(again.group["ir"][4:5, 3:6], res["ir"].astype(np.float32))
    np.testing.assert_array_equal(again.group["flags"][4:5, 3:6], res["flags"])
    done = again.done_mask()
    assert done[4:5, 3:6].all() and done.sum() == 3
    assert (2, 1) not in again.pending_chunks() and len(again.pending_chunks()) == 8
    # everything outside the chunk is untouched: NaN parameters, no flags
    d = again.group["direct_delay_ps"][...]
    assert np.isnan(np.delete(d, [3, 4, 5], axis=1)).all() and np.isnan(d[:4]).all()


def test_rewriting_a_chunk_is_idempotent(tmp_path):
    store = _store(tmp_path)
    res = _chunk_result(store, 0, 0, seed=2)
    store.write_chunk(0, 0, res)
    first = {k: store.group[k][...] for k in store.group.array_keys()}
    ChunkWriter(store.path)(0, 0, res)  # the same chunk again, through the picklable writer
    for k, v in first.items():
        np.testing.assert_array_equal(store.group[k][...], v)


def test_chunk_writer_opens_its_store_once_and_pickles_as_its_path(tmp_path, monkeypatch):
    """A writer keeps the store it opened for its later chunks (threads share it); a pickled copy
    carries only the path and opens the store again where it runs."""
    import pickle
    import threading

    import decomposition.store.resultstore as rs

    store = _store(tmp_path)
    opened = []
    real = rs.open_result_store

    def counting(*args, **kwargs):
        opened.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(rs, "open_result_store", counting)
    writer = ChunkWriter(store.path)
    jobs = [(iy, ix) for iy in range(3) for ix in range(3)]
    threads = [threading.Thread(target=writer, args=(iy, ix, _chunk_result(store, iy, ix, seed=10 * iy + ix)))
               for iy, ix in jobs]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(opened) == 1
    again = real(store.path)
    assert again.done_mask().all()
    for iy, ix in jobs:
        ys, xs = again.chunk_slices(iy, ix)
        want = _chunk_result(store, iy, ix, seed=10 * iy + ix)
        np.testing.assert_array_equal(again.group["sss"][ys, xs], want["sss"].astype(np.float32))
    copy = pickle.loads(pickle.dumps(writer))
    assert copy == writer and copy is not writer
    copy(0, 0, _chunk_result(store, 0, 0, seed=99))
    assert len(opened) == 2
    np.testing.assert_array_equal(real(store.path).group["flags"][0:2, 0:3], _chunk_result(store, 0, 0, seed=99)["flags"])


def test_mismatched_writes_are_refused_before_anything_is_written(tmp_path):
    store = _store(tmp_path)
    res = _chunk_result(store, 0, 0, seed=3)
    bad = dict(res, params=dict(res["params"], ir_delay_ps=np.zeros((2, 3, 5))))
    with pytest.raises(ResultStoreError, match="ir_delay_ps has shape"):
        store.write_chunk(0, 0, bad)
    missing = dict(res, params={k: v for k, v in res["params"].items() if k != "sss_alpha_per_ps"})
    with pytest.raises(ResultStoreError, match="missing.*sss_alpha_per_ps"):
        store.write_chunk(0, 0, missing)
    with pytest.raises(ResultStoreError, match="outside"):
        store.write_chunk(3, 0, res)
    assert not store.done_mask().any()
    assert np.isnan(store.group["direct_delay_ps"][...]).all()


def test_extra_parameters_and_no_components(tmp_path):
    keys = CORE_MAP_KEYS + ("direct_delay_ps_stderr",)
    store = _store(tmp_path, param_keys=keys, ir_param_keys=("ir_delay_ps_stderr",), write_components=False)
    assert "direct" not in store.group and "ir" not in store.group
    assert store.group["direct_delay_ps_stderr"].shape == (5, 7)
    assert store.group["ir_delay_ps_stderr"].shape == (5, 7, 2)
    assert store.group["direct_delay_ps_stderr"].attrs["units"] == "ps"
    res = _chunk_result(store, 0, 0, seed=4)
    res["params"]["ir_delay_ps_stderr"] = np.ones((2, 3, 2))
    store.write_chunk(0, 0, res)
    np.testing.assert_array_equal(store.group["ir_delay_ps_stderr"][0:2, 0:3], 1.0)


def test_xarray_opens_with_dims_units_and_attributes(tmp_path):
    xr = pytest.importorskip("xarray")
    store = _store(tmp_path, signal_units="photons")
    store.write_chunk(0, 0, _chunk_result(store, 0, 0, seed=5))
    ds = xr.open_zarr(store.path, consolidated=False)
    assert ds["direct_delay_ps"].dims == ("y", "x")
    assert ds["ir_delay_ps"].dims == ("y", "x", "r")
    assert ds["ir"].dims == ("y", "x", "r", "t")
    assert ds["residual"].dims == ("y", "x", "t")
    assert ds["sss_alpha_per_ps"].attrs["units"] == "1/ps"
    assert ds["direct_amplitude"].attrs["units"] == "photons"
    np.testing.assert_allclose(ds["t"].values[:2], [4.0, 6.0])
    assert ds.attrs["method"] == "convscd" and ds.attrs["options"] == {"a": 1}
    assert ds.attrs["time_bin_ps"] == 2.0 and ds.attrs["n_ir"] == 2
    assert bool(ds["done"][0:2, 0:3].all()) and not bool(ds["done"][2:, :].any())


def test_open_names_what_is_wrong(tmp_path):
    with pytest.raises(ResultStoreError, match="no such file"):
        open_result_store(tmp_path / "missing.zarr")
    g = zarr.open_group(str(tmp_path / "cube.zarr"), mode="w")
    g.attrs["streaklab_kind"] = "cube"
    with pytest.raises(ResultStoreError, match="'cube' store"):
        open_result_store(tmp_path / "cube.zarr")
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("hello")
    with pytest.raises(ResultStoreError):
        open_result_store(tmp_path / "plain")
    store = _store(tmp_path)
    del store.group["sss_amplitude"]
    with pytest.raises(ResultStoreError, match="sss_amplitude"):
        open_result_store(store.path)


def test_existing_paths_are_protected(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "keep.txt").write_text("precious")
    with pytest.raises(FileExistsError, match="--overwrite"):
        create_result_store(tmp_path / "data", shape=(2, 2, 4), chunks=(1, 1), n_ir=1, time_bin_ps=2.0, t0_ps=2.0)
    assert (tmp_path / "data" / "keep.txt").read_text() == "precious"
    with pytest.raises(ResultStoreError, match="holds the input"):
        prepare_output_path(tmp_path / "data", overwrite=True, protect=[tmp_path / "data"])
    with pytest.raises(ResultStoreError, match="holds the input"):
        prepare_output_path(tmp_path, overwrite=True, protect=[tmp_path / "data" / "keep.txt"])
    assert (tmp_path / "data" / "keep.txt").exists()
    store = create_result_store(tmp_path / "data", shape=(2, 2, 4), chunks=(1, 1), n_ir=1, time_bin_ps=2.0,
                                t0_ps=2.0, overwrite=True)
    assert not (tmp_path / "data" / "keep.txt").exists() and store.grid == (2, 2)


def test_every_chunk_file_is_fsynced_before_done_and_done_after(tmp_path, monkeypatch):
    """A power cut must not leave a chunk marked done whose results never reached the disk:
    every file the chunk wrote is fsync'd (with its directories) before the done flag's file."""
    import core.durable as durable

    synced = []
    real = durable.fsync_path
    monkeypatch.setattr(durable, "fsync_path", lambda p: (synced.append(str(p)), real(p)))
    store = _store(tmp_path)
    store.write_chunk(1, 2, _chunk_result(store, 1, 2, seed=3))
    root = store.path.rstrip("/")
    base = tmp_path / "res.zarr"
    written = sorted(str(p) for p in base.rglob("*")
                     if p.is_file() and p.relative_to(base).parts[1:4] == ("c", "1", "2"))
    assert len(written) == len(store.param_keys) + 8    # + rms, flags, valid, 4 components, done
    files = [p for p in synced if not (tmp_path / p).is_dir()]
    assert sorted(set(files)) == written
    done_file = f"{root}/done/c/1/2"
    assert files[-1] == done_file and files.count(done_file) == 1
    assert f"{root}/done/c/1" in synced and f"{root}/direct/c/1/2" in synced


def test_values_beyond_float32_are_flagged_never_inf(tmp_path):
    from decomposition.store.resultstore import OUT_OF_RANGE

    store = _store(tmp_path)
    res = _chunk_result(store, 0, 0, seed=2)
    res["direct"][1, 2, 5] = 1e39                     # finite in float64, inf as float32
    res["residual"][0, 0, :] = -5e38
    store.write_chunk(0, 0, res)
    g = open_result_store(store.path).group
    direct, resid, flags = g["direct"][0:2, 0:3], g["residual"][0:2, 0:3], g["flags"][0:2, 0:3]
    assert not np.isinf(direct).any() and not np.isinf(resid).any()
    assert np.isnan(direct[1, 2, 5]) and np.isnan(resid[0, 0]).all()
    assert direct[1, 2, 4] == np.float32(res["direct"][1, 2, 4])     # the rest of the pixel is kept
    expect = res["flags"].astype(np.uint16)
    expect[1, 2] |= OUT_OF_RANGE
    expect[0, 0] |= OUT_OF_RANGE
    np.testing.assert_array_equal(flags, expect)


def test_quality_arrays_say_what_they_mean(tmp_path):
    from decomposition.api import FLAG_NAMES

    store = _store(tmp_path, flag_names=FLAG_NAMES)
    a = store.group["flags"].attrs
    table = {**FLAG_NAMES, 256: "OUT_OF_RANGE"}          # every bit in order, the store's own among them
    assert a["flag_masks"] == sorted(table)
    assert a["flag_meanings"].split() == [table[b] for b in sorted(table)]
    assert store.group["valid"].attrs["flag_meanings"] == "not_decomposed decomposed"
    assert store.group["done"].attrs["flag_values"] == [0, 1] and store.group["done"].attrs["units"] == "1"
