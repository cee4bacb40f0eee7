"""Phasors of binned decays: the (g, s) coordinates of a phasor plot, with NumPy alone.

A phasor is the normalised Fourier coefficient of a decay at one frequency,

    g + i s = integral x(t) exp(i omega t) dt / integral x(t) dt,    omega = 2 pi f,

at ``f = harmonic / (L * time_bin_ps)``: harmonic 1 of the window of L bins, the convention of
fluorescence-lifetime imaging where the decay is taken as periodic with the window.  A single
exponential exp(-t / tau) starting at t = 0 lies on the universal semicircle (g - 1/2)^2 + s^2 =
1/4 at g = 1 / (1 + (omega tau)^2), s = omega tau g, and a mixture lies inside it at the
intensity-weighted mean of its components' phasors.

Time origin and the bins
------------------------
Bin ``k`` holds the signal integrated over ``[k dt, (k + 1) dt)`` (dt = ``time_bin_ps``), time
measured from the leading edge of bin 0 -- as a streak camera or a TCSPC histogram records it.
On the project's time axis (bin ``k`` centred at ``t0_ps + k dt``, see :mod:`core.model`) that
edge lies at ``t0_ps - dt / 2``.  A decay whose onset lies later, at ``onset_ps`` after that
edge, is rotated by ``omega * onset_ps``; :func:`phasor` takes the onset and rotates it back.

Binned sampling
---------------
The discrete sum over bins, ``B = sum_k b_k exp(i omega k dt)``, places each bin's content at
its leading edge.  With ``b_k`` the signal convolved with the bin's box and read at ``k dt``,

    B = X(omega) * sinc(omega dt / 2) * exp(-i omega dt / 2) / dt   (+ aliases at omega + 2 pi m / dt)

-- the box's transfer function relative to the bins' starts (relative to their centres it is
the real ``sinc(omega dt / 2)``).  :func:`phasor` divides it out: exact for a decay with no
content above the bins' Nyquist frequency (one smoothed by an instrument response of a bin or
more).  Plain sampling (``bin_correction=False``) lags by half a bin: exp(-t / 50 ps) at 2 ps bins
in a 512-bin window reads at a phase lifetime of 48.9 ps.  An ideal step-onset exponential
keeps an alias term: its corrected phase and modulation lifetimes are off by about
((dt / tau)^2 + (2 pi harmonic / L)^2) / 12 -- 1 % at dt / tau = 0.35 in a long window.

Decays that do not reach zero
-----------------------------
The sum runs over the window as if the signal were periodic with it.  A single exponential
cut at the window's end, repeated with period T = L dt, is (up to a scale) the steady state of a
pulse train at period T, so it reads at its own lifetime whatever T / tau.  For a mixture,
component i's weight is multiplied by 1 - exp(-T / tau_i): the fractions a laser at repetition
period T would give.  No further correction is made.

Shapes and units: profiles (..., L) of bin counts or any real numbers; ``time_bin_ps`` and
lifetimes in picoseconds; frequencies in cycles per picosecond.
"""
from __future__ import annotations

import math

import numpy as np

from core.errors import StreaklabError

__all__ = ["PhasorError", "phasor", "phasor_lifetime", "semicircle", "window_frequency_per_ps"]

#: float64 samples handled per block (bounds the temporary memory on large cubes)
_BLOCK_SAMPLES = 1 << 22


class PhasorError(StreaklabError, ValueError):
    """Input a phasor cannot be computed from; the message names the argument and the problem."""


def _positive_finite(value, name: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise PhasorError(f"{name} must be a positive finite number, got {value!r}") from None
    if isinstance(value, bool) or not (math.isfinite(number) and number > 0):
        raise PhasorError(f"{name} must be a positive finite number, got {value!r}")
    return number


def _harmonic(harmonic) -> int:
    if isinstance(harmonic, bool) or not isinstance(harmonic, (int, np.integer)) or harmonic < 1:
        raise PhasorError(f"harmonic must be an integer >= 1, got {harmonic!r}")
    return int(harmonic)


def window_frequency_per_ps(n_bins: int, time_bin_ps: float, harmonic: int = 1) -> float:
    """Frequency of ``harmonic`` of a window of ``n_bins`` bins: harmonic / (n_bins * time_bin_ps).

    Returns
    -------
    float, cycles per picosecond.
    """
    dt = _positive_finite(time_bin_ps, "time_bin_ps")
    h = _harmonic(harmonic)
    if isinstance(n_bins, bool) or not isinstance(n_bins, (int, np.integer)) or n_bins < 1:
        raise PhasorError(f"n_bins must be an integer >= 1, got {n_bins!r}")
    return h / (int(n_bins) * dt)


def phasor(profiles, time_bin_ps: float, *, harmonic: int = 1, axis: int = -1, onset_ps=0.0,
           bin_correction: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Phasor coordinates (g, s) of binned decays at a harmonic of the window.

    Parameters
    ----------
    profiles : array_like, shape (..., L)
        Real bin contents (counts or any real numbers; integer dtypes included), each bin the
        signal integrated over its width; bin ``k`` spans ``[k dt, (k + 1) dt)`` from the leading
        edge of bin 0.  Must be finite.
    time_bin_ps : float
        Bin width dt in picoseconds (> 0).
    harmonic : int
        Harmonic of the window (>= 1): the frequency is ``harmonic / (L * time_bin_ps)``.  The
        window needs L >= 2 * harmonic + 1 bins.
    axis : int
        The time axis of ``profiles`` (default the last).
    onset_ps : float or array_like broadcastable to ``profiles`` without ``axis``
        Time of the decay's onset (the excitation) after the leading edge of bin 0, in ps; the
        phasor is rotated back by ``omega * onset_ps``.  Default 0: the decay starts with bin 0.
    bin_correction : bool
        Divide out the bins' transfer function ``sinc(omega dt / 2) exp(-i omega dt / 2)``
        (default).  False gives the plain sampled phasor (each bin's content at its start), the
        coordinates of ``phasorpy.phasor.phasor_from_signal``.

    Returns
    -------
    g, s : ndarray, shape ``profiles.shape`` without ``axis``, float64
        Real and imaginary phasor coordinates (dimensionless; s > 0 for a decay).  NaN where a
        profile's bins sum to zero (an empty pixel), without a warning.

    Raises
    ------
    PhasorError
        A non-positive or non-finite ``time_bin_ps``, a harmonic below 1 or above the window's
        Nyquist limit, non-real or non-finite samples (the message counts the profiles that hold
        them), a non-finite onset, or an onset that does not broadcast.

    Notes
    -----
    The sums run over blocks of profiles with a matrix product: no loop per pixel.  See the module
    docstring for the bin correction and the periodic-window convention.
    """
    h = _harmonic(harmonic)
    dt = _positive_finite(time_bin_ps, "time_bin_ps")
    x = np.asarray(profiles)
    if x.dtype.kind not in "uif":
        raise PhasorError(f"profiles must be real numbers, got dtype {x.dtype}")
    if x.ndim < 1:
        raise PhasorError("profiles must have a time axis, got a scalar")
    try:
        x = np.moveaxis(x, axis, -1)
    except np.exceptions.AxisError:
        raise PhasorError(f"axis {axis} is out of range for profiles of shape {np.shape(profiles)}") from None
    n_bins = x.shape[-1]
    if n_bins < 2 * h + 1:
        raise PhasorError(f"harmonic {h} needs at least {2 * h + 1} time bins, the profiles have {n_bins}")
    out_shape = x.shape[:-1]
    onset = np.asarray(onset_ps, dtype=float) if np.ndim(onset_ps) else float(onset_ps)
    if not np.all(np.isfinite(onset)):
        raise PhasorError(f"onset_ps must be finite, got {onset_ps!r}")
    try:
        onset = np.broadcast_to(onset, out_shape)
    except ValueError:
        raise PhasorError(f"onset_ps of shape {np.shape(onset_ps)} does not broadcast to the "
                          f"profiles' pixel shape {out_shape}") from None

    flat = x.reshape(-1, n_bins)
    angle = 2.0 * np.pi * h * np.arange(n_bins) / n_bins
    basis = np.stack([np.ones(n_bins), np.cos(angle), np.sin(angle)], axis=1)  # (L, 3)
    sums = np.empty((flat.shape[0], 3))
    block = max(1, _BLOCK_SAMPLES // n_bins)
    bad = 0
    for start in range(0, flat.shape[0], block):
        part = flat[start:start + block].astype(np.float64, copy=False)
        finite = np.isfinite(part).all(axis=1)
        if not finite.all():
            bad += int(np.count_nonzero(~finite))
            continue
        sums[start:start + block] = part @ basis
    if bad:
        raise PhasorError(f"{bad} of {flat.shape[0]} profiles hold NaN or inf samples; "
                          "a phasor needs finite bins (mask or fill them first)")

    with np.errstate(divide="ignore", invalid="ignore"):
        z = (sums[:, 1] + 1j * sums[:, 2]) / sums[:, 0]
    z[sums[:, 0] == 0] = complex(np.nan, np.nan)  # both coordinates, not nan + 0j
    omega = 2.0 * np.pi * h / (n_bins * dt)
    if bin_correction:
        half = omega * dt / 2.0
        z *= np.exp(1j * half) / np.sinc(half / np.pi)  # np.sinc(x) = sin(pi x) / (pi x)
    z = z.reshape(out_shape)
    if np.any(onset != 0):
        z = z * np.exp(-1j * omega * onset)
    return np.array(z.real), np.array(z.imag)  # copies: contiguous, 0-d for one profile


def phasor_lifetime(g, s, frequency_per_ps) -> tuple[np.ndarray, np.ndarray]:
    """Apparent single lifetimes of phasor coordinates: from the phase and from the modulation.

    Parameters
    ----------
    g, s : array_like, broadcastable
        Phasor coordinates.
    frequency_per_ps : float or array_like
        The phasor's frequency in cycles per ps (``window_frequency_per_ps``), > 0.

    Returns
    -------
    tau_phase_ps, tau_modulation_ps : ndarray, float64, picoseconds
        ``s / (omega g)`` and ``sqrt(1 / (g^2 + s^2) - 1) / omega`` with omega = 2 pi f.  Equal
        for a point on the universal semicircle.  The phase lifetime is inf at g = 0 (s > 0) and
        negative for g < 0; the modulation lifetime is NaN where g^2 + s^2 > 1 (no single
        exponential has such a modulation).  No warnings.
    """
    f = np.asarray(frequency_per_ps, dtype=float)
    if not np.all(np.isfinite(f) & (f > 0)):
        raise PhasorError(f"frequency_per_ps must be positive and finite, got {frequency_per_ps!r}")
    g = np.asarray(g, dtype=float)
    s = np.asarray(s, dtype=float)
    omega = 2.0 * np.pi * f
    with np.errstate(divide="ignore", invalid="ignore"):
        tau_phase = s / (omega * g)
        tau_mod = np.sqrt(1.0 / (g * g + s * s) - 1.0) / omega
    return tau_phase, tau_mod


def semicircle(n_points: int = 101, *, lifetimes_ps=None, frequency_per_ps: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Points (g, s) on the universal semicircle, the phasors of single exponentials.

    Parameters
    ----------
    n_points : int
        Number of equally spaced points from (0, 0) (tau = inf) to (1, 0) (tau = 0), >= 2;
        ignored when ``lifetimes_ps`` is given.
    lifetimes_ps : array_like, optional
        Lifetimes (ps, >= 0) whose phasors to return instead (tick marks on a plot); needs
        ``frequency_per_ps``.
    frequency_per_ps : float, optional
        The phasor's frequency in cycles per ps.

    Returns
    -------
    g, s : ndarray, shape (n_points,) or ``lifetimes_ps``'s shape, float64
        ``g = 1 / (1 + (omega tau)^2)``, ``s = omega tau g``.
    """
    if lifetimes_ps is None:
        if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or n_points < 2:
            raise PhasorError(f"n_points must be an integer >= 2, got {n_points!r}")
        angle = np.linspace(np.pi, 0.0, int(n_points))
        return 0.5 + 0.5 * np.cos(angle), 0.5 * np.sin(angle)
    if frequency_per_ps is None:
        raise PhasorError("semicircle(lifetimes_ps=...) needs frequency_per_ps")
    f = _positive_finite(frequency_per_ps, "frequency_per_ps")
    tau = np.asarray(lifetimes_ps, dtype=float)
    if not np.all(np.isfinite(tau) & (tau >= 0)):
        raise PhasorError(f"lifetimes_ps must be finite and >= 0, got {lifetimes_ps!r}")
    wt = 2.0 * np.pi * f * tau
    g = 1.0 / (1.0 + wt * wt)
    return g, wt * g
