"""A one-line progress display: lines done, rate and time left."""
from __future__ import annotations

import sys
import time

__all__ = ["Progress", "format_duration"]


def format_duration(seconds: float) -> str:
    """``H:MM:SS`` for a non-negative number of seconds (``--:--:--`` if unknown)."""
    if seconds is None or not seconds >= 0 or seconds == float("inf"):
        return "--:--:--"
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class Progress:
    """Progress of a scan, printed to ``stream`` (stderr by default).

    On a terminal the line is redrawn in place; otherwise (a log file, a pipe) one
    line is printed per update.  The rate counts only the lines of this session.

    Parameters
    ----------
    total : int
        Lines in the scan.
    done : int
        Lines already on disk when the session started (resume).
    """

    def __init__(self, total: int, done: int = 0, *, stream=None, clock=time.monotonic, label: str = "capture"):
        self.total = int(total)
        self.start_done = self.done = int(done)
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.t0 = clock()
        self.label = label
        self.extra = ""
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def text(self) -> str:
        elapsed = self.clock() - self.t0
        new = self.done - self.start_done
        rate = new / elapsed if elapsed > 0 and new > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else None
        pct = 100.0 * self.done / self.total if self.total else 100.0
        return (f"{self.label}: {self.done}/{self.total} lines ({pct:.0f}%), "
                f"{rate:.2f} lines/s, {format_duration(left)} left" + (f"; {self.extra}" if self.extra else ""))

    def update(self, done: int, extra: str = "") -> None:
        """Show ``done`` lines on disk; ``extra`` (e.g. what a consumer of the lines has done) is appended."""
        self.done = int(done)
        self.extra = str(extra)
        if self._tty:
            self.stream.write("\r\x1b[K" + self.text())
        else:
            self.stream.write(self.text() + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._tty:
            self.stream.write("\n")
            self.stream.flush()
