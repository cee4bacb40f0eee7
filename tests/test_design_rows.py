"""The design rows of refinement and the Jacobian of the Fisher information evaluate each kernel
on its support only: inside it the values are exactly those of ``kernel_derivatives`` on the
whole axis, outside it they are zero where the whole-axis values are at the exp floor."""
import numpy as np
import pytest

from decomposition.constants import SSS_SLOT
from decomposition.kernels.derivatives import kernel_derivatives
from decomposition.model import fisher
from decomposition.model.varpro import design_rows

L, TB = 512, 2.0
T = TB * np.arange(1, L + 1)


def _slots():
    """Four pixels, K = 4: direct, sss, two inter-reflections (one absent, one off the axis)."""
    delay = np.array([[100.0, 104.0, 400.0, 700.0],
                      [30.0, 30.0, 900.0, 0.0],
                      [500.0, 510.0, 0.0, 0.0],
                      [150.0, 152.0, 450.0, 2048.0]])       # the last: wholly after the axis ends
    sigma = np.array([[3.0, 3.0, 3.0, 3.0], [5.0, 5.0, 5.0, 5.0], [2.5, 2.5, 2.5, 2.5], [4.0, 4.0, 4.0, 4.0]])
    alpha = np.array([0.03, 0.01, 0.05, 0.02])
    present = np.array([[1, 1, 1, 1], [1, 1, 1, 0], [1, 1, 0, 0], [1, 1, 1, 1]], bool)
    return delay, sigma, alpha, present


def _whole_axis_rows(y, delay, sigma, alpha, present, tb, sw):
    """The rows as :func:`design_rows` documents them, every kernel on the whole axis."""
    n, k = delay.shape
    m = np.zeros((n, 3 * k + 2, L))
    m[:, -1] = y
    for p in range(n):
        for j in np.flatnonzero(present[p]):
            a = alpha[p] if j == SSS_SLOT else None
            v = kernel_derivatives(T - delay[p, j], sigma[p, j], a, time_bin_ps=tb)
            m[p, j], m[p, k + j], m[p, 2 * k + j] = v[0], v[1], v[2] * sigma[p, j]
            if j == SSS_SLOT:
                m[p, 3 * k] = v[3] * alpha[p]
    if sw is not None:
        m[:, :-1] *= sw[:, None, :]
    return m


@pytest.mark.parametrize("tb", [None, TB])
@pytest.mark.parametrize("weighted", [False, True])
def test_windowed_rows_equal_the_whole_axis_rows(tb, weighted):
    delay, sigma, alpha, present = _slots()
    rng = np.random.default_rng(0)
    y = rng.normal(size=(4, L))
    sw = np.sqrt(rng.uniform(0.0, 2.0, size=(4, L))) if weighted else None
    got = design_rows(T, y, delay, sigma, alpha, present, tb, True, sw)
    ref = _whole_axis_rows(y, delay, sigma, alpha, present, tb, sw)
    # inside each window bit for bit; outside, what is left out is below 1e-290
    inside = got != 0.0
    np.testing.assert_array_equal(got[inside], ref[inside])
    assert np.max(np.abs(got - ref)) <= 1e-290
    # and the windows do cut: a 3 ps Gaussian at 100 ps covers well under half of the 1024 ps axis (the windows of a call share the widest one, 5 ps here)
    assert np.mean(got[0, 0] == 0.0) > 0.5 and np.mean(got[0, 4 + 0] == 0.0) > 0.5
    # a kernel wholly off the axis keeps its whole-axis (floor-level) values: its amplitude rests on them
    np.testing.assert_array_equal(got[3, [3, 7, 11]], ref[3, [3, 7, 11]])
    # the values alone (no derivatives) are the first rows of the same
    val = design_rows(T, y, delay, sigma, alpha, present, tb, False, sw)
    np.testing.assert_array_equal(val[:, :4], got[:, :4])
    np.testing.assert_array_equal(val[:, -1], got[:, -1])


def test_fisher_jacobian_rows_equal_the_whole_axis_rows():
    delay, sigma, alpha, present = _slots()
    amp = np.array([[1.0, 0.2, 0.5, 0.3]] * 4)
    slots = {"delay": delay, "sigma": sigma, "alpha": alpha, "present": present, "amplitude": amp}
    rows, free = fisher._jacobian(T, slots, np.ones(4), None)
    k = 4
    for p in range(4):
        for j in np.flatnonzero(present[p]):
            a = alpha[p] if j == SSS_SLOT else None
            v = kernel_derivatives(T - delay[p, j], sigma[p, j], a)
            ref = [amp[p, j] * v[1], v[0], amp[p, j] * v[2]] + ([amp[p, j] * v[3]] if j == SSS_SLOT else [])
            got = [rows[p, 3 * j], rows[p, 3 * j + 1], rows[p, 3 * j + 2]] + ([rows[p, 3 * k]] if j == SSS_SLOT else [])
            for g, r in zip(got, ref):
                inside = g != 0.0
                np.testing.assert_array_equal(g[inside], r[inside])
                assert np.max(np.abs(g - r)) <= 1e-290
    assert np.mean(rows[0, 1] == 0.0) > 0.5
