"""``streaklab calibrate-shading RUN --out FLAT.npy``: a flat field along time from a uniform-light capture.

Every finished line's frames are averaged and dark-subtracted, the lines averaged, and
:func:`reconstruction.shading.shading_flat` gives the sensitivity of every pixel and row (smooth
along time).  The result is an ordinary flat field, shape (x, rows): ``streaklab reconstruct
--flat FLAT.npy`` applies it.
"""
from __future__ import annotations

import sys

import numpy as np

from core.staging import check_output_location, describe_existing, staged_output
from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("source", metavar="RUN", help="run store of a uniform-light capture")
    parser.add_argument("--out", required=True, metavar="FLAT.npy", help="flat field to write (.npy)")
    parser.add_argument("--degree", type=int, default=6, help="degree of the row-sensitivity polynomial (default 6)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def run(args) -> int:
    from acquisition.runstore import open_run
    from reconstruction.build import mean_line_images
    from reconstruction.shading import shading_flat

    if not str(args.out).endswith(".npy"):
        raise CommandError(f"--out {args.out}: the flat field is written as a .npy file; name it *.npy")
    if describe_existing(args.source) != "run":
        raise CommandError(f"{args.source} is not a run store: calibrate-shading needs the raw streak rows "
                           f"of a uniform-light capture")
    check_output_location(args.out, inputs=(args.source,))
    run_store = open_run(args.source, mode="r")
    nx, n_rows = run_store.image_shape
    lines = np.flatnonzero(run_store.done_mask())
    if lines.size == 0:
        raise CommandError(f"{args.source}: no line has been acquired yet")
    image = sum(img for _, img in mean_line_images(run_store, lines)) / lines.size
    flat, rows = shading_flat(image * lines.size * run_store.frames_per_line, degree=args.degree)
    with staged_output(args.out, overwrite=args.overwrite, inputs=(args.source,), kind="file") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, flat)
    print(f"wrote the flat field {args.out}: ({nx}, {n_rows}), row sensitivity {rows.min():.3g} to {rows.max():.3g} "
          f"(degree {args.degree}) from {lines.size} lines", file=sys.stderr)
    return 0
