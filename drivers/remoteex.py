"""Hamamatsu streak camera over RemoteEx (the TCP remote control of HPD-TA / HiPic): the command table.

The wire format lives in :mod:`drivers.remoteex_wire`, the two connections
(command and data port: greetings, lock, timeouts, reconnect, data-port
framing) in :mod:`drivers.remoteex_link`.  This module says which commands
implement the :class:`~drivers.interfaces.StreakCamera` calls and what their
replies mean (RemoteEx programmer's handbook; section names in the comments):

* ``ImgDataGet(Current,Data)`` replies ``0,ImgDataGet,width,height,bytes_per_pixel,type``
  and the raw little-endian pixels (row-major, ``height`` rows of ``width``
  pixels) follow on the data port.  On a streak camera the rows are the sweep
  (time) direction and the columns the slit (space) direction.
* ``ImgDataGet(Current,ScalingTable,Vertical)`` replies ``0,ImgDataGet,count,type``
  and ``count`` little-endian float32 row times follow on the data port, in the
  unit of the time range (see :func:`~drivers.remoteex_wire.scaling_table_unit_ps`).
* ``AcqStatus()`` replies ``idle`` or ``busy`` followed by the mode.
* ``CamParamGet/Set(Location,Exposure[,value])`` take exposure times such as
  ``10 ms``; ``DevParamGet/Set(Streak,Time Range[,value])`` (a setting number on
  a synchroscan unit, a time such as ``1 ns`` on a single-sweep unit),
  ``DevParamSet(Streak,Mode,Focus|Operate)`` and
  ``DevParamGet/Set(Delaybox,Delay A[,seconds])`` address the streak unit and
  the delay generator.
* Live mode (acquisition commands, ``AcqLiveMonitor``/``ImgRingBufferGet``):
  ``AcqLiveMonitor(RingBuffer,N)`` makes the server announce every new live
  image with ``4,Livemonitor,RingBuffer,<seq>``; ``ImgRingBufferGet(Data,<seq>)``
  replies like ``ImgDataGet`` plus the sequence number and a time stamp, and
  the pixels follow on the data port.
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np

from .errors import DeviceError, DeviceTimeout, DriverError, ProtocolError
from .interfaces import StreakImage
from .remoteex_link import RemoteExLink
from .remoteex_wire import (COMMAND_BANNER, DATA_BANNER, DEFAULT_PORT, ERROR_MEANINGS, NOTIFICATION_CODES,
                            _BPP_DTYPE, format_command, format_exposure, format_seconds, normalize_time_range,
                            parse_exposure, parse_reply, scaling_table_unit_ps)

__all__ = [
    "RemoteExCamera",
    "ERROR_MEANINGS",
    "NOTIFICATION_CODES",
    "COMMAND_BANNER",
    "DATA_BANNER",
    "DEFAULT_PORT",
    "format_command",
    "parse_reply",
    "format_exposure",
    "parse_exposure",
    "format_seconds",
]

log = logging.getLogger(__name__)


class RemoteExCamera(RemoteExLink):
    """Streak camera driven through RemoteEx; implements :class:`drivers.interfaces.StreakCamera`.

    Parameters
    ----------
    host, port, data_port, timeout_s, connect_timeout_s, open_transports
        The connection (see :class:`~drivers.remoteex_link.RemoteExLink`).
    start_app : bool
        Send ``AppStart()`` after the first connection (starts HPD-TA/HiPic
        if it is not running yet).
    app_start_timeout_s : float
        Timeout for ``AppStart`` (the application may take a while to come up).
    acquire_mode : str
        Acquisition mode passed to ``AcqStart`` (``Acquire``: one image per start).
    exposure_location : str
        ``CamParamSet`` location holding the exposure of ``acquire_mode``.
    streak_device, delay_device, delay_parameter : str
        ``DevParam*`` names of the streak unit, the delay generator and its delay.
    poll_interval_s : float
        Pause between ``AcqStatus`` polls while an acquisition runs.
    synchroscan_table_unit_ps : float
        Picoseconds per scaling-table unit when the time range is a synchroscan
        setting number (a single-sweep range says its own unit).
    connect : bool
        Connect in the constructor (default).  Otherwise the first command does.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, data_port: int | None = None,
                 timeout_s: float = 5.0, connect_timeout_s: float = 5.0, start_app: bool = True,
                 app_start_timeout_s: float = 30.0, acquire_mode: str = "Acquire",
                 exposure_location: str = "Acquire", streak_device: str = "Streak",
                 delay_device: str = "Delaybox", delay_parameter: str = "Delay A",
                 poll_interval_s: float = 0.005, synchroscan_table_unit_ps: float = 1.0,
                 open_transports=None, connect: bool = True):
        super().__init__(host, port, data_port=data_port, timeout_s=timeout_s, connect_timeout_s=connect_timeout_s,
                         open_transports=open_transports)
        if not (isinstance(app_start_timeout_s, (int, float)) and math.isfinite(app_start_timeout_s)
                and app_start_timeout_s > 0):
            raise ValueError(f"app_start_timeout_s must be a positive number of seconds, got {app_start_timeout_s!r}")
        if not (math.isfinite(synchroscan_table_unit_ps) and synchroscan_table_unit_ps > 0):
            raise ValueError(f"synchroscan_table_unit_ps must be positive, got {synchroscan_table_unit_ps!r}")
        self.app_start_timeout_s = float(app_start_timeout_s)
        self.acquire_mode = acquire_mode
        self.exposure_location = exposure_location
        self.streak_device = streak_device
        self.delay_device = delay_device
        self.delay_parameter = delay_parameter
        self.poll_interval_s = float(poll_interval_s)
        self.synchroscan_table_unit_ps = float(synchroscan_table_unit_ps)
        self._start_app = bool(start_app)
        self._app_started = False
        self._settings: dict = {}
        self._last_image_info: dict = {}
        if connect:
            try:
                self.open()
            except BaseException:
                self.close()
                raise

    def open(self) -> None:
        """Connect (if not connected) and start the application if asked to."""
        with self._lock:
            super().open()
            if self._start_app and not self._app_started:
                self.command("AppStart", timeout_s=self.app_start_timeout_s)
                self._app_started = True

    # --------------------------------------------------------- device calls
    def identify(self) -> str:
        """Application type and version, e.g. ``'Hamamatsu HPD-TA 9.5 (RemoteEx at host:1001)'``."""
        with self._lock:
            app = ",".join(self.command("AppInfo", "Type")).strip()
            version = ",".join(self.command("AppInfo", "Version")).strip()
        return f"Hamamatsu {app} {version} (RemoteEx at {self.host}:{self.port})"

    def camera_info(self) -> list[str]:
        """The readout camera's description: model, then product number, serial, firmware, version lines.

        ``CamParamGet(Setup,CameraInfo)`` is the one multi-line reply of RemoteEx: the model
        comes in the reply, the other lines follow as CRLF-separated lines.
        """
        with self._lock:
            values = self.command("CamParamGet", "Setup", "CameraInfo")
            return [",".join(values).strip()] + self.read_continuation()

    def app_end(self) -> None:
        """Close the remote application (HPD-TA/HiPic)."""
        self.command("AppEnd")
        self._app_started = False

    def configure(self, *, time_range: int | str | None = None, exposure_s: float | None = None,
                  gain: int | None = None) -> None:
        """Set the streak time range, exposure (s) and MCP gain (setting).

        ``time_range`` is a synchroscan setting number (``2``) or a single-sweep time (``"1 ns"``).
        """
        if gain is not None and (isinstance(gain, bool) or not isinstance(gain, (int, np.integer))):
            raise ValueError(f"gain must be an integer setting, got {gain!r}")
        if isinstance(time_range, (float, np.floating)) or isinstance(time_range, bool):
            raise ValueError(f"time_range must be an integer setting or a time such as '1 ns', got {time_range!r}")
        tr = None
        if time_range is not None:
            tr = normalize_time_range(time_range)
            if isinstance(tr, int) and tr < 1:
                raise ValueError(f"time_range must be >= 1, got {tr}")
        if gain is not None and gain < 0:
            raise ValueError(f"gain must be >= 0, got {gain}")
        exposure_text = format_exposure(exposure_s) if exposure_s is not None else None
        with self._lock:
            if tr is not None:
                self.command("DevParamSet", self.streak_device, "Time Range", tr)
                self._settings["time_range"] = tr
            if exposure_text is not None:
                self.command("CamParamSet", self.exposure_location, "Exposure", exposure_text)
                self._settings["exposure_s"] = parse_exposure(exposure_text)
            if gain is not None:
                self.command("DevParamSet", self.streak_device, "MCP Gain", int(gain))
                self._settings["gain"] = int(gain)

    def exposure_s(self, location: str | None = None) -> float:
        """Exposure time read back from the camera, seconds (``location`` default: ``exposure_location``)."""
        values = self.command("CamParamGet", location or self.exposure_location, "Exposure")
        try:
            value = parse_exposure(values[0])
        except (IndexError, ValueError):
            raise ProtocolError("CamParamGet(Exposure) reply has no time value", ",".join(values).encode()) from None
        if location is None:
            self._settings["exposure_s"] = value
        return value

    def set_exposure_s(self, exposure_s: float, location: str) -> None:
        """Set the exposure of one acquisition location (``Live``, ``Acquire``, ``AI``, ``PC``)."""
        self.command("CamParamSet", location, "Exposure", format_exposure(exposure_s))

    def _dev_int(self, parameter: str) -> int:
        values = self.command("DevParamGet", self.streak_device, parameter)
        try:
            return int(float(values[0]))
        except (IndexError, ValueError):
            raise ProtocolError(f"DevParamGet({parameter}) reply is not a number", ",".join(values).encode()) from None

    def time_range(self) -> int | str:
        """Streak time range read back: a setting number, or a time such as ``'1 ns'``."""
        values = self.command("DevParamGet", self.streak_device, "Time Range")
        try:
            v = normalize_time_range(values[0])
        except (IndexError, ValueError):
            raise ProtocolError("DevParamGet(Time Range) reply is neither a setting number nor a time",
                                ",".join(values).encode()) from None
        self._settings["time_range"] = v
        return v

    def gain(self) -> int:
        """MCP gain setting read back from the streak unit."""
        self._settings["gain"] = v = self._dev_int("MCP Gain")
        return v

    def gain_off(self) -> bool:
        """MCP gain to 0 (the gain interlock); False when the streak unit has no MCP gain control.

        The streak unit's MCP is protected by setting its gain to 0 whenever no swept
        acquisition needs it: in Focus mode, after an acquisition ends, on shutdown and
        after a fault (see docs/streak-camera.md, "Gain interlocks").
        """
        try:
            self.command("DevParamSet", self.streak_device, "MCP Gain", 0)
        except DeviceError as exc:
            if exc.code != 2:           # 2: no such parameter: this unit has no MCP gain control
                raise
            return False
        self._settings["gain"] = 0
        return True

    def set_streak_mode(self, mode: str) -> None:
        """Streak unit mode: ``Operate`` (sweeping) or ``Focus`` (no sweep, for alignment).

        ``Focus`` sets the MCP gain to 0 first (:meth:`gain_off`): without the sweep all the
        light lands on one line of the phosphor.  ``Operate`` leaves the gain as it is.
        """
        if mode not in ("Operate", "Focus"):
            raise ValueError(f"streak mode must be 'Operate' or 'Focus', got {mode!r}")
        with self._lock:
            if mode == "Focus":
                self.gain_off()
            self.command("DevParamSet", self.streak_device, "Mode", mode)

    def operate(self) -> bool:
        """Streak unit in ``Operate`` mode (sweeping), as a swept acquisition needs before its gain
        is raised: a live view in Focus mode that was killed leaves the sweep off, and the MCP
        gain stays 0 in Focus mode.  False when the unit has no Mode control (nothing to switch)."""
        try:
            self.set_streak_mode("Operate")
        except DeviceError as exc:
            if exc.code != 2:            # 2: no such parameter: this streak unit has no Mode control
                raise
            return False
        return True

    def streak_mode(self) -> str:
        """Streak unit mode read back (``Operate`` or ``Focus``)."""
        values = self.command("DevParamGet", self.streak_device, "Mode")
        if not values:
            raise ProtocolError("DevParamGet(Mode) reply has no value", b"")
        return values[0].strip()

    def set_delay_ps(self, delay_ps: float) -> None:
        """Set the delay generator's delay (``Delay A``), picoseconds."""
        delay_ps = float(delay_ps)
        if not math.isfinite(delay_ps) or delay_ps < 0:
            raise ValueError(f"delay_ps must be finite and >= 0, got {delay_ps!r}")
        self.command("DevParamSet", self.delay_device, self.delay_parameter, format_seconds(delay_ps * 1e-12))
        self._settings["delay_ps"] = delay_ps

    def delay_ps(self) -> float:
        """Delay generator's delay read back, picoseconds."""
        values = self.command("DevParamGet", self.delay_device, self.delay_parameter)
        try:
            v = float(values[0]) * 1e12
        except (IndexError, ValueError):
            raise ProtocolError("DevParamGet(delay) reply is not a number", ",".join(values).encode()) from None
        self._settings["delay_ps"] = v
        return v

    def settings(self) -> dict:
        """All settings read back from the device: time_range, exposure_s, gain, delay_ps."""
        with self._lock:
            return {"time_range": self.time_range(), "exposure_s": self.exposure_s(),
                    "gain": self.gain(), "delay_ps": self.delay_ps()}

    def _refresh_settings(self) -> None:
        # Settings a rig may lack (no delay generator, no MCP gain control) are recorded as None.
        for key, getter in (("time_range", self.time_range), ("exposure_s", self.exposure_s),
                            ("gain", self.gain), ("delay_ps", self.delay_ps)):
            if key not in self._settings:
                try:
                    getter()
                except DeviceError as exc:
                    log.info("RemoteEx: %s not readable (%s); recorded as None", key, exc)
                    self._settings[key] = None

    def scaling_table_ps(self, *, timeout_s: float | None = None) -> np.ndarray | None:
        """The camera's own time calibration of the current image: the time of each row, ps after the trigger.

        Reads ``ImgDataGet(Current,ScalingTable,Vertical)`` (float32 per row, in the time
        range's unit).  Returns None when the camera refuses it (code 2: no such data, or
        7: the image has no table scaling, e.g. a unit without calibration).

        Returns
        -------
        ndarray, shape (rows,), float64, ps; or None.
        """
        def announced(values):
            try:
                n = int(values[0])
            except (IndexError, ValueError):
                raise ProtocolError("ImgDataGet(ScalingTable) reply lacks the number of values",
                                    ",".join(values).encode()) from None
            if not 0 < n <= 1 << 20:
                raise ProtocolError(f"ImgDataGet(ScalingTable) announced {n} values", ",".join(values).encode())
            return 4 * n

        with self._lock:
            tr = self._settings.get("time_range")
            if tr is None:
                tr = self.time_range()
            try:
                _, payload = self.transaction("ImgDataGet", ("Current", "ScalingTable", "Vertical"),
                                              timeout_s=timeout_s, data=announced)
            except DeviceError as exc:
                if exc.code in (2, 7):
                    log.info("RemoteEx: no scaling table (%s)", exc)
                    return None
                raise
        table = np.frombuffer(payload, dtype="<f4").astype(np.float64)
        unit_ps = scaling_table_unit_ps(tr)
        if unit_ps is None:
            unit_ps = self.synchroscan_table_unit_ps
        if not np.all(np.isfinite(table)):
            raise ProtocolError("scaling table holds non-finite values", payload[:64])
        return table * unit_ps

    def acq_status(self) -> tuple[str, str]:
        """``(status, mode)``: status ``'idle'`` or ``'busy'``; mode may be empty."""
        values = self.command("AcqStatus")
        if not values:
            raise ProtocolError("AcqStatus reply has no status", b"")
        return values[0].strip().lower(), (values[1].strip() if len(values) > 1 else "")

    def start(self, mode: str | None = None) -> None:
        """Start an acquisition in ``mode`` (default ``acquire_mode``)."""
        self.command("AcqStart", mode or self.acquire_mode)

    def stop(self) -> None:
        """Stop any running acquisition."""
        self.command("AcqStop")

    def _pixels(self, name: str, args, *, timeout_s: float | None) -> tuple[np.ndarray, dict]:
        """Run an image transfer (``ImgDataGet``/``ImgRingBufferGet``); (x, t) uint16 and the reply fields."""
        shape = {}

        def announced(values):
            try:
                w, h, bpp = int(values[0]), int(values[1]), int(values[2])
            except (IndexError, ValueError):
                raise ProtocolError(f"{name} reply lacks width,height,bytes-per-pixel",
                                    ",".join(values).encode()) from None
            if w <= 0 or h <= 0 or bpp not in _BPP_DTYPE or w * h > 1 << 28:
                raise ProtocolError(f"{name} announced an impossible image {w}x{h}x{bpp}",
                                    ",".join(values).encode())
            shape.update(w=w, h=h, bpp=bpp, type=values[3].strip() if len(values) > 3 else "",
                         extra=[v.strip() for v in values[4:]])
            return w * h * bpp

        _, payload = self.transaction(name, args, timeout_s=timeout_s, data=announced)
        img = np.frombuffer(payload, dtype=_BPP_DTYPE[shape["bpp"]]).reshape(shape["h"], shape["w"])
        if shape["bpp"] == 4 and img.size and img.max() > np.iinfo(np.uint16).max:
            raise ProtocolError("32-bit image holds values beyond the uint16 range", b"")
        return np.ascontiguousarray(img.T).astype(np.uint16, copy=False), shape

    def read_image(self, *, timeout_s: float | None = None) -> np.ndarray:
        """Transfer the current image.

        Returns
        -------
        ndarray, shape (x, t), uint16
            Axis 0 along the slit (image columns), axis 1 along the sweep (image rows).
        """
        img, self._last_image_info = self._pixels("ImgDataGet", ("Current", "Data"), timeout_s=timeout_s)
        return img

    # ------------------------------------------------------------ live mode
    def start_live(self, *, ring_buffers: int = 4) -> None:
        """Start live acquisition with ring-buffer monitoring (every new image is announced)."""
        if not 1 <= int(ring_buffers) <= 1000:
            raise ValueError(f"ring_buffers must be in 1..1000, got {ring_buffers!r}")
        with self._lock:
            self.live_events.clear()
            self.command("AcqLiveMonitor", "RingBuffer", int(ring_buffers))
            try:
                self.command("AcqStart", "Live")
            except DeviceError as exc:
                if exc.code != 7:
                    raise
                self.command("AcqStop")
                self.command("AcqStart", "Live")

    def live_image(self, *, timeout_s: float = 5.0) -> tuple[np.ndarray, int]:
        """The newest live image: ``(data (x, t) uint16, sequence number)``.

        Waits for the next announcement, skips older announcements already queued, and
        fetches that image from the ring buffer.
        """
        with self._lock:
            seq = None
            deadline = time.monotonic() + float(timeout_s)
            while seq is None:
                values = self.wait_live_event(max(deadline - time.monotonic(), 1e-3))
                for later in self.pending_live_events():    # the newest announcement wins
                    values = later
                if len(values) >= 2 and values[0].strip().lower() == "ringbuffer":
                    try:
                        seq = int(values[1])
                    except ValueError:
                        raise ProtocolError("live announcement has no sequence number",
                                            ",".join(values).encode()) from None
            img, info = self._pixels("ImgRingBufferGet", ("Data", seq), timeout_s=timeout_s)
        got = int(info["extra"][0]) if info["extra"] else seq
        return img, got

    def stop_live(self) -> None:
        """Stop the live acquisition and its monitoring."""
        with self._lock:
            self.command("AcqStop")
            self.command("AcqLiveMonitor", "Off")
            self.live_events.clear()

    def acquire(self, *, timeout_s: float = 10.0) -> StreakImage:
        """Take one streak image: start, wait until idle, transfer.

        The whole sequence runs under the connection lock, so concurrent callers
        each get a complete image of their own.

        Parameters
        ----------
        timeout_s : float
            Bound on the whole acquisition, seconds.

        Returns
        -------
        StreakImage with ``data`` of shape (x, t), uint16.
        """
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
        deadline = time.monotonic() + timeout_s

        def late():
            return DeviceTimeout(f"RemoteEx: acquisition not finished within {timeout_s} s")

        def remaining():
            r = deadline - time.monotonic()
            if r <= 0:
                raise late()
            return min(r, self.timeout_s)

        with self._lock:
            try:
                self._start_acquisition(remaining)
                while True:
                    try:
                        values = self.command("AcqStatus", timeout_s=remaining())
                    except DeviceTimeout:
                        # a status query started just before the deadline gets only what is left
                        # of it: its timeout is the acquisition's, and is reported as such
                        if time.monotonic() >= deadline:
                            raise late() from None
                        raise
                    if values and values[0].strip().lower() == "idle":
                        break
                    if deadline - time.monotonic() <= 0:
                        raise late()
                    time.sleep(min(self.poll_interval_s, max(0.0, deadline - time.monotonic())))
            except DeviceTimeout:
                self._abort_acquisition()
                raise
            taken = time.time()
            data = self.read_image(timeout_s=remaining())
            if not {"time_range", "exposure_s", "gain", "delay_ps"} <= self._settings.keys():
                self._refresh_settings()
            meta = {"time_range": self._settings.get("time_range"),
                    "exposure_s": self._settings.get("exposure_s"),
                    "gain": self._settings.get("gain"),
                    "delay_ps": self._settings.get("delay_ps"),
                    "acquired_unix_s": taken,
                    "image_type": self._last_image_info.get("type", ""),
                    "bytes_per_pixel": self._last_image_info["bpp"]}
        return StreakImage(data=data, metadata=meta)

    def _start_acquisition(self, remaining) -> None:
        try:
            self.command("AcqStart", self.acquire_mode, timeout_s=remaining())
        except DeviceError as exc:
            # 7 (cannot execute): an acquisition is still running, e.g. one left over
            # from an interrupted session.  Stop it and start ours once more.
            if exc.code != 7:
                raise
            log.warning("RemoteEx: AcqStart refused (%s); stopping the running acquisition and retrying", exc)
            self.command("AcqStop", timeout_s=remaining())
            self.command("AcqStart", self.acquire_mode, timeout_s=remaining())

    def _abort_acquisition(self) -> None:
        try:
            self.command("AcqStop", timeout_s=min(self.timeout_s, 2.0))
        except DriverError as exc:
            log.warning("RemoteEx: AcqStop after an acquisition timeout failed: %s", exc)

    # ------------------------------------------------------- context manager
    def __enter__(self):
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        """Stop any acquisition and set the MCP gain to 0 (the shutdown interlock), then disconnect."""
        try:
            self.stop()
            self.gain_off()
        except DriverError:
            if exc_type is None:
                self.close()
                raise
            log.exception("RemoteEx: could not stop the acquisition and set the gain to 0 while leaving "
                          "after an error")
        finally:
            self.close()
