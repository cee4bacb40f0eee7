"""Chunked decomposition: the batched solver mapped over pixel chunks of a dask array.

A cube ``(y, x, t)`` is split into pixel chunks ``(by, bx, all of t)``; every chunk becomes one
dask task that reads its block, runs :func:`decomposition.decompose` on the block's pixels as one
batch, and hands the result to a *sink* ``sink(iy, ix, result)`` (for a result store: a small
picklable object that reopens the store by path, so the task graph carries nothing that cannot
cross processes).  The tasks run on the local threaded scheduler or on a dask.distributed
client, and report each finished chunk through a callback, so a caller can show progress and
nothing is held back until the end.

Per-pixel policy for non-finite input: a pixel with any NaN or inf sample is not decomposed; its
parameters and components are NaN, ``valid`` is False and its flags hold the solver's NONFINITE
bit.  (A caller that
prefers a hard error checks the cube first with :func:`count_nonfinite_pixels`.)

Inter-reflection slots: the solver may return any number R of inter-reflections per call; the
result of a chunk always has ``n_ir`` slots, padded with NaN parameters and zero components, or
truncated to the ``n_ir`` earliest.  The chunk summary counts the pixels that had more
inter-reflections than were kept (truncated here, or flagged TRUNCATED by the solver).

Spatial coupling (``spatial=``, :mod:`decomposition.image.spatial`): a pixel's answer then depends
on its neighbours' data within :func:`decomposition.image.halo_pixels` pixels, so each task
reads its chunk with that halo around it (clipped at the image's borders), decomposes the haloed
block as one image (:func:`decomposition.image.decompose_image`) and keeps the chunk's interior:
the same answer as one call on the whole image.

This module knows nothing of files.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import dask
import dask.system
import dask.array as da
import dask.threaded
import numpy as np
from dask.callbacks import Callback
from ..flags import FLAG_DTYPE

__all__ = [
    "solve_block",
    "fit_ir_slots",
    "rechunk_pixels",
    "chunk_tasks",
    "run_tasks",
    "count_nonfinite_pixels",
]


def _solver():
    from decomposition import decompose  # imported at call time: workers import it themselves

    return decompose


def _image_solver():
    from decomposition.image import decompose_image  # imported at call time, as the solver

    return decompose_image


def _halo(spatial) -> int:
    from decomposition.image import halo_pixels

    return halo_pixels(spatial)


def _solve_image(full, interior, keep, *, time_bin_ps, method, spatial, shared_image=None, **keywords):
    """The coupled decomposition of the haloed block ``full`` (Y, X, L) cropped to ``interior``
    (two slices) and to the pixels ``keep`` (flat, bool) of it: arrays shaped as the per-pixel
    solver's on the kept pixels (``shared_image``: :func:`solve_block`)."""
    from decomposition.api import DecompositionResult

    keywords = dict(keywords, nan_policy="omit")
    res = _image_solver()(full, time_bin_ps, method, spatial=spatial, **(shared_image or {}), **keywords)

    def crop(a):
        a = np.asarray(a)[interior]
        return a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:])[keep]     # (no -1: R may be 0)

    return DecompositionResult(direct=crop(res.direct), sss=crop(res.sss),
                               interreflections=crop(res.interreflections),
                               params={k: crop(v) for k, v in res.params.items()}, residual=crop(res.residual),
                               flags=crop(res.flags), info=res.info)


def _nonfinite_flag() -> int:
    from decomposition import NONFINITE  # the solver's own bit for "not decomposed: NaN/inf samples"

    return int(NONFINITE)


def fit_ir_slots(a, n_ir: int, axis: int, fill) -> np.ndarray:
    """Pad (with ``fill``) or truncate axis ``axis`` of ``a`` to length ``n_ir``."""
    a = np.asarray(a)
    axis = axis % a.ndim
    r = a.shape[axis]
    if r == n_ir:
        return a
    if r > n_ir:
        return np.take(a, np.arange(n_ir), axis=axis)
    pad = list(a.shape)
    pad[axis] = n_ir - r
    dtype = np.result_type(a.dtype, np.asarray(fill).dtype)
    return np.concatenate([a.astype(dtype, copy=False), np.full(pad, fill, dtype=dtype)], axis=axis)


def solve_block(block, *, time_bin_ps: float, t0_ps: float | None = None, method: str = "convscd",
                components=None, n_ir: int = 2, with_components: bool = True, options: dict | None = None,
                spatial=None, interior=None, hold: dict | None = None, hold_stderr: dict | None = None,
                shared_image: dict | None = None) -> dict:
    """Decompose every pixel of one block.

    Parameters
    ----------
    block : ndarray, shape (by, bx, L)
        Time profiles, any real dtype; non-finite pixels are left out (see module docstring).
        With ``interior``, the chunk with its halo around it.
    spatial : bool, SpatialOptions or mapping, optional
        Couple neighbouring pixels (:func:`decomposition.image.decompose_image`'s ``spatial``).
    interior : (slice, slice), optional
        The chunk within a haloed ``block``; the results cover it alone.
    time_bin_ps, t0_ps : float
        Time axis (bin i at t0_ps + i * time_bin_ps; t0_ps defaults to time_bin_ps).
    method, components, options
        Passed to :func:`decomposition.decompose` (``options`` as keywords).
    n_ir : int
        Inter-reflection slots R kept per pixel.
    hold, hold_stderr : dict, optional
        Parameters every pixel holds and their errors ({key: (by, bx)}, from the whole cube's
        :class:`decomposition.image.shared.SharedEstimate`; :func:`decomposition.image.shared.decompose_held`).
    shared_image : dict, optional
        With ``spatial``: the keywords ``shared``, ``estimate``, ``window`` and ``regions`` of
        :func:`decomposition.image.decompose_image` for the haloed block (the whole cube's
        estimate, where the block lies in it).
    with_components : bool
        Also return the rendered component profiles and the residual.

    Returns
    -------
    dict with
        ``params``         dict of float64 arrays (by, bx) or (by, bx, n_ir), NaN = absent
        ``rms_residual``   (by, bx) float64, sqrt(mean over t of residual**2)
        ``flags``          (by, bx) uint16
        ``valid``          (by, bx) bool, pixel finite and decomposed
        ``direct``, ``sss``, ``residual`` (by, bx, L) and ``ir`` (by, bx, n_ir, L), in the solver's
        precision (float64),
        only if ``with_components``
        ``stats``          dict: pixels, invalid, ir_truncated, poor_fit (pixels flagged POOR_FIT), seconds
    """
    start = time.perf_counter()
    block = full = np.asarray(block)
    if block.ndim != 3:
        raise ValueError(f"a block must be (by, bx, L); got shape {block.shape}")
    if interior is not None:
        block = full[tuple(interior)]
    by, bx, nt = block.shape
    n_ir = int(n_ir)
    finite = np.isfinite(block).all(axis=-1) if block.dtype.kind == "f" else np.ones((by, bx), bool)
    flat = block.reshape(by * bx, nt)
    keep = finite.reshape(-1)
    n_ok = int(keep.sum())
    out = {"valid": finite.copy(), "flags": np.where(finite, 0, _nonfinite_flag()).astype(FLAG_DTYPE),
           "rms_residual": np.full((by, bx), np.nan)}
    params: dict[str, np.ndarray] = {}
    comps = {}
    truncated = poor = 0
    if n_ok:
        kwargs = dict(time_bin_ps=time_bin_ps, t0_ps=t0_ps, method=method,
                      **({"components": tuple(components)} if components is not None else {}), **(options or {}))
        if spatial is not None and spatial is not False:
            res = _solve_image(full, tuple(interior or (slice(None), slice(None))), keep, spatial=spatial,
                               shared_image=shared_image, **kwargs)
        else:
            prof = flat if n_ok == flat.shape[0] else flat[keep]
            if hold:
                from decomposition.image.shared import decompose_held

                def rows(values):
                    return {k: np.asarray(v, np.float64).reshape(-1)[keep] for k, v in values.items()}

                res = decompose_held(prof, hold=rows(hold), hold_stderr=rows(hold_stderr), **kwargs)
            else:
                res = _solver()(prof, **kwargs)
        for k, v in res.params.items():
            v = np.asarray(v, dtype=np.float64)
            if v.ndim == 2:  # per inter-reflection slot
                if v.shape[1] > n_ir:
                    truncated = max(truncated, int(np.isfinite(v[:, n_ir:]).any(axis=1).sum()))
                v = fit_ir_slots(v, n_ir, axis=1, fill=np.nan)
            params[k] = v
        resid = np.asarray(res.residual, dtype=np.float64)
        rms = np.sqrt(np.mean(np.square(resid), axis=-1))
        flags = np.asarray(res.flags).astype(FLAG_DTYPE)
        from decomposition import POOR_FIT, TRUNCATED  # more inter-reflections than it reports; misfits

        truncated = max(truncated, int(np.count_nonzero(flags & int(TRUNCATED))))
        poor = int(np.count_nonzero(flags & int(POOR_FIT)))
        if with_components:
            comps = {"direct": np.asarray(res.direct), "sss": np.asarray(res.sss), "residual": resid,
                     "ir": fit_ir_slots(np.asarray(res.interreflections), n_ir, axis=1, fill=0.0)}
    else:
        rms = flags = None

    def scatter(values, fill, dtype):
        """(n_ok, ...) values -> (by, bx, ...) with ``fill`` at left-out pixels."""
        values = np.asarray(values)
        if n_ok == by * bx:     # nothing left out: the solver's own arrays (filling a copy cost 3 % of a chunk)
            return values.astype(dtype, copy=False).reshape((by, bx) + values.shape[1:])
        full = np.full((by * bx,) + values.shape[1:], fill, dtype=dtype)
        full[keep] = values
        return full.reshape((by, bx) + values.shape[1:])

    if n_ok:
        out["params"] = {k: scatter(v, np.nan, np.float64) for k, v in params.items()}
        out["rms_residual"] = scatter(rms, np.nan, np.float64)
        out["flags"] = scatter(flags, _nonfinite_flag(), FLAG_DTYPE)
        if with_components:  # in the solver's precision: the store decides what fits its arrays
            for k, v in comps.items():
                out[k] = scatter(v, np.nan, np.result_type(np.asarray(v).dtype, np.float32))
    else:  # nothing to solve: shapes come from the caller's expectations
        out["params"] = None
        if with_components:
            out["direct"] = np.full((by, bx, nt), np.nan, np.float32)
            out["sss"] = np.full((by, bx, nt), np.nan, np.float32)
            out["residual"] = np.full((by, bx, nt), np.nan, np.float32)
            out["ir"] = np.full((by, bx, n_ir, nt), np.nan, np.float32)
    out["stats"] = {"pixels": by * bx, "invalid": by * bx - n_ok, "ir_truncated": truncated, "poor_fit": poor,
                    "seconds": time.perf_counter() - start}
    return out


def _fill_missing_params(result: dict, param_shapes: dict) -> dict:
    """Give an all-invalid chunk NaN parameters of the expected names and trailing shapes."""
    if result["params"] is None:
        by, bx = result["valid"].shape
        result["params"] = {k: np.full((by, bx) + tuple(trail), np.nan) for k, trail in param_shapes.items()}
    return result


def _solve_and_sink(block, iy, ix, sink, param_shapes, solve_kwargs, interior=None, held=None):
    result = _fill_missing_params(solve_block(block, interior=interior, **solve_kwargs, **(held or {})), param_shapes)
    stats = result.pop("stats")
    sink(iy, ix, result)
    return {"iy": iy, "ix": ix, **stats}


def rechunk_pixels(cube, chunks) -> "da.Array":
    """``cube`` (y, x, t) as a dask array chunked (by, bx, all of t); rechunks only if needed."""
    if not isinstance(cube, da.Array):
        cube = da.from_array(cube, chunks=(int(chunks[0]), int(chunks[1]), -1))
    if cube.ndim != 3:
        raise ValueError(f"a cube must be (y, x, t); got shape {cube.shape}")
    ny, nx, nt = cube.shape
    by, bx = min(int(chunks[0]), ny), min(int(chunks[1]), nx)
    want = (da.core.normalize_chunks((by,), (ny,))[0], da.core.normalize_chunks((bx,), (nx,))[0], (nt,))
    if tuple(cube.chunks) != want:
        cube = cube.rechunk(want)
    return cube


def chunk_tasks(cube, *, chunks, sink, param_shapes: dict, pending=None, shared=None, regions=None,
                **solve_kwargs) -> list:
    """One dask task per pending pixel chunk: read the block, solve it, ``sink(iy, ix, result)``.

    Parameters
    ----------
    cube : dask or numpy array, shape (y, x, t)
    chunks : (by, bx)
        Pixel chunk; chunk (iy, ix) covers rows iy*by ... and columns ix*bx ...
    sink : callable(iy, ix, result)
        Receives each chunk's result (see :func:`solve_block`, without ``stats``); must be
        picklable for a distributed scheduler.
    param_shapes : dict
        Parameter name -> trailing shape (``()`` or ``(n_ir,)``), used to give chunks with no
        finite pixel NaN parameters of the right names.
    pending : iterable of (iy, ix), optional
        Chunks to compute (default: all).
    shared : decomposition.image.shared.SharedEstimate, optional
        Parameters every pixel holds, estimated before from the whole cube; each task gets its
        chunk's held values (with ``regions``, the cube's (y, x) labels, for a decay rate per region).
    **solve_kwargs
        Keywords of :func:`solve_block`; with ``spatial``, each task reads its chunk with the
        coupling's halo (module docstring).

    Returns
    -------
    list of dask.delayed.Delayed, each computing a summary dict (iy, ix, pixels, invalid,
    ir_truncated, poor_fit, seconds).
    """
    arr = rechunk_pixels(cube, chunks)
    blocks = arr.to_delayed()
    gy, gx = blocks.shape[:2]
    if pending is None:
        pending = [(iy, ix) for iy in range(gy) for ix in range(gx)]
    token = dask.base.tokenize(arr.name, sink, sorted(solve_kwargs.items(), key=str))
    if shared is not None:
        token = dask.base.tokenize(token, shared.record(), None if regions is None else np.asarray(regions))
    halo = _halo(solve_kwargs.get("spatial"))
    ny, nx = arr.shape[:2]
    y_edges, x_edges = np.cumsum((0,) + arr.chunks[0]), np.cumsum((0,) + arr.chunks[1])
    tasks = []
    for iy, ix in pending:
        y0, y1, x0, x1 = int(y_edges[iy]), int(y_edges[iy + 1]), int(x_edges[ix]), int(x_edges[ix + 1])
        block, interior, window = blocks[iy, ix, 0], None, ((y0, y1), (x0, x1))
        if halo:
            hy0, hy1, hx0, hx1 = max(0, y0 - halo), min(ny, y1 + halo), max(0, x0 - halo), min(nx, x1 + halo)
            block = arr[hy0:hy1, hx0:hx1]
            interior = (slice(y0 - hy0, y1 - hy0), slice(x0 - hx0, x1 - hx0))
            window = ((hy0, hy1), (hx0, hx1))
        held = None
        if shared is not None:
            labels = None if regions is None else np.asarray(regions)[slice(*window[0]), slice(*window[1])]
            if halo:      # the haloed block decomposed as one image, holding the cube's estimate
                held = {"shared_image": {"shared": shared.names, "estimate": shared, "window": window,
                                         "regions": labels}}
            else:
                hold, err = shared.hold(labels, window)
                held = {"hold": hold, "hold_stderr": err}
        tasks.append(dask.delayed(_solve_and_sink, pure=False)(
            block, iy, ix, sink, param_shapes, solve_kwargs, interior, held,
            dask_key_name=f"decompose-chunk-{token}-{iy}-{ix}"))
    return tasks


class _ChunkDone(Callback):
    def __init__(self, on_done):
        super().__init__()
        self._on_done = on_done

    def _posttask(self, key, result, dsk, state, worker_id):
        if isinstance(key, str) and key.startswith("decompose-chunk-"):
            self._on_done(result)


def run_tasks(tasks, *, client=None, num_workers: int | None = None, on_done=None) -> list[dict]:
    """Run chunk tasks; call ``on_done(summary)`` as each chunk finishes.

    Parameters
    ----------
    tasks : list of Delayed from :func:`chunk_tasks`
    client : distributed.Client, optional
        Run on this cluster; otherwise on the local threaded scheduler.
    num_workers : int, optional
        Threads of the local scheduler (default: dask's, the number of cores).

    Returns
    -------
    list of the chunk summaries, in completion order.  An exception in any chunk (or
    KeyboardInterrupt) propagates; chunks finished before it have been sunk.  On the threaded
    scheduler the chunks running then are finished (and sunk) first; on a cluster the pending
    ones are cancelled (:func:`decomposition.store.cluster.wait_for_running` waits for those its
    workers are still running).
    """
    done: list[dict] = []

    def record(summary):
        done.append(summary)
        if on_done is not None:
            on_done(summary)

    if not tasks:
        return done
    if client is None:
        # the threaded scheduler itself, not its name: given the name, dask imports
        # dask.distributed to look for a running client (0.2 s on every run)
        pool = getattr(dask.threaded, "ContextAwareThreadPoolExecutor", ThreadPoolExecutor)(
            int(num_workers or dask.system.CPU_COUNT))
        try:
            with _ChunkDone(record):
                dask.compute(*tasks, scheduler=dask.threaded.get, pool=pool)
        finally:
            # after an error or Ctrl-C the chunks already running still finish and are sunk (a
            # thread cannot be stopped): wait for them, so that a caller counting what is on disk
            # afterwards counts everything; the chunks not started never start
            pool.shutdown(wait=True, cancel_futures=True)
        return done
    from distributed import as_completed

    futures = client.compute(tasks)
    try:
        for fut in as_completed(futures):
            record(fut.result())
    except BaseException:
        client.cancel(futures)
        raise
    return done


def count_nonfinite_pixels(cube, chunks=None) -> int:
    """Number of pixels of a (y, x, t) cube with any NaN or inf sample (one pass over the cube)."""
    arr = cube if isinstance(cube, da.Array) else da.from_array(cube, chunks=chunks or "auto")
    if arr.dtype.kind != "f":
        return 0
    return int((~da.isfinite(arr).all(axis=-1)).sum().compute())
