"""Which process owns a file streaklab left on disk, and whether that process is still running.

Markers written beside staged outputs (:mod:`core.staging`) and in the mirror
simulator's link folders (:mod:`drivers.sim.linkdir`) hold :func:`owner_record`:
``producer``, ``host``, ``pid`` and the process's ``started`` time (clock ticks
since boot from ``/proc/<pid>/stat`` on Linux, so a recycled pid is not taken
for the owner).  Whatever streaklab cleans up after a killed run, it cleans only
where :func:`owner_alive` says the owner is gone.
"""
from __future__ import annotations

import os
import socket
from pathlib import Path

__all__ = ["owner_record", "owner_alive", "owner_gone", "start_time"]


def start_time(pid: int) -> str | None:
    """The process's start time (clock ticks since boot) on Linux, to tell a reused pid apart."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def owner_record(**extra) -> dict:
    """The marker contents naming this process as the owner (plus ``extra`` fields)."""
    pid = os.getpid()
    return {"producer": "streaklab", "host": socket.gethostname(), "pid": pid,
            "started": start_time(pid), **extra}


def owner_alive(info: dict) -> bool:
    """False only when the marker's owner is known to be gone (same host, no such process)."""
    if info.get("host") != socket.gethostname():
        return True                          # another machine's process: cannot tell, so it may be running
    try:
        pid = int(info.get("pid", -1))
    except (TypeError, ValueError):
        return True
    if pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    started = info.get("started")
    return started is None or start_time(pid) in (None, started)


def owner_gone(info) -> bool:
    """True when ``info`` is a marker that streaklab wrote and its owner is known to be gone: what
    streaklab left may then be cleaned up (anything else is left alone)."""
    return isinstance(info, dict) and info.get("producer") == "streaklab" and not owner_alive(info)
