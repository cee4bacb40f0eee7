"""Robust pooling of per-pixel estimates: which pixels speak for an image, and what they say together.

:func:`select_pixels` picks a deterministic subsample of lit pixels spread over the image
(:func:`lit_score`); :func:`pooled` is an outlier-resistant weighted mean with a standard error
that allows for scatter beyond the pixels' own errors, :func:`pooled_positive` the same in the
logarithm, and :func:`fit_surface` a quadratic surface over (y, x) fitted the same way.  The
shared-parameter estimate (:mod:`decomposition.image.shared`) is built on them.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["N_SHARED_PIXELS", "SURFACE_TERMS", "lit_score", "select_pixels", "pooled", "pooled_positive",
           "fit_surface", "surface_design"]

#: pixels per region decomposed for the estimate (the brighter half, thinned evenly)
N_SHARED_PIXELS = 256
#: a per-pixel estimate this many scaled MADs from the median is an outlier
_OUTLIER_MADS = 5.0
#: the terms of the PSF map, in normalised coordinates u = (y - cy) / sy, v = (x - cx) / sx
SURFACE_TERMS = ("1", "y", "x", "y^2", "y*x", "x^2")


def lit_score(profiles) -> np.ndarray:
    """(...,) each profile's peak above its median (units of the profiles); -inf where a sample
    is not finite."""
    p = np.asarray(profiles, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        score = p.max(axis=-1) - np.median(p, axis=-1)
    return np.where(np.isfinite(p).all(axis=-1), score, -np.inf)


def select_pixels(score, labels, n_pixels: int = N_SHARED_PIXELS) -> np.ndarray:
    """Flat indices (sorted) of the pixels the estimate is made from.

    ``score`` (Y, X) from :func:`lit_score`, ``labels`` (Y, X) int (negative: in no region).
    In every region: of its pixels with a positive score the brighter half (at least one),
    thinned evenly in raster order to at most ``n_pixels``.  Deterministic.
    """
    score = np.asarray(score, dtype=np.float64).reshape(-1)
    labels = np.asarray(labels).reshape(-1)
    chosen = []
    for label in np.unique(labels[labels >= 0]):
        idx = np.flatnonzero((labels == label) & (score > 0))
        if idx.size == 0:
            continue
        order = idx[np.argsort(-score[idx], kind="stable")]
        bright = np.sort(order[:max(1, (order.size + 1) // 2)])
        if bright.size > n_pixels:
            bright = bright[np.linspace(0, bright.size - 1, n_pixels).round().astype(np.int64)]
        chosen.append(bright)
    return np.unique(np.concatenate(chosen)) if chosen else np.zeros(0, np.int64)


def pooled(values, stderr):
    """Robust pooled location of per-pixel estimates -> (estimate, standard error, pixels used).

    Pixels with a finite value and a finite positive error count; those beyond five scaled
    MADs of the median are dropped; the rest are averaged with weights 1 / (se^2 + tau^2),
    tau^2 = max(0, MAD^2 - median se^2) the scatter the errors do not explain.  The standard
    error is 1 / sqrt(sum w), times the Birge ratio sqrt(chi^2 / (n - 1)) where it exceeds 1.
    (nan, nan, 0) where no pixel counts.
    """
    v = np.asarray(values, np.float64).reshape(-1)
    se = np.asarray(stderr, np.float64).reshape(-1)
    ok = np.isfinite(v) & np.isfinite(se) & (se > 0)
    v, se = v[ok], se[ok]
    if v.size == 0:
        return math.nan, math.nan, 0
    med = np.median(v)
    mad = 1.4826 * np.median(np.abs(v - med))
    keep = np.abs(v - med) <= _OUTLIER_MADS * mad if mad > 0 else np.ones(v.size, bool)
    v, se = v[keep], se[keep]
    tau2 = max(0.0, mad ** 2 - float(np.median(se ** 2)))
    w = 1.0 / (se ** 2 + tau2)
    est = float(np.sum(w * v) / np.sum(w))
    err = 1.0 / math.sqrt(float(np.sum(w)))
    if v.size > 1:
        birge = math.sqrt(float(np.sum(w * (v - est) ** 2)) / (v.size - 1))
        err *= max(1.0, birge)
    return est, err, int(v.size)


def pooled_positive(values, stderr):
    """:func:`pooled` of a positive quantity (a width, a rate), in its logarithm: the error of a
    width grows with the width, so weights 1 / se^2 of the values themselves would favour the
    pixels whose estimate came out low.  -> (estimate, standard error, pixels used)."""
    v = np.asarray(values, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = v > 0
        est, err, n = pooled(np.log(np.where(ok, v, np.nan)), np.asarray(stderr, np.float64) / np.where(ok, v, np.nan))
    return math.exp(est) if n else math.nan, math.exp(est) * err if n else math.nan, n


def excess_spread(values, stderr) -> float:
    """How far per-pixel estimates of a positive quantity (a width) scatter beyond their own
    errors, relative: sqrt(max(0, MAD^2 - median se^2)) of their logarithms (the tau of
    :func:`pooled`), 0 where the errors explain the scatter; NaN where no pixel counts.  One
    instrument's width, read in many pixels, scatters as its errors say."""
    v = np.asarray(values, np.float64).reshape(-1)
    se = np.asarray(stderr, np.float64).reshape(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = (v > 0) & np.isfinite(v) & np.isfinite(se) & (se > 0)
        lv, lse = np.log(v[ok]), se[ok] / v[ok]
    if lv.size == 0:
        return math.nan
    mad = 1.4826 * float(np.median(np.abs(lv - np.median(lv))))
    return math.sqrt(max(0.0, mad ** 2 - float(np.median(lse ** 2))))


def surface_design(yy, xx, center, scale):
    u = (np.asarray(yy, np.float64) - center[0]) / scale[0]
    v = (np.asarray(xx, np.float64) - center[1]) / scale[1]
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)


def fit_surface(yy, xx, values, stderr, shape):
    """A quadratic surface in (y, x) fitted robustly to per-pixel estimates.

    -> (coefficients (6,), covariance (6, 6), center (cy, cx), scale (sy, sx), pixels used),
    the terms :data:`SURFACE_TERMS` in coordinates normalised by the image ``shape`` (Y, X).
    Weighted least squares with 1 / (se^2 + tau^2) as in :func:`pooled`, twice more with the
    points beyond five scaled MADs of the residuals dropped; the covariance is inflated by the
    Birge ratio.  An axis of one pixel has no terms in it (their coefficients 0, error 0).
    Raises ValueError where the points cannot determine the surface.
    """
    Y, X = shape
    center = ((Y - 1) / 2.0, (X - 1) / 2.0)
    scale = (max((Y - 1) / 2.0, 1.0), max((X - 1) / 2.0, 1.0))
    v = np.asarray(values, np.float64)
    se = np.asarray(stderr, np.float64)
    ok = np.isfinite(v) & np.isfinite(se) & (se > 0)
    yy, xx, v, se = np.asarray(yy)[ok], np.asarray(xx)[ok], v[ok], se[ok]
    cols = np.array([True, Y > 1, X > 1, Y > 2, Y > 1 and X > 1, X > 2])
    a = surface_design(yy, xx, center, scale)[:, cols]
    if v.size < 2 * a.shape[1]:
        raise ValueError(f"psf_map: {v.size} pixels with a width estimate cannot determine a "
                         f"{a.shape[1]}-term surface (at least {2 * a.shape[1]} needed)")
    keep = np.ones(v.size, bool)
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(a[keep] / se[keep, None], v[keep] / se[keep], rcond=None)
        r = v - a @ coef
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        tau2 = max(0.0, mad ** 2 - float(np.median(se[keep] ** 2)))
        keep = np.abs(r) <= _OUTLIER_MADS * mad if mad > 0 else np.ones(v.size, bool)
        w = 1.0 / (se ** 2 + tau2)
        sw = np.sqrt(w[keep])
        coef, *_ = np.linalg.lstsq(a[keep] * sw[:, None], v[keep] * sw, rcond=None)
    aw = a[keep] * sw[:, None]
    info = aw.T @ aw
    if np.linalg.matrix_rank(info) < a.shape[1]:
        raise ValueError("psf_map: the pixels with a width estimate do not spread over the image enough "
                         "to determine a quadratic surface")
    cov = np.linalg.inv(info)
    n = int(keep.sum())
    if n > a.shape[1]:
        chi2 = float(np.sum(w[keep] * (v[keep] - a[keep] @ coef) ** 2))
        cov = cov * max(1.0, chi2 / (n - a.shape[1]))
    full = np.zeros(6)
    full[cols] = coef
    full_cov = np.zeros((6, 6))
    full_cov[np.ix_(cols, cols)] = cov
    return full, full_cov, center, scale, n
