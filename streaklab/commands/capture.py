"""``streaklab capture --config SCAN.toml --out RUN.zarr [--simulate] [--resume] [--live RESULT.zarr]``: run a
capture session; with ``--live`` each line is also decomposed as it lands (:mod:`streaklab.live_decompose`)."""
from __future__ import annotations

import logging
import shlex
import signal
import sys
import threading

from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("--config", required=True,
                        help="scan configuration (TOML), or 'sim' for the packaged example of the simulated lab "
                             "('streaklab example-config' prints it)")
    parser.add_argument("--out", help="run store to write (default: output.path of the config)")
    parser.add_argument("--simulate", action="store_true",
                        help="capture from a simulated lab started in this process (ignores [devices])")
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted run: keep its finished lines, take the rest")
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    parser.add_argument("--live", metavar="RESULT.zarr",
                        help="decompose each line as it lands into this result store (resumable; equal to "
                             "'streaklab decompose' of the reconstructed cube with --per-pixel --chunks 1 NX)")
    parser.add_argument("--live-png", metavar="PATH",
                        help="with --live: maps of the direct delay and sss, refreshed as lines are decomposed")
    parser.add_argument("--live-png-every", type=int, default=4, metavar="N",
                        help="with --live-png: decomposed lines between two refreshes (default 4)")
    parser.add_argument("--target-delay-error-ps", metavar="E",
                        help="adaptive accumulation: each line takes frames until the direct-delay standard "
                             "error of its fit is at most E ps in its lit pixels, or camera.frames_per_line "
                             "frames (the maximum); the run store records the frames each line took")


def _resume_hint(args, out, *, resume: bool = True) -> str:
    cmd = ["streaklab", "capture", "--config", args.config, "--out", str(out)]
    if args.simulate:
        cmd.append("--simulate")
    if getattr(args, "target_delay_error_ps", None) is not None:
        cmd += ["--target-delay-error-ps", str(args.target_delay_error_ps)]
    if getattr(args, "live", None):
        cmd += ["--live", str(args.live)] + (["--live-png", str(args.live_png)] if args.live_png else [])
    return shlex.join(cmd + (["--resume"] if resume else []))


def run(args) -> int:
    from acquisition.config import load_config
    from acquisition.progress import Progress
    from acquisition.rig import run_capture
    from acquisition.session import CaptureFailed
    from core.staging import check_output_location

    logging.basicConfig(level=logging.WARNING, format="streaklab capture: %(message)s")
    config = load_config(args.config)
    out = args.out or config["output"].get("path")
    if not out:
        raise CommandError("no output: pass --out or set output.path in the config")
    check_output_location(out)              # before any device is opened: never inside another store
    rule = None
    if args.target_delay_error_ps is not None:
        from streaklab.adaptive import DelayErrorRule, parse_target_error_ps
        rule = DelayErrorRule(parse_target_error_ps(args.target_delay_error_ps))
    live = _live(args, out)
    if live is not None:
        live.launch()

    stop = threading.Event()
    progress = None

    def on_sigint(signum, frame):
        if stop.is_set():                       # second Ctrl-C: give up on the current line
            raise KeyboardInterrupt
        stop.set()
        print("\nstreaklab capture: stopping after the current line (Ctrl-C again to abort it)",
              file=sys.stderr, flush=True)

    def on_start(session):
        nonlocal progress
        if rule is not None:
            rule.start(session.store)
        if not args.quiet:
            for name, ident in session.devices.items():
                print(f"streaklab capture: {name}: {ident}", file=sys.stderr)
            done = session.lines_done()
            if done:
                print(f"streaklab capture: resuming {out}: {done} of {session.n_lines} lines already on disk",
                      file=sys.stderr)
            progress = Progress(session.n_lines, session.lines_done())
            progress.update(session.lines_done(), live.status() if live is not None else "")
        if live is not None:
            live.start(session.out)

    def on_line(session, line):
        if live is not None:
            live.line_landed(line)
        if progress is not None:
            progress.update(session.lines_done(), live.status() if live is not None else "")

    def on_sigterm(signum, frame):
        if not stop.is_set():
            stop.set()
            print("\nstreaklab capture: terminated; stopping after the current line", file=sys.stderr, flush=True)

    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {signal.SIGINT: signal.signal(signal.SIGINT, on_sigint),
                    signal.SIGTERM: signal.signal(signal.SIGTERM, on_sigterm)}
    try:
        result = run_capture(config, out, simulate=args.simulate, resume=args.resume, stop_event=stop,
                             on_line=on_line, on_start=on_start, line_good_enough=rule)
    except CaptureFailed as exc:
        print(f"streaklab capture: error: {exc}", file=sys.stderr)
        if not exc.store_created and not args.resume:
            if live is not None:
                live.close()
            print(f"streaklab capture: nothing was written to {out}; fix the device and run again:\n"
                  f"  {_resume_hint(args, out, resume=False)}", file=sys.stderr)
        else:
            _end_live(live, args, abandon=True)
            print(f"streaklab capture: {exc.lines_done} of {exc.n_lines} lines are safely in {out}; "
                  f"{exc.remedy} and resume with:\n  {_resume_hint(args, out)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        _end_live(live, args, abandon=True)
        print(f"\nstreaklab capture: aborted; finished lines are safely in {out}; resume with:\n"
              f"  {_resume_hint(args, out)}", file=sys.stderr)
        return 130
    except BaseException:       # the session could not start (store, configuration): nothing to decompose
        if live is not None:
            live.close()
        raise
    finally:
        if progress is not None:
            progress.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    live_ok = _end_live(live, args)
    if rule is not None:
        _report_adaptive(out, rule)
    if result.status == "complete":
        print(f"streaklab capture: {result.n_lines} lines in {out} "
              f"({len(result.acquired)} taken in this session)", file=sys.stderr)
        return 0 if live_ok else 1
    print(f"streaklab capture: stopped; {result.lines_done} of {result.n_lines} lines are safely in {out}; "
          f"resume with:\n  {_resume_hint(args, out)}", file=sys.stderr)
    return 130


def _live(args, out):
    """The live decomposition of ``--live`` (its paths checked before any device is opened), or None."""
    if not args.live:
        if args.live_png:
            raise CommandError("--live-png needs --live RESULT.zarr")
        return None
    from core.errors import StreaklabError
    from core.staging import check_output_location
    from decomposition.store.resultstore import prepare_output_path
    from streaklab.live_decompose import LiveDecomposition

    if args.live_png_every <= 0:
        raise CommandError(f"--live-png-every must be positive, got {args.live_png_every}")
    try:
        check_output_location(args.live, inputs=[out])
        prepare_output_path(args.live, protect=[out], resume=args.resume)
        if args.live_png:
            check_output_location(args.live_png, inputs=[out, args.live])
    except StreaklabError as exc:
        raise CommandError(f"--live: {exc}") from None
    return LiveDecomposition(args.live, resume=args.resume, png=args.live_png, png_every=args.live_png_every)


def _end_live(live, args, *, abandon: bool = False) -> bool:
    """Drain the live decomposition's queue (a Ctrl-C meanwhile, or ``abandon``: only the line in hand)
    and say where it stands -> False when it failed."""
    if live is None:
        return True
    def report(status):
        print(f"streaklab capture: {status}", file=sys.stderr, flush=True)

    try:
        if not abandon and live.alive():
            if not args.quiet:
                print(f"streaklab capture: capture done; {live.status()}; finishing the queued lines "
                      f"(Ctrl-C stops after the current one)", file=sys.stderr, flush=True)
            live.finish(report=None if args.quiet else report)
        else:
            live.finish(abandon=True)
    except KeyboardInterrupt:
        live.finish(abandon=True)
    if live.error is not None:
        print(f"streaklab capture: error: live decomposition into {live.out} stopped: {live.error}; "
              f"the capture is unaffected", file=sys.stderr)
        return False
    print(f"streaklab capture: live result {live.out}: {live.status()}", file=sys.stderr)
    return True


def _report_adaptive(out, rule) -> None:
    """One line: the frames the adaptive accumulation took, and how many lines missed the target."""
    import numpy as np

    from acquisition.runstore import open_run

    run = open_run(out, mode="r")
    done = run.done_mask()
    taken, reached = run.frames_taken()[done], run.target_reached()[done]
    missed = int((~reached).sum())
    print(f"streaklab capture: adaptive accumulation (target {rule.target_ps:g} ps): {int(taken.sum())} frames "
          f"in {done.sum()} lines (at most {run.frames_per_line} each); "
          + (f"{missed} line(s) missed the target at the maximum: {np.flatnonzero(done)[~reached].tolist()}"
             if missed else "every line reached the target"), file=sys.stderr)
