"""core.durable: chunk files and their directories reach the disk, together and with errors raised."""
import errno
import os

import numpy as np
import pytest
import zarr

import core.durable as durable


def _store(tmp_path):
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    for name in ("a", "b"):
        arr = root.create_array(name, shape=(4, 4), chunks=(2, 2), dtype="f4")
        arr[...] = np.arange(16, dtype="f4").reshape(4, 4)
    return tmp_path / "s.zarr"


def test_chunk_paths_name_the_file_then_each_directory_up_to_the_array(tmp_path):
    got = durable.chunk_paths(tmp_path, "a", (1, 0))
    assert got == [tmp_path / "a/c/1/0", tmp_path / "a/c/1", tmp_path / "a/c", tmp_path / "a"]
    assert durable.chunk_paths(tmp_path, "z", ()) == [tmp_path / "z/c", tmp_path / "z"]


def test_sync_chunks_syncs_every_file_and_directory_once(tmp_path, monkeypatch):
    path = _store(tmp_path)
    synced = []
    real = durable.fsync_path
    monkeypatch.setattr(durable, "fsync_path", lambda p: (synced.append(str(p)), real(p)))
    durable.sync_chunks(path, [("a", (0, 1)), ("b", (0, 1)), ("a", (1, 1)), ("a", (0, 1))])
    expect = set()
    for name, coords in (("a", (0, 1)), ("b", (0, 1)), ("a", (1, 1))):
        expect |= {str(p) for p in durable.chunk_paths(path, name, coords)}
    assert sorted(synced) == sorted(expect)          # each once, though ("a", (0, 1)) came twice
    assert (path / "a/c/1/1").is_file()


def test_a_failed_file_fsync_is_raised_a_refused_directory_fsync_is_not(tmp_path, monkeypatch):
    path = _store(tmp_path)
    real = os.fsync
    bad_dirs = []

    def fsync(fd, *, fail_files):
        if os.path.isdir(f"/proc/self/fd/{fd}"):
            bad_dirs.append(fd)
            raise OSError(errno.EINVAL, "directories cannot be synced here")
        if fail_files:
            raise OSError(errno.EIO, "I/O error")
        return real(fd)

    monkeypatch.setattr(durable.os, "fsync", lambda fd: fsync(fd, fail_files=False))
    durable.sync_chunks(path, [("a", (0, 0)), ("b", (1, 1))])        # directories refused: fine
    assert len(bad_dirs) == 6                                      # a/c/0, a/c, a; b/c/1, b/c, b
    monkeypatch.setattr(durable.os, "fsync", lambda fd: fsync(fd, fail_files=True))
    with pytest.raises(OSError, match="I/O error"):
        durable.sync_chunks(path, [("a", (0, 0)), ("b", (1, 1))])
    with pytest.raises(OSError, match="I/O error"):
        durable.sync_chunk(path, "a", (0, 0))


def test_missing_chunks_are_skipped(tmp_path):
    path = _store(tmp_path)
    durable.sync_chunks(path, [("a", (7, 7))])        # an all-fill chunk zarr never wrote


def _sync_in_child(path, out):
    durable.sync_chunks(path, [("a", (0, 0)), ("b", (0, 0))])
    out.put(durable._POOL[0] == os.getpid())


def test_a_forked_child_syncs_with_its_own_threads(tmp_path):
    """Threads do not survive a fork: a child (a dask worker, say) must not wait on the parent's pool."""
    import multiprocessing

    path = _store(tmp_path)
    durable.sync_chunks(path, [("a", (1, 1)), ("b", (1, 1))])        # the parent's pool exists
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_sync_in_child, args=(path, out))
    child.start()
    child.join(timeout=30)
    assert child.exitcode == 0, "the child hung or failed syncing"
    assert out.get(timeout=5) is True


def test_known_directories_are_not_synced_again_unless_a_new_one_below_them_appeared(tmp_path, monkeypatch):
    root = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    arr = root.create_array("a", shape=(4, 4, 3), chunks=(2, 2, 3), dtype="f4")
    arr[...] = np.ones((4, 4, 3), dtype="f4")
    path = tmp_path / "s.zarr"
    synced = []
    real = durable.fsync_path
    monkeypatch.setattr(durable, "fsync_path", lambda p: (synced.append(str(p)), real(p)))
    known: set = set()

    def sync(coords):
        synced.clear()
        durable.sync_chunks(path, [("a", coords)], known_dirs=known)
        return sorted(p[len(str(path)) + 1:] for p in synced)

    # the first chunk: its file and every directory up to the array's, as without known_dirs
    assert sync((0, 0, 0)) == sorted(["a/c/0/0/0", "a/c/0/0", "a/c/0", "a/c", "a"])
    # again: the file and the directory it is renamed into; nothing above changed
    assert sync((0, 0, 0)) == ["a/c/0/0", "a/c/0/0/0"]
    # a neighbour in the same row: its own new directory a/c/0/1 gained a/c/0 an entry
    assert sync((0, 1, 0)) == ["a/c/0", "a/c/0/1", "a/c/0/1/0"]
    # a new row: a/c/1 is new, so a/c changed; the array's folder did not
    assert sync((1, 0, 0)) == ["a/c", "a/c/1", "a/c/1/0", "a/c/1/0/0"]
    # a failed file fsync adds nothing to what is known
    monkeypatch.setattr(durable, "fsync_path", lambda p: (_ for _ in ()).throw(OSError(errno.EIO, "io")))
    with pytest.raises(OSError):
        durable.sync_chunks(path, [("a", (1, 1, 0))], known_dirs=known)
    assert str(path / "a/c/1/1") not in known
