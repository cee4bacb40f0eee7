"""``streaklab live --config SCAN.toml``: the streak camera's live image and a time profile, for alignment.

Uses the camera's live acquisition (``AcqStart(Live)`` with ring-buffer
monitoring) at the configured time range, gain and exposure, and shows a few
frames per second:

* a window (matplotlib) when a display is available, unless ``--no-window``;
* ``--png PATH``: the same figure written to PATH after every frame (replaced
  atomically, so a viewer never reads half a file);
* ``--npz PATH``: the last frame's image, profile and row times;
* always one status line per frame on stdout.

Ctrl-C (or SIGTERM) stops the live acquisition on the camera (``AcqStop``,
monitoring off; ``--focus`` puts the streak unit back in its previous mode)
and exits with status 130, without a traceback.  ``--simulate`` serves the
simulated camera in this process (laser on, mirror at 0 deg); otherwise the
camera at ``devices.camera`` is used (for example a ``streaklab sim-lab``).

``--laser-on`` also opens the laser-sync unit of ``[devices]`` (the simulated
one with ``--simulate``), sets the configured repetition rate and trigger
delay and switches its output on while live; it is switched off again at the
end (a capture session leaves it off).
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("--config", required=True, help="scan configuration (TOML): camera address and settings")
    parser.add_argument("--simulate", action="store_true", help="serve the simulated camera in this process")
    parser.add_argument("--frames", type=int, default=0, help="frames to show, then stop (default 0: until Ctrl-C)")
    parser.add_argument("--fps", type=float, default=4.0, help="most frames shown per second (default 4)")
    parser.add_argument("--exposure-s", type=float, help="live exposure, seconds (default: camera.exposure_s)")
    parser.add_argument("--focus", action="store_true", help="streak unit in Focus mode (sweep off) while live")
    parser.add_argument("--pixel", type=int, help="slit pixel whose time profile is shown (default: slit mean)")
    parser.add_argument("--png", metavar="PATH", help="write the figure to PATH after every frame")
    parser.add_argument("--npz", metavar="PATH", help="write the last frame (image, profile, row times) to PATH")
    parser.add_argument("--no-window", action="store_true", help="no window even if a display is available")
    parser.add_argument("--laser-on", action="store_true",
                        help="switch the laser-sync output on while live (rate and delay from [sync]), off after")


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("darwin", "win32")


class _Figure:
    """The image and the profile, drawn with matplotlib (on screen or into a PNG)."""

    def __init__(self, *, window: bool, png: str | None):
        import matplotlib

        if not window:
            matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt

        if window and matplotlib.get_backend().lower() in ("agg", "pdf", "ps", "svg", "cairo", "template"):
            raise RuntimeError(f"matplotlib has no interactive backend here ({matplotlib.get_backend()})")
        self.plt, self.window, self.png = plt, window, png
        self.fig, (self.ax_img, self.ax_prof) = plt.subplots(1, 2, figsize=(10, 4))
        self.im = self.line = None
        if window:
            plt.ion()
            plt.show(block=False)

    def show(self, frame) -> None:
        img = frame.image.T                                   # rows = time (vertical), columns = slit
        t = frame.row_times_ps if frame.row_times_ps is not None else range(frame.profile.size)
        # the title first: the layout below leaves room for it (set after, its top was cut off)
        self.ax_img.set_title(f"live frame {frame.index} (camera #{frame.sequence})")
        if self.im is None:
            self.im = self.ax_img.imshow(img, aspect="auto", origin="upper", cmap="magma")
            self.ax_img.set_xlabel("slit pixel x")
            self.ax_img.set_ylabel("streak row (time)")
            self.fig.colorbar(self.im, ax=self.ax_img, label="counts")
            (self.line,) = self.ax_prof.plot(t, frame.profile)
            self.ax_prof.set_xlabel("t (ps)" if frame.row_times_ps is not None else "streak row")
            self.ax_prof.set_ylabel("time profile (counts)")
            self.fig.tight_layout()
        else:
            self.im.set_data(img)
            self.line.set_data(t, frame.profile)
        self.im.set_clim(float(img.min()), float(max(img.max(), img.min() + 1)))
        self.ax_prof.relim()
        self.ax_prof.autoscale_view()
        if self.png:
            tmp = f"{self.png}.tmp.png"
            self.fig.savefig(tmp, dpi=80)
            os.replace(tmp, self.png)
        if self.window:
            self.fig.canvas.draw_idle()
            self.plt.pause(0.001)

    def close(self) -> None:
        self.plt.close(self.fig)


@contextlib.contextmanager
def _laser(config, lab):
    """The laser-sync unit with its output on (rate and delay from ``[sync]``); off again on leaving."""
    from acquisition.rig import _open_sync
    from acquisition.session import CaptureError
    from drivers.errors import DriverError

    try:
        sync = _open_sync(config, backend=lab.usb_backend if lab is not None else None)
    except (CaptureError, DriverError, OSError) as exc:
        raise CommandError(f"cannot open the laser sync: {exc}") from None
    with sync:
        try:
            sync.set_repetition_rate(config["sync"]["repetition_rate_hz"])
            sync.set_trigger_delay(config["sync"]["trigger_delay_ps"], channel=config["sync"]["channel"])
            sync.set_output(True)
        except DriverError as exc:
            raise CommandError(f"laser sync: {type(exc).__name__}: {exc}") from None
        try:
            yield sync
        finally:
            try:
                sync.set_output(False)
            except DriverError as exc:
                print(f"streaklab live: warning: could not switch the laser-sync output off: {exc}", file=sys.stderr)


def run(args) -> int:
    import numpy as np

    from acquisition.config import ConfigError, calibration_times_ps, load_config
    from acquisition.live import LiveOptions, LiveView
    from core.staging import check_output_location
    from drivers.errors import DriverError

    try:
        config = load_config(args.config)
        cam_cfg = config["camera"]
        options = LiveOptions(frames=args.frames, rate_hz=args.fps, focus=args.focus, pixel=args.pixel,
                              gain=cam_cfg.get("gain"),
                              exposure_s=args.exposure_s if args.exposure_s is not None else cam_cfg["exposure_s"],
                              frame_timeout_s=max(5.0, 3 * config["devices"]["timeout_s"]))
    except (ConfigError, ValueError) as exc:
        raise CommandError(str(exc)) from None
    for path in (args.png, args.npz):
        if path and not Path(path).resolve().parent.is_dir():
            raise CommandError(f"{path}: its directory does not exist")
        if path:
            check_output_location(path)

    poly = config["calibration"].get("time_poly_ps")
    fallback = (lambda n: calibration_times_ps(poly, n) + config["sync"]["trigger_delay_ps"]) if poly else None
    window = _has_display() and not args.no_window
    figure = None
    if window:
        try:
            figure = _Figure(window=True, png=args.png)
        except Exception as exc:  # noqa: BLE001 - any backend failure: carry on without a window
            print(f"streaklab live: no window ({type(exc).__name__}: {exc}); status lines"
                  f"{' and --png' if args.png else ''} only", file=sys.stderr)
    if figure is None and args.png:
        figure = _Figure(window=False, png=args.png)
    stop = threading.Event()
    interrupted = []

    def on_signal(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        interrupted.append(signum)
        stop.set()

    def show(frame):
        t = frame.row_times_ps
        where = f"row {frame.peak_row}" + (f" (t = {t[frame.peak_row]:.1f} ps)" if t is not None else "")
        print(f"live frame {frame.index} (camera #{frame.sequence}): image {frame.image.shape[0]}x"
              f"{frame.image.shape[1]}, max {int(frame.image.max())} counts, profile peak "
              f"{frame.profile.max():.1f} at {where}", flush=True)
        if figure is not None:
            figure.show(frame)
        if args.npz:
            tmp = f"{args.npz}.tmp.npz"
            np.savez(tmp, image=frame.image, profile=frame.profile, sequence=frame.sequence,
                     row_times_ps=t if t is not None else np.array([]))
            os.replace(tmp, args.npz)

    lab = None
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        from drivers.remoteex import RemoteExCamera

        if args.simulate:
            from acquisition.rig import simulated_scene, simulated_timebase
            from drivers.sim import SimulatedLab

            lab = SimulatedLab(seed=config["simulation"]["seed"], scene=simulated_scene(config), mirror=False,
                               sync=args.laser_on,
                               camera_options={"single_sweep": isinstance(cam_cfg["time_range"], str)},
                               timebase=simulated_timebase(config))
            lab.start()
            if not args.laser_on:
                lab.state.sync_output_enabled = True      # no sync unit to switch: the laser simply runs
            host, port = lab.camera_address
        else:
            host, _, p = config["devices"]["camera"].rpartition(":")
            port = int(p)
        timeout_s = config["devices"]["timeout_s"]
        with contextlib.ExitStack() as stack:
            if args.laser_on:
                stack.enter_context(_laser(config, lab))
            try:
                with RemoteExCamera(host, port, timeout_s=timeout_s, connect_timeout_s=timeout_s) as cam:
                    cam.configure(time_range=cam_cfg["time_range"])    # the gain: LiveView, by mode
                    shown = LiveView(cam, options, row_times_ps=fallback).run(show, stop)
            except DriverError as exc:
                raise CommandError(f"camera at {host}:{port}: {type(exc).__name__}: {exc}") from None
            except ValueError as exc:
                raise CommandError(str(exc)) from None
    except KeyboardInterrupt:
        print("\nstreaklab live: aborted", file=sys.stderr)
        return 130
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if figure is not None:
            figure.close()
        if lab is not None:
            lab.close()
    if interrupted:
        print(f"\nstreaklab live: stopped after {shown} frames; live acquisition stopped on the camera",
              file=sys.stderr)
        return 130
    print(f"streaklab live: {shown} frames shown", file=sys.stderr)
    return 0
