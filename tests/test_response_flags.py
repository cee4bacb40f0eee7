"""Quality flags of the response path (decompose(irf=...)) set by the Gaussian path's rules:
OFF_WINDOW (decomposition.model.components.runs_off_window on the response's atoms) and SPIKE (the
shared spike test, with the response as its narrowest kernel)."""
import math

import numpy as np
import pytest

from core.irf import render_shifted
from core.irf_models import gaussian_response, tailed_response
from decomposition import decompose
from decomposition.model.components import window_fraction
from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from decomposition.flags import OFF_WINDOW, SPIKE
from decomposition.response.resolve import resolve_response, spike_neighbour_ratio

T = 2.0
L = 256
T_PS = T + T * np.arange(L)


def test_window_fraction_of_response_atoms_is_the_gaussian_paths_measure():
    """With a Gaussian response (sigma = 2 bins: reproduced to 3e-9 of its peak) the response's
    atoms cover the same fraction of the window as the Gaussian path's atoms of that sigma."""
    sigma = 2.0 * T
    irf = gaussian_response(sigma, time_step_ps=T)
    delay = np.array([[T_PS[0] - 3.0, 100.0, T_PS[0]], [T_PS[-1], 60.0, T_PS[-1] - 30.0]])
    fam = np.array([[FAM_GAUSS, FAM_SSS, FAM_GAUSS], [FAM_GAUSS, FAM_SSS, FAM_NONE]], np.int8)
    lalp = np.where(fam == FAM_SSS, math.log(0.02), 0.0)
    st = {"fam": fam, "delay": delay, "lsig": np.full(fam.shape, math.log(sigma)), "lalp": lalp,
          "amp": np.ones(fam.shape)}
    got = window_fraction(st, T_PS, irf=irf)
    want = window_fraction({"fam": fam, "delay": delay, "lsig": np.full(fam.shape, math.log(sigma)),
                            "lalp": lalp, "amp": np.ones(fam.shape)}, T_PS)
    np.testing.assert_allclose(got, want, atol=1e-7)
    # the sss decays past the last bin by exp(-alpha (t_L - onset)); an empty slot counts as inside
    assert got[0, 1] == pytest.approx(1.0 - math.exp(-0.02 * (T_PS[-1] - 100.0)), abs=2e-5) and got[1, 2] == 1.0
    # cut by the first bin: the area after its left edge t_1 - T/2 (the bins' midpoint sum)
    for k in (0, 2):
        edge = (T_PS[0] - 0.5 * T - delay[0, k]) / sigma
        assert got[0, k] == pytest.approx(0.5 * math.erfc(edge / math.sqrt(2.0)), abs=3e-3)


@pytest.fixture(scope="module")
def tailed():
    return tailed_response(4.0, 0.2, 20.0, time_step_ps=T)


def test_off_window_on_the_response_path(tailed):
    """A direct whose peak lies before the first bin, or at it (the rising half of the core and
    more than OFF_WINDOW_MASS of the area outside), is flagged; one well inside is not, nor one
    whose tail alone runs a little past the last bin."""
    rng = np.random.default_rng(0)
    delay = np.array([-3.0, 0.0, 2.5, 60.0, 150.0, 480.0])
    flagged = np.array([True, True, True, False, False, False])
    y = render_shifted(tailed, T_PS, delay) + 0.01 * rng.standard_normal((delay.size, L))
    res = decompose(y, T, irf=tailed)
    assert np.all(np.abs(res.params["direct_delay_ps"] - delay) < 0.5)
    np.testing.assert_array_equal(res.flags & OFF_WINDOW != 0, flagged)


@pytest.mark.parametrize("sigma_ps", [2.0, 3.0, 4.0, 8.0])
def test_spike_ratio_of_a_gaussian_response_is_the_gaussian_rule(sigma_ps):
    """The response's smallest neighbour ratio is that of a centred Gaussian, exp(-T^2 / (2 s^2)),
    the Gaussian path's r_min for its narrowest sigma."""
    irf = resolve_response(gaussian_response(sigma_ps, time_step_ps=T), T, L)
    assert spike_neighbour_ratio(irf, T, 0.05) == pytest.approx(math.exp(-0.5 * (T / sigma_ps) ** 2), rel=1e-9)


def test_spike_on_a_tail_is_excluded_with_the_responses_own_ratio(tailed):
    """A one-sample spike of half the peak on the tail (14 ps after the direct, at 6-8 % of the
    peak) is a spike for the response (neighbour ratio 0.89), though not for the Gaussian grid's
    narrowest 1 ps kernel; excluded, it leaves no echo, where kept it becomes one.  Clean
    profiles flag nothing, and the Gaussian grid's options no longer change the test."""
    rng = np.random.default_rng(2)
    delay = 100.0 + rng.uniform(0.0, T, 12)
    clean = render_shifted(tailed, T_PS, delay) + 0.005 * rng.standard_normal((delay.size, L))
    j = int(np.argmin(np.abs(T_PS - 114.0)))
    spiky = clean.copy()
    spiky[:, j] += 0.5
    res = decompose(spiky, T, irf=tailed)
    assert res.info["spike_neighbour_ratio"] == pytest.approx(spike_neighbour_ratio(
        resolve_response(tailed, T, L), T, 0.05))
    assert np.all(res.flags & SPIKE)
    assert not np.isfinite(res.params["ir_delay_ps"]).any()
    assert np.abs(res.params["direct_delay_ps"] - delay).max() < 0.1
    kept = decompose(spiky, T, irf=tailed, spike_sigma=0.0)
    # (kept, the spike's residual also reads as noise that follows the signal in every pixel, and
    # the weighted refit puts the echo 0.0-1.2 ps before the spike's sample; unweighted, 0.0-0.4)
    assert np.all(np.abs(kept.params["ir_delay_ps"][:, 0] - T_PS[j]) < 1.5)
    assert not np.any(decompose(clean, T, irf=tailed).flags)
    other_grid = decompose(spiky, T, irf=tailed, sigma_range_ps=(8.0, 80.0))
    np.testing.assert_array_equal(other_grid.flags, res.flags)
    np.testing.assert_array_equal(other_grid.params["direct_delay_ps"], res.params["direct_delay_ps"])


def test_the_labels_rule_reads_a_responses_atoms_as_the_gaussian_paths():
    """One rule of the atoms a pixel keeps (``stages.label.final_atoms``): with a Gaussian
    response of sigma 2 bins, the window's heights and energies of its atoms are the Gaussian
    path's measures of that sigma (to the table's error); two shifted copies closer than the
    merge tolerance leave the larger one where it was (a response has no width to merge into),
    where the Gaussian rule merges them into one wider atom; an atom below the relative
    threshold goes on both.  Weighted energies (the samples' relative weights where the noise
    follows the signal, capped) agree too."""
    from decomposition.constants import SIGNIFICANCE_WEIGHT_CAP
    from decomposition.model.components import merge_gaussians, window_measures
    from decomposition.options import SolverOptions
    from decomposition.stages.label import final_atoms

    sigma = 2.0 * T
    irf = gaussian_response(sigma, time_step_ps=T)
    fam = np.array([[FAM_GAUSS, FAM_SSS, FAM_GAUSS, FAM_GAUSS], [FAM_GAUSS, FAM_NONE, FAM_GAUSS, FAM_NONE]], np.int8)
    st = {"fam": fam, "delay": np.array([[80.0, 86.0, 80.8, 160.0], [T_PS[0] - 3.0, 0.0, 200.0, 0.0]]),
          "lsig": np.full(fam.shape, math.log(sigma)), "lalp": np.where(fam == FAM_SSS, math.log(0.02), 0.0),
          "amp": np.array([[1.0, 0.3, 0.6, 0.02], [0.5, 0.0, 0.4, 0.0]])}
    h_r, e_r = window_measures(st, T_PS, irf=irf)
    h_g, e_g = window_measures(st, T_PS)
    np.testing.assert_allclose(h_r, h_g, atol=1e-7)
    np.testing.assert_allclose(e_r, e_g, rtol=1e-6, atol=1e-12)
    # the samples' relative weights (where the noise follows the signal), some above the cap:
    # the same weighted energies on both
    w = np.random.default_rng(1).uniform(0.0, 3.0 * SIGNIFICANCE_WEIGHT_CAP, (2, T_PS.size))
    hw_r, ew_r = window_measures(st, T_PS, w, irf=irf)
    hw_g, ew_g = window_measures(st, T_PS, w)
    np.testing.assert_array_equal(hw_r, h_r)
    np.testing.assert_allclose(ew_r, ew_g, rtol=1e-6, atol=1e-12)
    assert not np.allclose(ew_r, e_r)
    merged = merge_gaussians({k: v.copy() for k, v in st.items()}, T, 1.0, widths=False)
    np.testing.assert_array_equal(merged["fam"][0], [FAM_GAUSS, FAM_SSS, FAM_NONE, FAM_GAUSS])
    assert merged["delay"][0, 0] == 80.0 and merged["amp"][0, 0] == 1.0 and merged["lsig"][0, 0] == st["lsig"][0, 0]
    widened = merge_gaussians({k: v.copy() for k, v in st.items()}, T, 1.0)
    assert 80.0 < widened["delay"][0, 0] < 80.8 and widened["lsig"][0, 0] > st["lsig"][0, 0]
    opts = SolverOptions()
    kept_r = final_atoms({k: v.copy() for k, v in st.items()}, T_PS, T, opts, irf=irf)
    kept_g = final_atoms({k: v.copy() for k, v in st.items()}, T_PS, T, opts)
    assert kept_r["fam"][0, 3] == FAM_NONE and kept_g["fam"][0, 3] == FAM_NONE     # 2 % of the peak
    np.testing.assert_array_equal(kept_r["fam"][1], kept_g["fam"][1])
