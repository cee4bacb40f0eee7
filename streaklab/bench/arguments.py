"""Command-line values of the benchmarks: comma-separated choices and numbers, checked."""
from __future__ import annotations

import math
from pathlib import Path

from streaklab.cli import CommandError

__all__ = ["choices", "positive_floats", "output_folder"]


def choices(text: str, allowed, what: str) -> list[str]:
    """``"a,b"`` -> ["a", "b"] (lower case, first occurrence kept); CommandError naming ``--what``
    for an unknown item or an empty list."""
    items = [s.strip().lower() for s in str(text).split(",") if s.strip()]
    bad = [s for s in items if s not in allowed]
    if bad or not items:
        raise CommandError(f"--{what}: unknown {bad or 'empty list'}; choose from {', '.join(allowed)}")
    return list(dict.fromkeys(items))


def positive_floats(text: str, what: str) -> list[float]:
    """``"0.1,2"`` -> [0.1, 2.0] in the given order; CommandError naming ``--what`` unless every
    item is a finite positive number."""
    try:
        vals = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        vals = []
    if not vals or not all(math.isfinite(v) and v > 0 for v in vals):
        raise CommandError(f"--{what} must be a comma-separated list of positive numbers, got {text!r}")
    return vals


def output_folder(path) -> Path:
    """``--out``: the folder (made with its parents); CommandError if a file is in its place,
    OutputPathError if it is or lies inside a Zarr store (:func:`core.staging.check_output_location`)."""
    from core.staging import check_output_location

    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CommandError(f"--out {out} exists and is not a folder")
    check_output_location(out, folder=True)
    out.mkdir(parents=True, exist_ok=True)
    return out
