"""``streaklab bench adaptive``: adaptive accumulation against the fixed accumulation whose worst
line reaches the same direct-delay error, on the simulated lab's example scene.

1. A fixed capture of ``--max-frames`` frames per line; each line's error
   (:func:`streaklab.adaptive.line_delay_error_ps`) after its first k frames, k = 2..max.
2. The target E: ``--target-ps``, else the median line's error at half the maximum.
3. The fixed accumulation: the fewest frames K per line at which every line's error is at most E
   (from the prefixes of step 1); it costs K x lines frames.
4. An adaptive capture (``capture --target-delay-error-ps E``, the same maximum): the frames it
   took and the share of lines that reached E.

Printed: both frame counts, the saving, the share reached, and each target (at least 95 % of
lines reach E, at least 30 % fewer frames) as ``[met]``, ``[NOT met]`` or ``[not measured]``
(:func:`streaklab.bench.scoring.target_line`, as the other benches print theirs); ``--out DIR`` also writes
``adaptive.csv`` (one row per line).
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from streaklab.cli import CommandError

REACHED_TARGET = 0.95
SAVING_TARGET = 0.30


def add_arguments(parser) -> None:
    parser.add_argument("--target-ps", type=float, default=None,
                        help="target direct-delay error E, ps (default: the median line's error at half "
                             "the maximum frames)")
    parser.add_argument("--max-frames", type=int, default=16, help="most frames a line may take (default 16)")
    parser.add_argument("--lines", type=int, default=16, help="scan lines (default 16)")
    parser.add_argument("--n-x", type=int, default=64, help="slit pixels of the simulated camera (default 64)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of the simulated lab (default 0)")
    parser.add_argument("--out", help="folder for adaptive.csv (default: none written)")


def _config(args):
    from acquisition.config import example_config_path, parse_config
    import tomllib

    with open(example_config_path("sim"), "rb") as f:
        raw = tomllib.load(f)
    raw["camera"]["frames_per_line"] = args.max_frames
    raw["scan"]["count"] = args.lines
    raw.setdefault("simulation", {}).update({"seed": args.seed, "n_x": args.n_x})
    return parse_config(raw)


def run(args) -> int:
    from acquisition.rig import run_capture
    from acquisition.runstore import open_run
    from reconstruction.build import line_calibration
    from streaklab.adaptive import DelayErrorRule, line_delay_error_ps, parse_target_error_ps

    if args.max_frames < 2 or args.lines < 1 or args.n_x < 1:
        raise CommandError("--max-frames must be at least 2, --lines and --n-x at least 1")
    if args.target_ps is not None:
        parse_target_error_ps(args.target_ps, "--target-ps")
    cfg = _config(args)
    F, n = args.max_frames, args.lines
    with tempfile.TemporaryDirectory(prefix="streaklab-bench-adaptive-") as tmp:
        run_capture(cfg, Path(tmp) / "fixed.zarr", simulate=True)
        run = open_run(Path(tmp) / "fixed.zarr")
        calib = line_calibration(run)
        streaks = run["streaks"][...]
        err = np.full((n, F + 1), np.inf)
        for k in range(2, F + 1):
            for i in range(n):
                err[i, k] = line_delay_error_ps(calib, streaks[i, :k])
        target = float(np.median(err[:, max(2, F // 2)])) if args.target_ps is None else float(args.target_ps)
        worst = err[:, 2:].max(axis=0)
        fixed_k = 2 + int(np.argmax(worst <= target)) if (worst <= target).any() else None

        rule = DelayErrorRule(target)
        run_capture(cfg, Path(tmp) / "adaptive.zarr", simulate=True, on_start=lambda s: rule.start(s.store),
                    line_good_enough=rule)
        ad = open_run(Path(tmp) / "adaptive.zarr")
        taken, reached = ad.frames_taken(), ad.target_reached()

    total = int(taken.sum())
    print(f"target direct-delay error {target:.4g} ps; {n} lines, at most {F} frames each")
    print(f"line errors at {F} frames: best {err[:, F].min():.4g} ps, worst {err[:, F].max():.4g} ps")
    print(f"adaptive: {total} frames (per line {taken.tolist()}); {reached.mean():.0%} of lines reached the target")
    if fixed_k is None:
        print(f"fixed: no frame count up to {F} brings every line to the target; the saving is not measured")
        saving = None
    else:
        saving = 1.0 - total / (fixed_k * n)
        print(f"fixed: {fixed_k} frames per line for the worst line to reach it, {fixed_k * n} frames; "
              f"adaptive takes {saving:.0%} fewer")
    from streaklab.bench.scoring import target_line

    records = [{"text": f"at least {REACHED_TARGET:.0%} of lines reach the target", "met": bool(reached.mean() >= REACHED_TARGET),
                "detail": f"{reached.mean():.0%} ({int(reached.sum())} of {n})"},
               {"text": f"at least {SAVING_TARGET:.0%} fewer frames than the fixed accumulation whose worst line reaches it",
                "met": None if saving is None else bool(saving >= SAVING_TARGET),
                "detail": ("no fixed frame count reaches it" if saving is None
                           else f"{saving:.1%} ({total} frames against {fixed_k} x {n} = {fixed_k * n})")}]
    print("targets:")
    for r in records:
        print(target_line(r))
    if args.out:
        from streaklab.bench.tables import write_csv
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "adaptive.csv", [{"line": i, "frames_taken": int(taken[i]), "target_reached": bool(reached[i]),
                                          "fixed_frames": fixed_k if fixed_k is not None else "",
                                          "error_ps_at_max_frames": float(err[i, F])} for i in range(n)])
    return 0
