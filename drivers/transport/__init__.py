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

Layout: :mod:`.base` (the API, buffering, resynchronisation, reconnect),
:mod:`.serial_line`, :mod:`.tcp`, :mod:`.scripted`.  Import from
``drivers.transport``.

Subclasses implement four primitives: ``_open()``, ``_close_link()``,
``_send(data)`` and ``_receive(max_bytes, deadline)``; I/O failures are raised
as ``OSError`` (or pyserial's ``SerialException``) and turned into the errors
above by this base class.
"""
from .base import LineTransport
from .scripted import ScriptedTransport
from .serial_line import SerialLineTransport
from .tcp import TcpLineTransport

__all__ = ["LineTransport", "SerialLineTransport", "TcpLineTransport", "ScriptedTransport"]
