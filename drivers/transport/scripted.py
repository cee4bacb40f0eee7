"""An in-memory transport for byte-exact protocol tests (see :mod:`drivers.transport`)."""
from __future__ import annotations

from .base import LineTransport

__all__ = ["ScriptedTransport"]


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
