"""Checksummed Zarr arrays, and finding damaged chunks in them.

Every array streaklab writes is created through :func:`create_array`: its codec chain ends in
zarr 3's ``crc32c`` codec (a checksum of the compressed chunk, checked on every read), and it
writes chunks even when they hold only the fill value, so that a chunk file that is absent where
the store says data was written means damage, never "all fill".  Writers that reopen an array
use :func:`writable` for the same reason.

Reads that meet a damaged chunk raise :class:`DataIntegrityError`, one line naming the store,
the array and the chunk (:func:`read_checked`, :class:`CheckedReader` for dask).
:func:`check_chunk` and :func:`scan_array` are the chunk walk shared by the ``verify``
functions of every store kind.  Arrays written by earlier releases have no checksum
(:func:`has_checksums`); for them only undecodable chunks can be found.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from .errors import StreaklabError

__all__ = ["DataIntegrityError", "ChunkDamage", "create_array", "writable", "write_regions", "has_checksums",
           "chunk_file",
           "chunk_region", "chunk_grid", "consolidate", "check_chunk", "scan_array", "scan_group", "read_checked", "CheckedReader",
           "missing_chunks", "require_chunks", "open_member"]

_WRITE_ALL = {"write_empty_chunks": True}


class DataIntegrityError(StreaklabError, ValueError):
    """A chunk of a store is missing or fails its checksum (names the store, array and chunk)."""


@dataclass(frozen=True)
class ChunkDamage:
    """One damaged chunk: ``array`` (path in the store), chunk ``coords``, ``problem`` (a phrase)."""

    array: str
    coords: tuple
    problem: str

    def __str__(self) -> str:
        return f"{self.array} chunk {_coords(self.coords)}: {self.problem}"


def _coords(coords) -> str:
    return "(" + ", ".join(str(int(c)) for c in coords) + ")" if coords else "()"


def create_array(group: zarr.Group, name: str, *, zstd_level: int = 0, **kwargs) -> zarr.Array:
    """``group.create_array`` with zstd + crc32c and every written chunk stored.

    ``zstd_level``: 0 is zstd's default (3); 1 for large arrays written in a hot loop whose data
    compress no better at 3 (a result store's float32 components: the same ratios, 1.07-51x,
    in two thirds of the time)."""
    kwargs.setdefault("compressors", (ZstdCodec(level=int(zstd_level)), Crc32cCodec()))
    kwargs.setdefault("config", dict(_WRITE_ALL))
    return group.create_array(name, **kwargs)


def writable(arr: zarr.Array) -> zarr.Array:
    """The same array, writing chunks that hold only the fill value too."""
    return arr.with_config(dict(_WRITE_ALL))


def write_regions(writes) -> None:
    """Write several regions of several arrays together; returns once every one is written.

    Parameters
    ----------
    writes : iterable of (zarr.Array, selection, numpy array)
        Each value is written as ``arr[selection] = value`` would write it, with the array's own
        configuration (pass :func:`writable` arrays to store chunks holding only the fill value).

    One call into zarr's I/O loop for all of them instead of one per array: each call hands the
    work to zarr's loop thread and waits for it, and while other threads run Python that
    hand-over waits for the interpreter lock (about 2 ms a call on a busy 2-core machine).  The
    order among the writes is not defined; an error from any of them is raised here, after all
    have finished.  This is the batching zarr documents ``Array.async_array`` for, with the sync
    bridge of zarr itself (``zarr.core.sync.sync``); a zarr without either (``async_array`` became
    public late in the 3.1 series; the bridge is internal) gets the writes one by one.
    """
    import asyncio

    jobs = list(writes)
    try:
        from zarr.core.sync import sync
    except ImportError:
        sync = None
    if sync is None or not all(hasattr(arr, "async_array") for arr, _, _ in jobs):
        for arr, sel, value in jobs:
            arr[sel] = value
        return

    async def _all():
        done = await asyncio.gather(*(arr.async_array.setitem(sel, value) for arr, sel, value in jobs),
                                    return_exceptions=True)
        for outcome in done:
            if isinstance(outcome, BaseException):
                raise outcome

    sync(_all())


def consolidate(store_path) -> None:
    """Write the store's consolidated metadata (every array's metadata in the root ``zarr.json``), so
    ``xarray.open_zarr(path)`` opens it in one read without a warning.  streaklab itself never
    relies on it (it opens with ``use_consolidated=False``); array metadata never changes after a
    store is created, and group attributes live in the root document itself, so it stays correct
    while runs resume."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # "not part of the Zarr 3 specification yet": known
        zarr.consolidate_metadata(str(store_path))


def has_checksums(arr: zarr.Array) -> bool:
    return any(isinstance(c, Crc32cCodec) for c in arr.metadata.codecs)


def chunk_file(store_path, arr: zarr.Array, coords) -> Path:
    """Path of chunk ``coords`` of ``arr`` in the directory store at ``store_path``."""
    return Path(store_path).joinpath(*arr.path.split("/"), *arr.metadata.encode_chunk_key(tuple(coords)).split("/"))


def chunk_grid(arr: zarr.Array) -> tuple[int, ...]:
    return tuple(-(-s // c) for s, c in zip(arr.shape, arr.chunks))


def chunk_region(arr: zarr.Array, coords) -> tuple[slice, ...]:
    return tuple(slice(i * c, min(s, (i + 1) * c)) for i, c, s in zip(coords, arr.chunks, arr.shape))


def check_chunk(store_path, arr: zarr.Array, coords, *, must_exist: bool) -> str | None:
    """None if chunk ``coords`` is sound, else the problem ("missing", "fails its checksum", ...).

    An absent chunk is a problem only when ``must_exist`` (the store says it was written) and
    the array is checksummed (earlier releases skipped chunks holding only the fill value).
    """
    if arr.size == 0:
        return None
    if not chunk_file(store_path, arr, coords).is_file():
        return "missing" if must_exist and has_checksums(arr) else None
    try:
        arr[chunk_region(arr, coords)]
    except Exception as exc:  # noqa: BLE001 - any failure to decode is damage
        return _problem(exc)
    return None


def _problem(exc: BaseException) -> str:
    text = str(exc)
    if "checksum" in text.lower():
        return "fails its checksum (the bytes on disk changed)"
    return f"cannot be decoded ({type(exc).__name__}: {text.splitlines()[0] if text else ''})"


def scan_array(store_path, arr: zarr.Array, chunks: Iterable[tuple] | None = None, *,
               must_exist=lambda coords: True) -> Iterator[ChunkDamage]:
    """Check the given chunks of ``arr`` (default all); yield a :class:`ChunkDamage` for each bad one."""
    if chunks is None:
        chunks = np.ndindex(*chunk_grid(arr)) if arr.ndim else [()]
    for coords in chunks:
        problem = check_chunk(store_path, arr, tuple(coords), must_exist=must_exist(tuple(coords)))
        if problem:
            yield ChunkDamage(arr.path, tuple(int(c) for c in coords), problem)


def scan_group(store_path, group: zarr.Group, *, skip=()) -> Iterator[ChunkDamage]:
    """Check every chunk of every array in ``group`` and its sub-groups (all must exist), except ``skip``."""
    for name, node in sorted(group.members(max_depth=None), key=lambda m: m[0]):
        if isinstance(node, zarr.Array) and name not in skip:
            yield from scan_array(store_path, node)


def missing_chunks(store_path, arr: zarr.Array, chunks: Iterable[tuple]) -> list[tuple]:
    """The chunks among ``chunks`` whose files are absent (only a stat each; checksummed arrays only)."""
    if not has_checksums(arr) or arr.size == 0:
        return []
    return [tuple(c) for c in chunks if not chunk_file(store_path, arr, c).is_file()]


def require_chunks(store_path, arr: zarr.Array, chunks: Iterable[tuple]) -> None:
    """Raise :class:`DataIntegrityError` naming the first of ``chunks`` whose file is absent
    (:func:`missing_chunks`: a stat each), and how many are."""
    absent = missing_chunks(store_path, arr, chunks)
    if absent:
        more = f" ({len(absent)} chunks in all)" if len(absent) > 1 else ""
        raise DataIntegrityError(f"{store_path}: array {arr.path!r}, chunk {_coords(absent[0])} is missing{more}: its "
                                 f"file {chunk_file(store_path, arr, absent[0])} is gone; run 'streaklab verify "
                                 f"{store_path}' to list every damaged chunk and how to redo just those")


def _chunk_ranges(arr: zarr.Array, selection) -> list[range]:
    """Per dimension, the chunk indices a basic selection touches."""
    if not isinstance(selection, tuple):
        selection = (selection,)
    out = []
    for sel, c, s in zip(selection + (slice(None),) * (arr.ndim - len(selection)), arr.chunks, arr.shape):
        if isinstance(sel, slice):
            start, stop, _ = sel.indices(s)
            out.append(range(start // c, max(start, stop - 1) // c + 1))
        else:
            i = int(sel) % s // c if s else 0
            out.append(range(i, i + 1))
    return out


def _chunks_of(arr: zarr.Array, selection) -> str:
    """The chunk(s) a basic selection touches, for messages."""
    if not isinstance(selection, tuple):
        selection = (selection,)
    parts = []
    for dim, (sel, c, s) in enumerate(zip(selection + (slice(None),) * (arr.ndim - len(selection)),
                                          arr.chunks, arr.shape)):
        if isinstance(sel, slice):
            start, stop, _ = sel.indices(s)
            lo, hi = start // c, max(start, stop - 1) // c
            parts.append(str(lo) if lo == hi else f"{lo}..{hi}")
        else:
            parts.append(str(int(sel) % s // c if s else 0))
    return "(" + ", ".join(parts) + ")"


def read_checked(arr: zarr.Array, selection, *, store, expected=None) -> np.ndarray:
    """``arr[selection]``; a damaged chunk raises :class:`DataIntegrityError` naming it.

    ``expected`` (callable: chunk coords -> bool), when given, says which chunks the store holds
    by its own account: such a chunk whose file is absent (:func:`missing_chunks`) is damage
    too, where zarr itself would read the fill value.  A basic selection only.
    """
    if expected is not None:
        require_chunks(store, arr, [c for c in itertools.product(*_chunk_ranges(arr, selection)) if expected(c)])
    try:
        return arr[selection]
    except Exception as exc:  # noqa: BLE001
        if isinstance(exc, (KeyboardInterrupt, MemoryError)):
            raise
        raise DataIntegrityError(f"{store}: array {arr.path!r}, chunk {_chunks_of(arr, selection)} "
                                 f"{_problem(exc)}; run 'streaklab verify {store}' to list every damaged "
                                 f"chunk and how to redo just those") from None


class CheckedReader:
    """Array-like over a Zarr array for ``dask.array.from_array``: reads through :func:`read_checked`
    (``expected``: which chunks must be on disk, see there; it travels to dask's workers with
    the reader, so a worker that cannot see the store stops the run instead of reading fill
    values)."""

    def __init__(self, arr: zarr.Array, store: str, expected=None):
        self.arr, self.store, self.expected = arr, str(store), expected
        self.shape, self.dtype, self.ndim = arr.shape, arr.dtype, arr.ndim
        self.chunks = arr.chunks

    def __dask_tokenize__(self):
        return ("streaklab-checked", self.store, self.arr.path, self.shape, str(self.dtype))

    def __getitem__(self, selection):
        return read_checked(self.arr, selection, store=self.store, expected=self.expected)


def open_member(group: zarr.Group, name: str, store, error=ValueError):
    """``group[name]`` (None when absent); damaged metadata (a ``zarr.json`` that does not parse)
    raises ``error`` naming the array, instead of the JSON parser's or zarr's own exception."""
    try:
        return group[name] if name in group else None
    except Exception as exc:  # noqa: BLE001 - json.JSONDecodeError, zarr's metadata errors, ...
        if isinstance(exc, (KeyboardInterrupt, MemoryError)):
            raise
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise error(f"{store}/{name}: unreadable array metadata ({type(exc).__name__}: {first}); "
                    f"the store is damaged") from None
