"""Instrument responses: exact sub-bin shifts and sss convolutions against closed forms and quadrature."""
import warnings

import numpy as np
import pytest
from scipy import integrate

from core.irf import InstrumentResponse, ResponseError, render_shifted, render_sss
from core.irf_models import afterpulse_response, gaussian_fit, gaussian_response, model_value, tailed_response
from core.model import gaussian_kernel, sss_kernel

T = 2.0                                        # ps per bin
AXIS = T * np.arange(256)                      # uniform axis with the response's own step
# Delays at many sub-bin offsets (0, +-0.5 bin, thirds, ...) and many whole bins apart.
SUB = np.array([0.0, 0.5, -0.5, 1 / 3, -1 / 3, 0.123, 0.999, -0.999, 0.25, 0.75])
DELAYS = np.concatenate([200.0 + T * SUB, 63.0 + T * SUB, [0.0, 17.0 * T, 300.7]])
# The same times, not on the response's grid, and a non-uniform (streak-sweep-like) axis.
OFFGRID = AXIS + 0.37
SWEEP = np.polynomial.polynomial.polyval(np.arange(200), [1.0, 1.9, 0.002])


def _rel_err(got, ref):
    return np.max(np.abs(got - ref)) / np.max(np.abs(ref))


@pytest.mark.parametrize("axis", [AXIS, OFFGRID, SWEEP], ids=["on-grid", "off-grid", "sweep"])
def test_gaussian_shifts_are_exact_at_sub_bin_delays(axis):
    g = gaussian_response(2 * T, time_step_ps=T)            # sigma = 2 bins: exact to ~3e-9 of the peak
    assert g.peak_time_ps == pytest.approx(0.0, abs=1e-9)
    assert g.peak_per_ps == pytest.approx(1 / (2 * T * np.sqrt(2 * np.pi)), rel=1e-9)
    atoms = render_shifted(g, axis, DELAYS)
    ref = gaussian_kernel(axis[None, :] - DELAYS[:, None], 2 * T)
    assert atoms.shape == (DELAYS.size, axis.size)
    assert _rel_err(atoms, ref) < 3e-9


def test_shift_accuracy_follows_the_documented_aliasing_bound():
    # sigma = 1 bin: the documented exp(-(pi sigma / T)^2 / 2) = 7e-3 of the peak; sigma = 1.5 bins: 1.5e-5.
    for sigma, bound in ((T, 7.2e-3), (1.5 * T, 1.5e-5)):
        g = gaussian_response(sigma, time_step_ps=T)
        err = _rel_err(render_shifted(g, AXIS, DELAYS), gaussian_kernel(AXIS[None, :] - DELAYS[:, None], sigma))
        assert bound / 20 < err < bound
    with pytest.raises(ResponseError, match="below the time step"):
        gaussian_response(0.5 * T, time_step_ps=T)


@pytest.mark.parametrize("make", [
    lambda: tailed_response(2 * T, 0.3, 25.0, time_step_ps=T),
    lambda: tailed_response(2 * T, 0.02, 400.0, time_step_ps=T),           # long, weak diffusion tail
    lambda: tailed_response(3 * T, 0.5, 0.5, time_step_ps=T),              # tail much shorter than a bin
    lambda: afterpulse_response(2 * T, 0.05, 30.0, time_step_ps=T),
    lambda: afterpulse_response(2 * T, 0.1, 60.0, time_step_ps=T, tail_fraction=0.2, tail_tau_ps=15.0),
], ids=["tailed", "long-tail", "short-tail", "afterpulse", "afterpulse-tailed"])
@pytest.mark.parametrize("axis", [AXIS, SWEEP], ids=["on-grid", "sweep"])
def test_model_responses_shift_exactly_against_their_closed_form(make, axis):
    irf = make()
    assert irf.samples.sum() * irf.time_step_ps == pytest.approx(1.0, rel=1e-12)
    # The peak convention: the closed form's maximum is at t = 0, and so is the interpolant's.
    assert abs(irf.peak_time_ps) < 1e-6
    assert model_value(irf.model, 0.0, derivative=True) == pytest.approx(0.0, abs=1e-12 * irf.peak_per_ps)
    v = np.linspace(-3.0, 3.0, 601)
    assert np.all(model_value(irf.model, v) <= model_value(irf.model, 0.0) * (1 + 1e-12))
    atoms, d_atoms = render_shifted(irf, axis, DELAYS, normalization="area", derivative=True)
    rel = axis[None, :] - DELAYS[:, None]
    assert _rel_err(atoms, model_value(irf.model, rel)) < 1e-8
    assert _rel_err(d_atoms, -model_value(irf.model, rel, derivative=True)) < 1e-7
    # Unit-peak atoms are the same copies divided by the peak.
    np.testing.assert_allclose(render_shifted(irf, axis, DELAYS[:3]), atoms[:3] / irf.peak_per_ps, rtol=1e-12)


def test_tailed_closed_form_matches_a_numerical_convolution_and_has_the_right_area():
    sigma, f, tau = 3.0, 0.25, 20.0
    irf = tailed_response(sigma, f, tau, time_step_ps=1.0)
    off = irf.model["offset_ps"]
    for x in (-8.0, -1.0, 0.0, 2.5, 30.0, 150.0):
        g = lambda u: np.exp(-0.5 * ((x + off - u) / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi))
        c = x + off
        lo, hi = max(0.0, c - 12 * sigma), max(0.0, c + 12 * sigma)
        emg = integrate.quad(lambda u: g(u) * np.exp(-u / tau) / tau, lo, hi, epsabs=0, epsrel=1e-12)[0] \
            if hi > 0 else 0.0
        ref = (1 - f) * g(0.0) + f * emg
        assert model_value(irf.model, x) == pytest.approx(ref, rel=1e-9, abs=1e-15)
    t = np.linspace(-60, 2000, 200001)
    assert np.trapezoid(model_value(irf.model, t), t) == pytest.approx(1.0, rel=1e-7)
    # The tail falls off as exp(-t / tau) far after the peak.
    late = np.array([200.0, 300.0])
    ratio = model_value(irf.model, late)
    assert ratio[1] / ratio[0] == pytest.approx(np.exp(-100.0 / tau), rel=1e-9)


@pytest.mark.parametrize("alpha_t", [1e-6, 1e-3, 0.06, 1.0, 10.0, 100.0])
@pytest.mark.parametrize("axis", [AXIS, SWEEP], ids=["on-grid", "sweep"])
def test_gaussian_sss_matches_the_closed_form_kernel(alpha_t, axis):
    g = gaussian_response(2 * T, time_step_ps=T)
    alpha = alpha_t / T
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        atoms = render_sss(g, axis, DELAYS, alpha)
    ref = sss_kernel(axis[None, :] - DELAYS[:, None], 2 * T, alpha)
    assert np.all(np.isfinite(atoms))
    assert _rel_err(atoms, ref) < 5e-9


def _sss_quad(model, v, alpha):
    f = lambda u: np.exp(-alpha * u) * model_value(model, v - u)
    pts = [p for p in (v - 40.0, v, v + 40.0) if p > 0]
    return integrate.quad(f, 0.0, max(v + 200.0, 1.0), points=pts or None, epsabs=1e-16, epsrel=1e-11,
                          limit=500)[0]


@pytest.mark.parametrize("alpha", [5e-7, 0.03, 2.0])
def test_tailed_sss_matches_dense_numerical_convolution(alpha):
    irf = tailed_response(2 * T, 0.3, 25.0, time_step_ps=T)
    v = np.array([-20.0, -5.0, -1.3, 0.0, 0.7, 4.0, 11.0, 40.0, 120.0, 400.0, 900.0, 1500.0])
    got = render_sss(irf, v, 0.0, alpha, normalization="area")
    ref = np.array([_sss_quad(irf.model, x, alpha) for x in v])
    np.testing.assert_allclose(got, ref, rtol=2e-7, atol=1e-9 * ref.max())
    # Normalised to the peak the atom has area 1 / (alpha * peak) whatever the response.
    if alpha > 0.01:
        t = np.arange(-100, 40 / alpha + 2000, 0.5)
        area = np.trapezoid(render_sss(irf, t, 0.0, alpha), t)
        assert area == pytest.approx(1 / (alpha * irf.peak_per_ps), rel=1e-6)


def test_sss_continues_exponentially_beyond_the_response_window():
    g = gaussian_response(2 * T, time_step_ps=T)
    t = T * np.arange(3000)                                 # 6 ns: far beyond the 100 ps window
    atoms = render_sss(g, t, np.array([10.0, 10.0 + T / 2]), 0.004)
    ref = sss_kernel(t[None, :] - np.array([10.0, 10.0 + T / 2])[:, None], 2 * T, 0.004)
    assert _rel_err(atoms, ref) < 5e-9


def test_sss_derivatives_match_finite_differences():
    irf = afterpulse_response(2 * T, 0.08, 20.0, time_step_ps=T, tail_fraction=0.2, tail_tau_ps=15.0)
    d = np.array([100.0, 101.0, 140.3])
    a = np.array([1e-6, 0.02, 0.6])
    s, dd, da = render_sss(irf, AXIS, d, a, derivatives=True)
    h = 1e-4
    fd_d = (render_sss(irf, AXIS, d + h, a) - render_sss(irf, AXIS, d - h, a)) / (2 * h)
    fd_a = (render_sss(irf, AXIS, d, a + 1e-7) - render_sss(irf, AXIS, d, a - 1e-7)) / 2e-7
    assert _rel_err(dd, fd_d) < 1e-6
    assert _rel_err(da, fd_a) < 1e-5
    # The same derivatives on the non-uniform path, past the response window as well.
    s2, dd2, da2 = render_sss(irf, SWEEP, d, a, derivatives=True)
    fd_a2 = (render_sss(irf, SWEEP, d, a + 1e-7) - render_sss(irf, SWEEP, d, a - 1e-7)) / 2e-7
    assert _rel_err(da2, fd_a2) < 1e-5


def test_atoms_at_the_window_edge_and_outside_it():
    irf = tailed_response(2 * T, 0.3, 25.0, time_step_ps=T)
    # Direct truncated at the window's start (delay before the first bin) and one at the very end.
    d = np.array([-5.0, AXIS[0], AXIS[-1], AXIS[-1] + 3.0, -5000.0, 1e5])
    atoms = render_shifted(irf, AXIS, d, normalization="area")
    ref = model_value(irf.model, AXIS[None, :] - d[:, None])
    assert np.max(np.abs(atoms - ref)) < 1e-8 * irf.peak_per_ps
    assert np.all(atoms[4:] == 0.0)                          # entirely outside: exact zeros
    sss = render_sss(irf, AXIS, d, 0.05)
    assert np.all(np.isfinite(sss)) and np.all(sss[5] == 0.0)
    # An onset 5 ns before the window: only the far tail of the exponential, falling by exp(-alpha T) a bin.
    assert 0 < sss[4].max() < 1e-80
    np.testing.assert_allclose(sss[4][1:] / sss[4][:-1], np.exp(-0.05 * T), rtol=1e-9)


def test_atoms_vectorise_over_any_leading_shape():
    irf = gaussian_response(3.0, time_step_ps=T)
    d = 100.0 + np.arange(12.0).reshape(3, 4)
    alpha = np.full((3, 4), 0.02)
    assert render_shifted(irf, AXIS, d).shape == (3, 4, AXIS.size)
    out = render_sss(irf, AXIS, d, alpha)
    assert out.shape == (3, 4, AXIS.size)
    np.testing.assert_allclose(out[1, 2], render_sss(irf, AXIS, d[1, 2], 0.02), rtol=1e-13)
    assert render_shifted(irf, AXIS, 50.0).shape == (AXIS.size,)


def test_widths_and_moments():
    g = gaussian_response(4.0, time_step_ps=T)
    assert g.fwhm_ps() == pytest.approx(2 * np.sqrt(2 * np.log(2)) * 4.0, rel=1e-9)
    assert g.centroid_ps() == pytest.approx(0.0, abs=1e-9)
    tr = tailed_response(4.0, 0.25, 20.0, time_step_ps=T)
    # The centroid of (1 - f) N + f EMG lies f * tau after the Gaussian's centre.
    assert tr.centroid_ps() + tr.model["offset_ps"] == pytest.approx(0.25 * 20.0, rel=1e-9)


def test_gaussian_fit_says_how_far_a_response_is_from_the_gaussian():
    exact = gaussian_fit(gaussian_response(5.0, time_step_ps=T))
    assert exact["rms_misfit"] < 1e-8 and exact["sigma_ps"] == pytest.approx(5.0, rel=1e-7)
    assert exact["center_ps"] == pytest.approx(0.0, abs=1e-7)
    misfits = [gaussian_fit(tailed_response(5.0, f, 30.0, time_step_ps=T))["rms_misfit"] for f in (1e-4, 0.05, 0.2)]
    assert misfits[0] < 1e-3 < misfits[1] < misfits[2]
    # The residual it reports is the residual of its own Gaussian.
    irf = afterpulse_response(5.0, 0.1, 40.0, time_step_ps=T)
    fit = gaussian_fit(irf)
    t = irf.time_axis_ps()
    v = irf.samples / irf.peak_per_ps
    sel = slice(np.flatnonzero(v >= 0.01)[0], np.flatnonzero(v >= 0.01)[-1] + 1)
    g = fit["amplitude"] * gaussian_kernel(t[sel] - fit["center_ps"], fit["sigma_ps"])
    assert fit["rms_misfit"] == pytest.approx(np.sqrt(np.mean((g - v[sel]) ** 2)), rel=1e-9)


def test_response_validation_names_the_problem():
    t = np.arange(-20, 21) * 1.0
    good = np.exp(-0.5 * (t / 3) ** 2)
    r = InstrumentResponse(5 * good, 1.0, -20.0, {"source": "test"})
    assert r.samples.sum() == pytest.approx(1.0) and not r.samples.flags.writeable
    assert r.peak_time_ps == pytest.approx(0.0, abs=1e-12)
    # Centring moves the reference instant onto the peak.
    moved = InstrumentResponse(good, 1.0, -17.6).centred()
    assert moved.peak_time_ps == pytest.approx(0.0, abs=1e-9) and moved.t0_ps == pytest.approx(-20.0, abs=1e-9)
    cases = [
        (dict(samples=good[:5], time_step_ps=1.0), "at least 8 samples"),
        (dict(samples=np.where(t == 0, np.nan, good), time_step_ps=1.0), "finite"),
        (dict(samples=good, time_step_ps=0.0), "time_step_ps"),
        (dict(samples=good, time_step_ps=1.0, t0_ps=np.inf), "t0_ps"),
        (dict(samples=np.zeros(41), time_step_ps=1.0), "no positive peak"),
        (dict(samples=good - 0.1 * (t == 15), time_step_ps=1.0), "non-negative"),
        (dict(samples=np.exp(-0.5 * ((t + 20) / 3) ** 2), time_step_ps=1.0), "first sample"),
        (dict(samples=np.exp(-0.5 * ((t - 19) / 3) ** 2), time_step_ps=1.0), "last sample"),
        (dict(samples=good, time_step_ps=1.0, provenance={"x": object()}), "JSON"),
        (dict(samples=np.ones((3, 10)), time_step_ps=1.0), "1-D"),
    ]
    for kwargs, match in cases:
        with pytest.raises(ResponseError, match=match):
            InstrumentResponse(**kwargs)
    with pytest.raises(ResponseError, match="tail_fraction"):
        tailed_response(3.0, 1.0, 10.0, time_step_ps=1.0)
    with pytest.raises(ResponseError, match="alpha_per_ps"):
        render_sss(r, AXIS, 0.0, -1.0)
    with pytest.raises(ResponseError, match="normalization"):
        render_shifted(r, AXIS, 0.0, normalization="max")
    with pytest.raises(ResponseError, match="delay_ps"):
        render_shifted(r, AXIS, np.nan)
