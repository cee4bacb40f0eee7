"""The scenes of synthetic profiles: which components a pixel holds and where they lie.

Scene kinds (the paper's Fig. 3 and any other subset, :func:`parse_kind`), the parameter
ranges (:class:`SceneRanges`, with the named presets of :data:`SCENE_PRESETS`: ``legacy``, the
default, and ``paper``, the paper's parameter space), the draw of one parameter set per pixel
(:func:`draw_params`) and each pixel's regime (:func:`regime_variables`).  Rendering and noise
are :mod:`decomposition.evaluation.synthetic` and :mod:`decomposition.evaluation.synthetic_noise`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, sss_kernel, time_axis_ps

__all__ = ["FIG3_KINDS", "SceneRanges", "SCENE_PRESETS", "scene_ranges", "parse_kind", "parse_kinds",
           "draw_params", "regime_variables"]

FIG3_KINDS = {"a": "d+s", "b": "d+s+r2", "c": "d+s+r2+r3"}


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
        for name in _RANGE_NAMES:
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
