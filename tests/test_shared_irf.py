"""Shared onset and sss decay rate with a measured instrument response (decompose_image(irf=...)).

Known answers: cubes rendered through core.irf_models.tailed_response (20 % of the area in a
20 ps tail) with one onset and one decay rate per region; the estimate must lie within a few
standard errors of the truth and every pixel must hold it.  With a response, shared='psf' is
its time scale: a cube rendered through the response stretched 1.2x gives back 1.2.
"""
import numpy as np
import pytest

from core.irf_models import tailed_response
from decomposition.evaluation.synthetic import SceneRanges, make_cube
from decomposition.image import decompose_image
from decomposition.options import OptionError
from decomposition.response.resolve import resolve_response, stretched_response

TB, NT = 2.0, 160
IRF = tailed_response(3.0, 0.2, 20.0, time_step_ps=TB)


def _cube(seed, alpha, ny=6, nx=6, nsr=0.05, noise="white", response_override=None, nt=NT, **kw):
    ranges = SceneRanges(sigma_ps=(3.0, 3.0), alpha_per_ps=(alpha, alpha), direct_position=(0.2, 0.2))
    return make_cube(ny, nx, nt, nsr=nsr, noise=noise, seed=seed, kinds="d+s", time_bin_ps=TB, ranges=ranges,
                     response=IRF if response_override is None else response_override, **kw)


def _present(result, key):
    v = result.params[key]
    return v[np.isfinite(v)]


def test_shared_delay_with_a_response_known_answer_and_held_everywhere():
    d = _cube(21, 0.03)
    truth = float(d.params["direct_delay_ps"][0, 0])
    assert np.ptp(d.params["direct_delay_ps"]) == 0
    res = decompose_image(d.noisy, TB, components="d,s", stderr=True, shared="delay", irf=IRF)
    rec = res.info["shared"]
    assert rec["delay_key"] == "direct_delay_ps"
    assert abs(rec["delay_ps"] - truth) < 4 * rec["delay_ps_stderr"] and rec["delay_ps_stderr"] < 0.3, rec
    assert _present(res, "direct_delay_ps").size == 36
    np.testing.assert_array_equal(_present(res, "direct_delay_ps"), rec["delay_ps"])
    np.testing.assert_array_equal(_present(res, "direct_delay_ps_stderr"), rec["delay_ps_stderr"])


def test_shared_delay_and_alpha_per_region_with_a_response():
    a, b = _cube(22, 0.02), _cube(23, 0.045)
    truth = float(a.params["direct_delay_ps"][0, 0])
    assert truth == float(b.params["direct_delay_ps"][0, 0])
    cube = np.concatenate([a.noisy[:, :3], b.noisy[:, 3:]], axis=1)
    regions = np.zeros((6, 6), np.int32)
    regions[:, 3:] = 5
    res = decompose_image(cube, TB, components="d,s", stderr=True, shared="delay,alpha", regions=regions, irf=IRF)
    rec = res.info["shared"]
    assert abs(rec["delay_ps"] - truth) < 0.1, rec       # 5 % of a bin (0.031 and 0.095 ps, as above)
    alpha = res.params["sss_alpha_per_ps"]
    for label, true_alpha in (("0", 0.02), ("5", 0.045)):
        v, se = rec["sss_alpha_per_ps"][label], rec["sss_alpha_per_ps_stderr"][label]
        assert abs(v - true_alpha) < 4 * se and se < 0.15 * true_alpha, (label, v, se)
        inside = (regions == int(label)) & np.isfinite(alpha)
        assert inside.sum() >= 15
        np.testing.assert_array_equal(alpha[inside], v)
    np.testing.assert_array_equal(_present(res, "direct_delay_ps"), rec["delay_ps"])


def test_shared_psf_with_a_response_estimates_its_time_scale_and_holds_it():
    truth_s = 1.2
    wide = stretched_response(resolve_response(IRF, TB, NT), truth_s)
    d = _cube(24, 0.03, response_override=wide, nt=256)
    truth = float(d.params["direct_delay_ps"][0, 0])
    res = decompose_image(d.noisy, TB, components="d,s", stderr=True, shared="psf,delay", irf=IRF)
    rec = res.info["shared"]
    assert "psf_sigma_ps" not in rec and rec["pixels"]["psf"] >= 10
    s, se = rec["response_stretch"], rec["response_stretch_stderr"]
    # within 1.5 % of the truth: beyond its own error (se 0.002) the estimate carries the bias of
    # the components the pixels' fits hold (1.195 and 1.188 from two detections of the same cube);
    # so does the shared delay beside its own error
    assert abs(s / truth_s - 1.0) < 0.015 and se < 0.02, rec
    assert abs(rec["delay_ps"] - truth) < 0.1, rec       # 5 % of a bin (0.031 and 0.095 ps, as above)
    # every pixel decomposed with the stretched response: its record says so, and the fit is as
    # good as one with the true response given
    assert res.info["irf"]["provenance"]["stretch"] == s
    np.testing.assert_array_equal(_present(res, "direct_delay_ps"), rec["delay_ps"])
    assert _present(res, "direct_delay_ps").size == 36


def test_a_time_scale_the_window_cannot_hold_is_a_clear_error():
    wide = stretched_response(resolve_response(IRF, TB, NT), 1.2)
    d = _cube(27, 0.03, ny=3, nx=3, response_override=wide)
    with pytest.raises(ValueError, match="window of 160 bins holds"):
        decompose_image(d.noisy, TB, components="d,s", shared="psf", irf=IRF)


def test_shared_psf_map_with_a_response_is_refused_in_one_line():
    d = _cube(26, 0.03, ny=3, nx=3)
    with pytest.raises(OptionError, match=r"psf_map.*measured response"):
        decompose_image(d.noisy, TB, components="d,s", shared="psf", psf_map=True, irf=IRF)


def test_shared_delay_of_a_count_image_with_a_response():
    d = _cube(25, 0.03, nsr=0.0, noise="none", photons_per_pixel=400)
    truth = float(d.params["direct_delay_ps"][0, 0])
    res = decompose_image(d.noisy, TB, components="d,s", stderr=True, shared="delay,alpha", irf=IRF,
                          noise="poisson")
    rec = res.info["shared"]
    assert rec["pixels"]["likelihood"] >= 10
    assert abs(rec["delay_ps"] - truth) < 4 * rec["delay_ps_stderr"] and rec["delay_ps_stderr"] < 0.5, rec
    v, se = rec["sss_alpha_per_ps"]["0"], rec["sss_alpha_per_ps_stderr"]["0"]
    assert abs(v - 0.03) < 4 * se and se < 0.2 * 0.03, rec
    np.testing.assert_array_equal(_present(res, "direct_delay_ps"), rec["delay_ps"])


@pytest.mark.parametrize("factor", [0.0, -1.0, float("nan")])
def test_a_bad_stretch_is_refused_in_one_line(factor):
    from core.irf import ResponseError

    with pytest.raises(ResponseError, match="stretch must be a finite number > 0"):
        stretched_response(resolve_response(IRF, TB, NT), factor)
