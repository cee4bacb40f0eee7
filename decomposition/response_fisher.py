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
its fitted value understates the lifetime's error).  For count data the direct delay's and
the sss alpha's errors come from the profile deviance instead (:func:`profile_stderr`): at few
counts, and for a direct at the window's edge at any count, the deviance is far from
quadratic in them, and where it is quadratic the profile gives the Fisher error.  The
response has no width parameter: ``*_sigma_ps_stderr`` are NaN.
"""
from __future__ import annotations

import numpy as np

from .constants import FAM_NONE, FAM_SSS, POISSON_FIT_FLOOR, SSS_SLOT
from .response_atoms import slot_atoms

__all__ = ["slot_standard_errors", "profile_stderr", "PROFILE_STEP_SE"]

#: :func:`profile_stderr`'s step along the profile line, in Fisher standard errors (the
#: deviance rises by 4 there where it is quadratic: the error is half the 95 % profile interval)
PROFILE_STEP_SE = 2.0
#: Poisson scoring steps of the amplitudes and offset at each point of the profile line
PROFILE_SCORING_STEPS = 4


def slot_standard_errors(irf, t_ps, y, sw, fam, delay, lalp, amp, *, noise_sigma=None, tie_onset=None,
                         background=None, covariance=False):
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
    covariance : bool
        Also return ``cov`` (n, 3K + 1, 3K + 1): the covariance of (amplitudes, delays,
        log alphas, offset) in that order (normalised units, ps, dimensionless), NaN where
        the information is singular; rows and columns of fixed parameters are zero (a tied
        onset's row too: it moves with the direct delay).

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
    if tie_onset is not None and tie_onset.any():
        i_d, i_s = K + 0, K + SSS_SLOT
        tie = tie_onset & act[:, 0] & act[:, SSS_SLOT]
        cols[tie, i_d] += cols[tie, i_s]
        free[tie, i_s] = False
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
    out = {"amp": se[:, :K], "delay": se[:, K:2 * K],
           "alpha": np.where(fam == FAM_SSS, se[:, 2 * K:3 * K] * alpha, np.nan)}
    if covariance:
        out["cov"] = cov * np.square(noise)[:, None, None]
    return out


def profile_stderr(irf, t_ps, counts, fit, scale, fam, delay, lalp, amp, background, cov, dispersion, *,
                   parameter: str = "delay", tie_onset=None, step_se: float = PROFILE_STEP_SE):
    """Standard error of the direct delay or the sss alpha from the profile deviance (count data).

    The Fisher information is the curvature of the deviance at the solution; where the
    deviance is not quadratic over an error's range the error it gives is wrong on one side or
    both: at few photons (100 per pixel) the sss onset is nearly degenerate with the direct and
    held after it, and the deviance is skewed in the delay and in log alpha; a direct near or
    before the window's start, whose peak the counts barely hold, slides out with its amplitude
    growing to match the edge it leaves at little cost.  Here the delays and log alphas are
    moved along the profile line of the parameter p (the direct delay, or the sss's log alpha),
    theta(p) = theta_hat + (p - p_hat) cov[:, p] / var(p) (every other parameter at its
    conditional best to first order), to p_hat +- ``step_se`` x se(p); there the amplitudes and
    the offset, linear, are refitted to the counts (PROFILE_SCORING_STEPS Poisson scoring steps
    from the line's values, kept >= 0: an amplitude that must grow exponentially as its atom
    leaves the window is not held to the line's first order).  With rise D+ and D- of the
    Poisson deviance (chi2 units; read at POISSON_FIT_FLOOR, the fit's own objective) the half-widths of the profile interval are
    w+- = step_se x se / sqrt(D+-) (the Fisher error on a side where the deviance falls: the
    solution at a bound); each is then read once more where it puts the interval's edge,
    w+- <- step_se x w+- / sqrt(D+-(step_se x w+-)) (a secant step to the crossing: a skewed
    deviance is not quadratic between the first step and the edge), and the error returned
    is half the interval's length -- (w- + w+) / 2 for the delay, alpha (exp(w+) - exp(-w-)) / 2
    for alpha, whose interval is taken in log alpha -- never below the Fisher error (a side
    steeper than quadratic is the first-order line leaving the valley of the parameters it
    does not refit).  Where the deviance is quadratic, D+- = step_se^2 at both steps and the
    error is the Fisher one (for alpha, alpha sinh(se of log alpha)).

    Parameters
    ----------
    irf, t_ps
        The response and the time axis (L,), ps.
    counts : ndarray (n, L)        the counts (read on ``fit``)
    fit : ndarray (n, L) bool      fitted samples
    scale : ndarray (n,)           counts per normalised unit
    fam, delay, lalp, amp : (n, K) the fitted slots (normalised amplitudes)
    background : ndarray (n,) or None   fitted offset, normalised units, NaN where none
    cov : ndarray (n, 3K + 1, 3K + 1)   :func:`slot_standard_errors` ``cov`` (dispersion included)
    dispersion : ndarray (n,)      noise scale of the counts (the deviance is divided by its square)
    parameter : {"delay", "alpha"} the direct's delay (ps) or the sss's alpha (1/ps)
    tie_onset : ndarray (n,) bool, optional   the sss onset moves with the direct delay
    step_se : float                step, in Fisher standard errors (> 0)

    Returns
    -------
    ndarray (n,): the parameter's error (ps, or 1/ps); NaN where the slot is absent or the
    covariance singular (the Fisher error's NaN).
    """
    from .noise import count_deviance

    if not (np.isfinite(step_se) and step_se > 0):
        raise ValueError(f"step_se must be positive, got {step_se}")
    if parameter not in ("delay", "alpha"):
        raise ValueError(f"parameter must be 'delay' or 'alpha', got {parameter!r}")
    n, K = fam.shape
    j, present = (K, fam[:, 0] != FAM_NONE) if parameter == "delay" else (2 * K + SSS_SLOT, fam[:, SSS_SLOT] == FAM_SSS)
    var = cov[:, j, j]
    ok = present & np.isfinite(var) & (var > 0)
    out = np.full(n, np.nan)
    if not ok.any():
        return out
    idx = np.flatnonzero(ok)
    c = np.nan_to_num(cov[idx, :, j])
    se = np.sqrt(var[idx])
    line = c / var[idx, None]
    b0 = np.zeros(idx.size) if background is None else np.nan_to_num(np.asarray(background, np.float64)[idx])
    theta0 = np.concatenate([amp[idx], delay[idx], lalp[idx], b0[:, None]], axis=1)
    tie = np.zeros(idx.size, bool) if tie_onset is None else np.asarray(tie_onset, bool)[idx]
    f, y, m, sc = fam[idx], counts[idx], fit[idx], scale[idx]
    disp = np.asarray(dispersion, np.float64)[idx]

    has_b = np.zeros(idx.size, bool) if background is None else np.isfinite(np.asarray(background)[idx])
    on = np.concatenate([f != FAM_NONE, has_b[:, None]], axis=1)

    def deviance(theta, refit):
        d = theta[:, K:2 * K].copy()
        d[tie, SSS_SLOT] = d[tie, 0]
        phi = slot_atoms(irf, t_ps, f, d, theta[:, 2 * K:3 * K])
        x = np.concatenate([phi, np.ones((idx.size, 1, t_ps.size))], axis=1) * on[:, :, None] * sc[:, None, None]
        a = np.maximum(np.concatenate([theta[:, :K], theta[:, 3 * K:]], axis=1), 0.0) * on
        mu = np.einsum("pk,pkl->pl", a, x)
        for _ in range(refit):
            # the amplitudes and offset at their Poisson best for these delays: scoring steps
            w = np.where(m, 1.0 / np.maximum(mu, POISSON_FIT_FLOOR), 0.0)
            h = np.einsum("pkl,pl,pjl->pkj", x, w, x)
            dg = np.einsum("pkk->pk", h)
            # an atom left with (almost) nothing in the window keeps its amplitude
            h = h + np.eye(K + 1)[None] * (np.where(on, 1e-9 * dg.max(axis=1, keepdims=True) + 1e-12, 1.0))[:, :, None]
            g = np.einsum("pkl,pl->pk", x, w * (y - mu))
            step = np.linalg.solve(h, g[:, :, None])[..., 0]
            a = np.maximum(a + step, 0.0) * on
            mu = np.einsum("pk,pkl->pl", a, x)
        return count_deviance(y, mu, m, disp, floor_counts=POISSON_FIT_FLOOR)

    d0 = deviance(theta0, PROFILE_SCORING_STEPS)

    def half_width(sign, step):
        # the deviance's rise over d0 at ``step`` (n,) along the line, extrapolated as a
        # quadratic to where it rises by 1; the Fisher error where it does not rise
        rise = deviance(theta0 + sign * step[:, None] * line, PROFILE_SCORING_STEPS) - d0
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(rise > 0, step / np.sqrt(rise), np.nan)
        return np.where(np.isfinite(w), w, se)

    # first from step_se Fisher errors, then once more from the interval's edge that predicts
    # (step_se half-widths, where the rise should be step_se^2): a skewed deviance is not
    # quadratic between the two, and the second step reads it where the interval ends
    lo_w, hi_w = (half_width(sign, half_width(sign, step_se * se) * step_se) for sign in (-1.0, 1.0))
    # half the profile interval's length, never below the Fisher error: a side steeper than
    # quadratic is the first-order line leaving the valley of the parameters it does not
    # refit, not more information
    if parameter == "delay":
        out[idx] = np.maximum(0.5 * (lo_w + hi_w), se)
    else:
        alpha = np.exp(lalp[idx, SSS_SLOT])
        out[idx] = alpha * np.maximum(0.5 * (np.exp(hi_w) - np.exp(-lo_w)), se)
    return out
