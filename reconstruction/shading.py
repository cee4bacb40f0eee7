"""Shading along the time axis: the sensitivity of every streak row, from a uniform-light capture.

The photocathode, the phosphor and the sweep itself make the counts of a row depend on the row:
under light of constant intensity per ps a row collects in proportion to its sensitivity and to
the time it spans.  :func:`shading_flat` measures both at once from a capture of uniform light
(every line's frames averaged, dark subtracted): the row sensitivity is the slit-mean profile
fitted by a Legendre polynomial of the row (which smooths the photon noise without bending the
ends the way a moving average would), the slit sensitivity the row-mean of each pixel divided by
it.  Their product, normalised to mean 1, is a flat field of shape (x, rows): ``streaklab
reconstruct --flat`` divides every frame by it, after which counts per row are proportional to
the light per ps.
"""
from __future__ import annotations

import numpy as np

from core.errors import StreaklabError

__all__ = ["ShadingError", "shading_flat"]


class ShadingError(StreaklabError, ValueError):
    """A uniform-light capture that cannot give a shading correction (says why)."""


def shading_flat(image: np.ndarray, *, degree: int = 6, min_counts: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Flat field (x, rows) from a dark-subtracted uniform-light image.

    Parameters
    ----------
    image : ndarray, shape (x, n_rows)
        Mean counts per frame of a uniform-light capture, dark subtracted.
    degree : int
        Degree of the Legendre polynomial fitted to the row sensitivity (1 to 20).
    min_counts : float
        The slit-summed counts of the dimmest row must reach this (else the photon noise of the
        capture would dominate the correction).

    Returns
    -------
    flat : ndarray, shape (x, n_rows), float64, mean 1
        Relative sensitivity of every pixel and row (for ``--flat``).
    row_sensitivity : ndarray, shape (n_rows,), float64, mean 1
        The fitted sensitivity along time.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 2:
        raise ShadingError(f"uniform-light image must be 2-D (x, rows), got shape {img.shape}")
    if not (isinstance(degree, int) and 1 <= degree <= 20):
        raise ShadingError(f"degree must be an integer from 1 to 20, got {degree!r}")
    if not np.all(np.isfinite(img)):
        raise ShadingError(f"uniform-light image has {int(np.count_nonzero(~np.isfinite(img)))} non-finite values")
    nx, n_rows = img.shape
    profile = img.sum(axis=0)                                         # (rows,)
    if profile.min() < min_counts:
        raise ShadingError(f"uniform-light capture too dim: row {int(np.argmin(profile))} holds "
                           f"{profile.min():.3g} counts summed over the slit, fewer than {min_counts:g}")
    u = np.linspace(-1.0, 1.0, n_rows)
    coef = np.polynomial.legendre.legfit(u, profile, degree, w=1.0 / np.sqrt(profile))   # Poisson weights
    rows = np.polynomial.legendre.legval(u, coef)
    if rows.min() <= 0:
        raise ShadingError(f"the fitted row sensitivity is not positive (degree {degree} too high?)")
    rows /= rows.mean()
    cols = (img / rows[None, :]).mean(axis=1)                          # (x,)
    if cols.min() <= 0:
        raise ShadingError(f"slit pixel {int(np.argmin(cols))} received no light in the uniform-light capture")
    flat = cols[:, None] * rows[None, :]
    return flat / flat.mean(), rows
