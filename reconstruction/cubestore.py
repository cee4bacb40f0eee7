"""The calibrated-cube store: one Zarr v3 group holding a (y, x, t) cube.

Layout (every array has ``dimension_names``, so ``xarray.open_zarr`` opens it):

    cube   (y, x, t) float32   signal, chunked (by, bx, all of t)
    t      (t,)      float64   bin-centre times in ps (attrs: units = "ps")
    y      (y,)      float64   scan-line coordinate (attrs: units, e.g. "deg" of mirror angle or "pixel")
    x      (x,)      float64   slit coordinate (attrs: units = "pixel")

Group and ``cube`` attributes: ``streaklab_kind = "cube"``, ``time_bin_ps``, ``t0_ps`` (time of
bin 0), ``units`` of the signal, and ``provenance`` (a dict: what produced it, from what, with
which software version).  Other producers may add groups beside it (``truth`` for simulated
ground truth; ``irf``, the instrument response measured for this cube, in the layout of
:mod:`core.irfstore`: see :func:`write_cube_response` and :func:`read_cube_response`).  This module only reads and writes that layout; it knows nothing of solvers.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from core.errors import StreaklabError
from core.integrity import (consolidate, create_array, has_checksums, open_member, read_checked, scan_array,
                            scan_group)
from core.irf import InstrumentResponse
from core.irfstore import RESPONSE_KIND, read_response_group, write_response_group
from core.staging import check_output_path, staged_output

__all__ = ["CUBE_KIND", "IRF_GROUP", "NOISE_LAWS", "CubeStoreError", "Cube", "create_cube", "write_cube", "open_cube", "CubeCheck",
           "WrittenChunks", "written_chunks", "verify_cube", "write_cube_response", "read_cube_response"]

CUBE_KIND = "cube"
IRF_GROUP = "irf"
#: Values of a cube's ``noise_law`` attribute: "detector", every pixel one detector's read-out in
#: the same units (one read noise, one conversion gain).
NOISE_LAWS = ("detector",)


class CubeStoreError(StreaklabError, ValueError):
    """The path is not a usable cube store (says exactly why)."""


@dataclass(frozen=True)
class Cube:
    """An opened cube store.

    Attributes
    ----------
    path : str
    group : zarr.Group
    array : zarr.Array, shape (y, x, t)
    time_bin_ps, t0_ps : float
    attrs : dict   the cube array's attributes
    """

    path: str
    group: zarr.Group
    array: zarr.Array
    time_bin_ps: float
    t0_ps: float
    attrs: dict

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.array.shape)

    def time_axis_ps(self) -> np.ndarray:
        return self.t0_ps + self.time_bin_ps * np.arange(self.shape[2], dtype=np.float64)


def create_cube(path, shape, *, time_bin_ps: float, t0_ps: float, chunks=None, units: str = "counts",
                provenance: dict | None = None, y_coord=None, y_units: str = "pixel",
                overwrite: bool = False, dtype="float32", noise_law: str | None = None,
                long_name: str = "signal per pixel and time bin") -> Cube:
    """Create an empty cube store (filled with NaN) ready for region writes.

    Parameters
    ----------
    path : str or Path
        Directory store to create.
    shape : (ny, nx, nt)
    time_bin_ps, t0_ps : float
        Uniform time axis: bin i at ``t0_ps + i * time_bin_ps`` (ps).
    chunks : (by, bx) or (by, bx, nt), optional
        Pixel chunk size; the time axis is never split.  Default (min(ny, 16), min(nx, 64)).
    y_coord : array (ny,), optional
        Physical coordinate of each line (default: line index), in ``y_units``.
    noise_law : str, optional
        How the noise of the values scales, as an attribute ``noise_law``: ``"detector"`` where
        every pixel is one detector's read-out in the same units (one read noise and one
        conversion gain for all; no per-pixel gain correction such as a flat field).  Absent
        by default: nothing is claimed.
    long_name : str
        What the values are, the ``long_name`` attribute of ``cube`` (not of the group).
    """
    ny, nx, nt = (int(s) for s in shape)
    if min(ny, nx, nt) <= 0:
        raise CubeStoreError(f"cube shape must be positive, got {shape}")
    time_bin_ps = float(time_bin_ps)
    if not np.isfinite(time_bin_ps) or time_bin_ps <= 0:
        raise CubeStoreError(f"time_bin_ps must be positive, got {time_bin_ps}")
    if chunks is None:
        chunks = (min(ny, 16), min(nx, 64))
    by, bx = int(chunks[0]), int(chunks[1])
    if by <= 0 or bx <= 0:
        raise CubeStoreError(f"chunk sizes must be positive, got {chunks}")
    check_output_path(path, overwrite=overwrite)
    attrs = {
        "streaklab_kind": CUBE_KIND,
        "time_bin_ps": time_bin_ps,
        "t0_ps": float(t0_ps),
        "units": units,
        "provenance": dict(provenance or {}),
    }
    if noise_law is not None:
        if noise_law not in NOISE_LAWS:
            raise CubeStoreError(f"noise_law must be one of {', '.join(NOISE_LAWS)}, got {noise_law!r}")
        attrs["noise_law"] = noise_law
    g = zarr.open_group(str(path), mode="w")
    g.attrs.update(attrs)
    arr = create_array(g, "cube", shape=(ny, nx, nt), chunks=(min(by, ny), min(bx, nx), nt), dtype=dtype,
                       dimension_names=["y", "x", "t"], fill_value=np.nan,
                       attributes={**attrs, "long_name": str(long_name)})
    t = create_array(g, "t", shape=(nt,), dtype="float64", dimension_names=["t"],
                     attributes={"units": "ps", "long_name": "time of bin centre"})
    t[:] = float(t0_ps) + time_bin_ps * np.arange(nt)
    y = create_array(g, "y", shape=(ny,), dtype="float64", dimension_names=["y"],
                     attributes={"units": y_units, "long_name": "scan line"})
    y[:] = np.arange(ny, dtype=np.float64) if y_coord is None else np.asarray(y_coord, np.float64)
    x = create_array(g, "x", shape=(nx,), dtype="float64", dimension_names=["x"],
                     attributes={"units": "pixel", "long_name": "slit position"})
    x[:] = np.arange(nx, dtype=np.float64)
    return Cube(str(path), g, arr, time_bin_ps, float(t0_ps), dict(arr.attrs))


def write_cube(path, data, *, time_bin_ps: float, t0_ps: float | None = None, **kwargs) -> Cube:
    """Write a whole in-memory cube (y, x, t) into a new store.  ``t0_ps`` defaults to ``time_bin_ps``."""
    data = np.asarray(data)
    if data.ndim != 3:
        raise CubeStoreError(f"a cube must be 3-D (y, x, t); got an array of shape {data.shape}")
    cube = create_cube(path, data.shape, time_bin_ps=time_bin_ps,
                       t0_ps=time_bin_ps if t0_ps is None else t0_ps, **kwargs)
    cube.array[...] = data.astype(cube.array.dtype, copy=False)
    return cube


def open_cube(path, *, mode: str = "r") -> Cube:
    """Open and validate a cube store; raises :class:`CubeStoreError` naming what is wrong."""
    if not os.path.exists(path):
        raise CubeStoreError(f"{path}: no such file or directory")
    try:
        g = zarr.open_group(str(path), mode=mode, use_consolidated=False)
    except Exception as exc:  # zarr raises several types for "not a group"
        raise CubeStoreError(f"{path} is not a Zarr group: {exc}") from None
    arr = open_member(g, "cube", path, CubeStoreError)
    if arr is None:
        kind = g.attrs.get("streaklab_kind")
        hint = f" (it is a streaklab {kind!r} store)" if kind else ""
        raise CubeStoreError(f"{path} has no 'cube' array{hint}")
    if not isinstance(arr, zarr.Array):
        raise CubeStoreError(f"{path}/cube is not an array")
    if arr.ndim != 3:
        raise CubeStoreError(f"{path}/cube must be 3-D (y, x, t); it has shape {arr.shape}")
    dims = getattr(arr.metadata, "dimension_names", None)
    if dims is not None and tuple(dims) != ("y", "x", "t"):
        raise CubeStoreError(f"{path}/cube has dimensions {tuple(dims)}, expected ('y', 'x', 't')")
    attrs = dict(arr.attrs)
    if "time_bin_ps" not in attrs:
        raise CubeStoreError(f"{path}/cube lacks the 'time_bin_ps' attribute: the time axis is unknown")
    time_bin_ps = float(attrs["time_bin_ps"])
    if not np.isfinite(time_bin_ps) or time_bin_ps <= 0:
        raise CubeStoreError(f"{path}/cube has a non-positive time_bin_ps ({time_bin_ps})")
    t0_ps = float(attrs.get("t0_ps", time_bin_ps))
    return Cube(str(path), g, arr, time_bin_ps, t0_ps, attrs)


@dataclass(frozen=True)
class CubeCheck:
    """What :func:`verify_cube` found: ``checksums`` (False for stores of earlier releases) and
    ``damaged``, every damaged chunk of every array (``cube`` chunks are (y, x, t) pixel blocks)."""

    checksums: bool
    damaged: list

    @property
    def ok(self) -> bool:
        return not self.damaged


@dataclass(frozen=True)
class WrittenChunks:
    """Which chunks of a cube's ``cube`` array the store holds by its own account: a callable
    ``(iy, ix, it) -> bool`` for :func:`core.integrity.read_checked` and
    :func:`core.integrity.scan_array`.  Every chunk is written (zarr's fill value included),
    except that a chunk whose lines are all unfinished (``line_valid`` False: rows of NaN in a
    partial cube) may be absent.  Picklable: it travels with the cube's reader to dask's workers.
    """

    unfinished_row_chunks: frozenset = frozenset()

    def __call__(self, coords) -> bool:
        return int(coords[0]) not in self.unfinished_row_chunks


def written_chunks(cube: Cube) -> WrittenChunks:
    """The :class:`WrittenChunks` of an opened cube (reads its ``line_valid``, when it has one)."""
    valid = open_member(cube.group, "line_valid", cube.path, CubeStoreError)
    if valid is None:
        return WrittenChunks()
    rows = np.asarray(read_checked(valid, slice(None), store=cube.path), dtype=bool)
    by = int(cube.array.chunks[0])
    return WrittenChunks(frozenset(iy for iy in range(-(-rows.size // by)) if not rows[iy * by:(iy + 1) * by].any()))


def verify_cube(cube: Cube) -> CubeCheck:
    """Read every chunk of every array of a cube store (sub-groups such as ``truth`` included);
    a ``cube`` chunk of unfinished lines only may be absent (:func:`written_chunks`)."""
    damaged = list(scan_array(cube.path, cube.array, must_exist=written_chunks(cube)))
    damaged += scan_group(cube.path, cube.group, skip=(cube.array.path,))
    return CubeCheck(checksums=has_checksums(cube.array), damaged=damaged)


def _cube_path(cube) -> str:
    return cube.path if isinstance(cube, Cube) else str(cube)


def write_cube_response(cube, irf: InstrumentResponse, *, overwrite: bool = False) -> None:
    """Store an instrument response in the cube store's ``irf`` group.

    Parameters
    ----------
    cube : Cube or path
    irf : InstrumentResponse
    overwrite : bool
        Replace a response the cube already holds.

    The group is written beside its final place and renamed into it, so a cube holds either
    the whole new response, or the old one, or none.
    """
    path = _cube_path(cube)
    open_cube(path)
    target = Path(path) / IRF_GROUP
    if target.exists() and not overwrite:
        raise CubeStoreError(f"{path} already holds an instrument response (its '{IRF_GROUP}' group); "
                             f"pass overwrite=True (--overwrite) to replace it")
    with staged_output(target, overwrite=overwrite, kind=RESPONSE_KIND, within=path) as tmp:
        write_response_group(zarr.open_group(str(tmp), mode="w"), irf)
    consolidate(path)                   # the cube's consolidated metadata lists the new group


def read_cube_response(cube) -> InstrumentResponse | None:
    """The instrument response stored in a cube store, or None if it holds none."""
    path = _cube_path(cube)
    g = cube.group if isinstance(cube, Cube) else open_cube(path).group
    if IRF_GROUP not in g:
        return None
    sub = g[IRF_GROUP]
    if not isinstance(sub, zarr.Group):
        raise CubeStoreError(f"{path}/{IRF_GROUP} is not a group")
    return read_response_group(sub, where=f"{path}/{IRF_GROUP}")
