"""ConvSCD solver: convolutional sparse coding of time profiles (eqs. (3)-(5) of the paper).

What is solved
--------------
Per pixel, with the profile normalised to unit peak (see below), the objective is

    F(z) = 1/2 || r(p - sum_a k_a (*) z_a) ||_2^2  +  mu * sum_i log(1 + |z_i| / eps)

i.e. eq. (5) with the *squared* l2 data term (the standard form for coordinate
descent: it makes every one-dimensional sub-problem a quadratic plus a
log-sum term with a closed-form minimiser) and the log-sum sparsity penalty
written as ``log(1 + |z|/eps)`` (the paper's ``log|z|`` shifted so that a zero
coefficient costs nothing; ``eps`` keeps it finite).  ``r`` applies the
:class:`~decomposition.masks.SampleMask`: a sample is fitted, excluded
(detected single-sample spikes, non-finite) or censored from below (saturated:
the true value is at least the recorded one, so only a model *below* it is a
misfit, contributing max(p - model, 0)^2; such samples are never used to pick
atoms).  Coefficients are non-negative (light adds up; this also stops noise
from being explained by negative atoms).

Dictionary.  k1: unit-peak Gaussians g(t; sigma) over a sigma grid; k2: sss
kernels h(t; sigma, alpha) = g * exp(-alpha t) u(t) over a (sigma, alpha) grid,
scaled to unit peak so that every coefficient is a peak height and one
penalty treats both families alike.  Each atom is used at every integer-bin
shift from ``pre`` bins before the window start to the window end, so
components partly outside the window are representable; column norms are the
norms of the atoms *truncated to the window*.

Adaptive sparsity weight.  The noise standard deviation ``s`` of every pixel
is estimated robustly from its second differences (:mod:`decomposition.noise`; MAD / 0.6745 / sqrt(6):
smooth kernels have tiny second differences, white noise has variance 6 s^2);
the caller takes the larger of the whole-profile value and the value over the
samples above 10 % of the peak (photon noise grows with the signal), floored
at ``noise_floor`` (relative to the pixel's peak, so noiseless data still have
a finite detection limit).  Then ``mu = sparsity * s^2`` and
``eps = eps_rel * s``.  With eps << s each accepted atom costs about
``mu * log(z/eps)`` ~ 6-9 mu, so an atom enters only if it explains several
times the largest correlation pure noise produces over the whole dictionary
(about 2 log(#coordinates) s^2/2 ~ 10 s^2).  Because p is normalised per pixel
and s scales with p, the decision is exactly invariant to the profile's scale.

Physics used (eq. (2)).  One camera PSF c(t) blurs every component of a
profile, so by default (``tie_sigma``) all atoms of a pixel share one sigma;
and sss light enters the surface where the direct light is reflected, so the
sss onset is kept at or after the direct delay (``sss_after_direct``).  A
direct peak and an sss rising edge with the same onset and width are
degenerate to first order (dh/dt = g - alpha h), and these two constraints are
what makes d + s with close onsets separable at all in noise.

Algorithm: batched greedy convolutional coordinate descent with local refinement
-------------------------------------------------------------------------------
1. Gauss-Southwell pick.  For a block of pixels (pixels x time array) the
   correlations of the residual with every atom at every integer shift are
   computed at once: for a pixel's first atom by FFT with the precomputed
   spectra of the coarse dictionary (only the families some pixel may take);
   once it has one, with the Gaussian and the sss kernels at the pixel's own
   sigma, by compiled direct correlations that use the sss kernel's one-pole
   structure (:mod:`decomposition.kernels.pickcorr`).  The selection is compiled too
   (:mod:`decomposition.kernels.pick`).  For a zero coordinate with column norm n and
   correlation c the one-dimensional problem is
   (n/2)(z - u)^2 + mu log(1 + z/eps), u = c/n, whose minimiser on z >= 0 is
   the larger root of z^2 + (eps - u) z + (mu/n - u eps) = 0 if it beats z = 0.
   Each pixel takes the coordinate with the largest objective decrease
   (coordinates are ranked by c^2/n and the exact decrease is evaluated for
   the best three); a pixel stops when no coordinate decreases its objective
   (or at max_iter / max_components).  The *first* atom is taken from the
   Gaussian family by largest coefficient (the atom matching the main peak):
   the largest-decrease rule would start with a narrow sss atom swallowing the
   direct peak and the tail at once, or with a broad Gaussian covering several
   components, and no local refinement separates those again.  Where that
   start leaves a data term above 1.5x its noise expectation, the
   unrestricted start is run too and the pixel keeps the lower objective.
2. Local refinement (coarse-to-fine).  The paper's reference grid (sigma
   1-10 ps and alpha 0.01-0.05 /ps, 500 samples each: 250,000 sss atoms) is
   never correlated densely.  The coarse grid only *detects* atoms; after
   every pick the active atoms' delays, shared sigma, alpha and amplitudes are
   refined jointly and continuously by a few Levenberg-Marquardt steps
   (analytic Jacobians of both kernels; near sss onsets parametrised as
   direct delay + gap with an active set for gap >= 0), a step accepted for
   a pixel only if F decreases (:mod:`decomposition.kernels.atomlm`, compiled, one
   pixel at a time, each atom evaluated on its own support).  Refining
   before the next pick matters: a coarse atom that is slightly off leaves a derivative-shaped residual that
   would otherwise be "explained" by spurious extra atoms.
3. After the 5 % threshold and merging (``decomposition.model.components``), the
   kept atoms are refined on the data term alone (the usual debiasing after
   sparse selection: the log-sum penalty shrinks amplitudes along the d/s
   degeneracy), with a restart of sss onsets stuck at the direct delay or far
   before it.  With ``off_grid=False`` the refined values are then snapped
   to the reference grid (integer-bin delays, the grid's sigma/alpha) and the
   amplitudes re-fitted: the paper's discrete setting.
4. The objective of steps 1-2 never increases: a pick is an exact
   coordinate minimisation, LM steps are accepted only where F, evaluated
   exactly in float64, decreases, and
   amplitude-zero atoms are dropped (no change in F).  The per-pixel
   objective after every outer iteration is returned so callers and tests
   can check it.

Why this choice: pure coordinate descent over a 250k x L dictionary is
hopeless, and over a coarse dictionary alone it leaves grid-mismatch residuals
that become false components.  Greedy Gauss-Southwell plus continuous local
refinement keeps the paper's objective and sparsity model, finds the number of
components automatically, costs a handful of FFT passes per pixel, and gives
off-grid parameters.

Performance.  The per-pixel loops (the LM, the own-width correlations, the selection) are
compiled with numba and run one pixel at a time: each atom lives on its own support (a
Gaussian on a few widths, an sss tail by a one-pole recursion), so the normal equations sum
only over overlapping supports instead of building block-wide (P, K, 4, L) Jacobians.  The
compiled kernels release the GIL, so threads of one process scale nearly as processes do.  The
kernels are compiled without fast-math: reassociated sums and fused multiply-adds would follow
the CPU, and a chunk recomputed on another node must write the same bytes.  The first call in
a fresh install compiles the kernels (once; numba caches them next to the sources).  Measured
profiles, speeds and what was tried and not kept: docs/history.md.
"""
from __future__ import annotations

import numpy as np

from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, RESTART_FACTOR
from .dictionary import Dictionary, get_dictionary  # noqa: F401
from ..masks import SampleMask, check_mask
from ..options import GridSpec  # noqa: F401
from ..kernels.pickcorr import PickWorkspace
from .polish import polish_block, refit_amplitudes, snap_to_grid  # noqa: F401
from .score import score_coarse, score_pixel
from ..model.slots import (drop_zero, linked_onsets, new_state, objective, parameter_bounds,  # noqa: F401
                           put, refine_atoms, take)

__all__ = [
    "GridSpec",
    "Dictionary",
    "get_dictionary",
    "solve_block",
    "solve_multistart",
    "polish_block",
    "snap_to_grid",
    "refit_amplitudes",
    "objective",
    "FAM_NONE",
    "FAM_GAUSS",
    "FAM_SSS",
]


def solve_block(p, mask: SampleMask, s_eff, dic: Dictionary, *, max_components=4, max_gauss=4, allow_sss=True,
                sparsity=3.0, eps_rel=0.01, max_iter=8, n_lm=8, bound_factor=4.0, first_gauss=None,
                tie_sigma=True, sss_after_direct=True, lm_tol=1e-6, workspace: PickWorkspace | None = None):
    """Greedy convolutional coordinate descent with local refinement on a block.

    Parameters
    ----------
    p : ndarray (P, L) float64
        Profiles normalised to unit peak.
    mask : SampleMask
        Fitted and censored samples (censored ones take part in the refinement only).
    s_eff : ndarray (P,)
        Noise standard deviation per pixel (already floored, > 0).
    dic : Dictionary
    max_components, max_gauss : int
        Bounds on the number of atoms per pixel (all / Gaussian family).
    allow_sss : bool
        At most one sss atom per pixel when True, none when False.
    sparsity, eps_rel : float
        mu = sparsity * s^2, eps = eps_rel * s.
    max_iter : int
        Bound on the outer (pick + refine) iterations per pixel.
    n_lm : int
        Levenberg-Marquardt iterations after each pick.
    tie_sigma : bool
        One PSF width per pixel (eq. (2): a single c(t) blurs every component).
        A new atom takes the pixel's width when that decreases F; pixels whose
        atoms share a width keep sharing it in the refinement.
    sss_after_direct : bool
        The sss onset is kept at or after the earliest Gaussian (light enters
        the surface where it is directly reflected, so sss cannot arrive first).
    lm_tol : float
        Refinement of a pixel stops once a step gains less than lm_tol times
        the objective per fitted sample.
    first_gauss : ndarray (P,) bool, optional
        Pixels whose first pick must come from the Gaussian family (the
        second start of :func:`solve_multistart`).
    workspace : PickWorkspace, optional
        Scratch space of the own-width pick, held by the caller to reuse it across blocks
        (a fresh one per call when not given).

    Returns
    -------
    state : dict of (P, K) arrays: fam, amp (model amplitude), delay (ps),
        lsig (log sigma_ps), lalp (log alpha_per_ps), pen (penalty scale).
    info : dict with ``objective`` (P, max_iter + 1; NaN after a pixel stopped),
        ``n_iter`` (P,), ``converged`` (P,), ``lm_iterations``, ``mu``, ``eps``.
    """
    check_mask(mask, p.shape)
    P, L = p.shape
    K = int(max_components)
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    mu = sparsity * s_eff * s_eff
    eps = eps_rel * s_eff
    bounds = parameter_bounds(dic, bound_factor)
    st = new_state(P, K)
    hist = np.full((P, max_iter + 1), np.nan)
    r0 = mask.residual(p, 0.0)
    obj = 0.5 * np.einsum("pl,pl->p", r0, r0)
    hist[:, 0] = obj
    n_iter = np.zeros(P, np.int64)
    done = np.zeros(P, bool)
    converged = np.zeros(P, bool)
    first_family = np.zeros(P, np.int8)
    weighted = not bool(mask.fit.all())
    lm_total = 0
    model = np.zeros((P, L))
    workspace = PickWorkspace() if workspace is None else workspace   # reused by every pick
    for it in range(1, max_iter + 1):
        idx = np.nonzero(~done)[0]
        if idx.size == 0:
            break
        r = (p[idx] - model[idx]) * mask.fit[idx]
        fam = st["fam"][idx]
        n_act = (fam != FAM_NONE).sum(1)
        room = n_act < K
        allow_g = room & ((fam == FAM_GAUSS).sum(1) < max_gauss)
        allow_s = room & allow_sss & ~(fam == FAM_SSS).any(1)
        if first_gauss is not None:
            allow_s &= ~(first_gauss[idx] & (n_act == 0))
        min_s = np.full(idx.size, -np.inf)
        if sss_after_direct:
            min_s = np.where(fam == FAM_GAUSS, st["delay"][idx], np.inf).min(axis=1)
            min_s[~np.isfinite(min_s)] = -np.inf
        cand = {k: np.zeros(idx.size, v.dtype) for k, v in st.items()}
        dec = np.zeros(idx.size)
        # a measured response has one width: its coarse dictionary is every pixel's own
        own = (n_act > 0) if tie_sigma and dic.response is None else np.zeros(idx.size, bool)
        for grp, scorer in ((~own, "coarse"), (own, "pixel")):
            gsel = np.nonzero(grp & (allow_g | allow_s))[0]
            if gsel.size == 0:
                continue
            if scorer == "coarse":
                by_size = None if first_gauss is None else (first_gauss[idx[gsel]] & (n_act[gsel] == 0))
                c_, d_ = score_coarse(r[gsel], mask.fit[idx[gsel]], weighted, dic, mu[idx[gsel]], eps[idx[gsel]],
                                       allow_g[gsel], allow_s[gsel], min_s[gsel], by_size)
            else:
                sig = np.exp(np.where(fam[gsel] != FAM_NONE, st["lsig"][idx[gsel]], -np.inf).max(axis=1))
                c_, d_ = score_pixel(r[gsel], mask.fit[idx[gsel]], weighted, dic, sig, mu[idx[gsel]], eps[idx[gsel]],
                                     allow_g[gsel], allow_s[gsel], min_s[gsel], bound_factor, workspace)
            for k in cand:
                cand[k][gsel] = c_[k]
            dec[gsel] = d_
        stop = ~(dec > 1e-12 * np.maximum(obj[idx], 1e-300))
        converged[idx[stop]] = True
        done[idx[stop]] = True
        go = ~stop
        gi = idx[go]
        if gi.size == 0:
            break
        slot = np.argmax(st["fam"][gi] == FAM_NONE, axis=1)
        for k in st:
            st[k][gi, slot] = cand[k][go]
        if it == 1:
            first_family[gi] = cand["fam"][go]
        bdec = dec
        obj[gi] = obj[gi] - bdec[go]
        sub = take(st, gi)
        sub, o, nl, m_sub = refine_atoms(t, p[gi], mask[gi], sub, mu[gi], eps[gi], bounds, n_lm, obj[gi].copy(),
                                         tie_sigma, sss_after_direct, lm_tol, return_model=True, response=dic.response)
        exact = o       # F evaluated exactly after refinement (not the FFT pick's estimate)
        drop_zero(sub)
        put(st, gi, sub)
        model[gi] = m_sub
        obj[gi] = exact
        hist[gi, it] = exact
        n_iter[gi] = it
        lm_total += nl
    r_end = mask.residual(p, model)
    info = {"objective": hist, "n_iter": n_iter, "converged": converged, "lm_iterations": lm_total,
            "mu": mu, "eps": eps, "coordinates_searched": dic.n_coordinates,
            "first_family": first_family,
            "data_term": 0.5 * np.einsum("pl,pl->p", r_end, r_end)}
    return st, info


def solve_multistart(p, mask: SampleMask, s_eff, dic: Dictionary, sss_alone=False, restart=True, **opts):
    """Two greedy starts per pixel where needed; keep the lower objective.

    Greedy selection by largest objective decrease (Gauss-Southwell-q) tends
    to start with a narrow sss atom that swallows the direct peak together
    with the sss tail, after which local refinement cannot separate them; it
    also prefers a broad Gaussian covering several components.  The primary
    start therefore takes its *first* atom from the Gaussian family by largest
    coefficient (Gauss-Southwell-r: the atom that matches the main peak), all
    later picks by largest decrease.  Where that start does not explain the
    data down to the noise (data term above 1.5x its expected value for the
    estimated noise), the unrestricted Gauss-Southwell-q start is run as well
    and each pixel keeps the start with the lower final objective (both are
    monotone, so the kept history is too).

    ``restart=False`` keeps the primary start only.

    With ``sss_alone`` (for scenes where some pixels hold an sss component and
    no direct reflection) one unrestricted pick with its refinement is also
    tried for every pixel and kept where a single sss atom reaches a lower
    objective, and a direct sitting on an sss onset is dropped where that
    lowers the objective (:func:`_backward_direct`).  It costs about 40 % more
    time and is off by default: in the paper's model every pixel has a direct.
    """
    check_mask(mask, p.shape)
    has_g = bool(np.any(dic.fam == FAM_GAUSS)) and opts.get("max_gauss", 1) > 0
    expected = 0.5 * mask.used.sum(axis=1) * s_eff * s_eff
    first = np.ones(p.shape[0], bool) if has_g else None
    st, info = solve_block(p, mask, s_eff, dic, first_gauss=first, **opts)
    alone = np.zeros(p.shape[0], bool)
    if sss_alone and has_g and opts.get("allow_sss", True) and np.any(dic.fam == FAM_SSS):
        # A profile that is an sss alone gets a spurious direct (and more Gaussians) from the
        # Gaussian-first start; one unrestricted pick plus refinement is tried for every
        # pixel and kept where its objective is lower
        one, info1 = solve_block(p, mask, s_eff, dic, **{**opts, "max_iter": 1, "n_lm": 3 * opts.get("n_lm", 4)})
        alone = (_final(info1["objective"]) < _final(info["objective"])) & (one["fam"] == FAM_SSS).any(axis=1)
        a = np.nonzero(alone)[0]
        if a.size:
            k1 = one["fam"].shape[1]
            for key in st:
                st[key][a] = 0
                st[key][a, :k1] = one[key][a]
            st["pen"][a, k1:] = 1.0
            info["objective"][a] = np.nan
            info["objective"][a, :2] = info1["objective"][a]
            for key in ("n_iter", "converged", "first_family", "data_term"):
                info[key][a] = info1[key][a]
            info["converged"][a] = True
        info["lm_iterations"] += info1["lm_iterations"]
    info["sss_alone"] = int(alone.sum())
    redo = (np.nonzero((info["data_term"] > RESTART_FACTOR * expected) & ~alone)[0] if has_g and restart
            else np.zeros(0, np.int64))
    info["restarted"] = redo.size
    if redo.size:
        st2, info2 = solve_block(p[redo], mask[redo], s_eff[redo], dic, **opts)
        f1 = _final(info["objective"][redo])
        f2 = _final(info2["objective"])
        better = f2 < f1
        b = redo[better]
        put(st, b, take(st2, better))
        for key in ("objective", "n_iter", "converged", "first_family", "data_term"):
            info[key][b] = info2[key][better]
        info["lm_iterations"] += info2["lm_iterations"]
    if sss_alone and has_g and opts.get("allow_sss", True):
        _backward_direct(p, mask, s_eff, dic, st, info, opts)
    return st, info


def _backward_direct(p, mask, s_eff, dic, st, info, opts):
    """Backward step: drop a direct that sits on an sss onset where that lowers F.

    A profile that is an sss component alone is first given a Gaussian by the
    Gaussian-first start; the sss then takes the rest and both fit.  Removing
    the Gaussian, re-refining the remaining atoms and keeping the result where
    the objective (data term plus penalty) is lower undoes that.  The kept
    value replaces the pixel's last objective entry, which it lowers, so the
    history stays monotone.
    """
    lk, dsl, ssl = linked_onsets(st)
    cand = np.nonzero(lk)[0]
    if cand.size == 0:
        return
    L = p.shape[1]
    t = dic.t0_ps + dic.time_bin_ps * np.arange(L)
    sp = opts.get("sparsity", 3.0)
    er = opts.get("eps_rel", 0.01)
    mu = sp * s_eff[cand] ** 2
    eps = er * s_eff[cand]
    alt = take(st, cand)
    r_ = np.arange(cand.size)
    alt["fam"][r_, dsl[cand]] = FAM_NONE
    alt["amp"][r_, dsl[cand]] = 0.0
    bounds = parameter_bounds(dic, opts.get("bound_factor", 4.0))
    alt, o, nl, m = refine_atoms(t, p[cand], mask[cand], alt, mu, eps, bounds, 2 * opts.get("n_lm", 4), None,
                                 opts.get("tie_sigma", True), opts.get("sss_after_direct", True),
                                 opts.get("lm_tol", 1e-2), return_model=True, response=dic.response)
    drop_zero(alt)
    hist = info["objective"]
    last = hist.shape[1] - 1 - np.argmax(np.isfinite(hist[cand])[:, ::-1], axis=1)
    cur = hist[cand, last]
    better = o < cur
    b = cand[better]
    put(st, b, take(alt, better))
    hist[b, last[better]] = o[better]
    r = mask[b].residual(p[b], m[better])
    info["data_term"][b] = 0.5 * np.einsum("pl,pl->p", r, r)
    info["lm_iterations"] += nl
    info["backward"] = int(b.size)


def _final(hist):
    """Last finite value of each row of an objective history."""
    ok = np.isfinite(hist)
    last = hist.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1)
    return hist[np.arange(hist.shape[0]), last]

