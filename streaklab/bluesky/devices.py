"""ophyd-async devices over the streaklab drivers: streak camera, scan mirror, laser sync.

The devices speak to the instruments only through the existing drivers
(:mod:`drivers.remoteex`, :mod:`drivers.smc100`, :mod:`drivers.scpi_sync`) and their
transports.  The drivers are synchronous and not thread-safe, so every driver call runs on
the one worker thread of a :class:`DriverThread`, one at a time and in order: a call that a
RunEngine pause cancelled still finishes there before the next one starts.

Connected with ``mock=True`` (``init_devices(mock=True)``) no driver is needed or touched:
every signal is a mock signal, a mirror move sets its readback at once and a trigger
completes at once.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import math

import numpy as np
from bluesky.protocols import Location
from ophyd_async.core import (AsyncStatus, DeviceConnector, NotConnectedError, StandardReadable,
                              soft_signal_r_and_setter, soft_signal_rw)
from ophyd_async.core import StandardReadableFormat as Format

from drivers.errors import DeviceError, DeviceTimeout

__all__ = ["DriverThread", "StreakCameraDetector", "ScanMirrorMotor", "LaserSyncDevice"]


#: the longest a synchronous caller waits for one call on the driver thread (s)
RUN_TIMEOUT_S = 300.0


class DriverThread:
    """One worker thread that owns the drivers: every call runs there, one at a time, in order."""

    def __init__(self):
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="streaklab-drivers")

    async def call(self, fn, *args):
        """Run ``fn(*args)`` on the worker thread and return its result.

        Cancelling the awaiting task (a RunEngine pause) does not stop the call: it runs to its
        end (every driver call is bounded by its own timeout) before the next call starts.
        """
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

    def run(self, fn, *args, timeout_s: float = RUN_TIMEOUT_S):
        """Run ``fn(*args)`` on the worker thread from synchronous code; wait for its result,
        at most ``timeout_s`` (every driver call has its own, shorter timeout: this bound only
        guards a cleanup step that would otherwise wait for ever)."""
        future = self._executor.submit(fn, *args)
        try:
            return future.result(timeout=timeout_s)
        except concurrent.futures.TimeoutError:
            raise DeviceTimeout(f"{getattr(fn, '__qualname__', fn)} did not finish within {timeout_s:g} s "
                                f"on the driver thread") from None

    def shutdown(self) -> None:
        """Let the running call finish, then stop the thread."""
        self._executor.shutdown(wait=True)


class _DriverConnector(DeviceConnector):
    """Real connect: the device needs its driver; mock connect: no driver, mock signals."""

    async def connect_mock(self, device, mock):
        device._mocked = True
        await super().connect_mock(device, mock)

    async def connect_real(self, device, timeout, force_reconnect):
        if device._driver is None or device._thread is None:
            raise NotConnectedError(f"{device.name or type(device).__name__}: no driver to connect to "
                                    f"(build it with an open driver, or connect it with mock=True)")
        device._mocked = False
        await super().connect_real(device, timeout, force_reconnect)
        await device._connected()


class _DriverDevice(StandardReadable):
    def __init__(self, driver, thread: DriverThread | None, name: str):
        self._driver = driver
        self._thread = thread
        self._mocked = False
        super().__init__(name=name, connector=_DriverConnector())

    async def _connected(self) -> None:
        """After a real connect: read what the device reports (nothing by default)."""

    async def _call(self, fn, *args):
        return await self._thread.call(fn, *args)

    def _writes_through(self, write):
        """A soft signal's setter that hands the new value to the device: ``write(value)`` on the
        driver thread.  A mock put still reaches a soft signal's setter: connected in mock mode
        the value is only stored."""
        async def setter(value):
            if not self._mocked:
                await self._call(write, value)
        return setter


class ScanMirrorMotor(_DriverDevice):
    """The SMC100 scan mirror as a movable: ``set(angle_deg)`` moves and waits until it settles.

    Parameters
    ----------
    driver : drivers.interfaces.ScanMirror, optional
        The open mirror driver (None: only a mock connect is possible).
    thread : DriverThread, optional
    settle_timeout_s : float
        How long a move may take to settle (``scan.settle_timeout_s``).

    Signals
    -------
    user_readback : the settled mirror angle (deg), the reading (hinted).
    user_setpoint : the last target angle (deg).
    """

    def __init__(self, driver=None, thread: DriverThread | None = None, *, settle_timeout_s: float = 10.0,
                 name: str = ""):
        self._settle_timeout_s = float(settle_timeout_s)
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.user_readback, self._set_readback = soft_signal_r_and_setter(float, math.nan, units="deg")
        self.user_setpoint = soft_signal_rw(float, math.nan, units="deg")
        super().__init__(driver, thread, name)

    async def _connected(self) -> None:
        self._set_readback(float(await self._call(self._driver.position)))

    def _move(self, angle_deg: float) -> float:
        self._driver.move_to(angle_deg)
        return float(self._driver.wait_settled(timeout_s=self._settle_timeout_s))

    @AsyncStatus.wrap
    async def set(self, value: float) -> None:
        """Move to ``value`` (deg) and wait until the stage settles; the readback is the angle reached."""
        value = float(value)
        await self.user_setpoint.set(value)
        if self._mocked:
            self._set_readback(value)
            return
        self._set_readback(await self._call(self._move, value))

    async def locate(self) -> Location[float]:
        return {"setpoint": await self.user_setpoint.get_value(), "readback": await self.user_readback.get_value()}

    async def stop(self, success: bool = True) -> None:
        """Stop any motion; the readback is where the stage stopped."""
        if self._mocked or self._thread is None:
            return
        stop = getattr(self._driver, "stop", None)
        if stop is not None:
            await self._call(stop)
            self._set_readback(float(await self._call(self._driver.position)))


class LaserSyncDevice(_DriverDevice):
    """The SCPI laser sync with its settings as signals; setting one writes it to the unit.

    A setting the unit refuses (an entry in its error queue after the write) fails the set
    with :class:`drivers.errors.DeviceError`.

    Signals
    -------
    repetition_rate_hz, trigger_delay_ps, channel : configuration.
    output_enabled : whether the trigger output is on (read).
    """

    def __init__(self, driver=None, thread: DriverThread | None = None, *, repetition_rate_hz: float = 0.0,
                 trigger_delay_ps: float = 0.0, channel: int = 1, name: str = ""):
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.repetition_rate_hz = soft_signal_rw(float, float(repetition_rate_hz), units="Hz",
                                                     setter=self._writer(self._set_rate))
            self.trigger_delay_ps = soft_signal_rw(float, float(trigger_delay_ps), units="ps",
                                                   setter=self._writer(self._set_delay))
            self.channel = soft_signal_rw(int, int(channel))
        with self.add_children_as_readables():
            self.output_enabled = soft_signal_rw(bool, False, setter=self._writer(self._set_output))
        super().__init__(driver, thread, name)

    def _writer(self, write):
        """A setter writing ``write(value, channel)`` on the driver thread (stored only when mocked)."""
        async def setter(value):
            if not self._mocked:
                await self._call(write, value, await self.channel.get_value())
        return setter

    def _checked(self, fn) -> None:
        fn()
        errors = self._driver.read_errors()
        if errors:
            raise DeviceError(errors[0][0], errors[0][1], device="laser sync")

    def _set_rate(self, value, channel):
        self._checked(lambda: self._driver.set_repetition_rate(float(value)))

    def _set_delay(self, value, channel):
        self._checked(lambda: self._driver.set_trigger_delay(float(value), channel=int(channel)))

    def _set_output(self, value, channel):
        self._driver.set_output(bool(value))


class StreakCameraDetector(_DriverDevice):
    """The streak camera as a triggerable detector: one trigger takes one scan line into the run store.

    A trigger acquires the line named by :attr:`line` with the capture session's line step
    (:meth:`acquisition.session.CaptureSession.take_line`: mirror move, settle,
    ``frames_per_line`` frames, laser-sync check, durable write into the run store), so the
    frames go to the same bytes ``streaklab capture`` writes.  A line already on disk is not
    taken again: a trigger replayed after a RunEngine pause reports it as it is.  Staging
    runs the session's preparation (device check and settings, dark frames, store creation
    or resumption, the session's entry); unstaging closes the entry.

    Signals
    -------
    line : the scan line the next trigger takes (hinted reading).
    angle_deg : mirror angle reached for that line (deg), as stored.
    mean_counts : mean count of the line's frames (a live-plot value; the frames are in the run store).
    time_range, exposure_s, gain, frames_per_line, run_store : configuration.
    """

    def __init__(self, driver=None, thread: DriverThread | None = None, *, session=None,
                 time_range: str = "", exposure_s: float = 0.0, gain: int = 0, frames_per_line: int = 1,
                 run_store: str = "", name: str = ""):
        self._session = session
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.line = soft_signal_rw(int, -1)
        with self.add_children_as_readables():
            self.angle_deg, self._set_angle = soft_signal_r_and_setter(float, math.nan, units="deg")
            self.mean_counts, self._set_mean = soft_signal_r_and_setter(float, math.nan, units="counts")
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.time_range = soft_signal_rw(str, str(time_range), setter=self._setting("time_range"))
            self.exposure_s = soft_signal_rw(float, float(exposure_s), units="s",
                                             setter=self._setting("exposure_s"))
            self.gain = soft_signal_rw(int, int(gain), setter=self._setting("gain"))
            self.frames_per_line, _ = soft_signal_r_and_setter(int, int(frames_per_line))
            self.run_store, _ = soft_signal_r_and_setter(str, str(run_store))
        super().__init__(driver, thread, name)

    def _setting(self, key: str):
        def configure(value):
            if key == "time_range" and str(value).lstrip("-").isdigit():
                value = int(value)                      # a synchroscan setting number
            self._driver.configure(**{key: value})
        return self._writes_through(configure)

    @property
    def lines_todo(self) -> list[int]:
        """The lines not yet on disk (after :meth:`stage`); empty without a session."""
        return [] if self._session is None or self._session.store is None else self._session.lines_todo()

    def _begin(self) -> None:
        self._session.begin()
        if self._session.lines_todo():
            self._session.output_on()

    def _take(self, line: int) -> tuple[float, float]:
        session = self._session
        if not session.line_done(line):
            session.take_line(line)
        store = session.store
        angle = float(np.asarray(store["angle_deg"][line]))
        mean = float(np.asarray(store["streaks"][line], dtype=np.float64).mean())
        return angle, mean

    @AsyncStatus.wrap
    async def stage(self) -> None:
        """Prepare the session: check and configure the devices, dark frames, open the run store."""
        if self._mocked or self._session is None:
            return
        await self._call(self._begin)

    @AsyncStatus.wrap
    async def unstage(self) -> None:
        """Laser-sync output off; the session's entry is closed by the plan (it knows how the run ended)."""
        if self._mocked or self._session is None or self._thread is None:
            return
        await self._call(self._session.make_safe)

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Take the line named by :attr:`line` into the run store (or report it if already there)."""
        line = int(await self.line.get_value())
        if self._mocked:
            return
        if self._session is None:
            raise NotConnectedError(f"{self.name}: no capture session to take line {line} into")
        if not 0 <= line < self._session.n_lines:
            raise ValueError(f"{self.name}: line {line} is outside the scan's 0..{self._session.n_lines - 1}")
        angle, mean = await self._call(self._take, line)
        self._set_angle(angle)
        self._set_mean(mean)
