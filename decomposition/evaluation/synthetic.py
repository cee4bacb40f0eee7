"""Synthetic transient time profiles with known ground truth (the paper's Fig. 3).

Scenes (kinds, parameter ranges, presets, regimes) are drawn by :mod:`decomposition.evaluation.scenes`, noise
by :mod:`decomposition.evaluation.synthetic_noise`; this module renders them into profiles and cubes and
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
:mod:`decomposition.evaluation.synthetic_noise`), rescaled per pixel to the exact requested NSR.
Effects beyond the paper's model, on request (:mod:`decomposition.evaluation.synthetic_effects`): a
non-Gaussian instrument response (``response=``), a constant background (``background=``),
true photon counts at a chosen level (``photons_per_pixel=``, integer Poisson counts instead
of the NSR noise), a weak late echo (``echo_ratio=``) and a direct reflection before the
window's first bin (``direct_before_window_ps=``).  Their defaults add nothing.

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
from .synthetic_effects import (SyntheticEffects, count_photons, place_direct_before_window, render_with_response,
                                response_sigma_ps, set_echo)
from .synthetic_noise import NOISE_TYPES, _noise_type, add_noise, noise_realisation

__all__ = [
    "FIG3_KINDS",
    "NOISE_TYPES",
    "SceneRanges",
    "SCENE_PRESETS",
    "scene_ranges",
    "SyntheticData",
    "SyntheticEffects",
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
        Sum of the components plus the background: the expected value of ``noisy``.
    noisy : ndarray, S + (L,)
        ``clean`` plus the noise realisation; int64 photon counts with ``photons_per_pixel``.
    kinds : ndarray of str, S
        Component set of each pixel in canonical form (``"d+s+r2"``).
    time_bin_ps, t0_ps : float
        Time axis: bin i at ``t0_ps + i * time_bin_ps`` (ps).
    nsr : float
        Noise-to-signal ratio ||noise|| / ||clean|| of every pixel (NaN for photon counts).
    noise : str
        Noise type (``"white"``, ``"pink"``, ``"photon"``, ``"none"``, or ``"counts"`` for
        true photon counts).
    seed : int or None
    ranges : SceneRanges
        The ranges the scene was drawn from.
    bin_integrated : bool
        Whether the profiles are bin averages of the continuous model (else point samples).
    response : InstrumentResponse or None
        The instrument response the components were rendered with (None: each pixel's
        Gaussian of ``*_sigma_ps``).
    background : ndarray, S
        Constant level of every bin of each pixel (included in ``clean``), in the data's units.
    photons_per_pixel : float or None
        Expected signal photons per pixel when ``noisy`` holds photon counts (then every
        amplitude, component, ``clean`` and ``background`` is in expected counts per bin).
    counts_per_unit : ndarray, S, or None
        Counts per signal unit of each pixel (the factor the scene was scaled by to counts).
    echo : ndarray of bool, S, or None
        Pixels whose latest inter-reflection was set to ``echo_ratio`` x the direct.
    effects : SyntheticEffects
        The effect options the data were made with.
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
    response: object = None
    background: np.ndarray | float = 0.0
    photons_per_pixel: float | None = None
    counts_per_unit: np.ndarray | None = None
    echo: np.ndarray | None = None
    effects: SyntheticEffects = field(default_factory=SyntheticEffects)

    @property
    def noise_profile(self) -> np.ndarray:
        return self.noisy - self.clean

    @property
    def regimes(self) -> dict:
        """Per-pixel regime variables of the ground truth (see :func:`regime_variables`)."""
        return regime_variables(self.params, self.time_bin_ps)


# --------------------------------------------------------------------------- scene parameters

def _rng(seed, n: int = 2) -> tuple[np.random.Generator, ...]:
    """``n`` independent streams (scene, noise[, effects]) from one seed; the first two do not
    depend on ``n``."""
    if isinstance(seed, np.random.Generator):
        return tuple(seed.spawn(n))
    return tuple(np.random.default_rng(c) for c in np.random.SeedSequence(seed).spawn(n))


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
                  ranges: SceneRanges | None = None, bin_integrated: bool | None = None, response=None,
                  background: float = 0.0, photons_per_pixel: float | None = None,
                  echo_ratio: float | None = None, direct_before_window_ps=None) -> SyntheticData:
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
    bin_integrated : bool, optional
        Render each bin as the mean of the continuous model over its width
        (:func:`render_bin_integrated`, what a detector bin records) instead of a point sample
        at its centre (the solver's own model).  Default: True with ``photons_per_pixel``
        (counts are bin integrals), else False.
    response : core.irf.InstrumentResponse, optional
        Render every component with this instrument response instead of the Gaussian PSF
        (see :mod:`decomposition.evaluation.synthetic_effects`).  The scene is then laid out with one
        width for every pixel, the response's FWHM / 2.355, which is what the
        ``*_sigma_ps`` keys of the truth hold.
    background : float
        Constant level added to every bin (>= 0, signal units; the direct amplitudes are
        0.5-1).  Included in ``clean``.
    photons_per_pixel : float, optional
        True photon counting instead of the NSR noise: ``noisy`` holds integer counts drawn
        from Poisson laws with the bin-integrated expected counts as means, scaled so that
        each pixel's expected signal photons (background excluded) are this number; the
        truth is scaled to expected counts.  Needs ``nsr = 0``.
    echo_ratio : float, optional
        Each pixel's latest inter-reflection at this fraction (0-1] of its direct's amplitude
        (a weak late echo); the kinds must hold an inter-reflection.
    direct_before_window_ps : float or (lo, hi), optional
        Put each direct reflection this far (ps; a range is drawn uniformly per pixel)
        before the first bin, its sss onset following it: a direct truncated at the
        window's start.

    The default of every effect option adds nothing: the same seed gives the same arrays as
    without them.  The effects are validated by :class:`SyntheticEffects`.
    """
    kind = _noise_type(noise)
    if float(nsr) > 0 and kind == "none":
        raise ValueError("noise 'none' needs nsr = 0")
    effects = SyntheticEffects(response=response, background=background, photons_per_pixel=photons_per_pixel,
                               echo_ratio=echo_ratio, direct_before_window_ps=direct_before_window_ps)
    if effects.counting and float(nsr) > 0:
        raise ValueError(f"photons_per_pixel sets the noise (Poisson counts): leave nsr at 0, got nsr={nsr!r}")
    if bin_integrated is None:
        bin_integrated = effects.counting
    ranges = scene_ranges(ranges)
    if effects.response is not None:
        width = response_sigma_ps(effects.response)
        ranges = replace(ranges, sigma_ps=(width, width))
    t0 = float(time_bin_ps) if t0_ps is None else float(t0_ps)
    streams = _rng(seed, 3 if effects.any else 2)
    scene_rng, noise_rng = streams[:2]
    params, labels = draw_params(n_pixels, n_bins, kinds=kinds, time_bin_ps=time_bin_ps, t0_ps=t0,
                                 rng=scene_rng, ranges=ranges)
    echo = None
    if effects.echo_ratio is not None:
        echo = set_echo(params, effects.echo_ratio)
    if effects.direct_before_window_ps is not None:
        place_direct_before_window(params, t0, effects.direct_before_window_ps, streams[2])
    if effects.response is not None:
        comps = render_with_response(params, n_bins, time_bin_ps, t0, effects.response,
                                     bin_integrated=bool(bin_integrated))
    elif bin_integrated:
        comps = render_bin_integrated(params, n_bins, time_bin_ps, t0)
    else:
        comps = render_components(params, n_bins, time_bin_ps, t0)
    signal = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    lead = signal.shape[:-1]
    lam = None
    if effects.counting:
        noisy, lam = count_photons(signal, effects.background, effects.photons_per_pixel, noise_rng)
        for key in ("direct_amplitude", "sss_amplitude"):
            params[key] = params[key] * lam
        params["ir_amplitude"] = params["ir_amplitude"] * lam[..., None]
        comps = {"direct": comps["direct"] * lam[..., None], "sss": comps["sss"] * lam[..., None],
                 "interreflections": comps["interreflections"] * lam[..., None, None]}
        back = effects.background * lam
        clean = signal * lam[..., None] + back[..., None]
        kind, nsr = "counts", float("nan")
    else:
        back = np.full(lead, effects.background)
        clean = signal + effects.background if effects.background > 0 else signal
        if kind == "none" or float(nsr) == 0:
            noisy = clean.copy()
        else:
            noisy = add_noise(clean, nsr, kind, rng=noise_rng)
    return SyntheticData(params=params, components=comps, clean=clean, noisy=noisy, kinds=labels,
                         time_bin_ps=float(time_bin_ps), t0_ps=t0, nsr=float(nsr), noise=kind,
                         seed=seed if isinstance(seed, (int, np.integer)) else None, ranges=ranges,
                         bin_integrated=bool(bin_integrated), response=effects.response, background=back,
                         photons_per_pixel=effects.photons_per_pixel, counts_per_unit=lam, echo=echo,
                         effects=effects)


def make_cube(ny: int, nx: int, nt: int, *, nsr: float = 0.0, noise: str = "white", seed=None,
              time_bin_ps: float = 2.0, t0_ps: float | None = None, kinds=("a", "b", "c"),
              ranges: SceneRanges | None = None, bin_integrated: bool | None = None,
              **effects) -> SyntheticData:
    """A synthetic (ny, nx, nt) cube with ground truth: :func:`make_profiles` reshaped.

    ``effects``: the effect options of :func:`make_profiles` (``response``, ``background``,
    ``photons_per_pixel``, ``echo_ratio``, ``direct_before_window_ps``).

    Returns
    -------
    SyntheticData with leading shape (ny, nx): ``noisy`` is the cube (y, x, t), ``params``
    maps (y, x) / (y, x, R), ``components`` (y, x, t) / (y, x, R, t).
    """
    ny, nx = int(ny), int(nx)
    if ny <= 0 or nx <= 0 or int(nt) <= 1:
        raise ValueError(f"cube shape must be positive with at least 2 time bins, got {(ny, nx, nt)}")
    d = make_profiles(ny * nx, nt, nsr=nsr, noise=noise, seed=seed, kinds=kinds, time_bin_ps=time_bin_ps,
                      t0_ps=t0_ps, ranges=ranges, bin_integrated=bin_integrated, **effects)

    def rs(a):
        return a.reshape((ny, nx) + a.shape[1:])

    return replace(d, params={k: rs(v) for k, v in d.params.items()},
                   components={k: rs(v) for k, v in d.components.items()},
                   clean=rs(d.clean), noisy=rs(d.noisy), kinds=rs(d.kinds), background=rs(d.background),
                   counts_per_unit=None if d.counts_per_unit is None else rs(d.counts_per_unit),
                   echo=None if d.echo is None else rs(d.echo))
