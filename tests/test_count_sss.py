"""The count forward step's sss trial on the Gaussian path (``stages/grow.grow_counts``).

At a few hundred photons per pixel the detection weighs every sample with the Poisson noise at
the direct's peak, where an sss tail does not pay its penalty: a fifth of the d+s pixels at 300
photons ended with no sss before this trial.  The forward step tries one at the direct, judged by the Poisson
deviance, as the response path's count steps do; it must not put one where the scene has none.
"""
import numpy as np
import pytest

from decomposition import decompose
from decomposition.evaluation.synthetic import make_profiles
from decomposition.model.fidelity import fidelity

N_PX = 200
L = 256


def _scene(kinds, photons):
    return make_profiles(N_PX, L, seed=4, kinds=kinds, ranges="paper", photons_per_pixel=photons)


@pytest.mark.parametrize("photons, least", [(100, 0.84), (300, 0.93)])
def test_an_sss_the_detection_left_out_is_added_where_the_counts_hold_one(photons, least):
    d = _scene("d+s", photons)
    r = decompose(d.noisy, 2.0, t0_ps=d.t0_ps)
    without = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, grow=False)
    has = np.isfinite(r.params["sss_delay_ps"])
    had = np.isfinite(without.params["sss_delay_ps"])
    # every d+s pixel has an sss; without the forward steps (grow=False) 80 % (100 photons)
    # and 84 % (300) of them report one, with them 86 % and 95.5 % (before the sss trial 78 %
    # and 81 %)
    assert has.mean() >= least > had.mean()
    assert r.info["count_sss_added"] >= 0.05 * N_PX
    # what was added is the scene's sss: its amplitude and decay rate (measured: amplitude
    # ratios 0.99 and 0.98 in the median, |log alpha ratio| 0.18 and 0.08)
    added = has & ~had
    amp = r.params["sss_amplitude"][added] / d.params["sss_amplitude"][added]
    assert 0.7 < np.median(amp) < 1.4
    assert np.median(np.abs(np.log(r.params["sss_alpha_per_ps"][added] / d.params["sss_alpha_per_ps"][added]))) < 0.4
    assert fidelity(d.components, r)[added].mean() > fidelity(d.components, without)[added].mean()


@pytest.mark.parametrize("photons", [300, 1000])
def test_no_sss_is_put_where_the_scene_has_none(photons):
    d = _scene("d", photons)
    r = decompose(d.noisy, 2.0, t0_ps=d.t0_ps)
    assert np.isfinite(r.params["sss_delay_ps"]).mean() <= 0.02
    assert r.info["count_sss_added"] <= 0.02 * N_PX


def test_an_echo_is_not_taken_for_an_sss():
    # a trial sss whose onset the polish moved onto an echo the fit lacks is refused: on these
    # d+r2 scenes 12 % of the pixels reported an sss with it taken, 7 % as before the trial
    d = _scene("d+r2", 300)
    r = decompose(d.noisy, 2.0, t0_ps=d.t0_ps)
    assert r.info["count_sss_added"] <= 0.01 * N_PX
    assert np.isfinite(r.params["sss_delay_ps"]).mean() <= 0.10


def test_the_sss_trial_runs_where_no_inter_reflection_is_asked():
    # the count step ran only with "r" among the components; the sss trial needs only "s"
    d = _scene("d+s", 300)
    r = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, components=("d", "s"))
    assert r.info["count_sss_added"] >= 0.05 * N_PX
    assert np.isfinite(r.params["sss_delay_ps"]).mean() >= 0.95
    assert not np.isfinite(r.params["ir_delay_ps"]).any()
