"""``streaklab calibrate-irf RUN_OR_CUBE [--out IRF]``: the instrument response from a calibration capture.

The capture is of a calibration target (a mirror or a thin diffuser filling the view, one
direct return per pixel; ``simulation.scene = "calibration"`` on the simulated lab).  A cube
store is used as it is; a run store is reconstructed first (into a temporary cube).  The
response goes into the cube's ``irf`` group, or into ``--out`` (a Zarr store, or a ``.npz``
file), which a run store needs.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from core.staging import check_output_location, describe_existing
from core.words import counted
from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("source", metavar="RUN_OR_CUBE",
                        help="cube store (or run store) of a capture of the calibration target")
    parser.add_argument("--out", metavar="IRF", help="store the response here (Zarr directory, or a file ending in .npz) "
                                      "instead of in the cube's 'irf' group; required for a run store")
    parser.add_argument("--pre-ps", type=float, metavar="PS", help="extent of the response before its peak, ps "
                                                     "(default: three half-maximum widths plus two bins)")
    parser.add_argument("--post-ps", type=float, metavar="PS", help="extent after the peak, ps (default: what three quarters "
                                                      "of the pixels cover)")
    parser.add_argument("--min-snr", type=float, default=10.0, metavar="RATIO",
                        help="peak-to-noise ratio a pixel needs to be used (default 10)")
    parser.add_argument("--saturation-level", type=float, metavar="LEVEL",
                        help="samples at or above this level (cube units) mark a pixel saturated")
    parser.add_argument("--min-pixels", type=int, default=8, metavar="N", help="usable pixels needed (default 8)")
    parser.add_argument("--overwrite", action="store_true", help="replace a response already stored there")


def run(args) -> int:
    from core.irfstore import save_response
    from reconstruction.build import reconstruct
    from reconstruction.cubestore import open_cube, write_cube_response
    from reconstruction.irf import ResponseEstimateOptions, fit_response

    opts = ResponseEstimateOptions(pre_peak_ps=args.pre_ps, post_peak_ps=args.post_ps, min_snr=args.min_snr,
                                   saturation_level=args.saturation_level, min_pixels=args.min_pixels)
    source = Path(args.source)
    if args.out is not None:
        check_output_location(args.out, inputs=(source,))          # before the fit, not after it
    if describe_existing(source) == "run":
        if args.out is None:
            raise CommandError(f"{source} is a run store: give --out for the response "
                               f"(or reconstruct it and calibrate the cube, which keeps the response)")
        with tempfile.TemporaryDirectory(prefix=".calibrate-irf-", dir=source.resolve().parent) as tmp:
            cube = reconstruct(source, Path(tmp) / "cube.zarr")
            fit = fit_response(cube, options=opts, source={"run_store": str(source.resolve())})
    else:
        cube = open_cube(source)
        fit = fit_response(cube, options=opts, source={"store": str(source.resolve())})
    irf = fit.response
    if args.out is not None:
        where = str(save_response(args.out, irf, overwrite=args.overwrite, inputs=(source,)))
    else:
        write_cube_response(cube, irf, overwrite=args.overwrite)
        where = f"{source}/irf"
    prov = irf.provenance
    print(f"wrote the instrument response to {where}: {prov['pixels_used']:,} of {counted(prov['pixels_total'], 'pixel')}, "
          f"FWHM {irf.fwhm_ps():.3g} ps, {irf.n_samples} samples of {irf.time_step_ps:g} ps, "
          f"delays spread {prov['delay_spread_ps']:.3g} ps, alignment +-{prov['alignment_sd_ps']:.2g} ps; "
          f"the best Gaussian (sigma {prov['gaussian_fit']['sigma_ps']:.3g} ps) would leave "
          f"{100 * prov['gaussian_fit']['rms_misfit']:.2g} % of the peak as RMS misfit", file=sys.stderr)
    return 0
