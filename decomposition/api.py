"""Public entry point: ``decompose(profiles, time_bin_ps, method=...)``.

Input handling (validation, per-pixel normalisation, saturated samples,
single-sample spikes, non-finite samples) lives here; the numerical work is in
``decomposition.convscd`` (and ``decomposition.gradbm`` for the baseline), the
slot-to-component bookkeeping in ``decomposition.components``.

Per-pixel quality flags (``DecompositionResult.flags``, uint8 bitmask):

=========== ===== ==============================================================
EMPTY         1   no component: all-zero pixel or nothing above the noise
SATURATED     2   samples at the saturation level; excluded from the fit
POOR_FIT      4   residual RMS > ``poor_fit`` x estimated noise: the data are
                  outside what the model explains (offset, unmodelled shape, ...)
SPIKE         8   single-sample spike(s) (hot pixel / cosmic ray) excluded
NONFINITE    16   NaN/inf samples (``nan_policy="omit"``); pixel not decomposed
MAX_ITER     32   the solver hit ``max_iter`` before it converged
AT_BOUND     64   a refined sigma or alpha ended at its allowed bound
TRUNCATED   128   more inter-reflections found than ``max_reflections``
=========== ===== ==============================================================
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from . import components as comp
from . import convscd as cs
from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, empty_params, time_axis_ps

__all__ = [
    "decompose",
    "DecompositionResult",
    "parse_components",
    "EMPTY",
    "SATURATED",
    "POOR_FIT",
    "SPIKE",
    "NONFINITE",
    "MAX_ITER",
    "AT_BOUND",
    "TRUNCATED",
    "FLAG_NAMES",
]

EMPTY = np.uint8(1)
SATURATED = np.uint8(2)
POOR_FIT = np.uint8(4)
SPIKE = np.uint8(8)
NONFINITE = np.uint8(16)
MAX_ITER = np.uint8(32)
AT_BOUND = np.uint8(64)
TRUNCATED = np.uint8(128)
FLAG_NAMES = {1: "EMPTY", 2: "SATURATED", 4: "POOR_FIT", 8: "SPIKE", 16: "NONFINITE",
              32: "MAX_ITER", 64: "AT_BOUND", 128: "TRUNCATED"}

_FAMILIES = {"d", "r", "s"}


@dataclass
class DecompositionResult:
    """Decomposition of profiles of shape (..., L).

    Attributes
    ----------
    direct : ndarray (..., L)              rendered direct component
    sss : ndarray (..., L)                 rendered subsurface-scattering component
    interreflections : ndarray (..., R, L) r2, r3, ... in order of delay; zeros where absent
    params : dict of ndarray               model parameters, NaN where absent
                                           (keys of ``decomposition.model``)
    residual : ndarray (..., L)            profiles minus the sum of all components
    flags : ndarray (...,) uint8           quality bitmask (module constants)
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
        v = int(self.flags[index])
        return [name for bit, name in FLAG_NAMES.items() if v & bit]


def parse_components(components) -> frozenset:
    """``"d,r,s"`` / ``("d", "s")`` / ``"ds"`` -> frozenset of family letters."""
    if isinstance(components, str):
        items = [c for c in components.replace(",", " ").replace("+", " ").split()]
        if len(items) == 1 and len(items[0]) > 1:
            items = list(items[0])
    else:
        items = list(components)
    fams = frozenset(str(c).strip().lower() for c in items)
    bad = fams - _FAMILIES
    if bad or not fams:
        raise ValueError(f"components must be a non-empty selection of 'd', 'r', 's'; got {components!r}")
    if "r" in fams and "d" not in fams:
        raise ValueError("components: inter-reflections ('r') need the direct family ('d') too")
    return fams


def _as_profiles(profiles):
    arr = np.asarray(profiles)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
                                   or arr.dtype == np.bool_):
        raise ValueError(f"profiles must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim == 0:
        raise ValueError("profiles must have at least one dimension (..., L); got a 0-d scalar")
    return arr


def decompose(profiles, time_bin_ps: float = 2.0, method: str = "convscd", *, t0_ps: float | None = None,
              components=("d", "r", "s"),
              sigma_range_ps=(1.0, 10.0), n_sigma: int = 500,
              alpha_range_per_ps=(0.01, 0.05), n_alpha: int = 500,
              coarse_sigma: int = 4, coarse_sss_sigma: int = 3, coarse_alpha: int = 3,
              off_grid: bool = True, max_components: int = 6, max_reflections: int = 3,
              max_iter: int | None = None, n_lm: int = 4, n_polish: int = 30,
              lm_tol: float = 1e-2, sparsity: float = 3.0, eps_rel: float = 0.01, noise_floor: float = 1e-3,
              rel_threshold: float = 0.05, merge_tol_bins: float = 1.0, bound_factor: float = 4.0,
              poor_fit: float = 3.0, nan_policy: str = "raise", saturation_level: float | None = None,
              spike_sigma: float = 8.0, multistart: bool = True, shared_sigma: bool = True,
              sss_after_direct: bool = True, sss_alone: bool = False, block_size: int = 256,
              refine: bool = False, stderr: bool | None = None,
              **method_options) -> DecompositionResult:
    """Decompose time profiles into direct, inter-reflection and sss components.

    Parameters
    ----------
    profiles : array_like (..., L), any real dtype (uint16 camera data included)
        Time profiles; the last axis is time.
    time_bin_ps : float
        Bin width T in ps (> 0).
    method : {"convscd", "gradbm"}
    t0_ps : float, optional
        Time of the first bin (default ``time_bin_ps``: the paper's t = T..LT).
    components : str or sequence
        Families to look for: "d" direct, "r" inter-reflections, "s" sss
        (e.g. "d,s").  Families left out are neither built into the
        dictionary nor searched; without "r" at most one Gaussian per pixel.
    sigma_range_ps, n_sigma, alpha_range_per_ps, n_alpha
        Reference kernel grid.  The paper's setting (sigma 1-10 ps, alpha
        0.01-0.05 /ps, 500 samples each) is the default; it is searched
        coarse-to-fine, never densely.
    coarse_sigma, coarse_sss_sigma, coarse_alpha : int
        Grid values correlated in the detection step (Gaussian sigmas; sss
        sigmas x alphas).  Small values are fast; refinement does the rest.
    off_grid : bool
        Keep continuous refined parameters (True) or snap them to the
        reference grid with integer-bin delays (False, the paper's setting).
    max_components : int
        Atoms per pixel in the sparse-coding step.
    max_reflections : int
        R, the number of inter-reflection slots in the output.
    max_iter : int, optional
        Outer (pick + refine) iterations per pixel; default ``max_components + 2``.
    n_lm, n_polish : int
        Levenberg-Marquardt iterations after each pick / in the final polish.
    lm_tol : float
        A pixel's refinement stops when a step gains less than lm_tol x its
        objective per sample.
    sparsity, eps_rel, noise_floor : float
        Sparsity weight mu = sparsity * s^2 and eps = eps_rel * s, with s the
        per-pixel noise estimate floored at ``noise_floor`` x the pixel's peak.
    rel_threshold : float
        The paper's 5% threshold (peak height relative to the largest component).
    merge_tol_bins : float
        Gaussians of one pixel closer than this (in bins) are merged.
    bound_factor : float
        Refined sigma/alpha stay within the grid ranges widened by this factor.
    poor_fit : float
        POOR_FIT flag when residual RMS > poor_fit x noise estimate.
    nan_policy : {"raise", "omit"}
        NaN/inf samples raise ValueError, or ("omit") flag the pixel NONFINITE
        and leave it undecomposed (NaN parameters).
    saturation_level : float, optional
        Samples >= this are saturated (flagged, excluded from the fit).  Default:
        the dtype maximum for integer input, none for float input.
    spike_sigma : float
        Single-sample spikes this many noise sigmas above both neighbours, and
        too narrow for the narrowest kernel, are excluded and flagged (0 = off).
    shared_sigma : bool
        One PSF width per pixel shared by all its components (eq. (2) has a
        single camera PSF c(t)); False lets every atom have its own width.
    sss_after_direct : bool
        Keep the sss onset at or after the direct reflection (light enters the
        surface where it is directly reflected).  Removes the near-degeneracy
        of a direct peak and an sss rising edge at the same onset.
    multistart : bool
        Where the primary (Gaussian-first) start leaves a fit above the noise,
        also run the unrestricted largest-decrease start and keep the lower
        objective (see ``convscd.solve_multistart``); False: primary start only.
    sss_alone : bool
        Also consider, per pixel, an sss component with no direct reflection
        (scenes where some pixels see only light scattered out of a
        translucent volume).  About 40 % slower; off by default because the
        paper's model gives every pixel a direct (``components="s"`` handles
        scenes with sss only).
    block_size : int
        Pixels per solver block.
    refine : bool
        After the sparse step, refine every found component's continuous
        parameters by weighted least squares on the forward model
        (:func:`decomposition.refine.refine`: variable projection,
        never worse per pixel, component set kept).  Off by default:
        ``streaklab bench tradeoff`` measures no fidelity gain over the
        solver's own off-grid polish; it does help ``off_grid=False`` output.
    stderr : bool, optional
        Add per-pixel standard errors ``<key>_stderr`` (same shapes and units
        as the parameters, NaN where absent or not identifiable) to
        ``params``, from the Fisher information at the solution with the noise
        estimated from the residual (:func:`decomposition.fisher.standard_errors`).
        Default: the same as ``refine``.
    **method_options
        Passed to the GradBM baseline for ``method="gradbm"``.

    Returns
    -------
    DecompositionResult
    """
    T = float(time_bin_ps) if np.isscalar(time_bin_ps) else np.nan
    if not (np.isfinite(T) and T > 0):
        raise ValueError(f"time_bin_ps must be a positive finite number, got {time_bin_ps!r}")
    t0 = T if t0_ps is None else float(t0_ps)
    if not np.isfinite(t0):
        raise ValueError(f"t0_ps must be finite, got {t0_ps!r}")
    if method not in ("convscd", "gradbm"):
        raise ValueError(f"method must be 'convscd' or 'gradbm', got {method!r}")
    if nan_policy not in ("raise", "omit"):
        raise ValueError(f"nan_policy must be 'raise' or 'omit', got {nan_policy!r}")
    if method == "convscd" and method_options:
        raise TypeError(f"unknown options for method 'convscd': {sorted(method_options)}")
    fams = parse_components(components)
    grid = cs.GridSpec(tuple(sigma_range_ps), n_sigma, tuple(alpha_range_per_ps), n_alpha,
                       coarse_sigma, coarse_alpha, coarse_sss_sigma).check()
    max_components = int(max_components)
    if max_components < 1:
        raise ValueError("max_components must be >= 1")
    R = int(max_reflections) if "r" in fams else 0
    if R < 0:
        raise ValueError("max_reflections must be >= 0")
    max_iter = max_components + 2 if max_iter is None else int(max_iter)
    if max_iter < 1:
        raise ValueError("max_iter must be >= 1")

    arr = _as_profiles(profiles)
    lead, L = arr.shape[:-1], arr.shape[-1]
    min_bins = max(8, int(math.ceil(6.0 * grid.sigma_range_ps[1] / T)) + 1)
    if L < min_bins:
        raise ValueError(
            f"profiles have L={L} time bins; the kernels need at least {min_bins} "
            f"(6 x sigma_max {grid.sigma_range_ps[1]:g} ps / time_bin_ps {T:g} ps + 1)")
    P = int(np.prod(lead, dtype=np.int64))
    raw = arr.reshape(P, L)
    if saturation_level is None and np.issubdtype(arr.dtype, np.integer):
        saturation_level = float(np.iinfo(arr.dtype).max)
    x = raw.astype(np.float64)

    flags = np.zeros(P, np.uint8)
    finite = np.isfinite(x).all(axis=1)
    n_bad = int(P - finite.sum())
    if n_bad and nan_policy == "raise":
        raise ValueError(f"profiles contain NaN or inf samples in {n_bad} of {P} pixels "
                         f"(use nan_policy='omit' to flag and skip them)")
    flags[~finite] |= NONFINITE

    w = np.ones((P, L))
    sat = np.zeros((P, L), bool)
    if saturation_level is not None:
        sat = x >= float(saturation_level)
        w[sat] = 0.0
        flags[sat.any(axis=1)] |= SATURATED
    w[~finite] = 0.0
    xs = np.where(w > 0, x, 0.0)
    scale = np.abs(xs).max(axis=1)
    live = finite & (scale > 0)
    flags[finite & ~(scale > 0)] |= EMPTY

    params = empty_params((P,), n_ir=R)
    info = {"method": method, "time_bin_ps": T, "t0_ps": t0, "components": "".join(sorted(fams)),
            "nan_policy": nan_policy, "saturation_level": saturation_level}
    n_iter = np.zeros(P, np.int64)
    idx_live = np.nonzero(live)[0]
    pn = np.zeros((P, L))
    pn[idx_live] = xs[idx_live] / scale[idx_live, None]
    s_est = np.zeros(P)
    if idx_live.size:
        s_est[idx_live] = _noise(pn[idx_live], w[idx_live])
    s_eff = np.maximum(s_est, noise_floor)

    if spike_sigma and idx_live.size:
        sp = _spikes(pn[idx_live], w[idx_live], s_eff[idx_live], T, grid.sigma_range_ps[0], spike_sigma,
                     rel_threshold)
        rows = idx_live[sp.any(axis=1)]
        flags[rows] |= SPIKE
        w[idx_live] = np.where(sp, 0.0, w[idx_live])
        # re-normalise without the spikes
        xs = np.where(w > 0, x, 0.0)
        scale[idx_live] = np.abs(xs[idx_live]).max(axis=1)
        ok = scale[idx_live] > 0
        flags[idx_live[~ok]] |= EMPTY
        idx_live = idx_live[ok]
        pn[idx_live] = xs[idx_live] / scale[idx_live, None]
        s_eff[idx_live] = np.maximum(_noise(pn[idx_live], w[idx_live]), noise_floor)

    t = time_axis_ps(L, T, t0)
    if method == "gradbm":
        info.update(method_options)
        _run_gradbm(pn, idx_live, scale, T, t0, R, fams, params, method_options)
    else:
        opts = dict(max_components=max_components, max_gauss=(max_components if "r" in fams else 1) if "d" in fams else 0,
                    allow_sss="s" in fams, sparsity=sparsity, eps_rel=eps_rel, max_iter=max_iter, n_lm=n_lm,
                    bound_factor=bound_factor, tie_sigma=shared_sigma, sss_after_direct=sss_after_direct,
                    lm_tol=lm_tol)
        dic = cs.get_dictionary(L, T, t0, grid, "d" in fams, "s" in fams)
        info.update(dict(
            sigma_range_ps=grid.sigma_range_ps, n_sigma=grid.n_sigma, alpha_range_per_ps=grid.alpha_range_per_ps,
            n_alpha=grid.n_alpha, coarse_sigma=grid.coarse_sigma, coarse_sss_sigma=grid.coarse_sss_sigma,
            coarse_alpha=grid.coarse_alpha, off_grid=off_grid, max_components=max_components,
            max_reflections=R, max_iter=max_iter, n_lm=n_lm, n_polish=n_polish, lm_tol=lm_tol, sparsity=sparsity,
            eps_rel=eps_rel, noise_floor=noise_floor, rel_threshold=rel_threshold, merge_tol_bins=merge_tol_bins,
            bound_factor=bound_factor, poor_fit=poor_fit, spike_sigma=spike_sigma, multistart=multistart,
            shared_sigma=shared_sigma, sss_after_direct=sss_after_direct, sss_alone=sss_alone,
            block_size=block_size, n_atoms=int(dic.fam.size), coordinates_searched=int(dic.n_coordinates)))
        hist = np.full((P, max_iter + 1), np.nan)
        lm_total, restarted = 0, 0
        bounds = cs._bounds(dic, bound_factor)
        solver = cs.solve_multistart
        for b0 in range(0, idx_live.size, int(block_size)):
            bi = idx_live[b0:b0 + int(block_size)]
            # saturated samples: excluded while atoms are picked, censored in the final refinement
            # (code 2: the true value is at least the clip level, only a model below it is a misfit)
            pb = np.where(sat[bi], x[bi] / scale[bi, None], pn[bi])
            wb = np.where(sat[bi], 2.0, w[bi])
            sb = s_eff[bi].copy()
            extra = {"sss_alone": sss_alone, "restart": multistart}

            def solve(rows, s_rows):
                st, si = solver(pb[rows], np.where(sat[bi][rows], 0.0, wb[rows]), s_rows, dic, **opts, **extra)
                comp.threshold(st, t, rel_threshold)
                comp.merge_gaussians(st, T, merge_tol_bins)
                st, model, nl = cs.polish_block(pb[rows], wb[rows], st, s_rows, dic, sparsity=sparsity,
                                                eps_rel=eps_rel, n_lm=n_polish, bound_factor=bound_factor,
                                                tie_sigma=shared_sigma, sss_after_direct=sss_after_direct,
                                                lm_tol=lm_tol)
                return st, si, model, nl

            allr = np.arange(bi.size)
            st, sinfo, model_b, nl = solve(allr, sb)
            lm_total += sinfo["lm_iterations"] + nl
            # second pass where the noise is larger where the signal is (photon noise): the
            # sparsity weight must follow the noise at the components, not in the quiet tail
            s_sig = _signal_noise(pb - model_b, model_b, wb)
            again = np.nonzero(s_sig > 1.5 * sb)[0]
            if again.size:
                sb[again] = s_sig[again]
                st2, sinfo2, _, nl2 = solve(again, sb[again])
                lm_total += sinfo2["lm_iterations"] + nl2
                cs._put(st, again, st2)
                for key in ("objective", "n_iter", "converged"):
                    sinfo[key][again] = sinfo2[key]
                restarted += sinfo2.get("restarted", 0)
                s_eff[bi[again]] = sb[again]
            hist[bi] = sinfo["objective"]
            n_iter[bi] = sinfo["n_iter"]
            restarted += sinfo.get("restarted", 0)
            flags[bi[~sinfo["converged"]]] |= MAX_ITER
            if not off_grid:
                cs.snap_to_grid(st, dic)
                cs.refit_amplitudes(pb, wb, st, dic)
            comp.threshold(st, t, rel_threshold)
            comp.merge_gaussians(st, T, merge_tol_bins)   # refinement can bring two atoms together
            act = st["fam"] != cs.FAM_NONE
            at_b = act & ((st["lsig"] <= bounds["lsig"][0] + 1e-9) | (st["lsig"] >= bounds["lsig"][1] - 1e-9))
            at_b |= (st["fam"] == cs.FAM_SSS) & ((st["lalp"] <= bounds["lalp"][0] + 1e-9)
                                                 | (st["lalp"] >= bounds["lalp"][1] - 1e-9))
            flags[bi[at_b.any(axis=1)]] |= AT_BOUND
            pb_params, trunc = comp.classify(st, scale[bi], R)
            flags[bi[trunc]] |= TRUNCATED
            for k, v in pb_params.items():
                params[k][bi] = v
        info.update(objective=hist.reshape(lead + (max_iter + 1,)), n_iter=n_iter.reshape(lead),
                    lm_iterations=lm_total, restarted=restarted)

    # Off-grid refinement (decomposition.refine); saturated/spike/non-finite samples have weight 0.
    tied = shared_sigma and method == "convscd"
    if refine and idx_live.size:
        from .refine import refine as refine_params

        params, rinfo = refine_params(x, params, time_bin_ps=T, t0_ps=t0, weights=w, shared_sigma=tied,
                                      sss_after_direct=sss_after_direct and method == "convscd")
        info.update(refine_iterations=rinfo["iterations"].reshape(lead), refined=rinfo["refined"].reshape(lead))

    rend = comp.render_params(params, L, T, t0)
    total = rend["direct"] + rend["sss"] + rend["interreflections"].sum(axis=-2)
    residual = x - total
    # quality: residual against the noise estimate on the samples that were fitted
    if idx_live.size:
        rr = residual[idx_live]
        rw = np.where(sat[idx_live], np.maximum(rr, 0.0), rr * w[idx_live]) / scale[idx_live, None]
        nw = np.maximum(((w[idx_live] > 0) | sat[idx_live]).sum(axis=1), 1.0)
        rms = np.sqrt(np.einsum("pl,pl->p", rw, rw) / nw)
        # noise that grows with the signal (photon noise) is not a misfit
        s_sig = _signal_noise(rr / scale[idx_live, None], total[idx_live] / scale[idx_live, None],
                              np.where(sat[idx_live], 2.0, w[idx_live]))
        bad = rms > poor_fit * np.maximum(s_eff[idx_live], s_sig)
        flags[idx_live[bad]] |= POOR_FIT
    has_any = np.isfinite(params["direct_delay_ps"]) | np.isfinite(params["sss_delay_ps"])
    if R:
        has_any |= np.isfinite(params["ir_delay_ps"]).any(axis=1)
    flags[finite & ~has_any] |= EMPTY
    for k in DIRECT_KEYS + SSS_KEYS:
        params[k] = params[k].reshape(lead)
    for k in IR_KEYS:
        params[k] = params[k].reshape(lead + (R,))
    info["noise_sigma"] = (s_est * scale).reshape(lead)
    stderr = bool(refine) if stderr is None else bool(stderr)
    info.update(refine=bool(refine), stderr=stderr)
    if stderr:  # decomposition.fisher: Fisher information at the solution, noise from the residual
        from .fisher import standard_errors

        params.update(standard_errors(x.reshape(lead + (L,)), params, time_bin_ps=T, t0_ps=t0,
                                      weights=w.reshape(lead + (L,)), shared_sigma=tied,
                                      sss_after_direct=sss_after_direct and method == "convscd"))
    return DecompositionResult(
        direct=rend["direct"].reshape(lead + (L,)),
        sss=rend["sss"].reshape(lead + (L,)),
        interreflections=rend["interreflections"].reshape(lead + (R, L)),
        params=params,
        residual=residual.reshape(lead + (L,)),
        flags=flags.reshape(lead),
        info=info,
    )


def _noise(pn, w):
    """Per-pixel noise level from the second differences of the whole profile."""
    return cs.estimate_noise(pn, w)


def _signal_noise(resid, model, w, min_samples=12):
    """Noise level where the signal is, from the second differences of the residual.

    Over the samples where the fitted model exceeds 10 % of its peak (photon
    noise grows with the signal, so the whole-profile estimate, dominated by
    the quiet part of the window, is too low there).  Differencing the
    residual, not the data, leaves no peak curvature in the estimate, and a
    smooth misfit (an offset) is removed by the differencing too.  0 where
    fewer than ``min_samples`` samples qualify.
    """
    mag = np.abs(model)
    region = mag >= 0.1 * mag.max(axis=1, keepdims=True)
    d2 = np.abs(resid[:, 2:] - 2.0 * resid[:, 1:-1] + resid[:, :-2])
    ok = region[:, 1:-1] & ((w[:, 2:] == 1) & (w[:, 1:-1] == 1) & (w[:, :-2] == 1))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.where(ok, d2, np.nan), axis=1)
    med = np.where(np.isfinite(med) & (ok.sum(axis=1) >= min_samples), med, 0.0)
    return 1.4826 * med / math.sqrt(6.0)


def _spikes(pn, w, s, T, sigma_min_ps, k_sigma, min_rel=0.05):
    """Single-sample spikes: too narrow for the narrowest kernel and far above the noise.

    A component with sigma >= sigma_min has neighbours at least
    exp(-T^2 / (2 sigma_min^2)) of a centred peak; a sample whose larger
    neighbour is below half of that (plus a noise margin) and which exceeds
    both neighbours by ``k_sigma`` noise sigmas is a spike.
    """
    P, L = pn.shape
    out = np.zeros((P, L), bool)
    if L < 3:
        return out
    r_min = math.exp(-0.5 * (T / sigma_min_ps) ** 2)
    c = pn[:, 1:-1]
    nb = np.maximum(pn[:, :-2], pn[:, 2:])
    # (and above the 5 % rule: a smaller spike could never become a reported component; this
    # also keeps isolated counts of photon-limited data from being called spikes)
    big = np.maximum(k_sigma * s[:, None], min_rel * np.abs(pn).max(axis=1, keepdims=True))
    sp = (c - nb > big) & (nb < 0.5 * r_min * c + 3.0 * s[:, None]) & (w[:, 1:-1] > 0)
    out[:, 1:-1] = sp
    return out


def _run_gradbm(pn, idx_live, scale, T, t0, R, fams, params, options):
    from .gradbm import gradbm  # imported lazily: the baseline is optional for the ConvSCD path

    if idx_live.size == 0:
        return
    got = gradbm(pn[idx_live], T, t0, components=tuple(sorted(fams)), max_interreflections=R, **options)
    for k in DIRECT_KEYS + SSS_KEYS:
        if k in got:
            v = np.asarray(got[k], np.float64).reshape(idx_live.size)
            if k in ("direct_amplitude", "sss_amplitude"):
                v = v * scale[idx_live]
            params[k][idx_live] = v
    if R and "ir_delay_ps" in got:
        for k in IR_KEYS:
            v = np.asarray(got[k], np.float64).reshape(idx_live.size, -1)[:, :R]
            if k == "ir_amplitude":
                v = v * scale[idx_live, None]
            params[k][idx_live, : v.shape[1]] = v
