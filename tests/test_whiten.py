"""Correlated (pink) noise judged over a call's pixels: the penalised objectives of the stages
after the detection whiten their residuals by the call's noise spectrum."""
import numpy as np
import pytest

from decomposition import decompose
from decomposition.model.fidelity import fidelity
from decomposition.noise import residual_spectrum, whitened_chi2
from decomposition.noise import SpectralNoise
from decomposition.stages.objective import objective_variance
from decomposition.evaluation.synthetic import make_profiles

L = 256


def _shaped(rng, n, exponent):
    """(n, L) zero-mean Gaussian noise whose power falls as 1 / f^exponent (0: white), unit
    variance per sample on average."""
    spec = np.fft.rfft(rng.standard_normal((n, L)), axis=1)
    f = np.fft.rfftfreq(L)
    shape = np.ones_like(f)
    shape[1:] = f[1:] ** (-exponent / 2.0)
    shape[0] = 0.0 if exponent else 1.0
    x = np.fft.irfft(spec * shape, n=L, axis=1)
    return x / x.std()


def test_a_flat_spectrum_gives_the_plain_chi2():
    # Parseval: white noise of variance 1 has power L at every frequency, and then the whitened
    # data term is the sum of squares over the variance, to rounding
    rng = np.random.default_rng(0)
    r = rng.standard_normal((5, L))
    var = rng.uniform(0.5, 2.0, 5)
    got = whitened_chi2(r, np.full(L // 2 + 1, float(L)), var)
    np.testing.assert_allclose(got, (r * r).sum(axis=1) / var, rtol=1e-12)
    odd = rng.standard_normal((3, L + 1))
    np.testing.assert_allclose(whitened_chi2(odd, np.full((L + 1) // 2 + 1, float(L + 1)), np.ones(3)),
                               (odd * odd).sum(axis=1), rtol=1e-12)


def test_the_shared_spectrum_is_read_and_whitens_new_noise_of_it():
    rng = np.random.default_rng(1)
    white = residual_spectrum(_shaped(rng, 400, 0))
    assert abs(np.median(white[1:-1]) / L - 1.0) < 0.1          # flat, at L per unit variance
    pink = residual_spectrum(_shaped(rng, 400, 1))
    # 1/f: the lowest frequencies carry tens of times the power of the highest
    assert pink[1:4].mean() > 20 * pink[-20:].mean()
    # new noise of that law reads L per row on average, whitened by the spectrum read before,
    # and its plain sum of squares is nothing like it at the components' low frequencies
    fresh = _shaped(rng, 200, 1)
    chi = whitened_chi2(fresh, pink, np.ones(200))
    assert abs(chi.mean() / L - 1.0) < 0.1, chi.mean()
    # a row with a misfit adds power; the median ignores a few such rows
    spiked = _shaped(rng, 400, 1)
    spiked[:20] += 5.0 * np.sin(2 * np.pi * 40 * np.arange(L) / L)
    again = residual_spectrum(spiked)
    assert again[40] < 2.0 * pink[40]


def test_objective_variance_hands_on_the_spectrum():
    s = np.array([1.0, 2.0])
    spec = np.full(L // 2 + 1, float(L))
    got = objective_variance(s, np.array([3.0, 3.0]), None, spec)
    assert isinstance(got, SpectralNoise)
    np.testing.assert_array_equal(got.variance, [1.0, 4.0])
    np.testing.assert_array_equal(got.spectrum, spec)
    # without one: the variances, as before
    np.testing.assert_allclose(objective_variance(s, np.array([1.0, 3.0])), [1.0, 9.0])


def _pink(n, tb=2.0, nsr=0.11, seed=1):
    return make_profiles(n, 512, nsr=nsr, noise="pink", seed=seed, time_bin_ps=tb, ranges="paper",
                         bin_integrated=True)


def test_pink_calls_are_whitened_and_others_are_not():
    p = _pink(60)
    assert decompose(p.noisy, time_bin_ps=2.0).info["correlated_noise"] is True
    assert "correlated_noise" not in decompose(p.noisy, time_bin_ps=2.0, whiten=False).info
    w = make_profiles(60, 512, nsr=0.11, noise="white", seed=1, time_bin_ps=2.0, ranges="paper", bin_integrated=True)
    assert decompose(w.noisy, time_bin_ps=2.0).info["correlated_noise"] is False
    # photon noise is weighted by its variance law (and not stationary)
    ph = make_profiles(60, 512, nsr=0.11, noise="photon", seed=1, time_bin_ps=2.0, ranges="paper",
                       bin_integrated=True)
    r = decompose(ph.noisy, time_bin_ps=2.0)
    assert r.info["signal_weighted"] == 60 and r.info["correlated_noise"] is False
    # count data have their Poisson law
    counts = make_profiles(20, 256, seed=1, time_bin_ps=2.0, photons_per_pixel=1000).noisy
    assert "correlated_noise" not in decompose(counts, time_bin_ps=2.0).info


def test_white_noise_is_decomposed_as_without_whitening():
    w = make_profiles(60, 512, nsr=0.055, noise="white", seed=2, time_bin_ps=2.0, ranges="paper", bin_integrated=True)
    a, b = decompose(w.noisy, time_bin_ps=2.0).params, decompose(w.noisy, time_bin_ps=2.0, whiten=False).params
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=True), k


@pytest.mark.parametrize("tb, seed, lift", [(2.0, 1, 0.02), (4.0, 1, 0.005)])
def test_whitening_lifts_the_fidelity_under_pink_noise(tb, seed, lift):
    d = _pink(200, tb=tb, seed=seed)
    on = np.nanmean(fidelity(d.components, decompose(d.noisy, time_bin_ps=tb)))
    off = np.nanmean(fidelity(d.components, decompose(d.noisy, time_bin_ps=tb, whiten=False)))
    # measured: 2 ps 0.849 -> 0.891, 4 ps 0.872 -> 0.886 (600 px, seed 0: 2 ps 0.853 -> 0.886,
    # 4 ps 0.851 -> 0.880)
    assert on > off + lift, (off, on)


def test_the_doubt_test_reads_the_whitened_data_term():
    # in sample variances nearly every pink pixel's data term is above its expectation, so
    # nearly every pixel was searched; read whitened, about as many as under white noise
    p = _pink(200, seed=3)
    on = decompose(p.noisy, time_bin_ps=2.0)
    off = decompose(p.noisy, time_bin_ps=2.0, whiten=False)
    # measured: 140 and 199 of 200
    assert on.info["search_doubt"] < 0.8 * off.info["search_doubt"], (on.info["search_doubt"], off.info["search_doubt"])
    assert off.info["search_doubt"] > 0.9 * 200


def test_the_spectrum_from_periodograms_is_the_same_and_one_input_is_asked_for():
    from decomposition.noise import periodogram

    rng = np.random.default_rng(4)
    r = _shaped(rng, 50, 1)
    np.testing.assert_array_equal(residual_spectrum(r), residual_spectrum(power=periodogram(r)))
    with pytest.raises(ValueError, match="one of them"):
        residual_spectrum()
    with pytest.raises(ValueError, match="one of them"):
        residual_spectrum(r, power=periodogram(r))
