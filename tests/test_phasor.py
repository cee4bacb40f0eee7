"""decomposition.phasor: phasors of binned decays against closed forms and phasorpy."""
import warnings

import numpy as np
import pytest
from scipy.stats import exponnorm

from decomposition import phasor as ph
from decomposition.phasor import PhasorError, phasor, phasor_lifetime, semicircle, window_frequency_per_ps


def binned_exponential(tau_ps, time_bin_ps, n_bins, *, onset_ps=0.0, counts=1e4):
    """exp(-(t - onset) / tau) for t >= onset, integrated over each bin [k dt, (k + 1) dt)."""
    edges = np.arange(n_bins + 1) * time_bin_ps
    cdf = 1.0 - np.exp(-np.clip(edges - onset_ps, 0.0, None) / tau_ps)
    return counts * np.diff(cdf)


def semicircle_distance(g, s):
    return np.hypot(g - 0.5, s) - 0.5


# ---------------------------------------------------------------------------------------------
# the target: a single exponential lies on the universal semicircle at its lifetime, to 1 %
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("tau_ps, time_bin_ps, n_bins", [
    (50.0, 2.0, 512),     # the example: 2 ps bins, 1024 ps window
    (20.0, 2.0, 256),
    (10.0, 2.0, 1024),
    (6.0, 2.0, 512),      # dt / tau = 1/3
    (200.0, 2.0, 1024),
    (1000.0, 2.0, 512),   # far from zero at the window's end (periodic with the window)
    (5000.0, 1.0, 256),
    (50.0, 5.0, 64),
    (100.0, 10.0, 40),
    (3.0, 0.5, 2000),
])
def test_a_single_exponential_lies_on_the_semicircle_at_its_lifetime(tau_ps, time_bin_ps, n_bins):
    g, s = phasor(binned_exponential(tau_ps, time_bin_ps, n_bins), time_bin_ps)
    f = window_frequency_per_ps(n_bins, time_bin_ps)
    tau_phase, tau_mod = phasor_lifetime(g, s, f)
    assert abs(tau_phase / tau_ps - 1) < 0.01
    assert abs(tau_mod / tau_ps - 1) < 0.01
    g_true, s_true = semicircle(lifetimes_ps=tau_ps, frequency_per_ps=f)
    assert np.hypot(g - g_true, s - s_true) < 0.01 * np.hypot(g_true, s_true)
    assert abs(semicircle_distance(g, s)) < 0.005  # 1 % of the radius


def test_plain_sampling_reads_exp_50ps_at_2ps_bins_at_48_9ps():
    """The uncorrected path lags by half a bin; the corrected one is within 0.05 %."""
    x = binned_exponential(50.0, 2.0, 512)
    f = window_frequency_per_ps(512, 2.0)
    tau_plain, _ = phasor_lifetime(*phasor(x, 2.0, bin_correction=False), f)
    tau_corr, _ = phasor_lifetime(*phasor(x, 2.0), f)
    assert round(float(tau_plain), 1) == 48.9
    assert abs(tau_corr / 50.0 - 1) < 5e-4


def test_the_residual_of_a_step_onset_follows_its_alias_estimate():
    """Past the 1 % domain the corrected error is about ((dt/tau)^2 + (2 pi / L)^2) / 12."""
    for tau_ps, dt, n_bins in [(4.0, 2.0, 512), (50.0, 2.0, 16)]:
        f = window_frequency_per_ps(n_bins, dt)
        tau_phase, _ = phasor_lifetime(*phasor(binned_exponential(tau_ps, dt, n_bins), dt), f)
        estimate = ((dt / tau_ps) ** 2 + (2 * np.pi / n_bins) ** 2) / 12
        assert estimate > 0.01
        assert tau_phase / tau_ps - 1 == pytest.approx(estimate, rel=0.1)


def test_a_decay_smoothed_by_a_response_is_exact():
    """A band-limited decay (exponential convolved with a Gaussian response of 3 ps) binned at 2
    ps: dividing by the bins' transfer function recovers the continuous phasor
    exp(i w t0 - (w sigma)^2 / 2) / (1 - i w tau) to rounding; plain sampling is 0.6 % off."""
    tau, sigma, t0, dt, n_bins = 50.0, 3.0, 100.0, 2.0, 512
    period = dt * n_bins
    edges = np.arange(n_bins + 1) * dt
    x = sum(np.diff(exponnorm.cdf(edges - n * period, tau / sigma, loc=t0, scale=sigma)) for n in range(6))
    w = 2 * np.pi * window_frequency_per_ps(n_bins, dt)
    truth = np.exp(1j * w * t0 - (w * sigma) ** 2 / 2) / (1 - 1j * w * tau)
    g, s = phasor(x, dt)
    assert abs(complex(g, s) - truth) < 1e-7
    g0, s0 = phasor(x, dt, bin_correction=False)
    assert abs(complex(g0, s0) - truth) > 5e-3


def test_the_onset_is_rotated_back_per_pixel():
    dt, n_bins, tau = 2.0, 512, 50.0
    onsets = np.array([[0.0, 37.0], [101.3, 250.0]])
    x = np.stack([binned_exponential(tau, dt, n_bins, onset_ps=o) for o in onsets.ravel()]).reshape(2, 2, n_bins)
    f = window_frequency_per_ps(n_bins, dt)
    tau_phase, tau_mod = phasor_lifetime(*phasor(x, dt, onset_ps=onsets), f)
    assert np.all(np.abs(tau_phase / tau - 1) < 0.01)
    assert np.all(np.abs(tau_mod / tau - 1) < 0.01)
    late, _ = phasor_lifetime(*phasor(x[0, 1], dt), f)  # onset not given: the phase reads far longer
    assert late > 1.5 * tau


def test_a_mixture_lies_at_the_intensity_weighted_mean():
    """The correction is one complex factor, so phasors stay linear: two lifetimes' mixture sits
    on the chord between them, at the fraction of the intensity."""
    dt, n_bins = 2.0, 512
    a, b = binned_exponential(20.0, dt, n_bins, counts=300.0), binned_exponential(400.0, dt, n_bins, counts=700.0)
    za, zb, zm = (complex(*phasor(p, dt)) for p in (a, b, a + b))
    fa = a.sum() / (a + b).sum()
    assert abs(zm - (fa * za + (1 - fa) * zb)) < 1e-12


# ---------------------------------------------------------------------------------------------
# blocks, axes, dtypes
# ---------------------------------------------------------------------------------------------
def test_a_block_equals_its_pixels_one_by_one(monkeypatch):
    rng = np.random.default_rng(3)
    taus = rng.uniform(10.0, 300.0, size=(7, 9))
    cube = np.stack([binned_exponential(t, 2.0, 128, counts=1e6) for t in taus.ravel()]).reshape(7, 9, 128)
    cube = rng.poisson(cube).astype(np.uint32)
    g, s = phasor(cube, 2.0)
    assert g.shape == s.shape == (7, 9)
    monkeypatch.setattr(ph, "_BLOCK_SAMPLES", 5 * 128)  # 13 blocks of 5 pixels
    g_small, s_small = phasor(cube, 2.0)
    one = [phasor(cube[i, j], 2.0) for i in range(7) for j in range(9)]
    np.testing.assert_allclose(g, np.array([o[0] for o in one]).reshape(7, 9), rtol=0, atol=1e-13)
    np.testing.assert_allclose(s, np.array([o[1] for o in one]).reshape(7, 9), rtol=0, atol=1e-13)
    np.testing.assert_allclose(g_small, g, rtol=0, atol=1e-13)
    np.testing.assert_allclose(s_small, s, rtol=0, atol=1e-13)
    tau_phase, _ = phasor_lifetime(g, s, window_frequency_per_ps(128, 2.0))
    assert np.median(np.abs(tau_phase / taus - 1)) < 0.02  # Poisson noise at 1e6 counts


def test_time_axis_and_float32_give_the_same_numbers():
    x = np.stack([binned_exponential(t, 2.0, 64) for t in (10.0, 30.0, 90.0)])  # (3, 64)
    g, s = phasor(x, 2.0)
    g0, s0 = phasor(x.T, 2.0, axis=0)
    np.testing.assert_array_equal(g, g0)
    np.testing.assert_array_equal(s, s0)
    g32, s32 = phasor(x.astype(np.float32), 2.0)
    assert g32.dtype == np.float64
    np.testing.assert_allclose(g32, g, rtol=1e-6)
    np.testing.assert_allclose(s32, s, rtol=1e-6)


def test_the_uncorrected_path_agrees_with_phasorpy():
    from phasorpy.lifetime import phasor_semicircle, phasor_to_apparent_lifetime
    from phasorpy.phasor import phasor_from_signal

    rng = np.random.default_rng(7)
    cube = rng.poisson(50.0, size=(4, 5, 96)).astype(np.uint16)
    for harmonic, axis in [(1, -1), (2, -1), (3, 0)]:
        data = np.moveaxis(cube, -1, axis)
        g, s = phasor(data, 2.0, harmonic=harmonic, axis=axis, bin_correction=False)
        _, g_ref, s_ref = phasor_from_signal(data, axis=axis, harmonic=harmonic)
        np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(s, s_ref, rtol=0, atol=1e-12)
    x = binned_exponential(50.0, 2.0, 512)
    _, g_ref, s_ref = phasor_from_signal(x)
    g, s = phasor(x, 2.0, bin_correction=False)
    assert (float(g), float(s)) == pytest.approx((float(g_ref), float(s_ref)), abs=1e-13)
    f = window_frequency_per_ps(512, 2.0)
    g, s = phasor(x, 2.0)
    ours = phasor_lifetime(g, s, f)
    theirs = phasor_to_apparent_lifetime(g, s, f, unit_conversion=1.0)  # 1/ps and ps
    np.testing.assert_allclose(ours, theirs, rtol=1e-12)
    np.testing.assert_allclose(semicircle(11), phasor_semicircle(11), atol=1e-15)


def test_window_frequency_and_semicircle_ticks():
    assert window_frequency_per_ps(512, 2.0) == 1 / 1024
    assert window_frequency_per_ps(512, 2.0, harmonic=2) == 2 / 1024
    f = 1 / 1024
    g, s = semicircle(lifetimes_ps=[0.0, 1024 / (2 * np.pi)], frequency_per_ps=f)
    np.testing.assert_allclose(g, [1.0, 0.5])
    np.testing.assert_allclose(s, [0.0, 0.5])
    tau_phase, tau_mod = phasor_lifetime(g[1], s[1], f)
    assert tau_phase == pytest.approx(1024 / (2 * np.pi)) and tau_mod == pytest.approx(1024 / (2 * np.pi))


# ---------------------------------------------------------------------------------------------
# empty pixels and bad input
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bin_correction", [True, False])
def test_an_empty_pixel_is_nan_without_a_warning(bin_correction):
    x = np.zeros((2, 3, 32), dtype=np.uint16)
    x[0, 0] = np.round(binned_exponential(20.0, 2.0, 32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g, s = phasor(x, 2.0, bin_correction=bin_correction)
        tau_phase, tau_mod = phasor_lifetime(g, s, window_frequency_per_ps(32, 2.0))
    assert np.isfinite(g[0, 0]) and np.isfinite(s[0, 0])
    assert np.isnan(g).sum() == 5 and np.isnan(s).sum() == 5
    assert np.isnan(tau_phase).sum() == 5 and np.isnan(tau_mod).sum() == 5


def test_lifetimes_outside_the_semicircle_are_inf_or_nan_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tau_phase, tau_mod = phasor_lifetime([0.0, 0.9, 1.0], [0.5, 0.9, 0.0], 0.001)
    assert tau_phase[0] == np.inf
    assert np.isnan(tau_mod[1])  # modulation above 1
    assert tau_phase[2] == 0.0 and tau_mod[2] == 0.0


@pytest.mark.parametrize("time_bin_ps", [0.0, -2.0, np.nan, np.inf, "2 ps", None, True])
def test_a_bad_bin_width_is_refused(time_bin_ps):
    with pytest.raises(PhasorError, match="time_bin_ps must be a positive finite number"):
        phasor(np.ones(16), time_bin_ps)


def test_non_finite_samples_are_refused_and_counted():
    x = np.ones((2, 3, 16))
    x[0, 1, 4] = np.nan
    x[1, 2, 0] = np.inf
    with pytest.raises(PhasorError, match=r"2 of 6 profiles hold NaN or inf samples"):
        phasor(x, 2.0)


@pytest.mark.parametrize("call, message", [
    (lambda: phasor(np.ones(16), 2.0, harmonic=0), "harmonic must be an integer >= 1"),
    (lambda: phasor(np.ones(16), 2.0, harmonic=1.5), "harmonic must be an integer >= 1"),
    (lambda: phasor(np.ones(8), 2.0, harmonic=4), "harmonic 4 needs at least 9 time bins, the profiles have 8"),
    (lambda: phasor(np.ones(16) + 1j, 2.0), "profiles must be real numbers, got dtype complex128"),
    (lambda: phasor(np.array(["a"] * 16), 2.0), "profiles must be real numbers"),
    (lambda: phasor(np.float64(3.0), 2.0), "profiles must have a time axis"),
    (lambda: phasor(np.ones((3, 16)), 2.0, axis=2), "axis 2 is out of range for profiles of shape"),
    (lambda: phasor(np.ones((3, 16)), 2.0, onset_ps=np.nan), "onset_ps must be finite"),
    (lambda: phasor(np.ones((3, 16)), 2.0, onset_ps=[1.0, 2.0]), "onset_ps of shape"),
    (lambda: phasor_lifetime(0.5, 0.5, 0.0), "frequency_per_ps must be positive"),
    (lambda: semicircle(1), "n_points must be an integer >= 2"),
    (lambda: semicircle(lifetimes_ps=[10.0]), "needs frequency_per_ps"),
    (lambda: semicircle(lifetimes_ps=[-1.0], frequency_per_ps=0.001), "lifetimes_ps must be finite and >= 0"),
])
def test_bad_input_gets_a_clear_error(call, message):
    with pytest.raises(PhasorError, match=message):
        call()
