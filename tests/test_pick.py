"""Gauss-Southwell selection (decomposition.kernels.pick) against a direct reference."""
import numpy as np

from decomposition.kernels.pick import TOP_K, closed_form, select


def _reference(c, n2, mu, eps, allow, by_size, eligible):
    """Rank every coordinate (stable sort: ties to the lower index), then the exact rule."""
    n = c.shape[0]
    best, zb, db = np.zeros(n, np.int64), np.zeros(n), np.zeros(n)
    for i in range(n):
        nn = np.broadcast_to(n2, c.shape)[i].ravel()
        ci = c[i].ravel()
        u = np.divide(ci, nn, out=np.zeros_like(ci), where=nn > 0)
        ok = np.broadcast_to(allow, c.shape)[i].ravel() & (u > 0) & (u <= 20.0)
        if by_size[i]:
            ok &= np.broadcast_to(eligible, c.shape)[i].ravel()
        key = np.where(ok, u if by_size[i] else ci * u, -np.inf)
        order = np.argsort(-key, kind="stable")[:TOP_K]
        for j in order:
            if not np.isfinite(key[j]):
                break
            z, dec = closed_form(u[j], nn[j], mu[i], eps[i])
            if not z <= 20.0:
                dec = 0.0
            if by_size[i]:
                if dec > 0:
                    best[i], zb[i], db[i] = j, z, dec
                    break
            elif dec > db[i]:
                best[i], zb[i], db[i] = j, z, dec
    return best, zb, db


def test_closed_form_edge_cases():
    z, dec = closed_form([0.0, -1.0, 1.0, 1.0, 1e-3], [1.0, 1.0, 0.0, 1.0, 1.0], 0.1, 0.01)
    assert list(z[:3]) == [0.0, 0.0, 0.0] and list(dec[:3]) == [0.0, 0.0, 0.0]
    assert z[3] > 0 and dec[3] > 0 and z[4] == 0 and dec[4] == 0   # tiny u loses to z = 0


def test_select_matches_the_reference_rules_with_ties_masks_and_shared_norms():
    rng = np.random.default_rng(2)
    n, A, S = 40, 5, 60
    c = rng.normal(0, 1, (n, A, S))
    c[:5] = np.round(2 * c[:5]) / 2                 # many exact ties
    c[5, 2, 7] = np.nan                              # a non-finite correlation is never picked
    c[7] = -np.abs(c[7])                             # nothing decreases F: no pick
    n2_own = rng.uniform(0.5, 4.0, (n, A, S))
    n2_own[6, :, :10] = 0.0
    n2_shared = rng.uniform(0.5, 4.0, (1, A, S))
    n2_flat = np.ones((1, A, S))                     # with rounded c: exact key ties
    mu = rng.uniform(0.01, 0.5, n)
    eps = rng.uniform(1e-3, 1e-2, n)
    allow = rng.random((n, A, 1)) < 0.8
    by_size = rng.random(n) < 0.4
    eligible = rng.random((n, A, S)) < 0.7
    for n2 in (n2_own, n2_shared, n2_flat):
        got = select(c, n2, mu, eps, allow, by_size, eligible)
        want = _reference(c, n2, mu, eps, allow, by_size, eligible)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1], rtol=1e-14)
        np.testing.assert_allclose(got[2], want[2], rtol=1e-14)
        assert (got[2] > 0).sum() > n // 2
        assert got[0][7] == 0 and got[1][7] == 0 and got[2][7] == 0
    # without by_size / eligible every row takes the largest exact decrease of its top 3
    got = select(c, n2_own, mu, eps, allow)
    want = _reference(c, n2_own, mu, eps, allow, np.zeros(n, bool), True)
    np.testing.assert_array_equal(got[0], want[0])
