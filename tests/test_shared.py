"""Shared parameters of an image: estimated once from all pixels, held in every pixel's fit.

Known answers: cubes drawn with one PSF width, one onset, one decay rate per region (or a
PSF that varies smoothly over the image) and noise; the shared estimate must lie within a
few standard errors of the truth, every pixel must hold it, and the held fit must recover
the remaining parameters at least as well as the free one.
"""
import numpy as np
import pytest

from decomposition import decompose
from decomposition.evaluation.synthetic import SceneRanges, make_cube
from decomposition.image import decompose_image
from decomposition.image.pooling import lit_score, pooled, select_pixels
from decomposition.image.shared import SharedEstimate
from decomposition.model.fisher import standard_errors
from decomposition.model.refine import refine
from decomposition.options import OptionError

TB, NT = 2.0, 96


def _cube(seed, ny=8, nx=8, nsr=0.08, **ranges):
    base = dict(sigma_ps=(3.0, 3.0), alpha_per_ps=(0.03, 0.03), direct_position=(0.1, 0.3))
    base.update(ranges)
    return make_cube(ny, nx, NT, nsr=nsr, noise="white", seed=seed, kinds="d+s", time_bin_ps=TB,
                     ranges=SceneRanges(**base))


def _present(result, key):
    v = result.params[key]
    return v[np.isfinite(v)]


def _rmse(estimate, truth):
    e = np.asarray(estimate) - np.asarray(truth)
    return float(np.sqrt(np.nanmean(e ** 2)))


def test_hold_keeps_the_value_exactly_and_fits_the_rest_around_it():
    d = make_cube(1, 6, NT, seed=3, kinds="d+s", time_bin_ps=TB,
                  ranges=SceneRanges(sigma_ps=(3.0, 3.0), alpha_per_ps=(0.03, 0.03)))
    truth = {k: v[0] for k, v in d.params.items()}
    start = dict(truth, direct_sigma_ps=truth["direct_sigma_ps"] * 1.3, sss_sigma_ps=truth["sss_sigma_ps"] * 1.3,
                 direct_amplitude=truth["direct_amplitude"] * 1.5, sss_amplitude=truth["sss_amplitude"] * 0.5,
                 sss_alpha_per_ps=truth["sss_alpha_per_ps"] * 1.2)
    hold = {"sigma_ps": np.array([3.0, 3.0, 3.0, np.nan, 3.0, 3.0]), "sss_alpha_per_ps": 0.03}
    out, _ = refine(d.clean[0], start, time_bin_ps=TB, shared_sigma=True, sss_after_direct=True, hold=hold,
                     max_iter=200, ftol=1e-14)
    held = np.isfinite(hold["sigma_ps"])
    np.testing.assert_array_equal(out["direct_sigma_ps"][held], 3.0)
    np.testing.assert_array_equal(out["sss_alpha_per_ps"], 0.03)
    # noiseless data, the truth held: the free parameters stay at or go back to the truth
    np.testing.assert_allclose(out["direct_delay_ps"][held], truth["direct_delay_ps"][held], atol=1e-6)
    np.testing.assert_allclose(out["sss_amplitude"][held], truth["sss_amplitude"][held], rtol=1e-6)
    # NaN leaves that pixel's width free (refined back from 1.3x)
    assert abs(out["direct_sigma_ps"][~held][0] - 3.0) < 0.05
    se = standard_errors(d.clean[0] + 0.01, out, time_bin_ps=TB, shared_sigma=True, hold=hold)
    free = standard_errors(d.clean[0] + 0.01, out, time_bin_ps=TB, shared_sigma=True)
    assert np.isnan(se["direct_sigma_ps_stderr"][held]).all() and np.isnan(se["sss_alpha_per_ps_stderr"]).all()
    assert np.isfinite(se["direct_sigma_ps_stderr"][~held]).all()
    # fewer unknowns: the amplitudes are known better with the width and rate held
    assert (se["sss_amplitude_stderr"] <= free["sss_amplitude_stderr"] * (1 + 1e-9)).all()


def test_shared_psf_known_answer_and_held_in_every_pixel():
    d = _cube(seed=11, nsr=0.12)
    free = decompose(d.noisy, TB, components="d,s", stderr=True)
    res = decompose_image(d.noisy, TB, components="d,s", stderr=True, shared="psf")
    rec = res.info["shared"]
    est, se = rec["psf_sigma_ps"], rec["psf_sigma_ps_stderr"]
    assert 0.003 < se < 0.2
    assert abs(est - 3.0) < 4 * se
    for key in ("direct_sigma_ps", "sss_sigma_ps"):
        np.testing.assert_array_equal(_present(res, key), est)
        np.testing.assert_array_equal(_present(res, key + "_stderr"), se)
    # the held width helps the rest: the sss amplitude and onset closer to the truth
    for key in ("sss_amplitude", "direct_delay_ps"):
        assert _rmse(res.params[key], d.params[key]) <= _rmse(free.params[key], d.params[key]), key


def test_shared_psf_standard_error_covers_the_truth():
    # loose coverage: over independent cubes the truth lies within 2.5 SE of most estimates
    z = []
    for seed in (21, 22, 23, 24):
        rec = decompose_image(_cube(seed, ny=6, nx=6).noisy, TB, components="d,s", shared="psf").info["shared"]
        z.append((rec["psf_sigma_ps"] - 3.0) / rec["psf_sigma_ps_stderr"])
    z = np.abs(z)
    assert (z < 2.5).sum() >= 3 and z.max() < 5, z


def test_shared_delay_and_psf_together():
    d = _cube(seed=12, direct_position=(0.2, 0.2))
    truth = float(d.params["direct_delay_ps"][0, 0])
    assert np.ptp(d.params["direct_delay_ps"]) == 0
    free = decompose(d.noisy, TB, components="d,s", stderr=True)
    res = decompose_image(d.noisy, TB, components="d,s", stderr=True, shared="delay,psf")
    rec = res.info["shared"]
    assert rec["names"] == ["psf", "delay"] and rec["delay_key"] == "direct_delay_ps"
    assert abs(rec["delay_ps"] - truth) < 4 * rec["delay_ps_stderr"] and rec["delay_ps_stderr"] < 0.2
    np.testing.assert_array_equal(_present(res, "direct_delay_ps"), rec["delay_ps"])
    np.testing.assert_array_equal(_present(res, "direct_delay_ps_stderr"), rec["delay_ps_stderr"])
    assert _rmse(res.params["sss_amplitude"], d.params["sss_amplitude"]) \
        <= _rmse(free.params["sss_amplitude"], d.params["sss_amplitude"])


def test_shared_alpha_per_region():
    a = _cube(seed=13, alpha_per_ps=(0.02, 0.02))
    b = _cube(seed=14, alpha_per_ps=(0.045, 0.045))
    cube = np.concatenate([a.noisy[:, :4], b.noisy[:, 4:]], axis=1)
    regions = np.zeros((8, 8), np.int32)
    regions[:, 4:] = 7
    regions[0, 0] = -1                                  # left free
    res = decompose_image(cube, TB, components="d,s", stderr=True, shared="alpha", regions=regions)
    rec = res.info["shared"]
    assert rec["regions"] is True and set(rec["sss_alpha_per_ps"]) == {"0", "7"}
    for label, truth in (("0", 0.02), ("7", 0.045)):
        v, se = rec["sss_alpha_per_ps"][label], rec["sss_alpha_per_ps_stderr"][label]
        assert abs(v - truth) < 4 * se and se < 0.1 * truth, (label, v, se)
    alpha = res.params["sss_alpha_per_ps"]
    for label in (0, 7):
        inside = (regions == label) & np.isfinite(alpha)
        np.testing.assert_array_equal(alpha[inside], rec["sss_alpha_per_ps"][str(label)])
    assert alpha[0, 0] not in (rec["sss_alpha_per_ps"]["0"], rec["sss_alpha_per_ps"]["7"])


def test_psf_map_follows_a_slowly_varying_width():
    # a width that grows along y (a streak camera's slit): 2.5 ps at the top, 4.5 ps at the bottom
    ny, nx = 9, 6
    rows = [_cube(seed=30 + i, ny=1, nx=nx, sigma_ps=(s, s)) for i, s in enumerate(np.linspace(2.5, 4.5, ny))]
    cube = np.concatenate([r.noisy for r in rows], axis=0)
    res = decompose_image(cube, TB, components="d,s", shared="psf", psf_map=True)
    m = res.info["shared"]["psf_map"]
    coef, se = np.array(m["coefficients_ps"]), np.sqrt(np.diag(m["covariance_ps2"]))
    # truth in normalised y (u in -1..1): 3.5 + 1.0 u, no x or curvature
    truth = np.array([3.5, 1.0, 0.0, 0.0, 0.0, 0.0])
    assert (np.abs(coef - truth) < 4 * se + 1e-9).all(), (coef, se)
    width = res.params["direct_sigma_ps"]
    u = (np.arange(ny)[:, None] - 4.0) / 4.0
    v = (np.arange(nx)[None, :] - 2.5) / 2.5
    expect = coef[0] + coef[1] * u + coef[2] * v + coef[3] * u * u + coef[4] * u * v + coef[5] * v * v
    np.testing.assert_allclose(width[np.isfinite(width)], np.broadcast_to(expect, width.shape)[np.isfinite(width)],
                               rtol=1e-12)


def test_pooled_location_is_robust_and_its_error_honest():
    rng = np.random.default_rng(0)
    se = rng.uniform(0.05, 0.2, 400)
    v = 3.0 + rng.normal(0, 1, 400) * se
    v[:20] = 30.0                                        # outliers
    est, err, n = pooled(v, se)
    assert n == 380 and abs(est - 3.0) < 4 * err and err < 0.01
    assert np.isnan(pooled([np.nan], [0.1])[0])


def test_the_subsample_is_deterministic_and_takes_lit_pixels():
    cube = np.zeros((4, 5, 16))
    cube[1:3, 1:4, 8] = np.arange(1, 7).reshape(2, 3)
    idx = select_pixels(lit_score(cube), np.zeros((4, 5), int))
    np.testing.assert_array_equal(idx, [11, 12, 13])      # the brighter half of the six lit
    np.testing.assert_array_equal(idx, select_pixels(lit_score(cube), np.zeros((4, 5), int)))


def test_the_record_gives_back_the_same_held_values():
    d = _cube(seed=15, ny=6, nx=6)
    regions = np.zeros((6, 6), np.int64)
    res = decompose_image(d.noisy, TB, components="d,s", shared="psf,delay,alpha", psf_map=True, regions=regions)
    import json

    again = SharedEstimate.from_record(json.loads(json.dumps(res.info["shared"])))
    h1, e1 = SharedEstimate.from_record(res.info["shared"]).hold(regions)
    h2, e2 = again.hold(regions)
    for k in h1:
        np.testing.assert_array_equal(h1[k], h2[k])
        np.testing.assert_array_equal(e1[k], e2[k])


@pytest.mark.parametrize("kwargs, message", [
    (dict(shared="psf,width"), "unknown parameter 'width'"),
    (dict(shared="alpha", regions=np.zeros((3, 3), int)), "label image of shape"),
    (dict(shared="alpha", regions=np.zeros((4, 4))), "label image of shape"),
    (dict(shared="psf", regions=np.zeros((4, 4), int)), "give shared='alpha' too"),
    (dict(shared="delay", psf_map=True), "give shared='psf' too"),
    (dict(shared="psf", psf_map=True, irf=(np.exp(-0.5 * np.arange(-8, 9) ** 2 / 4), TB)), "measured response"),
])
def test_bad_options_are_refused_in_one_line(kwargs, message):
    cube = _cube(seed=16, ny=4, nx=4).noisy
    with pytest.raises(OptionError, match=message):
        decompose_image(cube, TB, components="d,s", **kwargs)


def test_no_lit_pixel_is_a_clear_error():
    with pytest.raises(ValueError, match="no lit pixel"):
        decompose_image(np.zeros((3, 3, NT)), TB, components="d,s", shared="psf")
    with pytest.raises(ValueError, match=r"hold\['sigma_ps'\]: values must be > 0"):
        decompose(np.ones((2, NT)), TB, hold={"sigma_ps": -1.0})
    with pytest.raises(ValueError, match="hold: unknown parameter"):
        decompose(np.ones((2, NT)), TB, hold={"width": 1.0})


def test_the_shared_psf_of_a_count_image_is_not_pulled_by_refits_that_step_into_a_worse_deviance():
    # reweighted refits (1 / model weights) stepped some pixels far off and the pooled deviance
    # then favoured another width: 4.37 ps for this image; the data's effective width is
    # sqrt(4^2 + 2^2 / 12) = 4.04 ps (sigma 4 ps, bins of 2 ps integrated)
    from decomposition.evaluation.spatial_scenes import make_spatial_scene

    scene = make_spatial_scene(16, 16, 256, seed=0, photons_per_pixel=1000.0)
    got = decompose_image(scene.profiles, 2.0, shared="psf", t0_ps=scene.t0_ps, noise="poisson")
    assert abs(got.info["shared"]["psf_sigma_ps"] - np.sqrt(16 + 4 / 12)) < 0.2


def test_the_pooled_likelihood_refits_an_even_thinning_of_the_selected_pixels(monkeypatch):
    import decomposition.image.shared as shared

    monkeypatch.setattr(shared, "N_LIKELIHOOD_PIXELS", 12)
    seen = []
    misfit = shared._pooled_misfit

    def spy(profiles, *args, **kwargs):
        seen.append(profiles.shape[0])
        return misfit(profiles, *args, **kwargs)

    monkeypatch.setattr(shared, "_pooled_misfit", spy)
    d = _cube(seed=11, nsr=0.12)          # 64 pixels, the brighter half selected
    rec = decompose_image(d.noisy, TB, components="d,s", shared="psf").info["shared"]
    assert rec["pixels"]["selected"] > 12
    assert rec["pixels"]["likelihood"] == 12 and seen and set(seen) == {12}
    est, se = rec["psf_sigma_ps"], rec["psf_sigma_ps_stderr"]
    assert abs(est - 3.0) < 4 * se and se < 0.2


def test_the_excess_spread_of_widths_is_what_their_errors_do_not_explain():
    from decomposition.image.pooling import excess_spread

    rng = np.random.default_rng(3)
    se = np.full(4000, 0.05)                        # 5 % errors
    one = 4.0 * np.exp(0.05 * rng.standard_normal(4000))
    assert excess_spread(one, se * one) < 0.03      # one width: its errors explain the scatter (to the MAD's noise)
    many = 4.0 * np.exp(np.hypot(0.05, 0.3) * rng.standard_normal(4000))
    assert abs(excess_spread(many, se * many) - 0.3) < 0.02
    assert np.isnan(excess_spread([np.nan, -1.0], [0.1, 0.1]))


def test_a_psf_shared_by_default_only_where_the_pixels_are_one_instrument():
    """estimate_shared(one_instrument=True) refuses a PSF the pixels' own widths do not share (each
    draws its own, 2-8 ps) and records how far they scatter; one PSF passes."""
    from decomposition.evaluation.spatial_scenes import make_spatial_scene
    from decomposition.evaluation.synthetic import make_profiles
    from decomposition.image.shared import ONE_INSTRUMENT_SPREAD, NotOneInstrument, image_estimate

    d = make_profiles(64, 128, nsr=0.02, seed=4, time_bin_ps=2.0)
    cube = d.noisy.reshape(8, 8, -1)
    with pytest.raises(NotOneInstrument, match="scatter by"):
        image_estimate(cube, None, 2.0, "convscd", ("psf",), keywords={}, one_instrument=True)
    est = image_estimate(cube, None, 2.0, "convscd", ("psf",), keywords={})        # asked for: shared
    assert est.psf_spread > ONE_INSTRUMENT_SPREAD and est.record()["psf_spread"] == est.psf_spread
    scene = make_spatial_scene(10, 10, 128, nsr=0.05, seed=1)
    est = image_estimate(scene.profiles, None, scene.time_bin_ps, "convscd", ("psf",),
                         keywords={"t0_ps": scene.t0_ps}, one_instrument=True)
    assert est.psf_spread <= ONE_INSTRUMENT_SPREAD and abs(est.psf_sigma_ps - scene.sigma_ps) < 0.2


def test_a_psf_map_that_is_not_a_width_everywhere_is_refused():
    """A 2 x 16 image of noisy widths (most pixels misfit by the Gaussian model): the quadratic
    surface fitted to them falls below zero at the image's corner, where every pixel's fit would
    have refused the held width with a traceback from inside its chunk.  The estimate refuses
    it, naming the pixel and the way out; one shared width is estimated as before."""
    cube = make_cube(2, 16, 256, nsr=0.05, seed=1).noisy
    with pytest.raises(ValueError, match=r"psf_map: the PSF width surface .* falls to -[0-9.]+ ps at pixel "
                                         r"\(y=1, x=15\) of the 2 x 16 image.*psf without psf_map"):
        decompose_image(cube, TB, shared="psf", psf_map=True)
    res = decompose_image(cube, TB, shared="psf")
    assert res.info["shared"]["psf_sigma_ps"] > 0
