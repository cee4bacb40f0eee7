"""``streaklab bench spatial``: what the whole image adds over one pixel at a time.

On spatially structured scenes (:func:`decomposition.evaluation.spatial_scenes.make_spatial_scene`:
two planes and a depth step, material patches, a corner inter-reflection, one instrument, 2 ps
bins) the columns of :data:`METHODS` decompose the same data side by side:

    per_pixel   ``decompose(profiles, 2.0)`` (``noise="poisson"`` on counts)
    spatial     ``decompose_image(profiles, 2.0, spatial=True, shared=("psf",))``
    oracle      :func:`decomposition.evaluation.oracle.oracle_fit`: the true component set, started
                at the truth, per pixel

``--methods`` picks the columns; a column whose method this build does not offer (an
:class:`decomposition.options.OptionError` from it) is printed as not available and its targets
as not measured.  Printed, each with its target and whether it is met:

1. mean fidelity, near edges (:attr:`SpatialScene.edges`) and away from them, at white NSR 0.11
   and 0.22 and at 100 and 1,000 photons per pixel (targets: spatial >= oracle + 0.02 at 0.11,
   + 0.05 at 0.22; spatial at 100 photons >= per-pixel at 1,000; near edges spatial >= per-pixel);
2. pooled echoes (:func:`decomposition.image.pooled.pooled_echoes` on the per-pixel answer, on a
   scene of at least :data:`ECHO_SCENE_MIN` pixels a side): a 1 %
   echo that one pixel cannot see (its own matched-filter significance under 5) but that is at
   least 5 sigma over 5 x 5 (the truth's) found in >= 90 % of those pixels; false echoes in
   under 1 % of the pixels without one (and, printed, outside the pool's reach of the echo);
3. spikes: 10 x single-sample spikes on bins of at least 100 expected counts of count images
   ~1,000 counts at the peak, flagged in >= 90 % by the spatial test
   (:func:`decomposition.image.pooled.refit_spikes`), beside the per-pixel SPIKE rate; no false
   SPIKE on pure Poisson draws;
4. speed: pixels per second of each column at NSR 0.11, and of per-pixel and spatial on a slice
   of ``bench speed``'s cube (target there: spatial >= 0.5 x per-pixel);
5. the demo's scene (``streaklab demo``'s simulated capture, ``--demo-lines`` lines): the
   AMBIGUOUS share (target < 5 % with spatial), its precision and recall against the pixels
   below 0.5 fidelity, and split directs (a pixel whose truth is a direct alone given an
   inter-reflection within 3 PSF widths of it; target none).

The scenes, their noise, the echo and spike scenes and the demo's capture are drawn from
``--seed`` (default 0).  ``--seeds`` (comma-separated, ranges a-b: ``0-4``; not with ``--seed``)
runs the whole bench on each seed's draw, prints each seed's table and target lines, then a table
of every target over the seeds: each seed's graded figure (spatial minus the other column's
fidelity, the speed ratio, a rate or a count) with ``met`` or ``NOT``, and on how many seeds it
is met.  One seed's figures are the same whether it runs alone or in a list.

``--out DIR`` writes ``spatial.csv`` (one row per seed, condition and column) and
``summary.json`` (the options, each target's verdict and figure per seed with the count of seeds
it is met on, and the rows).  The command exits 0: it is a report.
"""
from __future__ import annotations

import io
import tempfile
import time
from pathlib import Path

import numpy as np

from .arguments import chosen_seeds, choices, output_folder
from .scoring import target_line
from .tables import write_csv, write_json

METHODS = ("per_pixel", "spatial", "oracle")
TIME_BIN_PS = 2.0
#: (label, scene options) of the fidelity table
CONDITIONS = (("white NSR 0.11", {"nsr": 0.11}), ("white NSR 0.22", {"nsr": 0.22}),
              ("100 photons", {"photons_per_pixel": 100.0}), ("1000 photons", {"photons_per_pixel": 1000.0}))
#: the pooled-echo scene's smallest side: its echo rectangle must hold whole 5 x 5 pools
ECHO_SCENE_MIN = 24
#: the seeds run unless ``--seeds`` or ``--seed`` says otherwise
DEFAULT_SEEDS = "0"
TARGETS = {"beyond_oracle": {"white NSR 0.11": 0.02, "white NSR 0.22": 0.05}, "echo_recall": 0.90,
           "echo_false": 0.01, "echo_sigma": 5.0, "spike_recall": 0.90, "speed": 0.5, "ambiguous": 0.05}


def add_arguments(parser) -> None:
    parser.add_argument("--size", type=int, default=24, help="scene side in pixels (default 24)")
    parser.add_argument("--bins", type=int, default=256, help="time bins of 2 ps (default 256)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help=f"columns, comma-separated from {', '.join(METHODS)} (default all)")
    parser.add_argument("--echo-nsr", type=float, default=0.11,
                        help="white NSR of the pooled-echo scene (default 0.11: a 1 %% echo ~1.3 sigma in "
                             "one pixel, ~5 sigma over 5 x 5)")
    parser.add_argument("--demo-lines", type=int, default=16,
                        help="scan lines of the demo's scene (default 16, the demo's; 0: skip it)")
    parser.add_argument("--quick", action="store_true", help="16 x 16 scenes and 4 demo lines")
    parser.add_argument("--seed", type=int, default=None,
                        help=f"seed of the scenes and their noise (default {DEFAULT_SEEDS})")
    parser.add_argument("--seeds", default=None,
                        help="several seeds, each its own draw of every scene, graded apart, then a table of every "
                             "target over them (comma-separated, ranges a-b, e.g. 0-4); not with --seed")
    parser.add_argument("--out", help="folder for spatial.csv and summary.json (default: none written)")


# --------------------------------------------------------------------------- the columns

def _decompose_kwargs(scene) -> dict:
    return {"t0_ps": scene.t0_ps, **({"noise": "poisson"} if scene.noise == "counts" else {})}


def _per_pixel(scene):
    from decomposition import decompose

    return decompose(scene.profiles, scene.time_bin_ps, **_decompose_kwargs(scene))


def _spatial(scene):
    from decomposition.image import decompose_image

    return decompose_image(scene.profiles, scene.time_bin_ps, spatial=True, shared=("psf",), **_decompose_kwargs(scene))


def _oracle(scene):
    from decomposition.evaluation.oracle import oracle_fit

    return oracle_fit(scene.profiles, scene.params, time_bin_ps=scene.time_bin_ps, t0_ps=scene.t0_ps,
                      bin_integrated=scene.bin_integrated)


#: column name -> function(scene) -> an object with direct / sss / interreflections (and params)
COLUMNS = {"per_pixel": _per_pixel, "spatial": _spatial, "oracle": _oracle}


def run_column(name: str, scene) -> tuple[object, float, str | None]:
    """(answer or None, seconds, why not) of one column on one scene; a method this build does
    not offer (OptionError) is reported, not raised."""
    from decomposition.options import OptionError

    t = time.perf_counter()
    try:
        out = COLUMNS[name](scene)
    except OptionError as exc:
        return None, 0.0, str(exc)
    return out, time.perf_counter() - t, None


def fidelity_row(scene, answer) -> dict:
    """Mean fidelity over all pixels, those next to an edge and the others."""
    from decomposition.model.fidelity import fidelity

    f = fidelity(scene.components, answer)
    return {"fidelity": float(np.nanmean(f)), "edges": float(np.nanmean(f[scene.edges])),
            "away": float(np.nanmean(f[~scene.edges]))}


# --------------------------------------------------------------------------- pooled echoes

def pooled_truth_sigma(scene, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(Y, X) the truth's echo significance over the pool and in one pixel: the matched filter's
    expected peak over its noise, a sqrt(sum g^2) / sigma per pixel and summed over the aligned
    ``window`` x ``window`` neighbours (their noise added in quadrature)."""
    from decomposition.image.pooled import aligned_neighbours

    e = scene.regions["echo"]
    a = np.where(e, np.nan_to_num(scene.params["ir_amplitude"][..., 0]), 0.0)
    var = np.mean((np.asarray(scene.profiles, float) - scene.clean) ** 2, axis=-1)
    g = np.sqrt(np.sqrt(np.pi) * scene.sigma_ps / scene.time_bin_ps)
    amp, v = np.zeros(e.shape), np.zeros(e.shape)
    for _, _, (a_o, v_o) in aligned_neighbours((a, var), scene.params["direct_delay_ps"], scene.time_bin_ps, window):
        amp += a_o
        v += v_o
    return amp * g / np.sqrt(v), a * g / np.sqrt(var)


def echo_scores(scene, answer) -> dict:
    """Pooled echoes on a per-pixel answer: recall where the echo is >= 5 sigma pooled and under
    5 in one pixel, the per-pixel found rate there, false rates."""
    from scipy.ndimage import binary_dilation

    from decomposition.image.pooled import ECHO_WINDOW, pooled_echoes

    out, found, _ = pooled_echoes(scene.profiles, answer, scene.time_bin_ps, scene.t0_ps)
    pooled_sigma, own_sigma = pooled_truth_sigma(scene)
    e = scene.regions["echo"]
    target = e & (pooled_sigma >= TARGETS["echo_sigma"]) & (own_sigma < TARGETS["echo_sigma"])
    true_d = scene.params["ir_delay_ps"][..., 0]
    near = np.abs(out.params["ir_delay_ps"] - true_d[..., None]) <= 2.0 * scene.sigma_ps
    hit = found & np.any(near, axis=-1)
    before = np.any(np.abs(answer.params["ir_delay_ps"] - true_d[..., None]) <= 2.0 * scene.sigma_ps, axis=-1)
    reach = binary_dilation(e, structure=np.ones((ECHO_WINDOW, ECHO_WINDOW), bool))
    return {"pixels": int(target.sum()), "median_pooled_sigma": float(np.median(pooled_sigma[target])) if target.any() else float("nan"),
            "recall": float(hit[target].mean()) if target.any() else float("nan"),
            "per_pixel_recall": float(before[target].mean()) if target.any() else float("nan"),
            "false": float(found[~e].mean()), "false_outside_reach": float(found[~reach].mean()),
            "without": int((~e).sum())}


# --------------------------------------------------------------------------- spikes

def spike_scores(size: int, bins: int, seed: int) -> dict:
    """10 x single-sample spikes in count images ~1,000 counts at the peak: per-pixel and
    spatial SPIKE rates on the spiked pixels, and on a pure Poisson image."""
    from decomposition import decompose
    from decomposition.evaluation.spatial_scenes import make_spatial_scene
    from decomposition.flags import SPIKE
    from decomposition.image.pooled import refit_spikes

    unit = make_spatial_scene(size, size, bins, photons_per_pixel=1.0, seed=seed)
    photons = 1000.0 / float(np.median(unit.clean.max(axis=-1)))
    scene = make_spatial_scene(size, size, bins, photons_per_pixel=photons, seed=seed)
    rng = np.random.default_rng(seed + 1)
    x = np.array(scene.profiles, copy=True)
    Y, X, _ = x.shape
    hit = rng.random((Y, X)) < 0.5
    for y, xx in zip(*np.nonzero(hit)):
        i = rng.choice(np.flatnonzero(scene.clean[y, xx] >= 100.0))
        x[y, xx, i] = int(round(10.0 * scene.clean[y, xx, i]))
    kw = {"noise": "poisson", "t0_ps": scene.t0_ps}
    per = decompose(x, scene.time_bin_ps, **kw)
    spat, _, _ = refit_spikes(x, per, scene.time_bin_ps, "convscd", kw)
    pure = decompose(scene.profiles, scene.time_bin_ps, **kw)
    pure_s, _, _ = refit_spikes(scene.profiles, pure, scene.time_bin_ps, "convscd", kw)

    def rate(r, where):
        return float(((r.flags & SPIKE) > 0)[where].mean())

    return {"photons": photons, "spiked": int(hit.sum()), "per_pixel_recall": rate(per, hit),
            "spatial_recall": rate(spat, hit), "spatial_false_unspiked": rate(spat, ~hit),
            "per_pixel_false_pure": rate(pure, np.ones((Y, X), bool)),
            "spatial_false_pure": rate(pure_s, np.ones((Y, X), bool))}


# --------------------------------------------------------------------------- the demo's scene

def _warm_up(n_bins: int, spatial: bool) -> None:
    """Load the compiled kernels (numba's cache, or compile once) before anything is timed: the
    per-pixel path, and with ``spatial`` the spatial one on a small scene, floats and counts."""
    from decomposition.evaluation.spatial_scenes import make_spatial_scene
    from decomposition.warmup import warm_up

    warm_up(time_bin_ps=TIME_BIN_PS, n_bins=n_bins, quiet=True)
    for opts in (() if not spatial else ({"nsr": 0.11}, {"photons_per_pixel": 100.0})):
        scene = make_spatial_scene(12, 12, n_bins, time_bin_ps=TIME_BIN_PS, seed=0, **opts)
        _spatial(scene)


#: the slice of ``bench speed``'s cube the speed target is read on (rows, columns, bins of 2 ps)
SPEED_SHAPE = (16, 64, 512)


def speed_on_bench_speed_cube(seed: int) -> dict:
    """px/s of per-pixel ``decompose`` and ``decompose_image(spatial=True)`` (best of two each,
    after one warm call) on a slice of ``bench speed``'s synthetic cube (its generator and NSR),
    and their mean fidelities."""
    from decomposition import decompose
    from decomposition.evaluation.synthetic import make_cube
    from decomposition.image import decompose_image
    from decomposition.model.fidelity import fidelity

    data = make_cube(*SPEED_SHAPE, nsr=0.05, noise="white", seed=seed)
    x = np.asarray(data.noisy)
    n = x.shape[0] * x.shape[1]
    decompose(x[:2, :2], TIME_BIN_PS)
    decompose_image(x[:3, :3], TIME_BIN_PS, spatial=True)
    out = {}
    for name, run in (("per_pixel", lambda: decompose(x, TIME_BIN_PS)),
                      ("spatial", lambda: decompose_image(x, TIME_BIN_PS, spatial=True))):
        best = np.inf
        for _ in range(2):
            t = time.perf_counter()
            answer = run()
            best = min(best, time.perf_counter() - t)
        out[name] = n / best
        out[name + "_fidelity"] = float(np.nanmean(fidelity(data.components, answer)))
    return out


def demo_scene(lines: int, seed: int):
    """The demo's simulated capture (``streaklab demo``): (cube, time_bin_ps, t0_ps, truth components)."""
    from reconstruction.cubestore import open_cube
    from streaklab.commands.demo import _capture_cube

    with tempfile.TemporaryDirectory(prefix="streaklab-bench-spatial-") as tmp:
        path, truth, _ = _capture_cube(Path(tmp), lines=lines, nx=64, nt=256, seed=seed, stream=io.StringIO(),
                                       quiet=True)
        cube = open_cube(path)
        x = np.asarray(cube.array[:], np.float64)
        return x, float(cube.time_bin_ps), float(cube.t0_ps), {k: np.asarray(v, np.float64) for k, v in truth.items()}


def demo_scores(answer, truth: dict, time_bin_ps: float, t0_ps: float) -> dict:
    """AMBIGUOUS share, its precision / recall against the pixels below 0.5 fidelity, split directs."""
    from decomposition.flags import AMBIGUOUS
    from decomposition.model.fidelity import fidelity

    f = fidelity(truth, answer)
    amb = (answer.flags & AMBIGUOUS) > 0
    low = np.isfinite(f) & (f < 0.5)
    d_norm = np.linalg.norm(truth["direct"], axis=-1)
    alone = (d_norm > 0) & (np.linalg.norm(truth["sss"], axis=-1) <= 1e-9 * d_norm) & \
        (np.linalg.norm(truth["interreflections"], axis=(-2, -1)) <= 1e-9 * d_norm)
    peak_ps = t0_ps + time_bin_ps * np.argmax(truth["direct"], axis=-1)
    sig = np.nan_to_num(np.asarray(answer.params["direct_sigma_ps"], float), nan=4.0)
    ir = np.asarray(answer.params["ir_delay_ps"], float)
    split = alone & np.any(np.abs(ir - peak_ps[..., None]) <= 3.0 * sig[..., None], axis=-1)
    return {"pixels": int(f.size), "ambiguous": float(amb.mean()),
            "precision": float((amb & low).sum() / amb.sum()) if amb.any() else float("nan"),
            "recall": float((amb & low).sum() / low.sum()) if low.any() else float("nan"),
            "below_half": int(low.sum()), "split_directs": int(split.sum()), "direct_alone": int(alone.sum())}


# --------------------------------------------------------------------------- the report

def _fmt(v, spec=".3f"):
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def _rec(text, met, detail, value):
    """A target record: ``text``, ``met`` (bool, None: not measured), ``detail`` (the printed
    figures) and ``value`` (the one figure graded, short, for the table over seeds)."""
    return {"text": text, "met": met, "detail": detail, "value": value}


def _diff(a, b):
    return "n/a" if a is None or b is None else f"{a - b:+.3f}"


def run(args) -> int:
    from streaklab.cli import CommandError

    methods = choices(args.methods, METHODS, "methods")
    size = 16 if args.quick else int(args.size)
    demo_lines = min(4, args.demo_lines) if args.quick else int(args.demo_lines)
    if size < 12 or args.bins < 200 or demo_lines < 0:
        raise CommandError("--size must be at least 12, --bins at least 200, --demo-lines at least 0")
    if not (0 < args.echo_nsr < 1):
        raise CommandError(f"--echo-nsr must lie in (0, 1), got {args.echo_nsr!r}")
    seeds = chosen_seeds(args.seed, args.seeds, DEFAULT_SEEDS)
    out = output_folder(args.out) if args.out else None

    print(f"spatial scenes {size} x {size} x {args.bins} bins of {TIME_BIN_PS:g} ps, one PSF (sigma 4 ps); "
          f"columns: {', '.join(methods)}" + (f"; seeds {', '.join(map(str, seeds))}" if len(seeds) > 1 else ""))
    _warm_up(args.bins, spatial="spatial" in methods)
    rows, records = [], {}
    for seed in seeds:
        if len(seeds) > 1:
            print(f"seed {seed}:")
        seed_rows, records[seed] = run_seed(args, seed, methods, size, demo_lines)
        rows += [{"seed": seed, **r} for r in seed_rows]
    targets = seed_summary(records)
    if len(seeds) > 1:
        print(f"targets over {len(seeds)} seeds (the figure graded: spatial minus the other column's fidelity, "
              "spatial / per-pixel px/s, a rate or a count):")
        for line in format_seed_summary(targets, seeds):
            print(line)
    if out is not None:
        write_csv(out / "spatial.csv", rows)
        write_json(out / "summary.json", {
            "options": {"size": size, "bins": int(args.bins), "methods": methods, "echo_nsr": float(args.echo_nsr),
                        "demo_lines": demo_lines, "seeds": seeds},
            "targets": targets, "rows": rows})
    return 0


def seed_summary(records: dict) -> list[dict]:
    """One entry per target over the seeds: ``text``, ``seeds`` (per seed ``seed``, ``met``,
    ``value``, ``detail``), ``met_on`` (the seeds where it is met) and ``measured_on`` (those where
    it is measured).

    Parameters
    ----------
    records : dict seed -> list of target records (:func:`run_seed`'s, the same targets in the
        same order for every seed)
    """
    seeds = list(records)
    out = []
    for i, first in enumerate(records[seeds[0]]):
        per = [{"seed": s, **{k: records[s][i][k] for k in ("met", "value", "detail")}} for s in seeds]
        out.append({"text": first["text"], "seeds": per, "met_on": sum(p["met"] is True for p in per),
                    "measured_on": sum(p["met"] is not None for p in per)})
    return out


def format_seed_summary(targets: list[dict], seeds) -> list[str]:
    """The table over seeds: a row per target, a column per seed (its figure and ``met`` or
    ``NOT``; ``n/m`` where not measured), then "k of n seeds" it is met on (n: the seeds run)."""
    def cell(p):
        return "n/m" if p["met"] is None else f"{p['value']} {'met' if p['met'] else 'NOT'}"

    w_text = max(len("target"), *(len(t["text"]) for t in targets))
    w_cell = max(len(f"seed {max(seeds)}"), *(len(cell(p)) for t in targets for p in t["seeds"]))
    lines = [f"  {'target':<{w_text}}" + "".join(f"  {f'seed {s}':>{w_cell}}" for s in seeds) + "  met on"]
    for t in targets:
        k = "not measured" if not t["measured_on"] else f"{t['met_on']} of {len(seeds)} seeds"
        lines.append(f"  {t['text']:<{w_text}}" + "".join(f"  {cell(p):>{w_cell}}" for p in t["seeds"]) + f"  {k}")
    return lines


def run_seed(args, seed: int, methods, size: int, demo_lines: int) -> tuple[list[dict], list[dict]]:
    """The whole bench on the draws of one ``seed``, its table and target lines printed.

    Returns (rows of spatial.csv without the seed, target records :func:`_rec`), the same targets
    in the same order for every seed.
    """
    from decomposition.evaluation.spatial_scenes import make_spatial_scene

    rows, results, skipped, records = [], {}, {}, []
    print(f"{'condition':<16}" + "".join(f"{m:>30}" for m in methods))
    for label, opts in CONDITIONS:
        scene = make_spatial_scene(size, size, args.bins, time_bin_ps=TIME_BIN_PS, seed=seed, **opts)
        cells = []
        for m in methods:
            answer, seconds, why = run_column(m, scene)
            if answer is None:
                skipped[m] = why
                cells.append(f"{'not available':>30}")
                rows.append({"condition": label, "method": m, "error": why})
                continue
            r = fidelity_row(scene, answer)
            r["px_per_s"] = scene.profiles.shape[0] * scene.profiles.shape[1] / seconds if seconds > 0 else float("nan")
            results[(label, m)] = r
            rows.append({"condition": label, "method": m, **r})
            cells.append(f"{r['fidelity']:>8.3f} (edge {r['edges']:.3f} / {r['away']:.3f})")
        print(f"{label:<16}" + "".join(cells))
    for m, why in skipped.items():
        print(f"  {m}: not available in this build ({why})")

    def get(label, m, key="fidelity"):
        return results.get((label, m), {}).get(key)

    for label, margin in TARGETS["beyond_oracle"].items():
        s, o = get(label, "spatial"), get(label, "oracle")
        records.append(_rec(f"{label}: spatial >= oracle + {margin:g}", None if s is None or o is None else s >= o + margin,
                            f"spatial {_fmt(s)}, oracle {_fmt(o)}", _diff(s, o)))
    s100, p1000 = get("100 photons", "spatial"), get("1000 photons", "per_pixel")
    records.append(_rec("spatial at 100 photons >= per-pixel at 1000", None if s100 is None or p1000 is None else s100 >= p1000,
                        f"{_fmt(s100)} vs {_fmt(p1000)}", _diff(s100, p1000)))
    for label, _ in CONDITIONS:
        s, p = get(label, "spatial", "edges"), get(label, "per_pixel", "edges")
        records.append(_rec(f"{label}: near edges, spatial >= per-pixel", None if s is None or p is None else s >= p - 1e-12,
                            f"{_fmt(s)} vs {_fmt(p)}", _diff(s, p)))
    ps, pp = get("white NSR 0.11", "spatial", "px_per_s"), get("white NSR 0.11", "per_pixel", "px_per_s")
    print(f"speed at white NSR 0.11: per-pixel {_fmt(pp, '.0f')} px/s, spatial {_fmt(ps, '.0f')} px/s, "
          f"oracle {_fmt(get('white NSR 0.11', 'oracle', 'px_per_s'), '.0f')} px/s")
    speed = speed_on_bench_speed_cube(seed) if "spatial" in methods and "per_pixel" in methods else None
    if speed is not None:
        print(f"speed on bench speed's cube ({' x '.join(map(str, SPEED_SHAPE))}, white NSR 0.05, a PSF per pixel, so "
              f"spatial=True without shared): per-pixel {speed['per_pixel']:.0f} px/s, spatial {speed['spatial']:.0f} "
              f"px/s (fidelity {speed['per_pixel_fidelity']:.3f} / {speed['spatial_fidelity']:.3f})")
        rows.append({"condition": "bench speed's cube", "method": "per_pixel", "px_per_s": speed["per_pixel"]})
        rows.append({"condition": "bench speed's cube", "method": "spatial", "px_per_s": speed["spatial"]})
    records.append(_rec(f"speed on bench speed's cube: spatial >= {TARGETS['speed']:g} x per-pixel px/s",
                        None if speed is None else speed["spatial"] >= TARGETS["speed"] * speed["per_pixel"],
                        "n/a" if speed is None else f"{speed['spatial']:.0f} vs {speed['per_pixel']:.0f} px/s",
                        "n/a" if speed is None else f"x{speed['spatial'] / speed['per_pixel']:.2f}"))

    # pooled echoes, on the per-pixel answer
    echo_size = max(size, ECHO_SCENE_MIN)
    scene = make_spatial_scene(echo_size, echo_size, args.bins, time_bin_ps=TIME_BIN_PS, nsr=args.echo_nsr,
                               echo_ratio=0.01, seed=seed + 1)
    per, _, _ = run_column("per_pixel", scene)
    e = echo_scores(scene, per)
    print(f"pooled echoes (1 % echo, white NSR {args.echo_nsr:g}): {e['pixels']} pixels where it is >= 5 sigma over "
          f"5 x 5 (median {_fmt(e['median_pooled_sigma'], '.1f')}) and under 5 in one; found per pixel "
          f"{e['per_pixel_recall']:.1%}, pooled {_fmt(e['recall'], '.1%')}; false in {e['false']:.2%} of the "
          f"{e['without']} pixels without it ({e['false_outside_reach']:.2%} outside the pool's reach of it)")
    records.append(_rec(f"pooled echo found in >= {TARGETS['echo_recall']:.0%}",
                        None if not np.isfinite(e["recall"]) else e["recall"] >= TARGETS["echo_recall"],
                        _fmt(e["recall"], ".1%"), _fmt(e["recall"], ".1%")))
    records.append(_rec(f"false pooled echoes < {TARGETS['echo_false']:.0%}", e["false"] < TARGETS["echo_false"],
                        f"{e['false']:.2%}", f"{e['false']:.2%}"))
    rows.append({"condition": "pooled echoes", "method": "per_pixel+pooled", **e})

    sp = spike_scores(size, args.bins, seed + 2)
    print(f"spikes (10 x, {sp['spiked']} pixels, ~1000 counts at the peak): flagged per pixel "
          f"{sp['per_pixel_recall']:.1%}, spatial {sp['spatial_recall']:.1%}; false SPIKE on pure Poisson draws: "
          f"per pixel {sp['per_pixel_false_pure']:.2%}, spatial {sp['spatial_false_pure']:.2%}")
    records.append(_rec(f"spikes flagged in >= {TARGETS['spike_recall']:.0%}", sp["spatial_recall"] >= TARGETS["spike_recall"],
                        f"{sp['spatial_recall']:.1%}", f"{sp['spatial_recall']:.1%}"))
    records.append(_rec("no false SPIKE on pure Poisson draws", sp["spatial_false_pure"] == 0.0,
                        f"{sp['spatial_false_pure']:.2%}", f"{sp['spatial_false_pure']:.2%}"))
    rows.append({"condition": "spikes", "method": "per_pixel+spatial_spikes", **sp})

    if demo_lines:
        x, tb, t0, truth = demo_scene(demo_lines, seed)
        from types import SimpleNamespace

        demo = SimpleNamespace(profiles=x, time_bin_ps=tb, t0_ps=t0, noise="white")
        for m in [m for m in methods if m != "oracle"]:
            answer, _, why = run_column(m, demo)
            if answer is None:
                print(f"demo scene ({demo_lines} lines), {m}: not available")
                continue
            d = demo_scores(answer, truth, tb, t0)
            print(f"demo scene ({d['pixels']} pixels), {m}: AMBIGUOUS {d['ambiguous']:.1%}, precision "
                  f"{_fmt(d['precision'], '.2f')} recall {_fmt(d['recall'], '.2f')} against the {d['below_half']} "
                  f"pixels below 0.5 fidelity; split directs {d['split_directs']} of {d['direct_alone']}")
            results[("demo", m)] = d
            rows.append({"condition": "demo", "method": m, **d})
        d = results.get(("demo", "spatial"))
        records.append(_rec(f"demo --spatial: AMBIGUOUS < {TARGETS['ambiguous']:.0%}",
                            None if d is None else d["ambiguous"] < TARGETS["ambiguous"],
                            "n/a" if d is None else f"{d['ambiguous']:.1%}", "n/a" if d is None else f"{d['ambiguous']:.1%}"))
        records.append(_rec("demo --spatial: no split direct", None if d is None else d["split_directs"] == 0,
                            "n/a" if d is None else str(d["split_directs"]), "n/a" if d is None else str(d["split_directs"])))
    print("targets:")
    for r in records:
        print(target_line(r))
    return rows, records
