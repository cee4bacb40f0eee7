"""``streaklab demo [--out DIR]``: the whole pipeline on the simulated lab, checked against the truth.

1. capture: a scan of the SimulatedLab (simulated camera, scan mirror and laser sync spoken to
   through the real drivers) into a run store;
2. reconstruct: the calibrated (y, x, t) cube;
3. decompose: every pixel, chunk by chunk, into a result store;
4. report: figures and a summary;
5. compare with the simulated ground truth: mean decomposition fidelity per component class
   (:func:`decomposition.model.fidelity.fidelity`).

``--source simulate`` replaces steps 1-2 by a synthetic cube (``streaklab simulate``).  Every
output goes under ``--out`` (default ``demo-output``), a folder that may be neither a Zarr
store nor inside one.  The demo records what it wrote there in ``.streaklab-demo.json``
(each store by its kind and creation time, ``fidelity.json`` by its sha256, ``figs`` by its
file names); a rerun replaces exactly those products.  A product name taken by anything else
(a run captured there by hand, a store copied in, a file the record does not list) is refused
before anything is written, and so is a recorded store that now holds files not its own;
nothing else in the folder is touched.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from core.staging import OutputPathError, check_output_location, describe_existing, foreign_files
from core.words import counted
from streaklab.cli import CommandError

__all__ = ["add_arguments", "run", "run_demo", "class_fidelity"]

_PRODUCTS = ("run.zarr", "cube.zarr", "result.zarr", "figs", "fidelity.json")
#: the record of the products a demo wrote into its --out folder (see the module docstring)
RECORD = ".streaklab-demo.json"
_FIGURES = ("frames.png", "maps.png", "profiles.png", "summary.txt")


def _identity(p: Path) -> dict:
    """What a product is, to tell on a rerun that it is still the one this demo wrote."""
    if p.is_file():
        return {"sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
    kind = describe_existing(p)
    if kind in ("directory", None):
        return {"files": sorted(f.name for f in p.iterdir())}
    try:
        attrs = json.loads((p / "zarr.json").read_text()).get("attributes", {}) or {}
    except (OSError, ValueError, AttributeError):
        attrs = {}
    created = attrs.get("created_utc") or (attrs.get("provenance") or {}).get("created_utc")
    return {"kind": kind, "created_utc": created}


def _read_record(out: Path) -> dict:
    try:
        record = json.loads((out / RECORD).read_text())
    except (OSError, ValueError):
        return {}
    products = record.get("products") if isinstance(record, dict) else None
    return products if isinstance(products, dict) else {}


def _write_record(out: Path) -> None:
    """Record every product now in ``out`` (called after each step and at the end, however it ends)."""
    products = {name: _identity(out / name) for name in _PRODUCTS if (out / name).exists()}
    tmp = out / f"{RECORD}.tmp"
    tmp.write_text(json.dumps({"producer": "streaklab demo", "products": products}, indent=2))
    os.replace(tmp, out / RECORD)


def check_demo_output(out) -> list[Path]:
    """Check that the demo may write into ``out``; returns the earlier demo products to replace.

    Raises
    ------
    OutputPathError
        ``out`` is or lies inside a Zarr store, or a product name in it holds something an
        earlier demo into ``out`` did not write (or a recorded store now holds files that are
        not its own), named with the path.
    """
    out = Path(out)
    check_output_location(out, folder=True)
    if out.exists() and not out.is_dir():
        raise OutputPathError(f"refusing to write into {out}: it is {describe_existing(out)}, not a folder")
    record = _read_record(out) if out.is_dir() else {}
    replace = []
    for name in _PRODUCTS:
        p = out / name
        if not p.exists() and not p.is_symlink():
            continue
        known = record.get(name)
        ours = isinstance(known, dict) and not p.is_symlink()
        if ours and "files" in known and p.is_dir():    # the figures folder: report figures it listed
            extra = sorted({f.name for f in p.iterdir()} - (set(known["files"]) & set(_FIGURES)))
            if extra:
                raise OutputPathError(f"refusing to replace {p}: it holds files an earlier 'streaklab demo' did not "
                                      f"write ({', '.join(extra[:5])}{' and more' if len(extra) > 5 else ''}); "
                                      f"move them out first")
        elif ours:
            ours = _identity(p) == known
        if not ours:
            what = "a symbolic link" if p.is_symlink() else f"a {describe_existing(p)}"
            if what in ("a run", "a cube", "a decomposition", "a zarr"):
                what = f"{what} store"
            raise OutputPathError(f"refusing to replace {p} ({what}): an earlier 'streaklab demo' did not write it "
                                  f"({'it is not in' if known is None else 'it changed since it was recorded in'} "
                                  f"{out / RECORD}); move it away, or choose another --out")
        if p.is_dir() and "kind" in known:
            foreign = foreign_files(p)
            if foreign:
                raise OutputPathError(f"refusing to replace {p}: it holds files that are not the store's own "
                                      f"({', '.join(str(f.relative_to(p)) for f in foreign[:5])}"
                                      f"{' and more' if len(foreign) > 5 else ''}); move them out first")
        replace.append(p)
    return replace


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="demo-output",
                        help="folder for everything the demo writes (default demo-output)")
    parser.add_argument("--source", choices=("capture", "simulate"), default="capture",
                        help="capture: scan the simulated lab and reconstruct (default); "
                             "simulate: a synthetic cube with exact ground truth")
    parser.add_argument("--lines", type=int, default=16, help="scan lines (y) (default 16)")
    parser.add_argument("--nx", type=int, default=64, help="slit pixels (x) (default 64)")
    parser.add_argument("--nt", type=int, default=256, help="streak rows / time bins (default 256)")
    parser.add_argument("--method", choices=("convscd", "gradbm"), default="convscd",
                        help="solver: convscd (default) or the gradbm baseline")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="decompose on a local cluster of N processes (default: threads)")
    parser.add_argument("--nsr", type=float, default=0.05, help="noise-to-signal ratio of --source simulate")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the simulated scene and its noise (default 0); same seed, same data")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def class_fidelity(truth: dict, estimate: dict) -> dict:
    """Mean fidelity overall and per component class.

    Parameters
    ----------
    truth, estimate : dict
        ``direct`` (..., L), ``sss`` (..., L), ``interreflections`` (..., R, L) profiles.

    Returns
    -------
    dict: class -> {"mean": float, "pixels": int} for ``all``, ``direct``, ``sss`` and
    ``interreflections``; a class's mean is over the pixels whose truth holds it, and is
    1 - ||est_k - truth_k|| / ||truth_k|| (:func:`decomposition.model.fidelity.fidelity` on that class).
    """
    from decomposition.model.fidelity import fidelity

    out = {}
    f = fidelity(truth, estimate)
    ok = np.isfinite(f)
    out["all"] = {"mean": float(f[ok].mean()) if ok.any() else float("nan"), "pixels": int(ok.sum())}
    for k in ("direct", "sss", "interreflections"):
        fk = fidelity({k: truth[k]}, {k: estimate[k]})
        ok = np.isfinite(fk)
        out[k] = {"mean": float(fk[ok].mean()) if ok.any() else float("nan"), "pixels": int(ok.sum())}
    return out


def _estimate(store) -> dict:
    """Component profiles of a result store; undecomposed pixels count as empty."""
    g = store.group
    valid = np.asarray(g["valid"][...], bool)[..., None]
    if store.write_components:
        est = {"direct": g["direct"][...], "sss": g["sss"][...], "interreflections": g["ir"][...]}
    else:
        from core.model import render_components

        t = store.time_axis_ps()
        c = render_components(store.params(), t.size, float(store.attrs["time_bin_ps"]), float(t[0]))
        est = {"direct": c["direct"], "sss": c["sss"], "interreflections": c["interreflections"]}
    est = {k: np.nan_to_num(np.asarray(v, np.float64)) for k, v in est.items()}
    est["direct"] *= valid
    est["sss"] *= valid
    est["interreflections"] *= valid[..., None]
    return est


def _say(msg, stream):
    print(msg, file=stream, flush=True)


def _capture_cube(out: Path, *, lines, nx, nt, seed, stream, quiet):
    """Scan the simulated lab and reconstruct; -> (cube path, truth component dict, description)."""
    try:
        from acquisition.config import parse_config
        from acquisition.rig import run_capture, simulated_scene
        from reconstruction.build import reconstruct
    except ImportError as exc:
        raise CommandError(f"the capture pipeline is not available ({exc}); use --source simulate") from None
    from core.model import render_components
    from reconstruction.cubestore import open_cube

    config = _demo_config(parse_config, lines=lines, nx=nx, nt=nt, seed=seed)
    run_path, cube_path = out / "run.zarr", out / "cube.zarr"
    t0 = time.perf_counter()
    _say(f"[1/5] capture: {counted(config.n_lines, 'line')} x {counted(nx, 'pixel')} x {counted(nt, 'row')} from the simulated lab -> {run_path}",
         stream)
    run_capture(config, run_path, simulate=True)
    _say(f"      {time.perf_counter() - t0:.1f} s", stream)
    t0 = time.perf_counter()
    _say(f"[2/5] reconstruct -> {cube_path}", stream)
    reconstruct(run_path, cube_path)
    cube = open_cube(cube_path)
    _say(f"      cube {cube.shape[0]} x {cube.shape[1]} x {cube.shape[2]}, {cube.time_bin_ps:g} ps bins "
         f"({time.perf_counter() - t0:.1f} s)", stream)
    scene = simulated_scene(config)
    cam = config["camera"]
    scale = scene.signal_scale(cam["exposure_s"], cam.get("gain"))
    comps = render_components(scene.params, cube.shape[2], cube.time_bin_ps, cube.t0_ps)
    truth = {k: v * scale for k, v in comps.items()}
    return cube_path, truth, "simulated capture (SimulatedLab scene, photon and read noise)"


def _demo_config(parse_config, *, lines, nx, nt, seed):
    """The example simulated scan, resized to the demo's lines, pixels and rows."""
    import tomllib

    from acquisition.config import example_config_path

    example = example_config_path("sim")
    raw = tomllib.loads(example.read_text())
    raw.setdefault("scan", {})["count"] = int(lines)
    raw["scan"].pop("angles_deg", None)
    sim = raw.setdefault("simulation", {})
    sim.update({"n_x": int(nx), "n_t": int(nt), "seed": int(seed)})
    # The simulated sweep spans the same window whatever the number of rows (see VirtualScene.default),
    # so the calibration polynomial scales with the number of rows.
    if int(nt) != 256:
        c0, c1, c2 = raw["calibration"]["time_poly_ps"]
        raw["calibration"]["time_poly_ps"] = [c0, c1 * 256 / nt, c2 * (256 / nt) ** 2]
    return parse_config(raw, source=str(example))


def _simulated_cube(out: Path, *, lines, nx, nt, nsr, seed, stream):
    from decomposition.evaluation.synthetic import make_cube
    from streaklab.commands.simulate import simulate_command, write_simulation

    cube_path = out / "cube.zarr"
    t0 = time.perf_counter()
    _say(f"[1/5] simulate: synthetic cube {lines} x {nx} x {nt}, white noise at NSR {nsr:g} -> {cube_path}", stream)
    data = make_cube(lines, nx, nt, nsr=nsr, noise="white", seed=seed)
    write_simulation(cube_path, data, overwrite=True,
                     command=simulate_command((lines, nx, nt), nsr=nsr, noise="white", seed=seed))
    _say(f"[2/5] (no reconstruction needed: the cube is written directly; {time.perf_counter() - t0:.1f} s)", stream)
    truth = {k: np.asarray(v, np.float64) for k, v in data.components.items()}
    return cube_path, truth, f"synthetic cube (Fig. 3 kinds a/b/c, white noise NSR {nsr:g})"


def run_demo(out="demo-output", *, source="capture", lines=16, nx=64, nt=256, method="convscd", workers=None,
             nsr=0.05, seed=0, progress=True, stream=None) -> dict:
    """Run the demo; returns a dict with the output paths, timings and the fidelities."""
    stream = sys.stdout if stream is None else stream
    if min(lines, nx) < 1 or nt < 16:
        raise CommandError(f"demo size must be at least 1 line x 1 pixel x 16 bins; got {lines} x {nx} x {nt}")
    if source not in ("capture", "simulate"):
        raise CommandError(f"unknown source {source!r}")
    out = Path(out).resolve()
    earlier = check_demo_output(out)
    out.mkdir(parents=True, exist_ok=True)
    for p in earlier:  # the demo's own products from an earlier run
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink()
    _write_record(out)
    try:
        return _run_steps(out, source=source, lines=lines, nx=nx, nt=nt, method=method, workers=workers, nsr=nsr,
                          seed=seed, progress=progress, stream=stream)
    finally:  # whatever was written, also by an interrupted run, is the demo's to replace next time
        _write_record(out)


def _run_steps(out: Path, *, source, lines, nx, nt, method, workers, nsr, seed, progress, stream) -> dict:
    from decomposition.store.resultstore import open_result_store
    from reconstruction.cubestore import open_cube
    from decomposition.store.pipeline import decompose_to_store
    from streaklab.report import make_report

    start = time.perf_counter()
    if source == "capture":
        cube_path, truth, what = _capture_cube(out, lines=lines, nx=nx, nt=nt, seed=seed, stream=stream,
                                               quiet=not progress)
    else:
        cube_path, truth, what = _simulated_cube(out, lines=lines, nx=nx, nt=nt, nsr=nsr, seed=seed, stream=stream)
    _write_record(out)
    result_path = out / "result.zarr"
    t0 = time.perf_counter()
    _say(f"[3/5] decompose ({method}, {'%d worker processes' % workers if workers else 'threads'}) -> {result_path}",
         stream)
    # chunks of a few lines: several chunks even for a small scan, so workers share the work
    ny, nx_ = open_cube(cube_path).shape[:2]
    # as `streaklab decompose` does by default: the image coupled, one instrument's PSF shared
    summary = decompose_to_store(cube_path, result_path, method=method, workers=workers, progress=progress,
                                 chunks=(min(ny, 4), min(nx_, 64)), stream=sys.stderr, spatial="auto", shared="auto")
    _write_record(out)
    coupled = "spatial" in open_result_store(result_path).attrs.get("job", {})
    _say(f"      {counted(summary['pixels'], 'pixel')} in {time.perf_counter() - t0:.1f} s "
         f"({summary['pixels_per_s']:,.0f} px/s){', neighbouring pixels coupled' if coupled else ''}", stream)
    if summary.get("shared"):
        from streaklab.report import shared_line

        _say(f"      {shared_line(summary['shared'])}", stream)
    figs = out / "figs"
    _say(f"[4/5] report -> {figs}", stream)
    rep = make_report(result_path, figs)
    _say(f"[5/5] fidelity against the ground truth of the {what}", stream)
    fid = class_fidelity(truth, _estimate(open_result_store(result_path)))
    names = {"all": "all components", "direct": "direct", "sss": "subsurface scattering",
             "interreflections": "inter-reflections"}
    for k, v in fid.items():
        _say(f"      {names[k]:<22} mean fidelity {v['mean']:.3f}  ({counted(v['pixels'], 'pixel')} with it in the truth)", stream)
    (out / "fidelity.json").write_text(json.dumps({"source": what, "method": method, "fidelity": fid}, indent=2))
    total = time.perf_counter() - start
    _say(f"\ndone in {total:.1f} s. Outputs in {out}:", stream)
    for name in ("run.zarr", "cube.zarr", "result.zarr"):
        if (out / name).exists():
            _say(f"  {out / name}", stream)
    for f in rep["files"]:
        _say(f"  {f}", stream)
    _say(f"  {out / 'fidelity.json'}", stream)
    return {"out": out, "cube": cube_path, "result": result_path, "figs": figs, "fidelity": fid,
            "seconds": total, "report": rep}


def run(args) -> int:
    run_demo(args.out, source=args.source, lines=args.lines, nx=args.nx, nt=args.nt, method=args.method,
             workers=args.workers, nsr=args.nsr, seed=args.seed, progress=not args.quiet)
    return 0
