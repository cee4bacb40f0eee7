"""The compiled variable-projection step of the response path (decomposition/kernels/responselm.py).

Known answers: a copy of the block-array form of the least-squares fit (NumPy algebra on
(pixels, 2K, L) arrays, the form fit_slots used before the compiled loop) is kept here as the
reference; on random small cases -- shifted and sss slots, empty slots, a fitted offset, the
constraints active, bounds hit, zero weights -- the compiled fit takes the same steps (same
accepted / refused sequence, same iteration counts) and lands on the same slots to rounding.
"""
import numpy as np
import pytest

from core.irf import render_shifted, render_sss
from core.irf_models import tailed_response
from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS
from decomposition.kernels.responselm import LAMBDA0, LAMBDA_MAX
from decomposition.response.refine import _evaluate, _project, fit_slots

T = 2.0
L = 160
T_PS = T + T * np.arange(L)


def _reference(irf, t, y, sw, fam, delay, lalp, *, n_iter, lm_tol, delay_bounds_ps, lalp_bounds,
               sss_after_direct=True, first_is_direct=False, fit_background=None):
    """The block-array least-squares fit (every pixel of the block at once)."""
    P, K = fam.shape
    delay, lalp = _project(fam, np.where(fam != FAM_NONE, delay, 0.0), np.where(fam == FAM_SSS, lalp, 0.0),
                           delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
    fit_bg = None if fit_background is None else np.broadcast_to(np.asarray(fit_background, bool), (P,))
    cur = _evaluate(irf, t, y, sw, fam, delay, lalp, fit_bg)
    amp, cost = cur["amp"], cur["cost"]
    iters = np.zeros(P, np.int64)
    conv = np.zeros(P, bool)
    lam = np.full(P, LAMBDA0)
    n_used = np.maximum((sw > 0).sum(axis=1), 1)
    free = np.concatenate([fam != FAM_NONE, fam == FAM_SSS], axis=1)
    conv |= ~free.any(axis=1)
    state = {"delay": delay.copy(), "lalp": lalp.copy(), "amp": amp.copy(), "cost": cost.copy()}
    cache = cur
    for _ in range(int(n_iter)):
        idx = np.flatnonzero(~conv)
        if idx.size == 0:
            break
        c = {k: v[idx] for k, v in cache.items()}
        f = fam[idx]
        a = c["amp"][:, :K]
        g = np.concatenate([a[:, :, None] * c["dd"], a[:, :, None] * c["dl"]], axis=1) * sw[idx][:, None, :]
        fr = free[idx]
        g = np.where(fr[:, :, None], g, 0.0)
        proj = np.matmul(c["pw"], g.transpose(0, 2, 1))
        gp = g - np.matmul(np.matmul(proj.transpose(0, 2, 1), c["minv"]), c["pw"])
        jtj = np.matmul(gp, gp.transpose(0, 2, 1))
        jtr = np.matmul(g, c["resid"][:, :, None])[..., 0]
        dg = np.einsum("pjj->pj", jtj)
        scale_d = np.where(fr, dg + 1e-300, 1.0)
        lhs = jtj + (lam[idx][:, None] * scale_d)[:, :, None] * np.eye(2 * K)[None]
        lhs += np.eye(2 * K)[None] * (~fr)[:, :, None]
        step = np.linalg.solve(lhs, np.where(fr, jtr, 0.0)[..., None])[..., 0]
        finite = np.isfinite(step).all(axis=1)
        step = np.where(finite[:, None], step, 0.0)
        nd = state["delay"][idx] + np.where(fr[:, :K], step[:, :K], 0.0)
        nl = state["lalp"][idx] + np.where(fr[:, K:], step[:, K:], 0.0)
        nd, nl = _project(f, nd, nl, delay_bounds_ps, lalp_bounds, sss_after_direct, first_is_direct)
        trial = _evaluate(irf, t, y[idx], sw[idx], f, nd, nl, None if fit_bg is None else fit_bg[idx])
        ok = finite & np.isfinite(trial["cost"]) & (trial["cost"] < c["cost"])
        gain = c["cost"] - trial["cost"]
        iters[idx] += 1
        acc = idx[ok]
        state["delay"][acc], state["lalp"][acc] = nd[ok], nl[ok]
        state["amp"][acc], state["cost"][acc] = trial["amp"][ok], trial["cost"][ok]
        lam[acc] /= 3.0
        lam[idx[~ok]] *= 4.0
        small = ok & (gain < lm_tol * trial["cost"] / n_used[idx])
        conv[idx[small]] = True
        conv[idx[~ok & (lam[idx] > LAMBDA_MAX)]] = True
        for k in cache:
            cache[k][acc] = trial[k][ok]
    return {"delay": np.where(fam != FAM_NONE, state["delay"], np.nan),
            "lalp": np.where(fam == FAM_SSS, state["lalp"], np.nan),
            "amp": np.where(fam != FAM_NONE, state["amp"][:, :K], 0.0),
            "background": state["amp"][:, K] if fit_bg is not None else np.zeros(P),
            "cost": state["cost"], "resid": cache["resid"], "iterations": iters, "converged": conv}


@pytest.fixture(scope="module")
def irf():
    return tailed_response(4.0, 0.2, 30.0, time_step_ps=T)


def _case(irf, seed, P=40, K=4, degenerate=False):
    """Random pixels: a direct and an echo (shifted), an sss, empty slots, noise, starts off the
    truth by a few ps, an offset, some samples excluded."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(60, 150, P)
    e = d + rng.uniform(15, 120, P)
    al = rng.uniform(0.01, 0.08, P)
    y = (render_shifted(irf, T_PS, d) + rng.uniform(0.2, 0.8, P)[:, None] * render_shifted(irf, T_PS, e)
         + rng.uniform(0.01, 0.05, P)[:, None] * render_sss(irf, T_PS, d, al)
         + rng.uniform(-0.02, 0.05, P)[:, None] + 0.01 * rng.standard_normal((P, L)))
    sw = np.ones((P, L))
    sw[rng.random((P, L)) < 0.05] = 0.0
    y = np.where(sw > 0, y, 0.0)
    fam = np.zeros((P, K), np.int8)
    fam[:, 0] = FAM_GAUSS
    fam[:, 1] = np.where(rng.random(P) < 0.8, FAM_SSS, FAM_NONE)
    fam[:, 2] = np.where(rng.random(P) < 0.7, FAM_GAUSS, FAM_NONE)
    delay = np.stack([d + rng.normal(0, 3, P), d + rng.normal(0, 5, P), e + rng.normal(0, 4, P),
                      rng.uniform(0, 300, P)], axis=1)
    lalp = np.log(al * rng.uniform(0.5, 2.0, P))[:, None] * np.ones((1, K))
    delay[::7, 0] = -50.0                       # starts outside the delay bounds
    if degenerate:                              # an echo before the direct, an sss before the first atom
        delay[3::7, 2] = delay[3::7, 0] - 10.0
        delay[5::7, 1] = delay[5::7, 0] - 8.0
    return y, sw, fam, delay, lalp


_KW = dict(n_iter=12, lm_tol=1e-6, delay_bounds_ps=(0.0, 300.0), lalp_bounds=(np.log(1e-3), np.log(0.5)))


def _both(irf, y, sw, fam, delay, lalp, **kw):
    kw = {**_KW, **kw}
    return _reference(irf, T_PS, y, sw, fam, delay, lalp, **kw), fit_slots(irf, T_PS, y, sw, fam, delay, lalp, **kw)


@pytest.mark.parametrize("seed,first_is_direct,with_bg", [(0, False, False), (1, True, True), (2, True, False)])
def test_compiled_fit_takes_the_block_forms_steps(irf, seed, first_is_direct, with_bg):
    """Shifted atoms (a direct and an echo, some pixels one atom only): a well-posed fit, where
    the two forms differ only by their rounding -- the same steps kept and refused, the same
    answers to 1e-9 ps."""
    y, sw, fam, delay, lalp = _case(irf, seed)
    fam[:, 1] = FAM_NONE
    bg = (np.arange(y.shape[0]) % 3 != 0) if with_bg else None
    ref, got = _both(irf, y, sw, fam, delay, lalp, sss_after_direct=False, first_is_direct=first_is_direct,
                     fit_background=bg)
    assert np.array_equal(got.iterations, ref["iterations"])
    assert np.array_equal(got.converged, ref["converged"])
    assert (ref["iterations"] > 3).mean() > 0.5 and ref["converged"].any()
    act = fam != FAM_NONE
    assert np.array_equal(np.isnan(got.delay), ~act)
    assert np.allclose(got.delay[act], ref["delay"][act], rtol=0, atol=1e-9)
    assert np.allclose(got.amp, ref["amp"], rtol=1e-10, atol=1e-12)
    assert np.allclose(got.background, ref["background"], rtol=1e-10, atol=1e-12)
    assert np.allclose(got.cost, ref["cost"], rtol=1e-12, atol=0)
    assert np.allclose(got.resid, ref["resid"], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed,with_bg", [(0, False), (4, True)])
def test_compiled_fit_with_sss_matches_the_block_form(irf, seed, with_bg):
    """With an sss slot whose onset the constraint holds on the direct (the scenes' own sss):
    its onset derivative lies in the span of the atoms there, so both forms step along a
    direction made of rounding; the answers agree to 1e-3 ps and 1e-6 of the cost."""
    y, sw, fam, delay, lalp = _case(irf, seed)
    delay[:, 1] = np.maximum(delay[:, 1], delay[:, 0] + 3.0)
    bg = (np.arange(y.shape[0]) % 2 == 0) if with_bg else None
    ref, got = _both(irf, y, sw, fam, delay, lalp, sss_after_direct=True, first_is_direct=True, fit_background=bg)
    assert (got.iterations == ref["iterations"]).mean() >= 0.95
    act = fam != FAM_NONE
    sss = fam == FAM_SSS
    assert sss.sum() > 20
    assert np.allclose(got.delay[act], ref["delay"][act], rtol=0, atol=1e-3)
    assert np.allclose(got.lalp[sss], ref["lalp"][sss], rtol=0, atol=1e-5)
    assert np.allclose(got.amp, ref["amp"], rtol=0, atol=1e-5)
    assert np.allclose(got.cost, ref["cost"], rtol=1e-6, atol=0)


def test_compiled_fit_keeps_the_constraints_and_amplitude_only_fits(irf):
    """Starts that break the constraints (an echo before the direct, an sss before the first
    shifted atom, delays below their bound): every answer within them, no cost above the
    start's; with n_iter = 0 the amplitudes of the projected starts, as the block form."""
    kw = dict(lm_tol=1e-3, delay_bounds_ps=(0.0, 300.0), lalp_bounds=(np.log(1e-3), np.log(0.5)),
              sss_after_direct=True, first_is_direct=True)
    y, sw, fam, delay, lalp = _case(irf, 3, degenerate=True)
    f = fit_slots(irf, T_PS, y, sw, fam, delay, lalp, n_iter=8, **kw)
    act = fam != FAM_NONE
    assert np.all((f.delay[act] >= 0.0) & (f.delay[act] <= 300.0))
    sh = fam == FAM_GAUSS
    assert np.all(f.delay[:, 2][sh[:, 2]] >= f.delay[:, 0][sh[:, 2]])
    first = np.where(sh, f.delay, np.inf).min(axis=1)
    assert np.all(f.delay[:, 1][fam[:, 1] == FAM_SSS] >= first[fam[:, 1] == FAM_SSS])
    g = fit_slots(irf, T_PS, y, sw, fam, delay, lalp, n_iter=0, **kw)
    assert np.all(f.cost <= g.cost)
    # n_iter = 0: amplitudes only, at the projected starts, the same as the reference (the
    # starts that keep the atoms apart: an atom pushed onto another is collinear with it)
    y, sw, fam, delay, lalp = _case(irf, 3)
    fam[:, 1] = FAM_NONE
    g = fit_slots(irf, T_PS, y, sw, fam, delay, lalp, n_iter=0, **kw)
    ref = _reference(irf, T_PS, y, sw, fam, delay, lalp, n_iter=0, **kw)
    act = fam != FAM_NONE
    assert np.array_equal(g.iterations, np.zeros(y.shape[0], np.int64))
    assert np.allclose(g.delay[act], ref["delay"][act], rtol=0, atol=0)
    assert np.allclose(g.amp, ref["amp"], rtol=1e-9, atol=1e-12)
    # a pixel with no active slot: nothing fitted, its residual the weighted data
    fam0 = np.zeros_like(fam)
    h = fit_slots(irf, T_PS, y, sw, fam0, delay, lalp, n_iter=4, **kw)
    assert h.converged.all() and not h.iterations.any()
    assert np.array_equal(h.resid, y * sw) and np.allclose(h.cost, ((y * sw) ** 2).sum(axis=1))


def test_cross_products_are_the_sums_in_eight_lanes():
    """The LM's dot products are, bit for bit, eight partial sums (sample l in lane l mod 8, the
    samples past the last whole eight in lane 0), each taken one sample at a time from 0 (as
    np.cumsum sums), combined as ((0 + 4) + (1 + 5)) + ((2 + 6) + (3 + 7)): the same bits on
    every run, for the symmetric and the full form, on leading rows of larger buffers, the
    entries outside left alone."""
    from decomposition.kernels.responselm import _cross

    def lanes(p):
        n8 = p.size - p.size % 8
        a = [np.cumsum(np.concatenate([p[:n8:8], p[n8:]]))[-1]] + [np.cumsum(p[k:n8:8])[-1] if n8 else 0.0
                                                                    for k in range(1, 8)]
        return ((a[0] + a[4]) + (a[1] + a[5])) + ((a[2] + a[6]) + (a[3] + a[7]))

    rng = np.random.default_rng(7)
    for L in (37, 40, 5):
        x = rng.normal(size=(6, L)) * 10.0 ** rng.integers(-3, 4, size=(6, 1))
        y = rng.normal(size=(5, L))
        for nx, ny, sym in ((5, 5, True), (1, 1, True), (3, 4, False), (5, 1, False), (2, 3, False)):
            out = np.full((6, 6), np.nan)
            _cross(x, nx, x if sym else y, ny, sym, out)
            other = x if sym else y
            want = np.array([[lanes(x[i] * other[j]) for j in range(ny)] for i in range(nx)])
            assert np.array_equal(out[:nx, :ny], want)
            assert np.isnan(out[nx:]).all() and np.isnan(out[:, ny:]).all()
