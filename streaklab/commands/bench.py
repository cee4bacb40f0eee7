"""``streaklab bench NAME [options]``: run one benchmark.

Each benchmark is a module ``streaklab.bench.NAME`` with ``add_arguments(parser)`` and
``run(args) -> int``, imported only when it runs.  ``streaklab bench NAME --help`` shows
that benchmark's options.
"""
from __future__ import annotations

import argparse
import importlib

from streaklab.cli import CommandError

# name -> one-line description
BENCHMARKS = {
    "accuracy": "mean fidelity against NSR for ConvSCD and GradBM under the three noise types (paper Fig. 3(d))",
    "speed": "pixels per second of streaklab decompose on a synthetic cube",
    "tradeoff": "decomposition error against run time, with the physical limit",
    "stability": "stiff and extreme inputs (tiny and huge alpha*sigma and widths, 1e-30..1e30 scales, "
                 "saturation, spikes): outputs finite, iterations bounded, objective monotone, flags raised",
    "realism": "photon counts with a tailed response, afterpulse, background, weak echo or truncated direct: "
               "delay and lifetime bias and RMSE beside the Poisson reference, stderr calibration, echo found rate",
    "counts": "photon-counting data of the paper's scenes at each photon level: mean fidelity with the PSF width "
              "fitted or held at the truth, or through a measured response, beside a ceiling fitted from the truth",
    "timebase": "direct-delay RMSE of a simulated scan under trigger jitter and drift, aligned on the fiducial "
                "and not, beside the steady scan's",
    "spatial": "per-pixel, whole-image (neighbours coupled) and the per-pixel oracle side by side on images with "
               "depth steps and material patches, near edges and away; pooled echoes, spikes told by the "
               "neighbours, speed, the demo's scene",
    "adaptive": "capture --target-delay-error-ps against the fixed accumulation whose worst line reaches the "
                "same direct-delay error: frames taken, lines reaching the target",
    "live": "the cost to a capture of decomposing while it runs: the simulated lab's default scan captured with and "
            "without the in-capture decomposition, alternated, timed to the last line on disk; its result against "
            "reconstruct + decompose byte for byte",
}


def add_arguments(parser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "benchmarks:\n" + "\n".join(f"  {k:<10} {v}" for k, v in BENCHMARKS.items())
    parser.add_argument("name", metavar="NAME", help="benchmark to run: " + ", ".join(BENCHMARKS))
    parser.add_argument("options", nargs=argparse.REMAINDER, help="options of the benchmark (see NAME --help)")


def load(name: str):
    """Import the benchmark module ``streaklab.bench.<name>``; CommandError if there is none."""
    if name not in BENCHMARKS:
        raise CommandError(f"unknown benchmark {name!r}; available: {', '.join(BENCHMARKS)}")
    module_name = f"streaklab.bench.{name}"
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            raise CommandError(f"benchmark {name!r} is not installed in this copy of streaklab") from None
        raise


def run(args) -> int:
    module = load(args.name)
    parser = argparse.ArgumentParser(prog=f"streaklab bench {args.name}", description=BENCHMARKS[args.name])
    module.add_arguments(parser)
    sub_args = parser.parse_args(args.options)
    return int(module.run(sub_args) or 0)
