"""Fixtures shared by the tests."""
import os
import signal
from pathlib import Path

import pytest

from decomposition.methods.dictionary import get_dictionary
from decomposition.options import GridSpec

ROOT = Path(__file__).resolve().parents[1]


def pytest_sessionstart(session):
    """Load, or on a new install compile, the solver's kernels before the first test starts.

    A fresh clone has no numba cache: the first test of each process that decomposes would
    otherwise spend the one-time compile (about a minute on a 2-core machine) inside its own
    time limit, and a test bounded at 60 s for what it waits on failed on that alone.  Every
    process that runs tests warms up once here, outside any test's timer (the xdist controller
    runs none); once the cache is filled this costs about 2 s.  The tests of the first run's
    compile notice work on caches of their own (tests/test_first_run.py)."""
    config = session.config
    controller = not hasattr(config, "workerinput") and (config.getoption("numprocesses", None) or 0) != 0
    if controller or config.getoption("collectonly", False):
        return
    from decomposition.warmup import warm_up
    from drivers.sim.scene import simulated_response

    warm_up(quiet=True, image={"shared": ("psf",), "spatial": True})   # the per-pixel path, then the image's
    warm_up(quiet=True, n_bins=512, options={"irf": simulated_response("tailed")})


@pytest.fixture(scope="session")
def default_dictionary():
    """``build(n_bins, time_bin_ps=2.0, t0_ps=None)``: the solver's dictionary at the default grid,
    every family (the one ``decompose()`` uses for these settings; ``t0_ps`` defaults to one bin)."""
    def build(n_bins, time_bin_ps=2.0, t0_ps=None):
        t0 = time_bin_ps if t0_ps is None else t0_ps
        return get_dictionary(n_bins, time_bin_ps, t0, GridSpec(), True, True)

    return build


@pytest.fixture(scope="session", autouse=True)
def _ctrl_c_as_at_a_terminal():
    """Commands the tests start get SIGINT as a terminal's Ctrl-C does, also where the test run
    itself was started with SIGINT ignored (a background job of a shell without job control):
    an ignored SIGINT is inherited, a handler is not, and Python leaves an ignored one ignored,
    so an interrupted ``streaklab decompose`` would run to its end."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield


@pytest.fixture
def live_worker_at_normal_priority(tmp_path_factory, monkeypatch):
    """The worker process of ``capture --live`` at the normal scheduling priority, for the tests of
    what it computes (which never depends on its priority).

    At its own priority (nice 19) the worker gets about 1.5 % of a core that other work wants:
    where the test run keeps every core busy (``pytest -n 2`` on two cores), a test of a few
    seconds takes minutes.  The worker is a spawned interpreter, so the
    priority is left alone in it through a sitecustomize on its PYTHONPATH (and in this process,
    which lowers the worker's priority as it starts it).
    ``tests/test_live_decompose.py::test_the_live_worker_runs_at_the_lowest_priority`` checks the
    priority itself."""
    import streaklab.live_decompose as live

    site = tmp_path_factory.mktemp("live_site")
    (site / "sitecustomize.py").write_text(
        "import streaklab.live_decompose as _live\n_live._lowest_priority = lambda pid=0: None\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        [str(site), str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    monkeypatch.setattr(live, "_lowest_priority", lambda pid=0: None)
