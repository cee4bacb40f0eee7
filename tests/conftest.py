"""Fixtures shared by the solver's stage tests."""
import pytest

from decomposition.dictionary import get_dictionary
from decomposition.options import GridSpec


@pytest.fixture(scope="session")
def default_dictionary():
    """``build(n_bins, time_bin_ps=2.0, t0_ps=None)``: the solver's dictionary at the default grid,
    every family (the one ``decompose()`` uses for these settings; ``t0_ps`` defaults to one bin)."""
    def build(n_bins, time_bin_ps=2.0, t0_ps=None):
        t0 = time_bin_ps if t0_ps is None else t0_ps
        return get_dictionary(n_bins, time_bin_ps, t0, GridSpec(), True, True)

    return build
