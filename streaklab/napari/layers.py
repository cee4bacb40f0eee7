"""Layer data of streaklab stores for napari, without napari or Qt.

Everything here returns napari's *layer data tuples* ``(data, kwargs, layer_type)``: plain Python
and dask, so the reader, the maps and the live refresh are tested without a viewer, and napari
turns each tuple into a layer (``Layer.create(*tup)``).

Axes.  napari shows the last two axes of a layer and puts sliders on the others, so every array
is presented with its image axes last: a cube or a component as (t, y, x), inter-reflections as
(r, t, y, x), a map as (y, x), a streak image as (line, frame, x, row).  The arrays stay on disk:
each layer's data is a dask array over the store's Zarr array (transposed and masked lazily), so
opening a store reads only its coordinates and its ``done`` flags.

Scales.  An axis whose coordinate is uniform gets its step as ``scale`` and its first value as
``translate``, with the coordinate's ``units`` (time in ps from ``time_bin_ps``/``t0_ps``; scan
lines in the cube's y units, e.g. deg; slit pixels); an axis whose coordinate is not uniform (scan
angles taken unevenly) is shown by index, and the layer's metadata says so
(``streaklab_axes``).  Index axes (units ``"1"``) are shown in napari's default pixel units.
A run store's ``row`` axis is the camera's, not yet resampled to uniform time: it is shown by row
index, its times are in the metadata (``time_ps``).

Live stores.  Readers trust only ``done`` (docs/layout.md): pixels of a result store whose chunk is
not done, and lines of a run store that are not done, are shown as NaN (0 for the run's uint16
counts).  :func:`refresh_layer` re-reads the ``done`` flags of a layer's store and, when they have
changed, gives the layer data built anew (new dask keys, so no cached chunk of the old data is
reused); a widget's timer calls it while a capture or a decomposition writes the store.
"""
from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np

__all__ = ["STORE_KINDS", "store_kind", "store_layers", "open_result", "map_names", "map_layer", "pixel_view",
           "refresh_layer", "is_live", "SIGNAL_MAPS"]

#: the kinds of store the reader opens (group attribute ``streaklab_kind``)
STORE_KINDS = ("run", "cube", "decomposition")

#: parameter maps a result store's layers include when it is opened (others: :func:`map_layer`)
SIGNAL_MAPS = ("direct_delay_ps", "direct_amplitude", "sss_alpha_per_ps", "sss_amplitude", "rms_residual")

#: component maps: name -> the component cube it integrates over time
_COMPONENT_MAPS = {"direct_integral": "direct", "sss_integral": "sss", "ir_integral": "ir",
                   "residual_rms_map": "residual"}

_names = itertools.count()
_UNIFORM_RTOL = 1e-6


def store_kind(path) -> str | None:
    """The ``streaklab_kind`` of the Zarr v3 group at ``path`` (read from its ``zarr.json`` alone),
    or None when ``path`` is no directory, no Zarr v3 group, or a group without the attribute."""
    meta = Path(path) / "zarr.json"
    try:
        doc = json.loads(meta.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("node_type") != "group":
        return None
    kind = (doc.get("attributes") or {}).get("streaklab_kind")
    return kind if isinstance(kind, str) else None


# ----- axes ------------------------------------------------------------------------------------
def _napari_units(units: str | None) -> str | None:
    """A store's units string as napari takes it for an axis (pint's names: "ps", "deg",
    "pixel"); None (napari's default, pixel) for index axes ("1") and units pint does not know."""
    if units in (None, "", "1"):
        return None
    import pint

    try:
        parsed = pint.get_application_registry().parse_expression(units)
    except Exception:  # a units string pint does not know: the axis is shown in pixels
        return None
    return units if hasattr(parsed, "units") else None


def _axis(values, units: str | None, label: str) -> dict:
    """scale, translate, units and how an axis of coordinate ``values`` is shown."""
    v = np.asarray(values, np.float64)
    if v.size >= 2:
        step = np.diff(v)
        uniform = bool(np.all(np.isfinite(v)) and step[0] > 0
                       and np.allclose(step, step[0], rtol=_UNIFORM_RTOL, atol=0.0))
        if uniform:
            return {"label": label, "scale": float(step[0]), "translate": float(v[0]),
                    "units": _napari_units(units), "shown": f"by coordinate ({units})"}
        return {"label": label, "scale": 1.0, "translate": 0.0, "units": None,
                "shown": f"by index: its coordinate ({units}) is not uniform"}
    first = float(v[0]) if v.size and np.isfinite(v[0]) else 0.0
    return {"label": label, "scale": 1.0, "translate": first if units not in (None, "1") else 0.0,
            "units": _napari_units(units), "shown": f"by coordinate ({units})"}


def _index_axis(label: str, shown: str = "by index") -> dict:
    return {"label": label, "scale": 1.0, "translate": 0.0, "units": None, "shown": shown}


def _kwargs(axes: list[dict], name: str, metadata: dict, **extra) -> dict:
    units = [a["units"] for a in axes]
    kw = {"name": name, "scale": tuple(a["scale"] for a in axes),
          "translate": tuple(a["translate"] for a in axes),
          "axis_labels": tuple(a["label"] for a in axes),
          "metadata": {**metadata, "streaklab_axes": {a["label"]: a["shown"] for a in axes}}}
    if any(u is not None for u in units):
        kw["units"] = tuple(u if u is not None else "pixel" for u in units)
    kw.update(extra)
    return kw


def _lazy(array):
    """A dask array over a Zarr array with keys of its own (see the module's "Live stores")."""
    import dask.array as da

    return da.from_zarr(array, name=f"streaklab-{next(_names)}-{array.basename}")


def _attrs(array) -> dict:
    return {"units": str(array.attrs.get("units", "")), "long_name": str(array.attrs.get("long_name", ""))}


# ----- stores ----------------------------------------------------------------------------------
def store_layers(path) -> list[tuple]:
    """Layer data tuples of the streaklab store at ``path`` (a run, cube or result store).

    Raises the store's own error (:class:`~acquisition.runstore.RunStoreError`,
    :class:`~reconstruction.cubestore.CubeStoreError`,
    :class:`~decomposition.store.resultstore.ResultStoreError`) naming what is wrong, and
    ``ValueError`` for a path that is no streaklab store of those kinds.
    """
    kind = store_kind(path)
    if kind == "run":
        return _run_layers(str(path))
    if kind == "cube":
        return _cube_layers(str(path))
    if kind == "decomposition":
        return _result_layers(str(path))
    what = f"a streaklab {kind!r} store" if kind else "no streaklab store"
    raise ValueError(f"{path} is {what}; the reader opens run, cube and result stores")


def _meta(path: str, kind: str, array: str, attrs: dict, **more) -> dict:
    return {"streaklab_path": str(Path(path).resolve()), "streaklab_kind": kind, "streaklab_array": array,
            "units": attrs.get("units", ""), "long_name": attrs.get("long_name", ""), **more}


def _run_layers(path: str) -> list[tuple]:
    from acquisition.runstore import open_run

    run = open_run(path)
    return [_run_streaks(run), _run_dark(run)]


def _run_streaks(run, done=None) -> tuple:
    import dask.array as da

    s = run["streaks"]
    done = run.done_mask() if done is None else done
    data = da.where(da.from_array(done, chunks=1)[:, None, None, None], _lazy(s), np.uint16(0))
    x_axis = _axis(run.group["x"][...], "pixel", "x") if "x" in run.group else _index_axis("x")
    axes = [_index_axis("line", "by index, in acquisition order"), _index_axis("frame"), x_axis,
            _index_axis("row", "by camera row: its times (time_ps) are not uniform in general")]
    time_ps = run.group["time_ps"][...].tolist() if "time_ps" in run.group else None
    meta = _meta(run.path, "run", "streaks", _attrs(s), done=done.tolist(), time_ps=time_ps)
    return data, _kwargs(axes, f"{Path(run.path).name}: streaks", meta), "image"


def _run_dark(run) -> tuple:
    d = run["dark"]
    data = _lazy(d).mean(axis=0, dtype=np.float32)
    axes = [_axis(run.group["x"][...], "pixel", "x") if "x" in run.group else _index_axis("x"),
            _index_axis("row", "by camera row: its times (time_ps) are not uniform in general")]
    meta = _meta(run.path, "run", "dark", {**_attrs(d), "long_name": f"mean of {d.shape[0]} dark frames"},
                 dark_done=run.dark_done())
    return data, _kwargs(axes, f"{Path(run.path).name}: dark (mean)", meta, visible=False), "image"


def _txy_axes(group, t_axis: np.ndarray) -> list[dict]:
    return [_axis(t_axis, "ps", "t"), _axis(group["y"][...], str(group["y"].attrs.get("units", "pixel")), "y"),
            _axis(group["x"][...], str(group["x"].attrs.get("units", "pixel")), "x")]


def _cube_layers(path: str) -> list[tuple]:
    from reconstruction.cubestore import open_cube

    cube = open_cube(path)
    axes = _txy_axes(cube.group, cube.time_axis_ps())
    data = _lazy(cube.array).transpose(2, 0, 1)
    meta = _meta(cube.path, "cube", "cube", _attrs(cube.array))
    return [(data, _kwargs(axes, f"{Path(cube.path).name}: cube", meta), "image")]


def open_result(path: str):
    """The result store at ``path``, opened read-only (:func:`~decomposition.store.resultstore.open_result_store`)."""
    from decomposition.store.resultstore import open_result_store

    return open_result_store(path)


def _result_layers(path: str) -> list[tuple]:
    store = open_result(path)
    done = store.done_mask()
    layers = []
    if store.write_components:
        layers += [_component(store, name, done) for name in ("direct", "sss", "ir", "residual")]
    layers += [map_layer(store, name, done=done) for name in SIGNAL_MAPS]
    layers.append(_flags(store, done))
    return layers


def _masked(store, name: str, done: np.ndarray):
    """The store's array ``name`` (y, x, ...) as dask, NaN where ``done`` is false."""
    import dask.array as da

    a = _lazy(store.group[name])
    mask = da.from_array(done, chunks=store.chunks).reshape(done.shape + (1,) * (a.ndim - 2))
    return da.where(mask, a, np.nan)


def _component(store, name: str, done: np.ndarray) -> tuple:
    arr = store.group[name]
    axes = _txy_axes(store.group, store.time_axis_ps())
    data = _masked(store, name, done)
    if name == "ir":                                   # (y, x, r, t) -> (r, t, y, x)
        data = data.transpose(2, 3, 0, 1)
        axes = [_axis(store.group["r"][...], "1", "r")] + axes
    else:                                              # (y, x, t) -> (t, y, x)
        data = data.transpose(2, 0, 1)
    meta = _meta(store.path, "decomposition", name, _attrs(arr), done=done.tolist())
    blending = "additive" if name != "residual" else "translucent"
    return data, _kwargs(axes, f"{Path(store.path).name}: {name}", meta, blending=blending,
                         visible=name == "direct"), "image"


def _flags(store, done: np.ndarray) -> tuple:
    import dask.array as da

    arr = store.group["flags"]
    data = da.where(da.from_array(done, chunks=store.chunks), _lazy(arr), np.uint16(0))
    axes = _txy_axes(store.group, store.time_axis_ps())[1:]
    from streaklab.report import _flag_table

    meta = _meta(store.path, "decomposition", "flags", _attrs(arr), done=done.tolist(),
                 flag_names={str(bit): name for bit, name in _flag_table().items()})
    return data, _kwargs(axes, f"{Path(store.path).name}: flags", meta, visible=False), "labels"


def map_names(store) -> list[str]:
    """The maps :func:`map_layer` makes of a result store: every parameter (``ir_*`` with a slot
    axis r), ``rms_residual``, ``valid``, and with stored components their integrals over time
    (``direct_integral``, ``sss_integral``, ``ir_integral``; signal units x ps) and
    ``residual_rms_map`` (the same as ``rms_residual``, from the stored residual)."""
    names = list(store.param_keys) + ["rms_residual", "valid"]
    if store.write_components:
        names += list(_COMPONENT_MAPS)
    return names


def map_layer(store, name: str, *, done: np.ndarray | None = None) -> tuple:
    """A (y, x) map of a result store (or (r, y, x) for the inter-reflections' parameters) as an
    image layer data tuple with the store's scales and units; NaN where the chunk is not done.

    ``store`` is an opened :class:`~decomposition.store.resultstore.ResultStore` or its path.
    Raises ValueError naming the maps there are when ``name`` is none of :func:`map_names`."""
    store = open_result(store) if isinstance(store, (str, Path)) else store
    if name not in map_names(store):
        raise ValueError(f"{store.path} has no map {name!r}; its maps are {', '.join(map_names(store))}")
    done = store.done_mask() if done is None else done
    axes = _txy_axes(store.group, store.time_axis_ps())[1:]
    tb = float(store.attrs["time_bin_ps"])
    if name in _COMPONENT_MAPS:
        comp = _COMPONENT_MAPS[name]
        data = _masked(store, comp, done)
        signal = str(store.attrs.get("units", "counts"))
        if name == "residual_rms_map":
            data = (data ** 2).mean(axis=-1) ** 0.5
            attrs = {"units": signal, "long_name": "root-mean-square of the stored residual"}
        else:
            data = data.sum(axis=-1) * tb
            if comp == "ir":
                data = data.sum(axis=-1)               # over the slots
            attrs = {"units": f"{signal} ps", "long_name": f"{_attrs(store.group[comp])['long_name']}, "
                                                           f"integrated over time"}
    else:
        arr = store.group[name]
        attrs = _attrs(arr)
        data = _masked(store, name, done)
        if name == "valid":
            data = data.astype(np.float32)
        if data.ndim == 3:                             # (y, x, r) -> (r, y, x)
            data = data.transpose(2, 0, 1)
            axes = [_axis(store.group["r"][...], "1", "r")] + axes
    meta = _meta(store.path, "decomposition", name, attrs, done=done.tolist(), map=True)
    return data, _kwargs(axes, f"{Path(store.path).name}: {name}", meta, visible=False,
                         colormap="viridis"), "image"


# ----- live ------------------------------------------------------------------------------------
def is_live(metadata: dict) -> bool:
    """Whether a layer's store may still change under it: a run or result store whose ``done``
    flags (as the layer was built) are not all true."""
    done = metadata.get("done")
    return metadata.get("streaklab_kind") in ("run", "decomposition") and done is not None \
        and not bool(np.all(done))


def refresh_layer(metadata: dict) -> tuple | None:
    """Re-read the ``done`` flags of a layer's store: the layer's new data tuple when they differ
    from those the layer was built with, None when nothing has landed (or the layer is no live
    streaklab layer)."""
    if not is_live(metadata):
        return None
    path, kind, name = metadata["streaklab_path"], metadata["streaklab_kind"], metadata["streaklab_array"]
    if kind == "run":
        from acquisition.runstore import open_run

        run = open_run(path)
        done = run.done_mask()
        if np.array_equal(done, metadata["done"]) or name != "streaks":
            return None
        return _run_streaks(run, done)
    store = open_result(path)
    done = store.done_mask()
    if np.array_equal(done, metadata["done"]):
        return None
    if metadata.get("map"):
        return map_layer(store, name, done=done)
    if name == "flags":
        return _flags(store, done)
    return _component(store, name, done)


# ----- the pixel inspector's data --------------------------------------------------------------
def pixel_view(store, y: int, x: int) -> dict:
    """What the pixel inspector shows for pixel (y, x) (indices) of a result store.

    ``store`` is an opened :class:`~decomposition.store.resultstore.ResultStore` or its path.

    Returns
    -------
    dict: the profiles of :func:`streaklab.report.pixel_profiles` (``t`` ps; ``measured``,
    ``direct``, ``sss``, ``background``, ``fit``, ``residual`` (nt,); ``ir`` (R, nt); signal
    units), ``flags`` (int, the bit field), ``flag_names`` (list of str, empty for none), ``title``
    (the report's :func:`~streaklab.report.pixel_title`: coordinates and flags), ``done`` and
    ``valid`` (bool), ``units`` (signal units).  A pixel whose chunk is not done has NaN profiles
    and no flags: nothing of it is on disk yet.

    Raises ValueError when (y, x) lies outside the store.
    """
    from streaklab.report import flag_names, pixel_profiles, pixel_title

    store = open_result(store) if isinstance(store, (str, Path)) else store
    ny, nx, nt = store.shape
    y, x = int(y), int(x)
    if not (0 <= y < ny and 0 <= x < nx):
        raise ValueError(f"pixel (y={y}, x={x}) is outside {store.path} ({ny} x {nx} pixels)")
    done = bool(store.done_mask()[y, x])
    units = str(store.attrs.get("units", "counts"))
    if not done:
        nan = np.full(nt, np.nan)
        return {"t": store.time_axis_ps(), "measured": None, "direct": nan, "sss": nan.copy(),
                "ir": np.full((store.n_ir, nt), np.nan), "background": np.zeros(nt), "fit": nan.copy(),
                "residual": nan.copy(), "flags": 0, "flag_names": [], "done": False, "valid": False,
                "units": units, "title": f"y index {y}, x index {x}: not computed yet"}
    view = pixel_profiles(store, y, x)
    bits = int(store.group["flags"][y, x])
    view.update(flags=bits, flag_names=flag_names(bits), title=pixel_title(store, y, x), done=True,
                valid=bool(store.group["valid"][y, x]), units=units)
    return view
