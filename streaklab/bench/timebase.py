"""``streaklab bench timebase``: direct delays of a scan under trigger jitter and drift, aligned on a reference.

The same simulated scan (the example scene) is captured and decomposed three ways:

* ``steady``: a steady time base (the fiducial pulse present, no jitter, no drift),
  reconstructed without alignment: the reference;
* ``aligned``: trigger jitter (``--jitter-ps`` RMS) and drift (``--drift-ps-per-min``) over
  ``--minutes`` simulated minutes, reconstructed with every frame aligned on the reference
  ``--reference``: the fiducial pulse (``pulse``, the default), or the laser sync's measured
  trigger intervals (``sync``: the capture sets ``sync.reference``, the simulated unit measures
  each trigger with ``--reference-noise-ps`` RMS noise);
* ``unaligned``: the same capture reconstructed with ``--no-align``.

The simulator's clock is driven by the count of exposures rendered, so the scan spans exactly
``--minutes`` simulated minutes whatever the machine's speed: exposure ``k`` of ``N`` lit
exposures is taken at ``k * minutes * 60 / (N - 1)`` simulated seconds (``N`` counted on the
steady capture, which takes the same exposures).

Each cube is decomposed (ConvSCD) and its direct delays compared with the scene's truth
(``direct_delay_ps``, on the cube's time axis) over the lit pixels outside the fiducial's slit
pixels where the direct reflection is found in every cube.  Target: the aligned RMSE at most
:data:`TARGET_RATIO` times the steady one, printed as ``[met]`` or ``[NOT met]``
(:func:`streaklab.bench.scoring.target_line`); the unaligned ratio is printed beside it.  Where the
aligned reconstruction fails (the fiducial pulse leaves its band of rows: the drift and jitter
must stay within about -6 % .. +15 % of the window, see :mod:`drivers.sim.timebase`), the
benchmark says so, with the reason, and the target is not met.

Outputs in ``--out`` (default ``bench-output/timebase``): ``timebase.csv`` (one row per case),
``summary.json`` (options, rows, ratios, verdict) and the run, cube and result stores.
"""
from __future__ import annotations

import csv
import json
import math
import time

import numpy as np

from streaklab.cli import CommandError

from .arguments import output_folder

__all__ = ["TARGET_RATIO", "add_arguments", "run", "direct_delay_errors"]

#: the aligned direct-delay RMSE may be at most this multiple of the steady one
TARGET_RATIO = 1.1
CASES = ("steady", "aligned", "unaligned")
#: an error beyond this is a wrong peak taken for the direct (counted apart, still in the RMSE)
GROSS_ERROR_PS = 50.0
#: the default streak time range (synchroscan setting)
TIME_RANGE = 2


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
    parser.add_argument("--seed", type=int, default=3, help="seed of the scene, noise and jitter (default 3)")
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


def _config(args, sync=None, **simulation):
    """The scan's configuration (the simulated lab's, its calibration the simulated sweep)."""
    from acquisition.config import parse_config
    from acquisition.rig import simulated_scene

    raw = {"scan": {"start_deg": -6.0, "stop_deg": 6.0, "count": int(args.lines)},
           "camera": {"frames_per_line": int(args.frames), "time_range": int(args.time_range), "gain": 30, "acquire_timeout_s": 5.0},
           "dark": {"frames": 2}, "devices": {"timeout_s": 0.5},
           "session": {"retries": 2, "retry_backoff_s": 0.0},
           "simulation": {"seed": int(args.seed), "n_x": int(args.x), "n_t": int(args.t), "fiducial": True,
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


def direct_delay_errors(truth_ps, estimates_ps: dict, mask) -> tuple[np.ndarray, dict]:
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
    (common, stats) : the pixels counted (bool (ny, nx)) and name -> {"rmse_ps", "median_abs_ps",
    "gross" (pixels off by more than :data:`GROSS_ERROR_PS`)} (NaN where no pixel counts).
    """
    truth = np.asarray(truth_ps, np.float64)
    common = np.asarray(mask, bool).copy()
    for est in estimates_ps.values():
        common &= np.isfinite(np.asarray(est, np.float64))
    stats = {}
    for name, est in estimates_ps.items():
        err = np.asarray(est, np.float64)[common] - truth[common]
        nan = float("nan")
        stats[name] = {"rmse_ps": float(np.sqrt(np.mean(err ** 2))) if err.size else nan,
                       "median_abs_ps": float(np.median(np.abs(err))) if err.size else nan,
                       "gross": int(np.sum(np.abs(err) > GROSS_ERROR_PS))}
    return common, stats


def _finite_or_none(value):
    """``value`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")


def run(args) -> int:
    _check(args)
    from decomposition.store.pipeline import decompose_to_store
    from decomposition.store.resultstore import open_result_store
    from drivers.sim.timebase import FIDUCIAL_PIXELS
    from reconstruction.build import ReconstructionError, reconstruct

    out = output_folder(args.out)
    for name in ("steady.run.zarr", "moving.run.zarr") + tuple(f"{c}.{s}.zarr" for c in CASES for s in ("cube", "result")):
        if (out / name).exists():
            raise CommandError(f"{out / name} exists: give another --out or remove the earlier run's stores")
    t_start = time.perf_counter()
    on = "the fiducial pulse" if args.reference == "pulse" else \
        f"the laser sync's trigger intervals ({args.reference_noise_ps:g} ps RMS measurement noise)"
    print(f"timebase: {args.lines} lines x {args.x} pixels x {args.t} rows, {args.frames} frames per line; "
          f"jitter {args.jitter_ps:g} ps RMS, drift {args.drift_ps_per_min:g} ps/min over {args.minutes:g} simulated "
          f"min; aligned on {on}")

    # (a) the steady scan; it counts the lit exposures that set the clock's step for (b)
    params, steady_shifts, _ = _capture(_config(args), out / "steady.run.zarr", 0.0)
    n_exposures = int(steady_shifts.size)
    if n_exposures < 2:
        raise CommandError(f"the steady capture rendered {n_exposures} lit exposures; need at least 2")
    step_s = float(args.minutes) * 60.0 / (n_exposures - 1)
    # (b) the same scan with jitter and drift over the given simulated minutes
    reference = {} if args.reference == "pulse" else {"reference_noise_ps": float(args.reference_noise_ps)}
    moving_cfg = _config(args, sync={"reference": True} if reference else None, jitter_ps=float(args.jitter_ps),
                         drift_ps_per_min=float(args.drift_ps_per_min), **reference)
    _, shifts, times = _capture(moving_cfg, out / "moving.run.zarr", step_s)
    span_min = float(times[-1] - times[0]) / 60.0 if times.size else 0.0
    seconds_capture = time.perf_counter() - t_start

    sources = {"steady": ("steady.run.zarr", False), "aligned": ("moving.run.zarr", None),
               "unaligned": ("moving.run.zarr", False)}
    estimates, found, failures = {}, {}, {}
    t0 = time.perf_counter()
    for case, (run_name, align) in sources.items():
        try:
            reconstruct(out / run_name, out / f"{case}.cube.zarr", align=align,
                        align_on=args.reference if align is None else None)
        except ReconstructionError as exc:
            if align is False:
                raise
            failures[case] = str(exc)      # e.g. the fiducial left its band: no aligned cube, said below
            continue
        decompose_to_store(out / f"{case}.cube.zarr", out / f"{case}.result.zarr", progress=False)
        store = open_result_store(out / f"{case}.result.zarr")
        estimates[case] = np.asarray(store.group["direct_delay_ps"][...], np.float64)
    seconds_decompose = time.perf_counter() - t0

    truth = np.asarray(params["direct_delay_ps"], np.float64)
    lit = np.asarray(params["direct_amplitude"], np.float64) > 0
    lit[:, :FIDUCIAL_PIXELS] = False
    for case, est in estimates.items():
        found[case] = float(np.isfinite(est[lit]).mean()) if lit.any() else float("nan")
    common, stats = direct_delay_errors(truth, estimates, lit)
    for case in failures:
        stats[case] = {"rmse_ps": float("nan"), "median_abs_ps": float("nan"), "gross": -1}
        found[case] = float("nan")
    rmse = {c: stats[c]["rmse_ps"] for c in CASES}
    mae = {c: stats[c]["median_abs_ps"] for c in CASES}
    ratio_aligned = _ratio(rmse["aligned"], rmse["steady"])
    ratio_unaligned = _ratio(rmse["unaligned"], rmse["steady"])
    met = bool(ratio_aligned <= TARGET_RATIO)

    rows = [{"case": c, "direct_delay_rmse_ps": rmse[c], "ratio_to_steady": _ratio(rmse[c], rmse["steady"]),
             "direct_delay_median_abs_ps": mae[c], "median_abs_ratio_to_steady": _ratio(mae[c], mae["steady"]),
             f"pixels_off_by_over_{GROSS_ERROR_PS:g}ps": stats[c]["gross"],
             "direct_found_fraction": found[c], "pixels_counted": int(common.sum()),
             "failure": failures.get(c, "")} for c in CASES]
    with open(out / "timebase.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = {"options": {"jitter_ps": float(args.jitter_ps), "drift_ps_per_min": float(args.drift_ps_per_min),
                           "minutes": float(args.minutes), "lines": int(args.lines), "x": int(args.x),
                           "t": int(args.t), "frames": int(args.frames), "seed": int(args.seed),
                           "time_range": int(args.time_range), "reference": args.reference,
                           "reference_noise_ps": float(args.reference_noise_ps) if args.reference == "sync" else None},
               "lit_exposures": n_exposures, "simulated_span_min": span_min,
               "shift_rms_ps": float(np.sqrt(np.mean((shifts - shifts.mean()) ** 2))) if shifts.size else 0.0,
               "shift_range_ps": float(np.ptp(shifts)) if shifts.size else 0.0,
               "rows": rows, "ratio_aligned": ratio_aligned, "ratio_unaligned": ratio_unaligned,
               "target": {"ratio_aligned_at_most": TARGET_RATIO, "met": met,
                          "failure": failures.get("aligned", "")},
               "seconds_capture": seconds_capture, "seconds_reconstruct_decompose": seconds_decompose}
    (out / "summary.json").write_text(json.dumps(_finite_or_none(summary), indent=2, allow_nan=False) + "\n")

    print(f"{n_exposures} lit exposures over {span_min:.3g} simulated min; frame shifts: "
          f"{summary['shift_rms_ps']:.3g} ps RMS about their mean, {summary['shift_range_ps']:.3g} ps peak to peak")
    print(f"direct delay against the scene's truth over {int(common.sum())} lit pixels "
          f"(fiducial pixels excluded, direct found in every case):")
    for r in rows:
        if r["failure"]:
            print(f"  {r['case']:9s} no cube: {r['failure']}")
            continue
        print(f"  {r['case']:9s} RMSE {r['direct_delay_rmse_ps']:8.3f} ps  x{r['ratio_to_steady']:.3f} of steady;  "
              f"median |error| {r['direct_delay_median_abs_ps']:7.3f} ps  x{r['median_abs_ratio_to_steady']:.3f};  "
              f"{r[f'pixels_off_by_over_{GROSS_ERROR_PS:g}ps']} off by > {GROSS_ERROR_PS:g} ps;  "
              f"direct found in {100 * r['direct_found_fraction']:.1f}% of lit pixels")
    from .scoring import target_line

    detail = (f"the aligned reconstruction failed ({failures['aligned']})" if "aligned" in failures
              else f"x{ratio_aligned:.3f} (median |error| x{rows[1]['median_abs_ratio_to_steady']:.3f})")
    print("target:")
    print(target_line({"text": f"aligned direct-delay RMSE at most {TARGET_RATIO:g} x the steady scan's", "met": met,
                       "detail": f"{detail}; without alignment x{ratio_unaligned:.3f}"}))
    print(f"capture {seconds_capture:.1f} s, reconstruct and decompose {seconds_decompose:.1f} s; "
          f"wrote {out / 'timebase.csv'} and {out / 'summary.json'}")
    return 0
