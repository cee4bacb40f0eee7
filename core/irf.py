"""The instrument response c(t) as data: a sampled, unit-area response and its atoms.

A pixel's profile is p(t) = c(t) * e(t) + n(t) (eq. (1) of the ConvSCD paper).  The paper
and :mod:`core.model` take c to be a Gaussian; a real detector's response has a diffusion
tail, an afterpulse, a laser pulse's own tail.  :class:`InstrumentResponse` holds any
response as samples, and :func:`render_shifted` / :func:`render_sss` turn it into the two
kinds of atom the decomposition uses:

    direct and inter-reflections   c(t - d)                         (a shifted copy)
    subsurface scattering          (c * [exp(-alpha t) u(t)])(t - d)

Conventions
-----------
samples
    ``samples[j]`` is the response at ``t0_ps + j * time_step_ps`` ps, in 1/ps, normalised
    to unit area: ``samples.sum() * time_step_ps == 1`` (this is also the exact integral of
    the interpolant below).
reference instant
    t = 0 on the response's own axis is the instant a component's delay refers to: an atom
    with delay d has its reference instant at t = d.  Every response streaklab makes (the
    model responses below and :func:`reconstruction.irf.estimate_response`) puts t = 0 at
    the response's peak, the maximum of its interpolant (``peak_time_ps == 0``); for a
    Gaussian that is its centre, as in :mod:`core.model`.  ``centred()`` moves any response
    onto this convention.
the continuous response
    Between samples the response is the band-limited (sinc) interpolant of the samples,
    computed exactly as the trigonometric interpolant of the samples zero-padded to an odd
    length N on each side (``pad_samples`` zeros before, at least as many after) and
    restricted to that padded window; outside it the response is zero.  For a response
    whose spectrum is negligible beyond the Nyquist frequency 1 / (2 time_step_ps) and
    which has decayed to zero at both ends of its samples, this interpolant *is* the
    continuous response, so shifts by any fraction of a bin are exact: a Gaussian of
    standard deviation s sampled every T ps is reproduced to about
    exp(-(pi s / T)**2 / 2) of its peak (7e-3 at s = T, 1.5e-5 at s = 1.5 T, 3e-9 at
    s = 2 T).
normalisation of atoms
    ``normalization="peak"`` (default) divides every atom by ``peak_per_ps``, the peak of
    the continuous response, so that a shifted atom has unit peak like
    :func:`core.model.gaussian_kernel` and, for a Gaussian response, :func:`render_sss`
    equals :func:`core.model.sss_kernel`; amplitudes then keep their meaning (peak height
    of the direct reflection) when the Gaussian is replaced.  ``"area"`` returns the atoms
    in 1/ps (unit-area direct atoms).

Shifted copies are evaluated from the response's discrete Fourier transform with a phase
ramp: on a time axis with the response's own step one inverse FFT per atom gives the atom at
every bin (a whole-bin shift is an index offset), on any other axis the interpolant is
summed directly at the requested times.  The sss atom is the exact convolution of that same
interpolant with the causal exponential (see :func:`render_sss` for the closed form and its
stable evaluation for alpha * T from 0 to beyond 100).

Model responses with closed forms (Gaussian, Gaussian with a diffusion tail, main peak with
an afterpulse) and the distance of a response from its best Gaussian are in
:mod:`core.irf_models`.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sp_fft

from .errors import StreaklabError

__all__ = [
    "ResponseError",
    "InstrumentResponse",
    "render_shifted",
    "render_sss",
    "MIN_SAMPLES",
    "NEGATIVE_TOLERANCE",
    "EDGE_TOLERANCE",
]

MIN_SAMPLES = 8
# A sample may dip below zero by this fraction of the peak (noise of a measured response).
NEGATIVE_TOLERANCE = 0.05
# The first and last samples may be at most this fraction of the peak: the response must
# have decayed inside its window, or its shifted copies ring.
EDGE_TOLERANCE = 0.05

# Work arrays of the direct (non-FFT) evaluation are kept below this many elements.
_BLOCK_ELEMENTS = 2_000_000


class ResponseError(StreaklabError, ValueError):
    """An instrument response (or a request to render one) is unusable; the message says why."""


def _pad_samples(m: int) -> int:
    return max(8, m // 4)


@dataclass(frozen=True, eq=False)
class InstrumentResponse:
    """A sampled instrument response, normalised to unit area.

    Parameters
    ----------
    samples : array_like, shape (M,)
        Response at ``t0_ps + j * time_step_ps``; any positive scale (it is normalised to
        unit area, 1/ps).  Finite, at least :data:`MIN_SAMPLES` samples, non-negative within
        :data:`NEGATIVE_TOLERANCE` of the peak, and decayed to within
        :data:`EDGE_TOLERANCE` of the peak at both ends.
    time_step_ps : float
        Sample spacing in ps (> 0).
    t0_ps : float
        Time of ``samples[0]`` relative to the response's reference instant, ps (see the
        module docstring: streaklab's responses have their peak at t = 0).
    provenance : dict
        JSON-serialisable description of where the response came from.
    model : dict, optional
        Closed form of a model response (see :func:`model_value`); None for measured ones.

    Attributes
    ----------
    peak_time_ps, peak_per_ps : float
        Time (on the response's axis, ps) and value (1/ps) of the interpolant's maximum.
    """

    samples: np.ndarray
    time_step_ps: float
    t0_ps: float = 0.0
    provenance: dict = field(default_factory=dict)
    model: dict | None = None
    peak_time_ps: float = field(init=False)
    peak_per_ps: float = field(init=False)
    _spectrum: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        s = np.array(self.samples, dtype=np.float64, copy=True)
        if s.ndim != 1:
            raise ResponseError(f"response samples must be 1-D, got shape {s.shape}")
        if s.size < MIN_SAMPLES:
            raise ResponseError(f"a response needs at least {MIN_SAMPLES} samples, got {s.size}")
        if not np.all(np.isfinite(s)):
            raise ResponseError(f"response samples must be finite ({int(np.sum(~np.isfinite(s)))} are not)")
        dt = float(self.time_step_ps)
        if not (math.isfinite(dt) and dt > 0):
            raise ResponseError(f"time_step_ps must be positive and finite, got {self.time_step_ps!r}")
        t0 = float(self.t0_ps)
        if not math.isfinite(t0):
            raise ResponseError(f"t0_ps must be finite, got {self.t0_ps!r}")
        peak = s.max()
        area = s.sum() * dt
        if not (peak > 0 and area > 0):
            raise ResponseError("response samples have no positive peak (all zero or negative)")
        if s.min() < -NEGATIVE_TOLERANCE * peak:
            raise ResponseError(f"response samples reach {s.min() / peak:.3g} of the peak; a response must be "
                                f"non-negative within {NEGATIVE_TOLERANCE:g} of its peak")
        edge = max(abs(s[0]), abs(s[-1])) / peak
        if edge > EDGE_TOLERANCE:
            end = "first" if abs(s[0]) >= abs(s[-1]) else "last"
            raise ResponseError(f"the response has not decayed at its window edge: its {end} sample is "
                                f"{edge:.3g} of the peak (at most {EDGE_TOLERANCE:g}); record a longer window")
        try:
            prov = json.loads(json.dumps(dict(self.provenance or {})))
            model = None if self.model is None else json.loads(json.dumps(dict(self.model)))
        except (TypeError, ValueError) as exc:
            raise ResponseError(f"response provenance and model must be JSON-serialisable: {exc}") from None
        if abs(area - 1.0) > 1e-13:          # already unit area (e.g. read back from a store): keep the bits
            s /= area
        s.setflags(write=False)
        set_ = object.__setattr__
        set_(self, "samples", s)
        set_(self, "time_step_ps", dt)
        set_(self, "t0_ps", t0)
        set_(self, "provenance", prov)
        set_(self, "model", model)
        n = s.size + 2 * _pad_samples(s.size)
        n += 1 - n % 2                       # odd: no Nyquist bin, the interpolant is unambiguous
        padded = np.zeros(n)
        padded[_pad_samples(s.size):_pad_samples(s.size) + s.size] = s
        spec = sp_fft.rfft(padded)
        spec.setflags(write=False)
        set_(self, "_spectrum", spec)
        tp, vp = self._find_peak()
        set_(self, "peak_time_ps", tp)
        set_(self, "peak_per_ps", vp)

    # ----------------------------------------------------------------- geometry
    @property
    def n_samples(self) -> int:
        return int(self.samples.size)

    @property
    def pad_samples(self) -> int:
        """Zeros in front of the samples in the padded window of the interpolant."""
        return _pad_samples(self.n_samples)

    @property
    def n_padded(self) -> int:
        """Length N (odd) of the padded window."""
        return 2 * self._spectrum.size - 1

    @property
    def window_start_ps(self) -> float:
        """Start of the padded window on the response's axis, ps (the interpolant is zero before)."""
        return self.t0_ps - self.pad_samples * self.time_step_ps

    @property
    def window_ps(self) -> float:
        """Length of the padded window, ps."""
        return self.n_padded * self.time_step_ps

    def time_axis_ps(self) -> np.ndarray:
        """Sample times on the response's axis, shape (M,), ps."""
        return self.t0_ps + self.time_step_ps * np.arange(self.n_samples, dtype=np.float64)

    @property
    def spectrum(self) -> np.ndarray:
        """rfft of the zero-padded samples, shape ((N + 1) / 2,), complex, read-only: the interpolant is
        (1/N) [X_0 + 2 Re sum_k X_k exp(i omega_k (t - window_start_ps))] on the padded window."""
        return self._spectrum

    def angular_frequencies(self) -> np.ndarray:
        """omega_k = 2 pi k / (N time_step_ps), k = 0 .. (N - 1) / 2, rad/ps."""
        return 2.0 * np.pi * np.arange(self._spectrum.size) / self.window_ps

    def centred(self) -> "InstrumentResponse":
        """The same response with its peak at t = 0 (streaklab's reference convention)."""
        if self.peak_time_ps == 0.0:
            return self
        prov = dict(self.provenance)
        prov["recentred_by_ps"] = float(-self.peak_time_ps) + float(prov.get("recentred_by_ps", 0.0))
        model = None
        if self.model is not None:
            model = dict(self.model)
            model["offset_ps"] = float(model.get("offset_ps", 0.0)) + self.peak_time_ps
        return InstrumentResponse(self.samples, self.time_step_ps, self.t0_ps - self.peak_time_ps, prov, model)

    def centroid_ps(self) -> float:
        """First moment of the samples on the response's axis, ps."""
        return float(np.sum(self.samples * self.time_axis_ps()) * self.time_step_ps)

    def fwhm_ps(self) -> float:
        """Full width at half maximum of the interpolant, ps: between its outermost half-maximum
        crossings, each located on a grid of step / 64 and refined by a root search."""
        half = 0.5 * self.peak_per_ps
        above = np.flatnonzero(self.samples >= half)
        dt = self.time_step_ps
        fine = np.linspace(-1.0, 1.0, 129) * dt
        f = lambda t: float(self.evaluate(t)) - half
        out = []
        for j, side in ((above[0], 0), (above[-1], -1)):
            t = self.t0_ps + j * dt + fine
            up = np.flatnonzero(self.evaluate(t) >= half)[side]
            nb = up - 1 if side == 0 else up + 1
            if 0 <= nb < t.size:
                a, b = sorted((t[up], t[nb]))
                from scipy.optimize import brentq   # here: importing scipy.optimize costs 0.2 s

                out.append(brentq(f, a, b, xtol=1e-12))
            else:
                out.append(t[up])
        return float(out[1] - out[0])

    # --------------------------------------------------------------- evaluation
    def evaluate(self, t_ps, *, derivative: int = 0) -> np.ndarray:
        """The continuous response (or its first / second derivative) at times ``t_ps``.

        Parameters
        ----------
        t_ps : array_like
            Times on the response's own axis, ps; any shape.
        derivative : {0, 1, 2}

        Returns
        -------
        ndarray, shape of ``t_ps``, 1/ps (times 1/ps per derivative).
        """
        t = np.asarray(t_ps, dtype=np.float64)
        if derivative not in (0, 1, 2):
            raise ResponseError(f"derivative must be 0, 1 or 2, got {derivative!r}")
        d = (t.reshape(1, -1) - self.window_start_ps) / self.time_step_ps
        mult = (1j * self.angular_frequencies()) ** derivative
        out = _trig_eval(self._spectrum * mult, d, self.n_padded)[0]
        out[(d[0] < 0) | (d[0] >= self.n_padded)] = 0.0
        return out.reshape(t.shape)

    def _find_peak(self) -> tuple[float, float]:
        j = int(np.argmax(self.samples))
        t_grid = self.t0_ps + self.time_step_ps * (j + np.linspace(-1.0, 1.0, 129))
        v = self.evaluate(t_grid)
        t = float(t_grid[int(np.argmax(v))])
        lo, hi = t_grid[0], t_grid[-1]
        for _ in range(8):                   # Newton on c'(t) = 0, kept inside the bracket
            d1 = float(self.evaluate(t, derivative=1))
            d2 = float(self.evaluate(t, derivative=2))
            if not d2 < 0:
                break
            step = -d1 / d2
            t = min(max(t + step, lo), hi)
            if abs(step) < 1e-12 * self.time_step_ps:
                break
        return t, float(self.evaluate(t))

    def describe(self) -> dict:
        """A JSON-able summary (shape and widths, ps)."""
        return {"n_samples": self.n_samples, "time_step_ps": self.time_step_ps, "t0_ps": self.t0_ps,
                "peak_time_ps": self.peak_time_ps, "fwhm_ps": self.fwhm_ps(), "centroid_ps": self.centroid_ps(),
                "model": self.model}


def _trig_eval(spec: np.ndarray, d: np.ndarray, n: int) -> np.ndarray:
    """Real trigonometric interpolant with rfft coefficients ``spec`` at positions ``d``.

    ``spec`` (K,) or (A, K); ``d`` (A, P) positions in samples from the window start.
    Returns (A, P): (1/N) [Y_0 + 2 sum_k Re(Y_k z**k)], z = exp(2 pi i d / N), the powers of z
    by a running product (one complex multiply per term instead of a cos and a sin; the
    rounding grows like k * eps, below 1e-13 for any response of a few thousand samples).
    """
    spec = np.atleast_2d(spec)
    a, p = d.shape
    k = spec.shape[-1]
    out = np.empty((a, p))
    step = max(1, _BLOCK_ELEMENTS // max(1, p * k))
    for lo in range(0, a, step):
        hi = min(a, lo + step)
        sp = np.broadcast_to(spec, (a, k))[lo:hi]
        z = np.exp(2j * np.pi * d[lo:hi] / n)                              # (a, P)
        powers = np.empty((hi - lo, p, k), dtype=np.complex128)
        powers[..., 0] = 1.0
        if k > 1:
            powers[..., 1:] = z[..., None]
            np.cumprod(powers[..., 1:], axis=-1, out=powers[..., 1:])
        acc = np.einsum("apk,ak->ap", powers, sp)
        out[lo:hi] = (2.0 * acc.real - sp.real[:, None, 0]) / n
    return out


def _positions(irf: InstrumentResponse, t_ps, delay_ps):
    """Validated axis and delays; positions of every (atom, bin) in samples from the window start."""
    t = np.asarray(t_ps, dtype=np.float64)
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise ResponseError(f"t_ps must be a non-empty finite 1-D time axis, got shape {t.shape}")
    delay = np.asarray(delay_ps, dtype=np.float64)
    if not np.all(np.isfinite(delay)):
        raise ResponseError("delay_ps must be finite")
    lead = delay.shape
    flat = delay.reshape(-1)
    d = (t[None, :] - flat[:, None] - irf.window_start_ps) / irf.time_step_ps      # (A, L)
    uniform = t.size >= 2 and np.allclose(np.diff(t), irf.time_step_ps, rtol=1e-12, atol=0.0)
    return t, flat, lead, d, uniform or t.size == 1


def _shifted_eval(irf: InstrumentResponse, spec_rows: np.ndarray, d: np.ndarray, uniform: bool) -> np.ndarray:
    """Interpolant with per-atom spectra ``spec_rows`` (A, K) at positions ``d`` (A, L), inside the window."""
    n = irf.n_padded
    if not uniform:
        return _trig_eval(spec_rows, d, n)
    # Every bin of an atom has the same fractional position: one inverse FFT per atom on the
    # padded grid (phase ramp exp(2 pi i k phi / N)), then whole-bin offsets by indexing.
    base = d[:, 0]
    whole = np.floor(base)
    frac = base - whole
    ramp = np.exp(2j * np.pi * np.arange(spec_rows.shape[-1])[None, :] * frac[:, None] / n)
    grid = sp_fft.irfft(spec_rows * ramp, n=n, axis=-1)                   # (A, N) at j + frac
    idx = whole[:, None].astype(np.int64) + np.arange(d.shape[1])[None, :]
    inside = (idx >= 0) & (idx < n)
    return np.where(inside, np.take_along_axis(grid, np.clip(idx, 0, n - 1), axis=1), 0.0)


def _norm(irf: InstrumentResponse, normalization: str) -> float:
    if normalization == "peak":
        return 1.0 / irf.peak_per_ps
    if normalization == "area":
        return 1.0
    raise ResponseError(f"normalization must be 'peak' or 'area', got {normalization!r}")


def render_shifted(irf: InstrumentResponse, t_ps, delay_ps, *, normalization: str = "peak",
                   derivative: bool = False):
    """Shifted copies c(t - d) of the response: direct and inter-reflection atoms.

    Parameters
    ----------
    irf : InstrumentResponse
    t_ps : array_like, shape (L,)
        Time axis, ps (uniform or not; a uniform axis with the response's own step takes the
        FFT path, any other is evaluated directly, with the same result).
    delay_ps : array_like, shape (...,)
        Delay of each atom, ps: the atom's reference instant (its peak) is at t = delay.
    normalization : {"peak", "area"}
        Unit-peak atoms (default) or the response in 1/ps.
    derivative : bool
        Also return the derivative of every atom with respect to its delay.

    Returns
    -------
    atoms : ndarray, shape (..., L), float64
    d_atoms_d_delay : ndarray, shape (..., L), per ps (only with ``derivative=True``)
        d/dd c(t - d) = -c'(t - d).
    """
    t, flat, lead, d, uniform = _positions(irf, t_ps, delay_ps)
    scale = _norm(irf, normalization)
    spec = np.broadcast_to(irf._spectrum, (flat.size, irf._spectrum.size))
    inside = (d >= 0) & (d < irf.n_padded)
    out = np.where(inside, _shifted_eval(irf, spec, d, uniform), 0.0) * scale
    if not derivative:
        return out.reshape(lead + (t.size,))
    dspec = spec * (-1j * irf.angular_frequencies())
    dout = np.where(inside, _shifted_eval(irf, dspec, d, uniform), 0.0) * scale
    return out.reshape(lead + (t.size,)), dout.reshape(lead + (t.size,))


def _one_minus_exp_over_x(x):
    """phi(x) = (1 - exp(-x)) / x for x >= 0, phi(0) = 1, without cancellation."""
    x = np.asarray(x, dtype=np.float64)
    small = x < 1e-8
    safe = np.where(small, 1.0, x)
    return np.where(small, 1.0 - 0.5 * x, -np.expm1(-safe) / safe)


_PSI_COEFFS = [(n - 1) / math.factorial(n) * (-1) ** n for n in range(2, 14)]


def _psi(x):
    """psi(x) = (1 - exp(-x) (1 + x)) / x**2 for x >= 0, psi(0) = 1/2 (series below x = 0.1)."""
    x = np.asarray(x, dtype=np.float64)
    small = x < 0.1
    safe = np.where(small, 1.0, x)
    direct = (-np.expm1(-safe) - safe * np.exp(-safe)) / (safe * safe)
    series = np.zeros_like(x)
    for c in reversed(_PSI_COEFFS):
        series = series * x + c
    return np.where(small, series, direct)


def render_sss(irf: InstrumentResponse, t_ps, delay_ps, alpha_per_ps, *, normalization: str = "peak",
               derivatives: bool = False):
    """Subsurface-scattering atoms: the response convolved with a causal decaying exponential.

    s(v) = integral_0^inf exp(-alpha u) c(v - u) du, rendered at v = t - d.

    With the response's interpolant on its padded window [A, A + B) written as
    c = (1/N) [X_0 + 2 Re sum_k X_k exp(i w_k D)], D = v - A, the convolution is exact in
    closed form:

        s(D) = Q(D) - exp(-alpha D) Q(0) + (X_0 / N) D phi(alpha D),     0 <= D <= B
        Q(D) = (2/N) Re sum_{k>=1} X_k exp(i w_k D) / (alpha + i w_k)
        s(D) = s(B) exp(-alpha (D - B)),                                 D > B
        s(D) = 0,                                                        D < 0

    with phi(x) = (1 - exp(-x)) / x evaluated as -expm1(-x)/x.  Only exponentials of
    non-positive numbers appear and alpha + i w_k never vanishes for k >= 1, so it is
    stable for alpha * T from 0 (the blurred step) to far beyond 100 (s -> c / alpha).

    Parameters
    ----------
    irf : InstrumentResponse
    t_ps : array_like, shape (L,)
        Time axis, ps.
    delay_ps, alpha_per_ps : array_like, broadcast shape (...,)
        Onset (ps; the response's reference instant at the onset) and attenuation
        (1/ps, >= 0) of each atom.
    normalization : {"peak", "area"}
        Divide by the response's peak (default; equals :func:`core.model.sss_kernel` for a
        Gaussian response) or not (area 1/alpha).
    derivatives : bool
        Also return the derivatives with respect to delay and alpha.

    Returns
    -------
    atoms : ndarray, shape (..., L)
    d_delay, d_alpha : ndarray, shape (..., L) (only with ``derivatives=True``)
        d/dd s(t - d) = alpha s - c (per ps) and d/dalpha s (ps), the latter from the
        alpha-derivative of the closed form above (with psi(x) = (1 - e^-x (1 + x)) / x**2
        for the k = 0 term).
    """
    delay, alpha = np.broadcast_arrays(np.asarray(delay_ps, np.float64), np.asarray(alpha_per_ps, np.float64))
    if not np.all(np.isfinite(alpha)) or np.any(alpha < 0):
        raise ResponseError("alpha_per_ps must be non-negative and finite")
    t, flat, lead, d, uniform = _positions(irf, t_ps, delay)
    al = alpha.reshape(-1)
    scale = _norm(irf, normalization)
    n, dt = irf.n_padded, irf.time_step_ps
    w = irf.angular_frequencies()
    x0 = irf._spectrum[0].real
    denom = al[:, None] + 1j * w[None, :]                                  # (A, K), k = 0 unused
    denom[:, 0] = 1.0
    qspec = irf._spectrum[None, :] / denom
    qspec[:, 0] = 0.0
    q0 = (2.0 / n) * qspec.real.sum(axis=1)                                # Q(0) = Q(B), (A,)
    big_d = d * dt                                                         # D in ps, (A, L)
    b = n * dt
    inside = (d >= 0) & (d <= n)
    after = d > n
    a_col = al[:, None]
    dd = np.clip(big_d, 0.0, b)
    e_in = np.exp(-a_col * dd)
    q = np.where(d < n, _shifted_eval(irf, qspec, d, uniform), q0[:, None])          # Q(B) = Q(0)
    s_in = q - e_in * q0[:, None] + (x0 / n) * dd * _one_minus_exp_over_x(a_col * dd)
    s_b = q0 * (1.0 - np.exp(-al * b)) + (x0 / n) * b * _one_minus_exp_over_x(al * b)      # (A,)
    tail = np.exp(-a_col * np.clip(big_d - b, 0.0, None))
    s = np.where(inside, s_in, 0.0) + np.where(after, s_b[:, None] * tail, 0.0)
    shape = lead + (t.size,)
    if not derivatives:
        return (s * scale).reshape(shape)
    c = render_shifted(irf, t, flat, normalization="area")                  # (A, L)
    d_delay = a_col * s - c
    rspec = irf._spectrum[None, :] / (denom * denom)
    rspec[:, 0] = 0.0
    r0 = (2.0 / n) * rspec.real.sum(axis=1)
    r = np.where(d < n, _shifted_eval(irf, rspec, d, uniform), r0[:, None])
    ds_in = -(r - e_in * r0[:, None]) + dd * e_in * q0[:, None] - (x0 / n) * dd * dd * _psi(a_col * dd)
    eb = np.exp(-al * b)
    ds_b = -(r0 * (1.0 - eb)) + b * eb * q0 - (x0 / n) * b * b * _psi(al * b)
    ds_after = tail * (ds_b[:, None] - np.clip(big_d - b, 0.0, None) * s_b[:, None])
    d_alpha = np.where(inside, ds_in, 0.0) + np.where(after, ds_after, 0.0)
    return (s * scale).reshape(shape), (d_delay * scale).reshape(shape), (d_alpha * scale).reshape(shape)
