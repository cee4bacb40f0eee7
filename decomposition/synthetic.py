"""Synthetic transient time profiles with known ground truth (the paper's Fig. 3).

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

Noise (the paper's three fundamental types):

    "photon"    Poisson (shot) noise: counts ~ Poisson(lambda * p) / lambda, variance
                proportional to the clean signal p.  lambda (photons per unit signal) is
                chosen per pixel so that the expected NSR is the requested one.
    "detector"  pink noise: white Gaussian noise shaped in the Fourier domain by 1/sqrt(f),
                so its power spectrum falls as 1/f (zero mean: the DC term is removed).
    "white"     fluctuation noise: independent Gaussian samples.

Each realisation is then rescaled per pixel so that NSR = ||noise||_2 / ||clean||_2 holds
exactly (to rounding).  Everything is seeded: the same seed gives the same arrays.  The scene
and the noise use separate streams spawned from the seed, so the same seed gives the same
scene whatever the noise type and NSR.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import special

from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, render_components, sss_kernel, time_axis_ps

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

FIG3_KINDS = {"a": "d+s", "b": "d+s+r2", "c": "d+s+r2+r3"}
NOISE_TYPES = ("white", "pink", "photon")
_NOISE_ALIASES = {
    "white": "white", "fluctuation": "white", "gaussian": "white",
    "pink": "pink", "detector": "pink",
    "photon": "photon", "poisson": "photon", "shot": "photon",
    "none": "none",
}
# Above this expected count per bin the Poisson law is replaced by its normal limit
# (numpy's Poisson sampler refuses means above ~1e18; the two agree to ~1e-4 here).
_POISSON_NORMAL_LIMIT = 1e8


@dataclass(frozen=True)
class SceneRanges:
    """Ranges (inclusive bounds of uniform draws) of the synthetic scene parameters.

    Attributes
    ----------
    sigma_ps : (lo, hi)
        Camera PSF standard deviation in ps, one per pixel, shared by all its components.
        Default (2, 6): a 2 ps streak camera, inside the paper's dictionary range 1-10 ps.
    alpha_per_ps : (lo, hi)
        sss attenuation coefficient in 1/ps.  Default: the paper's range 0.01-0.05.
    direct_amplitude : (lo, hi)
        Peak height of the direct reflection (signal units).
    sss_relative_peak : (lo, hi)
        Peak of the rendered sss component as a fraction of the direct peak.
    ir_relative_peak : (lo, hi)
        Peak of each inter-reflection as a fraction of the direct peak.
    direct_position : (lo, hi)
        Direct delay as a fraction of the usable window (after the leading edge margin).
    sss_onset_sigma : (lo, hi)
        sss onset after the direct delay, in PSF widths.
    min_gap_sigma : float
        Least separation between consecutive Gaussian components (d, r2, r3, ...), in PSF widths.
    edge_sigma : float
        Least distance of every Gaussian component from either end of the window, in PSF widths.
    max_gap_sigma : float or None
        Largest separation between consecutive Gaussian components, in PSF widths: each gap is
        drawn uniformly from ``[min_gap_sigma, max_gap_sigma]`` (the excess over the minimum
        shrunk in proportion where the window cannot hold the chain).  None: the window left over
        after the minimum gaps is shared among the gaps at random (the legacy generator).
    log_uniform : tuple of str
        Names of the ``(lo, hi)`` ranges above drawn uniformly in log (even coverage of every
        decade; both bounds must then be positive).  Default: none.

    The named presets are in :data:`SCENE_PRESETS` (``"legacy"``, the default ranges, and
    ``"paper"``, the paper's parameter space); :func:`scene_ranges` looks one up by name.
    """

    sigma_ps: tuple[float, float] = (2.0, 6.0)
    alpha_per_ps: tuple[float, float] = (0.01, 0.05)
    direct_amplitude: tuple[float, float] = (0.5, 1.0)
    sss_relative_peak: tuple[float, float] = (0.2, 0.5)
    ir_relative_peak: tuple[float, float] = (0.2, 0.5)
    direct_position: tuple[float, float] = (0.0, 0.2)
    sss_onset_sigma: tuple[float, float] = (0.0, 2.0)
    min_gap_sigma: float = 6.0
    edge_sigma: float = 4.0
    max_gap_sigma: float | None = None
    log_uniform: tuple[str, ...] = ()

    def __post_init__(self):
        for name in ("sigma_ps", "alpha_per_ps", "direct_amplitude", "sss_relative_peak",
                     "ir_relative_peak", "direct_position", "sss_onset_sigma"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
                raise ValueError(f"SceneRanges.{name} must be a finite (lo, hi) with lo <= hi, got {(lo, hi)}")
        if self.sigma_ps[0] <= 0 or self.alpha_per_ps[0] <= 0 or self.direct_amplitude[0] <= 0:
            raise ValueError("SceneRanges: sigma_ps, alpha_per_ps and direct_amplitude must be positive")
        if not 0 <= self.direct_position[0] <= self.direct_position[1] <= 1:
            raise ValueError("SceneRanges.direct_position must lie in [0, 1]")
        if self.min_gap_sigma <= 0 or self.edge_sigma < 0:
            raise ValueError("SceneRanges: min_gap_sigma must be positive and edge_sigma non-negative")
        if self.max_gap_sigma is not None and not (np.isfinite(self.max_gap_sigma)
                                                   and self.max_gap_sigma >= self.min_gap_sigma):
            raise ValueError("SceneRanges.max_gap_sigma must be finite and >= min_gap_sigma (or None)")
        object.__setattr__(self, "log_uniform", tuple(self.log_uniform))
        for name in self.log_uniform:
            if name not in _RANGE_NAMES:
                raise ValueError(f"SceneRanges.log_uniform: {name!r} is not one of {_RANGE_NAMES}")
            if getattr(self, name)[0] <= 0:
                raise ValueError(f"SceneRanges.{name} is drawn log-uniformly and needs a positive lower bound")

    def draw(self, rng, name: str, size):
        """Uniform (or log-uniform, see ``log_uniform``) draws from the range ``name``."""
        lo, hi = (float(b) for b in getattr(self, name))
        if hi <= lo:
            return np.full(size, lo)
        if name in self.log_uniform:
            return np.exp(rng.uniform(np.log(lo), np.log(hi), size))
        return rng.uniform(lo, hi, size)


_RANGE_NAMES = ("sigma_ps", "alpha_per_ps", "direct_amplitude", "sss_relative_peak", "ir_relative_peak",
                "direct_position", "sss_onset_sigma")

#: Named scene presets.  ``"legacy"``: the ranges of the original generator (sigma 2-6 ps,
#: sss and inter-reflection peaks 0.2-0.5 of the direct's, sss onset 0-2 sigma after the
#: direct, Gaussian components >= 6 sigma apart).  ``"paper"``: the paper's parameter space
#: -- sigma 1-10 ps (its dictionary range), alpha 0.01-0.05 /ps, sss peak 0.05-3 x and
#: inter-reflection peaks 0.01-1 x the direct's (both log-uniform), sss onset 0-3 sigma after
#: the direct, consecutive Gaussian components 4-16 sigma apart.
SCENE_PRESETS = {
    "legacy": SceneRanges(),
    "paper": SceneRanges(sigma_ps=(1.0, 10.0), alpha_per_ps=(0.01, 0.05), direct_amplitude=(0.5, 1.0),
                         sss_relative_peak=(0.05, 3.0), ir_relative_peak=(0.01, 1.0),
                         direct_position=(0.0, 0.2), sss_onset_sigma=(0.0, 3.0), min_gap_sigma=4.0,
                         max_gap_sigma=16.0, edge_sigma=4.0,
                         log_uniform=("sss_relative_peak", "ir_relative_peak")),
}


def scene_ranges(ranges=None) -> SceneRanges:
    """``ranges`` as a :class:`SceneRanges`: a preset name of :data:`SCENE_PRESETS`, an instance,
    or None (the default ranges, ``"legacy"``)."""
    if ranges is None:
        return SceneRanges()
    if isinstance(ranges, SceneRanges):
        return ranges
    key = str(ranges).strip().lower()
    if key not in SCENE_PRESETS:
        raise ValueError(f"unknown scene preset {ranges!r}: use one of {', '.join(SCENE_PRESETS)}")
    return SCENE_PRESETS[key]


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


# --------------------------------------------------------------------------- component sets

_COMPONENT_RE = re.compile(r"^(d|s|r([2-9]|[1-9][0-9]+))$")


def parse_kind(kind) -> tuple[bool, bool, int]:
    """Parse one component-set spec into (has_direct, has_sss, n_interreflections).

    ``kind`` is a Fig. 3 letter ("a", "b", "c"), a ``+``-joined set of component names
    ("d+s+r2"), or an iterable of names (("d", "r2")).
    """
    if isinstance(kind, str):
        spec = FIG3_KINDS.get(kind.strip().lower(), kind)
        names = [n.strip().lower() for n in spec.split("+")]
    else:
        names = [str(n).strip().lower() for n in kind]
    names = [n for n in names if n]
    if not names:
        raise ValueError(f"empty component set {kind!r}: name at least one of d, s, r2, r3, ...")
    bad = [n for n in names if not _COMPONENT_RE.match(n)]
    if bad:
        raise ValueError(f"unknown component(s) {bad} in {kind!r}: use d, s, r2, r3, ... or a kind a, b, c")
    if len(set(names)) != len(names):
        raise ValueError(f"component set {kind!r} names a component twice")
    orders = sorted(int(n[1:]) for n in names if n.startswith("r"))
    if orders != list(range(2, 2 + len(orders))):
        raise ValueError(f"inter-reflections in {kind!r} must be r2, r3, ... without gaps "
                         "(they are numbered by order of arrival)")
    return "d" in names, "s" in names, len(orders)


def _canonical(has_d: bool, has_s: bool, n_ir: int) -> str:
    names = (["d"] if has_d else []) + (["s"] if has_s else []) + [f"r{k}" for k in range(2, 2 + n_ir)]
    return "+".join(names)


def parse_kinds(kinds) -> list[tuple[bool, bool, int]]:
    """Parse a list of kinds, or a comma-separated string of them ("a,b,c" or "d+s,d+r2")."""
    if isinstance(kinds, str):
        kinds = [k for k in kinds.split(",") if k.strip()]
    out = [parse_kind(k) for k in kinds]
    if not out:
        raise ValueError("no component kinds given")
    return out


# --------------------------------------------------------------------------- scene parameters

def _rng(seed) -> tuple[np.random.Generator, np.random.Generator]:
    """Two independent streams (scene, noise) from one seed."""
    if isinstance(seed, np.random.Generator):
        scene, noise = seed.spawn(2)
        return scene, noise
    ss = np.random.SeedSequence(seed)
    scene, noise = ss.spawn(2)
    return np.random.default_rng(scene), np.random.default_rng(noise)


def draw_params(n_pixels: int, n_bins: int, *, kinds=("a", "b", "c"), time_bin_ps: float = 2.0,
                t0_ps: float | None = None, rng=None, ranges: SceneRanges | None = None):
    """Draw ground-truth parameters for ``n_pixels`` profiles of ``n_bins`` bins.

    Kinds are assigned in equal shares (round robin over ``kinds``, then shuffled).

    Parameters
    ----------
    n_pixels, n_bins : int
    kinds : str or sequence
        Component sets (see :func:`parse_kind`), e.g. ``("a", "b", "c")`` or ``"d+s,d+r2"``.
    time_bin_ps : float
        Bin width T in ps.
    t0_ps : float, optional
        Time of bin 0 (default ``time_bin_ps``).
    rng : numpy.random.Generator or int, optional
    ranges : SceneRanges or str, optional
        Ranges or a preset name (see :func:`scene_ranges`); default the legacy ranges.

    Returns
    -------
    params : dict of ndarray, shapes (N,) and (N, R), R = most inter-reflections of any kind
    kinds : ndarray of str, (N,), canonical component set per pixel

    Raises
    ------
    ValueError
        If the window is too short to hold the requested components with the given margins.
    """
    ranges = scene_ranges(ranges)
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    n = int(n_pixels)
    if n < 0:
        raise ValueError(f"n_pixels must be non-negative, got {n_pixels}")
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    specs = parse_kinds(kinds)
    r_max = max(s[2] for s in specs)

    which = rng.permutation(np.arange(n) % len(specs))
    has_d = np.array([specs[i][0] for i in which], dtype=bool)
    has_s = np.array([specs[i][1] for i in which], dtype=bool)
    n_ir = np.array([specs[i][2] for i in which], dtype=np.int64)
    labels = np.array([_canonical(*specs[i]) for i in which], dtype=object).astype(str)

    sigma = ranges.draw(rng, "sigma_ps", n)
    edge = ranges.edge_sigma * sigma
    gap = ranges.min_gap_sigma * sigma
    t_first, t_last = t[0] + edge, t[-1] - edge
    # Gaussian components in arrival order: d (if any) then r2, r3, ...; the chain needs
    # (count - 1) gaps between its first and last member.
    n_gauss = has_d.astype(np.int64) + n_ir
    need = np.maximum(n_gauss - 1, 0) * gap
    slack = (t_last - t_first) - need
    if np.any(slack < 0):
        worst = int(np.argmin(slack))
        raise ValueError(
            f"time window of {n_bins} bins x {time_bin_ps} ps is too short for kind "
            f"{labels[worst]!r} with sigma {sigma[worst]:.2f} ps (needs {need[worst] + 2 * edge[worst]:.1f} ps); "
            "use more bins or narrower SceneRanges")
    pos = ranges.draw(rng, "direct_position", n)
    weights = rng.uniform(0.0, 1.0, (n, max(r_max, 1)))
    gaps = np.zeros((n, max(r_max, 1)))
    if ranges.max_gap_sigma is None:
        start = t_first + pos * slack  # delay of the first Gaussian component
        # Remaining slack shared among the gaps at random.
        spare = slack - pos * slack
        for k in range(r_max):  # small loop over inter-reflection orders, vectorised over pixels
            frac = weights[:, k] / np.maximum(n_ir, 1)
            gaps[:, k] = gap + frac * spare
    else:
        # Each gap uniform in [min_gap, max_gap] sigma, shrunk where the window cannot hold the chain.
        width = (ranges.max_gap_sigma - ranges.min_gap_sigma) * sigma
        gaps[:] = gap[:, None] + weights * width[:, None]
        order = np.arange(gaps.shape[1])[None, :]
        # Gaps that lie inside the chain: r2..r_{n_ir} after a direct; r3.. without one.
        inside = (order < n_ir[:, None]) & ((order > 0) | has_d[:, None])
        extra = np.where(inside, gaps - gap[:, None], 0.0).sum(axis=1)
        shrink = np.minimum(1.0, np.divide(slack, extra, out=np.ones(n), where=extra > 0))
        gaps = gap[:, None] + (gaps - gap[:, None]) * shrink[:, None]
        used = need + extra * shrink
        start = t_first + pos * (slack - (used - need))
    amp_d = ranges.draw(rng, "direct_amplitude", n)
    alpha = ranges.draw(rng, "alpha_per_ps", n)
    onset = ranges.draw(rng, "sss_onset_sigma", n) * sigma
    rel_s = ranges.draw(rng, "sss_relative_peak", n)
    rel_r = ranges.draw(rng, "ir_relative_peak", (n, max(r_max, 1)))

    p = {k: np.full(n, np.nan) for k in DIRECT_KEYS + SSS_KEYS}
    p.update({k: np.full((n, r_max), np.nan) for k in IR_KEYS})
    p["direct_delay_ps"][has_d] = start[has_d]
    p["direct_amplitude"][has_d] = amp_d[has_d]
    p["direct_sigma_ps"][has_d] = sigma[has_d]

    # Inter-reflections: after the direct one if present, else starting the chain.
    prev = np.where(has_d, start, start - gaps[:, 0])
    for k in range(r_max):
        on = n_ir > k
        delay = prev + gaps[:, k]
        p["ir_delay_ps"][on, k] = delay[on]
        p["ir_amplitude"][on, k] = (rel_r[:, k] * amp_d)[on]
        p["ir_sigma_ps"][on, k] = sigma[on]
        prev = delay

    # sss: onset shortly after the direct arrival (or where it would be); peak relative to d.
    sss_delay = start + onset
    peak = _sss_peak(sigma, alpha)
    p["sss_delay_ps"][has_s] = sss_delay[has_s]
    p["sss_amplitude"][has_s] = (rel_s * amp_d / peak)[has_s]
    p["sss_alpha_per_ps"][has_s] = alpha[has_s]
    p["sss_sigma_ps"][has_s] = sigma[has_s]
    return p, labels


def _sss_peak(sigma_ps, alpha_per_ps):
    """Peak value of the unit-amplitude sss kernel (dense search, vectorised)."""
    sigma_ps = np.asarray(sigma_ps, float)
    alpha_per_ps = np.asarray(alpha_per_ps, float)
    # The peak lies between the onset and a few sigma after it.
    x = np.linspace(-1.0, 4.0, 501)
    tt = sigma_ps[..., None] * x
    return sss_kernel(tt, sigma_ps[..., None], alpha_per_ps[..., None]).max(axis=-1)


def regime_variables(params: dict, time_bin_ps: float) -> dict[str, np.ndarray]:
    """Per-pixel variables that set how hard a pixel's split is, from its true parameters.

    Parameters
    ----------
    params : dict of ndarray
        Ground-truth parameters (keys of :mod:`core.model`), shapes S and S + (R,).
    time_bin_ps : float
        Bin width in ps.

    Returns
    -------
    dict of ndarray, each of shape S:
        ``sss_peak_ratio``  peak of the (point-sampled) sss component over the direct's peak
                            (NaN without a direct or an sss);
        ``onset_sigma``     sss onset after the direct delay, in PSF widths (NaN likewise);
        ``sigma_bins``      PSF sigma in bins (the direct's, else the sss's or first
                            inter-reflection's);
        ``n_ir``            number of inter-reflections (int);
        ``ir_min_peak_ratio`` peak of the weakest inter-reflection over the direct's peak
                            (NaN without a direct or without inter-reflections).
    """
    d_delay = np.asarray(params["direct_delay_ps"], np.float64)
    d_amp = np.asarray(params["direct_amplitude"], np.float64)
    d_sig = np.asarray(params["direct_sigma_ps"], np.float64)
    s_delay = np.asarray(params["sss_delay_ps"], np.float64)
    s_amp = np.asarray(params["sss_amplitude"], np.float64)
    s_sig = np.asarray(params["sss_sigma_ps"], np.float64)
    s_alpha = np.asarray(params["sss_alpha_per_ps"], np.float64)
    ir_sig = np.asarray(params["ir_sigma_ps"], np.float64)
    both = np.isfinite(d_delay) & np.isfinite(s_delay)
    peak = np.full(d_delay.shape, np.nan)
    if both.any():
        peak[both] = s_amp[both] * _sss_peak(s_sig[both], s_alpha[both]) / d_amp[both]
    onset = np.where(both, (s_delay - d_delay) / np.where(both, d_sig, 1.0), np.nan)
    sigma = np.where(np.isfinite(d_sig), d_sig, s_sig)
    if ir_sig.shape[-1]:
        sigma = np.where(np.isfinite(sigma), sigma, ir_sig[..., 0])
    ir_delay = np.asarray(params["ir_delay_ps"], np.float64)
    n_ir = np.isfinite(ir_delay).sum(axis=-1)
    ir_amp = np.where(np.isfinite(ir_delay), np.asarray(params["ir_amplitude"], np.float64), np.inf)
    weakest = ir_amp.min(axis=-1, initial=np.inf)
    ir_ratio = np.where(np.isfinite(d_delay) & (n_ir > 0), weakest / np.where(np.isfinite(d_amp), d_amp, 1.0), np.nan)
    return {"sss_peak_ratio": peak, "onset_sigma": onset, "sigma_bins": sigma / float(time_bin_ps),
            "n_ir": n_ir.astype(np.int64), "ir_min_peak_ratio": ir_ratio}


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


# --------------------------------------------------------------------------- noise

def _noise_type(noise: str) -> str:
    key = str(noise).strip().lower()
    if key not in _NOISE_ALIASES:
        raise ValueError(f"unknown noise type {noise!r}: use one of white, pink, photon (or none)")
    return _NOISE_ALIASES[key]


def _pink(rng, shape):
    """Zero-mean Gaussian noise with a 1/f power spectrum along the last axis."""
    n = shape[-1]
    white = rng.standard_normal(shape)
    spec = np.fft.rfft(white, axis=-1)
    f = np.fft.rfftfreq(n)
    shaping = np.zeros_like(f)
    shaping[1:] = 1.0 / np.sqrt(f[1:])
    return np.fft.irfft(spec * shaping, n=n, axis=-1)


def _photon(rng, clean, nsr):
    """Poisson noise with the photon count per unit signal set for the expected NSR."""
    if np.any(clean < 0):
        raise ValueError("photon (Poisson) noise needs non-negative clean profiles")
    total = clean.sum(axis=-1, keepdims=True)
    energy = np.square(clean).sum(axis=-1, keepdims=True)
    nsr2 = np.square(np.broadcast_to(nsr, clean.shape[:-1]))[..., None]
    ok = (total > 0) & (nsr2 > 0)
    # E||noise||^2 = sum(p) / lambda  =>  lambda = sum(p) / (nsr^2 ||p||^2).
    lam = np.where(ok, total / np.where(ok, nsr2 * energy, 1.0), 0.0)
    mean = lam * clean
    small = mean <= _POISSON_NORMAL_LIMIT
    counts = rng.poisson(np.where(small, mean, 0.0)).astype(np.float64)
    gauss = rng.standard_normal(clean.shape)
    counts = np.where(small, counts, mean + np.sqrt(mean) * gauss)
    safe = np.where(lam > 0, lam, 1.0)
    return np.where(lam > 0, counts / safe - clean, 0.0)


def noise_realisation(clean, nsr, noise: str = "white", *, rng=None) -> np.ndarray:
    """A noise realisation with exactly ``||noise|| / ||clean|| = nsr`` per profile.

    Parameters
    ----------
    clean : array_like, (..., L)
        Clean profiles (signal units).
    nsr : float or array_like broadcasting to (...,)
        Noise-to-signal ratio per profile (>= 0).
    noise : {"white", "pink", "photon", "none"}
        Also accepted: "fluctuation" (white), "detector" (pink), "poisson" (photon).
    rng : numpy.random.Generator or int, optional

    Returns
    -------
    ndarray, (..., L), float64.  Zero for all-zero clean profiles (the NSR is undefined there)
    and for ``nsr == 0``.
    """
    clean = np.asarray(clean, dtype=np.float64)
    if clean.ndim < 1 or clean.shape[-1] < 2:
        raise ValueError(f"clean profiles must have shape (..., L) with L >= 2, got {clean.shape}")
    if not np.all(np.isfinite(clean)):
        raise ValueError("clean profiles contain NaN or inf")
    nsr = np.asarray(nsr, dtype=np.float64)
    if np.any(~np.isfinite(nsr)) or np.any(nsr < 0):
        raise ValueError(f"nsr must be finite and >= 0, got {nsr}")
    try:
        nsr_b = np.broadcast_to(nsr, clean.shape[:-1])
    except ValueError:
        raise ValueError(f"nsr of shape {nsr.shape} does not match profiles of shape {clean.shape}") from None
    kind = _noise_type(noise)
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if kind == "none":
        if np.any(nsr_b > 0):
            raise ValueError("noise 'none' needs nsr = 0")
        return np.zeros_like(clean)
    if kind == "white":
        raw = rng.standard_normal(clean.shape)
    elif kind == "pink":
        raw = _pink(rng, clean.shape)
    else:
        raw = _photon(rng, clean, nsr_b)
    raw_norm = np.linalg.norm(raw, axis=-1)
    target = nsr_b * np.linalg.norm(clean, axis=-1)
    scale = np.divide(target, raw_norm, out=np.zeros_like(target), where=raw_norm > 0)
    return raw * scale[..., None]


def add_noise(clean, nsr, noise: str = "white", *, rng=None) -> np.ndarray:
    """``clean + noise_realisation(clean, nsr, noise, rng=rng)``, shape (..., L)."""
    clean = np.asarray(clean, dtype=np.float64)
    return clean + noise_realisation(clean, nsr, noise, rng=rng)


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
