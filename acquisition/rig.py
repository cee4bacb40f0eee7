"""Connecting the session to a rig: the real drivers at the configured addresses, or a simulated lab.

:func:`run_capture` is what ``streaklab capture`` calls: it opens the three drivers
(each a context manager that leaves its device safe), runs a
:class:`~acquisition.session.CaptureSession` over them, and closes them whatever
happened.  With ``simulate=True`` a :class:`drivers.sim.SimulatedLab` is started in
this process and the same real drivers talk to it over its socket, pty and pyusb
backend.
"""
from __future__ import annotations

import contextlib
import logging
import threading

import numpy as np

from drivers.errors import DriverError

from .config import SIMULATION_TIMEBASE_KEYS, ScanConfig, calibration_times_ps, simulated_example_address
from .session import CaptureError, CaptureSession, SessionResult

__all__ = ["simulated_scene", "simulated_timebase", "start_simulated_lab", "open_rig", "run_capture"]

log = logging.getLogger(__name__)


def simulated_scene(config: ScanConfig):
    """The virtual scene for ``--simulate``: one scene line per scan line, at the scan's angles.

    Uses ``VirtualScene.default`` (``VirtualScene.calibration`` with
    ``simulation.scene = "calibration"``, ``VirtualScene.etalon`` with ``"etalon"`` and
    ``simulation.etalon_ps``, ``VirtualScene.uniform`` with ``"uniform"``) with ``simulation.n_x`` slit pixels,
    ``simulation.n_t`` streak rows, ``simulation.seed`` and the instrument response named by
    ``simulation.response``; its line angles are the config's, sorted.
    """
    from drivers.sim.scene import VirtualScene, simulated_response

    sim = config["simulation"]
    response = simulated_response(sim.get("response", "gaussian"))
    if sim.get("scene", "default") == "calibration":
        base = VirtualScene.calibration(n_lines=config.n_lines, n_x=sim["n_x"], n_t=sim["n_t"], seed=sim["seed"],
                                        response=response)
    elif sim.get("scene") == "etalon":
        base = VirtualScene.etalon(n_lines=config.n_lines, n_x=sim["n_x"], n_t=sim["n_t"], seed=sim["seed"],
                                   etalon_ps=sim.get("etalon_ps", 20.0), response=response)
    elif sim.get("scene") == "uniform":
        base = VirtualScene.uniform(n_lines=config.n_lines, n_x=sim["n_x"], n_t=sim["n_t"], seed=sim["seed"])
    else:
        base = VirtualScene.default(n_lines=config.n_lines, n_x=sim["n_x"], n_t=sim["n_t"], seed=sim["seed"])
    return VirtualScene(params=base.params, angle_deg=np.sort(config.angles_deg), n_t=base.n_t,
                        time_calibration=base.time_calibration, photon_scale=base.photon_scale,
                        dark_level=base.dark_level, read_noise=base.read_noise,
                        reference_exposure_s=base.reference_exposure_s, reference_gain=base.reference_gain,
                        time_range=base.time_range, response=response)


def simulated_timebase(config: ScanConfig):
    """The simulated camera's time base from ``[simulation]`` (every effect off where not named)."""
    from drivers.sim.timebase import TimeBase

    sim = config["simulation"]
    return TimeBase(**{k: sim[k] for k in SIMULATION_TIMEBASE_KEYS if k in sim})


def start_simulated_lab(config: ScanConfig, *, wall_clock=None):
    """Start (enter) a SimulatedLab matching the config; the caller closes it.

    ``wall_clock`` (callable() -> float, seconds) drives the simulator's clock, the one the
    time base's drift follows (``time.monotonic`` by default; a benchmark passes its own to
    make the simulated time of every exposure exact).
    """
    from drivers.sim import SimulatedLab

    scene = simulated_scene(config)
    tr = config["camera"]["time_range"]
    # A time such as "1 ns" is a single-sweep unit's time range; a number a synchroscan unit's.
    sync_options = {k: config["simulation"][k] for k in ("reference_noise_ps",) if k in config["simulation"]}
    lab = SimulatedLab(seed=config["simulation"]["seed"], scene=scene, mirror=True, sync=True,
                       camera_options={"single_sweep": isinstance(tr, str)}, timebase=simulated_timebase(config),
                       wall_clock=wall_clock, sync_options=sync_options)
    lab.start()
    # The simulated sweep is what the scene says; warn if the config's calibration describes another.
    from drivers.sim.scene import TIME_RANGE_SCALE, time_range_scale

    try:
        truth = scene.row_times_ps(0.0, tr)
    except ValueError:
        truth = None                            # a setting the simulated unit refuses: the session says so
    if truth is not None and "time_poly_ps" in config["calibration"]:
        mine = calibration_times_ps(config["calibration"]["time_poly_ps"], scene.n_t)
        if np.max(np.abs(truth - mine)) > 1.0:
            log.warning("calibration.time_poly_ps differs from the simulated sweep by up to %.3g ps "
                        "(simulated: %s at time_range %s)", float(np.max(np.abs(truth - mine))),
                        list(np.round(scene.time_calibration * time_range_scale(tr)
                                      / TIME_RANGE_SCALE[scene.time_range], 9)), tr)
    return lab


def _open_sync(config: ScanConfig, *, backend=None):
    """The SCPI laser sync on USBTMC: found by the configured USB ids / serial, or the simulated unit."""
    from drivers.scpi_sync import ScpiLaserSync

    dev = config["devices"]
    kwargs = {"timeout_s": dev["timeout_s"], "camera_channel": config["sync"]["channel"]}
    if backend is not None:
        # The simulated unit, whatever ids [devices] gives for the real one.
        kwargs.update(backend=backend, vendor_id=backend.vendor_id, product_id=backend.product_id)
    else:
        if not any(k in dev for k in ("sync_vendor_id", "sync_serial")):
            raise CaptureError("devices.sync_vendor_id/sync_product_id or devices.sync_serial: required to find "
                               "the laser-sync unit on USB")
        for key, arg in (("sync_vendor_id", "vendor_id"), ("sync_product_id", "product_id"),
                         ("sync_serial", "serial_number")):
            if key in dev:
                kwargs[arg] = dev[key]
    return ScpiLaserSync(**kwargs)


@contextlib.contextmanager
def open_rig(config: ScanConfig, *, lab=None):
    """Open camera, mirror and laser sync; yields ``(camera, mirror, sync)``.

    Parameters
    ----------
    lab : SimulatedLab, optional
        Take the addresses from this running simulated lab instead of ``[devices]``.
    """
    from drivers.remoteex import RemoteExCamera
    from drivers.smc100 import SMC100Mirror

    dev = config["devices"]
    timeout_s = dev["timeout_s"]
    if lab is not None:
        cam_host, cam_port = lab.camera_address
        # the stable link, as a udev by-id link on the rig: a re-plugged port is found again
        mirror_port, backend = lab.mirror_stable_port, lab.usb_backend
    else:
        cam_host, _, port = dev["camera"].rpartition(":")
        cam_port, mirror_port, backend = int(port), dev["mirror"], None
    with contextlib.ExitStack() as stack:
        def enter(name, where, make, device):
            try:
                return stack.enter_context(make())
            except (DriverError, OSError) as exc:
                hint = ""
                if lab is None and simulated_example_address(config, device):
                    hint = ("; that is the example configuration's placeholder address, not a rig's: add "
                            "--simulate to capture from a simulated lab started in this process, or set "
                            "[devices] to your rig's addresses")
                raise CaptureError(f"cannot open the {name} at {where}: {exc}{hint}") from None

        camera = enter("camera", f"{cam_host}:{cam_port}",
                       lambda: RemoteExCamera(cam_host, cam_port, timeout_s=timeout_s, connect_timeout_s=timeout_s),
                       "camera")
        mirror = enter("mirror", mirror_port,
                       lambda: SMC100Mirror(mirror_port, address=dev["mirror_address"], timeout_s=timeout_s,
                                            xonxoff=dev["mirror_xonxoff"]), "mirror")
        sync_where = "the simulated USB backend" if backend is not None else \
            ", ".join(f"{k}={dev[k]!r}" for k in ("sync_vendor_id", "sync_product_id", "sync_serial") if k in dev) \
            or "USB (no id configured)"
        sync = enter("laser sync", sync_where, lambda: _open_sync(config, backend=backend), "sync")
        yield camera, mirror, sync


def run_capture(config: ScanConfig, out, *, simulate: bool = False, resume: bool = False, lab=None,
                stop_event: threading.Event | None = None, on_line=None, on_start=None,
                session_info: dict | None = None, line_good_enough=None) -> SessionResult:
    """Run one capture session end to end (open rig, session, close rig).

    Parameters
    ----------
    config : ScanConfig
    out : run store path.
    simulate : bool
        Start a SimulatedLab for this session (ignored when ``lab`` is given).
    lab : SimulatedLab, optional
        An already running simulated lab to capture from (tests, fault injection).
    stop_event, on_line, on_start, session_info, line_good_enough : see :class:`CaptureSession`.
    """
    info = {"simulated": bool(simulate or lab is not None), **(session_info or {})}
    with contextlib.ExitStack() as stack:
        if lab is None and simulate:
            lab = start_simulated_lab(config)
            stack.callback(lab.close)
        if lab is not None and config["simulation"].get("fiducial"):
            on_start = _recording_fiducial(lab, on_start)
        with open_rig(config, lab=lab) as (camera, mirror, sync):
            session = CaptureSession(config, out, camera, mirror, sync, resume=resume, stop_event=stop_event,
                                     on_line=on_line, on_start=on_start, session_info=info,
                                     line_good_enough=line_good_enough)
            return session.run()


def _recording_fiducial(lab, on_start):
    """``on_start`` that first records where the simulated fiducial pulse lies in the run store.

    The store's ``fiducial`` attribute, which ``streaklab reconstruct`` aligns every frame on:
    the band of rows and slit pixels to search and the pulse's nominal time (see
    :meth:`drivers.sim.timebase.TimeBase.fiducial_nominal`).
    """
    def start(session):
        session.store.group.attrs["fiducial"] = lab.fiducial_nominal()
        if on_start is not None:
            on_start(session)
    return start
