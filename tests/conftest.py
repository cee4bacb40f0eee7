"""Fixtures shared by the tests."""
import signal

import pytest

from decomposition.methods.dictionary import get_dictionary
from decomposition.options import GridSpec


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
