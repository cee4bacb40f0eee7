"""Fisher information, Cramér-Rao bounds and standard errors against known answers and Monte Carlo."""
import warnings

import numpy as np
import pytest

from decomposition.model.fisher import cramer_rao_bound, fisher_information, parameter_names, standard_errors
from core.model import empty_params, render_profile, time_axis_ps
from decomposition.model.refine import refine

T = 2.0


def _single(n, delay=101.0, amp=2.0, sigma=3.0):
    p = empty_params((n,), 0)
    p["direct_delay_ps"][:] = delay
    p["direct_amplitude"][:] = amp
    p["direct_sigma_ps"][:] = sigma
    return p


def test_isolated_gaussian_crb_matches_analytic_bound():
    L, nsr = 128, 0.05
    p = _single(1)
    clean = render_profile(p, L, T)[0]
    noise = nsr * np.linalg.norm(clean) / np.sqrt(L)
    crb = cramer_rao_bound(p, noise, n_bins=L, time_bin_ps=T)
    t = time_axis_ps(L, T)
    g = np.exp(-0.5 * ((t - 101.0) / 3.0) ** 2)
    # Delay decouples from amplitude and sigma (odd vs even columns about a bin centre):
    exact = noise / (2.0 * np.sqrt(np.sum((g * (t - 101.0) / 9.0) ** 2)))
    np.testing.assert_allclose(crb["direct_delay_ps_crb"][0], exact, rtol=1e-9)
    # ... and the continuum limit NSR * sigma * sqrt(2 / L).
    np.testing.assert_allclose(crb["direct_delay_ps_crb"][0], nsr * 3.0 * np.sqrt(2.0 / L), rtol=1e-3)
    assert np.isnan(crb["sss_delay_ps_crb"][0]) and crb["ir_delay_ps_crb"].shape == (1, 0)


def test_fisher_matches_finite_difference_jacobian():
    L = 160
    p = empty_params((1,), 1)
    p.update(direct_delay_ps=np.array([60.3]), direct_amplitude=np.array([1.5]), direct_sigma_ps=np.array([3.2]),
             sss_delay_ps=np.array([70.1]), sss_amplitude=np.array([0.08]), sss_alpha_per_ps=np.array([0.03]),
             sss_sigma_ps=np.array([2.7]), ir_delay_ps=np.array([[120.4]]), ir_amplitude=np.array([[0.4]]),
             ir_sigma_ps=np.array([[3.5]]))
    names = parameter_names(1)
    cols = []
    for name in names:
        key, idx = (name[:-3], (0, 0)) if name.endswith("]") else (name, (0,))
        h = 1e-6 * abs(p[key][idx])
        up = {k: v.copy() for k, v in p.items()}
        dn = {k: v.copy() for k, v in p.items()}
        up[key][idx] += h
        dn[key][idx] -= h
        cols.append((render_profile(up, L, T) - render_profile(dn, L, T))[0] / (2 * h))
    jac = np.array(cols)
    fisher, free = fisher_information(p, 0.01, n_bins=L, time_bin_ps=T)
    assert free.all()
    ref = jac @ jac.T / 0.01**2
    np.testing.assert_allclose(fisher[0], ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max())


@pytest.mark.timeout(60)
def test_refine_reaches_the_crb_for_isolated_direct_components():
    # Issue-6 target: delay RMSE within 1.5x the CRB at NSR 0.05 (white), Monte Carlo over 300 realisations.
    L, nsr, n = 128, 0.05, 300
    rng = np.random.default_rng(11)
    p = _single(n)
    clean = render_profile(p, L, T)
    noise = nsr * np.linalg.norm(clean[0]) / np.sqrt(L)
    y = clean + noise * rng.standard_normal(clean.shape)
    start = {k: v.copy() for k, v in p.items()}
    start["direct_delay_ps"] += rng.uniform(-1.0, 1.0, n)   # anywhere within a 2 ps grid cell
    start["direct_sigma_ps"] *= rng.uniform(0.85, 1.15, n)
    fit, info = refine(y, start, time_bin_ps=T)
    assert info["converged"].all() and info["refined"].all()
    crb = cramer_rao_bound(p, noise, n_bins=L, time_bin_ps=T)
    for key in ("direct_delay_ps", "direct_amplitude", "direct_sigma_ps"):
        rmse = np.sqrt(np.mean((fit[key] - p[key]) ** 2))
        ratio = rmse / crb[key + "_crb"][0]
        assert 0.8 < ratio < 1.5, (key, ratio)
    # Standard errors from the fit itself agree with the bound on average.
    se = standard_errors(y, fit, time_bin_ps=T)
    np.testing.assert_allclose(np.mean(se["direct_delay_ps_stderr"]), crb["direct_delay_ps_crb"][0], rtol=0.1)
    z = (fit["direct_delay_ps"] - p["direct_delay_ps"]) / se["direct_delay_ps_stderr"]
    assert 0.9 < np.mean(np.abs(z) < 1.96) <= 1.0  # ~95 % coverage
    assert np.isnan(se["sss_alpha_per_ps_stderr"]).all()


def test_singular_fisher_gives_nan_not_errors():
    p = empty_params((3,), 1)
    for i in range(3):
        p["direct_delay_ps"][i], p["direct_amplitude"][i], p["direct_sigma_ps"][i] = 80.0, 1.0, 3.0
    # Pixel 0: an inter-reflection identical to the direct component (indistinguishable).
    p["ir_delay_ps"][0, 0], p["ir_amplitude"][0, 0], p["ir_sigma_ps"][0, 0] = 80.0, 0.5, 3.0
    # Pixel 1: an inter-reflection far outside the window (no information about it at all).
    p["ir_delay_ps"][1, 0], p["ir_amplitude"][1, 0], p["ir_sigma_ps"][1, 0] = 5000.0, 0.5, 3.0
    # Pixel 2: well separated, fine.
    p["ir_delay_ps"][2, 0], p["ir_amplitude"][2, 0], p["ir_sigma_ps"][2, 0] = 140.0, 0.5, 3.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        crb = cramer_rao_bound(p, 0.01, n_bins=128, time_bin_ps=T)
        y = render_profile(p, 128, T) + 0.01 * np.random.default_rng(0).standard_normal((3, 128))
        se = standard_errors(y, p, time_bin_ps=T)
    for out, suffix in ((crb, "_crb"), (se, "_stderr")):
        assert np.isnan(out["direct_delay_ps" + suffix][:2]).all()
        assert np.isnan(out["ir_delay_ps" + suffix][:2]).all()
        assert np.isfinite(out["direct_delay_ps" + suffix][2]) and np.isfinite(out["ir_amplitude" + suffix][2, 0])


@pytest.mark.parametrize("scale", [1e-30, 1e30])
def test_bounds_scale_with_the_data(scale):
    p = empty_params((1,), 0)
    p.update(direct_delay_ps=np.array([50.0]), direct_amplitude=np.array([1.0]), direct_sigma_ps=np.array([3.0]),
             sss_delay_ps=np.array([58.0]), sss_amplitude=np.array([0.1]), sss_alpha_per_ps=np.array([0.02]),
             sss_sigma_ps=np.array([3.0]))
    ref = cramer_rao_bound(p, 0.01, n_bins=200, time_bin_ps=T)
    ps = dict(p, direct_amplitude=p["direct_amplitude"] * scale, sss_amplitude=p["sss_amplitude"] * scale)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = cramer_rao_bound(ps, 0.01 * scale, n_bins=200, time_bin_ps=T)
    for key, v in ref.items():
        want = v * scale if "amplitude" in key else v
        np.testing.assert_allclose(got[key], want, rtol=1e-9, err_msg=key)
    assert np.isfinite(ref["sss_alpha_per_ps_crb"]).all()


def test_bad_noise_is_rejected():
    p = _single(2)
    with pytest.raises(ValueError, match="noise_sigma"):
        cramer_rao_bound(p, np.ones(3), n_bins=64, time_bin_ps=T)
    with pytest.raises(ValueError, match="noise_sigma"):
        cramer_rao_bound(p, -1.0, n_bins=64, time_bin_ps=T)


def test_shared_sigma_bound_is_the_one_width_problem():
    # d + s with the onset under the direct peak: with free widths nearly degenerate, with one width
    # well posed.  The shared bound equals the bound of the reduced problem computed by hand.
    L = 200
    p = empty_params((1,), 1)
    p.update(direct_delay_ps=np.array([60.0]), direct_amplitude=np.array([1.0]), direct_sigma_ps=np.array([3.0]),
             sss_delay_ps=np.array([63.0]), sss_amplitude=np.array([0.05]), sss_alpha_per_ps=np.array([0.03]),
             sss_sigma_ps=np.array([3.0]), ir_delay_ps=np.array([[110.0]]), ir_amplitude=np.array([[0.3]]),
             ir_sigma_ps=np.array([[3.0]]))
    fisher, free = fisher_information(p, 0.01, n_bins=L, time_bin_ps=T)
    names = parameter_names(1)
    sig = [names.index(n) for n in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps[0]")]
    keep = [i for i in range(len(names)) if i not in sig[1:]]
    # Reduce: one width = d/dsigma summed over components -> F' = A^T F A.
    a = np.zeros((len(names), len(keep)))
    for j, i in enumerate(keep):
        a[i, j] = 1.0
    a[sig, keep.index(sig[0])] = 1.0
    cov = np.linalg.inv(a.T @ fisher[0] @ a)
    shared = cramer_rao_bound(p, 0.01, n_bins=L, time_bin_ps=T, shared_sigma=True)
    for name in ("direct_delay_ps", "sss_delay_ps", "sss_alpha_per_ps", "direct_sigma_ps"):
        j = keep.index(names.index(name))
        np.testing.assert_allclose(shared[name + "_crb"][0], np.sqrt(cov[j, j]), rtol=1e-6, err_msg=name)
    np.testing.assert_array_equal(shared["sss_sigma_ps_crb"], shared["direct_sigma_ps_crb"])
    indep = cramer_rao_bound(p, 0.01, n_bins=L, time_bin_ps=T)
    assert shared["sss_delay_ps_crb"][0] < indep["sss_delay_ps_crb"][0]
