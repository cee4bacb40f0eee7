"""The line-transport API and everything the implementations share (see :mod:`drivers.transport`)."""
from __future__ import annotations

import threading
import time

import serial

try:  # pyserial's POSIX backend lets termios.error (not an OSError) out of flush()/tcdrain
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - not POSIX
    class _TermiosError(Exception):
        pass

from ..errors import ConnectionLost, DeviceTimeout, ProtocolError

__all__ = ["LineTransport", "IO_ERRORS", "WriteBlocked"]

# Longest wait for the rest of a late reply caught mid-line when resynchronising (s).
RESYNC_WAIT_S = 0.2

IO_ERRORS = (serial.SerialException, OSError, _TermiosError)


class WriteBlocked(Exception):
    """The link did not take the bytes in time (flow control held, peer not reading)."""


class LineTransport:
    """Base of the line-oriented transports (see the module docstring).

    Parameters
    ----------
    terminator : bytes
        End of every line, e.g. ``b"\\r\\n"``.  A line is cut at the
        terminator's last byte; one that does not end with the whole
        terminator is a :class:`ProtocolError`.
    timeout_s : float
        Default time to wait for one reply, seconds.
    max_line : int
        Longest acceptable line, bytes; a longer one is a :class:`ProtocolError`.
    reconnect_attempts : int
        How often ``write``/``query`` reopen a broken link and try again (0: never).
    name : str
        How the link is named in error messages.
    """

    def __init__(self, *, terminator: bytes = b"\r\n", timeout_s: float = 1.0, max_line: int = 4096,
                 reconnect_attempts: int = 1, name: str = "link"):
        terminator = bytes(terminator)
        if not terminator:
            raise ValueError("terminator must be at least one byte")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if int(max_line) < len(terminator) + 1:
            raise ValueError(f"max_line must exceed the terminator length, got {max_line!r}")
        if int(reconnect_attempts) < 0:
            raise ValueError(f"reconnect_attempts must be >= 0, got {reconnect_attempts!r}")
        self.terminator = terminator
        self.timeout_s = float(timeout_s)
        self.max_line = int(max_line)
        self.reconnect_attempts = int(reconnect_attempts)
        self.name = str(name)
        self.lock = threading.RLock()
        self.stale = False          # a late reply may be in flight: drain before the next write
        self._rx = bytearray()      # received, not yet returned
        self._is_open = False
        self._closed = False

    # ------------------------------------------------------------ primitives (subclasses)
    def _open(self) -> None:
        raise NotImplementedError

    def _close_link(self) -> None:
        raise NotImplementedError

    def _send(self, data: bytes) -> None:
        raise NotImplementedError

    def _receive(self, max_bytes: int, deadline: float) -> bytes:
        """At least one byte, or ``b""`` once ``deadline`` (``time.monotonic()``) has passed."""
        raise NotImplementedError

    def _discard_input(self) -> bytes:
        """Drop input already buffered below this class (OS, driver); return it if known."""
        return b""

    # ------------------------------------------------------------ lifetime
    def connect(self) -> None:
        """Open the link (done by the constructors of the subclasses)."""
        with self.lock:
            if self._closed:
                raise ConnectionLost(f"{self.name}: transport is closed")
            try:
                self._open()
            except (*IO_ERRORS, ValueError) as exc:
                raise ConnectionLost(f"cannot open {self.name}: {exc}") from exc
            self._is_open = True
            self._rx.clear()
            self.stale = False

    def _drop(self) -> None:
        if self._is_open:
            self._is_open = False
            try:
                self._close_link()
            except IO_ERRORS:
                pass
        self._rx.clear()

    def reconnect(self) -> None:
        """Close the link and open it again; :class:`ConnectionLost` if it cannot be reopened."""
        with self.lock:
            self._drop()
            self.connect()

    def close(self) -> None:
        """Close for good (idempotent); every later call raises :class:`ConnectionLost`."""
        with self.lock:
            self._closed = True
            self._drop()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ helpers
    def _timeout(self, timeout_s) -> float:
        if timeout_s is None:
            return self.timeout_s
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        return float(timeout_s)

    def _ensure_open(self) -> None:
        if self._closed:
            raise ConnectionLost(f"{self.name}: transport is closed")
        if not self._is_open:
            self.connect()

    def _with_reconnect(self, operation):
        """Run ``operation()``; on an I/O error reopen the link and run it again (``reconnect_attempts``)."""
        with self.lock:
            attempt = 0
            while True:
                self._ensure_open()
                try:
                    return operation()
                except (serial.SerialTimeoutException, WriteBlocked) as exc:   # output blocked
                    self.stale = True
                    raise DeviceTimeout(f"{self.name}: write not done within {self.timeout_s:g} s") from exc
                except IO_ERRORS as exc:
                    self._drop()
                    if attempt >= self.reconnect_attempts:
                        raise ConnectionLost(f"{self.name}: connection lost ({exc})") from exc
                    attempt += 1
                    try:
                        self.connect()
                    except ConnectionLost as again:
                        raise ConnectionLost(f"{self.name}: connection lost ({exc}); "
                                             f"reconnecting failed: {again}") from exc

    def _write_now(self, data: bytes) -> None:
        if self.stale:
            self._resync_now()
        self._send(data)

    def _resync_now(self) -> None:
        """Discard stale input before a command, including the rest of a late line still in flight.

        A late reply can be caught mid-line (its first bytes have arrived, the rest is on the
        wire); discarding only what has arrived would leave its tail to be read as the next
        command's reply.  So when the discarded bytes stop inside a line, the rest of that line
        is awaited, for at most ``RESYNC_WAIT_S`` (or the timeout, if shorter), and discarded too.
        """
        dropped = self._drain_now()
        if not dropped or dropped.endswith(self.terminator):
            return
        deadline = time.monotonic() + min(self.timeout_s, RESYNC_WAIT_S)
        while not dropped.endswith(self.terminator):
            chunk = self._receive(self.max_line, deadline)
            if not chunk:
                return
            dropped += chunk

    def _drain_now(self) -> bytes:
        dropped = bytes(self._rx) + self._discard_input()
        self._rx.clear()
        self.stale = False
        return dropped

    def _fill(self, deadline: float, what: str, timeout_s: float) -> None:
        chunk = self._receive(self.max_line, deadline)
        if not chunk:
            self.stale = True
            raise DeviceTimeout(f"{self.name}: no complete {what} within {timeout_s:g} s "
                                f"(got {bytes(self._rx)!r})")
        self._rx += chunk

    def _read_line_now(self, timeout_s: float) -> bytes:
        deadline = time.monotonic() + timeout_s
        eol = self.terminator[-1]
        while True:
            end = self._rx.find(eol)
            if end >= 0:
                line = bytes(self._rx[:end + 1])
                del self._rx[:end + 1]
                if not line.endswith(self.terminator):
                    self.stale = True
                    raise ProtocolError(f"{self.name}: line does not end with {self.terminator!r}", line)
                return line
            if len(self._rx) > self.max_line:
                line = bytes(self._rx)
                self._rx.clear()
                self.stale = True
                raise ProtocolError(f"{self.name}: line longer than {self.max_line} bytes", line)
            self._fill(deadline, "line", timeout_s)

    def _read_exactly_now(self, n: int, timeout_s: float) -> bytes:
        deadline = time.monotonic() + timeout_s
        while len(self._rx) < n:
            self._fill(deadline, f"{n}-byte block", timeout_s)
        data = bytes(self._rx[:n])
        del self._rx[:n]
        return data

    # ------------------------------------------------------------ public API
    def write(self, data: bytes) -> None:
        """Send ``data`` (after discarding stale input); reconnect and resend once if the link broke."""
        data = bytes(data)
        if not data:
            raise ValueError("cannot send zero bytes")
        self._with_reconnect(lambda: self._write_now(data))

    def read_line(self, timeout_s: float | None = None) -> bytes:
        """The next line, terminator included.  :class:`DeviceTimeout` if none is complete in time."""
        timeout_s = self._timeout(timeout_s)
        with self.lock:
            self._ensure_open()
            try:
                return self._read_line_now(timeout_s)
            except IO_ERRORS as exc:
                self._drop()
                raise ConnectionLost(f"{self.name}: connection lost ({exc})") from exc

    def read_exactly(self, n: int, timeout_s: float | None = None) -> bytes:
        """Exactly ``n`` bytes.  :class:`DeviceTimeout` if fewer arrive in time (they stay buffered)."""
        n = int(n)
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        timeout_s = self._timeout(timeout_s)
        with self.lock:
            self._ensure_open()
            try:
                return self._read_exactly_now(n, timeout_s)
            except IO_ERRORS as exc:
                self._drop()
                raise ConnectionLost(f"{self.name}: connection lost ({exc})") from exc

    def query(self, data: bytes, timeout_s: float | None = None) -> bytes:
        """Send ``data`` and return the one reply line, as one exchange under the lock.

        If the link breaks, it is reopened and the whole exchange repeated
        (``reconnect_attempts`` times).  Bytes after the reply line mark the
        transport stale: they are discarded before the next write.
        """
        data = bytes(data)
        if not data:
            raise ValueError("cannot send zero bytes")
        timeout_s = self._timeout(timeout_s)

        def exchange():
            self._write_now(data)
            line = self._read_line_now(timeout_s)
            if self._rx:
                self.stale = True
            return line
        return self._with_reconnect(exchange)

    def drain(self) -> bytes:
        """Discard all pending input now; return what was discarded (as far as it is known)."""
        with self.lock:
            if not self._is_open:
                self._rx.clear()
                self.stale = False
                return b""
            try:
                return self._drain_now()
            except IO_ERRORS as exc:
                self._drop()
                raise ConnectionLost(f"{self.name}: connection lost ({exc})") from exc

    def describe(self) -> str:
        """How the link is named in messages (the port, ``host:port``)."""
        return self.name

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"
