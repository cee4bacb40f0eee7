"""Compiled scalar kernels (decomposition.jit) against scipy and core.model."""
import numpy as np
import pytest
from scipy import special

from decomposition import jit
from core.model import sss_kernel


def test_erfcx_matches_scipy_across_the_series_switch_and_far_tail():
    u = np.concatenate([np.linspace(0.0, 12.0, 2401), np.geomspace(12.0, 1e150, 400)])
    got = np.array([jit.erfcx(v) for v in u])
    ref = special.erfcx(u)
    np.testing.assert_allclose(got, ref, rtol=2e-14, atol=0)
    assert np.all(np.isfinite(got)) and np.all(got > 0)


@pytest.mark.parametrize("sigma_ps, alpha_per_ps", [(0.5, 1e-6), (3.0, 0.02), (10.0, 0.05), (2.0, 50.0)])
def test_sss_value_matches_the_forward_model(sigma_ps, alpha_per_ps):
    x = np.linspace(-8.0 * sigma_ps, 40.0 * sigma_ps, 501)
    with np.errstate(all="raise"):
        h = np.array([jit.sss_value(v, sigma_ps, alpha_per_ps)[0] for v in x])
        g = np.array([jit.sss_value(v, sigma_ps, alpha_per_ps)[1] for v in x])
    np.testing.assert_allclose(h, sss_kernel(x, sigma_ps, alpha_per_ps), rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(g, np.exp(-0.5 * (x / sigma_ps) ** 2), rtol=1e-15, atol=0)


def test_a_kernel_without_a_cache_location_still_compiles():
    """Code with no source file (or no writable cache directory) gets no disk cache, not an error."""
    ns = {"jit": jit}
    exec("@jit.njit\ndef twice(x):\n    return 2.0 * x\n", ns)
    assert ns["twice"](1.5) == 3.0
