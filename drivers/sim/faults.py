"""One-shot fault injection shared by the simulators.

A simulator owns a :class:`FaultInjector` and calls :meth:`FaultInjector.take`
with the name of every command it is about to answer; a matching pending fault
is removed and returned, and the simulator misbehaves accordingly instead of
answering normally.  Tests arm faults with :meth:`FaultInjector.inject`::

    sim.inject("drop_reply", command="AcqStatus")      # next AcqStatus gets no reply
    sim.inject("error", command="CamParamSet", code=10)
    sim.inject("close", times=2)                        # the next two commands, any name

Fault kinds every simulator understands (a simulator may add its own):

``drop_reply``  execute the command, send nothing back
``delay``       answer after ``delay_s`` seconds (longer than the client's timeout)
``garbage``     send bytes that do not follow the protocol instead of the answer
``close``       drop the connection without answering
``error``       do not execute; report the device error ``code``
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

COMMON_KINDS = frozenset({"drop_reply", "delay", "garbage", "close", "error"})


@dataclass(frozen=True)
class Fault:
    """One armed fault.

    Attributes
    ----------
    kind : str
        What goes wrong (see the module docstring).
    command : str or None
        Command name it applies to (case-insensitive); None matches any command.
    code : int or str or None
        Device error code for ``kind="error"``.
    delay_s : float
        Delay for ``kind="delay"`` in seconds.
    """

    kind: str
    command: str | None = None
    code: int | str | None = None
    delay_s: float = 2.0

    def matches(self, command: str) -> bool:
        return self.command is None or self.command.lower() == command.lower()


class FaultInjector:
    """Thread-safe list of one-shot faults.

    Parameters
    ----------
    kinds : iterable of str
        Fault kinds the owning simulator implements; anything else is rejected
        at :meth:`inject` time so a typo in a test fails loudly.
    """

    def __init__(self, kinds=COMMON_KINDS):
        self.kinds = frozenset(kinds)
        self._pending: list[Fault] = []
        self._lock = threading.Lock()

    def inject(self, kind: str, command: str | None = None, *, code=None, delay_s: float = 2.0,
               times: int = 1) -> None:
        """Arm ``times`` one-shot faults of ``kind`` for ``command`` (None: any command)."""
        if kind not in self.kinds:
            raise ValueError(f"unknown fault kind {kind!r}; this simulator knows {sorted(self.kinds)}")
        if kind == "error" and code is None:
            raise ValueError("fault kind 'error' needs a device error code (code=...)")
        if not (delay_s >= 0):
            raise ValueError(f"delay_s must be >= 0, got {delay_s!r}")
        times = int(times)
        if times < 1:
            raise ValueError(f"times must be >= 1, got {times}")
        fault = Fault(kind, command, code, float(delay_s))
        with self._lock:
            self._pending.extend([fault] * times)

    def take(self, command: str) -> Fault | None:
        """Remove and return the first pending fault that applies to ``command``, or None."""
        with self._lock:
            for i, fault in enumerate(self._pending):
                if fault.matches(command):
                    return self._pending.pop(i)
        return None

    def pending(self) -> list[Fault]:
        """Faults armed but not yet triggered, in order."""
        with self._lock:
            return list(self._pending)

    def clear(self) -> None:
        with self._lock:
            self._pending.clear()
