"""Public entry point: ``decompose(profiles, time_bin_ps, method=...)``.

``decompose()`` is the method as a flat sequence of stages, each a function with a typed
input and output in a module of its own:

1. prepare the samples (:mod:`decomposition.stages.prepare`): validation, scaling, masks, noise;
2. detect the components by sparse coding (:mod:`decomposition.stages.detect`;
   :mod:`decomposition.methods.convscd` is the solver, :mod:`decomposition.methods.gradbm` the baseline);
   then, for the pixels whose answer is in doubt, structured alternative starts kept by a
   penalised objective (:mod:`decomposition.stages.search`);
3. refine them off the grid, optionally (:mod:`decomposition.stages.refit`);
   for count data, the atoms polished with Poisson weights (:mod:`decomposition.stages.countpolish`);
4. label them direct / inter-reflections / sss (:mod:`decomposition.stages.label`);
5. render the fit and flag its quality (:mod:`decomposition.stages.quality`, :mod:`decomposition.flags`).

Options are validated once, into the frozen dataclasses of :mod:`decomposition.options`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field

import numpy as np

from .methods import convscd as cs
from .stages.countpolish import polish_counts
from .stages.detect import detect_components, detect_gradbm
from .flags import (AMBIGUOUS, AT_BOUND, DATA_FLAGS, EMPTY, FLAG_NAMES, MAX_ITER, NONFINITE, POOR_FIT,  # noqa: F401
                    SATURATED, OFF_WINDOW, SPIKE, TRUNCATED, WIDE_PSF, flag_names, mark)
from .stages.label import final_state, label_components, params_at_bound
from core.model import BACKGROUND_KEY, DIRECT_KEYS, IR_KEYS, SSS_KEYS
from .options import METHODS, options_from_mapping, parse_components, parse_nan_policy
from .stages.prepare import prepare_samples, time_axis
from .stages.quality import Fit, assess_fit
from .stages.refit import clear_unlit, component_errors, refine_components
from .stages.candidates import correlated_noise_spectrum, residual_significance_noise, signal_weights
from .stages.grow import grow_components, grow_counts, swap_components
from .stages.prune import prune_components
from .stages.search import STAGE_STARTS, search_components
from .model.slots import shape_bounds
from .constants import RESCUE_MISFIT_Z
from .stages.rescue import RESCUE_OPTIONS, data_term, misfit_beyond_noise, penalised_misfit, rescue_rows, take_rescued
from .response.resolve import resolve_response, response_record, spike_neighbour_ratio
from .response.path import decompose_with_response

__all__ = [
    "decompose",
    "DecompositionResult",
    "parse_components",
    "EMPTY",
    "SATURATED",
    "POOR_FIT",
    "SPIKE",
    "NONFINITE",
    "MAX_ITER",
    "AT_BOUND",
    "TRUNCATED",
    "AMBIGUOUS",
    "WIDE_PSF",
    "OFF_WINDOW",
    "FLAG_NAMES",
]


@dataclass
class DecompositionResult:
    """Decomposition of profiles of shape (..., L).

    Attributes
    ----------
    direct : ndarray (..., L)              rendered direct component
    sss : ndarray (..., L)                 rendered subsurface-scattering component
    interreflections : ndarray (..., R, L) r2, r3, ... in order of delay; zeros where absent
    params : dict of ndarray               model parameters, NaN where absent
                                           (keys of ``core.model``)
    residual : ndarray (..., L)            profiles minus the sum of all components
    flags : ndarray (...,) uint16          quality bitmask (:class:`decomposition.flags.Flag`)
    info : dict                            method, all options, iteration counts
    """

    direct: np.ndarray
    sss: np.ndarray
    interreflections: np.ndarray
    params: dict
    residual: np.ndarray
    flags: np.ndarray
    info: dict = field(default_factory=dict)

    def flag_names(self, index=()) -> list[str]:
        """Names of the flags set for one pixel (``index`` into the leading shape)."""
        return flag_names(self.flags[index])


def decompose(profiles, time_bin_ps: float = 2.0, method: str = "convscd", *, t0_ps: float | None = None,
              components=("d", "r", "s"), nan_policy: str = "raise", saturation_level: float | None = None,
              irf=None, **options) -> DecompositionResult:
    """Decompose time profiles into direct, inter-reflection and sss components.

    Parameters
    ----------
    profiles : array_like (..., L), any real dtype (uint16 camera data included)
        Time profiles; the last axis is time.
    time_bin_ps : float
        Bin width T in ps (> 0).
    method : {"convscd", "gradbm"}
    t0_ps : float, optional
        Time of the first bin (default ``time_bin_ps``: the paper's t = T..LT).
    components : str or sequence
        Families to look for: "d" direct, "r" inter-reflections, "s" sss,
        "b" background (e.g. "d,s" or "d,r,s,b").  Families left out are neither built
        into the dictionary nor searched; without "r" at most one Gaussian per pixel.
        "b", a constant offset per pixel (``params["background"]``, units of the
        profiles): estimated robustly from the samples at the noise level and subtracted
        before the sparse coding (:func:`decomposition.stages.background.estimate_background`),
        then fitted jointly with the amplitudes in the refinement, which always runs with
        it; kept where significant (its likelihood-ratio statistic at least
        ``background_chi2``), else reported as exactly 0.0 and the pixel refitted
        without it.  NaN where the pixel is not decomposed; without "b" there is no
        ``background`` key and nothing changes.  ConvSCD only.
    sigma_range_ps, n_sigma, alpha_range_per_ps, n_alpha
        Reference kernel grid.  The paper's setting (sigma 1-10 ps, alpha
        0.01-0.05 /ps, 500 samples each) is the default; it is searched
        coarse-to-fine, never densely.
    coarse_sigma, coarse_sss_sigma, coarse_alpha : int
        Grid values correlated in the detection step (Gaussian sigmas; sss
        sigmas x alphas).  Small values are fast; refinement does the rest.
    off_grid : bool
        Keep continuous refined parameters (True) or snap them to the
        reference grid with integer-bin delays (False, the paper's setting).
    max_components : int
        Atoms per pixel in the sparse-coding step.
    max_reflections : int
        R, the number of inter-reflection slots in the output.
    max_iter : int, optional
        Outer (pick + refine) iterations per pixel; default ``max_components + 2``.
    n_lm, n_polish : int
        Levenberg-Marquardt iterations after each pick / in the final polish.
    lm_tol : float
        A pixel's refinement stops when a step gains less than lm_tol x its
        objective per sample.
    sparsity, eps_rel, noise_floor : float
        Sparsity weight mu = sparsity * s^2 and eps = eps_rel * s, with s the
        per-pixel noise estimate floored at ``noise_floor`` x the pixel's peak.
    rel_threshold : float
        The paper's 5% threshold: an atom whose peak height inside the window is at least
        this fraction of the pixel's largest in-window peak is kept.
    significance_chi2 : float
        An atom below the relative threshold is still kept when it is significant against
        the noise where it lies: its in-window energy sum(c_i^2) / s^2 at least this
        (default 25, the energy of a 5-sigma sample; :func:`decomposition.model.components.threshold`).
        0 turns the significance rule for atoms off (the relative threshold alone).
    background_chi2 : float, optional
        A fitted background ("b") is kept when its likelihood-ratio statistic is at least
        this (>= 0; 0 keeps every fitted offset).  Default: ln(n) for a pixel of n fitted
        samples, the Bayesian information criterion for one parameter (5.5 for 256 bins;
        :func:`decomposition.stages.background.background_threshold`).
    merge_tol_bins : float
        Gaussians of one pixel closer than this (in bins) are merged.
    bound_factor : float
        Refined sigma/alpha stay within the grid ranges widened by this factor.
    poor_fit : float
        POOR_FIT flag when residual RMS > poor_fit x noise estimate.
    nan_policy : {"raise", "omit"}
        NaN/inf samples raise ValueError, or ("omit") flag the pixel NONFINITE
        and leave it undecomposed (NaN parameters).
    saturation_level : float, optional
        Samples >= this are saturated (flagged, excluded from the fit).  Default:
        the dtype maximum for integer input, none for float input.
    spike_sigma : float
        Single-sample spikes this many noise sigmas above both neighbours, and
        too narrow for the narrowest kernel, are excluded and flagged (0 = off).
        Count data (``noise="poisson"``) are tested against their counting
        statistics instead, at a fixed false-alarm rate per profile
        (:func:`decomposition.stages.prepare.find_count_spikes`); there ``spike_sigma``
        only switches the test on (> 0) or off.
    noise : {"gaussian", "poisson", "auto"}
        Noise model of the samples.  "gaussian": noise estimated from the data
        (the paper's setting).  "poisson": the samples are photon counts, whose
        variance is their expected value (spike test in Poisson terms, the
        solver's noise the Poisson noise at the signal).  "auto": "poisson" for
        count data -- an integer dtype, or floats that are all non-negative whole
        numbers (:func:`decomposition.noise.is_count_data`) -- else "gaussian".
        ``info["noise_model"]`` says which was used.
    shared_sigma : bool
        One PSF width per pixel shared by all its components (eq. (2) has a
        single camera PSF c(t)); False lets every atom have its own width.
    sss_after_direct : bool
        Keep the sss onset at or after the direct reflection (light enters the
        surface where it is directly reflected).  Removes the near-degeneracy
        of a direct peak and an sss rising edge at the same onset.
    multistart : bool
        Where the primary (Gaussian-first) start leaves a fit above the noise,
        also run the unrestricted largest-decrease start and keep the lower
        objective (see ``convscd.solve_multistart``); False: primary start only.
    sss_alone : bool
        Also consider, per pixel, an sss component with no direct reflection
        (scenes where some pixels see only light scattered out of a
        translucent volume).  About 40 % slower; off by default because the
        paper's model gives every pixel a direct (``components="s"`` handles
        scenes with sss only).
    block_size : int
        Pixels per solver block (default 512: ``bench speed``'s cube with its 1,024-pixel
        chunks, 2 threads, three alternations, against 256: white +2-4 %, 100 photons
        +7-9 % pixels/s; 128 was slower than 256).  Results agree to rounding: a block
        size moves 6 of 2,048 white-noise pixels and none at 100 photons.
    refine : bool
        After the sparse step, refine every found component's continuous
        parameters by weighted least squares on the forward model
        (:func:`decomposition.model.refine.refine`: variable projection,
        never worse per pixel, component set kept).  Off by default:
        ``streaklab bench tradeoff`` measures no fidelity gain over the
        solver's own off-grid polish; it does help ``off_grid=False`` output.
        Count data (``noise="poisson"``) are always polished with weights
        1 / Poisson variance of the model, reweighted POISSON_REFITS times, by
        the solver's compiled LM (:mod:`decomposition.stages.countpolish`): the Poisson
        maximum-likelihood fit, without a NumPy refit (``refine=True`` adds one).
        Widths and the sss attenuation stay within the solver's bounds (the grid's ranges
        widened by ``bound_factor``); AT_BOUND where one ends at a bound.  With the
        background family the refinement always runs, and a pixel whose components are not
        significant together against its offset alone (``significance_chi2``) is reported
        EMPTY with the mean as its offset (:func:`decomposition.stages.refit.clear_unlit`).
    search : bool
        Structured alternative starts for the pixels whose first answer is in
        doubt (an sss onset before the earliest Gaussian or far after it, an sss
        without a Gaussian, Gaussians without an sss, a leading edge steeper than
        the detected width, a fit above the noise): a direct and an sss on the
        leading edge, the earliest significant peak as the direct with and
        without the later Gaussians; each polished, the lowest penalised
        objective kept (:mod:`decomposition.stages.search`).
        ``info["search_wins"]`` counts which start each searched pixel kept.
    grow : bool
        Forward step after the search: where a pixel has a free slot and its
        largest residual bump away from its Gaussians is significant (or its data
        term exceeds search_doubt_chi2 times its expected value), a Gaussian there,
        polished with the rest, kept where the search's penalised objective is lower
        and the Gaussians stay resolved (:mod:`decomposition.stages.grow`);
        ``info["grown"]`` counts the pixels.  Then the sss swap: where the sss peaks
        more than SWAP_MODE_GAP_SIGMA widths after the direct, a Gaussian at its peak
        and its onset moved next to the direct, kept by the same rule
        (``info["swapped"]``).  Count data (``noise="poisson"``) also get
        a trial Gaussian at a faint echo after the threshold, kept where the Poisson
        deviance drops by ``significance_chi2`` (:func:`decomposition.stages.grow.grow_counts`;
        ``info["grown_counts"]``); with ``irf=`` the response path's echo steps
        (:mod:`decomposition.response.grow`).  Both need ``significance_chi2 > 0``.
    prune : bool
        Backward step after the search: where a pixel has an sss and a Gaussian
        less than PRUNE_GAP_SIGMA widths after its direct (often a late sss
        onset and a Gaussian filling the gap), that Gaussian is dropped, the
        rest polished, and the pruned answer kept where the search's penalised
        objective is lower (:mod:`decomposition.stages.prune`); ``info["pruned"]``
        counts the pixels.
    rescue : bool
        A second pass for the pixels flagged POOR_FIT at the end, or whose data term
        lies beyond what their noise allows (``RESCUE_MISFIT_Z`` standard deviations of a
        chi-square above its expectation; float data whose
        noise does not follow the signal): decomposed again without the detection's
        restart (:data:`decomposition.stages.rescue.RESCUE_OPTIONS`), the second answer
        taken, with its own flags, where its penalised misfit is lower by
        ``ambiguity_chi2`` (:mod:`decomposition.stages.rescue`); ``info["rescue_tried"]``
        and ``info["rescued"]`` count the pixels.
    signal_noise : bool
        Noise that follows the signal (photon / shot noise on float data, the
        Gaussian noise model): after the detection, each pixel's variance law
        floor + gain * model is fitted to its residual, and where the gain is
        significant the search, the forward step, the swap and the backward step
        score and polish with weights 1 / that variance instead of one noise level
        for every sample (:func:`decomposition.stages.candidates.signal_weights`).
        Count data (``noise="poisson"``) are weighted so everywhere, by their
        Poisson law at the detected model.
        ``info["signal_weighted"]`` counts the pixels weighted.  Correlated (pink) noise,
        judged over the call's pixels (their noise at the components' scale over their
        sample-to-sample noise, the median above WHITE_LAG_RATIO), is another matter: the
        search, the forward and backward steps then score every trial with its residual
        whitened by the call's noise spectrum, read off the detected residuals
        (:func:`decomposition.stages.candidates.correlated_noise_spectrum`);
        ``info["correlated_noise"]`` says whether it was.
    whiten : bool
        Where the call's noise is judged correlated (above), whiten the penalised objectives'
        residuals by its spectrum (default True); False: read them in the lagged noise level
        of each pixel, as before.
    signal_noise_law : {"auto", "pixel", "detector"}
        The variance law of float data whose noise follows the signal.  "auto" (default):
        where most of a call's pixels show such noise, every pixel is weighted by one law in
        the data's units, the medians of the pixels' read-noise floors and conversion gains
        (one detector behind every pixel); elsewhere only the pixels that show it, each by
        its own law.  "pixel": each pixel by its own law (where most pixels show such noise,
        every pixel with a positive gain).  "detector": the one law for every pixel whatever
        the pixels show.  The one law, where used, is recorded in
        ``info["signal_noise_law_fit"]`` (``floor`` and ``gain`` in the data's units).  Count
        data are weighted by their Poisson law either way.
    search_penalty, search_doubt_chi2 : float
        Weight of the parameter-count term of the search's objective (1 = BIC);
        a data term above this many times its expected value puts a pixel in doubt.
    ambiguity_chi2, ambiguity_split : float
        AMBIGUOUS flag of the search: another start whose objective (chi2 + k ln n, a BIC)
        is within ``ambiguity_chi2`` (default 10: below it the evidence for the best is
        less than "very strong") of the best's and whose split differs from the best's by
        more than ``ambiguity_split`` (1 - fidelity between them).
    ambiguity_sigma : float
        With a measured response (``irf``): a restored direct is taken where the fit without
        it lies within this many chi-square standard deviations (sqrt(2 n)) of the fit with
        it, and marks the pixel AMBIGUOUS where their splits differ by ``ambiguity_split``.
    stderr : bool, optional
        Add per-pixel standard errors ``<key>_stderr`` (same shapes and units
        as the parameters, NaN where absent or not identifiable) to
        ``params``, from the Fisher information at the solution with the noise
        estimated from the residual (:func:`decomposition.model.fisher.standard_errors`).
        Count data: from the Poisson Fisher information (weights 1 / model
        count, the noise scale known).
        Default: the same as ``refine``.
    **options
        The fields of :class:`decomposition.options.GridSpec` and
        :class:`decomposition.options.SolverOptions` above; for ``method="gradbm"`` also
        the baseline's own options (:data:`decomposition.methods.gradbm.GRADBM_DEFAULTS`).
    irf : InstrumentResponse, (samples, time_step_ps) tuple, or path, optional
        A measured instrument response to use instead of the Gaussian PSF
        (:func:`decomposition.response.resolve.resolve_response`: a path is read with
        :func:`core.irfstore.load_response`; a response sampled at another step is resampled
        onto ``time_bin_ps``; one whose samples span more than the window is refused).  Direct
        and inter-reflections are then shifted copies of the response (amplitude = peak height,
        delay = the response's reference instant, its peak), sss the response convolved with
        the decaying exponential; the stages are those of :mod:`decomposition.response.path`
        (greedy sparse coding over the response's dictionary at sub-bin phases, then
        variable-projection refinement of delays and alpha with linear amplitudes, always on;
        ``method="convscd"`` only).  The response has no width: every present component's
        ``*_sigma_ps`` is its Gaussian-equivalent sigma (FWHM / 2.3548), and
        ``*_sigma_ps_stderr`` is NaN.  The Gaussian options (``sigma_range_ps``, ``n_sigma``,
        ``coarse_sigma``, ``coarse_sss_sigma``, ``shared_sigma``, ``multistart``, ``search``,
        ``refine``) play no part (``sss_alone``: a pixel left with an sss and no direct is
        not flagged AMBIGUOUS); ``off_grid=False`` is refused.
        ``info["irf"]`` records the response (``describe()``, checksum, provenance).  Flags
        are the Gaussian path's where they apply, by the same rules (spikes judged against the
        response's shape; no WIDE_PSF: docs/instrument-response.md).  Cost:
        the response path is plain NumPy (no compiled kernel); see
        docs/instrument-response.md for its measured speed next to the Gaussian path's.
        Default None: the Gaussian PSF of the paper.

    Returns
    -------
    DecompositionResult
    """
    axis = time_axis(time_bin_ps, t0_ps)
    if method not in METHODS:
        raise ValueError(f"method must be 'convscd' or 'gradbm', got {method!r}")
    nan_policy = parse_nan_policy(nan_policy)
    fams = parse_components(components)
    grid, opts, method_options = options_from_mapping(options, strict=False)
    if method == "convscd" and method_options:
        raise TypeError(f"unknown options for method 'convscd': {sorted(method_options)}")
    background = "b" in fams
    if background and method != "convscd":
        raise ValueError(f"components: the background family ('b') is fitted by method 'convscd' only, "
                         f"not {method!r}")
    opts = opts.resolved(fams)
    R = opts.max_reflections
    if irf is not None:
        return _decompose_response(profiles, axis, method, fams, nan_policy, saturation_level, irf, grid, opts,
                                   background)

    samples = prepare_samples(profiles, axis, grid, nan_policy=nan_policy, saturation_level=saturation_level,
                              spike_sigma=opts.spike_sigma, noise_floor=opts.noise_floor,
                              rel_threshold=opts.rel_threshold, noise=opts.noise, background=background)
    info = {"method": method, "time_bin_ps": axis.time_bin_ps, "t0_ps": axis.t0_ps,
            "components": "".join(sorted(fams)), "nan_policy": nan_policy,
            "saturation_level": samples.saturation_level}
    flags = samples.flags.copy()
    noise_eff = samples.noise_eff
    flat_noise = None          # the live pixels whose noise was judged not to follow the signal
    if method == "gradbm":
        info.update(method_options)
        params = detect_gradbm(samples, R, fams, method_options)
    else:
        dic = cs.get_dictionary(samples.n_bins, axis.time_bin_ps, axis.t0_ps, grid, "d" in fams, "s" in fams)
        info.update(asdict(grid), **asdict(opts), n_atoms=int(dic.fam.size),
                    coordinates_searched=int(dic.n_coordinates))
        det = detect_components(samples, dic, opts, fams)
        if opts.signal_noise:
            det = dataclasses.replace(det, weights=signal_weights(samples, det, dic, opts, info))
            weighted = (np.zeros(samples.live.size, bool) if det.weights is None
                        else (det.weights != 1).any(axis=1))
            info["signal_weighted"] = int(weighted.sum())
            if samples.noise_model != "poisson":
                flat_noise = ~weighted
        # the noise at the components' scale, from the detected fit's residual: the search's
        # objective reads its data term in it where the noise is correlated (pink); where most
        # pixels' is, the data terms of every stage after this are whitened by the call's spectrum
        osig = None
        if samples.noise_model != "poisson" and (opts.search or opts.grow or opts.prune):
            osig = residual_significance_noise(samples, det, dic, opts)
            if opts.whiten:
                det = dataclasses.replace(det, noise_spectrum=correlated_noise_spectrum(samples, det, dic, opts, osig))
                info["correlated_noise"] = det.noise_spectrum is not None
        if opts.search:
            found = search_components(samples, det, dic, opts, fams, osig)
            det = dataclasses.replace(det, state=found.state)
            mark(flags, samples.live[found.ambiguous], AMBIGUOUS)
            wins = np.bincount(found.start[found.doubt], minlength=len(STAGE_STARTS))
            info.update(search_doubt=int(found.doubt.sum()),
                        search_wins={name: int(c) for name, c in zip(STAGE_STARTS, wins)},
                        ambiguous=int(found.ambiguous.sum()))
        # the steps after the search judge significance with the noise seen in the residual
        samples = dataclasses.replace(samples, lagged_noise=residual_significance_noise(samples, det, dic, opts))
        if opts.grow and "r" in fams:
            # (the forward step and the swap add inter-reflections: not where none are asked,
            # where an added Gaussian was dropped again by the labels, flagged TRUNCATED)
            state, grown = grow_components(samples, det, dic, opts)
            det = dataclasses.replace(det, state=state)
            info["grown"] = int(grown.sum())
            state, swapped = swap_components(samples, det, dic, opts)
            det = dataclasses.replace(det, state=state)
            info["swapped"] = int(swapped.sum())
        if opts.prune:
            state, pruned = prune_components(samples, det, dic, opts)
            det = dataclasses.replace(det, state=state)
            info["pruned"] = int(pruned.sum())
        if samples.noise_model == "poisson":
            det = dataclasses.replace(det, state=polish_counts(samples, det, dic, opts))
        final = None
        if samples.noise_model == "poisson" and opts.grow and "r" in fams:
            # after the threshold: the echo is kept by its own deviance test, weighed with the
            # counts where it lies, not by the threshold's noise at the direct's peak
            final, grown = grow_counts(samples, dataclasses.replace(det, state=final_state(samples, det, dic, opts)),
                                       dic, opts)
            info["grown_counts"] = int(grown.sum())
        labels = label_components(samples, det, dic, opts, state=final)
        params, noise_eff = labels.params, det.noise_eff
        flags |= labels.flags
        info.update(objective=det.objective.reshape(samples.lead + (opts.max_iter + 1,)),
                    n_iter=det.n_iter.reshape(samples.lead), lm_iterations=det.lm_iterations,
                    restarted=det.restarted)

    physics = {"shared_sigma": opts.shared_sigma and method == "convscd",
               "sss_after_direct": opts.sss_after_direct and method == "convscd"}
    if background:
        # the first estimate, refitted jointly with the amplitudes below (NaN: not decomposed)
        params[BACKGROUND_KEY] = np.full(samples.values.shape[0], np.nan)
        params[BACKGROUND_KEY][samples.live] = samples.background[samples.live]
    bg_stderr = None
    if (opts.refine or background or (samples.noise_model == "poisson" and method == "gradbm")) and samples.live.size:
        # within the solver's bounds on the widths and the attenuation, and flagged where it ends
        # at one: left free, a component fitted to one noisy sample on a pure background went
        # to a width of 0.2 ps and 10^5 times the counts, unflagged
        bounds = shape_bounds(grid, opts.bound_factor)
        params, rinfo = refine_components(samples, params, **physics, background_chi2=opts.background_chi2,
                                          bounds=bounds)
        bg_stderr = rinfo.pop("background_stderr", None)
        if background:
            # nothing above the offset: the components are noise fitted on a pure background
            # (the relative threshold always keeps the largest); the pixel is reported empty
            params, cleared, mean_stderr = clear_unlit(samples, params, opts.significance_chi2)
            flags[cleared] &= DATA_FLAGS
            info["cleared_unlit"] = int(cleared.sum())
            if bg_stderr is not None:
                bg_stderr = np.where(cleared.reshape(np.shape(bg_stderr)), mean_stderr.reshape(np.shape(bg_stderr)),
                                     bg_stderr)
        mark(flags, samples.live[params_at_bound({k: v[samples.live] for k, v in params.items()}, bounds)], AT_BOUND)
        info.update(rinfo)
    fit = assess_fit(samples, params, noise_eff, opts.poor_fit, flat_noise=flat_noise)
    flags |= fit.flags
    if method == "convscd":
        fit, params, flags = _rescue(profiles, samples, fit, params, flags, noise_eff, flat_noise, det.noise_spectrum,
                                     opts, info,
                                     dict(time_bin_ps=time_bin_ps, method=method, t0_ps=axis.t0_ps,
                                          components=components, nan_policy=nan_policy,
                                          saturation_level=saturation_level, **options))
    lead, L = samples.lead, samples.n_bins
    params = _reshape_params(params, lead, R)
    info["noise_sigma"] = (samples.noise * samples.scale).reshape(lead)
    info["noise_model"] = samples.noise_model
    info.update(refine=opts.refine, stderr=opts.stderr)
    if opts.stderr:
        params.update(component_errors(samples, params, **physics))
        if background:
            params[BACKGROUND_KEY + "_stderr"] = (bg_stderr if bg_stderr is not None
                                                  else np.full(lead, np.nan))
    return DecompositionResult(
        direct=fit.direct.reshape(lead + (L,)),
        sss=fit.sss.reshape(lead + (L,)),
        interreflections=fit.interreflections.reshape(lead + (R, L)),
        params=params,
        residual=fit.residual.reshape(lead + (L,)),
        flags=flags.reshape(lead),
        info=info,
    )


def _decompose_response(profiles, axis, method, fams, nan_policy, saturation_level, irf, grid, opts, background):
    """:func:`decompose` with an instrument response (:mod:`decomposition.response.path`)."""
    if method != "convscd":
        raise ValueError(f"irf= works with method='convscd' only, got method={method!r}")
    if not opts.off_grid:
        raise ValueError("off_grid=False snaps to the Gaussian grid; it has no meaning with a measured response (irf=)")
    n_bins = np.shape(profiles)[-1] if np.ndim(profiles) else 0
    response = resolve_response(irf, axis.time_bin_ps, n_bins)
    # the spike test's narrowest kernel is the response itself (0: no sample is narrower than it)
    ratio = spike_neighbour_ratio(response, axis.time_bin_ps, opts.rel_threshold)
    samples = prepare_samples(profiles, axis, grid, nan_policy=nan_policy, saturation_level=saturation_level,
                              spike_sigma=opts.spike_sigma if ratio > 0 else 0.0, noise_floor=opts.noise_floor,
                              rel_threshold=opts.rel_threshold, noise=opts.noise, background=background,
                              spike_neighbour_ratio=ratio if ratio > 0 else None)
    R = opts.max_reflections
    info = {"method": method, "time_bin_ps": axis.time_bin_ps, "t0_ps": axis.t0_ps,
            "components": "".join(sorted(fams)), "nan_policy": nan_policy,
            "saturation_level": samples.saturation_level, "irf": response_record(response),
            "spike_neighbour_ratio": ratio}
    info.update(asdict(grid), **asdict(opts))
    flags = samples.flags.copy()
    out = decompose_with_response(samples, response, grid, opts, fams)
    flags |= out.flags
    info.update(out.info)
    params = out.params
    core_keys = DIRECT_KEYS + SSS_KEYS + IR_KEYS + ((BACKGROUND_KEY,) if background else ())
    fit = assess_fit(samples, {k: params[k] for k in core_keys}, samples.noise_eff, opts.poor_fit, irf=response)
    flags |= fit.flags
    lead, L = samples.lead, samples.n_bins
    for k in list(params):
        params[k] = params[k].reshape(lead + np.shape(params[k])[1:])
    info["noise_sigma"] = (samples.noise * samples.scale).reshape(lead)
    info["noise_model"] = samples.noise_model
    return DecompositionResult(
        direct=fit.direct.reshape(lead + (L,)), sss=fit.sss.reshape(lead + (L,)),
        interreflections=fit.interreflections.reshape(lead + (R, L)), params=params,
        residual=fit.residual.reshape(lead + (L,)), flags=flags.reshape(lead), info=info)


def _rescue(profiles, samples, fit, params, flags, noise_eff, flat_noise, spectrum, opts, info, call):
    """The second pass of :mod:`decomposition.stages.rescue` on the POOR_FIT pixels and those whose data
    term lies beyond their noise: ``call`` holds the
    keywords of this call of :func:`decompose`, repeated with RESCUE_OPTIONS for those pixels.
    -> (fit, params, flags), the taken pixels' rows replaced (flat, P-shaped)."""
    info["rescue_tried"], info["rescued"] = 0, 0
    if not opts.rescue or all(getattr(opts, k) == v for k, v in RESCUE_OPTIONS.items()):
        return fit, params, flags         # off, or the first pass was already started so
    live = samples.live
    flat = None if flat_noise is None else np.zeros(samples.values.shape[0], bool)
    if flat is not None:
        flat[live] = flat_noise
    poor = np.zeros(samples.values.shape[0], bool)
    poor[live] = (flags[live] & POOR_FIT) != 0
    if samples.noise_model != "poisson":
        # and the misfits POOR_FIT forgives: a data term beyond what the noise allows (read only
        # where rescue_rows may take the pixel: its noise does not follow the signal)
        cand = live if flat is None else live[flat[live]]
        fit_c = samples.fit[cand]
        chi2 = data_term(fit.residual[cand], fit_c, noise_eff[cand] * samples.scale[cand], spectrum)
        poor[cand] |= misfit_beyond_noise(chi2, fit_c.sum(axis=1), RESCUE_MISFIT_Z)
    rows = rescue_rows(poor, flat, samples.noise_model == "poisson")
    info["rescue_tried"] = int(rows.size)
    if rows.size == 0:
        return fit, params, flags
    L = samples.n_bins
    again = decompose(np.asarray(profiles).reshape(-1, L)[rows], **dict(call, **RESCUE_OPTIONS, rescue=False))
    fit_mask = samples.fit[rows]
    noise = noise_eff[rows] * samples.scale[rows]
    first = {k: np.asarray(v)[rows] for k, v in params.items()}
    j1 = penalised_misfit(fit.residual[rows], fit_mask, noise, first, spectrum)
    j2 = penalised_misfit(np.nan_to_num(again.residual), fit_mask, noise, again.params, spectrum)
    take = take_rescued(j1, j2, opts.ambiguity_chi2)
    info["rescued"] = int(take.sum())
    if not take.any():
        return fit, params, flags
    r = rows[take]
    for k in params:
        params[k] = np.array(params[k], copy=True)
        params[k][r] = again.params[k][take]
    flags = flags.copy()
    flags[r] = again.flags[take]
    arrays = {name: np.array(getattr(fit, name), copy=True) for name in ("direct", "sss", "interreflections", "residual")}
    for name in arrays:
        arrays[name][r] = getattr(again, name)[take]
    return Fit(flags=fit.flags, **arrays), params, flags


def _reshape_params(params: dict, lead: tuple, n_ir: int) -> dict:
    for k in DIRECT_KEYS + SSS_KEYS + ((BACKGROUND_KEY,) if BACKGROUND_KEY in params else ()):
        params[k] = params[k].reshape(lead)
    for k in IR_KEYS:
        params[k] = params[k].reshape(lead + (n_ir,))
    return params
