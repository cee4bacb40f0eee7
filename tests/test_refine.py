"""Off-grid refinement: analytic kernel derivatives, exact recovery, never-worse, masks, extremes."""
import warnings

import numpy as np
import pytest

from core.model import empty_params, gaussian_kernel, render_profile, sss_kernel
from decomposition.kernels.derivatives import kernel_derivatives
from decomposition.model.refine import refine

T = 2.0


def _fd(fun, x, h):
    return (fun(x + h) - fun(x - h)) / (2 * h)


@pytest.mark.parametrize("sigma,alpha", [(3.0, 0.03), (0.5, 2.0), (10.0, 0.01), (1.0, 100.0), (4.0, 1e-4),
                                         (20.0, 5.0), (0.5, 2e-6)])
@pytest.mark.parametrize("binned", [False, True])
def test_sss_derivatives_match_finite_differences(sigma, alpha, binned):
    tb = T if binned else None
    t = np.linspace(-8 * sigma - 20, 200.0, 301)
    k, d_delay, d_sigma, d_alpha = kernel_derivatives(t, sigma, alpha, time_bin_ps=tb)
    np.testing.assert_allclose(k, sss_kernel(t, sigma, alpha, time_bin_ps=tb), rtol=1e-12, atol=1e-300)
    fd_delay = _fd(lambda d: kernel_derivatives(t - d, sigma, alpha, time_bin_ps=tb)[0], 0.0, 1e-6 * sigma)
    fd_sigma = _fd(lambda s: kernel_derivatives(t, s, alpha, time_bin_ps=tb)[0], sigma, 1e-6 * sigma)
    fd_alpha = _fd(lambda a: kernel_derivatives(t, sigma, a, time_bin_ps=tb)[0], alpha, 1e-6 * alpha)
    for got, ref in ((d_delay, fd_delay), (d_sigma, fd_sigma), (d_alpha, fd_alpha)):
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6 * np.max(np.abs(ref)) + 1e-12)


@pytest.mark.parametrize("sigma", [0.5, 3.0, 40.0])
def test_gaussian_derivatives_match_finite_differences(sigma):
    t = np.linspace(-6 * sigma, 6 * sigma, 101)
    k, d_delay, d_sigma = kernel_derivatives(t, sigma)
    np.testing.assert_allclose(k, gaussian_kernel(t, sigma), rtol=1e-14)
    fd_delay = _fd(lambda d: gaussian_kernel(t - d, sigma), 0.0, 1e-6 * sigma)
    fd_sigma = _fd(lambda s: gaussian_kernel(t, s), sigma, 1e-6 * sigma)
    np.testing.assert_allclose(d_delay, fd_delay, atol=1e-7 * np.abs(fd_delay).max())
    np.testing.assert_allclose(d_sigma, fd_sigma, atol=1e-7 * np.abs(fd_sigma).max())


def _scene(n, n_ir, rng):
    p = empty_params((n,), n_ir)
    p["direct_delay_ps"][:] = rng.uniform(60, 90, n)
    p["direct_amplitude"][:] = rng.uniform(0.5, 2.0, n)
    p["direct_sigma_ps"][:] = rng.uniform(2.0, 4.0, n)
    p["sss_delay_ps"][:] = p["direct_delay_ps"] + rng.uniform(5, 15, n)
    p["sss_amplitude"][:] = rng.uniform(0.05, 0.1, n) * p["direct_amplitude"]
    p["sss_alpha_per_ps"][:] = rng.uniform(0.01, 0.05, n)
    p["sss_sigma_ps"][:] = p["direct_sigma_ps"]
    for r in range(n_ir):
        p["ir_delay_ps"][:, r] = p["direct_delay_ps"] + 40.0 * (r + 1) + rng.uniform(-5, 5, n)
        p["ir_amplitude"][:, r] = rng.uniform(0.2, 0.5, n) * p["direct_amplitude"]
        p["ir_sigma_ps"][:, r] = p["direct_sigma_ps"]
    return p


def _perturb(p, rng, grid_ps=1.0):
    q = {k: v.copy() for k, v in p.items()}
    for key in ("direct_delay_ps", "sss_delay_ps", "ir_delay_ps"):
        q[key] = q[key] + rng.uniform(-grid_ps, grid_ps, q[key].shape)
    for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps", "sss_alpha_per_ps"):
        q[key] = q[key] * rng.uniform(0.9, 1.1, q[key].shape)
    for key in ("direct_amplitude", "sss_amplitude", "ir_amplitude"):
        q[key] = q[key] * rng.uniform(0.8, 1.2, q[key].shape)
    return q


def test_noiseless_off_grid_start_recovers_truth_exactly():
    rng = np.random.default_rng(3)
    p = _scene(40, 2, rng)
    y = render_profile(p, 200, T)
    q = _perturb(p, rng)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r, info = refine(y, q, time_bin_ps=T, max_iter=60)
    assert info["refined"].all() and info["converged"].all()
    for key in p:
        np.testing.assert_allclose(r[key], p[key], rtol=1e-5, atol=1e-6, err_msg=key)
    assert np.all(info["rss"] < 1e-12 * np.sum(y * y, axis=-1))


def test_never_worse_and_exact_input_kept():
    rng = np.random.default_rng(4)
    p = _scene(30, 1, rng)
    clean = render_profile(p, 160, T)
    noisy = clean + 0.05 * rng.standard_normal(clean.shape) * np.linalg.norm(clean, axis=-1, keepdims=True) / np.sqrt(160)
    # Truth on noiseless data: nothing can beat zero residual, so the input comes back bit for bit.
    r, info = refine(clean, p, time_bin_ps=T)
    assert not info["refined"].any()
    for key in p:
        np.testing.assert_array_equal(r[key], p[key])
    # Noisy data from an off-grid start: residual never grows; rejected pixels keep their input exactly.
    q = _perturb(p, rng, grid_ps=3.0)
    r, info = refine(noisy, q, time_bin_ps=T, max_iter=3)
    assert np.all(info["rss"] <= info["rss_input"])
    resid = noisy - render_profile(r, 160, T)
    np.testing.assert_allclose(np.sum(resid**2, -1), info["rss"], rtol=1e-8)
    r2, info2 = refine(noisy, r, time_bin_ps=T)  # refining a refined fit: still never worse
    assert np.all(info2["rss"] <= info2["rss_input"])
    keep = ~info2["refined"]
    for key in p:
        np.testing.assert_array_equal(r2[key][keep], r[key][keep])


def test_mixed_component_sets_in_one_block_keep_their_sets():
    rng = np.random.default_rng(5)
    p = _scene(8, 2, rng)
    p["sss_delay_ps"][0:2] = np.nan          # direct (+ir) only
    p["ir_delay_ps"][2:4, :] = np.nan        # d + s
    p["ir_delay_ps"][4, 1] = np.nan          # d + s + r2
    for key in p:                            # pixel 7: nothing at all
        p[key][7] = np.nan
    for key in ("sss_amplitude", "sss_alpha_per_ps", "sss_sigma_ps"):
        p[key][np.isnan(p["sss_delay_ps"])] = np.nan
    for key in ("ir_amplitude", "ir_sigma_ps"):
        p[key][np.isnan(p["ir_delay_ps"])] = np.nan
    y = render_profile(p, 220, T)
    y[7] = 0.0
    q = _perturb(p, rng)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r, info = refine(y, q, time_bin_ps=T, max_iter=60)
    for key in p:
        np.testing.assert_array_equal(np.isnan(r[key]), np.isnan(p[key]), err_msg=key)
        np.testing.assert_allclose(r[key], p[key], rtol=1e-5, atol=1e-6, err_msg=key)
    assert info["converged"][7] and not info["refined"][7] and info["iterations"][7] == 0


@pytest.mark.parametrize("scale", [1e-30, 1e-8, 1e30])
def test_scale_changes_amplitudes_only(scale):
    rng = np.random.default_rng(6)
    p = _scene(6, 1, rng)
    clean = render_profile(p, 180, T)
    y = clean + 0.02 * rng.standard_normal(clean.shape) * clean.max()
    q = _perturb(p, rng)
    r1, _ = refine(y, q, time_bin_ps=T)
    qs = dict(q)
    for key in ("direct_amplitude", "sss_amplitude", "ir_amplitude"):
        qs[key] = q[key] * scale
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rs, info = refine(y * scale, qs, time_bin_ps=T)
    for key in p:
        want = r1[key] * scale if key.endswith("amplitude") else r1[key]
        np.testing.assert_allclose(rs[key], want, rtol=1e-7, err_msg=key)


def test_stiff_sss_alpha_sigma_range_is_warning_free():
    # alpha * sigma from 1e-6 to 100, sigma from a quarter bin to 20 bins.
    sig = np.array([0.5, 3.0, 10.0, 40.0, 2.0, 1.0])
    alpha = np.array([2e-6, 1e-3, 0.05, 2.5, 5.0, 100.0])
    n = sig.size
    p = empty_params((n,), 0)
    p["direct_delay_ps"][:] = 100.0
    p["direct_amplitude"][:] = 1.0
    p["direct_sigma_ps"][:] = sig
    p["sss_delay_ps"][:] = 130.0
    p["sss_amplitude"][:] = 0.5 / sss_kernel(np.linspace(-50, 400, 901), sig[:, None], alpha[:, None]).max(-1)
    p["sss_alpha_per_ps"][:] = alpha
    p["sss_sigma_ps"][:] = sig
    clean = render_profile(p, 256, T)
    rng = np.random.default_rng(7)
    y = clean + 0.01 * rng.standard_normal(clean.shape)
    q = _perturb(p, rng, grid_ps=0.5)
    with warnings.catch_warnings(), np.errstate(all="warn"):
        warnings.simplefilter("error")
        r, info = refine(y, q, time_bin_ps=T, max_iter=40)
    assert np.all(info["rss"] <= info["rss_input"])
    assert np.all(info["iterations"] <= 40)
    for key in ("direct_delay_ps", "direct_amplitude", "sss_delay_ps", "sss_alpha_per_ps"):
        assert np.all(np.isfinite(r[key])), key
    # Every pixel ends at the noise floor (these extremes are too ill-posed to demand the truth back).
    assert np.all(info["rss"] / 256 < (1.5 * 0.01) ** 2)
    well_posed = sig <= 10.0
    np.testing.assert_allclose(r["direct_delay_ps"][well_posed & (sig > 1)], 100.0, atol=0.2)


def test_leading_dimensions_and_bad_input():
    rng = np.random.default_rng(8)
    p = _scene(6, 0, rng)
    y = render_profile(p, 150, T)
    p2 = {k: v.reshape((2, 3) + v.shape[1:]) for k, v in p.items()}
    r, info = refine(y.reshape(2, 3, 150), _perturb(p2, rng), time_bin_ps=T)
    assert r["direct_delay_ps"].shape == (2, 3) and info["iterations"].shape == (2, 3)
    np.testing.assert_allclose(r["direct_delay_ps"], p2["direct_delay_ps"], atol=1e-5)
    bad = y.copy()
    bad[2, 5] = np.nan
    with pytest.raises(ValueError, match="1 pixel"):
        refine(bad, p, time_bin_ps=T)
    with pytest.raises(ValueError, match="shape"):
        refine(y[:4], p, time_bin_ps=T)
    with pytest.raises(ValueError, match="time_bin_ps"):
        refine(y, p, time_bin_ps=0.0)


def test_weights_exclude_saturated_samples():
    rng = np.random.default_rng(9)
    p = _scene(10, 1, rng)
    clean = render_profile(p, 180, T)
    level = 0.7 * clean.max(axis=-1, keepdims=True)
    sat = clean >= level
    y = np.where(sat, level, clean)
    y[sat & (rng.random(y.shape) < 0.5)] = np.nan  # excluded samples may hold anything
    assert sat.any(axis=-1).all()
    w = np.where(sat, 0.0, 1.0)
    q = _perturb(p, rng)
    r, info = refine(y, q, time_bin_ps=T, weights=w, shared_sigma=True, max_iter=60)
    for key in ("direct_delay_ps", "direct_amplitude", "sss_alpha_per_ps", "ir_delay_ps"):
        np.testing.assert_allclose(r[key], p[key], rtol=1e-5, atol=1e-5, err_msg=key)
    with pytest.raises(ValueError, match="weights"):
        refine(clean, q, time_bin_ps=T, weights=-w)


def test_shared_sigma_fits_one_width_per_pixel():
    rng = np.random.default_rng(10)
    p = _scene(12, 2, rng)  # one PSF width per pixel, as the scene generator draws it
    clean = render_profile(p, 220, T)
    y = clean + 0.03 * rng.standard_normal(clean.shape) * clean.max(axis=-1, keepdims=True)
    q = _perturb(p, rng)
    r, info = refine(y, q, time_bin_ps=T, shared_sigma=True)
    np.testing.assert_array_equal(r["direct_sigma_ps"], r["sss_sigma_ps"])
    np.testing.assert_array_equal(r["ir_sigma_ps"], np.repeat(r["direct_sigma_ps"][:, None], 2, axis=1))
    assert np.all(info["rss"] <= info["rss_input"])
    ri, _ = refine(y, q, time_bin_ps=T)
    # One width is the better-posed problem: its direct delays are at least as good on average.
    err_shared = np.sqrt(np.mean((r["direct_delay_ps"] - p["direct_delay_ps"]) ** 2))
    err_indep = np.sqrt(np.mean((ri["direct_delay_ps"] - p["direct_delay_ps"]) ** 2))
    assert err_shared < 1.2 * err_indep


# ---- integration with decompose(): refine=True / stderr=True ------------------------------------

def _synthetic(n, nsr, seed, kinds=("a", "b", "c"), n_bins=256):
    from decomposition.evaluation.synthetic import make_profiles

    return make_profiles(n, n_bins, nsr=nsr, noise="white", seed=seed, kinds=kinds, time_bin_ps=T)


@pytest.mark.timeout(60)
def test_decompose_refine_never_worse_and_adds_standard_errors():
    from decomposition import decompose

    d = _synthetic(18, 0.03, 21)
    base = decompose(d.noisy, T)
    assert not any(k.endswith("_stderr") for k in base.params)
    res = decompose(d.noisy, T, refine=True)
    assert res.info["refine"] and res.info["stderr"] and res.info["refine_iterations"].shape == (18,)
    rss_base = np.sum(base.residual**2, axis=-1)
    rss_ref = np.sum(res.residual**2, axis=-1)
    assert np.all(rss_ref <= rss_base * (1 + 1e-12))
    for key in ("direct_delay_ps", "sss_alpha_per_ps", "ir_delay_ps"):
        se = res.params[key + "_stderr"]
        assert se.shape == res.params[key].shape
        np.testing.assert_array_equal(np.isfinite(se) & np.isfinite(res.params[key]), np.isfinite(se))
    assert np.isfinite(res.params["direct_delay_ps_stderr"]).mean() > 0.8
    only_se = decompose(d.noisy, T, stderr=True)
    assert "direct_delay_ps_stderr" in only_se.params and "refined" not in only_se.info


@pytest.mark.timeout(60)
def test_refine_takes_on_grid_output_off_the_grid():
    from decomposition import decompose

    d = _synthetic(24, 0.01, 22)
    on = decompose(d.noisy, T, off_grid=False, n_sigma=10, n_alpha=10)
    ref = decompose(d.noisy, T, off_grid=False, n_sigma=10, n_alpha=10, refine=True)
    err_on = np.nanmedian(np.abs(on.params["direct_delay_ps"] - d.params["direct_delay_ps"]))
    err_ref = np.nanmedian(np.abs(ref.params["direct_delay_ps"] - d.params["direct_delay_ps"]))
    assert err_on > 0.2  # grid-snapped delays are off by up to half a bin (1 ps) ...
    assert err_ref < 0.25 * err_on  # ... refined ones are not


@pytest.mark.timeout(60)
def test_decompose_standard_errors_match_the_crb_for_isolated_direct_components():
    from decomposition import decompose
    from decomposition.model.fisher import cramer_rao_bound

    d = _synthetic(60, 0.05, 23, kinds="d")
    res = decompose(d.noisy, T, refine=True)
    noise = np.linalg.norm(d.noisy - d.clean, axis=-1) / np.sqrt(d.clean.shape[-1])
    crb = cramer_rao_bound(d.params, noise, n_bins=d.clean.shape[-1], time_bin_ps=T, shared_sigma=True)
    ratio = res.params["direct_delay_ps_stderr"] / crb["direct_delay_ps_crb"]
    assert np.all(np.isfinite(ratio))
    assert 0.85 < np.median(ratio) < 1.15
    err = res.params["direct_delay_ps"] - d.params["direct_delay_ps"]
    assert np.sqrt(np.mean(err**2)) < 1.5 * np.sqrt(np.mean(crb["direct_delay_ps_crb"] ** 2))


def test_decompose_refine_with_saturated_uint16_input():
    from decomposition import decompose

    rng = np.random.default_rng(24)
    p = _scene(6, 1, rng)
    gain = 80000.0 / p["direct_amplitude"][:, None]  # every direct peak 20 % above the 16-bit range
    clean = render_profile(p, 200, T) * gain
    y = np.clip(clean + 300.0 * rng.standard_normal(clean.shape), 0, 65535).astype(np.uint16)
    sat = y == 65535
    assert sat.any(axis=-1).all()
    # additive noise of 300 units, not photon counts: the Gaussian model (integer input would
    # otherwise be taken for counts, whose variance is the model)
    base = decompose(y, T, noise="gaussian")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = decompose(y, T, refine=True, noise="gaussian")
    # Never worse on the samples that are fitted (saturated ones are excluded) ...
    rss = lambda r: np.sum(np.where(sat, 0.0, r.residual) ** 2, axis=-1)  # noqa: E731
    assert np.all(rss(res) <= rss(base) * (1 + 1e-12))
    # ... and still right wherever the sparse step got the direct component right.
    ok = (np.abs(base.params["direct_delay_ps"] - p["direct_delay_ps"]) < 0.5) & (
        np.abs(base.params["direct_amplitude"] / 80000.0 - 1) < 0.05)
    assert ok.sum() >= 2
    np.testing.assert_allclose(res.params["direct_delay_ps"][ok], p["direct_delay_ps"][ok], atol=0.5)
    np.testing.assert_allclose(res.params["direct_amplitude"][ok], 80000.0, rtol=0.05)
    assert np.all(np.isfinite(res.params["direct_delay_ps_stderr"][ok]))


def test_stderr_with_the_onset_constraint_active():
    from decomposition.model.fisher import standard_errors

    p = empty_params((1,), 0)
    p.update(direct_delay_ps=np.array([80.0]), direct_amplitude=np.array([1.0]), direct_sigma_ps=np.array([3.0]),
             sss_delay_ps=np.array([80.0]), sss_amplitude=np.array([0.05]), sss_alpha_per_ps=np.array([0.03]),
             sss_sigma_ps=np.array([3.0]))
    y = render_profile(p, 200, T) + 0.01 * np.random.default_rng(25).standard_normal((1, 200))
    free = standard_errors(y, p, time_bin_ps=T, shared_sigma=True)
    tied = standard_errors(y, p, time_bin_ps=T, shared_sigma=True, sss_after_direct=True)
    assert tied["sss_delay_ps_stderr"][0] == tied["direct_delay_ps_stderr"][0]
    assert np.isfinite(tied["direct_delay_ps_stderr"][0])
    # Without the tie the two delays at one onset are (nearly) indistinguishable.
    assert not (free["direct_delay_ps_stderr"][0] < 2 * tied["direct_delay_ps_stderr"][0])


def test_refinement_keeps_the_labels_in_order_of_delay():
    # Two close Gaussians (r2 weaker, 2 sigma after the direct); starts in valid order but
    # anywhere around them.  Unconstrained least squares swaps the labels for some pixels.
    rng = np.random.default_rng(31)
    n = 200
    p = empty_params((n,), 1)
    p["direct_delay_ps"][:], p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 100.0, 0.6, 3.0
    p["ir_delay_ps"][:, 0], p["ir_amplitude"][:, 0], p["ir_sigma_ps"][:, 0] = 106.0, 1.0, 3.0
    y = render_profile(p, 128, T) + 0.02 * rng.standard_normal((n, 128))
    start = {k: v.copy() for k, v in p.items()}
    start["direct_delay_ps"] = rng.uniform(96.0, 110.0, n)
    start["ir_delay_ps"][:, 0] = start["direct_delay_ps"] + rng.uniform(0.5, 4.0, n)
    r, info = refine(y, start, time_bin_ps=T, shared_sigma=True)
    assert np.all(r["ir_delay_ps"][:, 0] >= r["direct_delay_ps"])
    assert np.all(info["rss"] <= info["rss_input"])
    free, _ = refine(y, start, time_bin_ps=T, shared_sigma=True, keep_order=False)
    assert np.any(free["ir_delay_ps"][:, 0] < free["direct_delay_ps"])


def test_the_ratio_and_onset_priors_of_refine_pull_an_undetermined_split_to_the_prior():
    # a direct and an sss whose split the noisy samples hardly fix: a firm ratio prior puts the
    # sss amplitude at rho x the direct's, a zero weight leaves the fit as it was
    from core import model as _m
    p = _m.empty_params((1,), 0)
    p.update(direct_delay_ps=np.array([40.0]), direct_amplitude=np.array([1.0]), direct_sigma_ps=np.array([4.0]),
             sss_delay_ps=np.array([42.0]), sss_amplitude=np.array([0.05]), sss_sigma_ps=np.array([4.0]),
             sss_alpha_per_ps=np.array([0.05]))
    y = _m.render_profile(p, 128, 2.0) + 0.02 * np.random.default_rng(5).standard_normal((1, 128))
    free, _ = refine(y, p, time_bin_ps=2.0, shared_sigma=True, sss_after_direct=True, ratio_prior=(0.08, 0.0))
    firm, _ = refine(y, p, time_bin_ps=2.0, shared_sigma=True, sss_after_direct=True, ratio_prior=(0.08, 1e6),
                     onset_prior=(5.0, 1e6), alpha_prior=(np.log(0.04), 1e6))
    ratio = firm["sss_amplitude"] / firm["direct_amplitude"]
    assert abs(ratio[0] - 0.08) < 1e-3
    assert abs(firm["sss_delay_ps"][0] - firm["direct_delay_ps"][0] - 5.0) < 1e-2
    assert abs(firm["sss_alpha_per_ps"][0] - 0.04) < 1e-4
    assert abs(free["sss_amplitude"][0] / free["direct_amplitude"][0] - 0.08) > 1e-3
