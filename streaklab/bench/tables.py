"""CSV tables of the benchmarks: one row per dict, floats to six significant digits."""
from __future__ import annotations

import csv
from pathlib import Path

__all__ = ["write_csv"]


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
