"""Figures and a text summary of a decomposition result store (matplotlib, Agg backend).

* ``frames.png``    decomposed frames of each component at one time (cf. the ConvSCD paper's
  Figs. 4(c) and 5(c)): measured, direct, subsurface scattering, inter-reflections, residual.
* ``maps.png``      maps of the direct delay (depth), sss attenuation alpha, sss amplitude and
  the fit's rms residual.
* ``profiles.png``  time profiles of a few pixels: measured profile, each fitted component and the
  residual (cf. Fig. 4(b)), the time axis zoomed to the signal (:func:`signal_extent`).

A store decomposed from a synthetic cube that carries its ``truth`` group (``streaklab simulate``,
:func:`truth_of`) has the truth beside the estimate: true maps beside the estimated ones on one
colour scale, and the true components in the profile panels.
* ``summary.txt``   what was decomposed, how, and what was found.

Component frames and profiles come from the stored component cubes; a store written with
``--no-components`` has them rendered from its parameters with the forward model instead, with
the instrument response the store was decomposed with when it holds one (its ``irf`` group,
:meth:`decomposition.store.resultstore.ResultStore.response`), else with the Gaussian PSF.  The
summary says which response the fits were drawn with (:func:`response_text`).

Maps are drawn as xarray's ``DataArray.plot()`` draws a (y, x) array: cells centred on the
store's coordinates, x increasing to the right and y upwards, axes in the coordinates' units.
Colour limits are the 1st and 99th percentiles of each panel's nonzero values (taking in 0 where
it has zeros), so a component present in a few pixels, or one, is drawn at full scale; a frame
panel whose every value is zero, or at rounding level (:data:`EMPTY_PANEL_FRACTION`) below the
strongest panel of its figure, is shown flat and titled "none at this time".  Profile titles give the pixel's coordinates in the maps' units
(:func:`coordinate_text`: one number of decimals per axis) and its quality flags by name.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["make_report", "choose_time_ps", "choose_pixels", "summary_text", "measured_profiles", "frames_figure",
           "maps_figure", "profiles_figure", "colour_limits", "cell_edges", "flag_text", "flag_names",
           "pixel_title", "pixel_profiles",
           "coordinate_text", "coordinate_decimals", "signal_extent", "truth_of",
           "rendered_components", "response_text", "RENDER_BLOCK_PIXELS"]

# One-way depth per ps of round-trip delay: c / 2 in mm/ps.
_MM_PER_PS_DEPTH = 0.299792458 / 2.0


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _units(store) -> str:
    return str(store.attrs.get("units", "counts"))


def _valid(store) -> np.ndarray:
    return np.asarray(store.group["valid"][...], bool) & store.done_mask()


def choose_time_ps(store) -> float:
    """A time showing the scene: the bin nearest the median direct delay of the decomposed pixels
    (the first bin with the most signal if no direct reflection was found)."""
    t = store.time_axis_ps()
    delay = np.asarray(store.group["direct_delay_ps"][...])
    delay = delay[_valid(store) & np.isfinite(delay)]
    if delay.size:
        return float(t[np.argmin(np.abs(t - np.median(delay)))])
    return float(t[len(t) // 2])


def choose_pixels(store, n: int = 3) -> list[tuple[int, int]]:
    """Up to ``n`` informative pixels: the strongest direct, sss and inter-reflection pixels,
    then pixels of median fit quality."""
    valid = _valid(store)
    picks: list[tuple[int, int]] = []

    def add_argmax(values):
        v = np.where(valid & np.isfinite(values), values, -np.inf)
        if np.isfinite(v).any():
            yx = tuple(int(i) for i in np.unravel_index(np.argmax(v), v.shape))
            if yx not in picks:
                picks.append(yx)

    add_argmax(np.asarray(store.group["direct_amplitude"][...]))
    add_argmax(np.asarray(store.group["sss_amplitude"][...]))
    if store.n_ir:
        add_argmax(np.asarray(store.group["ir_amplitude"][..., 0]))
    rms = np.asarray(store.group["rms_residual"][...])
    order = np.argsort(np.where(valid & np.isfinite(rms), rms, np.inf), axis=None)
    n_ok = int((valid & np.isfinite(rms)).sum())
    for k in order[n_ok // 2:n_ok] if n_ok else []:
        if len(picks) >= n:
            break
        yx = tuple(int(i) for i in np.unravel_index(k, rms.shape))
        if yx not in picks:
            picks.append(yx)
    return picks[:n]


#: pixels rendered at a time when a report renders components from parameters (bounds the memory
#: of a response's atoms: a few MB per bin of the response's padded window)
RENDER_BLOCK_PIXELS = 4096


def rendered_components(store, ys, xs, it=None, *, irf="stored"):
    """Components of a region rendered from the store's parameters with the forward model.

    Parameters
    ----------
    store : ResultStore
    ys, xs : slice
        The (y, x) region.
    it : int, optional
        One time index (default: every bin).
    irf : "stored", InstrumentResponse or None
        The response to render with: "stored" (default) the store's own
        (:meth:`~decomposition.store.resultstore.ResultStore.response`; the Gaussian PSF when it holds
        none), None the Gaussian PSF with each component's ``*_sigma_ps``.

    Returns
    -------
    dict: ``direct``, ``sss`` (ny', nx', t) and ``ir`` (ny', nx', R, t), signal units (without the
    time axis when ``it`` is given).
    """
    from core.model import render_components

    from core.irf import InstrumentResponse

    if isinstance(irf, str) and irf == "stored":
        response = store.response()
    elif irf is None or isinstance(irf, InstrumentResponse):
        response = irf
    else:
        raise ValueError(f"irf must be 'stored', an InstrumentResponse or None, got {irf!r}")
    params = store.params(ys, xs)
    lead = np.shape(params["direct_delay_ps"])
    t = store.time_axis_ps()
    tb = float(store.attrs["time_bin_ps"])
    n_t, t0 = (t.size, float(t[0])) if it is None else (1, float(t[it]))
    flat = {k: np.asarray(v).reshape((-1,) + np.shape(v)[len(lead):]) for k, v in params.items()}
    n = int(np.prod(lead, dtype=np.int64))
    parts = {"direct": [], "sss": [], "interreflections": []}
    for lo in range(0, max(n, 1), RENDER_BLOCK_PIXELS):
        block = {k: v[lo:lo + RENDER_BLOCK_PIXELS] for k, v in flat.items()}
        c = render_components(block, n_t, tb, t0, irf=response)
        for k in parts:
            parts[k].append(c[k])
    out = {"direct": np.concatenate(parts["direct"]).reshape(lead + (n_t,)),
           "sss": np.concatenate(parts["sss"]).reshape(lead + (n_t,)),
           "ir": np.concatenate(parts["interreflections"]).reshape(lead + (store.n_ir, n_t))}
    if it is not None:
        out = {k: v[..., 0] for k, v in out.items()}
    return out


def _components_at(store, ys, xs, it=None):
    """Component arrays of a region: dict direct, sss, ir (summed over slots unless a single
    time is asked for), each (..., t) or (...) at time index ``it``; from the store or rendered
    (:func:`rendered_components`, with the store's response)."""
    g = store.group
    if store.write_components:
        if it is None:
            return {"direct": g["direct"][ys, xs], "sss": g["sss"][ys, xs], "ir": g["ir"][ys, xs],
                    "residual": g["residual"][ys, xs]}
        return {"direct": g["direct"][ys, xs, it], "sss": g["sss"][ys, xs, it],
                "ir": g["ir"][ys, xs, :, it], "residual": g["residual"][ys, xs, it]}
    return dict(rendered_components(store, ys, xs, it), residual=None)


def response_text(store) -> str:
    """Which instrument response the report's fits are drawn with, one line: the store's own
    response (its ``irf`` group), the Gaussian PSF, or -- for a store that records a response
    (``attrs["irf"]``) without holding it, written before result stores kept it -- what that
    means for the figures."""
    rec = dict(store.attrs.get("irf") or {})
    how = ("from the stored components" if store.write_components else "rendered from the parameters")
    irf = store.response()
    if irf is not None:
        name = (irf.model or {}).get("name")
        what = f"{'the ' + name + ' model' if name else 'a measured'} response"
        src = f", from {rec['source']}" if rec.get("source") else ""
        return (f"instrument response: {what} kept in the result store ({irf.n_samples} samples of "
                f"{irf.time_step_ps:g} ps, FWHM {irf.fwhm_ps():.3g} ps{src}); fits drawn {how} with it")
    if rec.get("kind") == "response":
        sha = str(rec.get("samples_sha256", "?"))[:12]
        if store.write_components:
            return (f"instrument response: a response (sha256 {sha}...) that this store records but does not "
                    f"hold (written before result stores kept it); fits drawn from the stored components, "
                    f"which the decomposition rendered with it")
        return (f"instrument response: a response (sha256 {sha}...) that this store records but does not "
                f"hold (written before result stores kept it); fits rendered from the parameters with the "
                f"Gaussian PSF of each component's Gaussian-equivalent sigma instead, an approximation")
    return f"instrument response: the Gaussian PSF (each component's own sigma); fits drawn {how}"


def measured_profiles(store, ys, xs, it=None):
    """The decomposed input over a region: (..., t), or (...) at time index ``it``; None if unknown.

    Read from the source named in the store's attributes (only the region, and only bin ``it``
    if given: a frame of a big cube never loads the cube); if the source has moved, rebuilt from
    the stored components plus the background (where the store has one) plus the residual when
    those were written."""
    tsel = slice(None) if it is None else int(it)
    src = store.attrs.get("source", {})
    path = src.get("path")
    try:
        if path and os.path.exists(path):
            if src.get("kind") == "npy":
                data = np.load(path, mmap_mode="r")
                data = data[None] if data.ndim == 2 else data
                return np.asarray(data[ys, xs, tsel], dtype=np.float64)
            from reconstruction.cubestore import open_cube

            return np.asarray(open_cube(path).array[ys, xs, tsel], dtype=np.float64)
    except Exception:  # an unreadable or replaced source: fall back below
        pass
    if store.write_components:
        c = _components_at(store, ys, xs, it)
        ir = np.asarray(c["ir"]).sum(axis=-2 if it is None else -1)  # over the slots r
        total = np.asarray(c["direct"], np.float64) + c["sss"] + ir + c["residual"]
        b = _background(store, ys, xs)
        return total + (b if it is not None else b[..., None])
    return None


def _background(store, ys, xs) -> np.ndarray:
    """The constant offset of a region's pixels (signal units), 0 where none was found (NaN) or
    the store has no ``background``: the part of the fit that is no rendered component."""
    if "background" not in store.param_keys:
        return np.zeros(np.shape(store.group["valid"][ys, xs]))
    b = np.asarray(store.group["background"][ys, xs], np.float64)
    return np.where(np.isfinite(b), b, 0.0)


def cell_edges(centres) -> np.ndarray:
    """Edges of the cells centred on ``centres`` (n + 1 values): midpoints between neighbours, the
    ends half a step out -- where xarray's ``.plot()`` puts them, so uneven scan angles are drawn
    where they were taken."""
    c = np.asarray(centres, np.float64)
    if c.size == 1:
        return np.array([c[0] - 0.5, c[0] + 0.5])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[c[0] - (mid[0] - c[0])], mid, [c[-1] + (c[-1] - mid[-1])]])


def colour_limits(data, *, symmetric=False, floor=None):
    """(vmin, vmax) for an image: the 1st and 99th percentiles of its finite nonzero values, the
    range widened to take in 0 where the image has exact zeros.

    Percentiles over the nonzero values keep a hot pixel from washing out a full image, yet show
    a sparse one: a component present in a handful of pixels (or in one) sets its own limits and
    is drawn, instead of vanishing under percentiles taken mostly over its zeros.  The limits
    never pass the image's own extremes.

    ``floor`` (> 0) is the smallest range worth showing, set from the scale of the data the image
    is compared with (a frame: the strongest panel of its figure): an image whose values all lie
    within it -- an empty component, or numerical noise at 1e-19 of the signal -- gets limits of
    that size and shows flat instead of stretching its noise over the whole colour map.  Without
    ``floor`` the image's own magnitude sets it (a constant map shows flat, not as noise).
    """
    a = np.asarray(data, np.float64)
    a = a[np.isfinite(a)]
    nz = a[a != 0]
    if nz.size:
        lo, hi = (float(v) for v in np.percentile(nz, [1, 99]))
        if nz.size < a.size:             # exact zeros: the range takes in 0
            lo, hi = min(lo, 0.0), max(hi, 0.0)
    else:
        lo, hi = 0.0, 0.0
    if floor is None or not np.isfinite(floor) or floor <= 0:
        scale = max(abs(lo), abs(hi))
        floor = 1e-6 * scale if scale > 0 else 1.0
    if symmetric:
        m = max(abs(lo), abs(hi), float(floor))
        return -m, m
    if hi - lo >= floor:
        return lo, hi
    if lo >= -floor and hi <= floor:     # nothing above the floor: an empty panel, zero at the bottom
        return (0.0, float(floor)) if lo >= 0 else (-float(floor), float(floor))
    mid = 0.5 * (lo + hi)
    return mid - 0.5 * floor, mid + 0.5 * floor


def _coord(store, name):
    arr = store.group[name]
    return np.asarray(arr[...], np.float64), str(arr.attrs.get("units", "pixel"))


def _image(ax, fig, data, store, title, label, cmap="viridis", symmetric=False, pad=0.05, floor=None,
           limits=None):
    """A (y, x) map drawn as xarray's ``.plot()`` draws it: cells centred on the coordinates, x
    increasing to the right and y upwards; colour limits ``limits`` or :func:`colour_limits`."""
    plt = _plt()
    y, y_units = _coord(store, "y")
    x, x_units = _coord(store, "x")
    cm = plt.get_cmap(cmap).with_extremes(bad="0.85")
    vmin, vmax = limits if limits is not None else colour_limits(data, symmetric=symmetric, floor=floor)
    xb, yb = cell_edges(x), cell_edges(y)
    mesh = ax.pcolormesh(xb, yb, np.ma.masked_invalid(data), cmap=cm, vmin=vmin, vmax=vmax, shading="flat")
    ax.set_xlim(xb.min(), xb.max())
    ax.set_ylim(yb.min(), yb.max())
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(f"x ({x_units})")
    ax.set_ylabel(f"y ({y_units})")
    cb = fig.colorbar(mesh, ax=ax, shrink=0.9, pad=pad)
    cb.set_label(label)
    return cb


def _save(fig, path) -> Path:
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return Path(path)


#: A frame panel whose largest value is below this fraction of the strongest panel of its figure
#: counts as empty ("none at this time"): zero to within float32 rounding of the signal, so that a
#: component present in a single pixel, however faint beside the rest, is never called absent.
EMPTY_PANEL_FRACTION = 1e-6


def frames_figure(store, time_ps: float):
    """The frames figure (matplotlib Figure): one panel per component at the bin nearest ``time_ps``."""
    plt = _plt()
    t = store.time_axis_ps()
    it = int(np.argmin(np.abs(t - time_ps)))
    ny, nx, _ = store.shape
    comps = _components_at(store, slice(None), slice(None), it)
    measured = measured_profiles(store, slice(None), slice(None), it)
    panels = []
    if measured is not None:
        panels.append(("measured", measured))
    panels += [("direct", comps["direct"]), ("subsurface scattering", comps["sss"]),
               ("inter-reflections (all)", np.asarray(comps["ir"]).sum(axis=-1) if store.n_ir
                else np.zeros((ny, nx)))]
    if comps["residual"] is not None:
        panels.append(("residual", comps["residual"]))
    done = store.done_mask()
    panels = [(name, np.where(done, np.asarray(img, np.float64), np.nan)) for name, img in panels]
    # One scale for the figure: the strongest panel's; a panel whose every value is at rounding
    # level below it is shown as empty.
    scale = max((_robust_max(img) for _, img in panels), default=0.0)
    floor = EMPTY_PANEL_FRACTION * scale if scale > 0 else None
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.4), squeeze=False)
    units = _units(store)
    for ax, (name, img) in zip(axes[0], panels):
        resid = name == "residual"
        peak = float(np.nanmax(np.abs(img))) if np.isfinite(img).any() else 0.0
        empty = peak == 0 or (floor is not None and peak < floor)
        _image(ax, fig, img, store, f"{name} (none at this time)" if empty else name, f"signal ({units})",
               cmap="coolwarm" if resid else "magma", symmetric=resid, floor=floor)
    how = "" if store.write_components else (
        " (components rendered from parameters with the "
        + ("stored instrument response)" if store.has_response else "Gaussian PSF)"))
    fig.suptitle(f"decomposed frames at t = {t[it]:.1f} ps{how}")
    fig.tight_layout()
    return fig


def _robust_max(img) -> float:
    """The magnitude a panel is drawn to: the 99th percentile of its finite nonzero |values|."""
    a = np.abs(np.asarray(img, np.float64))
    a = a[np.isfinite(a) & (a != 0)]
    return float(np.percentile(a, 99)) if a.size else 0.0


def plot_frames(store, time_ps: float, path) -> Path:
    return _save(frames_figure(store, time_ps), path)


def maps_figure(store):
    """The parameter-maps figure (matplotlib Figure).

    A store decomposed from a synthetic cube with its ``truth`` (:func:`truth_of`) shows each
    estimated map beside the true one on the same colour scale, and the direct delay's error
    (estimate - truth) beside the rms residual."""
    plt = _plt()
    g = store.group
    done = store.done_mask()
    truth = truth_of(store)
    units = _units(store)
    specs = [
        ("direct_delay_ps", "direct delay (depth)", "delay (ps); 1 ps = 0.15 mm depth", "viridis"),
        ("sss_alpha_per_ps", "subsurface attenuation alpha", "alpha (1/ps)", "cividis"),
        ("sss_amplitude", "subsurface amplitude b", f"b ({units})", "magma"),
        ("rms_residual", "fit rms residual", f"rms residual ({units})", "gray_r"),
    ]
    if truth is None:
        fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
        cells = [(ax, spec, None) for ax, spec in zip(axes.ravel(), specs)]
    else:
        fig, axes = plt.subplots(4, 2, figsize=(10, 14))
        cells = [(axes[i, 0], spec, None) for i, spec in enumerate(specs)]
        cells += [(axes[i, 1], spec, "truth") for i, spec in enumerate(specs[:3])]
    for ax, (key, title, label, cmap), which in cells:
        data = np.where(done, np.asarray(g[key][...], np.float64), np.nan)
        limits = None
        if truth is not None and key in truth:
            true = np.where(done, np.asarray(truth[key][...], np.float64), np.nan)
            limits = colour_limits(np.concatenate([data.ravel(), true.ravel()]))  # one scale for both
            if which == "truth":
                data, title = true, f"true {title}"
            else:
                title = f"estimated {title}"
        cb = _image(ax, fig, data, store, title, label, cmap, pad=0.2 if key == "direct_delay_ps" else 0.05,
                    limits=limits)
        if key == "direct_delay_ps":
            sec = cb.ax.secondary_yaxis("left", functions=(lambda d: d * _MM_PER_PS_DEPTH,
                                                            lambda z: z / _MM_PER_PS_DEPTH))
            sec.set_ylabel("depth c·t/2 (mm)")
    if truth is not None:
        err = np.where(done, np.asarray(g["direct_delay_ps"][...], np.float64)
                       - np.asarray(truth["direct_delay_ps"][...], np.float64), np.nan)
        _image(axes[3, 1], fig, err, store, "direct delay error (estimate - truth)", "error (ps)", "coolwarm",
               symmetric=True)
    fig.suptitle(f"parameter maps ({store.attrs.get('method', '?')})"
                 + (" beside the simulated truth" if truth is not None else "")
                 + "; grey = absent or not computed")
    fig.tight_layout()
    return fig


def plot_maps(store, path) -> Path:
    return _save(maps_figure(store), path)


def _flag_table() -> dict:
    """bit -> name of every flag a result store's ``flags`` may hold: the solver's
    (decomposition.FLAG_NAMES) and the store's own OUT_OF_RANGE."""
    from decomposition import FLAG_NAMES
    from decomposition.store.resultstore import OUT_OF_RANGE

    table = {int(bit): str(name) for bit, name in FLAG_NAMES.items()}
    table[OUT_OF_RANGE] = "OUT_OF_RANGE"
    return dict(sorted(table.items()))


def flag_help() -> dict:
    """flag name -> one line on what it means and what to do (decomposition.flags.FLAG_HELP and the
    store's OUT_OF_RANGE_HELP)."""
    from decomposition.flags import FLAG_HELP
    from decomposition.store.resultstore import OUT_OF_RANGE_HELP

    return {**{flag.name: text for flag, text in FLAG_HELP.items()}, "OUT_OF_RANGE": OUT_OF_RANGE_HELP}


def flag_names(bits: int) -> list[str]:
    """Quality flags of a result store's pixel by name, lowest bit first (the solver's
    decomposition.FLAG_NAMES and the store's own OUT_OF_RANGE); bits no table names as one entry
    "bits 0x..."; [] for 0."""
    bits = int(bits)
    table = _flag_table()
    names = [name for bit, name in sorted(table.items()) if bits & bit]
    known = 0
    for bit in table:
        known |= bit
    if bits & ~known:
        names.append(f"bits {bits & ~known:#x}")
    return names


def flag_text(bits: int) -> str:
    """Quality flags of a result store's pixel by name (:func:`flag_names`), e.g. "POOR_FIT, SPIKE";
    "none" for 0."""
    return ", ".join(flag_names(bits)) or "none"


def coordinate_decimals(values) -> int:
    """Decimals that print every coordinate of an axis alike and tell neighbours apart: the fewest
    (0 to 6) that keep each finite value within 5 % of the axis's smallest step of its rounded
    value (0 for whole pixels or line indices, 1 for mirror angles 4/3 deg apart)."""
    v = np.unique(np.asarray(values, np.float64)[np.isfinite(np.asarray(values, np.float64))])
    if v.size == 0:
        return 0
    step = float(np.min(np.diff(v))) if v.size > 1 else (abs(float(v[0])) or 1.0)
    for d in range(7):
        if np.max(np.abs(np.round(v, d) - v)) <= 0.05 * step:
            return d
    return 6


def coordinate_text(values, i: int, units: str) -> str:
    """Coordinate ``i`` of the axis ``values`` (in ``units``) as every figure prints it: with the
    axis's :func:`coordinate_decimals`, and its units unless they are pixels ("-0.7 deg", "6.0 deg",
    "x = 29")."""
    d = coordinate_decimals(values)
    text = f"{float(values[i]) + 0.0:.{d}f}"
    if text.lstrip("-").strip("0.") == "":     # no "-0.0"
        text = text.lstrip("-")
    return text if units == "pixel" else f"{text} {units}"


def pixel_title(store, y: int, x: int) -> str:
    """A profile's title: where the pixel is, in the maps' coordinates and units, and its flags."""
    yc, y_units = _coord(store, "y")
    xc, x_units = _coord(store, "x")
    note = "" if store.group["valid"][y, x] else "; not decomposed: non-finite input"
    return (f"y = {coordinate_text(yc, y, y_units)}, x = {coordinate_text(xc, x, x_units)} (--pixels {y},{x}); "
            f"flags: {flag_text(store.group['flags'][y, x])}{note}")


#: a profile figure's time axis spans where some component of its pixels exceeds this fraction of
#: its largest value, widened by :data:`PROFILE_MARGIN` of that span on either side (at least 5 bins)
PROFILE_SIGNAL_FRACTION = 0.01
PROFILE_MARGIN = 0.25


def truth_of(store):
    """The ground truth of the synthetic cube the store was decomposed from: the source cube's
    ``truth`` group (``streaklab simulate``) as a zarr group, when the source is still there and
    its truth covers the store's pixels and time bins; else None."""
    src = store.attrs.get("source", {})
    path = src.get("path")
    if src.get("kind") != "cube" or not path or not os.path.exists(path):
        return None
    try:
        from reconstruction.cubestore import open_cube

        g = open_cube(path).group
        truth = g["truth"] if "truth" in g else None
        if truth is None or "direct" not in truth or "t" not in truth:
            return None
        ny, nx, nt = store.shape
        if tuple(truth["direct"].shape) != (ny, nx, nt) or not np.allclose(truth["t"][...], store.time_axis_ps()):
            return None
        return truth
    except Exception:  # an unreadable or replaced source: no truth shown
        return None


def _truth_profiles(truth, y, x) -> dict:
    """The true components of one pixel: name -> (t,) profile (inter-reflections per slot)."""
    out = {"direct": np.asarray(truth["direct"][y, x], np.float64),
           "subsurface": np.asarray(truth["sss"][y, x], np.float64)}
    if "ir" in truth:
        for r, prof in enumerate(np.asarray(truth["ir"][y, x], np.float64)):
            out[f"inter-reflection r{r + 2}"] = prof
    return out


def signal_extent(t, profiles, *, fraction=PROFILE_SIGNAL_FRACTION, margin=PROFILE_MARGIN):
    """(t_lo, t_hi) for a profile plot: where any of ``profiles`` (each (t,)) exceeds ``fraction``
    of the largest |value| among them, widened by ``margin`` of that span (at least 5 bins) on
    either side and kept inside the time window; the whole window when nothing is nonzero."""
    t = np.asarray(t, np.float64)
    step = float(t[1] - t[0]) if t.size > 1 else 1.0
    whole = (float(t[0]) - 0.5 * step, float(t[-1]) + 0.5 * step)
    a = np.abs(np.array([np.nan_to_num(np.asarray(p, np.float64)) for p in profiles])) if profiles else None
    if a is None or a.size == 0 or not (a.max() > 0):
        return whole
    on = np.flatnonzero((a > fraction * a.max()).any(axis=0))
    lo, hi = float(t[on[0]]), float(t[on[-1]])
    pad = max(margin * (hi - lo), 5 * step)
    return max(whole[0], lo - pad), min(whole[1], hi + pad)


def pixel_profiles(store, y: int, x: int) -> dict:
    """One pixel's time profiles as the profile figures draw them.

    Returns
    -------
    dict of float64 arrays: ``t`` (nt,) bin centres in ps; ``measured`` (nt,) the decomposed input
    (None when neither the source nor the stored components give it, :func:`measured_profiles`);
    ``direct``, ``sss`` (nt,) and ``ir`` (R, nt) the fitted components (stored, or rendered from the
    parameters, :func:`_components_at`); ``background`` (nt,) the constant offset where the store
    has one (zeros otherwise); ``fit`` (nt,) their sum; ``residual`` (nt,) the stored residual, or
    measured - fit when the components were not stored (None without a measured profile).
    Signal units of the store.
    """
    ys, xs = slice(y, y + 1), slice(x, x + 1)
    c = _components_at(store, ys, xs)
    meas = measured_profiles(store, ys, xs)
    t = store.time_axis_ps()
    direct = np.asarray(c["direct"][0, 0], np.float64)
    sss = np.asarray(c["sss"][0, 0], np.float64)
    ir = np.asarray(c["ir"][0, 0], np.float64).reshape(store.n_ir, t.size)
    background = np.full(t.size, float(_background(store, ys, xs)[0, 0]))
    fit = direct + sss + ir.sum(axis=0) + background
    measured = None if meas is None else np.asarray(meas[0, 0], np.float64)
    if c["residual"] is not None:
        residual = np.asarray(c["residual"][0, 0], np.float64)
    else:
        residual = None if measured is None else measured - fit
    return {"t": t, "measured": measured, "direct": direct, "sss": sss, "ir": ir, "background": background,
            "fit": fit, "residual": residual}


def profiles_figure(store, pixels):
    """The time-profiles figure (matplotlib Figure) of ``pixels`` [(y index, x index), ...].

    The time axis spans the signal (:func:`signal_extent` of every fitted and true component
    shown); a store decomposed from a synthetic cube that carries its ``truth`` shows the true
    components beside the fitted ones (thin dashed, same colours).  Legends sit beside the
    panels, never over a curve."""
    plt = _plt()
    t = store.time_axis_ps()
    units = _units(store)
    truth = truth_of(store)
    fig, axes = plt.subplots(len(pixels), 1, figsize=(10.5, 2.6 * len(pixels)), squeeze=False, sharex=True)
    drawn = []
    for ax, (y, x) in zip(axes[:, 0], pixels):
        p = pixel_profiles(store, y, x)
        if p["measured"] is not None:
            ax.plot(t, p["measured"], color="0.55", lw=0, marker=".", ms=3, label="measured")
        ax.plot(t, p["direct"], color="tab:blue", lw=1.4, label="direct")
        ax.plot(t, p["sss"], color="tab:orange", lw=1.4, label="subsurface")
        drawn += [p["direct"], p["sss"]]
        colours = {"direct": "tab:blue", "subsurface": "tab:orange"}
        for r in range(store.n_ir):
            prof = p["ir"][r]
            colours[f"inter-reflection r{r + 2}"] = f"C{2 + r}"
            if np.isfinite(prof).any() and np.nanmax(np.abs(prof)) > 0:
                ax.plot(t, prof, lw=1.2, color=f"C{2 + r}", label=f"inter-reflection r{r + 2}")
                drawn.append(prof)
        ax.plot(t, p["fit"], color="k", lw=0.8, ls=":", label="sum of components")
        if p["residual"] is not None:
            ax.plot(t, p["residual"], color="tab:red", lw=0.8, ls="--", label="residual")
        if truth is not None:
            for r, (name, prof) in enumerate(_truth_profiles(truth, y, x).items()):
                if np.isfinite(prof).any() and np.nanmax(np.abs(prof)) > 0:
                    ax.plot(t, prof, lw=1.0, ls=(0, (4, 2)), color=colours.get(name, f"C{r}"), alpha=0.8,
                            label=f"true {name}")
                    drawn.append(prof)
        ax.set_ylabel(f"signal ({units})")
        ax.set_title(pixel_title(store, y, x), fontsize=10)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlim(*signal_extent(t, drawn))
    axes[-1, 0].set_xlabel("time (ps)")
    fig.tight_layout()
    return fig


def plot_profiles(store, pixels, path) -> Path:
    return _save(profiles_figure(store, pixels), path)


def _pct(a, q):
    return np.percentile(a, q) if a.size else np.nan


def shared_line(record: dict) -> str:
    """One line of the shared estimates (``SharedEstimate.record()``, a result store's ``shared``
    attribute) with their errors."""
    parts = []
    if record.get("psf_sigma_ps") is not None:
        parts.append(f"PSF sigma {record['psf_sigma_ps']:.4g} +- {record['psf_sigma_ps_stderr']:.2g} ps"
                     + (" (map centre)" if record.get("psf_map") else ""))
    if record.get("response_stretch") is not None:
        parts.append(f"response time scale {record['response_stretch']:.4g} +- "
                     f"{record['response_stretch_stderr']:.2g}")
    if record.get("delay_ps") is not None:
        parts.append(f"{record['delay_key'].split('_')[0]} onset {record['delay_ps']:.6g} +- "
                     f"{record['delay_ps_stderr']:.2g} ps")
    for label, value in record.get("sss_alpha_per_ps", {}).items():
        where = f" (region {label})" if record.get("regions") else ""
        parts.append(f"sss alpha{where} {value:.4g} +- {record['sss_alpha_per_ps_stderr'][label]:.2g} /ps")
    return "shared: " + "; ".join(parts)


def summary_text(store) -> str:
    """A short plain-text summary of a result store."""
    g, a = store.group, store.attrs
    ny, nx, nt = store.shape
    done = store.done_mask()
    valid = _valid(store)
    n = ny * nx
    src = a.get("source", {})
    lines = [
        f"result store: {store.path}",
        f"source: {src.get('path', '?')} ({src.get('kind', '?')}, shape {tuple(src.get('shape', ()))})",
        f"cube: {ny} x {nx} pixels x {nt} bins of {a['time_bin_ps']:g} ps (t0 = {a['t0_ps']:g} ps)",
        f"method: {a.get('method', '?')}; components searched: {','.join(a.get('components', []))}; "
        f"options: {a.get('options', {})}; streaklab {a.get('software_version', '?')}",
        f"pixels: {n}; done {int(done.sum())} ({100.0 * done.sum() / n:.1f}%); decomposed {int(valid.sum())}; "
        f"non-finite input {int((done & ~np.asarray(g['valid'][...], bool)).sum())}",
        response_text(store),
    ]
    if a.get("shared"):
        lines.append(shared_line(a["shared"]) + " (held in every pixel)")
    spatial = (a.get("job") or {}).get("spatial")
    if spatial:
        from decomposition.image import halo_pixels
        from decomposition.image.spatial import SpatialOptions

        # a store written by an older version may record options this one no longer has
        known = {k: v for k, v in spatial.items() if k in SpatialOptions.__dataclass_fields__}
        lines.append(f"spatial coupling: neighbours' answers as starts, {spatial['sweeps']} sweeps with an "
                     f"edge-preserving prior on the direct delays, pooled echoes and spikes (each chunk read with "
                     f"a halo of {halo_pixels(known)} pixels)")
    if not done.all():
        lines.append("INCOMPLETE: rerun 'streaklab decompose ... --resume' to finish")
    nv = max(int(valid.sum()), 1)
    dd = np.asarray(g["direct_delay_ps"][...])[valid]
    sa = np.asarray(g["sss_alpha_per_ps"][...])[valid]
    has_d = np.isfinite(dd)
    has_s = np.isfinite(sa)
    if store.n_ir:
        n_ir = np.isfinite(np.asarray(g["ir_delay_ps"][...])[valid]).sum(axis=-1)
    else:
        n_ir = np.zeros(int(valid.sum()), int)
    lines.append(f"found: direct in {100.0 * has_d.sum() / nv:.1f}% of decomposed pixels, "
                 f"sss in {100.0 * has_s.sum() / nv:.1f}%, "
                 f">=1 inter-reflection in {100.0 * (n_ir >= 1).sum() / nv:.1f}%"
                 + (f", >=2 in {100.0 * (n_ir >= 2).sum() / nv:.1f}%" if store.n_ir >= 2 else ""))
    if has_d.any():
        ds = np.asarray(g["direct_sigma_ps"][...])[valid][has_d]
        lo, hi = _pct(dd[has_d], 5), _pct(dd[has_d], 95)
        lines.append(f"direct delay: median {np.median(dd[has_d]):.2f} ps, 5-95% {lo:.2f} to {hi:.2f} ps "
                     f"(depth span {(hi - lo) * _MM_PER_PS_DEPTH:.2f} mm); "
                     f"sigma median {np.nanmedian(ds):.2f} ps")
    if has_s.any():
        lines.append(f"sss alpha: median {np.median(sa[has_s]):.4f} /ps, 5-95% {_pct(sa[has_s], 5):.4f} to "
                     f"{_pct(sa[has_s], 95):.4f} /ps")
    rms = np.asarray(g["rms_residual"][...])[valid]
    rms = rms[np.isfinite(rms)]
    if rms.size:
        lines.append(f"rms residual: median {np.median(rms):.4g} {_units(store)}, 95% {_pct(rms, 95):.4g}")
    flags = np.asarray(g["flags"][...])[valid].astype(np.int64)
    counts = {name: int(((flags & bit) != 0).sum()) for bit, name in _flag_table().items()}
    flagged = ", ".join(f"{name} {n}" for name, n in counts.items() if n)
    lines.append(f"flagged pixels: {int((flags != 0).sum())}" + (f" ({flagged})" if flagged else ""))
    help_text = flag_help()
    lines.extend(f"  {name}: {help_text[name]}" for name, n in counts.items() if n and name in help_text)
    return "\n".join(lines) + "\n"


def make_report(result_path, out_dir, *, time_ps: float | None = None, pixels=None) -> dict:
    """Write frames.png, maps.png, profiles.png and summary.txt into ``out_dir``.

    Parameters
    ----------
    result_path : str or Path
        A result store written by ``streaklab decompose``.
    out_dir : str or Path
        Folder for the figures (created).
    time_ps : float, optional
        Time of the frames (ps); default :func:`choose_time_ps`.
    pixels : list of (y, x), optional
        Pixels for the profile figure; default :func:`choose_pixels`.

    Returns
    -------
    dict: ``files`` (list of Paths), ``summary`` (str), ``time_ps``, ``pixels``.
    """
    from core.staging import check_output_location
    from decomposition.store.resultstore import open_result_store

    check_output_location(out_dir, inputs=(result_path,), folder=True)   # never into a store
    store = open_result_store(result_path)
    store.check_done_chunks_present()   # never draw a chunk marked done whose files are gone as if empty
    ny, nx, _ = store.shape
    if not store.done_mask().any():
        raise ValueError(f"{result_path} holds no finished chunk yet; nothing to report")
    if pixels:
        bad = [(y, x) for y, x in pixels if not (0 <= y < ny and 0 <= x < nx)]
        if bad:
            raise ValueError(f"pixels {bad} are outside the {ny} x {nx} image")
    else:
        pixels = choose_pixels(store)
    t = store.time_axis_ps()
    if time_ps is None:
        time_ps = choose_time_ps(store)
    elif not (t[0] - store.attrs["time_bin_ps"] <= time_ps <= t[-1] + store.attrs["time_bin_ps"]):
        raise ValueError(f"time {time_ps} ps is outside the cube's {t[0]:g} to {t[-1]:g} ps")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [plot_frames(store, time_ps, out / "frames.png"), plot_maps(store, out / "maps.png")]
    if pixels:
        files.append(plot_profiles(store, pixels, out / "profiles.png"))
    summary = summary_text(store)
    summary += f"frames at t = {float(t[np.argmin(np.abs(t - time_ps))]):.1f} ps; profiles of pixels {pixels}\n"
    (out / "summary.txt").write_text(summary)
    files.append(out / "summary.txt")
    return {"files": files, "summary": summary, "time_ps": float(time_ps), "pixels": list(pixels)}
