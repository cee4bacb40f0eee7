"""The two connections of a RemoteEx client: command port and data port, on :mod:`drivers.transport`.

:class:`RemoteExLink` owns one line transport per port (``\\r``-terminated lines)
and turns them into transactions: command, reply and, for image-like commands,
the announced number of bytes from the data port.

* Connecting opens both ports first and reads both greetings afterwards (the
  order Odemis' client uses; RemoteEx accepts either).
* One re-entrant lock serialises whole transactions, so a reply and its data
  always go back to the thread that sent the command.
* A connection that dropped is re-established once (both ports, greetings
  read again) and the interrupted command re-sent; if that fails:
  :class:`~drivers.errors.ConnectionLost`.  After a timeout or a malformed
  reply both ports are closed and the next command opens fresh ones, so a late
  or partial reply can never be taken for a later answer.
* Unsolicited messages (codes 4 and 5) are skipped wherever they arrive; live
  monitoring messages (``4,Livemonitor,...``) are kept for
  :meth:`RemoteExLink.wait_live_event`.  Replies to another command are skipped
  with a rate-limited warning (a server repeating them cannot flood the log).
* Before a data-port transfer, bytes already waiting on the data port (stray
  bytes, the tail of an interrupted transfer) are discarded; after it, bytes
  beyond the announced count mean the stream was misaligned and the transfer
  is refused (:class:`~drivers.errors.ProtocolError`).
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time

from .errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from .logutil import WarningLimiter
from .remoteex_wire import (COMMAND_BANNER, DATA_BANNER, DEFAULT_PORT, ERROR_MEANINGS, NOTIFICATION_CODES,
                            TERMINATOR, _MAX_LINE, format_command, parse_reply)
from .transport import TcpLineTransport

__all__ = ["RemoteExLink"]

log = logging.getLogger("drivers.remoteex")


class _Dropped(Exception):
    """Internal: the connection broke (EOF, reset, refused); the caller may reconnect once."""


class RemoteExLink:
    """Command and data connection to a RemoteEx server.

    Parameters
    ----------
    host : str
        RemoteEx server address.
    port : int
        Command port (RemoteEx default 1001).
    data_port : int, optional
        Data port; defaults to ``port + 1`` as RemoteEx does.
    timeout_s : float
        Default time allowed for one command's reply (seconds).
    connect_timeout_s : float
        Time allowed to connect and receive both greetings.
    open_transports : callable, optional
        ``open_transports(connect_timeout_s) -> (command_transport, data_transport)``,
        two :class:`~drivers.transport.LineTransport` objects.  Default: TCP to
        ``host:port`` and ``host:data_port``.  Tests pass in-memory
        :class:`~drivers.transport.ScriptedTransport` objects.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, data_port: int | None = None,
                 timeout_s: float = 5.0, connect_timeout_s: float = 5.0, open_transports=None):
        for name, v in (("timeout_s", timeout_s), ("connect_timeout_s", connect_timeout_s)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {v!r}")
        if not (0 < int(port) < 65536):
            raise ValueError(f"port must be in 1..65535, got {port!r}")
        self.host = host
        self.port = int(port)
        self.data_port = int(data_port) if data_port is not None else self.port + 1
        self.timeout_s = float(timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self._open_transports = open_transports or self._tcp_transports
        self._lock = threading.RLock()
        self._cmd = None
        self._data = None
        self._closed = False
        self.reconnects = 0            # connections a command had to (re)open after a drop or a reset
        self.live_events: collections.deque = collections.deque(maxlen=256)   # values of 4,Livemonitor,...
        self.stray_data_bytes = 0      # bytes discarded from the data port before transfers
        self._warnings = WarningLimiter(log)

    @property
    def address(self) -> tuple[str, int]:
        return (self.host, self.port)

    # ------------------------------------------------------------ connection
    def _tcp_transports(self, connect_timeout_s: float):
        options = dict(timeout_s=self.timeout_s, connect_timeout_s=connect_timeout_s, terminator=TERMINATOR,
                       reconnect_attempts=0)
        cmd = TcpLineTransport(self.host, self.port, max_line=_MAX_LINE, **options)
        try:
            data = TcpLineTransport(self.host, self.data_port, max_line=1 << 20, **options)
        except BaseException:
            cmd.close()
            raise
        return cmd, data

    def _connect(self) -> None:
        deadline = time.monotonic() + self.connect_timeout_s
        try:
            cmd, data = self._open_transports(self.connect_timeout_s)
        except ConnectionLost as exc:
            raise _Dropped(str(exc)) from None
        try:
            for t, banner, which in ((cmd, COMMAND_BANNER, "command"), (data, DATA_BANNER, "data")):
                remaining = deadline - time.monotonic()
                try:
                    got = t.read_line(timeout_s=max(remaining, 1e-3))
                except DeviceTimeout:
                    raise _Dropped(f"no RemoteEx greeting on the {which} port within "
                                   f"{self.connect_timeout_s} s") from None
                except ConnectionLost as exc:
                    raise _Dropped(f"{which} port closed before the RemoteEx greeting ({exc})") from None
                if got != banner:
                    raise ProtocolError(f"unexpected RemoteEx greeting on the {which} port (expected {banner!r})",
                                        got)
        except BaseException:
            cmd.close()
            data.close()
            raise
        self._cmd, self._data = cmd, data

    def _disconnect(self) -> None:
        for t in (self._cmd, self._data):
            if t is not None:
                t.close()
        self._cmd = self._data = None

    def open(self) -> None:
        """Connect both ports (if not connected)."""
        with self._lock:
            self._closed = False
            if self._cmd is None:
                try:
                    self._connect()
                except _Dropped as exc:
                    raise ConnectionLost(f"cannot connect to RemoteEx at {self.host}:{self.port}: {exc}") from None

    def close(self) -> None:
        """Close both connections (does not end the remote application)."""
        with self._lock:
            self._disconnect()
            self._closed = True

    # -------------------------------------------------------------- commands
    def command(self, name: str, *args, timeout_s: float | None = None) -> list[str]:
        """Send one command and return the values of its reply.

        Parameters
        ----------
        name : str
            Command name, e.g. ``"CamParamGet"``.
        *args
            Arguments; converted with ``str``.
        timeout_s : float, optional
            Time allowed for the reply (default: ``self.timeout_s``).

        Returns
        -------
        list of str
            The fields after ``code,Name``.

        Raises
        ------
        DeviceError
            The reply carries a non-zero code (``.code``, ``.meaning``).
        DeviceTimeout, ProtocolError, ConnectionLost
        """
        values, _ = self.transaction(name, args, timeout_s=timeout_s)
        return values

    def transaction(self, name: str, args=(), *, timeout_s: float | None = None, data=None):
        """Command, reply and (if ``data`` is a callable) the data-port payload, under the lock.

        ``data(values) -> int`` returns the byte count announced by the reply.
        Returns ``(values, payload_bytes_or_None)``.
        """
        wire = format_command(name, *args)
        timeout_s = self.timeout_s if timeout_s is None else float(timeout_s)
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"{self!r} is closed")
            last_drop = None
            for _attempt in range(2):
                deadline = time.monotonic() + timeout_s
                try:
                    if self._cmd is None:
                        log.info("RemoteEx: (re)connecting to %s:%s for %s", self.host, self.port, name)
                        self._connect()
                        self.reconnects += 1
                    if data is not None:
                        self._drain_data(name)
                    try:
                        self._cmd.write(wire)
                    except DeviceTimeout:
                        raise DeviceTimeout(f"RemoteEx: sending {wire!r} timed out") from None
                    values = self._read_reply(name, wire, deadline)
                    payload = None
                    if data is not None:
                        payload = self._recv_data(data(values), deadline)
                    return values, payload
                except (_Dropped, ConnectionLost) as exc:
                    self._disconnect()
                    last_drop = exc
                    log.warning("RemoteEx: connection dropped during %s: %s", name, exc)
                    continue
                except (DeviceTimeout, ProtocolError):
                    # The stream is in an unknown state: start afresh on the next command.
                    self._disconnect()
                    raise
            raise ConnectionLost(f"RemoteEx connection to {self.host}:{self.port} lost during {name} "
                                 f"and could not be re-established: {last_drop}")

    def _next_line(self, deadline: float, what: str) -> bytes:
        """The next command-port line without its CR (a leading LF, as after CRLF, removed)."""
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceTimeout(f"RemoteEx: {what} within the timeout")
        try:
            raw = self._cmd.read_line(timeout_s=remaining)
        except DeviceTimeout:
            raise DeviceTimeout(f"RemoteEx: {what} within the timeout") from None
        return raw[: -len(TERMINATOR)]

    def _note(self, code: int, rname: str, values: list[str], line: bytes) -> None:
        if code == 4 and rname.lower() == "livemonitor":
            self.live_events.append(list(values))
        log.debug("RemoteEx notification: %r", line)

    def _read_reply(self, name: str, wire: bytes, deadline: float) -> list[str]:
        command = wire.decode("ascii").strip()
        while True:
            raw = self._next_line(deadline, f"no reply to {command!r}")
            line = raw.lstrip(b"\n")
            if not line.strip():
                continue
            try:
                code, rname, values = parse_reply(line)
            except ProtocolError:
                if raw.startswith(b"\n"):
                    # An extra CRLF line of a multi-line reply (CamParamGet(Setup,CameraInfo)) nobody asked for.
                    self._warnings.warning("continuation", "RemoteEx: skipping extra reply line %r while "
                                           "waiting for %s", line, name)
                    continue
                raise
            if code in NOTIFICATION_CODES:
                self._note(code, rname, values, line)
                continue
            if rname.lower() != name.lower():
                self._warnings.warning("foreign-reply", "RemoteEx: skipping reply %r while waiting for %s",
                                       line, name)
                continue
            if code != 0:
                raise DeviceError(code, ERROR_MEANINGS.get(code, "unknown RemoteEx error code"),
                                  command=command, device="RemoteEx")
            return values

    def read_continuation(self, *, quiet_s: float = 0.2, max_lines: int = 16) -> list[str]:
        """Extra CRLF lines that follow a multi-line reply, until none arrives for ``quiet_s`` seconds.

        ``CamParamGet(Setup,CameraInfo)`` answers ``0,CamParamGet,<model>\\r`` followed by
        ``\\n<field>\\r`` lines (product number, serial number, firmware, version).
        """
        out = []
        with self._lock:
            while len(out) < max_lines and self._cmd is not None:
                try:
                    raw = self._next_line(time.monotonic() + quiet_s, "no more reply lines")
                except DeviceTimeout:
                    break
                line = raw.lstrip(b"\n")
                if raw.startswith(b"\n"):
                    out.append(line.decode("ascii", "replace"))
                    continue
                try:
                    code, rname, values = parse_reply(line)
                except ProtocolError:
                    self._disconnect()
                    raise
                if code not in NOTIFICATION_CODES:
                    self._disconnect()
                    raise ProtocolError("RemoteEx: unsolicited reply after a multi-line reply", line)
                self._note(code, rname, values, line)
        return out

    def wait_live_event(self, timeout_s: float) -> list[str]:
        """The values of the next live-monitoring message (``4,Livemonitor,...``), waiting up to ``timeout_s``.

        Messages that arrived while other commands were answered are returned first.

        Raises
        ------
        DeviceTimeout
            No live-monitoring message within ``timeout_s``.
        """
        deadline = time.monotonic() + float(timeout_s)
        with self._lock:
            while not self.live_events:
                self._read_event(deadline)
            return self.live_events.popleft()

    def pending_live_events(self, *, quiet_s: float = 0.002) -> list[list[str]]:
        """Every live-monitoring message already received (queued or waiting on the socket), oldest first."""
        with self._lock:
            while self._cmd is not None:
                try:
                    self._read_event(time.monotonic() + quiet_s)
                except DeviceTimeout:
                    break
            out = list(self.live_events)
            self.live_events.clear()
            return out

    def _read_event(self, deadline: float) -> None:
        """Read one unsolicited line (no command outstanding) and note it."""
        if self._cmd is None:
            self.open()
        try:
            raw = self._next_line(deadline, "no live image was announced")
        except ConnectionLost:
            self._disconnect()
            raise
        line = raw.lstrip(b"\n")
        if not line.strip():
            return
        try:
            code, rname, values = parse_reply(line)
        except ProtocolError:
            self._disconnect()
            raise
        if code in NOTIFICATION_CODES:
            self._note(code, rname, values, line)
        else:
            self._warnings.warning("foreign-reply", "RemoteEx: skipping reply %r while waiting for a "
                                   "live image", line)

    # ------------------------------------------------------------- data port
    def _drain_data(self, name: str) -> None:
        stray = self._data.drain()
        if stray:
            self.stray_data_bytes += len(stray)
            self._warnings.warning("stray-data", "RemoteEx: discarded %d stray bytes waiting on the data port "
                                   "before %s (first bytes %r)", len(stray), name, stray[:16])

    def _recv_data(self, nbytes: int, deadline: float) -> bytes:
        remaining = deadline - time.monotonic()
        try:
            if remaining <= 0:
                raise DeviceTimeout("deadline passed")
            payload = self._data.read_exactly(nbytes, timeout_s=remaining)
        except DeviceTimeout:
            got = len(self._data.drain())
            raise DeviceTimeout(f"RemoteEx: received {got} of {nbytes} data-port bytes within the timeout") from None
        extra = self._data.drain()
        if extra:
            raise ProtocolError(f"RemoteEx: the data port delivered {len(extra)} bytes beyond the {nbytes} "
                                f"announced; the transfer is misaligned", extra[:64])
        return payload

    def __repr__(self):
        return f"{type(self).__name__}({self.host!r}, {self.port}, data_port={self.data_port})"
