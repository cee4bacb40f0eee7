"""The plugin's Qt widgets: the pixel inspector and the maps widget.

Their data come from :mod:`.layers` and :mod:`._viewer` (no Qt there); these classes only lay
them out and draw them.
"""
from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from qtpy.QtCore import QTimer
from qtpy.QtWidgets import (QAbstractItemView, QComboBox, QLabel, QListWidget, QPushButton, QVBoxLayout,
                            QWidget)

from ._viewer import add_maps, any_live, pixel_at, refresh_layers, result_paths
from .layers import open_result, map_names, pixel_view

__all__ = ["PixelInspector", "MapsWidget", "REFRESH_MS"]

#: how often the widgets re-read the ``done`` flags of stores still being written (ms)
REFRESH_MS = 1000


class _StoreChooser(QComboBox):
    """The result stores shown in the viewer, kept up to date as layers come and go."""

    def __init__(self, viewer, parent=None):
        super().__init__(parent)
        self._viewer = viewer
        viewer.layers.events.inserted.connect(self.update_paths)
        viewer.layers.events.removed.connect(self.update_paths)
        self.update_paths()

    def update_paths(self, *_):
        current = self.currentText()
        self.clear()
        self.addItems(result_paths(self._viewer))
        if current:
            i = self.findText(current)
            if i >= 0:
                self.setCurrentIndex(i)


class PixelInspector(QWidget):
    """Click a pixel (of any layer of a result store) to see its measured profile, the fit, each
    component and the residual, and its quality flags by name.

    While a shown store is still being written, a timer (:data:`REFRESH_MS`) refreshes the
    streaklab layers as chunks land and redraws the pixel shown.
    """

    def __init__(self, napari_viewer):
        super().__init__()
        self.viewer = napari_viewer
        self.chooser = _StoreChooser(napari_viewer, self)
        self.label = QLabel("click a pixel of a result store's layer")
        self.label.setWordWrap(True)
        self.figure = Figure(figsize=(5, 3.5), layout="constrained")
        self.canvas = FigureCanvasQTAgg(self.figure)
        lay = QVBoxLayout(self)
        lay.addWidget(self.chooser)
        lay.addWidget(self.canvas)
        lay.addWidget(self.label)
        self.pixel: tuple[int, int] | None = None
        self.view: dict | None = None
        napari_viewer.mouse_drag_callbacks.append(self._on_click)
        self.timer = QTimer(self)
        self.timer.setInterval(REFRESH_MS)
        self.timer.timeout.connect(self.refresh)
        self.timer.start()

    @property
    def path(self) -> str | None:
        return self.chooser.currentText() or None

    def _on_click(self, viewer, event):
        if self.path is None:
            return
        yx = pixel_at(viewer, self.path, event.position)
        if yx is not None:
            self.show_pixel(*yx)

    def show_pixel(self, y: int, x: int) -> dict:
        """Draw pixel (y, x) (indices) of the chosen result store; returns what was drawn
        (:func:`.layers.pixel_view`)."""
        if self.path is None:
            raise ValueError("no result store is shown in the viewer")
        v = pixel_view(self.path, y, x)
        self.pixel, self.view = (int(y), int(x)), v
        self.figure.clear()
        ax = self.figure.add_subplot()
        t = v["t"]
        if v["measured"] is not None:
            ax.plot(t, v["measured"], color="0.55", lw=0, marker=".", ms=3, label="measured")
        ax.plot(t, v["fit"], color="k", lw=1.0, label="fit")
        ax.plot(t, v["direct"], color="tab:blue", lw=1.2, label="direct")
        ax.plot(t, v["sss"], color="tab:orange", lw=1.2, label="subsurface")
        for r, prof in enumerate(v["ir"]):
            if np.isfinite(prof).any() and np.nanmax(np.abs(prof)) > 0:
                ax.plot(t, prof, color=f"C{2 + r}", lw=1.0, label=f"inter-reflection r{r + 2}")
        if np.any(v["background"]):
            ax.plot(t, v["background"], color="0.3", lw=0.8, ls="-.", label="background")
        if v["residual"] is not None:
            ax.plot(t, v["residual"], color="tab:red", lw=0.8, ls="--", label="residual")
        ax.set_xlabel("time (ps)")
        ax.set_ylabel(f"signal ({v['units']})")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
        self.canvas.draw_idle()
        flags = ", ".join(v["flag_names"]) or "none"
        self.label.setText(f"{v['title']}" if not v["done"] else f"{v['title']}\nflags: {flags}")
        return v

    def refresh(self) -> int:
        """Refresh the viewer's live streaklab layers and redraw the pixel shown when they changed;
        returns how many layers changed."""
        if not any_live(self.viewer):
            return 0
        changed = refresh_layers(self.viewer)
        if changed and self.pixel is not None and self.path is not None:
            self.show_pixel(*self.pixel)
        return changed


class MapsWidget(QWidget):
    """Add component and parameter maps of a result store as layers, with the store's scales."""

    def __init__(self, napari_viewer):
        super().__init__()
        self.viewer = napari_viewer
        self.chooser = _StoreChooser(napari_viewer, self)
        self.names = QListWidget(self)
        self.names.setSelectionMode(QAbstractItemView.ExtendedSelection)
        self.button = QPushButton("Add maps", self)
        self.button.clicked.connect(self.add_selected)
        lay = QVBoxLayout(self)
        lay.addWidget(self.chooser)
        lay.addWidget(self.names)
        lay.addWidget(self.button)
        self.chooser.currentTextChanged.connect(self._list_maps)
        self._list_maps(self.chooser.currentText())
        self.timer = QTimer(self)
        self.timer.setInterval(REFRESH_MS)
        self.timer.timeout.connect(lambda: any_live(self.viewer) and refresh_layers(self.viewer))
        self.timer.start()

    def _list_maps(self, path):
        self.names.clear()
        if path:
            self.names.addItems(map_names(open_result(path)))

    def add_selected(self) -> list:
        """Add the selected maps as layers; returns them."""
        path = self.chooser.currentText()
        names = [item.text() for item in self.names.selectedItems()]
        return add_maps(self.viewer, path, names) if path and names else []
