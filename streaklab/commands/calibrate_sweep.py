"""``streaklab calibrate-sweep RUN --etalon-ps PS --out SWEEP``: the sweep's row times from an etalon capture.

The run is a capture of an etalon pulse pair (two pulses ``--etalon-ps`` apart) whose trigger
delay steps from line to line, so that the pair crosses the rows.  Each line's frames are
averaged, dark-subtracted and summed over the slit into one profile; both pulses are located in
it and the row-time curve is fitted (:mod:`reconstruction.sweep`).  The delays are
``--delays-ps`` (one per line, in acquisition order) or the run's ``line_delay_ps`` array;
without either only the pair separations are used.  The calibration is written to ``--out``
(a Zarr directory, or a file ending in ``.npz``) with the time range and row count it is for;
``streaklab reconstruct --sweep`` applies it.
"""
from __future__ import annotations

import sys

import numpy as np

from core.staging import check_output_location, describe_existing
from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("source", metavar="RUN", help="run store of an etalon capture (the raw rows are needed)")
    parser.add_argument("--out", required=True, metavar="SWEEP",
                        help="calibration to write (Zarr directory, or a file ending in .npz)")
    parser.add_argument("--etalon-ps", type=float, required=True, metavar="PS", help="separation of the pulse pair, ps")
    parser.add_argument("--delays-ps", type=float, nargs="+", metavar="PS",
                        help="trigger delay of each line, ps, in acquisition order (default: the run's "
                             "line_delay_ps array, else the pair separations alone)")
    parser.add_argument("--degree", type=int, default=4, help="degree of the row-time polynomial (default 4)")
    parser.add_argument("--min-snr", type=float, default=10.0, metavar="RATIO",
                        help="peak-to-noise ratio each pulse needs (default 10)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def run(args) -> int:
    from acquisition.runstore import open_run
    from core.integrity import read_checked
    from reconstruction.build import mean_line_images, row_times
    from reconstruction.sweep import fit_sweep, pair_rows, save_sweep

    if not (np.isfinite(args.etalon_ps) and args.etalon_ps > 0):
        raise CommandError(f"--etalon-ps must be positive, got {args.etalon_ps}")
    if not (np.isfinite(args.min_snr) and args.min_snr > 0):
        raise CommandError(f"--min-snr must be positive, got {args.min_snr}")
    if describe_existing(args.source) != "run":
        raise CommandError(f"{args.source} is not a run store: calibrate-sweep needs the raw streak rows "
                           f"of an etalon capture ('streaklab capture' output)")
    check_output_location(args.out, inputs=(args.source,))
    run_store = open_run(args.source, mode="r")
    nx, n_rows = run_store.image_shape
    done = run_store.done_mask()
    lines = np.flatnonzero(done)
    delays = None
    if args.delays_ps is not None:
        if len(args.delays_ps) != run_store.n_lines:
            raise CommandError(f"--delays-ps gives {len(args.delays_ps)} delays, the run has {run_store.n_lines} lines")
        delays = np.asarray(args.delays_ps, dtype=np.float64)
    elif "line_delay_ps" in run_store.group:
        delays = np.asarray(read_checked(run_store["line_delay_ps"], slice(None), store=run_store.path), np.float64)
    nominal, _ = row_times(run_store, n_rows)
    profiles = np.stack([img.sum(axis=0) for _, img in mean_line_images(run_store, lines)])  # (line, rows)
    sep_rows = args.etalon_ps / float(np.median(np.abs(np.diff(nominal))))
    pairs = pair_rows(profiles, sep_rows, min_snr=args.min_snr)
    time_range = run_store.config["camera"]["time_range"]
    cal = fit_sweep(pairs, args.etalon_ps, nominal, delays_ps=None if delays is None else delays[lines],
                    degree=args.degree, time_range=time_range,
                    provenance={"run_store": str(run_store.path), "lines": [int(i) for i in lines]})
    where = save_sweep(args.out, cal, overwrite=args.overwrite, inputs=(args.source,))
    prov = cal.provenance
    print(f"wrote the sweep calibration to {where}: time range {time_range!r}, {n_rows} rows, "
          f"{prov['pairs_used']} of {prov['pairs_total']} pairs used"
          f"{'' if prov['delays_used'] else ' (no delays: separations only)'}, RMS misfit {cal.residual_rms_ps:.3g} ps, "
          f"at most {prov['max_deviation_from_nominal_ps']:.3g} ps from the nominal sweep", file=sys.stderr)
    return 0
