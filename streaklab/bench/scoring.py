"""Scoring shared by the accuracy benchmarks: fidelity by regime beside the oracle's, flag
precision and recall, direct-delay failures, and the accuracy targets.

Regimes (:data:`REGIMES`) are bins of the per-pixel variables of
:func:`decomposition.evaluation.synthetic.regime_variables`: the sss peak over the direct's, the sss
onset after the direct in PSF widths, the PSF sigma in bins, the number of
inter-reflections and the weakest inter-reflection's peak over the direct's.  Each variable partitions the pixels (pixels where it is undefined, e.g.
without an sss, form an ``n/a`` row), so every variable's rows add up to the total.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "REGIMES",
    "MIN_REGIME_PIXELS",
    "POOR_FIDELITY",
    "regime_rows",
    "paired_gap_se",
    "gap_matrix",
    "within_limit",
    "flag_precision_recall",
    "direct_delay_failures",
    "TARGETS",
    "check_targets",
    "white_noise_j",
    "within_data",
    "target_records",
    "target_entry",
    "target_line",
    "worst_gap",
    "GAP_CEILING",
    "format_regime_table",
]

#: Regime rows with fewer pixels than this are marked and left out of the targets.
MIN_REGIME_PIXELS = 20
#: A pixel whose fidelity is below this counts as a failed split (for flag precision/recall).
POOR_FIDELITY = 0.5

_INF = math.inf
#: (title, regime variable, [(low, high, label), ...]) with bins low <= x < high.
REGIMES = (
    ("sss/direct peak", "sss_peak_ratio", ((0.0, 0.3, "< 0.3"), (0.3, 1.0, "0.3-1"), (1.0, _INF, ">= 1"))),
    ("sss onset (sigma)", "onset_sigma", ((-_INF, 1.0, "< 1"), (1.0, 2.0, "1-2"), (2.0, _INF, ">= 2"))),
    ("sigma (bins)", "sigma_bins", ((0.0, 1.0, "< 1"), (1.0, 2.0, "1-2"), (2.0, 4.0, "2-4"), (4.0, _INF, ">= 4"))),
    ("inter-reflections", "n_ir", ((-_INF, 0.5, "0"), (0.5, 1.5, "1"), (1.5, _INF, ">= 2"))),
    # Below 5 % of the direct's peak: under the paper's (and the solver's) relative threshold.
    ("weakest ir/direct", "ir_min_peak_ratio", ((0.0, 0.05, "< 0.05"), (0.05, _INF, ">= 0.05"))),
)


def _mean(x):
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else float("nan")


def paired_gap_se(f, f_ref) -> float:
    """Standard error of a gap between two mean fidelities on the same pixels.

    The pixels are paired (one scene, two fits), so the gap's error is that of the mean of the
    per-pixel differences, std(f - f_ref, ddof=1) / sqrt(k) over the k pixels where both are
    finite; NaN below two such pixels.  It is the spread of the scenes drawn: another seed
    moves a gap by about this much.
    """
    d = np.asarray(f, np.float64) - np.asarray(f_ref, np.float64)
    d = d[np.isfinite(d)]
    return float(d.std(ddof=1) / np.sqrt(d.size)) if d.size >= 2 else float("nan")


def regime_rows(regimes: dict, fidelities: dict, *, reference: str = "oracle",
                min_pixels: int = MIN_REGIME_PIXELS) -> list[dict]:
    """Mean fidelity of each method overall and per regime, beside the reference's, and the gap.

    Parameters
    ----------
    regimes : dict of ndarray, (N,)
        Regime variables per pixel (:func:`decomposition.evaluation.synthetic.regime_variables`).
    fidelities : dict of str -> ndarray, (N,)
        Per-pixel fidelity of each method (and of ``reference``) on the same pixels.
    reference : str
        Key of ``fidelities`` the gaps are taken to (the oracle).
    min_pixels : int
        Rows with fewer pixels are marked ``few = True``.

    Returns
    -------
    list of dict
        One row for all pixels (``regime = "all"``) then one per regime bin, each with
        ``regime``, ``bin``, ``n``, ``few``, ``fidelity[<method>]`` and, for every method other
        than the reference, ``gap[<method>]`` = its mean fidelity minus the reference's and
        ``gap_se[<method>]``, that gap's standard error (:func:`paired_gap_se`).
    """
    if reference not in fidelities:
        raise ValueError(f"reference {reference!r} is not among the methods {list(fidelities)}")
    n = len(np.asarray(fidelities[reference]))
    for m, f in fidelities.items():
        if np.shape(f) != (n,):
            raise ValueError(f"fidelity of {m!r} has shape {np.shape(f)}, expected ({n},)")

    def row(regime, label, sel):
        count = int(sel.sum())
        out = {"regime": regime, "bin": label, "n": count, "few": count < int(min_pixels)}
        for m, f in fidelities.items():
            out[f"fidelity[{m}]"] = _mean(np.asarray(f)[sel])
        for m in fidelities:
            if m != reference:
                out[f"gap[{m}]"] = out[f"fidelity[{m}]"] - out[f"fidelity[{reference}]"]
                out[f"gap_se[{m}]"] = paired_gap_se(np.asarray(fidelities[m])[sel],
                                                    np.asarray(fidelities[reference])[sel])
        return out

    rows = [row("all", "all", np.ones(n, bool))]
    for title, key, bins in REGIMES:
        x = np.asarray(regimes[key], np.float64)
        if x.shape != (n,):
            raise ValueError(f"regime variable {key!r} has shape {x.shape}, expected ({n},)")
        for lo, hi, label in bins:
            sel = (x >= lo) & (x < hi)
            if sel.any():  # empty bins (e.g. sigma >= 4 bins at 4 ps bins) are left out
                rows.append(row(title, label, sel))
        absent = ~np.isfinite(x)
        if absent.any():
            rows.append(row(title, "n/a", absent))
    return rows


def flag_precision_recall(flags, bit, fidelity, *, threshold: float = POOR_FIDELITY) -> dict:
    """How well a flag bit picks out the pixels whose fidelity is below ``threshold``.

    Parameters
    ----------
    flags : array_like of int, (N,)
        Per-pixel flag bitmasks (``DecompositionResult.flags``).
    bit : int
        The flag bit (or mask: a pixel is flagged when any of its bits is set).
    fidelity : array_like, (N,)
        Per-pixel fidelity; NaN pixels (empty truth) are left out.
    threshold : float

    Returns
    -------
    dict with ``n`` (pixels scored), ``flagged``, ``poor`` (fidelity < threshold),
    ``flagged_poor`` (both), ``precision`` = flagged_poor / flagged (NaN if nothing is
    flagged) and ``recall`` = flagged_poor / poor (NaN if no pixel is poor).
    """
    flags = np.asarray(flags).astype(np.int64)
    f = np.asarray(fidelity, np.float64)
    if flags.shape != f.shape:
        raise ValueError(f"flags {flags.shape} and fidelity {f.shape} differ in shape")
    ok = np.isfinite(f)
    flagged = ((flags & int(bit)) != 0) & ok
    poor = (f < float(threshold)) & ok
    both = int((flagged & poor).sum())
    nf, npoor = int(flagged.sum()), int(poor.sum())
    return {"n": int(ok.sum()), "flagged": nf, "poor": npoor, "flagged_poor": both,
            "precision": both / nf if nf else float("nan"), "recall": both / npoor if npoor else float("nan")}


def direct_delay_failures(truth: dict, estimate: dict, *, n_sigma: float = 2.0) -> np.ndarray:
    """Pixels with a true direct reflection whose estimate misses it or places it more than
    ``n_sigma`` true PSF widths away, shape (N,) bool."""
    t = np.asarray(truth["direct_delay_ps"], np.float64)
    e = np.asarray(estimate["direct_delay_ps"], np.float64)
    s = np.asarray(truth["direct_sigma_ps"], np.float64)
    has = np.isfinite(t)
    err = np.abs(e - t)
    return has & ~(err <= float(n_sigma) * s)


def white_noise_j(noisy, clean, components, params) -> np.ndarray:
    """(P,) the penalised misfit J = chi2 + k ln n of an answer on scenes with white noise,
    the chi2 in each pixel's own noise (the standard deviation of ``noisy - clean`` over its
    samples, which the bench knows) over all n samples, k its free parameters: the objective
    the solver's second pass and search compare answers by
    (:func:`decomposition.stages.rescue.penalised_misfit`), read here in the true noise.

    ``components``: the answer's profiles (a result, an oracle fit or a dict, as
    :func:`decomposition.model.fidelity.fidelity` takes them); ``params`` its parameter dict."""
    from decomposition.model.fidelity import component_profiles
    from decomposition.stages.rescue import penalised_misfit

    y = np.asarray(noisy, np.float64)
    c = component_profiles(components)
    model = c["direct"] + c["sss"] + c["interreflections"].sum(axis=-2)
    sigma = np.std(y - np.asarray(clean, np.float64), axis=-1)
    return penalised_misfit(np.nan_to_num(y - model), np.ones(y.shape, bool), sigma, params)


def within_data(j_method, j_oracle, margin: float) -> np.ndarray:
    """(P,) bool: answers the data do not tell from the truth -- J at most ``margin`` above the
    oracle's (the true component set fitted from the truth) or below it.  Where it is False a
    split better by more than ``margin`` exists (the oracle's) and the method did not reach it."""
    return np.asarray(j_method) <= np.asarray(j_oracle) + float(margin)


#: The accuracy targets, checked by :func:`check_targets` on the method ``convscd``:
#: (noise, NSR values, largest gap to the oracle) for the mean fidelity overall and in every
#: regime row with at least MIN_REGIME_PIXELS pixels; and, under white noise at NSR up to
#: 0.055, fewer than 1 % of pixels with a direct delay error above 2 sigma, all of them flagged.
TARGETS = {
    "gap": (("white", (0.001, 0.055, 0.11), 0.03), ("pink", (0.001, 0.055), 0.05),
            ("photon", (0.001, 0.055), 0.05)),
    "delay": {"noise": "white", "max_nsr": 0.055, "n_sigma": 2.0, "max_fraction": 0.01},
}


def within_limit(gap, limit):
    """The gap target's rule: a mean fidelity at most ``limit`` below the oracle's (arrays
    broadcast; False for a NaN gap)."""
    return np.asarray(gap) >= -np.asarray(limit)


#: The ceiling each gap target is also read against: a method that finds every component the
#: noise leaves visible and no other, fitted from the truth (``detectable`` in bench accuracy).
#: Where it misses a target as well, the target asks more than finding the visible components
#: delivers: the rest of the gap is the components the noise hides.
GAP_CEILING = "detectable"
#: The second reading of each gap target: the best-found fit of the detectable set (``best-found``
#: in bench accuracy: the truth's start and the method's answer's, the lower cost kept).  Where it
#: misses a target as well, the cost function's flat valleys and the hidden components together
#: cost more than the limit; the method's own gap to it is what the method's search costs.
GAP_BEST = "best-found"


def worst_gap(rows: list[dict], method: str):
    """The judged regime row (not ``few``) where ``method``'s gap is lowest, as
    ``(gap, regime, bin, se)`` (se NaN where the rows carry none); None where no judged row
    holds a finite gap for it."""
    worst = None
    for r in rows:
        if r["few"] or f"gap[{method}]" not in r:
            continue
        g = r[f"gap[{method}]"]
        if not np.isfinite(g):
            continue
        if worst is None or g < worst[0]:
            worst = (g, r["regime"], r["bin"], r.get(f"gap_se[{method}]", float("nan")))
    return worst


def _gap_text(worst, limit: float) -> str:
    """'worst gap G +- se (row, k se from the limit)'."""
    g, regime, b, se = worst
    where = "overall" if regime == "all" else f"{regime} {b}"
    err = f" +- {se:.3f}" if np.isfinite(se) else ""
    # how far the limit lies from the measured gap, in its standard errors: a gap within
    # about 2 of them is not told apart from the limit by these scenes
    sep = f", {abs(g + limit) / se:.1f} se from the limit" if np.isfinite(se) and se > 0 else ""
    return f"worst gap {g:+.3f}{err} ({where}{sep})"


def check_targets(points: list[dict], *, method: str = "convscd",
                  ceiling: str = GAP_CEILING) -> list[tuple[str, bool | None, str]]:
    """Check :data:`TARGETS` on measured points: ``(text, status, detail)`` of each record of
    :func:`target_records` (same arguments)."""
    return [(r["text"], r["met"], r["detail"]) for r in target_records(points, method=method, ceiling=ceiling)]


def target_records(points: list[dict], *, method: str = "convscd", ceiling: str = GAP_CEILING,
                   best: str = GAP_BEST) -> list[dict]:
    """Check :data:`TARGETS` on measured points, each target with the ceiling's own verdict.

    Parameters
    ----------
    points : list of dict
        One per (bin width, noise, NSR) with ``time_bin_ps``, ``noise``, ``nsr``, ``regimes``
        (rows of :func:`regime_rows`, with the oracle as reference), and per method
        ``delay_failures[<method>]`` and ``unflagged_failures[<method>]`` (counts) and ``n``.
    method : str
    ceiling : str
        A column of the regime rows whose own worst gap each gap target's detail names
        beside the method's, with whether it meets the limit (``the detectable ceiling: worst
        gap ..., met`` / ``not met``); left out where the rows lack it.
    best : str
        A second column read the same way (``the best-found fit: worst gap ..., met``), and the
        method's worst gap against it where the point holds ``regimes_best_found`` (regime rows
        with that column as the reference: ``method against it: worst gap ..., within the limit``
        / ``beyond the limit``); left out where the rows lack it.

    Returns
    -------
    list of dict: ``text``, ``met`` (True, False or None: not measured), ``detail``,
    ``ceiling_met`` (the ceiling's verdict on a gap target: True, False, or None where it was
    not measured or the target is not a gap target) and, where the ceiling misses it,
    ``met_where_ceiling_meets``: the method's verdict over the judged rows where the ceiling's
    own gap is within the limit (True: the whole miss lies in rows the noise decides; None
    where there is no such row or the ceiling meets the target); ``best_met`` (the ``best``
    column's verdict, None where not measured) and ``within_limit_of_best`` (the method's worst
    gap to the ``best`` column within the limit, None where not measured).
    """
    out = []
    bins = sorted({p["time_bin_ps"] for p in points})
    for noise, nsrs, limit in TARGETS["gap"]:
        for tb in bins:
            for nsr in nsrs:
                text = (f"{method} mean fidelity within {limit:g} of the oracle, {noise} noise, NSR {nsr:g}, "
                        f"{tb:g} ps bins, overall and per regime (rows >= {MIN_REGIME_PIXELS} px)")
                here = [p for p in points if p["noise"] == noise and p["time_bin_ps"] == tb
                        and math.isclose(p["nsr"], nsr)]
                if not here:
                    out.append(_record(text, None, "not measured"))
                    continue
                worst = worst_gap(here[0]["regimes"], method)
                if worst is None:
                    out.append(_record(text, None, "no regime row with enough pixels"))
                    continue
                detail, ceiling_met, met_beside = _gap_text(worst, limit), None, None
                rows = here[0]["regimes"]
                top = worst_gap(rows, ceiling) if ceiling != method else None
                if top is not None:
                    ceiling_met = bool(within_limit(top[0], limit))
                    detail += f"; the {ceiling} ceiling: {_gap_text(top, limit)}, {'met' if ceiling_met else 'not met'}"
                    if not ceiling_met:
                        # the method in the rows where the ceiling meets the limit: a miss there
                        # is the method's own, whatever the rows the noise decides
                        fair = [r for r in rows if np.isfinite(r.get(f"gap[{ceiling}]", np.nan))
                                and within_limit(r[f"gap[{ceiling}]"], limit)]
                        w = worst_gap(fair, method)
                        if w is not None:
                            met_beside = bool(within_limit(w[0], limit))
                            detail += (f"; {method} in the rows the ceiling meets: {_gap_text(w, limit)}, "
                                       f"{'met' if met_beside else 'not met'}")
                best_met = near_best = None
                top = worst_gap(rows, best) if best != method else None
                if top is not None:
                    best_met = bool(within_limit(top[0], limit))
                    detail += f"; the {best} fit: {_gap_text(top, limit)}, {'met' if best_met else 'not met'}"
                    w = worst_gap(here[0].get("regimes_best_found", []), method)
                    if w is not None:
                        near_best = bool(within_limit(w[0], limit))
                        detail += (f"; {method} against the {best} fit: {_gap_text(w, limit)}, "
                                   f"{'within' if near_best else 'beyond'} the limit")
                out.append(_record(text, bool(within_limit(worst[0], limit)), detail, ceiling_met, met_beside,
                                   best_met, near_best))
    d = TARGETS["delay"]
    for tb in bins:
        here = [p for p in points if p["noise"] == d["noise"] and p["time_bin_ps"] == tb
                and p["nsr"] <= d["max_nsr"] + 1e-12]
        text = (f"{method}: < {d['max_fraction']:.0%} of pixels with a direct delay error > {d['n_sigma']:g} sigma, "
                f"none of them unflagged, {d['noise']} noise, NSR <= {d['max_nsr']:g}, {tb:g} ps bins")
        if not here:
            out.append(_record(text, None, "not measured"))
            continue
        n = sum(p["n"] for p in here)
        bad = sum(p[f"delay_failures[{method}]"] for p in here)
        unflagged = sum(p[f"unflagged_failures[{method}]"] for p in here)
        ok = bad < d["max_fraction"] * n and unflagged == 0
        detail = f"{bad} of {n} pixels ({bad / n:.1%}), {unflagged} of them unflagged"
        key = f"unflagged_failures_within_data[{method}]"
        if unflagged and all(key in p for p in here):
            within = sum(p[key] for p in here)
            detail += (f" ({within} of those the data do not tell from the truth: J within "
                       f"{here[0]['within_data_margin']:g} of the oracle's, or below it)")
        out.append(_record(text, ok, detail))
    return out


def target_entry(record: dict) -> dict:
    """A target record as ``summary.json`` keeps it: its ``text`` under ``target``, the rest as is."""
    return {"target": record["text"], **{k: v for k, v in record.items() if k != "text"}}


def target_line(record: dict) -> str:
    """A target record as the benches print it: ``  [met] text: detail`` (``NOT met``, ``not measured``)."""
    mark = "not measured" if record["met"] is None else ("met" if record["met"] else "NOT met")
    return f"  [{mark}] {record['text']}: {record['detail']}"


def _record(text, met, detail, ceiling_met=None, met_where_ceiling_meets=None, best_met=None,
            within_limit_of_best=None) -> dict:
    return {"text": text, "met": met, "detail": detail, "ceiling_met": ceiling_met,
            "met_where_ceiling_meets": met_where_ceiling_meets, "best_met": best_met,
            "within_limit_of_best": within_limit_of_best}


def target_limit(noise: str, nsr: float) -> float:
    """The gap limit :data:`TARGETS` sets for a (noise, NSR) point, NaN where none is set."""
    for t_noise, nsrs, limit in TARGETS["gap"]:
        if t_noise == noise and any(math.isclose(nsr, x) for x in nsrs):
            return float(limit)
    return float("nan")


def gap_matrix(points: list[dict], method: str = "convscd", key: str = "regimes", ceiling: str | None = None) -> dict:
    """Every regime row's gap at every measured point, as arrays for a figure.

    Parameters
    ----------
    points : list of dict
        As for :func:`check_targets` (``time_bin_ps``, ``noise``, ``nsr`` and the rows of
        :func:`regime_rows` under ``key``).
    method : str
    key : str
        ``"regimes"`` (gaps to the oracle) or ``"regimes_detectable"``.
    ceiling : str, optional
        A column of the same rows (``"detectable"``) whose own gap is judged too.

    Returns
    -------
    dict with ``rows`` (R,) "(regime) (bin)" labels in the order of the first point, ``columns``
    (C,) "2 ps white 0.055" labels, and (R, C) arrays ``gap``, ``se`` (NaN where a point lacks
    the row), ``n`` (0 there), ``judged`` (the row counts for a target at that point: it has
    :data:`MIN_REGIME_PIXELS` pixels and the point a limit) and ``failed`` (judged and the gap
    below minus the limit); ``limit`` (C,), NaN where no target is set; with ``ceiling`` also
    ``ceiling_failed`` (R, C): judged, and the ceiling's own gap in that row below minus the
    limit (the row asks more than that ceiling delivers).
    """
    labels, seen = [], set()
    for p in points:
        for r in p[key]:
            lab = (r["regime"], r["bin"])
            if lab not in seen:
                seen.add(lab)
                labels.append(lab)
    R, C = len(labels), len(points)
    gap, se, top = np.full((R, C), np.nan), np.full((R, C), np.nan), np.full((R, C), np.nan)
    n = np.zeros((R, C), np.int64)
    few = np.ones((R, C), bool)
    limit = np.array([target_limit(p["noise"], p["nsr"]) for p in points])
    where = {lab: i for i, lab in enumerate(labels)}
    for j, p in enumerate(points):
        for r in p[key]:
            i = where[(r["regime"], r["bin"])]
            gap[i, j] = r.get(f"gap[{method}]", np.nan)
            se[i, j] = r.get(f"gap_se[{method}]", np.nan)
            if ceiling is not None:
                top[i, j] = r.get(f"gap[{ceiling}]", np.nan)
            n[i, j], few[i, j] = r["n"], r["few"]
    judged = ~few & np.isfinite(gap) & np.isfinite(limit)[None, :]
    with np.errstate(invalid="ignore"):
        failed = judged & ~within_limit(gap, limit[None, :])
        ceiling_failed = judged & np.isfinite(top) & ~within_limit(top, limit[None, :])
    columns = [f"{p['time_bin_ps']:g} ps {p['noise']} {p['nsr']:g}" for p in points]
    out = {"rows": [f"{a} {b}" if a != "all" else "all" for a, b in labels], "columns": columns,
           "gap": gap, "se": se, "n": n, "judged": judged, "failed": failed, "limit": limit}
    if ceiling is not None:
        out["ceiling_failed"] = ceiling_failed
    return out


def format_regime_table(rows: list[dict], methods, reference: str = "oracle") -> list[str]:
    """Text lines of a regime table: n, each method's mean fidelity, the reference's, and gaps."""
    others = [m for m in methods if m != reference]
    head = f"    {'regime':<18s} {'bin':<7s} {'n':>5s} " + " ".join(f"{m:>8s}" for m in others)
    head += f" {reference:>8s} " + " ".join(f"{'gap ' + m + ' +- se':>22s}" for m in others)
    lines = [head]
    for r in rows:
        mark = "*" if r["few"] else " "
        line = f"    {r['regime']:<18s} {r['bin']:<7s} {r['n']:>5d}{mark}"
        line += " ".join(f"{r[f'fidelity[{m}]']:8.3f}" for m in others)
        line += f" {r[f'fidelity[{reference}]']:8.3f} "
        line += " ".join(f"{r[f'gap[{m}]']:+14.3f} +- {r.get(f'gap_se[{m}]', float('nan')):.3f}" for m in others)
        lines.append(line)
    if any(r["few"] for r in rows):
        lines.append(f"    (* fewer than {MIN_REGIME_PIXELS} pixels: not used for the targets)")
    return lines
