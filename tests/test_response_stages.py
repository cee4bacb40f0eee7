"""The stages over ConvSCD's slot state with a measured response: the slot renderers and the
amplitude solve read the instrument from the dictionary (model/slots.py, methods/polish.py),
the search stage runs over the response's atoms where it is asked for (``search=True``), the grow
stage by default on float data and the prune stage by default."""
import numpy as np
from scipy.optimize import nnls

from core.irf import render_shifted, render_sss
from core.irf_models import tailed_response
from decomposition import decompose
from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from decomposition.evaluation.synthetic import make_profiles
from decomposition.masks import SampleMask
from decomposition.methods.dictionary import Dictionary
from decomposition.methods.polish import refit_amplitudes
from decomposition.model.fidelity import fidelity
from decomposition.kernels.atomlm import nnls_amplitudes
from decomposition.kernels.projected import response_instrument
from decomposition.model.slots import eval_atoms, render
from decomposition.options import GridSpec, SolverOptions

T, L, T0 = 2.0, 160, 2.0
AXIS = T0 + T * np.arange(L)
IRF = tailed_response(4.0, 0.25, 20.0, time_step_ps=T)


def _state(fam, delay, alpha, amp):
    fam = np.array(fam, np.int8)
    return {"fam": fam, "delay": np.array(delay, float), "lsig": np.zeros(fam.shape),
            "lalp": np.log(np.array(alpha, float)), "amp": np.array(amp, float), "pen": np.ones(fam.shape)}


def test_the_slot_renderers_draw_the_response_atoms():
    """A shifted slot is the response with its peak at the delay (unit peak); an sss slot is the
    response convolved with the exponential, scaled to unit peak; empty slots draw nothing."""
    st = _state([[FAM_GAUSS, FAM_SSS, FAM_NONE]], [[50.3, 50.3, 90.0]], [[1.0, 0.03, 1.0]], [[2.0, 0.5, 7.0]])
    shifted = render_shifted(IRF, AXIS, np.array([50.3]))[0]
    sss = render_sss(IRF, AXIS, np.array([50.3]), np.array([0.03]))[0]
    atoms = eval_atoms(AXIS, st["fam"][0], st["delay"][0], st["lsig"][0], st["lalp"][0], IRF)
    np.testing.assert_allclose(atoms[0], shifted, atol=1e-6)
    np.testing.assert_allclose(atoms[1] / atoms[1].max(), sss / sss.max(), atol=1e-6)
    assert not atoms[2].any()
    np.testing.assert_allclose(render(AXIS, st, IRF)[0], 2.0 * atoms[0] + 0.5 * atoms[1], atol=1e-12)
    # without the response the Gaussian PSF's atoms, which differ
    assert np.abs(render(AXIS, st)[0] - render(AXIS, st, IRF)[0]).max() > 0.1


def test_the_amplitudes_of_a_responses_atoms_solve_the_nonnegative_least_squares():
    """The Gaussian path's compiled NNLS (``nnls_amplitudes``) over a response's table atoms,
    against scipy's NNLS on the same atoms over the fitted samples: an atom the data want
    negative ends at 0, and ``refit_amplitudes`` over a response's dictionary drops it."""
    rng = np.random.default_rng(4)
    st = _state([[FAM_GAUSS, FAM_GAUSS, FAM_SSS]] * 3, [[40.0, 95.0, 40.0]] * 3, [[1.0, 1.0, 0.02]] * 3,
                [[1.0, 1.0, 1.0]] * 3)
    atoms = [eval_atoms(AXIS, st["fam"][0], st["delay"][0], st["lsig"][0], st["lalp"][0], IRF)] * 3
    true = np.array([[1.0, 0.3, 0.4], [0.8, -0.2, 0.5], [0.0, 0.6, 0.9]])
    p = np.einsum("pk,pkl->pl", true, np.array(atoms)) + 0.01 * rng.standard_normal((3, L))
    fit = np.ones((3, L), bool)
    fit[0, 70:90] = False                       # a gap in the fitted samples
    got = nnls_amplitudes(T0, T, p, fit, st["fam"], st["amp"], st["delay"], st["lsig"], st["lalp"], sweeps=200,
                          inst=response_instrument(IRF, AXIS))
    for i in range(3):
        ref, _ = nnls((atoms[i] * fit[i]).T, p[i] * fit[i])
        np.testing.assert_allclose(got[i], ref, atol=1e-6)
    assert got[1, 1] == 0.0
    dic = Dictionary(L, T, T0, GridSpec(), True, True, response=IRF)
    st2 = {k: v.copy() for k, v in st.items()}
    refit_amplitudes(p, SampleMask(fit, np.zeros_like(fit)), st2, dic)
    assert st2["fam"][1, 1] == FAM_NONE and np.all(st2["amp"][st2["fam"] != FAM_NONE] > 0)


def test_the_search_is_off_by_default_with_a_response_and_on_for_the_gaussian_psf():
    assert SolverOptions().resolved("drs").search is True
    assert SolverOptions().resolved("drs", response=True).search is False
    assert SolverOptions(search=True).resolved("drs", response=True).search is True
    assert SolverOptions(search=False).resolved("drs").search is False


def test_the_search_over_the_response_mends_wrong_splits():
    """Paper scenes through a tailed response, white noise: with ``search=True`` the structured
    starts run over the response's atoms for the pixels in doubt; the mean fidelity rises
    (measured 0.879 -> 0.918, the prune stage off in both to see the search alone) and no pixel
    loses more than 0.05 of it.  By default the search does not run with a response."""
    irf = tailed_response(4.0, 0.2, 30.0, time_step_ps=2.0)
    d = make_profiles(120, 256, nsr=0.05, seed=1, ranges="paper", response=irf, bin_integrated=True)
    plain = decompose(d.noisy, 2.0, irf=irf, prune=False)
    searched = decompose(d.noisy, 2.0, irf=irf, search=True, prune=False)
    assert plain.info["search"] is False and "search_wins" not in plain.info
    assert searched.info["search"] is True and searched.info["search_doubt"] > 0
    assert sum(searched.info["search_wins"].values()) == searched.info["search_doubt"]
    f0, f1 = fidelity(d.components, plain), fidelity(d.components, searched)
    assert np.nanmean(f1) >= np.nanmean(f0) + 0.01
    assert np.all(f1 >= f0 - 0.05)


def test_the_prune_stage_runs_over_the_response_by_default():
    """Paper scenes through a tailed response, white noise, 120 of each of seeds 2-5: the prune
    stage (the Gaussian path's backward step) runs over the response's atoms by default, after
    the grow stage (the forward step, over the same atoms); the mean fidelity over the 480 rises
    over ``prune=False`` (measured +0.0051, +0.0084, +0.0154, +0.0099; seed 2 alone gained
    0.014 before the grow stage ran over a response, which now does part of the prune's work),
    and at least twice as many pixels gain more than 0.05 of it as lose that much (15 and 5)."""
    irf = tailed_response(4.0, 0.2, 30.0, time_step_ps=2.0)
    f0, f1 = [], []
    for seed in (2, 3, 4, 5):
        d = make_profiles(120, 256, nsr=0.05, seed=seed, ranges="paper", response=irf, bin_integrated=True)
        plain = decompose(d.noisy, 2.0, irf=irf, prune=False)
        pruned = decompose(d.noisy, 2.0, irf=irf)
        assert "pruned" not in plain.info and pruned.info["pruned"] > 0
        f0.append(fidelity(d.components, plain))
        f1.append(fidelity(d.components, pruned))
    f0, f1 = np.concatenate(f0), np.concatenate(f1)
    assert np.nanmean(f1) >= np.nanmean(f0) + 0.005
    assert np.sum(f1 > f0 + 0.05) >= 2 * np.sum(f1 < f0 - 0.05)


def test_the_grow_stage_runs_over_the_response_on_float_data_and_not_on_counts():
    """Paper scenes through a tailed response, 200 in white noise at each of (seed 2, NSR 0.05),
    (0, 0.03), (1, 0.08): the grow stage (the Gaussian path's forward step: a Gaussian at a
    resolved residual bump, and at the peak of a late sss) runs over the response's atoms, and
    the response path's own echo steps do not; the mean fidelity over the 600 rises over
    ``grow=False`` (measured +0.0031, +0.0050, +0.0059: 23-35 late sss peaks swapped per
    setting; 13 pixels gain more than 0.05 of it, one loses that much).  The same scenes as
    photon counts take the response's own echo steps, weighed by their deviance, and not the
    grow stage."""
    irf = tailed_response(4.0, 0.2, 30.0, time_step_ps=2.0)
    f0, f1 = [], []
    for seed, nsr in ((2, 0.05), (0, 0.03), (1, 0.08)):
        d = make_profiles(200, 256, nsr=nsr, seed=seed, ranges="paper", response=irf, bin_integrated=True)
        grown = decompose(d.noisy, 2.0, irf=irf)
        plain = decompose(d.noisy, 2.0, irf=irf, grow=False)
        assert "swapped" not in plain.info and grown.info["swapped"] > 0
        assert grown.info["response_echo_added"] == 0 and grown.info["response_sss_swapped"] == 0
        f0.append(fidelity(d.components, plain))
        f1.append(fidelity(d.components, grown))
    f0, f1 = np.concatenate(f0), np.concatenate(f1)
    assert np.nanmean(f1) >= np.nanmean(f0) + 0.002
    assert np.sum(f1 > f0 + 0.05) >= 2 * max(np.sum(f1 < f0 - 0.05), 1)
    counts = make_profiles(40, 256, seed=2, ranges="paper", response=irf, photons_per_pixel=1000.0)
    r = decompose(counts.noisy, 2.0, irf=irf)
    assert r.info["noise_model"] == "poisson"
    assert "swapped" not in r.info and "grown" not in r.info and "response_echo_added" in r.info


def _with_and_without(irf, noise, option, n, check):
    """Mean-fidelity inputs of a stage's test: ``n`` paper scenes of 512 bins through ``irf`` in
    ``noise`` at NSR 0.11, seeds 2 and 3, decomposed by default and with ``option`` False;
    ``check(default, without)`` asserts on each pair -> (fidelities without, with) over both."""
    f0, f1 = [], []
    for seed in (2, 3):
        d = make_profiles(n, 512, nsr=0.11, noise=noise, seed=seed, ranges="paper", response=irf, bin_integrated=True)
        on = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, irf=irf)
        off = decompose(d.noisy, 2.0, t0_ps=d.t0_ps, irf=irf, **{option: False})
        check(on, off)
        f0.append(fidelity(d.components, off))
        f1.append(fidelity(d.components, on))
    return np.concatenate(f0), np.concatenate(f1)


def test_pink_noise_through_a_response_is_whitened_as_on_the_gaussian_path():
    """The correlated-noise stage runs over a response's atoms on float data: in pink noise
    (NSR 0.11, 300 paper scenes of 512 bins through the simulated camera's tailed response,
    seeds 2 and 3) it finds the noise correlated and the grow and prune stages whiten their
    objectives by its spectrum; the mean fidelity over the 600 rises over ``whiten=False``
    (measured 0.8583 -> 0.8640 and 0.8519 -> 0.8618).  In white noise it finds none, and the
    answer is that of ``whiten=False`` to the bit; count data do not take it."""
    from drivers.sim.scene import simulated_response
    irf = simulated_response("tailed")

    def found(whitened, plain):
        assert whitened.info["correlated_noise"] is True and "correlated_noise" not in plain.info

    f0, f1 = _with_and_without(irf, "pink", "whiten", 300, found)
    assert np.nanmean(f1) >= np.nanmean(f0) + 0.003
    w = make_profiles(60, 512, nsr=0.11, noise="white", seed=2, ranges="paper", response=irf, bin_integrated=True)
    white = decompose(w.noisy, 2.0, t0_ps=w.t0_ps, irf=irf)
    assert white.info["correlated_noise"] is False
    np.testing.assert_array_equal(white.residual, decompose(w.noisy, 2.0, t0_ps=w.t0_ps, irf=irf, whiten=False).residual)
    counts = make_profiles(20, 512, seed=2, ranges="paper", response=irf, photons_per_pixel=1000.0)
    assert "correlated_noise" not in decompose(counts.noisy, 2.0, t0_ps=counts.t0_ps, irf=irf).info


def test_photon_noise_through_a_response_is_weighted_by_its_variance_law_as_on_the_gaussian_path():
    """The signal-noise stage runs over a response's atoms on float data: under photon noise
    (NSR 0.11, 200 paper scenes of 512 bins through the simulated camera's tailed response, seeds
    2 and 3) it finds the noise following the signal in every pixel, and the grow, prune and
    search stages, the labels' threshold and the refit weigh the samples by the detector's
    variance law.  The mean fidelity over the 400 rises over ``signal_noise=False`` by at least
    0.1 (measured 0.6536 -> 0.8366 and 0.6327 -> 0.8515), and at least five times as many pixels
    gain more than 0.05 of it as lose that much (256 and 29).  White noise follows no signal: no pixel is
    weighted, and the answer is that of ``signal_noise=False`` to the bit."""
    from drivers.sim.scene import simulated_response
    irf = simulated_response("tailed")

    def found(weighted, plain):
        assert weighted.info["signal_weighted"] == 200 and "signal_weighted" not in plain.info
        assert weighted.info["signal_noise_law_fit"]["gain"] > 0

    f0, f1 = _with_and_without(irf, "photon", "signal_noise", 200, found)
    assert np.nanmean(f1) >= np.nanmean(f0) + 0.1
    assert np.sum(f1 > f0 + 0.05) >= 5 * np.sum(f1 < f0 - 0.05)
    w = make_profiles(100, 512, nsr=0.055, noise="white", seed=2, ranges="paper", response=irf, bin_integrated=True)
    white = decompose(w.noisy, 2.0, t0_ps=w.t0_ps, irf=irf)
    plain = decompose(w.noisy, 2.0, t0_ps=w.t0_ps, irf=irf, signal_noise=False)
    assert white.info["signal_weighted"] == 0
    np.testing.assert_array_equal(white.residual, plain.residual)
    np.testing.assert_array_equal(white.flags, plain.flags)


def test_the_backward_step_over_the_response_drops_an_atom_on_the_sss_onset_and_keeps_an_echo():
    """The prune stage's step (:func:`decomposition.stages.prune.prune_block`) over a response's
    atoms: pixels of a direct and an sss whose onset lies 6 ps after it, in white noise, given a
    second shifted atom on that onset, lose it (it does not pay for its parameters), and the
    onset comes back to within 0.5 ps; the same pixels with a true echo 14 ps after the direct
    (30 % of it) keep theirs."""
    from core.irf_components import gaussian_equivalent_sigma_ps
    from decomposition.stages.prune import prune_block

    rng = np.random.default_rng(6)
    n = 8
    d = rng.uniform(60.0, 120.0, n)
    shifted = lambda x: render_shifted(IRF, AXIS, x)              # noqa: E731
    clean = shifted(d) + 0.5 * render_sss(IRF, AXIS, d + 6.0, np.full(n, 0.03))
    y = np.vstack([clean, clean + 0.3 * shifted(d + 14.0)]) + 0.01 * rng.standard_normal((2 * n, L))
    third = np.concatenate([d + 6.3, d + 14.0])
    st = _state(np.tile([FAM_GAUSS, FAM_SSS, FAM_GAUSS, FAM_NONE], (2 * n, 1)),
                np.column_stack([np.tile(d, 2), np.tile(d + 6.0, 2), third, np.zeros(2 * n)]),
                np.tile([1.0, 0.03, 1.0, 1.0], (2 * n, 1)),
                np.column_stack([np.ones(2 * n), np.full(2 * n, 0.5), np.r_[np.full(n, 0.05), np.full(n, 0.3)],
                                 np.zeros(2 * n)]))
    st["lsig"][:] = np.log(gaussian_equivalent_sigma_ps(IRF))
    dic = Dictionary(L, T, T0, GridSpec(), True, True, response=IRF)
    mask = SampleMask(np.ones(y.shape, bool), np.zeros(y.shape, bool))
    opts = SolverOptions().resolved("drs", response=True)
    out, pruned = prune_block(y, mask, st, np.full(2 * n, 0.01), dic, opts)
    assert pruned[:n].all()
    assert ((out["fam"][:n] == FAM_GAUSS).sum(axis=1) == 1).all()
    onset = np.where(out["fam"][:n] == FAM_SSS, out["delay"][:n], 0.0).sum(axis=1)
    np.testing.assert_allclose(onset, d + 6.0, atol=0.5)
    echo = np.where((out["fam"][n:] == FAM_GAUSS) & (out["delay"][n:] > d[:, None] + 7.0), out["delay"][n:], np.nan)
    np.testing.assert_allclose(np.nanmax(echo, axis=1), d + 14.0, atol=0.5)


def test_the_sss_swap_rule_reads_a_response_and_passes_over_pixels_without_an_sss():
    """:func:`decomposition.stages.grow.late_fast_sss` over a response's atoms: a fast sss whose
    hump peaks far after the direct passes, with its mode where the response's sss atom peaks; a
    slow one does not; a pixel without an sss (its decay rates NaN, as the response's detection
    leaves them) does not pass and raises nothing."""
    from decomposition.stages.grow import late_fast_sss

    st = _state([[FAM_GAUSS, FAM_SSS], [FAM_GAUSS, FAM_SSS], [FAM_GAUSS, FAM_GAUSS]],
                [[40.0, 80.0], [40.0, 80.0], [40.0, 60.0]], [[1.0, 0.5], [1.0, 0.002], [np.nan, np.nan]],
                np.ones((3, 2)))
    d0, sigma = np.full(3, 40.0), np.full(3, 4.0)
    ss, mode, passes = late_fast_sss(AXIS, st, d0, sigma, IRF)
    hump = render_sss(IRF, AXIS, np.array([80.0]), np.array([0.5]))[0]
    assert passes.tolist() == [True, False, False] and ss[:2].tolist() == [1, 1]
    assert mode[0] == AXIS[np.argmax(hump)] and np.isnan(mode[2])
