"""The chunked pipeline: decompose every pixel of a cube into a result store, chunk by chunk.

The cube is read with dask in pixel chunks (all of t in each), every chunk is decomposed as one
batch and written into its own region of the result store as soon as it is finished, then
marked done.  Interrupted runs (Ctrl-C, a crash, a killed process) keep every finished chunk;
``resume=True`` computes only the rest and gives the same store as an uninterrupted run.

Also accepts a ``.npy`` array (y, x, t) or (n, t) with ``time_bin_ps`` for small inputs.
:func:`decompose_to_store` is used by ``streaklab decompose``, ``demo`` and ``bench speed``;
bad input raises :class:`PipelineError` before any work starts.  Its messages name the
command-line flags, the way most users meet them.
"""

# One module over 600 lines on purpose: the input checks, the chunk loop and the resume bookkeeping
# make one promise (docs/layout.md: finished chunks kept, a resumed run equal to an uninterrupted
# one).
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from core.errors import StreaklabError
from core.integrity import CheckedReader, DataIntegrityError, chunk_grid, read_checked, require_chunks
from decomposition.options import METHODS

__all__ = ["PipelineError", "decompose_to_store", "ChunkProgress", "StreamedDecomposition"]


class PipelineError(StreaklabError, ValueError):
    """The input or the settings of a chunked decomposition are unusable (says exactly why)."""


class ChunkProgress:
    """Progress over chunks on a stream: done/total, pixel rate, time left.

    On a terminal the line is redrawn in place; otherwise a line is printed at most every
    ``interval_s`` seconds and at the end.
    """

    def __init__(self, total_chunks: int, total_pixels: int, *, already_chunks: int = 0, stream=None,
                 interval_s: float = 2.0, label: str = "decompose"):
        self.total_chunks, self.total_pixels = int(total_chunks), int(total_pixels)
        self.chunks = int(already_chunks)
        self.pixels = 0
        self.stream = sys.stderr if stream is None else stream
        self.interval_s = interval_s
        self.label = label
        self.start = time.monotonic()
        self._last = -math.inf
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def update(self, summary: dict) -> None:
        self.chunks += 1
        self.pixels += int(summary.get("pixels", 0))
        now = time.monotonic()
        if self._tty or now - self._last >= self.interval_s or self.chunks == self.total_chunks:
            self._last = now
            self.stream.write(("\r" if self._tty else "") + self.line() + ("" if self._tty else "\n"))
            self.stream.flush()

    def line(self) -> str:
        elapsed = max(time.monotonic() - self.start, 1e-9)
        rate = self.pixels / elapsed
        left_px = max(self.total_pixels - self.pixels, 0)
        eta = _fmt_s(left_px / rate) if rate > 0 else "?"
        pct = 100.0 * self.chunks / max(self.total_chunks, 1)
        return (f"{self.label}: {self.chunks}/{self.total_chunks} chunks ({pct:.0f}%), "
                f"{rate:,.0f} px/s, {eta} left")

    def close(self) -> None:
        if self._tty:
            self.stream.write("\n")
            self.stream.flush()


def _fmt_s(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


# ---------------------------------------------------------------------------------------------
# input
# ---------------------------------------------------------------------------------------------
def _open_input(path, *, time_bin_ps, t0_ps, chunks):
    """-> (dask array (y, x, t), source-description dict, time_bin_ps, t0_ps, default chunks, units, y coord)."""
    import dask.array as da

    from reconstruction.cubestore import CubeStoreError, open_cube, written_chunks

    p = Path(path)
    if p.is_file() and p.suffix.lower() != ".npy":
        kind = _file_kind(p)
        if kind == "hdf5":
            raise PipelineError(f"{path} is an HDF5 (NeXus) file; decompose reads cube stores: convert it first "
                                f"with 'streaklab import {path} --out {p.with_suffix('.zarr').name}'")
        if kind != "npy":
            raise PipelineError(f"{path} is neither a cube store (a .zarr folder) nor a .npy array")
    if p.suffix == ".npy" or p.is_file():
        if time_bin_ps is None:
            raise PipelineError(f"{path}: a .npy input needs --time-bin-ps (its time axis is not stored)")
        try:
            data = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise PipelineError(f"{path}: cannot read as a .npy array: {exc}") from None
        listed = data.ndim == 2          # a list of profiles: one row of an image, but no image
        if listed:
            data = data[None]
        if data.ndim != 3:
            raise PipelineError(f"{path}: expected an array (y, x, t) or (n, t); got shape {data.shape}")
        if data.dtype.kind not in "fiu":
            raise PipelineError(f"{path}: expected real numbers; got dtype {data.dtype}")
        if min(data.shape) == 0:
            raise PipelineError(f"{path}: empty array of shape {data.shape}")
        tb = float(time_bin_ps)
        if not np.isfinite(tb) or tb <= 0:
            raise PipelineError(f"--time-bin-ps must be positive, got {time_bin_ps}")
        t0 = tb if t0_ps is None else float(t0_ps)
        default_chunks = (min(data.shape[0], 16), min(data.shape[1], 64))
        ch = chunks or default_chunks
        arr = da.from_array(data, chunks=(ch[0], ch[1], -1))
        source = {"path": str(p.resolve()), "kind": "npy", "shape": list(data.shape), "attrs": {},
                  **({"layout": "profiles (n, t)"} if listed else {})}
        return arr, source, tb, t0, default_chunks, "counts", None, "pixel"
    if time_bin_ps is not None or t0_ps is not None:
        raise PipelineError("--time-bin-ps/--t0-ps are for .npy input; a cube store carries its own time axis")
    # by its absolute path: the reader travels to dask's workers, which may run in other folders
    p = p.resolve()
    try:
        cube = open_cube(str(p))
        expected = written_chunks(cube)
    except CubeStoreError as exc:
        raise PipelineError(f"not a usable cube: {exc}") from None
    if cube.array.dtype.kind not in "fiu":
        raise PipelineError(f"{path}/cube holds {cube.array.dtype} values, not real numbers")
    # a chunk the cube should hold whose file is gone would read as NaN: stop before any work
    require_chunks(str(p), cube.array, [c for c in np.ndindex(*chunk_grid(cube.array)) if expected(c)])
    # read through the checksum and presence checks: a damaged chunk is named, not a traceback
    # from a worker, and a worker that cannot see the cube stops the run instead of reading NaN
    arr = da.from_array(CheckedReader(cube.array, str(p), expected=expected), chunks=cube.array.chunks,
                        fancy=False, asarray=True)
    source = {"path": str(p.resolve()), "kind": "cube", "shape": list(cube.shape),
              "attrs": _jsonable(cube.attrs)}
    y_units, y_coord = "pixel", None
    if "y" in cube.group:
        y_coord = np.asarray(read_checked(cube.group["y"], slice(None), store=str(p)), np.float64)
        y_units = str(cube.group["y"].attrs.get("units", "pixel"))
    default_chunks = tuple(int(c) for c in cube.array.chunks[:2])
    return (arr, source, cube.time_bin_ps, cube.t0_ps, default_chunks, str(cube.attrs.get("units", "counts")),
            y_coord, y_units)


def _file_kind(p: Path) -> str:
    """'npy', 'hdf5' or 'other', from the file's first bytes."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(8)
    except OSError:
        return "other"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head == b"\x89HDF\r\n\x1a\n":
        return "hdf5"
    return "other"


def _flag_table() -> dict:
    """The solver's flag table (bit -> name): the one place the flag names are defined."""
    from decomposition.api import FLAG_NAMES

    return {int(bit): str(name) for bit, name in dict(FLAG_NAMES).items()}


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def chunk_bytes(by: int, bx: int, nt: int, n_ir: int, write_components: bool = True) -> int:
    """Estimated peak memory of solving one (by, bx) pixel chunk of ``nt`` bins: the block (float64),
    the solver's batched temporaries (about four profiles per pixel), the rendered components
    (float32) and the dictionaries of candidate pulses (about 1000 atoms of nt bins)."""
    per_pixel = nt * (8 + 4 * 8 + (4 * (3 + n_ir) if write_components else 0))
    return by * bx * per_pixel + 1000 * nt * 8


def _check_sizes(input_path, nt, chunks, n_ir, write_components) -> None:
    """The input's time bins and one chunk's working memory against the documented limits."""
    from core import limits as L

    try:
        L.check_count("t", int(nt), L.MAX_TIME_BINS, "time bins")
        L.check_memory("--chunks", chunk_bytes(chunks[0], chunks[1], nt, n_ir, write_components),
                       L.MAX_CHUNK_BYTES, what=f"to solve a {chunks[0]} x {chunks[1]} pixel chunk of {nt} bins "
                                               f"(limits.MAX_CHUNK_BYTES)")
    except L.LimitError as exc:
        raise PipelineError(f"{input_path}: {exc}") from None


def _check_option_types(options: dict) -> None:
    """Solver options against their fields (:mod:`decomposition.options`: name, type, range), in one line."""
    from decomposition.methods.gradbm import GRADBM_DEFAULTS
    from decomposition.options import OptionError, options_from_mapping

    try:
        options_from_mapping({k: v for k, v in options.items() if k not in GRADBM_DEFAULTS}, strict=False)
    except OptionError as exc:
        raise PipelineError(f"--{exc}") from None   # "--option NAME: what is wrong"


def _one_line(exc) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def _probe_params(*, nt, time_bin_ps, t0_ps, method, components, options, pulse=False):
    """Run the solver on one all-zero profile: checks the options before any work and names the
    parameters (and their per-pixel dimensionality) the store must hold.  An all-zero profile
    skips the fit, and with it most options: ``pulse=True`` solves a pulse too (once the kernels
    are loaded: it runs the compiled fit)."""
    from decomposition.store.chunked import _solver

    _check_option_types(options)
    profiles = np.zeros((1, nt))
    if pulse:
        bins = np.arange(nt, dtype=np.float64)
        profiles = np.stack([profiles[0], np.exp(-0.5 * ((bins - nt / 3) / 2.0) ** 2)])
    try:
        res = _solver()(profiles, time_bin_ps=time_bin_ps, t0_ps=t0_ps, method=method,
                        components=tuple(components), **options)
    except (TypeError, ValueError, ArithmeticError) as exc:
        raise PipelineError(f"the solver refuses these settings: {_one_line(exc)}") from None
    map_keys, ir_keys = [], []
    for k, v in res.params.items():
        nd = np.ndim(v)
        if nd == 1:
            map_keys.append(k)
        elif nd == 2:
            ir_keys.append(k)
        else:
            raise PipelineError(f"solver parameter {k!r} has an unexpected shape {np.shape(v)} for one pixel")
    info = {k: v for k, v in dict(getattr(res, "info", {}) or {}).items()
            if isinstance(v, (str, int, float, bool, tuple, list, type(None)))}  # settings, not per-pixel arrays
    return map_keys, ir_keys, info


# ---------------------------------------------------------------------------------------------
# the pipeline
# ---------------------------------------------------------------------------------------------
def decompose_to_store(input_path, out_path, *, method: str = "convscd", components=("d", "s", "r"),
                       options: dict | None = None, chunks=None, workers: int | None = None,
                       scheduler: str | None = None, threads: int | None = None, n_ir: int = 3,
                       write_components: bool = True, nan_policy: str = "omit", resume: bool = False,
                       overwrite: bool = False, time_bin_ps: float | None = None, t0_ps: float | None = None,
                       progress: bool = True, stream=None, tls=None, irf="auto", spatial=None, shared=(),
                       regions=None, psf_map: bool = False) -> dict:
    """Decompose a cube (or .npy array) chunk by chunk into a result store.

    ``spatial`` (True, a :class:`decomposition.image.spatial.SpatialOptions` or a mapping of its
    fields) couples neighbouring pixels: each chunk is read with the coupling's halo and gives
    the answer of one call on the whole image (:mod:`decomposition.store.chunked`).  Its options
    are part of the job a ``--resume`` must match.  ``spatial="auto"`` and ``shared="auto"`` (the CLI's
    defaults) couple an image (a list of profiles per pixel: :func:`_auto_spatial`) and share its
    PSF where its pixels' own widths are one instrument's (:func:`_auto_shared`); a resumed run
    keeps what its store was started with.

    ``shared`` ("psf,delay,alpha" or a subset), ``regions`` (a .npy path or a (y, x) integer
    array of labels: one sss decay rate per label) and ``psf_map``: the parameters every pixel
    shares (:func:`decomposition.image.decompose_image`), estimated ONCE before any chunk runs
    from a deterministic subsample of the whole cube (:mod:`decomposition.image.shared`),
    written to the store's ``shared`` attribute with their standard errors, and held in every
    chunk.  A ``--resume`` reads them back from that attribute (the job records the names, the
    map option and the sha256 of the labels), so a resumed run holds the identical values.

    ``irf`` chooses the instrument response (see :func:`resolve_pipeline_response`): "auto"
    (default) the response stored in the cube's ``irf`` group when it has one, else the
    Gaussian PSF; "gaussian" the Gaussian PSF whatever the cube holds; a path to a stored
    response (:func:`core.irfstore.load_response`) or an :class:`core.irf.InstrumentResponse`.
    The response used is recorded in the store's attributes (``irf``: its description,
    Gaussian-equivalent sigma, sha256 of its samples and provenance, plus ``irf_source``;
    ``{"kind": "gaussian"}`` without one), kept itself in the store's ``irf`` group (its
    samples, time step and provenance, :meth:`ResultStore.response`), and its sha256 is part of
    the job a ``--resume`` must match.

    Returns a summary dict: out, shape, chunks_done (this run), chunks_before (done by the runs it
    resumed), chunks_total, pixels (decomposed in this run: pixels skipped for NaN/inf samples
    are not counted, nor in the rates), pixels_skipped (this run's), the counts of every finished
    chunk of the store (see :func:`_store_counts`; this run's alone in ``this_run``),
    noise_law (``signal_noise_law`` and its source: "cube" where the cube's ``noise_law``
    attribute chose it, "option" or "default"),
    seconds (all stages), seconds_setup (opening, checks,
    store creation, cluster start, and loading the compiled kernels), seconds_compile (the part of
    the setup that compiled kernels missing from numba's cache: 0.0 once they are cached),
    seconds_compute (reading, solving, writing the chunks) and pixels_per_s (all stages).  Raises :class:`PipelineError` for bad input, before any work starts.
    ``tls`` (a :class:`decomposition.store.cluster.TlsFiles`) holds the credentials of a ``tls://``
    scheduler.
    """
    from decomposition.image.shared import NotOneInstrument
    from decomposition.store.chunked import chunk_tasks, count_nonfinite_pixels, run_tasks
    from decomposition.store.resultstore import (ChunkWriter, ResultStoreError, create_result_store, open_result_store,
                                                 prepare_output_path)
    from core.provenance import __version__
    from decomposition.options import parse_nan_policy

    stream = sys.stderr if stream is None else stream
    t_start = time.perf_counter()
    options = dict(options or {})
    components = tuple(components)
    if method not in METHODS:
        raise PipelineError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    if n_ir < 0:
        raise PipelineError(f"--max-interreflections must be >= 0, got {n_ir}")
    try:   # one vocabulary (decomposition.options.NAN_POLICIES); the CLI's older words are aliases
        nan_policy = parse_nan_policy(nan_policy)
    except ValueError as exc:
        raise PipelineError(f"--nan-policy: {exc}") from None
    if resume and overwrite:
        raise PipelineError("--resume and --overwrite contradict each other; choose one")
    if chunks is not None and (len(chunks) != 2 or min(chunks) <= 0):
        raise PipelineError(f"--chunks takes two positive sizes, got {chunks}")
    if workers is not None and workers <= 0:
        raise PipelineError(f"--workers must be positive, got {workers}")
    if threads is not None and (threads <= 0 or workers is not None or scheduler is not None):
        raise PipelineError("--threads takes a positive count and applies only to the local threaded scheduler "
                           "(not with --workers or --scheduler)")
    if "max_reflections" in options and int(options["max_reflections"]) != int(n_ir):
        raise PipelineError(f"--option max_reflections={options['max_reflections']} contradicts "
                           f"--max-interreflections {n_ir}; give only --max-interreflections")
    options["max_reflections"] = int(n_ir)  # the solver reports exactly the slots the store keeps
    auto_shared = isinstance(shared, str) and shared == AUTO
    names, regions = _shared_settings(() if auto_shared else shared, regions, psf_map and not auto_shared)
    out_path = str(Path(out_path).resolve())

    arr, source, tb, t0, default_chunks, units, y_coord, y_units = _open_input(
        input_path, time_bin_ps=time_bin_ps, t0_ps=t0_ps, chunks=chunks)
    ny, nx, nt = arr.shape
    if regions is not None and regions.shape != (ny, nx):
        raise PipelineError(f"--regions: the labels have shape {regions.shape}, the cube's image is {(ny, nx)}")
    law_source = _apply_noise_law(method, options, source["attrs"])
    response, irf_source = resolve_pipeline_response(irf, input_path, source["kind"], tb, nt)
    irf_attrs = {"kind": "gaussian"}
    if response is not None:
        from decomposition.response.resolve import response_record

        irf_attrs = dict(_jsonable(response_record(response)), kind="response", source=irf_source)
    solver_options = dict(options, irf=response) if response is not None else options

    existing = None
    if resume and os.path.exists(out_path) and any(Path(out_path).iterdir()):

        try:
            prepare_output_path(out_path, protect=[source["path"]], resume=True)
            existing = open_result_store(out_path, mode="r+")
            existing.check_done_chunks_present()
        except (ResultStoreError, DataIntegrityError) as exc:
            raise PipelineError(f"cannot resume: {exc}") from None
        if chunks is None:
            chunks = tuple(existing.chunks)
    chunks = tuple(int(c) for c in (chunks or default_chunks))
    chunks = (min(chunks[0], ny), min(chunks[1], nx))
    _check_sizes(input_path, nt, chunks, n_ir, write_components)  # before the probe and warm-up allocate

    job = _job(method=method, components=components, options=options, n_ir=n_ir, chunks=chunks,
               write_components=write_components, nan_policy=nan_policy, source=source, time_bin_ps=tb, t0_ps=t0)
    if response is not None:             # absent for the Gaussian: older stores resume as before
        job["irf_sha256"] = irf_attrs["samples_sha256"]
    if isinstance(spatial, str) and spatial == AUTO:
        spatial = _auto_spatial(source, method, existing, ny * nx)
    if auto_shared:
        names = _auto_shared(spatial, response, existing)
        names, regions = _shared_settings(names, regions, psf_map)
    spatial_opts = _spatial_options(spatial)
    if spatial_opts is not None:         # absent without it: older stores resume as before
        if source.get("layout") == "profiles (n, t)":
            raise PipelineError(f"--spatial couples neighbouring pixels of an image; {input_path} is a list of "
                                f"profiles (n, t) with no neighbours: give an array (y, x, t) or a cube store")
        job["spatial"] = dataclasses.asdict(spatial_opts)
    if names:                            # absent without --shared: older stores resume as before
        job["shared"] = list(names)
        job["psf_map"] = bool(psf_map)
        job["regions_sha256"] = (None if regions is None
                                 else hashlib.sha256(np.ascontiguousarray(regions, np.int64).tobytes()).hexdigest())
    if existing is not None:
        _check_same_job(existing, job, out_path)
    else:

        try:  # refuse an occupied path (or one overlapping the input) before spending time on checks
            prepare_output_path(out_path, overwrite=overwrite, protect=[source["path"]])
        except (FileExistsError, ResultStoreError) as exc:
            raise PipelineError(str(exc)) from None

    map_keys, ir_keys, info = _probe_params(nt=nt, time_bin_ps=tb, t0_ps=t0, method=method,
                                            components=components, options=solver_options)
    # Load the compiled kernels here, once, before any worker starts (on a fresh install: compile
    # and cache them, saying so): workers then find them in the cache instead of each compiling.
    # With a response, its own path's kernels, warmed up with that response.
    from decomposition.warmup import warm_up

    warm_options = solver_options
    if response is not None:
        # the response path's float and count kernels differ: those of the data's kind only
        # (noise="auto"'s rule on the first row's first pixels)
        from decomposition.noise import resolve_noise_model

        first = np.asarray(arr[0, :min(nx, 64)].compute())
        warm_options = dict(solver_options, noise=resolve_noise_model(solver_options.get("noise", "auto"), first))
    try:
        image = ({"shared": tuple(names), "psf_map": bool(psf_map), "spatial": spatial_opts or False}
                 if names or spatial_opts is not None else None)     # the kernels of the image-level stages too
        seconds_compile = warm_up(time_bin_ps=tb, n_bins=nt, method=method, components=components,
                                  options=warm_options, image=image, stream=stream, quiet=not progress)
    except (TypeError, ValueError):  # settings its synthetic scenes do not suit: the workers compile instead
        seconds_compile = 0.0
    _probe_params(nt=nt, time_bin_ps=tb, t0_ps=t0, method=method, components=components, options=solver_options,
                  pulse=True)   # the options the fit uses, before any output exists
    if nan_policy == "raise":
        bad = count_nonfinite_pixels(arr)
        if bad:
            raise PipelineError(f"{input_path}: {bad} of {ny * nx} pixels have NaN or inf samples; "
                               f"use --nan-policy mark to decompose the rest and mark those invalid")

    estimate = None
    if names:
        try:
            estimate = _shared_estimate(existing, arr, regions, tb, t0, method, names, psf_map, components,
                                        solver_options, out_path, one_instrument=auto_shared)
        except (NotOneInstrument, PipelineError) as exc:
            # the default's PSF where the cube is not one instrument's, or has no lit pixel to tell
            if not auto_shared or existing is not None:
                raise
            names = ()
            for key in ("shared", "psf_map", "regions_sha256"):
                job.pop(key, None)
            if progress:
                print(f"decompose: nothing shared: {exc}", file=stream)
    client = cluster = None
    try:
        if scheduler is not None or workers is not None:  # connect before anything is written
            client, cluster = _connect(scheduler, workers, tls)
        if scheduler is not None and source["kind"] == "cube":  # its workers read the cube by path
            _check_workers_see(client, source["path"])
        if existing is None:
            attrs = {"method": method, "components": list(components), "options": job["options"],
                     "solver_info": _jsonable(info), "nan_policy": nan_policy,
                     "software_version": __version__, "source": source, "job": job, "irf": irf_attrs,
                     "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
            if estimate is not None:
                attrs["shared"] = _jsonable(estimate.record())
            try:
                store = create_result_store(out_path, shape=(ny, nx, nt), chunks=chunks, n_ir=n_ir, time_bin_ps=tb,
                                            t0_ps=t0, param_keys=map_keys, ir_param_keys=ir_keys,
                                            write_components=write_components, signal_units=units, y_coord=y_coord,
                                            y_units=y_units, attrs=attrs, overwrite=overwrite,
                                            protect=[source["path"]], flag_names=_flag_table(), irf=response)
            except (ResultStoreError, FileExistsError) as exc:
                raise PipelineError(str(exc)) from None
        else:
            store = existing
            store.remove_partials()
        pending = store.pending_chunks()
        gy, gx = store.grid
        total = gy * gx
        param_shapes = {k: () for k in map_keys}
        param_shapes.update({k: (int(n_ir),) for k in ir_keys})
        tasks = chunk_tasks(arr, chunks=chunks, sink=ChunkWriter(out_path), param_shapes=param_shapes,
                            pending=pending, time_bin_ps=tb, t0_ps=t0, method=method, components=components,
                            n_ir=int(n_ir), with_components=write_components, options=solver_options,
                            shared=estimate, regions=regions,
                            **({"spatial": spatial_opts} if spatial_opts is not None else {}))
        pending_pixels = int(sum(_region_pixels(store, iy, ix) for iy, ix in pending))
        if progress and resume and existing is not None:
            print(f"decompose: resuming {out_path}: {total - len(pending)}/{total} chunks already done",
                  file=stream)
        bar = (ChunkProgress(total, pending_pixels, already_chunks=total - len(pending), stream=stream)
               if progress else None)
        stats = {"invalid": 0, "ir_truncated": 0, "poor_fit": 0}

        def on_done(summary):
            stats["invalid"] += summary["invalid"]
            stats["ir_truncated"] += summary["ir_truncated"]
            stats["poor_fit"] += summary.get("poor_fit", 0)
            if bar is not None:
                bar.update(summary)

        t_compute = time.perf_counter()
        try:
            run_tasks(tasks, client=client, num_workers=threads, on_done=on_done)
        except DataIntegrityError as exc:           # a damaged chunk of the input
            if bar is not None:
                bar.close()
            raise DataIntegrityError(f"{exc} (the chunks finished before it are in {out_path}; --resume "
                                     f"continues once the input is mended)") from None
        except (OSError, KeyboardInterrupt) as exc:  # a full or read-only disk, or Ctrl-C
            if bar is not None:
                bar.close()
            left = 0
            if client is not None:  # let the workers' running chunks end before counting what is on disk
                if cluster is None:  # an existing cluster's workers finish the (cancelled) chunks they run
                    left = _wait_for_running(client, tasks, stream if progress else None)
                _close_quietly(client, cluster)   # a cluster of our own ends its running chunks with it
                client = cluster = None
            done_now = int(store.done_chunks().sum())
            how, fix = (("interrupted", "") if isinstance(exc, KeyboardInterrupt)
                        else ("stopped", "fix the problem below and "))
            late = ("" if not left else " (the cluster did not answer: chunks it was running may still land)"
                    if left < 0 else f" ({left} more were still running on the cluster and may land later)")
            print(f"decompose: {how}; {done_now}/{total} chunks are on disk in {out_path}{late}; {fix}"
                  f"rerun with --resume to finish", file=stream)
            raise
        if bar is not None:
            bar.close()
        t_end = time.perf_counter()
        seconds, seconds_compute = t_end - t_start, t_end - t_compute
        decomposed = pending_pixels - stats["invalid"]      # skipped pixels are neither counted nor timed
        summary = {"out": out_path, "shape": [ny, nx, nt], "chunks_done": len(pending), "chunks_total": total,
                   "chunks_before": total - len(pending), "pixels": decomposed, "pixels_skipped": stats["invalid"],
                   "this_run": {"invalid_pixels": stats["invalid"], "ir_truncated_pixels": stats["ir_truncated"],
                                "poor_fit_pixels": stats["poor_fit"]},
                   **_store_counts(store, source),
                   "seconds": seconds, "seconds_compute": seconds_compute, "seconds_setup": seconds - seconds_compute,
                   "pixels_per_s": decomposed / seconds if seconds > 0 else float("nan"),
                   "seconds_compile": seconds_compile, "irf": irf_attrs,
                   "noise_law": {"signal_noise_law": options.get("signal_noise_law", "auto"), "source": law_source},
                   "shared": None if estimate is None else estimate.record()}
        return summary
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


#: ``spatial`` of :func:`decompose_to_store` that lets the input decide (the CLI's default): :func:`_auto_spatial`
AUTO = "auto"


def _auto_shared(spatial, response, existing) -> tuple:
    """What ``shared="auto"`` means: resuming, what the store was started with (its job);
    otherwise the PSF width where the image is coupled with the Gaussian PSF (a measured
    response is the instrument already), held only where the pixels' own widths are one
    instrument's (:data:`decomposition.image.shared.ONE_INSTRUMENT_SPREAD`; else nothing)."""
    if existing is not None:
        return tuple(existing.attrs.get("job", {}).get("shared", ()))
    return ("psf",) if spatial is not None and spatial is not False and response is None else ()


def _auto_spatial(source: dict, method: str, existing, n_pixels: int):
    """What ``spatial="auto"`` means for this input: resuming, the coupling the store was started
    with (its job); otherwise an image of surfaces (a cube or a (y, x, t) array of more than one
    pixel) decomposed with ConvSCD is coupled (True), and a list of profiles, or another method,
    is decomposed per pixel (None)."""
    if existing is not None:
        return existing.attrs.get("job", {}).get("spatial")
    image = source.get("layout") != "profiles (n, t)" and n_pixels > 1 and method == "convscd"
    return True if image else None


def _shared_settings(shared, regions, psf_map):
    """--shared, --regions, --psf-map checked -> (names, labels (y, x) int64 or None)."""
    from decomposition.image.api import parse_shared
    from decomposition.options import OptionError

    try:
        names = parse_shared(shared)
    except OptionError as exc:
        raise PipelineError(f"--shared: {exc}") from None
    if psf_map and "psf" not in names:
        raise PipelineError("--psf-map: give --shared psf too (the map is the shared PSF's)")
    if regions is None:
        return names, None
    if "alpha" not in names:
        raise PipelineError("--regions: give --shared alpha too (the regions are where one sss decay rate holds)")
    if isinstance(regions, (str, os.PathLike)):
        try:
            labels = np.load(regions, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise PipelineError(f"--regions {regions}: cannot read a .npy label image ({_one_line(exc)})") from None
    else:
        labels = np.asarray(regions)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise PipelineError(f"--regions: expected a (y, x) integer label image, got {labels.dtype} {labels.shape}")
    return names, labels.astype(np.int64)


def _shared_estimate(existing, arr, regions, tb, t0, method, names, psf_map, components, solver_options, out_path,
                     one_instrument: bool = False):
    """The shared parameters: read back from a resumed store's ``shared`` attribute, else
    estimated once from the whole cube (lit scores chunk by chunk, then the selected pixels)."""
    from decomposition.image.pooling import lit_score
    from decomposition.image.shared import NotOneInstrument, SharedEstimate, image_estimate

    if existing is not None:
        record = existing.attrs.get("shared")
        if record is None:
            raise PipelineError(f"cannot resume {out_path}: its shared parameters were never written; "
                                f"use --overwrite to start again")
        return SharedEstimate.from_record(record)
    import dask.array as da

    score = np.asarray(da.map_blocks(lambda b: lit_score(b), arr, drop_axis=2, dtype=np.float64).compute())
    ny, nx = score.shape

    def gather(idx):
        yy, xx = np.unravel_index(idx, (ny, nx))
        return np.asarray(arr.vindex[yy, xx].compute())

    keywords = dict(solver_options, t0_ps=t0, components=tuple(components))
    try:
        return image_estimate(arr, regions, tb, method, names, psf_map=psf_map, keywords=keywords, score=score,
                              gather=gather, one_instrument=one_instrument)
    except NotOneInstrument:
        raise
    except ValueError as exc:
        raise PipelineError(f"--shared: {_one_line(exc)}") from None


def _apply_noise_law(method: str, options: dict, source_attrs: dict) -> str:
    """Set ``signal_noise_law`` in ``options`` (in place) from the input's ``noise_law`` attribute where
    no option chose it; -> where the law came from: "option", "cube" or "default"."""
    if "signal_noise_law" in options:
        return "option"
    if method == "convscd" and source_attrs.get("noise_law") == "detector":
        # the cube says one detector's read-out lies behind every pixel: its noise has one law
        options["signal_noise_law"] = "detector"
        return "cube"
    return "default"


def _spatial_options(spatial):
    """``spatial=`` -> its :class:`decomposition.image.spatial.SpatialOptions` (None: off); a bad
    option is a :class:`PipelineError`."""
    from decomposition.image.spatial import spatial_options
    from decomposition.options import OptionError

    try:
        return spatial_options(spatial)
    except OptionError as exc:
        raise PipelineError(f"--spatial: {exc}") from None


def _job(*, method, components, options, n_ir, chunks, write_components, nan_policy, source, time_bin_ps,
         t0_ps) -> dict:
    """The settings a ``--resume`` must match (the store's ``job`` attribute)."""
    return {"method": method, "components": list(components), "options": _jsonable(options), "n_ir": int(n_ir),
            "chunks": list(chunks), "write_components": bool(write_components), "nan_policy": nan_policy,
            "source_path": source["path"], "source_shape": source["shape"], "time_bin_ps": time_bin_ps,
            "t0_ps": t0_ps,
            # a cube rewritten at the same path (new provenance) is another input
            "source_attrs_sha256": hashlib.sha256(json.dumps(source["attrs"], sort_keys=True).encode()).hexdigest()}


def _check_same_job(existing, job: dict, out_path) -> None:
    """Refuse to resume a store started with other settings (names every difference)."""
    from decomposition.options import parse_nan_policy

    before = dict(existing.attrs.get("job", {}))
    if "nan_policy" in before:      # stores written with the older words read the same
        try:
            before["nan_policy"] = parse_nan_policy(before["nan_policy"])
        except ValueError:
            pass
    diff = sorted(k for k in set(job) | set(before) if job.get(k) != before.get(k))
    if diff:
        details = "; ".join(f"{k}: the input's attributes (provenance) changed: it was rewritten"
                            if k == "source_attrs_sha256" else f"{k}: stored {before.get(k)!r}, now {job.get(k)!r}"
                            for k in diff)
        raise PipelineError(f"cannot resume {out_path}: it was started with different settings ({details}); "
                           f"use the original settings, or --overwrite to start again")


class StreamedDecomposition:
    """A result store filled from blocks a caller hands in as they become available (a capture
    decomposing its scan lines as they land), chunk by chunk, with the rules and the store of
    :func:`decompose_to_store`: the same options (the noise law from the input's ``noise_law``),
    the same solver call per chunk, the same writes, the same resume.  A store written this way
    holds the same arrays as ``decompose_to_store`` of the finished cube with the same chunks
    and settings.

    Open one with :meth:`open`; then :meth:`solve` ``(iy, ix, block)`` for every chunk of
    :attr:`pending` (in any order, from one thread at a time).
    """

    def __init__(self, store, sink, param_shapes, solve_kwargs):
        self.store, self._sink = store, sink
        self._param_shapes, self._solve_kwargs = param_shapes, solve_kwargs

    @classmethod
    def open(cls, out_path, *, shape, chunks, time_bin_ps: float, t0_ps: float, source: dict,
             units: str = "counts", y_coord=None, y_units: str = "pixel", method: str = "convscd",
             components=("d", "s", "r"), options: dict | None = None, n_ir: int = 3,
             write_components: bool = True, nan_policy: str = "omit", resume: bool = False,
             progress: bool = False, stream=None) -> "StreamedDecomposition":
        """Create the store at ``out_path`` (or, with ``resume``, reopen it: its settings must match).

        ``shape`` (ny, nx, nt) and ``chunks`` (by, bx) as the finished cube's; ``source`` a dict
        with path, kind, shape and attrs (``attrs["noise_law"]`` as a cube's).  Raises
        :class:`PipelineError` for bad settings or an occupied ``out_path``.
        """
        from decomposition.options import parse_nan_policy
        from decomposition.store.resultstore import (ChunkWriter, ResultStoreError, create_result_store,
                                                     open_result_store, prepare_output_path)
        from core.provenance import __version__

        options = dict(options or {})
        components = tuple(components)
        if method not in METHODS:
            raise PipelineError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        try:
            nan_policy = parse_nan_policy(nan_policy)
        except ValueError as exc:
            raise PipelineError(f"--nan-policy: {exc}") from None
        options["max_reflections"] = int(n_ir)
        _apply_noise_law(method, options, source["attrs"])
        ny, nx, nt = (int(v) for v in shape)
        chunks = (min(int(chunks[0]), ny), min(int(chunks[1]), nx))
        _check_sizes(source["path"], nt, chunks, n_ir, write_components)
        out_path = str(Path(out_path).resolve())
        job = _job(method=method, components=components, options=options, n_ir=n_ir, chunks=chunks,
                   write_components=write_components, nan_policy=nan_policy, source=source,
                   time_bin_ps=float(time_bin_ps), t0_ps=float(t0_ps))
        map_keys, ir_keys, info = _probe_params(nt=nt, time_bin_ps=time_bin_ps, t0_ps=t0_ps, method=method,
                                                components=components, options=options)
        try:
            if resume and os.path.exists(out_path) and any(Path(out_path).iterdir()):
                prepare_output_path(out_path, protect=[source["path"]], resume=True)
                store = open_result_store(out_path, mode="r+")
                store.check_done_chunks_present()
                _check_same_job(store, job, out_path)
                store.remove_partials()
            else:
                attrs = {"method": method, "components": list(components), "options": job["options"],
                         "solver_info": _jsonable(info), "nan_policy": nan_policy, "software_version": __version__,
                         "source": source, "job": job, "irf": {"kind": "gaussian"},
                         "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
                store = create_result_store(out_path, shape=(ny, nx, nt), chunks=chunks, n_ir=n_ir,
                                            time_bin_ps=time_bin_ps, t0_ps=t0_ps, param_keys=map_keys,
                                            ir_param_keys=ir_keys, write_components=write_components,
                                            signal_units=units, y_coord=y_coord, y_units=y_units, attrs=attrs,
                                            protect=[source["path"]], flag_names=_flag_table())
        except (ResultStoreError, DataIntegrityError, FileExistsError) as exc:
            raise PipelineError(f"{out_path}: {exc}") from None
        from decomposition.warmup import warm_up

        try:
            warm_up(time_bin_ps=time_bin_ps, n_bins=nt, method=method, components=components, options=options,
                    stream=sys.stderr if stream is None else stream, quiet=not progress)
        except (TypeError, ValueError):  # settings its synthetic scenes do not suit: the first chunk compiles
            pass
        param_shapes = {k: () for k in map_keys}
        param_shapes.update({k: (int(n_ir),) for k in ir_keys})
        solve_kwargs = {"time_bin_ps": time_bin_ps, "t0_ps": t0_ps, "method": method, "components": components,
                        "n_ir": int(n_ir), "with_components": write_components, "options": options}
        return cls(store, ChunkWriter(out_path), param_shapes, solve_kwargs)

    @property
    def pending(self) -> list[tuple[int, int]]:
        """Chunks (iy, ix) not yet done."""
        return self.store.pending_chunks()

    def solve(self, iy: int, ix: int, block) -> dict:
        """Decompose ``block`` (by, bx, nt), the input of chunk (iy, ix), and write it into the store
        (marked done last) -> the chunk's summary (iy, ix, pixels, invalid, ir_truncated, poor_fit, seconds)."""
        from decomposition.store.chunked import _solve_and_sink

        return _solve_and_sink(np.asarray(block), int(iy), int(ix), self._sink, self._param_shapes,
                               self._solve_kwargs)


def resolve_pipeline_response(irf, input_path, input_kind: str, time_bin_ps: float, n_bins: int):
    """The response a chunked decomposition uses -> (InstrumentResponse or None, where it came from).

    ``irf``: "auto" (the cube's stored ``irf`` group if any, else None: the Gaussian),
    "gaussian" (None), a path, or an :class:`core.irf.InstrumentResponse`.  The response is
    checked against the input's time axis here (:func:`decomposition.response.resolve.resolve_response`:
    resampled onto the bins when its step differs, refused when longer than the window), so
    a bad response stops the run before anything is written.
    """
    from core.irf import InstrumentResponse, ResponseError
    from decomposition.response.resolve import resolve_response

    if irf is None or (isinstance(irf, str) and irf.lower() == "gaussian"):
        return None, "gaussian"
    if isinstance(irf, str) and irf.lower() == "auto":
        if input_kind != "cube":
            return None, "gaussian"
        from reconstruction.cubestore import CubeStoreError, read_cube_response

        try:
            found = read_cube_response(str(input_path))
        except (ResponseError, CubeStoreError) as exc:
            raise PipelineError(f"{input_path}: its stored instrument response is unusable: {exc} "
                                f"(--irf gaussian ignores it)") from None
        if found is None:
            return None, "gaussian"
        raw, where = found, f"{Path(input_path).resolve()}/irf (stored in the cube)"
    elif isinstance(irf, InstrumentResponse):
        raw, where = irf, "given"
    else:
        raw, where = str(irf), str(Path(str(irf)).resolve())
    try:
        return resolve_response(raw, time_bin_ps, n_bins), where
    except ResponseError as exc:
        raise PipelineError(f"--irf {irf if not isinstance(irf, InstrumentResponse) else 'response'}: {exc}") from None


def _store_counts(store, source) -> dict:
    """Counts over every finished chunk of the store (this run's and those of runs it resumed):
    decomposed_pixels, invalid_pixels (NaN/inf samples, not decomposed), unfinished_line_pixels
    (of those, the pixels on lines the capture did not finish: the cube's ``line_valid``),
    ir_truncated_pixels and poor_fit_pixels (flags TRUNCATED and POOR_FIT)."""
    from decomposition import POOR_FIT, TRUNCATED

    g = store.group
    done = store.done_mask()
    valid = np.asarray(read_checked(g["valid"], slice(None), store=store.path), bool) & done
    flags = np.asarray(read_checked(g["flags"], slice(None), store=store.path)).astype(np.int64)
    unfinished = 0
    if source["kind"] == "cube":
        from reconstruction.cubestore import open_cube

        line_valid = _cube_rows(open_cube(source["path"]), "line_valid")
        if line_valid is not None:
            unfinished = int((done & ~valid & ~line_valid[:, None]).sum())
    return {"decomposed_pixels": int(valid.sum()), "invalid_pixels": int((done & ~valid).sum()),
            "unfinished_line_pixels": unfinished,
            "ir_truncated_pixels": int((done & ((flags & int(TRUNCATED)) != 0)).sum()),
            "poor_fit_pixels": int((valid & ((flags & int(POOR_FIT)) != 0)).sum())}


def _cube_rows(cube, name):
    """The cube's (y,) array ``name`` read through the checksum check, or None when it has none."""
    from core.integrity import open_member
    from reconstruction.cubestore import CubeStoreError

    arr = open_member(cube.group, name, cube.path, CubeStoreError)
    return None if arr is None else np.asarray(read_checked(arr, slice(None), store=cube.path), bool)


def _wait_for_running(client, tasks, stream) -> int:
    """After an interrupt: wait (Ctrl-C ignored, with a timeout) for the chunks an existing
    cluster's workers are still running; -> how many still ran at the timeout (-1: no answer)."""
    from decomposition.store.cluster import SETTLE_TIMEOUT_S, ignore_sigint, quiet_distributed, wait_for_running

    if stream is not None:
        print(f"decompose: waiting for the chunks the cluster is running to end (at most "
              f"{SETTLE_TIMEOUT_S:g} s)", file=stream, flush=True)
    with ignore_sigint(), quiet_distributed():
        return wait_for_running(client, [t.key for t in tasks], timeout_s=SETTLE_TIMEOUT_S)


def _region_pixels(store, iy, ix) -> int:
    ys, xs = store.chunk_slices(iy, ix)
    return (ys.stop - ys.start) * (xs.stop - xs.start)


def _close_quietly(client, cluster) -> None:
    """Close an interrupted run's client and cluster, silencing distributed's shutdown chatter
    (a second Ctrl-C meanwhile is ignored)."""
    from decomposition.store.cluster import ignore_sigint, quiet_distributed

    with ignore_sigint(), quiet_distributed():
        for thing in (client, cluster):
            if thing is not None:
                try:
                    thing.close()
                except Exception:  # shutting down after an interrupt: nothing left to save
                    pass


def _check_workers_see(client, path) -> None:
    from decomposition.store.cluster import ClusterError, check_workers_see

    try:
        check_workers_see(client, [path])
    except ClusterError as exc:
        raise PipelineError(str(exc)) from None


def _connect(scheduler, workers, tls=None):
    """-> (Client, LocalCluster or None); see :mod:`decomposition.store.cluster`."""
    from decomposition.store.cluster import ClusterError, connect_scheduler, start_local_cluster

    try:
        if scheduler is not None:
            return connect_scheduler(scheduler, tls=tls), None
        return start_local_cluster(int(workers))
    except ClusterError as exc:
        raise PipelineError(str(exc)) from None
