"""Documented size and time limits: every size a user or a file can ask for is checked here first.

One home for the limits of the whole pipeline (capture, reconstruct, import, decompose).  A
request is refused *before* anything is allocated or written, with a one-line
:class:`LimitError` that names the key (a config key, an option or the file's field), what it
asks for and the limit.  Requests that fit the documented limit are also compared with the
memory available now (``MemAvailable`` of ``/proc/meminfo``, else ``os.sysconf``) or, for files
to be written, with the free space of the target file system.

The limits (see ``docs/capture.md`` and ``docs/decompose.md``):

==========================  ==============  ===================================================
name                        value           what it bounds
==========================  ==============  ===================================================
MAX_SCAN_LINES              100 000         ``scan.count`` / entries of ``scan.angles_deg``
MAX_IMAGE_PIXELS            16 777 216      pixels of one streak image (4096 x 4096)
MAX_LINE_BYTES              4 GiB           frames of one scan line held in memory
                                            (``camera.frames_per_line`` x image bytes), and
                                            the dark frames (``dark.frames`` x image bytes)
MAX_TIME_BINS               65 536          time bins of a cube (``calibration.time_bin_ps``,
                                            an imported or decomposed cube's ``t``)
MAX_CUBE_BYTES              1 TiB           a cube (y, x, t) written by reconstruct or import
MAX_CHUNK_BYTES             2 GiB           the solver's working memory for one pixel chunk
MAX_TIMEOUT_S               86 400 s        every ``*_timeout_s`` and ``camera.exposure_s``
MAX_RETRIES                 20              ``session.retries``
MAX_BACKOFF_WAIT_S          60 s            one retry wait (``retry_backoff_s * 2**attempt``)
MAX_BACKOFF_TOTAL_S         600 s           all retry waits of one step together
MAX_CONFIG_BYTES            1 MiB           a TOML configuration file
MAX_HANDSHAKE_BYTES         1 MiB           the first message of a dask scheduler
==========================  ==============  ===================================================
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from .errors import StreaklabError

__all__ = [
    "LimitError", "MAX_SCAN_LINES", "MAX_IMAGE_PIXELS", "MAX_LINE_BYTES", "MAX_TIME_BINS", "MAX_CUBE_BYTES",
    "MAX_CHUNK_BYTES", "MAX_TIMEOUT_S", "MAX_RETRIES", "MAX_BACKOFF_WAIT_S", "MAX_BACKOFF_TOTAL_S",
    "MAX_CONFIG_BYTES", "MAX_HANDSHAKE_BYTES", "available_memory", "check_count", "check_memory", "check_disk",
    "backoff_waits", "format_bytes", "time_bin_message",
]

GiB = 1 << 30

MAX_SCAN_LINES = 100_000
MAX_IMAGE_PIXELS = 4096 * 4096
MAX_LINE_BYTES = 4 * GiB
MAX_TIME_BINS = 65_536
MAX_CUBE_BYTES = 1024 * GiB
MAX_CHUNK_BYTES = 2 * GiB
MAX_TIMEOUT_S = 86_400.0
MAX_RETRIES = 20
MAX_BACKOFF_WAIT_S = 60.0
MAX_BACKOFF_TOTAL_S = 600.0
MAX_CONFIG_BYTES = 1 << 20
MAX_HANDSHAKE_BYTES = 1 << 20


class LimitError(StreaklabError, ValueError):
    """A request exceeds a documented limit or the memory / disk space there is (names key and limit)."""


def format_bytes(n: float) -> str:
    """``1536`` -> ``'1.50 KiB'``."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} PiB"  # pragma: no cover


def available_memory() -> int | None:
    """Bytes of memory available to new allocations now (None if the system does not say)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_count(key: str, count: int, limit: int, what: str = "") -> int:
    """Refuse ``count`` above ``limit``: ``"scan.count: 1000000000 lines exceeds the limit of 100000"``."""
    if count > limit:
        unit = f" {what}" if what else ""
        raise LimitError(f"{key}: {count}{unit} exceeds the limit of {limit}{unit}")
    return int(count)


def check_memory(key: str, nbytes: int, limit: int, *, what: str = "", memory: int | None = None) -> int:
    """Refuse a request of ``nbytes`` above ``limit`` or above the memory available now.

    Parameters
    ----------
    key : the config key / option / field that decides the size (named in the message).
    nbytes : bytes the request needs.
    limit : the documented limit for it.
    what : what the bytes are, for the message (e.g. "for the frames of one line").
    memory : available memory to compare with (default: :func:`available_memory`).
    """
    nbytes = int(nbytes)
    what = f" {what}" if what else ""
    if nbytes > limit:
        raise LimitError(f"{key}: needs {format_bytes(nbytes)}{what}, above the limit of {format_bytes(limit)}")
    avail = available_memory() if memory is None else memory
    if avail is not None and nbytes > avail:
        raise LimitError(f"{key}: needs {format_bytes(nbytes)}{what}, but only {format_bytes(avail)} of memory "
                         f"is available")
    return nbytes


def check_disk(key: str, nbytes: int, limit: int, path, *, what: str = "") -> int:
    """Refuse to write ``nbytes`` above ``limit`` or above the free space of the file system of ``path``."""
    nbytes = int(nbytes)
    what = f" {what}" if what else ""
    if nbytes > limit:
        raise LimitError(f"{key}: needs {format_bytes(nbytes)}{what}, above the limit of {format_bytes(limit)}")
    p = Path(path).resolve()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        return nbytes
    if nbytes > free:
        raise LimitError(f"{key}: needs {format_bytes(nbytes)}{what}, but only {format_bytes(free)} are free "
                         f"on the file system of {p}")
    return nbytes


def time_bin_message(time_bin_ps: float, window_ps: float, n_bins: float) -> str | None:
    """Why ``n_bins`` bins of ``time_bin_ps`` over a ``window_ps`` window are refused, or None."""
    if np.isfinite(n_bins) and n_bins <= MAX_TIME_BINS:
        return None
    return (f"calibration.time_bin_ps = {time_bin_ps:g} ps makes {n_bins:.3g} time bins of the calibrated window "
            f"of {window_ps:.6g} ps, above the limit of {MAX_TIME_BINS} bins (limits.MAX_TIME_BINS); use a wider bin")


def backoff_waits(retries: int, backoff_s: float) -> list[float]:
    """The waits before retry 1, 2, ...: ``backoff_s * 2**k``, each at most MAX_BACKOFF_WAIT_S."""
    waits, w = [], float(backoff_s)
    for _ in range(int(retries)):
        waits.append(min(w, MAX_BACKOFF_WAIT_S))
        w = min(w * 2.0, MAX_BACKOFF_WAIT_S)
    return waits
