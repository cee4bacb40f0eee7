"""The virtual scene the simulated streak camera looks at.

A scene is a stack of ``n_lines`` scan lines, each of ``n_x`` pixels along the
camera slit.  Every pixel carries its ground-truth time-profile parameters in
the parameter-dict convention of :mod:`decomposition.model` (direct reflection,
inter-reflections, subsurface scattering), with leading shape ``(n_lines, n_x)``.
Each scan line sits at one mirror angle (``angle_deg``).

The streak sweep is not linear: streak pixel row ``r`` (0-based, ``n_t`` rows)
records the light that arrived at

    t(r) = sum_k c_k r**k      (ps after the camera trigger)

with the polynomial coefficients ``time_calibration`` (lowest order first,
strictly increasing over the rows).  A trigger delay ``delay_ps`` opens the
window later, so row ``r`` then sees scene time ``t(r) * time_scale + delay_ps``,
where ``time_scale`` stretches the sweep for other time-range settings.

Counts of one frame::

    mean   = photon_scale * exposure_s / reference_exposure_s * gain_factor * (profile + background)
    counts = dark_level + Poisson(mean) + Normal(0, read_noise), rounded, clipped to uint16

with ``gain_factor = 2 ** ((gain - reference_gain) / GAIN_DOUBLING_STEPS)`` (an
MCP gain is close to exponential in its setting).  No light reaches the camera
when the laser output is off: the frame is dark level plus read noise only.

The camera's instrument response is the Gaussian of each component's ``*_sigma_ps``
unless the scene is given a ``response`` (:class:`core.irf.InstrumentResponse`); then every
direct return and inter-reflection is a shifted copy of that response and the sss the
response convolved with its exponential, each scaled so that its amplitude is the peak
height (the ``*_sigma_ps`` parameters are then unused).  :func:`simulated_response` gives
the named ones (``"tailed"``: a diffusion tail, ``"afterpulse"``: a small delayed copy), and
:meth:`VirtualScene.calibration` a calibration target (a flat mirror: one direct return per
pixel at a known delay map).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.irf import InstrumentResponse, render_shifted, render_sss
from core.irf_models import afterpulse_response, tailed_response
from core.model import BACKGROUND_KEY, DIRECT_KEYS, IR_KEYS, SSS_KEYS, empty_params, render_profile

__all__ = ["VirtualScene", "TIME_RANGE_SCALE", "SINGLE_SWEEP_REFERENCE_S", "GAIN_DOUBLING_STEPS",
           "time_range_scale", "SIMULATED_RESPONSES", "SIMULATED_SCENES", "simulated_response"]

# Instrument responses of the simulated camera, by name; "gaussian" is each component's own sigma.
SIMULATED_RESPONSES = ("gaussian", "tailed", "afterpulse")
# Scenes of the simulated lab, by name (classmethods of VirtualScene).
SIMULATED_SCENES = ("default", "calibration", "etalon", "uniform")


def simulated_response(name: str) -> InstrumentResponse | None:
    """The simulated camera's instrument response by name (None for ``"gaussian"``).

    ``"tailed"``: a 6 ps Gaussian with 20 % of its area in a 40 ps exponential diffusion
    tail; ``"afterpulse"``: a 6 ps Gaussian followed 60 ps later by a copy of 5 % of its
    area.  Both sampled every 2 ps (exact to far below 1e-12 of the peak), peak at t = 0.
    """
    if name == "gaussian":
        return None
    prov = {"source": "simulated camera", "name": name}
    if name == "tailed":
        return tailed_response(6.0, 0.2, 40.0, time_step_ps=2.0, provenance=prov)
    if name == "afterpulse":
        return afterpulse_response(6.0, 0.05, 60.0, time_step_ps=2.0, provenance=prov)
    raise ValueError(f"unknown simulated response {name!r} (known: {', '.join(SIMULATED_RESPONSES)})")

# Sweep duration of each synchroscan time-range setting relative to setting 2.
TIME_RANGE_SCALE = {1: 0.5, 2: 1.0, 3: 2.0, 4: 4.0}
# A single-sweep time range such as "1 ns" stretches the reference sweep (setting 2, whose
# window is about 560 ps) by its nominal duration over this one.
SINGLE_SWEEP_REFERENCE_S = 500e-12
# MCP gain steps that double the signal.
GAIN_DOUBLING_STEPS = 10.0
UINT16_MAX = np.iinfo(np.uint16).max
# Focus mode (no sweep): the slit image sits on this fraction of the rows, Gaussian of this width.
FOCUS_ROW_FRACTION = 0.5
FOCUS_SIGMA_ROWS = 1.5


def time_range_scale(time_range) -> float:
    """Sweep duration of a time range relative to synchroscan setting 2.

    ``time_range`` is a synchroscan setting number (key of :data:`TIME_RANGE_SCALE`) or a
    single-sweep time such as ``"1 ns"`` (nominal duration over :data:`SINGLE_SWEEP_REFERENCE_S`).
    """
    from drivers.remoteex_wire import normalize_time_range, time_range_seconds

    try:
        tr = normalize_time_range(time_range)
    except ValueError:
        raise ValueError(f"time_range must be one of {sorted(TIME_RANGE_SCALE)} or a time such as '1 ns', "
                         f"got {time_range!r}") from None
    if isinstance(tr, int):
        if tr not in TIME_RANGE_SCALE:
            raise ValueError(f"time_range must be one of {sorted(TIME_RANGE_SCALE)} or a time such as '1 ns', "
                             f"got {time_range!r}")
        return TIME_RANGE_SCALE[tr]
    return time_range_seconds(tr) / SINGLE_SWEEP_REFERENCE_S


@dataclass(eq=False)
class VirtualScene:
    """Per-pixel ground truth of the virtual lab and how the camera sees it.

    Attributes
    ----------
    params : dict of ndarray
        Ground truth, keys of :data:`decomposition.model.PARAM_KEYS`; shapes
        (n_lines, n_x) and (n_lines, n_x, R) for the inter-reflection keys.
        Delays in ps after the laser pulse reaches the camera with zero delay.
    angle_deg : ndarray, shape (n_lines,)
        Mirror angle of each scan line, degrees, strictly increasing.
    n_t : int
        Streak rows (time axis of a frame).
    time_calibration : ndarray, shape (K,)
        Polynomial coefficients, lowest order first: streak row -> time in ps
        relative to the trigger, at ``time_range`` and zero delay.  Strictly
        increasing over rows 0 .. n_t - 1.
    photon_scale : float
        Mean photo-counts per unit profile amplitude at the reference exposure and gain.
    dark_level : float
        Dark offset in counts.
    read_noise : float
        Gaussian read-noise standard deviation in counts.
    reference_exposure_s, reference_gain, time_range
        Settings at which ``photon_scale`` and ``time_calibration`` hold.
    response : InstrumentResponse, optional
        The camera's instrument response; None (default) is each component's Gaussian.
    background : float
        Ambient light reaching every pixel at a constant rate, in profile-amplitude units
        per row (>= 0, default 0): added to every clean profile, so it is scaled like the
        signal by exposure and gain and photon-counted with it (unlike ``dark_level``, a
        noiseless offset).
    """

    params: dict
    angle_deg: np.ndarray
    n_t: int
    time_calibration: np.ndarray
    photon_scale: float = 800.0
    dark_level: float = 100.0
    read_noise: float = 3.0
    reference_exposure_s: float = 0.01
    reference_gain: int = 30
    time_range: int = 2
    response: InstrumentResponse | None = None
    background: float = 0.0
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.params = {k: np.asarray(v, dtype=np.float64) for k, v in self.params.items()}
        self.angle_deg = np.asarray(self.angle_deg, dtype=np.float64)
        self.time_calibration = np.asarray(self.time_calibration, dtype=np.float64)
        self.n_t = int(self.n_t)
        self.validate()

    # ------------------------------------------------------------------ shape
    @property
    def n_lines(self) -> int:
        return int(self.angle_deg.shape[0])

    @property
    def n_x(self) -> int:
        return int(self.params["direct_delay_ps"].shape[1])

    def validate(self) -> None:
        """Raise ValueError naming the first inconsistency."""
        missing = [k for k in DIRECT_KEYS + SSS_KEYS + IR_KEYS if k not in self.params]
        if missing:
            raise ValueError(f"scene params lack keys {missing}")
        if self.angle_deg.ndim != 1 or self.angle_deg.size == 0:
            raise ValueError("angle_deg must be a non-empty 1-D array")
        if not np.all(np.isfinite(self.angle_deg)) or np.any(np.diff(self.angle_deg) <= 0):
            raise ValueError("angle_deg must be finite and strictly increasing")
        shape = self.params["direct_delay_ps"].shape
        if len(shape) != 2 or shape[0] != self.n_lines:
            raise ValueError(f"params must have shape (n_lines={self.n_lines}, n_x); direct_delay_ps has {shape}")
        for k in DIRECT_KEYS + SSS_KEYS:
            if self.params[k].shape != shape:
                raise ValueError(f"params[{k!r}] has shape {self.params[k].shape}, expected {shape}")
        ir_shape = self.params["ir_delay_ps"].shape
        for k in IR_KEYS:
            if self.params[k].shape != ir_shape or ir_shape[:2] != shape:
                raise ValueError(f"params[{k!r}] has shape {self.params[k].shape}, expected {shape} + (R,)")
        if self.n_t < 2:
            raise ValueError(f"n_t must be >= 2, got {self.n_t}")
        if self.time_calibration.ndim != 1 or self.time_calibration.size < 2:
            raise ValueError("time_calibration needs at least two coefficients (offset and slope)")
        t = self.row_times_ps()
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ValueError("time_calibration is not strictly increasing over the streak rows")
        for name in ("photon_scale", "reference_exposure_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        for name in ("dark_level", "read_noise", "background"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be non-negative and finite, got {v!r}")
        if self.time_range not in TIME_RANGE_SCALE:
            raise ValueError(f"time_range must be one of {sorted(TIME_RANGE_SCALE)}, got {self.time_range!r}")
        if self.response is not None and not isinstance(self.response, InstrumentResponse):
            raise ValueError(f"response must be an InstrumentResponse or None, got {type(self.response).__name__}")

    # ------------------------------------------------------------- geometry
    def row_times_ps(self, delay_ps: float = 0.0, time_range: int | str | None = None) -> np.ndarray:
        """Scene time seen by each streak row, shape (n_t,), ps.

        Parameters
        ----------
        delay_ps : float
            Trigger delay: the window opens this much later.
        time_range : int or str, optional
            Streak time range (see :func:`time_range_scale`); defaults to the scene's own.
        """
        scale = 1.0
        if time_range is not None:
            scale = time_range_scale(time_range) / TIME_RANGE_SCALE[self.time_range]
        rows = np.arange(self.n_t, dtype=np.float64)
        return np.polynomial.polynomial.polyval(rows, self.time_calibration) * scale + float(delay_ps)

    def line_index(self, angle_deg: float) -> int:
        """Index of the scan line whose angle is nearest ``angle_deg``."""
        return int(np.argmin(np.abs(self.angle_deg - float(angle_deg))))

    # ------------------------------------------------------------ rendering
    def line_params(self, line: int) -> dict:
        """Parameter dict of one scan line, leading shape (n_x,)."""
        return {k: v[line] for k, v in self.params.items()}

    def clean_line(self, line: int, delay_ps: float = 0.0, time_range: int | str | None = None) -> np.ndarray:
        """Noise-free profile of one scan line at the calibrated row times.

        Returns
        -------
        ndarray, shape (n_x, n_t), float64, in profile-amplitude units.
        """
        key = (int(line), float(delay_ps), time_range)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        out = self.clean_line_at(line, self.row_times_ps(delay_ps, time_range))
        if len(self._cache) >= 64:
            self._cache.clear()
        self._cache[key] = out
        return out

    def clean_line_at(self, line: int, times_ps: np.ndarray) -> np.ndarray:
        """Noise-free profile of one scan line seen at the given scene times (one per row, ps).

        Returns
        -------
        ndarray, shape (n_x, times_ps.size), float64, in profile-amplitude units (background included).
        """
        times = np.asarray(times_ps, dtype=np.float64)
        p = self.line_params(line)
        out = self._render_with_response(p, times) if self.response is not None else self._render_gaussian(p, times)
        if self.background > 0:
            out = out + self.background
        return out

    def _render_gaussian(self, p: dict, times: np.ndarray) -> np.ndarray:
        """One line's profiles with the Gaussian PSF: (n_x, n_t).

        Every (pixel, row) pair is rendered as a one-bin profile sampled at t0_ps = 0, with the
        delays moved by the row's time: g(t_r - d) = g(0 - (d - t_r))."""
        shifted = {}
        for k, v in p.items():
            if k in ("direct_delay_ps", "sss_delay_ps"):
                shifted[k] = v[:, None] - times[None, :]                      # (n_x, n_t)
            elif k == "ir_delay_ps":
                shifted[k] = v[:, None, :] - times[None, :, None]             # (n_x, n_t, R)
            elif k in IR_KEYS:
                shifted[k] = np.broadcast_to(v[:, None, :], (v.shape[0], self.n_t, v.shape[1]))
            else:
                shifted[k] = np.broadcast_to(v[:, None], (v.shape[0], self.n_t))
        return render_profile(shifted, 1, time_bin_ps=1.0, t0_ps=0.0)[..., 0]

    def _render_with_response(self, p: dict, times: np.ndarray) -> np.ndarray:
        """One line's profiles with the scene's ``response``: (n_x, n_t), peak-height amplitudes."""
        out = np.zeros((p["direct_delay_ps"].shape[0], times.size))
        pairs = [(p["direct_delay_ps"], p["direct_amplitude"])]
        pairs += [(p["ir_delay_ps"][:, r], p["ir_amplitude"][:, r]) for r in range(p["ir_delay_ps"].shape[1])]
        for delay, amp in pairs:
            ok = np.isfinite(delay) & np.isfinite(amp)
            if ok.any():
                out[ok] += amp[ok, None] * render_shifted(self.response, times, delay[ok])
        delay, amp, alpha = p["sss_delay_ps"], p["sss_amplitude"], p["sss_alpha_per_ps"]
        ok = np.isfinite(delay) & np.isfinite(amp) & np.isfinite(alpha) & (alpha >= 0)
        if ok.any():
            out[ok] += amp[ok, None] * render_sss(self.response, times, delay[ok], alpha[ok])
        return out

    def expected_counts(self, line: int, *, delay_ps: float = 0.0, exposure_s: float | None = None,
                        gain: int | None = None, time_range: int | str | None = None,
                        light: bool = True) -> np.ndarray:
        """Mean counts of a frame (before noise and clipping), shape (n_x, n_t), float64."""
        signal = self.signal_scale(exposure_s, gain) * self.clean_line(line, delay_ps, time_range) if light \
            else np.zeros((self.n_x, self.n_t))
        return self.dark_level + signal

    def signal_scale(self, exposure_s: float | None = None, gain: int | None = None) -> float:
        """Mean counts per unit profile amplitude at these settings."""
        exposure_s = self.reference_exposure_s if exposure_s is None else float(exposure_s)
        gain = self.reference_gain if gain is None else gain
        return self.photon_scale * exposure_s / self.reference_exposure_s \
            * 2.0 ** ((gain - self.reference_gain) / GAIN_DOUBLING_STEPS)

    def expected_focus_counts(self, line: int, *, exposure_s: float | None = None, gain: int | None = None,
                              light: bool = True) -> np.ndarray:
        """Mean counts in focus mode (sweep off), shape (n_x, n_t), float64.

        Without the sweep all of a pixel's light over the window lands on the slit image:
        a Gaussian of ``FOCUS_SIGMA_ROWS`` rows centred on row ``FOCUS_ROW_FRACTION * (n_t - 1)``.
        """
        out = np.full((self.n_x, self.n_t), self.dark_level, dtype=np.float64)
        if light:
            total = self.clean_line(line).sum(axis=-1)                       # (n_x,)
            rows = np.arange(self.n_t, dtype=np.float64)
            g = np.exp(-0.5 * ((rows - FOCUS_ROW_FRACTION * (self.n_t - 1)) / FOCUS_SIGMA_ROWS) ** 2)
            out += self.signal_scale(exposure_s, gain) * total[:, None] * (g / g.sum())[None, :]
        return out

    def render_frame(self, line: int, rng: np.random.Generator, *, delay_ps: float = 0.0,
                     exposure_s: float | None = None, gain: int | None = None,
                     time_range: int | str | None = None, light: bool = True, focus: bool = False,
                     dark: bool = True, signal_mean: np.ndarray | None = None) -> np.ndarray:
        """One noisy frame (``focus``: sweep off, see :meth:`expected_focus_counts`).

        ``dark=False`` leaves out the dark level and the read noise (photon counting).
        ``signal_mean`` (n_x, n_t), mean photo-counts above the dark level, replaces the scene's
        own (the simulated camera's time-base effects, :mod:`drivers.sim.timebase`); the noise
        is drawn the same way.

        Returns
        -------
        ndarray, shape (n_x, n_t), uint16 counts.
        """
        counts = np.full((self.n_x, self.n_t), self.dark_level if dark else 0.0, dtype=np.float64)
        if light:
            if signal_mean is not None:
                mean = signal_mean
            elif focus:
                mean = self.expected_focus_counts(line, exposure_s=exposure_s, gain=gain) - self.dark_level
            else:
                mean = self.signal_scale(exposure_s, gain) * self.clean_line(line, delay_ps, time_range)
            counts += rng.poisson(np.clip(mean, 0.0, 1e12))
        if not dark:
            return np.clip(counts, 0, UINT16_MAX).astype(np.uint16)
        counts += rng.normal(0.0, self.read_noise, size=counts.shape) if self.read_noise > 0 else 0.0
        return np.clip(np.rint(counts), 0, UINT16_MAX).astype(np.uint16)

    # ------------------------------------------------------------- defaults
    @classmethod
    def calibration(cls, n_lines: int = 8, n_x: int = 64, n_t: int = 256, seed: int = 0,
                    response: InstrumentResponse | None = None) -> "VirtualScene":
        """A calibration target: a flat mirror filling the view, one direct return per pixel.

        The mirror is tilted, so the return's delay runs across the view (known delay map:
        ``params["direct_delay_ps"]``, from 25 % to 33 % of the window, every pixel at another
        sub-bin offset) at a uniform amplitude of 0.8; nothing else returns light.  The
        sweep is that of :meth:`default`.

        Parameters
        ----------
        n_lines, n_x, n_t, seed
            As in :meth:`default` (``seed`` perturbs the tilt).
        response : InstrumentResponse, optional
            The camera's response (None: the Gaussian, sigma 6 ps).
        """
        base = cls.default(n_lines=n_lines, n_x=n_x, n_t=n_t, seed=seed)
        window_ps = float(np.polynomial.polynomial.polyval(base.n_t - 1, base.time_calibration))
        rng = np.random.default_rng(seed + 1)
        y = (np.arange(base.n_lines) + 0.5) / base.n_lines
        x = (np.arange(base.n_x) + 0.5) / base.n_x
        Y, X = np.meshgrid(y, x, indexing="ij")
        p = empty_params((base.n_lines, base.n_x), n_ir=0)
        p["direct_delay_ps"][:] = window_ps * (0.25 + (0.05 + rng.uniform(-0.005, 0.005)) * X + 0.03 * Y)
        p["direct_amplitude"][:] = 0.8
        p["direct_sigma_ps"][:] = 6.0
        return cls(params=p, angle_deg=base.angle_deg, n_t=base.n_t, time_calibration=base.time_calibration,
                   response=response)

    @classmethod
    def etalon(cls, n_lines: int = 24, n_x: int = 8, n_t: int = 256, seed: int = 0, *, etalon_ps: float = 20.0,
               response: InstrumentResponse | None = None) -> "VirtualScene":
        """A sweep-calibration target: an etalon's pulse pair, ``etalon_ps`` apart, in every pixel.

        The pair stands for the laser seen through an etalon while the trigger delay steps from
        line to line: line ``l``'s first pulse arrives at :meth:`etalon_arrivals_ps` ``[l]``, from 8 %
        to 85 % of the window less the separation, so the pairs cross every part of the sweep.
        The second pulse carries 0.8 of the first's amplitude; both have a sigma of 2.5 ps (a
        short pulse) and are the same across the slit.  ``streaklab calibrate-sweep`` takes
        ``--delays-ps`` equal to minus these arrivals (a delay later by d moves the pair d earlier).
        """
        base = cls.default(n_lines=n_lines, n_x=n_x, n_t=n_t, seed=seed)
        if not (np.isfinite(etalon_ps) and etalon_ps > 0):
            raise ValueError(f"etalon_ps must be positive, got {etalon_ps!r}")
        window_ps = float(np.polynomial.polynomial.polyval(base.n_t - 1, base.time_calibration))
        if etalon_ps > 0.25 * window_ps:
            raise ValueError(f"etalon_ps {etalon_ps:g} is over a quarter of the {window_ps:.0f} ps window")
        arrival = cls.etalon_arrivals_ps(base.n_lines, window_ps, etalon_ps)
        p = empty_params((base.n_lines, base.n_x), n_ir=1)
        p["direct_delay_ps"][:] = arrival[:, None]
        p["direct_amplitude"][:] = 1.0
        p["direct_sigma_ps"][:] = 2.5
        p["ir_delay_ps"][:, :, 0] = arrival[:, None] + etalon_ps
        p["ir_amplitude"][:, :, 0] = 0.8
        p["ir_sigma_ps"][:, :, 0] = 2.5
        return cls(params=p, angle_deg=base.angle_deg, n_t=base.n_t, time_calibration=base.time_calibration,
                   response=response)

    @classmethod
    def uniform(cls, n_lines: int = 8, n_x: int = 64, n_t: int = 256, seed: int = 0, *,
                level: float = 1.0) -> "VirtualScene":
        """A shading target: light of one level at every time and pixel (a lamp on the slit), so
        that a capture shows the camera's sensitivity along the time axis and nothing else."""
        base = cls.default(n_lines=n_lines, n_x=n_x, n_t=n_t, seed=seed)
        if not (np.isfinite(level) and level > 0):
            raise ValueError(f"level must be positive, got {level!r}")
        p = empty_params((base.n_lines, base.n_x), n_ir=0)
        p[BACKGROUND_KEY] = np.full((base.n_lines, base.n_x), float(level))
        return cls(params=p, angle_deg=base.angle_deg, n_t=base.n_t, time_calibration=base.time_calibration)

    @staticmethod
    def etalon_arrivals_ps(n_lines: int, window_ps: float, etalon_ps: float) -> np.ndarray:
        """The first pulse's arrival on each line of :meth:`etalon` (n_lines,), ps."""
        return np.linspace(0.08 * window_ps, 0.85 * window_ps - etalon_ps, int(n_lines))

    @classmethod
    def default(cls, n_lines: int = 16, n_x: int = 64, n_t: int = 256, seed: int = 0) -> "VirtualScene":
        """A plausible table-top scene.

        A back wall whose depth increases across x (direct only), a translucent
        round object in the middle (weak direct plus subsurface scattering, like
        a tomato) and a corner on the right (direct plus second- and third-bounce
        inter-reflections).  All light arrives inside the time window at zero
        trigger delay.  ``seed`` perturbs the geometry slightly so scenes differ.

        Parameters
        ----------
        n_lines, n_x, n_t : int
            Scan lines, pixels per line, streak rows.
        seed : int
            Seed of the geometric perturbations.
        """
        n_lines, n_x, n_t = int(n_lines), int(n_x), int(n_t)
        if n_lines < 1 or n_x < 1 or n_t < 16:
            raise ValueError(f"need n_lines >= 1, n_x >= 1, n_t >= 16; got {n_lines}, {n_x}, {n_t}")
        rng = np.random.default_rng(seed)
        # Sweep: ~2 ps per row at the start, slowing down to ~2.6 ps per row at the end
        # (for 256 rows); normalised so any n_t spans the same ~560 ps window.
        calib = np.array([2.0, 460.8 / n_t, 102.4 / n_t**2])
        window_ps = float(np.polynomial.polynomial.polyval(n_t - 1, calib))

        y = (np.arange(n_lines) + 0.5) / n_lines                                 # (n_lines,)
        x = (np.arange(n_x) + 0.5) / n_x                                          # (n_x,)
        Y, X = np.meshgrid(y, x, indexing="ij")                                   # (n_lines, n_x)
        tilt = rng.uniform(-0.1, 0.1)
        p = empty_params((n_lines, n_x), n_ir=2)

        # Back wall: direct only, farther to the right and slightly tilted in y.
        wall_delay = window_ps * (0.30 + 0.12 * X + 0.03 * (Y - 0.5) * (1 + tilt))
        p["direct_delay_ps"][:] = wall_delay
        p["direct_amplitude"][:] = 0.8 - 0.3 * X
        p["direct_sigma_ps"][:] = 6.0

        # Translucent object: a disc in the middle, nearer than the wall.
        cy, cx = 0.5 + rng.uniform(-0.05, 0.05), 0.45 + rng.uniform(-0.05, 0.05)
        r2 = ((Y - cy) / 0.32) ** 2 + ((X - cx) / 0.2) ** 2
        obj = r2 < 1.0
        bulge = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
        obj_delay = window_ps * (0.22 - 0.04 * bulge)
        p["direct_delay_ps"][obj] = obj_delay[obj]
        p["direct_amplitude"][obj] = 0.25
        p["sss_delay_ps"][obj] = obj_delay[obj] + 2.0
        p["sss_amplitude"][obj] = 0.03 + 0.01 * bulge[obj]
        p["sss_alpha_per_ps"][obj] = 0.025
        p["sss_sigma_ps"][obj] = 6.0

        # Corner on the right: second and third bounces after the direct return.
        corner = (X > 0.78) & ~obj
        depth = (X - 0.78) / 0.22
        p["ir_delay_ps"][corner, 0] = wall_delay[corner] + window_ps * (0.08 + 0.06 * depth[corner])
        p["ir_amplitude"][corner, 0] = 0.3
        p["ir_sigma_ps"][corner, 0] = 6.0
        p["ir_delay_ps"][corner, 1] = wall_delay[corner] + window_ps * (0.18 + 0.10 * depth[corner])
        p["ir_amplitude"][corner, 1] = 0.1
        p["ir_sigma_ps"][corner, 1] = 6.0

        angle = np.linspace(-10.0, 10.0, n_lines) if n_lines > 1 else np.zeros(1)
        return cls(params=p, angle_deg=angle, n_t=n_t, time_calibration=calib)
