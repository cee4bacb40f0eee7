"""Waiting on a decomposition that runs in another process or thread, as the interrupt tests do."""
import time


def wait_for_done_chunks(out, n, proc=None, timeout_s=60.0):
    """Return once the result store at ``out`` has at least ``n`` chunks done; fail if ``proc``
    (a ``subprocess.Popen``, optional) ends first or nothing is done within ``timeout_s``."""
    from decomposition.store.resultstore import open_result_store

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc is not None:
            assert proc.poll() is None, proc.communicate()
        try:
            if open_result_store(out).done_chunks().sum() >= n:
                return
        except Exception:  # store not created yet
            pass
        time.sleep(0.02)
    raise AssertionError(f"no {n} chunks done in {out} within {timeout_s:g} s")


# A sitecustomize for every process of a run (the command and its worker processes): it slows
# each chunk's solve down, so that the run is reliably still going when a test's Ctrl-C arrives;
# the first chunk each process solves goes at full speed (the tests only wait for it to land).
SLOW_SOLVE_SITE = ("import time\nimport decomposition.store.chunked as _c\n_f = _c.solve_block\n_solved = []\n"
                   "def _slow(*a, **k):\n    if _solved:\n        time.sleep(1.5)\n    _solved.append(1)\n"
                   "    return _f(*a, **k)\n_c.solve_block = _slow\n")
