"""Estimating the instrument response from a direct reflection: exactness, noise bounds and refusals."""
import numpy as np
import pytest

from core.irf import render_shifted
from core.irf_models import afterpulse_response, tailed_response
from reconstruction.cubestore import open_cube, write_cube
from reconstruction.irf import (
    ResponseEstimateError, ResponseEstimateOptions, estimate_response, fit_response,
)

T, L = 2.0, 256
AXIS = T * np.arange(L)
TRUTH = tailed_response(5.0, 0.25, 30.0, time_step_ps=T)


def calibration_profiles(truth, n, seed, *, noise=1.0, background=5.0, delays=(90.0, 130.0), amps=(80.0, 160.0)):
    """Profiles of a flat target: one shifted copy of ``truth`` per pixel at a random sub-bin delay."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(*delays, n)
    a = rng.uniform(*amps, n)
    p = a[:, None] * render_shifted(truth, AXIS, d) + background + noise * rng.standard_normal((n, L))
    return p, d, a


def _peak_normalised_error(fit, truth):
    r = fit.response
    return r.samples / r.peak_per_ps - render_shifted(truth, r.time_axis_ps(), 0.0)


@pytest.mark.parametrize("truth", [TRUTH, afterpulse_response(4.0, 0.08, 40.0, time_step_ps=T)],
                         ids=["tailed", "afterpulse"])
def test_noise_free_estimate_is_exact(truth):
    prof, d, a = calibration_profiles(truth, 24, seed=1, noise=0.0)
    fit = fit_response(prof, T)
    assert fit.used.all() and fit.response.provenance["pixels_used"] == 24
    assert np.max(np.abs(_peak_normalised_error(fit, truth))) < 1e-7
    np.testing.assert_allclose(fit.delay_ps, d, atol=1e-6)             # peak convention: same reference
    np.testing.assert_allclose(fit.amplitude, a, rtol=1e-8)
    np.testing.assert_allclose(fit.background, 5.0, atol=1e-9)
    assert fit.response.peak_time_ps == pytest.approx(0.0, abs=1e-9)
    assert fit.response.samples.sum() * T == pytest.approx(1.0, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 5])
def test_noisy_estimate_error_follows_from_the_noise(seed):
    sigma_n = 1.0
    prof, d, a = calibration_profiles(TRUTH, 64, seed=seed, noise=sigma_n)
    fit = fit_response(prof, T)
    prov = fit.response.provenance
    # The least-squares average of P pixels of amplitude a_i has a per-sample error of
    # sigma_n / sqrt(sum a_i^2) (peak-normalised); alignment noise adds at most as much again.
    sigma_e = sigma_n / np.sqrt(np.sum(a ** 2))
    rms = np.sqrt(np.mean(_peak_normalised_error(fit, TRUTH) ** 2))
    assert rms < 2.5 * sigma_e
    # Delays: matched-filter scatter at the Cramér-Rao level the provenance reports, a common
    # offset (where the noisy template's peak lands) far below a bin.
    err = fit.delay_ps - d
    assert 0.7 < np.std(err) / prov["alignment_sd_ps"] < 1.4
    assert abs(err.mean()) < 5 * prov["alignment_sd_ps"]
    assert prov["delay_spread_ps"] == pytest.approx(np.std(d), rel=0.01)
    np.testing.assert_allclose(fit.amplitude, a, rtol=0.05)


def test_pixels_that_cannot_help_are_left_out_and_counted():
    prof, d, a = calibration_profiles(TRUTH, 60, seed=2)
    rng = np.random.default_rng(9)
    prof[0:4] = np.minimum(prof[0:4], 60.0)                          # saturated: clipped flat tops
    prof[4:8] = 5.0 + rng.standard_normal((4, L))                    # no signal
    prof[8:11] = (100 * render_shifted(TRUTH, AXIS, np.array([3.0, 10.0, 20.0]))
                  + 5.0 + rng.standard_normal((3, L)))                # cut off at the window's start
    prof[11:14] += 40 * render_shifted(TRUTH, AXIS, d[11:14] + 60.0)  # a second reflection
    prof[14, 30] = np.nan
    fit = fit_response(prof, T)
    assert fit.dropped == {"non_finite": 1, "saturated": 4, "no_baseline": 3, "low_signal": 4, "outlier": 3,
                           "beyond_max_pixels": 0}
    assert fit.used.sum() == 45 and not fit.used[:15].any()
    assert np.all(np.isnan(fit.delay_ps[:15])) and np.all(np.isfinite(fit.delay_ps[15:]))
    good = a[15:]
    assert np.sqrt(np.mean(_peak_normalised_error(fit, TRUTH) ** 2)) < 2.5 / np.sqrt(np.sum(good ** 2))
    # A cap on the pixels keeps the brightest (amplitude over noise).
    capped = fit_response(prof, T, options=ResponseEstimateOptions(max_pixels=10))
    assert capped.used.sum() == 10 and capped.dropped["beyond_max_pixels"] == 60 - 12 - 10
    assert np.min(capped.amplitude[capped.used]) > np.median(fit.amplitude[fit.used])
    bright = capped.amplitude[capped.used]
    assert np.sqrt(np.mean(_peak_normalised_error(capped, TRUTH) ** 2)) < 2.5 / np.sqrt(np.sum(bright ** 2))
    # An explicit saturation level catches clipping below the flat-top test.
    prof2, _, _ = calibration_profiles(TRUTH, 20, seed=3)
    level = np.sort(prof2.max(axis=1))[4]
    fit2 = fit_response(prof2, T, options=ResponseEstimateOptions(saturation_level=level, min_pixels=4))
    assert fit2.dropped["saturated"] == 16 and fit2.used.sum() == 4


def test_estimates_that_are_impossible_are_refused_with_the_reason():
    prof, _, _ = calibration_profiles(TRUTH, 3, seed=4)
    with pytest.raises(ResponseEstimateError, match=r"only 3 of 3 pixels .*need at least 8"):
        fit_response(prof, T)
    noise = 5.0 + np.random.default_rng(0).standard_normal((40, L))
    with pytest.raises(ResponseEstimateError, match="40 low signal"):
        fit_response(noise, T)
    prof, _, _ = calibration_profiles(TRUTH, 20, seed=4)
    with pytest.raises(ResponseEstimateError, match="20 saturated"):
        fit_response(np.minimum(prof, 40.0), T)
    with pytest.raises(ResponseEstimateError, match="time_bin_ps"):
        fit_response(prof, 0.0)
    with pytest.raises(ResponseEstimateError, match="at least 16 time bins"):
        fit_response(prof[:, :10], T)
    with pytest.raises(ResponseEstimateError, match="min_snr"):
        ResponseEstimateOptions(min_snr=-1.0)
    with pytest.raises(ResponseEstimateError, match="min_pixels"):
        ResponseEstimateOptions(min_pixels=0)
    # A response window longer than the tail has decayed in: named, with what to do.
    with pytest.raises(ResponseEstimateError, match="has not decayed"):
        fit_response(prof, T, options=ResponseEstimateOptions(post_peak_ps=20.0))


def test_estimate_from_a_cube_store_records_where_it_came_from(tmp_path):
    prof, d, _ = calibration_profiles(TRUTH, 32, seed=6)
    cube = write_cube(tmp_path / "cal.zarr", prof.reshape(4, 8, L), time_bin_ps=T, t0_ps=10.0)
    fit = fit_response(open_cube(cube.path), options=ResponseEstimateOptions(min_pixels=16))
    assert fit.delay_ps.shape == (4, 8)
    np.testing.assert_allclose(fit.delay_ps.ravel(), d + 10.0, atol=0.2)
    irf = estimate_response(open_cube(cube.path))
    assert irf.provenance["store"] == cube.path and irf.provenance["shape"] == [4, 8, L]
    assert irf.provenance["pixels_used"] == 32 and irf.provenance["software_version"]
