"""Where outputs may go, and write-then-rename: an error never leaves half an output or destroys an old one.

:func:`check_output_location` is the one rule for where any output may go (never an input, inside
one or holding one; never inside a Zarr store, nor into one as a folder of files);
:func:`check_output_path` adds what may be replaced there (never a store of another kind, never
a store holding files that are not its own); :func:`check_no_links` refuses writes into a store
with a symbolic link inside.

While a command writes ``out``, three names beside it belong to it::

    .OUT.partial-TOKEN          the new store or file being written
    .OUT.old-TOKEN              the old ``out``, for the moment between the two renames and its removal
    .OUT.staging-TOKEN.json     the marker: which process (host, pid, start time) owns the other two

A process killed while it holds them leaves them behind; the next staged write into the same
directory (:func:`clean_stale_staging`) removes what such dead owners left, and puts an old
``out`` back where the kill fell between the two renames.  Nothing without a marker, and
nothing whose owner still runs, is touched.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path

from .errors import OutputExistsError
from .integrity import consolidate
from .owner import owner_gone
from .owner import owner_record

__all__ = ["check_output_location", "check_output_path", "OutputPathError", "describe_existing", "enclosing_store",
           "foreign_files", "check_no_links", "staged_output", "clean_stale_staging"]

class OutputPathError(OutputExistsError):
    """An output path that would destroy an input, or a store of another kind (says which)."""


_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def describe_existing(path) -> str | None:
    """What lies at ``path``: a streaklab store kind (``"run"``, ``"cube"``, ...), ``"zarr"`` (a Zarr
    store of other software), ``"hdf5"``, ``"file"``, ``"directory"``, or None when nothing is there."""
    p = Path(path)
    if not p.exists():
        return None
    if p.is_file():
        with open(p, "rb") as f:
            return "hdf5" if f.read(8) == _HDF5_MAGIC else "file"
    meta = p / "zarr.json"
    if not meta.is_file():
        return "zarr" if (p / ".zgroup").exists() or (p / ".zarray").exists() else "directory"
    try:
        attrs = json.loads(meta.read_text()).get("attributes", {}) or {}
    except (OSError, ValueError):
        return "zarr"
    kind = attrs.get("streaklab_kind")
    return str(kind) if kind else "zarr"


_WHAT = {"run": "a streaklab run store (raw capture data)", "zarr": "a Zarr store of other software",
         "hdf5": "an HDF5 file", "file": "a file that is not HDF5", "directory": "a directory"}


def _what(found: str) -> str:
    return _WHAT.get(found, f"a streaklab {found!r} store")


def _store_inside(directory: Path) -> Path | None:
    """The first Zarr store found below ``directory`` (a directory holding ``zarr.json``), or None."""
    for dirpath, dirnames, filenames in os.walk(directory):
        if "zarr.json" in filenames or ".zgroup" in filenames or ".zarray" in filenames:
            return Path(dirpath)
    return None


_ZARR_METADATA = ("zarr.json", ".zgroup", ".zarray", ".zattrs", ".zmetadata")


def _is_store(p: Path) -> bool:
    return any((p / name).is_file() for name in _ZARR_METADATA[:3])


def enclosing_store(path) -> Path | None:
    """The nearest Zarr store strictly above ``path`` (a directory with ``zarr.json``, ``.zgroup`` or
    ``.zarray``, looked for up to the file system's root), or None."""
    for q in Path(path).resolve().parents:
        if _is_store(q):
            return q
    return None


# a chunk file below an array's directory: v3 keys (``c``, ``c/0/3``, ``c.0.3``), v2 keys (``0.3``, ``0/3``)
_CHUNK_KEY = re.compile(r"^(c([./]\d+)*|\d+([./]\d+)*)$")
# zarr-python's local store writes every file to ``NAME.<32 hex>.partial`` first, then renames it
_ZARR_TEMPORARY = re.compile(r"\.[0-9a-f]{32}\.partial$")


def foreign_files(store) -> list[Path]:
    """Files below a Zarr store that are not the store's own, sorted.

    The store's own files are its metadata documents (``zarr.json``, and the ``.z*`` ones of
    Zarr v2), the chunk files below each array's directory (named by their chunk keys) and the
    temporaries zarr-python leaves when killed (``*.<hex>.partial``).  Anything else (a figure,
    notes, another program's file) is foreign: replacing the store would delete it.
    """
    root = Path(store)
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        meta = d / "zarr.json"
        is_array = (d / ".zarray").is_file()
        if meta.is_file():
            try:
                is_array = json.loads(meta.read_text()).get("node_type") == "array"
            except (OSError, ValueError, AttributeError):     # damaged metadata: what lies below is unknown
                dirnames[:] = []
                continue
        if is_array:                                     # everything below is chunk files
            for sub, _, names in os.walk(d):
                for name in names:
                    rel = (Path(sub) / name).relative_to(d).as_posix()
                    if rel in _ZARR_METADATA:
                        continue
                    if not _CHUNK_KEY.match(_ZARR_TEMPORARY.sub("", rel)):
                        found.append(Path(sub) / name)
            dirnames[:] = []
            continue
        found += [d / name for name in filenames if name not in _ZARR_METADATA and not _ZARR_TEMPORARY.search(name)]
    return sorted(found)


def _overlap(p: Path, path, inputs) -> None:
    for q in inputs:
        q = Path(q).resolve()
        if p == q or p in q.parents or q in p.parents:
            where = "lies inside" if q in p.parents else "holds"
            raise OutputPathError(f"refusing to write to {path}: it {where} the input {q}; choose another path")


def check_output_location(path, *, inputs=(), within=None, folder: bool = False) -> None:
    """The one rule for where any command may write: the place itself, whatever is there now.

    Parameters
    ----------
    path : the output path (a store, a file, or with ``folder`` a folder that receives files).
    inputs : paths the command reads; an output equal to one of them, inside one (e.g.
        ``run.zarr/streaks``) or containing one is refused.
    within : a store the output is a part of by design (a cube's ``irf`` group), or None.
    folder : ``path`` is a folder the command writes files into (figures, reports): it may not
        be a Zarr store itself either.

    Raises
    ------
    OutputPathError
        The output would overlap an input, or lie inside a Zarr store (any store: a new store,
        figure or file inside one is not the store's own, and later readers warn about it or a
        replacement deletes it), or, with ``folder``, be a Zarr store.
    """
    p = Path(path).resolve()
    _overlap(p, path, inputs)
    outer = enclosing_store(p)
    if outer is not None and (within is None or Path(within).resolve() != outer):
        raise OutputPathError(f"refusing to write to {path}: it lies inside the Zarr store {outer}, "
                              f"{_what(describe_existing(outer))}; choose a path outside it")
    if folder and p.is_dir() and _is_store(p):
        raise OutputPathError(f"refusing to write files into {path}: it is {_what(describe_existing(p))}; "
                              f"give a folder of their own, outside any store")


def check_output_path(path, *, overwrite: bool = False, inputs=(), kind: str | None = None,
                      within=None, keep: bool = False) -> None:
    """The one rule for where a command may write a new store or file (nothing is removed here).

    Parameters
    ----------
    path : the output path; first checked by :func:`check_output_location` (never an input,
        inside one or holding one; never inside a Zarr store other than ``within``).
    overwrite : bool
        An existing, non-empty ``path`` is refused without it.
    inputs : paths the command reads (see :func:`check_output_location`), refused even with
        ``overwrite``.
    kind : what the command writes: a streaklab store kind (``"cube"``, ``"decomposition"``,
        ...) or ``"hdf5"``.  ``overwrite`` replaces only a store of that same kind (or plain
        files and directories that are no store and hold none); a store of another kind, above
        all a run store of raw data, or a directory holding any Zarr store, is refused: its owner
        removes it, streaklab never does.  Without ``kind`` any existing path may be replaced.
        Either way a store holding files that are not its own (:func:`foreign_files`, e.g.
        figures put there) is refused, naming them.
    within : see :func:`check_output_location`.
    keep : the existing store is written into, not replaced (resuming it): the check of the
        files that are not its own is left out, since none of them is deleted.

    Raises
    ------
    OutputPathError
        The output would overlap an input, lie inside a store, replace a store of another
        kind, or delete files that are not the store's.
    OutputExistsError
        ``path`` exists and ``overwrite`` is not given.
    """
    p = Path(path).resolve()
    check_output_location(path, inputs=inputs, within=within)
    if not p.exists() or (p.is_dir() and not any(p.iterdir())):
        return
    if not overwrite:
        raise OutputExistsError(f"{path} already exists; pass overwrite=True to replace it", path=path)
    if not keep and p.is_dir() and _is_store(p) and (kind is None or describe_existing(p) == kind):
        foreign = foreign_files(p)
        if foreign:
            names = ", ".join(str(f.relative_to(p)) for f in foreign[:5])
            more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
            raise OutputPathError(f"refusing to replace {path}: it holds files that are not the store's own "
                                  f"({names}{more}), which replacing it would delete; move them out first")
    if kind is None:
        return
    found = describe_existing(p)
    if found == "directory":                 # no store itself; but replacing it would delete any store inside
        inner = _store_inside(p)
        if inner is not None:
            raise OutputPathError(f"refusing to replace {path}: it holds {_what(describe_existing(inner))} at "
                                  f"{inner}; remove it yourself if you mean to, or choose another path")
        return
    if found == kind or found == "file":     # the same kind, or no store at all
        return
    raise OutputPathError(f"refusing to replace {path}: it is {_what(found)}, and --overwrite replaces only "
                          f"{'an HDF5 file' if kind == 'hdf5' else f'a {kind} store'}; remove it yourself if "
                          f"you mean to, or choose another path")


def check_no_links(store) -> None:
    """Refuse to write into a store holding a symbolic link anywhere below its root.

    Writes (resuming a run or a decomposition, repairing) go through the store's own paths;
    a link inside (``res.zarr/direct/c -> elsewhere``) would send them outside the store.
    The root itself may be a link: it is the path the user named.
    """
    root = Path(store)
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            q = Path(dirpath) / name
            if q.is_symlink():
                raise OutputPathError(f"{q} is a symbolic link inside the store {store} (to {os.readlink(q)}); "
                                      f"refusing to write through it: replace the link by the data, or copy the store")


_MARKER = re.compile(r"^\.(?P<name>.+)\.staging-(?P<token>[0-9a-f]{8})\.json$")


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        p.unlink()


def _names(out: Path, token: str) -> tuple[Path, Path, Path]:
    d = out.parent
    return (d / f".{out.name}.partial-{token}", d / f".{out.name}.old-{token}",
            d / f".{out.name}.staging-{token}.json")


def clean_stale_staging(directory) -> list[Path]:
    """Remove what killed streaklab writes left in ``directory``; returns the paths removed.

    Only names recorded by a marker (see the module docstring) whose owning process is gone.
    When the kill fell between the two renames (``out`` absent, the old one still beside it),
    the old ``out`` is put back instead of being removed.
    """
    removed = []
    d = Path(directory)
    try:
        markers = [p for p in d.iterdir() if _MARKER.match(p.name)]
    except OSError:
        return removed
    for marker in markers:
        m = _MARKER.match(marker.name)
        try:
            info = json.loads(marker.read_text())
        except (OSError, ValueError):
            continue
        if not owner_gone(info):
            continue
        out = d / m["name"]
        tmp, trash, _ = _names(out, m["token"])
        if trash.exists() and not out.exists() and not out.is_symlink():
            os.replace(trash, out)
        for p in (tmp, trash):
            if p.exists() or p.is_symlink():
                _remove(p)
                removed.append(p)
        marker.unlink(missing_ok=True)
    return removed


@contextmanager
def staged_output(out, *, overwrite: bool = False, inputs=(), kind: str | None = None, within=None):
    """Yield a temporary path beside ``out``; on success move it to ``out``.

    ``out`` is checked first by :func:`check_output_path` (an existing
    non-empty path needs ``overwrite``; never an input; never inside a store other than
    ``within``; never a store of another ``kind``).  The
    caller writes a directory store or a file at the yielded path.  If the body raises,
    the temporary is removed and ``out`` is untouched; otherwise an existing ``out``
    is replaced only once the new one is complete.  What earlier, killed runs left beside
    ``out`` is cleaned first (:func:`clean_stale_staging`).
    """
    out = Path(out).resolve()
    check_output_path(out, overwrite=overwrite, inputs=inputs, kind=kind, within=within)
    clean_stale_staging(out.parent)
    token = uuid.uuid4().hex[:8]
    tmp, trash, marker = _names(out, token)
    marker.write_text(json.dumps(owner_record(out=out.name)))
    try:
        yield tmp
        if (tmp / "zarr.json").is_file():       # a complete Zarr store: index it for other readers
            consolidate(tmp)
        if out.exists():
            os.replace(out, trash)
            try:
                os.replace(tmp, out)
            except BaseException:
                os.replace(trash, out)
                raise
            _remove(trash)
        else:
            os.replace(tmp, out)
    finally:
        if tmp.exists() or tmp.is_symlink():
            _remove(tmp)
        marker.unlink(missing_ok=True)
