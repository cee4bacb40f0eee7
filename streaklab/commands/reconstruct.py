"""``streaklab reconstruct RUN --out CUBE``: a run store to a calibrated (y, x, t) cube."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("run", help="run store written by 'streaklab capture'")
    parser.add_argument("--out", required=True, help="cube store to write (Zarr directory)")
    parser.add_argument("--chunks", nargs=2, type=int, metavar=("BY", "BX"),
                        help="cube chunk size in pixels (time is never split); default 16 64")
    parser.add_argument("--flat", metavar="FLAT.npy", help="flat field, shape (x, t) or (x,); normalised to mean 1")
    parser.add_argument("--allow-partial", action="store_true",
                        help="reconstruct a run with unfinished lines (their cube rows are NaN, line_valid False)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument("--time-source", choices=("auto", "camera", "config"),
                        help="row times: the camera's scaling table recorded at capture, the configured "
                             "polynomial, or auto (the table when the run has one); default: the run's "
                             "calibration.time_source")
    parser.add_argument("--align", action=argparse.BooleanOptionalAction, default=None,
                        help="align every frame on the run's time reference before averaging "
                             "(default: on when the run records a fiducial pulse or the laser sync's "
                             "trigger intervals)")
    parser.add_argument("--align-on", choices=("pulse", "sync"),
                        help="the reference: the fiducial pulse in the frames, or the laser sync's measured "
                             "trigger intervals (sync.reference); default: the one the run records, the "
                             "pulse where it records both")
    parser.add_argument("--sweep", metavar="SWEEP", help="sweep calibration from 'streaklab calibrate-sweep' "
                        "(a .npz, a sweep store, or a cube holding one): its row times replace the camera's")
    parser.add_argument("--fiducial-min-snr", type=float, default=5.0, metavar="RATIO",
                        help="peak-to-noise ratio the fiducial needs in every frame (default 5)")


def run(args) -> int:
    from reconstruction.build import ALIGN_REFERENCES, reconstruct

    if args.chunks is not None and min(args.chunks) <= 0:
        raise CommandError(f"--chunks must be positive, got {args.chunks[0]} {args.chunks[1]}")
    if not (np.isfinite(args.fiducial_min_snr) and args.fiducial_min_snr > 0):
        raise CommandError(f"--fiducial-min-snr must be positive, got {args.fiducial_min_snr}")
    cube = reconstruct(args.run, args.out, chunks=args.chunks, flat_path=args.flat,
                       allow_partial=args.allow_partial, overwrite=args.overwrite,
                       time_source=args.time_source, align=args.align, sweep_path=args.sweep,
                       fiducial_min_snr=args.fiducial_min_snr, align_on=args.align_on)
    ny, nx, nt = cube.shape
    missing = cube.attrs["provenance"].get("lines_missing", [])
    note = f", {len(missing)} unfinished lines left NaN" if missing else ""
    prov = cube.attrs["provenance"]
    print(f"wrote {cube.path}: cube (y={ny}, x={nx}, t={nt}) float32, {cube.time_bin_ps:g} ps bins from "
          f"{cube.t0_ps:g} ps{note}; row times from the {prov.get('time_calibration_source')}", file=sys.stderr)
    if prov.get("aligned_on_fiducial"):
        from core.integrity import read_checked
        corr = np.asarray(read_checked(cube.group["fiducial_correction_ps"], ..., store=cube.path))
        corr = corr[np.isfinite(corr)]
        on = "the laser sync's trigger intervals" if prov.get("alignment_reference") == ALIGN_REFERENCES["sync"] \
            else "the fiducial"
        print(f"aligned {corr.size} frames on {on}: corrections {corr.min():+.3g} to {corr.max():+.3g} ps, "
              f"RMS {np.sqrt(np.mean(corr ** 2)):.3g} ps (fiducial_correction_ps)", file=sys.stderr)
        if "uncovered_bins" in cube.group:
            gap = np.asarray(read_checked(cube.group["uncovered_bins"], ..., store=cube.path))
            if gap.any():
                print(f"streaklab reconstruct: note: {int((gap > 0).sum())} of {gap.size} lines were moved so far "
                      f"that up to {int(gap.max())} bins at the window's ends lie outside every frame: 0 there "
                      f"(uncovered_bins)", file=sys.stderr)
    if prov.get("camera_and_config_agree") is False:
        print(f"streaklab reconstruct: warning: the camera's scaling table and calibration.time_poly_ps differ by "
              f"up to {prov['camera_vs_config_max_diff_ps']:.3g} ps", file=sys.stderr)
    return 0
