"""Compiled own-width correlations (decomposition.kernels.pickcorr) against dense sums, and the solver using them."""
import math

import numpy as np
import pytest

from decomposition.methods import convscd as cs
from decomposition.methods.dictionary import coarse_values
from decomposition.kernels.pick import select
from decomposition.methods.score import score_pixel
from decomposition import decompose
from decomposition.api import SPIKE
from decomposition.evaluation.metrics import mean_fidelity
from core.model import sss_kernel
from decomposition.kernels.pickcorr import PickWorkspace, pixel_correlations
from decomposition.evaluation.synthetic import make_profiles

SIGMAS = np.array([0.3, 1.0, 2.0, 4.5, 10.0])             # 0.3 ps: below one bin at T = 2 ps
ALPHAS = np.array([1e-4, 0.01, 0.0224, 0.05, 5.0])


def _dense(r, sig, alphas, T, pre, H, w1=None):
    """The definition: kernels sampled on d in [-H, L + pre), divided by their largest sample,
    zero before -H; c[i, a, j] = sum_m r[m] k(m - s_j), n2 = sum_m w1[m] k(m - s_j)^2."""
    n, L = r.shape
    d_axis = np.arange(-H, L + pre)
    shifts = np.arange(-pre, L)
    d = np.arange(L)[None, :] - shifts[:, None]               # (S, L): m - s_j, always < L + pre
    nk = 1 + alphas.size
    c = np.zeros((n, nk, shifts.size))
    n2 = np.zeros_like(c)
    peak = np.zeros((n, nk))
    for i in range(n):
        kernels = [np.exp(-0.5 * (d_axis * T / sig[i]) ** 2)]
        kernels += [sss_kernel(d_axis * T, sig[i], a) for a in alphas]
        for a, k in enumerate(kernels):
            peak[i, a] = k.max()
            K = np.where(d >= -H, (k / peak[i, a])[np.clip(d + H, 0, None)], 0.0)
            c[i, a] = K @ r[i]
            n2[i, a] = (K * K) @ (np.ones(L) if w1 is None else w1[i])
    return c, n2, peak


@pytest.mark.parametrize("L, T", [(64, 2.0), (64, 0.5), (512, 2.0)])
@pytest.mark.parametrize("weighted", [False, True])
def test_correlations_norms_and_peaks_match_dense_sums(L, T, weighted):
    rng = np.random.default_rng(L + int(4 * T))
    r = rng.standard_normal((SIGMAS.size, L))
    r[:, L // 3] += 40.0                                      # a peak well inside the window
    w1 = (rng.random(r.shape) > 0.1).astype(float) if weighted else None
    pre = int(math.ceil(3.0 * 10.0 / T)) + 1
    H = int(math.ceil(6.0 * SIGMAS.max() / T)) + 1            # at T = 0.5 the 10 ps kernels outrun L + pre
    c, n2, peak = pixel_correlations(r, SIGMAS, ALPHAS, time_bin_ps=T, pre=pre, half_bins=H, w1=w1)
    c0, n20, peak0 = _dense(r, SIGMAS, ALPHAS, T, pre, H, w1)
    assert c.shape == n2.shape == (SIGMAS.size, 1 + ALPHAS.size, L + pre)
    np.testing.assert_allclose(peak, peak0, rtol=1e-12, atol=0)
    # every (pixel, kernel) row to 1e-10 of its own largest value
    assert np.all(np.abs(c - c0) <= 1e-10 * np.abs(c0).max(axis=2, keepdims=True))
    assert np.all(np.abs(n2 - n20) <= 1e-10 * n20.max(axis=2, keepdims=True))
    assert np.all(n20.max(axis=2) > 0)


def test_kernels_partly_outside_the_window_and_empty_inputs():
    T, L, pre = 2.0, 64, 16
    r = np.zeros((2, L))
    r[:, 0] = 1.0                                             # one sample at the window start
    sig = np.array([3.0, 3.0])
    c, n2, peak = pixel_correlations(r, sig, np.array([0.02]), time_bin_ps=T, pre=pre, half_bins=10)
    # c at shift s is the kernel at d = -s: the Gaussian's samples, i.e. exp(-(sT)^2 / 2 sigma^2)
    s = np.arange(-pre, L)
    np.testing.assert_allclose(c[0, 0], np.where(s <= 10, np.exp(-0.5 * (s * T / 3.0) ** 2), 0.0), atol=1e-14)
    np.testing.assert_allclose(c[0, 1, :pre + 1], sss_kernel(-s[:pre + 1] * T, 3.0, 0.02) / peak[0, 1],
                               rtol=1e-12)
    assert np.all(c[0, 1, pre + 11:] == 0)                      # onset more than H bins after the sample
    g_only = pixel_correlations(r, sig, np.zeros(0), time_bin_ps=T, pre=pre, half_bins=10)   # no sss family
    for got, ref in zip(g_only, (c, n2, peak)):
        np.testing.assert_array_equal(got, ref[:, :1])
    e = pixel_correlations(np.zeros((0, L)), np.zeros(0), np.array([0.02]), time_bin_ps=T, pre=pre, half_bins=10)
    assert [a.shape for a in e] == [(0, 2, L + pre), (0, 2, L + pre), (0, 2)]


@pytest.mark.parametrize("kwargs, match", [
    ({"sig_ps": np.array([0.0])}, "sig_ps"),
    ({"sig_ps": np.array([1.0, 2.0])}, "one width per pixel"),
    ({"alphas_per_ps": np.array([np.nan])}, "alphas_per_ps"),
    ({"time_bin_ps": -1.0}, "time_bin_ps"),
    ({"half_bins": 0}, "half_bins"),
    ({"w1": np.ones((1, 5))}, "w1"),
])
def test_bad_arguments_are_named(kwargs, match):
    args = {"sig_ps": np.array([1.0]), "alphas_per_ps": np.array([0.02]), "time_bin_ps": 2.0, "pre": 4,
            "half_bins": 4}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        pixel_correlations(np.zeros((1, 8)), **args)


def test_score_pixel_picks_the_best_coordinate_of_the_dense_formulation(default_dictionary):
    """Weighted block: the pick (atom, shift, amplitude, decrease) equals the one from dense sums."""
    L, T = 128, 2.0
    dic = default_dictionary(L, T)
    data = make_profiles(8, L, nsr=0.05, noise="white", seed=3)
    p = data.noisy / data.noisy.max(axis=1, keepdims=True)
    fit = np.ones(p.shape, bool)
    fit[:, 40] = False                                        # an excluded sample
    fit[:3, 41] = False                                       # censored samples: never used to pick
    r = p * fit
    sig = np.linspace(1.5, 7.0, p.shape[0])
    mu = np.full(p.shape[0], 3.0 * 0.05 ** 2)
    eps = np.full(p.shape[0], 0.01 * 0.05)
    yes = np.ones(p.shape[0], bool)
    min_s = np.full(p.shape[0], -np.inf)
    cand, dec = score_pixel(r, fit, True, dic, sig, mu, eps, yes, yes, min_s, 4.0)
    alphas = coarse_values(*dic.grid.alpha_range_per_ps, dic.grid.coarse_alpha)
    H = int(math.ceil(6.0 * sig.max() / T)) + 1
    c0, n20, peak0 = _dense(r, sig, alphas, T, dic.pre, H, fit.astype(float))
    best, z, d0 = select(c0, np.where(n20 > 1e-12, n20, 0.0), mu, eps,
                             np.ones((p.shape[0], 1 + alphas.size, 1), bool))
    a_i, j_i = np.divmod(best, dic.shifts.size)
    rows = np.arange(p.shape[0])
    np.testing.assert_allclose(dec, d0, rtol=1e-9)
    assert np.all(dec > 0)
    np.testing.assert_array_equal(cand["fam"], np.where(a_i == 0, cs.FAM_GAUSS, cs.FAM_SSS))
    np.testing.assert_allclose(cand["delay"], dic.t0_ps + dic.shifts[j_i] * T)
    np.testing.assert_allclose(cand["amp"], z / peak0[rows, a_i], rtol=1e-9)


def test_whole_solver_fidelity_unchanged():
    data = make_profiles(256, 512, nsr=0.05, seed=0)
    # 0.95553 with the FFT formulation of the own-width pick (same data and solver otherwise)
    assert mean_fidelity(data.components, decompose(data.noisy, time_bin_ps=2.0)) >= 0.95553 - 0.002


def test_whole_solver_on_a_weighted_block_with_spikes():
    data = make_profiles(48, 512, nsr=0.05, noise="white", seed=4)
    clean = mean_fidelity(data.components, decompose(data.noisy, time_bin_ps=2.0))
    spiky = data.noisy.copy()
    rng = np.random.default_rng(5)
    hit = rng.choice(48, 16, replace=False)
    for i in hit:                                             # cosmic-ray hits where there is no signal
        quiet = np.flatnonzero(data.clean[i] < 0.01 * data.clean[i].max())
        spiky[i, rng.choice(quiet[(quiet > 5) & (quiet < 505)])] += 0.8 * spiky[i].max()
    res = decompose(spiky, time_bin_ps=2.0)
    assert np.all(res.flags[hit] & SPIKE)
    assert mean_fidelity(data.components, res) >= clean - 0.01


def test_reused_buffers_give_the_same_results():
    rng = np.random.default_rng(9)
    kw = {"time_bin_ps": 2.0, "pre": 16, "half_bins": 20}
    al = np.array([0.01, 0.05])
    big = rng.standard_normal((6, 96)), rng.uniform(1.0, 6.0, 6)
    small = rng.standard_normal((2, 96)), rng.uniform(1.0, 6.0, 2)
    fresh = [pixel_correlations(r, s, al, **kw) for r, s in (big, small)]
    ws = PickWorkspace()
    for (r, s), ref in zip((big, small, big), fresh + fresh[:1]):   # grows, shrinks, grows again
        got = pixel_correlations(r, s, al, out=ws, **kw)
        for g, f in zip(got, ref):
            np.testing.assert_array_equal(g, f)
    # the workspace is the caller's: another one (another thread's) is never written
    other = PickWorkspace()
    c_a, _, _ = pixel_correlations(big[0], big[1], al, out=ws, **kw)
    keep = c_a.copy()
    pixel_correlations(small[0], small[1], al, out=other, **kw)
    np.testing.assert_array_equal(c_a, keep)


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("n_alpha", [3, 2])
def test_rows_a_pixel_may_not_take_are_skipped_and_the_rest_unchanged(weighted, n_alpha):
    """need_gauss / need_sss / sss_from: every value of the rows a pixel may take (the Gaussian
    at every shift, the sss kernels from sss_from on) is bit for bit that of a full call."""
    rng = np.random.default_rng(4)
    n, L, T, pre = 12, 200, 2.0, 9
    r = rng.normal(size=(n, L))
    sig = rng.choice(SIGMAS, n)
    alphas = ALPHAS[1:1 + n_alpha]
    w1 = (rng.random((n, L)) > 0.1).astype(float) if weighted else None
    H = int(math.ceil(4 * sig.max() / T)) + 1
    c0, n0, p0 = pixel_correlations(r, sig, alphas, time_bin_ps=T, pre=pre, half_bins=H, w1=w1)
    need_g = np.arange(n) % 3 != 1              # rows 1, 4, ...: sss only
    need_s = np.arange(n) % 3 != 0              # rows 0, 3, ...: Gaussian only
    start = rng.integers(0, L + pre, n)
    ws = PickWorkspace()
    ws.arrays(n, 1 + alphas.size, L + pre)[0][:] = np.nan     # stale buffer contents stay unread
    c1, n1, p1 = pixel_correlations(r, sig, alphas, time_bin_ps=T, pre=pre, half_bins=H, w1=w1, out=ws,
                                    need_gauss=need_g, need_sss=need_s, sss_from=start)
    for i in range(n):
        if need_g[i]:
            np.testing.assert_array_equal(c1[i, 0], c0[i, 0])
            np.testing.assert_array_equal(n1[i, 0], n0[i, 0])
        if need_s[i]:
            j = 0 if need_g[i] else start[i]
            np.testing.assert_array_equal(c1[i, 1:, j:], c0[i, 1:, j:])
            np.testing.assert_array_equal(n1[i, 1:, j:], n0[i, 1:, j:])
            np.testing.assert_array_equal(p1[i, 1:], p0[i, 1:])
    assert np.isnan(c1[np.nonzero(~need_s)[0], 1:]).all()    # not computed
