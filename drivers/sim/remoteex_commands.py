"""The command table of the simulated RemoteEx server: what each command does and answers.

:class:`RemoteExCommands` holds the state of the simulated application (HPD-TA),
readout camera, streak unit and delay generator, and one ``_cmd_<name>`` method
per command (names case-insensitive).  A handler returns ``(values, payload)``:
the reply fields after ``0,Name`` and the bytes for the data port (or None), or
raises :class:`Reply` with an error code.  The server
(:mod:`drivers.sim.camera`) does the networking and calls :meth:`tick` between
commands so that live images appear on time.

Commands (RemoteEx programmer's handbook, section of each in brackets):

* [General] ``AppInfo``, ``AsyncCommandStatus`` (``pending,preparing,active[,command]``),
  ``Stop``;
* [Application] ``AppStart``, ``AppEnd``, ``AppLicenceGet`` (six 0/1 flags: application
  key, acquire, save, fitting, photon correction, transmission/absorption);
* [Acquisition] ``AcqStart(Live|SingleLive|Acquire|AI|PC)``, ``AcqStatus``,
  ``AcqStop[(timeout_ms)]``, ``AcqLiveMonitor(Off|Notify|NotifyTimeStamp|RingBuffer[,N]|
  Average|Minimum|Maximum[,FullArea|Subarray,X,Y,DX,DY]|Profile,type,FullArea|Subarray,X,Y,DX,DY)``;
* [Camera] ``CamParamGet/Set/Info/InfoEx``, ``CamParamsList`` on Setup, Live, Acquire,
  AI, PC (``CamParamGet(Setup,CameraInfo)`` answers over several CRLF lines);
* [External devices] ``DevParamGet/Set/Info/InfoEx``, ``DevParamsList`` on the streak
  unit (Streak, Streakcamera, TD) and the delay generator (Delaybox, Del, Delay, Del1),
  plus the keywords DeviceName, PluginName, OptionName1..4;
* [Image] ``ImgDataGet(current,Data|Display|Profile,...|ScalingTable,Vertical)``,
  ``ImgRingBufferGet(Data,seq)`` (with the frames themselves in
  :mod:`drivers.sim.remoteex_images`).

Modes.  ``Acquire`` renders one frame; ``AI`` (analog integration) sums
``NrExposures`` frames; ``PC`` (photon counting) sums ``NrExposures`` photon-count
frames (no dark level, no read noise).  ``Live`` renders a new frame every
live interval until ``AcqStop``; ``SingleLive`` renders one.  With
``AcqLiveMonitor`` on, every live frame is announced on the command port:
``4,Livemonitor,RingBuffer,<seq>`` (the ring buffer keeps the last N),
``4,Livemonitor,Notify``, ``4,Livemonitor,NotifyTimeStamp,<ms>``,
``4,Livemonitor,Average|Minimum|Maximum,<value>``, or
``4,Livemonitor,Profile,<n>,<v1>,...`` (profile types as for ``ImgDataGet``).  The streak unit's ``Mode``
``Focus`` turns the sweep off (the slit image on the middle rows).

Choices where the handbook leaves the code open: a scaling table of an image
without table scaling is refused with 7; a ring-buffer sequence number newer
than the newest image with 7; writing ring-buffer data to a file is not
simulated (7).
"""
from __future__ import annotations

import time

import numpy as np

from drivers.remoteex_wire import format_seconds, normalize_time_range, parse_exposure

from .remoteex_images import RemoteExImages
from .remoteex_params import SINGLE_SWEEP_RANGES, Reply, camera_params, delay_params, need as _need, streak_params

__all__ = ["RemoteExCommands", "Reply"]

_STREAK_NAMES = {"streak", "streakcamera", "td"}
_DELAY_NAMES = {"delaybox", "del", "delay", "del1"}
_MODES = {"live": "Live", "singlelive": "SingleLive", "acquire": "Acquire", "ai": "AI", "pc": "PC"}
_MONITORS = {"off": "Off", "notify": "Notify", "notifytimestamp": "NotifyTimeStamp", "ringbuffer": "RingBuffer",
             "average": "Average", "minimum": "Minimum", "maximum": "Maximum", "profile": "Profile"}
_CAMERA_INFO = ("Product number: C13440-20C (simulated)", "Serial number: 000001", "Firmware: 1.0.A",
                "Version: 1.0.A-streaklab")
_DEVICE_NAMES = {"streak": ("C5680 streak unit (simulated)", "Streak plugin (simulated)"),
                 "delay": ("delay generator (simulated)", "Delay plugin (simulated)")}


class RemoteExCommands(RemoteExImages):
    """Device state and command handlers (mixed into :class:`~drivers.sim.camera.RemoteExSimulator`).

    The owner sets ``scene``, ``state``, ``seed``, ``frame_time_s``, ``app_type``,
    ``app_version``, ``single_sweep``, ``scaling_table``, ``timebase`` and ``clock`` and calls
    :meth:`_init_device` once.

    Ground truth for tests: :attr:`gain_log` holds ``(simulated time s, MCP gain, streak
    mode)`` at the start and whenever the gain or the mode changes; :attr:`frame_shifts` one
    dict per exposure rendered with time-base effects (``sim_time_s``, ``jitter_ps``,
    ``drift_ps``, ``shift_ps``, see :mod:`drivers.sim.timebase`).
    """

    def _init_device(self) -> None:
        self.app_started = False
        tr = SINGLE_SWEEP_RANGES[0] if self.single_sweep else str(int(self.scene.time_range))
        self._streak = streak_params(single_sweep=self.single_sweep, time_range=tr, gain=self.scene.reference_gain)
        self._delay = delay_params()
        self._camera = camera_params(exposure_s=self.scene.reference_exposure_s, n_x=self.scene.n_x,
                                     n_t=self.scene.n_t)
        self._mode: str | None = None          # running acquisition mode
        self._busy_until = 0.0
        self._image: np.ndarray | None = None  # (n_t, n_x) uint16, rows = time
        self._image_meta: dict = {}
        self._view_key = None
        self._view_index = -1
        self._monitor = "Off"
        self._monitor_region = None            # (x, y, dx, dy) of Average/Minimum/Maximum/Profile; None: full
        self._monitor_profile = None           # profile type 1, 2 or 3
        self._ring: dict[int, tuple[np.ndarray, float]] = {}
        self._ring_size = 10
        self._live_seq = 0
        self._live_due = 0.0
        self._epoch = time.monotonic()
        self.outbox: list[bytes] = []          # unsolicited messages for the client (code 4)
        self.frame_shifts: list[dict] = []     # time-base shift of every exposure rendered with effects on
        self.gain_log: list[tuple[float, int, str]] = []
        self._log_gain()

    def _log_gain(self) -> None:
        """Record ``(simulated time s, MCP gain, streak mode)`` in :attr:`gain_log` if either changed."""
        entry = (self.clock.now_s(), self.gain, str(self._streak["mode"].value))
        if not self.gain_log or self.gain_log[-1][1:] != entry[1:]:
            self.gain_log.append(entry)

    # ------------------------------------------------------------ settings
    @property
    def time_range(self) -> int | str:
        return normalize_time_range(self._streak["time range"].value)

    @property
    def gain(self) -> int:
        return int(float(self._streak["mcp gain"].value))

    @property
    def delaybox_s(self) -> float:
        return float(self._delay["delay a"].value)

    def exposure_for(self, location: str) -> float:
        return parse_exposure(self._camera[location]["exposure"].value)

    @property
    def exposure_s(self) -> float:
        return self.exposure_for("acquire")

    @property
    def focus(self) -> bool:
        return self._streak["mode"].value == "Focus"

    def acq_status_mode(self) -> str | None:
        """The running acquisition mode (``Live``, ``Acquire``, ...), None when idle (for tests and tools)."""
        self._poll()
        return self._mode

    def live_interval_s(self) -> float:
        """Time between two live frames: the live exposure, at least 20 ms (and the frame time)."""
        return max(self.exposure_for("live"), self.frame_time_s, 0.02)

    # ------------------------------------------------------------ dispatch
    def execute(self, name: str, args: list[str]):
        """Run one command; returns ``(reply values, data-port payload or None)``."""
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            raise Reply(2)
        self._poll()
        return handler(args)

    def _need_app(self):
        if not self.app_started:
            raise Reply(3)

    def _poll(self):
        if self._mode in ("Acquire", "AI", "PC") and time.monotonic() >= self._busy_until:
            self._mode = None

    # ------------------------------------------------------------ general, application
    def _cmd_appinfo(self, args):
        _need(args, 1)
        info = {"type": self.app_type, "version": self.app_version, "title": "streaklab RemoteEx simulator",
                "titlelong": "streaklab RemoteEx simulator (simulated streak camera)", "date": "2026-01-01",
                "directory": "C:\\simulated\\", "progdatadir": "C:\\simulated\\data\\"}
        value = info.get(args[0].lower())
        if value is None:
            raise Reply(2)
        return [value], None

    def _cmd_asynccommandstatus(self, args):
        if self._mode is not None:
            return ["1", "0", "1", "AcqStart"], None
        return ["0", "0", "0"], None

    def _cmd_stop(self, args):
        return [], None

    def _cmd_appstart(self, args):
        self.app_started = True
        return [], None

    def _cmd_append(self, args):
        self._need_app()
        self.app_started = False
        self._mode = None
        return [], None

    def _cmd_applicenceget(self, args):
        return ["1", "1", "1", "0", "1", "0"], None

    # ------------------------------------------------------------ acquisition
    def _cmd_acqstart(self, args):
        self._need_app()
        _need(args, 1)
        mode = _MODES.get(args[0].strip().lower())
        if mode is None:
            raise Reply(2)
        if self._mode is not None:
            raise Reply(7)
        self._mode = mode
        if mode in ("Live", "SingleLive"):
            self._live_due = time.monotonic() + self.live_interval_s()
            return [], None
        n = 1 if mode == "Acquire" else int(float(self._camera[mode.lower()]["nrexposures"].value))
        self._image, self._image_meta = self._render(mode, n)
        self._busy_until = time.monotonic() + self.frame_time_s * n
        return [], None

    def _cmd_acqstatus(self, args):
        self._need_app()
        return (["busy", self._mode] if self._mode is not None else ["idle"]), None

    def _cmd_acqstop(self, args):
        if args and args[0].strip():
            try:
                timeout_ms = float(args[0])
            except ValueError:
                raise Reply(1) from None
            if not 1 <= timeout_ms <= 60000:
                raise Reply(10)
        self._mode = None
        return [], None

    def _cmd_acqlivemonitor(self, args):
        self._need_app()
        _need(args, 1)
        monitor = _MONITORS.get(args[0].strip().lower())
        if monitor is None:
            raise Reply(2)
        area, profile_type = None, None
        if monitor == "RingBuffer" and len(args) > 1 and args[1].strip():
            try:
                size = int(args[1])
            except ValueError:
                raise Reply(1) from None
            if not 1 <= size <= 1000:
                raise Reply(10)
            self._ring_size = size
        elif monitor == "Profile":
            _need(args, 3)
            try:
                profile_type = int(args[1])
            except ValueError:
                raise Reply(1) from None
            if profile_type not in (1, 2, 3):
                raise Reply(10)
            area = self._monitor_area(args[2:])
        elif monitor in ("Average", "Minimum", "Maximum"):
            area = self._monitor_area(args[1:]) if len(args) > 1 else None
        self._monitor, self._monitor_region, self._monitor_profile = monitor, area, profile_type
        if monitor != "RingBuffer":
            self._ring.clear()
        return [], None

    def _monitor_area(self, args):
        """``FullArea`` (None) or ``Subarray,X,Y,DX,DY`` -> (x, y, dx, dy) inside the image."""
        kind = args[0].strip().lower() if args else ""
        if kind == "fullarea":
            return None
        if kind != "subarray":
            raise Reply(2)
        _need(args, 5)
        try:
            x, y, dx, dy = (int(a) for a in args[1:5])
        except ValueError:
            raise Reply(1) from None
        if x < 0 or y < 0 or dx < 1 or dy < 1 or x + dx > self.scene.n_x or y + dy > self.scene.n_t:
            raise Reply(10)
        return x, y, dx, dy

    def _monitor_message(self, stamp_ms: float) -> str | None:
        """The text after ``4,Livemonitor,`` for the current live frame (None: monitoring off)."""
        img = self._image
        if self._monitor_region is not None:
            x, y, dx, dy = self._monitor_region
            region = img[y:y + dy, x:x + dx]
        else:
            region = img
        if self._monitor == "Off":
            return None
        if self._monitor == "Profile":
            args = [str(self._monitor_profile)]
            if self._monitor_region is not None:
                args += [str(v) for v in self._monitor_region]
            values = self._profile(img, args)
            return "Profile," + ",".join([str(values.size)] + [f"{v:.6g}" for v in values])
        return {"Notify": "Notify", "NotifyTimeStamp": f"NotifyTimeStamp,{stamp_ms:.0f}",
                "RingBuffer": f"RingBuffer,{self._live_seq}", "Average": f"Average,{region.mean():.6g}",
                "Minimum": f"Minimum,{int(region.min())}", "Maximum": f"Maximum,{int(region.max())}"}[self._monitor]

    def tick(self) -> None:
        """Produce the live frame that is due, if any, and queue its announcement in :attr:`outbox`."""
        if self._mode not in ("Live", "SingleLive"):
            return
        now = time.monotonic()
        if now < self._live_due:
            return
        interval = self.live_interval_s()
        self._live_due = max(self._live_due + interval, now)      # never a burst of stale frames
        self._live_seq += 1
        self._image, self._image_meta = self._render("Live", 1)
        stamp_ms = (now - self._epoch) * 1e3
        if self._monitor == "RingBuffer":
            self._ring[self._live_seq] = (self._image, stamp_ms)
            for old in sorted(self._ring)[:-self._ring_size]:
                del self._ring[old]
        message = self._monitor_message(stamp_ms)
        if message is not None:
            self.outbox.append(f"4,Livemonitor,{message}\r".encode("ascii"))
        if self._mode == "SingleLive":
            self._mode = None

    def next_event_in_s(self) -> float | None:
        """Seconds until the next live frame (None if live mode is off)."""
        if self._mode not in ("Live", "SingleLive"):
            return None
        return max(0.0, self._live_due - time.monotonic())

    # ------------------------------------------------------------ camera parameters
    def _cam_param(self, args):
        loc = self._camera.get(args[0].strip().lower())
        if loc is None:
            raise Reply(2)
        param = loc.get(args[1].strip().lower())
        if param is None:
            raise Reply(2)
        return param

    def _cmd_camparamget(self, args):
        self._need_app()
        _need(args, 2)
        param = self._cam_param(args)
        if param.name == "CameraInfo":
            return ["\r\n".join((param.value, *_CAMERA_INFO))], None
        return [param.value], None

    def _cmd_camparamset(self, args):
        self._need_app()
        _need(args, 3)
        param = self._cam_param(args)
        if self._mode is not None and param.name in ("Binning", "HWidth", "VWidth", "ScanMode"):
            raise Reply(3)
        param.set(args[2])
        return [], None

    def _cmd_camparaminfo(self, args):
        self._need_app()
        _need(args, 2)
        return self._cam_param(args).info(), None

    def _cmd_camparaminfoex(self, args):
        self._need_app()
        _need(args, 2)
        return self._cam_param(args).cam_info_ex(), None

    def _cmd_camparamslist(self, args):
        self._need_app()
        _need(args, 1)
        loc = self._camera.get(args[0].strip().lower())
        if loc is None:
            raise Reply(2)
        return [len(loc), *(p.name for p in loc.values())], None

    # ------------------------------------------------------------ external devices
    def _device(self, name: str):
        dev = name.strip().lower()
        if dev in _STREAK_NAMES:
            return "streak", self._streak
        if dev in _DELAY_NAMES:
            return "delay", self._delay
        raise Reply(2)

    def _dev_param(self, args):
        _, table = self._device(args[0])
        param = table.get(args[1].strip().lower())
        if param is None:
            raise Reply(2)
        return param

    def _cmd_devparamget(self, args):
        self._need_app()
        _need(args, 2)
        which, _ = self._device(args[0])
        key = args[1].strip().lower()
        names = _DEVICE_NAMES[which]
        special = {"devicename": names[0], "pluginname": names[1], "optionname1": "", "optionname2": "",
                   "optionname3": "", "optionname4": ""}
        if key in special:
            return [special[key]], None
        param = self._dev_param(args)
        if param.name == "Delay A":
            return [format_seconds(self.delaybox_s)], None
        return [param.value], None

    def _cmd_devparamset(self, args):
        self._need_app()
        _need(args, 3)
        param = self._dev_param(args)
        raw = args[2].strip()
        if param.name == "MCP Gain":
            try:
                number = float(raw)
            except ValueError:
                raise Reply(1) from None
            if number != int(number):
                raise Reply(10)
        if param.name == "Time Range":
            try:
                raw = str(normalize_time_range(raw))
            except ValueError:
                raise Reply(10) from None
        param.set(raw)
        if param.name in ("MCP Gain", "Mode"):
            self._log_gain()
        return [], None

    def _cmd_devparaminfo(self, args):
        self._need_app()
        _need(args, 2)
        return self._dev_param(args).info(), None

    def _cmd_devparaminfoex(self, args):
        self._need_app()
        _need(args, 2)
        return self._dev_param(args).dev_info_ex(), None

    def _cmd_devparamslist(self, args):
        self._need_app()
        _need(args, 1)
        _, table = self._device(args[0])
        return [len(table), *(p.name for p in table.values())], None
