"""The simulated streak camera's time base: trigger jitter, drift, sweep nonlinearity, shading, fiducial.

A real camera's time base moves under the capture: the trigger jitters from frame to
frame, drifts over minutes, the sweep is not quite the calibrated one and the
sensitivity varies along the time axis.  :class:`TimeBase` describes these effects of
the simulated camera (every one off by default: frames are then those of a perfect time
base, bit for bit), and :class:`SimClock` the simulator's own clock that the drift
follows.

Conventions (``n_t`` streak rows, ``u = r / (n_t - 1)`` for row ``r``, ``span_ps`` the
nominal window: last minus first nominal row time at the current time range, zero delay):

* **nominal row times** ``t_nom(r)``: the scene's calibrated sweep, what the camera's
  scaling table reports (the table does not know about the effects below);
* **sweep nonlinearity** ``n``: the true row times are
  ``t_true(r) = t_nom(r) + n * span_ps * 4 u (1 - u)``, a quadratic bow that is 0 at the
  first and last rows and ``n * span_ps`` at the middle row (``|n| < 0.25`` keeps the
  sweep increasing);
* **shift** of frame ``k``: ``s_k = jitter_k + drift(t_k)`` ps, with ``jitter_k`` drawn from
  ``Normal(0, jitter_ps)`` (seeded by the lab's seed and the frame number) and
  ``drift(t) = drift_ps_per_min * t / 60`` at the simulated time ``t`` (s) of the frame.
  A positive shift makes the light arrive later in the window: row ``r`` sees scene time
  ``t_true(r) + delay_ps - s_k``;
* **shading** ``h``: the signal (not the dark level) of row ``r`` is multiplied by the
  sensitivity ``1 + h * (2 u - 1)`` (a linear ramp from ``1 - h`` at the first row to
  ``1 + h`` at the last; ``0 <= h < 1``);
* **fiducial**: a Gaussian pulse (sigma :data:`FIDUCIAL_SIGMA_PS`, peak
  :data:`FIDUCIAL_AMPLITUDE` in profile-amplitude units) alone on slit pixels
  ``0 .. FIDUCIAL_PIXELS - 1`` (a reference fibre on the slit's edge: the scene's light does not
  reach them) at window time ``FIDUCIAL_FRACTION * span_ps`` after the first
  nominal row time, whatever the delay setting, plus the frame's shift ``s_k``; like the scene
  it is seen at the true row times and shaded.  Its nominal position is
  :meth:`TimeBase.fiducial_nominal` (recorded in a run store's ``fiducial``
  attribute by a simulated capture, where ``streaklab reconstruct`` aligns every frame on it).

Focus mode has no sweep: none of these effects apply there.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["TimeBase", "SimClock", "FIDUCIAL_PIXELS", "FIDUCIAL_FRACTION", "FIDUCIAL_SIGMA_PS",
           "FIDUCIAL_AMPLITUDE", "MAX_SWEEP_NONLINEARITY"]

# The fiducial pulse: slit pixels 0 .. FIDUCIAL_PIXELS - 1, at this fraction of the window.
FIDUCIAL_PIXELS = 2
FIDUCIAL_FRACTION = 0.06
FIDUCIAL_SIGMA_PS = 4.0
FIDUCIAL_AMPLITUDE = 1.0
# A bow of a quarter of the window would make the sweep stand still at the first row.
MAX_SWEEP_NONLINEARITY = 0.25
# Stream of the jitter draws, apart from the frames' noise streams.
_JITTER_STREAM = 0x6A177E


@dataclass(frozen=True)
class TimeBase:
    """What the simulated camera's time base does (see the module docstring for the curves).

    Attributes
    ----------
    jitter_ps : float
        RMS of the Gaussian trigger jitter of each exposure, ps (>= 0).
    drift_ps_per_min : float
        Slow drift of the trigger, ps per simulated minute (any sign).
    sweep_nonlinearity : float
        Largest deviation of the true row times from the nominal ones, as a fraction of the
        window (|n| < 0.25).
    shading : float
        Sensitivity ramp along the time axis: ``1 + shading * (2 u - 1)`` (0 <= shading < 1).
    clock_speed : float
        Simulated seconds per wall-clock second (> 0).
    fiducial : bool
        Put the fiducial pulse in every frame.
    """

    jitter_ps: float = 0.0
    drift_ps_per_min: float = 0.0
    sweep_nonlinearity: float = 0.0
    shading: float = 0.0
    clock_speed: float = 1.0
    fiducial: bool = False

    def __post_init__(self):
        for name in ("jitter_ps", "drift_ps_per_min", "sweep_nonlinearity", "shading", "clock_speed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.jitter_ps < 0:
            raise ValueError(f"jitter_ps must be >= 0, got {self.jitter_ps!r}")
        if not abs(self.sweep_nonlinearity) < MAX_SWEEP_NONLINEARITY:
            raise ValueError(f"sweep_nonlinearity must be in (-{MAX_SWEEP_NONLINEARITY}, "
                             f"{MAX_SWEEP_NONLINEARITY}) (the sweep must keep increasing), "
                             f"got {self.sweep_nonlinearity!r}")
        if not 0 <= self.shading < 1:
            raise ValueError(f"shading must be in [0, 1), got {self.shading!r}")
        if not self.clock_speed > 0:
            raise ValueError(f"clock_speed must be > 0, got {self.clock_speed!r}")
        if not isinstance(self.fiducial, bool):
            raise ValueError(f"fiducial must be true or false, got {self.fiducial!r}")

    @property
    def active(self) -> bool:
        """True when any effect changes the frames (the clock speed alone does not)."""
        return bool(self.jitter_ps or self.drift_ps_per_min or self.sweep_nonlinearity or self.shading
                    or self.fiducial)

    def as_dict(self) -> dict:
        return asdict(self)

    # ------------------------------------------------------------ curves
    @staticmethod
    def _u(n_t: int) -> np.ndarray:
        return np.arange(n_t, dtype=np.float64) / (n_t - 1)

    def true_row_times_ps(self, nominal_ps: np.ndarray) -> np.ndarray:
        """The rows' true times, shape (n_t,), ps: ``nominal + n * span * 4 u (1 - u)``."""
        nominal_ps = np.asarray(nominal_ps, dtype=np.float64)
        if not self.sweep_nonlinearity:
            return nominal_ps.copy()
        u = self._u(nominal_ps.size)
        span_ps = float(nominal_ps[-1] - nominal_ps[0])
        return nominal_ps + self.sweep_nonlinearity * span_ps * 4.0 * u * (1.0 - u)

    def sensitivity(self, n_t: int) -> np.ndarray:
        """Multiplicative sensitivity of each row, shape (n_t,): ``1 + shading * (2 u - 1)``."""
        return 1.0 + self.shading * (2.0 * self._u(n_t) - 1.0)

    def drift_ps(self, sim_time_s: float) -> float:
        """Drift at a simulated time (s since the clock started), ps."""
        return self.drift_ps_per_min * float(sim_time_s) / 60.0

    def jitter_draw_ps(self, seed: int, frame: int) -> float:
        """Trigger jitter of exposure number ``frame`` (0-based, since the camera started), ps."""
        if not self.jitter_ps:
            return 0.0
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, _JITTER_STREAM, int(frame)])
        return float(rng.normal(0.0, self.jitter_ps))

    def fiducial_nominal(self, nominal_ps: np.ndarray) -> dict:
        """Where the fiducial pulse lies with no jitter, drift or nonlinearity.

        Returns
        -------
        dict
            The run store's ``fiducial`` attribute, as :func:`reconstruction.align.parse_fiducial`
            reads it: ``row_start``, ``row_stop`` (the band of rows searched: the whole window,
            since the fiducial's slit pixels see nothing else), ``x_start``, ``x_stop`` (the slit
            pixels), ``nominal_ps`` (its time on the nominal row-time axis, the scaling table's);
            and, for reference, ``row`` (fractional nominal row), ``sigma_ps``, ``amplitude``.
        """
        nominal_ps = np.asarray(nominal_ps, dtype=np.float64)
        t = float(nominal_ps[0] + FIDUCIAL_FRACTION * (nominal_ps[-1] - nominal_ps[0]))
        row = float(np.interp(t, nominal_ps, np.arange(nominal_ps.size, dtype=np.float64)))
        return {"row_start": 0, "row_stop": int(nominal_ps.size), "x_start": 0, "x_stop": FIDUCIAL_PIXELS, "nominal_ps": t,
                "row": row, "sigma_ps": FIDUCIAL_SIGMA_PS, "amplitude": FIDUCIAL_AMPLITUDE}

    def fiducial_profile(self, nominal_ps: np.ndarray, true_ps: np.ndarray, shift_ps: float) -> np.ndarray:
        """The fiducial pulse at the true row times for a frame shifted by ``shift_ps``: (n_t,)."""
        t = self.fiducial_nominal(nominal_ps)["nominal_ps"] + float(shift_ps)
        return FIDUCIAL_AMPLITUDE * np.exp(-0.5 * ((np.asarray(true_ps) - t) / FIDUCIAL_SIGMA_PS) ** 2)


class SimClock:
    """The simulator's clock: ``speed`` simulated seconds per second of ``wall``.

    Parameters
    ----------
    speed : float
        Simulated seconds per wall-clock second (> 0).
    wall : callable() -> float, optional
        Wall clock in seconds (``time.monotonic`` by default; a test passes its own to make the
        simulated time exact).
    """

    def __init__(self, speed: float = 1.0, wall=None):
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
            raise ValueError(f"clock speed must be a positive number, got {speed!r}")
        self.speed = float(speed)
        self._wall = wall if wall is not None else time.monotonic
        self._start = float(self._wall())

    def now_s(self) -> float:
        """Simulated seconds since the clock was made."""
        return self.speed * (float(self._wall()) - self._start)
