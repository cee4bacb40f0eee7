"""Public entry point: ``decompose(profiles, time_bin_ps, method=...)``.

:func:`decompose` checks its options once, into the frozen dataclasses of
:mod:`decomposition.options`, then runs one declared list of named stages in order,
:data:`STAGES`, for the Gaussian PSF and a measured instrument response (``irf=``) alike.  Each
stage is a small function here that calls one stage module of :mod:`decomposition.stages` (with
a measured response, of :mod:`decomposition.response`) and records what it did; the list is the
one place the order is written, and docs/decomposition.md lists the same names in the same order
(tests/test_docs.py checks it).
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from .methods import convscd as cs
from .stages.countpolish import polish_counts
from .stages.detect import detect_components, detect_gradbm
from .flags import (AMBIGUOUS, AT_BOUND, DATA_FLAGS, EMPTY, FLAG_DTYPE, FLAG_NAMES, MAX_ITER, NONFINITE, POOR_FIT,  # noqa: F401
                    SATURATED, OFF_WINDOW, SPIKE, TRUNCATED, WIDE_PSF, flag_names, mark)
from .stages.label import final_state, label_components, params_at_bound
from core.model import BACKGROUND_KEY, DIRECT_KEYS, IR_KEYS, SSS_KEYS
from .options import METHODS, GridSpec, SolverOptions, options_from_mapping, parse_components, parse_nan_policy
from .stages.prepare import prepare_samples, time_axis
from .stages.quality import Fit, assess_fit
from .stages.refit import clear_unlit, component_errors, refine_components
from .stages.candidates import correlated_noise_spectrum, residual_significance_noise, signal_weights
from .stages.grow import grow_components, grow_counts, swap_components
from .stages.prune import prune_components
from .stages.search import STAGE_STARTS, search_components
from .model.slots import shape_bounds
from .model.refine import check_hold
from .constants import FAM_SSS, RESCUE_MISFIT_Z
from .stages.rescue import RESCUE_OPTIONS, data_term, penalised_misfit, rescue_rows, take_rescued
from .stages.selection import misfit_beyond_noise
from .response.resolve import resolve_response, response_record, spike_neighbour_ratio, spike_settings
from .response import path as rp

__all__ = ["decompose", "stage_seconds", "DecompositionResult", "Stage", "STAGES", "parse_components", "EMPTY",
           "SATURATED", "POOR_FIT", "SPIKE", "NONFINITE", "MAX_ITER", "AT_BOUND", "TRUNCATED", "AMBIGUOUS", "WIDE_PSF",
           "OFF_WINDOW", "FLAG_NAMES"]


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


@dataclass(frozen=True)
class Stage:
    """One named step of a declared stage list (:data:`STAGES` of :func:`decompose`, and
    :data:`decomposition.image.api.IMAGE_STAGES`): ``run(call)`` reads and updates the call's state."""

    name: str
    run: Callable[[object], None]
    purpose: str


@dataclass
class _Call:
    """What one call of :func:`decompose` carries from stage to stage (flat pixel arrays, P rows)."""

    profiles: object
    axis: object
    method: str
    fams: frozenset
    nan_policy: str
    saturation_level: float | None
    grid: GridSpec
    opts: SolverOptions
    method_options: dict
    irf: object
    keywords: dict              # this call's keywords, for the second pass of the rescue stage
    background: bool = False
    samples: object = None      # stages.prepare.Samples
    info: dict = field(default_factory=dict)
    flags: np.ndarray | None = None
    noise_eff: np.ndarray | None = None
    flat_noise: np.ndarray | None = None   # the live pixels whose noise was judged not to follow the signal
    dic: object = None          # methods.dictionary: the coarse kernels (ConvSCD)
    det: object = None          # stages.detect.Detection (ConvSCD)
    osig: np.ndarray | None = None         # noise at the components' scale, for the search's objective
    final: object = None        # slot state after the count-data echo step, else None
    params: dict | None = None
    bg_stderr: np.ndarray | None = None
    fit: Fit | None = None
    response: object = None     # the resolved instrument response (irf=)
    rfit: object = None         # response.path.ResponseFit: the response's stages' state
    hold: dict | None = None    # parameters held at given values, {HOLD_KEYS: (P,)} (hold=)
    result: "DecompositionResult | None" = None

    @property
    def convscd(self) -> bool:
        """The stages of ConvSCD over the Gaussian dictionary apply (method "convscd", no
        measured response)."""
        return self.method == "convscd" and self.irf is None


# --------------------------------------------------------------------------- the stages

def _prepare(c: _Call) -> None:
    opts, axis = c.opts, c.axis
    ratio = None
    if c.irf is not None:
        if c.method != "convscd":
            raise ValueError(f"irf= works with method='convscd' only, got method={c.method!r}")
        if not opts.off_grid:
            raise ValueError("off_grid=False snaps to the Gaussian grid; it has no meaning with a measured "
                             "response (irf=)")
        n_bins = np.shape(c.profiles)[-1] if np.ndim(c.profiles) else 0
        c.response = resolve_response(c.irf, axis.time_bin_ps, n_bins)
        # the spike test's narrowest kernel is the response itself (0: no sample is narrower than it)
        ratio = spike_neighbour_ratio(c.response, axis.time_bin_ps, opts.rel_threshold)
    c.samples = prepare_samples(c.profiles, axis, c.grid, nan_policy=c.nan_policy,
                                saturation_level=c.saturation_level,
                                noise_floor=opts.noise_floor, rel_threshold=opts.rel_threshold, noise=opts.noise,
                                background=c.background,
                                **spike_settings(c.response, axis.time_bin_ps, opts.spike_sigma, opts.rel_threshold,
                                                 ratio))
    c.info = {"method": c.method, "time_bin_ps": axis.time_bin_ps, "t0_ps": axis.t0_ps,
              "components": "".join(sorted(c.fams)), "nan_policy": c.nan_policy,
              "saturation_level": c.samples.saturation_level}
    if c.response is not None:
        c.info.update(irf=response_record(c.response), spike_neighbour_ratio=ratio)
        c.info.update(asdict(c.grid), **asdict(opts))
    c.flags = c.samples.flags.copy()
    c.noise_eff = c.samples.noise_eff


def _detect(c: _Call) -> None:
    samples, opts = c.samples, c.opts
    if c.response is not None:
        c.rfit = rp.detect(samples, c.response, c.grid, opts, c.fams, hold=c.hold)
        c.dic, c.det = c.rfit.dic, c.rfit.det
        return
    if not c.convscd:
        c.info.update(c.method_options)
        c.params = detect_gradbm(samples, opts.max_reflections, c.fams, c.method_options)
        return
    c.dic = cs.get_dictionary(samples.n_bins, c.axis.time_bin_ps, c.axis.t0_ps, c.grid, "d" in c.fams,
                              "s" in c.fams)
    c.info.update(asdict(c.grid), **asdict(opts), n_atoms=int(c.dic.fam.size),
                  coordinates_searched=int(c.dic.n_coordinates))
    c.det = detect_components(samples, c.dic, opts, c.fams)


def _signal_noise(c: _Call) -> None:
    # over a measured response's atoms as over the Gaussian PSF's: the grow, prune and search
    # stages, the labels' threshold and the refinement weigh their samples by the law found
    if not (c.method == "convscd" and c.opts.signal_noise):
        return
    c.det = dataclasses.replace(c.det, weights=signal_weights(c.samples, c.det, c.dic, c.opts, c.info))
    weighted = (np.zeros(c.samples.live.size, bool) if c.det.weights is None
                else (c.det.weights != 1).any(axis=1))
    c.info["signal_weighted"] = int(weighted.sum())
    if c.samples.noise_model != "poisson":
        c.flat_noise = ~weighted


def _correlated_noise(c: _Call) -> None:
    # the noise at the components' scale, from the detected fit's residual: the search's
    # objective reads its data term in it where the noise is correlated (pink); where most
    # pixels' is, the data terms of every stage after this are whitened by the call's spectrum
    # (over a measured response's atoms as over the Gaussian PSF's)
    opts = c.opts
    if c.method != "convscd" or c.samples.noise_model == "poisson" or not (opts.search or opts.grow or opts.prune):
        return
    c.osig = residual_significance_noise(c.samples, c.det, c.dic, opts)
    if opts.whiten:
        c.det = dataclasses.replace(c.det, noise_spectrum=correlated_noise_spectrum(c.samples, c.det, c.dic, opts,
                                                                                    c.osig))
        c.info["correlated_noise"] = c.det.noise_spectrum is not None


def _search(c: _Call) -> None:
    if not (c.method == "convscd" and c.opts.search):
        return
    found = search_components(c.samples, c.det, c.dic, c.opts, c.fams, c.osig)
    c.det = dataclasses.replace(c.det, state=found.state)
    mark(c.flags, c.samples.live[found.ambiguous], AMBIGUOUS)
    wins = np.bincount(found.start[found.doubt], minlength=len(STAGE_STARTS))
    c.info.update(search_doubt=int(found.doubt.sum()),
                  search_wins={name: int(n) for name, n in zip(STAGE_STARTS, wins)},
                  ambiguous=int(found.ambiguous.sum()))


def _residual_noise(c: _Call) -> None:
    # the steps after the search judge significance with the noise seen in the residual
    if c.convscd:
        c.samples = dataclasses.replace(c.samples,
                                        lagged_noise=residual_significance_noise(c.samples, c.det, c.dic, c.opts))


def _grow(c: _Call) -> None:
    # (the forward step and the swap add inter-reflections: not where none are asked,
    # where an added Gaussian was dropped again by the labels, flagged TRUNCATED); over a
    # measured response's atoms on float data -- its count data take the response's own echo
    # steps, weighed by their deviance where the counts are few (forward_steps)
    if not (c.method == "convscd" and c.opts.grow and "r" in c.fams):
        return
    if c.response is not None and c.samples.noise_model == "poisson":
        return
    state, grown = grow_components(c.samples, c.det, c.dic, c.opts)
    c.det = dataclasses.replace(c.det, state=state)
    c.info["grown"] = int(grown.sum())
    state, swapped = swap_components(c.samples, c.det, c.dic, c.opts)
    c.det = dataclasses.replace(c.det, state=state)
    c.info["swapped"] = int(swapped.sum())


def _prune(c: _Call) -> None:
    if not (c.method == "convscd" and c.opts.prune):
        return
    state, pruned = prune_components(c.samples, c.det, c.dic, c.opts)
    c.det = dataclasses.replace(c.det, state=state)
    c.info["pruned"] = int(pruned.sum())


def _count_polish(c: _Call) -> None:
    if c.convscd and c.samples.noise_model == "poisson":
        c.det = dataclasses.replace(c.det, state=polish_counts(c.samples, c.det, c.dic, c.opts))


def _count_grow(c: _Call) -> None:
    # after the threshold: an echo or an sss is kept by its own deviance test, weighed with
    # the counts where it lies, not by the threshold's noise at the direct's peak
    if not (c.convscd and c.samples.noise_model == "poisson" and c.opts.grow and ("r" in c.fams or "s" in c.fams)):
        return
    thresholded = dataclasses.replace(c.det, state=final_state(c.samples, c.det, c.dic, c.opts))
    c.final, grown = grow_counts(c.samples, thresholded, c.dic, c.opts)
    has_sss = (thresholded.state["fam"] == FAM_SSS).any(axis=1)
    c.info["grown_counts"] = int(grown.sum())
    c.info["count_sss_added"] = int(((c.final["fam"] == FAM_SSS).any(axis=1) & ~has_sss).sum())


def _label(c: _Call) -> None:
    if c.response is not None:
        rp.label(c.rfit, c.samples, c.opts, c.det.state, c.det.weights)
        return
    if not c.convscd:
        return
    samples, det = c.samples, c.det
    labels = label_components(samples, det, c.dic, c.opts, state=c.final)
    c.params, c.noise_eff = labels.params, det.noise_eff
    c.flags |= labels.flags
    c.info.update(objective=det.objective.reshape(samples.lead + (c.opts.max_iter + 1,)),
                  n_iter=det.n_iter.reshape(samples.lead), lm_iterations=det.lm_iterations,
                  restarted=det.restarted)
    if c.opts.likelihood_counts and samples.noise_model == "poisson" and samples.live.size:
        # the stages after the labels are the response path's, over the Gaussian PSF of each
        # pixel's width: the count fit and the count forward steps of a measured response
        c.rfit = rp.hand_over(samples, c.dic, det, c.grid, c.opts, c.params, c.hold)
        c.info["counts_handed_over"] = int(samples.live.size)


def _physics(c: _Call) -> dict:
    return {"shared_sigma": c.opts.shared_sigma and c.convscd,
            "sss_after_direct": c.opts.sss_after_direct and c.method == "convscd"}


def _refit(c: _Call) -> None:
    if c.rfit is not None:
        rp.refit(c.rfit, c.samples, _signal_weights(c))
        return
    samples, opts, params, flags = c.samples, c.opts, c.params, c.flags
    if c.background:
        # the first estimate, refitted jointly with the amplitudes below (NaN: not decomposed)
        params[BACKGROUND_KEY] = np.full(samples.values.shape[0], np.nan)
        params[BACKGROUND_KEY][samples.live] = samples.background[samples.live]
    if not ((opts.refine or c.background or c.hold or (samples.noise_model == "poisson" and not c.convscd))
            and samples.live.size):
        return
    # within the solver's bounds on the widths and the attenuation, and flagged where it ends
    # at one: left free, a component fitted to one noisy sample on a pure background went
    # to a width of 0.2 ps and 10^5 times the counts, unflagged
    bounds = shape_bounds(c.grid, opts.bound_factor)
    params, rinfo = refine_components(samples, params, **_physics(c), background_chi2=opts.background_chi2,
                                      bounds=bounds, hold=c.hold, signal_weights=_signal_weights(c))
    c.bg_stderr = rinfo.pop("background_stderr", None)
    if c.background:
        # nothing above the offset: the components are noise fitted on a pure background
        # (the relative threshold always keeps the largest); the pixel is reported empty
        params, cleared, mean_stderr = clear_unlit(samples, params, opts.significance_chi2)
        flags[cleared] &= DATA_FLAGS
        c.info["cleared_unlit"] = int(cleared.sum())
        if c.bg_stderr is not None:
            shape = np.shape(c.bg_stderr)
            c.bg_stderr = np.where(cleared.reshape(shape), mean_stderr.reshape(shape), c.bg_stderr)
    mark(flags, samples.live[params_at_bound({k: v[samples.live] for k, v in params.items()}, bounds)], AT_BOUND)
    c.info.update(rinfo)
    c.params = params


def _signal_weights(c: _Call):
    """(P, L) the signal-noise stage's sample weights of the live pixels (1 elsewhere) on float
    data whose noise follows the signal, for the refinement; None where there are none."""
    if c.det is None or c.det.weights is None or c.samples.noise_model == "poisson":
        return None
    w = np.ones(c.samples.values.shape)
    w[c.samples.live] = c.det.weights
    return w


def _forward_steps(c: _Call) -> None:
    if c.rfit is not None:
        rp.forward_steps(c.rfit, c.samples, c.opts, c.fams)


def _offset_test(c: _Call) -> None:
    if c.rfit is not None:
        rp.offset_test(c.rfit, c.samples, c.opts)


def _final_atoms(c: _Call) -> None:
    if c.rfit is None:
        return
    out = rp.final_atoms(c.rfit, c.samples, c.opts, c.fams, hold=c.hold)
    if c.response is None:
        # the Gaussian path's labels handed over: their window and bound flags were the
        # labelled atoms', the final atoms' replace them
        c.flags &= FLAG_DTYPE(~(AT_BOUND | OFF_WINDOW) & 0xFFFF)
    c.flags |= out.flags
    c.info.update(out.info)
    c.params = out.params
    if out.background_stderr is not None:
        c.bg_stderr = out.background_stderr.reshape(c.samples.lead)


def _quality(c: _Call) -> None:
    c.fit = assess_fit(c.samples, c.params, c.noise_eff, c.opts.poor_fit, irf=c.response, flat_noise=c.flat_noise)
    c.flags |= c.fit.flags


def _rescue_stage(c: _Call) -> None:
    if c.method != "convscd":
        return
    # the second pass runs the whole path again, with the resolved response where there is one
    keywords = c.keywords if c.response is None else dict(c.keywords, irf=c.response)
    spectrum = None if c.det is None else c.det.noise_spectrum
    c.fit, c.params, c.flags = _rescue(c.profiles, c.samples, c.fit, c.params, c.flags, c.noise_eff, c.flat_noise,
                                       spectrum, c.opts, c.info, keywords, c.hold)


def _assemble(c: _Call, params: dict) -> None:
    """The call's :class:`DecompositionResult`: the rendered fit, ``params`` and flags in the
    input's leading shape, with the noise the call estimated in ``info`` (both paths' last step)."""
    samples, fit = c.samples, c.fit
    lead, L, R = samples.lead, samples.n_bins, c.opts.max_reflections
    c.info["noise_sigma"] = (samples.noise * samples.scale).reshape(lead)
    c.info["noise_model"] = samples.noise_model
    c.result = DecompositionResult(
        direct=fit.direct.reshape(lead + (L,)), sss=fit.sss.reshape(lead + (L,)),
        interreflections=fit.interreflections.reshape(lead + (R, L)), params=params,
        residual=fit.residual.reshape(lead + (L,)), flags=c.flags.reshape(lead), info=c.info)


def _finish(c: _Call) -> None:
    samples, opts = c.samples, c.opts
    lead = samples.lead
    params = _reshape_params(c.params, lead, opts.max_reflections)
    c.info.update(refine=opts.refine, stderr=opts.stderr)
    if opts.stderr:
        params.update(component_errors(samples, params, **_physics(c), hold=c.hold, irf=c.response))
        if c.background:
            params[BACKGROUND_KEY + "_stderr"] = (c.bg_stderr if c.bg_stderr is not None
                                                  else np.full(lead, np.nan))
    _assemble(c, params)


#: The stages of :func:`decompose`, run in this order for every instrument (docs/decomposition.md
#: lists them in the same order; tests/test_docs.py checks it).  A stage that does not apply to the
#: call (its option off, another method, noise model or instrument) returns at once.  The GradBM
#: baseline (``method="gradbm"``) runs prepare, detect, refit, quality and finish; a measured
#: response (``irf=``) runs prepare, detect, signal_noise, correlated_noise and grow (these two on
#: float data), search (where ``search=True``), prune, label, refit, forward_steps, offset_test,
#: final_atoms, quality, rescue and finish, its detect, search, grow, prune, label and refit over
#: the response's atoms (:mod:`decomposition.response.path`).  Count data on the Gaussian PSF with
#: ``likelihood_counts`` run the response's refit, forward_steps, offset_test and final_atoms
#: after their own label stage, over the Gaussian PSF of each pixel's width.
STAGES = (
    Stage("prepare", _prepare, "validate, scale and mask the samples; noise, spikes, background estimate"),
    Stage("detect", _detect, "the method's first answer: sparse coding over the coarse dictionary"),
    Stage("signal_noise", _signal_noise, "weights for noise that follows the signal (signal_noise=True)"),
    Stage("correlated_noise", _correlated_noise, "noise at the components' scale; whitening where it is pink"),
    Stage("search", _search, "structured alternative starts for the pixels in doubt (search=True)"),
    Stage("residual_noise", _residual_noise, "the residual's noise, for the significance tests after the search"),
    Stage("grow", _grow, "add a Gaussian at a significant residual bump; swap a late sss's peak (grow=True)"),
    Stage("prune", _prune, "drop a Gaussian on the direct's sss onset where the data allow (prune=True)"),
    Stage("count_polish", _count_polish, "count data: the atoms polished with Poisson weights"),
    Stage("count_grow", _count_grow, "count data: an echo or an sss after the threshold, kept by its deviance "
                                     "(grow=True)"),
    Stage("label", _label, "snap (on-grid), threshold, merge and name the atoms; their flags"),
    Stage("refit", _refit, "off-grid refinement with the background; clear unlit pixels; AT_BOUND"),
    Stage("forward_steps", _forward_steps, "response: a direct (and for counts an sss, an echo) added after the "
                                           "refinement where the deviance pays"),
    Stage("offset_test", _offset_test, "response: the fitted offset kept where significant, refitted without it "
                                       "elsewhere"),
    Stage("final_atoms", _final_atoms, "response: the final atoms' flags and every pixel's parameters"),
    Stage("quality", _quality, "render the fit and flag its quality"),
    Stage("rescue", _rescue_stage, "decompose the misfit pixels once more, differently started (rescue=True)"),
    Stage("finish", _finish, "shape the outputs; standard errors (stderr=True)"),
)


def decompose(profiles, time_bin_ps: float = 2.0, method: str = "convscd", *, t0_ps: float | None = None,
              components=("d", "r", "s"), nan_policy: str = "raise", saturation_level: float | None = None,
              irf=None, hold=None, **options) -> DecompositionResult:
    """Decompose time profiles into direct, inter-reflection and sss components.

    Runs the stages of :data:`STAGES` in order; the method, each stage and the flags are
    described in docs/decomposition.md.

    Parameters
    ----------
    profiles : array_like (..., L), any real dtype (uint16 camera data included)
        Time profiles in any units (counts for count data); the last axis is time.
    time_bin_ps : float
        Bin width T in ps (> 0).
    method : {"convscd", "gradbm"}
        The solver: ConvSCD, or the GradBM baseline (:mod:`decomposition.methods.gradbm`).
    t0_ps : float, optional
        Time of the first bin in ps (default ``time_bin_ps``: the paper's t = T..LT).
    components : str or sequence
        Families to look for: "d" direct, "r" inter-reflections, "s" sss, "b" a constant
        background per pixel (e.g. "d,s" or "d,r,s,b"; :func:`decomposition.options.component_letters`).
        Families left out are neither built into the dictionary nor searched; without "r" at
        most one Gaussian per pixel; "b" with ``method="convscd"`` only.
    nan_policy : {"raise", "omit"}
        NaN/inf samples raise ValueError, or ("omit") flag the pixel NONFINITE and leave it
        undecomposed (NaN parameters).
    saturation_level : float, optional
        Samples >= this (units of the profiles) are saturated: flagged, left out of the
        picking, censored in the fit.  Default: the dtype maximum for integer input, none for
        float input.
    irf : InstrumentResponse, (samples, time_step_ps) tuple, or path, optional
        A measured instrument response used instead of the Gaussian PSF
        (:func:`decomposition.response.resolve.resolve_response`; docs/instrument-response.md).
    hold : dict, optional
        Parameters held at given values in the final fit of every pixel
        ({key of :data:`decomposition.model.refine.HOLD_KEYS`: a scalar or an array of the
        profiles' leading shape, NaN: free there}): the width of every component, the direct's or
        the sss onset, the sss decay rate.  The component set is found as without it; the refit
        then puts the held values in and fits the rest around them (their standard errors NaN).
        The whole-cube estimates of :func:`decomposition.image.decompose_image` come this way.
        With ``irf`` the onsets and the decay rate (a response has no width to hold): held in
        the refinement over the response's atoms, its forward steps' refits and its errors.
    **options
        The fields of :class:`decomposition.options.GridSpec` and
        :class:`decomposition.options.SolverOptions`, each documented there; for
        ``method="gradbm"`` also the baseline's own options
        (:data:`decomposition.methods.gradbm.GRADBM_DEFAULTS`).

    Returns
    -------
    DecompositionResult
        Arrays shaped like ``profiles`` (``(..., L)``; ``(..., R, L)`` for the
        inter-reflections, ``(...,)`` for the flags); ``info`` holds the method, every option
        and the stages' counts.
    """
    call = _new_call(profiles, time_bin_ps, method, t0_ps=t0_ps, components=components, nan_policy=nan_policy,
                     saturation_level=saturation_level, irf=irf, hold=hold, **options)
    for stage in STAGES:
        stage.run(call)
    return call.result


def stage_seconds(profiles, time_bin_ps: float = 2.0, method: str = "convscd", **kwargs):
    """:func:`decompose` (the same arguments, the same result) with the wall-clock seconds each
    stage of :data:`STAGES` took: -> (DecompositionResult, {stage name: seconds}), every stage in
    order (one that does not apply returns at once).  The second pass's whole call counts as
    ``rescue``.
    For benchmarks (``streaklab bench speed``): where a call's time goes, per instrument."""
    call = _new_call(profiles, time_bin_ps, method, **kwargs)
    seconds = {}
    for stage in STAGES:
        start = time.perf_counter()
        stage.run(call)
        seconds[stage.name] = time.perf_counter() - start
    return call.result, seconds


def _new_call(profiles, time_bin_ps: float = 2.0, method: str = "convscd", *, t0_ps: float | None = None,
              components=("d", "r", "s"), nan_policy: str = "raise", saturation_level: float | None = None,
              irf=None, hold=None, **options) -> _Call:
    """The checked arguments of :func:`decompose` as the state its stages share."""
    axis = time_axis(time_bin_ps, t0_ps)
    if method not in METHODS:
        raise ValueError(f"method must be 'convscd' or 'gradbm', got {method!r}")
    nan_policy = parse_nan_policy(nan_policy)
    fams = parse_components(components)
    if hold and irf is not None and "sigma_ps" in hold:
        raise ValueError("hold['sigma_ps'] holds the Gaussian PSF's width; a measured response (irf=) has none "
                         "(hold onsets and sss decay rates only)")
    hold = check_hold(hold, np.shape(profiles)[:-1]) or None
    grid, opts, method_options = options_from_mapping(options, strict=False)
    if method == "convscd" and method_options:
        raise TypeError(f"unknown options for method 'convscd': {sorted(method_options)}")
    background = "b" in fams
    if background and method != "convscd":
        raise ValueError(f"components: the background family ('b') is fitted by method 'convscd' only, "
                         f"not {method!r}")
    keywords = dict(time_bin_ps=time_bin_ps, method=method, t0_ps=axis.t0_ps, components=components,
                    nan_policy=nan_policy, saturation_level=saturation_level, **options)
    return _Call(profiles=profiles, axis=axis, method=method, fams=fams, nan_policy=nan_policy,
                 saturation_level=saturation_level, grid=grid, opts=opts.resolved(fams, response=irf is not None),
                 method_options=method_options, irf=irf, keywords=keywords, background=background, hold=hold)


def _rescue(profiles, samples, fit, params, flags, noise_eff, flat_noise, spectrum, opts, info, call, hold=None):
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
    again = decompose(np.asarray(profiles).reshape(-1, L)[rows], **dict(call, **RESCUE_OPTIONS, rescue=False),
                      hold=None if hold is None else {k: v[rows] for k, v in hold.items()})
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
