"""Decomposition of transient time profiles into direct, inter-reflection and sss components."""
from .model import (  # noqa: F401
    gaussian_kernel,
    render_components,
    render_profile,
    sss_kernel,
    time_axis_ps,
)
