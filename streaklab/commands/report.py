"""``streaklab report result.zarr --out figs/ [--time-ps T] [--pixels y,x ...]``: figures and a summary."""
from __future__ import annotations

from streaklab.cli import CommandError

__all__ = ["add_arguments", "run"]


def _pixel(text: str) -> tuple[int, int]:
    try:
        y, x = (int(v) for v in text.split(","))
    except ValueError:
        raise CommandError(f"--pixels takes y,x pairs such as 3,17; got {text!r}") from None
    return y, x


def add_arguments(parser) -> None:
    parser.add_argument("result", help="result store written by 'streaklab decompose'")
    parser.add_argument("--out", required=True, help="folder for the PNGs and summary.txt")
    parser.add_argument("--time-ps", type=float, default=None,
                        help="time of the component frames in ps (default: the median direct delay)")
    parser.add_argument("--pixels", nargs="+", default=None, metavar="Y,X",
                        help="pixels for the time-profile figure (default: picked automatically)")


def run(args) -> int:
    from streaklab.report import make_report

    pixels = [_pixel(p) for p in args.pixels] if args.pixels else None
    try:
        rep = make_report(args.result, args.out, time_ps=args.time_ps, pixels=pixels)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    print(rep["summary"], end="")
    for f in rep["files"]:
        print(f"wrote {f}")
    return 0
