"""Rate-limited warnings: a device that repeats the same fault must not flood the log.

A driver reading a stream can meet the same problem thousands of times a second
(a server repeating a reply for another command, noise on a line).  Every
occurrence is counted, but a message with a given key is logged at most once per
``interval_s``; the next one logged says how many were suppressed in between::

    limiter = WarningLimiter(log, interval_s=5.0)
    limiter.warning("foreign-reply", "RemoteEx: skipping reply %r while waiting for %s", line, name)
"""
from __future__ import annotations

import logging
import threading
import time

__all__ = ["WarningLimiter"]


class WarningLimiter:
    """Log each kind of warning at most once per ``interval_s``.

    Parameters
    ----------
    logger : logging.Logger
    interval_s : float
        Shortest time between two records with the same key, seconds.
    clock : callable
        Monotonic clock (seconds); replaceable in tests.

    Attributes
    ----------
    counts : dict
        Occurrences per key since the limiter was made (logged or not).
    """

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0, clock=time.monotonic):
        if not interval_s > 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s!r}")
        self.logger = logger
        self.interval_s = float(interval_s)
        self.clock = clock
        self.counts: dict = {}
        self._last: dict = {}          # key -> time of the last record
        self._suppressed: dict = {}    # key -> occurrences not logged since then
        self._lock = threading.Lock()

    def log(self, level: int, key, message: str, *args) -> bool:
        """Log ``message % args`` unless ``key`` was logged less than ``interval_s`` ago; True if logged."""
        now = self.clock()
        with self._lock:
            self.counts[key] = self.counts.get(key, 0) + 1
            last = self._last.get(key)
            if last is not None and now - last < self.interval_s:
                self._suppressed[key] = self._suppressed.get(key, 0) + 1
                return False
            suppressed = self._suppressed.pop(key, 0)
            self._last[key] = now
        if suppressed:
            message += " (%d similar messages suppressed in the last %.3g s)"
            args = (*args, suppressed, now - last)
        self.logger.log(level, message, *args)
        return True

    def warning(self, key, message: str, *args) -> bool:
        return self.log(logging.WARNING, key, message, *args)
