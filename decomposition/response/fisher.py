"""Standard errors of a response-path fit from its Fisher information.

At the solution, the model of a pixel is m = sum_k a_k phi_k(d_k[, alpha_k]); its Jacobian has,
per present component, the columns phi_k (amplitude), a_k d phi_k / d d_k (delay) and, for
sss, a_k d phi_k / d log alpha.  With weights w (the fit's) and noise sigma of a unit-weight
sample, the covariance is sigma^2 (J^T W J)^-1; sigma is the residual estimate
sqrt(RSS_w / (n - p)) (Gaussian noise), or given (count data: 1 / model-count weights and
the measured dispersion, the Poisson Fisher information).  Where ``sss_after_direct`` holds
the onset at the direct delay the two delays are one parameter and share its error.  A fitted
constant background (the ``b`` family) is one more column, of ones: its uncertainty enters the
components' errors (an offset and a slow sss tail are partly the same light, so holding it at
its fitted value understates the lifetime's error).  For count data every error is the Fisher
one, with the weights of the deviance the fit maximises: since that fit is the Poisson maximum
likelihood, they describe its scatter at 100-10,000 photons per pixel (bench realism's
median |error| / stderr within 10 % of 0.674, except the delay of a direct truncated at the
window's start at 100 photons, whose estimate is itself biased; a profile of the deviance,
used before, made them too wide: see docs/instrument-response.md).  The
response has no width parameter: ``*_sigma_ps_stderr`` are NaN.
"""
from __future__ import annotations

import numpy as np

from ..constants import FAM_NONE, FAM_SSS, SSS_SLOT
from .atoms import slot_atoms

__all__ = ["slot_standard_errors"]


def slot_standard_errors(irf, t_ps, y, sw, fam, delay, lalp, amp, *, noise_sigma=None, tie_onset=None,
                         background=None, held=None):
    """Per-slot standard errors in the refinement layout (normalised units).

    Parameters
    ----------
    y, sw : ndarray (n, L)           profiles and square-root weights (normalised units)
    fam, delay, lalp, amp : (n, K)   the fitted slots (slot 0 direct, SSS_SLOT sss)
    noise_sigma : ndarray (n,), optional   noise of a unit-weight sample (default: from the residual)
    tie_onset : ndarray (n,) bool, optional   the sss onset is held at the direct delay
    background : ndarray (n,), optional
        Fitted constant offset (normalised units, ``y`` holds it) where finite: a column of
        ones in the information; NaN or None: no offset fitted.  Its own error is not returned.
    held : (held_delay, held_lalp) of (n, K) bool, optional
        Delays / log alphas held at given values (not parameters: no column in the
        information, their errors NaN).  A held onset is not tied to the direct.

    Returns
    -------
    dict of (n, K): ``amp``, ``delay``, ``alpha`` (alpha's error, 1/ps; NaN outside sss) --
    NaN where the slot is empty or the information matrix is singular.
    """
    n, K = fam.shape
    L = np.size(t_ps)
    act = fam != FAM_NONE
    phi, dd, dl = slot_atoms(irf, t_ps, fam, delay, lalp, derivatives=True)
    bg = np.zeros(n, bool) if background is None else np.isfinite(np.asarray(background, np.float64))
    cols = np.concatenate([phi, amp[:, :, None] * dd, amp[:, :, None] * dl, np.ones((n, 1, L))],
                          axis=1) * sw[:, None, :]
    free = np.concatenate([act, act, fam == FAM_SSS, bg[:, None]], axis=1)
    h_d, h_l = held if held is not None else (np.zeros((n, K), bool), np.zeros((n, K), bool))
    if tie_onset is not None:
        # a held onset (either) is no parameter to share
        tie_onset = tie_onset & ~h_d[:, 0] & ~h_d[:, SSS_SLOT]
    if tie_onset is not None and tie_onset.any():
        i_d, i_s = K + 0, K + SSS_SLOT
        tie = tie_onset & act[:, 0] & act[:, SSS_SLOT]
        cols[tie, i_d] += cols[tie, i_s]
        free[tie, i_s] = False
    free[:, K:2 * K] &= ~h_d
    free[:, 2 * K:3 * K] &= ~h_l
    cols = np.where(free[:, :, None], cols, 0.0)
    info = np.einsum("pjl,pml->pjm", cols, cols) + np.eye(3 * K + 1)[None] * (~free)[:, :, None]
    model = np.einsum("pk,pkl->pl", amp, phi)
    if background is not None:
        model = model + np.where(bg, np.asarray(background, np.float64), 0.0)[:, None]
    resid = (y - model) * sw
    if noise_sigma is None:
        dof = (sw > 0).sum(axis=1) - free.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            noise = np.where(dof > 0, np.sqrt(np.einsum("pl,pl->p", resid, resid) / np.maximum(dof, 1)), np.nan)
    else:
        noise = np.asarray(noise_sigma, np.float64) * np.ones(n)
    cov = np.full((n, 3 * K + 1, 3 * K + 1), np.nan)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(noise) & (np.linalg.cond(info) < 1e14)
    if ok.any():
        cov[ok] = np.linalg.inv(info[ok]) * (free[ok, :, None] & free[ok, None, :])
    cov_diag = np.einsum("pjj->pj", cov)
    se = np.sqrt(np.maximum(cov_diag, 0.0)) * noise[:, None]
    se = np.where(free, se, np.nan)
    if tie_onset is not None and tie_onset.any():
        tie = tie_onset & act[:, 0] & act[:, SSS_SLOT]
        se[tie, K + SSS_SLOT] = se[tie, K]
    alpha = np.exp(np.where(fam == FAM_SSS, lalp, 0.0))
    return {"amp": se[:, :K], "delay": se[:, K:2 * K],
            "alpha": np.where(fam == FAM_SSS, se[:, 2 * K:3 * K] * alpha, np.nan)}
