"""``streaklab bench speed``: pixels per second of ``streaklab decompose`` on a synthetic cube.

A seeded synthetic cube (default 64 x 672 x 512 (y, x, t), Fig. 3 kinds a/b/c, white noise at
NSR 0.05; ``--scenes paper`` (default, the paper's parameter space, bin-integrated) or
``legacy``) is written as a cube store, then decomposed by each method with 1 and 2 workers
through :func:`decomposition.store.pipeline.decompose_to_store` -- the code path of the
command, all stages included: opening the cube, the solver check, starting the local cluster,
reading, solving and writing every chunk into a result store.  ``--workers N`` means what it
means for the command (a local cluster of N single-threaded worker processes); ``threads:N``
runs the command's default threaded scheduler with N threads instead.

Each configuration runs in its own child process; the parent samples the resident memory of
that process and all its descendants (workers included; the list of descendants is refreshed
every second) every 50 ms and reports the peak sum,
next to the largest single-process peak (``ru_maxrss``).

The floor: one pass of FFT correlation of every profile with a Gaussian kernel over the same
cube (read each chunk, rfft, multiply, irfft), on the same number of threads as the largest
worker count -- no decomposition can be faster than reading and correlating each pixel once.
Printed: pixels/s of every configuration (all stages, and over the chunks alone), its time
relative to the floor, peak memory, and the time the paper-size 600 x 672 x 512 cube would take
(the measured setup time plus its pixels at the measured rate over the chunks).  Writes
``speed.json``.

``--option KEY=VALUE`` (repeatable) hands a solver option to every run, as ``streaklab
decompose --option`` takes it (``rescue=false`` times the first pass alone); the options are
printed and kept in ``speed.json``, and the target is judged only on runs with the defaults.

One run moves with the machine (on the shared 2-core machine the same code read 1,816-1,981
px/s within an hour): ``--repeat N`` times every configuration N times, in rounds that run each
configuration once, prints each run and the median and range per configuration, and judges
the target on the median (``summaries`` in ``speed.json``).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from streaklab.cli import CommandError

from .arguments import output_folder

PAPER_SHAPE = (600, 672, 512)
DEFAULT_SHAPE = (64, 672, 512)
TARGET_PX_PER_S = 2000        # default ConvSCD on 2 cores, all stages
TARGET_PAPER_S = 3.5 * 60
ROOT = Path(__file__).resolve().parents[2]


def add_arguments(parser) -> None:
    parser.add_argument("--shape", type=int, nargs=3, default=DEFAULT_SHAPE, metavar=("NY", "NX", "NT"),
                        help="synthetic cube (default 64 672 512)")
    parser.add_argument("--nsr", type=float, default=0.05, help="white-noise NSR (default 0.05)")
    parser.add_argument("--photons", type=float, default=None, metavar="N",
                        help="photon counts instead of white noise: Poisson counts of N expected photons per "
                             "pixel (whole numbers, so decompose takes its Poisson noise model)")
    parser.add_argument("--methods", default="convscd,gradbm", help="comma-separated (default convscd,gradbm)")
    parser.add_argument("--workers", default="1,2",
                        help="comma-separated worker counts (local cluster processes), or threads:N for the "
                             "threaded scheduler (default 1,2)")
    parser.add_argument("--chunks", type=int, nargs=2, default=(16, 64), metavar=("BY", "BX"),
                        help="pixel chunk of the cube and the computation (default 16 64)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic cube (default 0)")
    parser.add_argument("--scenes", default="paper",
                        help="scene preset of the cube: paper (the paper's parameter space, bin-integrated; "
                             "default) or legacy (the original generator, point-sampled)")
    parser.add_argument("--out", default="bench-output/speed",
                        help="folder for speed.json (default bench-output/speed)")
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="time every configuration N times, in rounds (each round runs every "
                             "configuration once, so a machine that slows down slows them alike); the "
                             "target is judged on the median (default 1)")
    parser.add_argument("--keep", action="store_true", help="keep the synthetic cube and result stores")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="a solver option for every run, as streaklab decompose takes it (repeatable; "
                             "e.g. rescue=false); the target is judged on the defaults only")


def _parse_workers(text):
    out = []
    for part in text.split(","):
        part = part.strip()
        try:
            if part.startswith("threads:"):
                n = int(part.split(":", 1)[1])
                kind = "threads"
            else:
                n = int(part)
                kind = "processes"
        except ValueError:
            raise CommandError(f"--workers takes counts like 1,2 or threads:2; got {part!r}") from None
        if n <= 0:
            raise CommandError(f"worker counts must be positive, got {n}")
        out.append((kind, n))
    return out


def write_synthetic_cube(path, shape, *, nsr, seed, chunks, rows_per_block=8, scenes="legacy", photons=None):
    """Write a seeded synthetic cube store block by block (memory bounded by a block); -> seconds.

    ``scenes`` names a preset of :data:`decomposition.evaluation.synthetic.SCENE_PRESETS`; ``paper``
    scenes are rendered bin-integrated, ``legacy`` ones point-sampled.  With ``photons`` the
    samples are Poisson counts of the clean profiles scaled to that many expected photons per
    pixel (``nsr`` is then unused)."""
    from decomposition.evaluation.synthetic import make_cube
    from reconstruction.cubestore import create_cube

    ny, nx, nt = shape
    t0 = time.perf_counter()
    cube = create_cube(path, shape, time_bin_ps=2.0, t0_ps=2.0, chunks=chunks, units="arbitrary",
                       provenance={"producer": "streaklab bench speed", "nsr": nsr,
                                   "noise": "white" if photons is None else f"photon counts, {photons:g} per pixel",
                                   "seed": seed, "scenes": scenes},
                       overwrite=True)
    for i, y0 in enumerate(range(0, ny, rows_per_block)):
        rows = min(rows_per_block, ny - y0)
        data = make_cube(rows, nx, nt, nsr=nsr if photons is None else 0.0, noise="white", seed=seed * 100003 + i,
                         ranges=scenes, bin_integrated=scenes == "paper")
        if photons is None:
            cube.array[y0:y0 + rows] = data.noisy.astype(np.float32)
        else:
            clean = data.clean
            total = np.maximum(clean.sum(axis=-1, keepdims=True), 1e-300)
            rng = np.random.default_rng(seed * 100003 + i)
            cube.array[y0:y0 + rows] = rng.poisson(clean * (photons / total)).astype(np.float32)
    return time.perf_counter() - t0


def fft_floor(cube_path, *, threads: int) -> dict:
    """Time one FFT-correlation pass over a cube store; -> {seconds, pixels_per_s}."""
    import dask
    import dask.array as da

    from reconstruction.cubestore import open_cube

    cube = open_cube(cube_path)
    arr = da.from_zarr(cube.array)
    nt = cube.shape[2]
    n = 2 * nt
    t = (np.arange(n) - n // 2) * cube.time_bin_ps
    kernel = np.fft.ifftshift(np.exp(-0.5 * (t / 3.0) ** 2))
    spec = np.conj(np.fft.rfft(kernel))

    def correlate(block):
        f = np.fft.rfft(block.astype(np.float64), n=n, axis=-1)
        return np.fft.irfft(f * spec, n=n, axis=-1)[..., :nt].max(axis=-1)

    start = time.perf_counter()
    with dask.config.set(scheduler="threads", num_workers=threads):
        arr.map_blocks(correlate, drop_axis=2, dtype=np.float64).sum().compute()
    seconds = time.perf_counter() - start
    pixels = cube.shape[0] * cube.shape[1]
    return {"seconds": seconds, "pixels_per_s": pixels / seconds, "threads": threads}


_CHILD = """
import json, resource, sys
from decomposition.store.pipeline import decompose_to_store
cfg = json.loads(sys.argv[1])
s = decompose_to_store(cfg["cube"], cfg["out"], method=cfg["method"], workers=cfg["workers"],
                       threads=cfg["threads"], chunks=cfg["chunks"], options=cfg["options"], overwrite=True,
                       progress=False)
s["maxrss_self_kib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
s["maxrss_children_kib"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print("RESULT " + json.dumps(s))
"""


def run_config(cube_path, out_path, *, method, kind, n, chunks, options=None, timeout_s=3600) -> dict:
    """Decompose in a child process, sampling the memory of its process tree; -> summary dict.
    ``options``: solver options of ``decompose_to_store`` (default: none)."""
    import psutil

    cfg = {"cube": str(Path(cube_path).resolve()), "out": str(Path(out_path).resolve()), "method": method, "chunks": list(chunks),
           "workers": n if kind == "processes" else None, "threads": n if kind == "threads" else None,
           "options": dict(options or {})}
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    # the child runs in the caller's folder with absolute paths: relative --out paths mean the same there
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, json.dumps(cfg)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = 0
    deadline = time.monotonic() + timeout_s
    try:
        ps = psutil.Process(proc.pid)
        tree, listed = [ps], 0.0
        while proc.poll() is None:
            now = time.monotonic()
            if now > deadline:
                raise CommandError(f"{method} with {kind}={n} did not finish in {timeout_s} s")
            if now - listed > 1.0:
                # finding the descendants scans every process on the machine: at 20 Hz that took a
                # third of a core from the run being measured, so the tree is listed once a second
                try:
                    tree, listed = [ps] + ps.children(recursive=True), now
                except psutil.Error:
                    pass
            total = 0
            for c in tree:
                try:
                    total += c.memory_info().rss
                except psutil.Error:
                    pass
            peak = max(peak, total)
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            proc.kill()
        stdout, stderr = proc.communicate()
    lines = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise CommandError(f"decompose ({method}, {kind}={n}) failed with status {proc.returncode}:\n{stderr[-3000:]}")
    s = json.loads(lines[-1][len("RESULT "):])
    one = max(s["maxrss_self_kib"], s["maxrss_children_kib"]) / 1024
    # The sampled sum can miss a short peak that ru_maxrss (exact, per process) saw: the peak of
    # the whole run is at least the larger of the two.
    s.update({"method": method, "scheduler": kind, "workers": n, "peak_rss_tree_mib": peak / 2**20,
              "peak_rss_one_process_mib": one, "peak_rss_mib": max(peak / 2**20, one)})
    return s


def _label(kind, n) -> str:
    return f"{n} worker process{'es' if n > 1 else ''}" if kind == "processes" else f"{n} threads"


def _timed_run(cube_path, out_path, *, method, kind, n, chunks, pixels, floor, options=None) -> dict:
    """One timed decomposition of the cube, printed as one line; -> its summary dict."""
    load_before = os.getloadavg()[0]
    s = run_config(cube_path, out_path, method=method, kind=kind, n=n, chunks=chunks, options=options)
    s["load_average_1min_before"] = load_before
    compute_pps = pixels / s["seconds_compute"]
    s["compute_pixels_per_s"] = compute_pps
    paper_s = s["seconds_setup"] + PAPER_SHAPE[0] * PAPER_SHAPE[1] / compute_pps
    s["paper_cube_s"] = paper_s
    s["floor_ratio"] = floor["pixels_per_s"] / s["pixels_per_s"]
    print(f"{method:8s} {_label(kind, n):20s} {s['pixels_per_s']:>9,.0f} px/s all stages "
          f"({s['seconds']:.1f} s = {s['seconds_setup']:.1f} s setup + "
          f"{s['seconds_compute']:.1f} s over the chunks "
          f"at {compute_pps:,.0f} px/s), "
          f"{s['floor_ratio']:.1f}x the FFT floor's time, {memory_text(s)}; "
          f"paper-size {PAPER_SHAPE[0]}x{PAPER_SHAPE[1]}x{PAPER_SHAPE[2]} cube: {paper_s / 60:.1f} min "
          f"[load average before: {load_before:.1f} on {os.cpu_count()} cores]", flush=True)
    return s


def _summaries(rows) -> list[dict]:
    """Per (method, scheduler, workers), in the order first run: the runs' count and the median,
    minimum and maximum of their pixels per second (all stages) and the median paper-size time."""
    groups: dict = {}
    for s in rows:
        groups.setdefault((s["method"], s["scheduler"], s["workers"]), []).append(s)
    out = []
    for (method, kind, n), runs in groups.items():
        pps = np.array([r["pixels_per_s"] for r in runs])
        out.append({"method": method, "scheduler": kind, "workers": n, "runs": len(runs),
                    "pixels_per_s_median": float(np.median(pps)), "pixels_per_s_min": float(pps.min()),
                    "pixels_per_s_max": float(pps.max()),
                    "paper_cube_s_median": float(np.median([r["paper_cube_s"] for r in runs]))})
    return out


def memory_text(s) -> str:
    """The memory part of a result line: one peak, and how it was measured."""
    if s["scheduler"] == "threads":
        return f"peak memory {s['peak_rss_mib']:,.0f} MiB (one process)"
    return (f"peak memory {s['peak_rss_mib']:,.0f} MiB for all processes together "
            f"(largest single process {s['peak_rss_one_process_mib']:,.0f} MiB)")


def run(args) -> int:
    ny, nx, nt = args.shape
    if min(ny, nx) <= 0 or nt < 16:
        raise CommandError(f"--shape needs positive NY NX and NT >= 16, got {args.shape}")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in ("convscd", "gradbm")]
    if bad or not methods:
        raise CommandError(f"--methods takes convscd and/or gradbm; got {args.methods!r}")
    workers = _parse_workers(args.workers)
    options = {}
    if args.option:
        from streaklab.commands.decompose import parse_solver_options

        for method in methods:          # every name checked against each method's options
            options = parse_solver_options(args.option, method, check_values=True)
    if args.repeat < 1:
        raise CommandError(f"--repeat must be at least 1, got {args.repeat}")
    from decomposition.evaluation.synthetic import SCENE_PRESETS

    if args.photons is not None and not (np.isfinite(args.photons) and args.photons > 0):
        raise CommandError(f"--photons must be a positive number, got {args.photons:g}")
    if args.scenes not in SCENE_PRESETS:
        raise CommandError(f"--scenes: unknown preset {args.scenes!r}; choose from {', '.join(SCENE_PRESETS)}")
    out = output_folder(args.out).resolve()
    chunks = (min(args.chunks[0], ny), min(args.chunks[1], nx))
    pixels = ny * nx
    with tempfile.TemporaryDirectory(dir=out, prefix="work-") as tmp:
        work = Path(tmp) if not args.keep else out
        cube_path = work / "cube.zarr"
        noise_text = (f"white noise, NSR {args.nsr:g}" if args.photons is None
                      else f"photon counts, {args.photons:g} per pixel")
        print(f"writing a synthetic {ny} x {nx} x {nt} cube ({noise_text}, seed {args.seed}, "
              f"chunks {chunks[0]} x {chunks[1]}) ...", flush=True)
        try:
            gen_s = write_synthetic_cube(cube_path, (ny, nx, nt), nsr=args.nsr, seed=args.seed, chunks=chunks,
                                         scenes=args.scenes, photons=args.photons)
        except ValueError as exc:
            raise CommandError(f"{exc} (or --scenes legacy)") from None
        from decomposition.warmup import warm_up

        for method in methods:  # compile once here, if needed, not inside the first timed run
            warm_up(time_bin_ps=2.0, n_bins=nt, method=method, label="bench speed")
        floor = fft_floor(cube_path, threads=max(n for _, n in workers))
        print(f"floor: one FFT-correlation pass, {floor['threads']} threads: {floor['pixels_per_s']:,.0f} px/s "
              f"({floor['seconds']:.2f} s)", flush=True)
        rows = []
        for rnd in range(args.repeat):
            if args.repeat > 1:
                print(f"round {rnd + 1} of {args.repeat}", flush=True)
            for method in methods:
                for kind, n in workers:
                    s = _timed_run(cube_path, work / f"result-{method}-{kind}{n}.zarr", method=method, kind=kind,
                                   n=n, chunks=chunks, pixels=pixels, floor=floor, options=options)
                    s["round"] = rnd
                    rows.append(s)
    if nt != PAPER_SHAPE[2]:
        print(f"note: the paper-size projection assumes {nt} bins per profile, as measured, not {PAPER_SHAPE[2]}")
    summaries = _summaries(rows)
    for m in summaries:
        if args.repeat > 1:
            print(f"{m['method']:8s} {_label(m['scheduler'], m['workers']):20s} over {m['runs']} runs: "
                  f"median {m['pixels_per_s_median']:,.0f} px/s all stages "
                  f"(range {m['pixels_per_s_min']:,.0f}-{m['pixels_per_s_max']:,.0f})", flush=True)
    for m in summaries:
        if m["method"] == "convscd" and m["workers"] == 2 and not options:
            how = _label(m["scheduler"], m["workers"])
            ok = m["pixels_per_s_median"] >= TARGET_PX_PER_S and m["paper_cube_s_median"] <= TARGET_PAPER_S
            where = "" if (ny, nx, nt) == DEFAULT_SHAPE else " (the target is defined on the default --shape)"
            over = f" (median of {m['runs']} runs)" if m["runs"] > 1 else ""
            print(f"target, convscd with {how}: [{'met' if ok else 'NOT met'}] "
                  f"{m['pixels_per_s_median']:,.0f} px/s all stages{over} (target >= {TARGET_PX_PER_S:,}), "
                  f"paper-size cube {m['paper_cube_s_median'] / 60:.1f} min (target < {TARGET_PAPER_S / 60:.1f}){where}")
    if options:
        print(f"options {options}: the target is judged on the defaults, not here")
    report = {"shape": [ny, nx, nt], "nsr": args.nsr, "photons": args.photons, "seed": args.seed, "chunks": list(chunks),
              "options": options,
              "cpu_count": os.cpu_count(), "cube_write_s": gen_s, "floor": floor, "runs": rows,
              "repeat": args.repeat, "summaries": summaries,
              "paper_shape": list(PAPER_SHAPE)}
    (out / "speed.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out / 'speed.json'}")
    return 0
