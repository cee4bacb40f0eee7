"""The mirror simulator's link folders: ``/tmp/streaklab-mirror-*``, marked with their owner.

A :class:`~drivers.sim.mirror.MirrorSimulator` keeps its stable port link (the
``/dev/serial/by-id``-style symlink to the current pty) in a private folder
under the temporary directory.  A process that is killed cannot remove it, so
every folder is marked when it is made: a file :data:`MARKER` holding
:func:`core.owner.owner_record` (host, pid and the process's start time, so a
recycled pid is not mistaken for the owner).

:func:`remove_stale_link_dirs` removes exactly the folders that

* are named ``streaklab-mirror-*`` directly in the temporary directory,
* are real folders (not links) owned by this user,
* hold a readable streaklab marker whose process is gone (:func:`core.owner.owner_gone`), and
* contain nothing but the marker and the simulator's links,

and leaves everything else alone.
"""
from __future__ import annotations

import json
import os
import tempfile

from core.owner import owner_gone, owner_record

__all__ = ["PREFIX", "MARKER", "make_link_dir", "remove_link_dir", "remove_stale_link_dirs"]

PREFIX = "streaklab-mirror-"
MARKER = "owner.json"
_OWN_NAMES = {MARKER, "ttySMC100", "ttySMC100.new"}


def make_link_dir(parent: str | None = None) -> str:
    """Create a marked ``streaklab-mirror-*`` folder; returns its path."""
    path = tempfile.mkdtemp(prefix=PREFIX, dir=parent)
    with open(os.path.join(path, MARKER), "w", encoding="ascii") as f:
        json.dump(owner_record(), f)
    return path


def remove_link_dir(path: str) -> None:
    """Remove a folder made by :func:`make_link_dir` (only its own entries; idempotent)."""
    try:
        names = os.listdir(path)
    except FileNotFoundError:
        return
    for name in names:
        if name in _OWN_NAMES:
            try:
                os.unlink(os.path.join(path, name))
            except FileNotFoundError:
                pass
    try:
        os.rmdir(path)
    except OSError:
        pass   # something else was put there: leave it


def remove_stale_link_dirs(parent: str | None = None) -> list[str]:
    """Remove the marked link folders whose owning process is gone; return their paths."""
    parent = tempfile.gettempdir() if parent is None else parent
    removed = []
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return removed
    for entry in entries:
        if not entry.name.startswith(PREFIX):
            continue
        try:
            if not entry.is_dir(follow_symlinks=False) or entry.stat(follow_symlinks=False).st_uid != os.getuid():
                continue
            names = set(os.listdir(entry.path))
            with open(os.path.join(entry.path, MARKER), encoding="ascii") as f:
                owner = json.load(f)
        except (OSError, ValueError):
            continue          # not ours, or not readable: leave it
        if not owner_gone(owner) or not names <= _OWN_NAMES:
            continue
        remove_link_dir(entry.path)
        if not os.path.lexists(entry.path):
            removed.append(entry.path)
    return removed
