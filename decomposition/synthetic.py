"""Synthetic transient time profiles with known ground truth (the paper's Fig. 3).

Scenes (kinds, parameter ranges, presets, regimes) are drawn by :mod:`decomposition.scenes`, noise
by :mod:`decomposition.synthetic_noise`; this module renders them into profiles and cubes and
keeps all of their public names.

A synthetic pixel holds any subset of the component classes

    d    direct reflection (a Gaussian-blurred delta)
    s    subsurface scattering (sss; a Gaussian-blurred delayed decaying exponential)
    r2, r3, ...  inter-reflections (Gaussian-blurred deltas after the direct one)

rendered with :func:`core.model.render_components`, plus one of the paper's three
noise types at an exact noise-to-signal ratio.  The kinds of the paper's Fig. 3 are

    "a" = d + s,   "b" = d + s + r2,   "c" = d + s + r2 + r3,

and any other subset is written with ``+`` (``"d+r2"``, ``"s"``, ``"d+s+r2+r3+r4"``).
Inter-reflections are numbered by order of arrival, so ``r3`` needs ``r2``; in the parameter
dict the inter-reflection columns are in that order (column 0 = r2), which is the order a
decomposition reports them in.

Scene parameters (drawn uniformly, or log-uniformly where a preset says so, from the ranges
of :class:`SceneRanges`, documented there; named presets in :data:`SCENE_PRESETS`: ``legacy``,
the default, and ``paper``, the paper's parameter space) follow eq. (2): one camera PSF width sigma per pixel shared by all of its components;
the direct reflection arrives first, the sss onset shortly after it (light enters the surface
where it is directly lit), and the inter-reflections later, each at least ``min_gap_sigma``
PSF widths after the previous Gaussian component and every Gaussian component at least
``edge_sigma`` widths inside the time window.  :func:`regime_variables` gives each pixel's
regime (sss/direct peak ratio, sss onset in PSF widths, sigma in bins, number of
inter-reflections).

Rendering: point samples of the model at the bin centres (the solver's own model), or
(``bin_integrated=True``) each bin the mean of the continuous model over its width, in closed
form (:func:`render_bin_integrated`), as a detector bin records it.

Noise: one of the paper's three fundamental types ("photon", "detector" (pink), "white"; see
:mod:`decomposition.synthetic_noise`), rescaled per pixel to the exact requested NSR.
Everything is seeded: the same seed gives the same arrays.  The scene
and the noise use separate streams spawned from the seed, so the same seed gives the same
scene whatever the noise type and NSR.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import special

from core.model import render_components, sss_kernel, time_axis_ps

from .scenes import (FIG3_KINDS, SCENE_PRESETS, SceneRanges, draw_params, parse_kind, parse_kinds,
                     regime_variables, scene_ranges)
from .synthetic_noise import NOISE_TYPES, _noise_type, add_noise, noise_realisation

__all__ = [
    "FIG3_KINDS",
    "NOISE_TYPES",
    "SceneRanges",
    "SCENE_PRESETS",
    "scene_ranges",
    "SyntheticData",
    "regime_variables",
    "render_bin_integrated",
    "parse_kind",
    "parse_kinds",
    "draw_params",
    "noise_realisation",
    "add_noise",
    "make_profiles",
    "make_cube",
]
@dataclass(frozen=True)
class SyntheticData:
    """Synthetic profiles with their ground truth; leading shape ``S`` (``(N,)`` or ``(ny, nx)``).

    Attributes
    ----------
    params : dict of ndarray
        Ground-truth parameters, keys of :mod:`core.model`, shapes S / S + (R,), NaN = absent.
    components : dict of ndarray
        Clean rendered classes: ``direct`` S + (L,), ``sss`` S + (L,), ``interreflections`` S + (R, L).
    clean : ndarray, S + (L,)
        Sum of the components.
    noisy : ndarray, S + (L,)
        ``clean`` plus the noise realisation.
    kinds : ndarray of str, S
        Component set of each pixel in canonical form (``"d+s+r2"``).
    time_bin_ps, t0_ps : float
        Time axis: bin i at ``t0_ps + i * time_bin_ps`` (ps).
    nsr : float
        Noise-to-signal ratio ||noise|| / ||clean|| of every pixel.
    noise : str
        Noise type (``"white"``, ``"pink"``, ``"photon"`` or ``"none"``).
    seed : int or None
    ranges : SceneRanges
        The ranges the scene was drawn from.
    bin_integrated : bool
        Whether the profiles are bin averages of the continuous model (else point samples).
    """

    params: dict
    components: dict
    clean: np.ndarray
    noisy: np.ndarray
    kinds: np.ndarray
    time_bin_ps: float
    t0_ps: float
    nsr: float
    noise: str
    seed: int | None = None
    ranges: SceneRanges = field(default_factory=SceneRanges)

    bin_integrated: bool = False

    @property
    def noise_profile(self) -> np.ndarray:
        return self.noisy - self.clean

    @property
    def regimes(self) -> dict:
        """Per-pixel regime variables of the ground truth (see :func:`regime_variables`)."""
        return regime_variables(self.params, self.time_bin_ps)


# --------------------------------------------------------------------------- scene parameters

def _rng(seed) -> tuple[np.random.Generator, np.random.Generator]:
    """Two independent streams (scene, noise) from one seed."""
    if isinstance(seed, np.random.Generator):
        scene, noise = seed.spawn(2)
        return scene, noise
    ss = np.random.SeedSequence(seed)
    scene, noise = ss.spawn(2)
    return np.random.default_rng(scene), np.random.default_rng(noise)


# --------------------------------------------------------------------------- bin-integrated rendering

def _erfc_diff(x1, x2):
    """erf(x2) - erf(x1) for x1 <= x2, computed from erfc on the side away from zero (no
    cancellation in either tail)."""
    lo = x1 > 0
    hi = x2 < 0
    out = special.erf(x2) - special.erf(x1)
    out = np.where(lo, special.erfc(x1) - special.erfc(x2), out)
    return np.where(hi, special.erfc(-x2) - special.erfc(-x1), out)


def render_bin_integrated(params: dict, n_bins: int, time_bin_ps: float = 2.0,
                          t0_ps: float | None = None) -> dict[str, np.ndarray]:
    """Components averaged over each bin's width, in closed form.

    A detector bin integrates the signal over its width T; bin ``i`` holds the mean of the
    continuous model over ``[t_i - T/2, t_i + T/2]``.  For the Gaussian g with delay d,

        mean_i = sigma sqrt(pi/2) [erf(z2) - erf(z1)] / T,   z = (t -+ T/2 - d) / (sigma sqrt 2),

    and, since the sss kernel obeys dh/dt = g - alpha h,

        mean_i = ([G](t_i - T/2 .. t_i + T/2) - [h](...)) / (alpha T),   G(t) = integral of g up to t,

    both with erf differences taken on the tail side (see ``_erfc_diff``).  Independent of the
    quadrature in :mod:`core.model`, so it can check it.

    Parameters
    ----------
    params : dict of ndarray
        Keys of :mod:`core.model`, shapes S and S + (R,); NaN = absent.  sss
        attenuations must be positive.
    n_bins, time_bin_ps, t0_ps
        Time axis (see :func:`core.model.time_axis_ps`).

    Returns
    -------
    dict with ``direct`` S + (L,), ``sss`` S + (L,), ``interreflections`` S + (R, L).
    """
    T = float(time_bin_ps)
    t = time_axis_ps(n_bins, T, t0_ps)
    sq2 = np.sqrt(2.0)
    c = np.sqrt(np.pi / 2.0)

    def gauss(delay, amp, sigma):
        delay, amp, sigma = (np.asarray(v, np.float64)[..., None] for v in (delay, amp, sigma))
        on = np.isfinite(delay) & np.isfinite(amp) & np.isfinite(sigma)
        s = np.where(on, sigma, 1.0)
        tt = t - np.where(on, delay, 0.0)
        m = s * c * _erfc_diff((tt - T / 2) / (s * sq2), (tt + T / 2) / (s * sq2)) / T
        return np.where(on, np.where(on, amp, 0.0) * m, 0.0)

    def sss(delay, amp, alpha, sigma):
        delay, amp, alpha, sigma = (np.asarray(v, np.float64)[..., None] for v in (delay, amp, alpha, sigma))
        on = np.isfinite(delay) & np.isfinite(amp) & np.isfinite(sigma) & np.isfinite(alpha) & (alpha > 0)
        s, a = np.where(on, sigma, 1.0), np.where(on, alpha, 1.0)
        tt = np.broadcast_to(t - np.where(on, delay, 0.0), np.broadcast_shapes(on.shape, t.shape))
        s, a = np.broadcast_to(s, tt.shape), np.broadcast_to(a, tt.shape)
        dg = s * c * _erfc_diff((tt - T / 2) / (s * sq2), (tt + T / 2) / (s * sq2))
        dh = sss_kernel(tt + T / 2, s, a) - sss_kernel(tt - T / 2, s, a)
        m = np.maximum((dg - dh) / (a * T), 0.0)
        return np.where(on, np.where(on, amp, 0.0) * m, 0.0)

    out = {"direct": gauss(params["direct_delay_ps"], params["direct_amplitude"], params["direct_sigma_ps"]),
           "sss": sss(params["sss_delay_ps"], params["sss_amplitude"], params["sss_alpha_per_ps"],
                      params["sss_sigma_ps"]),
           "interreflections": gauss(params["ir_delay_ps"], params["ir_amplitude"], params["ir_sigma_ps"])}
    return out


# --------------------------------------------------------------------------- data sets

def make_profiles(n_pixels: int, n_bins: int, *, nsr: float = 0.0, noise: str = "white", seed=None,
                  kinds=("a", "b", "c"), time_bin_ps: float = 2.0, t0_ps: float | None = None,
                  ranges: SceneRanges | None = None, bin_integrated: bool = False) -> SyntheticData:
    """``n_pixels`` synthetic profiles (N, L) with ground truth; see the module docstring.

    Parameters
    ----------
    n_pixels, n_bins : int
    nsr : float
        Noise-to-signal ratio of every pixel (>= 0).
    noise : str
        "white", "pink", "photon" (aliases "fluctuation", "detector", "poisson") or "none".
    seed : int, numpy.random.Generator or None
        Same seed -> same scene and same noise; the scene does not depend on ``noise``/``nsr``.
    kinds : str or sequence
        Component sets assigned in equal shares (default the Fig. 3 kinds a, b, c).
    time_bin_ps, t0_ps : float
        Time axis (ps); ``t0_ps`` defaults to ``time_bin_ps``.
    ranges : SceneRanges or str, optional
        Scene ranges, or the name of a preset of :data:`SCENE_PRESETS` (``"legacy"``, the
        default, or ``"paper"``).
    bin_integrated : bool
        Render each bin as the mean of the continuous model over its width
        (:func:`render_bin_integrated`, what a detector bin records) instead of a point sample
        at its centre (the solver's own model).
    """
    kind = _noise_type(noise)
    if float(nsr) > 0 and kind == "none":
        raise ValueError("noise 'none' needs nsr = 0")
    ranges = scene_ranges(ranges)
    t0 = float(time_bin_ps) if t0_ps is None else float(t0_ps)
    scene_rng, noise_rng = _rng(seed)
    params, labels = draw_params(n_pixels, n_bins, kinds=kinds, time_bin_ps=time_bin_ps, t0_ps=t0,
                                 rng=scene_rng, ranges=ranges)
    if bin_integrated:
        comps = render_bin_integrated(params, n_bins, time_bin_ps, t0)
    else:
        comps = render_components(params, n_bins, time_bin_ps, t0)
    clean = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    if kind == "none" or float(nsr) == 0:
        noisy = clean.copy()
    else:
        noisy = add_noise(clean, nsr, kind, rng=noise_rng)
    return SyntheticData(params=params, components=comps, clean=clean, noisy=noisy, kinds=labels,
                         time_bin_ps=float(time_bin_ps), t0_ps=t0, nsr=float(nsr), noise=kind,
                         seed=seed if isinstance(seed, (int, np.integer)) else None, ranges=ranges,
                         bin_integrated=bool(bin_integrated))


def make_cube(ny: int, nx: int, nt: int, *, nsr: float = 0.0, noise: str = "white", seed=None,
              time_bin_ps: float = 2.0, t0_ps: float | None = None, kinds=("a", "b", "c"),
              ranges: SceneRanges | None = None, bin_integrated: bool = False) -> SyntheticData:
    """A synthetic (ny, nx, nt) cube with ground truth: :func:`make_profiles` reshaped.

    Returns
    -------
    SyntheticData with leading shape (ny, nx): ``noisy`` is the cube (y, x, t), ``params``
    maps (y, x) / (y, x, R), ``components`` (y, x, t) / (y, x, R, t).
    """
    ny, nx = int(ny), int(nx)
    if ny <= 0 or nx <= 0 or int(nt) <= 1:
        raise ValueError(f"cube shape must be positive with at least 2 time bins, got {(ny, nx, nt)}")
    d = make_profiles(ny * nx, nt, nsr=nsr, noise=noise, seed=seed, kinds=kinds, time_bin_ps=time_bin_ps,
                      t0_ps=t0_ps, ranges=ranges, bin_integrated=bin_integrated)

    def rs(a):
        return a.reshape((ny, nx) + a.shape[1:])

    return replace(d, params={k: rs(v) for k, v in d.params.items()},
                   components={k: rs(v) for k, v in d.components.items()},
                   clean=rs(d.clean), noisy=rs(d.noisy), kinds=rs(d.kinds))
