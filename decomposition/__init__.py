"""Decomposition of transient time profiles into direct, inter-reflection and sss components.

The package, bottom up (``tests/test_layers.py`` holds the table of who may import whom):

``constants``, ``flags``, ``masks``, ``options``
    numbers, flag bits, sample masks and the options every layer shares
``kernels/``
    the compiled (numba) kernels
``noise``
    noise estimates and deviances
``model/``
    the parametric model the stages share: slot states, atoms of any response, components,
    refines, Fisher errors, fidelity
``methods/``
    ConvSCD and the GradBM baseline
``stages/``
    the stages :func:`decompose` runs
``response/``
    the stages' implementations for a measured instrument response (``decompose(irf=...)``)
``api``
    :func:`decompose` and :class:`DecompositionResult`; ``warmup`` loads the kernels before timing
``image/``
    :func:`decompose_image`: one image as one problem (shared parameters, spatial coupling)
``store/``
    the chunked store pipeline above the solver: cube store in, result store out
``evaluation/``
    synthetic scenes, reference fits and accuracy metrics for benchmarks and tests (the solver
    never imports it)
``phasor``
    phasor coordinates (g, s) of binned decays for a phasor plot (NumPy alone; nothing imports it)

:func:`decompose` and :class:`DecompositionResult` load the solver on first use, so importing a
lower subpackage alone (the kernels, the evaluation code) does not load the stages.
"""
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

_API = ("DecompositionResult", "decompose")
_IMAGE = ("decompose_image",)


def __getattr__(name):
    if name in _API:
        from . import api  # the solver, loaded on first use (see the module docstring)

        return getattr(api, name)
    if name in _IMAGE:
        from . import image

        return getattr(image, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API) | set(_IMAGE))
