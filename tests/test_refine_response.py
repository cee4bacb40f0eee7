"""The variable-projection refinement over a measured response's atoms (decomposition.model.refine,
``irf=``): the Gaussian path's engine (decomposition.model.varpro, decomposition.kernels.projected)
rendering the response's table atoms instead of Gaussians.

Known answers: noise-free profiles rendered with the response's exact interpolant
(decomposition.model.atoms.params_profile) are fitted back to their parameters from perturbed starts;
an offset and zero-weight samples are handled as with the Gaussian PSF.
"""
import numpy as np
import pytest

from core.irf_models import tailed_response
from decomposition.model.atoms import params_profile
from decomposition.model.refine import refine

T = 2.0
L = 256
T_PS = T + T * np.arange(L)


@pytest.fixture(scope="module")
def irf():
    return tailed_response(4.0, 0.2, 30.0, time_step_ps=T)


def _scene(n, seed, onset_ps=(3.0, 8.0)):
    rng = np.random.default_rng(seed)
    nan = np.full(n, np.nan)
    d = rng.uniform(60, 120, n)
    truth = {"direct_delay_ps": d, "direct_amplitude": rng.uniform(0.5, 1.0, n), "direct_sigma_ps": nan.copy(),
             "sss_delay_ps": d + rng.uniform(*onset_ps, n), "sss_amplitude": rng.uniform(0.1, 0.4, n),
             "sss_sigma_ps": nan.copy(), "sss_alpha_per_ps": rng.uniform(0.02, 0.1, n),
             "ir_delay_ps": (d + rng.uniform(30, 60, n))[:, None], "ir_amplitude": rng.uniform(0.1, 0.3, (n, 1)),
             "ir_sigma_ps": np.full((n, 1), np.nan)}
    start = {k: v.copy() for k, v in truth.items()}
    start["direct_delay_ps"] = d + rng.normal(0, 0.5, n)
    start["sss_delay_ps"] = np.maximum(truth["sss_delay_ps"] + rng.normal(0, 0.5, n), start["direct_delay_ps"])
    start["ir_delay_ps"] = truth["ir_delay_ps"] + rng.normal(0, 0.5, (n, 1))
    start["sss_alpha_per_ps"] = truth["sss_alpha_per_ps"] * np.exp(rng.normal(0, 0.1, n))
    start["direct_amplitude"] = truth["direct_amplitude"] * 1.1
    return truth, start


def test_clean_profiles_are_fitted_back_to_their_parameters(irf):
    truth, start = _scene(24, 0)
    y = params_profile(irf, T_PS, truth)
    out, info = refine(y, start, time_bin_ps=T, irf=irf, max_iter=60, ftol=1e-15, sss_after_direct=True)
    assert info["refined"].all()
    for key, tol in (("direct_delay_ps", 1e-5), ("sss_delay_ps", 1e-4), ("ir_delay_ps", 1e-5),
                     ("sss_alpha_per_ps", 1e-6), ("direct_amplitude", 1e-6), ("sss_amplitude", 1e-5),
                     ("ir_amplitude", 1e-6)):
        np.testing.assert_allclose(out[key], truth[key], atol=tol, err_msg=key)
    # a response has no width: the width keys come back as given
    for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"):
        assert np.array_equal(out[key], start[key], equal_nan=True)


def test_the_truth_is_the_fit_of_its_own_profile(irf):
    truth, _ = _scene(8, 1)
    y = params_profile(irf, T_PS, truth)
    out, info = refine(y, truth, time_bin_ps=T, irf=irf, max_iter=5)
    # the compiled table atoms are the exact interpolant's to the table's error
    assert np.all(info["rss_input"] < 1e-20 * np.sum(y * y, axis=-1))
    np.testing.assert_allclose(out["direct_delay_ps"], truth["direct_delay_ps"], atol=1e-9)


def test_an_offset_and_zero_weight_samples(irf):
    truth, start = _scene(12, 2)
    y = params_profile(irf, T_PS, truth) + 0.05
    w = np.ones_like(y)
    w[:, 150:160] = 0.0
    y[:, 150:160] = np.nan          # ignored where the weight is 0
    start["background"] = np.zeros(12)
    out, info = refine(y, start, time_bin_ps=T, irf=irf, weights=w, fit_background=True, max_iter=60, ftol=1e-15,
                       sss_after_direct=True)
    np.testing.assert_allclose(out["background"], 0.05, atol=1e-7)
    np.testing.assert_allclose(out["direct_delay_ps"], truth["direct_delay_ps"], atol=1e-5)


def test_held_onset_stays_and_the_rest_is_fitted_around_it(irf):
    truth, start = _scene(10, 3)
    y = params_profile(irf, T_PS, truth)
    out, _ = refine(y, start, time_bin_ps=T, irf=irf, max_iter=60, ftol=1e-15,
                    hold={"direct_delay_ps": truth["direct_delay_ps"]})
    assert np.array_equal(out["direct_delay_ps"], truth["direct_delay_ps"])
    np.testing.assert_allclose(out["ir_delay_ps"], truth["ir_delay_ps"], atol=1e-5)


def test_bad_combinations_are_refused(irf):
    truth, start = _scene(2, 4)
    y = params_profile(irf, T_PS, truth)
    with pytest.raises(ValueError, match="bin_integrated"):
        refine(y, start, time_bin_ps=T, irf=irf, bin_integrated=True)
    with pytest.raises(ValueError, match="sigma_ps"):
        refine(y, start, time_bin_ps=T, irf=irf, hold={"sigma_ps": 3.0})


def _response_state(irf, y, params, components="d,r,s"):
    """The response path's state for profiles ``y`` refitted from ``params`` (its refinement,
    the detection skipped): (ResponseFit, samples, opts, slots)."""
    from decomposition.options import GridSpec, SolverOptions, parse_components
    from decomposition.response import path as rp
    from decomposition.response.label import param_slots
    from decomposition.response.refine import refit_slots
    from decomposition.stages.prepare import prepare_samples, time_axis
    fams = parse_components(components)
    opts = SolverOptions().resolved(fams)
    samples = prepare_samples(y, time_axis(T, T), GridSpec(), noise_floor=opts.noise_floor,
                              rel_threshold=opts.rel_threshold, noise=opts.noise)
    rf = rp.detect(samples, irf, GridSpec(), opts, fams)
    fam, delay, lalp = param_slots(params, rf.refine_kw["R"])
    slots = refit_slots(samples.profiles[samples.live], fam, delay, lalp, rf.b_est, rf.with_bg, params,
                        **rf.refine_kw)
    return rf, samples, opts, slots


def _with_slot(rf, s, rows, slot, delay_ps, amp):
    """Slots ``s`` with a shifted atom put in ``slot`` of the pixels ``rows`` (normalised amplitude
    ``amp``), their parameters rebuilt."""
    from decomposition.constants import FAM_GAUSS
    from decomposition.response.label import slots_to_params
    from decomposition.response.refine import Slots
    fam, delay, amps = s.fam.copy(), s.delay.copy(), s.amp.copy()
    fam[rows, slot], delay[rows, slot], amps[rows, slot] = FAM_GAUSS, delay_ps, amp
    params = slots_to_params(fam, delay, s.lalp, amps, rf.refine_kw["scale"], rf.sigma_eq_ps, rf.refine_kw["R"])
    params.pop("background", None)
    return Slots(fam, delay, s.lalp, amps, params, s.background, s.iterations)


def _padded(params, n_ir=3):
    out = dict(params)
    for key in ("ir_delay_ps", "ir_amplitude", "ir_sigma_ps"):
        v = np.full((np.shape(params["direct_delay_ps"])[0], n_ir), np.nan)
        v[:, :1] = params[key]
        out[key] = v
    return out


def test_a_far_sss_on_an_echo_is_swapped_for_the_echo_on_count_data(irf):
    """The forward steps' far-sss swap (decomposition.response.grow): 8 pixels of a direct and one
    echo 60 ps after it, no sss, at 1,000 photons, whose fit put a fast sss (alpha at its bound,
    0.2 / ps) on the echo.  The swap turns each into the shifted copy it is, within 1 ps of the
    echo; without the swap the echo rounds keep the sss there (it fits the echo's peak, and no
    echo fits beside it)."""
    from decomposition.constants import FAM_GAUSS, FAM_NONE, SSS_SLOT
    from decomposition.options import parse_components
    from decomposition.response import path as rp
    n = 8
    d = np.random.default_rng(3).uniform(60, 100, n)
    nan = np.full(n, np.nan)
    no_ir = np.full((n, 3), np.nan)
    truth = {"direct_delay_ps": d, "direct_amplitude": np.ones(n), "direct_sigma_ps": nan,
             "sss_delay_ps": nan, "sss_amplitude": nan, "sss_alpha_per_ps": nan, "sss_sigma_ps": nan,
             "ir_delay_ps": np.where(np.arange(3) == 0, d[:, None] + 60.0, np.nan),
             "ir_amplitude": np.where(np.arange(3) == 0, 0.3, no_ir), "ir_sigma_ps": no_ir}
    mu = params_profile(irf, T_PS, truth)
    scale = 1000.0 / mu.sum(axis=1)
    y = np.random.default_rng(7).poisson(mu * scale[:, None]).astype(np.float64)
    start = {**truth, "direct_amplitude": scale, "sss_delay_ps": d + 60.0, "sss_amplitude": 0.3 * scale,
             "sss_alpha_per_ps": np.full(n, 0.2), "ir_delay_ps": no_ir, "ir_amplitude": no_ir}
    rf, samples, opts, slots = _response_state(irf, y, start)
    assert samples.noise_model == "poisson"
    assert np.all(np.abs(slots.delay[:, SSS_SLOT] - (d + 60.0)) < 20.0)     # the fit kept the sss on the echo
    rf.slots = slots
    rp.forward_steps(rf, samples, opts, parse_components("d,r,s"))
    assert rf.grow_info["response_sss_swapped"] == n
    fam = rf.slots.fam
    assert np.all(fam[:, SSS_SLOT] == FAM_NONE) and np.all((fam[:, 2:] == FAM_GAUSS).sum(axis=1) == 1)
    echo_ps = np.where(fam[:, 2:] == FAM_GAUSS, rf.slots.delay[:, 2:], 0.0).sum(axis=1)
    np.testing.assert_allclose(echo_ps, d + 60.0, atol=1.0)
    np.testing.assert_allclose(rf.slots.delay[:, 0], d, atol=0.5)


def test_two_shifted_copies_the_refit_puts_on_one_delay_are_one_atom(irf):
    """A direct given twice (the second copy 0.2 ps after it): the refit's merge rule keeps one
    shifted atom, in the direct's slot, with the light of both."""
    from decomposition.constants import FAM_GAUSS
    from decomposition.response.refine import refit_slots
    truth, _ = _scene(6, 7)
    y = params_profile(irf, T_PS, truth)
    rf, samples, opts, slots = _response_state(irf, y, _padded(truth))
    s = _with_slot(rf, slots, np.arange(6), 3, slots.delay[:, 0] + 0.2, 0.2)
    out = refit_slots(samples.profiles[samples.live], s.fam, s.delay, s.lalp, rf.b_est, rf.with_bg, s.params,
                      **rf.refine_kw)
    assert ((out.fam == FAM_GAUSS).sum(axis=1) == 2).all()       # the direct and the true echo
    np.testing.assert_allclose(out.params["direct_amplitude"], truth["direct_amplitude"], rtol=1e-4)
    np.testing.assert_allclose(out.params["direct_delay_ps"], truth["direct_delay_ps"], atol=1e-3)


def test_the_engine_returns_the_weighted_residual_of_its_fit(irf):
    """refine_block(residual=True) over the response's atoms, with an offset and zero-weight
    samples: the residual it returns is sw (y - sum_k c_k phi_k - b) of the fit it returns (the
    atoms rendered afresh), its sum of squares the fit's RSS; NaN for a pixel whose fit is not
    kept (no data: nothing to lower)."""
    from decomposition.constants import FAM_GAUSS, FAM_SSS
    from decomposition.kernels.response import response_table, slot_rows
    from decomposition.model.varpro import Layout, refine_block

    n = 7
    truth, start = _scene(n, 5)
    rng = np.random.default_rng(5)
    y = params_profile(irf, T_PS, truth) + 0.05 + 0.01 * rng.standard_normal((n, L))
    y[-1] = 0.0
    sw = np.ones((n, L))
    sw[:, 150:160] = 0.0
    delay = np.stack([start["direct_delay_ps"], start["sss_delay_ps"], start["ir_delay_ps"][:, 0]], axis=1)
    slots = {"delay": delay, "sigma": np.ones((n, 3)), "amplitude": np.zeros((n, 3)), "present": np.ones((n, 3), bool),
             "alpha": start["sss_alpha_per_ps"], "fit_background": np.ones(n, bool), "background": np.zeros(n)}
    lay = Layout(3)
    lo, hi = lay.bounds((0.0, 600.0), (0.0, 0.0), (-10.0, 2.0))
    table = response_table(irf)
    out, info = refine_block(T_PS, y * sw, slots, lay, (lo, hi), None, 40, 1e-12, 1e-3, sw=sw, table=table,
                             positive=False, residual=True)
    kept = info["refined"]
    assert kept[:-1].all() and not kept[-1]
    assert np.isnan(info["residual"][-1]).all()
    fam = np.array([[FAM_GAUSS, FAM_SSS, FAM_GAUSS]] * n, np.int8)
    alpha = np.where(fam == FAM_SSS, out["alpha"][:, None], 0.0)
    phi = slot_rows(table, T_PS, fam, out["delay"], alpha)
    want = sw * (y - np.einsum("nk,nkl->nl", out["amplitude"], phi) - out["background"][:, None])
    np.testing.assert_allclose(info["residual"][kept], want[kept], rtol=0, atol=1e-12 * np.max(np.abs(y)))
    np.testing.assert_allclose(np.sum(info["residual"][kept] ** 2, axis=1), info["rss"][kept], rtol=1e-10)


def test_a_layout_without_widths_takes_the_same_fit(irf):
    """Layout(widths=False): theta = [delays, log alpha] (a response's atoms have no width); over
    the response's atoms refine_block takes the same fit as with the width parameters held, to
    rounding on well-separated atoms; the Gaussian PSF's atoms refuse it."""
    from decomposition.kernels.response import response_table
    from decomposition.model.varpro import Layout, refine_block

    n = 6
    truth, start = _scene(n, 6)
    y = params_profile(irf, T_PS, truth) + 0.002 * np.random.default_rng(6).standard_normal((n, L))
    delay = np.stack([start["direct_delay_ps"], start["sss_delay_ps"], start["ir_delay_ps"][:, 0]], axis=1)
    slots = {"delay": delay, "sigma": np.ones((n, 3)), "amplitude": np.zeros((n, 3)), "present": np.ones((n, 3), bool),
             "alpha": start["sss_alpha_per_ps"]}
    lean = Layout(3, widths=False)
    assert lean.p == 4 and np.array_equal(lean.pack(delay, np.ones((n, 3)), slots["alpha"], slots["present"]),
                                          np.column_stack([delay, np.log(slots["alpha"])]))
    fits = []
    for lay in (lean, Layout(3)):
        bounds = lay.bounds((0.0, 600.0), (0.0, 0.0), (-10.0, 2.0))
        fits.append(refine_block(T_PS, y, slots, lay, bounds, None, 40, 1e-12, 1e-3, table=response_table(irf),
                                 positive=False))
    (a, ia), (b, ib) = fits
    assert ia["refined"].all() and ib["refined"].all()
    for key in ("delay", "alpha", "amplitude"):
        np.testing.assert_allclose(a[key], b[key], rtol=1e-9, err_msg=key)
    with pytest.raises(ValueError, match="widths"):
        refine_block(T_PS, y, slots, lean, lean.bounds((0.0, 600.0), (0.0, 0.0), (-10.0, 2.0)), None, 5, 1e-12,
                     1e-3)
    with pytest.raises(ValueError, match="shared"):
        Layout(3, shared_sigma=True, widths=False)


def test_a_count_fit_step_singular_to_rounding_is_refused_not_raised():
    """A damped system singular to rounding (a degenerate pair of columns under a damping
    shrunk below their rounding) gives a NaN step, which the count fit refuses like any
    non-finite step; the other systems of the batch are solved exactly."""
    from decomposition.response.refine import _solve_rows

    lhs = np.array([[[2.0, 0.0], [0.0, 4.0]], [[1.0, 1.0], [1.0, 1.0]], [[3.0, 1.0], [1.0, 2.0]]])
    rhs = np.array([[2.0, 4.0], [1.0, 1.0], [5.0, 5.0]])
    out = _solve_rows(lhs, rhs)
    np.testing.assert_allclose(out[0], [1.0, 1.0])
    assert np.all(np.isnan(out[1]))
    np.testing.assert_allclose(out[2], [1.0, 2.0])
    np.testing.assert_allclose(_solve_rows(lhs[[0, 2]], rhs[[0, 2]]), out[[0, 2]])


@pytest.mark.parametrize("dispersion", [False, True])
def test_the_compiled_count_fit_is_the_numpy_loop(irf, monkeypatch, dispersion):
    """The count fit's compiled loop (decomposition.kernels.countlm) against its NumPy reference
    (``COMPILED`` off) on Poisson counts from perturbed starts: an offset fitted on half the
    pixels, a held onset, a gap in the fitted samples, pixels without an echo, and the counts'
    dispersion: the same iterations and stopping, the same fit to rounding, and the truth found."""
    from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS
    from decomposition.response import refine as rr

    n = 24
    truth, _ = _scene(n, 5)
    truth["ir_amplitude"][::3] = 0.0
    rng = np.random.default_rng(5)
    fam = np.tile(np.array([FAM_GAUSS, FAM_SSS, FAM_GAUSS], np.int8), (n, 1))
    fam[::3, 2] = FAM_NONE
    delay = np.stack([truth["direct_delay_ps"], truth["sss_delay_ps"], truth["ir_delay_ps"][:, 0]], axis=1)
    lalp = np.zeros((n, 3))
    lalp[:, 1] = np.log(truth["sss_alpha_per_ps"])
    scale = rng.uniform(400.0, 1200.0, n)
    held = np.full(n, 2.0)
    mu_true = params_profile(irf, T_PS, truth) * scale[:, None] + held[:, None] + 1.5
    counts = rng.poisson(mu_true).astype(np.float64)
    fit = np.ones((n, L), bool)
    fit[:, 150:160] = False
    disp = rng.uniform(1.0, 1.3, n) if dispersion else None
    cd = rr.CountData(counts, scale, held, fit, disp)
    y = (counts - held[:, None]) / scale[:, None]
    sw = cd.weights(mu_true - 1.5)
    d0 = delay + rng.normal(0.0, 1.0, delay.shape)
    held_delay = np.zeros((n, 3), bool)
    held_delay[1::5, 0] = True
    d0[1::5, 0] = delay[1::5, 0]
    kw = dict(n_iter=60, lm_tol=1e-8, delay_bounds_ps=(0.0, 500.0), lalp_bounds=(-8.0, 1.0), sss_after_direct=True,
              first_is_direct=True, fit_background=np.arange(n) % 2 == 0, counts=cd, held_delay=held_delay)
    fits = {}
    for compiled in (False, True):
        monkeypatch.setattr(rr, "COMPILED", compiled)
        fits[compiled] = rr.fit_slots(irf, T_PS, y, sw, fam, d0, lalp + 0.2 * (fam == FAM_SSS), **kw)
    ref, got = fits[False], fits[True]
    assert np.array_equal(got.iterations, ref.iterations)
    assert np.array_equal(got.converged, ref.converged) and ref.converged.all()
    np.testing.assert_allclose(got.delay, ref.delay, rtol=0, atol=1e-8)
    np.testing.assert_allclose(got.lalp, ref.lalp, rtol=0, atol=1e-8)
    np.testing.assert_allclose(got.amp, ref.amp, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got.background, ref.background, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.cost, ref.cost, rtol=1e-11)
    np.testing.assert_allclose(got.resid, ref.resid, rtol=0, atol=1e-8)
    # a known answer: the onsets found within a fraction of a sample, the held one kept, the
    # fitted offset's correction the 1.5 counts added and the deviance there about one per
    # fitted sample (the pixels that fit none carry the 1.5 counts as misfit)
    assert np.all(got.delay[1::5, 0] == delay[1::5, 0])
    present = fam != FAM_NONE
    assert np.abs(got.delay - delay)[present].max() < 1.0
    np.testing.assert_allclose((got.background * scale)[::2], 1.5, atol=1.0)
    assert np.all(got.background[1::2] == 0.0)
    dev = got.cost * (1.0 if disp is None else disp ** 2)
    assert np.all(dev[::2] < 1.5 * fit.sum(axis=1)[::2])
    assert dev[1::2].mean() > 1.2 * dev[::2].mean()


def test_the_count_fit_at_the_extremes(irf, monkeypatch):
    """The count fit (compiled, and its NumPy reference) on extreme pixels: 1e9 counts per unit,
    1e-3 counts per unit (next to no counts), no counts at all, no fitted sample, and NaN on the
    samples that are not fitted.  Every fit ends, within its iterations, with finite outputs;
    the compiled fit reads no sample that is not fitted (NaN there gives the answer of zeros
    there), and equals the reference's."""
    from decomposition.constants import FAM_GAUSS, FAM_SSS
    from decomposition.response import refine as rr

    n = 5
    truth, _ = _scene(n, 7)
    fam = np.tile(np.array([FAM_GAUSS, FAM_SSS, FAM_GAUSS], np.int8), (n, 1))
    delay = np.stack([truth["direct_delay_ps"], truth["sss_delay_ps"], truth["ir_delay_ps"][:, 0]], axis=1)
    lalp = np.zeros((n, 3))
    lalp[:, 1] = np.log(truth["sss_alpha_per_ps"])
    scale = np.array([1e9, 1e-3, 50.0, 50.0, 50.0])
    held = np.array([0.0, 0.0, 0.0, 5.0, 0.0])
    counts = np.random.default_rng(7).poisson(params_profile(irf, T_PS, truth) * scale[:, None]
                                              + held[:, None]).astype(np.float64)
    counts[2] = 0.0
    fit = np.ones((n, L), bool)
    fit[3] = False
    fit[4, 20:40] = False
    kw = dict(n_iter=40, lm_tol=1e-8, delay_bounds_ps=(0.0, 500.0), lalp_bounds=(-8.0, 1.0), first_is_direct=True,
              fit_background=True)

    def fitted(compiled, c):
        monkeypatch.setattr(rr, "COMPILED", compiled)
        y = (c - held[:, None]) / scale[:, None]
        return rr.fit_slots(irf, T_PS, y, fit.astype(np.float64), fam, delay + 1.0, lalp,
                            counts=rr.CountData(c, scale, held, fit, None), **kw)

    got, ref = fitted(True, counts), fitted(False, counts)
    with_nan = counts.copy()
    with_nan[~fit] = np.nan
    unread = fitted(True, with_nan)
    for f in (got, ref, unread):
        assert np.all(f.iterations <= 40)
        for name in ("amp", "background", "cost", "resid"):
            assert np.all(np.isfinite(getattr(f, name))), name
    for name in ("delay", "lalp", "amp", "background", "cost", "resid", "iterations"):
        assert np.array_equal(getattr(unread, name), getattr(got, name), equal_nan=True), name
    np.testing.assert_allclose(got.cost, ref.cost, rtol=1e-7)       # 1e9 counts: rounding at 2e-8
    np.testing.assert_allclose(got.delay, ref.delay, rtol=0, atol=1e-6)
    assert np.all(got.amp[2] == 0.0) and got.cost[2] < 1.0         # no counts: no light
    assert got.cost[3] == 0.0 and got.iterations[3] >= 1             # nothing fitted: nothing to lower
    np.testing.assert_allclose(got.delay[0], delay[0], atol=1e-3)     # 1e9 counts: the truth


def test_the_refit_weighs_its_samples_by_the_signal_noise_weights(irf):
    """The response path's refit (response.refine.refit_slots) with the signal-noise stage's
    sample weights: a blob of light where those weights are 0 does not move the fit -- it is the
    fit of the profiles without the blob, to rounding, at the truth -- while the unweighted refit
    is pulled off by it."""
    from decomposition.response.label import param_slots
    from decomposition.response.refine import refit_slots
    n = 6
    truth, start = _scene(n, 5)
    start = _padded(start)
    clean = params_profile(irf, T_PS, truth)
    blob = clean.copy()
    blob[:, 70:86] += 0.3 * clean.max(axis=1, keepdims=True)
    w = np.ones_like(clean)
    w[:, 70:86] = 0.0

    def fitted(y, weights):
        rf, samples, opts, _ = _response_state(irf, y, start)
        fam, delay, lalp = param_slots(start, rf.refine_kw["R"])
        kw = dict(rf.refine_kw, weights=weights)
        return refit_slots(samples.profiles[samples.live], fam, delay, lalp, rf.b_est, rf.with_bg, start, **kw)

    on_blob, on_clean, unweighted = fitted(blob, w), fitted(clean, w), fitted(blob, None)
    np.testing.assert_allclose(on_blob.delay, on_clean.delay, atol=1e-6)
    np.testing.assert_allclose(on_blob.params["sss_alpha_per_ps"], on_clean.params["sss_alpha_per_ps"], rtol=1e-6)
    np.testing.assert_allclose(on_blob.delay[:, 0], truth["direct_delay_ps"], atol=1e-3)
    assert np.all(np.abs(unweighted.delay - on_clean.delay).max(axis=1) > 0.2)     # 0.38-14.6 ps
