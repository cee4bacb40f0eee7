"""``streaklab example-config [--name sim] [--out FILE] [--overwrite]``: the packaged example scan
configuration, printed or written to a file to edit.

``streaklab capture --config sim`` uses the same file without copying it.
"""
from __future__ import annotations

import sys
from pathlib import Path

from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    from acquisition.config import EXAMPLE_CONFIGS

    parser.add_argument("--name", choices=sorted(EXAMPLE_CONFIGS), default="sim",
                        help="which example (default sim: a scan of the simulated lab)")
    parser.add_argument("--out", default=None, metavar="FILE",
                        help="write it to FILE (default: print it)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing FILE")


def run(args) -> int:
    from acquisition.config import ConfigError, example_config_path
    from core.staging import check_output_location

    try:
        text = example_config_path(args.name).read_text()
    except (ConfigError, OSError) as exc:
        raise CommandError(str(exc)) from None
    if args.out is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.out)
    if out.is_dir():
        raise CommandError(f"{out} is a folder; give a file name such as {out / 'scan.toml'}")
    if out.exists() and not args.overwrite:
        raise CommandError(f"{out} already exists; pass --overwrite to replace it")
    check_output_location(out)
    try:
        out.write_text(text)
    except OSError as exc:
        raise CommandError(f"cannot write {out}: {exc.strerror or exc}") from None
    print(f"wrote {out}; run it with: streaklab capture --config {out} --out run.zarr --simulate",
          file=sys.stderr)
    return 0
