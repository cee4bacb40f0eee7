"""Frames and image transfers of the simulated RemoteEx server.

:class:`RemoteExImages` (a base of :class:`~drivers.sim.remoteex_commands.RemoteExCommands`)
renders the frame of an acquisition from the shared lab state and answers the
image commands of the RemoteEx handbook ("Image commands"):
``ImgDataGet(current, Data|Display|Profile,type[,x,y,dx,dy]|ScalingTable,Vertical)``
and ``ImgRingBufferGet(Data,seq)``.  Frame noise is seeded per frame (see
:func:`frame_seed`), so the same seed and the same commands give the same bytes.
"""
from __future__ import annotations

import numpy as np

from drivers.remoteex_wire import format_exposure, scaling_table_unit_ps

from .remoteex_params import Reply, need as _need
from .timebase import FIDUCIAL_PIXELS

__all__ = ["RemoteExImages", "frame_seed"]

_MODE_LOCATION = {"Live": "live", "SingleLive": "live", "Acquire": "acquire", "AI": "ai", "PC": "pc"}


def _zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def frame_seed(seed: int, angle_deg: float, delay_ps: float, output: bool, index: int) -> np.random.SeedSequence:
    """Seed sequence of one frame's noise (angle quantised to 1e-6 deg, delay to 1e-3 ps)."""
    return np.random.SeedSequence([_zigzag(int(seed)), _zigzag(int(round(angle_deg * 1e6))),
                                   _zigzag(int(round(delay_ps * 1e3))), int(bool(output)), int(index)])


class RemoteExImages:
    """Frame rendering and the image commands (state lives in the command table)."""

    # ------------------------------------------------------------ images
    def _current_image(self) -> np.ndarray:
        if self._mode in ("Acquire", "AI", "PC"):
            raise Reply(3)
        if self._image is None:
            raise Reply(7)
        return self._image

    def _cmd_imgdataget(self, args):
        self._need_app()
        _need(args, 2)
        dest, kind = args[0].strip().lower(), args[1].strip().lower()
        if dest != "current":
            if dest.isdigit() and int(dest) <= 19:
                raise Reply(7)                     # only the current image exists here
            raise Reply(2)
        img = self._current_image()
        if kind == "data":
            return [img.shape[1], img.shape[0], 2, "Data"], img.astype("<u2").tobytes()
        if kind == "display":
            lo, hi = float(img.min()), float(img.max())
            disp = np.zeros(img.shape, np.uint8) if hi <= lo else \
                np.rint((img - lo) * (255.0 / (hi - lo))).astype(np.uint8)
            return [img.shape[1], img.shape[0], 1, "Display"], disp.tobytes()
        if kind == "profile":
            profile = self._profile(img, args[2:])
            return [profile.size, "Profile"], profile.astype("<f4").tobytes()
        if kind == "scalingtable":
            _need(args, 3)
            direction = args[2].strip().lower()
            if direction in ("h", "hor", "horizontal", "x"):
                raise Reply(7)                     # no spectrograph: no horizontal table scaling
            if direction not in ("v", "ver", "vertical", "y"):
                raise Reply(2)
            if not self.scaling_table or self.focus:
                raise Reply(7)
            table = self._scaling_table()
            return [table.size, "ScalingTable"], table.astype("<f4").tobytes()
        raise Reply(2)

    def _scaling_table(self) -> np.ndarray:
        """Row times of the sweep (no delay) in the time range's unit (ps for a synchroscan setting)."""
        unit_ps = scaling_table_unit_ps(self.time_range) or 1.0
        return self.scene.row_times_ps(0.0, self.time_range) / unit_ps

    @staticmethod
    def _profile(img: np.ndarray, args) -> np.ndarray:
        _need(args, 1)
        try:
            kind = int(args[0])
            x, y, dx, dy = (int(a) for a in args[1:5]) if len(args) >= 5 else (0, 0, img.shape[1], img.shape[0])
        except ValueError:
            raise Reply(1) from None
        if kind not in (1, 2, 3):
            raise Reply(10)
        if x < 0 or y < 0 or dx < 1 or dy < 1 or x + dx > img.shape[1] or y + dy > img.shape[0]:
            raise Reply(10)
        area = img[y:y + dy, x:x + dx].astype(np.float64)
        if kind == 1:
            return area[0]
        return area.sum(axis=0) if kind == 2 else area.sum(axis=1)

    def _cmd_imgringbufferget(self, args):
        self._need_app()
        _need(args, 2)
        if args[0].strip().lower() != "data":
            raise Reply(2)
        if len(args) > 2 and args[2].strip():
            raise Reply(7)                         # writing to a file is not simulated
        try:
            seq = int(args[1])
        except ValueError:
            raise Reply(1) from None
        if not self._ring or seq > max(self._ring):
            raise Reply(7)
        seq = max(seq, min(self._ring))
        img, stamp_ms = self._ring[seq]
        return [img.shape[1], img.shape[0], 2, "Data", seq, f"{stamp_ms:.0f}"], img.astype("<u2").tobytes()

    # ------------------------------------------------------------ frames
    def _render(self, mode: str, n: int):
        """Render the frame of one acquisition (``n`` exposures summed for AI and PC); (n_t, n_x) uint16."""
        with self.state.lock:
            angle = float(self.state.mirror_angle_deg)
            light = bool(self.state.sync_output_enabled)
            sync_delay_ps = float(self.state.sync_delay_ps)
        delay_ps = sync_delay_ps + self.delaybox_s * 1e12
        exposure_s = self.exposure_for(_MODE_LOCATION[mode])
        tr, focus = self.time_range, self.focus
        key = (round(angle, 6), round(delay_ps, 3), light, exposure_s, self.gain, tr, focus)
        if key == self._view_key:
            self._view_index += 1
        else:
            self._view_key, self._view_index = key, 0
        seed_seq = frame_seed(self.seed, angle, delay_ps, light, self._view_index)
        rng = np.random.default_rng(seed_seq)
        line = self.scene.line_index(angle)
        total = None
        effects = self.timebase.active and not focus          # no sweep in focus mode: no time-base effects
        first_shift = len(self.frame_shifts)
        for _ in range(n):
            mean = self._timebase_mean(line, delay_ps, exposure_s, tr) if effects and light else None
            frame = self.scene.render_frame(line, rng, delay_ps=delay_ps, exposure_s=exposure_s, gain=self.gain,
                                            time_range=tr, light=light, focus=focus, dark=mode != "PC",
                                            signal_mean=mean)
            total = frame.astype(np.float64) if total is None else total + frame
        self.frames_rendered += 1
        if light:
            # the sync unit sees the trigger of this frame: the channel's delay less the frame's shift
            # (the mean over its exposures); its measurement noise is seeded like the frame's noise
            shifts = [f["shift_ps"] for f in self.frame_shifts[first_shift:]]
            shift = float(np.mean(shifts)) if shifts else 0.0
            with self.state.lock:
                self.state.triggers.append((sync_delay_ps - shift, tuple(int(e) for e in seed_seq.entropy)))
        frame = np.clip(total, 0, np.iinfo(np.uint16).max).astype(np.uint16)
        meta = {"line": line, "angle_deg": angle, "delay_ps": delay_ps, "light": light, "index": self._view_index,
                "mode": mode, "exposures": n, "focus": focus, "time_range": tr,
                "exposure": format_exposure(exposure_s)}
        return np.ascontiguousarray(frame.T), meta     # (n_t, n_x): image rows are the sweep direction

    def _timebase_mean(self, line: int, delay_ps: float, exposure_s: float, tr) -> np.ndarray:
        """Mean photo-counts (n_x, n_t) of one exposure under the time base's effects; records its shift.

        See :mod:`drivers.sim.timebase` for the curves.  Each exposure draws its own jitter.
        """
        tb = self.timebase
        nominal = self.scene.row_times_ps(0.0, tr)
        true = tb.true_row_times_ps(nominal)
        sim_time_s = self.clock.now_s()
        jitter = tb.jitter_draw_ps(self.seed, len(self.frame_shifts))
        drift = tb.drift_ps(sim_time_s)
        shift = jitter + drift
        self.frame_shifts.append({"sim_time_s": sim_time_s, "jitter_ps": jitter, "drift_ps": drift,
                                  "shift_ps": shift})
        clean = self.scene.clean_line_at(line, true + float(delay_ps) - shift)       # (n_x, n_t)
        if tb.fiducial:
            clean = clean.copy()
            clean[:FIDUCIAL_PIXELS] = tb.fiducial_profile(nominal, true, shift)[None, :]   # its own slit pixels
        return self.scene.signal_scale(exposure_s, self.gain) * clean * tb.sensitivity(nominal.size)[None, :]

    @property
    def last_frame_info(self) -> dict:
        """Line, angle, delay, light, noise index and mode of the most recent frame."""
        return dict(self._image_meta)
