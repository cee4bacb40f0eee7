"""The npe2 reader: streaklab stores (Zarr v3 groups with ``streaklab_kind`` run, cube or
decomposition) as napari layers; any other path is declined (None) so other readers may take it."""
from __future__ import annotations

from .layers import STORE_KINDS, store_kind, store_layers


def get_reader(path):
    """A function reading ``path`` (a path or a list of paths) into layer data tuples, or None
    when any of them is no streaklab run, cube or result store."""
    paths = [path] if isinstance(path, (str, bytes)) or not hasattr(path, "__iter__") else list(path)
    if not paths or any(store_kind(str(p).rstrip("/")) not in STORE_KINDS for p in paths):
        return None
    return read_stores


def read_stores(path) -> list[tuple]:
    """Layer data tuples of every store in ``path`` (one path or a list), see
    :func:`streaklab.napari.layers.store_layers`."""
    paths = [path] if isinstance(path, (str, bytes)) or not hasattr(path, "__iter__") else list(path)
    layers = []
    for p in paths:
        layers += store_layers(str(p).rstrip("/"))
    return layers
