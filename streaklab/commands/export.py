"""``streaklab export CUBE --out CUBE.h5``: a cube store to NeXus/HDF5 (NXentry/NXdata)."""
from __future__ import annotations

import sys


def add_arguments(parser) -> None:
    parser.add_argument("cube", help="cube store (Zarr directory)")
    parser.add_argument("--out", required=True, help="HDF5 file to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def run(args) -> int:
    from reconstruction.nexus import export_cube

    out = export_cube(args.cube, args.out, overwrite=args.overwrite)
    print(f"wrote {out} (NeXus: /entry/data, signal 'cube', axes y, x, t)", file=sys.stderr)
    return 0
