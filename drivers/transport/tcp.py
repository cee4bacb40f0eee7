"""TCP client connections (see :mod:`drivers.transport`)."""
from __future__ import annotations

import socket
import time

from .base import LineTransport, WriteBlocked

__all__ = ["TcpLineTransport"]


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
            raise WriteBlocked(f"send blocked for {self.timeout_s:g} s") from exc

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
