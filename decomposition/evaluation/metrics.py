"""Accuracy of a decomposition against ground truth.

Decomposition fidelity (:func:`decomposition.model.fidelity.fidelity`, the measure of the paper's
Fig. 3(d)) lives with the solver, which reads its split distance in it; this module averages
it over pixels.  Per-parameter helpers compare parameter dicts (keys of :mod:`core.model`) on the
pixels where both sides hold the component.
"""
from __future__ import annotations

import numpy as np

from ..model.fidelity import fidelity

__all__ = [
    "mean_fidelity",
    "parameter_error",
    "delay_error_ps",
    "delay_rmse_ps",
    "detection_counts",
]


def mean_fidelity(truth, estimate) -> float:
    """Mean of :func:`fidelity` over the pixels whose truth holds a component (NaN if none does)."""
    f = fidelity(truth, estimate)
    ok = np.isfinite(f)
    return float(f[ok].mean()) if ok.any() else float("nan")


def _param(params, key, n_ir=None):
    if key not in params:
        raise KeyError(f"parameter dict lacks {key!r}")
    a = np.asarray(params[key], dtype=np.float64)
    if n_ir is not None and a.shape[-1] < n_ir:
        pad = [(0, 0)] * a.ndim
        pad[-1] = (0, n_ir - a.shape[-1])
        a = np.pad(a, pad, constant_values=np.nan)
    return a


def parameter_error(truth: dict, estimate: dict, key: str, *, relative: bool = False) -> np.ndarray:
    """``estimate[key] - truth[key]`` where both are present, NaN elsewhere.

    For inter-reflection keys (``ir_*``, shape (..., R)) the shorter R is padded with NaN
    (absent) before comparing in order of arrival.  ``relative=True`` divides by ``|truth|``.
    """
    if key.startswith("ir_"):
        n = max(np.shape(truth[key])[-1], np.shape(estimate[key])[-1])
        t, e = _param(truth, key, n), _param(estimate, key, n)
    else:
        t, e = _param(truth, key), _param(estimate, key)
    if t.shape != e.shape:
        raise ValueError(f"{key}: truth {t.shape} and estimate {e.shape} differ in shape")
    diff = e - t
    if relative:
        with np.errstate(divide="ignore", invalid="ignore"):
            diff = diff / np.abs(t)
    return diff


def delay_error_ps(truth: dict, estimate: dict, family: str = "direct") -> np.ndarray:
    """Delay error (ps) of one family (``"direct"``, ``"sss"`` or ``"ir"``), NaN where unmatched."""
    if family not in ("direct", "sss", "ir"):
        raise ValueError(f"family must be 'direct', 'sss' or 'ir', got {family!r}")
    return parameter_error(truth, estimate, f"{family}_delay_ps")


def delay_rmse_ps(truth: dict, estimate: dict, family: str = "direct") -> float:
    """Root-mean-square delay error (ps) over the components present on both sides (NaN if none)."""
    e = delay_error_ps(truth, estimate, family)
    ok = np.isfinite(e)
    return float(np.sqrt(np.mean(np.square(e[ok])))) if ok.any() else float("nan")


def detection_counts(truth: dict, estimate: dict, family: str = "direct") -> dict[str, int]:
    """Counts of matched, missed and spurious components of one family (by presence of the delay)."""
    if family not in ("direct", "sss", "ir"):
        raise ValueError(f"family must be 'direct', 'sss' or 'ir', got {family!r}")
    key = f"{family}_delay_ps"
    if family == "ir":
        n = max(np.shape(truth[key])[-1], np.shape(estimate[key])[-1])
        t, e = np.isfinite(_param(truth, key, n)), np.isfinite(_param(estimate, key, n))
    else:
        t, e = np.isfinite(_param(truth, key)), np.isfinite(_param(estimate, key))
    return {"matched": int(np.sum(t & e)), "missed": int(np.sum(t & ~e)), "spurious": int(np.sum(~t & e))}
