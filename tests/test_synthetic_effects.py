"""Effects of the synthetic generator: non-Gaussian responses, background, photon counts, weak
late echoes and a direct truncated at the window's start; the defaults untouched."""
import numpy as np
import pytest

from core.irf_models import afterpulse_response, gaussian_response, model_value, tailed_response
from core.model import render_components, time_axis_ps
from decomposition.evaluation.scenes import draw_params
from decomposition.evaluation.synthetic import make_cube, make_profiles, render_bin_integrated
from decomposition.evaluation.synthetic_effects import (SyntheticEffects, bin_averaged_response, count_photons,
                                                       response_sigma_ps)
from decomposition.evaluation.synthetic_noise import add_noise

L, T = 256, 2.0


@pytest.mark.parametrize("noise, bin_integrated", [("white", False), ("photon", True)])
def test_defaults_are_the_paper_model_draw_for_draw(noise, bin_integrated):
    """The default call is the scene draw of stream 0 rendered and noised with stream 1 of the
    seed, and passing every effect at its neutral value changes nothing."""
    d = make_profiles(24, L, nsr=0.05, noise=noise, seed=11, bin_integrated=bin_integrated)
    scene, noise_ss = np.random.SeedSequence(11).spawn(2)
    p, kinds = draw_params(24, L, kinds=("a", "b", "c"), time_bin_ps=T, t0_ps=T, rng=np.random.default_rng(scene))
    comps = (render_bin_integrated if bin_integrated else render_components)(p, L, T, T)
    clean = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    np.testing.assert_array_equal(d.clean, clean)
    np.testing.assert_array_equal(d.noisy, add_noise(clean, 0.05, noise, rng=np.random.default_rng(noise_ss)))
    np.testing.assert_array_equal(d.kinds, kinds)
    n = make_profiles(24, L, nsr=0.05, noise=noise, seed=11, bin_integrated=bin_integrated, response=None,
                      background=0.0, photons_per_pixel=None, echo_ratio=None, direct_before_window_ps=None)
    np.testing.assert_array_equal(n.noisy, d.noisy)
    assert d.response is None and d.photons_per_pixel is None and not d.effects.any
    np.testing.assert_array_equal(d.background, 0.0)


@pytest.mark.parametrize("bin_integrated", [False, True])
def test_a_gaussian_response_renders_the_gaussian_model(bin_integrated):
    irf = gaussian_response(4.0, time_step_ps=T)
    d = make_profiles(40, L, seed=3, response=irf, kinds="d+s+r2", bin_integrated=bin_integrated)
    np.testing.assert_allclose(d.params["direct_sigma_ps"], 4.0, rtol=1e-9)
    ref = (render_bin_integrated if bin_integrated else render_components)(d.params, L, T, T)
    for key in ("direct", "sss", "interreflections"):
        np.testing.assert_allclose(d.components[key], ref[key], atol=1e-8)
    assert d.response is irf


@pytest.mark.parametrize("irf", [tailed_response(3.0, 0.3, 25.0, time_step_ps=T),
                                 afterpulse_response(3.0, 0.1, 30.0, time_step_ps=T)], ids=["tailed", "afterpulse"])
def test_bin_averaged_response_is_the_mean_over_each_bin(irf):
    """Against the closed form of the model averaged over each bin by a dense midpoint rule."""
    box = bin_averaged_response(irf, T)
    t = np.linspace(-20.0, 80.0, 51) + 0.37
    sub = (np.arange(400) + 0.5) / 400 - 0.5
    dense = model_value(irf.model, t[:, None] + T * sub[None, :]).mean(axis=1)
    np.testing.assert_allclose(box.evaluate(t), dense, atol=2e-6 * dense.max())
    assert box.time_step_ps == irf.time_step_ps and abs(box.samples.sum() * T - 1) < 1e-12


def test_photon_counts_are_integers_with_the_requested_mean_and_background():
    irf = tailed_response(4.0, 0.2, 30.0, time_step_ps=T)
    d = make_profiles(3000, L, seed=5, kinds="d+s", response=irf, photons_per_pixel=300.0, background=0.01)
    assert d.noisy.dtype == np.int64 and d.noise == "counts" and d.bin_integrated
    assert d.noisy.min() >= 0
    signal = d.clean - d.background[:, None]
    # Expected signal photons per pixel are the requested level; the truth is in counts.
    np.testing.assert_allclose(signal.sum(axis=1), 300.0, rtol=1e-12)
    np.testing.assert_allclose(d.components["direct"] + d.components["sss"], signal, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(d.background, 0.01 * d.counts_per_unit)
    # Counts: mean and variance equal to the expected counts (Poisson), to their sampling error.
    total = d.noisy.sum(axis=1)
    expected = d.clean.sum(axis=1)
    z = (total - expected).sum() / np.sqrt(expected.sum())
    assert abs(z) < 4
    np.testing.assert_allclose(np.var(total - expected), expected.mean(), rtol=0.1)
    # Far from any light (the first bins, the direct at >= 4 sigma) only the background is counted.
    early = d.noisy[:, :4].astype(float).mean(axis=1)
    np.testing.assert_allclose(early.mean(), d.background.mean(), rtol=0.05)


def test_echo_is_the_latest_component_at_the_ratio():
    d = make_profiles(30, L, seed=2, kinds="d+s+r2+r3", echo_ratio=0.01)
    ratio = d.params["ir_amplitude"][:, 1] / d.params["direct_amplitude"]
    np.testing.assert_allclose(ratio, 0.01, rtol=1e-12)
    assert np.all(d.params["ir_delay_ps"][:, 1] > d.params["ir_delay_ps"][:, 0])
    # Rendered on 0.5 ps bins a point sample is within 0.25 ps of each peak (sigma >= 2 ps: < 1 % low).
    fine = make_profiles(30, 1024, seed=2, kinds="d+s+r2+r3", echo_ratio=0.01, time_bin_ps=0.5)
    peak = fine.components["interreflections"][:, 1].max(axis=1) / fine.components["direct"].max(axis=1)
    np.testing.assert_allclose(peak, 0.01, rtol=0.01)
    assert d.echo.all()
    with pytest.raises(ValueError, match="inter-reflection"):
        make_profiles(6, L, seed=2, kinds="d+s", echo_ratio=0.01)


def test_truncated_direct_has_its_peak_before_the_window():
    base = make_profiles(30, L, seed=4, kinds="d+s+r2")
    d = make_profiles(30, L, seed=4, kinds="d+s+r2", direct_before_window_ps=(1.0, 6.0))
    t = time_axis_ps(L, T)
    lead = t[0] - d.params["direct_delay_ps"]
    assert np.all((lead >= 1.0) & (lead <= 6.0))
    # Its falling edge only: the direct falls monotonically from the first bin on.
    direct = d.components["direct"]
    assert np.all(direct.argmax(axis=1) == 0) and np.all(np.diff(direct[:, :8], axis=1) < 0)
    # The sss keeps its onset after the direct; the inter-reflections stay where they were.
    np.testing.assert_allclose(d.params["sss_delay_ps"] - d.params["direct_delay_ps"],
                               base.params["sss_delay_ps"] - base.params["direct_delay_ps"], atol=1e-12)
    np.testing.assert_array_equal(d.params["ir_delay_ps"], base.params["ir_delay_ps"])


def test_cube_carries_the_effects():
    c = make_cube(3, 4, L, seed=1, kinds="d+s", photons_per_pixel=1000.0, background=0.02,
                  response=gaussian_response(4.0, time_step_ps=T))
    assert c.noisy.shape == (3, 4, L) and c.background.shape == (3, 4) and c.counts_per_unit.shape == (3, 4)
    np.testing.assert_allclose((c.clean - c.background[..., None]).sum(axis=-1), 1000.0, rtol=1e-12)


def test_effect_options_are_validated():
    with pytest.raises(ValueError, match="background"):
        SyntheticEffects(background=-1.0)
    with pytest.raises(ValueError, match="photons_per_pixel"):
        SyntheticEffects(photons_per_pixel=0.0)
    with pytest.raises(ValueError, match="echo_ratio"):
        SyntheticEffects(echo_ratio=1.5)
    with pytest.raises(ValueError, match="direct_before_window_ps"):
        SyntheticEffects(direct_before_window_ps=(5.0, 1.0))
    with pytest.raises(ValueError, match="InstrumentResponse"):
        SyntheticEffects(response="tailed")
    with pytest.raises(ValueError, match="nsr"):
        make_profiles(4, L, nsr=0.1, photons_per_pixel=100.0)
    with pytest.raises(ValueError, match="no signal"):
        # seeded: a draw of a wide enough PSF leaves a tail of the direct inside the window
        make_profiles(4, L, kinds="d", photons_per_pixel=100.0, direct_before_window_ps=200.0, seed=0)
    # a tail of 1e-320 inside the window is no signal: scaled to 100 photons it would overflow
    clean = np.zeros((2, 8))
    clean[0, 3] = 1.0
    clean[1, 7] = 1e-320
    with pytest.raises(ValueError, match="no signal"):
        count_photons(clean, 0.0, 100.0, np.random.default_rng(0))


def test_response_width_is_its_fwhm_in_sigmas():
    assert abs(response_sigma_ps(gaussian_response(3.0, time_step_ps=1.0)) - 3.0) < 1e-9
