"""Synthetic ground truth and the paper's three noise types at an exact NSR."""
import numpy as np
import pytest

from core.model import render_components, render_profile, time_axis_ps
from decomposition.evaluation.synthetic import (
    SCENE_PRESETS, SceneRanges, add_noise, draw_params, make_cube, make_profiles, noise_realisation, parse_kind,
    regime_variables, render_bin_integrated, scene_ranges,
)


def _nsr(d):
    return np.linalg.norm(d.noisy - d.clean, axis=-1) / np.linalg.norm(d.clean, axis=-1)


@pytest.mark.parametrize("noise", ["white", "pink", "photon"])
def test_same_seed_same_arrays_other_seed_differs(noise):
    a = make_profiles(12, 96, nsr=0.05, noise=noise, seed=7)
    b = make_profiles(12, 96, nsr=0.05, noise=noise, seed=7)
    c = make_profiles(12, 96, nsr=0.05, noise=noise, seed=8)
    np.testing.assert_array_equal(a.noisy, b.noisy)
    for k in a.params:
        np.testing.assert_array_equal(a.params[k], b.params[k])
    np.testing.assert_array_equal(a.kinds, b.kinds)
    assert not np.allclose(a.noisy, c.noisy)


def test_scene_does_not_depend_on_noise_settings():
    a = make_profiles(9, 96, nsr=0.01, noise="white", seed=3)
    b = make_profiles(9, 96, nsr=0.2, noise="photon", seed=3)
    np.testing.assert_array_equal(a.clean, b.clean)


@pytest.mark.parametrize("noise", ["white", "pink", "photon"])
@pytest.mark.parametrize("nsr", [0.001, 0.055, 0.2])
def test_nsr_is_exact_per_pixel(noise, nsr):
    d = make_profiles(30, 128, nsr=nsr, noise=noise, seed=1)
    np.testing.assert_allclose(_nsr(d), nsr, rtol=1e-10)


def test_per_pixel_nsr_array_and_zero_profiles():
    clean = np.zeros((3, 64))
    clean[1] = np.hanning(64)
    clean[2] = 5 * np.hanning(64)
    n = noise_realisation(clean, np.array([0.1, 0.02, 0.3]), "white", rng=0)
    assert np.all(n[0] == 0)  # NSR undefined for an empty profile: no noise invented
    got = np.linalg.norm(n[1:], axis=-1) / np.linalg.norm(clean[1:], axis=-1)
    np.testing.assert_allclose(got, [0.02, 0.3], rtol=1e-12)


def test_pink_noise_spectrum_falls_as_one_over_f():
    n = noise_realisation(np.ones((16, 2**14)), 0.1, "pink", rng=2)
    power = np.mean(np.abs(np.fft.rfft(n, axis=-1)) ** 2, axis=0)
    f = np.fft.rfftfreq(n.shape[-1])
    sel = (f > 1e-3) & (f < 0.4)
    slope = np.polyfit(np.log(f[sel]), np.log(power[sel]), 1)[0]
    assert slope == pytest.approx(-1.0, abs=0.05)
    # White noise, for contrast, is flat.
    w = noise_realisation(np.ones((16, 2**14)), 0.1, "white", rng=2)
    pw = np.mean(np.abs(np.fft.rfft(w, axis=-1)) ** 2, axis=0)
    assert abs(np.polyfit(np.log(f[sel]), np.log(pw[sel]), 1)[0]) < 0.05


def test_photon_noise_variance_proportional_to_signal():
    # A long ramp, so that the exact-NSR rescaling (one factor per profile) barely disturbs
    # the per-bin statistics.
    clean = np.linspace(0.0, 1.0, 256)
    profiles = np.broadcast_to(clean, (4000, 256))
    n = noise_realisation(profiles, 0.05, "photon", rng=4)
    var = n.var(axis=0)
    assert var[0] == 0.0  # no signal, no shot noise
    # Variance per unit signal, averaged over 8 groups of bins from dim to bright: constant.
    ratio = (var[1:] / clean[1:])[:248].reshape(8, 31).mean(axis=1)
    np.testing.assert_allclose(ratio, ratio.mean(), rtol=0.05)
    # Expected lambda: sum(p) / (nsr^2 ||p||^2), so var = p / lambda.
    lam = clean.sum() / (0.05**2 * np.sum(clean**2))
    assert ratio.mean() == pytest.approx(1 / lam, rel=0.05)
    # White noise, for contrast, has the same variance in dim and bright bins.
    w = noise_realisation(profiles, 0.05, "white", rng=4).var(axis=0)
    assert w[:32].mean() == pytest.approx(w[-32:].mean(), rel=0.05)


def test_camera_noise_has_one_photon_scale_for_every_pixel():
    # pixels of one shape at brightness 1, 4 and 16: one photon scale means the noise variance
    # follows each sample's signal with one slope, so the NSR halves with every 4x brightness
    shape = np.hanning(128)
    clean = np.concatenate([np.broadcast_to(b * shape, (2000, 128)) for b in (1.0, 4.0, 16.0)])
    n = noise_realisation(clean, 0.05, "camera", rng=5)
    # the NSR of all the profiles together is the one asked for, exactly
    assert np.linalg.norm(n) / np.linalg.norm(clean) == pytest.approx(0.05, rel=1e-12)
    nsr = (np.linalg.norm(n, axis=1) / np.linalg.norm(clean, axis=1)).reshape(3, -1).mean(axis=1)
    np.testing.assert_allclose(nsr[:2] / nsr[1:], 2.0, rtol=0.03)
    # variance per unit signal: the same for every brightness (Poisson at one scale)
    var = n.reshape(3, 2000, 128).var(axis=1)
    mid = slice(32, 96)
    slope = (var[:, mid] / clean.reshape(3, 2000, 128)[:, 0, mid]).mean(axis=1)
    np.testing.assert_allclose(slope, slope.mean(), rtol=0.05)
    # per-pixel NSR values are refused: the camera has one NSR for all its profiles
    with pytest.raises(ValueError, match="one NSR"):
        noise_realisation(clean[:2], np.array([0.05, 0.1]), "camera", rng=0)
    with pytest.raises(ValueError, match="non-negative"):
        add_noise(-np.ones((2, 8)), 0.1, "camera", rng=0)
    d = make_profiles(20, 128, nsr=0.05, noise="camera", seed=3)
    assert d.noise == "camera" and np.linalg.norm(d.noisy - d.clean) / np.linalg.norm(d.clean) == pytest.approx(0.05)


def test_photon_noise_refuses_negative_signal():
    with pytest.raises(ValueError, match="non-negative"):
        add_noise(-np.ones((2, 8)), 0.1, "photon", rng=0)
    with pytest.raises(ValueError, match="non-negative"):
        add_noise(np.array([[1.0, 0.5, -1e-6, 0.0]]), 0.1, "photon", rng=0)


def test_photon_noise_reads_rounding_level_negatives_as_no_light():
    # a profile rendered through a response by FFT convolution holds -4e-16 where it is 0
    clean = np.array([[0.0, 1.0, 0.5, 0.2, 0.0, 0.0]] * 3)
    rounded = clean.copy()
    rounded[:, [0, 4, 5]] = -4e-16
    np.testing.assert_array_equal(noise_realisation(rounded, 0.1, "photon", rng=5),
                                  noise_realisation(clean, 0.1, "photon", rng=5))


def test_noise_aliases_and_bad_input():
    c = np.hanning(32)[None]
    np.testing.assert_array_equal(noise_realisation(c, 0.1, "fluctuation", rng=1),
                                  noise_realisation(c, 0.1, "white", rng=1))
    with pytest.raises(ValueError, match="unknown noise type"):
        noise_realisation(c, 0.1, "brown")
    with pytest.raises(ValueError, match="nsr"):
        noise_realisation(c, -0.1, "white")
    with pytest.raises(ValueError, match="NaN"):
        noise_realisation(np.full((1, 8), np.nan), 0.1, "white")


def test_fig3_kinds_and_arbitrary_subsets():
    assert parse_kind("a") == (True, True, 0)
    assert parse_kind("b") == (True, True, 1)
    assert parse_kind("c") == (True, True, 2)
    assert parse_kind("d+r2+r3+r4") == (True, False, 3)
    assert parse_kind(("s",)) == (False, True, 0)
    with pytest.raises(ValueError, match="r2, r3"):
        parse_kind("d+r3")
    with pytest.raises(ValueError, match="unknown component"):
        parse_kind("d+x")


def test_parameters_are_plausible_and_ordered():
    d = make_profiles(300, 256, seed=5, kinds="a,b,c,d+r2+r3+r4")
    p, t = d.params, time_axis_ps(256)
    labels, counts = np.unique(d.kinds, return_counts=True)
    assert set(labels) == {"d+s", "d+s+r2", "d+s+r2+r3", "d+r2+r3+r4"}
    assert np.all(counts == 75)  # equal shares
    sig = p["direct_sigma_ps"]
    assert np.all((sig >= 2) & (sig <= 6))
    has_s = np.isfinite(p["sss_delay_ps"])
    assert np.all((p["sss_alpha_per_ps"][has_s] >= 0.01) & (p["sss_alpha_per_ps"][has_s] <= 0.05))
    assert np.all(p["sss_delay_ps"][has_s] >= p["direct_delay_ps"][has_s])
    # Direct first, then inter-reflections in order, at least 6 sigma apart, inside the window.
    chain = np.concatenate([p["direct_delay_ps"][:, None], p["ir_delay_ps"]], axis=1)
    gaps = np.diff(chain, axis=1)
    ok = np.isfinite(gaps)
    assert np.all(gaps[ok] >= 6 * np.broadcast_to(sig[:, None], gaps.shape)[ok] - 1e-9)
    fin = np.isfinite(chain)
    edge = 4 * np.broadcast_to(sig[:, None], chain.shape)
    assert np.all(chain[fin] >= t[0] + edge[fin] - 1e-9) and np.all(chain[fin] <= t[-1] - edge[fin] + 1e-9)
    # Number of inter-reflections matches each pixel's kind; kind 'a' pixels have none.
    n_ir = np.isfinite(p["ir_delay_ps"]).sum(axis=1)
    expect = np.array([k.count("r") for k in d.kinds])
    np.testing.assert_array_equal(n_ir, expect)
    # The components add up to the clean profile, rendered by the model.
    np.testing.assert_allclose(d.clean, render_profile(p, 256), atol=1e-12)
    # sss peak is the documented fraction of the direct peak.
    rel = d.components["sss"][has_s].max(axis=1) / p["direct_amplitude"][has_s]
    assert np.all((rel > 0.19) & (rel < 0.51))


def test_window_too_short_is_a_clear_error():
    with pytest.raises(ValueError, match="too short"):
        draw_params(4, 32, kinds="c", rng=0)
    # Narrower ranges make it fit.
    p, _ = draw_params(4, 32, kinds="c", rng=0, ranges=SceneRanges(sigma_ps=(1.0, 1.0)))
    assert np.isfinite(p["ir_delay_ps"]).all()


def test_make_cube_shapes():
    c = make_cube(3, 4, 128, nsr=0.02, noise="pink", seed=0)
    assert c.noisy.shape == (3, 4, 128)
    assert c.params["direct_delay_ps"].shape == (3, 4)
    assert c.params["ir_delay_ps"].shape == (3, 4, 2)
    assert c.components["interreflections"].shape == (3, 4, 2, 128)
    np.testing.assert_allclose(_nsr(c), 0.02, rtol=1e-10)
    flat = make_profiles(12, 128, nsr=0.02, noise="pink", seed=0)
    np.testing.assert_array_equal(c.noisy.reshape(12, 128), flat.noisy)


# --------------------------------------------------------------------------- presets, regimes, bin-integrated rendering

def test_paper_preset_draws_inside_its_ranges():
    r = SCENE_PRESETS["paper"]
    assert r.sigma_ps == (1.0, 10.0) and r.sss_relative_peak == (0.05, 3.0) and r.ir_relative_peak == (0.01, 1.0)
    assert r.sss_onset_sigma == (0.0, 3.0) and r.min_gap_sigma == 4.0
    for T in (1.0, 4.0):
        d = make_profiles(400, 512, seed=2, time_bin_ps=T, ranges="paper", kinds="a,b,c,d+r2+r3+r4")
        p, t = d.params, time_axis_ps(512, T)
        sig = p["direct_sigma_ps"]
        assert np.all((sig >= 1) & (sig <= 10))
        assert sig.max() > 9 and sig.min() < 2  # the whole range is visited
        has_s = np.isfinite(p["sss_delay_ps"])
        a = p["sss_alpha_per_ps"][has_s]
        assert np.all((a >= 0.01) & (a <= 0.05))
        onset = (p["sss_delay_ps"] - p["direct_delay_ps"])[has_s] / sig[has_s]
        assert np.all((onset >= 0) & (onset <= 3)) and onset.min() < 0.3 and onset.max() > 2.7
        # sss peak relative to the direct's, measured on a dense (0.25 ps) rendering of 150 pixels.
        sub = {k: v[has_s][:150] for k, v in p.items()}
        dense = render_components(sub, int(512 * T * 4), 0.25, t0_ps=T)["sss"]
        rel_s = dense.max(axis=1) / sub["direct_amplitude"]
        assert np.all((rel_s > 0.05 * 0.98) & (rel_s < 3.0 * 1.001)) and rel_s.max() > 2 and rel_s.min() < 0.1
        on = np.isfinite(p["ir_amplitude"])
        rel_r = (p["ir_amplitude"] / p["direct_amplitude"][:, None])[on]
        assert np.all((rel_r >= 0.01) & (rel_r <= 1.0)) and rel_r.min() < 0.03
        # Consecutive Gaussian components 4-16 sigma apart, all inside the window.
        chain = np.concatenate([p["direct_delay_ps"][:, None], p["ir_delay_ps"]], axis=1)
        gaps = np.diff(chain, axis=1) / sig[:, None]
        ok = np.isfinite(gaps)
        assert np.all(gaps[ok] >= 4 - 1e-9) and np.all(gaps[ok] <= 16 + 1e-9)
        fin = np.isfinite(chain)
        edge = 4 * np.broadcast_to(sig[:, None], chain.shape)
        assert np.all(chain[fin] >= t[0] + edge[fin] - 1e-9) and np.all(chain[fin] <= t[-1] - edge[fin] + 1e-9)


def test_legacy_preset_is_the_default_generator():
    assert SCENE_PRESETS["legacy"] == SceneRanges()
    a = make_profiles(50, 256, nsr=0.01, seed=4)
    b = make_profiles(50, 256, nsr=0.01, seed=4, ranges="legacy")
    np.testing.assert_array_equal(a.noisy, b.noisy)
    assert scene_ranges("paper") is SCENE_PRESETS["paper"] and scene_ranges(None) == SceneRanges()
    with pytest.raises(ValueError, match="unknown scene preset"):
        scene_ranges("nosuch")
    with pytest.raises(ValueError, match="log-uniformly"):
        SceneRanges(sss_onset_sigma=(0.0, 1.0), log_uniform=("sss_onset_sigma",))
    with pytest.raises(ValueError, match="max_gap_sigma"):
        SceneRanges(min_gap_sigma=6.0, max_gap_sigma=5.0)


def test_regime_variables_follow_the_parameters():
    d = make_profiles(90, 512, seed=3, time_bin_ps=4.0, ranges="paper")
    r, p = d.regimes, d.params
    np.testing.assert_allclose(r["sigma_bins"], p["direct_sigma_ps"] / 4.0)
    np.testing.assert_allclose(r["onset_sigma"], (p["sss_delay_ps"] - p["direct_delay_ps"]) / p["direct_sigma_ps"])
    np.testing.assert_array_equal(r["n_ir"], [k.count("r") for k in d.kinds])
    rel = p["ir_amplitude"] / p["direct_amplitude"][:, None]
    has = r["n_ir"] > 0
    np.testing.assert_allclose(r["ir_min_peak_ratio"][has], np.nanmin(rel[has], axis=1))
    assert np.isnan(r["ir_min_peak_ratio"][~has]).all()
    # The sss peak ratio is that of the rendered components (dense rendering, 0.1 ps).
    dense = make_profiles(90, 512 * 40, seed=3, time_bin_ps=0.1, t0_ps=4.0, ranges="paper", kinds="a")
    rd = dense.regimes
    peak = dense.components["sss"].max(axis=1) / dense.components["direct"].max(axis=1)
    np.testing.assert_allclose(rd["sss_peak_ratio"], peak, rtol=2e-3)
    q = regime_variables({**p, "sss_delay_ps": np.full(90, np.nan)}, 4.0)
    assert np.isnan(q["sss_peak_ratio"]).all() and np.isnan(q["onset_sigma"]).all()


@pytest.mark.parametrize("T", [1.0, 4.0])
def test_bin_integrated_rendering_is_the_bin_mean_of_the_model(T):
    params = {"direct_delay_ps": np.array([40.0, 61.3]), "direct_amplitude": np.array([1.0, 0.7]),
              "direct_sigma_ps": np.array([1.0, 6.0]),
              "sss_delay_ps": np.array([40.5, 70.0]), "sss_amplitude": np.array([0.2, 0.05]),
              "sss_alpha_per_ps": np.array([0.05, 0.01]), "sss_sigma_ps": np.array([1.0, 6.0]),
              "ir_delay_ps": np.array([[90.2, np.nan], [150.0, 230.7]]), "ir_amplitude": np.array([[0.3, np.nan],
                                                                                                  [0.01, 1.0]]),
              "ir_sigma_ps": np.array([[1.0, np.nan], [6.0, 6.0]])}
    n = 400 // int(T)
    got = render_bin_integrated(params, n, T)
    # Dense midpoint rule over each bin of the point-sampled model.
    k = 2000
    fine = render_components(params, n * k, T / k, t0_ps=T - T / 2 + T / (2 * k))
    for key in ("direct", "sss", "interreflections"):
        ref = fine[key].reshape(fine[key].shape[:-1] + (n, k)).mean(axis=-1)
        np.testing.assert_allclose(got[key], ref, rtol=0, atol=2e-7)
        assert got[key].min() >= 0
    # Absent components render as zeros; the sss tail keeps full relative precision late in the window.
    assert np.all(got["interreflections"][0, 1] == 0)
    late = got["sss"][1, -5:]
    ref = fine["sss"][1].reshape(n, k).mean(axis=-1)[-5:]
    np.testing.assert_allclose(late, ref, rtol=1e-5)
    # make_profiles renders with it and says so.
    d = make_profiles(5, 256, seed=0, time_bin_ps=T, ranges="paper", bin_integrated=True)
    np.testing.assert_allclose(d.clean, sum_components(render_bin_integrated(d.params, 256, T)), atol=1e-12)
    assert d.bin_integrated


def sum_components(c):
    return c["direct"] + c["sss"] + c["interreflections"].sum(axis=-2)
