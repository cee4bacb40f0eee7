"""The count statistics the forward steps decide with (decomposition.noise), against known answers."""
import math

import numpy as np

from decomposition.constants import POISSON_VARIANCE_FLOOR
from decomposition.noise import anscombe_residual, atom_gain, count_deviance, poisson_deviance, removal_deviance


def test_count_deviance_is_the_poisson_deviance_on_the_fitted_samples():
    y = np.array([[3.0, 0.0, 2.0, 7.0]])
    mu = np.array([[3.0, 0.5, 1.0, 0.0]])
    fit = np.array([[True, True, True, False]])
    want = 2.0 * (0.0 + 0.5 + (2.0 * math.log(2.0) - 1.0))
    np.testing.assert_allclose(count_deviance(y, mu, fit), [want], rtol=1e-12)
    np.testing.assert_allclose(count_deviance(y, mu, fit, dispersion=np.array([2.0])), [want / 4.0], rtol=1e-12)
    # a model of ~0 is floored as the weights are: one count there costs 2 (log(1/floor) - 1 + floor)
    z = count_deviance(np.array([[1.0]]), np.array([[0.0]]), np.array([[True]]))
    f = POISSON_VARIANCE_FLOOR
    np.testing.assert_allclose(z, [2.0 * (math.log(1.0 / f) - 1.0 + f)], rtol=1e-12)
    np.testing.assert_allclose(poisson_deviance(y[:, :3], mu[:, :3]), [want], rtol=1e-12)


def test_count_deviance_reads_odd_models_and_any_shape_as_the_formula_does():
    """A NaN model count is read as 0 (then floored), an infinite one as infinite; samples that
    do not count add nothing whatever they hold; rows of any leading shape, summed per row:
    against the per-sample formula written out here."""
    rng = np.random.default_rng(3)
    mu = rng.gamma(2.0, 4.0, (2, 3, 64))
    y = rng.poisson(mu).astype(float)
    fit = rng.random(mu.shape) > 0.1
    mu[0, 0, 5] = np.nan
    fit[0, 0, 5] = True
    mu[1, 2, 9] = np.nan                     # not fitted: adds nothing
    fit[1, 2, 9] = False
    y[1, 2, 9] = np.nan
    f = POISSON_VARIANCE_FLOOR
    want = np.zeros((2, 3))
    for idx in np.ndindex(2, 3):
        for yi, mi, ok in zip(y[idx], mu[idx], fit[idx]):
            if ok:
                m = max(0.0 if math.isnan(mi) else mi, f)
                want[idx] += 2.0 * ((yi * math.log(yi / m) if yi > 0 else 0.0) - (yi - m))
    np.testing.assert_allclose(count_deviance(y, mu, fit), want, rtol=1e-12)
    assert np.isfinite(want).all()
    inf = mu.copy()
    inf[0, 1, 3] = np.inf
    fit_all = np.ones(mu.shape, bool)
    got = count_deviance(np.nan_to_num(y), inf, fit_all)
    assert np.isinf(got[0, 1]) and np.isfinite(np.delete(got.ravel(), 1)).all()


def test_removal_deviance_is_the_energy_rule_at_large_counts():
    """Where the counts are large the deviance is the chi2 with variance mu: taking an atom c
    out of a model that fits raises it by sum c^2 / mu, the Gaussian path's energy rule."""
    t = np.arange(200.0)
    base = 1e6 * (1.0 + np.exp(-0.5 * ((t - 60.0) / 4.0) ** 2))
    atom = 5e3 * np.exp(-0.5 * ((t - 140.0) / 4.0) ** 2)
    mu = base + atom
    y = mu.copy()[None]
    fit = np.ones_like(y, bool)
    got = removal_deviance(y, mu[None], np.stack([base - 1e6, atom])[None], fit)
    np.testing.assert_allclose(got[0, 1], np.sum(atom ** 2 / mu), rtol=0.01)
    assert got[0, 0] > got[0, 1]
    # an empty slot reads 0
    assert removal_deviance(y, mu[None], np.zeros((1, 1, t.size)), fit)[0, 0] == 0.0


def test_atom_gain_is_the_best_amplitude_with_the_rest_held():
    rng = np.random.default_rng(4)
    t = np.arange(64.0)
    phi = np.exp(-0.5 * ((t - 30.0) / 2.5) ** 2)[None].repeat(3, axis=0)
    mu = np.stack([np.full(64, 0.3), np.full(64, 5.0), np.zeros(64)])         # the last: model ~0
    truth = np.array([4.0, 6.0, 2.0])
    y = rng.poisson(mu + truth[:, None] * phi).astype(float)
    fit = np.ones_like(y, bool)
    gain, amp = atom_gain(y, mu, phi, fit)
    # brute force over the amplitude, the atom added to the floored model
    mu_f = np.maximum(mu, POISSON_VARIANCE_FLOOR)
    for p in range(3):
        def dev(a):
            return poisson_deviance(y[p], mu_f[p] + a * phi[p])
        coarse = np.linspace(0.0, 20.0, 2001)
        a0 = coarse[int(np.argmin([dev(a) for a in coarse]))]
        fine = np.linspace(a0 - 0.02, a0 + 0.02, 4001)
        devs = np.array([dev(a) for a in fine])
        assert abs(amp[p] - fine[np.argmin(devs)]) < 2e-5
        assert abs(amp[p] - truth[p]) < 3.0 * math.sqrt(truth[p] + 1.0)
        np.testing.assert_allclose(gain[p], dev(0.0) - devs.min(), rtol=1e-7, atol=1e-9)
    # a deficit where the atom lies: amplitude 0, nothing gained
    g0, a0 = atom_gain(np.zeros((1, 64)), np.full((1, 64), 2.0), phi[:1], fit[:1])
    assert g0[0] == 0.0 and a0[0] == 0.0


def test_anscombe_residual_is_bounded_where_the_model_is_empty():
    y = np.array([[1.0, 0.0, 4.0, 1e6 + 3e3]])
    mu = np.array([[0.0, 0.0, 4.0, 1e6]])
    fit = np.ones_like(y, bool)
    z = anscombe_residual(y, mu, fit)[0]
    np.testing.assert_allclose(z[0], 2.0 * (math.sqrt(1.375) - math.sqrt(0.375)), rtol=1e-12)   # 1.12 sigma
    assert z[1] == 0.0 and z[2] == 0.0
    np.testing.assert_allclose(z[3], 3e3 / math.sqrt(1e6), rtol=2e-3)         # (y - mu) / sqrt(mu) at large mu
    # the Pearson residual of that single count would be (1 - floor) / sqrt(floor), ~7 sigma
    assert z[0] < 0.2 * (1.0 - POISSON_VARIANCE_FLOOR) / math.sqrt(POISSON_VARIANCE_FLOOR)
    np.testing.assert_allclose(anscombe_residual(y, mu, fit, dispersion=np.array([2.0]))[0], z / 2.0)
    assert np.all(anscombe_residual(y, mu, np.zeros_like(fit)) == 0.0)
