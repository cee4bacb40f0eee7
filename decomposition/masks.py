"""Which samples the solver fits: a fit mask and a censored mask, never numeric codes.

A sample is *fitted* (its residual counts), *censored* from below (saturated: the true value
is at least the recorded one, so only a model below it is a misfit, contributing
max(p - model, 0)^2), or neither (excluded: non-finite, a spike).  The two boolean arrays of
a :class:`SampleMask` travel from the input check (:mod:`decomposition.stages.prepare`) down to the
compiled kernels (:mod:`decomposition.kernels.atomlm`); nothing on the way is a number that could be
mistaken for a least-squares weight.  Real weights (1 / variance) are a different thing and
are taken only where they are weights, as an argument of their own: the compiled LM's
``weights`` (:func:`decomposition.kernels.atomlm.lm_refine`, the count polish),
:func:`decomposition.model.refine.refine` and :func:`decomposition.model.fisher.standard_errors`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SampleMask", "check_mask"]


@dataclass(frozen=True)
class SampleMask:
    """Fit and censored masks of P profiles of L samples.

    Attributes
    ----------
    fit : ndarray (P, L) bool         samples fitted exactly
    censored : ndarray (P, L) bool    samples censored from below (never also in ``fit``)
    """

    fit: np.ndarray
    censored: np.ndarray

    def __post_init__(self):
        for name in ("fit", "censored"):
            v = getattr(self, name)
            if not (isinstance(v, np.ndarray) and v.dtype == np.bool_):
                raise TypeError(f"SampleMask.{name} must be a boolean array (a mask, not weights); "
                                f"got {getattr(v, 'dtype', type(v).__name__)}")
        if self.fit.shape != self.censored.shape or self.fit.ndim != 2:
            raise ValueError(f"SampleMask: fit {self.fit.shape} and censored {self.censored.shape} must be the "
                             f"same (P, L) shape")
        if np.any(self.fit & self.censored):
            raise ValueError("SampleMask: a sample cannot be both fitted and censored")

    @classmethod
    def all_fitted(cls, shape) -> "SampleMask":
        """Every sample fitted, none censored."""
        return cls(np.ones(shape, bool), np.zeros(shape, bool))

    @classmethod
    def of_fit(cls, fit) -> "SampleMask":
        """The fitted samples ``fit`` (bool), none censored."""
        fit = np.asarray(fit)
        return cls(fit, np.zeros(fit.shape, bool))

    @classmethod
    def _trusted(cls, fit, censored) -> "SampleMask":
        """A mask derived from a checked one (no second check)."""
        m = object.__new__(cls)
        object.__setattr__(m, "fit", fit)
        object.__setattr__(m, "censored", censored)
        return m

    def __getitem__(self, rows) -> "SampleMask":
        """The masks of the pixels ``rows``."""
        return SampleMask._trusted(self.fit[rows], self.censored[rows])

    def uncensored(self) -> "SampleMask":
        """The same fitted samples with the censored ones excluded (picking atoms uses no
        censored sample)."""
        return SampleMask._trusted(self.fit, np.zeros(self.fit.shape, bool))

    @property
    def shape(self) -> tuple:
        return self.fit.shape

    @property
    def used(self) -> np.ndarray:
        """(P, L) bool: samples that can contribute to the data term (fitted or censored)."""
        return self.fit | self.censored

    def residual(self, p: np.ndarray, model) -> np.ndarray:
        """(P, L) residual under the masks: p - model on fitted samples, max(p - model, 0) on
        censored ones, 0 elsewhere."""
        r = p - model
        return np.where(self.censored, np.maximum(r, 0.0), r * self.fit)


def check_mask(mask, shape=None) -> SampleMask:
    """``mask`` itself if it is a :class:`SampleMask` (of ``shape``); a clear error otherwise.

    Numeric arrays are refused: a weight of 0.5 must not silently become "excluded" (real
    weights are the separate ``weights`` argument of :func:`decomposition.kernels.atomlm.lm_refine`, or
    go to :func:`decomposition.model.refine.refine`).
    """
    if not isinstance(mask, SampleMask):
        what = f"an array of {mask.dtype}" if isinstance(mask, np.ndarray) else type(mask).__name__
        raise TypeError(f"expected a SampleMask (fit and censored masks), got {what}; the solver takes no "
                        f"per-sample weights (real weights, 1/variance, go to decomposition.model.refine.refine)")
    if shape is not None and mask.shape != tuple(shape):
        raise ValueError(f"the sample mask has shape {mask.shape}, the profiles {tuple(shape)}")
    return mask
