"""A phasor plot for napari: the (g, s) histogram of an image layer's decays, linked to the image.

:class:`PhasorWidget` computes the phasor (:func:`decomposition.phasor.phasor`) of every pixel of
a chosen image layer holding time profiles (a cube, or a result store's measured profiles: data
(..., t), the time axis chosen in the widget), shows their 2-D histogram with the universal
semicircle and lifetime ticks, and links plot and image both ways:

- a region selected on the plot (a circle dragged from its centre or a polygon clicked vertex by
  vertex; :meth:`PhasorWidget.select_region` and :meth:`PhasorWidget.select_polygon` do the same
  from code) marks its pixels with 1 in the Labels layer ``"phasor selection"``;
- the pixels of a Labels layer (non-zero) or a Shapes layer (inside any shape) chosen in the
  widget are drawn over the histogram (:meth:`PhasorWidget.highlight_layer`).

The logic -- phasors of an image, which pixels fall in a region, which phasors belong to a pixel
mask -- lives in the Qt-free functions of this module.  A Labels or Shapes layer is read in the
image layer's data coordinates; one of the image's full shape is reduced over the time axis (a
pixel is selected when any of its time planes is).
"""
from __future__ import annotations

import numpy as np
from qtpy.QtWidgets import (  # qtpy first: matplotlib's Qt canvas takes the binding it loaded
    QComboBox, QDoubleSpinBox, QFormLayout, QLabel, QPushButton, QSpinBox, QVBoxLayout, QWidget)
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon
from matplotlib.path import Path as _MplPath
from matplotlib.widgets import PolygonSelector

from decomposition.phasor import PhasorError, phasor, semicircle, window_frequency_per_ps

__all__ = ["PhasorWidget", "image_phasor", "pixels_in_circle", "pixels_in_polygon",
           "phasors_of_mask", "spatial_mask", "lifetime_ticks_ps"]

#: name of the Labels layer that shows a plot selection in the image
SELECTION_LAYER = "phasor selection"
#: most highlighted phasors drawn as points (a random subset above it)
MAX_POINTS = 20000


# ---------------------------------------------------------------------------------------------
# Qt-free logic
# ---------------------------------------------------------------------------------------------
def image_phasor(data, time_bin_ps: float, *, time_axis: int = -1, harmonic: int = 1):
    """Phasors of every pixel of an image of time profiles.

    Parameters
    ----------
    data : array_like, shape (..., L) with the time axis at ``time_axis``
        Bin contents (a cube's mean counts per frame, say).
    time_bin_ps : float
        Bin width in ps.

    Returns
    -------
    g, s : ndarray, the image's shape without the time axis, float64
        NaN where a pixel's profile holds NaN/inf samples (an unfinished line of a cube) or
        sums to zero.
    """
    x = np.moveaxis(np.asarray(data), time_axis, -1)
    if x.dtype.kind not in "uif":
        raise PhasorError(f"the layer's data must be real numbers, got dtype {x.dtype}")
    flat = x.reshape(-1, x.shape[-1])
    finite = np.isfinite(flat).all(axis=1)
    g = np.full(flat.shape[0], np.nan)
    s = np.full(flat.shape[0], np.nan)
    g[finite], s[finite] = phasor(flat[finite], time_bin_ps, harmonic=harmonic)
    return g.reshape(x.shape[:-1]), s.reshape(x.shape[:-1])


def pixels_in_circle(g, s, center, radius: float) -> np.ndarray:
    """Pixels whose phasor lies within ``radius`` of ``center`` = (g, s): bool, shape of ``g``."""
    gc, sc = (float(v) for v in center)
    if not (np.isfinite(radius) and radius > 0 and np.isfinite(gc) and np.isfinite(sc)):
        raise PhasorError(f"a circle needs a finite centre and a positive radius, got {center!r}, {radius!r}")
    with np.errstate(invalid="ignore"):
        return np.hypot(np.asarray(g) - gc, np.asarray(s) - sc) <= radius  # NaN -> False


def pixels_in_polygon(g, s, vertices) -> np.ndarray:
    """Pixels whose phasor lies inside the polygon ``vertices`` (n, 2) of (g, s): bool, shape of ``g``."""
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3 or not np.isfinite(v).all():
        raise PhasorError(f"a polygon needs at least 3 finite (g, s) vertices, got shape {v.shape}")
    g = np.asarray(g, dtype=float)
    s = np.asarray(s, dtype=float)
    ok = np.isfinite(g) & np.isfinite(s)
    inside = np.zeros(g.shape, dtype=bool)
    inside[ok] = _MplPath(v).contains_points(np.column_stack([g[ok], s[ok]]))
    return inside


def spatial_mask(selection, image_shape, time_axis: int = -1) -> np.ndarray:
    """A pixel mask (the image's shape without the time axis) from a selection array.

    ``selection`` is either of that spatial shape, or of the image's full shape (a Labels layer
    made over the image; shape masks rasterised at its shape), reduced over the time axis: a
    pixel is selected when it is non-zero in any time plane.
    """
    sel = np.asarray(selection)
    image_shape = tuple(image_shape)
    axis = time_axis % len(image_shape)
    spatial = image_shape[:axis] + image_shape[axis + 1:]
    if sel.shape == spatial:
        return sel != 0
    if sel.shape == image_shape:
        return np.any(sel != 0, axis=axis)
    raise PhasorError(f"a selection of shape {sel.shape} fits neither the image {image_shape} "
                      f"nor its pixels {spatial}")


def phasors_of_mask(g, s, mask):
    """The finite phasors (g, s), 1-D, of the pixels where ``mask`` (shape of ``g``) is true."""
    g = np.asarray(g)
    s = np.asarray(s)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != g.shape:
        raise PhasorError(f"a pixel mask of shape {mask.shape} does not match the phasor image {g.shape}")
    keep = mask & np.isfinite(g) & np.isfinite(s)
    return g[keep], s[keep]


def lifetime_ticks_ps(frequency_per_ps: float) -> np.ndarray:
    """Round lifetimes (1, 2, 5 x 10^k ps) spread over the semicircle at this frequency
    (omega tau from 0.1 to 10), for tick marks."""
    omega = 2 * np.pi * frequency_per_ps
    lo, hi = 0.1 / omega, 10.0 / omega
    ticks = [m * 10.0 ** e for e in range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))) + 1)
             for m in (1, 2, 5)]
    return np.array([t for t in ticks if lo <= t <= hi])


def _broadcast_mask(mask, image_shape, time_axis):
    """The spatial mask as uint8 labels of the image's full shape (a read-only view, no copy)."""
    labels = np.expand_dims(mask.astype(np.uint8), time_axis % len(image_shape))
    return np.broadcast_to(labels, tuple(image_shape))


# ---------------------------------------------------------------------------------------------
# the widget
# ---------------------------------------------------------------------------------------------


class PhasorWidget(QWidget):
    """Phasor plot of an image layer of time profiles, linked to the image both ways.

    Parameters
    ----------
    napari_viewer : napari.Viewer or napari.components.ViewerModel
        The viewer whose layers it reads and writes (napari passes it by this name when the
        widget is opened from the Plugins menu).

    Attributes
    ----------
    g, s : ndarray or None
        The phasors of the last computed layer (its shape without the time axis).
    selection : ndarray of bool or None
        The pixels of the last plot selection.
    """

    def __init__(self, napari_viewer, parent=None):
        super().__init__(parent)
        self.viewer = napari_viewer
        self.g = self.s = self.selection = None
        self.highlighted = (np.empty(0), np.empty(0))
        self._image = None
        self._region = None
        self._press = None

        self.image_combo = QComboBox()
        self.selection_combo = QComboBox()
        self.time_axis = QSpinBox()
        self.time_axis.setRange(-8, 7)
        self.time_axis.setValue(-1)
        self.time_bin = QDoubleSpinBox()
        self.time_bin.setDecimals(4)
        self.time_bin.setRange(1e-4, 1e6)
        self.time_bin.setValue(2.0)
        self.time_bin.setSuffix(" ps")
        self.harmonic = QSpinBox()
        self.harmonic.setRange(1, 16)
        self.mode = QComboBox()
        self.mode.addItems(["circle (drag from its centre)", "polygon (click the vertices)"])
        self.compute_button = QPushButton("Compute phasors")
        self.highlight_button = QPushButton("Show the layer's pixels on the plot")
        self.status = QLabel("")
        self.status.setWordWrap(True)

        self.figure = Figure(figsize=(4, 3.2), tight_layout=True)
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.axes = self.figure.add_subplot()

        form = QFormLayout()
        form.addRow("image layer", self.image_combo)
        form.addRow("time axis", self.time_axis)
        form.addRow("time bin (without metadata)", self.time_bin)
        form.addRow("harmonic", self.harmonic)
        form.addRow("select on the plot", self.mode)
        form.addRow("labels / shapes layer", self.selection_combo)
        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addWidget(self.compute_button)
        layout.addWidget(self.canvas)
        layout.addWidget(self.highlight_button)
        layout.addWidget(self.status)

        self.compute_button.clicked.connect(lambda: self.compute())
        self.highlight_button.clicked.connect(lambda: self.highlight_layer())
        self.mode.currentIndexChanged.connect(lambda _: self._arm_selector())
        for event in (napari_viewer.layers.events.inserted, napari_viewer.layers.events.removed):
            event.connect(lambda _=None: self._refresh_layers())
        self.canvas.mpl_connect("button_press_event", self._on_press)
        self.canvas.mpl_connect("button_release_event", self._on_release)
        self._polygon_selector = None
        self._refresh_layers()
        self._draw()

    # -- layers ------------------------------------------------------------------------------
    def _layers(self, kinds):
        return [layer for layer in self.viewer.layers if type(layer).__name__ in kinds]

    def _refresh_layers(self):
        for combo, kinds in ((self.image_combo, {"Image"}), (self.selection_combo, {"Labels", "Shapes"})):
            current = combo.currentText()
            combo.blockSignals(True)
            combo.clear()
            combo.addItems([layer.name for layer in self._layers(kinds) if layer.name != SELECTION_LAYER])
            if current:
                combo.setCurrentText(current)
            combo.blockSignals(False)

    def _layer(self, name, kinds):
        for layer in self._layers(kinds):
            if layer.name == name:
                return layer
        raise PhasorError(f"no {' or '.join(sorted(kinds))} layer named {name!r} in the viewer")

    # -- computing ---------------------------------------------------------------------------
    def compute(self, layer=None):
        """Compute and plot the phasors of ``layer`` (default: the one chosen in the widget).

        The bin width is the layer's ``metadata["time_bin_ps"]`` where it has one, else the
        widget's value."""
        layer = self._layer(self.image_combo.currentText(), {"Image"}) if layer is None else layer
        time_bin_ps = float(layer.metadata.get("time_bin_ps", self.time_bin.value()))
        axis = self.time_axis.value()
        data = np.asarray(layer.data)
        self.g, self.s = image_phasor(data, time_bin_ps, time_axis=axis, harmonic=self.harmonic.value())
        self._image = layer
        self._image_shape = data.shape
        self._axis = axis % data.ndim
        self.frequency_per_ps = window_frequency_per_ps(data.shape[self._axis], time_bin_ps, self.harmonic.value())
        self.selection = None
        self.highlighted = (np.empty(0), np.empty(0))
        n = int(np.isfinite(self.g).sum())
        self.status.setText(f"{layer.name}: {n} of {self.g.size} pixels have a phasor "
                            f"(f = {self.frequency_per_ps * 1e3:.4g} GHz, time bin {time_bin_ps:g} ps)")
        self._draw()
        self._arm_selector()
        return self.g, self.s

    def _require(self):
        if self.g is None:
            raise PhasorError("compute the phasors of an image layer first")

    # -- plot -> image -----------------------------------------------------------------------
    def select_region(self, center, radius):
        """Select the pixels whose phasor lies within ``radius`` of ``center`` = (g, s)."""
        self._require()
        self._region = ("circle", (float(center[0]), float(center[1])), float(radius))
        return self._set_selection(pixels_in_circle(self.g, self.s, center, radius))

    def select_polygon(self, vertices):
        """Select the pixels whose phasor lies inside the polygon ``vertices`` (n, 2) of (g, s)."""
        self._require()
        self._region = ("polygon", np.asarray(vertices, dtype=float))
        return self._set_selection(pixels_in_polygon(self.g, self.s, vertices))

    def _set_selection(self, mask):
        self.selection = mask
        labels = _broadcast_mask(mask, self._image_shape, self._axis)
        kwargs = {"scale": self._image.scale, "translate": self._image.translate}
        if SELECTION_LAYER in self.viewer.layers:
            layer = self.viewer.layers[SELECTION_LAYER]
            layer.data = labels
        else:
            layer = self.viewer.add_labels(labels, name=SELECTION_LAYER, opacity=0.5, **kwargs)
        self.status.setText(f"{int(mask.sum())} pixels selected on the plot")
        self._draw()
        return mask

    def _on_press(self, event):
        if event.inaxes is self.axes and self.mode.currentIndex() == 0 and self.g is not None:
            self._press = (event.xdata, event.ydata)

    def _on_release(self, event):
        if self._press is None:
            return
        start, self._press = self._press, None
        if event.inaxes is self.axes:
            radius = float(np.hypot(event.xdata - start[0], event.ydata - start[1]))
            if radius > 0:
                self.select_region(start, radius)

    def _arm_selector(self):
        if self._polygon_selector is not None:
            self._polygon_selector.disconnect_events()
            self._polygon_selector = None
        if self.mode.currentIndex() == 1 and self.g is not None:
            self._polygon_selector = PolygonSelector(self.axes, lambda verts: self.select_polygon(verts),
                                                     useblit=False)

    # -- image -> plot -----------------------------------------------------------------------
    def highlight_layer(self, layer=None):
        """Draw over the histogram the phasors of the pixels a Labels layer marks (non-zero) or a
        Shapes layer covers (default: the layer chosen in the widget)."""
        self._require()
        if layer is None:
            layer = self._layer(self.selection_combo.currentText(), {"Labels", "Shapes"})
        if type(layer).__name__ == "Shapes":
            masks = layer.to_masks(mask_shape=self._image_shape)
            selection = np.any(masks, axis=0) if len(masks) else np.zeros(self._image_shape, dtype=bool)
        else:
            selection = np.asarray(layer.data)
        return self.highlight_mask(spatial_mask(selection, self._image_shape, self._axis))

    def highlight_mask(self, mask):
        """Draw over the histogram the phasors of the pixels where ``mask`` is true."""
        self._require()
        self.highlighted = phasors_of_mask(self.g, self.s, mask)
        self.status.setText(f"{self.highlighted[0].size} phasors of the selected pixels shown")
        self._draw()
        return self.highlighted

    # -- drawing -----------------------------------------------------------------------------
    def _draw(self):
        ax = self.axes
        ax.clear()
        gc, sc = semicircle(201)
        ax.plot(gc, sc, color="0.4", lw=1)
        if self.g is not None:
            ok = np.isfinite(self.g) & np.isfinite(self.s)
            if ok.any():
                hist, ge, se = np.histogram2d(self.g[ok], self.s[ok], bins=200, range=[[-0.05, 1.05], [-0.05, 0.65]])
                shown = np.ma.masked_equal(hist.T, 0)
                ax.imshow(np.log1p(shown), origin="lower", extent=(ge[0], ge[-1], se[0], se[-1]),
                          aspect="auto", cmap="viridis", interpolation="nearest")
            ticks = lifetime_ticks_ps(self.frequency_per_ps)
            tg, ts = semicircle(lifetimes_ps=ticks, frequency_per_ps=self.frequency_per_ps)
            ax.plot(tg, ts, "o", color="0.4", ms=3)
            for t, x, y in zip(ticks, tg, ts):
                ax.annotate(f"{t:g} ps", (x, y), textcoords="offset points", xytext=(2, 3), fontsize=7)
            hg, hs = self.highlighted
            if hg.size:
                pick = np.random.default_rng(0).permutation(hg.size)[:MAX_POINTS]
                ax.plot(hg[pick], hs[pick], ".", color="tab:orange", ms=2, alpha=0.6)
            if self.selection is not None and self._region is not None:
                style = {"fill": False, "color": "tab:red", "lw": 1.5}
                kind, *shape = self._region
                ax.add_patch(Circle(*shape, **style) if kind == "circle" else Polygon(shape[0], closed=True, **style))
        ax.set_xlim(-0.05, 1.05)
        ax.set_ylim(-0.05, 0.65)
        ax.set_aspect("equal")
        ax.set_xlabel("g")
        ax.set_ylabel("s")
        self.canvas.draw_idle()
