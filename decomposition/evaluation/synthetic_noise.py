"""Noise realisations for synthetic profiles: the paper's three fundamental noise types.

    "photon"    Poisson (shot) noise: counts ~ Poisson(lambda * p) / lambda, variance
                proportional to the clean signal p.  lambda (photons per unit signal) is
                chosen per pixel so that the expected NSR is the requested one.
    "detector"  pink noise: white Gaussian noise shaped in the Fourier domain by 1/sqrt(f),
                so its power spectrum falls as 1/f (zero mean: the DC term is removed).
    "white"     fluctuation noise: independent Gaussian samples.

Each realisation is rescaled per pixel so that NSR = ||noise||_2 / ||clean||_2 holds exactly
(to rounding).  Beyond the paper's three:

    "camera"    shot noise of one camera: Poisson counts at one photon scale lambda for every
                profile (one conversion gain), so a bright pixel has a lower NSR than a faint
                one.  lambda is chosen so that the expected NSR of all the profiles together
                (the norms summed over them) is the requested one, and the realisation is
                rescaled by one factor so that it holds exactly; every profile's own NSR is
                left to its brightness.  ``nsr`` must be one value.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["NOISE_TYPES", "noise_realisation", "add_noise"]

NOISE_TYPES = ("white", "pink", "photon", "camera")
_NOISE_ALIASES = {
    "white": "white", "fluctuation": "white", "gaussian": "white",
    "pink": "pink", "detector": "pink",
    "photon": "photon", "poisson": "photon", "shot": "photon",
    "camera": "camera",
    "none": "none",
}
# Above this expected count per bin the Poisson law is replaced by its normal limit
# (numpy's Poisson sampler refuses means above ~1e18; the two agree to ~1e-4 here).
_POISSON_NORMAL_LIMIT = 1e8


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


def _poisson_counts(rng, mean):
    """Poisson counts of expected value ``mean`` (>= 0), float64; above _POISSON_NORMAL_LIMIT
    their normal limit."""
    small = mean <= _POISSON_NORMAL_LIMIT
    counts = rng.poisson(np.where(small, mean, 0.0)).astype(np.float64)
    gauss = rng.standard_normal(mean.shape)
    return np.where(small, counts, mean + np.sqrt(mean) * gauss)


def _photon(rng, clean, nsr):
    """Poisson noise with the photon count per unit signal set for the expected NSR."""
    # a profile rendered through a response by FFT convolution holds rounding-level negatives
    # (-4e-16 of a unit peak) where it is 0: those are 0 photons; a real negative is refused
    peak = np.max(np.abs(clean), axis=-1, keepdims=True)
    if np.any(clean < -1e-12 * peak):
        raise ValueError("photon (Poisson) noise needs non-negative clean profiles")
    clean = np.maximum(clean, 0.0)
    total = clean.sum(axis=-1, keepdims=True)
    energy = np.square(clean).sum(axis=-1, keepdims=True)
    nsr2 = np.square(np.broadcast_to(nsr, clean.shape[:-1]))[..., None]
    ok = (total > 0) & (nsr2 > 0)
    # E||noise||^2 = sum(p) / lambda  =>  lambda = sum(p) / (nsr^2 ||p||^2).
    lam = np.where(ok, total / np.where(ok, nsr2 * energy, 1.0), 0.0)
    counts = _poisson_counts(rng, lam * clean)
    safe = np.where(lam > 0, lam, 1.0)
    return np.where(lam > 0, counts / safe - clean, 0.0)


def _camera(rng, clean, nsr):
    """Poisson noise at one photon scale for every profile of ``clean``, set for the expected
    NSR of all of them together (see the module docstring), rescaled to it exactly."""
    if np.any(clean < 0):
        raise ValueError("camera (Poisson) noise needs non-negative clean profiles")
    total, energy = float(clean.sum()), float(np.square(clean).sum())
    if not (total > 0 and nsr > 0):
        return np.zeros_like(clean)
    lam = total / (nsr * nsr * energy)              # E||noise||^2 = sum(p) / lambda over all
    raw = _poisson_counts(rng, lam * clean) / lam - clean
    norm = float(np.linalg.norm(raw))
    return raw * (nsr * math.sqrt(energy) / norm) if norm > 0 else raw


def noise_realisation(clean, nsr, noise: str = "white", *, rng=None) -> np.ndarray:
    """A noise realisation with exactly ``||noise|| / ||clean|| = nsr`` per profile.

    Parameters
    ----------
    clean : array_like, (..., L)
        Clean profiles (signal units).
    nsr : float or array_like broadcasting to (...,)
        Noise-to-signal ratio per profile (>= 0).
    noise : {"white", "pink", "photon", "camera", "none"}
        Also accepted: "fluctuation" (white), "detector" (pink), "poisson" (photon).
    rng : numpy.random.Generator or int, optional

    Returns
    -------
    ndarray, (..., L), float64.  Zero for all-zero clean profiles (the NSR is undefined there)
    and for ``nsr == 0``.  ``"camera"``: the NSR of all the profiles together (one value of
    ``nsr``), see the module docstring.
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
    if kind == "camera":
        if np.ptp(nsr_b) > 0:
            raise ValueError("camera noise has one NSR for all the profiles together; got several")
        return _camera(rng, clean, float(nsr_b.flat[0]) if nsr_b.size else 0.0)
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
