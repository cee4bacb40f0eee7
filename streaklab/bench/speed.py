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

Where the time goes (``--stage-pixels N``, default :data:`STAGE_PIXELS`; ``stages`` in
``speed.json``): after the timed runs, the cube's first N profiles are decomposed once more in
the bench's own process with the pipeline's solver settings, per method and response, and the
seconds of each stage of :data:`decomposition.api.STAGES` are printed per 1,000 profiles with
their share of the call -- the same stage names as docs/decomposition.md -- and drawn in
``stages.png`` (one bar per method and response, the stages stacked in the order they run).

``--option KEY=VALUE`` (repeatable) hands a solver option to every run, as ``streaklab
decompose --option`` takes it (``rescue=false`` times the first pass alone); the options are
printed and kept in ``speed.json``, and the target is judged only on runs with the defaults.

``--irf NAME|PATH`` times the response path: ``gaussian`` (default, the Gaussian PSF), a model
response of the simulated camera by name (``tailed``, ``afterpulse``; see
:func:`drivers.sim.scene.simulated_response`) or a stored response (a ``.npz`` file, a response
store or a cube store's ``irf`` group, :func:`core.irfstore.load_response`).  With a response the
cube is rendered through it, and every configuration is decomposed twice in each round, with
that response and with ``gaussian`` on the same cube, and the ratio of their pixels per second
is printed (``ratios`` in ``speed.json``) against its target (at least
:data:`TARGET_RESPONSE_RATIO`); the pixels-per-second target is judged for both.  Only
``convscd`` takes a response.

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
#: a measured response's pixels per second over the Gaussian's on the same cube, at least
TARGET_RESPONSE_RATIO = 0.8
ROOT = Path(__file__).resolve().parents[2]
#: profiles of the stage-by-stage breakdown (``--stage-pixels``)
STAGE_PIXELS = 2048


def add_arguments(parser) -> None:
    parser.add_argument("--shape", type=int, nargs=3, default=DEFAULT_SHAPE, metavar=("NY", "NX", "NT"),
                        help="synthetic cube (default 64 672 512)")
    parser.add_argument("--nsr", type=float, default=0.05, help="white-noise NSR (default 0.05)")
    parser.add_argument("--photons", type=float, default=None, metavar="N",
                        help="photon counts instead of white noise: Poisson counts of N expected photons per "
                             "pixel (whole numbers, so decompose takes its Poisson noise model)")
    parser.add_argument("--methods", default=None,
                        help="comma-separated (default convscd,gradbm; convscd with --irf other than gaussian)")
    parser.add_argument("--irf", default="gaussian", metavar="NAME|PATH",
                        help="instrument response: gaussian (default), a simulated model response by name "
                             "(tailed, afterpulse) or a stored response (.npz or store); with a response the "
                             "cube is rendered through it and each run is timed with it and with gaussian")
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
    parser.add_argument("--stage-pixels", type=int, default=STAGE_PIXELS, metavar="N",
                        help=f"after the timed runs, where the time goes: the cube's first N profiles "
                             f"decomposed in this process, timed stage by stage, per method and response "
                             f"(default {STAGE_PIXELS}; 0: not)")
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


def bench_response(text):
    """``--irf``: None for ``gaussian``, else the named simulated response or the stored one at
    that path (:class:`core.irf.InstrumentResponse`); CommandError naming the problem."""
    from drivers.sim.scene import SIMULATED_RESPONSES, simulated_response

    name = str(text).strip()
    if name.lower() == "gaussian":
        return None
    if name.lower() in SIMULATED_RESPONSES:
        return simulated_response(name.lower())
    from core.errors import StreaklabError
    from core.irfstore import load_response

    if not os.path.exists(name):
        raise CommandError(f"--irf {name!r}: neither a response name ({', '.join(SIMULATED_RESPONSES)}) "
                           f"nor an existing response file or store")
    try:
        return load_response(name)
    except (StreaklabError, ValueError, OSError) as exc:
        raise CommandError(f"--irf {name}: {exc}") from None


def write_synthetic_cube(path, shape, *, nsr, seed, chunks, rows_per_block=8, scenes="legacy", photons=None,
                         response=None):
    """Write a seeded synthetic cube store block by block (memory bounded by a block); -> seconds.

    ``scenes`` names a preset of :data:`decomposition.evaluation.synthetic.SCENE_PRESETS`; ``paper``
    scenes are rendered bin-integrated, ``legacy`` ones point-sampled.  With ``photons`` the
    samples are Poisson counts of the clean profiles scaled to that many expected photons per
    pixel (``nsr`` is then unused).  ``response`` (an :class:`core.irf.InstrumentResponse`):
    every component rendered through it instead of the Gaussian PSF."""
    from decomposition.evaluation.synthetic import make_cube
    from decomposition.evaluation.synthetic_effects import count_photons
    from reconstruction.cubestore import create_cube

    ny, nx, nt = shape
    t0 = time.perf_counter()
    cube = create_cube(path, shape, time_bin_ps=2.0, t0_ps=2.0, chunks=chunks, units="arbitrary",
                       provenance={"producer": "streaklab bench speed", "nsr": nsr,
                                   "noise": "white" if photons is None else f"photon counts, {photons:g} per pixel",
                                   "seed": seed, "scenes": scenes,
                                   "response": "gaussian" if response is None else dict(response.provenance)},
                       overwrite=True)
    for i, y0 in enumerate(range(0, ny, rows_per_block)):
        rows = min(rows_per_block, ny - y0)
        data = make_cube(rows, nx, nt, nsr=nsr if photons is None else 0.0, noise="white", seed=seed * 100003 + i,
                         ranges=scenes, bin_integrated=scenes == "paper", response=response)
        if photons is None:
            cube.array[y0:y0 + rows] = data.noisy.astype(np.float32)
        else:
            # the synthetic data's Poisson rule: a response's ringing far from its peak (below zero
            # at 1e-9 of it) is clipped before the draw
            counts, _ = count_photons(data.clean, 0.0, photons, np.random.default_rng(seed * 100003 + i))
            cube.array[y0:y0 + rows] = counts.astype(np.float32)
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
                       progress=False, irf=cfg["irf"])
s["maxrss_self_kib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
s["maxrss_children_kib"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print("RESULT " + json.dumps(s))
"""


def run_config(cube_path, out_path, *, method, kind, n, chunks, options=None, irf="gaussian",
               timeout_s=3600) -> dict:
    """Decompose in a child process, sampling the memory of its process tree; -> summary dict.
    ``options``: solver options of ``decompose_to_store`` (default: none); ``irf``: its ``irf``
    argument ("gaussian" or the path of a stored response)."""
    import psutil

    cfg = {"cube": str(Path(cube_path).resolve()), "out": str(Path(out_path).resolve()), "method": method, "chunks": list(chunks),
           "workers": n if kind == "processes" else None, "threads": n if kind == "threads" else None,
           "options": dict(options or {}), "irf": str(irf)}
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


def stage_breakdown(cube_path, *, method: str, response=None, irf_name: str = "gaussian",
                    pixels: int = STAGE_PIXELS, options=None) -> dict:
    """Where a call's time goes: the cube's first ``pixels`` profiles, as stored, decomposed in
    this process with the pipeline's solver settings (components d, s, r; 3 inter-reflection
    slots; NaN pixels omitted; ``options``; the response ``response``, named ``irf_name``, or the
    Gaussian PSF), timed stage by stage (:func:`decomposition.api.stage_seconds`);
    -> {method, irf, pixels, seconds, stage_seconds}.  Run after a warm-up: the first call of a
    kernel compiles it."""
    from decomposition.api import stage_seconds
    from reconstruction.cubestore import open_cube

    cube = open_cube(cube_path)
    ny, nx, nt = cube.shape
    rows = min(ny, -(-int(pixels) // nx))
    profiles = np.asarray(cube.array[:rows]).reshape(-1, nt)[:int(pixels)]
    start = time.perf_counter()
    _, seconds = stage_seconds(profiles, cube.time_bin_ps, method, t0_ps=cube.t0_ps, components=("d", "s", "r"),
                               nan_policy="omit", max_reflections=3, irf=response, **(options or {}))
    total = time.perf_counter() - start
    return {"method": method, "irf": irf_name, "pixels": int(profiles.shape[0]),
            "seconds": total, "stage_seconds": seconds}


def stage_text(b: dict) -> str:
    """A :func:`stage_breakdown` as printed lines: the call, then each stage that took at least
    1 % of it, with its seconds per 1,000 profiles and share."""
    per_k = 1000.0 / max(b["pixels"], 1)
    head = (f"{b['method']:8s} [{b['irf']}] where the time goes, {b['pixels']:,} profiles in this process: "
            f"{b['seconds']:.2f} s ({b['pixels'] / b['seconds']:,.0f} px/s)")
    parts = [f"{name} {sec * per_k:.3f} s ({100 * sec / b['seconds']:.0f} %)"
             for name, sec in b["stage_seconds"].items() if sec >= 0.01 * b["seconds"]]
    return head + "\n    per 1,000 profiles: " + ", ".join(parts)


def stage_figure(breakdowns: list[dict]):
    """``stages.png`` as a matplotlib Figure: one bar per :func:`stage_breakdown` (method and
    response), its stages stacked in the order they run, seconds per 1,000 profiles; a stage
    under 1 % of every call is left out, the same colour for a stage in every bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name in breakdowns[0]["stage_seconds"]
             if any(b["stage_seconds"][name] >= 0.01 * b["seconds"] for b in breakdowns)]
    fig, ax = plt.subplots(figsize=(7.0, 1.2 + 0.55 * len(breakdowns)))
    labels = [f"{b['method']} [{b['irf']}]" for b in breakdowns]
    left = np.zeros(len(breakdowns))
    for k, name in enumerate(names):
        width = np.array([1000.0 * b["stage_seconds"][name] / b["pixels"] for b in breakdowns])
        ax.barh(labels, width, left=left, color=f"C{k % 10}", hatch="//" if k >= 10 else None, label=name)
        left += width
    ax.invert_yaxis()
    ax.set_xlabel("seconds per 1,000 profiles, one thread")
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.35 - 0.1 / len(breakdowns)))
    ax.set_title(f"where a call's time goes ({breakdowns[0]['pixels']:,} profiles per bar)", fontsize=9)
    fig.tight_layout()
    return fig


def _label(kind, n) -> str:
    return f"{n} worker process{'es' if n > 1 else ''}" if kind == "processes" else f"{n} threads"


def _timed_run(cube_path, out_path, *, method, kind, n, chunks, pixels, floor, options=None, irf=None,
               paired=False) -> dict:
    """One timed decomposition of the cube, printed as one line; -> its summary dict.
    ``irf``: None (the Gaussian) or (label, path of the stored response); ``paired``: the bench
    times a response and the Gaussian (each line names its own)."""
    load_before = os.getloadavg()[0]
    s = run_config(cube_path, out_path, method=method, kind=kind, n=n, chunks=chunks, options=options,
                   irf="gaussian" if irf is None else irf[1])
    s["irf_name"] = "gaussian" if irf is None else irf[0]
    s["paired"] = bool(paired)
    s["load_average_1min_before"] = load_before
    compute_pps = pixels / s["seconds_compute"]
    s["compute_pixels_per_s"] = compute_pps
    paper_s = s["seconds_setup"] + PAPER_SHAPE[0] * PAPER_SHAPE[1] / compute_pps
    s["paper_cube_s"] = paper_s
    s["floor_ratio"] = floor["pixels_per_s"] / s["pixels_per_s"]
    print(f"{method:8s} {_irf_tag(s)}{_label(kind, n):20s} {s['pixels_per_s']:>9,.0f} px/s all stages "
          f"({s['seconds']:.1f} s = {s['seconds_setup']:.1f} s setup + "
          f"{s['seconds_compute']:.1f} s over the chunks "
          f"at {compute_pps:,.0f} px/s), "
          f"{s['floor_ratio']:.1f}x the FFT floor's time, {memory_text(s)}; "
          f"paper-size {PAPER_SHAPE[0]}x{PAPER_SHAPE[1]}x{PAPER_SHAPE[2]} cube: {paper_s / 60:.1f} min "
          f"[load average before: {load_before:.1f} on {os.cpu_count()} cores]", flush=True)
    return s


def _irf_tag(s) -> str:
    """``[name] `` of a run's (or summary's) response where the bench compares two, else ''."""
    return f"[{s.get('irf_name', s.get('irf'))}] " if s.get("paired") else ""


def _summaries(rows) -> list[dict]:
    """Per (method, response, scheduler, workers), in the order first run: the runs' count and the
    median, minimum and maximum of their pixels per second (all stages) and the median paper-size
    time."""
    groups: dict = {}
    for s in rows:
        groups.setdefault((s["method"], s.get("irf_name", "gaussian"), s["scheduler"], s["workers"]), []).append(s)
    out = []
    for (method, irf_name, kind, n), runs in groups.items():
        pps = np.array([r["pixels_per_s"] for r in runs])
        out.append({"method": method, "irf": irf_name, "paired": runs[0].get("paired", False),
                    "scheduler": kind, "workers": n, "runs": len(runs),
                    "pixels_per_s_median": float(np.median(pps)), "pixels_per_s_min": float(pps.min()),
                    "pixels_per_s_max": float(pps.max()),
                    "paper_cube_s_median": float(np.median([r["paper_cube_s"] for r in runs]))})
    return out


def response_ratios(summaries) -> list[dict]:
    """Per (method, scheduler, workers) timed with a response and with the Gaussian: the medians'
    pixels per second of each and the response's over the Gaussian's (1.0: as fast)."""
    by = {(m["method"], m["irf"], m["scheduler"], m["workers"]): m for m in summaries}
    out = []
    for (method, irf_name, kind, n), m in by.items():
        g = by.get((method, "gaussian", kind, n))
        if irf_name == "gaussian" or g is None:
            continue
        out.append({"method": method, "irf": irf_name, "scheduler": kind, "workers": n,
                    "pixels_per_s_response": m["pixels_per_s_median"], "pixels_per_s_gaussian": g["pixels_per_s_median"],
                    "response_over_gaussian": m["pixels_per_s_median"] / g["pixels_per_s_median"]})
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
    response = bench_response(args.irf)
    methods_text = args.methods if args.methods is not None else ("convscd,gradbm" if response is None else "convscd")
    methods = [m.strip() for m in methods_text.split(",") if m.strip()]
    bad = [m for m in methods if m not in ("convscd", "gradbm")]
    if bad or not methods:
        raise CommandError(f"--methods takes convscd and/or gradbm; got {methods_text!r}")
    if response is not None and "gradbm" in methods:
        raise CommandError(f"--irf {args.irf}: only convscd takes an instrument response; use --methods convscd")
    workers = _parse_workers(args.workers)
    options = {}
    if args.option:
        from streaklab.commands.decompose import parse_solver_options

        for method in methods:          # every name checked against each method's options
            options = parse_solver_options(args.option, method, check_values=True)
    if args.repeat < 1:
        raise CommandError(f"--repeat must be at least 1, got {args.repeat}")
    if args.stage_pixels < 0:
        raise CommandError(f"--stage-pixels must be 0 (not) or a number of profiles, got {args.stage_pixels}")
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
        irf_text = "" if response is None else f", rendered with the response {args.irf}"
        print(f"writing a synthetic {ny} x {nx} x {nt} cube ({noise_text}{irf_text}, seed {args.seed}, "
              f"chunks {chunks[0]} x {chunks[1]}) ...", flush=True)
        try:
            gen_s = write_synthetic_cube(cube_path, (ny, nx, nt), nsr=args.nsr, seed=args.seed, chunks=chunks,
                                         scenes=args.scenes, photons=args.photons, response=response)
        except ValueError as exc:
            raise CommandError(f"{exc} (or --scenes legacy)") from None
        irfs = [None]
        if response is not None:
            from core.irfstore import save_response

            irf_label = Path(args.irf).name if os.path.exists(args.irf) else args.irf.lower()
            irfs = [(irf_label, str(save_response(work / "irf.npz", response, overwrite=True))), None]
        from decomposition.warmup import warm_up

        for method in methods:  # compile once here, if needed, not inside the first timed run
            warm_up(time_bin_ps=2.0, n_bins=nt, method=method, label="bench speed")
            if response is not None:
                warm_up(time_bin_ps=2.0, n_bins=nt, method=method, label="bench speed",
                        options={"irf": response})
        floor = fft_floor(cube_path, threads=max(n for _, n in workers))
        print(f"floor: one FFT-correlation pass, {floor['threads']} threads: {floor['pixels_per_s']:,.0f} px/s "
              f"({floor['seconds']:.2f} s)", flush=True)
        rows = []
        for rnd in range(args.repeat):
            if args.repeat > 1:
                print(f"round {rnd + 1} of {args.repeat}", flush=True)
            for method in methods:
                for kind, n in workers:
                    for irf in irfs:        # with a response: it and the Gaussian, alternated
                        tag = "" if irf is None else f"-{irf[0]}"
                        s = _timed_run(cube_path, work / f"result-{method}-{kind}{n}{tag}.zarr", method=method,
                                       kind=kind, n=n, chunks=chunks, pixels=pixels, floor=floor, options=options,
                                       irf=irf, paired=response is not None)
                        s["round"] = rnd
                        rows.append(s)
        stages = []
        if args.stage_pixels:
            for method in methods:
                for irf in irfs:
                    b = stage_breakdown(cube_path, method=method, response=None if irf is None else response,
                                        irf_name="gaussian" if irf is None else irf[0], pixels=args.stage_pixels,
                                        options=options)
                    print(stage_text(b), flush=True)
                    stages.append(b)
    if nt != PAPER_SHAPE[2]:
        print(f"note: the paper-size projection assumes {nt} bins per profile, as measured, not {PAPER_SHAPE[2]}")
    summaries = _summaries(rows)
    for m in summaries:
        if args.repeat > 1:
            print(f"{m['method']:8s} {_irf_tag(m)}{_label(m['scheduler'], m['workers']):20s} over {m['runs']} runs: "
                  f"median {m['pixels_per_s_median']:,.0f} px/s all stages "
                  f"(range {m['pixels_per_s_min']:,.0f}-{m['pixels_per_s_max']:,.0f})", flush=True)
    for m in summaries:
        if m["method"] == "convscd" and m["workers"] == 2 and not options:
            how = _irf_tag(m) + _label(m["scheduler"], m["workers"])
            ok = m["pixels_per_s_median"] >= TARGET_PX_PER_S and m["paper_cube_s_median"] <= TARGET_PAPER_S
            where = "" if (ny, nx, nt) == DEFAULT_SHAPE else " (the target is defined on the default --shape)"
            over = f" (median of {m['runs']} runs)" if m["runs"] > 1 else ""
            print(f"target, convscd with {how}: [{'met' if ok else 'NOT met'}] "
                  f"{m['pixels_per_s_median']:,.0f} px/s all stages{over} (target >= {TARGET_PX_PER_S:,}), "
                  f"paper-size cube {m['paper_cube_s_median'] / 60:.1f} min (target < {TARGET_PAPER_S / 60:.1f}){where}")
    ratios = response_ratios(summaries)
    for r in ratios:
        print(f"{r['method']:8s} {_label(r['scheduler'], r['workers'])}: {r['irf']} {r['pixels_per_s_response']:,.0f} "
              f"px/s, gaussian {r['pixels_per_s_gaussian']:,.0f} px/s on the same cube: the response path at "
              f"{r['response_over_gaussian']:.2f}x the Gaussian's pixels per second "
              f"[{'met' if r['response_over_gaussian'] >= TARGET_RESPONSE_RATIO else 'NOT met'}: "
              f"target >= {TARGET_RESPONSE_RATIO:g}x]", flush=True)
    if options:
        print(f"options {options}: the target is judged on the defaults, not here")
    report = {"shape": [ny, nx, nt], "nsr": args.nsr, "photons": args.photons, "seed": args.seed, "chunks": list(chunks),
              "options": options,
              "cpu_count": os.cpu_count(), "cube_write_s": gen_s, "floor": floor, "runs": rows,
              "repeat": args.repeat, "summaries": summaries,
              "irf": args.irf if response is None else {"name": args.irf, "provenance": response.provenance},
              "ratios": ratios, "stages": stages,
              "paper_shape": list(PAPER_SHAPE)}
    (out / "speed.json").write_text(json.dumps(report, indent=2))
    written = [out / "speed.json"]
    if stages:
        import matplotlib.pyplot as plt

        fig = stage_figure(stages)
        fig.savefig(out / "stages.png", dpi=120, bbox_inches="tight")
        plt.close(fig)
        written.append(out / "stages.png")
    print(f"wrote {' and '.join(str(p) for p in written)}")
    return 0
