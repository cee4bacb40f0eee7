"""ConvSCD internals: FFT correlations, closed-form coordinate step, noise estimate, monotone descent."""
import warnings

import numpy as np
import pytest

from decomposition.methods import convscd as cs
from decomposition import decompose
from core.model import gaussian_kernel, sss_kernel, time_axis_ps
from decomposition.masks import SampleMask
from decomposition.noise import masked_median, noise_sigma
from decomposition.model.slots import parameter_bounds
from decomposition.kernels.pick import closed_form
from decomposition.evaluation.synthetic import make_profiles

T = 2.0


def _atom(dic, a, j, L):
    """Window-truncated unit-peak atom a at shift j, rendered directly."""
    t = time_axis_ps(L, T) - (dic.t0_ps + j * T)
    if dic.fam[a] == cs.FAM_GAUSS:
        k = gaussian_kernel(t, dic.sigma_ps[a])
    else:
        k = sss_kernel(t, dic.sigma_ps[a], dic.alpha_per_ps[a])
    return k / dic.peak[a]


def test_fft_correlations_and_truncated_norms_match_direct_sums():
    L = 96
    dic = cs.Dictionary(L, T, T, cs.GridSpec(coarse_sigma=2, coarse_alpha=2, coarse_sss_sigma=1), True, True)
    rng = np.random.default_rng(0)
    r = rng.standard_normal((3, L))
    c = dic.correlate(r)
    w = (rng.random((3, L)) > 0.2).astype(float)
    cw = dic.correlate(w, squared=True)
    assert c.shape == (3, dic.fam.size, L + dic.pre)
    for a in range(dic.fam.size):
        for jj in (0, 5, dic.pre, dic.pre + 40, L + dic.pre - 1):   # includes shifts before the window
            j = dic.shifts[jj]
            k = _atom(dic, a, j, L)
            np.testing.assert_allclose(c[:, a, jj], r @ k, rtol=1e-9, atol=1e-7)  # kernels cut at 6 sigma
            assert dic.norm2[a, jj] == pytest.approx(k @ k, rel=1e-7, abs=1e-7)
            np.testing.assert_allclose(cw[:, a, jj], w @ (k * k), rtol=1e-9, atol=1e-7)


def test_closed_form_coordinate_step_is_the_exact_minimiser():
    rng = np.random.default_rng(1)
    u = rng.uniform(-1, 2, 200)
    n = rng.uniform(0.1, 20, 200)
    mu, eps = 0.05, 0.01
    z, dec = closed_form(u, n, mu, eps)
    grid = np.linspace(0, 3, 30001)
    f = 0.5 * n[:, None] * (grid[None] - u[:, None]) ** 2 + mu * np.log1p(grid[None] / eps)
    zbest = grid[np.argmin(f, axis=1)]
    fz = 0.5 * n * (z - u) ** 2 + mu * np.log1p(z / eps)
    assert np.all(fz <= f.min(axis=1) + 1e-9)
    np.testing.assert_allclose(z, zbest, atol=2e-4)
    np.testing.assert_allclose(dec, 0.5 * n * u * u - fz, atol=1e-12)
    assert np.all(dec >= 0) and np.all(z >= 0)


def test_noise_estimate_is_robust_to_signal():
    rng = np.random.default_rng(2)
    data = make_profiles(50, 512, nsr=0.0, noise="none", seed=3)
    clean = data.clean / np.abs(data.clean).max(axis=1, keepdims=True)
    s = 0.02
    est = noise_sigma(clean + s * rng.standard_normal(clean.shape))
    assert np.median(est) == pytest.approx(s, rel=0.1)
    assert np.all(np.abs(est / s - 1) < 0.3)
    assert np.all(noise_sigma(np.zeros((2, 64))) == 0)


def test_masked_median_is_the_nanmedian_of_the_kept_entries():
    """Odd and even counts, ties, NaN and inf entries, rows with one entry and with none:
    the same values as numpy's nanmedian of the row with the other entries set to NaN."""
    rng = np.random.default_rng(11)
    v = np.round(rng.normal(size=(40, 31)), 1)          # rounded: ties between kept entries
    ok = rng.random(v.shape) < 0.5
    v[0, :3] = [np.nan, np.inf, -np.inf]
    ok[0, :3] = True
    ok[1] = False
    ok[2] = False
    ok[2, 7] = True
    ok[3] = True
    ok[4] = False
    ok[4, [2, 9]] = True
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nanmedian(np.where(ok, v, np.nan), axis=1)
    got = masked_median(v, ok)
    np.testing.assert_array_equal(got, ref)
    assert np.isnan(got[1]) and got[2] == v[2, 7] and got[4] == (v[4, 2] + v[4, 9]) / 2
    assert masked_median(np.zeros((3, 0)), np.zeros((3, 0), bool)).shape == (3,)


def test_masked_median_selection_on_long_and_adversarial_rows():
    """The in-place selection on rows of a profile's length: sorted, reversed, all equal, two
    values, a few distinct values and random rows of every length from 1 to 600 give
    np.median's value exactly."""
    rng = np.random.default_rng(5)
    L = 600
    rows = [np.arange(L, dtype=float), np.arange(L, 0, -1, dtype=float), np.full(L, 3.25),
            np.tile([1.0, -1.0], L // 2), rng.integers(0, 4, L).astype(float),
            np.concatenate([np.zeros(L // 2), np.ones(L // 2)])[::-1]]
    rows += [rng.normal(size=L) for _ in range(40)]
    v = np.array(rows)
    for m in list(range(1, 40)) + [255, 256, 511, 512, 599, 600]:
        ok = np.zeros(v.shape, bool)
        ok[:, :m] = True
        np.testing.assert_array_equal(masked_median(v, ok), np.median(v[:, :m], axis=1), err_msg=f"m={m}")


def test_objective_never_increases_and_iterations_are_bounded():
    data = make_profiles(24, 256, nsr=0.08, noise="white", seed=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = decompose(data.noisy, T, max_iter=6)
    h = res.info["objective"]
    assert h.shape == (24, 7)
    assert np.all(np.isfinite(h[:, 0]))
    d = np.diff(h, axis=1)
    ok = np.isfinite(d)
    assert ok.sum() > 24
    assert np.all(d[ok] <= 1e-12 * np.abs(h[:, :-1][ok]))
    # once a pixel stops, it stays stopped
    stopped = np.isnan(h)
    assert np.all(stopped[:, :-1] <= stopped[:, 1:])
    assert res.info["n_iter"].max() <= 6
    assert np.all(res.info["n_iter"] >= 2)


def test_family_selection_shrinks_the_search():
    L = 256
    g = cs.GridSpec()
    full = cs.get_dictionary(L, T, T, g, True, True)
    no_s = cs.get_dictionary(L, T, T, g, True, False)
    assert cs.get_dictionary(L, T, T, g, True, True) is full       # cached
    assert not np.any(no_s.fam == cs.FAM_SSS)
    assert no_s.n_coordinates < full.n_coordinates / 2
    data = make_profiles(120, L, nsr=0.01, noise="white", seed=5, kinds=("d+r2",))  # ~20 ms a call
    import time

    def best_of_3(**kw):
        times = []
        for _ in range(3):
            t0 = time.process_time()
            res = decompose(data.noisy, T, **kw)
            times.append(time.process_time() - t0)
        return res, min(times)

    r_full, t_full = best_of_3()
    r_dr, t_dr = best_of_3(components="d,r")
    assert r_dr.info["coordinates_searched"] < r_full.info["coordinates_searched"]
    assert np.isnan(r_dr.params["sss_delay_ps"]).all() and not r_dr.sss.any()
    assert t_dr < 1.5 * t_full          # generous: the point is that it is not slower
    np.testing.assert_allclose(r_dr.params["direct_delay_ps"], data.params["direct_delay_ps"], atol=0.5)


def test_refinement_keeps_parameters_within_bounds(default_dictionary):
    """Unrestricted greedy start and polish on photon-noise data: every refined delay,
    width and attenuation stays inside its bounds (no runaway step), nothing overflows."""
    from decomposition.model import components as comp

    data = make_profiles(30, 256, nsr=0.05, noise="photon", seed=1)
    p = data.noisy / np.abs(data.noisy).max(axis=1, keepdims=True)
    mask = SampleMask.all_fitted(p.shape)
    s = np.maximum(noise_sigma(p), 1e-3)
    dic = default_dictionary(256, T)
    t = time_axis_ps(256, T)
    with np.errstate(over="raise", invalid="raise", divide="raise"), warnings.catch_warnings():
        warnings.simplefilter("error")
        st, info = cs.solve_block(p, mask, s, dic, max_components=6, max_gauss=6)
        comp.threshold(st, t)
        st, model, _ = cs.polish_block(p, mask, st, s, dic)
    b = parameter_bounds(dic, 4.0)
    act = st["fam"] != cs.FAM_NONE
    assert act.any()
    assert np.all((st["delay"][act] >= b["delay"][0]) & (st["delay"][act] <= b["delay"][1]))
    assert np.all((st["lsig"][act] >= b["lsig"][0] - 1e-12) & (st["lsig"][act] <= b["lsig"][1] + 1e-12))
    assert np.all(np.isfinite(model))


def test_dictionary_cache_is_explicit_and_bounded():
    from decomposition.methods.dictionary import DictionaryCache, get_dictionary

    cache = DictionaryCache(maxsize=2)
    g = cs.GridSpec(coarse_sigma=2, coarse_alpha=1, coarse_sss_sigma=1)
    a = get_dictionary(64, 2.0, 2.0, g, True, True, cache=cache)
    assert get_dictionary(64, 2.0, 2.0, g, True, True, cache=cache) is a and len(cache) == 1
    get_dictionary(64, 2.0, 2.0, g, True, False, cache=cache)
    get_dictionary(64, 2.0, 2.0, g, False, True, cache=cache)          # evicts the least recently used (a)
    assert len(cache) == 2 and get_dictionary(64, 2.0, 2.0, g, True, True, cache=cache) is not a
    fresh = get_dictionary(64, 2.0, 2.0, g, True, True, cache=None)
    assert fresh is not a and np.array_equal(fresh.norm2, a.norm2)
    cache.clear()
    assert len(cache) == 0


def test_dictionary_cache_serves_concurrent_threads():
    import threading

    from decomposition.methods.dictionary import DictionaryCache, get_dictionary

    cache = DictionaryCache(maxsize=1)                 # every other call evicts: the racy path
    grids = [cs.GridSpec(coarse_sigma=1 + i % 2, coarse_alpha=1, coarse_sss_sigma=1) for i in range(2)]
    errors = []

    def work(i):
        try:
            for j in range(30):
                d = get_dictionary(64, 2.0, 2.0, grids[(i + j) % 2], True, True, cache=cache)
                assert d.grid == grids[(i + j) % 2]
        except Exception as exc:                        # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors and len(cache) == 1
