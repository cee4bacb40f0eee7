"""The measured-response implementations of the stages of :func:`decomposition.decompose`.

:data:`decomposition.api.STAGES` is one list for every instrument.  With a measured response
(``irf=``) its ``prepare``, ``quality`` and ``finish`` (standard errors included) are the
Gaussian path's, given the response, and so is ``rescue`` (the whole path again, differently
started); ``detect`` (ConvSCD over the response's dictionary), ``label`` and ``refit`` run the
functions here on the response's atoms; ``forward_steps``, ``offset_test`` and ``final_atoms``
are the response's own; of the stages between ``detect`` and ``label`` the signal-noise
stage (the samples' weights where the noise follows the signal), the correlated-noise and grow
stages (float data), the prune stage (the backward step) and the search where it is asked for
(``search=True``) run, each the Gaussian path's code over the response's atoms on its
detection; the count polish and count grow steps of the Gaussian dictionary do not apply.  Each
function here reads and updates one :class:`ResponseFit`, the state of the call's live pixels:

* :func:`detect`: ConvSCD's sparse coding over the response's dictionary (the Gaussian path's
  :func:`decomposition.stages.detect.detect_components`, its atoms as the sparse coding leaves
  them: no threshold, polish or second noise pass -- the refit below relocates every atom);
* :func:`label`: threshold, merge, physics labels (:mod:`decomposition.response.label`);
* :func:`refit`: every pixel's delays and sss alpha by variable projection, amplitudes by linear
  least squares (:mod:`decomposition.response.refine`), with the order kept (no
  inter-reflection before the direct, no sss onset before it with ``sss_after_direct``);
  count data (``noise="poisson"``) fitted to their Poisson deviance instead, by Fisher
  scoring over delays, alphas and amplitudes together (the Poisson maximum-likelihood fit,
  :func:`decomposition.response.refine.fit_slots` with ``CountData``).  It always runs
  (``n_polish`` iterations): the detection's relocation is short (``n_lm`` iterations per added
  atom) and there is no grid to snap to;
* :func:`forward_steps` (:mod:`decomposition.response.grow`): a direct where a fast sss took its
  light (AMBIGUOUS where the data do not determine it), an sss for count data's pixels left
  without one, an echo where the residual in noise sigmas holds one, an sss far after the
  direct turned into the echo it is -- each kept where the deviance drops by
  ``significance_chi2``;
* :func:`offset_test`: the fitted offset (the ``b`` family) kept where significant, the pixel
  refitted without it elsewhere;
* :func:`final_atoms`: the flags of the final atoms and the parameters of every pixel.

Count data on the Gaussian PSF with ``likelihood_counts`` take the same refit, forward steps,
offset test and final atoms after the Gaussian path's labels (:func:`hand_over`), the instrument
then the Gaussian PSF of each pixel's width (:class:`decomposition.model.atoms.GaussianPSF`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import BACKGROUND_KEY, empty_params
from ..stages.background import background_significant, background_threshold
from ..model.components import off_window
from ..model.atoms import GaussianPSF
from ..model.refine import hold_params
from ..constants import FAM_GAUSS, FAM_SSS, SSS_SLOT
from ..flags import AMBIGUOUS, AT_BOUND, FLAG_DTYPE, MAX_ITER, OFF_WINDOW, TRUNCATED, mark
from ..stages.label import at_bound
from ..options import GridSpec, SolverOptions
from ..stages.prepare import Samples
from ..stages.refit import background_stats
from ..methods.dictionary import get_dictionary
from ..stages.detect import detect_components
from .label import label_response, param_slots
from .grow import GrowContext, grow_response
from .refine import Slots, pixel_widths, refine_rows, refit_slots

__all__ = ["ResponseFit", "ResponseOutcome", "detect", "hand_over", "label", "refit", "forward_steps",
           "offset_test", "final_atoms"]


@dataclass(frozen=True)
class ResponseOutcome:
    """``params`` (P-shaped, keys of :mod:`core.model`), ``flags`` (P,) (MAX_ITER, AT_BOUND,
    TRUNCATED, OFF_WINDOW, AMBIGUOUS), ``info`` (dict), ``background_stderr`` ((P,), NaN where
    no offset is kept; None without the ``b`` family)."""

    params: dict
    flags: np.ndarray
    info: dict
    background_stderr: np.ndarray | None = None


@dataclass
class ResponseFit:
    """What the response's stages carry for the n live pixels of one call (slot arrays in the
    refinement layout of :mod:`decomposition.response.refine`, normalised units)."""

    irf: object                 # the instrument: the resolved InstrumentResponse, on the samples'
                                # step, or the Gaussian PSF of each pixel's held width (GaussianPSF)
    t: np.ndarray               # (L,) sample times, ps
    sigma_eq_ps: object         # the (Gaussian-equivalent) width, ps: float, or (n,) one per pixel
    bounds: dict                # {"delay_ps", "lalp"}: the refinement's bounds
    refine_kw: dict             # keywords of refit_slots for all n pixels
    b_est: np.ndarray           # (n,) the offset's first estimate (0 without the b family)
    with_bg: bool
    dic: object = None          # methods.dictionary.Dictionary over the response
    det: object = None          # the detection (stages.detect.Detection)
    params: dict | None = None  # the labels (n-shaped)
    trunc: np.ndarray | None = None
    slots: Slots | None = None
    ambiguous: np.ndarray | None = None
    grow_info: dict = field(default_factory=dict)
    background_chi2: np.ndarray | None = None     # (P,)
    background_stderr: np.ndarray | None = None   # (P,)

    @property
    def response(self):
        """The measured response, None for the Gaussian PSF (whose widths the parameters carry)."""
        return None if isinstance(self.irf, GaussianPSF) else self.irf

    @property
    def alphas_per_ps(self) -> np.ndarray:
        """The dictionary's sss decay rates (the grid's coarse alphas, each once; none without the
        sss family)."""
        return self.dic.sss_alphas_per_ps


def detect(samples: Samples, irf, grid: GridSpec, opts: SolverOptions, components, hold=None) -> ResponseFit:
    """The call's :class:`ResponseFit` with the detection over the response's dictionary.
    ``hold`` ({key of :data:`decomposition.model.refine.HOLD_KEYS` but ``sigma_ps``: (P,) values,
    NaN free}, checked): onsets and decay rates held at given values in the refinement and the
    forward steps' refits."""
    rf = _response_fit(samples, irf, gaussian_equivalent_sigma_ps(irf), grid, opts, hold)
    ax = samples.axis
    rf.dic = get_dictionary(samples.n_bins, ax.time_bin_ps, ax.t0_ps, grid, "d" in components, "s" in components,
                            response=irf)
    rf.det = detect_components(samples, rf.dic, opts, components, polish=False)
    return rf


def _response_fit(samples: Samples, irf, sigma_eq, grid: GridSpec, opts: SolverOptions, hold) -> ResponseFit:
    """The :class:`ResponseFit` of the live pixels over the instrument ``irf`` of width
    ``sigma_eq`` (ps; a float, or (n,) one per live pixel), before any stage has run."""
    L, R = samples.n_bins, opts.max_reflections
    ax = samples.axis
    t = ax.t0_ps + ax.time_bin_ps * np.arange(L)
    live = samples.live
    a_lo, a_hi = grid.alpha_range_per_ps
    span = L * ax.time_bin_ps
    bounds = {"delay_ps": (t[0] - span, t[-1] + span),
              "lalp": (math.log(a_lo / opts.bound_factor), math.log(a_hi * opts.bound_factor))}
    counts = samples.noise_model == "poisson"
    refine_kw = dict(irf=irf, t=t, ax=ax, fit_mask=samples.fit[live], scale=samples.scale[live], opts=opts,
                     bounds=bounds, disp=samples.dispersion[live] if counts else None, sigma_eq=sigma_eq, R=R)
    if hold:
        refine_kw["hold"] = {k: np.asarray(v, np.float64)[live] for k, v in hold.items()}
    with_bg = samples.background is not None
    return ResponseFit(irf=irf, t=t, sigma_eq_ps=sigma_eq, bounds=bounds, refine_kw=refine_kw, with_bg=with_bg,
                       b_est=samples.background[live] if with_bg else np.zeros(live.size))


def hand_over(samples: Samples, dic, det, grid: GridSpec, opts: SolverOptions, params: dict,
              hold: dict | None) -> ResponseFit:
    """The Gaussian path's labels of count data handed to the stages here (``likelihood_counts``):
    the refit, forward steps, offset test and final atoms over
    :class:`decomposition.model.atoms.GaussianPSF`, each live pixel's width held at
    ``hold["sigma_ps"]`` where finite, else at its labelled width (the grid's narrowest for a
    pixel with no component).

    Where the width is known, what parts the two paths on counts is what follows the labels:
    the Poisson likelihood's refit of every pixel and the count forward steps on the refitted
    atoms (docs/history.md).  ``dic``, ``det``: the Gaussian path's dictionary and detection;
    ``params`` (P,): its labels; ``hold``: the call's checked holds, or None (the onsets and
    the decay rate are held here too)."""
    live = samples.live
    labelled = np.where(np.isfinite(params["direct_sigma_ps"]), params["direct_sigma_ps"], params["sss_sigma_ps"])
    if np.ndim(params.get("ir_sigma_ps")) == 2:
        ir = np.where(np.isfinite(params["ir_sigma_ps"]), params["ir_sigma_ps"], np.inf).min(axis=1, initial=np.inf)
        labelled = np.where(np.isfinite(labelled), labelled, ir)
    held = hold["sigma_ps"] if hold and "sigma_ps" in hold else np.full(samples.values.shape[0], np.nan)
    sigma = np.where(np.isfinite(held), held, labelled)[live]
    sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, grid.sigma_range_ps[0])
    rest = {k: v for k, v in (hold or {}).items() if k != "sigma_ps"}
    rf = _response_fit(samples, GaussianPSF(sigma), sigma, grid, opts, rest)
    rf.dic, rf.det = dic, det
    rf.params = {k: np.asarray(v)[live].copy() for k, v in params.items()}
    # every component at its pixel's width (the refit's first weights render these parameters)
    for key in ("direct_sigma_ps", "sss_sigma_ps", "ir_sigma_ps"):
        if key in rf.params:
            v = rf.params[key]
            rf.params[key] = np.where(np.isfinite(v), sigma.reshape((-1,) + (1,) * (v.ndim - 1)), v)
    rf.trunc = np.zeros(live.size, bool)
    return rf


def label(rf: ResponseFit, samples: Samples, opts: SolverOptions, state: dict, weights=None) -> None:
    """Threshold, merge and name the atoms of ``state`` (the detection's slot state, searched
    where the search ran; :func:`decomposition.response.label.label_response`); ``weights``
    (n, L): the samples' relative least-squares weights where the noise follows the signal
    (:attr:`decomposition.stages.detect.Detection.weights`), None: all alike."""
    live = samples.live
    rf.params, rf.trunc = label_response(state, rf.irf, rf.t, samples.scale[live], rf.sigma_eq_ps,
                                         opts.max_reflections, opts, time_bin_ps=samples.axis.time_bin_ps,
                                         noise=samples.significance_sigma(live, samples.noise_eff[live]),
                                         weights=weights)


def refit(rf: ResponseFit, samples: Samples, signal_weights=None) -> None:
    """Refine the labelled components of every live pixel; the profiles are the samples less
    the offset's first estimate (0 without the ``b`` family).  ``signal_weights`` (P, L): float
    data's relative sample weights where the noise follows the signal, read by this refit and
    every refit and deviance after it (the forward steps, the offset test)."""
    rf.refine_kw["weights"] = None if signal_weights is None else signal_weights[samples.live]
    fam, delay, lalp = param_slots(rf.params, rf.refine_kw["R"])
    rf.slots = refit_slots(samples.profiles[samples.live], fam, delay, lalp, rf.b_est, rf.with_bg, rf.params,
                           **rf.refine_kw)


def forward_steps(rf: ResponseFit, samples: Samples, opts: SolverOptions, components) -> None:
    """The forward steps after the refinement (:func:`decomposition.response.grow.grow_response`)."""
    ctx = GrowContext(samples, rf.irf, rf.b_est, rf.with_bg, rf.refine_kw, opts)
    rf.slots, rf.grow_info, rf.ambiguous = grow_response(ctx, rf.slots, alphas_per_ps=rf.alphas_per_ps,
                                                         components=components)


def offset_test(rf: ResponseFit, samples: Samples, opts: SolverOptions) -> None:
    """With the ``b`` family: the fitted offset kept where its test finds it significant, the
    pixel refitted without it (the data themselves, the offset exactly 0) elsewhere."""
    if not rf.with_bg:
        return
    P, live, R = samples.values.shape[0], samples.live, rf.refine_kw["R"]
    fam, delay, lalp, amp, params, background, iterations = rf.slots
    fit_mask, scale = rf.refine_kw["fit_mask"], rf.refine_kw["scale"]
    full = empty_params((P,), n_ir=R)
    for k, v in params.items():
        full[k][live] = v
    full[BACKGROUND_KEY] = np.zeros(P)
    full[BACKGROUND_KEY][live] = background
    chi2, stderr = background_stats(samples, full, rf.response)
    keep = background_significant(chi2[live], background_threshold(fit_mask, opts.background_chi2))
    drop = np.flatnonzero(~keep)
    if drop.size:
        y0 = np.where(fit_mask[drop], samples.values[live[drop]], 0.0) / scale[drop, None]
        p0 = {k: v[drop] for k, v in params.items()}
        p0[BACKGROUND_KEY] = np.zeros(drop.size)
        sub = refine_rows(rf.refine_kw, drop)
        d_slots = refit_slots(y0, fam[drop], delay[drop], lalp[drop], np.zeros(drop.size), False, p0, **sub)
        fam, delay, lalp, amp = fam.copy(), delay.copy(), lalp.copy(), amp.copy()
        fam[drop], delay[drop], lalp[drop], amp[drop] = d_slots[:4]
        for k in params:
            params[k][drop] = d_slots[4][k]
        background[drop] = 0.0
        iterations[drop] += d_slots[6]
    params[BACKGROUND_KEY] = background
    rf.slots = Slots(fam, delay, lalp, amp, params, background, iterations)
    rf.background_stderr = np.full(P, np.nan)
    rf.background_stderr[live[keep]] = stderr[live[keep]]
    rf.background_chi2 = np.zeros(P)
    rf.background_chi2[live] = chi2[live]


def final_atoms(rf: ResponseFit, samples: Samples, opts: SolverOptions, components, hold=None) -> ResponseOutcome:
    """The flags of the final atoms and every pixel's parameters (held values put in exactly)."""
    P, live, R = samples.values.shape[0], samples.live, opts.max_reflections
    fam, delay, lalp, amp, params, background, iterations = rf.slots
    det, t = rf.det, rf.t
    flags = np.zeros(P, FLAG_DTYPE)
    mark(flags, live[~det.converged], MAX_ITER)
    mark(flags, live[rf.trunc], TRUNCATED)
    # the Gaussian path's rules on the final atoms: alpha at its bound (the response has no width
    # to hit one), a component running off the window's edge
    lsig = np.broadcast_to(pixel_widths(rf.sigma_eq_ps, fam.shape[0])[1][:, None], fam.shape)
    state = {"fam": fam, "delay": delay, "lsig": lsig, "lalp": lalp}
    mark(flags, live[at_bound(state, {"lsig": (-np.inf, np.inf), "lalp": rf.bounds["lalp"]})], AT_BOUND)
    mark(flags, live[off_window(state, t, irf=rf.response).any(axis=1)], OFF_WINDOW)
    # the split the data do not determine: a restored direct within the noise of the fit
    # without it, or (the search stage's rule) an sss left with no direct where the paper's
    # model gives every pixel one
    ambiguous = rf.ambiguous
    if "d" in components and not opts.sss_alone:
        ambiguous = ambiguous | ((fam[:, 0] != FAM_GAUSS) & (fam[:, SSS_SLOT] == FAM_SSS))
    mark(flags, live[ambiguous], AMBIGUOUS)

    out = empty_params((P,), n_ir=R)
    if rf.with_bg:
        out[BACKGROUND_KEY] = np.full(P, np.nan)          # NaN where not decomposed
    for k, v in params.items():
        out[k][live] = v
    if hold:
        # the held values themselves (the refinement holds log alpha: exp(log(alpha)) may differ
        # from alpha in its last bit)
        out = hold_params(out, hold, (P,))
    info = {"n_atoms": int(rf.dic.fam.size), "coordinates_searched": int(rf.dic.n_coordinates),
            "restarted": det.restarted,
            "response_alphas_per_ps": [float(a) for a in rf.alphas_per_ps],
            **rf.grow_info,
            "n_iter": det.n_iter.reshape(samples.lead),
            "refine_iterations": _scatter(P, live, iterations, 0).reshape(samples.lead)}
    if rf.with_bg:
        info["background_chi2"] = rf.background_chi2.reshape(samples.lead)
    return ResponseOutcome(params=out, flags=flags, info=info, background_stderr=rf.background_stderr)


def _scatter(P, live, v, fill):
    out = np.full(P, fill, dtype=np.asarray(v).dtype)
    out[live] = v
    return out
