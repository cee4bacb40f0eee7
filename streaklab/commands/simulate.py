"""``streaklab simulate --out CUBE --shape NY NX NT``: a synthetic cube with its ground truth.

The store is an ordinary cube store (:mod:`reconstruction.cubestore`: ``cube`` (y, x, t)
float32, ``t``, ``y``, ``x``) plus a group ``truth``:

    truth/direct_delay_ps, direct_amplitude, direct_sigma_ps             (y, x)     float64
    truth/sss_delay_ps, sss_amplitude, sss_alpha_per_ps, sss_sigma_ps    (y, x)     float64
    truth/ir_delay_ps, ir_amplitude, ir_sigma_ps                         (y, x, r)  float64
    truth/direct, truth/sss                                              (y, x, t)  float32
    truth/ir                                                             (y, x, r, t) float32
    truth/t (t,) ps, truth/y, truth/x (as in the cube), truth/r (r,) bounce number (2, 3, ...)

NaN marks an absent component; the ``ir`` profiles of absent inter-reflections are zero.
Every array has ``dimension_names`` and a ``units`` attribute; the ``truth`` group's
attributes record ``nsr``, ``noise``, ``seed``, ``kinds``, the time axis and the scene
ranges.  ``xarray.open_zarr(path, group="truth", consolidated=False)`` opens the truth.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import shlex
import sys

import numpy as np

from streaklab.cli import CommandError

SIGNAL_UNITS = "arbitrary"

_PARAM_UNITS = {
    "delay_ps": "ps", "sigma_ps": "ps", "alpha_per_ps": "1/ps", "amplitude": SIGNAL_UNITS,
}


def add_arguments(parser) -> None:
    parser.add_argument("--out", required=True, help="cube store to write (Zarr directory)")
    parser.add_argument("--shape", nargs=3, type=int, required=True, metavar=("NY", "NX", "NT"),
                        help="cube size: lines, slit pixels, time bins")
    parser.add_argument("--nsr", type=float, default=0.05,
                        help="noise-to-signal ratio ||noise|| / ||clean|| of every pixel (default 0.05)")
    parser.add_argument("--noise", default="white",
                        help="white (fluctuation), pink (detector), photon (Poisson) or none (default white)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0); same seed, same cube")
    parser.add_argument("--time-bin-ps", type=float, default=2.0, help="time bin width in ps (default 2)")
    parser.add_argument("--t0-ps", type=float, default=None, help="time of the first bin in ps (default: one bin)")
    parser.add_argument("--kinds", default="a,b,c",
                        help="component sets in equal shares, comma-separated: a = d+s, b = d+s+r2, "
                             "c = d+s+r2+r3, or any set like d+r2 (default a,b,c)")
    parser.add_argument("--scenes", default="legacy",
                        help="scene preset: legacy (default) or paper (the paper's parameter space: sigma 1-10 ps, "
                             "sss peak 0.05-3 x and inter-reflections 0.01-1 x the direct's, onset 0-3 sigma)")
    parser.add_argument("--bin-integrated", action="store_true",
                        help="render each bin as the mean of the model over its width (default: point samples)")
    parser.add_argument("--chunks", nargs=2, type=int, metavar=("BY", "BX"),
                        help="chunk size in pixels (time is never split); default 16 64")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def _units(key: str) -> str:
    for suffix, unit in _PARAM_UNITS.items():
        if key.endswith(suffix):
            return unit
    raise KeyError(key)


def simulate_command(shape, *, nsr: float = 0.05, noise: str = "white", seed: int = 0, time_bin_ps: float = 2.0,
                     t0_ps: float | None = None, kinds: str = "a,b,c", scenes: str = "legacy",
                     bin_integrated: bool = False, chunks=None) -> str:
    """The ``streaklab simulate`` command line that writes this cube again, every setting spelled
    out and no ``--out``: a store records it (provenance ``command``) and ``verify`` adds the path
    it was given, so a copied or moved store is rewritten where it is."""
    argv = ["streaklab", "simulate", "--shape", *(str(int(n)) for n in shape), "--nsr", repr(float(nsr)),
            "--noise", str(noise), "--seed", str(int(seed)), "--time-bin-ps", repr(float(time_bin_ps))]
    if t0_ps is not None:
        argv += ["--t0-ps", repr(float(t0_ps))]
    argv += ["--kinds", str(kinds), "--scenes", str(scenes)]
    if bin_integrated:
        argv.append("--bin-integrated")
    if chunks is not None:
        argv += ["--chunks", *(str(int(c)) for c in chunks)]
    return shlex.join(argv)


def command_for(command: str, out) -> str | None:
    """A recorded ``streaklab simulate`` command (:func:`simulate_command`, or an earlier
    release's, which named its own ``--out``) writing to ``out`` instead, with ``--overwrite``;
    None for any other command."""
    try:
        argv = shlex.split(command)
    except ValueError:
        return None
    if argv[:2] != ["streaklab", "simulate"]:
        return None
    kept, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--out":
            skip = True
        elif not (arg.startswith("--out=") or arg == "--overwrite"):
            kept.append(arg)
    return shlex.join(kept + ["--out", str(out), "--overwrite"])


def write_simulation(path, data, *, chunks=None, overwrite: bool = False, command: str | None = None):
    """Write a :class:`decomposition.evaluation.synthetic.SyntheticData` cube (leading shape (ny, nx)) and its truth.

    The store is written beside ``path`` and renamed into place when complete, so an error
    never leaves half a store or destroys an existing one.  ``command``: the command line that
    writes it again (:func:`simulate_command`), kept in the provenance.  Returns the opened cube.
    """
    import zarr

    from core.integrity import create_array
    from decomposition.store.resultstore import long_name_for
    from reconstruction.cubestore import open_cube, write_cube
    from core.staging import staged_output
    from core.provenance import __version__

    ny, nx, nt = data.noisy.shape
    n_ir = data.params["ir_delay_ps"].shape[-1]
    ranges = dataclasses.asdict(data.ranges)
    settings = {"nsr": data.nsr, "noise": data.noise, "seed": data.seed,
                "kinds": sorted(set(np.asarray(data.kinds).ravel().tolist())),
                "time_bin_ps": data.time_bin_ps, "t0_ps": data.t0_ps, "bin_integrated": data.bin_integrated,
                "scene_ranges": {k: list(v) if isinstance(v, tuple) else v for k, v in ranges.items()}}
    provenance = {"producer": "streaklab simulate", "software_version": __version__,
                  "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                  "synthetic": settings}
    if command:
        provenance["command"] = command
    if chunks is None:
        chunks = (min(ny, 16), min(nx, 64))
    by, bx = min(int(chunks[0]), ny), min(int(chunks[1]), nx)
    with staged_output(path, overwrite=overwrite, kind="cube") as tmp:
        write_cube(tmp, data.noisy, time_bin_ps=data.time_bin_ps, t0_ps=data.t0_ps, chunks=(by, bx),
                   units=SIGNAL_UNITS, provenance=provenance)
        root = zarr.open_group(str(tmp), mode="r+")
        g = root.create_group("truth")
        g.attrs.update({"streaklab_kind": "truth", "description": "ground truth of the simulated cube",
                        "units": SIGNAL_UNITS, **settings})
        t = create_array(g, "t", shape=(nt,), dtype="float64", dimension_names=["t"],
                         attributes={"units": "ps", "long_name": "time of bin centre"})
        t[:] = data.t0_ps + data.time_bin_ps * np.arange(nt)
        for dim, size in (("y", ny), ("x", nx)):
            c = create_array(g, dim, shape=(size,), dtype="float64", dimension_names=[dim],
                             attributes=dict(root[dim].attrs))
            c[:] = root[dim][:]
        r = create_array(g, "r", shape=(n_ir,), chunks=(max(n_ir, 1),), dtype="int64", dimension_names=["r"],
                         attributes={"units": "1", "long_name": "bounce number of the inter-reflection"})
        if n_ir:
            r[:] = np.arange(2, 2 + n_ir)
        for key, value in data.params.items():
            dims = ["y", "x", "r"] if value.ndim == 3 else ["y", "x"]
            ch = (by, bx) + ((max(n_ir, 1),) if value.ndim == 3 else ())
            a = create_array(g, key, shape=value.shape, chunks=ch, dtype="float64", dimension_names=dims,
                             fill_value=np.nan, attributes={"units": _units(key), "long_name": f"true {long_name_for(key)}",
                                                             "absent": "NaN"})
            if value.size:
                a[...] = value
        comps = {"direct": (data.components["direct"], ["y", "x", "t"], "direct reflection"),
                 "sss": (data.components["sss"], ["y", "x", "t"], "subsurface scattering"),
                 "ir": (data.components["interreflections"], ["y", "x", "r", "t"],
                        "inter-reflections r2, r3, ... in order of arrival")}
        for name, (value, dims, long_name) in comps.items():
            ch = (by, bx) + ((max(n_ir, 1),) if len(dims) == 4 else ()) + (nt,)
            a = create_array(g, name, shape=value.shape, chunks=ch, dtype="float32", dimension_names=dims,
                             fill_value=0.0, attributes={"units": SIGNAL_UNITS, "long_name": f"clean {long_name}"})
            if value.size:
                a[...] = value.astype(np.float32)
    return open_cube(path)


def run(args) -> int:
    from decomposition.evaluation.synthetic import make_cube

    ny, nx, nt = args.shape
    if min(ny, nx) <= 0 or nt < 2:
        raise CommandError(f"--shape needs positive NY NX and NT >= 2, got {ny} {nx} {nt}")
    if args.chunks is not None and min(args.chunks) <= 0:
        raise CommandError(f"--chunks must be positive, got {args.chunks[0]} {args.chunks[1]}")
    if not np.isfinite(args.nsr) or args.nsr < 0:
        raise CommandError(f"--nsr must be a finite number >= 0, got {args.nsr}")
    if not np.isfinite(args.time_bin_ps) or args.time_bin_ps <= 0:
        raise CommandError(f"--time-bin-ps must be positive, got {args.time_bin_ps}")
    try:
        data = make_cube(ny, nx, nt, nsr=args.nsr, noise=args.noise, seed=args.seed,
                         time_bin_ps=args.time_bin_ps, t0_ps=args.t0_ps, kinds=args.kinds, ranges=args.scenes,
                         bin_integrated=bool(args.bin_integrated))
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    command = simulate_command(args.shape, nsr=args.nsr, noise=args.noise, seed=args.seed,
                               time_bin_ps=args.time_bin_ps, t0_ps=args.t0_ps, kinds=args.kinds, scenes=args.scenes,
                               bin_integrated=bool(args.bin_integrated), chunks=args.chunks)
    cube = write_simulation(args.out, data, chunks=args.chunks, overwrite=args.overwrite, command=command)
    n_ir = data.params["ir_delay_ps"].shape[-1]
    print(f"wrote {cube.path}: cube (y={ny}, x={nx}, t={nt}) with ground truth in group 'truth' "
          f"(up to {n_ir} inter-reflections); {data.noise} noise at NSR {data.nsr:g}, seed {args.seed}",
          file=sys.stderr)
    return 0
