"""``streaklab import CUBE.h5 --out CUBE``: a NeXus/HDF5 cube back into a Zarr cube store."""
from __future__ import annotations

import sys


def add_arguments(parser) -> None:
    parser.add_argument("h5", help="NeXus/HDF5 file (from 'streaklab export' or any NXdata with a 3-D signal)")
    parser.add_argument("--out", required=True, help="cube store to write (Zarr directory)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def run(args) -> int:
    from reconstruction.nexus import import_cube

    out = import_cube(args.h5, args.out, overwrite=args.overwrite)
    print(f"wrote {out}", file=sys.stderr)
    return 0
