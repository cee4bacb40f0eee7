"""The ``streaklab`` command: a thin dispatcher over one module per subcommand.

Subcommand modules are imported only when their command runs, so ``streaklab
--help`` stays fast and a missing optional piece never breaks the others.
"""
from __future__ import annotations

import argparse
import errno
import importlib
import os
import re
import sys

from core.errors import OutputExistsError, StreaklabError

from . import __version__

# name -> (module, one-line help)
COMMANDS = {
    "demo": ("streaklab.commands.demo", "run the whole pipeline on the simulated lab and report"),
    "simulate": ("streaklab.commands.simulate", "write a synthetic cube with its ground truth"),
    "sim-lab": ("streaklab.commands.simlab", "serve the simulated camera and mirror until Ctrl-C"),
    "example-config": ("streaklab.commands.example_config", "print or write the example scan configuration"),
    "capture": ("streaklab.commands.capture", "run a capture session into a Zarr run store"),
    "live": ("streaklab.commands.live", "live streak image and time profile for alignment (Ctrl-C stops)"),
    "reconstruct": ("streaklab.commands.reconstruct", "turn a run store into a calibrated (y, x, t) cube"),
    "calibrate-irf": ("streaklab.commands.calibrate_irf",
                      "estimate the instrument response from a capture of a calibration target"),
    "calibrate-sweep": ("streaklab.commands.calibrate_sweep",
                        "fit the sweep's row times from a capture of an etalon pulse pair at several delays"),
    "calibrate-shading": ("streaklab.commands.calibrate_shading",
                          "a flat field along time (per-row sensitivity) from a uniform-light capture"),
    "export": ("streaklab.commands.export", "export a cube to NeXus/HDF5"),
    "import": ("streaklab.commands.import_h5", "import a NeXus/HDF5 cube back into Zarr"),
    "decompose": ("streaklab.commands.decompose", "decompose every pixel of a cube"),
    "verify": ("streaklab.commands.verify", "read every chunk of a store; name damaged lines/chunks and how to redo them"),
    "report": ("streaklab.commands.report", "figures and a summary of a result store"),
    "bench": ("streaklab.commands.bench", "benchmarks: accuracy, speed, tradeoff, stability, realism, counts, timebase, "
                                          "adaptive, spatial, live"),
}


#: the BLAS libraries' own thread pools, one thread each unless the user set them: the commands
#: run their own parallelism (dask threads, or worker processes, to which dask.distributed's
#: nanny gives one BLAS thread already), and an idle BLAS pool spins on the cores those threads
#: need (``bench speed``, 2 threads on 2 cores: +5 % pixels/s under white noise).  Set before
#: any command imports numpy, which reads them once, as it loads its BLAS.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ=None) -> None:
    """Set each of :data:`BLAS_THREAD_VARIABLES` to 1 in ``environ`` (default ``os.environ``)
    where it is not set already."""
    environ = os.environ if environ is None else environ
    for name in BLAS_THREAD_VARIABLES:
        environ.setdefault(name, "1")


class CommandError(Exception):
    """An error in the command line the user can fix; printed without a traceback, exit status 2.

    The library's own errors (:class:`core.errors.StreaklabError`) are printed the same way.
    """


def output_exists(exc: FileExistsError) -> Exception:
    """A taken output path, in the command line's words (the error itself when it names no path)."""
    path = getattr(exc, "path", None)
    if path is None:
        return exc
    return CommandError(f"{path} already exists; pass --overwrite to replace it")


# staged outputs (and their marker) are written beside --out, under these names
_STAGED = re.compile(r"/\.([^/]+)\.(?:partial-[0-9a-f]{8}|old-[0-9a-f]{8}|staging-[0-9a-f]{8}\.json)")


def describe_os_error(exc: OSError) -> str:
    """One line for a file-system error: the path (the user's --out, not its staging name) and the reason."""
    reason = exc.strerror or str(exc).splitlines()[0]
    if exc.errno == errno.ENOSPC:
        reason = "no space left on the device"
    elif exc.errno == errno.ENOTDIR:
        reason = "a file stands where a folder should be"
    name = exc.filename
    if name is None:  # h5py puts the path and the reason into its message
        found = re.search(r"name = '([^']+)'.*error message = '([^']+)'", str(exc))
        if not found:
            return f"cannot write: {_STAGED.sub(lambda m: '/' + m.group(1), reason)}"
        name, reason = found.groups()
    return f"cannot write {_STAGED.sub(lambda m: '/' + m.group(1), str(name))}: {reason}"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="streaklab",
        description="Streak-camera transient imaging: capture, reconstruct and decompose picosecond time profiles.",
    )
    parser.add_argument("--version", action="version", version=f"streaklab {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv or argv[0] not in COMMANDS:
        parser.parse_args(argv or ["--help"])
        return 2
    name = argv[0]
    one_blas_thread()
    module = importlib.import_module(COMMANDS[name][0])
    sub = argparse.ArgumentParser(prog=f"streaklab {name}", description=COMMANDS[name][1])
    module.add_arguments(sub)
    args = sub.parse_args(argv[1:])
    args.command_words = argv          # as typed: a command can print the line that continues it
    try:
        return int(module.run(args) or 0)
    except (CommandError, StreaklabError) as exc:
        if isinstance(exc, OutputExistsError):
            exc = output_exists(exc)
        print(f"streaklab {name}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # read-only or full file system, a file where a folder should be, /proc, ...
        print(f"streaklab {name}: error: {describe_os_error(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nstreaklab {name}: interrupted", file=sys.stderr)
        return 130
