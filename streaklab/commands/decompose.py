"""``streaklab decompose``: decompose every pixel of a cube into a result store, chunk by chunk.

    streaklab decompose cube.zarr --out result.zarr [--method convscd|gradbm] [--components d,s,r[,b]]
                        [--workers N | --scheduler tcp://HOST:PORT] [--chunks BY BX]
                        [--resume] [--overwrite] [--no-components]
                        [--shared psf,delay,alpha [--regions labels.npy] [--psf-map]]

The cube is read with dask in pixel chunks (all of t in each), every chunk is decomposed as one
batch and written into its own region of the result store as soon as it is finished, then
marked done.  Interrupted runs (Ctrl-C, a crash, a killed process) keep every finished chunk;
``--resume`` computes only the rest and gives the same store as an uninterrupted run.

``--shared`` makes parameters global, as FLIM global analysis does: estimated once from the
whole cube before any chunk runs, written to the result store's ``shared`` attribute with their
standard errors, and held in every pixel's fit (docs/decomposition.md, "Shared parameters").

Also accepts a ``.npy`` array (y, x, t) or (n, t) with ``--time-bin-ps`` for small inputs.
This module only parses the arguments and prints; the pipeline itself is
:func:`decomposition.store.pipeline.decompose_to_store`.
"""
from __future__ import annotations

import json

from core.words import counted, plural
from decomposition.options import METHODS
from decomposition.store.pipeline import decompose_to_store
from streaklab.cli import CommandError

__all__ = ["add_arguments", "run", "parse_components"]


#: print the POOR_FIT note when at least this fraction of the decomposed pixels carry the flag
POOR_FIT_NOTE_FRACTION = 0.5


def add_arguments(parser) -> None:
    parser.add_argument("input", help="cube store (.zarr) or a .npy array (y, x, t) or (n, t)")
    parser.add_argument("--out", required=True, help="result store to write (.zarr directory)")
    parser.add_argument("--method", choices=METHODS, default="convscd", help="solver (default convscd)")
    parser.add_argument("--components", default="d,s,r",
                        help="component families to look for, comma-separated from d (direct), s (subsurface), "
                             "r (inter-reflections), b (a constant background per pixel); default d,s,r")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None, metavar="N",
                       help="run on a local cluster of N worker processes (default: threads in this process)")
    where.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                       help="run on an existing dask.distributed cluster (workers must see the same paths); "
                            "tls://HOST:PORT with --tls-ca-file/--tls-cert/--tls-key for a secured one")
    parser.add_argument("--tls-ca-file", default=None, metavar="CA.pem",
                        help="with --scheduler tls://...: CA certificate of the cluster")
    parser.add_argument("--tls-cert", default=None, metavar="CERT.pem",
                        help="with --scheduler tls://...: this client's certificate (may hold the key too)")
    parser.add_argument("--tls-key", default=None, metavar="KEY.pem",
                        help="with --scheduler tls://...: this client's private key")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="threads of the local scheduler when neither --workers nor --scheduler is given "
                             "(default: number of cores)")
    parser.add_argument("--chunks", type=int, nargs=2, default=None, metavar=("BY", "BX"),
                        help="pixel chunk (default: the cube's own chunking)")
    parser.add_argument("--max-interreflections", type=int, default=3, metavar="R",
                        help="inter-reflections kept per pixel, in order of delay (default 3, the solver's "
                             "default; pixels with more are flagged TRUNCATED)")
    parser.add_argument("--no-components", action="store_true",
                        help="store parameters and fit quality only, not the component cubes")
    parser.add_argument("--nan-policy", choices=("omit", "raise", "mark", "error"), default="omit",
                        help="pixels with NaN/inf samples: 'omit' leaves them undecomposed with valid=False "
                             "(default); 'raise' refuses the cube before any work ('mark' and 'error' are "
                             "the same two)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="solver option (repeatable); VALUE is read as JSON if it parses, else as a string")
    parser.add_argument("--time-bin-ps", type=float, default=None, help="time bin of a .npy input (ps)")
    parser.add_argument("--t0-ps", type=float, default=None, help="time of bin 0 of a .npy input (ps; default one bin)")
    coupling = parser.add_mutually_exclusive_group()
    coupling.add_argument("--spatial", action="store_true",
                          help="couple neighbouring pixels (neighbours' answers as starts, an edge-preserving "
                               "prior on the direct delays, pooled echoes); chunks are read with a halo.  The "
                               "default for an image (a cube, or a (y, x, t) array) decomposed with convscd, "
                               "with the PSF width shared where the pixels' own widths are one instrument's "
                               "(Gaussian PSF); a resumed run keeps its store's choice")
    coupling.add_argument("--per-pixel", action="store_true",
                          help="decompose every pixel on its own (no coupling, nothing shared unless --shared "
                               "says so): the default for a list of profiles (n, t)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run into --out")
    parser.add_argument("--overwrite", action="store_true", help="replace whatever is at --out")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.add_argument("--shared", default=None, metavar="psf,delay,alpha",
                        help="parameters every pixel shares, estimated once from the whole cube (with standard "
                             "errors, in the store's 'shared' attribute) and held in each pixel's fit: 'psf' the "
                             "PSF width (one instrument), 'delay' the onset (a microscope), 'alpha' the sss decay "
                             "rate; any comma-separated combination (with a measured response (--irf) 'psf' is "
                             "its time scale, a stretch; no --psf-map)")
    parser.add_argument("--regions", default=None, metavar="LABELS.npy",
                        help="with --shared alpha: a (y, x) integer label image, one decay rate per label >= 0 "
                             "(negative labels keep their own)")
    parser.add_argument("--psf-map", action="store_true",
                        help="with --shared psf: the width as a smooth quadratic surface over (y, x) (a streak "
                             "camera's slit) instead of one number")
    parser.add_argument("--irf", default="auto", metavar="PATH|gaussian|auto",
                        help="instrument response: a stored response (.npz, response store, or a cube's irf "
                             "group); 'gaussian' forces the Gaussian PSF; default 'auto': the response stored "
                             "in the input cube if it has one, else the Gaussian")


def parse_components(text: str) -> tuple[str, ...]:
    """``"d,s,r"`` -> ``("d", "s", "r")`` (validated by the solver's own parser, order kept, no duplicates)."""
    from decomposition.options import component_letters

    try:
        return component_letters(text)
    except ValueError as exc:
        raise CommandError(f"--components takes a comma-separated subset of d, s, r, b: {exc}") from None


def parse_solver_options(items, method: str = "convscd", check_values: bool = False) -> dict:
    """``KEY=VALUE`` items -> {key: value}; VALUE is read as JSON if it parses, else as a string.

    Every key is checked against the solver's option fields (and, for ``gradbm``, the
    baseline's options); the values against the fields' types and ranges by
    ``decompose_to_store``, before any work, or here with ``check_values`` (for callers that
    spend time before they decompose: the benchmarks).
    """
    from decomposition.methods.gradbm import GRADBM_DEFAULTS
    from decomposition.options import OptionError, option_names, options_from_mapping

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise CommandError(f"--option takes KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    extra = set(GRADBM_DEFAULTS) if method == "gradbm" else set()
    for key in out:
        if key not in option_names() and key not in extra:
            raise CommandError(f"--option {key}: the solver refuses these settings: unknown option "
                               f"(known: {', '.join(sorted(set(option_names()) | extra))})")
    if check_values:
        try:
            options_from_mapping(out, strict=False)
        except OptionError as exc:
            raise CommandError(f"--option: the solver refuses these settings: {exc}") from None
    return out      # else the values are checked against their fields by the pipeline, before any work


def _tls_files(args):
    given = [f for f, v in (("--tls-ca-file", args.tls_ca_file), ("--tls-cert", args.tls_cert),
                            ("--tls-key", args.tls_key)) if v is not None]
    if not given:
        return None
    if args.scheduler is None:
        raise CommandError(f"{given[0]} is for --scheduler tls://...; --workers starts its own secured cluster")
    if args.tls_ca_file is None or args.tls_cert is None:
        raise CommandError("--scheduler tls://... needs both --tls-ca-file and --tls-cert (and --tls-key unless "
                           "the certificate file holds the key)")
    from decomposition.store.cluster import TlsFiles

    return TlsFiles(args.tls_ca_file, args.tls_cert, args.tls_key)


def resume_command(args) -> str:
    """The command line that continues this run: the words it was started with
    (``args.command_words``, recorded by the CLI), without ``--overwrite``, with ``--resume``."""
    import shlex

    typed = getattr(args, "command_words", None) or ["decompose", str(args.input), "--out", str(args.out)]
    words = [w for w in typed
             if not (w.startswith("--ov") and "--overwrite".startswith(w))]   # argparse takes its prefixes too
    return shlex.join(["streaklab", *words] + ([] if "--resume" in words else ["--resume"]))


class Terminated(KeyboardInterrupt):
    """SIGTERM: stops the run the way Ctrl-C does (finished chunks kept, the count printed)."""


def run(args) -> int:
    import signal
    import sys
    import threading

    def on_sigterm(signum, frame):
        raise Terminated()

    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        return _run(args)
    except KeyboardInterrupt as exc:
        print(f"streaklab decompose: {'terminated' if isinstance(exc, Terminated) else 'interrupted'}; "
              f"resume with:\n  {resume_command(args)}", file=sys.stderr, flush=True)
        return 143 if isinstance(exc, Terminated) else 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _spatial_choice(args):
    """--spatial: True; --per-pixel: None; neither: "auto" (an image is coupled, a list of
    profiles is not; a resumed run keeps its store's choice)."""
    if args.spatial:
        return True
    return None if args.per_pixel else "auto"


def _run(args) -> int:
    tls = _tls_files(args)
    summary = decompose_to_store(
        args.input, args.out, method=args.method, components=parse_components(args.components),
        options=parse_solver_options(args.option, args.method), chunks=args.chunks, workers=args.workers, scheduler=args.scheduler,
        threads=args.threads, n_ir=args.max_interreflections, write_components=not args.no_components,
        nan_policy=args.nan_policy, resume=args.resume, overwrite=args.overwrite, time_bin_ps=args.time_bin_ps,
        t0_ps=args.t0_ps, progress=not args.quiet, tls=tls, irf=args.irf, spatial=_spatial_choice(args),
        shared=args.shared if args.shared is not None else ("auto" if _spatial_choice(args) == "auto" else None),
        regions=args.regions, psf_map=args.psf_map)
    ny, nx, nt = summary["shape"]
    if summary.get("shared"):
        from streaklab.report import shared_line

        print(shared_line(summary["shared"]))
    irf = summary.get("irf", {})
    if irf.get("kind") == "response":
        print(f"instrument response: {irf['source']} (FWHM {irf['fwhm_ps']:.2f} ps, {irf['n_samples']} samples "
              f"of {irf['time_step_ps']:g} ps, sha256 {irf['samples_sha256'][:12]})")
    else:
        print("instrument response: the Gaussian PSF")
    if summary.get("noise_law", {}).get("source") == "cube":
        print("photon noise: one camera's variance law for every pixel of a chunk (the cube's noise_law; "
              "--option signal_noise_law=auto to judge it from the pixels)")
    if summary["chunks_done"] == 0:
        print(f"nothing to do: {'the' if summary['chunks_total'] == 1 else 'all'} {counted(summary['chunks_total'], 'chunk')} "
              f"of {summary['out']} {plural(summary['chunks_total'], 'was', 'were')} already done")
        return 0
    print(f"decomposed {counted(summary['pixels'], 'pixel')} of a {ny} x {nx} x {nt} cube in {summary['seconds']:.1f} s "
          f"({summary['pixels_per_s']:,.0f} px/s) -> {summary['out']}")
    if summary.get("seconds_compile"):
        print(f"note: {summary['seconds_compile']:.1f} s of that compiled the solver's kernels, once; "
              f"later runs load them from the cache")
    if summary.get("chunks_before"):
        print(f"the notes count the whole store: the {counted(summary['chunks_done'], 'chunk')} of this run and the "
              f"{counted(summary['chunks_before'], 'chunk')} done before it")
    if summary["invalid_pixels"]:
        print(f"note: {counted(summary['invalid_pixels'], 'pixel')} had NaN/inf samples and "
              f"{plural(summary['invalid_pixels'], 'was', 'were')} not decomposed (valid = False)")
    if summary.get("unfinished_line_pixels"):
        print(f"note: {summary['unfinished_line_pixels']:,} of them lie on scan lines the capture did not finish "
              f"(line_valid False in the cube): 'streaklab capture --resume', then reconstruct, to take them")
    judged = summary.get("decomposed_pixels", summary["pixels"])
    if judged > 0 and summary.get("poor_fit_pixels", 0) >= POOR_FIT_NOTE_FRACTION * judged:
        families = parse_components(args.components)
        with_b = ",".join(families + (() if "b" in families else ("b",)))
        print(f"note: {summary['poor_fit_pixels']:,} of {counted(judged, 'pixel')} "
              f"{plural(summary['poor_fit_pixels'], 'is', 'are')} flagged POOR_FIT: the model misses light "
              f"they hold. A constant offset under the data (--components {with_b} fits one), a response that is "
              f"not a Gaussian (--irf, streaklab calibrate-irf) or pulses cut by the window's edge are the usual causes")
    if summary["ir_truncated_pixels"]:
        print(f"note: {counted(summary['ir_truncated_pixels'], 'pixel')} had more than "
              f"{counted(args.max_interreflections, 'inter-reflection')} (flagged TRUNCATED); the later ones were dropped "
              f"(raise --max-interreflections to keep them)")
    return 0
