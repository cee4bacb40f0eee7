"""Every evaluation of the kernels against the one reference, core.model."""
import numpy as np
import pytest

from decomposition.kernels import jit
from decomposition.kernels.derivatives import kernel_derivatives
from core.model import gaussian_kernel, sss_kernel


@pytest.mark.parametrize("sigma_ps, alpha_per_ps", [(0.5, 1e-6), (3.0, 0.02), (10.0, 0.05), (2.0, 50.0)])
def test_the_derivative_carrying_and_the_compiled_kernels_are_the_forward_model(sigma_ps, alpha_per_ps):
    t = np.linspace(-40.0 * sigma_ps, 60.0 * sigma_ps, 2001)
    ref = sss_kernel(t, sigma_ps, alpha_per_ps)
    with np.errstate(all="raise", under="ignore"):
        h = kernel_derivatives(t, sigma_ps, alpha_per_ps)[0]
        g = kernel_derivatives(t, sigma_ps)[0]
    np.testing.assert_allclose(h, ref, rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(g, gaussian_kernel(t, sigma_ps), rtol=1e-15, atol=1e-300)
    twin = np.array([jit.sss_value(v, sigma_ps, alpha_per_ps)[0] for v in t])
    np.testing.assert_allclose(twin, ref, rtol=1e-13, atol=1e-300)
    # bin-integrated values too
    tb = 2.0
    np.testing.assert_allclose(kernel_derivatives(t, sigma_ps, alpha_per_ps, time_bin_ps=tb)[0],
                               sss_kernel(t, sigma_ps, alpha_per_ps, time_bin_ps=tb), rtol=1e-13, atol=1e-300)
