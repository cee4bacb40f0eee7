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
:data:`FLAG_HELP` gives each flag one line for a user: what it means and what to do about it
(the report's summary prints it for every flag that occurs).
"""
from __future__ import annotations

import enum

import numpy as np

__all__ = ["Flag", "FLAG_NAMES", "FLAG_HELP", "FLAG_DTYPE", "flag_names", "mark", "EMPTY", "SATURATED", "POOR_FIT", "SPIKE",
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

#: flag -> one line for a user: what the flag means for the pixel, then what can be done about it
FLAG_HELP = {
    Flag.EMPTY: "nothing above the noise (a dark or all-zero pixel), so no component: expected off the "
                "object; elsewhere check the exposure, gain and alignment",
    Flag.SATURATED: "samples reached the saturation level; the fit took them as at least that level: "
                    "lower the exposure or the gain and capture again",
    Flag.POOR_FIT: "the residual is above poor_fit (3) times the noise: the model misses light the data hold; "
                   "a constant offset (--components ...,b), a response that is not a Gaussian (--irf, "
                   "streaklab calibrate-irf) or pulses cut by the window's edge are the usual causes",
    Flag.SPIKE: "single-sample spikes (a hot pixel or a cosmic ray) were left out of the fit: usually "
                "harmless; a pixel flagged in every capture is a hot pixel",
    Flag.NONFINITE: "NaN/inf samples: the pixel was not decomposed; fill the gap in the input (a line "
                    "missing from a partial reconstruction: finish the capture with --resume)",
    Flag.MAX_ITER: "the solver stopped at max_iter before it converged; the answer may be unfinished: "
                   "raise it (--option max_iter=N)",
    Flag.AT_BOUND: "a fitted width (sigma) or sss decay (alpha) ended at its allowed bound: widen the grid "
                   "(--option sigma_range_ps=[LO,HI] or alpha_range_per_ps=[LO,HI]), or measure the "
                   "response (--irf) if it is not a Gaussian",
    Flag.TRUNCATED: "more inter-reflections were found than are kept; the later ones were dropped: raise "
                    "--max-interreflections to keep them",
    Flag.AMBIGUOUS: "the data do not determine how the light splits among the components (another split fits "
                    "about as well, or a weak direct sits just before a much larger return): treat the "
                    "split as uncertain; less noise (longer exposure, more frames) narrows it",
    Flag.WIDE_PSF: "the fitted direct is wider than the grid's sigma_range_ps, typically an sss hump taken for "
                   "a broad direct: trust its direct/sss split less; if the response is that wide, use --irf",
    Flag.OFF_WINDOW: "a component runs off the edge of the time window; its parameters are extrapolated from "
                     "the part inside: move the light into the window (sync.trigger_delay_ps) and capture again",
}

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
