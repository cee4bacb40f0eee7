"""decompose(hold=..., irf=...): onsets and the sss decay rate held with a measured response.

Known answers: profiles rendered through core.irf_models.tailed_response with a direct, an sss
and an echo; held at the rendered onset and decay rate, every fitted pixel reports exactly the
held values (their errors NaN: not fitted), the rest of the fit stays at the truth, and the
errors of what is still fitted stay finite.  Held at a wrong onset, the fit reports it and
moves the others around it (it is not overwritten after the fact).
"""
import numpy as np
import pytest

from core.irf import render_shifted, render_sss
from core.irf_models import tailed_response
from decomposition import decompose

T = 2.0
L = 384
T_PS = T + T * np.arange(L)


@pytest.fixture(scope="module")
def tailed():
    return tailed_response(6.0, 0.2, 40.0, time_step_ps=T)


def _scene(irf, n, seed, *, d0=200.0, alpha=0.025, noise=0.01, counts=False):
    rng = np.random.default_rng(seed)
    d = np.full(n, d0)
    e = d + rng.uniform(80, 150, n)
    y = (render_shifted(irf, T_PS, d) + 0.4 * render_shifted(irf, T_PS, e)
         + 0.05 * render_sss(irf, T_PS, d, np.full(n, alpha)))
    if counts:
        return rng.poisson(np.clip(y, 0, None) * 400.0).astype(np.float64), e
    return y + noise * rng.standard_normal(y.shape), e


def test_held_onset_and_alpha_are_reported_and_the_rest_fitted(tailed):
    y, e = _scene(tailed, 16, 3)
    res = decompose(y, T, irf=tailed, stderr=True,
                    hold={"direct_delay_ps": 200.0, "sss_delay_ps": 200.0, "sss_alpha_per_ps": 0.025})
    p = res.params
    assert np.all(p["direct_delay_ps"] == 200.0) and np.all(p["sss_delay_ps"] == 200.0)
    assert np.all(p["sss_alpha_per_ps"] == 0.025)
    assert np.all(np.isnan(p["direct_delay_ps_stderr"])) and np.all(np.isnan(p["sss_alpha_per_ps_stderr"]))
    assert np.all(np.isfinite(p["direct_amplitude_stderr"])) and np.all(np.isfinite(p["ir_delay_ps_stderr"][:, 0]))
    assert np.max(np.abs(p["ir_delay_ps"][:, 0] - e)) < 0.5
    assert np.allclose(p["direct_amplitude"], 1.0, atol=0.02)


def test_a_wrong_held_onset_is_held_and_the_rest_moves(tailed):
    y, e = _scene(tailed, 8, 4)
    free = decompose(y, T, irf=tailed).params
    held = decompose(y, T, irf=tailed, hold={"direct_delay_ps": 203.0}).params
    assert np.all(held["direct_delay_ps"] == 203.0)
    assert np.all(np.abs(free["direct_delay_ps"] - 200.0) < 0.5)
    # the sss onset (rendered at 200) kept at or after the held direct; the echo still found at
    # the truth (the wrong onset's misfit may take an atom of its own)
    assert np.all(held["sss_delay_ps"] >= 203.0)
    assert np.all(np.nanmin(np.abs(held["ir_delay_ps"] - e[:, None]), axis=1) < 1.0)
    # the misfit of the wrong onset is the fit's: its residual is larger than the free fit's
    assert np.all(held["direct_amplitude"] != free["direct_amplitude"])


def test_held_alpha_with_count_data(tailed):
    y, _ = _scene(tailed, 8, 5, counts=True)
    res = decompose(y, T, irf=tailed, noise="poisson", stderr=True, hold={"sss_alpha_per_ps": 0.025})
    p = res.params
    has = np.isfinite(p["sss_delay_ps"])
    assert has.sum() >= 6
    assert np.all(p["sss_alpha_per_ps"][has] == 0.025)
    assert np.all(np.isnan(p["sss_alpha_per_ps_stderr"][has]))
    assert np.all(np.isfinite(p["sss_delay_ps_stderr"][has]))


def test_held_width_is_refused_with_a_response(tailed):
    y, _ = _scene(tailed, 2, 6)
    with pytest.raises(ValueError, match="sigma_ps.*measured response"):
        decompose(y, T, irf=tailed, hold={"sigma_ps": 6.0})
