"""Decomposition of transient time profiles into direct, inter-reflection and sss components."""
from core.model import (  # noqa: F401
    gaussian_kernel,
    render_components,
    render_profile,
    sss_kernel,
    time_axis_ps,
)
from .flags import (  # noqa: F401
    AMBIGUOUS,
    AT_BOUND,
    EMPTY,
    FLAG_NAMES,
    MAX_ITER,
    NONFINITE,
    OFF_WINDOW,
    POOR_FIT,
    SATURATED,
    SPIKE,
    TRUNCATED,
    WIDE_PSF,
    Flag,
    flag_names,
)
from .api import DecompositionResult, decompose  # noqa: F401
