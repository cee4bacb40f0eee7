"""Durable writes to Zarr v3 directory stores: fsync a chunk file and the directories above it.

zarr-python 3.1's LocalStore writes each chunk to a temporary file and renames it into place,
so a chunk is never torn; but until the file and its directory entries are fsync'd, a power
cut can still lose a chunk that a later "done" flag already claims.  Stores that mark work as
done (the run store's lines, the result store's chunks) sync the data chunks first and the
flag after them.
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["fsync_path", "sync_chunk"]


def fsync_path(path) -> None:
    """fsync a file or directory; a missing path is skipped (zarr leaves all-fill chunks unwritten)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse fsync on directories; the data file was synced
        pass
    finally:
        os.close(fd)


def sync_chunk(store_path, name: str, coords: tuple[int, ...]) -> None:
    """fsync chunk ``coords`` of array ``name`` in the store at ``store_path``, then its directories.

    The chunk key is zarr v3's default encoding with "/" (``name/c/i/j/...``; ``name/c`` for a
    0-d array), which is what every streaklab store uses.
    """
    root = Path(store_path) / name
    chunk = root.joinpath("c", *map(str, coords)) if coords else root / "c"
    fsync_path(chunk)
    d = chunk.parent
    while True:
        fsync_path(d)
        if d == root:
            break
        d = d.parent
