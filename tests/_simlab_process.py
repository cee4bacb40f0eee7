"""``streaklab sim-lab`` in a subprocess, for the tests: start it, read its addresses, stop it."""
import os
import selectors
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def start_sim_lab(*args, deadline_s: float = 30.0):
    """Start ``streaklab sim-lab *args`` and read its address lines up to ``ready``.

    Returns (process, {name: value}); the process is stopped (:func:`stop_sim_lab`) if it
    prints no ``ready`` line within ``deadline_s`` or exits first."""
    proc = subprocess.Popen([sys.executable, "-m", "streaklab", "sim-lab", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        return proc, _read_addresses(proc, deadline_s)
    except BaseException:
        stop_sim_lab(proc)
        raise


def _read_addresses(proc, deadline_s):
    info, buf, end = {}, b"", time.monotonic() + deadline_s
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while "ready" not in info:
            left = end - time.monotonic()
            assert left > 0, f"sim-lab printed no 'ready' line in {deadline_s} s; got {buf!r}"
            if not sel.select(left):
                continue
            chunk = os.read(proc.stdout.fileno(), 4096)
            assert chunk, f"sim-lab exited early: {buf!r} / {proc.stderr.read()!r}"
            buf += chunk
            info = dict(line.partition(" ")[::2] for line in buf.decode().splitlines())
    return info


def stop_sim_lab(proc):
    """Kill ``proc`` if it still runs, wait for it, and close its pipes."""
    if proc.poll() is None:
        proc.kill()
        proc.wait(5)
    proc.stdout.close()
    proc.stderr.close()
