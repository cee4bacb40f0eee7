"""Compiled Levenberg-Marquardt refinement of a pixel's atoms (decomposition.kernels.atomlm)."""
import numpy as np
import pytest

from decomposition.kernels import atomlm
from decomposition.methods import convscd as cs
from decomposition.constants import GAUSS_SUPPORT_SIGMA
from decomposition.masks import SampleMask
from decomposition.kernels.onsets import onset_links
from decomposition.model.slots import new_state, parameter_bounds, render
from core.model import gaussian_kernel, sss_kernel, time_axis_ps

T = 2.0
L = 256
T0 = T



#: the atoms' documented approximations (decomposition/constants.py): nothing beyond
#: GAUSS_SUPPORT_SIGMA widths, where a unit Gaussian is below exp(-18) of its peak, and erfc
#: taken as 2 in the sss tail past TAIL_SIGMA (erfc(4) / 2 ~ 8e-9 relative)
_CUT = 1.01 * np.exp(-0.5 * GAUSS_SUPPORT_SIGMA ** 2)
_REL = 1e-8

def _state(rows):
    """Slot state from rows of (fam, amp, delay_ps, sigma_ps, alpha_per_ps or None)."""
    K = max(len(r) for r in rows) + 1            # one spare inactive slot
    st = new_state(len(rows), K)
    for i, atoms in enumerate(rows):
        for k, (fam, amp, d, s, a) in enumerate(atoms):
            st["fam"][i, k] = fam
            st["amp"][i, k] = amp
            st["delay"][i, k] = d
            st["lsig"][i, k] = np.log(s)
            st["lalp"][i, k] = np.log(a) if a else 0.0
    return st


def _profile(atoms):
    t = time_axis_ps(L, T)
    out = np.zeros(L)
    for fam, amp, d, s, a in atoms:
        out += amp * (gaussian_kernel(t - d, s) if fam == cs.FAM_GAUSS else sss_kernel(t - d, s, a))
    return out


def _bounds():
    return parameter_bounds(cs.get_dictionary(L, T, T0, cs.GridSpec(), True, True), 4.0)


@pytest.mark.parametrize("fam, amp, delay, sigma, alpha", [
    (cs.FAM_GAUSS, 0.8, 101.3, 4.2, None),
    (cs.FAM_GAUSS, 1.0, -6.0, 3.0, None),          # mostly before the window
    (cs.FAM_SSS, 0.05, 150.7, 3.5, 0.03),
    (cs.FAM_SSS, 0.02, 480.0, 2.0, 0.011),         # onset near the window's end
    (cs.FAM_SSS, 0.3, 20.0, 6.0, 0.9),             # decays faster than the PSF is wide
])
def test_atom_values_and_derivative_columns(fam, amp, delay, sigma, alpha):
    """The atom equals core.model's kernel (within the documented cut and tail, _CUT and
    _REL), and each derivative column equals a central difference of amp * kernel in
    (amp, delay, log sigma, log alpha)."""
    t = time_axis_ps(L, T)
    lalp = np.log(alpha) if alpha else 0.0

    def render(a, d, ls, la):
        J = np.zeros((4, L))
        lo, hi = atomlm._eval_slot(T0, T, L, fam, a, d, ls, la, J, 0, L, np.empty(0))
        out = np.zeros(L)
        out[lo:hi] = a * J[0, lo:hi]
        return out, J, lo, hi

    model, J, lo, hi = render(amp, delay, np.log(sigma), lalp)
    ref = amp * (gaussian_kernel(t - delay, sigma) if fam == cs.FAM_GAUSS else sss_kernel(t - delay, sigma, alpha))
    np.testing.assert_allclose(model, ref, rtol=_REL, atol=_CUT * ref.max())
    x = np.array([amp, delay, np.log(sigma), lalp])
    n_par = 4 if fam == cs.FAM_SSS else 3
    for q in range(n_par):
        h = 1e-6 * max(1.0, abs(x[q]))
        up, dn = x.copy(), x.copy()
        up[q] += h
        dn[q] -= h
        ru, rd = render(*up)[0], render(*dn)[0]
        fd = (ru - rd) / (2 * h)
        col = np.zeros(L)
        col[lo:hi] = J[q, lo:hi]
        same = (ru != 0) == (rd != 0)            # not where the step moves the support's cut
        assert same.sum() >= L - 2
        np.testing.assert_allclose(col[same], fd[same], rtol=0, atol=2e-6 * max(np.abs(fd).max(), 1e-3))


def test_noiseless_profile_is_recovered_from_a_perturbed_start():
    truth = [(cs.FAM_GAUSS, 0.7, 120.4, 3.0, None), (cs.FAM_SSS, 0.03, 123.9, 3.0, 0.025),
             (cs.FAM_GAUSS, 0.25, 260.2, 3.0, None)]
    # (a start with the sss onset closer to the direct than the truth can collapse onto the
    # direct, where the two are degenerate to first order: polish_block's restart handles that)
    start = [(cs.FAM_GAUSS, 0.6, 120.0, 3.4, None), (cs.FAM_SSS, 0.025, 125.0, 3.4, 0.03),
             (cs.FAM_GAUSS, 0.2, 259.0, 3.4, None)]
    p = _profile(truth)[None]
    mask = SampleMask.all_fitted(p.shape)
    st = _state([start])
    zero = np.zeros(1)
    out, obj, iters, model = atomlm.lm_refine(T0, T, p, mask, st, zero, np.ones(1), _bounds(), 200,
                                              tie_sigma=True, sss_after_direct=True, tol=0.0)
    got = sorted(zip(out["delay"][0, :3], out["amp"][0, :3], np.exp(out["lsig"][0, :3])))
    want = sorted((d, a, s) for _, a, d, s, _ in truth)
    np.testing.assert_allclose(np.array(got), np.array(want), rtol=1e-6, atol=1e-6)
    sss = out["fam"][0] == cs.FAM_SSS
    np.testing.assert_allclose(np.exp(out["lalp"][0][sss]), [0.025], rtol=1e-6)
    assert obj[0] < 1e-16 and 0 < iters[0] <= 200
    np.testing.assert_allclose(model[0], p[0], atol=1e-9)
    assert np.all(st["amp"][0, :3] == [0.6, 0.025, 0.2])      # the input state is not modified


def _random_block(n, seed):
    rng = np.random.default_rng(seed)
    rows, truths = [], []
    for _ in range(n):
        s = rng.uniform(1.5, 6.0)
        d = rng.uniform(40, 300)
        truth = [(cs.FAM_GAUSS, 1.0, d, s, None), (cs.FAM_SSS, rng.uniform(0.005, 0.05), d + rng.uniform(0, 2 * s), s,
                                                   rng.uniform(0.01, 0.05))]
        if rng.random() < 0.5:
            truth.append((cs.FAM_GAUSS, rng.uniform(0.1, 0.5), d + rng.uniform(30, 150), s, None))
        truths.append(truth)
        fs = rng.uniform(0.85, 1.15)               # one width per pixel, as the solver keeps it
        rows.append([(f, a * rng.uniform(0.6, 1.4), dd + rng.normal(0, 1.5), ss * fs,
                      aa * rng.uniform(0.7, 1.4) if aa else None) for f, a, dd, ss, aa in truth])
    p = np.stack([_profile(t) for t in truths])
    p += rng.normal(0, 0.02, p.shape)
    return p, _state(rows)


def test_objective_never_increases_and_reported_values_are_exact():
    """On noisy blocks with excluded and censored samples: F at the returned state is
    at most F at the start for every pixel, and the returned F and model are those of the
    returned state as the numpy objective evaluates them."""
    p, st = _random_block(60, seed=3)
    fit = np.ones(p.shape, bool)
    fit[:20, 60:70] = False
    cens = np.zeros(p.shape, bool)
    cens[20:40] = p[20:40] > 0.6
    mask = SampleMask(fit & ~cens, cens)
    s = np.full(p.shape[0], 0.02)
    mu, eps = 3 * s * s, 0.01 * s
    t = time_axis_ps(L, T)
    m0 = render(t, st)
    f0 = cs.objective(p, mask, m0, st, mu, eps)
    for tie, after in [(True, True), (False, False), (True, False)]:
        out, obj, iters, model = atomlm.lm_refine(T0, T, p, mask, st, mu, eps, _bounds(), 12, tie_sigma=tie,
                                                  sss_after_direct=after, tol=1e-6)
        assert np.all(obj <= f0) and np.mean(obj < 0.5 * f0) > 0.8
        m1 = render(t, out)
        np.testing.assert_allclose(model, m1, atol=1e-12)
        np.testing.assert_allclose(obj, cs.objective(p, mask, m1, out, mu, eps), rtol=1e-12)
        assert np.all(iters <= 12)
        act = out["fam"] != cs.FAM_NONE
        if tie:   # pixels that started with one width keep one width
            ls = np.where(act, out["lsig"], np.nan)
            assert np.all(np.nanmax(ls, axis=1) - np.nanmin(ls, axis=1) <= 1e-12)
        if after:  # an sss onset never moves before a Gaussian it is tied to
            g = np.where(out["fam"] == cs.FAM_GAUSS, out["delay"], np.inf).min(axis=1)
            sd = np.where(out["fam"] == cs.FAM_SSS, out["delay"], np.nan)
            near = np.nanmax(sd, axis=1) > g - 3 * np.exp(out["lsig"][:, 0])
            assert np.all(np.nanmax(sd, axis=1)[near] >= g[near] - 1e-9)


def test_excluded_samples_do_not_influence_the_fit():
    p, st = _random_block(20, seed=5)
    fit = np.ones(p.shape, bool)
    fit[:, 100:120] = False
    mask = SampleMask.of_fit(fit)
    s = np.full(p.shape[0], 0.02)
    args = (st, 3 * s * s, 0.01 * s, _bounds(), 10)
    a = atomlm.lm_refine(T0, T, p, mask, *args, tie_sigma=True, sss_after_direct=True, tol=1e-6)
    q = p.copy()
    q[:, 100:120] = 1e6
    b = atomlm.lm_refine(T0, T, q, mask, *args, tie_sigma=True, sss_after_direct=True, tol=1e-6)
    for k in ("amp", "delay", "lsig", "lalp"):
        np.testing.assert_array_equal(a[0][k], b[0][k])
    np.testing.assert_array_equal(a[1], b[1])


def test_slots_are_compacted_and_empty_pixels_pass_through():
    st = _state([[(cs.FAM_GAUSS, 0.5, 100.0, 3.0, None)], []])
    st["fam"][0] = [cs.FAM_NONE, cs.FAM_GAUSS]      # active slot second
    st["amp"][0] = [0.0, 0.5]
    st["delay"][0] = [0.0, 100.0]
    st["lsig"][0] = [0.0, np.log(3.0)]
    p = np.stack([_profile([(cs.FAM_GAUSS, 0.5, 101.0, 3.0, None)]), np.zeros(L)])
    out, obj, iters, model = atomlm.lm_refine(T0, T, p, SampleMask.all_fitted(p.shape), st, np.zeros(2), np.ones(2), _bounds(), 50)
    assert list(out["fam"][0]) == [cs.FAM_GAUSS, cs.FAM_NONE]
    assert abs(out["delay"][0, 0] - 101.0) < 1e-6
    assert iters[1] == 0 and obj[1] == 0.0 and not model[1].any()


def test_atom_profiles_are_the_model_kernels_and_empty_slots_are_zero():
    t = time_axis_ps(L, T)
    fam = np.array([cs.FAM_GAUSS, cs.FAM_SSS, cs.FAM_NONE, cs.FAM_SSS], np.int8)
    delay = np.array([80.0, 150.5, 10.0, -30.0])
    sig = np.array([2.5, 4.0, 3.0, 6.0])
    alp = np.array([1.0, 0.02, 1.0, 0.05])
    got = atomlm.atom_profiles(T0, T, L, fam, delay, np.log(sig), np.log(alp))
    np.testing.assert_allclose(got[0], gaussian_kernel(t - delay[0], sig[0]), rtol=_REL, atol=_CUT)
    np.testing.assert_allclose(got[1], sss_kernel(t - delay[1], sig[1], alp[1]), rtol=_REL, atol=_CUT)
    assert not got[2].any()
    np.testing.assert_allclose(got[3], sss_kernel(t - delay[3], sig[3], alp[3]), rtol=_REL, atol=_CUT)


@pytest.mark.parametrize("time_bin_ps", [0.5, 2.0, 10.0])
def test_atom_values_hold_their_relative_accuracy_at_extreme_widths_and_decays(time_bin_ps):
    """Widths from a twentieth of a bin (every bin evaluated afresh) to 80 bins (Gaussian factors
    stepped from bin to bin), decays from 1e-4 to 5 /ps (alpha sigma from 1e-5 to 200): every
    sample the kernels evaluate within 1e-12 of core.model's value relative to that value (the
    sss tail, where erfc is taken as 2, within _REL), none NaN or inf."""
    n = 384
    t = time_axis_ps(n, time_bin_ps)
    worst = worst_gauss = 0.0
    for sig in (0.025 * time_bin_ps, 0.3, 1.0, 3.7, 12.0, 40.0):
        for alp in (1e-4, 0.01, 0.05, 0.9, 5.0):
            d = t[0] + 0.3 * n * time_bin_ps + 0.37 * time_bin_ps
            fam = np.array([cs.FAM_GAUSS, cs.FAM_SSS], np.int8)
            got = atomlm.atom_profiles(t[0], time_bin_ps, n, fam, np.array([d, d]), np.log([sig, sig]),
                                       np.log([1.0, alp]))
            assert np.isfinite(got).all()
            for row, ref in ((got[0], gaussian_kernel(t - d, sig)), (got[1], sss_kernel(t - d, sig, alp))):
                on = (row != 0) & (ref > 1e-280)
                assert np.all(row[ref > 1e-3 * ref.max()] != 0)            # the support covers the atom
                err = np.abs(row[on] - ref[on]) / ref[on]
                worst = max(worst, float(np.max(err, initial=0.0)))
                if row is got[0]:
                    worst_gauss = max(worst_gauss, float(np.max(err, initial=0.0)))
    assert worst < _REL
    assert worst_gauss < 1e-12


def test_onset_tie_rule_has_one_home_and_reads_as_stated():
    rng = np.random.default_rng(3)
    P, K = 400, 4
    fam = rng.choice([cs.FAM_NONE, cs.FAM_GAUSS, cs.FAM_SSS], size=(P, K), p=[0.3, 0.5, 0.2]).astype(np.int8)
    delay = rng.uniform(0.0, 60.0, (P, K))
    delay[::7, 1] = delay[::7, 0]                          # equal delays: the first slot is the direct
    lsig = np.log(rng.uniform(1.0, 6.0, (P, K)))
    linked, dsl, ssl = onset_links(fam, delay, lsig)
    for i in range(P):
        g = [k for k in range(K) if fam[i, k] == cs.FAM_GAUSS]
        s = [k for k in range(K) if fam[i, k] == cs.FAM_SSS]
        d = min(g, key=lambda k: (delay[i, k], k)) if g else 0
        sk = s[0] if s else 0
        want = bool(g and s and delay[i, d] - delay[i, sk] < 3.0 * np.exp(lsig[i, sk]))
        assert (linked[i], dsl[i], ssl[i]) == (want, d, sk), i
    assert linked.any() and not linked.all()
    far, _, _ = onset_links(fam, delay, lsig, near_sigma=np.inf)   # the polish's retry: any onset
    assert np.array_equal(far, (fam == cs.FAM_GAUSS).any(1) & (fam == cs.FAM_SSS).any(1))


def test_weights_of_one_are_the_unweighted_fit_exactly():
    """weights=ones is the default objective bit for bit."""
    rng = np.random.default_rng(4)
    atoms = [(cs.FAM_GAUSS, 0.9, 100.0, 3.0, None), (cs.FAM_SSS, 0.05, 104.0, 3.0, 0.02)]
    p = (_profile(atoms) + 0.01 * rng.standard_normal(L))[None]
    st = _state([[(cs.FAM_GAUSS, 0.7, 97.0, 4.0, None), (cs.FAM_SSS, 0.04, 103.0, 4.0, 0.03)]])
    mask = SampleMask.all_fitted(p.shape)
    args = (T0, T, p, mask, st, np.zeros(1), np.full(1, 1e-3), _bounds(), 30)
    a = atomlm.lm_refine(*args)
    b = atomlm.lm_refine(*args, weights=np.ones(p.shape))
    for k in a[0]:
        np.testing.assert_array_equal(a[0][k], b[0][k])
    np.testing.assert_array_equal(a[1], b[1])


def test_zero_weights_ignore_corrupted_samples():
    """Samples corrupted by a large bump, weighted 0, leave the fit at the clean truth; with
    weight 1 they pull it away (known answer: the generating parameters)."""
    truth = [(cs.FAM_GAUSS, 0.8, 200.0, 4.0, None)]
    p = _profile(truth)
    t = time_axis_ps(L, T)
    bad = np.abs(t - 215.0) < 8.0
    p = np.where(bad, p + 0.3, p)[None]
    w = np.where(bad, 0.0, 1.0)[None]
    st = _state([[(cs.FAM_GAUSS, 0.6, 204.0, 5.0, None)]])
    mask = SampleMask.all_fitted(p.shape)
    args = (T0, T, p, mask, st, np.zeros(1), np.full(1, 1e-3), _bounds(), 60)
    got, _, _, _ = atomlm.lm_refine(*args, weights=w)
    assert got["amp"][0, 0] == pytest.approx(0.8, rel=1e-6)
    assert got["delay"][0, 0] == pytest.approx(200.0, abs=1e-5)
    assert np.exp(got["lsig"][0, 0]) == pytest.approx(4.0, rel=1e-6)
    plain, _, _, _ = atomlm.lm_refine(*args)
    assert abs(plain["delay"][0, 0] - 200.0) > 0.5


@pytest.mark.parametrize("weights, message", [
    (np.ones((1, L - 1)), "shape"),
    (np.full((1, L), -1.0), ">= 0"),
    (np.full((1, L), np.nan), "finite"),
])
def test_bad_weights_are_refused(weights, message):
    st = _state([[(cs.FAM_GAUSS, 0.6, 100.0, 3.0, None)]])
    p = _profile([(cs.FAM_GAUSS, 0.6, 100.0, 3.0, None)])[None]
    with pytest.raises(ValueError, match=message):
        atomlm.lm_refine(T0, T, p, SampleMask.all_fitted(p.shape), st, np.zeros(1), np.full(1, 1e-3), _bounds(), 5,
                         weights=weights)


def test_state_models_are_the_slot_sums_of_the_atoms():
    """state_models renders each pixel as its active atoms added in slot order: the same
    values, bit for bit, as summing atom_profiles rows; empty slots and empty pixels add nothing."""
    st = _state([[(cs.FAM_GAUSS, 0.8, 101.3, 4.2, None), (cs.FAM_SSS, 0.05, 104.0, 4.2, 0.03),
                  (cs.FAM_GAUSS, 0.2, 300.0, 4.2, None)],
                 [(cs.FAM_SSS, 0.3, -10.0, 2.0, 0.011)],
                 []])
    for key in ("fam", "amp", "delay", "lsig", "lalp"):     # the sss to the last slot: an empty one between
        st[key][0, 3] = st[key][0, 1]
    st["fam"][0, 1] = cs.FAM_NONE
    st["amp"][0, 1] = 7.0                                      # an empty slot's amplitude counts for nothing
    got = atomlm.state_models(T0, T, L, st["fam"], st["amp"], st["delay"], st["lsig"], st["lalp"])
    want = np.zeros((3, L))
    for p in range(3):
        for k in range(st["fam"].shape[1]):
            if st["fam"][p, k] != cs.FAM_NONE:
                want[p] += atomlm.atom_profiles(T0, T, L, st["fam"][p, k:k + 1], st["delay"][p, k:k + 1],
                                                st["lsig"][p, k:k + 1], st["lalp"][p, k:k + 1])[0] * st["amp"][p, k]
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(render(time_axis_ps(L, T), st), want)
    assert want[0].max() > 0.5 and want[1].max() > 0 and not want[2].any()


@pytest.mark.parametrize("tie, link, weighted", [(True, True, False), (True, False, True), (False, False, False),
                                                 (False, True, True)])
def test_normal_equations_equal_the_direct_sums(tie, link, weighted):
    """J^T W J and J^T r of the compiled refinement (the sss tail past the other atoms summed in
    closed form, the rest over support overlaps) equal the plain products of the full Jacobian
    -- width columns merged for tied widths, the sss delay added to the direct's for a linked
    onset, fixed columns zero -- to rounding, on d + s (+ r2, + an early r inside the tail) pixels."""
    rng = np.random.default_rng(5)
    checked = 0
    for trial in range(40):
        s = rng.uniform(0.8, 8.0)
        d = rng.uniform(20, 300)
        atoms = [(cs.FAM_GAUSS, 1.0, d, s, None), (cs.FAM_SSS, rng.uniform(0.01, 0.3), d + rng.uniform(0, 2 * s), s,
                                                    rng.uniform(0.005, 0.2))]
        if trial % 2:
            atoms.append((cs.FAM_GAUSS, rng.uniform(0.1, 0.5), d + rng.uniform(20, 200), s, None))
        if trial % 5 == 0:
            atoms.insert(0, (cs.FAM_GAUSS, 0.3, rng.uniform(0, L * T), s, None))   # anywhere, even first
        K = len(atoms)
        fam = np.array([a[0] for a in atoms], np.int8)
        amp = np.array([a[1] for a in atoms])
        delay = np.array([a[2] for a in atoms])
        lsig = np.log([a[3] for a in atoms])
        lalp = np.log([a[4] or 1.0 for a in atoms])
        J = np.zeros((4 * K, L))
        lo, hi = np.zeros(K, np.int64), np.zeros(K, np.int64)
        model = np.zeros(L)
        atomlm._render(T0, T, L, K, fam, amp, delay, lsig, lalp, J, lo, hi, model)
        full = np.zeros((4 * K, L))
        for k in range(K):
            atomlm._eval_slot(T0, T, L, fam[k], amp[k], delay[k], lsig[k], lalp[k], full, 4 * k, L, np.empty(0))
        r = rng.normal(0, 0.05, L)
        jw = rng.uniform(0.2, 3.0, L) * (rng.random(L) > 0.1) if weighted else np.ones(L)
        tied, linked, dsl, ssl = atomlm._links(K, fam, delay, lsig, tie, link)
        n = 4 * K
        JtJ, g = np.zeros((n, n)), np.zeros(n)
        free, clo, chi, act = np.zeros(n, np.bool_), np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, np.int64)
        bp, pa, pb = np.zeros(2 * n + 2, np.int64), np.zeros(n * (n + 1) // 2, np.int64), np.zeros(n * (n + 1) // 2, np.int64)
        atomlm._normal_equations(T0, T, K, fam, amp, delay, lsig, lalp, J, lo, hi, r, jw, tied, linked, dsl, ssl, JtJ, g,
                                 free, clo, chi, act, bp, pa, pb)
        ref = full.copy()
        keep = np.array([fam[c // 4] != cs.FAM_NONE and (c % 4 != 3 or fam[c // 4] == cs.FAM_SSS) for c in range(n)])
        if tied:
            ref[2] = full[2::4].sum(axis=0)
            keep[6::4] = False
        if linked:
            ref[4 * dsl + 1] = full[4 * dsl + 1] + full[4 * ssl + 1]
        ref[~keep] = 0.0
        want_jtj = (ref * jw) @ ref.T
        want_g = ref @ r
        scale = np.sqrt(np.outer(np.diag(want_jtj), np.diag(want_jtj))) + 1e-300
        np.testing.assert_array_less(np.abs(JtJ - want_jtj) / scale, 1e-11)
        np.testing.assert_array_less(np.abs(g - want_g) / (np.sqrt(np.diag(want_jtj) * (r @ (jw * r))) + 1e-300), 1e-11)
        assert np.array_equal(free, keep)
        checked += linked == link and tied == tie
    assert checked > 20                    # the rule asked for applied on most pixels


def test_damped_step_solves_the_marquardt_system_over_the_free_parameters():
    """The step solves (JtJ + lam diag(JtJ)) x = g over the parameters not fixed, to rounding,
    on Gram matrices of a few to 16 columns (conditioning up to ~1e8), with the fixed ones 0; a
    damped matrix that is not positive definite (no Gram matrix) gives a zero step, not a wrong
    one."""
    rng = np.random.default_rng(11)
    for n in (1, 3, 8, 16):
        for trial in range(20):
            G = rng.normal(size=(n, 3 * n)) * np.logspace(0, 4, n)[:, None]
            JtJ = G @ G.T
            g = rng.normal(size=n)
            fixed = rng.random(n) < 0.25
            lam = 10.0 ** rng.uniform(-9, 3)
            A, x, idx = np.zeros((n, n + 1)), np.full(n, np.nan), np.zeros(n, np.int64)
            atomlm._damped_step(n, JtJ, g, fixed, lam, A, x, idx)
            f = ~fixed
            want = np.zeros(n)
            if f.any():
                M = JtJ[np.ix_(f, f)] + lam * np.diag(np.diag(JtJ)[f])
                want[f] = np.linalg.solve(M, g[f])
                np.testing.assert_allclose(M @ x[f], g[f], rtol=0, atol=1e-9 * np.abs(M).max() * np.abs(want).max())
            assert np.all(x[fixed] == 0.0)
    # indefinite: [[1, 2], [2, 1]] damped by 1e-3 has a negative eigenvalue
    x = np.full(2, np.nan)
    atomlm._damped_step(2, np.array([[1.0, 2.0], [2.0, 1.0]]), np.ones(2), np.zeros(2, np.bool_), 1e-3,
                        np.zeros((2, 3)), x, np.zeros(2, np.int64))
    assert np.all(x == 0.0)


def test_nnls_amplitudes_recover_known_amplitudes_and_stay_non_negative():
    """Noiseless sums of fixed atoms: the amplitudes come back from any start; an atom the data
    do not contain (here: one whose best amplitude is negative) is held at 0; samples that are
    not fitted do not count; empty slots stay 0."""
    atoms = [(cs.FAM_GAUSS, 0.8, 101.3, 4.2, None), (cs.FAM_SSS, 0.05, 104.0, 4.2, 0.03),
             (cs.FAM_GAUSS, 0.2, 300.0, 4.2, None)]
    st = _state([atoms, atoms])
    p = np.stack([_profile(atoms), _profile(atoms[:2]) - _profile([atoms[2]])])    # pixel 1: the r2 pulls down
    fit = np.ones(p.shape, bool)
    p[:, 30:40] = 50.0                                 # corrupted samples, excluded
    fit[:, 30:40] = False
    start = np.array([[0.1, 0.1, 0.1, 3.0], [2.0, 0.0, 1.0, 3.0]])      # the empty 4th slot's value is ignored
    got = atomlm.nnls_amplitudes(T0, T, p, fit, st["fam"], start, st["delay"], st["lsig"], st["lalp"], sweeps=400)
    np.testing.assert_allclose(got[0, :3], [0.8, 0.05, 0.2], rtol=1e-6)
    assert got[1, 2] == 0.0 and got[1, 0] > 0 and got[1, 1] > 0
    assert got[0, 3] == 0.0 and got[1, 3] == 0.0
    # the constrained optimum: no feasible direction lowers the fitted-sample residual
    phi = atomlm.atom_profiles(T0, T, L, st["fam"][1, :3], st["delay"][1, :3], st["lsig"][1, :3], st["lalp"][1, :3])
    grad = phi[:, fit[1]] @ (p[1, fit[1]] - got[1, :3] @ phi[:, fit[1]])
    assert abs(grad[0]) < 1e-8 and abs(grad[1]) < 1e-8 and grad[2] < 0


def test_window_sums_are_those_of_the_atom_rows():
    """atom_window_sums: the largest value, the sum and the sum of squares of each atom_profiles
    row (atoms inside, across and outside the window; empty rows give zeros)."""
    fam = np.array([cs.FAM_GAUSS, cs.FAM_SSS, cs.FAM_NONE, cs.FAM_SSS, cs.FAM_GAUSS], np.int8)
    delay = np.array([80.0, 150.5, 10.0, -30.0, -400.0])
    lsig = np.log([2.5, 4.0, 3.0, 6.0, 3.0])
    lalp = np.log([1.0, 0.02, 1.0, 0.05, 1.0])
    rows = atomlm.atom_profiles(T0, T, L, fam, delay, lsig, lalp)
    got = atomlm.atom_window_sums(T0, T, L, fam, delay, lsig, lalp)
    np.testing.assert_array_equal(got[:, 0], rows.max(axis=1))
    np.testing.assert_allclose(got[:, 1], rows.sum(axis=1), rtol=1e-13)
    np.testing.assert_allclose(got[:, 2], (rows * rows).sum(axis=1), rtol=1e-13)
    assert not got[2].any() and not got[4].any() and got[1, 1] > 10 and got[3, 0] > 0


def test_weighted_squares_are_those_of_the_atom_rows():
    """atom_weighted_squares: sum_i min(w_i, cap) phi_i^2 of each atom_profiles row, with the
    weights of the pixel each atom belongs to; bad weights are refused."""
    fam = np.array([cs.FAM_GAUSS, cs.FAM_SSS, cs.FAM_NONE, cs.FAM_SSS, cs.FAM_GAUSS], np.int8)
    delay = np.array([80.0, 150.5, 10.0, -30.0, -400.0])
    lsig = np.log([2.5, 4.0, 3.0, 6.0, 3.0])
    lalp = np.log([1.0, 0.02, 1.0, 0.05, 1.0])
    pix = np.array([1, 0, 2, 1, 0])
    w = np.random.default_rng(2).uniform(0.0, 12.0, (3, L))
    rows = atomlm.atom_profiles(T0, T, L, fam, delay, lsig, lalp)
    got = atomlm.atom_weighted_squares(T0, T, L, fam, delay, lsig, lalp, w, pix, 5.0)
    np.testing.assert_allclose(got, (rows * rows * np.minimum(w[pix], 5.0)).sum(axis=1), rtol=1e-12)
    assert got[1] > 0 and got[2] == 0 and got[4] == 0
    with pytest.raises(ValueError, match="weights have shape"):
        atomlm.atom_weighted_squares(T0, T, L, fam, delay, lsig, lalp, w[:, :-1], pix)


def test_an_unfitted_sample_changes_nothing_whatever_it_holds():
    """A pixel whose samples all count or are left out takes the LM's branch-free objective; one
    whose left-out sample is not finite (or that has a censored sample) the per-sample test.
    Both read the same objective: the same atoms, objective and model from the same start, and
    a NaN where a sample does not count never reaches the answer."""
    atoms = [(cs.FAM_GAUSS, 0.9, 101.3, 4.2, None), (cs.FAM_SSS, 0.3, 104.0, 4.2, 0.03)]
    rng = np.random.default_rng(5)
    clean = _profile(atoms)
    p = np.tile(clean + 0.002 * rng.standard_normal(L), (3, 1))
    fit = np.ones((3, L), bool)
    fit[:, 40] = False
    p[1, 40] = np.nan                          # not finite where it does not count
    p[2, 40] = 1e6                             # and huge
    cens = np.zeros((3, L), bool)
    start = _state([[(cs.FAM_GAUSS, 0.7, 103.0, 5.0, None), (cs.FAM_SSS, 0.2, 106.0, 5.0, 0.02)]] * 3)
    st, obj, it, model = atomlm.lm_refine(T0, T, p, SampleMask(fit, cens), start, np.zeros(3), np.full(3, 1e-5),
                                          _bounds(), 30)
    assert np.all(it > 3) and np.all(np.isfinite(obj)) and np.all(np.isfinite(model))
    for key in ("amp", "delay", "lsig", "lalp"):
        np.testing.assert_allclose(st[key][1:], np.broadcast_to(st[key][0], st[key][1:].shape), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(obj[1:], obj[0], rtol=1e-12)
    np.testing.assert_allclose(model[1:], np.broadcast_to(model[0], (2, L)), rtol=0, atol=1e-13)
    # the fit found the atoms, and its objective is the data term of the samples that count
    assert abs(st["delay"][0, 0] - 101.3) < 0.5
    r = np.where(fit[0], p[0] - model[0], 0.0)
    assert obj[0] == pytest.approx(0.5 * np.sum(r * r), rel=1e-10)
