"""Per-pixel quality flags of a decomposition (``DecompositionResult.flags``, a uint16 bitmask).

=========== ===== ==============================================================
EMPTY         1   no component: all-zero pixel or nothing above the noise
SATURATED     2   samples at the saturation level; excluded from the fit
POOR_FIT      4   residual RMS > ``poor_fit`` x estimated noise, over the window or
                  over the direct's own samples: the data are outside what the
                  model explains (offset, unmodelled shape, a direct of the wrong
                  width, ...)
SPIKE         8   single-sample spike(s) (hot pixel / cosmic ray) excluded
NONFINITE    16   NaN/inf samples (``nan_policy="omit"``); pixel not decomposed
MAX_ITER     32   the solver hit ``max_iter`` before it converged
AT_BOUND     64   a refined sigma or alpha ended at its allowed bound
TRUNCATED   128   more inter-reflections found than ``max_reflections``
AMBIGUOUS   512   the data do not determine the split: two starts of the search
                  (:mod:`decomposition.stages.search`) with materially different splits
                  reach objectives within the noise of each other; or the direct
                  is weak (< 15 % of the peak) just before a much larger sss or
                  inter-reflection onset (:func:`decomposition.stages.quality.weak_direct`);
                  or an inter-reflection is more than 1.5x as high as the direct
                  (:func:`decomposition.stages.quality.bright_echo`);
                  or, with a measured response, the pixel has an sss and no
                  direct, or a direct not significant in its own fit
                  (:mod:`decomposition.response.grow`)
WIDE_PSF   1024   the fitted PSF width is above the kernel grid's ``sigma_range_ps``
                  (an sss hump taken for a broad direct, typically)
OFF_WINDOW 2048   a kept component runs off the window's edge: a Gaussian (or a
                  shifted response) centred within OFF_WINDOW_EDGE_SIGMA widths of
                  the window's edge or beyond it, or more than
                  OFF_WINDOW_MASS of a component's area outside the window
                  (:func:`decomposition.model.components.off_window`); its parameters
                  are extrapolated, only its in-window part was judged
=========== ===== ==============================================================

Bit 256 is the result store's own ``OUT_OF_RANGE`` (:mod:`decomposition.store.resultstore`).

The bit values are part of the result-store format: stores written by any version read the
same.  :data:`FLAG_NAMES` (bit -> name) is derived from :class:`Flag`, never kept by hand.
"""
from __future__ import annotations

import enum

import numpy as np

__all__ = ["Flag", "FLAG_NAMES", "FLAG_DTYPE", "flag_names", "mark", "EMPTY", "SATURATED", "POOR_FIT", "SPIKE",
           "NONFINITE", "MAX_ITER", "AT_BOUND", "TRUNCATED", "AMBIGUOUS", "WIDE_PSF", "OFF_WINDOW", "DATA_FLAGS"]

#: dtype of a flags array
FLAG_DTYPE = np.uint16


class Flag(enum.IntFlag):
    """Quality bits of one pixel (see the module docstring)."""

    EMPTY = 1
    SATURATED = 2
    POOR_FIT = 4
    SPIKE = 8
    NONFINITE = 16
    MAX_ITER = 32
    AT_BOUND = 64
    TRUNCATED = 128
    AMBIGUOUS = 512
    WIDE_PSF = 1024
    OFF_WINDOW = 2048


#: bit value -> flag name, in bit order
FLAG_NAMES = {int(f): f.name for f in Flag}

EMPTY = Flag.EMPTY
SATURATED = Flag.SATURATED
POOR_FIT = Flag.POOR_FIT
SPIKE = Flag.SPIKE
NONFINITE = Flag.NONFINITE
MAX_ITER = Flag.MAX_ITER
AT_BOUND = Flag.AT_BOUND
TRUNCATED = Flag.TRUNCATED
AMBIGUOUS = Flag.AMBIGUOUS
WIDE_PSF = Flag.WIDE_PSF
OFF_WINDOW = Flag.OFF_WINDOW

#: the bits that describe the samples themselves, not a fit of them
DATA_FLAGS = FLAG_DTYPE(SATURATED | SPIKE | NONFINITE)


def flag_names(bits) -> list[str]:
    """Names of the flags set in one bitmask value, in bit order."""
    v = int(bits)
    return [name for bit, name in FLAG_NAMES.items() if v & bit]


def mark(flags: np.ndarray, where, flag: Flag) -> None:
    """Set ``flag`` in ``flags[where]`` in place (``flags``: a :data:`FLAG_DTYPE` array)."""
    flags[where] |= FLAG_DTYPE(flag)
