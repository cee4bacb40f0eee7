"""Fixed numbers of the ConvSCD solver, each with its unit and the reason for its value.

Every module of :mod:`decomposition` takes these from here; none keeps a private copy.
Numbers a user may reasonably change are options (:mod:`decomposition.options`), not
constants.

Atom families
-------------
Codes of the ``fam`` slot arrays (int8) shared by the solver, the compiled kernels and the
component bookkeeping.
"""
from __future__ import annotations

import math

__all__ = [
    "FAM_NONE",
    "FAM_GAUSS",
    "FAM_SSS",
    "SIGNIFICANCE_LAG_BINS",
    "GAUSS_SUPPORT_SIGMA",
    "CORR_SUPPORT_SIGMA",
    "DICT_SUPPORT_SIGMA",
    "DICT_PRE_SIGMA",
    "TAIL_SIGMA",
    "NEAR_SIGMA",
    "ONSET_TIE_SIGMA",
    "EARLY_DIRECT_STARTS_SIGMA",
    "EARLY_DIRECT_NEAR_SIGMA",
    "AMP_MAX",
    "RESTART_FACTOR",
    "RESTART_POOL_FRACTION",
    "MAD_TO_SIGMA",
    "SIGNAL_REGION_FRACTION",
    "MIN_NOISE_SAMPLES",
    "SPIKE_FALSE_ALARM",
    "POISSON_VARIANCE_FLOOR",
    "POISSON_FIT_FLOOR",
    "POOR_FIT_DIRECT_SIGMA",
    "SEARCH_NEAR_DIRECT_CHI2",
    "WEAK_DIRECT_FRACTION",
    "WEAK_DIRECT_ONSET_SIGMA",
    "UNSEEN_DIRECT_LEAD_SIGMA",
    "BRIGHT_ECHO_RATIO",
    "PRE_DIRECT_LEVEL",
    "PRE_DIRECT_SIGMA",
    "POISSON_REFITS",
    "PEARSON_MIN_COUNTS",
    "BOUND_TOL",
    "SSS_SLOT",
    "SEARCH_EDGE_LEVEL",
    "SEARCH_PEAK_LEVEL",
    "SEARCH_IR_GAP_SIGMA",
    "SEARCH_EDGE_GAP_SIGMA",
    "PRUNE_GAP_SIGMA",
    "PRUNE_ONSET_SIGMA",
    "GROW_EXCLUDE_SIGMA",
    "SWAP_MODE_GAP_SIGMA",
    "SWAP_MIN_ALPHA_SIGMA",
    "SEARCH_DEFAULT_SIGMA_PS",
    "SEARCH_DEFAULT_ALPHA_PER_PS",
    "RISE_10_50_SIGMA",
    "NARROW_FRACTION",
    "BACKGROUND_START_QUANTILE",
    "BACKGROUND_CLIP_SIGMA",
    "BACKGROUND_ITERATIONS",
    "BACKGROUND_COUNT_WINDOW_BINS",
    "OFF_WINDOW_MASS",
    "OFF_WINDOW_EDGE_SIGMA",
    "RESOLVED_SIGMA",
    "SSS_RESOLVED_CHI2_FACTOR",
    "WHITE_LAG_RATIO",
]

#: empty slot
FAM_NONE = 0
#: unit-peak Gaussian g(t; sigma): the direct reflection and the inter-reflections
FAM_GAUSS = 1
#: unit-peak sss kernel h(t; sigma, alpha): subsurface scattering
FAM_SSS = 2

#: Gaussian support in the compiled per-pixel kernels, in sigma (dimensionless).  Beyond
#: +-6 sigma a unit-peak Gaussian is below exp(-18) ~ 1.5e-8 of its peak: under the float32
#: resolution of a cube's samples (2^-24 ~ 6e-8) and five decades under the lowest noise the
#: benchmarks use; the sss kernel's non-recursive part (its rising edge) has the same support.
#: (At 8 sigma, with the sss tail from 6 sqrt 2 sigma on, the refinement took 10-15 % more
#: time for the same fidelity to four decimals.)
GAUSS_SUPPORT_SIGMA = 6.0

#: Gaussian support of the own-width correlations of the pick (:mod:`decomposition.kernels.pickcorr`),
#: in sigma: beyond +-8 sigma a unit Gaussian is below exp(-32) ~ 1e-14, under float64
#: rounding of the sums, so the correlations are the dense sums' (their tests hold them to
#: 1e-10); the pick compares correlations of atoms against each other, and is not where the
#: time goes.
CORR_SUPPORT_SIGMA = 8.0

#: Half-width of the sampled dictionary kernels (FFT pick) and the shortest window the
#: solver accepts, in sigma (dimensionless).  exp(-18) ~ 1.5e-8 of the peak beyond 6 sigma:
#: far below any noise, and only the coarse pick uses these kernels (the refinement
#: evaluates atoms on :data:`GAUSS_SUPPORT_SIGMA`).  Also the own-width pick's sampling
#: half-width H, which sets the kernels' peak normalisation.
DICT_SUPPORT_SIGMA = 6.0

#: Atoms may start this many widths of the largest sigma before the window (in sigma):
#: a component partly before the first bin is still representable.
DICT_PRE_SIGMA = 3.0

#: Past alpha sigma^2 + this many sigma after an sss onset the kernel is taken as its pure
#: exponential tail (erfc(u) as 2) and continued by its one-pole recursion: u = -4 in units
#: of sqrt 2, where erfc(-u) = erfc(4) ~ 1.5e-8, a relative error of 8e-9, under the float32
#: resolution of a cube's samples as for :data:`GAUSS_SUPPORT_SIGMA`.
TAIL_SIGMA = 4.0 * math.sqrt(2.0)

#: An sss onset less than this many PSF widths before the earliest Gaussian is tied to it
#: (``sss_after_direct``): refined as direct delay + gap with gap >= 0.
NEAR_SIGMA = 3.0

#: The response path's standard errors: an sss onset within this many response widths
#: (Gaussian-equivalent) after the direct is read as tied to it.  There the onset's derivative,
#: alpha s - c, lies all but in the span of the sss and the direct atoms themselves, and the
#: Fisher information is singular (condition over 1e14 for gaps up to 0.02 widths: 58 of 400
#: count pixels at 400 photons per peak, tailed response, once the Poisson fit approached the
#: bound instead of being projected onto it).
ONSET_TIE_SIGMA = 0.05

#: The response path: a direct fitted before the window is refitted from the window's first sample
#: less these many response widths (Gaussian-equivalent), the lowest deviance kept
#: (:func:`decomposition.response.grow.grow_response`, step 0b).
EARLY_DIRECT_STARTS_SIGMA = (0.0, 1.0, 2.0)
#: ... a start within this many widths of the fitted direct is not refitted (the same answer).
EARLY_DIRECT_NEAR_SIGMA = 0.5

#: The response path, count data: an sss whose onset lies more than this many response widths
#: (Gaussian-equivalent) after its direct is refitted with the onset started at the direct, the
#: lower deviance kept (:func:`decomposition.response.grow.grow_response`, step 0c).  A late onset
#: is a local optimum of the fit at few counts: the direct moves later to fill the gap.
ONSET_RESTART_SIGMA = 1.0

#: Largest component peak the pick accepts, in units of the pixel's largest sample: a
#: coefficient far above the data is a degenerate (near-zero-norm) coordinate, not light.
AMP_MAX = 20.0

#: POOR_FIT's second test (:mod:`decomposition.stages.quality`) weighs the residual over the direct's
#: delay +- this many fitted widths (plus one bin) (dimensionless).
POOR_FIT_DIRECT_SIGMA = 3.0

#: The search's near-direct doubt test (:func:`decomposition.stages.search.search_block`): a pixel
#: is in doubt when its data term per sample over the direct's samples (as POOR_FIT_DIRECT_SIGMA)
#: exceeds this many noise variances (dimensionless).  The noise there is the pixel's one estimate,
#: and photon noise is largest at the direct's peak.
SEARCH_NEAR_DIRECT_CHI2 = 3.0

#: POOR_FIT for light before the direct (photon counts,
#: :func:`decomposition.stages.quality.light_before_direct`): the direct's leading edge is where its
#: response rises from PRE_DIRECT_LEVEL of its peak (dimensionless), and the counts before it must
#: exceed the model's by PRE_DIRECT_SIGMA on the Poisson law (sigma, one-sided).
PRE_DIRECT_LEVEL = 1e-3
PRE_DIRECT_SIGMA = 5.0

#: The response path reports no direct where its direct explains nothing, lies where no sample sees
#: it and more than this many Gaussian-equivalent widths before the light it would lead (the sss
#: onset, else the first sample): nothing in the data places it (dimensionless;
#: ``response_grow._unseen_direct``).
UNSEEN_DIRECT_LEAD_SIGMA = 8.0

#: AMBIGUOUS for a weak direct just before a much larger onset
#: (:func:`decomposition.stages.quality.weak_direct`): the direct's peak below this fraction of the
#: other light's (dimensionless), an sss onset or inter-reflection within WEAK_DIRECT_ONSET_SIGMA
#: direct widths (plus one bin) after it.
WEAK_DIRECT_FRACTION = 0.15
WEAK_DIRECT_ONSET_SIGMA = 4.0
#: AMBIGUOUS for an inter-reflection brighter than the direct by more than this ratio of their peak
#: heights (:func:`decomposition.stages.quality.bright_echo`; dimensionless).
BRIGHT_ECHO_RATIO = 1.5

#: Restart threshold (dimensionless ratio).  Used twice, for the same reason: a fit whose
#: misfit exceeds its noise expectation by half again is not explained by the noise.
#: (1) the multi-start: where the Gaussian-first start leaves a data term above
#: RESTART_FACTOR x its expectation 1/2 n s^2, the unrestricted start is run as well;
#: (2) the second noise pass: where the noise estimated at the signal exceeds
#: RESTART_FACTOR x the whole-profile estimate (photon noise), the block is solved again
#: with the larger sparsity weight.
RESTART_FACTOR = 1.5
#: The second noise pass on float data runs only where at least this fraction of the call's
#: live pixels have their noise at the signal above RESTART_FACTOR x their noise: shot noise is
#: a detector's, seen in most pixels (photon noise, paper scenes at NSR 0.055: 94 %); where a
#: few pixels show it (white and pink noise: 9 % at 2 ps bins, 17 % at 4 ps) it is their misfit,
#: and a pass with the noise raised to it leaves them with fewer components than the data
#: hold (a 1.9 ps direct and an inter-reflection fitted as one Gaussian 8 ps wide, its noise
#: raised to 0.16 of the peak).  Count data keep the pass per pixel.
RESTART_POOL_FRACTION = 0.5

#: Gaussian noise sigma per median absolute value of its second differences, divided
#: further by sqrt(6) (the variance of a white second difference is 6 s^2):
#: 1 / Phi^-1(3/4) = 1.4826.
MAD_TO_SIGMA = 1.4826

#: The noise "where the signal is" is estimated over the samples where the fitted model
#: exceeds this fraction of its peak (dimensionless).
SIGNAL_REGION_FRACTION = 0.1

#: Fewer usable second differences than this give no noise estimate at the signal (a few
#: samples around a narrow peak measure its curvature, not the noise).
MIN_NOISE_SAMPLES = 12

#: Count data (``noise="poisson"``): the probability that a spike-free profile has any sample
#: flagged as a spike (dimensionless, per profile).  The per-sample test threshold is the
#: normal quantile of 1 - SPIKE_FALSE_ALARM / (L - 2) in the variance-stabilised domain (about
#: 6 standard deviations at L = 512): a million spike-free profiles give about one flag.
SPIKE_FALSE_ALARM = 1e-6

#: Count data: the Poisson variance of a sample is its model value, floored at this many
#: counts (the weight 1 / variance stays finite where the model is ~0, far from the signal).
#: A larger floor moves the fit away from the maximum-likelihood one: on 1500 FLIM-like pixels
#: at 100 photons the median lifetime bias was -2.3 % with 0.5 counts, -1.9 % with 0.02 and
#: -1.0 % with 0.005 (three refits), each +-0.4 %; 0.02 keeps stray counts far in a kernel's
#: tail from pulling the fit (weight at most 50).
POISSON_VARIANCE_FLOOR = 0.02

#: Count data, the response path's refinement (:class:`decomposition.response.refine.CountData`):
#: the floor (counts) of the variance in its weights and of the model in its objective, the Poisson
#: deviance; one floor for both, so that each step is Fisher scoring of the objective it is judged
#: by and the fixed point is the maximum likelihood of that objective.  With the weights at
#: POISSON_VARIANCE_FLOOR and the deviance read at 1e-6 the steps disagreed with the objective where
#: a count sits on a model below 0.02: they stalled 1-4 deviance units above the optimum, lifetimes
#: short.  The floor trades efficiency where the model is complete against robustness to light it
#: lacks (an echo the counts hide pulls an sss tail). The significance tests keep
#: POISSON_VARIANCE_FLOOR.
POISSON_FIT_FLOOR = 1e-3

#: Count data: reweighted refits, each with the weights 1 / max(model, floor) of the previous
#: model (iteratively reweighted least squares: its fixed point is the Poisson maximum-likelihood
#: fit; two refits from the detection's least-squares model reach it to well within the
#: standard errors).
POISSON_REFITS = 2

#: Count data: the noise scale of a fit is measured on the samples whose model is at least
#: this many counts (there the Pearson residual (y - mu)^2 / mu of Poisson counts averages 1
#: within a few per cent; below, the variance floor and the skew of the law take over).
PEARSON_MIN_COUNTS = 5.0

#: A refined log sigma or log alpha within this of its bound (in log units, i.e. relative
#: 1e-9) is at the bound (AT_BOUND flag): the projection puts it exactly there, rounding
#: a hair inside.
BOUND_TOL = 1e-9

#: Slot layout of the refinement and the Fisher information (:mod:`decomposition.model.refine`):
#: slot 0 the direct reflection, this one the sss component, 2.. the inter-reflections.
SSS_SLOT = 1

# --- the search stage (:mod:`decomposition.stages.search`) -------------------------------------------

#: the leading edge of a profile: its first sample at this fraction of the smoothed peak
SEARCH_EDGE_LEVEL = 0.1
#: a significant local maximum of the smoothed profile: at least this fraction of its peak
SEARCH_PEAK_LEVEL = 0.2
#: a detected Gaussian more than this many PSF widths after a start's direct is kept as its
#: inter-reflection; closer ones are dropped (the start's direct replaces them)
SEARCH_IR_GAP_SIGMA = 3.0
#: the ``edge`` start's sss onset, this many (start) PSF widths after its direct.  An onset at the
#: direct (0) lost the sss-hump pixels: from there the polish slides both atoms onto the hump (a
#: wide shared width, the direct tens of ps late).
SEARCH_EDGE_GAP_SIGMA = 1.5
#: the search's ``wide`` start: the peak start at the detected direct's own width, where that is
#: more than this many times the default start width (SEARCH_DEFAULT_SIGMA_PS).  A wide direct (8-10
#: ps) with a small sss lost it to two or three Gaussians from every start at the default width.
SEARCH_WIDE_FACTOR = 1.5
#: the search's ``rise`` start: the grid's narrowest width, but at least this many bins.  A direct
#: narrower than half a bin falls on one point sample, so a start there polishes a width the data
#: hardly see.
SEARCH_RISE_MIN_BINS = 0.5
#: the backward step (:mod:`decomposition.stages.prune`) tries to drop a Gaussian closer than this
#: many PSF widths after the direct, where the pixel has an sss.
PRUNE_GAP_SIGMA = 6.0
#: its second start without that Gaussian moves the sss onset to this many widths after the
#: direct (0.5 and 1 measured alike)
PRUNE_ONSET_SIGMA = 1.0
#: the forward step (:mod:`decomposition.stages.grow`) places its Gaussian at the largest residual
#: more than this many widths from every Gaussian of the pixel (2 and 3 measured alike)
GROW_EXCLUDE_SIGMA = 2.0
#: the forward step's sss swap (decomposition.stages.grow.swap_block) is tried where the sss peaks
#: more than this many PSF widths after the direct: the pixels whose sss may have taken in a
#: Gaussian.
SWAP_MODE_GAP_SIGMA = 3.0
#: ... and where the sss decays fast enough against the PSF for its hump to pass for a Gaussian:
#: alpha * sigma at least this.
SWAP_MIN_ALPHA_SIGMA = 0.09
#: the response path's echo trial (:mod:`decomposition.response.grow`) is refitted only where
#: the matched-filter estimate of its chi2 at the trial position is at least this fraction of
#: ``significance_chi2`` (the deviance of the refit decides; the estimate only saves the refits
#: of pixels with nothing to find)
GROW_TRIAL_FRACTION = 0.5
#: an echo is a bump of the PSF's width: the forward step of count data tries one only where
#: the atom gains more there than one this many times wider at the same place (a broad excess
#: -- an sss tail the fit lacks, an offset it does not model -- is no echo)
GROW_BROAD_FACTOR = 3.0
#: width (ps) and attenuation (1/ps) of a start where the detection found none
SEARCH_DEFAULT_SIGMA_PS = 3.0
SEARCH_DEFAULT_ALPHA_PER_PS = 0.03
#: a Gaussian rises from 10 % to 50 % of its peak in sqrt(2 ln 10) - sqrt(2 ln 2) = 0.969 sigma
RISE_10_50_SIGMA = math.sqrt(2 * math.log(10)) - math.sqrt(2 * math.log(2))
#: the search's narrow start is tried where the width from the rise is below this fraction
#: of the detected width
NARROW_FRACTION = 0.7

# --- the background family and the window (:mod:`decomposition.stages.background`, label) ---------

#: the first background estimate starts at this quantile of a profile's samples: below the
#: median (components only add light), above the far noise tail (-0.67 sigma of pure noise)
BACKGROUND_START_QUANTILE = 0.25
#: samples within this many noise sigmas of the current estimate are at the noise level
BACKGROUND_CLIP_SIGMA = 3.0
#: clipped-mean iterations of the estimate (each moves it to the mean of the samples at the
#: noise level; five settle it to well below the noise on the paper's windows)
BACKGROUND_ITERATIONS = 5
#: count data: a sample is at the background level when the mean count of this many bins
#: centred on it is (a single count cannot tell a faint component from the background: below
#: one count per bin the Poisson noise of one sample is larger than either)
BACKGROUND_COUNT_WINDOW_BINS = 16
#: a component whose area outside the window is more than this fraction of its total area
#: runs off the window's edge (OFF_WINDOW flag); a Gaussian centred on the first or the last
#: bin has half of it outside
OFF_WINDOW_MASS = 0.2
#: a peaked component (a Gaussian, a shifted response) whose delay lies within this many of its
#: widths of the window's edge runs off it too: its rise (or fall) is cut and its delay read
#: off one side (the OFF_WINDOW flag; dimensionless)
OFF_WINDOW_EDGE_SIGMA = 2.0
#: an atom below the relative threshold may be kept on its significance alone only when its
#: delay is more than this many PSF widths from that of every larger atom of its pixel (the
#: inter-reflection gap of the search stage): a faint atom closer than that is the model's
#: correction of the larger one's shape (seen on noiseless data), not a component
RESOLVED_SIGMA = 3.0
#: a faint atom within RESOLVED_SIGMA widths of a larger sss onset, but resolved from every
#: larger peaked atom, is kept on its significance when its energy is at least this many times
#: the significance bar (``significance_chi2`` noise variances): an sss rises over several
#: widths, and an echo on its rise (1-3 % of the direct, e.g. 2,100 noise variances at NSR
#: 0.001) is a component, while a faint atom there can also be the sss's shape correction
#: (52 noise variances on a scene whose model is exact: tests/test_grow.py's late-peaking sss).
#: Before the detection's polish every larger atom hides a faint one alike (``None``).
SSS_RESOLVED_CHI2_FACTOR = 4.0
#: the in-window significance test weighs an atom's energy with the noise across this many samples
#: (at most a quarter of the window) where that is above the sample-to-sample noise
#: (decomposition.noise.lagged_noise_sigma): correlated noise makes component-sized bumps that
#: second differences do not see. On the profile the lagged estimate also holds the components'
#: slopes (under white noise at NSR 0.055 1.45x the true sigma, median), which WHITE_LAG_RATIO
#: corrects after the search.
SIGNIFICANCE_LAG_BINS = 64
#: after the search the lagged noise is measured on the fit's residual, and replaces the profile's
#: where it is at most this many times the sample-to-sample noise (white at the component scale;
#: decomposition.stages.candidates.residual_significance_noise).
WHITE_LAG_RATIO = 1.35

# Noise that follows the signal (decomposition.stages.candidates.signal_weights): a pixel's fitted
# variance law floor + gain * model is used where the gain exceeds this many standard errors ...
SIGNAL_NOISE_Z = 5.0
# ... and the variance at the model's peak exceeds the floor by this factor (2x in all) ...
SIGNAL_NOISE_PEAK_RATIO = 1.0
# ... with the floor kept at least this fraction of the peak's variance ...
SIGNAL_NOISE_FLOOR_FRACTION = 0.01
# ... and only where the gain read at a lag of 2 samples is below this multiple of the gain at 1:
# independent noise gives the same law at both lags, a misfit of a component (structure wider than a
# sample, at a noise too low to hide it) about 4x.
SIGNAL_NOISE_LAG_RATIO = 1.5
# The verdict pooled over the pixels of one call: a detector's noise law is the detector's, not a
# pixel's.  Where at least this fraction of the live pixels (and at least SIGNAL_NOISE_POOL_MIN of
# them) pass the tests above, every pixel whose fitted gain is positive is weighted by its own law,
# also where its gain alone is not significant (a few samples under a narrow direct at 4 ps bins) or
# its lag test read a misfit as structure (the misfit the search is there to repair).
SIGNAL_NOISE_POOL_FRACTION = 0.5
SIGNAL_NOISE_POOL_MIN = 16
# ... or where the call's own statistics say so: the median over its pixels of their gain's
# significance at least this and the median of their gain read at a lag of two samples over the gain
# below SIGNAL_NOISE_LAG_RATIO.  Read noise can hide each pixel's gain, not the call's.
SIGNAL_NOISE_POOL_Z = 3.0
# The in-window significance test of an atom under weights (decomposition.model.components.
# window_measures): a sample's weight counts at most this much, i.e. the noise where the atom lies
# at most half the pixel's.  Under shot noise a weak inter-reflection after the direct lies where
# the noise is several times lower than at the peak and becomes significant; uncapped, weights
# fitted to a misfit instead (sub-bin PSFs at NSR 0.001, pink noise) kept spurious atoms in quiet
# parts.
SIGNIFICANCE_WEIGHT_CAP = 4.0
# The second pass (decomposition.stages.rescue) also takes the pixels whose data term, in the noise the
# first pass weighed them with (whitened by the call's spectrum where its noise is correlated),
# lies more than this many standard deviations of a chi-square of n_fit degrees of freedom above
# its expectation, n_fit + z sqrt(2 n_fit) (1.19 n_fit for 512 samples): a misfit the POOR_FIT
# bar (3 noise sigmas of residual RMS, a data term 9 times its expectation) forgives.
RESCUE_MISFIT_Z = 3.0
