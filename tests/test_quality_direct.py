"""POOR_FIT's second test: the residual over the direct's own samples (decomposition.stages.quality)."""
import numpy as np

from core.model import render_profile
from decomposition.flags import POOR_FIT
from decomposition.noise import signal_noise_sigma
from decomposition.options import GridSpec
from decomposition.stages.prepare import prepare_samples, time_axis
from decomposition.stages.quality import assess_fit, direct_misfit

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
    from decomposition.model.components import render_params
    from decomposition.flags import AMBIGUOUS
    from decomposition.stages.quality import weak_direct

    t = T + T * np.arange(L)
    cases = [(0.05, 403.0, True),     # weak, sss onset 2.5 widths after: in doubt
             (1.0, 403.0, False),     # a strong direct
             (0.05, 410.0, False),    # weak, but the onset 8 widths later: resolved
             (0.05, 405.5, True)]     # 4.6 widths later, but within one bin of the 4 widths
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


def _narrow_chain(n, bin_integrated=True):
    """A direct narrower than half a 4 ps bin with a near-equal inter-reflection 5 widths later,
    a weaker one 13 widths later and a faint sss (one pixel of the paper scenes at 4 ps bins
    that the solver fitted with one Gaussian 4 times too wide), rendered bin-integrated (as
    that scene) or point-sampled (the model assess_fit renders)."""
    full = lambda v: np.full(n, float(v))
    params = {"direct_delay_ps": full(357.54), "direct_amplitude": full(0.8276), "direct_sigma_ps": full(1.9),
              "sss_delay_ps": full(362.11), "sss_amplitude": full(0.0594), "sss_alpha_per_ps": full(0.0404),
              "sss_sigma_ps": full(1.9), "ir_delay_ps": np.tile([367.01, 383.31], (n, 1)),
              "ir_amplitude": np.tile([0.7917, 0.1611], (n, 1)), "ir_sigma_ps": np.full((n, 2), 1.9)}
    return params, render_profile(params, L, T, bin_integrated=bin_integrated)


def test_misfit_read_as_noise_is_still_poor_fit_where_the_noise_is_flat():
    # the one-Gaussian fit of the narrow chain: its misfit on the scale of a bin is what the
    # solver's second noise pass read as the noise at the signal (0.16 of the peak in the
    # pixel this is drawn from), so against that noise the fit looks fine; a pixel whose noise
    # was judged not to follow the signal is read against its whole-profile noise instead
    params, clean = _narrow_chain(N, bin_integrated=False)
    rng = np.random.default_rng(11)
    s = prepare_samples(clean + 6e-5 * rng.standard_normal(clean.shape), time_axis(T), GridSpec())
    one = _params((365.0, 0.618, 8.11), (np.nan, np.nan, np.nan))
    res = (s.values - render_profile(one, L, T)) / s.scale[:, None]
    rms = np.sqrt(np.mean(res ** 2, axis=1))
    assert np.all(rms > 20 * s.noise_eff)        # tens of noise sigmas off (noise_eff at its floor)
    inflated = 0.5 * rms                           # the misfit taken for noise
    assert not np.any(assess_fit(s, one, inflated, 3.0).flags & POOR_FIT)
    flat = np.ones(s.live.size, bool)
    assert np.all(assess_fit(s, one, inflated, 3.0, flat_noise=flat).flags & POOR_FIT)
    # the true split against the same flat noise is no poor fit
    assert not np.any(assess_fit(s, params, s.noise_eff, 3.0, flat_noise=flat).flags & POOR_FIT)


def test_narrow_chain_direct_is_found_or_flagged_in_decompose():
    from decomposition import decompose

    n_hard, n_easy = 8, 40
    params, clean = _narrow_chain(n_hard)
    easy = render_profile(_params((200.0, 1.0, 4.0), (204.0, 0.3, 0.02), n_easy), L, T)
    rng = np.random.default_rng(5)
    data = np.concatenate([clean, easy])
    data = data + 1e-3 * data.max() * rng.standard_normal(data.shape)
    r = decompose(data, time_bin_ps=T)
    est = r.params["direct_delay_ps"][:n_hard]
    off = ~(np.abs(est - params["direct_delay_ps"]) <= 2 * params["direct_sigma_ps"])
    assert np.all(~off | (r.flags[:n_hard] != 0))
    assert not np.any(r.flags[n_hard:] & POOR_FIT)


def test_an_echo_brighter_than_the_direct_is_ambiguous():
    from decomposition.constants import BRIGHT_ECHO_RATIO
    from decomposition.flags import AMBIGUOUS
    from decomposition.stages.quality import bright_echo

    p = _params((400.0, 1.0, 1.2), (403.0, 0.5, 0.025), 5)
    ratio = BRIGHT_ECHO_RATIO
    p["ir_delay_ps"] = np.array([[420.0, 440.0], [420.0, 440.0], [420.0, np.nan], [420.0, np.nan], [np.nan, np.nan]])
    p["ir_amplitude"] = np.array([[0.3, 0.99 * ratio], [0.3, 1.01 * ratio], [np.nan, np.nan], [2 * ratio, np.nan],
                                  [np.nan, np.nan]])
    p["ir_amplitude"][2, 0] = 0.5
    p["ir_sigma_ps"] = np.full((5, 2), 1.2)
    p["direct_delay_ps"][3] = np.nan          # no direct: nothing to compare with
    p["direct_amplitude"][3] = np.nan
    assert bright_echo(p).tolist() == [False, True, False, False, False]
    # no inter-reflection slots at all
    assert not bright_echo(_params((400.0, 1.0, 1.2), (403.0, 0.5, 0.025), 2)).any()
    # through the quality stage
    clean = render_profile(p, L, T)
    s = prepare_samples(clean + 0.002 * np.random.default_rng(4).standard_normal(clean.shape), time_axis(T), GridSpec())
    flags = assess_fit(s, p, s.noise_eff, 3.0).flags
    assert (flags & AMBIGUOUS != 0).tolist()[:3] == [False, True, False]


def test_gaussians_closer_than_resolved_sigma_are_ambiguous():
    from decomposition.constants import RESOLVED_SIGMA
    from decomposition.flags import AMBIGUOUS
    from decomposition.stages.quality import unresolved_gaussians

    sigma = 6.0
    p = _params((400.0, 1.0, sigma), (405.0, 0.1, 0.03), 5)
    close = RESOLVED_SIGMA * sigma
    p["ir_delay_ps"] = np.array([[400.0 + 0.99 * close, np.nan],         # the first echo too near the direct
                                 [400.0 + 1.01 * close, np.nan],         # resolved
                                 [500.0, 500.0 + 0.5 * close],           # two echoes one hump
                                 [np.nan, 450.0],                        # the order of the slots does not matter
                                 [np.nan, np.nan]])
    p["ir_amplitude"] = np.where(np.isfinite(p["ir_delay_ps"]), 0.3, np.nan)
    p["ir_sigma_ps"] = np.where(np.isfinite(p["ir_delay_ps"]), sigma, np.nan)
    p["direct_delay_ps"][3] = 455.0
    assert unresolved_gaussians(p).tolist() == [True, False, True, True, False]
    p["direct_sigma_ps"][:] = np.nan                                     # no width (no direct): no judgement
    assert not unresolved_gaussians(p).any()
    assert not unresolved_gaussians(_params((400.0, 1.0, 1.2), (403.0, 0.5, 0.025), 2)).any()
    # through the quality stage
    p["direct_sigma_ps"][:] = sigma
    clean = render_profile(p, L, T)
    s = prepare_samples(clean + 0.002 * np.random.default_rng(4).standard_normal(clean.shape), time_axis(T), GridSpec())
    flags = assess_fit(s, p, s.noise_eff, 3.0).flags
    assert (flags & AMBIGUOUS != 0).tolist() == [True, False, True, True, False]
