"""``streaklab bench accuracy``: decomposition fidelity against noise (the paper's Fig. 3(d)),
beside what the data allow.

For each bin width, each noise type (white, pink, photon) and each noise-to-signal ratio on a
log-spaced grid from 0.001 to 0.2 (plus 0.005 and 0.055, the paper's two reference points;
or the values of ``--nsr``), the same synthetic scenes of the Fig. 3(a)-(c) kinds (d+s,
d+s+r2, d+s+r2+r3, in equal shares) are decomposed by ConvSCD and by GradBM through
:func:`decomposition.decompose`, and fitted by the oracle
(:func:`decomposition.evaluation.oracle.oracle_fit`: least squares of the true component set started at
the true parameters, a ceiling for any method) and by the same oracle on the significant
components only (``detectable``, :func:`decomposition.evaluation.oracle.significant_truth`: the ceiling of
a method that finds every component the noise leaves visible and no other).  On bin-integrated
scenes also by the ``own-model`` ceiling: the oracle with the components rendered point-sampled,
as ``decompose`` renders them; the oracle's lead over it is what that rendering costs, its lead
over a method what the method's search and model selection cost.  Scenes come from a preset of
:data:`decomposition.evaluation.synthetic.SCENE_PRESETS` (default ``paper``, the paper's parameter space,
rendered bin-integrated; ``legacy`` for the original generator, point-sampled).
``--option KEY=VALUE`` (repeatable) decomposes the ConvSCD rows with that solver option, as
``streaklab decompose --option`` takes it (``rescue=false``: without the second pass for a
misfit); it is printed and kept in ``summary.json``, and the targets are then those settings'.

Outputs in ``--out``: ``accuracy.csv`` (one row per method, bin width, noise type and NSR,
with the oracle's mean fidelity and the gap to it, and the mean fidelity with the
inter-reflections paired to the least error instead of by arrival), ``regimes.csv`` (mean fidelity of every
method and the oracle per regime, each gap with its standard error over the pixels drawn, see
:mod:`streaklab.bench.scoring`), ``flags.csv``
(precision and recall of every flag bit against pixels with fidelity < 0.5),
``accuracy.png`` (fidelity against NSR, one panel per noise type), ``regimes.png`` (the first
method's gap to the oracle in every regime row at every point, the failing targets outlined)
and ``summary.json``.
Printed: per point the regime table (method, oracle, gap +- its standard error) and each method's gap to the
detectable ceiling and to the own-model ceiling (overall and its worst regime row); for each method and noise type the
largest NSR up to which mean fidelity stays >= 0.90; each method's run time per pixel; the
paper's reference check (ConvSCD >= 0.90 at NSR 0.055 under white noise, and above GradBM at
every NSR above 0.005); and the accuracy targets against the oracle as met / not met lines
(:data:`streaklab.bench.scoring.TARGETS`), each with its worst gap's standard error and how many
of them lie between the gap and the limit (a gap within about two is not told apart from the
limit by these scenes: more ``--pixels`` or another ``--seed`` decide it).  Each gap target also
names the detectable ceiling's own worst gap and whether that meets the limit, and the line above
the list counts the unmet targets the ceiling misses as well: there the components the noise
hides cost more than the limit, so no method that reports only what the data show meets it.
Such a line also gives the method's worst gap over the rows the ceiling meets: only where that
is within the limit does the whole miss lie in rows the noise decides.
Under white noise, where the bench knows each pixel's noise, every point also reads the
unflagged wrong answers (fidelity < 0.5, no flag) against the oracle's: how many have a
penalised misfit J = chi2 + k ln n (:func:`streaklab.bench.scoring.white_noise_j`) within the
search's ``ambiguity_chi2`` (10) of the oracle's or below it -- answers the data do not tell
from the truth, which no flag built on the data can single out -- and how many leave a split
better by more than that unreached; the direct-delay target's line reads its unflagged
failures the same way.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from decomposition.options import METHODS
from streaklab.cli import CommandError

from .arguments import choices, output_folder, positive_floats
from .scoring import GAP_BEST
from .tables import write_csv

LEVEL = 0.90
TARGET_NSR = 0.055
TARGET_FLOOR_NSR = 0.005
NOISES = ("white", "pink", "photon")
#: Noise types --noise accepts besides the default three: "camera", the shot noise of one camera
#: (one photon scale for every pixel; decomposition.evaluation.synthetic_noise), where the NSR of the
#: point is that of all its pixels together.
EXTRA_NOISES = ("camera",)
# Opt-in: ConvSCD followed by the stand-alone structured_search of decomposition.stages.search
# (a prototype, not part of decompose); its time includes the ConvSCD run.
EXTRA_METHODS = ("search",)
#: the "any flag" row of the flag table: every bit of the 16-bit flags
ANY_FLAG = 0xFFFF
ORACLE = "oracle"
#: the oracle on the significant component set (decomposition.evaluation.oracle.significant_truth)
DETECTABLE = "detectable"
CEILINGS = (ORACLE, DETECTABLE)
#: the oracle in the solver's own model: the true component set, started at the truth, rendered
#: point-sampled as decompose renders it, on bin-integrated scenes (on point-sampled ones it is
#: the oracle itself, so it is left out there); the gap between it and the oracle is what the
#: model's rendering costs, the gap between a method and it what the method's search costs
OWN_MODEL = "own-model"
#: the detectable ceiling's component set fitted once more from ConvSCD's answer mapped onto it
#: (:func:`decomposition.evaluation.best_found.answer_start`, its width included), and per pixel the fit of
#: lower least-squares cost kept (:func:`decomposition.evaluation.best_found.lowest_cost`): the best fit of
#: that set the two starts find.  Started at the truth, the detectable ceiling stays in the
#: optimum nearest it; where the cost is flat (a direct and an sss onset trading light, a direct
#: narrower than a bin) no method that must find its own start is told to stop there.  The gap
#: between the detectable ceiling and this one is what that flatness costs; the gap between
#: ConvSCD and this one what ConvSCD's search costs.  Fitted where ConvSCD runs.
BEST_FOUND = GAP_BEST


def ceilings(bin_integrated: bool, best_found: bool = False) -> tuple:
    """The ceilings fitted beside the methods: the oracle, the detectable ceiling, on
    bin-integrated scenes the own-model ceiling (:data:`OWN_MODEL`), and with ``best_found``
    (ConvSCD among the methods) the best-found fit (:data:`BEST_FOUND`)."""
    return CEILINGS + ((OWN_MODEL,) if bin_integrated else ()) + ((BEST_FOUND,) if best_found else ())


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="bench-output/accuracy", help="output folder (default bench-output/accuracy)")
    parser.add_argument("--pixels", type=int, default=150,
                        help="profiles per (noise type, NSR) point, in equal shares of the kinds (default 150)")
    parser.add_argument("--quick", action="store_true",
                        help="a few seconds: 12 pixels of 128 bins at NSR 0.001, 0.055, 0.2")
    parser.add_argument("--n-bins", type=int, default=512, help="time bins per profile (default 512)")
    parser.add_argument("--time-bin-ps", default="2",
                        help="bin width(s) in ps, comma-separated, e.g. 2,4 (default 2)")
    parser.add_argument("--nsr-points", type=int, default=10,
                        help="log-spaced NSR values from 0.001 to 0.2 (default 10; 0.005 and 0.055 are added)")
    parser.add_argument("--nsr", default=None,
                        help="explicit NSR values, comma-separated (instead of the log-spaced grid)")
    parser.add_argument("--noise", default=",".join(NOISES), help="noise types, comma-separated (default the paper's three: white, pink, photon; also camera: "
                             "the shot noise of one camera, one photon scale for every pixel)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help="methods, comma-separated (default convscd,gradbm; also search: ConvSCD followed "
                             "by the stand-alone structured_search of decomposition.stages.search, six refines on every "
                             "pixel); the oracle always runs")
    parser.add_argument("--kinds", default="a,b,c", help="scene kinds (default a,b,c: Fig. 3(a)-(c))")
    parser.add_argument("--scenes", default="paper",
                        help="scene preset: paper (the paper's parameter space, default) or legacy")
    parser.add_argument("--render", choices=("bin", "point"), default=None,
                        help="bin: each bin the mean of the model over its width; point: point samples "
                             "(default bin for paper scenes, point for legacy)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of scenes and noise (default 0)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="a ConvSCD solver option, as streaklab decompose takes it (repeatable; e.g. "
                             "rescue=false): the convscd rows (and the search's base) are decomposed so")


def nsr_grid(points: int) -> np.ndarray:
    """Log-spaced NSR values from 0.001 to 0.2 plus the reference points 0.005 and 0.055."""
    if points < 2:
        raise ValueError(f"need at least 2 NSR points, got {points}")
    grid = np.concatenate([np.geomspace(0.001, 0.2, int(points)), [TARGET_FLOOR_NSR, TARGET_NSR]])
    return np.unique(np.round(grid, 12))


def largest_nsr_at_level(nsr, fidelity, level: float = LEVEL):
    """Largest NSR up to which the fidelity curve stays >= ``level``.

    Scans the grid upwards and interpolates linearly in log NSR between the last point at or
    above the level and the first point below it.

    Returns
    -------
    (value, note): ``value`` a float, or None if the curve is below the level at the first
    point; ``note`` is "interpolated", "below grid" or "above grid" (the level holds at
    every point, so the true value is at least the last NSR).
    """
    nsr = np.asarray(nsr, float)
    f = np.asarray(fidelity, float)
    order = np.argsort(nsr)
    nsr, f = nsr[order], f[order]
    below = ~(f >= level)  # NaN counts as failing
    if not below.any():
        return float(nsr[-1]), "above grid"
    i = int(np.argmax(below))
    if i == 0:
        return None, "below grid"
    x0, x1 = math.log(nsr[i - 1]), math.log(nsr[i])
    f0, f1 = f[i - 1], f[i]
    frac = 1.0 if not np.isfinite(f1) or f0 == f1 else (f0 - level) / (f0 - f1)
    return float(math.exp(x0 + min(max(frac, 0.0), 1.0) * (x1 - x0))), "interpolated"


def best_found_fit(data, seen: dict, detectable, answer: dict, time_bin_ps: float, bin_integrated: bool):
    """The :data:`BEST_FOUND` ceiling of one point: the ``seen`` component set (the detectable
    ceiling's, whose fit from the truth is ``detectable``) fitted from ``answer`` (ConvSCD's
    parameters) mapped onto it, the lower least-squares cost kept per pixel (a tie: the
    detectable ceiling's)."""
    from core.model import time_axis_ps
    from decomposition.evaluation.best_found import MATCH_WIDTHS, answer_start, lowest_cost
    from decomposition.evaluation.oracle import oracle_fit

    t = time_axis_ps(np.shape(data.noisy)[-1], time_bin_ps, data.t0_ps)
    start = answer_start(seen, answer, delay_range_ps=(float(t[0]), float(t[-1])),
                         match_ps=MATCH_WIDTHS * np.asarray(seen["direct_sigma_ps"], np.float64), widths=True)
    other = oracle_fit(data.noisy, start, time_bin_ps=time_bin_ps, t0_ps=data.t0_ps, bin_integrated=bin_integrated)
    return lowest_cost([detectable, other], cost="rss")


def _score(data, est_components, est_params, flags, noise: str):
    """Per-pixel fidelity, direct-delay failures, flags, fidelity with the inter-reflections
    paired to the least error (:func:`decomposition.model.fidelity.fidelity`, ``ir_pairing="matched"``)
    and, under white noise, the penalised misfit J in the true noise
    (:func:`streaklab.bench.scoring.white_noise_j`; None under other noise) of one estimate."""
    from decomposition.model.fidelity import fidelity

    from .scoring import direct_delay_failures, white_noise_j

    f = fidelity(data.components, est_components)
    fail = direct_delay_failures(data.params, est_params)
    matched = fidelity(data.components, est_components, ir_pairing="matched")
    j = white_noise_j(data.noisy, data.clean, est_components, est_params) if noise == "white" else None
    return f, fail, np.asarray(flags).astype(np.int64), matched, j


def measure(*, pixels: int, n_bins: int, time_bin_ps, nsrs, noises, methods, kinds, seed: int,
            scenes: str = "paper", bin_integrated: bool = True, progress=None, options=None):
    """Run the sweep.

    Parameters
    ----------
    time_bin_ps : float or sequence of float
        Bin width(s) in ps; each gets its own scenes (same seed).
    methods : sequence of str
        Solver methods (``convscd``, ``gradbm``); the oracle is always added.
    scenes : str
        Scene preset (:data:`decomposition.evaluation.synthetic.SCENE_PRESETS`).
    bin_integrated : bool
        Render the scenes bin-integrated (the oracle fits them with the same rendering).
    options : dict, optional
        Solver options of ConvSCD's ``decompose`` (the ``convscd`` rows and the ``search``
        method's base); GradBM and the ceilings never see them.

    Returns
    -------
    rows : list of dict
        One per (method, bin width, noise, NSR), oracle included.
    per_pixel : dict
        Seconds per pixel of each method.
    points : list of dict
        One per (bin width, noise, NSR): ``regimes`` (rows of
        :func:`streaklab.bench.scoring.regime_rows`), ``flags`` (precision/recall rows),
        failure counts per method (see :func:`streaklab.bench.scoring.check_targets`).
    """
    from decomposition import decompose
    from decomposition.api import FLAG_NAMES
    from core.model import render_components
    from decomposition.evaluation.oracle import oracle_fit, significant_truth
    from decomposition.stages.search import structured_search
    from decomposition.evaluation.synthetic import make_profiles

    from decomposition.options import SolverOptions

    from .scoring import POOR_FIDELITY, flag_precision_recall, regime_rows, within_data

    margin = SolverOptions().ambiguity_chi2        # the search's own bar for "very strong" evidence

    from decomposition.warmup import warm_up

    bins = [float(time_bin_ps)] if np.isscalar(time_bin_ps) else [float(t) for t in time_bin_ps]
    every = list(methods) + list(ceilings(bin_integrated, "convscd" in methods))
    solvers = sorted({"convscd" if m == "search" else m for m in methods})
    for tb in bins:  # compiling (or loading) the kernels is not part of any point's time
        for method in solvers:
            warm_up(time_bin_ps=tb, n_bins=n_bins, method=method, label="bench accuracy")
    rows, points = [], []
    spent = {m: 0.0 for m in every}
    counted = {m: 0 for m in every}
    for tb in bins:
        for noise in noises:
            for nsr in nsrs:
                data = make_profiles(pixels, n_bins, nsr=float(nsr), noise=noise, seed=seed, kinds=kinds,
                                     time_bin_ps=tb, ranges=scenes, bin_integrated=bin_integrated)
                labels = sorted(set(data.kinds.tolist()))
                scored, seconds, results = {}, {}, {}
                search_info = None
                for method in every:
                    t_start = time.perf_counter()
                    extra = 0.0
                    if method == ORACLE:
                        est = oracle_fit(data.noisy, data.params, time_bin_ps=tb, bin_integrated=bin_integrated)
                        est_params, flags = est.params, np.zeros(pixels, np.int64)
                    elif method == DETECTABLE:
                        sigma = np.std(data.noisy - data.clean, axis=-1)
                        seen = significant_truth(data.params, data.components, sigma)
                        est = detectable = oracle_fit(data.noisy, seen, time_bin_ps=tb, bin_integrated=bin_integrated)
                        est_params, flags = est.params, np.zeros(pixels, np.int64)
                    elif method == BEST_FOUND:
                        est = best_found_fit(data, seen, detectable, results["convscd"].params, tb, bin_integrated)
                        est_params, flags = est.params, np.zeros(pixels, np.int64)
                    elif method == OWN_MODEL:
                        est = oracle_fit(data.noisy, data.params, time_bin_ps=tb, bin_integrated=False)
                        est_params, flags = est.params, np.zeros(pixels, np.int64)
                    elif method == "search":
                        base = results.get("convscd")
                        if base is None:
                            base = decompose(data.noisy, time_bin_ps=tb, method="convscd", **dict(options or {}))
                        else:
                            extra = seconds["convscd"]
                        est_params, _ = structured_search(data.noisy, base.params, time_bin_ps=tb)
                        est = render_components(est_params, n_bins, tb)
                        flags = base.flags
                    else:
                        est = decompose(data.noisy, time_bin_ps=tb, method=method,
                                        **(dict(options or {}) if method == "convscd" else {}))
                        est_params, flags = est.params, est.flags
                        results[method] = est
                        if "search_wins" in est.info:
                            search_info = {"doubt": est.info["search_doubt"], "wins": est.info["search_wins"],
                                           "weighted": est.info.get("signal_weighted", 0)}
                    seconds[method] = time.perf_counter() - t_start + extra
                    spent[method] += seconds[method]
                    counted[method] += pixels
                    scored[method] = _score(data, est, est_params, flags, noise)
                f_or = scored[ORACLE][0]
                point = {"time_bin_ps": tb, "noise": noise, "nsr": float(nsr), "n": pixels,
                         "regimes": regime_rows(data.regimes, {m: scored[m][0] for m in every}, reference=ORACLE),
                         "regimes_detectable": regime_rows(data.regimes,
                                                           {m: scored[m][0] for m in every if m != ORACLE},
                                                           reference=DETECTABLE),
                         "flags": [], "search": search_info}
                if OWN_MODEL in scored:
                    point["regimes_own_model"] = regime_rows(data.regimes,
                                                             {m: scored[m][0] for m in list(methods) + [OWN_MODEL]},
                                                             reference=OWN_MODEL)
                if BEST_FOUND in scored:
                    point["regimes_best_found"] = regime_rows(data.regimes,
                                                              {m: scored[m][0] for m in list(methods) + [BEST_FOUND]},
                                                              reference=BEST_FOUND)
                # the pixels with two or more inter-reflections, by arrival and matched (the whole
                # point's means are in the rows below)
                two = np.asarray(data.regimes["n_ir"]) >= 2
                if two.any():
                    point["matched_two_ir"] = {m: (float(np.nanmean(scored[m][0][two])),
                                                   float(np.nanmean(scored[m][3][two]))) for m in every}
                j_or = scored[ORACLE][4]
                if j_or is not None:
                    point["within_data_margin"] = margin
                for method in every:
                    f, fail, flags, f_matched, j = scored[method]
                    if j is not None and method not in ceilings(True, True):
                        # the unflagged wrong answers (and direct-delay failures) the data do not
                        # tell from the truth, against those where a better split exists
                        near = within_data(j, j_or, margin)
                        poor = (f < POOR_FIDELITY) & (flags == 0)
                        point[f"unflagged_poor[{method}]"] = int(poor.sum())
                        point[f"unflagged_poor_within_data[{method}]"] = int((poor & near).sum())
                        point[f"unflagged_failures_within_data[{method}]"] = int((fail & (flags == 0) & near).sum())
                    row = {"method": method, "time_bin_ps": tb, "noise": noise, "nsr": float(nsr), "pixels": pixels,
                           "scenes": scenes, "render": "bin" if bin_integrated else "point",
                           "mean_fidelity": float(np.nanmean(f)), "median_fidelity": float(np.nanmedian(f)),
                           "p10_fidelity": float(np.nanpercentile(f, 10)),
                           "fraction_at_level": float(np.mean(f >= LEVEL)),
                           "oracle_mean_fidelity": float(np.nanmean(f_or)),
                           "gap_to_oracle": float(np.nanmean(f) - np.nanmean(f_or)),
                           "fraction_below_0.5": float(np.mean(f < POOR_FIDELITY)),
                           "mean_fidelity_matched": float(np.nanmean(f_matched)),
                           "direct_delay_failures": int(fail.sum()),
                           "unflagged_direct_delay_failures": int((fail & (flags == 0)).sum()),
                           "seconds_per_pixel": seconds[method] / pixels}
                    for lab in labels:
                        row[f"mean_fidelity[{lab}]"] = float(np.nanmean(f[data.kinds == lab]))
                    rows.append(row)
                    point[f"delay_failures[{method}]"] = row["direct_delay_failures"]
                    point[f"unflagged_failures[{method}]"] = row["unflagged_direct_delay_failures"]
                    if method not in ceilings(True, True):
                        for bit, name in sorted(FLAG_NAMES.items()):
                            point["flags"].append({"method": method, "flag": name, "bit": bit,
                                                   **flag_precision_recall(flags, bit, f)})
                        point["flags"].append({"method": method, "flag": "any", "bit": ANY_FLAG,
                                               **flag_precision_recall(flags, ANY_FLAG, f)})
                    if progress:
                        progress(row)
                points.append(point)
    per_pixel = {m: (spent[m] / counted[m] if counted[m] else float("nan")) for m in every}
    return rows, per_pixel, points


def summarise(rows, methods, noises):
    """Thresholds per (method, noise) and the target check."""
    out = {"level": LEVEL, "largest_nsr_at_level": {}, "target": {}}
    curves = {}
    for m in methods:
        for n in noises:
            sel = [r for r in rows if r["method"] == m and r["noise"] == n]
            nsr = [r["nsr"] for r in sel]
            fid = [r["mean_fidelity"] for r in sel]
            curves[(m, n)] = dict(zip(nsr, fid))
            value, note = largest_nsr_at_level(nsr, fid)
            out["largest_nsr_at_level"][f"{m}/{n}"] = {"nsr": value, "note": note}
    if ("convscd", "white") in curves:
        c = curves[("convscd", "white")]
        at = c.get(TARGET_NSR)
        out["target"]["convscd_white_fidelity_at_0.055"] = at
        out["target"]["convscd_white_at_level_at_0.055"] = bool(at is not None and at >= LEVEL)
    if ("convscd", "white") in curves and ("gradbm", "white") in curves:
        for n in noises:
            c, g = curves.get(("convscd", n), {}), curves.get(("gradbm", n), {})
            above = sorted(x for x in c if x > TARGET_FLOOR_NSR and x in g)
            losses = [x for x in above if not c[x] > g[x]]
            out["target"][f"convscd_beats_gradbm_above_0.005[{n}]"] = {"holds": not losses and bool(above),
                                                                      "nsr_where_not": losses}
    return out


def _plot(path: Path, rows, methods, noises, per_pixel):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(noises), figsize=(4.2 * len(noises), 3.6), sharey=True, squeeze=False)
    style = {"convscd": ("C0", "o"), "gradbm": ("C3", "s"), "search": ("C2", "D"), ORACLE: ("0.3", "^")}
    bins = sorted({r["time_bin_ps"] for r in rows})
    dashes = ["-", "--", ":", "-."]
    for ax, noise in zip(axes[0], noises):
        for m in list(methods) + [ORACLE]:
            for k, tb in enumerate(bins):
                sel = sorted((r["nsr"], r["mean_fidelity"]) for r in rows
                             if r["method"] == m and r["noise"] == noise and r["time_bin_ps"] == tb)
                if not sel:
                    continue
                x, y = zip(*sel)
                color, marker = style.get(m, (None, "^"))
                label = f"{m} ({per_pixel[m] * 1e3:.2g} ms/pixel)" if k == 0 else None
                if len(bins) > 1:
                    label = f"{m}, {tb:g} ps bins" + (f" ({per_pixel[m] * 1e3:.2g} ms/pixel)" if k == 0 else "")
                ax.plot(x, y, marker=marker, color=color, ls=dashes[k % len(dashes)], label=label)
        ax.axhline(LEVEL, color="0.5", lw=0.8, ls="--")
        ax.axvline(TARGET_NSR, color="0.7", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_xlabel("noise-to-signal ratio")
        ax.set_title(f"{noise} noise")
        ax.set_ylim(max(-0.05, min(0.5, ax.get_ylim()[0])), 1.02)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("mean decomposition fidelity")
    axes[0][0].legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_regimes(path: Path, points, method: str) -> None:
    """``regimes.png``: the gap of ``method`` to the oracle in every regime row (rows) at every
    point (columns), coloured, each cell with its gap and standard error; outlined where the
    row fails its target, hatched where the detectable ceiling's own gap fails it too (the
    components the noise hides cost more than the limit), hatched the other way where the
    best-found fit's does (cross-hatched where both), faded where it is not judged (fewer
    than MIN_REGIME_PIXELS pixels, or no target at that point)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.patches import Rectangle

    from .scoring import GAP_CEILING, MIN_REGIME_PIXELS, gap_matrix

    g = gap_matrix(points, method, ceiling=GAP_CEILING)
    best_failed = gap_matrix(points, method, ceiling=GAP_BEST)["ceiling_failed"]
    R, C = g["gap"].shape
    fig, ax = plt.subplots(figsize=(max(6.5, 2.6 + 0.78 * C), 1.8 + 0.34 * R))
    norm = TwoSlopeNorm(vmin=-0.15, vcenter=0.0, vmax=0.05)
    shown = np.clip(np.where(np.isfinite(g["gap"]), g["gap"], 0.0), -0.15, 0.05)
    im = ax.imshow(shown, cmap="RdBu", norm=norm, aspect="auto")
    for i in range(R):
        for j in range(C):
            if not np.isfinite(g["gap"][i, j]):
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, color="0.85"))
                continue
            faded = not g["judged"][i, j]
            if faded:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, color="white", alpha=0.6))
            se = g["se"][i, j]
            text = f"{g['gap'][i, j]:+.3f}" + (f"\n\u00b1{se:.3f}" if np.isfinite(se) else "")
            ax.text(j, i, text, ha="center", va="center", fontsize=5.5, color="0.45" if faded else "black")
            if g["failed"][i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=1.6, ec="black"))
            if g["ceiling_failed"][i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=0, hatch="////", ec="0.35"))
            if best_failed[i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=0, hatch="\\\\\\\\", ec="0.35"))
    ax.set_xticks(range(C), g["columns"], rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(R), g["rows"], fontsize=7)
    ax.set_title(f"{method} mean fidelity minus the oracle's, by regime\n(outlined: target not met; faded: not judged, "
                 f"< {MIN_REGIME_PIXELS} px or no target;\nhatched /: the {GAP_CEILING} ceiling misses it too, "
                 f"\\: the {BEST_FOUND} fit does)", fontsize=8)
    fig.colorbar(im, ax=ax, fraction=0.025, pad=0.01, label="gap to the oracle")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _overall_and_worst(rows, method: str) -> str:
    """'gap G +- se overall, worst W +- se (regime)' of ``method`` in regime rows against one
    reference (rows of :func:`streaklab.bench.scoring.regime_rows`; the worst among the judged)."""
    worst = min((r for r in rows if not r["few"] or r["regime"] == "all"), key=lambda r: r[f"gap[{method}]"])
    where = "overall" if worst["regime"] == "all" else f"{worst['regime']} {worst['bin']}"
    top = rows[0]
    return (f"gap {top[f'gap[{method}]']:+.3f} +- {top[f'gap_se[{method}]']:.3f} overall, worst "
            f"{worst[f'gap[{method}]']:+.3f} +- {worst[f'gap_se[{method}]']:.3f} ({where})")


def target_header(records: list[dict], ceiling: str) -> str:
    """The line above the target list: how many are met, and how many of the unmet gap targets
    the ``ceiling`` misses as well (records of :func:`streaklab.bench.scoring.target_records`)."""
    met = sum(r["met"] is True for r in records)
    unmet = [r for r in records if r["met"] is False]
    beyond = [r for r in unmet if r["ceiling_met"] is False]
    only = sum(r.get("met_where_ceiling_meets") is True for r in beyond)
    head = f"accuracy targets against the oracle ({met} met, {len(unmet)} not met"
    if not beyond:
        return head + (f"; none of the not met is missed by the {ceiling} ceiling as well{_best_clause(unmet)}):"
                       if unmet else "):")
    return (f"{head}; {len(beyond)} of the not met are missed by the {ceiling} ceiling as well, where the "
            f"components the noise hides cost more than the limit, and {only} of those are met in every row the "
            f"ceiling meets{_best_clause(unmet)}):")


def _best_clause(unmet: list[dict]) -> str:
    """The header's reading of the not met targets against the best-found fit (empty where no
    record carries it)."""
    read = [r for r in unmet if r.get("best_met") is not None]
    if not read:
        return ""
    missed = sum(r["best_met"] is False for r in read)
    near = sum(r.get("within_limit_of_best") is True for r in read)
    return (f"; {missed} of the not met are missed by the best-found fit as well, and in {near} convscd is "
            f"within the limit of the best-found fit in every row")


def _print_levels(summary, nsrs, prefix=""):
    for key, v in summary["largest_nsr_at_level"].items():
        m, n = key.split("/")
        if v["nsr"] is None:
            text = f"none (below {LEVEL:.2f} already at NSR {min(nsrs):g})"
        elif v["note"] == "above grid":
            text = f">= {v['nsr']:.4g} (holds over the whole grid)"
        else:
            text = f"{v['nsr']:.4g}"
        print(f"  {prefix}{m:8s} {n:6s} {text}")


def run(args) -> int:
    from decomposition.evaluation.synthetic import SCENE_PRESETS

    from .scoring import GAP_CEILING, format_regime_table, target_entry, target_line, target_records

    noises = choices(args.noise, NOISES + EXTRA_NOISES, "noise")
    methods = choices(args.methods, METHODS + EXTRA_METHODS, "methods")
    scenes = str(args.scenes).strip().lower()
    if scenes not in SCENE_PRESETS:
        raise CommandError(f"--scenes: unknown preset {args.scenes!r}; choose from {', '.join(SCENE_PRESETS)}")
    render = args.render or ("bin" if scenes == "paper" else "point")
    bins = positive_floats(args.time_bin_ps, "time-bin-ps")
    if args.quick:
        pixels, n_bins, nsrs = 12, 128, np.array([0.001, TARGET_NSR, 0.2])
    else:
        pixels, n_bins = args.pixels, args.n_bins
        try:
            nsrs = np.array(sorted(set(positive_floats(args.nsr, "nsr")))) if args.nsr else nsr_grid(args.nsr_points)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
    if pixels <= 0:
        raise CommandError(f"--pixels must be positive, got {pixels}")
    options = {}
    if args.option:
        from streaklab.commands.decompose import parse_solver_options

        options = parse_solver_options(args.option, "convscd", check_values=True)
    out = output_folder(args.out)

    def progress(r):
        print(f"  {r['method']:8s} {r['time_bin_ps']:g} ps {r['noise']:6s} NSR {r['nsr']:<8.4g} "
              f"mean fidelity {r['mean_fidelity']:7.3f}  ({r['seconds_per_pixel'] * 1e3:.3g} ms/pixel)",
              file=sys.stderr)

    print(f"accuracy: {pixels} profiles x {len(nsrs)} NSR values x {len(noises)} noise types, {n_bins} bins "
          f"of {', '.join(f'{b:g}' for b in bins)} ps, {scenes} scenes ({render}-sampled), kinds {args.kinds}, "
          f"seed {args.seed}" + (f", ConvSCD options {options}" if options else ""), file=sys.stderr)
    try:
        rows, per_pixel, points = measure(pixels=pixels, n_bins=n_bins, time_bin_ps=bins, nsrs=nsrs,
                                          noises=noises, methods=methods, kinds=args.kinds, seed=args.seed,
                                          scenes=scenes, bin_integrated=render == "bin", progress=progress,
                                          options=options)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    every = list(methods) + list(ceilings(render == "bin", "convscd" in methods))
    by_bin = {f"{tb:g}": summarise([r for r in rows if r["time_bin_ps"] == tb], every, noises) for tb in bins}
    summary = dict(by_bin[f"{bins[0]:g}"])
    targets = target_records(points) if "convscd" in methods else []
    targets += target_records(points, method="search") if "search" in methods else []
    summary.update({"by_time_bin_ps": by_bin, "seconds_per_pixel": per_pixel, "pixels": pixels, "n_bins": n_bins,
                    "time_bin_ps": bins, "nsr": [float(x) for x in nsrs], "noises": noises,
                    "methods": every, "kinds": args.kinds, "scenes": scenes, "render": render, "seed": args.seed,
                    "quick": bool(args.quick), "options": options,
                    "oracle_targets": [target_entry(r) for r in targets]})
    csv_path, png_path, json_path = out / "accuracy.csv", out / "accuracy.png", out / "summary.json"
    reg_path, flag_path = out / "regimes.csv", out / "flags.csv"
    write_csv(csv_path, rows)
    keys = ("time_bin_ps", "noise", "nsr")
    write_csv(reg_path, [{**{k: p[k] for k in keys}, **r} for p in points for r in p["regimes"]])
    write_csv(flag_path, [{**{k: p[k] for k in keys}, **r} for p in points for r in p["flags"]])
    _plot(png_path, rows, methods, noises, per_pixel)
    regimes_png = out / "regimes.png"
    _plot_regimes(regimes_png, points, "convscd" if "convscd" in methods else methods[0])
    json_path.write_text(json.dumps(summary, indent=2) + "\n")

    print("mean fidelity beside the oracle's (true component set, fitted from the truth), and the gap:")
    for p in points:
        print(f"  {p['time_bin_ps']:g} ps bins, {p['noise']} noise, NSR {p['nsr']:g} ({p['n']} pixels):")
        for line in format_regime_table(p["regimes"], every, ORACLE):
            print(line)
        if p.get("search"):
            wins = ", ".join(f"{name} {c}" for name, c in p["search"]["wins"].items())
            print(f"    ConvSCD search: {p['search']['doubt']} pixels in doubt; kept start: {wins}; "
                  f"{p['search'].get('weighted', 0)} pixels weighted for noise that follows the signal")
        for m in methods:
            print(f"    {m} against the detectable ceiling (the oracle on the significant components): "
                  f"{_overall_and_worst(p['regimes_detectable'], m)}")
            if p.get("regimes_own_model"):
                print(f"    {m} against the own-model ceiling (the oracle in decompose's point-sampled "
                      f"rendering): {_overall_and_worst(p['regimes_own_model'], m)}")
            if p.get("regimes_best_found"):
                print(f"    {m} against the best-found fit (the significant components from the truth and from "
                      f"ConvSCD's answer, the lower cost kept): {_overall_and_worst(p['regimes_best_found'], m)}")
        if p.get("matched_two_ir"):
            pairs = ", ".join(f"{m} {p['matched_two_ir'][m][1]:.3f} (by arrival {p['matched_two_ir'][m][0]:.3f})"
                              for m in every)
            print(f"    two or more inter-reflections, paired to the least error instead of by arrival "
                  f"(the bounce labels aside): {pairs}")
        fails = ", ".join(f"{m} {p[f'delay_failures[{m}]']} ({p[f'unflagged_failures[{m}]']} unflagged)"
                          for m in every)
        print(f"    direct delay error > 2 sigma: {fails}")
        for m in methods:
            if f"unflagged_poor[{m}]" in p:
                n_poor, near = p[f"unflagged_poor[{m}]"], p[f"unflagged_poor_within_data[{m}]"]
                print(f"    unflagged pixels below fidelity 0.5 ({m}): {n_poor}; {near} of them the data do not tell "
                      f"from the truth (J = chi2 + k ln n in the true noise within {p['within_data_margin']:g} of the "
                      f"oracle's, or below it), {n_poor - near} where the oracle's split is better by more")
        for fr in p["flags"]:
            if fr["flagged"] or fr["flag"] == "any":
                print(f"    flag {fr['flag']:<10s} ({fr['method']}): {fr['flagged']} flagged, {fr['poor']} with "
                      f"fidelity < 0.5; precision {fr['precision']:.2f}, recall {fr['recall']:.2f}")

    for tb in bins:
        print(f"largest NSR with mean fidelity >= {LEVEL:.2f}" + (f" ({tb:g} ps bins):" if len(bins) > 1 else ":"))
        _print_levels(by_bin[f"{tb:g}"], nsrs)
    print("run time per pixel: " + ", ".join(f"{m} {per_pixel[m] * 1e3:.3g} ms" for m in every))
    for tb in bins:
        tgt = by_bin[f"{tb:g}"]["target"]
        at = f" ({tb:g} ps bins)" if len(bins) > 1 else ""
        if "convscd_white_fidelity_at_0.055" in tgt and tgt["convscd_white_fidelity_at_0.055"] is not None:
            f55 = tgt["convscd_white_fidelity_at_0.055"]
            print(f"target: ConvSCD mean fidelity at NSR {TARGET_NSR} (white){at} = {f55:.3f} "
                  f"({'meets' if f55 >= LEVEL else 'misses'} >= {LEVEL:.2f})")
        for key, v in tgt.items():
            if key.startswith("convscd_beats_gradbm"):
                n = key[key.index("[") + 1:-1]
                detail = "yes" if v["holds"] else "no, not at NSR " + ", ".join(f"{x:.4g}" for x in v["nsr_where_not"])
                print(f"target: ConvSCD above GradBM at every NSR > {TARGET_FLOOR_NSR} ({n}){at}: {detail}")
    if targets:
        print(target_header(targets, GAP_CEILING))
        for r in targets:
            print(target_line(r))
    print(f"wrote {csv_path}, {reg_path}, {flag_path}, {png_path}, {regimes_png}, {json_path}")
    return 0
