"""The compiled evaluation of the variable-projection refine (kernels.projected) agrees with the
NumPy reference path (model.varpro with COMPILED off): its amplitudes, RSS and normal equations to
1e-12 of their size, and refine() with every prior and a hold to 1e-9 in every parameter."""
import numpy as np
import pytest

from core.model import render_profile
from decomposition.model import varpro
from decomposition.model.refine import refine
from decomposition.model.varpro import Layout

L, TB = 256, 2.0
T = TB * np.arange(1, L + 1)


def _batch(rng, n, k, shared):
    """n pixels of k slots (direct, sss, inter-reflections; some absent, one wholly after the
    axis), their layout, theta and free mask (a tenth of the parameters held)."""
    lay = Layout(k, shared)
    present = rng.random((n, k)) < 0.7
    present[:, 0] = True
    delay = np.sort(rng.uniform(40.0, 420.0, (n, k)), axis=1)
    delay[:, 1] = delay[:, 0] + rng.uniform(0.0, 12.0, n)
    delay[0, k - 1], present[0, k - 1] = 2000.0, True
    sigma = rng.uniform(2.0, 6.0, (n, k))
    alpha = rng.uniform(0.02, 0.3, n)
    theta = np.where(lay.free(present), lay.pack(delay, sigma, alpha, present), 0.0)
    free = lay.free(present) & ~(rng.random((n, lay.p)) < 0.1)
    return lay, theta, present, free


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("background", [False, True])
@pytest.mark.parametrize("ratio_prior", [False, True])
def test_normal_equations_match_numpy(shared, background, ratio_prior, monkeypatch):
    rng = np.random.default_rng(7)
    n, k = 24, 4
    lay, theta, present, free = _batch(rng, n, k, shared)
    sw = np.sqrt(rng.uniform(0.5, 2.0, (n, L)))
    y = rng.normal(size=(n, L)) * sw
    bg = (rng.random(n) < 0.5) if background else None
    amp = None
    if ratio_prior:
        amp = np.zeros((n, k))
        amp[present[:, 1], 0], amp[present[:, 1], 1] = -0.6 * 3.0, 3.0
    for jac in (True, False):
        got = varpro._evaluate(lay, T, y, theta, present, free, None, jac, sw, bg, amp)
        monkeypatch.setattr(varpro, "COMPILED", False)
        want = varpro._evaluate(lay, T, y, theta, present, free, None, jac, sw, bg, amp)
        monkeypatch.setattr(varpro, "COMPILED", True)
        for g, w in zip(got, want):
            if w is None:
                assert g is None
                continue
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12 * np.max(np.abs(w)))


def _pixels(rng, n):
    params = {"direct_delay_ps": rng.uniform(80.0, 150.0, n), "direct_amplitude": rng.uniform(0.5, 1.5, n),
              "direct_sigma_ps": np.full(n, 4.0), "sss_amplitude": rng.uniform(0.1, 0.5, n),
              "sss_sigma_ps": np.full(n, 4.0), "sss_alpha_per_ps": rng.uniform(0.03, 0.2, n),
              "ir_delay_ps": rng.uniform(200.0, 400.0, (n, 1)), "ir_amplitude": rng.uniform(0.1, 0.4, (n, 1)),
              "ir_sigma_ps": np.full((n, 1), 4.0)}
    params["sss_delay_ps"] = params["direct_delay_ps"] + rng.uniform(0.0, 5.0, n)
    params["sss_amplitude"][-3:] = np.nan      # three pixels without an sss
    return params


@pytest.mark.parametrize("shared_sigma", [True, False])
def test_refine_with_priors_and_holds_matches_numpy(shared_sigma, monkeypatch):
    # every prior, held widths and decay rates, an offset fitted on half the pixels and held on
    # a quarter
    rng = np.random.default_rng(3)
    n = 24
    truth = _pixels(rng, n)
    y = render_profile(truth, L, TB, TB) + rng.normal(0.0, 0.02, (n, L)) + 0.05
    start = {k: v + rng.normal(0.0, 0.5, np.shape(v)) if "delay" in k else v for k, v in truth.items()}
    every = np.arange(n)
    start["background"] = np.where(every % 4 == 3, 0.05, 0.0)       # held on a quarter of the pixels
    kw = dict(time_bin_ps=TB, t0_ps=TB, shared_sigma=shared_sigma, sss_after_direct=True,
              fit_background=every % 2 == 0,
              weights=rng.uniform(0.5, 2.0, (n, L)),
              delay_prior=(truth["direct_delay_ps"] + 0.3, np.full(n, 50.0)),
              onset_prior=(np.full(n, 2.0), np.full(n, 5.0)),
              alpha_prior=(np.log(np.nan_to_num(truth["sss_alpha_per_ps"], nan=0.1)), np.full(n, 20.0)),
              ratio_prior=(np.full(n, 0.3), np.full(n, 1.0)),
              hold={"sigma_ps": np.where(every % 3 == 0, 4.0, np.nan),
                    "sss_alpha_per_ps": np.where(every % 4 == 1, 0.05, np.nan)})
    got, got_info = refine(y, start, **kw)
    monkeypatch.setattr(varpro, "COMPILED", False)
    want, want_info = refine(y, start, **kw)
    assert got_info["refined"].sum() > n // 2          # the fits moved: a comparison of refits
    np.testing.assert_array_equal(got_info["refined"], want_info["refined"])
    np.testing.assert_array_equal(got_info["iterations"], want_info["iterations"])
    for key in want:
        np.testing.assert_allclose(got[key], want[key], rtol=1e-9, atol=1e-9, err_msg=key)
    for key in ("rss", "rss_input"):
        np.testing.assert_allclose(got_info[key], want_info[key], rtol=1e-11, err_msg=key)


@pytest.mark.parametrize("shared_sigma", [True, False])
def test_standard_errors_match_numpy(shared_sigma, monkeypatch):
    # the Fisher information's rows and Gram product compiled (kernels.projected.fisher_gram):
    # weights, an offset on some pixels, onsets at the direct (sss_after_direct), holds; to 1e-6
    # (a few of these pixels' Fisher matrices are ill-conditioned, their errors tens of ps: the
    # rounding of the Gram product is amplified by their condition)
    from decomposition.model.fisher import cramer_rao_bound, standard_errors

    rng = np.random.default_rng(5)
    n = 24
    params = _pixels(rng, n)
    params["sss_delay_ps"][:4] = params["direct_delay_ps"][:4]        # the onset constraint active
    params["ir_delay_ps"][0, 0] = 2000.0                               # an echo after the axis ends
    y = render_profile(params, L, TB, TB) + rng.normal(0.0, 0.02, (n, L))
    every = np.arange(n)
    kw = dict(time_bin_ps=TB, t0_ps=TB, weights=rng.uniform(0.5, 2.0, (n, L)), shared_sigma=shared_sigma,
              sss_after_direct=True, offset=every % 2 == 0,
              hold={"sigma_ps": np.where(every % 3 == 0, 4.0, np.nan),
                    "sss_alpha_per_ps": np.where(every % 5 == 1, 0.05, np.nan)})
    got = standard_errors(y, params, **kw)
    got_crb = cramer_rao_bound(params, 0.02, n_bins=L, time_bin_ps=TB, t0_ps=TB, shared_sigma=shared_sigma)
    monkeypatch.setattr(varpro, "COMPILED", False)
    want = standard_errors(y, params, **kw)
    want_crb = cramer_rao_bound(params, 0.02, n_bins=L, time_bin_ps=TB, t0_ps=TB, shared_sigma=shared_sigma)
    for g, w in ((got, want), (got_crb, want_crb)):
        assert g.keys() == w.keys()
        assert np.isfinite(w["direct_delay_ps_stderr" if "direct_delay_ps_stderr" in w else "direct_delay_ps_crb"]).sum() > n // 2
        for key in w:
            np.testing.assert_array_equal(np.isnan(g[key]), np.isnan(w[key]), err_msg=key)
            np.testing.assert_allclose(g[key], w[key], rtol=1e-6, err_msg=key)


def _table_design_rows(table):
    """varpro.design_rows for a response's table atoms (kernels.response.slot_rows): the atoms, their
    delay derivatives, zero width rows, the sss log decay rate's derivative, each weighted; the data."""
    from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS, SSS_SLOT
    from decomposition.kernels.response import slot_rows

    def rows(t, y, delay, sigma, alpha, present, tb, jac, sw=None):
        n, k = present.shape
        fam = np.where(present, FAM_GAUSS, FAM_NONE).astype(np.int8)
        fam[:, SSS_SLOT] = np.where(present[:, SSS_SLOT], FAM_SSS, FAM_NONE)
        phi, dd, da = slot_rows(table, t, fam, np.where(present, delay, 0.0),
                                np.where(fam == FAM_SSS, alpha[:, None], 0.0), derivatives=True)
        m = np.zeros((n, 3 * k + 2 if jac else k + 1, t.size))
        m[:, :k] = phi
        if jac:
            m[:, k:2 * k] = dd
            m[:, 3 * k] = da[:, SSS_SLOT] * alpha[:, None]
        m[:, :-1] *= sw[:, None, :]
        m[:, -1] = y
        return m
    return rows


@pytest.mark.parametrize("background", [False, True])
def test_table_normal_equations_match_numpy(background, monkeypatch):
    """A response's table atoms (the widths held, as refine_block holds them): the compiled
    evaluation's amplitudes, RSS, J^T J and J^T r equal Kaufman's algebra of the NumPy path over
    the same atoms; the rows and columns of the held parameters are zero."""
    from core.irf_models import tailed_response
    from decomposition.kernels.projected import instrument
    from decomposition.kernels.response import response_table

    table = response_table(tailed_response(4.0, 0.2, 30.0, time_step_ps=TB))
    rng = np.random.default_rng(11)
    n, k = 24, 4
    lay, theta, present, free = _batch(rng, n, k, False)
    free &= ~lay.held(np.zeros((n, k), bool), np.ones(n, bool), np.zeros(n, bool))
    theta[:, k:2 * k] = 0.0
    sw = np.sqrt(rng.uniform(0.5, 2.0, (n, L)))
    y = rng.normal(size=(n, L)) * sw
    bg = (rng.random(n) < 0.5) if background else None
    for jac in (True, False):
        got = varpro._evaluate(lay, T, y, theta, present, free, None, jac, sw, bg, None, instrument(table, T))
        monkeypatch.setattr(varpro, "COMPILED", False)
        monkeypatch.setattr(varpro, "design_rows", _table_design_rows(table))
        want = varpro._evaluate(lay, T, y, theta, present, free, None, jac, sw, bg, None)
        monkeypatch.undo()
        for g, w in zip(got, want):
            if w is None:
                assert g is None
                continue
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12 * np.max(np.abs(w)))
        if jac:
            held = ~free
            assert np.all(got[2][held[:, :, None] | held[:, None, :]] == 0.0)
            assert np.all(got[3][held] == 0.0)


@pytest.mark.parametrize("residual", [False, True])
def test_compiled_steps_match_numpy_over_table_atoms(residual, monkeypatch):
    """The damped loop compiled one pixel at a time (kernels.projlm) takes the NumPy loop's steps
    over a response's table atoms: noisy profiles from perturbed starts, weights, an offset on half
    the pixels, every prior and a held decay rate; the same iterations, the same kept fits and the
    parameters to 1e-9 (a pixel's sss well above the noise, so that no step is ill-conditioned)."""
    from core.irf_models import tailed_response
    from decomposition.constants import FAM_GAUSS, FAM_SSS
    from decomposition.kernels.response import response_table, slot_rows

    table = response_table(tailed_response(4.0, 0.2, 30.0, time_step_ps=TB))
    rng = np.random.default_rng(5)
    n, k = 32, 3
    lay = Layout(k, widths=False)
    present = np.ones((n, k), bool)
    delay = rng.uniform(60.0, 120.0, n)
    onset = delay + rng.uniform(0.5, 3.0, n)
    echo = delay + rng.uniform(40.0, 80.0, n)
    alpha = rng.uniform(0.03, 0.1, n)
    theta = lay.pack(np.stack([delay, onset, echo], 1), np.ones((n, k)), alpha, present)
    fam = np.broadcast_to(np.array([FAM_GAUSS, FAM_SSS, FAM_GAUSS]), (n, k))
    rows = slot_rows(table, T, fam, np.stack([delay, onset, echo], 1), np.broadcast_to(alpha[:, None], (n, k)))
    amps = np.stack([rng.uniform(0.5, 1.0, n), rng.uniform(0.3, 0.6, n), rng.uniform(0.2, 0.4, n)], 1)
    sw = np.sqrt(rng.uniform(0.5, 2.0, (n, L)))
    bg = rng.random(n) < 0.5
    y = (np.einsum("nk,nkl->nl", amps, rows) + 0.1 * bg[:, None] + rng.normal(0.0, 0.01, (n, L))) * sw
    start = theta + np.concatenate([rng.normal(0.0, 2.0, (n, k)), rng.normal(0.0, 0.3, (n, 1))], 1)
    start[:, 1] = np.maximum(start[:, 1], start[:, 0])
    slots = {"present": present, "delay": start[:, :k], "sigma": np.ones((n, k)), "alpha": np.exp(start[:, k]),
             "amplitude": np.zeros((n, k)), "fit_background": bg, "background": np.zeros(n),
             "delay_prior_mean": delay + 0.2, "delay_prior_weight": np.full(n, 5.0),
             "onset_prior_mean": onset - delay, "onset_prior_weight": np.full(n, 1.0),
             "alpha_prior_mean": np.log(alpha), "alpha_prior_weight": np.full(n, 2.0),
             "ratio_prior_mean": amps[:, 1] / amps[:, 0], "ratio_prior_weight": np.full(n, 0.5)}
    held = np.zeros((n, lay.p), bool)
    held[::4, k] = True
    bounds = lay.bounds((0.0, 600.0), (0.0, 0.0), (np.log(1e-3), np.log(1.0)))
    kw = dict(sw=sw, sss_after_direct=True, held=held, table=table, residual=residual)
    got, got_info = varpro.refine_block(T, y, slots, lay, bounds, None, 30, 1e-8, 1e-6, **kw)
    monkeypatch.setattr(varpro, "_steps_compiled", varpro._steps_numpy)
    want, want_info = varpro.refine_block(T, y, slots, lay, bounds, None, 30, 1e-8, 1e-6, **kw)
    assert want_info["refined"].all() and np.all(want_info["iterations"] > 2)     # the fits moved
    for key in ("refined", "converged", "iterations"):
        np.testing.assert_array_equal(got_info[key], want_info[key], err_msg=key)
    for key in ("delay", "alpha", "amplitude", "background"):
        np.testing.assert_allclose(got[key], want[key], rtol=1e-9, atol=1e-9, err_msg=key)
    np.testing.assert_allclose(got_info["rss"], want_info["rss"], rtol=1e-10)
    if residual:
        np.testing.assert_allclose(got_info["residual"], want_info["residual"], rtol=0, atol=1e-10)


@pytest.mark.parametrize("earliest", [False, True])
def test_compiled_constraints_match_numpy(earliest):
    """The compiled loop's projections onto the ordering constraints (the sss onset at or after the
    direct or the earliest shifted atom; inter-reflections in order) equal varpro's, NaN included."""
    from decomposition.kernels import projlm

    rng = np.random.default_rng(2)
    n, k = 400, 4
    theta = rng.uniform(50.0, 60.0, (n, k + 1))
    theta[rng.random((n, k + 1)) < 0.03] = np.nan
    present = rng.random((n, k)) < 0.7
    want = varpro._keep_order(varpro._onset_after_direct(theta.copy(), present, earliest), present)
    got = theta.copy()
    for p in range(n):
        projlm._onset_after_direct(got[p], present[p], earliest)
        projlm._keep_order(got[p], present[p])
    assert not np.array_equal(want, theta, equal_nan=True)      # the projections moved some
    np.testing.assert_array_equal(got, want)
