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
