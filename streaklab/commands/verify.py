"""``streaklab verify STORE [--mark-for-resume]``: read every chunk of a store and name the damaged ones.

Works on run, cube and result stores.  Damage is reported by scan line (run store) or by pixel
chunk (cube and result stores), with the commands that recapture or recompute just that part.
A run or result store whose capture or decomposition stopped before the end is named incomplete
(how much of it is done) with the command that finishes it: its undamaged part alone is not "sound".
``--mark-for-resume`` clears the ``done`` flags of the damaged lines or chunks (it never deletes
data), so that ``capture --resume`` or ``decompose --resume`` redoes exactly those.  The exit
status is 1 when damage is found, 0 when the store is sound (complete or not).

Every command printed names the store at the path verify was given, not the path it was first
written at (a copied or moved store is redone where it is).
"""
from __future__ import annotations

import shlex
from pathlib import Path

from core.words import counted
from streaklab.cli import CommandError


def add_arguments(parser) -> None:
    parser.add_argument("store", help="run, cube or result store (Zarr directory)")
    parser.add_argument("--mark-for-resume", action="store_true",
                        help="clear the done flags of damaged lines (run store) or pixel chunks (result store) so "
                             "that --resume redoes just those; no data is deleted")


def _say(text: str) -> None:
    print(text)


def _list(damage, limit: int = 20) -> None:
    for d in damage[:limit]:
        _say(f"  {d}")
    if len(damage) > limit:
        _say(f"  ... and {len(damage) - limit} more")


def _no_checksums(path) -> None:
    _say(f"note: {path} was written without checksums (an earlier streaklab release): chunks that decode "
         f"were taken as sound, and changed bytes cannot be detected in them")


def _config_name(source) -> str:
    """The --config argument that names a run's configuration: 'sim' for the packaged example."""
    if not source:
        return "SCAN.toml"
    from acquisition.config import example_config_path

    return "sim" if Path(source).resolve() == example_config_path("sim") else str(source)


def _run(path, mark: bool) -> int:
    from acquisition.runstore import open_run

    run = open_run(path, mode="r+" if mark else "r")
    check = run.verify()
    _say(f"{path}: run store, {counted(run.n_lines, 'line')}")
    if not check.checksums:
        _no_checksums(path)
    config = _config_name(run.attrs.get("config_source"))
    simulated = any(s.get("simulated") for s in run.attrs.get("sessions", []))
    capture = shlex.join(["streaklab", "capture", "--config", str(config), "--out", str(path)]
                         + (["--simulate"] if simulated else []) + ["--resume"])
    if not check.complete:
        dark = "; the dark frames are not taken yet" if check.dark_pending else ""
        _say(f"incomplete: {check.lines_done:,} of {counted(check.n_lines, 'line')} captured{dark} "
             f"(the capture stopped before the end)")
    if check.ok:
        _say("no damage found" + (" in the captured lines" if not check.complete else ""))
        if not check.complete:
            _say("finish the capture with:")
            _say(f"  {capture}")
        return 0
    for line, damage in check.lines.items():
        _say(f"line {line}:")
        _list(damage)
    if check.dark:
        _say("dark frames:")
        _list(check.dark)
    if check.other:
        _say("other arrays (a recapture does not mend these; restore them from a copy):")
        _list(check.other)
    lines = list(check.lines)
    if lines or check.dark:
        what = ", ".join(map(str, lines)) if lines else ""
        if mark:
            run.mark_lines_not_done(lines)
            if check.dark:
                run.mark_dark_not_done()
            _say(f"marked {'lines ' + what if lines else ''}{' and ' if lines and check.dark else ''}"
                 f"{'the dark frames' if check.dark else ''} not done; recapture just those with:")
        else:
            _say("to recapture just those" + ("" if check.complete else " and finish the capture") + ":")
            _say(f"  {shlex.join(['streaklab', 'verify', str(path), '--mark-for-resume'])}")
        _say(f"  {capture}")
    elif not check.complete:
        _say("finish the capture with:")
        _say(f"  {capture}")
    return 1


def _cube(path, mark: bool) -> int:
    from reconstruction.cubestore import open_cube, verify_cube

    cube = open_cube(path)
    check = verify_cube(cube)
    ny, nx, nt = cube.shape
    _say(f"{path}: cube store, (y={ny}, x={nx}, t={nt})")
    if not check.checksums:
        _no_checksums(path)
    if check.ok:
        _say("no damage found")
        return 0
    by, bx = cube.array.chunks[:2]
    for d in check.damaged:
        where = ""
        if d.array == "cube":
            iy, ix = d.coords[:2]
            where = f" (y {iy * by}..{min(ny, (iy + 1) * by) - 1}, x {ix * bx}..{min(nx, (ix + 1) * bx) - 1})"
        _say(f"  {d}{where}")
    prov = cube.attrs.get("provenance", {}) or {}
    if mark:
        _say("a cube store has no done flags; --mark-for-resume changes nothing")
    if prov.get("run_path"):
        _say("rebuild it from its run with:")
        _say(f"  {shlex.join(['streaklab', 'reconstruct', prov['run_path'], '--out', str(path), '--overwrite'])}")
    elif prov.get("imported_from"):
        _say("import it again with:")
        _say(f"  {shlex.join(['streaklab', 'import', prov['imported_from'], '--out', str(path), '--overwrite'])}")
    elif prov.get("command"):
        from streaklab.commands.simulate import command_for

        again = command_for(prov["command"], path)
        if again is not None:
            _say(f"write it again with:\n  {again}")
        else:
            _say(f"it was written by '{prov['command']}': run that again, or restore it from a copy")
    else:
        _say("restore it from a copy")
    return 1


def _result(path, mark: bool) -> int:
    from decomposition.store.resultstore import open_result_store

    store = open_result_store(path, mode="r+" if mark else "r")
    check = store.verify()
    gy, gx = store.grid
    ny, nx = store.shape[:2]
    _say(f"{path}: result store, {ny} x {nx} pixels in {counted(gy * gx, 'chunk')} of "
         f"{store.chunks[0]} x {store.chunks[1]}")
    if not check.checksums:
        _no_checksums(path)
    source = (store.attrs.get("source") or {}).get("path", "CUBE")
    resume = (f"{shlex.join(['streaklab', 'decompose', str(source), '--out', str(path), '--resume'])}"
              f"  (with the settings of the original run: see the store's 'job' attribute)")
    if not check.complete:
        _say(f"incomplete: {check.chunks_done:,} of {counted(check.n_chunks, 'pixel chunk')} decomposed "
             f"(the decomposition stopped before the end)")
    if check.ok:
        _say("no damage found" + (" in the decomposed chunks" if not check.complete else ""))
        if not check.complete:
            _say("finish the decomposition with:")
            _say(f"  {resume}")
        return 0
    for (iy, ix), damage in check.chunks.items():
        ys, xs = store.chunk_slices(iy, ix)
        _say(f"pixel chunk ({iy}, {ix}) (y {ys.start}..{ys.stop - 1}, x {xs.start}..{xs.stop - 1}):")
        _list(damage)
    if check.other:
        _say("coordinate arrays (a recomputation does not mend these; restore them from a copy):")
        _list(check.other)
    if check.chunks:
        if mark:
            store.mark_chunks_not_done(list(check.chunks))
            _say(f"marked {counted(len(check.chunks), 'pixel chunk')} not done; recompute just those with:")
        else:
            _say("to recompute just those" + ("" if check.complete else " and finish the decomposition") + ":")
            _say(f"  {shlex.join(['streaklab', 'verify', str(path), '--mark-for-resume'])}")
        _say(f"  {resume}")
    elif not check.complete:
        _say("finish the decomposition with:")
        _say(f"  {resume}")
    return 1


def run(args) -> int:
    from acquisition.runstore import RUN_KIND
    from core.staging import describe_existing
    from decomposition.store.resultstore import RESULT_KIND
    from reconstruction.cubestore import CUBE_KIND

    kind = describe_existing(args.store)
    handlers = {RUN_KIND: _run, CUBE_KIND: _cube, RESULT_KIND: _result}
    if kind is None:
        raise CommandError(f"{args.store}: no such file or directory")
    if kind not in handlers:
        raise CommandError(f"{args.store} is not a run, cube or result store (it is {kind!r})")
    return handlers[kind](args.store, args.mark_for_resume)   # the stores' own errors: printed by the CLI
