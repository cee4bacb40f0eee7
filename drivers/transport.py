"""Line-oriented byte transports shared by the drivers: serial, TCP, and a scripted in-memory one.

A driver is split into a *command table* (what to send, what the reply means)
and a *transport* (how bytes get there and back).  Every transport here has the
same small API, :class:`LineTransport`:

==========================  ==================================================
``write(data)``             send bytes (retried once after a reconnect if the
                            link broke)
``read_line(timeout_s)``    bytes up to and including the line terminator
``read_exactly(n, ...)``    exactly ``n`` bytes (binary payloads)
``query(data, timeout_s)``  ``write`` + ``read_line`` as one exchange, under
                            the lock, repeated once after a reconnect
``drain()``                 discard (and return) whatever input is pending
``reconnect()``             close and reopen the link
``close()``                 close for good (idempotent)
``lock``                    an ``RLock``: hold it to make several calls one
                            exchange that no other thread can split
==========================  ==================================================

Errors are the drivers' own (:mod:`drivers.errors`): no reply within the
timeout is :class:`DeviceTimeout`, a line that is too long or does not end with
the full terminator is :class:`ProtocolError` (``raw`` holds the bytes), a
broken link that one reconnect does not mend is :class:`ConnectionLost`.  No
pyserial, socket or OS exception leaves this module.

Resynchronisation: after a timeout or a malformed line the transport is
*stale* — a late or partial reply may still arrive — and the next ``write``
first discards all pending input.  A ``query`` whose reply line is followed
by more bytes marks the transport stale too (one request, one reply line).

Implementations:

* :class:`SerialLineTransport` — pyserial (``serial_for_url``: a device path,
  a pty, ``loop://``, ``rfc2217://``), with ``xonxoff``/``rtscts`` flow control
  configurable;
* :class:`TcpLineTransport` — a TCP client socket with connect and read timeouts;
* :class:`ScriptedTransport` — no I/O at all: a list of ``(sent, reply)`` pairs
  checked byte for byte, in order, in the style of PyMeasure's
  ``expected_protocol``.  A reply that never comes is a timeout at once, so
  protocol tests need no thread, socket or sleep::

      with ScriptedTransport([(b"1TP\\r\\n", b"1TP12.5\\r\\n"), (b"1ST\\r\\n", None)]) as t:
          mirror = SMC100Mirror(transport=t)
          assert mirror.position() == 12.5
          mirror.stop()
      # leaving the block asserts that every scripted exchange happened

Subclasses implement four primitives: ``_open()``, ``_close_link()``,
``_send(data)`` and ``_receive(max_bytes, deadline)``; I/O failures are raised
as ``OSError`` (or pyserial's ``SerialException``) and turned into the errors
above by this base class.
"""
from __future__ import annotations

import socket
import threading
import time

import serial

try:  # pyserial's POSIX backend lets termios.error (not an OSError) out of flush()/tcdrain
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - not POSIX
    class _TermiosError(Exception):
        pass

from .errors import ConnectionLost, DeviceTimeout, ProtocolError

__all__ = ["LineTransport", "SerialLineTransport", "TcpLineTransport", "ScriptedTransport"]

_IO_ERRORS = (serial.SerialException, OSError, _TermiosError)


class _WriteBlocked(Exception):
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
            except (*_IO_ERRORS, ValueError) as exc:
                raise ConnectionLost(f"cannot open {self.name}: {exc}") from exc
            self._is_open = True
            self._rx.clear()
            self.stale = False

    def _drop(self) -> None:
        if self._is_open:
            self._is_open = False
            try:
                self._close_link()
            except _IO_ERRORS:
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
                except (serial.SerialTimeoutException, _WriteBlocked) as exc:   # output blocked
                    self.stale = True
                    raise DeviceTimeout(f"{self.name}: write not done within {self.timeout_s:g} s") from exc
                except _IO_ERRORS as exc:
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
            self._drain_now()
        self._send(data)

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
            except _IO_ERRORS as exc:
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
            except _IO_ERRORS as exc:
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
            except _IO_ERRORS as exc:
                self._drop()
                raise ConnectionLost(f"{self.name}: connection lost ({exc})") from exc

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"


class SerialLineTransport(LineTransport):
    """A serial line through pyserial.

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyUSB0``, a pty's ``/dev/pts/N``, a stable link) or
        any pyserial URL (``loop://``, ``rfc2217://host:port``).
    baudrate, bytesize, parity, stopbits
        Line settings (pyserial values).
    xonxoff, rtscts : bool
        Software / hardware flow control.
    timeout_s : float
        Default reply timeout and write timeout, seconds.
    read_slice_s : float
        Longest single blocking read; the reply deadline is checked between reads.
    **kwargs
        ``terminator``, ``max_line``, ``reconnect_attempts`` (see :class:`LineTransport`).
    """

    def __init__(self, port: str, *, baudrate: int = 9600, bytesize: int = serial.EIGHTBITS,
                 parity: str = serial.PARITY_NONE, stopbits: float = serial.STOPBITS_ONE,
                 xonxoff: bool = False, rtscts: bool = False, timeout_s: float = 1.0,
                 read_slice_s: float = 0.05, **kwargs):
        super().__init__(timeout_s=timeout_s, name=str(port), **kwargs)
        if not read_slice_s > 0:
            raise ValueError(f"read_slice_s must be > 0, got {read_slice_s!r}")
        self.port = str(port)
        self.settings = dict(baudrate=int(baudrate), bytesize=bytesize, parity=parity, stopbits=stopbits,
                             xonxoff=bool(xonxoff), rtscts=bool(rtscts))
        self.read_slice_s = float(read_slice_s)
        self.serial = None
        self.connect()

    def _open(self) -> None:
        self.serial = serial.serial_for_url(self.port, timeout=self.read_slice_s,
                                            write_timeout=self.timeout_s, **self.settings)

    def _close_link(self) -> None:
        ser, self.serial = self.serial, None
        if ser is not None:
            ser.close()

    def _send(self, data: bytes) -> None:
        self.serial.write(data)
        self.serial.flush()

    def _receive(self, max_bytes: int, deadline: float) -> bytes:
        ser = self.serial
        while time.monotonic() < deadline:
            chunk = ser.read(max(1, min(ser.in_waiting, max_bytes)))
            if chunk:
                return chunk
        return b""

    def _discard_input(self) -> bytes:
        ser = self.serial
        pending = ser.read(ser.in_waiting) if ser.in_waiting else b""
        ser.reset_input_buffer()
        return pending


class TcpLineTransport(LineTransport):
    """A TCP client connection.

    Parameters
    ----------
    host : str
    port : int
    timeout_s : float
        Default reply timeout, seconds.
    connect_timeout_s : float, optional
        Time allowed to establish the connection (default: ``timeout_s``).
    **kwargs
        ``terminator``, ``max_line``, ``reconnect_attempts`` (see :class:`LineTransport`).
    """

    def __init__(self, host: str, port: int, *, timeout_s: float = 1.0,
                 connect_timeout_s: float | None = None, **kwargs):
        port = int(port)
        if not 0 < port < 65536:
            raise ValueError(f"port must be 1..65535, got {port}")
        super().__init__(timeout_s=timeout_s, name=f"{host}:{port}", **kwargs)
        self.host, self.port = str(host), port
        self.connect_timeout_s = self._timeout(connect_timeout_s)
        self.sock = None
        self.connect()

    def _open(self) -> None:
        self.sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def _close_link(self) -> None:
        sock, self.sock = self.sock, None
        if sock is not None:
            sock.close()

    def _send(self, data: bytes) -> None:
        self.sock.settimeout(self.timeout_s)
        try:
            self.sock.sendall(data)
        except socket.timeout as exc:
            raise _WriteBlocked(f"send blocked for {self.timeout_s:g} s") from exc

    def _receive(self, max_bytes: int, deadline: float) -> bytes:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return b""
        self.sock.settimeout(remaining)
        try:
            chunk = self.sock.recv(max(1, max_bytes))
        except socket.timeout:
            return b""
        if not chunk:
            raise ConnectionResetError("peer closed the connection")
        return chunk

    def _discard_input(self) -> bytes:
        out = bytearray()
        self.sock.setblocking(False)
        try:
            while True:
                try:
                    chunk = self.sock.recv(65536)
                except (BlockingIOError, InterruptedError):
                    break
                if not chunk:
                    raise ConnectionResetError("peer closed the connection")
                out += chunk
        finally:
            self.sock.setblocking(True)
        return bytes(out)


class ScriptedTransport(LineTransport):
    """In-memory transport that checks the exact bytes written against a script.

    Parameters
    ----------
    script : list of (bytes, reply)
        In order, what the driver must write and what the far end does then.
        ``reply`` is the bytes that become readable (possibly several lines, or
        an incomplete one), ``None`` for no answer, or an ``OSError`` instance
        to make that write fail as a broken link would (the transport then
        reconnects, see ``reconnects``, and the resent bytes are matched
        against the next step).
    **kwargs
        ``terminator``, ``timeout_s``, ``max_line``, ``reconnect_attempts``.

    A read that finds no complete reply fails with :class:`DeviceTimeout` at
    once (nothing more can arrive).  A write that differs from the script
    raises ``AssertionError`` naming the step, the expected and the actual
    bytes; the failure is also kept, so :meth:`assert_done` reports it even if
    a driver swallowed the exception.  Use it as a context manager, or call
    :meth:`assert_done` at the end: both fail if scripted steps were not used
    or replies were left unread.

    Attributes
    ----------
    written : list of bytes
        Every write, in order.
    reconnects : int
        How often the link was reopened.
    drained : list of bytes
        What each discard of stale input threw away.
    """

    def __init__(self, script=(), **kwargs):
        kwargs.setdefault("name", "scripted")
        super().__init__(**kwargs)
        self.script = [self._step(i, step) for i, step in enumerate(script)]
        self.written: list[bytes] = []
        self.drained: list[bytes] = []
        self.failures: list[str] = []
        self.reconnects = 0
        self._step_no = 0
        self._pending = bytearray()   # "on the wire": readable by the driver
        self._opened = 0
        self.connect()

    @staticmethod
    def _step(i, step):
        try:
            sent, reply = step
        except (TypeError, ValueError):
            raise ValueError(f"script step {i} must be a (sent, reply) pair, got {step!r}") from None
        if not isinstance(sent, (bytes, bytearray)) or not sent:
            raise ValueError(f"script step {i}: sent must be non-empty bytes, got {sent!r}")
        if reply is not None and not isinstance(reply, (bytes, bytearray, OSError)):
            raise ValueError(f"script step {i}: reply must be bytes, None or an OSError, got {reply!r}")
        return bytes(sent), (bytes(reply) if isinstance(reply, (bytes, bytearray)) else reply)

    def extend(self, script) -> None:
        """Append more steps to the script."""
        start = len(self.script)
        self.script.extend(self._step(start + i, step) for i, step in enumerate(script))

    def feed(self, data: bytes) -> None:
        """Make ``data`` readable now, unasked (a late reply, noise)."""
        self._pending += bytes(data)

    # primitives
    def _open(self) -> None:
        if self._opened:
            self.reconnects += 1
            self._pending.clear()     # a new link starts with nothing in flight
        self._opened += 1

    def _close_link(self) -> None:
        pass

    def _fail(self, message: str):
        self.failures.append(message)
        raise AssertionError(message)

    def _send(self, data: bytes) -> None:
        self.written.append(data)
        if self._step_no >= len(self.script):
            self._fail(f"ScriptedTransport: unexpected write {data!r} after the last of "
                       f"{len(self.script)} scripted steps")
        expected, reply = self.script[self._step_no]
        if data != expected:
            self._fail(f"ScriptedTransport: step {self._step_no}: expected {expected!r}, got {data!r}")
        self._step_no += 1
        if isinstance(reply, OSError):
            raise reply
        if reply is not None:
            self._pending += reply

    def _receive(self, max_bytes: int, deadline: float) -> bytes:
        chunk = bytes(self._pending[:max_bytes])
        del self._pending[:max_bytes]
        return chunk

    def _discard_input(self) -> bytes:
        out = bytes(self._pending)
        self._pending.clear()
        return out

    def _drain_now(self) -> bytes:
        dropped = super()._drain_now()
        self.drained.append(dropped)
        return dropped

    # checks
    @property
    def steps_left(self) -> int:
        return len(self.script) - self._step_no

    def assert_done(self) -> None:
        """Fail unless every scripted step was written and every reply byte was read or discarded."""
        problems = list(self.failures)
        if self._step_no < len(self.script):
            problems.append(f"{len(self.script) - self._step_no} scripted step(s) never written, "
                            f"next expected {self.script[self._step_no][0]!r}")
        unread = bytes(self._rx) + bytes(self._pending)
        if unread and not self.stale:
            problems.append(f"reply bytes left unread: {unread!r}")
        if problems:
            raise AssertionError("ScriptedTransport: " + "; ".join(problems))

    def __exit__(self, exc_type, *exc) -> None:
        try:
            if exc_type is None:
                self.assert_done()
        finally:
            self.close()
