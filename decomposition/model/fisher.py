"""Fisher information, Cramér-Rao bounds and standard errors of component parameters.

For a profile y = mu(theta) + n with white Gaussian noise of standard
deviation sigma_n per sample, the Fisher information of the parameters is

    F = J^T J / sigma_n^2,      J_ij = d mu(t_i) / d theta_j,

and any unbiased estimator has cov(theta_hat) >= F^-1 (the Cramér-Rao bound).
theta holds, for every present component, its delay (ps), amplitude, sigma (ps)
and, for sss, alpha (1/ps), in those natural units; J uses the analytic kernel
derivatives of :func:`decomposition.model.refine.kernel_derivatives` (the same model
the refinement fits).

Worked case, used by the tests: an isolated Gaussian a g(t - t_d; s) whose
samples are symmetric about t_d.  The delay column a g t / s^2 is odd about
t_d while the amplitude and sigma columns are even, so F is block diagonal and

    var(t_d) >= sigma_n^2 / (a^2 sum_i (g(t_i) (t_i - t_d) / s^2)^2)
             ~ sigma_n^2 2 T s / (sqrt(pi) a^2)     (many samples per sigma)

which at a noise-to-signal ratio NSR = ||n|| / ||mu|| over L bins is
std(t_d) >= NSR s sqrt(2 / L).

Singular or numerically singular Fisher matrices (two components that the data
cannot tell apart, a component entirely outside the window) give NaN for every
parameter of that pixel, never an exception or an inf.
"""

from __future__ import annotations

import numpy as np

from core.model import DIRECT_KEYS, IR_KEYS, SSS_KEYS, time_axis_ps
from ..constants import FAM_GAUSS, FAM_NONE, FAM_SSS, SSS_SLOT
from .atoms import params_profile, slot_atoms
from .refine import apply_weights, check_hold, held_slots, slot_arrays
from . import varpro
from ..kernels.jit import kernel_array
from ..kernels.projected import fisher_gram
from ..kernels.response import TABLE_REL_ERROR
from .varpro import CHUNK_PIXELS, kernel_windows

__all__ = ["fisher_information", "cramer_rao_bound", "standard_errors", "parameter_names"]

# Smallest eigenvalue, relative to the largest, of the correlation-normalised
# Fisher matrix for which the pixel's parameters count as identifiable: the relative accuracy
# of the atoms the matrix is built from, below which its small eigenvalues are not known (the
# analytic Gaussian's rounding; a measured response's table atoms, TABLE_REL_ERROR of their
# peak).  On bench realism's truncated directs (a peak before the window), the response's
# pixels whose smallest eigenvalue lay between the two had errors up to several times their
# scatter: taken in, the delay's median |error| / stderr fell to 0.56 at 1,000 photons.
_RCOND = 1e-12
_RCOND_RESPONSE = TABLE_REL_ERROR


def parameter_names(n_ir: int) -> list[str]:
    """Names of the rows/columns of :func:`fisher_information`'s matrices, in order.

    Slot order direct, sss, ir[0..R-1]; per slot delay, amplitude, sigma; the
    sss alpha comes last.  Inter-reflection names carry their index, e.g.
    ``ir_delay_ps[1]``.
    """
    names = []
    slots = [("direct", None), ("sss", None)] + [("ir", r) for r in range(int(n_ir))]
    for fam, r in slots:
        for q in ("delay_ps", "amplitude", "sigma_ps"):
            names.append(f"{fam}_{q}" + (f"[{r}]" if r is not None else ""))
    names.append("sss_alpha_per_ps")
    return names


def _jacobian(t, slots, amp_scale, tb, irf=None):
    """Model Jacobian rows (n, 3K+1, L) in natural units, amplitudes divided by amp_scale (n,),
    and which rows are free; ``irf``: a measured response's atoms (:func:`_response_jacobian`)."""
    if irf is not None:
        return _response_jacobian(t, slots, amp_scale, irf)
    present = slots["present"]
    n, k = present.shape
    rows = np.zeros((n, 3 * k + 1, t.size))
    amp = np.where(present, slots["amplitude"], 0.0) / amp_scale[:, None]
    q, L = 3 * k + 1, t.size
    flat = rows.reshape(-1)
    # Each kernel on its support only (zero outside, as in the design rows of the fit).
    for pix, slot, idx, vals in kernel_windows(t, slots["delay"], slots["sigma"], slots["alpha"], present, tb, True):
        a = amp[pix, slot][:, None]
        base = ((pix * q + 3 * slot) * L)[:, None] + idx
        flat[base] = a * vals[1]
        flat[base + L] = vals[0]
        flat[base + 2 * L] = a * vals[2]
        if len(vals) == 4:
            flat[((pix * q + 3 * k) * L)[:, None] + idx] = a * vals[3]
    free = np.concatenate([np.repeat(present, 3, axis=1), present[:, SSS_SLOT:SSS_SLOT + 1]], axis=1)
    return rows, free


def _response_jacobian(t, slots, amp_scale, irf):
    """:func:`_jacobian`'s rows for a measured response's atoms, in the Gaussian layout (per slot
    delay, amplitude, width; the sss decay rate last): a_k d phi_k / d delay_k, phi_k, and
    a_s d phi_s / d alpha (:func:`decomposition.model.atoms.slot_atoms`, the response's table
    atoms).  The response has no width: those rows are zero and not free."""
    present = slots["present"]
    n, k = present.shape
    fam = np.where(present, FAM_GAUSS, FAM_NONE).astype(np.int8)
    fam[:, SSS_SLOT] = np.where(present[:, SSS_SLOT], FAM_SSS, FAM_NONE)
    delay = np.where(present, slots["delay"], 0.0)
    alpha = np.where(present[:, SSS_SLOT], np.maximum(slots["alpha"], np.finfo(np.float64).tiny), 1.0)
    lalp = np.zeros((n, k))
    lalp[:, SSS_SLOT] = np.log(alpha)
    amp = np.where(present, slots["amplitude"], 0.0) / amp_scale[:, None]
    phi, dd, dl = slot_atoms(irf, t, fam, delay, lalp, derivatives=True)
    rows = np.zeros((n, 3 * k + 1, t.size))
    rows[:, 0:3 * k:3] = amp[:, :, None] * dd
    rows[:, 1:3 * k:3] = phi
    rows[:, 3 * k] = amp[:, SSS_SLOT, None] * dl[:, SSS_SLOT] / alpha[:, None]   # d / d alpha
    free = np.zeros((n, 3 * k + 1), bool)
    free[:, 0:3 * k:3] = present
    free[:, 1:3 * k:3] = present
    free[:, 3 * k] = present[:, SSS_SLOT]
    return rows, free


def _prepare(params, n_bins, time_bin_ps, t0_ps):
    if "direct_delay_ps" in params:
        lead = np.shape(params["direct_delay_ps"])
    elif "ir_delay_ps" in params:
        lead = np.shape(params["ir_delay_ps"])[:-1]
    else:
        raise ValueError("params holds no component delays")
    slots = slot_arrays(params, lead)
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    amp = np.where(slots["present"], np.abs(slots["amplitude"]), 0.0)
    amp_scale = np.max(amp, axis=-1, initial=0.0)
    amp_scale = np.where(amp_scale > 0, amp_scale, 1.0)
    return lead, slots, t, amp_scale


def _sigma_rows(k):
    return 3 * np.arange(k) + 2


def _tie_sigma(rows, free, present):
    """One width parameter per pixel: its column is the sum of the components' sigma columns.

    It is stored in the row of the pixel's first present component; the other
    sigma rows become zero and not free.  Returns the index of that slot (n,).
    """
    n, k = present.shape
    sig = _sigma_rows(k)
    first = np.argmax(present, axis=1)
    total = rows[:, sig].sum(axis=1)
    rows[:, sig] = 0.0
    free[:, sig] = False
    pix = np.arange(n)
    rows[pix, 3 * first + 2] = total
    free[pix, 3 * first + 2] = present.any(axis=1)
    return first


def _onset_at_direct(slots, tie_ps=0.0):
    """Pixels whose sss onset sits at the lower bound sss_delay >= direct_delay (the constraint is
    active), or within ``tie_ps`` of it (a fit that approaches the bound without being projected
    onto it, where the two delays' columns are degenerate)."""
    pres = slots["present"]
    d, s = slots["delay"][:, 0], slots["delay"][:, SSS_SLOT]
    with np.errstate(invalid="ignore"):
        return pres[:, 0] & pres[:, SSS_SLOT] & (s - d <= np.maximum(tie_ps, 1e-9 * np.maximum(1.0, np.abs(d))))


def _tied_onsets(slots, sss_after_direct, tie_ps):
    """(n,) bool: the pixels whose direct delay and sss onset are one parameter of the information
    (``sss_after_direct`` and :func:`_onset_at_direct`), None without ``sss_after_direct``.  The
    tie holds with a held direct too: on the direct, the onset's column is a combination of the
    two atoms (d/d onset of the sss atom = alpha (sss atom) - the shifted atom), so it is no
    parameter of its own, and with the direct it is held."""
    if not sss_after_direct:
        return None
    return _onset_at_direct(slots, tie_ps)


def _unit_information(params, n_bins, time_bin_ps, t0_ps, bin_integrated, sw=None, shared_sigma=False,
                      tie_onset=None, offset=None, fixed=None, irf=None):
    """J^T W J for unit noise with amplitudes divided by a per-pixel scale; see fisher_information.

    ``tie_onset`` (n,) bool: pixels whose sss onset shares the direct's delay (one column, the
    sum of the two).  ``offset`` (n,) bool: pixels with a fitted constant offset, one more row
    and column (last, of ones: the offset divided by the same scale); without it the matrices
    are P x P.  ``fixed`` (n, 3K+1) bool: parameters held at known values (no column, not
    free).  ``irf``: the columns of a measured response's atoms (:func:`_response_jacobian`)
    instead of the Gaussian PSF's."""
    lead, slots, t, amp_scale = _prepare(params, n_bins, time_bin_ps, t0_ps)
    tb = float(time_bin_ps) if bin_integrated else None
    n, k = slots["present"].shape
    p = 3 * k + 1 + (offset is not None)
    tie_onset = np.zeros(n, bool) if tie_onset is None else np.asarray(tie_onset, bool)
    slots["tied_onset"] = tie_onset
    if irf is not None and (shared_sigma or tb is not None):
        raise ValueError("a measured response (irf) has no width to share and is point-sampled: "
                         "shared_sigma and bin_integrated do not apply")
    if varpro.COMPILED and tb is None and irf is None:
        info, free, tied = _compiled_information(t, slots, amp_scale, sw, shared_sigma, tie_onset, offset, fixed)
        slots["tied_slot"] = tied if shared_sigma else None
        return lead, slots, info, free, amp_scale
    info = np.empty((n, p, p))
    free = np.empty((n, p), dtype=bool)
    tied = np.zeros(n, dtype=np.int64)
    # Cache-sized chunks of pixels: the (pixels, P, L) Jacobian never exists for a whole block.
    for i in range(0, n, CHUNK_PIXELS):
        ch = slice(i, i + CHUNK_PIXELS)
        sub = {name: slots[name][ch] for name in ("delay", "amplitude", "sigma", "alpha", "present")}
        rows, fr = _jacobian(t, sub, amp_scale[ch], tb, irf)
        if offset is not None:
            on = np.asarray(offset, bool)[ch]
            rows = np.concatenate([rows, np.broadcast_to(on[:, None, None], (on.size, 1, t.size)).astype(float)],
                                  axis=1)
            fr = np.concatenate([fr, on[:, None]], axis=1)
        if sw is not None:
            rows *= sw[ch, None, :]
        if shared_sigma:
            tied[ch] = _tie_sigma(rows, fr, sub["present"])
        if tie_onset.any():
            # An active onset constraint leaves one delay for both components.
            on = np.flatnonzero(tie_onset[ch])
            rows[on, 0] += rows[on, 3 * SSS_SLOT]
            rows[on, 3 * SSS_SLOT] = 0.0
            fr[on, 3 * SSS_SLOT] = False
        if fixed is not None:
            fx = np.zeros(fr.shape, bool)
            fx[:, :fixed.shape[1]] = fixed[ch]
            if shared_sigma:       # the tied width sits in the first present slot's sigma row
                fx[np.arange(fx.shape[0]), 3 * tied[ch] + 2] |= fixed[ch][:, _sigma_rows(k)].any(axis=1)
            rows[fx] = 0.0
            fr &= ~fx
        info[ch] = rows @ rows.swapaxes(-1, -2)
        free[ch] = fr
    slots["tied_slot"] = tied if shared_sigma else None
    return lead, slots, info, free, amp_scale


def _compiled_information(t, slots, amp_scale, sw, shared_sigma, tie_onset, offset, fixed):
    """The point-sampled ``info``, ``free`` and tied slots of :func:`_unit_information`, the
    rows and their Gram product compiled (:func:`decomposition.kernels.projected.fisher_gram`);
    the free parameters as the NumPy path marks them."""
    present = slots["present"]
    n, k = present.shape
    pix = np.arange(n)
    free = np.concatenate([np.repeat(present, 3, axis=1), present[:, SSS_SLOT:SSS_SLOT + 1]], axis=1)
    if offset is not None:
        free = np.concatenate([free, np.asarray(offset, bool)[:, None]], axis=1)
    p = free.shape[1]
    tied = np.full(n, -1, np.int64)
    if shared_sigma:
        tied = np.argmax(present, axis=1).astype(np.int64)
        free[:, _sigma_rows(k)] = False
        free[pix, 3 * tied + 2] = present.any(axis=1)
    onset = tie_onset
    free[onset, 3 * SSS_SLOT] = False
    fx = np.zeros((n, p), bool)
    if fixed is not None:
        fx[:, :fixed.shape[1]] = fixed
        if shared_sigma:
            fx[pix, 3 * tied + 2] |= fixed[:, _sigma_rows(k)].any(axis=1)
        free &= ~fx
    info = np.empty((n, p, p))
    if n:
        amp = np.where(present, slots["amplitude"], 0.0) / amp_scale[:, None]
        fisher_gram(kernel_array(t, np.float64), kernel_array(slots["delay"], np.float64),
                    kernel_array(slots["sigma"], np.float64), kernel_array(slots["alpha"], np.float64),
                    kernel_array(amp, np.float64), kernel_array(present, np.bool_),
                    np.zeros((0, t.size)) if sw is None else kernel_array(sw, np.float64),
                    np.zeros(0, np.bool_) if offset is None else kernel_array(offset, np.bool_),
                    kernel_array(tied, np.int64) if shared_sigma else np.full(n, -1, np.int64),
                    kernel_array(onset, np.bool_), kernel_array(fx, np.bool_), info)
    return info, free, np.where(tied >= 0, tied, 0)


def _amplitude_rows(k):
    idx = np.zeros(3 * k + 1, dtype=bool)
    idx[1:3 * k:3] = True
    return idx


def fisher_information(params, noise_sigma, *, n_bins: int, time_bin_ps: float = 2.0,
                       t0_ps: float | None = None, shared_sigma: bool = False, bin_integrated: bool = False):
    """Fisher information of the component parameters under white Gaussian noise.

    Parameters
    ----------
    params : dict of ndarray
        Parameter dict (keys of :mod:`core.model`), leading shape (...,),
        NaN where absent.
    noise_sigma : float or array_like broadcastable to (...,)
        Noise standard deviation per time bin, in the units of the profile (> 0).
    n_bins, time_bin_ps, t0_ps
        Time axis of the profiles (see :func:`core.model.time_axis_ps`).
    shared_sigma : bool
        All components of a pixel share one width (see ``refine(shared_sigma=True)``):
        that single parameter takes the sigma row of the pixel's first present
        component; the other sigma rows are zero.
    bin_integrated : bool
        Use bin-averaged kernels (as ``model.render_profile(bin_integrated=True)``).

    Returns
    -------
    fisher : ndarray, shape (..., P, P), P = 3 (2 + R) + 1
        Rows/columns named by :func:`parameter_names`; units are the inverse
        products of the parameters' units.  Rows and columns of absent
        components are zero.
    free : ndarray of bool, shape (..., P)
        Which rows belong to present components.
    """
    lead, slots, info, free, amp_scale = _unit_information(params, n_bins, time_bin_ps, t0_ps,
                                                            bin_integrated, None, shared_sigma)
    noise = _noise(noise_sigma, lead)
    # Undo the amplitude normalisation: d mu / d amplitude rows were computed for
    # amplitudes / scale, the other rows carry amplitude / scale as a factor.
    k = slots["present"].shape[1]
    is_amp = _amplitude_rows(k)
    fac = np.where(is_amp[None, :], 1.0, amp_scale[:, None])  # (n, P)
    with np.errstate(over="ignore"):
        fisher = info * fac[:, :, None] * fac[:, None, :] / (noise * noise)[:, None, None]
    return fisher.reshape(lead + fisher.shape[1:]), free.reshape(lead + free.shape[1:])


def _noise(noise_sigma, lead):
    noise = np.asarray(noise_sigma, dtype=np.float64)
    try:
        noise = np.broadcast_to(noise, lead).reshape(-1)
    except ValueError:
        raise ValueError(f"noise_sigma of shape {noise.shape} does not broadcast to the pixel shape {lead}") from None
    if np.any(~np.isfinite(noise)) or np.any(noise < 0):
        raise ValueError("noise_sigma must be finite and non-negative")
    return noise


def _covariance_diag(info, free, rcond=_RCOND):
    """sqrt(diag(inv(info))) over the free rows, NaN for pixels whose matrix is (near) singular
    (its correlation matrix's smallest eigenvalue at most ``rcond`` times its largest)."""
    n, p, _ = info.shape
    d = np.sqrt(np.where(free, np.einsum("npp->np", info), 1.0))
    ok_diag = np.all(np.where(free, d > 0, True), axis=-1) & np.all(np.isfinite(info), axis=(1, 2))
    d = np.where(d > 0, d, 1.0)
    corr = info / (d[:, :, None] * d[:, None, :])
    mask = free[:, :, None] & free[:, None, :]
    corr = np.where(mask, corr, 0.0)
    pidx = np.arange(p)
    corr[:, pidx, pidx] = 1.0
    corr = np.where(np.isfinite(corr), corr, 0.0)
    w, v = np.linalg.eigh(corr)
    ok = ok_diag & (w[:, 0] > rcond * w[:, -1])
    w = np.where(ok[:, None], w, 1.0)
    inv_diag = np.einsum("npk,nk->np", v * v, 1.0 / w)
    out = np.sqrt(inv_diag) / d
    out = np.where(free & ok[:, None], out, np.nan)
    return out


def _to_dict(std, slots, lead, suffix):
    k = slots["present"].shape[1]
    n_ir = k - 2
    out = {}
    for fam, slot, keys in (("direct", 0, DIRECT_KEYS), ("sss", SSS_SLOT, ("sss_delay_ps", "sss_amplitude", "sss_sigma_ps"))):
        for j, key in enumerate(keys):
            out[key + suffix] = std[:, 3 * slot + j].reshape(lead)
    out["sss_alpha_per_ps" + suffix] = std[:, 3 * k].reshape(lead)
    for j, key in enumerate(IR_KEYS):
        cols = 3 * np.arange(2, k) + j
        out[key + suffix] = std[:, cols].reshape(lead + (n_ir,))
    order = DIRECT_KEYS + SSS_KEYS + IR_KEYS
    return {key + suffix: out[key + suffix] for key in order}


def _bound(params, noise, n_bins, time_bin_ps, t0_ps, bin_integrated, suffix, sw=None, shared_sigma=False,
           tie_onset=None, offset=None, fixed=None, irf=None):
    lead, slots, info, free, amp_scale = _unit_information(params, n_bins, time_bin_ps, t0_ps,
                                                            bin_integrated, sw, shared_sigma, tie_onset, offset,
                                                            fixed, irf)
    # for unit noise, normalised amplitudes
    std_unit = _covariance_diag(info, free, _RCOND if irf is None else _RCOND_RESPONSE)
    std_unit = std_unit[:, :3 * slots["present"].shape[1] + 1]   # the offset's own is not reported
    on = slots["tied_onset"]
    std_unit[on, 3 * SSS_SLOT] = std_unit[on, 0]
    if shared_sigma:
        n, k = slots["present"].shape
        tied = std_unit[np.arange(n), 3 * slots["tied_slot"] + 2]
        std_unit[:, _sigma_rows(k)] = np.where(slots["present"], tied[:, None], np.nan)
    k = slots["present"].shape[1]
    is_amp = _amplitude_rows(k)
    # Amplitude rows were for amplitude / scale: their std scales back up; the
    # other parameters' rows carried amplitude / scale, so theirs scales down.
    noise_rel = noise / amp_scale
    std = np.where(is_amp[None, :], std_unit * noise[:, None], std_unit * noise_rel[:, None])
    return _to_dict(std, slots, lead, suffix)


def cramer_rao_bound(params, noise_sigma, *, n_bins: int, time_bin_ps: float = 2.0,
                     t0_ps: float | None = None, shared_sigma: bool = False,
                     bin_integrated: bool = False, offset=None) -> dict[str, np.ndarray]:
    """Cramér-Rao lower bounds (standard deviations) of every present parameter.

    Parameters
    ----------
    params : dict of ndarray
        True parameters (keys of :mod:`core.model`), leading shape (...,).
    noise_sigma : float or array_like broadcastable to (...,)
        White Gaussian noise standard deviation per time bin (>= 0), in the
        units of the profile.
    n_bins, time_bin_ps, t0_ps, bin_integrated
        Time axis and sampling of the profiles.
    shared_sigma : bool
        The components of a pixel share one (unknown) width; every present
        component's ``sigma_ps_crb`` is then the bound of that one width.
    offset : array_like of bool broadcastable to (...,), optional
        Pixels whose model also has an unknown constant offset (one more parameter).

    Returns
    -------
    dict of ndarray
        ``<key>_crb`` for every parameter key (e.g. ``direct_delay_ps_crb`` in
        ps, ``sss_alpha_per_ps_crb`` in 1/ps, ``ir_delay_ps_crb`` of shape
        (..., R)): the smallest standard deviation any unbiased estimator can
        reach, all parameters of all present components being unknown.  NaN
        where the component is absent or the pixel's Fisher matrix is singular.
    """
    lead = np.shape(params["direct_delay_ps"]) if "direct_delay_ps" in params else np.shape(params["ir_delay_ps"])[:-1]
    noise = _noise(noise_sigma, lead)
    if offset is not None:
        offset = np.broadcast_to(np.asarray(offset, bool), lead).reshape(-1)
    return _bound(params, noise, n_bins, time_bin_ps, t0_ps, bin_integrated, "_crb", None, shared_sigma,
                  offset=offset)


def standard_errors(profiles, params, *, time_bin_ps: float = 2.0, t0_ps: float | None = None,
                    weights=None, shared_sigma: bool = False, sss_after_direct: bool = False,
                    bin_integrated: bool = False, noise_sigma=None, offset=None,
                    hold=None, irf=None, onset_tie_ps: float = 0.0) -> dict[str, np.ndarray]:
    """Per-pixel standard errors of fitted parameters from the Fisher information at the solution.

    Unless ``noise_sigma`` gives it, the noise level of each pixel is estimated from its
    residual, sigma_n^2 = ||y - mu(theta)||^2 / (L - P_free), with P_free the number of
    fitted parameters of the pixel; this is accurate when ``params`` is the
    least-squares fit (e.g. the output of :func:`decomposition.model.refine.refine`).

    Count data: with ``weights`` 1 / variance of the Poisson law at the model
    (:func:`decomposition.noise.poisson_weights`) and ``noise_sigma=1`` this is the Poisson
    Fisher information sum_i (d mu_i / d theta)^2 / mu_i, the bound the Poisson
    maximum-likelihood fit reaches.  (The residual estimate would be biased there: where
    the variance is floored, far from the signal, a weighted squared residual averages
    less than one.)

    Parameters
    ----------
    profiles : array_like, shape (..., L)
        The profiles the parameters were fitted to.
    params : dict of ndarray
        Fitted parameters, leading shape (...,).
    time_bin_ps, t0_ps, bin_integrated
        Time axis and sampling.
    weights : array_like, shape (..., L), optional
        Relative sample weights of the fit (as in :func:`decomposition.model.refine.refine`);
        samples of weight 0 (saturated, excluded) do not count, and the noise
        estimate is that of a unit-weight sample.
    shared_sigma : bool
        The fit used one width per pixel (as ``refine(shared_sigma=True)``).
    sss_after_direct : bool
        The fit kept sss onsets at or after the direct delay.  Where that
        constraint is active (onset equal to the direct delay) the two delays
        are one parameter, and both get its standard error.
    noise_sigma : float or array_like broadcastable to (...,), optional
        Known standard deviation of a unit-weight sample (1 where ``weights`` are the
        inverse variances); default: estimated from the residual as above.
    offset : array_like of bool broadcastable to (...,), optional
        Pixels whose fit also had a constant offset (the ``b`` family), already taken out of
        ``profiles``: one more parameter, a column of ones, whose uncertainty enters the
        components' errors (an offset and a slow sss tail are partly the same light).  Its
        own error is not returned.
    hold : dict, optional
        Parameters the fit held at given values (``hold=`` of
        :func:`decomposition.model.refine.refine`; only which pixels hold which matters):
        they are no parameters of the information, and their own errors are NaN.
    irf : InstrumentResponse, optional
        The fit's components are atoms of this measured response
        (:func:`decomposition.model.atoms.slot_atoms`) instead of Gaussians: the information
        has no width parameters (``*_sigma_ps_stderr`` NaN); ``shared_sigma`` and
        ``bin_integrated`` do not apply.
    onset_tie_ps : float
        With ``sss_after_direct``: an onset within this many ps after the direct delay counts
        as on it (a fit that approaches the bound, like the Poisson fit of a measured
        response, rather than one projected onto it; 0: only onsets on the bound).

    Returns
    -------
    dict of ndarray
        ``<key>_stderr`` for every parameter key, in the parameter's units; NaN
        where the component is absent, the pixel has no residual degrees of
        freedom, or its Fisher matrix is singular.
    """
    y = np.asarray(profiles, dtype=np.float64)
    if y.ndim < 1:
        raise ValueError("profiles must have shape (..., L)")
    y, sw = apply_weights(y, weights)
    lead = y.shape[:-1]
    n_bins = y.shape[-1]
    if not np.all(np.isfinite(y)):
        bad = int(np.sum(~np.isfinite(y).all(axis=-1)))
        raise ValueError(f"profiles contain NaN or inf samples in {bad} pixel(s)")
    slots = slot_arrays(params, lead)
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    tb = float(time_bin_ps) if bin_integrated else None
    present = slots["present"]
    n = present.shape[0]
    y2 = y.reshape(n, n_bins)
    amp = np.where(present, slots["amplitude"], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sig = np.where(present, slots["sigma"], 1.0)
        alp = np.where(present[:, SSS_SLOT], slots["alpha"], 1.0)
    delay = np.where(present, slots["delay"], 0.0)
    if irf is None:
        rss = varpro.rss_at(t, y2 if sw is None else y2 * sw, delay, sig, alp, present, amp, np.zeros(n), tb, sw)
    else:
        r = y2 - np.nan_to_num(params_profile(irf, t, params).reshape(n, n_bins))
        r = r if sw is None else r * sw
        rss = np.einsum("pl,pl->p", r, r)
    n_used = n_bins if sw is None else np.sum(sw > 0, axis=-1)
    # the response has no width parameter
    n_fitted = (3 if irf is None else 2) * present.sum(axis=-1) + present[:, SSS_SLOT]
    if offset is not None:
        offset = np.broadcast_to(np.asarray(offset, bool), lead).reshape(n)
        n_fitted = n_fitted + offset
    if shared_sigma:
        n_fitted = n_fitted - np.maximum(slots["present"].sum(axis=-1) - 1, 0)
    fixed = None
    hold = check_hold(hold, lead)
    if hold:
        k = present.shape[1]
        d_held, s_held, a_held = held_slots(hold, n, k)
        fixed = np.zeros((n, 3 * k + 1), bool)
        fixed[:, 3 * np.arange(k)] = d_held & present
        fixed[:, _sigma_rows(k)] = s_held[:, None] & present
        fixed[:, 3 * k] = a_held & present[:, SSS_SLOT]
        n_sigma = 1 if shared_sigma else present.sum(axis=-1)
        n_fitted = n_fitted - fixed[:, 3 * np.arange(k)].sum(axis=1) - fixed[:, 3 * k] \
            - np.where(s_held & present.any(axis=1), n_sigma, 0)
    tie = _tied_onsets(slots, sss_after_direct, onset_tie_ps)
    if tie is not None:
        n_fitted = n_fitted - tie
    dof = n_used - n_fitted
    with np.errstate(invalid="ignore", divide="ignore"):
        noise = np.where(dof > 0, np.sqrt(rss / np.maximum(dof, 1)), np.nan)
    if noise_sigma is not None:
        noise = np.where(dof > 0, _noise(noise_sigma, lead), np.nan)
    out = _bound(params, np.where(np.isfinite(noise), noise, 0.0), n_bins, time_bin_ps, t0_ps,
                 bin_integrated, "_stderr", sw, shared_sigma, tie, offset, fixed, irf)
    if np.any(~np.isfinite(noise)):
        bad = ~np.isfinite(noise)
        for key, v in out.items():
            v2 = v.reshape(bad.size, -1)
            v2[bad] = np.nan
    return out
