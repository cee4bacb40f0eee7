"""core.integrity.write_regions: several arrays' regions written in one call, as the item writes would."""
import numpy as np
import pytest
import zarr

from core.integrity import create_array, writable, write_regions


def _group(tmp_path):
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    a = create_array(root, "a", shape=(4, 6), chunks=(2, 3), dtype="f8", fill_value=np.nan)
    b = create_array(root, "b", shape=(4, 6, 5), chunks=(2, 3, 5), dtype="f4", fill_value=0.0)
    c = create_array(root, "c", shape=(4, 6), chunks=(2, 3), dtype=bool, fill_value=False)
    return root, a, b, c


def test_every_region_reads_back_as_written_and_the_rest_keeps_its_fill(tmp_path):
    root, a, b, c = _group(tmp_path)
    rng = np.random.default_rng(3)
    va = rng.normal(size=(2, 3))
    vb = rng.normal(size=(2, 3, 5)).astype(np.float32)
    write_regions([(a, (slice(2, 4), slice(3, 6)), va), (b, (slice(0, 2), slice(0, 3)), vb),
                   (c, (slice(2, 4), slice(0, 3)), np.ones((2, 3), bool))])
    again = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")   # from disk, not from a cache
    np.testing.assert_array_equal(again["a"][2:4, 3:6], va)
    assert np.isnan(again["a"][:2]).all() and np.isnan(again["a"][2:, :3]).all()
    np.testing.assert_array_equal(again["b"][0:2, 0:3], vb)
    assert not again["b"][2:].any()
    assert again["c"][2:4, 0:3].all() and again["c"][...].sum() == 6


def test_a_region_of_only_the_fill_value_is_stored_through_a_writable_array(tmp_path):
    """A chunk file for a region holding just the fill value: the store's resume and verify expect
    one for every chunk written (zarr skips them by default)."""
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    plain = root.create_array("c", shape=(4, 6), chunks=(2, 3), dtype=bool, fill_value=False)
    write_regions([(writable(plain), (slice(0, 2), slice(0, 3)), np.zeros((2, 3), bool)),
                   (plain, (slice(0, 2), slice(3, 6)), np.zeros((2, 3), bool))])
    assert (tmp_path / "s.zarr/c/c/0/0").is_file()
    assert not (tmp_path / "s.zarr/c/c/0/1").exists()     # the array's own setting: skipped


def test_a_failing_write_is_raised_and_the_others_still_land(tmp_path):
    root, a, b, c = _group(tmp_path)
    read_only = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["b"]
    va = np.arange(6.0).reshape(2, 3)
    with pytest.raises(ValueError, match="read-only"):
        write_regions([(read_only, (slice(0, 2), slice(0, 3)), np.ones((2, 3, 5), np.float32)),
                       (a, (slice(0, 2), slice(0, 3)), va)])
    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["a"][:2, :3], va)
    assert not zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["b"][...].any()


def test_without_zarrs_batching_bridge_the_writes_go_one_by_one(tmp_path, monkeypatch):
    """A zarr without ``zarr.core.sync`` (internal API) still gets every region written."""
    import builtins

    real_import = builtins.__import__

    def no_bridge(name, *args, **kwargs):
        if name == "zarr.core.sync":
            raise ImportError("no zarr.core.sync here")
        return real_import(name, *args, **kwargs)

    root, a, b, c = _group(tmp_path)
    va = np.arange(6.0).reshape(2, 3)
    monkeypatch.setattr(builtins, "__import__", no_bridge)
    write_regions([(a, (slice(2, 4), slice(0, 3)), va), (c, (slice(0, 2), slice(3, 6)), np.ones((2, 3), bool))])
    monkeypatch.undo()
    again = zarr.open_group(str(tmp_path / "s.zarr"), mode="r")
    np.testing.assert_array_equal(again["a"][2:4, 0:3], va)
    assert again["c"][0:2, 3:6].all() and again["c"][...].sum() == 6


def test_create_array_keeps_the_checksum_at_any_zstd_level(tmp_path):
    from zarr.codecs import Crc32cCodec, ZstdCodec

    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    for name, level in (("default", None), ("fast", 1)):
        kw = {} if level is None else {"zstd_level": level}
        a = create_array(root, name, shape=(4, 8), chunks=(2, 8), dtype="f4", fill_value=np.nan, **kw)
        a[...] = np.arange(32, dtype="f4").reshape(4, 8)
        (zstd,) = [c for c in a.metadata.codecs if isinstance(c, ZstdCodec)]
        assert zstd.level == (0 if level is None else level)
        assert any(isinstance(c, Crc32cCodec) for c in a.metadata.codecs)
        np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "s.zarr"), mode="r")[name][...],
                                      np.arange(32, dtype="f4").reshape(4, 8))
