"""Synthetic ground truth and the paper's three noise types at an exact NSR."""
import numpy as np
import pytest

from core.model import render_profile, time_axis_ps
from decomposition.synthetic import (
    SceneRanges, add_noise, draw_params, make_cube, make_profiles, noise_realisation, parse_kind,
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


def test_photon_noise_refuses_negative_signal():
    with pytest.raises(ValueError, match="non-negative"):
        add_noise(-np.ones((2, 8)), 0.1, "photon", rng=0)


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
