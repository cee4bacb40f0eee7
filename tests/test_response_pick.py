"""The detection's compiled pick (decomposition/kernels/responsepick.py, used by response/detect.py).

Known answers: a copy of the block-array pick (full FFT correlation with every kernel, masks on
(pixels, kernels, shifts) arrays, argmax) is kept here as the reference; on random residuals
and slots -- every family constraint, atoms near existing shifted slots, rows with nothing
allowed -- the compiled pick chooses the same atom with the same gain and amplitude.
"""
import numpy as np
import pytest

from core.irf import render_shifted, render_sss
from core.irf_models import tailed_response
from decomposition.constants import AMP_MAX, FAM_GAUSS, FAM_NONE, FAM_SSS
from decomposition.response.detect import _pick
from decomposition.response.dictionary import FAM_SHIFTED, ResponseDictionary

T = 2.0
L = 200
T_PS = T + T * np.arange(L)


def _reference(dic, resid, fam, delay, n_shift_max, allow_sss, tol_ps):
    c = dic.correlate(resid)
    norm2 = dic.norm2
    ok = (norm2 > 0)[None] & (c > 0)
    amp = c / np.where(norm2 > 0, norm2, 1.0)[None]
    ok &= amp <= AMP_MAX
    n_sh = (fam == FAM_GAUSS).sum(axis=1)
    has_s = (fam == FAM_SSS).any(axis=1)
    shifted = (dic.fam == FAM_SHIFTED)[None, :, None]
    ok &= ~(shifted & (n_sh >= n_shift_max)[:, None, None])
    ok &= ~(~shifted & (has_s | (not allow_sss))[:, None, None])
    grid = dic.delay_ps(np.arange(dic.fam.size)[:, None], dic.shifts[None, :])
    for k in range(fam.shape[1]):
        near = np.abs(grid[None] - np.where(fam[:, k] == FAM_GAUSS, delay[:, k], np.inf)[:, None, None]) < tol_ps
        ok &= ~(shifted & near)
    gain = np.where(ok, c * amp, -np.inf)
    flat = np.argmax(gain.reshape(gain.shape[0], -1), axis=1)
    a_idx, s_idx = np.unravel_index(flat, gain.shape[1:])
    rows = np.arange(gain.shape[0])
    return gain[rows, a_idx, s_idx], amp[rows, a_idx, s_idx], a_idx, s_idx


@pytest.fixture(scope="module")
def setup():
    irf = tailed_response(4.0, 0.2, 30.0, time_step_ps=T)
    dic = ResponseDictionary(irf, L, T, T, phases=4, alphas_per_ps=[0.01, 0.03, 0.1])
    rng = np.random.default_rng(5)
    P, K = 60, 4
    d = rng.uniform(40, 250, P)
    y = (render_shifted(irf, T_PS, d) + 0.5 * render_shifted(irf, T_PS, d + rng.uniform(10, 100, P))
         + 0.04 * render_sss(irf, T_PS, d, rng.uniform(0.01, 0.1, P)) + 0.02 * rng.standard_normal((P, L)))
    y[::9] *= -1.0                                   # rows with few or no positive correlations
    y[4::9] *= 100.0                                 # amplitudes beyond AMP_MAX
    fam = np.zeros((P, K), np.int8)
    fam[:, 0] = np.where(rng.random(P) < 0.7, FAM_GAUSS, FAM_NONE)
    fam[:, 1] = np.where(rng.random(P) < 0.4, FAM_SSS, FAM_NONE)
    fam[:, 2] = np.where(rng.random(P) < 0.4, FAM_GAUSS, FAM_NONE)
    delay = np.stack([d, d, d + 30.0, np.zeros(P)], axis=1) + rng.normal(0, 1.0, (P, K))
    return dic, y, fam, delay


@pytest.mark.parametrize("n_shift_max,allow_sss", [(1, False), (2, True), (3, True), (0, True), (0, False)])
def test_compiled_pick_chooses_the_block_forms_atom(setup, n_shift_max, allow_sss):
    dic, y, fam, delay = setup
    tol = 1.5 * T
    ref = _reference(dic, y, fam, delay, n_shift_max, allow_sss, tol)
    got = _pick(dic, y, fam, delay, n_shift_max, allow_sss, tol)
    assert np.array_equal(np.isfinite(got[0]), np.isfinite(ref[0]))
    fin = np.isfinite(ref[0])
    if n_shift_max or allow_sss:
        assert fin.any()
    else:
        assert not fin.any()
    assert np.array_equal(got[2][fin], ref[2][fin]) and np.array_equal(got[3][fin], ref[3][fin])
    assert np.allclose(got[0][fin], ref[0][fin], rtol=1e-12, atol=0)
    assert np.allclose(got[1][fin], ref[1][fin], rtol=1e-12, atol=0)
    # nothing chosen near an existing shifted slot, nothing of a closed family
    a, s = got[2][fin], got[3][fin]
    d = dic.delay_ps(a, dic.shifts[s])
    sh = dic.fam[a] == FAM_SHIFTED
    near = (np.abs(d[:, None] - np.where(fam[fin] == FAM_GAUSS, delay[fin], np.inf)) < tol).any(axis=1)
    assert not (sh & near).any()
    assert np.all(got[1][fin] <= AMP_MAX)


def test_pick_atoms_reads_through_gather_and_keeps_the_first_of_equal_gains():
    """Hand-made correlations: the shift s is read at c[..., gather[s]]; of two equal gains the
    earlier kernel (then shift) wins; a closed family, a non-positive correlation, an empty atom,
    an amplitude above amp_max and a shifted atom near a shifted slot are never chosen."""
    from decomposition.kernels.responsepick import pick_atoms

    gather = np.array([3, 0, 1])                       # shifts 0, 1, 2 at entries 3, 0, 1
    c = np.zeros((4, 2, 4))
    c[:, 0, 0] = 2.0                                   # kernel 0 (shifted), shift 1: gain 4
    c[:, 1, 3] = 2.0                                   # kernel 1 (sss), shift 0: gain 4 too
    c[:, 0, 2] = 9.0                                   # entry 2 is no shift: never read
    norm2 = np.ones((2, 3))
    shifted = np.array([True, False])
    grid = np.array([[0.0, 10.0, 20.0], [0.0, 10.0, 20.0]])
    fam = np.zeros((4, 2), np.int8)
    delay = np.zeros((4, 2))
    fam[1, 0], delay[1, 0] = FAM_GAUSS, 11.0          # row 1: a shifted slot near shift 1
    fam[2, 1] = FAM_SSS                                # row 2: has its sss
    gain, amp, a, s = pick_atoms(c, gather, norm2, shifted, grid, fam, delay, 2, True, 2.0, 20.0)
    assert list(a) == [0, 1, 0, 0] and list(s) == [1, 0, 1, 1]
    assert np.allclose(gain, 4.0) and np.allclose(amp, 2.0)
    # nothing allowed: closed families, or only negative / empty / too large atoms
    g0, *_ = pick_atoms(c, gather, norm2, shifted, grid, fam, delay, 0, False, 2.0, 20.0)
    assert np.all(g0 == -np.inf)
    g1, *_ = pick_atoms(-c, gather, norm2, shifted, grid, fam, delay, 2, True, 2.0, 20.0)
    assert np.all(g1 == -np.inf)
    g2, *_ = pick_atoms(c, gather, np.zeros((2, 3)), shifted, grid, fam, delay, 2, True, 2.0, 20.0)
    assert np.all(g2 == -np.inf)
    g3, *_ = pick_atoms(c, gather, norm2, shifted, grid, fam, delay, 2, True, 2.0, 1.5)
    assert np.all(g3 == -np.inf)
