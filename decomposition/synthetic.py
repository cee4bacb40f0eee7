"""Synthetic transient time profiles with known ground truth (the paper's Fig. 3).

A synthetic pixel holds any subset of the component classes

    d    direct reflection (a Gaussian-blurred delta)
    s    subsurface scattering (sss; a Gaussian-blurred delayed decaying exponential)
    r2, r3, ...  inter-reflections (Gaussian-blurred deltas after the direct one)

rendered with :func:`decomposition.model.render_components`, plus one of the paper's three
noise types at an exact noise-to-signal ratio.  The kinds of the paper's Fig. 3 are

    "a" = d + s,   "b" = d + s + r2,   "c" = d + s + r2 + r3,

and any other subset is written with ``+`` (``"d+r2"``, ``"s"``, ``"d+s+r2+r3+r4"``).
Inter-reflections are numbered by order of arrival, so ``r3`` needs ``r2``; in the parameter
dict the inter-reflection columns are in that order (column 0 = r2), which is the order a
decomposition reports them in.

Scene parameters (all drawn uniformly from the ranges of :class:`SceneRanges`, documented
there) follow eq. (2): one camera PSF width sigma per pixel shared by all of its components;
the direct reflection arrives first, the sss onset shortly after it (light enters the surface
where it is directly lit), and the inter-reflections later, each at least ``min_gap_sigma``
PSF widths after the previous Gaussian component and every Gaussian component at least
``edge_sigma`` widths inside the time window.

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

from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, render_components, sss_kernel, time_axis_ps

__all__ = [
    "FIG3_KINDS",
    "NOISE_TYPES",
    "SceneRanges",
    "SyntheticData",
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


@dataclass(frozen=True)
class SyntheticData:
    """Synthetic profiles with their ground truth; leading shape ``S`` (``(N,)`` or ``(ny, nx)``).

    Attributes
    ----------
    params : dict of ndarray
        Ground-truth parameters, keys of :mod:`decomposition.model`, shapes S / S + (R,), NaN = absent.
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

    @property
    def noise_profile(self) -> np.ndarray:
        return self.noisy - self.clean


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


def _uniform(rng, bounds, size):
    lo, hi = (float(b) for b in bounds)
    return rng.uniform(lo, hi, size) if hi > lo else np.full(size, lo)


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
    ranges : SceneRanges, optional

    Returns
    -------
    params : dict of ndarray, shapes (N,) and (N, R), R = most inter-reflections of any kind
    kinds : ndarray of str, (N,), canonical component set per pixel

    Raises
    ------
    ValueError
        If the window is too short to hold the requested components with the given margins.
    """
    ranges = ranges or SceneRanges()
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

    sigma = _uniform(rng, ranges.sigma_ps, n)
    edge = ranges.edge_sigma * sigma
    gap = ranges.min_gap_sigma * sigma
    t_first, t_last = t[0] + edge, t[-1] - edge
    # Gaussian components in arrival order: d (if any) then r2, r3, ...; the chain needs
    # (count - 1) minimum gaps between its first and last member.
    n_gauss = has_d.astype(np.int64) + n_ir
    need = np.maximum(n_gauss - 1, 0) * gap
    slack = (t_last - t_first) - need
    if np.any(slack < 0):
        worst = int(np.argmin(slack))
        raise ValueError(
            f"time window of {n_bins} bins x {time_bin_ps} ps is too short for kind "
            f"{labels[worst]!r} with sigma {sigma[worst]:.2f} ps (needs {need[worst] + 2 * edge[worst]:.1f} ps); "
            "use more bins or narrower SceneRanges")
    pos = _uniform(rng, ranges.direct_position, n)
    start = t_first + pos * slack  # delay of the first Gaussian component
    # Remaining slack shared among the gaps at random.
    spare = slack - pos * slack
    weights = rng.uniform(0.0, 1.0, (n, max(r_max, 1)))
    gaps = np.zeros((n, max(r_max, 1)))
    for k in range(r_max):  # small loop over inter-reflection orders, vectorised over pixels
        frac = weights[:, k] / np.maximum(n_ir, 1)
        gaps[:, k] = gap + frac * spare
    amp_d = _uniform(rng, ranges.direct_amplitude, n)
    alpha = _uniform(rng, ranges.alpha_per_ps, n)
    onset = _uniform(rng, ranges.sss_onset_sigma, n) * sigma
    rel_s = _uniform(rng, ranges.sss_relative_peak, n)
    rel_r = rng.uniform(ranges.ir_relative_peak[0], ranges.ir_relative_peak[1], (n, max(r_max, 1)))

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
    ranges : SceneRanges, optional
    bin_integrated : bool
        Render kernels averaged over each bin instead of point-sampled.
    """
    kind = _noise_type(noise)
    if float(nsr) > 0 and kind == "none":
        raise ValueError("noise 'none' needs nsr = 0")
    ranges = ranges or SceneRanges()
    t0 = float(time_bin_ps) if t0_ps is None else float(t0_ps)
    scene_rng, noise_rng = _rng(seed)
    params, labels = draw_params(n_pixels, n_bins, kinds=kinds, time_bin_ps=time_bin_ps, t0_ps=t0,
                                 rng=scene_rng, ranges=ranges)
    comps = render_components(params, n_bins, time_bin_ps, t0, bin_integrated=bin_integrated)
    clean = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    if kind == "none" or float(nsr) == 0:
        noisy = clean.copy()
    else:
        noisy = add_noise(clean, nsr, kind, rng=noise_rng)
    return SyntheticData(params=params, components=comps, clean=clean, noisy=noisy, kinds=labels,
                         time_bin_ps=float(time_bin_ps), t0_ps=t0, nsr=float(nsr), noise=kind,
                         seed=seed if isinstance(seed, (int, np.integer)) else None, ranges=ranges)


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
