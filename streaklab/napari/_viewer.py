"""Viewer-side operations without Qt: add a store's layers or a result store's maps to a viewer
(a ``napari.Viewer`` or a headless ``napari.components.ViewerModel``), refresh live layers, and
map a click to a pixel of a result store."""
from __future__ import annotations

import numpy as np

from .layers import is_live, map_layer, refresh_layer, store_layers

__all__ = ["add_store", "add_maps", "refresh_layers", "result_paths", "pixel_at"]


def _add(viewer, tuples) -> list:
    from napari.layers import Layer

    return [viewer.add_layer(Layer.create(*tup)) for tup in tuples]


def add_store(viewer, path) -> list:
    """Add the layers of the streaklab store at ``path`` (as the reader gives them); returns them."""
    return _add(viewer, store_layers(path))


def add_maps(viewer, path, names) -> list:
    """Add maps ``names`` of the result store at ``path`` (:func:`.layers.map_layer`) as layers."""
    from .layers import open_result

    store = open_result(str(path))
    done = store.done_mask()
    return _add(viewer, [map_layer(store, name, done=done) for name in names])


def refresh_layers(viewer) -> int:
    """Give every live streaklab layer of ``viewer`` the data of its store as it is now (see
    :func:`.layers.refresh_layer`); returns how many layers changed."""
    changed = 0
    for layer in list(viewer.layers):
        new = refresh_layer(layer.metadata)
        if new is not None:
            layer.data = new[0]
            layer.metadata = new[1]["metadata"]
            changed += 1
    return changed


def any_live(viewer) -> bool:
    """Whether some streaklab layer of ``viewer`` shows a store that is still being written."""
    return any(is_live(layer.metadata) for layer in viewer.layers)


def result_paths(viewer) -> list[str]:
    """The result stores shown in ``viewer`` (by the layers' ``streaklab_path``), in layer order."""
    paths = []
    for layer in viewer.layers:
        md = layer.metadata
        if md.get("streaklab_kind") == "decomposition" and md["streaklab_path"] not in paths:
            paths.append(md["streaklab_path"])
    return paths


def pixel_at(viewer, path, world_position) -> tuple[int, int] | None:
    """(y, x) indices of the pixel of result store ``path`` under ``world_position`` (a click's
    position in the viewer's world coordinates), or None when it falls outside the store."""
    layer = next((ly for ly in viewer.layers if ly.metadata.get("streaklab_path") == path), None)
    if layer is None:
        return None
    pos = np.asarray(world_position, np.float64)[-layer.ndim:]
    data = np.asarray(layer.world_to_data(pos), np.float64)
    y, x = int(np.round(data[-2])), int(np.round(data[-1]))
    ny, nx = layer.data.shape[-2:]
    return (y, x) if 0 <= y < ny and 0 <= x < nx else None
