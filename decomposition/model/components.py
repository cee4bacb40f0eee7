"""From solver atoms to named components: threshold, merge, classify, render.

The solver (``decomposition.methods.convscd``) returns, per pixel, up to K atoms in
"slot" arrays of shape (P, K): family (Gaussian or sss), amplitude, delay,
log sigma, log alpha.  This module turns them into the parameter dict of
``core.model`` (direct d, inter-reflections r2, r3, ..., sss s):

1. Threshold (the paper's global 5% rule, applied per pixel): an atom is kept
   if the peak height of its rendered component *inside the time window*
   is at least ``rel_threshold`` of the largest such peak height in the pixel,
   or if it is significant against the noise where it lies (its in-window energy
   sum c_i^2 / s^2 at least ``significance_chi2``): a faint echo far from a bright
   direct is real when the noise says so, whatever its ratio to the direct (only an
   atom resolved from the larger ones: a faint atom under a bright one corrects its shape).
   Peak height (not the raw coefficient) is used because the two families
   have differently scaled kernels; it is what a user sees in the profile.
   An atom that runs off the window's edge (:func:`off_window`) is judged by its
   in-window part like every other.
2. Merge: Gaussian atoms of one pixel whose delays differ by less than
   ``merge_tol_bins`` time bins are one component split in two; they are
   replaced by a single Gaussian with the same total area, area-weighted mean
   delay and the combined second moment.
3. Physics (``sss_after_direct``): an sss onset before the direct is moved to the direct's
   delay (light enters the surface where it is directly reflected).
4. Classify: the earliest Gaussian is the direct reflection d; later ones are
   r2, r3, ... in order of delay; the sss atom (at most one) is s.

Everything works on whole blocks with array operations; the only Python loops
run over the (few) slots.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import (FAM_GAUSS, FAM_NONE, FAM_SSS, OFF_WINDOW_EDGE_SIGMA, OFF_WINDOW_MASS, RESOLVED_SIGMA, SSS_RESOLVED_CHI2_FACTOR,
                         SIGNIFICANCE_WEIGHT_CAP)
from ..kernels.atomlm import atom_weighted_squares, atom_window_sums, state_models
from .atoms import params_components, slot_atoms
from .slots import axis_of
from core.model import BACKGROUND_KEY, empty_params

__all__ = ["peak_heights", "window_measures", "window_fraction", "off_window", "runs_off_window", "threshold",
           "keep_atoms",
           "merge_gaussians",
           "clip_sss_onset", "classify", "render_params"]


def _in_window(st: dict, t_ps: np.ndarray):
    """What the window sees of the unit atoms of the active slots: (rows, slots, sums (n, 3)) with
    the largest value, the sum and the sum of squares of each atom over the window's samples."""
    act = st["fam"] != FAM_NONE
    pi, ki = np.nonzero(act)
    sums = atom_window_sums(*axis_of(t_ps), t_ps.size, st["fam"][pi, ki], st["delay"][pi, ki], st["lsig"][pi, ki],
                            st["lalp"][pi, ki])
    return pi, ki, sums


def peak_heights(st: dict, t_ps: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Peak height inside the window of every active atom, shape (P, K); 0 for empty slots."""
    return window_measures(st, t_ps)[0]


def window_measures(st: dict, t_ps: np.ndarray, weights=None, irf=None):
    """What the window sees of every active atom: its peak height max_i |c_i| and its energy
    sum_i c_i^2 over the window's samples, both (P, K), units of the profile and its square;
    0 for empty slots.  ``weights`` (P, L): the energy is sum_i w_i c_i^2 instead (relative
    weights of the samples, :attr:`Detection.weights`), each weight at most
    SIGNIFICANCE_WEIGHT_CAP.  ``irf``: the atoms are a measured response's
    (:func:`decomposition.model.atoms.slot_atoms`, their largest sample the height)."""
    act = st["fam"] != FAM_NONE
    h, e = np.zeros(act.shape), np.zeros(act.shape)
    if irf is not None:
        if act.any():
            phi = slot_atoms(irf, t_ps, st["fam"], np.nan_to_num(st["delay"]), np.nan_to_num(st["lalp"]))
            a = np.abs(st["amp"])
            h = a * phi.max(axis=2)
            if weights is None:
                e = a * a * np.einsum("pkl,pkl->pk", phi, phi)
            else:
                w = np.minimum(np.asarray(weights, np.float64), SIGNIFICANCE_WEIGHT_CAP)
                e = a * a * np.einsum("pkl,pkl,pl->pk", phi, phi, w)
        return h, e
    if act.any():
        pi, ki, sums = _in_window(st, t_ps)
        a = np.abs(st["amp"][pi, ki])
        h[pi, ki] = a * sums[:, 0]
        if weights is None:
            e[pi, ki] = a * a * sums[:, 2]
        else:
            e[pi, ki] = a * a * atom_weighted_squares(*axis_of(t_ps), t_ps.size, st["fam"][pi, ki], st["delay"][pi, ki],
                                                      st["lsig"][pi, ki], st["lalp"][pi, ki], weights, pi,
                                                      SIGNIFICANCE_WEIGHT_CAP)
    return h, e


def window_fraction(st: dict, t_ps: np.ndarray, irf=None) -> np.ndarray:
    """Fraction of every active atom's area inside the window, (P, K) in [0, 1] (1 for empty
    slots): T sum_i phi(t_i) over the kernel's area (sigma sqrt(2 pi) for a Gaussian,
    sigma sqrt(2 pi) / alpha for the sss kernel, :mod:`core.model`).  ``irf``: the atoms are a
    measured response's unit-peak atoms (:func:`decomposition.model.atoms.slot_atoms`), whose
    areas are 1 / peak for a shifted copy (the response has unit area) and 1 / (alpha peak) for
    the sss atom, ``peak`` = ``irf.peak_per_ps``."""
    act = st["fam"] != FAM_NONE
    out = np.ones(act.shape)
    if irf is not None:
        if act.any() and t_ps.size > 1:
            T = float(t_ps[1] - t_ps[0])
            fam, lalp = st["fam"], st["lalp"]
            phi = slot_atoms(irf, t_ps, fam, np.nan_to_num(st["delay"]), np.nan_to_num(lalp))
            area = np.full(fam.shape, 1.0 / irf.peak_per_ps)
            sss = fam == FAM_SSS
            area[sss] /= np.exp(lalp[sss])
            out[act] = np.clip(T * phi[act].sum(axis=-1) / area[act], 0.0, 1.0)
        return out
    if act.any() and t_ps.size > 1:
        T = float(t_ps[1] - t_ps[0])
        pi, ki, sums = _in_window(st, t_ps)
        area = np.exp(st["lsig"][pi, ki]) * math.sqrt(2.0 * math.pi)
        sss = st["fam"][pi, ki] == FAM_SSS
        area = np.where(sss, area / np.exp(np.where(sss, st["lalp"][pi, ki], 0.0)), area)
        out[pi, ki] = np.clip(T * sums[:, 1] / area, 0.0, 1.0)
    return out


def off_window(st: dict, t_ps: np.ndarray, mass_out: float = OFF_WINDOW_MASS, irf=None) -> np.ndarray:
    """(P, K) bool: active atoms that run off either edge of the window -- a Gaussian (a shifted
    copy of a measured response ``irf``) centred within OFF_WINDOW_EDGE_SIGMA of its widths
    (``st["lsig"]``; a response's Gaussian-equivalent width) of the window's edge (half a bin
    outside the first or the last sample) or beyond it, or any atom with more than ``mass_out``
    of its area outside the window (:func:`window_fraction`); the rule of
    :func:`runs_off_window`."""
    return runs_off_window(st["fam"] != FAM_NONE, st["fam"] == FAM_GAUSS, st["delay"],
                           window_fraction(st, t_ps, irf), t_ps, mass_out, width_ps=np.exp(st["lsig"]))


def runs_off_window(active: np.ndarray, peaked: np.ndarray, delay_ps: np.ndarray, fraction_in: np.ndarray,
                    t_ps: np.ndarray, mass_out: float = OFF_WINDOW_MASS, width_ps=None,
                    edge_widths: float = OFF_WINDOW_EDGE_SIGMA) -> np.ndarray:
    """The OFF_WINDOW rule, (P, K) bool, for atoms of any shape.

    An active atom runs off the window when it peaks at its delay (``peaked``: a Gaussian, a
    shifted copy of a measured response; not an sss, whose delay is its onset) and that delay
    lies more than half a bin before the first sample or after the last (within ``edge_widths``
    of its widths of there, with ``width_ps``), or when less than ``1 - mass_out`` of its area
    lies inside the window.

    Parameters
    ----------
    active, peaked : ndarray (P, K) bool
    delay_ps : ndarray (P, K)
        Delays, ps (read where ``active & peaked``).
    fraction_in : ndarray (P, K)
        Fraction of each atom's area inside the window, in [0, 1] (:func:`window_fraction`, or
        the same measure of a response's atoms).
    t_ps : ndarray (L,)
        The window's sample times, ps (uniform).
    mass_out : float
        Largest fraction of the area allowed outside (OFF_WINDOW_MASS).
    width_ps : ndarray broadcasting to (P, K) or float, optional
        The peaked atoms' widths (a Gaussian's sigma; a response's Gaussian-equivalent sigma).
        Given, a peaked atom also runs off where its delay lies within ``edge_widths`` of them
        of the window's edge (half a bin outside the first or the last sample): its rise (or
        fall) is cut, and its delay is read off the other side alone.
    """
    half = 0.5 * float(t_ps[1] - t_ps[0]) if t_ps.size > 1 else 0.0
    reach = 0.0 if width_ps is None else edge_widths * np.asarray(width_ps, np.float64)
    with np.errstate(invalid="ignore"):
        centre_out = peaked & ((delay_ps - reach < t_ps[0] - half) | (delay_ps + reach > t_ps[-1] + half))
    return active & (centre_out | (fraction_in < 1.0 - mass_out))


def _resolved(st: dict, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (P, K) bool arrays: the active atoms whose delay (a Gaussian's centre, an sss onset)
    lies more than RESOLVED_SIGMA widths from that of every larger atom (by in-window peak
    ``h``) of the pixel, and those for which this holds against every larger Gaussian (an sss
    onset then hides nothing).  A faint atom under a larger one is the model's correction of
    its shape, not a component of its own, so only resolved atoms may pass on significance
    alone."""
    act = st["fam"] != FAM_NONE
    sig = np.exp(st["lsig"])
    gap = np.abs(st["delay"][:, :, None] - st["delay"][:, None, :])
    width = np.maximum(sig[:, :, None], sig[:, None, :])
    near = act[:, None, :] & (h[:, None, :] > h[:, :, None]) & ~(gap > RESOLVED_SIGMA * width)
    by_gaussian = near & (st["fam"] == FAM_GAUSS)[:, None, :]
    return act & ~near.any(axis=2), act & ~by_gaussian.any(axis=2)


def _drop(st, mask):
    st["fam"][mask] = FAM_NONE
    st["amp"][mask] = 0.0


def threshold(st: dict, t_ps: np.ndarray, rel_threshold: float = 0.05, noise=None,
              significance_chi2: float = 0.0, weights=None,
              sss_factor: float | None = SSS_RESOLVED_CHI2_FACTOR, irf=None) -> dict:
    """Drop the atoms that are neither large nor significant inside the window (in place).

    An atom is kept when its in-window peak is at least ``rel_threshold`` x the pixel's
    largest in-window peak (the paper's relative rule, on what the window shows: an atom
    extrapolated to a peak before the first bin counts with its height at the first bin), or
    when it is significant against the noise where it lies: its in-window energy
    sum_i c_i^2 / s^2 at least ``significance_chi2`` (``noise`` s (P,), units of the profile;
    for an atom of known shape that energy is the increase of the data term when it is
    removed, the likelihood-ratio statistic), and it is resolved from every larger atom
    (its delay more than RESOLVED_SIGMA widths from theirs, :mod:`decomposition.constants`).  Without ``noise`` or with
    ``significance_chi2 = 0`` the relative rule alone.  Atoms with no sample in the window are
    always dropped.  ``weights`` (P, L): the energy weighs each sample so (where the noise
    follows the signal, s^2 / weight is the noise variance there).  ``sss_factor``: see
    :func:`keep_atoms`.  ``irf``: the atoms are a measured response's (:func:`window_measures`).
    """
    h, e = window_measures(st, t_ps, weights, irf)
    keep = keep_atoms(st, h, e, rel_threshold, noise, significance_chi2, sss_factor)
    _drop(st, (st["fam"] != FAM_NONE) & ~keep)
    # atoms entirely outside the window render as zero everywhere inside it
    _drop(st, (st["fam"] != FAM_NONE) & ~(h > 0))
    return st


def keep_atoms(st: dict, h: np.ndarray, e: np.ndarray, rel_threshold: float, noise=None,
               significance_chi2: float = 0.0, sss_factor: float | None = SSS_RESOLVED_CHI2_FACTOR) -> np.ndarray:
    """(P, K) bool: the atoms of ``st`` that :func:`threshold`'s rule keeps, from their in-window
    peak heights ``h`` and energies ``e`` (P, K) (:func:`window_measures`, or the same measures
    of a measured response's atoms) and the pixels' ``noise`` (P,); the one home of the rule
    for every kind of atom.  Widths for the resolution test are ``st["lsig"]``.

    ``sss_factor``: an atom that only a larger sss onset hides (resolved from every larger
    Gaussian) passes at ``sss_factor`` times the significance bar (default
    :data:`~decomposition.constants.SSS_RESOLVED_CHI2_FACTOR`); None: every larger atom hides
    alike (the detection's pruning before its polish)."""
    top = h.max(axis=1, keepdims=True)
    keep = h >= rel_threshold * top
    if noise is not None and significance_chi2 > 0:
        s2 = np.asarray(noise, np.float64).reshape(-1, 1) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            resolved, from_gaussians = _resolved(st, h)
            keep |= (s2 > 0) & (e >= significance_chi2 * s2) & resolved
            if sss_factor is not None:
                keep |= (s2 > 0) & (e >= sss_factor * significance_chi2 * s2) & from_gaussians
    return keep


def merge_gaussians(st: dict, time_bin_ps: float, merge_tol_bins: float = 1.0, widths: bool = True) -> dict:
    """Merge Gaussian atoms of one pixel closer than ``merge_tol_bins`` bins (in place): into
    the Gaussian of their summed area, mean delay and variance; without ``widths`` (the shifted
    copies of a measured response, which has no width to merge into) the larger atom is kept
    as it is, in the earlier of the two slots (a pixel's direct stays in its slot), and the
    later slot emptied."""
    K = st["fam"].shape[1]
    tol = merge_tol_bins * time_bin_ps
    if not widths:
        # one pass is the fixed point: a kept atom does not move
        fam = st["fam"]
        for i in range(K):
            for j in range(i + 1, K):
                m = (fam[:, i] == FAM_GAUSS) & (fam[:, j] == FAM_GAUSS) & (np.abs(st["delay"][:, i] - st["delay"][:, j]) < tol)
                take = m & (st["amp"][:, i] < st["amp"][:, j])
                for key in ("delay", "amp"):
                    st[key][take, i] = st[key][take, j]
                fam[m, j] = FAM_NONE
                st["amp"][m, j] = 0.0
        return st
    changed = True
    while changed:
        changed = False
        for i in range(K):
            for j in range(i + 1, K):
                m = ((st["fam"][:, i] == FAM_GAUSS) & (st["fam"][:, j] == FAM_GAUSS)
                     & (np.abs(st["delay"][:, i] - st["delay"][:, j]) < tol))
                if not m.any():
                    continue
                changed = True
                si, sj = np.exp(st["lsig"][m, i]), np.exp(st["lsig"][m, j])
                ai, aj = st["amp"][m, i] * si, st["amp"][m, j] * sj      # areas / sqrt(2 pi)
                tot = ai + aj
                di, dj = st["delay"][m, i], st["delay"][m, j]
                mean = (ai * di + aj * dj) / tot
                var = (ai * (si**2 + di**2) + aj * (sj**2 + dj**2)) / tot - mean**2
                sig = np.sqrt(np.maximum(var, 1e-12 * np.minimum(si, sj) ** 2))
                st["delay"][m, i] = mean
                st["lsig"][m, i] = np.log(sig)
                st["amp"][m, i] = tot / sig
                rows = np.nonzero(m)[0]
                st["fam"][rows, j] = FAM_NONE
                st["amp"][rows, j] = 0.0
    return st


def clip_sss_onset(st: dict) -> np.ndarray:
    """Move every sss onset that lies before the pixel's earliest Gaussian to that Gaussian's
    delay (in place; pixels without a Gaussian keep theirs); -> (P,) bool, the pixels changed."""
    g = st["fam"] == FAM_GAUSS
    d0 = np.where(g, st["delay"], np.inf).min(axis=1)
    early = (st["fam"] == FAM_SSS) & (st["delay"] < d0[:, None]) & np.isfinite(d0)[:, None]
    st["delay"] = np.where(early, d0[:, None], st["delay"])
    return early.any(axis=1)


def classify(st: dict, scale: np.ndarray, n_ir: int):
    """Slot state -> parameter dict (amplitudes multiplied back by ``scale``).

    Parameters
    ----------
    st : dict of (P, K) slot arrays
    scale : ndarray (P,)
        Per-pixel normalisation factor (profile = scale * normalised profile).
    n_ir : int
        Number of inter-reflection slots R in the output.

    Returns
    -------
    params : dict of ndarrays, shapes (P,) and (P, R)
    truncated : ndarray (P,) bool, pixels with more than R inter-reflections
        (the R largest by peak height are kept).
    """
    P, K = st["fam"].shape
    out = empty_params((P,), n_ir=n_ir)
    g = st["fam"] == FAM_GAUSS
    delay = np.where(g, st["delay"], np.inf)
    order = np.argsort(delay, axis=1, kind="stable")
    rows = np.arange(P)[:, None]
    gs = g[rows, order]
    d_s, a_s, s_s = st["delay"][rows, order], st["amp"][rows, order], np.exp(st["lsig"][rows, order])
    has_d = gs[:, 0]
    out["direct_delay_ps"][has_d] = d_s[has_d, 0]
    out["direct_amplitude"][has_d] = a_s[has_d, 0] * scale[has_d]
    out["direct_sigma_ps"][has_d] = s_s[has_d, 0]
    n_g = g.sum(axis=1)
    truncated = n_g - 1 > n_ir
    if n_ir > 0 and K > 1:
        ir_present = gs[:, 1:]
        ird, ira, irs = d_s[:, 1:], a_s[:, 1:], s_s[:, 1:]
        if truncated.any():
            # keep the R largest (by peak height = amplitude for unit-peak Gaussians), in delay order
            key = np.where(ir_present, ira, -np.inf)
            rank = np.argsort(np.argsort(-key, axis=1, kind="stable"), axis=1, kind="stable")
            ir_present = ir_present & (rank < n_ir)
        # compact present entries to the front, keeping delay order
        pos = np.cumsum(ir_present, axis=1) - 1
        r_i, c_i = np.nonzero(ir_present & (pos < n_ir))
        dest = pos[r_i, c_i]
        out["ir_delay_ps"][r_i, dest] = ird[r_i, c_i]
        out["ir_amplitude"][r_i, dest] = ira[r_i, c_i] * scale[r_i]
        out["ir_sigma_ps"][r_i, dest] = irs[r_i, c_i]
    s = st["fam"] == FAM_SSS
    has_s = s.any(axis=1)
    ks = np.argmax(s, axis=1)
    r = np.nonzero(has_s)[0]
    out["sss_delay_ps"][r] = st["delay"][r, ks[r]]
    out["sss_amplitude"][r] = st["amp"][r, ks[r]] * scale[r]
    out["sss_sigma_ps"][r] = np.exp(st["lsig"][r, ks[r]])
    out["sss_alpha_per_ps"][r] = np.exp(st["lalp"][r, ks[r]])
    return out, truncated


def render_params(params: dict, n_bins: int, time_bin_ps: float, t0_ps: float, irf=None) -> dict:
    """Rendered components (``direct`` (P, L), ``sss`` (P, L), ``interreflections`` (P, R, L),
    and ``background`` (P, L) where ``params`` has one); with the instrument response ``irf``
    instead of the Gaussian PSF when given: the response's table atoms the solver fitted
    (:func:`decomposition.model.atoms.params_components`, within
    :data:`~decomposition.kernels.response.TABLE_REL_ERROR` of each atom's peak of the exact
    interpolant).

    The Gaussian-PSF components are the solver's own compiled atoms
    (:func:`decomposition.kernels.atomlm.state_models`: the kernels of :mod:`core.model` within 1e-12
    relative where they are evaluated, Gaussians cut at GAUSS_SUPPORT_SIGMA widths where they
    are below exp(-18) of their peak, the sss tail continued where erfc differs from 2 by
    less than 1e-8 relative); an absent component (NaN delay, amplitude or width) renders as zeros.
    """
    if irf is not None:
        return params_components(irf, t0_ps + time_bin_ps * np.arange(int(n_bins)), params)
    P = np.shape(params["direct_delay_ps"])[0]
    L = int(n_bins)

    def one(fam, delay, amp, sigma, alpha=None):
        delay, amp, sigma = (np.asarray(v, np.float64).reshape(-1) for v in (delay, amp, sigma))
        alpha = np.ones_like(delay) if alpha is None else np.asarray(alpha, np.float64).reshape(-1)
        on = np.isfinite(delay) & np.isfinite(amp) & np.isfinite(sigma) & (sigma > 0) & np.isfinite(alpha) & (alpha > 0)
        f = np.where(on, fam, FAM_NONE).astype(np.int8)[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            return state_models(t0_ps, time_bin_ps, L, f, np.where(on, amp, 0.0)[:, None],
                                np.where(on, delay, 0.0)[:, None], np.log(np.where(on, sigma, 1.0))[:, None],
                                np.log(np.where(on, alpha, 1.0))[:, None])

    out = {"direct": one(FAM_GAUSS, params["direct_delay_ps"], params["direct_amplitude"], params["direct_sigma_ps"]),
           "sss": one(FAM_SSS, params["sss_delay_ps"], params["sss_amplitude"], params["sss_sigma_ps"],
                      params["sss_alpha_per_ps"])}
    R = np.shape(params["ir_delay_ps"])[-1]
    out["interreflections"] = one(FAM_GAUSS, params["ir_delay_ps"], params["ir_amplitude"],
                                  params["ir_sigma_ps"]).reshape(P, R, L)
    if BACKGROUND_KEY in params:
        b = np.asarray(params[BACKGROUND_KEY], np.float64).reshape(P)
        out["background"] = np.broadcast_to(np.where(np.isfinite(b), b, 0.0)[:, None], (P, L)).copy()
    return out

