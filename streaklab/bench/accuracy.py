"""``streaklab bench accuracy``: decomposition fidelity against noise (the paper's Fig. 3(d)).

For each noise type (white, pink, photon) and each noise-to-signal ratio on a log-spaced grid
from 0.001 to 0.2 (plus 0.005 and 0.055, the paper's two reference points), the same
synthetic scenes of the Fig. 3(a)-(c) kinds (d+s, d+s+r2, d+s+r2+r3, in equal shares) are
decomposed by ConvSCD and by GradBM through :func:`decomposition.decompose`, and the mean
fidelity of each method is recorded (:func:`decomposition.metrics.fidelity`).

Outputs in ``--out``: ``accuracy.csv`` (one row per method, noise type and NSR),
``accuracy.png`` (fidelity against NSR, one panel per noise type) and ``summary.json``.
Printed: for each method and noise type the largest NSR up to which mean fidelity stays
>= 0.90 (interpolated in log NSR between grid points), each method's run time per pixel,
and the target (ConvSCD >= 0.90 at NSR 0.055 under white noise, and above GradBM
at every NSR above 0.005).
"""
from __future__ import annotations

import csv
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from streaklab.cli import CommandError

LEVEL = 0.90
TARGET_NSR = 0.055
TARGET_FLOOR_NSR = 0.005
NOISES = ("white", "pink", "photon")
METHODS = ("convscd", "gradbm")


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="bench-output/accuracy", help="output folder (default bench-output/accuracy)")
    parser.add_argument("--pixels", type=int, default=150,
                        help="profiles per (noise type, NSR) point, in equal shares of the kinds (default 150)")
    parser.add_argument("--quick", action="store_true",
                        help="a few seconds: 12 pixels of 128 bins at NSR 0.001, 0.055, 0.2")
    parser.add_argument("--n-bins", type=int, default=256, help="time bins per profile (default 256)")
    parser.add_argument("--time-bin-ps", type=float, default=2.0, help="bin width in ps (default 2)")
    parser.add_argument("--nsr-points", type=int, default=10,
                        help="log-spaced NSR values from 0.001 to 0.2 (default 10; 0.005 and 0.055 are added)")
    parser.add_argument("--noise", default=",".join(NOISES), help="noise types, comma-separated (default all three)")
    parser.add_argument("--methods", default=",".join(METHODS), help="methods, comma-separated (default convscd,gradbm)")
    parser.add_argument("--kinds", default="a,b,c", help="scene kinds (default a,b,c: Fig. 3(a)-(c))")
    parser.add_argument("--seed", type=int, default=0, help="random seed of scenes and noise (default 0)")


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


def _split(text: str, allowed, what: str):
    items = [s.strip().lower() for s in text.split(",") if s.strip()]
    bad = [s for s in items if s not in allowed]
    if bad or not items:
        raise CommandError(f"--{what}: unknown {bad or 'empty list'}; choose from {', '.join(allowed)}")
    return items


def measure(*, pixels: int, n_bins: int, time_bin_ps: float, nsrs, noises, methods, kinds, seed: int,
            progress=None):
    """Run the sweep; returns (rows, seconds per pixel per method)."""
    from decomposition import decompose
    from decomposition.metrics import fidelity
    from decomposition.synthetic import make_profiles

    from decomposition.jit import warm_up

    for method in methods:  # compiling (or loading) the kernels is not part of any point's time
        warm_up(time_bin_ps=time_bin_ps, n_bins=n_bins, method=method, label="bench accuracy")
    rows = []
    spent = {m: 0.0 for m in methods}
    counted = {m: 0 for m in methods}
    for noise in noises:
        for nsr in nsrs:
            data = make_profiles(pixels, n_bins, nsr=float(nsr), noise=noise, seed=seed, kinds=kinds,
                                 time_bin_ps=time_bin_ps)
            labels = sorted(set(data.kinds.tolist()))
            for method in methods:
                t_start = time.perf_counter()
                res = decompose(data.noisy, time_bin_ps=time_bin_ps, method=method)
                dt = time.perf_counter() - t_start
                spent[method] += dt
                counted[method] += pixels
                f = fidelity(data.components, res)
                row = {"method": method, "noise": noise, "nsr": float(nsr), "pixels": pixels,
                       "mean_fidelity": float(np.nanmean(f)), "median_fidelity": float(np.nanmedian(f)),
                       "p10_fidelity": float(np.nanpercentile(f, 10)),
                       "fraction_at_level": float(np.mean(f >= LEVEL)),
                       "seconds_per_pixel": dt / pixels}
                for lab in labels:
                    row[f"mean_fidelity[{lab}]"] = float(np.nanmean(f[data.kinds == lab]))
                rows.append(row)
                if progress:
                    progress(row)
    per_pixel = {m: (spent[m] / counted[m] if counted[m] else float("nan")) for m in methods}
    return rows, per_pixel


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


def _write_csv(path: Path, rows):
    fields = []
    for r in rows:
        fields += [k for k in r if k not in fields]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def _plot(path: Path, rows, methods, noises, per_pixel):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(noises), figsize=(4.2 * len(noises), 3.6), sharey=True, squeeze=False)
    style = {"convscd": ("C0", "o"), "gradbm": ("C3", "s")}
    for ax, noise in zip(axes[0], noises):
        for m in methods:
            sel = sorted((r["nsr"], r["mean_fidelity"]) for r in rows if r["method"] == m and r["noise"] == noise)
            if not sel:
                continue
            x, y = zip(*sel)
            color, marker = style.get(m, (None, "^"))
            ax.plot(x, y, marker=marker, color=color, label=f"{m} ({per_pixel[m] * 1e3:.2g} ms/pixel)")
        ax.axhline(LEVEL, color="0.5", lw=0.8, ls="--")
        ax.axvline(TARGET_NSR, color="0.7", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_xlabel("noise-to-signal ratio")
        ax.set_title(f"{noise} noise")
        ax.set_ylim(max(-0.05, min(0.5, ax.get_ylim()[0])), 1.02)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("mean decomposition fidelity")
    axes[0][0].legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(args) -> int:
    noises = _split(args.noise, NOISES, "noise")
    methods = _split(args.methods, METHODS, "methods")
    if args.quick:
        pixels, n_bins, nsrs = 12, 128, np.array([0.001, TARGET_NSR, 0.2])
    else:
        pixels, n_bins = args.pixels, args.n_bins
        try:
            nsrs = nsr_grid(args.nsr_points)
        except ValueError as exc:
            raise CommandError(str(exc)) from None
    if pixels <= 0:
        raise CommandError(f"--pixels must be positive, got {pixels}")
    if not math.isfinite(args.time_bin_ps) or args.time_bin_ps <= 0:
        raise CommandError(f"--time-bin-ps must be positive, got {args.time_bin_ps}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CommandError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)

    def progress(r):
        print(f"  {r['method']:8s} {r['noise']:6s} NSR {r['nsr']:<8.4g} mean fidelity {r['mean_fidelity']:7.3f}"
              f"  ({r['seconds_per_pixel'] * 1e3:.3g} ms/pixel)", file=sys.stderr)

    print(f"accuracy: {pixels} profiles x {len(nsrs)} NSR values x {len(noises)} noise types, {n_bins} bins "
          f"of {args.time_bin_ps:g} ps, kinds {args.kinds}, seed {args.seed}", file=sys.stderr)
    try:
        rows, per_pixel = measure(pixels=pixels, n_bins=n_bins, time_bin_ps=args.time_bin_ps, nsrs=nsrs,
                                  noises=noises, methods=methods, kinds=args.kinds, seed=args.seed,
                                  progress=progress)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    summary = summarise(rows, methods, noises)
    summary.update({"seconds_per_pixel": per_pixel, "pixels": pixels, "n_bins": n_bins,
                    "time_bin_ps": args.time_bin_ps, "nsr": [float(x) for x in nsrs], "noises": noises,
                    "methods": methods, "kinds": args.kinds, "seed": args.seed, "quick": bool(args.quick)})
    csv_path, png_path, json_path = out / "accuracy.csv", out / "accuracy.png", out / "summary.json"
    _write_csv(csv_path, rows)
    _plot(png_path, rows, methods, noises, per_pixel)
    json_path.write_text(json.dumps(summary, indent=2) + "\n")

    print(f"largest NSR with mean fidelity >= {LEVEL:.2f}:")
    for key, v in summary["largest_nsr_at_level"].items():
        m, n = key.split("/")
        if v["nsr"] is None:
            text = f"none (below {LEVEL:.2f} already at NSR {min(nsrs):g})"
        elif v["note"] == "above grid":
            text = f">= {v['nsr']:.4g} (holds over the whole grid)"
        else:
            text = f"{v['nsr']:.4g}"
        print(f"  {m:8s} {n:6s} {text}")
    print("run time per pixel: " + ", ".join(f"{m} {per_pixel[m] * 1e3:.3g} ms" for m in methods))
    tgt = summary["target"]
    if "convscd_white_fidelity_at_0.055" in tgt and tgt["convscd_white_fidelity_at_0.055"] is not None:
        f55 = tgt["convscd_white_fidelity_at_0.055"]
        print(f"target: ConvSCD mean fidelity at NSR {TARGET_NSR} (white) = {f55:.3f} "
              f"({'meets' if f55 >= LEVEL else 'misses'} >= {LEVEL:.2f})")
    for key, v in tgt.items():
        if key.startswith("convscd_beats_gradbm"):
            n = key[key.index("[") + 1:-1]
            detail = "yes" if v["holds"] else "no, not at NSR " + ", ".join(f"{x:.4g}" for x in v["nsr_where_not"])
            print(f"target: ConvSCD above GradBM at every NSR > {TARGET_FLOOR_NSR} ({n}): {detail}")
    print(f"wrote {csv_path}, {png_path}, {json_path}")
    return 0
