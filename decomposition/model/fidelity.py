"""Fidelity of a decomposition's split against another: the distance of two component splits.

Decomposition fidelity (the measure of the paper's Fig. 3(d)), per pixel, over the component
classes k = d, s, r2, r3, ...::

    fidelity = 1 - sum_k ||est_k - truth_k||_2 / sum_k ||truth_k||_2

A class missing on either side is a zero profile, so a missed component costs its whole norm
and a spurious one costs its own norm.  Fidelity is 1 for a perfect estimate, 0 for an empty
one, and can go below 0 when spurious components outweigh the truth.  It is undefined (NaN)
for a pixel whose truth holds no component at all.

Inter-reflections are compared by order of arrival (r2 with r2, r3 with r3, ...), which is how
both the ground truth and a decomposition list them: the bounce labels count, so a missed
first echo that leaves the second one labelled r2 costs both slots.  ``ir_pairing="matched"``
pairs them instead so that the pixel's error is least (each estimated inter-reflection with at
most one true one, the rest against zero profiles): it measures the echoes found, whatever
their bounce labels, and tells a lost label order (a faint first echo missed) from a wrong echo.

The solver reads the same measure between two of its own fits: the response path calls a
better fit ambiguous where its split lies more than ``ambiguity_split`` (1 - fidelity) away
from the one it replaces.
"""
from __future__ import annotations

from itertools import permutations

import numpy as np

__all__ = ["component_profiles", "fidelity", "MAX_MATCHED_IR"]

_CLASSES = ("direct", "sss", "interreflections")


def component_profiles(obj) -> dict[str, np.ndarray]:
    """Component classes of ``obj`` as ``{"direct", "sss", "interreflections"}`` arrays.

    ``obj`` is a dict with those keys (as :func:`core.model.render_components`
    returns) or an object with those attributes (a decomposition result).  A missing
    ``direct``/``sss`` is taken as zeros, a missing ``interreflections`` as R = 0.
    """
    get = obj.get if isinstance(obj, dict) else (lambda k: getattr(obj, k, None))
    d, s, r = (get(k) for k in _CLASSES)
    if d is None and s is None and r is None:
        raise ValueError("expected component profiles with keys/attributes 'direct', 'sss', 'interreflections'")
    if d is not None:
        shape = np.shape(d)
    elif s is not None:
        shape = np.shape(s)
    else:
        r = np.asarray(r, dtype=np.float64)
        if r.ndim < 2:
            raise ValueError(f"interreflections must have shape (..., R, L), got {r.shape}")
        shape = r.shape[:-2] + r.shape[-1:]
    if len(shape) < 1:
        raise ValueError("component profiles must have a time axis (..., L)")
    d = np.zeros(shape) if d is None else np.asarray(d, dtype=np.float64)
    s = np.zeros(shape) if s is None else np.asarray(s, dtype=np.float64)
    r = np.zeros(shape[:-1] + (0, shape[-1])) if r is None else np.asarray(r, dtype=np.float64)
    if d.shape != shape or s.shape != shape:
        raise ValueError(f"direct {d.shape} and sss {s.shape} profiles must have the same shape")
    if r.ndim != d.ndim + 1 or r.shape[:-2] != shape[:-1] or r.shape[-1] != shape[-1]:
        raise ValueError(f"interreflections must have shape {shape[:-1]} + (R, {shape[-1]}), got {r.shape}")
    return {"direct": d, "sss": s, "interreflections": r}


def _pad_ir(r, n):
    if r.shape[-2] == n:
        return r
    pad = [(0, 0)] * r.ndim
    pad[-2] = (0, n - r.shape[-2])
    return np.pad(r, pad)


#: Largest number of inter-reflection slots ``ir_pairing="matched"`` pairs (R! pairings are tried).
MAX_MATCHED_IR = 6


def _matched_ir_error(tr, er):
    """(...,) the least sum over pairings of ||er_i - tr_j|| for (..., R, L) inter-reflection
    profiles (both padded to R): the pairwise errors once, then every permutation of R slots
    summed over them, all pixels at a time."""
    R = tr.shape[-2]
    if R == 0:
        return np.zeros(tr.shape[:-2])
    if R > MAX_MATCHED_IR:
        raise ValueError(f"ir_pairing='matched' pairs up to {MAX_MATCHED_IR} inter-reflections per pixel, got {R}")
    cost = np.linalg.norm(er[..., :, None, :] - tr[..., None, :, :], axis=-1)      # (..., R est, R true)
    rows = np.arange(R)
    best = None
    for perm in permutations(range(R)):
        total = cost[..., rows, list(perm)].sum(axis=-1)
        best = total if best is None else np.minimum(best, total)
    return best


def fidelity(truth, estimate, *, ir_pairing: str = "order") -> np.ndarray:
    """Per-pixel decomposition fidelity (see the module docstring).

    Parameters
    ----------
    truth, estimate : dict or result object
        Component profiles: ``direct`` (..., L), ``sss`` (..., L), ``interreflections``
        (..., R, L); R may differ between the two (the shorter is padded with zero profiles).
    ir_pairing : {"order", "matched"}
        Inter-reflections compared slot by slot in order of arrival (the bounce labels, the
        default), or paired to the least error (up to MAX_MATCHED_IR of them).

    Returns
    -------
    ndarray, (...,), float64; NaN where the truth has no component.
    """
    if ir_pairing not in ("order", "matched"):
        raise ValueError(f"ir_pairing must be 'order' or 'matched', got {ir_pairing!r}")
    t = component_profiles(truth)
    e = component_profiles(estimate)
    if t["direct"].shape != e["direct"].shape:
        raise ValueError(f"truth profiles {t['direct'].shape} and estimate profiles {e['direct'].shape} differ in shape")
    n_ir = max(t["interreflections"].shape[-2], e["interreflections"].shape[-2])
    tr, er = _pad_ir(t["interreflections"], n_ir), _pad_ir(e["interreflections"], n_ir)
    if ir_pairing == "order":
        ir_err = np.linalg.norm(er - tr, axis=-1).sum(axis=-1)
    else:
        ir_err = _matched_ir_error(tr, er)
    err = (np.linalg.norm(e["direct"] - t["direct"], axis=-1)
           + np.linalg.norm(e["sss"] - t["sss"], axis=-1)
           + ir_err)
    ref = (np.linalg.norm(t["direct"], axis=-1) + np.linalg.norm(t["sss"], axis=-1)
           + np.linalg.norm(tr, axis=-1).sum(axis=-1))
    out = np.full(ref.shape, np.nan)
    np.divide(err, ref, out=out, where=ref > 0)
    return np.where(ref > 0, 1.0 - out, np.nan)
