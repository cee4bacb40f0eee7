"""Durable writes to Zarr v3 directory stores: fsync a chunk file and the directories above it.

zarr-python 3.1's LocalStore writes each chunk to a temporary file and renames it into place,
so a chunk is never torn; but until the file and its directory entries are fsync'd, a power
cut can still lose a chunk that a later "done" flag already claims.  Stores that mark work as
done (the run store's lines, the result store's chunks) sync the data chunks first and the
flag after them.

A result chunk is some twenty arrays, each a file and three directories: about eighty fsyncs.
One after another each waits for its own journal commit (about 4 ms each on the ext4 disks
measured, 0.33 s per chunk, as long as solving a quarter of it); issued together the file
system commits them in a few shared transactions (80 files: 0.33 s -> 0.02 s).  So
:func:`sync_chunks` syncs a set of chunks at once, from a few threads, and returns when all of
them are on disk: the ordering that matters (every data chunk before its done flag) is kept by
the caller syncing the flag in a later call.  A caller that writes many chunks of one store
passes the set of directories it has synced (``known_dirs``): a directory whose entries did not
change is not synced again, which halves a result chunk's fsyncs after the first of each row.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

__all__ = ["fsync_path", "sync_chunk", "sync_chunks", "chunk_paths"]

SYNC_THREADS = 16   # fsyncs in flight at once: enough to fill a journal commit, cheap to start


def fsync_path(path) -> None:
    """fsync a file or directory; a missing path is skipped (zarr leaves all-fill chunks unwritten).

    An error syncing a file (EIO, ENOSPC: the data may not be on disk) is raised; one syncing a
    directory is not, since some file systems refuse fsync on directories.
    """
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        os.fsync(fd)
    except OSError:
        if not os.path.isdir(path):
            raise
    finally:
        os.close(fd)


def chunk_paths(store_path, name: str, coords: tuple[int, ...]) -> list[Path]:
    """The chunk file of ``coords`` in array ``name`` and the directories up to the array's, in that order.

    The chunk key is zarr v3's default encoding with "/" (``name/c/i/j/...``; ``name/c`` for a
    0-d array), which is what every streaklab store uses.
    """
    root = Path(store_path) / name
    chunk = root.joinpath("c", *map(str, coords)) if coords else root / "c"
    paths = [chunk]
    d = chunk.parent
    while True:
        paths.append(d)
        if d == root:
            break
        d = d.parent
    return paths


def sync_chunk(store_path, name: str, coords: tuple[int, ...]) -> None:
    """fsync chunk ``coords`` of array ``name`` in the store at ``store_path`` and its directories
    (:func:`sync_chunks` of the one chunk)."""
    sync_chunks(store_path, [(name, coords)])


def sync_chunks(store_path, chunks, *, known_dirs: set | None = None) -> None:
    """fsync several chunks and their directories together; returns once every one is synced.

    Parameters
    ----------
    store_path : str or Path
        The store's root folder.
    chunks : iterable of (name, coords)
        Array name and chunk coordinates, as for :func:`sync_chunk`.
    known_dirs : set of str, optional
        Directories whose own entry in their parent is already on disk, kept by the caller for
        one store across calls (and filled in here).  A chunk's file and the directory holding
        it are always synced (the write renames the file into it); a directory above is synced
        only where the one below it is not known, i.e. new since this caller first met it: a
        directory whose entries did not change needs no fsync.  A result chunk's 80 fsyncs
        become about 44 after the first chunk of each row.  None: every directory up to the
        array's, as before.

    The fsyncs run concurrently (up to :data:`SYNC_THREADS`), so the file system can commit
    them together; the order among them is not defined, which is why a done flag must be
    synced by a later call.  An error from any of them is raised here, and then no directory
    is added to ``known_dirs``.
    """
    seen: dict[str, Path] = {}
    learned: list[str] = []
    for name, coords in chunks:
        chain = chunk_paths(store_path, name, tuple(coords))
        keep = len(chain)
        if known_dirs is not None:
            keep = 2                                    # the file and the directory holding it
            while keep < len(chain) and str(chain[keep - 1]) not in known_dirs:
                keep += 1                               # that one is new: its parent gained an entry
            learned.extend(str(d) for d in chain[1:keep - 1])
        for p in chain[:keep]:
            seen.setdefault(str(p), p)
    paths = list(seen.values())
    if len(paths) <= 1:
        for p in paths:
            fsync_path(p)
    else:
        for _ in _pool().map(fsync_path, paths):
            pass
    if known_dirs is not None:
        known_dirs.update(learned)


_POOL: tuple[int, ThreadPoolExecutor] | None = None
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    """The process's fsync threads, started once (starting 16 threads per chunk cost more than
    the fsyncs); a forked child starts its own, since threads do not survive a fork."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] != os.getpid():
            _POOL = (os.getpid(), ThreadPoolExecutor(max_workers=SYNC_THREADS, thread_name_prefix="streaklab-fsync"))
        return _POOL[1]
