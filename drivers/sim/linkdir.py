"""The mirror simulator's link folders: ``/tmp/streaklab-mirror-*``, marked with their owner.

A :class:`~drivers.sim.mirror.MirrorSimulator` keeps its stable port link (the
``/dev/serial/by-id``-style symlink to the current pty) in a private folder
under the temporary directory.  A process that is killed cannot remove it, so
every folder is marked when it is made: a file :data:`MARKER` holding the
owning process id and that process's start time (from ``/proc``, where there
is one, so a recycled pid is not mistaken for the owner).

:func:`remove_stale_link_dirs` removes exactly the folders that

* are named ``streaklab-mirror-*`` directly in the temporary directory,
* are real folders (not links) owned by this user,
* hold a readable marker whose process is gone, and
* contain nothing but the marker and the simulator's links,

and leaves everything else alone.
"""
from __future__ import annotations

import json
import os
import tempfile

__all__ = ["PREFIX", "MARKER", "make_link_dir", "remove_link_dir", "remove_stale_link_dirs"]

PREFIX = "streaklab-mirror-"
MARKER = "owner.json"
_OWN_NAMES = {MARKER, "ttySMC100", "ttySMC100.new"}


def _start_time(pid: int):
    """Start time of ``pid`` in clock ticks since boot (``/proc/<pid>/stat`` field 22), or None."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read().decode("ascii", "replace")
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may contain spaces
    fields = stat[stat.rfind(")") + 2:].split()
    try:
        return int(fields[19])
    except (IndexError, ValueError):
        return None


def _alive(pid: int, start) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True           # exists, owned by someone else
    if start is not None:
        now = _start_time(pid)
        if now is not None and now != start:
            return False      # the pid was recycled by another process
    return True


def make_link_dir(parent: str | None = None) -> str:
    """Create a marked ``streaklab-mirror-*`` folder; returns its path."""
    path = tempfile.mkdtemp(prefix=PREFIX, dir=parent)
    pid = os.getpid()
    with open(os.path.join(path, MARKER), "w", encoding="ascii") as f:
        json.dump({"pid": pid, "start": _start_time(pid)}, f)
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
            pid, start = int(owner["pid"]), owner.get("start")
        except (OSError, ValueError, KeyError, TypeError):
            continue          # not ours, or not readable: leave it
        if pid <= 0 or not names <= _OWN_NAMES or _alive(pid, start):
            continue
        remove_link_dir(entry.path)
        if not os.path.lexists(entry.path):
            removed.append(entry.path)
    return removed
