"""The whole virtual rig in one context manager: camera, scan mirror and laser sync.

::

    with SimulatedLab(seed=0) as lab:
        cam = RemoteExCamera(*lab.camera_address)                    # TCP, 127.0.0.1
        mirror = SMC100Mirror(lab.mirror_port)                       # /dev/pts/N
        dev = usb.core.find(backend=lab.usb_backend, idVendor=...)   # pyusb

All three simulators share one :class:`~drivers.sim.state.LabState`: the mirror
writes its angle, the sync unit its delay and output state, and the camera
renders what the :class:`~drivers.sim.scene.VirtualScene` looks like under them.
"""
from __future__ import annotations

import dataclasses
import importlib
import logging

import numpy as np

from .camera import RemoteExSimulator
from .scene import VirtualScene, simulated_response
from .state import LabState
from .timebase import TimeBase

__all__ = ["SimulatedLab"]

log = logging.getLogger(__name__)


class SimulatedLab:
    """Camera, mirror and laser-sync simulators on one shared state.

    Parameters
    ----------
    seed : int
        Seed of the camera noise (and of the default scene's geometry).
    scene : VirtualScene, optional
        What the camera sees; ``VirtualScene.default(seed=seed)`` if omitted.
    response : InstrumentResponse or str, optional
        The simulated camera's instrument response for the default scene (a response, or a
        name of :data:`~drivers.sim.scene.SIMULATED_RESPONSES`); a given ``scene`` keeps its own.
    camera_port : int
        RemoteEx command port; 0 (default) picks a free ephemeral pair.
    frame_time_s : float
        Simulated duration of one camera acquisition.
    mirror, sync : bool or None
        Start the mirror / laser-sync simulator: True (default) requires it,
        False leaves it out, None starts it when its module is available.
    mirror_options, sync_options : dict, optional
        Extra keyword arguments for ``MirrorSimulator`` and ``UsbtmcBackend``.
    camera_options : dict, optional
        Extra keyword arguments for ``RemoteExSimulator`` (``single_sweep``, ``scaling_table``).
    timebase : TimeBase, optional
        The camera's time-base effects (:mod:`drivers.sim.timebase`: jitter, drift, sweep
        nonlinearity, shading, fiducial, clock speed); all off by default.
    wall_clock : callable() -> float, optional
        Wall clock under the simulator's clock (``time.monotonic`` by default; tests pass their own).

    Attributes
    ----------
    state : LabState
    scene : VirtualScene
    camera : RemoteExSimulator
    mirror : MirrorSimulator or None
    sync : UsbtmcBackend or None
    """

    def __init__(self, seed: int = 0, scene: VirtualScene | None = None, *, camera_port: int = 0,
                 frame_time_s: float = 0.002, mirror: bool | None = True, sync: bool | None = True,
                 mirror_options: dict | None = None, sync_options: dict | None = None,
                 camera_options: dict | None = None, response=None, timebase: TimeBase | None = None,
                 wall_clock=None):
        self.seed = int(seed)
        if scene is not None and response is not None:
            raise ValueError("give the response to the scene (VirtualScene(response=...)) or to SimulatedLab, not both")
        if scene is None:
            scene = VirtualScene.default(seed=self.seed)
            if response is not None:
                scene = dataclasses.replace(
                    scene, response=simulated_response(response) if isinstance(response, str) else response)
        self.scene = scene
        self.state = LabState()
        self.camera = RemoteExSimulator(self.state, self.scene, seed=self.seed, port=camera_port,
                                        frame_time_s=frame_time_s, timebase=timebase, wall_clock=wall_clock,
                                        **dict(camera_options or {}))
        self._want_mirror, self._want_sync = mirror, sync
        self.unavailable: dict[str, str] = {}   # simulators left out because their module is missing
        self._mirror_options = dict(mirror_options or {})
        self._sync_options = dict(sync_options or {})
        self.mirror = None
        self.sync = None
        self._started = False

    # ------------------------------------------------------------- lifetime
    def start(self) -> "SimulatedLab":
        if self._started:
            raise RuntimeError("SimulatedLab already started")
        try:
            self.camera.start()
            mirror_cls = self._simulator_class("mirror", "MirrorSimulator", self._want_mirror)
            if mirror_cls is not None:
                self.mirror = mirror_cls(self.state, **self._mirror_options).start()
            sync_cls = self._simulator_class("usbtmc", "UsbtmcBackend", self._want_sync)
            if sync_cls is not None:
                self.sync = sync_cls(self.state, **self._sync_options)
        except BaseException:
            self.close()
            raise
        self._started = True
        return self

    def _simulator_class(self, module: str, name: str, wanted: bool | None):
        if wanted is False:
            return None
        full = f"{__package__}.{module}"
        try:
            return getattr(importlib.import_module(full), name)
        except ModuleNotFoundError as exc:
            if exc.name != full:
                raise   # the module exists but something it needs is missing: a real error
            if wanted:
                raise RuntimeError(f"SimulatedLab: {name} is not available: {exc}") from exc
            self.unavailable[module] = str(exc)
            log.warning("SimulatedLab: %s not available (%s); running without it", name, exc)
            return None

    def close(self) -> None:
        """Stop every simulator that runs (idempotent)."""
        if self.mirror is not None:
            try:
                self.mirror.close()
            except Exception:  # noqa: BLE001 - keep closing the others
                log.exception("SimulatedLab: closing the mirror simulator failed")
            self.mirror = None
        if self.sync is not None:
            closer = getattr(self.sync, "close", None)
            if closer is not None:
                try:
                    closer()
                except Exception:  # noqa: BLE001
                    log.exception("SimulatedLab: closing the sync simulator failed")
            self.sync = None
        self.camera.stop()
        self._started = False

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ addresses
    @property
    def camera_address(self) -> tuple[str, int]:
        """``(host, command_port)`` of the RemoteEx server (data port = command port + 1)."""
        return self.camera.address

    @property
    def mirror_port(self) -> str:
        """Path of the mirror controller's serial port (the pty's ``/dev/pts/N``)."""
        if self.mirror is None:
            raise RuntimeError(f"the mirror simulator is not running in this SimulatedLab "
                               f"{self.unavailable.get('mirror', '')}".rstrip())
        return self.mirror.port

    @property
    def mirror_stable_port(self) -> str:
        """A link to the mirror's current pty that survives a simulated re-plug."""
        if self.mirror is None:
            raise RuntimeError(f"the mirror simulator is not running in this SimulatedLab "
                               f"{self.unavailable.get('mirror', '')}".rstrip())
        return self.mirror.stable_port

    @property
    def usb_backend(self):
        """The pyusb backend object serving the simulated USBTMC laser-sync unit."""
        if self.sync is None:
            raise RuntimeError(f"the laser-sync simulator is not running in this SimulatedLab "
                               f"{self.unavailable.get('usbtmc', '')}".rstrip())
        return self.sync

    # ---------------------------------------------------------- ground truth
    @property
    def timebase(self) -> TimeBase:
        """The camera's time-base effects."""
        return self.camera.timebase

    def sim_time_s(self) -> float:
        """The simulator's clock: simulated seconds since the lab was made."""
        return self.camera.clock.now_s()

    def nominal_row_times_ps(self) -> np.ndarray:
        """Row times the camera reports (its scaling table, ps, zero delay), shape (n_t,)."""
        return self.scene.row_times_ps(0.0, self.camera.time_range)

    def true_row_times_ps(self) -> np.ndarray:
        """Row times the frames are rendered at (the sweep nonlinearity applied), shape (n_t,)."""
        return self.timebase.true_row_times_ps(self.nominal_row_times_ps())

    def shading_curve(self) -> np.ndarray:
        """Multiplicative sensitivity of each row, shape (n_t,)."""
        return self.timebase.sensitivity(self.scene.n_t)

    def frame_shifts_ps(self) -> np.ndarray:
        """Shift (jitter + drift, ps) applied to each exposure rendered with effects on, in order."""
        return np.array([f["shift_ps"] for f in self.camera.frame_shifts], dtype=np.float64)

    def fiducial_nominal(self) -> dict:
        """Where the fiducial pulse lies at the current time range (see :meth:`TimeBase.fiducial_nominal`)."""
        return self.timebase.fiducial_nominal(self.nominal_row_times_ps())

    def gain_log(self) -> list[tuple[float, int, str]]:
        """``(simulated time s, MCP gain, streak mode)`` at the start and at every change."""
        return list(self.camera.gain_log)

    def describe(self) -> dict:
        """Addresses of the running simulators, for printing or logging."""
        host, port = self.camera_address
        out = {"camera": f"{host}:{port}", "camera_data_port": self.camera.data_port, "seed": self.seed,
               "streak_unit": "single-sweep" if self.camera.single_sweep else "synchroscan",
               "scaling_table": self.camera.scaling_table}
        if self.mirror is not None:
            out["mirror"] = self.mirror.port
            out["mirror_stable"] = self.mirror.stable_port
        if self.sync is not None:
            out["sync"] = "pyusb backend (in-process)"
        return out
