"""Forward model: closed forms against direct numerical convolution, and the stiff extremes."""
import warnings

import numpy as np
import pytest
from scipy import integrate

from core.model import (
    empty_params, gaussian_kernel, render_components, render_profile, sss_kernel, time_axis_ps,
)


def _sss_by_quadrature(t, sigma, alpha):
    f = lambda tau: np.exp(-alpha * tau - (t - tau) ** 2 / (2 * sigma**2))
    lo, hi = max(0.0, t - 12 * sigma), max(0.0, t + 12 * sigma)
    if hi <= 0:
        return 0.0
    return integrate.quad(f, lo, hi, epsabs=0, epsrel=1e-12, limit=200)[0]


@pytest.mark.parametrize("sigma,alpha", [(3.0, 0.03), (1.0, 0.05), (10.0, 0.01), (0.5, 2.0), (4.0, 1e-6)])
def test_sss_kernel_matches_numerical_convolution(sigma, alpha):
    t = np.linspace(-5 * sigma, 60.0, 41)
    ref = np.array([_sss_by_quadrature(x, sigma, alpha) for x in t])
    got = sss_kernel(t, sigma, alpha)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-14 * ref.max())


def test_discrete_convolution_reproduces_sampled_kernel():
    # Fine-grid Riemann convolution of the Gaussian with the causal exponential.
    dt, sigma, alpha = 0.01, 2.5, 0.04
    tau = np.arange(0, 400, dt)
    t = np.arange(-20, 100, dt)
    g = gaussian_kernel(np.arange(-30, 30, dt), sigma)
    e = np.exp(-alpha * tau)
    conv = np.convolve(g, e)[: t.size + 3000] * dt  # index 0 <-> t = -30
    tc = -30 + dt * np.arange(conv.size)
    sel = (tc > -10) & (tc < 80)
    np.testing.assert_allclose(sss_kernel(tc[sel], sigma, alpha), conv[sel], rtol=2e-3, atol=2e-3)


@pytest.mark.parametrize("alpha_sigma", [1e-6, 1e-3, 1.0, 10.0, 100.0])
@pytest.mark.parametrize("sigma", [0.5, 2.0, 40.0])
def test_sss_kernel_finite_and_accurate_on_stiff_grid(alpha_sigma, sigma):
    alpha = alpha_sigma / sigma
    t = np.linspace(-2000.0, 5000.0, 3001)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h = sss_kernel(t, sigma, alpha)
    assert np.all(np.isfinite(h)) and np.all(h >= 0)
    # Late-time tail is the pure exponential scaled by exp(alpha^2 sigma^2 / 2) sigma sqrt(2 pi).
    late = t > alpha * sigma**2 + 12 * sigma
    if late.any():
        log_tail = np.log(sigma * np.sqrt(2 * np.pi)) + 0.5 * (alpha * sigma) ** 2 - alpha * t[late]
        keep = log_tail > -690  # the kernel renders exponents below -700 as exact zeros
        np.testing.assert_allclose(np.log(h[late][keep]), log_tail[keep], rtol=1e-9, atol=1e-9)
        assert np.all(h[late][log_tail < -720] == 0.0)  # no subnormals far in the tail
    # For large alpha*sigma the exponential is much shorter than the PSF: h -> g(t - 1/alpha) / alpha.
    if alpha_sigma >= 100:
        near = np.abs(t) < 3 * sigma
        np.testing.assert_allclose(h[near] * alpha, gaussian_kernel(t[near] - 1 / alpha, sigma), rtol=1e-3)


def test_sss_area():
    sigma, alpha = 3.0, 0.02
    t = np.arange(-50, 3000, 0.05)
    area = np.trapezoid(sss_kernel(t, sigma, alpha), t)
    assert area == pytest.approx(sigma * np.sqrt(2 * np.pi) / alpha, rel=1e-4)


def test_bin_integrated_gaussian_is_bin_mean():
    T, sigma = 2.0, 0.5
    t = np.arange(-4, 4.01, T)
    got = gaussian_kernel(t, sigma, time_bin_ps=T)
    from scipy.special import erf
    ref = sigma * np.sqrt(np.pi / 2) * (erf((t + T / 2) / (sigma * np.sqrt(2))) - erf((t - T / 2) / (sigma * np.sqrt(2)))) / T
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-15)


def test_render_components_absent_is_zero_and_sum_is_profile():
    p = empty_params((2,), n_ir=2)
    p["direct_delay_ps"][0], p["direct_amplitude"][0], p["direct_sigma_ps"][0] = 100.0, 2.0, 3.0
    p["sss_delay_ps"][0], p["sss_amplitude"][0], p["sss_alpha_per_ps"][0], p["sss_sigma_ps"][0] = 100.0, 0.1, 0.02, 3.0
    p["ir_delay_ps"][0, 0], p["ir_amplitude"][0, 0], p["ir_sigma_ps"][0, 0] = 160.0, 0.5, 3.0
    c = render_components(p, 256, 2.0)
    assert c["direct"].shape == (2, 256) and c["interreflections"].shape == (2, 2, 256)
    assert np.all(c["direct"][1] == 0) and np.all(c["interreflections"][0, 1] == 0)
    t = time_axis_ps(256, 2.0)
    assert t[0] == 2.0 and t[-1] == 512.0
    assert c["direct"][0].max() == pytest.approx(2.0, rel=1e-12)  # delay 100 ps is on bin 49
    np.testing.assert_allclose(render_profile(p, 256, 2.0),
                               c["direct"] + c["sss"] + c["interreflections"].sum(-2))


@pytest.mark.parametrize("bad", [0.0, -1.0, np.nan])
def test_bad_time_bin_and_sigma(bad):
    with pytest.raises(ValueError, match="time_bin_ps"):
        time_axis_ps(10, bad)
    with pytest.raises(ValueError, match="sigma_ps"):
        gaussian_kernel(np.zeros(3), bad)
