"""Cube stores to and from HDF5 files that follow the NeXus NXdata conventions.

File layout written by :func:`export_cube`::

    /                      @NX_class = "NXroot", @default = "entry", @creator
    /entry                 @NX_class = "NXentry", @default = "data"
    /entry/data            @NX_class = "NXdata", @signal = "cube", @axes = ["y", "x", "t"],
                           @y_indices = 0, @x_indices = 1, @t_indices = 2,
                           @time_bin_ps, @t0_ps, @provenance (JSON text)
    /entry/data/cube       (y, x, t) float32   @units, @long_name
    /entry/data/y, x, t    axis arrays          @units ("deg"/"pixel", "pixel", "ps"), @long_name
    /entry/data/<other>    every other top-level array of the cube store (line_valid, ...)
    /entry/<group>/...     @NX_class = "NXcollection": sub-groups of the store (e.g. ``truth``)

So any NeXus reader plots ``cube`` against its axes.  For a lossless round trip,
every dataset and group also carries ``@streaklab_zarr`` (JSON: the Zarr array's
or group's attributes, dimension names, chunks and fill value), which
:func:`import_cube` uses to rebuild the store exactly.  A plain NXdata file
written by other software (no ``@streaklab_zarr``) is imported too, provided its
signal is 3-D with a uniform time axis.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import zarr

from core import limits as L
from core.errors import StreaklabError
from core.integrity import create_array, read_checked
from core.staging import staged_output

from .cubestore import CUBE_KIND, CubeStoreError, create_cube, open_cube

__all__ = ["NexusError", "export_cube", "import_cube"]

META = "streaklab_zarr"
RESERVED = {"entry"}


class NexusError(StreaklabError, ValueError):
    """The HDF5 file is not a usable NeXus cube (says why)."""


def _json(obj) -> str:
    return json.dumps(obj, allow_nan=True, sort_keys=True)


def _fill_json(fill):
    if fill is None:
        return None
    v = np.asarray(fill).item()
    if isinstance(v, float) and not math.isfinite(v):
        return repr(v)  # 'nan', 'inf', '-inf'
    return v


def _fill_value(spec, dtype):
    if spec is None:
        return None
    if isinstance(spec, str):
        return float(spec)
    return np.asarray(spec, dtype=dtype).item()


def _simple_attr(value):
    """Native HDF5 form of an attribute value, or None if it needs JSON."""
    if isinstance(value, (str, bool, int, float)):
        return value
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
        return np.array(value, dtype=h5py.string_dtype())
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                         for v in value):
        return np.asarray(value)
    return None


def _copy_array(arr: zarr.Array, parent: h5py.Group, name: str, store) -> None:
    if arr.dtype.kind not in "biuf":
        raise NexusError(f"array {arr.path!r} has dtype {arr.dtype}, which this exporter does not handle")
    kwargs = {}
    if arr.ndim and arr.size:
        kwargs = {"chunks": tuple(min(c, s) for c, s in zip(arr.chunks, arr.shape)), "compression": "gzip",
                  "compression_opts": 4, "shuffle": True}
    ds = parent.create_dataset(name, shape=arr.shape, dtype=arr.dtype, **kwargs)
    if arr.ndim == 0:
        ds[()] = read_checked(arr, (), store=store)
    elif arr.size:
        step = arr.chunks[0]
        for i in range(0, arr.shape[0], step):
            ds[i:i + step] = read_checked(arr, slice(i, i + step), store=store)
    attrs = dict(arr.attrs)
    for k, v in attrs.items():
        native = _simple_attr(v)
        if native is not None:
            ds.attrs[k] = native
    dims = getattr(arr.metadata, "dimension_names", None)
    ds.attrs[META] = _json({"attributes": attrs, "dimension_names": None if dims is None else list(dims),
                            "chunks": list(arr.chunks), "fill_value": _fill_json(arr.metadata.fill_value)})


def _copy_group_contents(g: zarr.Group, h: h5py.Group, *, store, skip=(),
                         groups_into: h5py.Group | None = None) -> None:
    """Copy ``g``'s arrays into ``h`` and its sub-groups (as NXcollection) into ``groups_into`` (default ``h``)."""
    for name, arr in sorted(g.arrays()):
        if name not in skip:
            _copy_array(arr, h, name, store)
    for name, sub in sorted(g.groups()):
        hs = (h if groups_into is None else groups_into).create_group(name)
        hs.attrs["NX_class"] = "NXcollection"
        hs.attrs[META] = _json({"attributes": dict(sub.attrs)})
        _copy_group_contents(sub, hs, store=store)


def export_cube(cube_path, out_path, *, overwrite: bool = False) -> Path:
    """Write a cube store as a NeXus/HDF5 file.

    Parameters
    ----------
    cube_path : path of a cube store (validated with :func:`reconstruction.cubestore.open_cube`).
    out_path : path of the ``.h5`` file to write.
    overwrite : replace an existing file (only once the new one is complete).

    Returns
    -------
    Path of the written file.
    """
    from core.provenance import __version__

    cube = open_cube(cube_path)
    g = cube.group
    clash = sorted(n for n, _ in g.groups() if n in RESERVED | {"data"})
    if clash:
        raise NexusError(f"{cube_path}: a sub-group named {clash[0]!r} collides with the NeXus layout")
    out = Path(out_path)
    with staged_output(out, overwrite=overwrite, inputs=[cube_path], kind="hdf5") as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["NX_class"] = "NXroot"
            f.attrs["default"] = "entry"
            f.attrs["creator"] = f"streaklab {__version__}"
            f.attrs["HDF5_Version"] = h5py.version.hdf5_version
            entry = f.create_group("entry")
            entry.attrs["NX_class"] = "NXentry"
            entry.attrs["default"] = "data"
            data = entry.create_group("data")
            root_attrs = dict(g.attrs)
            data.attrs["NX_class"] = "NXdata"
            data.attrs["signal"] = "cube"
            data.attrs["axes"] = np.array(["y", "x", "t"], dtype=h5py.string_dtype())
            for i, ax in enumerate(("y", "x", "t")):
                data.attrs[f"{ax}_indices"] = np.int32(i)
            data.attrs["time_bin_ps"] = cube.time_bin_ps
            data.attrs["t0_ps"] = cube.t0_ps
            data.attrs["provenance"] = _json(root_attrs.get("provenance", cube.attrs.get("provenance", {})))
            data.attrs[META] = _json({"attributes": root_attrs})
            _copy_group_contents(g, data, store=cube_path, groups_into=entry)
    return out


def _find_nxdata(f: h5py.File, path) -> tuple[h5py.Group, h5py.Group]:
    def cls(obj):
        v = obj.attrs.get("NX_class")
        return v.decode() if isinstance(v, bytes) else v

    entries = [f[k] for k in f if isinstance(f[k], h5py.Group) and cls(f[k]) == "NXentry"]
    if not entries:
        raise NexusError(f"{path}: no NXentry group (NX_class='NXentry'); not a NeXus file")
    default = f.attrs.get("default")
    default = default.decode() if isinstance(default, bytes) else default
    entry = f[default] if default and default in f and f[default] in entries else entries[0]
    datas = [entry[k] for k in entry if isinstance(entry[k], h5py.Group) and cls(entry[k]) == "NXdata"]
    if not datas:
        raise NexusError(f"{path}: {entry.name} holds no NXdata group")
    d_default = entry.attrs.get("default")
    d_default = d_default.decode() if isinstance(d_default, bytes) else d_default
    data = entry[d_default] if d_default and d_default in entry and entry[d_default] in datas else datas[0]
    return entry, data


def _meta(obj) -> dict:
    """``obj``'s @streaklab_zarr attribute as a dict, or a NexusError naming the object."""
    text = obj.attrs[META]
    try:
        meta = json.loads(text.decode() if isinstance(text, bytes) else text)
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError, RecursionError) as exc:
        raise NexusError(f"{obj.file.filename}: {obj.name}@{META} is not valid JSON ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else ''}); the file is damaged") from None
    if not isinstance(meta, dict):
        raise NexusError(f"{obj.file.filename}: {obj.name}@{META} must be a JSON object; the file is damaged")
    return meta


def _restore_array(ds: h5py.Dataset, g: zarr.Group, name: str) -> None:
    meta = _meta(ds)
    shape = ds.shape
    chunks = tuple(meta["chunks"]) if shape else None
    kwargs = {"chunks": chunks} if chunks else {}
    arr = create_array(g, name, shape=shape, dtype=ds.dtype, fill_value=_fill_value(meta["fill_value"], ds.dtype),
                       dimension_names=meta["dimension_names"], attributes=meta["attributes"], **kwargs)
    if not shape:
        arr[...] = ds[()]
    elif ds.size:
        step = chunks[0]
        for i in range(0, shape[0], step):
            arr[i:i + step] = ds[i:i + step]


def _restore_group(h: h5py.Group, g: zarr.Group, *, skip=()) -> None:
    for name in sorted(h):
        if name in skip:
            continue
        obj = h[name]
        if isinstance(obj, h5py.Dataset):
            if META not in obj.attrs:
                raise NexusError(f"{obj.name} lacks @{META}; the file was changed after export")
            _restore_array(obj, g, name)
        else:
            meta = _meta(obj) if META in obj.attrs else {}
            sub = g.create_group(name, attributes=meta.get("attributes", {}))
            _restore_group(obj, sub)


def _import_foreign(data: h5py.Group, tmp: Path, path) -> None:
    """Plain NXdata from other software: signal (y, x, t) with axis arrays; t must be uniform."""
    signal = data.attrs.get("signal")
    signal = signal.decode() if isinstance(signal, bytes) else signal
    if not signal or signal not in data:
        raise NexusError(f"{path}: {data.name} has no @signal naming a dataset")
    sig = data[signal]
    if sig.ndim != 3:
        raise NexusError(f"{path}: signal {sig.name} must be 3-D (y, x, t); it has shape {sig.shape}")
    axes = [a.decode() if isinstance(a, bytes) else str(a) for a in np.atleast_1d(data.attrs.get("axes", []))]
    if len(axes) != 3 or any(a not in data for a in axes):
        raise NexusError(f"{path}: {data.name}@axes must name three axis datasets, got {axes}")
    t = np.asarray(data[axes[2]][...], dtype=np.float64)
    if t.shape != (sig.shape[2],) or t.size < 2 or not np.allclose(np.diff(t), t[1] - t[0], rtol=1e-6) \
            or t[1] <= t[0]:
        raise NexusError(f"{path}: the time axis {axes[2]!r} must be uniform and increasing to import as a cube")
    units = data[axes[2]].attrs.get("units", "ps")
    units = units.decode() if isinstance(units, bytes) else units
    if units != "ps":
        raise NexusError(f"{path}: time axis units must be 'ps', got {units!r}")
    yu = data[axes[0]].attrs.get("units", "pixel")
    yu = yu.decode() if isinstance(yu, bytes) else yu
    cube = create_cube(tmp, sig.shape, time_bin_ps=float(t[1] - t[0]), t0_ps=float(t[0]),
                       provenance={"imported_from": str(Path(path).resolve())}, y_coord=data[axes[0]][...],
                       y_units=str(yu))
    step = cube.array.chunks[0]
    for i in range(0, sig.shape[0], step):
        cube.array[i:i + step] = sig[i:i + step]


def _check_sizes(h5_path, f: h5py.File, entry: h5py.Group, data: h5py.Group, out_path) -> None:
    """Every size the file declares, against the documented limits, before anything is written.

    An HDF5 file may declare datasets far larger than itself (unwritten chunks read as the fill
    value), so the declared shapes are what the import would write.
    """
    if META in data.attrs:
        datasets = []
        entry.visititems(lambda name, obj: datasets.append(obj) if isinstance(obj, h5py.Dataset) else None)
        signal = data.get("cube")
        chunk_rows = {}
        for ds in datasets:
            meta = _meta(ds) if META in ds.attrs else {}
            chunks = meta.get("chunks") if ds.shape else []
            if ds.shape and (not isinstance(chunks, list) or len(chunks) != ds.ndim
                             or not all(isinstance(c, int) and c > 0 for c in chunks)):
                raise NexusError(f"{h5_path}: {ds.name}@{META} chunks must be {ds.ndim} positive integers, "
                                 f"got {chunks!r}")
            chunk_rows[ds.name] = min(chunks[0], ds.shape[0]) if ds.shape else 1
    else:
        signal_name = data.attrs.get("signal")
        signal_name = signal_name.decode() if isinstance(signal_name, bytes) else signal_name
        signal = data.get(signal_name) if signal_name else None
        if not isinstance(signal, h5py.Dataset):
            return  # _import_foreign names the problem
        datasets = [signal]
        chunk_rows = {signal.name: min(16, signal.shape[0]) if signal.shape else 1}
    try:
        if isinstance(signal, h5py.Dataset) and signal.ndim == 3:
            L.check_count(f"{signal.name} (t)", int(signal.shape[2]), L.MAX_TIME_BINS, "time bins")
        total = 0
        for ds in datasets:
            itemsize = max(ds.dtype.itemsize, 4)
            row_bytes = int(np.prod(ds.shape[1:], dtype=np.float64)) * (ds.dtype.itemsize + itemsize)
            L.check_memory(ds.name, chunk_rows[ds.name] * row_bytes, L.MAX_CHUNK_BYTES,
                           what=f"to copy {chunk_rows[ds.name]} rows of {ds.shape} at a time (limits.MAX_CHUNK_BYTES)")
            total += int(np.prod(ds.shape, dtype=np.float64)) * itemsize
        key = signal.name if isinstance(signal, h5py.Dataset) else data.name
        L.check_disk(key, total, L.MAX_CUBE_BYTES, Path(out_path).parent,
                     what=f"to import {'it' if len(datasets) == 1 else f'it and {len(datasets) - 1} more arrays'} "
                          f"(limits.MAX_CUBE_BYTES)")
    except L.LimitError as exc:
        raise NexusError(f"{h5_path}: {exc}") from None


def import_cube(h5_path, out_path, *, overwrite: bool = False) -> Path:
    """Rebuild a cube store from a NeXus/HDF5 file (see :func:`export_cube`).

    Returns
    -------
    Path of the written cube store (validated by :func:`open_cube`).
    """
    p = Path(h5_path)
    if not p.exists():
        raise NexusError(f"{h5_path}: no such file")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise NexusError(f"{h5_path} is not an HDF5 file: {exc}") from None
    with f, staged_output(out_path, overwrite=overwrite, inputs=[h5_path], kind=CUBE_KIND) as tmp:
        entry, data = _find_nxdata(f, h5_path)
        _check_sizes(h5_path, f, entry, data, out_path)   # before anything is written at tmp
        if META in data.attrs:
            meta = _meta(data)
            g = zarr.open_group(str(tmp), mode="w", attributes=meta.get("attributes", {}))
            _restore_group(data, g)
            _restore_group(entry, g, skip={data.name.rsplit("/", 1)[-1]})
        else:
            _import_foreign(data, tmp, h5_path)
        try:
            open_cube(tmp)
        except CubeStoreError as exc:
            raise NexusError(f"{h5_path}: imported data is not a valid cube: {exc}") from None
    return Path(out_path)
