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

Performance.  Measured on the 2-core machine with 1024 synthetic pixels
(``decomposition.evaluation.synthetic.make_profiles(1024, 512, nsr=0.05,
noise="white", seed=0)``, kinds a, b, c; ``decompose(profiles,
time_bin_ps=2.0)`` with default options, one process, best of 3 after a
warm-up call) and with ``streaklab bench speed --methods convscd``
(64 x 672 x 512, NSR 0.05, all stages of ``streaklab decompose``):

==========================================  =========  ==========  =========
step                                        1024 px     fidelity    bench, 2
                                            (px/s)                  workers
==========================================  =========  ==========  =========
block-wide numpy (previous release)         594        0.95189     1,051
LM compiled per pixel (atomlm)              1,019      0.95189
selection compiled (pick)                   1,082      0.95189     ~1,400*
own-width correlations compiled (pickcorr)  ~1,900     0.95189     ~2,000*
coarse pass: allowed families only          ~2,060     0.95189     2,621
==========================================  =========  ==========  =========

(* measured while other work shared the machine.)  With 2 threads instead of
2 worker processes the bench gives 2,800 px/s: the compiled kernels release
the GIL.  Where the time goes now (cProfile of the 1024 px run): the
compiled LM about a third; the own-width correlations and the selection
about 15 %; the coarse FFT pass about 8 %; the rest is block bookkeeping in
``solve_block``, noise estimates (medians), spike detection and rendering
the final components with :mod:`core.model`.  Why it helped: the
numpy LM spent its time on (P, K, 4, L) float32 Jacobians, window placement
and live-set bookkeeping, and the own-width pick on per-pixel kernel
evaluation and FFTs; per pixel, compiled, each atom lives on its own
support (a Gaussian on +-8 sigma, an sss tail by a one-pole recursion) and
the normal equations sum only over overlapping supports.  The first call
in a fresh install compiles the kernels (10-15 s, once; numba caches
them next to the sources).  Tried without a measurable gain earlier: float32
FFTs for picking, blocks larger than 256 pixels (since then, 512 did: see below).

On the paper scenes (the default ``bench speed`` cube, with the search, grow and prune
stages), one thread, 2,000 pixels of the bench cube (``make_cube(8, 672, 512, nsr=0.05,
seed=0, ranges="paper", bin_integrated=True)``), best of 3, seconds per stage:

==================  =======  ======  =========  ==========
version             detect   search  the rest   total
==================  =======  ======  =========  ==========
before              1.20     1.15    0.39       2.74
now                 0.85     0.51    0.22       1.58
==================  =======  ======  =========  ==========

(2,000 pixels at 1,000 photons: 2.35 -> 1.29 s; stages best of 3 runs each.)  ``streaklab
bench speed --shape 32 672 512 --methods convscd --workers threads:2`` in the same minutes (load
average 0.7-1.3 on the 2 cores): 1,103 -> 1,880 px/s all stages, ``--photons 1000``: 1,298 ->
2,449 px/s.  What did it: the LM's normal equations
summed segment by segment with four sums side by side, and over the sss tail past the other
atoms in closed form (:func:`decomposition.kernels.atomlm._tail_sums`); atom values from one erfc per
bin with stepped exponentials; the own-width pick correlating only what a pixel may take (no
sss kernels once it has its sss atom: two thirds of the picks); NNLS, rendering, window
measures, medians and the count gain compiled; identical search starts polished once.
Results are equal to rounding (no pixel of 2,000 differs by more than 1e-6 relative; bench
accuracy unchanged to 6 decimals).  The compiled LM is now about 55 % of the time (110,000
iterations per 2,000 pixels at ~6.5 us).  Tried and dropped: polishing the search's starts
in rounds and stopping the hopeless ones (the restarts cost what the dropped iterations saved,
and fidelity fell), a short polish of every start with the leading one finished (winners
change), fewer LM steps per pick or per polish (fidelity moves by up to 0.01 either way),
fast-math reductions (slower, and not reproducible).

Later, on ``streaklab bench speed --shape 16 672 512 --methods convscd --workers threads:2``
(white NSR 0.05 / ``--photons 100``): 1,551 / 1,780 px/s before, then -- each step measured
on its own -- one BLAS thread per command (an idle OpenBLAS pool had spun beside the two dask
threads; +5 % white), trial steps rendered without their derivative columns (-2 / -3 % LM
time, identical results), Gaussians cut at 6 widths and the sss tail's recursion from u = -4
(LM time -13 / -9 %; fidelity the same to 4 decimals), a count refit skipped where it would
repeat itself (identical results), and blocks of 512 pixels (+2-4 / +7-9 %): 1,676-1,713 /
2,039-2,054 px/s; then the FFT correlation 64 rows at a time and the noise at the signal in one
compiled pass (both identical results).  On the default 64 x 672 x 512 cube: white 1,700 ->
1,915-1,917 px/s (target 2,000, not met), 100 photons 2,077 -> 2,489-2,536 (met).  The LM rejects 37-41 % of its trial steps in the search's polish; a first
damping of 1e-2 instead of 1e-3 rejected fewer and ended lower (summed objective -4 %, photon
LM time -6 %) but moved bench accuracy's means by -0.005..+0.009 and its targets by -1 / -2 on
two seeds: not kept.  Memory: numpy's huge pages off (``NUMPY_MADVISE_HUGEPAGE=0``) steadied one
thread's timing on 2,048 pixels but did not speed up the bench: not set.

Then: medians by an in-place quickselect (numba's ``np.partition`` copied every row: 300 x 512
masked medians 2.32 -> 1.90 ms) and the search's smoothing with its padding inside the FFT and
its filter built in place (6.1 -> 4.2 ms), both exact: default cube 1,951 / 2,000 -> 1,996 /
2,004 px/s alternated; three runs an hour later 1,968-1,975.  Measured, not kept: a looser LM
stop (``lm_tol`` 0.03 / 0.1: +4.5 / +7.5 % px/s, split over detection and search alike, but
where the direct / sss split is weakly determined the direct's amplitude error grows from
0.016 to 0.020 / 0.029, median of 40 pixels in ``tests/test_decompose_irf.py``; position and
lifetime errors on 1,200 paper pixels unchanged); glibc's malloc told to keep freed blocks up to
32 MiB (``mallopt``: 25,000-36,000 page faults -> 12 in one thread, +2-3 % there, nothing in the
threaded bench).

Then: the Marquardt step by Cholesky factorisation (the damped Gram matrix is positive definite)
instead of Gaussian elimination with pivoting: the LM calls of one decompose replayed (2,048
pixels of the default cube) 0.94 -> 0.91-0.92 s, the same iterations and objectives within
3e-13; ``--repeat 3`` median 1,984 -> 2,005 px/s (the two medians an hour apart), alternated
pairs 1,920 (compiling) / 1,993 / 1,963 -> 2,002 / 1,989 / 1,978: within the machine's noise.  Where the LM's
time goes (each part run twice per iteration in a replay, the increase read as its cost, of
0.93 s): the normal equations about 0.44 s, the trial render 0.30, the accepted step's
derivative columns 0.28, the damped solve 0.14 (before Cholesky), the trial objective 0.06.
The search's polishes are two thirds of the LM's iterations; 19 % of them stop at ``n_polish``
(30 iterations), a third of the search's LM time.  Threads: 2 threads of one process decompose
2,041-2,132 px/s where two processes side by side do 2,207 (1,119 + 1,088) and one thread
1,131-1,142: per stage, the time spent waiting (wall less thread CPU time) is 2 % of the stages'
time and their CPU time rises 3 % (shared caches); the interpreter lock is not the lever.
Measured again, not kept: ``lm_tol`` 0.05 everywhere (+3.8 % px/s, three alternated pairs;
paper scenes 36 points +0.0002, seed 2 +0.0006, within their noise) saves only 6.5 % of the
search's LM iterations, and on single pixels chosen by earlier tests it moved which start wins
and a fast-sss-hump pixel's fidelity (0.985 -> 0.922).  The amplitude error quoted above is the
data's, not the stop's: on that test's scenes (direct and sss at one onset, SNR 100) the
direct's median amplitude error is 0.016 / 0.024 / 0.021 / 0.063 (seeds 3-6) at 1e-2 and
0.023 / 0.024 / 0.021 / 0.063 at 0.05, the oracle's 0.004-0.006, and the data term equals the oracle's to 0.01 noise
variances (the split at a shared onset is weakly determined; the oracle starts at it).

Then: erfcx from a table of degree-12 polynomials, one per half unit of u below 10
(:func:`decomposition.kernels.jit.erfcx`, relative error 4e-15; 6 against 17 ns for exp(u^2) erfc(u)),
and the sss atom's samples as g erfcx(u) where u >= 0 and 2 f - g erfcx(-u) elsewhere
(:func:`decomposition.kernels.jit.sss_erfc_part`; g and f stepped from bin to bin), so no library
transcendental per sample in the atoms or the own-width pick; and the LM's trial objective,
for pixels without a censored sample, without a branch per sample and with four sums side by
side.  The LM calls of one decompose replayed (1,024 pixels of ``make_profiles(..., seed=3,
ranges="paper", bin_integrated=True)``, 86,146 iterations): 6.34-6.41 -> 5.83-6.00 us per
iteration, the same iterations and objectives; bench accuracy's 54 points (seeds 0-2) the same
to four decimals.  ``bench speed`` (default cube, 2 threads), alternated with the code before on a
slow day: white 1,392 / 1,442 / 1,427 -> 1,471 / 1,520 / 1,523 px/s (+5-7 %); ``--photons 100``
1,929 / 1,911 -> 1,916 / 1,945 (no change); the count polish's Poisson deviance then compiled
(:func:`decomposition.noise._masked_deviance_rows`, one pass per row instead of six full-size
temporaries; the count polish 0.243 -> 0.194 s of 1.7 s on 2,048 pixels at 100 photons, count
data's fidelities and flags identical on 3,200 pixels): ``--photons 100`` 1,967 / 1,887 ->
2,030 / 2,052 px/s, alternated.  The signal-noise law's fit likewise in one kernel per row
(:func:`decomposition.noise.signal_variance`: the stage 0.073 -> 0.042 s on 2,048 white pixels,
the laws the same to 1e-13): white 1,412 / 1,453 / 1,433 -> 1,501 / 1,511 / 1,485 px/s with all
of these, alternated.  Measured, not kept: an Anscombe transform in one compiled pass
(4.6x faster in float64, but float32 counts were transformed in float32 and would change; no
gain in the stages); numba's fast-math flags
(``reassoc``, ``contract``) took the LM to 5.2 us per iteration, but reassociated sums follow
the CPU's vector width and fused multiply-adds its instruction set, so a chunk recomputed on
another node of a cluster would no longer write the same bytes; numba's ``arcp`` on top: no
gain; four interleaved recursions for the sss tail (its one-pole product is not the bottleneck:
an sss atom costs 0.5-1 us, mostly its exactly evaluated rise); a countdown instead of the
modulo that restarts the stepped exponentials: no gain; Nielsen's damping update (gain ratio
instead of /3 and x4): 4 % fewer iterations but more of them accepted (each accepted one builds
the normal equations), slower.  The slow pixels of the search's polish alternate accepted and
rejected steps (13 % stop at ``n_polish``; 4 % of the starts end more than 1 % above the
objective 200 iterations reach).
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
        own = (n_act > 0) if tie_sigma else np.zeros(idx.size, bool)
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
                                         tie_sigma, sss_after_direct, lm_tol, return_model=True)
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
                                 opts.get("lm_tol", 1e-2), return_model=True)
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

