"""The oracle: what the data allow a decomposition to reach, given the true component set.

For synthetic profiles with known ground truth, the oracle fits the *true* component set of
each pixel by nonlinear least squares started *at the true parameters*
(:func:`decomposition.model.refine.refine`, one PSF width per pixel, sss onset kept at or after
the direct, inter-reflections kept in order), with the forward model the data were rendered
with (point-sampled or bin-integrated).  It never has to decide which components are there
nor find a start, so its fidelity is a ceiling for any method on the same data: the gap
between a method and the oracle is what the method loses, and the oracle's own distance from
1 is what the noise costs.

That ceiling knows components no detector can see: an inter-reflection at 1 % of the direct
under NSR 0.055 noise is fitted from its true start, while a method that must find it cannot.
:func:`significant_truth` keeps, of a pixel's true components, the direct and those whose
in-window energy is significant against the pixel's noise (the solver's energy rule,
``significance_chi2`` times the noise variance); the oracle on that set is the *detectable*
ceiling: what a method reaches that finds every significant component and none other.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.model import render_components
from ..model.refine import refine

__all__ = ["OracleOptions", "OracleFit", "oracle_fit", "significant_truth"]


@dataclass(frozen=True)
class OracleOptions:
    """Settings of the oracle's least-squares fit.

    Attributes
    ----------
    max_iter : int
        Levenberg-Marquardt iterations per pixel (>= 1).
    ftol : float
        Relative decrease of the residual sum of squares below which a pixel has converged.
    block_size : int
        Pixels fitted together.
    """

    max_iter: int = 100
    ftol: float = 1e-9
    block_size: int = 1024

    def __post_init__(self):
        if int(self.max_iter) < 1:
            raise ValueError(f"OracleOptions.max_iter must be >= 1, got {self.max_iter}")
        if not (np.isfinite(self.ftol) and self.ftol > 0):
            raise ValueError(f"OracleOptions.ftol must be positive, got {self.ftol}")
        if int(self.block_size) < 1:
            raise ValueError(f"OracleOptions.block_size must be >= 1, got {self.block_size}")


@dataclass(frozen=True)
class OracleFit:
    """The oracle's estimate, in the layout of a decomposition result.

    Attributes
    ----------
    params : dict of ndarray
        Fitted parameters (keys of :mod:`core.model`), shapes S and S + (R,).
    direct, sss : ndarray, S + (L,)
        Rendered components (with the data's rendering).
    interreflections : ndarray, S + (R, L)
    info : dict of ndarray
        ``refine``'s per-pixel information (``iterations``, ``converged``, ``rss`` ...).
    """

    params: dict
    direct: np.ndarray
    sss: np.ndarray
    interreflections: np.ndarray
    info: dict


def oracle_fit(profiles, truth_params: dict, *, time_bin_ps: float = 2.0, t0_ps: float | None = None,
               bin_integrated: bool = False, options: OracleOptions | None = None) -> OracleFit:
    """Fit the true component set, started at the true parameters.

    Parameters
    ----------
    profiles : array_like, S + (L,)
        Measured (noisy) profiles.
    truth_params : dict of ndarray
        True parameters (shapes S and S + (R,), NaN = absent): the start, and the set of
        components fitted.
    time_bin_ps, t0_ps : float
        Time axis in ps (bin ``i`` at ``t0_ps + i * time_bin_ps``; t0 defaults to one bin).
    bin_integrated : bool
        Fit bin-averaged kernels (for data rendered that way) instead of point samples.
    options : OracleOptions, optional

    Returns
    -------
    OracleFit
        Its ``direct`` / ``sss`` / ``interreflections`` can be given to
        :func:`decomposition.model.fidelity.fidelity` like a decomposition result.
    """
    options = options or OracleOptions()
    y = np.asarray(profiles, dtype=np.float64)
    params, info = refine(y, truth_params, time_bin_ps=time_bin_ps, t0_ps=t0_ps, max_iter=int(options.max_iter),
                          ftol=float(options.ftol), block_size=int(options.block_size), shared_sigma=True,
                          sss_after_direct=True, keep_order=True, bin_integrated=bool(bin_integrated))
    comps = render_components(params, y.shape[-1], time_bin_ps, t0_ps, bin_integrated=bool(bin_integrated))
    return OracleFit(params=params, direct=comps["direct"], sss=comps["sss"],
                     interreflections=comps["interreflections"], info=info)


def significant_truth(truth_params: dict, components: dict, noise_sigma, *, significance_chi2: float = 25.0) -> dict:
    """The true parameters without the components the noise hides.

    Parameters
    ----------
    truth_params : dict of ndarray
        True parameters (shapes S and S + (R,), NaN = absent).
    components : dict of ndarray
        The true components as rendered in the data: ``direct`` and ``sss`` S + (L,),
        ``interreflections`` S + (R, L) (:attr:`decomposition.evaluation.synthetic.SyntheticData.components`).
    noise_sigma : array_like, S or S + (L,)
        Standard deviation of each pixel's noise, in the profiles' units; or of each sample's
        (photon counts: the square root of the expected counts), where the energy is then
        read in that sample's variance.
    significance_chi2 : float
        An sss or an inter-reflection stays where its in-window energy (sum of squares of its
        samples) is at least this many times the noise variance (the solver's
        ``significance_chi2``); with per-sample noise, where the sum of its squared samples
        over their variances is (a sample of zero variance counts where the component is not
        zero there).

    Returns
    -------
    dict of ndarray
        A copy of ``truth_params`` with the hidden sss and inter-reflections set to NaN (the
        inter-reflections that stay moved to the front, in their order); the direct is kept.
    """
    from core.model import IR_KEYS, SSS_KEYS

    if not (np.isfinite(significance_chi2) and significance_chi2 >= 0):
        raise ValueError(f"significance_chi2 must be finite and >= 0, got {significance_chi2}")
    out = {k: np.array(v, dtype=np.float64, copy=True) for k, v in truth_params.items()}
    var = np.asarray(noise_sigma, dtype=np.float64) ** 2
    if np.any(~np.isfinite(var)):
        raise ValueError("noise_sigma must be finite")
    sss = np.asarray(components["sss"], np.float64)
    irs = np.asarray(components["interreflections"], np.float64)
    if var.ndim == 0:
        var = np.full(sss.shape[:-1], float(var))
    if var.shape == sss.shape:
        # per-sample variances: each component's chi2 against zero, a sample of no variance
        # counting infinitely where the component is not zero there
        def chi2(c, v):
            c2 = c * c
            return np.sum(np.where(v > 0, c2 / np.where(v > 0, v, 1.0), np.where(c2 > 0, np.inf, 0.0)), axis=-1)
        hidden = ~(chi2(sss, var) >= significance_chi2)
        keep = chi2(irs, var[..., None, :]) >= significance_chi2                                # S + (R,)
    elif var.shape == sss.shape[:-1]:
        level = significance_chi2 * var
        hidden = ~(np.sum(sss ** 2, axis=-1) >= level)
        keep = np.sum(irs ** 2, axis=-1) >= level[..., None]                                    # S + (R,)
    else:
        raise ValueError(f"noise_sigma must have the pixels' shape {sss.shape[:-1]} or the samples' "
                         f"{sss.shape}, got {var.shape}")
    for k in SSS_KEYS:
        if k in out:
            out[k][hidden] = np.nan
    if "ir_delay_ps" in out and out["ir_delay_ps"].shape[-1]:
        keep &= np.isfinite(out["ir_delay_ps"])
        order = np.argsort(~keep, axis=-1, kind="stable")          # kept ones first, in order
        for k in IR_KEYS:
            if k in out:
                v = np.where(keep, out[k], np.nan)
                out[k] = np.take_along_axis(v, order, axis=-1)
    return out
