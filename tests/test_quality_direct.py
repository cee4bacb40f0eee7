"""POOR_FIT's second test: the residual over the direct's own samples (decomposition.quality)."""
import numpy as np

from core.model import render_profile
from decomposition.flags import POOR_FIT
from decomposition.noise import signal_noise_sigma
from decomposition.options import GridSpec
from decomposition.prepare import prepare_samples, time_axis
from decomposition.quality import assess_fit, direct_misfit

T = 4.0          # ps per bin: a direct narrower than one bin
L = 512
N = 40


def _params(direct, sss, n=N):
    """P-shaped parameters: direct (delay_ps, amplitude, sigma_ps), sss (onset_ps, amplitude,
    alpha_per_ps), the sss sharing the direct's width; no inter-reflections."""
    d, a, s = direct
    o, b, alpha = sss
    full = lambda v: np.full(n, float(v))
    return {"direct_delay_ps": full(d), "direct_amplitude": full(a), "direct_sigma_ps": full(s),
            "sss_delay_ps": full(o), "sss_amplitude": full(b), "sss_alpha_per_ps": full(alpha),
            "sss_sigma_ps": full(s), "ir_delay_ps": np.full((n, 0), np.nan), "ir_amplitude": np.full((n, 0), np.nan),
            "ir_sigma_ps": np.full((n, 0), np.nan)}


TRUE = _params((400.0, 1.0, 1.2), (403.0, 0.5, 0.025))


def _wide():
    """The wrong split of the narrow direct: a direct three times too wide (the sss sharing its
    width), amplitudes the least-squares fit to the clean profile."""
    clean = render_profile(TRUE, L, T)[0]
    unit_d = render_profile(_params((401.0, 1.0, 3.6), (403.0, 0.0, 0.025), 1), L, T)[0]
    unit_s = render_profile(_params((401.0, 0.0, 3.6), (403.0, 1.0, 0.025), 1), L, T)[0]
    (a, b), *_ = np.linalg.lstsq(np.stack([unit_d, unit_s], axis=1), clean, rcond=None)
    return _params((401.0, a, 3.6), (403.0, b, 0.025))


WIDE = _wide()


def _samples(noise=0.008, seed=0):
    clean = render_profile(TRUE, L, T)
    rng = np.random.default_rng(seed)
    return prepare_samples(clean + noise * rng.standard_normal(clean.shape), time_axis(T), GridSpec())


def _whole_rms_over_noise(samples, params):
    """The whole-window test's statistic: residual RMS over the larger of the noise and the
    noise at the signal (second differences of the residual, raised by this misfit)."""
    model = render_profile(params, L, T) / samples.scale[:, None]
    res = samples.values / samples.scale[:, None] - model
    noise = np.maximum(samples.noise_eff, signal_noise_sigma(res, model, samples.fit))
    return np.sqrt(np.mean(res ** 2, axis=1)) / noise


def test_true_split_reads_as_noise_on_the_direct_samples():
    s = _samples()
    total = render_profile(TRUE, L, T)
    ratio = direct_misfit(s, TRUE, s.values - total, total, s.noise_eff[s.live])
    # chi2 / n of white noise over ~9 samples: mean 1, and the RMS of 40 pixels near 1
    assert 0.8 < np.sqrt(np.mean(ratio ** 2)) < 1.25
    assert not np.any(assess_fit(s, TRUE, s.noise_eff, 3.0).flags & POOR_FIT)


def test_wrong_direct_width_is_poor_fit_though_the_whole_profile_rms_is_not():
    s = _samples()
    # the whole-window test alone would pass it: the misfit sits on a few of 512 samples
    assert np.all(_whole_rms_over_noise(s, WIDE) < 3.0)
    total = render_profile(WIDE, L, T)
    assert np.all(direct_misfit(s, WIDE, s.values - total, total, s.noise_eff[s.live]) > 3.0)
    assert np.all(assess_fit(s, WIDE, s.noise_eff, 3.0).flags & POOR_FIT)


def test_pixel_without_direct_is_not_judged_on_it():
    s = _samples()
    none = {k: v.copy() for k, v in WIDE.items()}
    none["direct_delay_ps"][:] = np.nan
    total = render_profile(none, L, T)
    np.testing.assert_array_equal(direct_misfit(s, none, s.values - total, total, s.noise_eff[s.live]), 0.0)
