"""``streaklab bench timebase``: direct delays of a scan under trigger jitter and drift, aligned on a reference.

The same simulated scan (the example scene) is captured twice and decomposed four ways:

* ``steady``: a steady time base (the fiducial pulse present, no jitter, no drift),
  reconstructed without alignment: the reference;
* ``aligned``: trigger jitter (``--jitter-ps`` RMS) and drift (``--drift-ps-per-min``) over
  ``--minutes`` simulated minutes, reconstructed with every frame aligned on the reference
  ``--reference``: the fiducial pulse (``pulse``, the default), or the laser sync's measured
  trigger intervals (``sync``: the capture sets ``sync.reference``, the simulated unit measures
  each trigger with ``--reference-noise-ps`` RMS noise);
* ``unaligned``: the same capture reconstructed with ``--no-align``;
* ``steady_aligned``: the steady capture aligned on its fiducial pulse, as ``reconstruct`` does
  by default for a run that records one: what the alignment's resampling alone costs, apart
  from the jitter and drift it undoes (printed; the target reads ``steady``).

The simulator's clock is driven by the count of exposures rendered, so the scan spans exactly
``--minutes`` simulated minutes whatever the machine's speed: exposure ``k`` of ``N`` lit
exposures is taken at ``k * minutes * 60 / (N - 1)`` simulated seconds (``N`` counted on the
steady capture, which takes the same exposures).

Each seed (``--seeds``, default :data:`DEFAULT_SEEDS`; ``--seed N`` for one) is its own draw of
the scene, its noise and the jitter, captured, reconstructed and decomposed in its own sub-folder
``seed-N`` of ``--out``.  Each cube is decomposed (ConvSCD) and its direct delays compared with
the scene's truth (``direct_delay_ps``, on the cube's time axis) over the lit pixels outside the
fiducial's slit pixels where the direct reflection is found in every cube.

The grade pools the errors of every seed's pixels (:func:`pooled_stats`): the RMSE over one
seed's ~1,000 pixels is dominated by the 0-2 pixels where a noise bump is taken for the direct
(each off by tens to hundreds of ps, in the steady scan as in the aligned one), so one seed's
ratio swings several-fold from seed to seed; pooled over several draws, those gross errors weigh
by how often they occur.  Per case the pooled RMSE, median |error| and the count of pixels off by
more than :data:`GROSS_ERROR_PS` are printed, and for each seed its own ratio and counts.  Target:
the pooled aligned RMSE at most :data:`TARGET_RATIO` times the pooled steady one, printed as
``[met]`` or ``[NOT met]`` (:func:`streaklab.bench.scoring.target_line`); the unaligned ratio is
printed beside it.  Where the aligned reconstruction of any seed fails (the fiducial pulse leaves
its band of rows: the drift and jitter must stay within about -6 % .. +15 % of the window, see
:mod:`drivers.sim.timebase`), the benchmark says so, with the reason, and the target is not met.

Outputs in ``--out`` (default ``bench-output/timebase``): ``timebase.csv`` (one row per seed and
case, then the pooled rows, ``seed`` "pooled"), ``summary.json`` (options, each seed's figures,
the pooled rows, ratios, verdict) and in ``seed-N/`` the seed's run, cube and result stores.
"""
from __future__ import annotations

import csv
import math
import time

import numpy as np

from streaklab.cli import CommandError

from .arguments import chosen_seeds, output_folder
from .tables import write_json

__all__ = ["TARGET_RATIO", "DEFAULT_SEEDS", "add_arguments", "run", "delay_errors", "error_stats",
           "direct_delay_errors", "pooled_stats"]

#: the aligned direct-delay RMSE may be at most this multiple of the steady one
TARGET_RATIO = 1.1
CASES = ("steady", "aligned", "unaligned", "steady_aligned")
#: an error beyond this is a wrong peak taken for the direct (counted apart, still in the RMSE)
GROSS_ERROR_PS = 50.0
#: the default streak time range (synchroscan setting)
TIME_RANGE = 2
#: the seeds run unless ``--seeds`` or ``--seed`` says otherwise: 8 draws, about 1.5-2 minutes on 2 cores
DEFAULT_SEEDS = "1-8"


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="bench-output/timebase", help="output folder (default bench-output/timebase)")
    parser.add_argument("--jitter-ps", type=float, default=3.0, help="RMS trigger jitter per exposure, ps (default 3)")
    parser.add_argument("--drift-ps-per-min", type=float, default=10.0,
                        help="trigger drift, ps per simulated minute (default 10)")
    parser.add_argument("--minutes", type=float, default=10.0,
                        help="simulated minutes from the first to the last exposure (default 10)")
    parser.add_argument("--lines", type=int, default=16, help="scan lines (default 16)")
    parser.add_argument("--x", type=int, default=64, help="slit pixels (default 64)")
    parser.add_argument("--t", type=int, default=256, help="streak rows (time bins, default 256)")
    parser.add_argument("--frames", type=int, default=2, help="frames per scan line (default 2)")
    parser.add_argument("--time-range", type=int, default=TIME_RANGE,
                        help=f"synchroscan time range setting 1..4 (default {TIME_RANGE}, the example scene's ~560 ps window)")
    parser.add_argument("--seeds", default=None,
                        help="seeds of the scene, noise and jitter: each its own draw, in its own sub-folder seed-N of "
                             "--out, the grade pooled over all their pixels (comma-separated, ranges a-b; "
                             f"default {DEFAULT_SEEDS})")
    parser.add_argument("--seed", type=int, default=None, help="one seed: shorthand for --seeds N")
    parser.add_argument("--reference", choices=("pulse", "sync"), default="pulse",
                        help="align on the fiducial pulse or on the laser sync's trigger intervals (default pulse)")
    parser.add_argument("--reference-noise-ps", type=float, default=0.5,
                        help="RMS noise of the simulated sync unit's trigger-interval measurement, ps "
                             "(--reference sync; default 0.5)")


def _check(args) -> None:
    for name, lo in (("lines", 2), ("x", 8), ("t", 64), ("frames", 1)):
        v = getattr(args, name)
        if v < lo:
            raise CommandError(f"--{name} must be at least {lo}, got {v}")
    if args.time_range not in (1, 2, 3, 4):
        raise CommandError(f"--time-range must be a synchroscan setting 1..4, got {args.time_range}")
    for name in ("jitter_ps", "drift_ps_per_min", "minutes"):
        v = getattr(args, name)
        if not math.isfinite(v):
            raise CommandError(f"--{name.replace('_', '-')} must be a finite number, got {v}")
    if not (math.isfinite(args.reference_noise_ps) and args.reference_noise_ps >= 0):
        raise CommandError(f"--reference-noise-ps must be a finite number >= 0, got {args.reference_noise_ps}")
    if args.jitter_ps < 0:
        raise CommandError(f"--jitter-ps must be >= 0, got {args.jitter_ps}")
    if not args.minutes > 0:
        raise CommandError(f"--minutes must be positive, got {args.minutes}")


def _config(args, seed: int, sync=None, **simulation):
    """The scan's configuration (the simulated lab's, its calibration the simulated sweep)."""
    from acquisition.config import parse_config
    from acquisition.rig import simulated_scene

    raw = {"scan": {"start_deg": -6.0, "stop_deg": 6.0, "count": int(args.lines)},
           "camera": {"frames_per_line": int(args.frames), "time_range": int(args.time_range), "gain": 30, "acquire_timeout_s": 5.0},
           "dark": {"frames": 2}, "devices": {"timeout_s": 0.5},
           "session": {"retries": 2, "retry_backoff_s": 0.0},
           "simulation": {"seed": int(seed), "n_x": int(args.x), "n_t": int(args.t), "fiducial": True,
                          "clock_speed": 1.0, **simulation},
           "calibration": {"time_poly_ps": [0.0, 1.0]}, **({"sync": sync} if sync else {})}
    from drivers.sim.scene import TIME_RANGE_SCALE, time_range_scale

    scene = simulated_scene(parse_config(raw))
    poly = scene.time_calibration * time_range_scale(args.time_range) / TIME_RANGE_SCALE[scene.time_range]
    raw["calibration"]["time_poly_ps"] = [float(c) for c in poly]
    return parse_config(raw)


def _capture(config, path, step_s: float):
    """Capture ``config`` into ``path`` on a lab whose clock advances ``step_s`` per lit exposure.

    Returns (scene params, frame shifts ps (N,), simulated times s (N,)).
    """
    from acquisition.rig import run_capture, start_simulated_lab

    holder = {}

    def wall_s() -> float:
        camera = holder.get("camera")
        return 0.0 if camera is None else step_s * len(camera.frame_shifts)

    lab = start_simulated_lab(config, wall_clock=wall_s)
    try:
        holder["camera"] = lab.camera
        result = run_capture(config, path, lab=lab)
        if result.status != "complete":
            raise CommandError(f"the simulated capture into {path} ended {result.status!r}")
        shifts = lab.frame_shifts_ps()
        times = np.array([f["sim_time_s"] for f in lab.camera.frame_shifts], dtype=np.float64)
        params = {k: np.array(v) for k, v in lab.scene.params.items()}
    finally:
        lab.close()
    return params, shifts, times


def delay_errors(truth_ps, estimates_ps: dict, mask) -> tuple[np.ndarray, dict]:
    """Direct-delay errors of each estimate over the pixels where every estimate is finite.

    Parameters
    ----------
    truth_ps : ndarray (ny, nx)
        The scene's direct delays, ps.
    estimates_ps : dict name -> ndarray (ny, nx)
        Decomposed direct delays, ps (NaN where no direct was found).
    mask : ndarray of bool (ny, nx)
        The pixels that may count (lit, outside the fiducial).

    Returns
    -------
    (common, errors) : the pixels counted (bool (ny, nx)) and name -> estimate minus truth over
    them, ps (1-D, the pixels in row-major order).
    """
    truth = np.asarray(truth_ps, np.float64)
    common = np.asarray(mask, bool).copy()
    for est in estimates_ps.values():
        common &= np.isfinite(np.asarray(est, np.float64))
    return common, {name: np.asarray(est, np.float64)[common] - truth[common] for name, est in estimates_ps.items()}


def error_stats(errors_ps) -> dict:
    """``{"rmse_ps", "median_abs_ps", "gross"}`` of direct-delay errors (ps, any shape): the RMSE,
    the median absolute error (NaN for no error) and the count off by more than
    :data:`GROSS_ERROR_PS`."""
    err = np.asarray(errors_ps, np.float64).ravel()
    nan = float("nan")
    return {"rmse_ps": float(np.sqrt(np.mean(err ** 2))) if err.size else nan,
            "median_abs_ps": float(np.median(np.abs(err))) if err.size else nan,
            "gross": int(np.sum(np.abs(err) > GROSS_ERROR_PS))}


#: the figures of a case without a cube
_NO_STATS = {"rmse_ps": float("nan"), "median_abs_ps": float("nan"), "gross": -1}


def direct_delay_errors(truth_ps, estimates_ps: dict, mask) -> tuple[np.ndarray, dict]:
    """:func:`delay_errors`' pixels counted and name -> :func:`error_stats` of its errors."""
    common, errors = delay_errors(truth_ps, estimates_ps, mask)
    return common, {name: error_stats(err) for name, err in errors.items()}


def pooled_stats(errors_by_seed) -> dict:
    """name -> :func:`error_stats` of every seed's errors of that name taken together.

    The RMSE over one seed's ~1,000 pixels rests on the 0-2 pixels where a noise bump is taken for
    the direct (each off by hundreds of ps), so it swings several-fold from seed to seed; pooled,
    each seed's gross errors weigh by their share of all the pixels.

    Parameters
    ----------
    errors_by_seed : sequence of dict name -> ndarray
        Each seed's errors (ps, :func:`delay_errors`); a name missing from a seed (no estimate
        there) has no pooled figure (NaN, gross -1).
    """
    names = list(dict.fromkeys(n for errs in errors_by_seed for n in errs))
    out = {}
    for name in names:
        if all(name in errs for errs in errors_by_seed):
            out[name] = error_stats(np.concatenate([np.asarray(errs[name], np.float64).ravel()
                                                     for errs in errors_by_seed]))
        else:
            out[name] = dict(_NO_STATS)
    return out


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")


def _seeds(args) -> list[int]:
    """The seeds to run: ``--seed N`` (one), ``--seeds`` or :data:`DEFAULT_SEEDS`."""
    return chosen_seeds(args.seed, args.seeds, DEFAULT_SEEDS)


def _store_names() -> tuple[str, ...]:
    return ("steady.run.zarr", "moving.run.zarr") + tuple(f"{c}.{s}.zarr" for c in CASES for s in ("cube", "result"))


def _run_seed(args, seed: int, folder) -> dict:
    """One seed's draw: captured steady and moving into ``folder``, reconstructed, decomposed.

    Returns a dict: ``errors`` (case -> direct-delay errors ps over the pixels counted, for the
    cases that have a cube), ``failures`` (case -> why it has no cube), ``found`` (case -> fraction
    of the lit pixels where the direct was found), ``lit`` (lit pixels outside the fiducial),
    ``pixels_counted``, ``lit_exposures``, ``simulated_span_min``, ``shift_rms_ps``,
    ``shift_range_ps``, ``seconds_capture`` and ``seconds_reconstruct_decompose``.
    """
    from decomposition.store.pipeline import decompose_to_store
    from decomposition.store.resultstore import open_result_store
    from drivers.sim.timebase import FIDUCIAL_PIXELS
    from reconstruction.build import ReconstructionError, reconstruct

    t_start = time.perf_counter()
    # (a) the steady scan; it counts the lit exposures that set the clock's step for (b)
    params, steady_shifts, _ = _capture(_config(args, seed), folder / "steady.run.zarr", 0.0)
    n_exposures = int(steady_shifts.size)
    if n_exposures < 2:
        raise CommandError(f"the steady capture of seed {seed} rendered {n_exposures} lit exposures; need at least 2")
    step_s = float(args.minutes) * 60.0 / (n_exposures - 1)
    # (b) the same scan with jitter and drift over the given simulated minutes
    reference = {} if args.reference == "pulse" else {"reference_noise_ps": float(args.reference_noise_ps)}
    moving_cfg = _config(args, seed, sync={"reference": True} if reference else None, jitter_ps=float(args.jitter_ps),
                         drift_ps_per_min=float(args.drift_ps_per_min), **reference)
    _, shifts, times = _capture(moving_cfg, folder / "moving.run.zarr", step_s)
    seconds_capture = time.perf_counter() - t_start

    sources = {"steady": ("steady.run.zarr", False), "aligned": ("moving.run.zarr", None),
               "unaligned": ("moving.run.zarr", False), "steady_aligned": ("steady.run.zarr", None)}
    estimates, failures = {}, {}
    t0 = time.perf_counter()
    for case, (run_name, align) in sources.items():
        try:
            on = ("pulse" if case == "steady_aligned" else args.reference) if align is None else None
            reconstruct(folder / run_name, folder / f"{case}.cube.zarr", align=align, align_on=on)
        except ReconstructionError as exc:
            if align is False:
                raise
            failures[case] = str(exc)      # e.g. the fiducial left its band: no aligned cube, said below
            continue
        decompose_to_store(folder / f"{case}.cube.zarr", folder / f"{case}.result.zarr", progress=False)
        store = open_result_store(folder / f"{case}.result.zarr")
        estimates[case] = np.asarray(store.group["direct_delay_ps"][...], np.float64)

    truth = np.asarray(params["direct_delay_ps"], np.float64)
    lit = np.asarray(params["direct_amplitude"], np.float64) > 0
    lit[:, :FIDUCIAL_PIXELS] = False
    common, errors = delay_errors(truth, estimates, lit)
    return {"errors": errors, "failures": failures,
            "found": {c: int(np.isfinite(est[lit]).sum()) for c, est in estimates.items()},
            "lit": int(lit.sum()), "pixels_counted": int(common.sum()), "lit_exposures": n_exposures,
            "simulated_span_min": float(times[-1] - times[0]) / 60.0 if times.size else 0.0,
            "shift_rms_ps": float(np.sqrt(np.mean((shifts - shifts.mean()) ** 2))) if shifts.size else 0.0,
            "shift_range_ps": float(np.ptp(shifts)) if shifts.size else 0.0,
            "seconds_capture": seconds_capture, "seconds_reconstruct_decompose": time.perf_counter() - t0}


def _rows(seed, stats: dict, found: dict, lit: int, pixels_counted: int, failures: dict) -> list[dict]:
    """The CSV's three rows (one per case) of one seed or of the pool (``seed`` "pooled")."""
    rmse = {c: stats[c]["rmse_ps"] for c in CASES}
    mae = {c: stats[c]["median_abs_ps"] for c in CASES}
    return [{"seed": seed, "case": c, "direct_delay_rmse_ps": rmse[c], "ratio_to_steady": _ratio(rmse[c], rmse["steady"]),
             "direct_delay_median_abs_ps": mae[c], "median_abs_ratio_to_steady": _ratio(mae[c], mae["steady"]),
             f"pixels_off_by_over_{GROSS_ERROR_PS:g}ps": stats[c]["gross"],
             "direct_found_fraction": found[c] / lit if c in found and lit else float("nan"),
             "pixels_counted": pixels_counted, "failure": failures.get(c, "")} for c in CASES]


def run(args) -> int:
    _check(args)
    seeds = _seeds(args)
    out = output_folder(args.out)
    for seed in seeds:
        folder = out / f"seed-{seed}"
        if folder.exists() and not folder.is_dir():
            raise CommandError(f"{folder} exists and is not a folder: give another --out or remove it")
        for name in _store_names():
            if (folder / name).exists():
                raise CommandError(f"{folder / name} exists: give another --out or remove the earlier run's stores")
    on = "the fiducial pulse" if args.reference == "pulse" else \
        f"the laser sync's trigger intervals ({args.reference_noise_ps:g} ps RMS measurement noise)"
    print(f"timebase: {args.lines} lines x {args.x} pixels x {args.t} rows, {args.frames} frames per line; "
          f"jitter {args.jitter_ps:g} ps RMS, drift {args.drift_ps_per_min:g} ps/min over {args.minutes:g} simulated "
          f"min; aligned on {on}; seeds {', '.join(map(str, seeds))}, each in {out}/seed-N")

    per_seed, errors_by_seed, rows = [], [], []
    gross = f"pixels_off_by_over_{GROSS_ERROR_PS:g}ps"
    for seed in seeds:
        folder = output_folder(out / f"seed-{seed}")
        r = _run_seed(args, seed, folder)
        stats = {c: error_stats(r["errors"][c]) if c in r["errors"] else _NO_STATS for c in CASES}
        seed_rows = _rows(seed, stats, r["found"], r["lit"], r["pixels_counted"], r["failures"])
        rows += seed_rows
        errors_by_seed.append(r["errors"])
        entry = {"seed": seed, **{k: r[k] for k in ("lit_exposures", "simulated_span_min", "shift_rms_ps",
                                                    "shift_range_ps", "pixels_counted", "seconds_capture",
                                                    "seconds_reconstruct_decompose")},
                 "ratio_aligned": seed_rows[1]["ratio_to_steady"], "ratio_unaligned": seed_rows[2]["ratio_to_steady"],
                 "failures": r["failures"], "found": r["found"], "lit": r["lit"]}
        per_seed.append(entry)
        counts = ", ".join(f"{c} {row[gross]}" for c, row in zip(CASES, seed_rows) if not row["failure"])
        aligned = (f"aligned no cube: {r['failures']['aligned']}" if "aligned" in r["failures"] else
                   f"aligned RMSE x{entry['ratio_aligned']:.3f} of steady ({seed_rows[1]['direct_delay_rmse_ps']:.3f} "
                   f"against {seed_rows[0]['direct_delay_rmse_ps']:.3f} ps)")
        print(f"  seed {seed}: {aligned}; off by > {GROSS_ERROR_PS:g} ps: {counts}; {r['pixels_counted']} pixels, "
              f"{r['lit_exposures']} lit exposures over {r['simulated_span_min']:.3g} simulated min, frame shifts "
              f"{r['shift_rms_ps']:.3g} ps RMS, {r['shift_range_ps']:.3g} ps peak to peak; "
              f"{r['seconds_capture'] + r['seconds_reconstruct_decompose']:.1f} s", flush=True)

    pooled_failures = {}
    for entry in per_seed:
        for case, why in entry["failures"].items():
            pooled_failures.setdefault(case, f"seed {entry['seed']}: {why}")
    found = {c: sum(e["found"][c] for e in per_seed) for c in CASES if all(c in e["found"] for e in per_seed)}
    pooled = pooled_stats(errors_by_seed)       # a case without a cube in some seed: NaN, said below
    pooled = {c: pooled.get(c, _NO_STATS) for c in CASES}
    n_counted = sum(e["pixels_counted"] for e in per_seed)
    pooled_rows = _rows("pooled", pooled, found, sum(e["lit"] for e in per_seed), n_counted, pooled_failures)
    rows += pooled_rows
    ratio_aligned = pooled_rows[1]["ratio_to_steady"]
    ratio_unaligned = pooled_rows[2]["ratio_to_steady"]
    met = bool(ratio_aligned <= TARGET_RATIO)
    seconds_capture = sum(e["seconds_capture"] for e in per_seed)
    seconds_decompose = sum(e["seconds_reconstruct_decompose"] for e in per_seed)

    with open(out / "timebase.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    seed_ratios = [e["ratio_aligned"] for e in per_seed]
    summary = {"options": {"jitter_ps": float(args.jitter_ps), "drift_ps_per_min": float(args.drift_ps_per_min),
                           "minutes": float(args.minutes), "lines": int(args.lines), "x": int(args.x),
                           "t": int(args.t), "frames": int(args.frames), "seeds": seeds,
                           "time_range": int(args.time_range), "reference": args.reference,
                           "reference_noise_ps": float(args.reference_noise_ps) if args.reference == "sync" else None},
               "seeds": per_seed, "rows": pooled_rows, "per_seed_rows": rows[:-len(CASES)],
               "pixels_counted": n_counted, "ratio_aligned": ratio_aligned, "ratio_unaligned": ratio_unaligned,
               "target": {"ratio_aligned_at_most": TARGET_RATIO, "pooled_over_seeds": len(seeds), "met": met,
                          "failure": pooled_failures.get("aligned", "")},
               "seconds_capture": seconds_capture, "seconds_reconstruct_decompose": seconds_decompose}
    write_json(out / "summary.json", summary)

    print(f"pooled over {len(seeds)} seed{'s' if len(seeds) > 1 else ''}: direct delay against the scenes' truth over "
          f"{n_counted} lit pixels (fiducial pixels excluded, direct found in every case):")
    for r in pooled_rows:
        if r["failure"]:
            print(f"  {r['case']:14s} no cube: {r['failure']}")
            continue
        print(f"  {r['case']:14s} RMSE {r['direct_delay_rmse_ps']:8.3f} ps  x{r['ratio_to_steady']:.3f} of steady;  "
              f"median |error| {r['direct_delay_median_abs_ps']:7.3f} ps  x{r['median_abs_ratio_to_steady']:.3f};  "
              f"{r[gross]} off by > {GROSS_ERROR_PS:g} ps;  "
              f"direct found in {100 * r['direct_found_fraction']:.1f}% of lit pixels")
    from .scoring import target_line

    finite = [x for x in seed_ratios if math.isfinite(x)]
    spread = (f"; seeds x{min(finite):.2f} .. x{max(finite):.2f}, {sum(x <= TARGET_RATIO for x in finite)} of "
              f"{len(seeds)} at most {TARGET_RATIO:g}" if len(seeds) > 1 and finite else "")
    detail = (f"the aligned reconstruction failed ({pooled_failures['aligned']})" if "aligned" in pooled_failures
              else f"x{ratio_aligned:.3f} pooled over {len(seeds)} seed{'s' if len(seeds) > 1 else ''} "
                   f"(median |error| x{pooled_rows[1]['median_abs_ratio_to_steady']:.3f}{spread})")
    print("target:")
    print(target_line({"text": f"aligned direct-delay RMSE at most {TARGET_RATIO:g} x the steady scan's", "met": met,
                       "detail": f"{detail}; without alignment x{ratio_unaligned:.3f}"}))
    print(f"capture {seconds_capture:.1f} s, reconstruct and decompose {seconds_decompose:.1f} s; "
          f"wrote {out / 'timebase.csv'} and {out / 'summary.json'}")
    return 0
