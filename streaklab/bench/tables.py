"""CSV tables of the benchmarks: one row per dict, floats to six significant digits."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

__all__ = ["write_csv", "finite_or_none", "write_json"]


def _fmt(v):
    return f"{v:.6g}" if isinstance(v, float) else v


def write_csv(path: Path | str, rows, fields=None) -> None:
    """Write ``rows`` (dicts) to ``path``; columns ``fields``, or every key in order of first use."""
    if fields is None:
        fields = []
        for r in rows:
            fields += [k for k in r if k not in fields]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(fields))
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt(r.get(k, "")) for k in fields})


def finite_or_none(value):
    """``value`` (dicts, lists, tuples, scalars) with every non-finite float replaced by None
    (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: Path | str, value) -> None:
    """Write ``value`` to ``path`` as indented JSON, every non-finite float as null."""
    Path(path).write_text(json.dumps(finite_or_none(value), indent=2, allow_nan=False) + "\n")
