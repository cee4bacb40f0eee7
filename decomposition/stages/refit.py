"""The ``refit`` and ``finish`` stages of :func:`decomposition.decompose`: off-grid refinement and standard errors.

:func:`refine_components` moves every found component's continuous parameters to the
weighted least-squares optimum of the forward model (:func:`decomposition.model.refine.refine`,
never worse per pixel, component set kept); :func:`component_errors` adds per-pixel standard
errors from the Fisher information at the solution (:func:`decomposition.model.fisher.standard_errors`).
Excluded samples (saturated, spikes, non-finite) have weight 0 in both.

Count data (``noise="poisson"``): the weights are 1 / variance of the Poisson law at the
model (:func:`sample_weights`), and the refit is repeated POISSON_REFITS times, each with the
previous model's weights (iteratively reweighted least squares, whose fixed point is the
Poisson maximum-likelihood fit), a pixel keeping a refit only where it lowers the Poisson
deviance.  ``decompose`` reaches that fit without this stage, in the
compiled polish of :mod:`decomposition.stages.countpolish`; this refit runs for count data only with
``refine=True`` (and for the GradBM baseline).  The standard errors use weights 1 / model count with the
noise scale measured on the fit (:func:`decomposition.noise.fit_dispersion`, 1 for pure
counts): the Poisson Fisher information.
"""
from __future__ import annotations

import numpy as np

from core.irf_components import gaussian_equivalent_sigma_ps
from core.model import BACKGROUND_KEY, render_profile
from ..constants import ONSET_TIE_SIGMA, POISSON_FIT_FLOOR, POISSON_REFITS, POISSON_VARIANCE_FLOOR
from ..noise import count_deviance, fit_dispersion, poisson_weights
from .prepare import Samples
from ..model.slots import select_rows
from .background import background_significant, background_test, background_threshold, light_test, offset_alone
from ..model.fisher import standard_errors
from ..model.refine import hold_params, refine

__all__ = ["refine_components", "component_errors", "sample_weights", "background_stats", "clear_unlit"]


def sample_weights(samples: Samples, params: dict, signal_weights=None) -> np.ndarray:
    """(P, L) least-squares weights: the fit mask, times ``signal_weights`` (P, L) where given
    (float data whose noise follows the signal: :attr:`decomposition.stages.detect.Detection.weights`
    of the live pixels, 1 elsewhere), or for count data 1 / Poisson variance of the model of
    ``params`` (P-shaped) on the fitted samples."""
    if samples.noise_model != "poisson":
        return samples.weights if signal_weights is None else samples.weights * signal_weights
    return poisson_weights(_model(samples, params), samples.fit, samples.dispersion)


def _model(samples: Samples, params: dict, irf=None) -> np.ndarray:
    """(P, L) model of P-shaped ``params`` (0 where a pixel has none; ``irf``: the response's
    atoms instead of Gaussians)."""
    axis = samples.axis
    with np.errstate(invalid="ignore"):
        model = render_profile(params, samples.n_bins, axis.time_bin_ps, axis.t0_ps, irf=irf)
    return np.where(np.isfinite(model), model, 0.0)


def refine_components(samples: Samples, params: dict, *, shared_sigma: bool, sss_after_direct: bool,
                      background_chi2: float | None = None, bounds: dict | None = None, hold: dict | None = None,
                      signal_weights=None):
    """-> (refined params (P-shaped), {"refine_iterations", "refined"} in the input's leading shape).

    ``bounds`` ({"lsig", "lalp"}: log sigma_ps and log alpha_per_ps, as the solver's
    :func:`decomposition.model.slots.shape_bounds`): the refinement's bounds on every width and the sss
    attenuation (default :func:`decomposition.model.refine.refine`'s, a tenth of a bin to the window
    and 1e-7-1e3 per ps).

    With a ``background`` in ``params`` (the ``b`` family) the offset of every live pixel is
    fitted jointly with the amplitudes; then, where it is not significant
    (:func:`decomposition.stages.background.background_significant` at the threshold of
    :func:`decomposition.stages.background.background_threshold` for ``background_chi2``, the
    likelihood-ratio statistic of :func:`background_stats`), it is set to 0 and the pixel
    refitted without it.  ``info`` then also holds ``background_chi2`` (the statistic) and
    ``background_stderr`` (units of the profiles; NaN where the offset was left out).

    ``hold`` ({key of :data:`decomposition.model.refine.HOLD_KEYS`: (P,) values, NaN free}):
    parameters put in at the start and held there (:func:`decomposition.model.refine.refine`);
    the never-worse rule of the count data's refits compares with that held start.

    ``signal_weights`` (P, L): float data's relative sample weights where the noise follows the
    signal (:func:`sample_weights`); the refinement weighs its residual by them, as the stages
    before it did (unweighted, it took the noise at the peak for structure again;
    docs/history.md).
    """
    axis = samples.axis
    if hold:
        params = hold_params(params, hold, (samples.values.shape[0],))
    n_fits = POISSON_REFITS if samples.noise_model == "poisson" else 1
    P = samples.values.shape[0]
    iterations = np.zeros(P, np.int64)
    refined = np.zeros(P, bool)
    with_bg = BACKGROUND_KEY in params
    fit_bg = np.zeros(P, bool)
    if with_bg:
        fit_bg[samples.live] = True

    counts = samples.noise_model == "poisson"
    limits = {} if bounds is None else {"sigma_bounds_ps": tuple(np.exp(bounds["lsig"])),
                                        "alpha_bounds_per_ps": tuple(np.exp(bounds["lalp"]))}

    def deviance(params):
        return count_deviance(samples.values, _model(samples, params), samples.fit, samples.dispersion)

    def fits(params, fit_bg):
        # count data: a refit is kept for a pixel only where it lowers the Poisson deviance, the
        # fit's own objective (the weights of a model that lacks a component can pull an atom
        # onto the counts of a missed tail; see decomposition.stages.countpolish)
        dev_best = deviance(params) if counts else None
        for _ in range(n_fits):
            new, rinfo = refine(samples.values, params, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                                weights=sample_weights(samples, params, signal_weights), shared_sigma=shared_sigma,
                                sss_after_direct=sss_after_direct, fit_background=fit_bg, hold=hold, **limits)
            nonlocal iterations, refined
            iterations += rinfo["iterations"].reshape(-1)
            refined |= rinfo["refined"].reshape(-1)
            if counts:
                dev = deviance(new)
                better = dev < dev_best
                new = select_rows(better, new, {k: params.get(k, v) for k, v in new.items()})
                dev_best = np.where(better, dev, dev_best)
            params = new
        return params

    params = fits(params, fit_bg)
    lead = samples.lead
    info = {"refine_iterations": iterations, "refined": refined}
    if with_bg:
        chi2, stderr = background_stats(samples, params)
        keep = background_significant(chi2, background_threshold(samples.fit, background_chi2)) & fit_bg
        drop = fit_bg & ~keep
        if drop.any():
            params = dict(params)
            params[BACKGROUND_KEY] = np.where(drop, 0.0, params[BACKGROUND_KEY])
            params = fits(params, keep)
        info.update(background_chi2=chi2, background_stderr=np.where(keep, stderr, np.nan))
    return params, {k: v.reshape(lead) for k, v in info.items()}


def clear_unlit(samples: Samples, params: dict, significance_chi2: float):
    """Pixels whose components are not significant together against their offset alone
    (:func:`decomposition.stages.background.light_test` below ``significance_chi2``) lose them: every
    component NaN, the offset the mean of the fitted samples.  -> (params (P-shaped, a new
    dict), cleared (P,) bool, stderr (P,): the standard error of a cleared pixel's mean,
    units of the profiles, NaN elsewhere).  ``params`` must hold ``background``; only live
    pixels are judged."""
    live = samples.live
    cleared = np.zeros(samples.values.shape[0], bool)
    stderr = np.full(samples.values.shape[0], np.nan)
    if live.size == 0:
        return params, cleared, stderr
    counts = samples.noise_model == "poisson"
    values, fit = samples.values[live], samples.fit[live]
    stat = light_test(values, _model(samples, params)[live], fit, counts=counts,
                      noise=samples.noise_eff[live] * samples.scale[live],
                      dispersion=None if samples.dispersion is None else samples.dispersion[live])
    cleared[live] = stat < significance_chi2
    if not cleared.any():
        return params, cleared, stderr
    out = {k: np.array(v, dtype=np.float64, copy=True) for k, v in params.items()}
    for k, v in out.items():
        if k != BACKGROUND_KEY and not k.endswith("_stderr"):
            v[cleared] = np.nan
    n = np.maximum(fit.sum(axis=1), 1)
    mean = offset_alone(values, fit)
    c = cleared[live]
    out[BACKGROUND_KEY][live[c]] = mean[c]
    if counts:      # Poisson: the variance of a count is its mean (times the dispersion's square)
        disp = np.ones(live.size) if samples.dispersion is None else samples.dispersion[live]
        se = disp * np.sqrt(np.maximum(mean, 0.0) / n)
    else:
        se = samples.noise_eff[live] * samples.scale[live] / np.sqrt(n)
    stderr[live[c]] = se[c]
    return out, cleared, stderr


def background_stats(samples: Samples, params: dict, irf=None):
    """Likelihood-ratio statistic and standard error (units of the profiles) of each pixel's
    fitted offset (:func:`decomposition.stages.background.background_test`) under the noise model:
    Gaussian, weights the fit mask and the pixel's noise estimate; count data, weights
    1 / Poisson variance of the model (which includes the offset), noise scale the dispersion.
    ``irf``: the components are the response's atoms (the response path)."""
    axis = samples.axis
    if samples.noise_model == "poisson":
        weights = poisson_weights(_model(samples, params, irf), samples.fit, samples.dispersion)
        noise = np.ones(samples.values.shape[0])
    else:
        weights = samples.weights
        noise = samples.noise_eff * samples.scale
    return background_test(samples.values, params, weights, noise, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                           irf=irf)


def component_errors(samples: Samples, params: dict, *, shared_sigma: bool, sss_after_direct: bool,
                     hold: dict | None = None, irf=None) -> dict:
    """``<key>_stderr`` arrays for ``params`` (in the input's leading shape); ``hold`` (P,)-shaped
    values of the parameters the fit held (:func:`refine_components`): not parameters of the
    information, their errors NaN.

    ``irf``: the components are atoms of this measured response (the information of its atoms,
    no width parameters).  Its count data were fitted to their Poisson deviance with the
    variance floored at POISSON_FIT_FLOOR (:mod:`decomposition.response.refine`), so the errors
    take those weights; and that fit approaches the onset's bound without being projected onto
    it, so an onset within ONSET_TIE_SIGMA response widths of the direct shares its delay."""
    axis = samples.axis
    shape = samples.lead + (samples.n_bins,)
    n_pix = samples.values.shape[0]
    flat = {k: np.reshape(v, (n_pix,) + np.shape(v)[len(samples.lead):]) for k, v in params.items()}
    values = samples.values
    comp_params = params
    offset = None
    if BACKGROUND_KEY in params:
        # the offset taken out of the data and, where kept (not exactly 0 after its test), one
        # more parameter of the information
        b = np.nan_to_num(flat[BACKGROUND_KEY])
        values = values - b[:, None]
        offset = (b != 0.0).reshape(samples.lead)
        comp_params = {k: v for k, v in params.items() if k != BACKGROUND_KEY}
    noise = None
    if samples.noise_model == "poisson":
        # weights 1 / Poisson variance, the noise scale measured on the fit (1 for pure counts)
        model = _model(samples, flat, irf)
        weights = poisson_weights(model, samples.fit,
                                  floor_counts=POISSON_VARIANCE_FLOOR if irf is None else POISSON_FIT_FLOOR)
        noise = fit_dispersion(samples.values, model, samples.fit).reshape(samples.lead)
    else:
        weights = samples.weights
    tie_ps = 0.0 if irf is None else ONSET_TIE_SIGMA * gaussian_equivalent_sigma_ps(irf)
    return standard_errors(values.reshape(shape), comp_params, time_bin_ps=axis.time_bin_ps, t0_ps=axis.t0_ps,
                           weights=weights.reshape(shape), shared_sigma=shared_sigma,
                           sss_after_direct=sss_after_direct, noise_sigma=noise, offset=offset,
                           hold=None if not hold else {k: np.reshape(v, samples.lead) for k, v in hold.items()},
                           irf=irf, onset_tie_ps=tie_ps)
