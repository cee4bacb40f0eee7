"""Live view for alignment: the camera's live acquisition, one frame and time profile at a time.

:class:`LiveView` starts the camera's live mode with ring-buffer monitoring
(``AcqLiveMonitor(RingBuffer,N)`` and ``AcqStart(Live)``), hands every new image
with its time profile to a callback at a bounded rate, and always stops the
live acquisition on the camera (``AcqStop``, monitoring off) when it ends —
after the requested number of frames, on an error, or on Ctrl-C.  Optionally the
streak unit is put in ``Focus`` mode (sweep off) for the duration and put back
afterwards (the driver sets the MCP gain to 0 before Focus mode); the MCP gain is set to 0
when the live acquisition ends.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from drivers.errors import DriverError

__all__ = ["LiveOptions", "LiveFrame", "LiveView"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiveOptions:
    """What the live view does.

    Attributes
    ----------
    frames : int
        Frames to show, then stop; 0 runs until interrupted.
    rate_hz : float
        Most frames per second shown (the camera may deliver more; the newest wins).
    exposure_s : float
        Live exposure time, seconds.
    focus : bool
        Streak unit in ``Focus`` mode (no sweep, MCP gain 0) while live.
    gain : int or None
        MCP gain setting for a swept live view, set after the unit is put in ``Operate`` mode
        (never raised in Focus mode); None leaves the gain as it is.
    pixel : int or None
        Slit pixel whose time profile is shown; None: the mean over the slit.
    frame_timeout_s : float
        Longest wait for one live image, seconds.
    ring_buffers : int
        Images the camera keeps in its live ring buffer.
    """

    frames: int = 0
    rate_hz: float = 4.0
    exposure_s: float = 0.01
    focus: bool = False
    gain: int | None = None
    pixel: int | None = None
    frame_timeout_s: float = 5.0
    ring_buffers: int = 4

    def __post_init__(self):
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or self.frames < 0:
            raise ValueError(f"frames must be an integer >= 0 (0: until interrupted), got {self.frames!r}")
        for name in ("rate_hz", "exposure_s", "frame_timeout_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if self.gain is not None and (isinstance(self.gain, bool) or not isinstance(self.gain, int) or self.gain < 0):
            raise ValueError(f"gain must be an integer setting >= 0, got {self.gain!r}")
        if self.pixel is not None and (not isinstance(self.pixel, int) or self.pixel < 0):
            raise ValueError(f"pixel must be a slit pixel index >= 0, got {self.pixel!r}")
        if not 1 <= int(self.ring_buffers) <= 1000:
            raise ValueError(f"ring_buffers must be in 1..1000, got {self.ring_buffers!r}")


@dataclass(frozen=True)
class LiveFrame:
    """One live image as shown.

    Attributes
    ----------
    index : int
        0 for the first frame shown, then 1, 2, ...
    sequence : int
        The camera's ring-buffer sequence number.
    image : ndarray, shape (x, t), uint16
    profile : ndarray, shape (t,), float64
        Time profile: the chosen slit pixel, or the mean over the slit.
    row_times_ps : ndarray, shape (t,) or None
        Time of each row (the camera's scaling table, else the configured calibration).
    received_s : float
        ``time.monotonic()`` when the image arrived.
    """

    index: int
    sequence: int
    image: np.ndarray
    profile: np.ndarray
    row_times_ps: np.ndarray | None
    received_s: float

    @property
    def peak_row(self) -> int:
        return int(np.argmax(self.profile))


class LiveView:
    """Run the camera's live mode and show frames.

    Parameters
    ----------
    camera : RemoteExCamera
        An open camera driver (with ``start_live``, ``live_image``, ``stop_live``).
    options : LiveOptions
    row_times_ps : callable(n_rows) -> ndarray or None, optional
        Fallback row times when the camera has no scaling table (e.g. the configured polynomial).
    """

    def __init__(self, camera, options: LiveOptions, *, row_times_ps=None):
        self.camera = camera
        self.options = options
        self._fallback_times = row_times_ps
        self.frames_shown = 0
        self._mode_before: str | None = None

    def _row_times(self, n_rows: int):
        if self.options.focus:
            return None                              # no sweep, no time axis
        try:
            table = self.camera.scaling_table_ps()
        except DriverError as exc:
            log.info("live: no scaling table (%s)", exc)
            table = None
        if table is not None and table.shape == (n_rows,):
            return table
        return None if self._fallback_times is None else self._fallback_times(n_rows)

    def run(self, show, stop_event: threading.Event | None = None) -> int:
        """Show frames with ``show(frame)`` until done or ``stop_event`` is set; returns the number shown.

        The live acquisition is stopped on the camera however this ends
        (including ``KeyboardInterrupt``, which is re-raised afterwards).
        """
        stop_event = stop_event or threading.Event()
        opt = self.options
        cam = self.camera
        if opt.focus:
            self._mode_before = cam.streak_mode()
            cam.set_streak_mode("Focus")
        else:
            # swept: the sweep on before the gain is raised (a killed Focus view leaves it off)
            operate = getattr(cam, "operate", None)
            if operate is not None:
                operate()
            if opt.gain is not None:
                cam.configure(gain=opt.gain)
        try:
            cam.set_exposure_s(opt.exposure_s, "Live")
            cam.start_live(ring_buffers=opt.ring_buffers)
            period_s = 1.0 / opt.rate_hz
            times = None
            next_at = time.monotonic()
            while (opt.frames == 0 or self.frames_shown < opt.frames) and not stop_event.is_set():
                image, seq = cam.live_image(timeout_s=opt.frame_timeout_s)
                received = time.monotonic()
                if opt.pixel is not None and opt.pixel >= image.shape[0]:
                    raise ValueError(f"pixel {opt.pixel} is outside the slit (0..{image.shape[0] - 1})")
                if times is None:
                    times = self._row_times(image.shape[1])
                profile = (image[opt.pixel].astype(np.float64) if opt.pixel is not None
                           else image.mean(axis=0, dtype=np.float64))
                show(LiveFrame(self.frames_shown, seq, image, profile, times, received))
                self.frames_shown += 1
                next_at += period_s
                wait = next_at - time.monotonic()
                if wait > 0 and (opt.frames == 0 or self.frames_shown < opt.frames):
                    stop_event.wait(wait)             # holds the rate; a stop request ends the wait
                else:
                    next_at = time.monotonic()
        finally:
            self._stop()
        return self.frames_shown

    def _stop(self) -> None:
        try:
            self.camera.stop_live()
        except DriverError as exc:
            log.warning("live: stopping the live acquisition failed: %s", exc)
        off = getattr(self.camera, "gain_off", None)
        if off is not None:
            try:
                off()                                 # the gain interlock: 0 once the acquisition ends
            except DriverError as exc:
                log.warning("live: could not set the MCP gain to 0: %s", exc)
        if self._mode_before is not None:
            try:
                self.camera.set_streak_mode(self._mode_before)
            except (DriverError, ValueError) as exc:
                log.warning("live: could not put the streak unit back in %s mode: %s", self._mode_before, exc)
