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


def _weak_direct_params(direct_amplitude, sss_onset_ps, n=1):
    return _params((400.0, direct_amplitude, 1.2), (sss_onset_ps, 0.5, 0.025), n)   # sss peak 1.33


def test_weak_direct_just_before_a_larger_onset_is_ambiguous():
    from decomposition.components import render_params
    from decomposition.flags import AMBIGUOUS
    from decomposition.quality import weak_direct

    t = T + T * np.arange(L)
    cases = [(0.05, 403.0, True),     # weak, sss onset 2.5 widths after: in doubt
             (1.0, 403.0, False),     # a strong direct
             (0.05, 410.0, False)]    # weak, but the onset 8 widths later: resolved
    for amp, onset, want in cases:
        p = _weak_direct_params(amp, onset)
        rend = render_params(p, L, T, T)
        if onset < 405.0:                                   # the case is on the side it names
            peak_ratio = rend["direct"].max() / rend["sss"][0, (t >= 400.0) & (t <= 400.0 + 6 * 1.2 + T)].max()
            assert (peak_ratio < 0.15) == (amp < 0.5)
        assert weak_direct(p, rend, t).tolist() == [want]
    # in the decomposition's flags, through the quality stage
    p = _weak_direct_params(0.05, 403.0, N)
    s = prepare_samples(render_profile(p, L, T) + 0.002 * np.random.default_rng(3).standard_normal((N, L)),
                        time_axis(T), GridSpec())
    assert np.all(assess_fit(s, p, s.noise_eff, 3.0).flags & AMBIGUOUS)
    assert not np.any(assess_fit(s, TRUE, s.noise_eff, 3.0).flags & AMBIGUOUS)


def test_direct_not_judged_where_the_noise_at_the_signal_is_unmeasured():
    # photon-like noise on a dark baseline: the whole-profile noise is the floor, far below the
    # noise at the peak; a lone direct spans too few samples to measure the latter
    lone = _params((400.0, 1.0, 3.0), (np.nan, np.nan, np.nan))
    clean = render_profile(lone, L, T)
    rng = np.random.default_rng(5)
    noisy = clean + 0.015 * np.sqrt(clean) * rng.standard_normal(clean.shape)
    s = prepare_samples(noisy, time_axis(T), GridSpec())
    total = render_profile(lone, L, T)
    model = total / s.scale[:, None]
    assert np.all(signal_noise_sigma(s.values / s.scale[:, None] - model, model, s.fit) == 0.0)
    # against the floor the true split itself would read as a misfit ...
    assert np.median(direct_misfit(s, lone, s.values - total, total, s.noise_eff[s.live])) > 3.0
    # ... so it is not judged there
    assert not np.any(assess_fit(s, lone, s.noise_eff, 3.0).flags & POOR_FIT)
