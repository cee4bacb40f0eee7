"""``streaklab bench live``: capture with and without ``--live``, alternated, and the live result
against the offline decomposition.

The simulated lab's default scan (the packaged example, ``--config sim``; with ``--lines N`` a
copy of it with ``scan.count = N``, written to the output folder as ``scan.toml``) is captured
``--pairs`` times without ``--live`` and as often with it, as ``streaklab capture ... --simulate
--quiet [--live RESULT.zarr]`` in a process of its own, one capture at a time.  The two captures
of a pair alternate in order (pair 1 without first, pair 2 with, ...) so that a slow drift of the
machine's load weighs on both alike; one capture without ``--live`` before the first pair warms
the page cache and is not counted (``--warmup 0``: none).

Each capture is timed from the moment its process is started to its last line on disk: the
latest modification time of the run store's ``done`` chunks, which the capture writes last for
each line (the file system's clock ticks every few ms).  What the process does after that, the
live worker's drain of its queue, is reported apart as ``drain``.  The 1-minute load average
(``os.getloadavg``) is recorded before each capture: on a busy machine the figures mean less.

Printed: each pair's two times and their ratio (with / without), the median ratio and the
spread of the ratios, the median drain; then the targets (:func:`streaklab.bench.scoring.target_line`):

* the median ratio at most :data:`TARGET_RATIO` (``--live`` costs the capture at most 5 %);
* each live result equals ``streaklab reconstruct`` then ``streaklab decompose --per-pixel --chunks 1 NX``
  of its own run byte for byte in every array (:func:`streaklab.live_decompose.differing_arrays`),
  checked after every capture is timed, so that each capture but the first follows another.

Outputs in ``--out`` (default ``bench-output/live``): ``live.csv`` (one row per capture),
``summary.json`` (options, captures, ratios, verdicts) and the run, cube and result stores.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from streaklab.cli import CommandError

from .arguments import output_folder

__all__ = ["TARGET_RATIO", "add_arguments", "run", "last_line_on_disk"]

#: a capture with ``--live`` may take at most this multiple of the time of one without it (median of the pairs)
TARGET_RATIO = 1.05
#: the folder above the ``streaklab`` package: the captures run this copy of it
ROOT = Path(__file__).resolve().parents[2]


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="bench-output/live", help="output folder (default bench-output/live)")
    parser.add_argument("--pairs", type=int, default=4,
                        help="pairs of captures, one without --live and one with it (default 4)")
    parser.add_argument("--lines", type=int, default=None,
                        help="scan lines (default: the packaged example's 16; fewer for a quick run)")
    parser.add_argument("--warmup", type=int, default=1,
                        help="captures without --live before the first pair, not counted (default 1)")
    parser.add_argument("--timeout-s", type=float, default=600.0,
                        help="longest wait for one capture, its live drain included, s (default 600)")


def _check(args) -> None:
    if args.pairs < 1:
        raise CommandError(f"--pairs must be at least 1, got {args.pairs}")
    if args.lines is not None and args.lines < 1:
        raise CommandError(f"--lines must be at least 1, got {args.lines}")
    if args.warmup < 0:
        raise CommandError(f"--warmup must be at least 0, got {args.warmup}")
    if not args.timeout_s > 0:
        raise CommandError(f"--timeout-s must be positive, got {args.timeout_s}")


def _config(out: Path, lines) -> str:
    """The ``--config`` of the captures: ``sim`` itself, or a copy with ``scan.count = lines`` in ``out``."""
    if lines is None:
        return "sim"
    import tomllib

    from acquisition.config import example_config_path, load_config

    with open(example_config_path("sim"), "rb") as f:
        raw = tomllib.load(f)
    raw["scan"]["count"] = int(lines)
    text = []
    for name, section in raw.items():
        text.append(f"[{name}]\n")
        for key, value in section.items():
            if isinstance(value, dict):
                raise CommandError(f"the packaged example has a nested table [{name}.{key}]; bench live cannot copy it")
            text.append(f"{key} = {json.dumps(value)}\n")    # strings, numbers, booleans, lists: TOML as written
    path = out / "scan.toml"
    path.write_text("".join(text))
    load_config(path)                  # checked as the captures will read it
    return str(path)


def last_line_on_disk(run_path) -> float:
    """The time the capture finished its last line: the latest modification time of the ``done``
    chunks of the run store at ``run_path`` (written after each line's data), s since the epoch."""
    from acquisition.runstore import open_run
    from core.durable import chunk_paths

    run = open_run(run_path, mode="r")
    done = np.flatnonzero(run.done_mask())
    if done.size == 0:
        raise CommandError(f"{run_path} holds no finished line")
    return max(os.stat(chunk_paths(run_path, "done", (int(i),))[0]).st_mtime for i in done)


def _capture(config: str, run_path: Path, live_path, timeout_s: float) -> dict:
    """One ``streaklab capture`` in a process of its own -> load average before, seconds to the
    last line on disk, seconds after it until the process ended (the live drain)."""
    cmd = [sys.executable, "-m", "streaklab", "capture", "--config", config, "--out", str(run_path),
           "--simulate", "--quiet"] + ([] if live_path is None else ["--live", str(live_path)])
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    load = os.getloadavg()[0]
    t0 = time.time()
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise CommandError(f"the capture into {run_path} did not end within {timeout_s:g} s (--timeout-s)") from None
    t_end = time.time()
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["no message"])[-1]
        raise CommandError(f"the capture into {run_path} ended with exit status {proc.returncode}: {last}")
    t_last = last_line_on_disk(run_path)
    return {"load_1min": load, "capture_s": t_last - t0, "drain_s": t_end - t_last}


def _offline_differences(run_path: Path, cube_path: Path, result_path: Path, live_path: Path) -> list[str]:
    """``streaklab reconstruct`` and ``streaklab decompose --per-pixel --chunks 1 NX`` of the run, compared with
    the live result -> the arrays that differ."""
    from acquisition.runstore import open_run
    from streaklab.cli import main
    from streaklab.live_decompose import differing_arrays

    nx = open_run(run_path, mode="r").image_shape[0]
    for argv in (["reconstruct", str(run_path), "--out", str(cube_path)],
                 ["decompose", str(cube_path), "--out", str(result_path), "--per-pixel", "--chunks", "1", str(nx),
                  "--quiet"]):
        said = io.StringIO()          # the commands' reports, shown only when one fails
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            status = main(argv)
        if status != 0:
            last = (said.getvalue().strip().splitlines() or ["no message"])[-1]
            raise CommandError(f"streaklab {' '.join(argv)} failed: {last}")
    return differing_arrays(live_path, result_path)


def _names(i: int) -> dict:
    p = f"pair{i}"
    return {"plain": f"{p}.plain.run.zarr", "live": f"{p}.live.run.zarr", "result": f"{p}.live.result.zarr",
            "cube": f"{p}.offline.cube.zarr", "offline": f"{p}.offline.result.zarr"}


def run(args) -> int:
    _check(args)
    from .scoring import target_line

    out = output_folder(args.out)
    names = [_names(i) for i in range(1, args.pairs + 1)]
    taken = [f"warmup{k}.run.zarr" for k in range(1, args.warmup + 1)] + [n for d in names for n in d.values()]
    for name in taken:
        if (out / name).exists():
            raise CommandError(f"{out / name} exists: give another --out or remove the earlier run's stores")
    config = _config(out, args.lines)
    print(f"live: streaklab capture --config {config} --simulate, {args.pairs} pair(s) with and without --live, "
          f"alternated ({args.warmup} warm-up capture(s) first, not counted)")
    for k in range(1, args.warmup + 1):
        _capture(config, out / f"warmup{k}.run.zarr", None, args.timeout_s)

    rows, ratios, differences = [], [], {}
    print(f"  {'pair':>4s}  {'first':5s}  {'load':>5s} {'without s':>9s}  {'load':>5s} {'with s':>8s} "
          f"{'drain s':>8s}  {'ratio':>6s}")
    for i, d in enumerate(names, start=1):
        order = ("plain", "live") if i % 2 else ("live", "plain")
        got = {}
        for mode in order:
            live_path = out / d["result"] if mode == "live" else None
            got[mode] = _capture(config, out / d[mode], live_path, args.timeout_s)
            rows.append({"pair": i, "mode": "with --live" if mode == "live" else "without", "order": order.index(mode) + 1,
                         **got[mode]})
        ratio = got["live"]["capture_s"] / got["plain"]["capture_s"]
        ratios.append(ratio)
        print(f"  {i:4d}  {'with' if order[0] == 'live' else 'w/o':5s}  {got['plain']['load_1min']:5.2f} "
              f"{got['plain']['capture_s']:9.3f}  {got['live']['load_1min']:5.2f} {got['live']['capture_s']:8.3f} "
              f"{got['live']['drain_s']:8.3f}  x{ratio:.3f}", flush=True)
    # checked once every capture is timed: no capture follows a reconstruction and decomposition here
    for i, d in enumerate(names, start=1):
        differences[i] = _offline_differences(out / d["live"], out / d["cube"], out / d["offline"], out / d["result"])

    median = float(statistics.median(ratios))
    drain = float(statistics.median(r["drain_s"] for r in rows if r["mode"] == "with --live"))
    plain = float(statistics.median(r["capture_s"] for r in rows if r["mode"] == "without"))
    speed_met = bool(median <= TARGET_RATIO)
    unequal = {i: d for i, d in differences.items() if d}
    equal_met = not unequal
    with open(out / "live.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = {"options": {"pairs": int(args.pairs), "lines": args.lines, "warmup": int(args.warmup), "config": config},
               "captures": rows, "ratios": ratios, "median_ratio": median,
               "ratio_min": float(min(ratios)), "ratio_max": float(max(ratios)),
               "median_capture_without_s": plain, "median_drain_s": drain,
               "differing_arrays": {str(i): d for i, d in differences.items()},
               "targets": {"median_ratio_at_most": TARGET_RATIO, "speed_met": speed_met, "equal_met": equal_met}}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")

    print(f"median ratio x{median:.3f} (pairs x{min(ratios):.3f} .. x{max(ratios):.3f}, "
          f"{sum(r <= TARGET_RATIO for r in ratios)} of {len(ratios)} within x{TARGET_RATIO:g}); "
          f"median capture without --live {plain:.3f} s; the live drain after the capture {drain:.3f} s (median, not counted)")
    print("targets:")
    print(target_line({"text": f"capture with --live at most {TARGET_RATIO:g} x the time without it (median of "
                               f"{len(ratios)} pair(s), start to last line on disk)", "met": speed_met,
                       "detail": f"x{median:.3f}"}))
    detail = ("every array the same" if equal_met else
              "; ".join(f"pair {i}: {', '.join(d)}" for i, d in unequal.items()))
    print(target_line({"text": "the live result equals reconstruct + decompose --per-pixel --chunks 1 NX of its run, byte for "
                               f"byte in every array (each of the {len(differences)} live run(s))",
                       "met": equal_met, "detail": detail}))
    print(f"wrote {out / 'live.csv'} and {out / 'summary.json'}")
    return 0
