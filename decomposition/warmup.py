"""Load (or compile once and cache) every compiled kernel a decomposition uses, before timing it.

:func:`warm_up` decomposes a handful of small profiles rendered here by the forward model
(:func:`core.model.render_profile`): every family the settings ask for, at two noise levels, and
one pixel with a spike (its fit excludes a sample, which takes the weighted code paths).  Each
takes paths, and argument layouts, that the others do not, so the kernels numba compiles for
them are those a real run loads.  With an instrument response (``options["irf"]``) the profiles
are rendered with that response and also decomposed as photon counts (with ``noise="poisson"``
only as counts, with ``"gaussian"`` only as floats): the response path's table atoms, least
squares and Poisson fits are compiled kernels of their own.  A run that decomposes whole images
(``image``: the shared parameters and the spatial coupling of :func:`decomposition.image.decompose_image`)
has kernels of its own too: the profiles are then also decomposed as one small image with those
settings.  The profiles only need to take those paths; their values do not matter, and no
benchmark scene is needed to build them.
"""
from __future__ import annotations

import time

import numpy as np

from core.irf import InstrumentResponse
from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, empty_params, render_profile
from .api import decompose
from .image import decompose_image
from .kernels.jit import compile_notice, quiet_notice

__all__ = ["warm_up"]

#: the window the profiles are laid on when the caller's holds too few bins for them (bins, ps)
_DEFAULT_AXIS = (256, 2.0)


def _profiles(kinds, n_pixels: int, n_bins: int, time_bin_ps: float, rng, irf=None) -> np.ndarray:
    """(n_pixels * len(kinds), n_bins) noiseless profiles, ``n_pixels`` of each kind ("d", "d+s",
    "d+s+r2", ...: the families present, r2 / r3 the inter-reflections), with the direct in
    the window's first quarter, a PSF of 2 % of the window (at least 1.5 bins) -- or the
    response ``irf`` (an :class:`core.irf.InstrumentResponse`) when given -- and the echoes
    spread over its middle."""
    window_ps = n_bins * time_bin_ps
    out = []
    for kind in kinds:
        parts = kind.split("+")
        n_ir = sum(p.startswith("r") for p in parts)
        p = empty_params((n_pixels,), n_ir=n_ir)
        sigma = np.full(n_pixels, max(0.02 * window_ps, 1.5 * time_bin_ps))
        delay = window_ps * rng.uniform(0.15, 0.25, n_pixels)
        if "d" in parts:
            p.update(zip(DIRECT_KEYS, (delay, rng.uniform(0.5, 1.0, n_pixels), sigma)))
        if "s" in parts:
            p.update(zip(SSS_KEYS, (delay + sigma, rng.uniform(0.2, 0.5, n_pixels),
                                    np.full(n_pixels, 10.0 / window_ps), sigma)))
        if n_ir:
            at = delay[:, None] + window_ps * (0.2 + 0.15 * np.arange(n_ir))[None, :]
            p.update(zip(IR_KEYS, (at, rng.uniform(0.1, 0.3, (n_pixels, n_ir)), np.repeat(sigma[:, None], n_ir, 1))))
        out.append(render_profile(p, n_bins, time_bin_ps, irf=irf))
    return np.concatenate(out)


def warm_up(*, time_bin_ps: float = 2.0, n_bins: int = 256, method: str = "convscd", components=("d", "r", "s"),
            options: dict | None = None, image: dict | None = None, stream=None, label: str = "decompose",
            quiet: bool = False):
    """Load (or compile, with :func:`~decomposition.kernels.derivatives.jit.compile_notice`, and cache) every
    kernel a decomposition with these settings uses, by decomposing a few small profiles of
    every kind of scene they ask for.

    Run before timing anything, and before starting worker processes (they then load the cached
    kernels instead of each compiling them).  Costs a fraction of a second once the cache is warm.
    ``options`` are the decomposition's (``irf``: its response, which the profiles are then
    rendered with, when an :class:`core.irf.InstrumentResponse`, and decomposed both as floats
    and as counts, see the module docstring;
    ``noise``: "poisson" decomposes counts only, "gaussian" floats only).  With a response the
    profiles lie on the given axis itself (the window the response needs); without one on a
    window of 64 to 512 bins.  ``image``: the keywords of :func:`decomposition.image.decompose_image`
    a run uses beyond ``options`` (``shared``, ``psf_map``, ``spatial``; None or empty: per-pixel
    runs only).
    Returns the number of seconds spent compiling (0.0 when everything came from the cache).
    """
    opts = dict(options or {})
    irf = opts.get("irf")
    time_bin_ps = float(time_bin_ps)
    if irf is None:
        n_bins = int(max(64, min(int(n_bins), 512)))
        if n_bins * time_bin_ps < 64 * 2.0:   # a window too short for the scenes: the kernels are the same on the default axis
            n_bins, time_bin_ps = _DEFAULT_AXIS
    else:   # the run's own axis: the window its response needs
        n_bins = int(n_bins)
    comps = set(components)
    full = "+".join((["d"] if "d" in comps else []) + (["s"] if "s" in comps else [])
                    + (["r2", "r3"] if "r" in comps else []))
    kinds = tuple(dict.fromkeys(([full] if full else []) + (["d"] if "d" in comps else [])
                                + (["d+s"] if {"d", "s"} <= comps else []) + (["d+s+r2"] if comps >= {"d", "s", "r"} else [])))
    rng = np.random.default_rng(0)
    clean = _profiles(kinds, 2, n_bins, time_bin_ps, rng, irf if isinstance(irf, InstrumentResponse) else None)
    # low and high noise, and a pixel with a spike
    noisy = np.concatenate([clean + nsr * clean.max(axis=1, keepdims=True) * rng.standard_normal(clean.shape)
                            for nsr in (0.05, 0.2)])
    spiked = noisy[:1].copy()
    spiked[0, n_bins // 5] += 20.0 * np.abs(spiked).max()
    noisy = np.concatenate([noisy, spiked])
    noise = str(opts.get("noise", "auto")).lower()
    batches = [noisy] if noise != "poisson" else []
    if noise == "poisson" or (irf is not None and noise == "auto"):
        # photon counts (~200 at the peak): the response path's Poisson fits
        batches.append(rng.poisson(np.maximum(200.0 * clean / clean.max(axis=1, keepdims=True), 0.0)).astype(np.float64))
    with (quiet_notice() if quiet else compile_notice(stream, label=label)) as watch:
        for data in batches:
            decompose(data, time_bin_ps=time_bin_ps, method=method, components=tuple(components), **opts)
            if image:
                # (the PSF map is a NumPy surface over the image, held per pixel through the same
                # kernels as one shared width; the warm-up's few pixels cannot determine one)
                rows = data.shape[0] // 2
                decompose_image(data[:2 * rows].reshape(2, rows, n_bins), time_bin_ps=time_bin_ps, method=method,
                                components=tuple(components), **dict(image, psf_map=False), **opts)
    return 0.0 if watch.started is None else time.monotonic() - watch.started
