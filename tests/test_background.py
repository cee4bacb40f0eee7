"""The background family ``b``, significance inside the window and the OFF_WINDOW flag."""
import numpy as np
import pytest

from core.model import empty_params, render_components, render_profile
from decomposition import decompose
from decomposition.stages.background import (background_significant, background_test, background_threshold,
                                             estimate_background)
from decomposition.model.components import off_window, threshold, window_fraction
from decomposition.constants import FAM_GAUSS, FAM_SSS
from decomposition.flags import FLAG_NAMES, OFF_WINDOW, POOR_FIT
from decomposition.options import parse_components
from decomposition.evaluation.synthetic import make_profiles
from decomposition.model.refine import refine
from decomposition.model.slots import new_state

T = 2.0


def _scene(n, rng, *, amp=1.0, n_bins=256):
    p = empty_params((n,), n_ir=0)
    p["direct_delay_ps"][:] = rng.uniform(60, 120, n)
    p["direct_amplitude"][:] = amp
    p["direct_sigma_ps"][:] = 3.0
    p["sss_delay_ps"][:] = p["direct_delay_ps"] + 6.0
    p["sss_amplitude"][:] = 0.08 * amp
    p["sss_sigma_ps"][:] = 3.0
    p["sss_alpha_per_ps"][:] = 0.03
    return p, render_profile(p, n_bins, T)


# --------------------------------------------------------------------------- the model and the options

def test_render_adds_background_only_when_present():
    p, clean = _scene(3, np.random.default_rng(0))
    assert "background" not in render_components(p, 256, T)
    q = dict(p, background=np.array([0.5, np.nan, -0.25]))
    c = render_components(q, 256, T)
    np.testing.assert_array_equal(c["background"][0], 0.5)
    np.testing.assert_array_equal(c["background"][1], 0.0)       # NaN: no background
    np.testing.assert_allclose(render_profile(q, 256, T) - clean, c["background"])
    with pytest.raises(ValueError, match="background"):
        render_components(dict(p, background=np.zeros(4)), 256, T)


@pytest.mark.parametrize("spec, letters", [("d,s,b", {"d", "s", "b"}), ("d,r,s,b", {"d", "r", "s", "b"}),
                                           ("s,b", {"s", "b"}), ("dsb", {"d", "s", "b"}),
                                           (("direct", "background"), {"d", "b"})])
def test_components_accept_background(spec, letters):
    assert parse_components(spec) == frozenset(letters)


@pytest.mark.parametrize("spec, match", [("b", "needs a component family"), ("d,x", "unknown component family 'x'"),
                                         ("r,b", "need the direct"), ("", "non-empty")])
def test_bad_components_rejected(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_components(spec)


def test_background_needs_convscd():
    _, clean = _scene(2, np.random.default_rng(0))
    with pytest.raises(ValueError, match="convscd"):
        decompose(clean, T, method="gradbm", components="d,s,b")


# --------------------------------------------------------------------------- the two rules

def test_estimate_background_known_offset():
    rng = np.random.default_rng(1)
    _, clean = _scene(200, rng)
    y = clean + 0.07 + 0.01 * rng.standard_normal(clean.shape)
    b = estimate_background(y)
    # the faint sss tail within the clip biases it up by a fraction of the noise (the joint fit
    # of the refinement removes that)
    assert abs(b.mean() - 0.07) < 0.005 and b.std() < 0.003
    direct = render_profile({k: v for k, v in _scene(200, rng)[0].items() if k.startswith("direct")}, 256, T)
    counts = rng.poisson(400 * direct + 3.0).astype(float)
    bc = estimate_background(counts, counts >= 0, counts=True)
    assert abs(bc.mean() - 3.0) < 0.3
    with pytest.raises(ValueError, match="shape"):
        estimate_background(np.zeros(5))


def test_estimate_background_of_faint_counts():
    """Below one count per bin the estimate judges a sample by the mean count around it: a faint
    sss tail is not taken for background (the per-sample clip took ~0.2 counts per bin for it)."""
    for background, true_counts in ((0.0, 0.0), (0.02, None)):
        d = make_profiles(200, 256, seed=5, kinds="d+s", photons_per_pixel=100.0, background=background)
        b_true = np.broadcast_to(d.background, (200,)) if true_counts is None else np.zeros(200)
        b = estimate_background(d.noisy.astype(float), counts=True)
        assert (b >= 0).all()
        # true offsets 0 and ~0.21 counts per bin; the faint tails inside the clip add a little
        assert 0.0 <= np.mean(b - b_true) < 0.04 and np.std(b - b_true) < 0.06


def test_background_threshold_is_the_information_criterion():
    fit = np.ones((3, 256), bool)
    fit[1, :56] = False
    fit[2] = False
    np.testing.assert_allclose(background_threshold(fit), [np.log(256), np.log(200), 0.0])
    np.testing.assert_array_equal(background_threshold(fit, 25.0), 25.0)
    assert background_significant(np.array([5.5, 5.6]), background_threshold(fit[:1])).tolist() == [False, True]


def test_background_false_positive_rate_white_noise():
    """No offset in the scene: kept in P(chi2_1 >= ln 256) = 1.9 % of the pixels, none at 25."""
    d = make_profiles(400, 256, seed=11, kinds="d+s", nsr=0.02)
    got = decompose(d.noisy, T, t0_ps=d.t0_ps, components="d,r,s,b")
    rate = np.mean(got.params["background"] != 0.0)
    assert 0.005 <= rate <= 0.04
    strict = decompose(d.noisy, T, t0_ps=d.t0_ps, components="d,r,s,b", background_chi2=25.0)
    assert np.all(strict.params["background"] == 0.0)


def test_background_test_is_the_increase_of_the_data_term():
    """delta chi2 equals RSS(b removed, amplitudes refitted) - RSS(joint fit), in noise units."""
    rng = np.random.default_rng(2)
    p, clean = _scene(5, rng)
    y = clean + 0.02 + 0.01 * rng.standard_normal(clean.shape)
    comps = render_components({k: (np.where(np.isfinite(v), 1.0, v) if k.endswith("amplitude") else v)
                               for k, v in p.items()}, 256, T)
    A = np.stack([comps["direct"], comps["sss"]], axis=1)
    A1 = np.concatenate([A, np.ones((5, 1, 256))], axis=1)
    rss = []
    for design in (A1, A):
        c = np.stack([np.linalg.lstsq(design[i].T, y[i], rcond=None)[0] for i in range(5)])
        rss.append(((y - np.einsum("pk,pkl->pl", c, design)) ** 2).sum(axis=1))
        if design is A1:
            b = c[:, -1]
    s = np.full(5, 0.01)
    dchi2, se = background_test(y, dict(p, background=b), np.ones_like(y), s, time_bin_ps=T)
    np.testing.assert_allclose(dchi2, (rss[1] - rss[0]) / s**2, rtol=1e-6)
    assert np.all(se > 0) and np.all(se < 0.01)
    assert background_significant(np.array([24.9, 25.0]), 25.0).tolist() == [False, True]


def test_refine_fits_background_jointly():
    rng = np.random.default_rng(3)
    p, clean = _scene(40, rng)
    y = clean + 0.05 + 0.005 * rng.standard_normal(clean.shape)
    start = {k: v.copy() for k, v in p.items()}
    start["direct_delay_ps"] = start["direct_delay_ps"] + 0.5
    out, info = refine(y, dict(start, background=np.zeros(40)), time_bin_ps=T, shared_sigma=True,
                       sss_after_direct=True, fit_background=True)
    assert info["refined"].all()
    np.testing.assert_allclose(out["background"], 0.05, atol=0.003)
    np.testing.assert_allclose(out["sss_alpha_per_ps"], 0.03, rtol=0.05)
    # held fixed: subtracted and returned as given
    held, _ = refine(y, dict(start, background=np.full(40, 0.05)), time_bin_ps=T, shared_sigma=True)
    np.testing.assert_array_equal(held["background"], 0.05)
    np.testing.assert_allclose(held["direct_delay_ps"], p["direct_delay_ps"], atol=0.1)


# --------------------------------------------------------------------------- decompose with "b"

def test_background_recovered_white_and_lifetime_unbiased():
    rng = np.random.default_rng(4)
    p, clean = _scene(60, rng)
    y = clean + 0.01 * rng.standard_normal(clean.shape)
    ref = decompose(y, T, components="d,s")
    off = decompose(y + 0.05, T, components="d,s")
    got = decompose(y + 0.05, T, components="d,s,b", stderr=True)
    b = got.params["background"]
    assert abs(b.mean() - 0.05) < 0.001 and np.all(np.abs(b - 0.05) < 0.005)
    assert np.all(np.isfinite(got.params["background_stderr"]))
    a_ref, a_off, a_b = (np.median(r.params["sss_alpha_per_ps"]) for r in (ref, off, got))
    # the lifetime with the offset fitted is that of the same data without an offset
    assert abs(a_b - a_ref) < 0.0002 and abs(a_b - 0.03) < 0.002
    assert abs(a_off - 0.03) > 0.002             # the offset left in biases the lifetime
    assert not np.any(got.flags & POOR_FIT)
    np.testing.assert_allclose(got.residual.std(axis=1), 0.01, rtol=0.2)


def test_background_recovered_poisson_counts():
    rng = np.random.default_rng(5)
    p, clean = _scene(60, rng, amp=400.0)
    y = rng.poisson(clean + 5.0).astype(np.uint16)
    got = decompose(y, T, components="d,s,b", stderr=True)
    assert got.info["noise_model"] == "poisson"
    b, se = got.params["background"], got.params["background_stderr"]
    assert abs(b.mean() - 5.0) < 0.1
    # the spread matches the stated standard error
    assert 0.6 < b.std() / np.median(se) < 1.5
    assert abs(np.median(got.params["sss_alpha_per_ps"]) - 0.03) < 0.001


def test_background_left_out_where_there_is_none():
    rng = np.random.default_rng(6)
    p, clean = _scene(60, rng)
    y = clean + 0.01 * rng.standard_normal(clean.shape)
    ref = decompose(y, T, components="d,s", refine=True)     # "b" always refines
    got = decompose(y, T, components="d,s,b")
    b = got.params["background"]
    # not significant in (nearly) every pixel: reported as exactly 0
    assert np.mean(b == 0.0) >= 0.95
    zero = b == 0.0
    # the same answer as without the family (the first estimate, subtracted before the sparse
    # coding, can move a pixel's detection)
    rel = np.abs(got.params["sss_alpha_per_ps"] / ref.params["sss_alpha_per_ps"] - 1)
    assert np.mean(rel[zero] < 1e-3) >= 0.95
    assert "background" not in ref.params


def test_background_nan_where_not_decomposed():
    rng = np.random.default_rng(7)
    _, clean = _scene(3, rng)
    y = clean + 0.02
    y[1, 5] = np.nan
    got = decompose(y, T, components="d,s,b", nan_policy="omit")
    assert np.isnan(got.params["background"][1]) and np.isfinite(got.params["background"][[0, 2]]).all()


# --------------------------------------------------------------------------- thresholds and the window

def _state(fams, delays, amps, sigma=3.0, alpha=0.03):
    st = new_state(1, len(fams))
    for k, (f, d, a) in enumerate(zip(fams, delays, amps)):
        st["fam"][0, k], st["delay"][0, k], st["amp"][0, k] = f, d, a
    st["lsig"][:] = np.log(sigma)
    st["lalp"][:] = np.log(alpha)
    return st


def test_window_fraction_and_off_window_known_answers():
    t = 0.0 + T * np.arange(256)
    st = _state([FAM_GAUSS, FAM_GAUSS, FAM_GAUSS, FAM_SSS], [-3.0, 0.0, 200.0, 600.0], [1, 1, 1, 1])
    frac = window_fraction(st, t)[0]
    # a Gaussian centred on the first sample has half of its area inside (plus half a bin)
    assert abs(frac[1] - 0.5 - 0.5 * T / (3.0 * np.sqrt(2 * np.pi))) < 0.01
    assert frac[2] > 0.999 and frac[3] < 0.01
    assert off_window(st, t)[0].tolist() == [True, True, False, True]


def test_a_peak_within_two_widths_of_the_window_edge_runs_off_it():
    # its rise (at the start) or fall (at the end) is cut: the delay is read off one side
    from decomposition.model.components import runs_off_window
    from decomposition.constants import OFF_WINDOW_EDGE_SIGMA

    t = 0.0 + T * np.arange(256)
    half = T / 2
    edge = OFF_WINDOW_EDGE_SIGMA * 3.0
    delays = np.array([[-half + 0.9 * edge, -half + 1.1 * edge, t[-1] + half - 0.9 * edge,
                        t[-1] + half - 1.1 * edge, -half + 0.5 * edge]])
    active = np.ones((1, 5), bool)
    peaked = np.array([[True, True, True, True, False]])       # the last: an sss onset
    inside = np.ones((1, 5))
    got = runs_off_window(active, peaked, delays, inside, t, width_ps=3.0)
    assert got.tolist() == [[True, False, True, False, False]]
    assert not runs_off_window(active, peaked, delays, inside, t).any()   # without widths: centres only
    # the Gaussian path's rule: each atom by its own width
    st = _state([FAM_GAUSS, FAM_GAUSS], [5.0, 12.0], [1, 1])
    st["lsig"][:] = np.log([3.0, 3.0])
    assert off_window(st, t)[0].tolist() == [True, False]


def test_a_direct_just_before_the_window_placed_inside_it_is_off_window():
    # photon counts of a direct 3-7 ps before the first bin, the response modelled: the fit
    # places the direct a few ps inside the window (the data cannot tell), its rise cut
    from streaklab.bench import realism

    setup = realism.effect_setup("truncated", T)
    d = make_profiles(120, 256, seed=4000, kinds=setup["kinds"], time_bin_ps=T, photons_per_pixel=100.0,
                      **setup["options"])
    params, res = realism.run_variant("modelled", d, setup, T)
    d_err, _ = realism.pixel_errors(d.params, params)
    off = np.abs(d_err) > 8
    assert off.sum() >= 5
    assert np.all(res.flags[off] != 0)
    assert np.mean((res.flags & OFF_WINDOW) != 0) > 0.8


def test_threshold_keeps_a_significant_faint_atom():
    t = T * np.arange(256)
    st = _state([FAM_GAUSS, FAM_GAUSS], [50.0, 300.0], [1.0, 0.01])
    kept = threshold({k: v.copy() for k, v in st.items()}, t, 0.05)
    assert kept["fam"][0].tolist() == [FAM_GAUSS, 0]                 # the relative rule alone
    # energy of the faint atom: 1e-4 * sum g^2 = 1e-4 * sqrt(pi) sigma / T = 2.66e-4
    e = 1e-4 * np.sqrt(np.pi) * 3.0 / T
    for s, keep in ((np.sqrt(e / 25.0) * 0.99, True), (np.sqrt(e / 25.0) * 1.01, False)):
        out = threshold({k: v.copy() for k, v in st.items()}, t, 0.05, np.array([s]), 25.0)
        assert (out["fam"][0, 1] == FAM_GAUSS) == keep


def test_a_faint_atom_near_a_larger_sss_onset_passes_at_the_sss_factor_times_the_bar():
    """A faint Gaussian 2 widths after a larger sss's onset, 10 widths after the direct: the sss
    hides it unless its energy reaches SSS_RESOLVED_CHI2_FACTOR x the bar; a larger Gaussian as
    close hides it whatever its energy; with ``sss_factor=None`` every larger atom hides alike."""
    from decomposition.model.components import window_measures
    from decomposition.constants import SSS_RESOLVED_CHI2_FACTOR

    t = T * np.arange(256)
    st = _state([FAM_GAUSS, FAM_SSS, FAM_GAUSS], [50.0, 74.0, 80.0], [1.0, 0.3, 0.01])
    h, e = window_measures(st, t)
    assert h[0, 1] > h[0, 2] and h[0, 2] < 0.05 * h[0].max()      # the sss is the larger, the echo faint
    bar = 25.0
    for multiple, keep in ((1.01 * SSS_RESOLVED_CHI2_FACTOR, True), (0.99 * SSS_RESOLVED_CHI2_FACTOR, False),
                           (2.0, False)):
        s = np.array([np.sqrt(e[0, 2] / (multiple * bar))])          # the echo's energy: multiple x the bar
        out = threshold({k: v.copy() for k, v in st.items()}, t, 0.05, s, bar)
        assert (out["fam"][0, 2] == FAM_GAUSS) == keep
        assert out["fam"][0, 1] == FAM_SSS and out["fam"][0, 0] == FAM_GAUSS
        old = threshold({k: v.copy() for k, v in st.items()}, t, 0.05, s, bar, sss_factor=None)
        assert old["fam"][0, 2] != FAM_GAUSS
    # a larger Gaussian as close (the direct 2 widths before it) hides it at any energy
    g = _state([FAM_GAUSS, FAM_GAUSS], [74.0, 80.0], [1.0, 0.01])
    hg, eg = window_measures(g, t)
    out = threshold({k: v.copy() for k, v in g.items()}, t, 0.05, np.array([np.sqrt(eg[0, 1] / 1e4)]), bar)
    assert out["fam"][0, 1] != FAM_GAUSS


def _echo_scene(n, rng, direct_delay_ps):
    """A direct truncated at the window start and an echo at 1 % of the direct's peak, 5 noise
    sigmas above the noise."""
    p = empty_params((n,), n_ir=1)
    p["direct_delay_ps"][:] = direct_delay_ps
    p["direct_amplitude"][:] = 1.0
    p["direct_sigma_ps"][:] = 3.0
    p["ir_delay_ps"][:, 0] = rng.uniform(150, 350, n)
    p["ir_amplitude"][:, 0] = 0.01
    p["ir_sigma_ps"][:, 0] = 3.0
    y = render_profile(p, 256, T, 0.0) + 0.002 * rng.standard_normal((n, 256))
    return p, y


def test_one_percent_echo_found_with_truncated_direct():
    rng = np.random.default_rng(8)
    p, y = _echo_scene(200, rng, -3.0)
    r = decompose(y, T, t0_ps=0.0, components="d,r")
    found = (np.abs(r.params["ir_delay_ps"] - p["ir_delay_ps"][:, :1]) < 9.0).any(axis=1)
    assert found.mean() >= 0.95
    assert np.all(r.flags & OFF_WINDOW)                       # the direct runs off the first bin
    # with the relative rule alone the echo is lost
    r0 = decompose(y[:20], T, t0_ps=0.0, components="d,r", significance_chi2=0.0)
    assert not np.isfinite(r0.params["ir_delay_ps"]).any()


def test_off_window_not_set_for_components_inside():
    rng = np.random.default_rng(9)
    p, y = _echo_scene(20, rng, 60.0)
    r = decompose(y, T, t0_ps=0.0, components="d,r")
    assert not np.any(r.flags & OFF_WINDOW)
    assert FLAG_NAMES[2048] == "OFF_WINDOW"


def test_lagged_noise_is_sigma_for_white_noise_and_larger_for_pink():
    """Known answers: white noise of sigma 0.01 reads 0.01 at every lag (within the estimate's
    sampling spread); a random walk (the extreme of low-frequency noise) reads sqrt(lag / 2)
    times its step, far above what second differences see."""
    from decomposition.noise import lagged_noise_sigma, noise_sigma

    rng = np.random.default_rng(3)
    white = 0.01 * rng.standard_normal((50, 4096))
    for lag in (1, 4, 64):
        np.testing.assert_allclose(np.median(lagged_noise_sigma(white, None, lag)), 0.01, rtol=0.03)
    walk = np.cumsum(0.01 * rng.standard_normal((50, 4096)), axis=1)
    for lag in (4, 64):
        np.testing.assert_allclose(np.median(lagged_noise_sigma(walk, None, lag)), 0.01 * np.sqrt(lag / 2),
                                   rtol=0.1)
    assert np.median(noise_sigma(walk)) < 0.01
    with pytest.raises(ValueError, match="lag_bins"):
        lagged_noise_sigma(white, None, 0)


def test_pink_noise_bumps_are_mostly_not_significant_components():
    """One direct under strong pink noise (NSR 0.1): weighed with the sample-to-sample noise,
    the significance route turns the noise's slow bumps into 3.3 extra components per pixel;
    with the noise across SIGNIFICANCE_LAG_BINS samples, 0.77 (the relative rule alone: 0).
    The energy test assumes white noise; this keeps its error on correlated noise bounded."""
    from decomposition.evaluation.synthetic_noise import noise_realisation

    rng = np.random.default_rng(12)
    n, L = 60, 512
    p = empty_params((n,), n_ir=0)
    p["direct_delay_ps"][:] = rng.uniform(300, 700, n)
    p["direct_amplitude"][:] = 1.0
    p["direct_sigma_ps"][:] = 3.0
    clean = render_profile(p, L, T)
    y = clean + noise_realisation(clean, 0.1, "pink", rng=rng)
    count = lambda r: (np.isfinite(r.params["ir_delay_ps"]).sum(axis=1)  # noqa: E731
                       + np.isfinite(r.params["sss_delay_ps"]))
    got = count(decompose(y, T))
    ref = count(decompose(y, T, significance_chi2=0.0))
    assert ref.mean() == 0.0
    assert got.mean() < 1.0


# --------------------------------------------------------------------------- light above the offset

def test_light_test_is_the_data_term_of_the_offset_alone_less_the_model():
    from decomposition.stages.background import light_test
    from decomposition.noise import count_deviance

    rng = np.random.default_rng(12)
    p, clean = _scene(4, rng, amp=50.0)
    y = rng.poisson(clean + 2.0).astype(float)
    fit = np.ones(y.shape, bool)
    fit[:, :10] = False
    model = clean + 2.0
    flat = np.broadcast_to((y[:, 10:].mean(axis=1))[:, None], y.shape)
    want = count_deviance(y, flat, fit) - count_deviance(y, model, fit)
    np.testing.assert_allclose(light_test(y, model, fit, counts=True), want, rtol=1e-12)
    assert np.all(want > 100)
    z = clean + 0.3 + 0.01 * rng.standard_normal(clean.shape)
    rss0 = ((z[:, 10:] - z[:, 10:].mean(axis=1, keepdims=True)) ** 2).sum(axis=1)
    rss = ((z[:, 10:] - (clean + 0.3)[:, 10:]) ** 2).sum(axis=1)
    np.testing.assert_allclose(light_test(z, clean + 0.3, fit, counts=False, noise=np.full(4, 0.01)),
                               (rss0 - rss) / 1e-4, rtol=1e-10)


@pytest.mark.parametrize("level", [0.2, 5.0])
def test_pure_background_counts_are_empty_with_their_offset(level):
    # no light but the offset: every component the fit finds is noise, and the relative
    # threshold keeps the largest of them whatever its size
    from decomposition.flags import EMPTY

    y = np.random.default_rng(3).poisson(level, (60, 256)).astype(np.uint16)
    got = decompose(y, T, components="d,s,r,b", stderr=True)
    assert np.all(got.flags == EMPTY)
    # the standard error of a mean of Poisson counts (the dispersion measured, about 1)
    ratio = got.params["background_stderr"] / np.sqrt(y.mean(axis=1) / 256)
    assert np.all((ratio > 0.8) & (ratio < 1.25))
    # the same pixels as a (6, 10) image
    img = decompose(y.reshape(6, 10, 256), T, components="d,s,r,b", stderr=True)
    np.testing.assert_array_equal(img.params["background_stderr"].ravel(), got.params["background_stderr"])
    np.testing.assert_array_equal(img.params["background"].ravel(), got.params["background"])
    assert got.info["cleared_unlit"] == 60
    for key in ("direct_delay_ps", "sss_delay_ps"):
        assert np.all(np.isnan(got.params[key]))
    assert np.all(np.isnan(got.params["ir_delay_ps"]))
    np.testing.assert_allclose(got.params["background"], y.mean(axis=1), rtol=1e-12)


def test_pure_offset_float_data_are_empty_and_a_signal_on_it_is_kept():
    from decomposition.flags import EMPTY

    rng = np.random.default_rng(4)
    flat = 3.0 + 0.05 * rng.standard_normal((30, 256))
    p, clean = _scene(30, rng, amp=1.0)
    lit = clean + 3.0 + 0.05 * rng.standard_normal(clean.shape)
    got = decompose(np.concatenate([flat, lit]), T, components="d,s,b")
    assert np.all(got.flags[:30] == EMPTY)
    assert got.info["cleared_unlit"] == 30
    np.testing.assert_allclose(got.params["background"][:30], flat.mean(axis=1), rtol=1e-12)
    assert not np.any(got.flags[30:] & EMPTY)
    np.testing.assert_allclose(got.params["direct_delay_ps"][30:], p["direct_delay_ps"], atol=0.5)


def test_refined_widths_stay_within_the_solver_bounds_and_are_flagged_there():
    from decomposition.flags import AT_BOUND
    from decomposition.stages.label import params_at_bound
    from decomposition.options import GridSpec
    from decomposition.model.slots import shape_bounds

    bounds = shape_bounds(GridSpec(), 4.0)
    lo_s, hi_s = np.exp(bounds["lsig"])
    p = empty_params((4,), n_ir=1)
    p["direct_sigma_ps"][:] = [3.0, lo_s, 3.0, np.nan]
    p["ir_sigma_ps"][:, 0] = [np.nan, np.nan, hi_s, np.nan]
    p["sss_sigma_ps"][:] = [3.0, np.nan, np.nan, 3.0]
    p["sss_alpha_per_ps"][:] = [0.03, np.nan, np.nan, np.exp(bounds["lalp"][0])]
    assert params_at_bound(p, bounds).tolist() == [False, True, True, True]
    # a direct far narrower than a bin on a pure background: refined at the bound, flagged
    y = np.full((1, 256), 20.0)
    y[0, 100] = 400.0
    got = decompose(y, T, components="d,b")
    assert got.params["direct_sigma_ps"][0] >= lo_s * (1 - 1e-9)
    assert got.flags[0] & AT_BOUND
