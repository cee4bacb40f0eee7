"""The oracle: what the data allow a decomposition to reach, given the true component set.

For synthetic profiles with known ground truth, the oracle fits the *true* component set of
each pixel by nonlinear least squares started *at the true parameters*
(:func:`decomposition.refine.refine`, one PSF width per pixel, sss onset kept at or after
the direct, inter-reflections kept in order), with the forward model the data were rendered
with (point-sampled or bin-integrated).  It never has to decide which components are there
nor find a start, so its fidelity is a ceiling for any method on the same data: the gap
between a method and the oracle is what the method loses, and the oracle's own distance from
1 is what the noise costs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.model import render_components
from .refine import refine

__all__ = ["OracleOptions", "OracleFit", "oracle_fit"]


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
        :func:`decomposition.metrics.fidelity` like a decomposition result.
    """
    options = options or OracleOptions()
    y = np.asarray(profiles, dtype=np.float64)
    params, info = refine(y, truth_params, time_bin_ps=time_bin_ps, t0_ps=t0_ps, max_iter=int(options.max_iter),
                          ftol=float(options.ftol), block_size=int(options.block_size), shared_sigma=True,
                          sss_after_direct=True, keep_order=True, bin_integrated=bool(bin_integrated))
    comps = render_components(params, y.shape[-1], time_bin_ps, t0_ps, bin_integrated=bool(bin_integrated))
    return OracleFit(params=params, direct=comps["direct"], sss=comps["sss"],
                     interreflections=comps["interreflections"], info=info)
