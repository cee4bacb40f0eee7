"""Command-line values of the benchmarks: comma-separated choices and numbers, checked."""
from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

from streaklab.cli import CommandError

__all__ = ["choices", "positive_floats", "seed_list", "chosen_seeds", "output_folder"]


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


def seed_list(text: str, what: str = "seeds") -> list[int]:
    """``"1-4,7"`` -> [1, 2, 3, 4, 7] in the given order: comma-separated non-negative integers and
    inclusive ranges ``a-b`` (``a <= b``); CommandError naming ``--what`` for an empty list, an
    item that is neither, a descending range or a seed given twice."""
    seeds: list[int] = []
    for item in (s.strip() for s in str(text).split(",")):
        lo, dash, hi = item.partition("-")
        if not (lo.strip().isdigit() and (not dash or hi.strip().isdigit())):
            raise CommandError(f"--{what} must be comma-separated non-negative integers or ranges a-b "
                               f"(e.g. 1-8 or 1,2,5), got {text!r}")
        a, b = int(lo), int(hi) if dash else int(lo)
        if b < a:
            raise CommandError(f"--{what}: the range {item} runs backwards (give {b}-{a})")
        seeds.extend(range(a, b + 1))
    twice = sorted(s for s, n in Counter(seeds).items() if n > 1)
    if twice:
        raise CommandError(f"--{what}: seed {', '.join(map(str, twice))} given more than once in {text!r}")
    return seeds


def chosen_seeds(seed, seeds, default: str) -> list[int]:
    """The seeds a benchmark runs: ``--seed N`` (one, an int or None), ``--seeds`` (a
    :func:`seed_list` text or None) or ``default`` (a :func:`seed_list` text) when neither is
    given; CommandError if both are given or ``--seed`` is negative."""
    if seed is not None and seeds is not None:
        raise CommandError(f"give --seed or --seeds, not both (--seed {seed} is --seeds {seed}), "
                           f"got --seed {seed} --seeds {seeds}")
    if seed is not None:
        if seed < 0:
            raise CommandError(f"--seed must be a non-negative integer, got {seed}")
        return [int(seed)]
    return seed_list(default if seeds is None else seeds)


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
