"""Count data on the Gaussian PSF through the response path's count stages (``likelihood_counts``).

With ``likelihood_counts=True`` the Gaussian path's labels of count data are handed to the stages
a measured response's counts take after its labels -- the Poisson likelihood's refit and the
count forward steps -- over :class:`decomposition.model.atoms.GaussianPSF`, the Gaussian PSF of
each pixel's width as an instrument of those stages.
"""
import math

import numpy as np
import pytest
from scipy.ndimage import convolve1d

from core.model import render_components
from decomposition import decompose
from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from decomposition.evaluation.synthetic import make_profiles
from decomposition.model.atoms import GaussianPSF, params_profile, shifted_slot_atoms, slot_atoms, sss_slot_atoms
from decomposition.model.fidelity import fidelity
from decomposition.options import OptionError
from decomposition.response import grow as rg
from decomposition.response.label import slots_to_params
from decomposition.response.refine import CountData, fit_slots

T = 2.0 + 2.0 * np.arange(256)


def _true_widths(d):
    return np.where(np.isfinite(d.params["direct_sigma_ps"]), d.params["direct_sigma_ps"], d.params["sss_sigma_ps"])


def test_the_gaussian_psf_instrument_renders_the_gaussian_paths_components():
    widths = np.array([1.5, 3.0, 7.5])
    inst = GaussianPSF(widths)
    fam = np.array([[FAM_GAUSS, FAM_SSS, FAM_GAUSS], [FAM_GAUSS, FAM_NONE, FAM_NONE],
                    [FAM_GAUSS, FAM_SSS, FAM_NONE]], np.int8)
    delay = np.array([[100.0, 101.0, 180.0], [60.5, 0.0, 0.0], [250.0, 250.0, 0.0]])
    lalp = np.array([[0.0, math.log(0.05), 0.0], [0.0, 0.0, 0.0], [0.0, math.log(0.2), 0.0]])
    amp = np.array([[1.0, 0.3, 0.2], [2.0, 0.0, 0.0], [0.5, 0.1, 0.0]])
    scale = np.array([10.0, 3.0, 7.0])
    phi = slot_atoms(inst, T, fam, delay, lalp)
    # a shifted atom is the unit-peak Gaussian of its pixel's width (exact zeros where it is
    # below 1e-10 of its peak); an empty slot renders nothing
    assert np.allclose(phi[1, 0], np.exp(-0.5 * ((T - 60.5) / 3.0) ** 2), rtol=0, atol=1e-10)
    assert not phi[1, 1:].any()
    # the components of the parameters it reports are the Gaussian path's rendering of them
    params = slots_to_params(fam, delay, lalp, amp, scale, widths, 1)
    assert np.array_equal(params["direct_sigma_ps"], widths)
    direct = render_components(params, T.size, 2.0, 2.0)
    model = np.einsum("pk,pkl->pl", amp, phi) * scale[:, None]
    total = direct["direct"] + direct["sss"] + direct["interreflections"].sum(axis=1)
    assert np.allclose(total, model, rtol=1e-6, atol=1e-9 * model.max())
    assert np.allclose(params_profile(inst, T, params), model, rtol=1e-6, atol=1e-9 * model.max())
    # the single atoms of each pixel's width
    assert np.allclose(shifted_slot_atoms(inst, T, delay[:, 0]), phi[:, 0])
    s = sss_slot_atoms(inst.rows([0, 2]), T, delay[[0, 2], 1], np.exp(lalp[[0, 2], 1]))
    assert np.allclose(s, phi[[0, 2], 1])


def test_the_instrument_refuses_widths_it_cannot_render():
    for bad in ([0.0, 2.0], [np.nan], [[2.0]], [-1.0]):
        with pytest.raises(ValueError, match="one finite positive width per pixel"):
            GaussianPSF(np.array(bad, dtype=float))
    with pytest.raises(ValueError, match="counts only"):
        fit_slots(GaussianPSF(np.array([3.0])), T, np.zeros((1, T.size)), np.ones((1, T.size)),
                  np.array([[FAM_GAUSS]], np.int8), np.array([[50.0]]), np.zeros((1, 1)), n_iter=5, lm_tol=1e-6,
                  delay_bounds_ps=(0.0, 600.0), lalp_bounds=(-8.0, 0.0))


def test_the_count_fit_over_held_gaussian_widths_finds_the_scenes_delays_and_decay_rates():
    rng = np.random.default_rng(2)
    n = 40
    widths = rng.uniform(1.5, 8.0, n)
    inst = GaussianPSF(widths)
    fam = np.tile(np.array([FAM_GAUSS, FAM_SSS], np.int8), (n, 1))
    delay = np.stack([rng.uniform(80, 300, n), np.zeros(n)], axis=1)
    delay[:, 1] = delay[:, 0] + 1.0
    lalp = np.stack([np.zeros(n), np.log(rng.uniform(0.03, 0.3, n))], axis=1)
    amp = np.stack([np.ones(n), rng.uniform(0.05, 0.3, n)], axis=1)
    scale = np.full(n, 2.0e4)          # ~10^5 photons per pixel
    mu = np.einsum("pk,pkl->pl", amp, slot_atoms(inst, T, fam, delay, lalp)) * scale[:, None]
    counts = rng.poisson(mu).astype(float)
    cd = CountData(counts, scale, np.zeros(n), np.ones(counts.shape, bool), None)
    start_d = delay + rng.normal(0, 0.2, delay.shape) * widths[:, None]
    start_d[:, 1] = np.maximum(start_d[:, 1], start_d[:, 0])
    start_l = lalp + np.array([0.0, 0.1])
    f = fit_slots(inst, T, counts / scale[:, None], np.sqrt(1.0 / np.maximum(mu, 1.0)) * scale[:, None], fam,
                  start_d, start_l, n_iter=60, lm_tol=1e-10, delay_bounds_ps=(-500.0, 1000.0),
                  lalp_bounds=(math.log(1e-3), math.log(2.0)), counts=cd)
    # at 10^5 photons the direct delay is fixed to a tenth of a ps, the decay rate to a per
    # cent (measured: 0.068 ps and 0.4 % in the median; 0.063 ps and 0.3 % started at the truth)
    assert np.median(np.abs(f.delay[:, 0] - delay[:, 0])) < 0.15
    assert np.median(np.abs(f.lalp[:, 1] - lalp[:, 1])) < 0.02
    # the deviance per sample of a Poisson draw near its optimum (measured 0.30 in the median)
    assert np.median(f.cost / T.size) < 0.5


def test_each_pixel_is_smoothed_by_its_own_width():
    rng = np.random.default_rng(0)
    y = rng.poisson(3.0, (3, T.size)).astype(float)
    widths = np.array([2.0, 5.0, 9.0])

    class Ctx:
        t = T
        irf = GaussianPSF(widths)
        width = widths

    got = rg._smooth(Ctx, np.arange(3), y)
    for i, s in enumerate(widths):
        half = max(int(math.ceil(3.0 * s / 2.0)), 1)
        kernel = np.exp(-0.5 * np.square(np.arange(-half, half + 1) * 2.0 / s))
        assert np.allclose(got[i], convolve1d(y[i], kernel, mode="constant"), rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [5, 6])
def test_counts_with_a_known_width_gain_from_the_likelihood_stages(seed):
    # measured on these 200 pixels (256 bins): 0.372 -> 0.610 and 0.682 -> 0.735 (seed 5),
    # 0.474 -> 0.631 and 0.704 -> 0.754 (seed 6) at 100 and 300 photons
    for photons, gain in ((100, 0.10), (300, 0.03)):
        d = make_profiles(200, 256, seed=seed, ranges="paper", photons_per_pixel=photons)
        hold = {"sigma_ps": _true_widths(d)}
        before = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, hold=hold)
        after = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, hold=hold, likelihood_counts=True)
        assert "counts_handed_over" not in before.info
        assert after.info["counts_handed_over"] == 200
        assert fidelity(d.components, after).mean() >= fidelity(d.components, before).mean() + gain
        # the widths stay where they were held
        on = np.isfinite(after.params["direct_sigma_ps"])
        assert np.array_equal(after.params["direct_sigma_ps"][on], hold["sigma_ps"][on])


def test_float_data_and_omitted_pixels():
    d = make_profiles(60, 256, seed=1, ranges="paper", nsr=0.05)
    a = decompose(d.noisy, 2.0, t0_ps=d.t0_ps)
    b = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, likelihood_counts=True)
    # float data: no count stages to hand over to
    assert all(np.array_equal(a.params[k], b.params[k], equal_nan=True) for k in a.params)
    assert "counts_handed_over" not in b.info
    c = make_profiles(60, 256, seed=1, ranges="paper", photons_per_pixel=300)
    x = c.noisy.astype(float)
    x[7, 30] = np.nan
    r = decompose(x, 2.0, t0_ps=c.t0_ps, nan_policy="omit", noise="poisson", likelihood_counts=True, stderr=True)
    assert r.info["counts_handed_over"] == 59
    assert r.flag_names(7) == ["NONFINITE"] and np.isnan(r.params["direct_delay_ps"][7])
    assert np.isfinite(r.params["direct_delay_ps_stderr"]).mean() > 0.9


def test_the_option_is_checked():
    d = make_profiles(4, 64, seed=0, photons_per_pixel=100)
    with pytest.raises(OptionError, match="likelihood_counts"):
        decompose(d.noisy, 2.0, likelihood_counts="yes")


@pytest.mark.parametrize("width_ps", [0.3, 30.0])
def test_extreme_widths_and_counts_stay_finite(width_ps):
    # widths far under a bin and far over the components' spacing, a million photons per pixel
    d = make_profiles(30, 256, seed=2, ranges="paper", photons_per_pixel=1e6)
    r = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, hold={"sigma_ps": width_ps}, likelihood_counts=True, stderr=True)
    for key, v in r.params.items():
        assert not np.isinf(v).any(), key
    assert np.isfinite(r.residual).all()
    # no light, one count, saturation: nothing to hand over is reported as nothing
    x = np.zeros((3, 256), np.uint16)
    x[1, 100] = 1
    x[2, 50:60] = 65535
    r = decompose(x, 2.0, hold={"sigma_ps": width_ps}, likelihood_counts=True)
    assert [r.flag_names(i) for i in range(3)] == [["EMPTY"], ["EMPTY"], ["EMPTY", "SATURATED"]]
