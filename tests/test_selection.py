"""The model-selection rules (decomposition/stages/selection.py) against hand-computed values."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from core.model import empty_params
from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS, MAD_TO_SIGMA
from decomposition.masks import SampleMask
from decomposition.model.slots import new_state, render
from decomposition.noise import SpectralNoise, noise_sigma
from decomposition.stages.selection import (ambiguity_tolerance, data_term, families, free_parameters, is_ambiguous,
                                            log_samples, misfit_beyond_noise, noise_band, penalised,
                                            penalised_objective)

G, S, N = FAM_GAUSS, FAM_SSS, FAM_NONE


def test_free_parameters_of_a_slot_state_for_each_width_rule():
    fam = np.array([[G, S, G, N],          # direct, sss, one echo
                    [N, N, N, N],          # nothing
                    [S, N, N, N]], np.int8)  # an sss alone
    # delay + amplitude per atom, alpha per sss, then the widths
    assert free_parameters(fam, "per_atom").tolist() == [6 + 1 + 3, 0, 2 + 1 + 1]
    assert free_parameters(fam, "shared").tolist() == [6 + 1 + 1, 0, 2 + 1 + 1]
    assert free_parameters(fam, "fixed").tolist() == [6 + 1, 0, 2 + 1]
    with pytest.raises(ValueError, match="widths"):
        free_parameters(fam, "each")


def test_families_of_parameters_count_like_the_slot_state():
    p = empty_params((4,), n_ir=3)
    p["direct_delay_ps"][[0, 1, 2]] = 10.0
    p["sss_delay_ps"][[1, 2, 3]] = 12.0
    p["ir_delay_ps"][2, :2] = [40.0, 60.0]
    fam = families(p)
    assert fam.tolist() == [[G, N, N, N, N], [G, S, N, N, N], [G, S, G, G, N], [N, S, N, N, N]]
    # d; d + s; d + s + 2 r; s alone -- one shared width
    assert free_parameters(fam, "shared").tolist() == [2 + 1, 2 + 3 + 1, 2 + 3 + 4 + 1, 3 + 1]


def test_penalised_objective_is_chi2_plus_weighted_k_ln_n():
    assert log_samples(np.array([0, 1, 100])).tolist() == [0.0, 0.0, math.log(100)]
    j = penalised(np.array([12.5]), np.array([5]), np.log([100.0]), 2.0)
    assert j[0] == pytest.approx(12.5 + 2 * 5 * math.log(100), rel=1e-15)


def test_data_term_per_pixel_per_sample_and_whitened():
    r = np.array([[1.0, -2.0, 0.0, 3.0], [0.5, 0.5, 0.5, 0.5]])
    assert data_term(r, np.array([1.0, 0.25])).tolist() == [14.0, 4.0]
    per_sample = np.array([[1.0, 4.0, 1.0, 9.0], [1.0, 1.0, 1.0, 1.0]])
    assert data_term(r, per_sample).tolist() == [3.0, 1.0]
    # a white spectrum (L at every frequency per unit variance): the whitened term is the plain one
    white = SpectralNoise(np.full(3, 4.0), np.array([1.0, 0.25]))
    np.testing.assert_allclose(data_term(r, white), [14.0, 4.0], rtol=1e-12)


def test_penalised_objective_of_a_slot_state():
    t = 2.0 + 2.0 * np.arange(64)
    st = new_state(2, 3)
    st["fam"][:, 0] = G
    st["fam"][1, 1] = S
    st["amp"][:, :2] = 1.0
    st["delay"][:, :2] = 60.0
    st["lsig"][:, :2] = math.log(4.0)
    st["lalp"][:, 1] = math.log(0.03)
    r = np.zeros((2, 64))
    r[:, 10] = [3.0, -1.0]
    p = render(t, st) + r
    fit = np.ones((2, 64), bool)
    fit[:, :4] = False
    opts = SimpleNamespace(search_penalty=1.0, shared_sigma=True)
    # chi2 = 9 / 1 and 1 / 0.5; k = 3 and 6 (shared width); n = 60 fitted samples
    j = penalised_objective(t, p, SampleMask.of_fit(fit), st, np.array([1.0, 0.5]), np.log([60.0, 60.0]), opts)
    np.testing.assert_allclose(j, [9.0 + 3 * math.log(60), 2.0 + 6 * math.log(60)], rtol=1e-12)
    opts = SimpleNamespace(search_penalty=1.0, shared_sigma=False)
    j = penalised_objective(t, p, SampleMask.of_fit(fit), st, np.array([1.0, 0.5]), np.log([60.0, 60.0]), opts)
    np.testing.assert_allclose(j, [9.0 + 3 * math.log(60), 2.0 + 7 * math.log(60)], rtol=1e-12)


def test_chi2_beyond_noise_at_the_boundary():
    # n = 50, z = 3: n + z sqrt(2 n) = 50 + 3 * 10 = 80
    assert noise_band(50, 3.0) == 30.0
    got = misfit_beyond_noise(np.array([79.9, 80.0, np.nextafter(80.0, 81.0), np.nan]), np.full(4, 50), 3.0)
    assert got.tolist() == [False, False, True, False]


def test_ambiguity_tolerances_and_test():
    opts = SimpleNamespace(ambiguity_chi2=10.0, ambiguity_sigma=3.0)
    assert ambiguity_tolerance("evidence", opts) == 10.0
    assert ambiguity_tolerance("noise", opts, np.array([50, 200])).tolist() == [30.0, 60.0]
    with pytest.raises(ValueError, match="n_fit"):
        ambiguity_tolerance("noise", opts)
    with pytest.raises(ValueError, match="criterion"):
        ambiguity_tolerance("bic", opts)

    delta = np.array([5.0, 10.0, 10.5, 0.0, 2.0, 1.0])
    split = np.array([0.5, 0.4, 0.9, 0.1, 0.9, np.nan])
    asked = []

    def distance(r):
        asked.append(r.tolist())
        return split[r]

    where = np.array([True, True, True, True, False, True])
    got = is_ambiguous(delta, 10.0, distance, 0.3, where=where)
    # within the tolerance (<= 10), a rival (where), and a split more than 0.3 away (NaN: not)
    assert got.tolist() == [True, True, False, False, False, False]
    assert asked == [[0, 1, 3, 5]]          # the distance is read only where the fits compete
    asked.clear()
    assert not is_ambiguous(delta + 100.0, 10.0, distance, 0.3).any() and asked == []
    # a tolerance per pixel (the noise criterion)
    got = is_ambiguous(delta, np.array([1.0, 1.0, 20.0, 1.0, 1.0, 1.0]), lambda r: split[r], 0.3)
    assert got.tolist() == [False, False, True, False, False, False]


def test_noise_sigma_difference_order():
    # y = slope i + a (-1)^i over 9 samples: first differences slope -/+ 2a (4 each, median the
    # slope, every deviation 2a); second differences +/- 4a
    a, slope = 0.25, 3.0
    i = np.arange(9)
    y = (slope * i + a * (-1.0) ** i)[None, :]
    assert noise_sigma(y, order=1)[0] == pytest.approx(MAD_TO_SIGMA * 2 * a / math.sqrt(2), rel=1e-14)
    assert noise_sigma(y)[0] == pytest.approx(MAD_TO_SIGMA * 4 * a / math.sqrt(6), rel=1e-14)
    # the fitted samples only: the last two samples carry a jump the estimate must not see
    z = y.copy()
    z[0, 7:] += 50.0
    fit = np.ones_like(z, bool)
    fit[0, 7:] = False
    assert noise_sigma(z, fit[:, :], order=1)[0] == pytest.approx(MAD_TO_SIGMA * 2 * a / math.sqrt(2), rel=1e-14)
    assert noise_sigma(z, np.zeros_like(fit), order=1)[0] == 0.0
    with pytest.raises(ValueError, match="order"):
        noise_sigma(y, order=3)
