"""Spatially structured synthetic images: what neighbouring pixels of one capture share.

:func:`make_spatial_scene` renders an image ``(Y, X, L)`` of time profiles seen through ONE
instrument (one Gaussian PSF width for every pixel) with ground truth per pixel:

* **depth**: two tilted planes that meet at a vertical step at ``x = X // 2`` (the right plane
  :data:`STEP_PS` later): the direct delay is smooth within each plane and jumps at the step;
* **materials**: four patches (a 2 x 2 layout whose vertical boundary lies at ``X // 3``, off
  the depth step, and horizontal boundary at ``Y // 2``), each with its own sss peak ratio
  (sss peak over direct peak) and decay rate, from :data:`MATERIALS`;
* **corner**: the pixels of the near plane within :data:`CORNER_WIDTH` columns of the step see
  the other plane: an inter-reflection whose delay after the direct grows with the distance to
  the corner (:data:`CORNER_PS_PER_PIXEL` per column of distance, both ways), its amplitude
  falling with it;
* **weak echo** (``echo_ratio``): a rectangle in the lower left (rows ``Y // 2 + 1 ..``,
  columns ``1 .. X // 3 - 1``, away from the corner) where an echo of ``echo_ratio`` x the
  direct's amplitude arrives :data:`ECHO_AFTER_PS` after the direct, the offset drifting
  slowly across the rectangle (a hidden surface seen through every pixel of it).

Each pixel holds at most one inter-reflection (the regions are disjoint).  Noise: one of
:mod:`decomposition.evaluation.synthetic_noise`'s types at an exact NSR per pixel, or true
photon counts (``photons_per_pixel``, :func:`decomposition.evaluation.synthetic_effects.count_photons`,
the truth then in expected counts).  Rendering: point samples of the solver's model, or
(default with counts) the bin averages of :func:`decomposition.evaluation.synthetic.render_bin_integrated`.

:func:`edge_mask` marks the pixels next to a depth or material edge (a label differing within
the 3 x 3 neighbourhood), the pixels where coupling neighbours could mislead.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.model import render_components, sss_kernel

from .synthetic import _rng, render_bin_integrated
from .synthetic_effects import count_photons
from .synthetic_noise import _noise_type, add_noise

__all__ = ["SpatialScene", "make_spatial_scene", "edge_mask", "MATERIALS", "STEP_PS", "CORNER_WIDTH",
           "CORNER_PS_PER_PIXEL", "ECHO_AFTER_PS"]

#: (sss peak / direct peak, sss decay rate per ps) of the four material patches
MATERIALS = ((0.3, 0.05), (0.8, 0.02), (0.15, 0.1), (0.5, 0.035))
#: the far plane's direct arrives this much later than the near one at the step (ps)
STEP_PS = 40.0
#: columns of the near plane, next to the step, that see an inter-reflection from the far plane
CORNER_WIDTH = 3
#: the corner inter-reflection's delay after the direct: a base plus this much per column of
#: distance from the step (ps); its amplitude falls from CORNER_AMPLITUDE of the direct
CORNER_BASE_PS = 30.0
CORNER_PS_PER_PIXEL = 8.0
CORNER_AMPLITUDE = 0.4
#: the weak echo's delay after the direct (ps), at the rectangle's top-left pixel
ECHO_AFTER_PS = 150.0


@dataclass(frozen=True)
class SpatialScene:
    """A synthetic image with its ground truth; arrays lead with ``(Y, X)``.

    Attributes
    ----------
    profiles : ndarray (Y, X, L)
        The noisy image (int64 counts with ``photons_per_pixel``).
    clean : ndarray (Y, X, L)
        Its expected value.
    params : dict of ndarray
        Truth, keys of :mod:`core.model`, shapes (Y, X) and (Y, X, 1); NaN absent.
    components : dict of ndarray
        The clean classes as rendered: ``direct``, ``sss`` (Y, X, L), ``interreflections`` (Y, X, 1, L).
    edges : ndarray (Y, X) bool
        Pixels next to a depth or material edge (:func:`edge_mask`).
    regions : dict of ndarray (Y, X) bool
        ``corner`` (the corner inter-reflection), ``echo`` (the weak echo; all False without
        ``echo_ratio``), ``near`` / ``far`` (the two planes).
    depth_labels, material_labels : ndarray (Y, X) int
    time_bin_ps, t0_ps, sigma_ps : float
    noise : str
        The noise type, or ``"counts"``.
    nsr : float
        NaN for counts.
    photons_per_pixel : float or None
    bin_integrated : bool
        Whether the profiles are bin averages of the model (then fit them that way).
    seed : int or None
    """

    profiles: np.ndarray
    clean: np.ndarray
    params: dict
    components: dict
    edges: np.ndarray
    regions: dict
    depth_labels: np.ndarray
    material_labels: np.ndarray
    time_bin_ps: float
    t0_ps: float
    sigma_ps: float
    noise: str
    nsr: float
    photons_per_pixel: float | None
    bin_integrated: bool
    seed: int | None


def edge_mask(*labels) -> np.ndarray:
    """(Y, X) bool: pixels with a different label in any of ``labels`` (integer images (Y, X))
    among their 8 neighbours -- both sides of every edge."""
    if not labels:
        raise ValueError("edge_mask needs at least one label image")
    shape = np.shape(labels[0])
    out = np.zeros(shape, bool)
    for lab in labels:
        lab = np.asarray(lab)
        if lab.shape != shape or lab.ndim != 2:
            raise ValueError(f"label images must all be (Y, X) of shape {shape}, got {lab.shape}")
        pad = np.pad(lab, 1, mode="edge")
        Y, X = shape
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                out |= pad[1 + dy:1 + dy + Y, 1 + dx:1 + dx + X] != lab
    return out


def _sss_peak(sigma_ps: float, alpha: float) -> float:
    t = np.linspace(-6.0 * sigma_ps, 6.0 * sigma_ps + 8.0 / alpha, 4001)
    return float(sss_kernel(t, sigma_ps, alpha).max())


def make_spatial_scene(ny: int = 32, nx: int = 32, n_bins: int = 256, *, time_bin_ps: float = 2.0,
                       t0_ps: float | None = None, sigma_ps: float = 4.0, nsr: float = 0.0, noise: str = "white",
                       photons_per_pixel: float | None = None, echo_ratio: float | None = None,
                       bin_integrated: bool | None = None, seed=None) -> SpatialScene:
    """A spatially structured image with ground truth (see the module docstring).

    Parameters
    ----------
    ny, nx : int
        Image size (at least 8 x 8: the layout needs room for its patches and corner).
    n_bins : int
        Time bins L; the window must hold the latest component (at least ~ 300 ps + 6 sigma).
    time_bin_ps, t0_ps : float
        Time axis (ps); ``t0_ps`` defaults to one bin.
    sigma_ps : float
        The one PSF width of every pixel and component (ps).
    nsr, noise
        Noise-to-signal ratio of every pixel and the type (``"white"``, ``"pink"``, ``"photon"``,
        ``"none"``; :func:`decomposition.evaluation.synthetic_noise.add_noise`).
    photons_per_pixel : float, optional
        Integer Poisson counts with this many expected signal photons per pixel instead
        (``nsr`` must then be 0).
    echo_ratio : float, optional
        The weak echo's amplitude over the direct's, in (0, 1]; None: no echo region.
    bin_integrated : bool, optional
        Default: True with counts (a detector bin integrates), else False (the solver's model).
    seed : int, optional
        The same seed gives the same arrays (the layout is fixed; the seed draws the noise and
        the planes' small shading).

    Returns
    -------
    SpatialScene
    """
    ny, nx, L = int(ny), int(nx), int(n_bins)
    if ny < 8 or nx < 8:
        raise ValueError(f"spatial scene: need at least 8 x 8 pixels, got {ny} x {nx}")
    if not (np.isfinite(sigma_ps) and sigma_ps > 0):
        raise ValueError(f"spatial scene: sigma_ps must be positive, got {sigma_ps!r}")
    if echo_ratio is not None and not (0 < float(echo_ratio) <= 1):
        raise ValueError(f"spatial scene: echo_ratio must lie in (0, 1], got {echo_ratio!r}")
    kind = _noise_type(noise)
    if photons_per_pixel is not None and float(nsr) > 0:
        raise ValueError(f"spatial scene: photons_per_pixel sets the noise; leave nsr at 0, got {nsr!r}")
    T = float(time_bin_ps)
    t0 = T if t0_ps is None else float(t0_ps)
    counting = photons_per_pixel is not None
    bin_integrated = counting if bin_integrated is None else bool(bin_integrated)
    scene_rng, noise_rng = _rng(seed, 2)

    y, x = np.mgrid[0:ny, 0:nx].astype(np.float64)
    step_col = nx // 2
    far = x >= step_col
    depth_labels = far.astype(np.int64)
    start = t0 + 12.0 * sigma_ps
    tilt = scene_rng.uniform(0.4, 0.8, 2)                    # ps per pixel, the two planes' slopes
    direct_delay = np.where(far, start + STEP_PS + tilt[1] * (y - x + step_col), start + tilt[0] * (x + 0.5 * y))
    material_labels = (x >= nx // 3).astype(np.int64) + 2 * (y >= ny // 2).astype(np.int64)
    shading = 0.25 * np.cos(2 * np.pi * (x / nx + scene_rng.uniform())) * np.cos(np.pi * y / ny)
    direct_amp = 0.7 + shading                                # 0.45 .. 0.95, smooth
    ratio = np.array([m[0] for m in MATERIALS])[material_labels]
    alpha = np.array([m[1] for m in MATERIALS])[material_labels]
    peaks = np.array([_sss_peak(sigma_ps, m[1]) for m in MATERIALS])[material_labels]
    sigma = np.full((ny, nx), float(sigma_ps))

    dist = step_col - 1 - x                                   # columns from the step, on the near side
    corner = (~far) & (dist < CORNER_WIDTH)
    echo = np.zeros((ny, nx), bool)
    if echo_ratio is not None:
        echo[ny // 2 + 1:, 1:max(2, nx // 3 - 1)] = True
    ir_delay = np.full((ny, nx, 1), np.nan)
    ir_amp = np.full((ny, nx, 1), np.nan)
    ir_delay[corner, 0] = direct_delay[corner] + CORNER_BASE_PS + CORNER_PS_PER_PIXEL * 2.0 * dist[corner]
    ir_amp[corner, 0] = CORNER_AMPLITUDE * direct_amp[corner] * (1.0 - dist[corner] / (CORNER_WIDTH + 1.0))
    if echo.any():
        drift = 0.3 * (y - (ny // 2 + 1)) + 0.2 * (x - 1)
        ir_delay[echo, 0] = direct_delay[echo] + ECHO_AFTER_PS + drift[echo]
        ir_amp[echo, 0] = float(echo_ratio) * direct_amp[echo]
    latest = np.nanmax(np.where(np.isfinite(ir_delay[..., 0]), ir_delay[..., 0], direct_delay))
    t_last = t0 + (L - 1) * T
    if latest + 6.0 * sigma_ps > t_last:
        raise ValueError(f"spatial scene: {L} bins of {T:g} ps end at {t_last:g} ps, before the latest "
                         f"component ({latest:g} ps + 6 sigma); give more bins")

    params = {"direct_delay_ps": direct_delay, "direct_amplitude": direct_amp, "direct_sigma_ps": sigma.copy(),
              "sss_delay_ps": direct_delay + 0.5 * sigma_ps, "sss_amplitude": ratio * direct_amp / peaks,
              "sss_alpha_per_ps": alpha, "sss_sigma_ps": sigma.copy(),
              "ir_delay_ps": ir_delay, "ir_amplitude": ir_amp,
              "ir_sigma_ps": np.where(np.isfinite(ir_delay), float(sigma_ps), np.nan)}
    if bin_integrated:
        comps = render_bin_integrated(params, L, T, t0)
    else:
        comps = render_components(params, L, T, t0)
    signal = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    if counting:
        profiles, lam = count_photons(signal, 0.0, float(photons_per_pixel), noise_rng)
        for key in ("direct_amplitude", "sss_amplitude"):
            params[key] = params[key] * lam
        params["ir_amplitude"] = params["ir_amplitude"] * lam[..., None]
        comps = {"direct": comps["direct"] * lam[..., None], "sss": comps["sss"] * lam[..., None],
                 "interreflections": comps["interreflections"] * lam[..., None, None]}
        clean = signal * lam[..., None]
        kind, nsr_out = "counts", float("nan")
    else:
        clean = signal
        profiles = clean.copy() if (kind == "none" or float(nsr) == 0) else add_noise(clean, nsr, kind, rng=noise_rng)
        nsr_out = float(nsr)
    regions = {"corner": corner, "echo": echo, "near": ~far, "far": far}
    return SpatialScene(profiles=profiles, clean=clean, params=params, components=comps,
                        edges=edge_mask(depth_labels, material_labels), regions=regions, depth_labels=depth_labels,
                        material_labels=material_labels, time_bin_ps=T, t0_ps=t0, sigma_ps=float(sigma_ps),
                        noise=kind, nsr=nsr_out, photons_per_pixel=None if not counting else float(photons_per_pixel),
                        bin_integrated=bin_integrated, seed=seed if isinstance(seed, (int, np.integer)) else None)
