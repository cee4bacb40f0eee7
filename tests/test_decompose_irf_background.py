"""The background family 'b' on the response path: decompose(irf=..., components="...,b").

Known answers: scenes of a tailed response (20 % of the area in a 30 ps tail) with and without
a constant offset (decomposition.evaluation.synthetic.make_profiles, same seed: same components), white
noise and Poisson counts.  The offset must be recovered, the delays and lifetimes must not
move against the scene without it, an offset the scene does not have must be exactly 0.0,
and a pixel that is not decomposed has NaN.
"""
import numpy as np
import pytest

from core.irf import render_shifted
from core.irf_models import gaussian_response, tailed_response
from decomposition import decompose
from decomposition.constants import FAM_GAUSS, FAM_NONE
from decomposition.response.refine import fit_slots
from decomposition.evaluation.synthetic import make_profiles

T = 2.0
L = 256
N = 32


@pytest.fixture(scope="module")
def tailed():
    return tailed_response(4.0, 0.2, 30.0, time_step_ps=T)


def _run(irf, background, **noise):
    d = make_profiles(N, L, seed=3, kinds="d+s", response=irf, background=background, **noise)
    counts = "photons_per_pixel" in noise
    r = decompose(d.noisy, T, t0_ps=d.t0_ps, irf=irf, components="d,r,s,b",
                  noise="poisson" if counts else "gaussian", stderr=True)
    return d, r.params


def _biases(d, p):
    delay = np.mean(p["direct_delay_ps"] - d.params["direct_delay_ps"])
    tau = np.mean(d.params["sss_alpha_per_ps"] / p["sss_alpha_per_ps"] - 1.0)
    return delay, tau


@pytest.mark.parametrize("noise", [{"nsr": 0.01}, {"photons_per_pixel": 10_000}], ids=["white", "counts"])
def test_background_recovered_and_components_unmoved(tailed, noise):
    d0, p0 = _run(tailed, 0.0, **noise)
    d1, p1 = _run(tailed, 0.02, **noise)
    b_true = np.broadcast_to(d1.background, (N,))
    assert (b_true > 0).all()
    # recovered: every pixel's offset kept, within 2 % (median) and 4 standard errors (each)
    err = p1["background"] - b_true
    assert np.all(p1["background"] != 0.0)
    assert abs(np.median(err / b_true)) < 0.02
    z = np.abs(err) / p1["background_stderr"]
    assert np.all(np.isfinite(z)) and np.all(z < 4.0)
    assert 0.35 < np.median(z) < 1.1                    # 0.674 for a calibrated standard error
    # none where the scene has none: exactly 0.0, no standard error, but for the ~2 % the
    # information criterion keeps (test_background.py measures the rate)
    zero = p0["background"] == 0.0
    assert np.mean(zero) >= 0.9 and np.all(np.isnan(p0["background_stderr"][zero]))
    # the components: unbiased and where the scene without the offset puts them
    (dd0, tau0), (dd1, tau1) = _biases(d0, p0), _biases(d1, p1)
    tol_tau = 0.01 if "nsr" in noise else 0.02
    assert abs(dd1) < 0.1 and abs(dd1 - dd0) < 0.1                   # ps; the response's FWHM is ~10 ps
    assert abs(tau1) < tol_tau and abs(tau1 - tau0) < tol_tau


def test_background_nan_where_not_decomposed(tailed):
    d = make_profiles(4, L, seed=1, kinds="d+s", response=tailed, background=0.02, nsr=0.01)
    y = np.array(d.noisy)
    y[1] = 0.0                          # empty
    y[2, 10] = np.nan                   # non-finite, omitted
    r = decompose(y, T, t0_ps=d.t0_ps, irf=tailed, components="d,s,b", nan_policy="omit", stderr=True)
    b = r.params["background"]
    assert np.isnan(b[2]) and np.isnan(r.params["background_stderr"][2])
    assert b[1] == 0.0 or np.isnan(b[1])
    assert np.allclose(b[[0, 3]], 0.02, rtol=0.1)
    assert "background" not in decompose(y[[0, 3]], T, t0_ps=d.t0_ps, irf=tailed, components="d,s").params


def test_fit_slots_constant_column_exact(tailed):
    t = T + T * np.arange(L)
    delay = np.array([150.0, 212.3])
    y = np.stack([0.8 * render_shifted(tailed, t, delay[:1])[0] + 0.05,
                  0.6 * render_shifted(tailed, t, delay[1:])[0] - 0.01])
    fam = np.array([[FAM_GAUSS, FAM_NONE], [FAM_GAUSS, FAM_NONE]], np.int8)
    start = np.array([[152.5, 0.0], [210.0, 0.0]])
    kw = dict(n_iter=50, lm_tol=1e-14, delay_bounds_ps=(-500.0, 1000.0), lalp_bounds=(-6.0, -2.0))
    f = fit_slots(tailed, t, y, np.ones_like(y), fam, start, np.zeros((2, 2)), fit_background=np.ones(2, bool), **kw)
    assert np.allclose(f.delay[:, 0], delay, atol=1e-6)
    assert np.allclose(f.amp[:, 0], [0.8, 0.6], atol=1e-8)
    assert np.allclose(f.background, [0.05, -0.01], atol=1e-9)
    # without the column the offset is not modelled and the fit is worse
    g = fit_slots(tailed, t, y, np.ones_like(y), fam, start, np.zeros((2, 2)), **kw)
    assert np.all(g.background == 0.0) and np.all(g.cost > 100 * f.cost + 1e-6)


def test_background_at_100_photons_kept_and_lifetime_unbiased():
    """A background of ~0.2 counts per bin (half as many counts as the signal): kept in every
    pixel by the information criterion (the 5-sigma threshold dropped it in ~22 % of them,
    where the sss then absorbed it: lifetime bias +22 %)."""
    irf = gaussian_response(4.0, time_step_ps=T)
    d = make_profiles(200, L, seed=3, kinds="d+s", response=irf, background=0.02, photons_per_pixel=100.0)
    r = decompose(d.noisy, T, t0_ps=d.t0_ps, irf=irf, components="d,r,s,b", noise="poisson")
    b, b_true = r.params["background"], np.broadcast_to(d.background, (200,))
    found = np.isfinite(r.params["sss_alpha_per_ps"])
    assert found.mean() > 0.75 and np.mean(b[found] != 0.0) >= 0.95
    assert abs(np.mean(b[found] - b_true[found])) < 0.02            # counts per bin
    tau_rel = d.params["sss_alpha_per_ps"][found] / r.params["sss_alpha_per_ps"][found] - 1.0
    assert abs(np.mean(tau_rel)) < 0.06 and np.sqrt(np.mean(tau_rel ** 2)) < 0.4


def test_no_background_at_100_photons_left_out():
    """Counts without an offset: the offset is kept in few pixels (it was kept in 28 %, where
    the first estimate, ~0.2 counts per bin taken from the sss tail, hid the sss from the
    pursuit and the offset then took its light)."""
    irf = gaussian_response(4.0, time_step_ps=T)
    d = make_profiles(200, L, seed=5, kinds="d+s", response=irf, photons_per_pixel=100.0)
    r = decompose(d.noisy, T, t0_ps=d.t0_ps, irf=irf, components="d,r,s,b", noise="poisson")
    assert np.mean(r.params["background"] != 0.0) <= 0.03
    assert np.mean(np.isfinite(r.params["sss_alpha_per_ps"])) >= 0.95
