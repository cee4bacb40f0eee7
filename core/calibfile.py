"""A calibration on disk: a standalone Zarr store, a ``.npz`` file, or a named group of a cube store.

The instrument response (:mod:`core.irfstore`) and the sweep calibration
(:mod:`reconstruction.sweep`) are stored the same way: a few arrays and the group's attributes,
``streaklab_kind`` naming what they are.  :func:`save_calibration` writes either form staged
beside the path and renamed into place; :func:`open_calibration` finds the calibration at a
path and says in one line why a path holds none.
"""
from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from .staging import staged_output

__all__ = ["FoundCalibration", "save_calibration", "open_calibration"]


def save_calibration(path, *, kind: str, arrays: dict, attributes: dict, write_group: Callable,
                     overwrite: bool = False, inputs=()) -> Path:
    """Write a calibration to ``path``: a ``.npz`` file of ``arrays`` plus ``attributes`` (a JSON
    string) when ``path`` ends in ``.npz``, else a Zarr store filled by ``write_group(group)``.
    Staged and renamed into place; an existing ``path`` needs ``overwrite`` and is replaced only
    when it is of ``kind`` (or a plain file); ``inputs`` are never written over."""
    path = Path(path)
    with staged_output(path, overwrite=overwrite, inputs=inputs, kind="file" if path.suffix == ".npz" else kind) as tmp:
        if path.suffix == ".npz":
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays, attributes=np.array(json.dumps(attributes)))
        else:
            write_group(zarr.open_group(str(tmp), mode="w"))
    return path


@dataclass
class FoundCalibration:
    """What :func:`open_calibration` found: the ``.npz`` file's ``arrays`` and ``attributes``, or
    the Zarr ``group`` that holds the calibration; ``where`` names it in messages."""

    where: str
    group: zarr.Group | None = None
    arrays: dict | None = None
    attributes: dict | None = None


def open_calibration(path, *, kind: str, group_name: str, array_names: tuple, error: type, what: str) -> FoundCalibration:
    """Find the calibration of ``kind`` at ``path``: a ``.npz`` file holding ``array_names``, a store
    of that kind, or the ``group_name`` group of another store (a cube).  Anything else raises
    ``error`` with one line naming the path and ``what`` was looked for."""
    path = Path(path)
    if not os.path.exists(path):
        raise error(f"{what} {path}: no such file or directory")
    if path.suffix == ".npz" or path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {name: z[name] for name in array_names}
                attributes = json.loads(str(z["attributes"]))
        except (OSError, ValueError, KeyError) as exc:
            raise error(f"{path} is not {_article(what)} .npz file: {exc}") from None
        return FoundCalibration(str(path), arrays=arrays, attributes=attributes)
    try:
        g = zarr.open_group(str(path), mode="r", use_consolidated=False)
    except Exception as exc:  # zarr raises several types for "not a group"
        raise error(f"{path} is not a Zarr group: {exc}") from None
    found = g.attrs.get("streaklab_kind")
    if found != kind and group_name in g and isinstance(g[group_name], zarr.Group):
        return FoundCalibration(f"{path}/{group_name}", group=g[group_name])
    if found != kind:
        hint = f" (a streaklab {found!r} store with no '{group_name}' group)" if found else ""
        raise error(f"{path} holds no {what}{hint}")
    return FoundCalibration(str(path), group=g)


def _article(what: str) -> str:
    return ("an " if what[:1] in "aeiou" else "a ") + what
