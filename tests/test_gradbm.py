"""GradBM baseline: recovery of clean components, family selection, batching and bad input."""
import warnings

import numpy as np
import pytest

from decomposition.methods.gradbm import gradbm
from decomposition.model.fidelity import fidelity
from core.model import render_components, render_profile
from decomposition.evaluation.synthetic import make_profiles

L = 192


def test_isolated_direct_reflection_recovered():
    p = {"direct_delay_ps": np.array([60.3, 100.0, 33.7]), "direct_amplitude": np.array([1.0, 2.0, 0.5]),
         "direct_sigma_ps": np.array([3.0, 5.0, 2.0])}
    est = gradbm(render_profile(p, 128))
    assert np.all(np.abs(est["direct_delay_ps"] - p["direct_delay_ps"]) < 2.0)  # within one bin
    np.testing.assert_allclose(est["direct_delay_ps"], p["direct_delay_ps"], atol=0.05)
    np.testing.assert_allclose(est["direct_amplitude"], p["direct_amplitude"], rtol=0.01)
    np.testing.assert_allclose(est["direct_sigma_ps"], p["direct_sigma_ps"], rtol=0.02)
    assert np.all(np.isnan(est["sss_delay_ps"])) and np.all(np.isnan(est["ir_delay_ps"]))


def test_direct_plus_sss_parameters_reasonable():
    d = make_profiles(40, L, kinds="a", seed=11)
    est = gradbm(d.clean)
    t, e = d.params, est
    assert np.all(np.abs(e["direct_delay_ps"] - t["direct_delay_ps"]) < 2.0)
    assert np.all(np.isfinite(e["sss_delay_ps"]))
    assert np.median(np.abs(e["direct_amplitude"] / t["direct_amplitude"] - 1)) < 0.15
    assert np.median(np.abs(e["sss_alpha_per_ps"] / t["sss_alpha_per_ps"] - 1)) < 0.25
    assert np.median(np.abs(e["sss_delay_ps"] - t["sss_delay_ps"])) < 2 * np.median(t["sss_sigma_ps"])
    assert np.all(np.isnan(e["ir_delay_ps"]))  # no spurious inter-reflections on clean data
    f = fidelity(d.components, render_components(e, L))
    assert np.mean(f) > 0.75


def test_interreflections_found_in_order():
    d = make_profiles(40, L, kinds="b,c", seed=12)
    est = gradbm(d.clean)
    n_true = np.isfinite(d.params["ir_delay_ps"]).sum(axis=1)
    n_est = np.isfinite(est["ir_delay_ps"]).sum(axis=1)
    assert np.mean(n_est == n_true) >= 0.95
    both = np.isfinite(est["ir_delay_ps"][:, :2]) & np.isfinite(d.params["ir_delay_ps"])
    err = np.abs(est["ir_delay_ps"][:, :2] - d.params["ir_delay_ps"])[both]
    # An inter-reflection riding on the sss hump can be pulled off (the baseline's known
    # weakness); most land within one bin.
    assert np.median(err) < 1.0 and np.mean(err < 2.0) >= 0.85
    dl = np.diff(est["ir_delay_ps"], axis=1)
    assert np.all(dl[np.isfinite(dl)] > 0)


def test_component_families_can_be_left_out():
    d = make_profiles(12, L, kinds="c", seed=3)
    only_d = gradbm(d.clean, components=("d",))
    assert np.all(np.isfinite(only_d["direct_delay_ps"]))
    assert np.all(np.isnan(only_d["sss_delay_ps"])) and only_d["ir_delay_ps"].shape == (12, 0)
    no_s = gradbm(d.clean, components="d,r", max_interreflections=2)
    assert np.all(np.isnan(no_s["sss_delay_ps"])) and no_s["ir_delay_ps"].shape == (12, 2)


def test_batch_equals_pixel_by_pixel():
    d = make_profiles(9, L, nsr=0.03, noise="pink", seed=4)
    whole = gradbm(d.noisy)
    for i in range(9):
        one = gradbm(d.noisy[i:i + 1])
        for k in whole:
            np.testing.assert_allclose(one[k][0], whole[k][i], rtol=1e-9, atol=1e-12, equal_nan=True)


def test_empty_and_flat_pixels_give_empty_decomposition_without_warnings():
    y = np.zeros((3, 64))
    y[1] = 0.5  # flat: no rising edge
    y[2] = -np.hanning(64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        est = gradbm(y)
    for k, v in est.items():
        assert np.all(np.isnan(v)), k


def test_noise_makes_the_baseline_worse():
    f = []
    for nsr in (0.0, 0.1):
        d = make_profiles(60, L, nsr=nsr, noise="white", seed=5)
        f.append(np.mean(fidelity(d.components, render_components(gradbm(d.noisy), L))))
    assert f[0] > 0.8 and f[1] < f[0] - 0.1


def test_bad_arguments():
    y = np.zeros((2, 64))
    with pytest.raises(TypeError, match="unknown option"):
        gradbm(y, edge_fractoin=0.2)
    with pytest.raises(ValueError, match=r"\(N, L\)"):
        gradbm(np.zeros(64))
    with pytest.raises(ValueError, match="component family"):
        gradbm(y, components=("d", "x"))


def test_time_axis_is_respected():
    # 1 ps bins starting at 500 ps; positional and keyword time axis agree.
    p = {"direct_delay_ps": np.array([560.4]), "direct_amplitude": np.array([1.0]),
         "direct_sigma_ps": np.array([2.5])}
    from core.model import render_profile as rp
    y = rp(p, 200, time_bin_ps=1.0, t0_ps=500.0)
    a = gradbm(y, 1.0, 500.0)
    b = gradbm(y, time_bin_ps=1.0, t0_ps=500.0)
    assert a["direct_delay_ps"][0] == pytest.approx(560.4, abs=0.05)
    assert a["direct_sigma_ps"][0] == pytest.approx(2.5, rel=0.02)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


@pytest.mark.parametrize("scale", [1e-30, 1e30])
def test_scaling_the_profile_scales_only_the_amplitudes(scale):
    d = make_profiles(12, L, nsr=0.02, noise="white", seed=8)
    a, b = gradbm(d.noisy), gradbm(d.noisy * scale)
    for k in a:
        expect = a[k] * scale if k.endswith("amplitude") else a[k]
        np.testing.assert_allclose(b[k], expect, rtol=1e-6, equal_nan=True, err_msg=k)
