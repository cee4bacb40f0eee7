"""The decomposition result store: one Zarr v3 group per decomposed cube.

Layout (every array has ``dimension_names``; ``xarray.open_zarr(path)`` opens it)::

    direct_delay_ps, direct_amplitude, direct_sigma_ps,          (y, x)     float64, NaN = absent
    sss_delay_ps, sss_amplitude, sss_alpha_per_ps, sss_sigma_ps  (y, x)     float64, NaN = absent
    ir_delay_ps, ir_amplitude, ir_sigma_ps                       (y, x, r)  float64, NaN = absent
    background (with the ``b`` family)                            (y, x)     float64, signal units
    <any further solver parameter, e.g. *_stderr>                (y, x) or (y, x, r)
    rms_residual   (y, x)        float64  sqrt(mean over t of residual**2), signal units
    flags          (y, x)        uint16   the solver's per-pixel quality flags (+ OUT_OF_RANGE, 256)
    valid          (y, x)        bool     the pixel's profile was finite and was decomposed
    done           (y, x)        bool     the pixel's chunk has been written completely
    direct, sss, residual  (y, x, t)     float32  rendered components (optional)
    ir                     (y, x, r, t)  float32  rendered inter-reflections r2, r3, ... (optional)
    t (t,) ps, y (y,), x (x,), r (r,)    coordinates (r: bounce number 2, 3, ... of slot r2, r3, ...)
    irf/response, irf/irf_t  (irf_t,)    float64  the instrument response the fits were made with
                                                  (optional: absent for the Gaussian PSF)

Every array is chunked on the same pixel grid ``(by, bx)`` (with all of ``t`` and ``r`` in one
chunk), so each pixel chunk of a computation owns exactly one Zarr chunk of every array: writers
of different chunks never touch the same file, and rewriting a chunk writes the same bytes to the
same files (idempotent).  ``done`` is written last, after every other array of the chunk, and the
local store replaces chunk files atomically, so after a crash ``done`` is true exactly for pixels
whose results are all on disk.

Group attributes: ``streaklab_kind = "decomposition"``, ``method``, ``options`` (every solver
option), ``components`` (families searched), ``n_ir`` (R), ``chunks``, ``write_components``,
``nan_policy``, ``param_keys``, ``software_version``, ``source`` (path, shape, attributes of the
decomposed cube), ``time_bin_ps``, ``t0_ps``, ``units`` (signal units).

The optional group ``irf`` holds the instrument response the solver used (after resampling onto
the bins and cropping), in the layout of :mod:`core.irfstore` (the same as a cube store's ``irf``
group: samples in 1/ps, sample times in ps, the response's attributes and provenance), so
anything that re-renders the fits from the parameters renders them with the same response
(:meth:`ResultStore.response`); ``xarray.open_zarr(path, group="irf")`` reads it without
streaklab.  Stores of the Gaussian PSF, and those written before the group existed, have none.

This module only reads and writes that layout; it knows nothing of solvers.
"""

# One module over 600 lines on purpose: the result store's layout, writer, reader and checks are one
# format; kept together, a change to the layout touches one file.
from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

from core.durable import sync_chunk, sync_chunks
from core.errors import OutputExistsError, StreaklabError
from core.integrity import (ChunkDamage, DataIntegrityError, create_array, has_checksums, missing_chunks,
                            open_member, read_checked, scan_array, scan_group, writable, write_regions)
from core.irf import InstrumentResponse, ResponseError
from core.irfstore import read_response_group, samples_sha256, write_response_group
from core.staging import OutputPathError, check_no_links, check_output_path, staged_output

__all__ = [
    "RESULT_KIND",
    "RESPONSE_GROUP",
    "OUT_OF_RANGE",
    "OUT_OF_RANGE_HELP",
    "FORMAT_VERSION",
    "CORE_MAP_KEYS",
    "CORE_IR_KEYS",
    "COMPONENT_NAMES",
    "ResultStoreError",
    "long_name_for",
    "ResultStore",
    "ChunkWriter",
    "create_result_store",
    "open_result_store",
    "prepare_output_path",
]

RESULT_KIND = "decomposition"
#: The store's own bit in ``flags``, above the solver's eight: a rendered component or the residual of
#: the pixel exceeds the float32 range of the component arrays; those values are stored as NaN (the
#: float64 parameters are exact).
OUT_OF_RANGE = 256
#: one line for a user about :data:`OUT_OF_RANGE` (as :data:`decomposition.flags.FLAG_HELP` for the solver's)
OUT_OF_RANGE_HELP = ("a rendered component or the residual exceeded the float32 range and is stored as NaN; "
                     "the fitted parameters (float64) are exact: use them, or scale the input down")
FORMAT_VERSION = 1
#: the group that holds the instrument response of the fits (absent: the Gaussian PSF)
RESPONSE_GROUP = "irf"
CORE_MAP_KEYS = ("direct_delay_ps", "direct_amplitude", "direct_sigma_ps",
                 "sss_delay_ps", "sss_amplitude", "sss_alpha_per_ps", "sss_sigma_ps")
CORE_IR_KEYS = ("ir_delay_ps", "ir_amplitude", "ir_sigma_ps")
COMPONENT_NAMES = ("direct", "sss", "ir", "residual")
_QUALITY = ("rms_residual", "flags", "valid")

_LONG_NAMES = {
    "direct_delay_ps": "direct reflection delay", "direct_amplitude": "direct reflection peak height",
    "direct_sigma_ps": "direct reflection PSF sigma", "sss_delay_ps": "subsurface scattering onset",
    "sss_amplitude": "subsurface scattering amplitude b", "sss_alpha_per_ps": "subsurface attenuation alpha",
    "sss_sigma_ps": "subsurface PSF sigma", "ir_delay_ps": "inter-reflection delay",
    "ir_amplitude": "inter-reflection peak height", "ir_sigma_ps": "inter-reflection PSF sigma",
    "background": "constant offset (background) per pixel",
    "rms_residual": "root-mean-square fit residual", "flags": "solver quality flags (bit field)",
    "valid": "profile finite and decomposed", "done": "chunk written completely",
    "direct": "direct component", "sss": "subsurface scattering component",
    "ir": "inter-reflection components", "residual": "measured minus fitted profile",
}


class ResultStoreError(StreaklabError, ValueError):
    """The path is not a usable result store, or a write does not fit it (says exactly why)."""


def long_name_for(key: str) -> str:
    """The ``long_name`` of a parameter or quality array of a result store (also used for the
    ``truth`` group of a simulated cube): e.g. "direct reflection delay"; ``<key>_stderr`` is
    "standard error of the ..."; a solver's own parameter without one is named by its key."""
    if key.endswith("_stderr"):
        return f"standard error of the {long_name_for(key[: -len('_stderr')])}"
    return _LONG_NAMES.get(key, key)


def _units_for(key: str, signal_units: str) -> str:
    base = key[: -len("_stderr")] if key.endswith("_stderr") else key
    if base.endswith("_per_ps"):
        return "1/ps"
    if base.endswith("_ps"):
        return "ps"
    if base.endswith("_amplitude") or base in ("rms_residual", "background") + COMPONENT_NAMES:
        return signal_units
    return "1"


def prepare_output_path(path, *, overwrite: bool = False, protect=(), resume: bool = False) -> None:
    """Check that a new result store may be written at ``path`` (nothing is removed here).

    The rule is :func:`core.staging.check_output_path`: an absent or empty path is
    fine; anything else needs ``overwrite`` and may then only be a result store (or no store at
    all); a path in ``protect`` (the input), inside it or containing it is always refused.
    With ``resume`` the store at ``path`` is to be continued, not replaced.
    """
    try:
        check_output_path(path, overwrite=overwrite or resume, inputs=protect, kind=RESULT_KIND, keep=resume)
    except OutputPathError as exc:
        raise ResultStoreError(str(exc)) from None
    except OutputExistsError:
        raise OutputExistsError(f"{path} already exists; pass --overwrite to replace it "
                                f"(or --resume to continue a run into it)") from None


@dataclass
class ResultCheck:
    """What :meth:`ResultStore.verify` found: ``checksums`` (False for stores of earlier releases),
    ``chunks`` (pixel chunk (iy, ix) -> list of ChunkDamage, for chunks marked done or whose
    ``done`` flags are damaged), ``other`` (damaged coordinate arrays and response arrays),
    ``chunks_done`` (pixel chunks wholly marked done, damaged or not) and ``n_chunks``."""

    checksums: bool
    chunks: dict
    other: list
    chunks_done: int = 0
    n_chunks: int = 0

    @property
    def complete(self) -> bool:
        """Every pixel chunk was computed (or its done flag is damaged, which counts as damage); damage aside."""
        return self.chunks_done + sum(1 for d in self.chunks.values()
                                      if any(x.array == "done" for x in d)) >= self.n_chunks

    @property
    def ok(self) -> bool:
        return not (self.chunks or self.other)


@dataclass
class ResultStore:
    """An opened result store.

    Attributes
    ----------
    path : str
    group : zarr.Group
    shape : (ny, nx, nt)
    chunks : (by, bx)    pixel chunk of every array
    n_ir : int           R, inter-reflection slots
    param_keys : tuple of str, names of the parameter arrays
    write_components : bool
    attrs : dict         group attributes
    """

    path: str
    group: zarr.Group
    shape: tuple
    chunks: tuple
    n_ir: int
    param_keys: tuple
    write_components: bool
    attrs: dict
    # name -> array opened for writing (see _arrays)
    _opened_arrays: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    # directories whose entries this object has synced (core.durable.sync_chunks' known_dirs)
    _synced_dirs: set = field(default_factory=set, init=False, repr=False, compare=False)

    # ----- chunk grid --------------------------------------------------------------------------
    @property
    def grid(self) -> tuple[int, int]:
        """Number of pixel chunks along y and x."""
        (ny, nx, _), (by, bx) = self.shape, self.chunks
        return (-(-ny // by), -(-nx // bx))

    def chunk_slices(self, iy: int, ix: int) -> tuple[slice, slice]:
        """The (y, x) region of chunk (iy, ix)."""
        gy, gx = self.grid
        if not (0 <= iy < gy and 0 <= ix < gx):
            raise ResultStoreError(f"chunk ({iy}, {ix}) is outside the {gy} x {gx} chunk grid")
        (ny, nx, _), (by, bx) = self.shape, self.chunks
        return slice(iy * by, min(ny, (iy + 1) * by)), slice(ix * bx, min(nx, (ix + 1) * bx))

    def done_mask(self) -> np.ndarray:
        """(ny, nx) bool: pixels whose chunk is completely written."""
        return np.asarray(read_checked(self.group["done"], slice(None), store=self.path), dtype=bool)

    # ----- integrity ---------------------------------------------------------------------------
    def pixel_arrays(self) -> list[str]:
        """Arrays chunked on the pixel grid (everything but the coordinates)."""
        names = list(self.param_keys) + list(_QUALITY) + ["done"]
        return names + (list(COMPONENT_NAMES) if self.write_components else [])

    def _chunk_coords(self, name: str, iy: int, ix: int) -> tuple:
        return (iy, ix) + (0,) * (self.group[name].ndim - 2)

    def absent_chunks(self) -> list[ChunkDamage]:
        """Chunk files missing where ``done`` says the chunk is written (a stat each)."""
        done = [(int(a), int(b)) for a, b in np.argwhere(self.done_chunks())]
        out = []
        for name in self.pixel_arrays():
            if name == "done":
                continue
            arr = self.group[name]
            out.extend(ChunkDamage(name, c, "missing")
                       for c in missing_chunks(self.path, arr, [self._chunk_coords(name, *ij) for ij in done]))
        return out

    def check_done_chunks_present(self) -> None:
        """Raise :class:`DataIntegrityError` naming the chunks marked done whose files are missing."""
        absent = self.absent_chunks()
        if not absent:
            return
        where = sorted({d.coords[:2] for d in absent})
        shown = ", ".join(f"({iy}, {ix})" for iy, ix in where[:10]) + (f", ... ({len(where)} in all)"
                                                                       if len(where) > 10 else "")
        raise DataIntegrityError(
            f"{self.path}: pixel chunk{'s' if len(where) > 1 else ''} {shown} {'are' if len(where) > 1 else 'is'} "
            f"marked done but {', '.join(sorted({d.array for d in absent}))} chunk files are missing; run "
            f"'streaklab verify {self.path} --mark-for-resume', then 'streaklab decompose ... --resume' to "
            f"recompute just those")

    def verify(self) -> "ResultCheck":
        """Read every chunk marked done; damage is reported per pixel chunk (see :class:`ResultCheck`)."""
        g, path = self.group, self.path
        gy, gx = self.grid
        chunks: dict[tuple, list] = {}
        done_arr = g["done"]
        done = []
        for ij in np.ndindex(gy, gx):
            bad = list(scan_array(path, done_arr, [ij], must_exist=lambda c: False))
            if bad:
                chunks.setdefault(ij, []).extend(bad)
            elif done_arr[self.chunk_slices(*ij)].all():
                done.append(ij)
        for name in self.pixel_arrays():
            if name == "done":
                continue
            arr = g[name]
            for d in scan_array(path, arr, [self._chunk_coords(name, *ij) for ij in done]):
                chunks.setdefault(d.coords[:2], []).append(d)
        other = [d for name in ("t", "y", "x", "r") for d in scan_array(path, g[name])]
        if self.has_response:
            other.extend(scan_group(path, g[RESPONSE_GROUP]))
        return ResultCheck(checksums=has_checksums(done_arr), chunks=dict(sorted(chunks.items())), other=other,
                           chunks_done=len(done), n_chunks=gy * gx)

    def mark_chunks_not_done(self, chunks) -> None:
        """Clear ``done`` over the given pixel chunks (durably) so ``decompose --resume`` recomputes them."""
        done = writable(self.group["done"])
        for iy, ix in chunks:
            ys, xs = self.chunk_slices(int(iy), int(ix))
            done[ys, xs] = np.zeros((ys.stop - ys.start, xs.stop - xs.start), dtype=bool)
            sync_chunk(self.path, "done", (int(iy), int(ix)))

    def done_chunks(self) -> np.ndarray:
        """(gy, gx) bool: chunks completely written."""
        done = self.done_mask()
        gy, gx = self.grid
        out = np.zeros((gy, gx), dtype=bool)
        for iy in range(gy):
            for ix in range(gx):
                ys, xs = self.chunk_slices(iy, ix)
                out[iy, ix] = bool(done[ys, xs].all())
        return out

    def remove_partials(self) -> int:
        """Delete chunk-file temporaries (``*.partial``) a killed writer left behind; returns how many."""
        n = 0
        for f in Path(self.path).rglob("*.partial"):
            f.unlink(missing_ok=True)
            n += 1
        return n

    def pending_chunks(self) -> list[tuple[int, int]]:
        """Chunk indices still to compute, in row-major order."""
        return [tuple(int(i) for i in ij) for ij in np.argwhere(~self.done_chunks())]

    # ----- writes ------------------------------------------------------------------------------
    def _arrays(self, names) -> dict:
        """name -> the array opened for writing (:func:`writable`), each opened once per store
        object (``group[name]`` reads and parses the array's metadata, which never changes after
        the store is created)."""
        cache = self._opened_arrays
        for k in names:
            if k not in cache:
                cache[k] = writable(self.group[k])
        return {k: cache[k] for k in names}

    def write_chunk(self, iy: int, ix: int, result: dict) -> None:
        """Write one chunk's results into its region, then mark it done.

        Parameters
        ----------
        iy, ix : int
            Chunk index on :attr:`grid`.
        result : dict
            ``params`` (dict: every key of :attr:`param_keys`, shape (by, bx) or (by, bx, R)),
            ``rms_residual`` (by, bx), ``flags`` (by, bx), ``valid`` (by, bx) and, when the
            store holds components, ``direct``, ``sss``, ``residual`` (by, bx, t) and
            ``ir`` (by, bx, R, t); (by, bx) is the chunk's actual size (smaller at the edges).
        """
        ys, xs = self.chunk_slices(iy, ix)
        region = (ys.stop - ys.start, xs.stop - xs.start)
        nt, r = self.shape[2], self.n_ir
        params = result["params"]
        missing = [k for k in self.param_keys if k not in params]
        extra = [k for k in params if k not in self.param_keys]
        if missing or extra:
            raise ResultStoreError(f"chunk ({iy}, {ix}) parameters do not match the store: "
                                   f"missing {missing}, not in the store {extra}")
        names = tuple(self.param_keys) + _QUALITY + (("direct", "sss", "residual", "ir") if self.write_components
                                                     else ()) + ("done",)
        g = self._arrays(names)
        writes = []
        for k in self.param_keys:
            trail = g[k].shape[2:]
            writes.append((k, params[k], region + trail))
        for k in _QUALITY:
            writes.append((k, result[k], region))
        if self.write_components:
            for k in ("direct", "sss", "residual"):
                writes.append((k, result[k], region + (nt,)))
            writes.append(("ir", result["ir"], region + (r, nt)))
        for k, value, shape in writes:
            value = np.asarray(value)
            if value.shape != shape:
                raise ResultStoreError(f"chunk ({iy}, {ix}): {k} has shape {value.shape}, the store expects {shape}")
        writes = self._fit_to_dtypes(writes, region, g)
        write_regions((g[k], (ys, xs), np.asarray(value).astype(g[k].dtype, copy=False)) for k, value, _ in writes)
        # durable before it is marked done: a power cut must not leave a chunk flagged done
        # whose data never reached the disk (resume would skip it)
        sync_chunks(self.path, [(k, (iy, ix) + (0,) * (len(shape) - 2)) for k, _, shape in writes],
                    known_dirs=self._synced_dirs)
        g["done"][ys, xs] = np.ones(region, dtype=bool)  # last: the chunk is complete on disk
        sync_chunks(self.path, [("done", (iy, ix))], known_dirs=self._synced_dirs)

    def _fit_to_dtypes(self, writes: list, region: tuple, arrays) -> list:
        """Values too large for their array's float dtype (float32 components) become NaN, and
        their pixels get :data:`OUT_OF_RANGE` in ``flags``: never an inf that looks like data.
        ``arrays``: name -> the opened zarr array."""
        g = arrays
        over = np.zeros(region, dtype=bool)
        fitted = []
        for k, value, shape in writes:
            dt = g[k].dtype
            value = np.asarray(value)
            if dt.kind == "f" and value.dtype.kind == "f" and value.dtype.itemsize > dt.itemsize:
                big = np.isfinite(value) & (np.abs(value) > np.finfo(dt).max)
                if big.any():
                    value = np.where(big, np.nan, value)
                    over |= big.reshape(region + (-1,)).any(axis=-1)
            fitted.append((k, value, shape))
        if over.any():
            if g["flags"].dtype.itemsize < 2:                  # a store of an earlier release
                raise ResultStoreError(f"{self.path}: results of {int(over.sum())} pixels do not fit the float32 "
                                       f"component arrays, and this store's uint8 flags cannot mark them; "
                                       f"decompose into a new store")
            fitted = [(k, (np.asarray(v).astype(np.uint16) | np.where(over, OUT_OF_RANGE, 0).astype(np.uint16))
                       if k == "flags" else v, s) for k, v, s in fitted]
        return fitted

    # ----- reads -------------------------------------------------------------------------------
    def params(self, ys=slice(None), xs=slice(None)) -> dict[str, np.ndarray]:
        """The parameter dict over a (y, x) region (default: everything)."""
        return {k: self.group[k][ys, xs] for k in self.param_keys}

    def time_axis_ps(self) -> np.ndarray:
        return np.asarray(self.group["t"][...], dtype=np.float64)

    @property
    def has_response(self) -> bool:
        """Whether the store holds the instrument response of its fits (group ``irf``)."""
        return RESPONSE_GROUP in self.group

    def response(self) -> InstrumentResponse | None:
        """The instrument response the fits were made with, or None (the Gaussian PSF, or a store
        written before result stores kept the response: ``attrs["irf"]`` then still describes it).

        Raises :class:`ResultStoreError` when the group is unreadable or its samples are not
        those whose sha256 the store recorded (``attrs["irf"]["samples_sha256"]``)."""
        if not self.has_response:
            return None
        where = f"{self.path}/{RESPONSE_GROUP}"
        sub = self.group[RESPONSE_GROUP]
        if not isinstance(sub, zarr.Group):
            raise ResultStoreError(f"{where} is not a group")
        try:
            irf = read_response_group(sub, where=where)
        except ResponseError as exc:
            raise ResultStoreError(str(exc)) from None
        recorded = dict(self.attrs.get("irf") or {}).get("samples_sha256")
        if recorded is not None and recorded != samples_sha256(irf):
            raise ResultStoreError(f"{where}: its samples are not the response the store recorded "
                                   f"(sha256 {samples_sha256(irf)[:12]}..., recorded {str(recorded)[:12]}...)")
        return irf


def create_result_store(path, *, shape, chunks, n_ir: int, time_bin_ps: float, t0_ps: float,
                        param_keys=None, ir_param_keys=(), write_components: bool = True,
                        signal_units: str = "counts", y_coord=None, y_units: str = "pixel",
                        attrs: dict | None = None, overwrite: bool = False, protect=(),
                        flag_names: dict | None = None, irf: InstrumentResponse | None = None) -> ResultStore:
    """Create an empty result store (parameters NaN, nothing done) ready for chunk writes.

    Parameters
    ----------
    path : str or Path
        Directory store to create; see :func:`prepare_output_path` for an existing path.
    shape : (ny, nx, nt)
        Shape of the decomposed cube.
    chunks : (by, bx)
        Pixel chunk of every array (the computation's chunk).
    n_ir : int
        R, number of inter-reflection slots kept per pixel.
    time_bin_ps, t0_ps : float
        Time axis of the cube (bin i at t0_ps + i * time_bin_ps, ps).
    param_keys : sequence of str, optional
        Names of per-pixel (y, x) parameter arrays; default :data:`CORE_MAP_KEYS`.
    ir_param_keys : sequence of str
        Names of per-slot (y, x, r) parameter arrays in addition to :data:`CORE_IR_KEYS`.
    write_components : bool
        Also create the component cubes (as big as the input each).
    attrs : dict, optional
        Extra group attributes (method, options, source, ...); JSON-serialisable.
    flag_names : dict bit -> name, optional
        The solver's flag table, written as the CF ``flag_masks`` / ``flag_meanings`` of ``flags``
        (with the store's own :data:`OUT_OF_RANGE` bit).
    irf : InstrumentResponse, optional
        The instrument response the fits are made with, kept in the group :data:`RESPONSE_GROUP`
        (see the module docstring); None for the Gaussian PSF.
    """
    if irf is not None and not isinstance(irf, InstrumentResponse):
        raise ResultStoreError(f"irf must be an InstrumentResponse or None, got {type(irf).__name__}")
    ny, nx, nt = (int(s) for s in shape)
    by, bx = (int(c) for c in chunks)
    n_ir = int(n_ir)
    if min(ny, nx, nt) <= 0 or by <= 0 or bx <= 0 or n_ir < 0:
        raise ResultStoreError(f"bad result store geometry: shape {shape}, chunks {chunks}, n_ir {n_ir}")
    by, bx = min(by, ny), min(bx, nx)
    map_keys = tuple(CORE_MAP_KEYS if param_keys is None else param_keys)
    ir_keys = tuple(CORE_IR_KEYS) + tuple(k for k in ir_param_keys if k not in CORE_IR_KEYS)
    all_keys = map_keys + ir_keys
    if len(set(all_keys)) != len(all_keys):
        raise ResultStoreError(f"duplicate parameter names in {all_keys}")
    reserved = set(_QUALITY) | set(COMPONENT_NAMES) | {"done", "t", "y", "x", "r"}
    if reserved & set(all_keys):
        raise ResultStoreError(f"parameter names clash with store arrays: {sorted(reserved & set(all_keys))}")
    prepare_output_path(path, overwrite=overwrite, protect=protect)
    # complete before it appears at ``path``
    with staged_output(path, overwrite=True, inputs=protect, kind=RESULT_KIND) as tmp:
        _write_skeleton(tmp, shape=(ny, nx, nt), chunks=(by, bx), n_ir=n_ir, time_bin_ps=time_bin_ps,
                        t0_ps=t0_ps, map_keys=map_keys, ir_keys=ir_keys, write_components=write_components,
                        signal_units=signal_units, y_coord=y_coord, y_units=y_units, attrs=attrs,
                        flag_names=flag_names)
        if irf is not None:
            write_response_group(zarr.open_group(str(tmp), mode="r+").create_group(RESPONSE_GROUP), irf)
    return open_result_store(path, mode="r+")


def _write_skeleton(path, *, shape, chunks, n_ir, time_bin_ps, t0_ps, map_keys, ir_keys, write_components,
                    signal_units, y_coord, y_units, attrs, flag_names):
    ny, nx, nt = shape
    by, bx = chunks
    all_keys = map_keys + ir_keys
    meta = {
        "streaklab_kind": RESULT_KIND,
        "format_version": FORMAT_VERSION,
        "time_bin_ps": float(time_bin_ps),
        "t0_ps": float(t0_ps),
        "units": signal_units,
        "n_ir": n_ir,
        "chunks": [by, bx],
        "write_components": bool(write_components),
        "param_keys": list(all_keys),
    }
    meta.update(attrs or {})
    g = zarr.open_group(str(path), mode="w")
    g.attrs.update(meta)

    def arr(name, shp, chk, dtype, dims, fill, units=None, zstd_level=0, **extra):
        a = {"long_name": long_name_for(name)}
        if units is not None:
            a["units"] = units
        a.update(extra)
        return create_array(g, name, shape=shp, chunks=chk, dtype=dtype, dimension_names=dims,
                            fill_value=fill, attributes=a, zstd_level=zstd_level)

    for k in map_keys:
        arr(k, (ny, nx), (by, bx), "float64", ["y", "x"], np.nan, _units_for(k, signal_units))
    for k in ir_keys:
        arr(k, (ny, nx, n_ir), (by, bx, max(n_ir, 1)), "float64", ["y", "x", "r"], np.nan,
            _units_for(k, signal_units))
    arr("rms_residual", (ny, nx), (by, bx), "float64", ["y", "x"], np.nan, signal_units)
    table = {**{int(b): str(n) for b, n in dict(flag_names or {}).items()}, OUT_OF_RANGE: "OUT_OF_RANGE"}
    arr("flags", (ny, nx), (by, bx), "uint16", ["y", "x"], 0, "1",
        flag_masks=sorted(table), flag_meanings=" ".join(table[b] for b in sorted(table)),
        comment="bit field; 0 = no flag. OUT_OF_RANGE is the store's own: a component did not fit float32 "
                "and is stored as NaN")
    arr("valid", (ny, nx), (by, bx), "bool", ["y", "x"], False, "1", flag_values=[0, 1],
        flag_meanings="not_decomposed decomposed",
        comment="False: the profile had NaN/inf samples (or was never computed); its results are NaN")
    arr("done", (ny, nx), (by, bx), "bool", ["y", "x"], False, "1", flag_values=[0, 1],
        flag_meanings="pending written",
        comment="True once every array of the pixel's chunk is on disk; --resume recomputes the rest")
    if write_components:
        # zstd level 1: these are nearly all of a chunk's bytes, and compress no better at 3
        for k in ("direct", "sss", "residual"):
            arr(k, (ny, nx, nt), (by, bx, nt), "float32", ["y", "x", "t"], np.nan, signal_units, zstd_level=1)
        arr("ir", (ny, nx, n_ir, nt), (by, bx, max(n_ir, 1), nt), "float32", ["y", "x", "r", "t"], np.nan,
            signal_units, zstd_level=1)
    t = arr("t", (nt,), (nt,), "float64", ["t"], np.nan, "ps")
    t.attrs["long_name"] = "time of bin centre"
    t[:] = float(t0_ps) + float(time_bin_ps) * np.arange(nt)
    y = arr("y", (ny,), (ny,), "float64", ["y"], np.nan, y_units)
    y.attrs["long_name"] = "scan line"
    y[:] = np.arange(ny, dtype=np.float64) if y_coord is None else np.asarray(y_coord, np.float64)
    x = arr("x", (nx,), (nx,), "float64", ["x"], np.nan, "pixel")
    x.attrs["long_name"] = "slit position"
    x[:] = np.arange(nx, dtype=np.float64)
    r = arr("r", (n_ir,), (max(n_ir, 1),), "int64", ["r"], 0, "1")
    r.attrs["long_name"] = "bounce number of the inter-reflection (2 = r2, 3 = r3, ...)"
    if n_ir:
        r[:] = np.arange(2, 2 + n_ir)


def _from_group(path: str, g: zarr.Group) -> ResultStore:
    a = dict(g.attrs)
    shape = (int(g["y"].shape[0]), int(g["x"].shape[0]), int(g["t"].shape[0]))
    return ResultStore(path=path, group=g, shape=shape, chunks=tuple(int(c) for c in a["chunks"]),
                       n_ir=int(a["n_ir"]), param_keys=tuple(a["param_keys"]),
                       write_components=bool(a["write_components"]), attrs=a)


def open_result_store(path, *, mode: str = "r", check_links: bool = True) -> ResultStore:
    """Open and validate a result store; raises :class:`ResultStoreError` naming what is wrong.

    ``mode`` is ``"r"`` (read only) or ``"r+"`` (chunk writes); ``r+`` refuses a store with a
    symbolic link inside (see :func:`core.staging.check_no_links`) unless
    ``check_links`` is False (the per-chunk writers of a run whose store was checked on opening).
    """
    if mode not in ("r", "r+"):
        raise ValueError(f"mode must be 'r' or 'r+', got {mode!r}")
    if not os.path.exists(path):
        raise ResultStoreError(f"{path}: no such file or directory")
    if mode == "r+" and check_links:
        try:
            check_no_links(path)
        except OutputPathError as exc:
            raise ResultStoreError(str(exc)) from None
    try:
        g = zarr.open_group(str(path), mode=mode, use_consolidated=False)
    except Exception as exc:  # zarr raises several types for "not a group"
        raise ResultStoreError(f"{path} is not a Zarr group: {exc}") from None
    kind = g.attrs.get("streaklab_kind")
    if kind != RESULT_KIND:
        what = f"a streaklab {kind!r} store" if kind else "not a streaklab store"
        raise ResultStoreError(f"{path} is not a decomposition result store ({what})")
    a = dict(g.attrs)
    version = a.get("format_version")
    if version != FORMAT_VERSION:
        raise ResultStoreError(f"{path} has result format version {version}; this streaklab reads {FORMAT_VERSION}")
    needed = list(a.get("param_keys", [])) + list(_QUALITY) + ["done", "t", "y", "x", "r"]
    if a.get("write_components"):
        needed += list(COMPONENT_NAMES)
    missing = [k for k in needed if open_member(g, k, path, ResultStoreError) is None]
    if missing:
        raise ResultStoreError(f"{path} is incomplete: arrays {missing} are missing")
    return _from_group(str(path), g)


@dataclass(frozen=True)
class ChunkWriter:
    """Picklable sink ``writer(iy, ix, result)`` that opens the store by path and writes one chunk.

    Safe to ship to worker processes: it pickles as its path alone.  The store it opens is kept
    for the writer's later chunks in the same process (opening and validating a store reads every
    array's metadata: about 30 ms, a quarter of a 1024-pixel chunk's write); threads share it.
    """

    path: str

    def __post_init__(self):
        object.__setattr__(self, "_opened", {})
        object.__setattr__(self, "_lock", threading.Lock())

    def __reduce__(self):
        return (ChunkWriter, (self.path,))

    def _store(self) -> ResultStore:
        pid = os.getpid()                    # a forked process opens its own
        with self._lock:
            store = self._opened.get(pid)
            if store is None:
                store = self._opened[pid] = open_result_store(self.path, mode="r+", check_links=False)
        return store

    def __call__(self, iy: int, ix: int, result: dict) -> None:
        self._store().write_chunk(iy, ix, result)
