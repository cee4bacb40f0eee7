"""decompose(): recovery of the paper's Fig. 3 kinds, input validation, scale/dtype invariance."""
import warnings

import numpy as np
import pytest

from decomposition import EMPTY, NONFINITE, POOR_FIT, SATURATED, decompose
from decomposition.model.fidelity import fidelity
from core.model import empty_params, render_components, render_profile
from decomposition.evaluation.synthetic import make_profiles

T = 2.0


def _one_pixel(direct=(200.3, 1.0, 3.0), sss=(205.0, 0.03, 0.02, 3.0), irs=(), L=256):
    p = empty_params((1,), n_ir=len(irs))
    p["direct_delay_ps"][0], p["direct_amplitude"][0], p["direct_sigma_ps"][0] = direct
    if sss is not None:
        (p["sss_delay_ps"][0], p["sss_amplitude"][0], p["sss_alpha_per_ps"][0], p["sss_sigma_ps"][0]) = sss
    for k, (d, a, s) in enumerate(irs):
        p["ir_delay_ps"][0, k], p["ir_amplitude"][0, k], p["ir_sigma_ps"][0, k] = d, a, s
    return p, render_profile(p, L, T)


@pytest.fixture(scope="module")
def noiseless():
    data = make_profiles(24, 256, nsr=0.0, noise="none", seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = decompose(data.noisy, T)
    return data, res


def test_noiseless_fig3_kinds_recovered(noiseless):
    data, res = noiseless
    f = fidelity(data.components, res)
    for kind in ("d+s", "d+s+r2", "d+s+r2+r3"):
        sel = data.kinds == kind
        assert sel.sum() == 8
        assert f[sel].mean() >= 0.98, (kind, f[sel])
    assert f.min() >= 0.9
    # the right set of components: a direct and an sss everywhere, the right number of reflections
    assert np.isfinite(res.params["direct_delay_ps"]).all()
    assert np.isfinite(res.params["sss_delay_ps"]).all()
    n_true = np.isfinite(data.params["ir_delay_ps"]).sum(axis=1)
    n_est = np.isfinite(res.params["ir_delay_ps"]).sum(axis=1)
    np.testing.assert_array_equal(n_est, n_true)
    # delays within one time bin
    assert np.nanmax(np.abs(res.params["direct_delay_ps"] - data.params["direct_delay_ps"])) < T
    assert np.nanmax(np.abs(res.params["sss_delay_ps"] - data.params["sss_delay_ps"])) < T
    R = data.params["ir_delay_ps"].shape[1]
    err = np.abs(res.params["ir_delay_ps"][:, :R] - data.params["ir_delay_ps"])
    assert np.nanmax(err) < T
    assert res.flags.max() == 0


def test_result_shapes_and_residual(noiseless):
    data, res = noiseless
    N, L = data.noisy.shape
    assert res.direct.shape == (N, L) and res.sss.shape == (N, L)
    assert res.interreflections.shape[0] == N and res.interreflections.shape[2] == L
    assert res.params["ir_delay_ps"].shape == (N, res.interreflections.shape[1])
    assert res.flags.shape == (N,) and res.flags.dtype == np.uint16
    total = res.direct + res.sss + res.interreflections.sum(axis=1)
    np.testing.assert_allclose(res.residual, data.noisy - total)
    assert res.info["method"] == "convscd" and res.info["n_sigma"] == 500 and res.info["n_alpha"] == 500
    assert res.info["n_iter"].shape == (N,) and res.info["n_iter"].max() <= res.info["max_iter"]


def test_rendered_components_are_the_model_kernels_of_the_parameters(noiseless):
    """direct, sss and every inter-reflection of the result are core.model's rendering of the
    result's parameters (to 2e-8 of each component's peak: the compiled atoms stop where a
    Gaussian is below exp(-18) of its peak and take erfc as 2 in the sss tail, within 1e-8;
    absent components are zeros)."""
    data, res = noiseless
    L = data.noisy.shape[1]
    ref = render_components(res.params, L, T)
    for key, got in (("direct", res.direct), ("sss", res.sss), ("interreflections", res.interreflections)):
        want = ref[key]
        peak = np.abs(want).max(axis=-1, keepdims=True)
        np.testing.assert_array_less(np.abs(got - want), np.broadcast_to(2e-8 * peak + 1e-300, got.shape))
        assert not got[peak[..., 0] == 0].any()
    assert np.isfinite(res.params["sss_delay_ps"]).sum() > 0 and np.isfinite(res.params["ir_delay_ps"]).sum() > 0


def test_leading_shape_kept():
    _, y = _one_pixel()
    cube = np.broadcast_to(y, (2, 3, y.shape[-1])).copy()
    res = decompose(cube, T)
    assert res.direct.shape == cube.shape and res.flags.shape == (2, 3)
    assert res.params["direct_delay_ps"].shape == (2, 3)
    assert np.allclose(res.params["direct_delay_ps"], 200.3, atol=0.05)


def test_components_without_sss_or_reflections():
    p, y = _one_pixel(sss=None, irs=[(300.0, 0.5, 3.0)])
    res = decompose(y, T, components="d,r")
    assert np.isnan(res.params["sss_delay_ps"]).all() and not res.sss.any()
    assert res.params["ir_delay_ps"][0, 0] == pytest.approx(300.0, abs=0.05)
    res1 = decompose(y, T, components=("d",))
    # without "r": one Gaussian per pixel at most, no inter-reflection slots
    assert res1.interreflections.shape == (1, 0, y.shape[-1])
    assert res1.params["direct_delay_ps"][0] == pytest.approx(200.3, abs=0.5)
    with pytest.raises(ValueError, match="components"):
        decompose(y, T, components="d,x")
    with pytest.raises(ValueError, match="direct"):
        decompose(y, T, components="r")


def test_no_inter_reflection_is_grown_where_none_is_asked():
    # the forward step and the sss swap add Gaussians after the direct; without "r" the labels
    # dropped each one again and flagged the pixel TRUNCATED (178 of 600 such count pixels)
    from decomposition.flags import TRUNCATED
    from decomposition.evaluation.synthetic import make_profiles

    d = make_profiles(120, 256, seed=7, kinds=["d+s"], time_bin_ps=T, ranges="paper", photons_per_pixel=1000.0,
                      background=0.05)
    res = decompose(d.noisy, T, components="d,s")
    assert "grown" not in res.info and "swapped" not in res.info
    assert not np.any(res.flags & TRUNCATED)
    with_r = decompose(d.noisy, T, components="d,s,r")
    assert with_r.info["grown"] + with_r.info["swapped"] > 0       # where they are asked, they run


def test_all_zero_pixel_is_empty_without_warnings():
    _, y = _one_pixel()
    x = np.vstack([np.zeros_like(y[0]), y[0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = decompose(x, T)
    assert res.flags[0] & EMPTY and not res.flags[1] & EMPTY
    assert all(np.isnan(v[0]).all() for v in res.params.values())
    assert not res.direct[0].any() and not res.sss[0].any() and not res.residual[0].any()


@pytest.mark.parametrize("bad", [0.0, -2.0, np.nan, np.inf])
def test_bad_time_bin(bad):
    _, y = _one_pixel()
    with pytest.raises(ValueError, match="time_bin_ps"):
        decompose(y, bad)


def test_bad_rank_dtype_and_length():
    with pytest.raises(ValueError, match="0-d"):
        decompose(np.float64(3.0), T)
    with pytest.raises(ValueError, match="L=20 time bins"):
        decompose(np.ones((3, 20)), T)
    with pytest.raises(ValueError, match="real numeric"):
        decompose(np.ones((2, 64), complex), T)
    with pytest.raises(ValueError, match="method"):
        decompose(np.ones((2, 64)), T, method="magic")


def test_nonfinite_samples_raise_or_are_flagged():
    _, y = _one_pixel()
    x = np.repeat(y, 4, axis=0)
    x[1, 10] = np.nan
    x[3, 0] = np.inf
    with pytest.raises(ValueError, match="2 of 4 pixels"):
        decompose(x, T)
    res = decompose(x, T, nan_policy="omit")
    np.testing.assert_array_equal((res.flags & NONFINITE) > 0, [False, True, False, True])
    assert np.isnan(res.params["direct_delay_ps"][[1, 3]]).all()
    assert np.isfinite(res.params["direct_delay_ps"][[0, 2]]).all()
    assert not res.direct[[1, 3]].any()


def test_scale_invariance_1e_minus30_to_1e30():
    _, y = _one_pixel(irs=[(320.0, 0.4, 3.0)])
    rng = np.random.default_rng(0)
    y = y + 0.01 * rng.standard_normal(y.shape)
    ref = decompose(y, T)
    for s in (1e-30, 1e-12, 1e12, 1e30):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            res = decompose(y * s, T)
        for k, v in ref.params.items():
            if k.endswith("amplitude"):
                np.testing.assert_allclose(res.params[k], v * s, rtol=1e-9, equal_nan=True)
            else:
                np.testing.assert_allclose(res.params[k], v, rtol=1e-9, atol=1e-9, equal_nan=True)
        np.testing.assert_array_equal(res.flags, ref.flags)
        np.testing.assert_allclose(res.direct, ref.direct * s, rtol=0, atol=1e-8 * s * np.abs(y).max())


def test_uint16_float32_float64_agree():
    p, y = _one_pixel(irs=[(320.0, 0.4, 3.0)])
    counts = np.round(y * 30000.0)
    r64 = decompose(counts, T)
    r32 = decompose(counts.astype(np.float32), T)
    r16 = decompose(counts.astype(np.uint16), T)
    for r in (r32, r16):
        for k, v in r64.params.items():
            np.testing.assert_allclose(r.params[k], v, rtol=1e-6, atol=1e-6, equal_nan=True)
    assert r16.flags[0] & SATURATED == 0
    assert r64.params["direct_delay_ps"][0] == pytest.approx(200.3, abs=0.1)


def test_saturated_uint16_samples_are_flagged_and_excluded():
    p, y = _one_pixel(sss=(205.0, 0.03, 0.02, 3.0), irs=[(320.0, 0.4, 3.0)])
    counts = np.round(y * 80000.0)                 # the direct peak exceeds the 16-bit range
    sat = np.minimum(counts, 65535).astype(np.uint16)
    assert (sat == 65535).sum() >= 2
    res = decompose(sat, T)
    assert res.flags[0] & SATURATED
    # fitted on the unsaturated samples: the peak height is extrapolated above the clip level
    assert res.params["direct_amplitude"][0] == pytest.approx(80000.0, rel=0.05)
    assert res.params["direct_delay_ps"][0] == pytest.approx(200.3, abs=0.3)


def test_poor_fit_flag_on_unmodelled_offset():
    _, y = _one_pixel()
    rng = np.random.default_rng(1)
    noisy = y + 0.002 * rng.standard_normal(y.shape)
    good = decompose(noisy, T)
    bad = decompose(noisy + np.sin(np.arange(y.shape[-1]) / 3.0) * 0.1, T)
    assert not good.flags[0] & POOR_FIT
    assert bad.flags[0] & POOR_FIT


def test_convscd_beats_gradbm_at_nsr_005():
    data = make_profiles(24, 256, nsr=0.05, noise="white", seed=7)
    f_c = fidelity(data.components, decompose(data.noisy, T, method="convscd")).mean()
    f_g = fidelity(data.components, decompose(data.noisy, T, method="gradbm")).mean()
    assert f_c > f_g
    assert f_c >= 0.9


def test_on_grid_setting_snaps_to_the_reference_grid():
    data = make_profiles(6, 256, nsr=0.0, noise="none", seed=2)
    res = decompose(data.noisy, T, off_grid=False, n_sigma=10, n_alpha=5)
    grid_s = np.linspace(1.0, 10.0, 10)
    grid_a = np.linspace(0.01, 0.05, 5)
    for key in ("direct_delay_ps", "sss_delay_ps", "ir_delay_ps"):
        v = res.params[key][np.isfinite(res.params[key])]
        np.testing.assert_allclose((v - T) / T, np.round((v - T) / T), atol=1e-9)      # integer bins
    for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"):
        v = res.params[key][np.isfinite(res.params[key])]
        assert np.all(np.min(np.abs(v[:, None] - grid_s[None]), axis=1) < 1e-9)
    a = res.params["sss_alpha_per_ps"][np.isfinite(res.params["sss_alpha_per_ps"])]
    assert a.size and np.all(np.min(np.abs(a[:, None] - grid_a[None]), axis=1) < 1e-9)
    assert fidelity(data.components, res).mean() > 0.8


def test_sss_alone_pixels():
    data = make_profiles(8, 256, nsr=0.0, noise="none", seed=4, kinds=("s",))
    for kw in (dict(sss_alone=True), dict(components="s")):
        res = decompose(data.noisy, T, **kw)
        assert fidelity(data.components, res).min() >= 0.98, kw
        assert np.isnan(res.params["direct_delay_ps"]).all()
        np.testing.assert_allclose(res.params["sss_delay_ps"], data.params["sss_delay_ps"], atol=T)


def _function_body_lines(path, name):
    """Lines of a top-level function's body after its docstring (last line - first statement + 1)."""
    import ast
    tree = ast.parse(open(path, encoding="utf-8").read())
    fn = next(node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == name)
    body = fn.body
    if isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    return fn.end_lineno - body[0].lineno + 1, len(ast.get_docstring(fn).splitlines())


def test_decompose_is_a_short_dispatcher_with_a_short_docstring():
    import decomposition.api as api
    body, doc = _function_body_lines(api.__file__, "decompose")
    assert body <= 60, f"decompose() body has {body} lines (at most 60)"
    assert doc <= 60, f"decompose() docstring has {doc} lines (at most 60): options belong on their fields"


def test_decompose_runs_the_declared_stages_in_order(monkeypatch):
    import decomposition.api as api
    ran = []
    traced_stages = tuple(api.Stage(s.name, (lambda call, s=s: (ran.append(s.name), s.run(call))), s.purpose)
                          for s in api.STAGES)
    monkeypatch.setattr(api, "STAGES", traced_stages)
    data = make_profiles(4, 128, nsr=0.01, seed=3).noisy
    res = decompose(data, T, rescue=False)
    assert ran == [s.name for s in traced_stages]
    assert res.params["direct_delay_ps"].shape == (4,)
    assert len({s.name for s in api.STAGES}) == len(api.STAGES)
    assert all(s.purpose and "\n" not in s.purpose for s in api.STAGES)


def test_stage_seconds_times_every_stage_of_the_same_call_as_decompose():
    import time

    import decomposition.api as api
    from drivers.sim.scene import simulated_response

    tailed = simulated_response("tailed")
    for kw in ({}, {"irf": tailed}, {"method": "gradbm"}):
        data = make_profiles(12, 512, nsr=0.02, seed=4, ranges="paper", response=kw.get("irf")).noisy
        want = decompose(data, T, **kw)
        start = time.perf_counter()
        got, seconds = api.stage_seconds(data, T, **kw)
        wall = time.perf_counter() - start
        # the same answer, bit for bit: the same call, its stages timed
        assert set(got.params) == set(want.params)
        for key in want.params:
            assert np.array_equal(got.params[key], want.params[key], equal_nan=True), key
        assert np.array_equal(got.flags, want.flags) and np.array_equal(got.residual, want.residual)
        assert list(seconds) == [s.name for s in api.STAGES]
        assert all(v >= 0.0 for v in seconds.values()) and sum(seconds.values()) <= wall
        # the stages that do the work take the time: detection always, a stage that does not apply ~nothing
        assert seconds["detect"] > 0.05 * wall
        skipped = "forward_steps" if "irf" not in kw else "search"
        assert seconds[skipped] < 0.01 * wall
    with pytest.raises(ValueError, match="method must be"):
        api.stage_seconds(data, T, method="nosuch")
