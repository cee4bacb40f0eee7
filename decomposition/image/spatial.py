"""Spatial coupling of an image's pixels (``decompose_image(..., spatial=True)``): its options, the
state its steps share (:class:`Coupling`), and the joint refinement.

Neighbouring pixels of a scene mostly see the same surface: their direct delays differ by a
smooth slope, except at the edges of objects.  After the per-pixel pass two steps use that,
each over the image axes (y, x) of a flattened image of P pixels, on blocks of pixels (the only
Python loops run over neighbour offsets and sweeps):

1. **Neighbours' answers as starts** (:mod:`decomposition.image.neighbours`): the pixels in
   doubt refitted from their neighbours' answers, each keeping its own fit or the one the
   neighbours support.
2. **Joint refinement** (:func:`joint_refinement`): ``sweeps`` Jacobi sweeps in which every
   pixel is refitted with a Gaussian pseudo-observation of its direct delay
   (:func:`decomposition.model.refine.refine`'s ``delay_prior``) at a robust estimate from the
   neighbours within ``radius`` pixels (:func:`neighbour_prior`).  The estimate is a Tukey
   biweight mean around the neighbours' median, each neighbour weighed by
   1 / (its standard error^2 + ``delay_scale_ps``^2), so that a neighbour across an edge
   (many sigma from the median) has no weight.  The prior's precision is
   1 / (``delay_scale_ps``^2 + the estimate's variance), times the biweight of the pixel's
   own delay against the estimate in the pixel's own standard error: a pixel whose own data put
   its delay many sigma from its neighbours' (its side of an edge, or a clean signal amid noisy
   ones) is not pulled, and one whose data hardly fix it is pulled most.  Against the pixel's
   own precision 1 / stderr^2 the prior moves a well-determined delay by a fraction
   stderr^2 / (stderr^2 + 1 / precision) of the gap.  With ``material_prior`` (the default) the
   sweeps also carry priors on what a material shares: ln(sss amplitude / direct amplitude),
   ln(sss decay rate) and the sss onset after the direct (each with its own scale), estimated
   over the pixel's material.  Such a parameter is one value per material, not a smooth
   surface: the ratio's and decay rate's prior is the median of the members of the pixel's
   material within ``material_radius`` (:func:`material_members`: the neighbours whose ratio and
   decay rate both agree with the pixel's own, where they are at least half; none among pixels
   each of its own material), and the onset's is the censored location of the neighbours'
   onsets (:func:`onset_prior`, :func:`censored_location`: an onset at its bound 0 is "at most
   0", not 0) where the pixel has such members.  After the first sweep only the pixels
   whose prior appeared, went, or moved (its mean by 1 % of its standard deviation, its
   precision by 1 %) are refitted, and the sweeps stop early where none did
   (``info["spatial_refits"]`` counts the refits).

The answer at a pixel depends only on the data within :func:`coupling_reach` pixels of it (one
pixel for the first step, ``material_radius`` per round of material starts, ``radius`` or with
the material prior the larger of it and ``material_radius`` per sweep), so a chunked run reads
each chunk with that halo and keeps the interior (:mod:`decomposition.store.chunked`).

Either instrument: with a measured response (``irf=``) every refit, objective, screen and error
reads the response's atoms (:func:`decomposition.model.refine.refine`'s ``irf``, the compiled
kernels' instrument argument), and a shared response time scale stretches the response.  The
neighbour starts' data term and the joint refinement are both weighed by
:func:`objective_weights`, as the per-pixel refit weighs its samples (the fit mask and the
pixel's noise, times noise^2 / the call's detector law where the noise follows the signal, or
Poisson weights at the pixel's model for count data); neither is whitened by a
correlated-noise spectrum.  The standard
errors reported are those of the pixel's own data at the final fit (the prior not included).
"""

# One module over 600 lines on purpose: the spatial options, the material tests, the priors they
# build and the joint refinement that reads them are one mechanism over one neighbourhood layout.
from __future__ import annotations

import inspect
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.special import log_ndtr

from core.model import BACKGROUND_KEY, DIRECT_KEYS, IR_KEYS, SSS_KEYS, render_profile, time_axis_ps
from ..constants import SSS_SLOT
from ..api import DecompositionResult, decompose
from ..flags import AMBIGUOUS, EMPTY, POOR_FIT
from ..kernels.projected import GAUSSIAN_PSF, response_instrument
from ..model.atoms import params_profile
from ..model.refine import refine, slot_arrays, unit_widths
from ..model.varpro import rss_at
from ..response.resolve import resolve_response, spike_settings
from .shared import held_response
from ..model.slots import shape_bounds
from ..options import OptionError, _documented, _flag, _number, options_from_mapping, parse_components
from ..stages.candidates import detector_variance
from ..stages.prepare import prepare_samples, time_axis
from ..stages.quality import assess_fit
from ..stages.refit import component_errors, sample_weights
from ..stages.selection import families, free_parameters, log_samples, penalised

__all__ = ["SpatialOptions", "spatial_options", "coupling_reach", "Coupling", "prepare_coupling", "objective_weights",
           "noise_variance", "take_rows", "objective", "refit", "shifted", "NEIGHBOURS_8", "neighbour_prior",
           "mixed_neighbourhood", "censored_location", "onset_prior", "material_members",
           "material_prior", "prior_values", "refine_priors", "joint_refinement", "coupled_result"]

#: the 8 neighbours' offsets (dy, dx)
NEIGHBOURS_8 = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))


@_documented
@dataclass(frozen=True)
class SpatialOptions:
    """Options of the spatial coupling (``decompose_image(spatial=...)``)."""

    #: Refit the pixels in doubt from each of their 8 neighbours' parameter sets.
    neighbour_starts: bool = True
    #: A direct delay agrees with a neighbour's within this many ps (the doubt test).
    doubt_delay_ps: float = 4.0
    #: Jacobi sweeps of the joint refinement with the neighbours' delay prior (0: none; at most:
    #: they stop where no pixel's prior moved).
    sweeps: int = 3
    #: Neighbourhood radius of the prior, pixels (1: the 8 neighbours; a square of side 2r+1).
    radius: int = 1
    #: How far a direct delay may differ from its neighbours' on one smooth surface, ps: the
    #: prior's own standard deviation (small: strong smoothing; large: little).
    delay_scale_ps: float = 0.5
    #: Tukey biweight cut-off, in standard deviations: a neighbour (or the pixel itself) farther
    #: from the neighbourhood's estimate has no weight (an edge).
    edge_sigma: float = 3.0
    #: The joint refinement's prior also on what a material shares between neighbours: the sss
    #: amplitude over the direct's and the sss decay rate (their logarithms) and the sss onset
    #: after the direct, read from the members of the pixel's material within
    #: ``material_radius`` (``material_agreement_sigma``; a pixel without enough members has
    #: none); the material starts (``material_starts``) run only with it.
    material_prior: bool = True
    #: How far the natural logarithm of the sss-to-direct amplitude ratio may differ between
    #: neighbours on one material: the ratio prior's own standard deviation.
    ratio_scale: float = 0.05
    #: The same for the natural logarithm of the sss decay rate.
    alpha_scale: float = 0.05
    #: The same for the sss onset after the direct delay, ps.
    onset_scale_ps: float = 1.5
    #: The material starts' homogeneity test: a neighbourhood whose values scatter beyond their
    #: standard errors and scale at this significance level (Cochran's Q against its chi^2) is
    #: not one material, and proposes no material start (:func:`mixed_neighbourhood`).
    homogeneity_p: float = 0.05
    #: Neighbourhood radius of the material starts and of the material prior, pixels: the
    #: neighbours whose sss a pixel fitted without one is offered (:mod:`decomposition.image.material`)
    #: and those whose material the prior reads (:func:`material_members`, :func:`onset_prior`; a
    #: material is one value over a patch, so more neighbours share it than the delay prior's own
    #: ``radius`` weighs).
    material_radius: int = 2
    #: The material prior's members: the neighbours within ``material_radius`` whose own ln(sss /
    #: direct amplitude) and ln(sss decay rate) both agree with the pixel's own within this many
    #: standard deviations (their standard errors and scales in quadrature; :func:`material_members`).
    material_agreement_sigma: float = 2.0
    #: Pixels fitted without an sss whose neighbourhood is one material with an sss are refitted
    #: with it at the neighbourhood's values (:mod:`decomposition.image.material`), kept where
    #: the data support it.
    material_starts: bool = True
    #: Rounds of material starts: each round reads the answers the last one left, so a material's
    #: sss reaches pixels whose neighbours gained it in the round before (0: none).
    material_rounds: int = 2

    def __post_init__(self):
        object.__setattr__(self, "neighbour_starts", _flag("neighbour_starts", self.neighbour_starts))
        object.__setattr__(self, "doubt_delay_ps", _number("doubt_delay_ps", self.doubt_delay_ps, lo=0, lo_open=True))
        object.__setattr__(self, "sweeps", _number("sweeps", self.sweeps, lo=0, integer=True))
        object.__setattr__(self, "radius", _number("radius", self.radius, lo=1, integer=True))
        object.__setattr__(self, "delay_scale_ps", _number("delay_scale_ps", self.delay_scale_ps, lo=0, lo_open=True))
        object.__setattr__(self, "edge_sigma", _number("edge_sigma", self.edge_sigma, lo=0, lo_open=True))
        object.__setattr__(self, "material_prior", _flag("material_prior", self.material_prior))
        object.__setattr__(self, "ratio_scale", _number("ratio_scale", self.ratio_scale, lo=0, lo_open=True))
        object.__setattr__(self, "alpha_scale", _number("alpha_scale", self.alpha_scale, lo=0, lo_open=True))
        object.__setattr__(self, "onset_scale_ps", _number("onset_scale_ps", self.onset_scale_ps, lo=0, lo_open=True))
        object.__setattr__(self, "homogeneity_p", _number("homogeneity_p", self.homogeneity_p, lo=0, lo_open=True))
        object.__setattr__(self, "material_radius", _number("material_radius", self.material_radius, lo=1, integer=True))
        object.__setattr__(self, "material_starts", _flag("material_starts", self.material_starts))
        object.__setattr__(self, "material_rounds", _number("material_rounds", self.material_rounds, lo=0, integer=True))
        object.__setattr__(self, "material_agreement_sigma",
                           _number("material_agreement_sigma", self.material_agreement_sigma, lo=0, lo_open=True))
        if not self.homogeneity_p < 1:
            raise OptionError(f"option homogeneity_p: must be < 1, got {self.homogeneity_p!r}")


def spatial_options(spatial) -> SpatialOptions | None:
    """``spatial=`` of :func:`decompose_image` -> its options, or None for no coupling: False /
    None, True (the defaults), a :class:`SpatialOptions`, or a mapping of its field names."""
    if spatial is None or spatial is False or (isinstance(spatial, np.bool_) and not spatial):
        return None
    if spatial is True or (isinstance(spatial, np.bool_) and spatial):
        return SpatialOptions()
    if isinstance(spatial, SpatialOptions):
        return spatial
    if isinstance(spatial, dict):
        unknown = sorted(set(spatial) - set(SpatialOptions.__dataclass_fields__))
        if unknown:
            raise OptionError(f"spatial: unknown option(s) {', '.join(map(str, unknown))}; choose from "
                              f"{', '.join(SpatialOptions.__dataclass_fields__)}")
        return SpatialOptions(**spatial)
    raise OptionError(f"spatial: must be true, false, a SpatialOptions or a mapping of its options, got {spatial!r}")


def coupling_reach(options: SpatialOptions) -> int:
    """How far (pixels, along y and x) the coupled answer at a pixel reaches into the image: the
    neighbour starts read the 8 neighbours (1), each round of material starts the
    ``material_radius`` neighbourhood (with the material prior), each sweep the ``radius``
    neighbourhood (the delay prior) or, with the material prior, the larger of it and the
    ``material_radius`` one (the image path's whole reach, its halo, is
    :func:`decomposition.image.api.halo_pixels`)."""
    starts = options.material_radius * options.material_rounds if options.material_prior and options.material_starts else 0
    sweep = max(options.radius, options.material_radius) if options.material_prior else options.radius
    return int(options.neighbour_starts) + starts + options.sweeps * sweep


# --------------------------------------------------------------------------- the call's setup

@dataclass
class Coupling:
    """What the two steps share: the prepared samples of the flattened image (P pixels), its
    shape, the per-pixel options, the current parameters (P-shaped) and what was done."""

    shape: tuple            # (Y, X)
    samples: object         # stages.prepare.Samples, lead (P,)
    opts: object            # SolverOptions, resolved
    grid: object
    physics: dict           # shared_sigma, sss_after_direct
    widths: str             # how widths count in k (selection.free_parameters)
    bounds: dict            # refinement's sigma and alpha bounds
    params: dict            # P-shaped, component keys (and background)
    flags: np.ndarray       # (P,)
    live: np.ndarray        # (P,) bool: decomposed pixels
    resolved: np.ndarray    # (P,) bool: the search's AMBIGUOUS resolved by the neighbours
    info: dict
    hold: dict = field(default_factory=dict)   # {HOLD_KEYS: (P,)}: parameters every fit keeps (shared=)
    noise_law: dict | None = None   # {"floor", "gain"}: the detector's photon-noise law the search weighed by
    irf: object = None      # the measured response the components are atoms of (resolved), or None: the Gaussian PSF
    inst: tuple = GAUSSIAN_PSF      # its atoms for the compiled kernels (kernels.projected.instrument)


def _decompose_default(name):
    return inspect.signature(decompose).parameters[name].default


def prepare_coupling(cube: np.ndarray, result: DecompositionResult, time_bin_ps: float, method: str,
                     keywords: dict, *, hold: dict | None = None) -> Coupling:
    """The samples of ``cube`` (Y, X, L) prepared as :func:`decompose` prepared them for
    ``result`` (its keywords), and ``result``'s parameters flattened to P = Y X pixels;
    ``hold`` ({HOLD_KEYS: (Y, X)}) the parameters every refit keeps (the shared ones; a
    response's shared time scale stretches the response, :func:`decomposition.image.shared.held_response`).
    With a measured response (``keywords["irf"]``) every fit, objective and error of the coupling
    reads the response's atoms."""
    Y, X, L = cube.shape
    hold, kw = held_response(L, time_bin_ps, dict(hold or {}), dict(keywords))
    irf = kw.pop("irf", None)
    if irf is not None:         # (``result``'s call refused it with another method than convscd)
        irf = resolve_response(irf, time_bin_ps, L)
    t0 = kw.pop("t0_ps", _decompose_default("t0_ps"))
    fams = parse_components(kw.pop("components", _decompose_default("components")))
    nan_policy = kw.pop("nan_policy", _decompose_default("nan_policy"))
    saturation = kw.pop("saturation_level", _decompose_default("saturation_level"))
    grid, opts, _ = options_from_mapping(kw, strict=False)
    opts = opts.resolved(fams, response=irf is not None)
    axis = time_axis(time_bin_ps, t0)
    samples = prepare_samples(cube.reshape(Y * X, L), axis, grid, nan_policy=nan_policy, saturation_level=saturation,
                              noise_floor=opts.noise_floor, rel_threshold=opts.rel_threshold, noise=opts.noise,
                              background="b" in fams,
                              **spike_settings(irf, time_bin_ps, opts.spike_sigma, opts.rel_threshold))
    convscd = method == "convscd"
    physics = {"shared_sigma": opts.shared_sigma and convscd and irf is None,
               "sss_after_direct": opts.sss_after_direct and convscd}
    keys = DIRECT_KEYS + SSS_KEYS + IR_KEYS + ((BACKGROUND_KEY,) if BACKGROUND_KEY in result.params else ())
    P = Y * X
    params = {k: np.array(result.params[k], np.float64).reshape((P,) + np.shape(result.params[k])[2:]) for k in keys}
    live = np.zeros(P, bool)
    live[samples.live] = True
    bounds = shape_bounds(grid, opts.bound_factor)
    widths = "fixed" if irf is not None else "shared" if physics["shared_sigma"] else "per_atom"
    return Coupling(shape=(Y, X), samples=samples, opts=opts, grid=grid, physics=physics,
                    widths=widths, bounds=bounds, params=params,
                    flags=np.asarray(result.flags).reshape(P).copy(), live=live, resolved=np.zeros(P, bool), info={},
                    hold={k: np.broadcast_to(np.asarray(v, np.float64), (Y, X)).reshape(P) for k, v in (hold or {}).items()},
                    noise_law=_searched_law(result.info, samples.noise_model), irf=irf,
                    inst=response_instrument(irf, time_axis_ps(L, time_bin_ps, t0)))


def _searched_law(info: dict, noise_model: str) -> dict | None:
    """The detector's variance law (``floor`` + ``gain`` x signal, the data's units) by which the
    per-pixel call weighed its float samples (``info["signal_noise_law_fit"]`` with a positive
    gain, :func:`decomposition.stages.candidates.signal_weights`), or None (count data, or no
    such law)."""
    law = info.get("signal_noise_law_fit")
    if noise_model == "poisson" or not isinstance(law, dict) or not float(law.get("gain", 0.0)) > 0:
        return None
    return {"floor": float(law["floor"]), "gain": float(law["gain"])}


def noise_variance(c: Coupling) -> np.ndarray:
    """(P,) the variance the weighted residual's squares are read in (Poisson weights: 1)."""
    s = c.samples
    if s.noise_model == "poisson":
        return np.ones(s.values.shape[0])
    return np.maximum(s.noise_eff * s.scale, 1e-300) ** 2


def objective_weights(c: Coupling, params: dict) -> np.ndarray:
    """(P, L) the weights the fits of a pixel are refitted and compared with (J's data term in
    :func:`objective`), read at the model of ``params`` and the same for every candidate of a
    pixel: as the per-pixel search weighed its samples.  Count data: the Poisson weights; float
    data whose noise follows the signal (the call's detector law, :attr:`Coupling.noise_law`):
    the fit mask times noise^2 / the law's variance at the model, so that the data term is the
    sum of residual^2 / variance (photon noise, largest at the peaks, is not read as structure
    that a split direct or an extra inter-reflection would explain); else the fit mask."""
    w = sample_weights(c.samples, params)
    if c.noise_law is None:
        return w
    s = c.samples
    scale = np.maximum(np.nan_to_num(s.scale), 1e-300)
    model = np.maximum(_model(c, params), 0.0) / scale[:, None]
    var = detector_variance(c.noise_law["floor"], c.noise_law["gain"], model, scale)
    with np.errstate(invalid="ignore", divide="ignore"):
        law = np.nan_to_num(s.noise_eff[:, None] ** 2 / var, nan=0.0, posinf=0.0)
    return np.where(w > 0, w * law, 0.0)


def take_rows(params: dict, rows) -> dict:
    return {k: v[rows] for k, v in params.items()}


def _model(c: Coupling, params: dict) -> np.ndarray:
    axis = c.samples.axis
    with np.errstate(invalid="ignore"):
        if c.irf is None:
            m = render_profile(params, c.samples.n_bins, axis.time_bin_ps, axis.t0_ps)
        else:
            m = params_profile(c.irf, time_axis_ps(c.samples.n_bins, axis.time_bin_ps, axis.t0_ps), params)
    return np.where(np.isfinite(m), m, 0.0)


def objective(c: Coupling, rows: np.ndarray, params: dict, weights: np.ndarray) -> np.ndarray:
    """(n,) J of ``params`` (n-shaped) on the pixels ``rows``, the residual weighed by ``weights``
    (n, L) in the pixels' noise (:mod:`decomposition.stages.selection`): its data term the
    weighted RSS at the model (:func:`decomposition.model.varpro.rss_at`, the refine's own
    kernels -- a response's atoms with one -- and offset) over the pixel's noise variance."""
    s = c.samples
    n = len(rows)
    slots = slot_arrays(params if c.irf is None else unit_widths(params), (n,))
    present = slots["present"]
    with np.errstate(invalid="ignore"):
        sig = np.where(present, slots["sigma"], 1.0)
        alp = np.where(present[:, SSS_SLOT], slots["alpha"], 1.0)
    offset = np.nan_to_num(np.asarray(params[BACKGROUND_KEY], np.float64)) if BACKGROUND_KEY in params else np.zeros(n)
    sw = np.sqrt(weights)
    rss = rss_at(time_axis_ps(s.n_bins, s.axis.time_bin_ps, s.axis.t0_ps), s.values[rows] * sw,
                 np.where(present, slots["delay"], 0.0), sig, alp, present, np.where(present, slots["amplitude"], 0.0),
                 offset, None, sw, c.inst)
    k = free_parameters(families(params), c.widths)
    return penalised(rss / noise_variance(c)[rows], k, log_samples(s.fit[rows].sum(axis=1)), c.opts.search_penalty)


def refit(c: Coupling, rows: np.ndarray, start: dict, weights: np.ndarray, prior=None, priors=None) -> dict:
    """The refit of ``start`` (n-shaped) on the pixels ``rows``, as the per-pixel refit stage
    runs it (bounds, physics, the background fitted where the pixel has one); ``prior`` the
    direct delay's (mean, weight), ``priors`` more of :func:`decomposition.model.refine.refine`'s
    priors by keyword (``alpha_prior``, ``ratio_prior``)."""
    s = c.samples
    fit_bg = (np.isfinite(start[BACKGROUND_KEY]) & (start[BACKGROUND_KEY] != 0)) if BACKGROUND_KEY in start else False
    out, _ = refine(s.values[rows], start, time_bin_ps=s.axis.time_bin_ps, t0_ps=s.axis.t0_ps, weights=weights,
                    fit_background=fit_bg, sigma_bounds_ps=tuple(np.exp(c.bounds["lsig"])),
                    alpha_bounds_per_ps=tuple(np.exp(c.bounds["lalp"])), delay_prior=prior,
                    hold={k: v[rows] for k, v in c.hold.items()} or None, **(priors or {}), **c.physics,
                    irf=c.irf)
    return out


# --------------------------------------------------------------------------- neighbourhoods

def shifted(a: np.ndarray, shape: tuple, dy: int, dx: int, fill) -> np.ndarray:
    """(P, ...) ``a`` of an image ``shape`` (Y, X) read at (y + dy, x + dx): ``fill`` off the image."""
    Y, X = shape
    img = a.reshape((Y, X) + a.shape[1:])
    out = np.full_like(img, fill)
    ys, yd = slice(max(dy, 0), Y + min(dy, 0)), slice(max(-dy, 0), Y + min(-dy, 0))
    xs, xd = slice(max(dx, 0), X + min(dx, 0)), slice(max(-dx, 0), X + min(-dx, 0))
    out[yd, xd] = img[ys, xs]
    return out.reshape(a.shape)


def _offsets(radius: int):
    r = int(radius)
    return tuple((dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if (dy, dx) != (0, 0))


def neighbour_prior(delay: np.ndarray, stderr: np.ndarray, shape: tuple, options: SpatialOptions,
                    scale: float | None = None):
    """The robust neighbourhood estimate of each pixel's direct delay (or of another parameter
    neighbours share) and the prior's precision.

    Parameters
    ----------
    delay, stderr : ndarray (P,)
        The pixels' direct delays and their standard errors, ps (NaN: none); or another
        parameter's values and standard errors in its units.
    shape : (Y, X)
    options : SpatialOptions
    scale : float, optional
        How far the parameter may differ between neighbours on one surface, its units (the
        prior's own standard deviation); default ``options.delay_scale_ps``.

    Returns
    -------
    mean : ndarray (P,)       the estimate, ps (NaN where no neighbour has weight)
    precision : ndarray (P,)  the prior's precision on the pixel's delay, 1/ps^2 (0: no prior)
    """
    tau2 = (options.delay_scale_ps if scale is None else float(scale)) ** 2
    c_edge = options.edge_sigma
    nd, ns, ok = _neighbourhood(delay, stderr, shape, options.radius)
    nd_ok = np.where(ok, nd, np.nan)
    P = delay.size
    mean = np.full(P, np.nan)
    precision = np.zeros(P)
    have = ok.any(axis=0)
    if not have.any():
        return mean, precision
    with np.errstate(invalid="ignore", divide="ignore"):
        m, w, _ = _biweight_mean(nd_ok[:, have], ns[:, have], ok[:, have], tau2, c_edge)
        wsum = w.sum(axis=0)
        var_m = np.where(wsum > 0, 1.0 / np.where(wsum > 0, wsum, 1.0), np.inf)
        own = delay[have]
        z = (own - m) / np.sqrt(stderr[have] ** 2 + var_m + tau2)
        b = _tukey(z, c_edge)
        prec = np.where(np.isfinite(m), b / (tau2 + var_m), 0.0)
    mean[have] = m
    precision[have] = prec
    return mean, precision


def _neighbourhood(values: np.ndarray, stderr: np.ndarray, shape: tuple, radius: int):
    """(n_off, P) the values and standard errors of each pixel's neighbours within ``radius``,
    and where both are finite."""
    offs = _offsets(radius)
    nd = np.stack([shifted(values, shape, dy, dx, np.nan) for dy, dx in offs])
    ns = np.stack([shifted(stderr, shape, dy, dx, np.nan) for dy, dx in offs])
    return nd, ns, np.isfinite(nd) & np.isfinite(ns)


def _tukey(z, c):
    """Tukey's biweight (1 - (z / c)^2)^2 of standardised deviations ``z``: 0 at and beyond ``c``
    and where ``z`` is not finite."""
    return np.where(np.isfinite(z) & (np.abs(z) < c), (1 - (z / c) ** 2) ** 2, 0.0)


def _mills(c):
    """The inverse Mills ratio phi(c) / Phi(c), in a form stable far into either tail."""
    return np.exp(-0.5 * c * c - 0.5 * np.log(2 * np.pi) - log_ndtr(c))


def _biweight_mean(nd, ns, ok, tau2, c_edge):
    """Tukey biweight mean of neighbours ``nd`` (n_off, n) around their median, each weighed by
    1 / (its stderr ``ns``^2 + ``tau2``) -> (mean (n,), weights (n_off, n), variances (n_off, n))."""
    median = np.nanmedian(nd, axis=0)
    var = np.where(ok, ns ** 2 + tau2, np.inf)
    u = (nd - median) / np.sqrt(var)
    w = np.where(ok, _tukey(u, c_edge) / var, 0.0)
    wsum = w.sum(axis=0)
    m = np.where(wsum > 0, (w * np.nan_to_num(nd)).sum(axis=0) / np.where(wsum > 0, wsum, 1.0), np.nan)
    return m, w, var


def mixed_neighbourhood(values: np.ndarray, stderr: np.ndarray, shape: tuple, options: SpatialOptions,
                        scale: float, radius: int | None = None, stray_share: float | None = None) -> np.ndarray:
    """(P,) bool: the pixels whose neighbourhood does not share one value of a piecewise-constant
    parameter (a material's): the homogeneity test of the material starts
    (:mod:`decomposition.image.material`).

    Cochran's Q of the neighbours within ``radius`` (default ``options.radius``), each in its
    standard error and ``scale`` (Q = sum (v - mean)^2 / (stderr^2 + scale^2)), lies beyond the
    chi^2 quantile of df = n - 1 degrees of freedom at significance ``options.homogeneity_p``.
    Neighbours of one material scatter as their errors say and pass; neighbours each of its own
    material (their values spread over many standard errors, which the biweight alone would read
    as a few agreeing neighbours and an edge) fail, and so does a pixel next to a material edge.
    A pixel with fewer than two neighbours in the test is mixed.  NaN values (no such parameter)
    are left out.

    ``stray_share`` None: Q of ALL the neighbours about their biweight mean.  A number: the
    neighbours beyond ``options.edge_sigma`` of the neighbourhood's median (each in its standard
    error and ``scale``), strays, are left out and Q is that of the rest about their weighted
    mean, where the strays are fewer than half of the neighbours and hold at most ``stray_share``
    of their information (the sum of 1 / (stderr^2 + scale^2)); else the neighbourhood is mixed.
    At a few hundred photons one material's answers hold strays (an onset at its bound, a noisy
    fit) that would fail the test on all of them; answers of other materials that are sure of
    their values still fail it.  With ``stray_share`` 1 only the count decides: a chance
    majority of neighbours each of its own material can pass, a reading that may only propose
    (the material starts, :mod:`decomposition.image.material`, each kept only where the pixel's
    own data agree).
    """
    from scipy.stats import chi2

    radius = options.radius if radius is None else int(radius)
    nd, ns, ok = _neighbourhood(values, stderr, shape, radius)
    n = ok.sum(axis=0)
    mixed = np.ones(values.size, bool)
    test = n >= 2
    if not test.any():
        return mixed
    nd, ns, ok, n = np.where(ok, nd, np.nan)[:, test], ns[:, test], ok[:, test], n[test]
    with np.errstate(invalid="ignore", divide="ignore"):
        if stray_share is None:
            m, _, var = _biweight_mean(nd, ns, ok, float(scale) ** 2, options.edge_sigma)
            q = np.where(ok, np.nan_to_num(nd - m) ** 2 / var, 0.0).sum(axis=0)
            mixed[test] = ~np.isfinite(m) | (q > chi2.isf(options.homogeneity_p, n - 1))
            return mixed
        var = np.where(ok, ns ** 2 + float(scale) ** 2, np.inf)
        inl = ok & (np.abs(nd - np.nanmedian(nd, axis=0)) < options.edge_sigma * np.sqrt(var))
        n_in = inl.sum(axis=0)
        w = np.where(inl, 1.0 / var, 0.0)
        wsum, w_all = w.sum(axis=0), np.where(ok, 1.0 / var, 0.0).sum(axis=0)
        m = (w * np.nan_to_num(nd)).sum(axis=0) / np.where(wsum > 0, wsum, 1.0)
        q = np.where(inl, np.nan_to_num(nd - m) ** 2 / var, 0.0).sum(axis=0)
    one = ((n_in >= 2) & (2 * n_in > n) & (w_all - wsum <= float(stray_share) * w_all)
           & (q <= chi2.isf(options.homogeneity_p, np.maximum(n_in - 1, 1))))
    mixed[test] = ~one
    return mixed


def censored_location(values: np.ndarray, stderr: np.ndarray, censored: np.ndarray, tau2: float,
                      bound: float, edge_sigma: float, iterations: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """The maximum-likelihood location of samples left-censored at ``bound`` (a Tobit location),
    column by column: ((n,) location, (n,) its variance).

    Each sample is the location plus a normal error of variance stderr^2 + ``tau2``.  A sample
    at its bound (``censored``) is an answer the bound stopped, "at most ``bound``", not the value
    ``bound``: its likelihood is the normal CDF at the bound, Phi((bound - location) / s), its
    own standard error (that of a parameter held at its bound) replaced by the median standard
    error of the column's free samples (a stopped answer would have scattered as they do), or 0
    where none is free.  Where half the samples sit at the bound their median is the bound; this
    location lies where the free ones and the share of stopped ones say.  The log-likelihood is
    concave in the location, so its score is solved by bisection, on blocks of columns at once;
    the location is kept at or above ``bound`` (all stopped: ``bound``).  Robust in two passes:
    free samples beyond ``edge_sigma`` of the first pass's location (each in its own s) are left
    out of the second.

    Parameters
    ----------
    values, stderr : ndarray (m, n)
        The samples of n columns and their standard errors (NaN: no sample).
    censored : ndarray (m, n) bool
        The samples at the bound (their values are not read).
    tau2 : float
        The samples' spread beyond their standard errors (the prior's scale squared).
    bound : float
        The lower bound the samples' parameter was held at.
    edge_sigma : float
        The robust cut-off of the second pass, in standard deviations.
    iterations : int
        Bisection steps (the bracket shrinks by 2 each).

    Returns
    -------
    location : ndarray (n,)   NaN where a column has no sample
    variance : ndarray (n,)   the location's variance, 1 / its Fisher information (inf: none)
    """
    free = ~censored & np.isfinite(values) & np.isfinite(stderr)
    cens = np.asarray(censored, bool)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        se_free = _free_median(stderr, free)
        var_f = np.where(free, stderr ** 2 + tau2, np.inf)
        var_c = np.nan_to_num(se_free, nan=0.0) ** 2 + tau2
        s_c = np.sqrt(var_c)
        v = np.where(free, values, 0.0)

        def score(mu, use):
            z = np.where(use, (v - mu) / var_f, 0.0).sum(axis=0)
            c = (bound - mu) / s_c
            mills = _mills(c)
            return z - cens.sum(axis=0) * mills / s_c

        def solve(use):
            lo = np.full(values.shape[1], float(bound))
            hi = np.maximum(np.where(use, v, bound).max(axis=0), bound) + 1e-9
            at_bound = score(lo, use) <= 0
            for _ in range(iterations):
                mid = 0.5 * (lo + hi)
                up = score(mid, use) > 0
                lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
            return np.where(at_bound, float(bound), 0.5 * (lo + hi))

        mu = solve(free)
        use = free & (np.abs(v - mu) <= edge_sigma * np.sqrt(var_f))
        mu = solve(use)
        # Fisher information: the free samples' 1 / var plus each stopped one's
        c = (bound - mu) / s_c
        mills = _mills(c)
        info = np.where(use, 1.0 / var_f, 0.0).sum(axis=0) + cens.sum(axis=0) * mills * (mills + c) / var_c
        var = np.where(info > 0, 1.0 / np.where(info > 0, info, 1.0), np.inf)
    none = ~(use | cens).any(axis=0)
    return np.where(none, np.nan, mu), np.where(none, np.inf, var)


#: an sss onset (ps after the direct) at most this is at its bound 0 (the refinement projects an
#: onset before the direct onto it)
ONSET_BOUND_PS = 1e-6

def _free_median(stderr: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(n,) the median of ``stderr`` (m, n) over the ``free`` rows of each column (NaN: none)."""
    out = np.full(stderr.shape[1], np.nan)
    cols = free.any(axis=0)
    if cols.any():
        out[cols] = np.nanmedian(np.where(free, stderr, np.nan)[:, cols], axis=0)
    return out


def onset_prior(onset: np.ndarray, stderr: np.ndarray, shape: tuple, options: SpatialOptions,
                material: np.ndarray | None = None):
    """The material prior of the sss onset after the direct: (mean (P,), precision (P,)).

    The mean is the censored location (:func:`censored_location`) of the neighbours' onsets within
    ``options.material_radius`` (the pixel itself left out), an onset at its bound 0
    (:data:`ONSET_BOUND_PS`) read as "at most 0" rather than as 0: at a few hundred photons, or
    where the sss is weak against the noise, half of one material's onsets sit at the bound and
    the rest scatter late, so a median sits at 0 and a homogeneity test of the values finds
    every such neighbourhood mixed.  The prior is given where ``material`` (P,) bool (the pixel
    has a material by its ratio and decay rate, :func:`material_members`; None: everywhere); the
    estimate's second pass leaves out free onsets beyond ``options.edge_sigma``, and the pixel's own onset weighs the
    prior by its Tukey biweight against the mean in its standard error, the mean's and
    ``onset_scale_ps`` (a pixel sure of another onset is not pulled).  A pixel whose own onset is
    at the bound has no standard error of its own (the onset is held there, tied to the direct):
    it is read as the bound stopping a free onset that scatters like the neighbours' free ones
    (their median standard error), and weighs the prior by how far the mean lies above the bound
    in that error.  Precision b / (``onset_scale_ps``^2 + the mean's variance), b that biweight;
    0 and mean NaN where no neighbour has an onset.
    """
    tau2 = options.onset_scale_ps ** 2
    nd, ns, ok = _neighbourhood(onset, stderr, shape, options.material_radius)
    nd = np.where(ok, nd, np.nan)
    cen = ok & (nd <= ONSET_BOUND_PS)
    P = onset.size
    mean, precision = np.full(P, np.nan), np.zeros(P)
    have = ok.any(axis=0) & np.isfinite(onset)
    if material is not None:
        have &= material
    if not have.any():
        return mean, precision
    nd, ns, ok, cen = nd[:, have], ns[:, have], ok[:, have], cen[:, have]
    m, var_m = censored_location(nd, ns, cen, tau2, 0.0, options.edge_sigma)
    free = ok & ~cen
    with np.errstate(invalid="ignore", divide="ignore"):
        se_free = np.nan_to_num(_free_median(ns, free), nan=0.0)
        own, own_se = onset[have], stderr[have]
        z = np.where(own <= ONSET_BOUND_PS, np.maximum(m, 0.0) / np.sqrt(se_free ** 2 + var_m + tau2),
                     (own - m) / np.sqrt(own_se ** 2 + var_m + tau2))
        b = _tukey(z, options.edge_sigma)
        mean[have] = m
        precision[have] = np.where(np.isfinite(m), b / (tau2 + var_m), 0.0)
    return mean, precision


def material_members(values: dict, shape: tuple, options: SpatialOptions,
                     names: tuple = ("ratio", "alpha")) -> np.ndarray:
    """(n_off, P) bool: which neighbours within ``options.material_radius`` (in the order of
    :func:`_neighbourhood`) are of the pixel's own material, by its own answers.

    A material is told by its sss-to-direct amplitude ratio and its sss decay rate (their
    logarithms, the better determined of what a material shares): a neighbour is a member where
    both of its values differ from the pixel's by at most ``options.material_agreement_sigma``
    standard deviations of the difference, sqrt(stderr_pixel^2 + stderr_neighbour^2 + 2 scale^2),
    and the members are at least half of the neighbours with both values (a minority that agrees
    is chance, among pixels each of its own material, or the far side of an edge).  A pixel or
    neighbour without an sss (NaN) has no members.

    Parameters
    ----------
    values : dict
        {name: ((P,) values, (P,) standard errors, the prior's scale)} holding ``names`` as
        :func:`prior_values` gives them.
    shape : (Y, X)
    options : SpatialOptions
    names : tuple
        The parameters read (a decay rate held by ``shared=`` tells no material: leave it out).
    """
    k = options.material_agreement_sigma
    members = have = None
    for name in names:
        v, se, scale = values[name]
        nd, ns, ok = _neighbourhood(v, se, shape, options.material_radius)
        with np.errstate(invalid="ignore"):
            agree = ok & (np.abs(nd - v) <= k * np.sqrt(ns ** 2 + se ** 2 + 2.0 * float(scale) ** 2))
        members = agree if members is None else members & agree
        have = ok if have is None else have & ok
    return members & (2 * members.sum(axis=0) >= have.sum(axis=0))


#: the fewest members (:func:`material_members`) that give a pixel a material prior
MATERIAL_MEMBERS_MIN = 2


def material_prior(values: np.ndarray, shape: tuple, options: SpatialOptions, scale: float,
                   members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The material prior of the sss amplitude ratio or decay rate: (mean (P,), precision (P,)).

    The mean is the median of the pixel's own value and those of its ``members`` (n_off, P)
    (:func:`material_members`, within ``options.material_radius``); the precision
    1 / ``scale``^2 where the pixel has at least :data:`MATERIAL_MEMBERS_MIN` members with a
    value, else 0 (no prior).  The median, not a weighted mean: at a few hundred photons one
    material's answers are heavy-tailed, and their standard errors do not say which are off.
    """
    nd, _, ok = _neighbourhood(values, np.zeros_like(values), shape, options.material_radius)
    nd = np.where(members & ok, nd, np.nan)
    n = np.isfinite(nd).sum(axis=0)
    with np.errstate(invalid="ignore"):
        allv = np.concatenate([nd, values[None]], axis=0)
        have = np.isfinite(allv).any(axis=0)
        mean = np.full(values.size, np.nan)
        mean[have] = np.nanmedian(allv[:, have], axis=0)
    on = (n >= MATERIAL_MEMBERS_MIN) & np.isfinite(mean)
    return np.where(on, mean, np.nan), np.where(on, 1.0 / float(scale) ** 2, 0.0)


#: the parameters of the joint refinement's prior: name -> the keyword of
#: :func:`decomposition.model.refine.refine` that carries it
_PRIOR_KEYWORDS = {"delay": "delay_prior", "onset": "onset_prior", "ratio": "ratio_prior", "alpha": "alpha_prior"}


def _shared_values(params: dict, live: np.ndarray, options: SpatialOptions, err: dict | None = None) -> dict:
    """{name: ((P,) values, (P,) standard errors or None, the prior's scale)} of the parameters
    neighbours share (NaN where a pixel has none): the direct delay (ps) and, with
    ``options.material_prior``, the sss onset after the direct (ps), ln(sss amplitude / direct
    amplitude) and ln(sss decay rate).  ``err``: the ``<key>_stderr`` arrays (P,) from the
    pixel's own data, for the values' standard errors (the ratio's two amplitudes combined as if
    independent; a held decay rate has none)."""
    def se(f):
        return None if err is None else f()

    out = {"delay": (np.where(live, params["direct_delay_ps"], np.nan),
                     se(lambda: np.where(live, err["direct_delay_ps_stderr"], np.nan)), options.delay_scale_ps)}
    if not options.material_prior:
        return out
    cd, cs, alpha = params["direct_amplitude"], params["sss_amplitude"], params["sss_alpha_per_ps"]
    with np.errstate(invalid="ignore", divide="ignore"):
        ok_r = live & (cd > 0) & (cs > 0)
        ratio = np.where(ok_r, np.log(cs / cd), np.nan)
        ratio_se = se(lambda: np.where(ok_r, np.hypot(err["sss_amplitude_stderr"] / cs,
                                                      err["direct_amplitude_stderr"] / cd), np.nan))
        ok_a = live & (alpha > 0)
        log_alpha = np.where(ok_a, np.log(alpha), np.nan)
        alpha_se = se(lambda: np.where(ok_a, err["sss_alpha_per_ps_stderr"] / alpha, np.nan))
    ok_o = live & np.isfinite(cs)
    out["onset"] = (np.where(ok_o, params["sss_delay_ps"] - params["direct_delay_ps"], np.nan),
                    se(lambda: np.where(ok_o, np.hypot(err["sss_delay_ps_stderr"], err["direct_delay_ps_stderr"]),
                                        np.nan)), options.onset_scale_ps)
    out["ratio"] = (ratio, ratio_se, options.ratio_scale)
    out["alpha"] = (log_alpha, alpha_se, options.alpha_scale)
    return out


def refine_priors(priors: dict, noise2: np.ndarray, direct_amplitude: np.ndarray) -> dict:
    """{name of :func:`_shared_values`: ((n,) mean, (n,) precision)} -> the keywords of
    :func:`decomposition.model.refine.refine` that carry them (``delay_prior``, ...), each
    (mean, weight): the precision times the pixels' noise variance ``noise2`` (n,)
    (:func:`noise_variance`), the ratio's in the amplitudes at ``direct_amplitude`` (n,)."""
    kw = {}
    for name, (m, p) in priors.items():
        w = p * noise2
        if name == "ratio":
            # ln(c_s / c_d) - mean ~ (c_s - rho c_d) / (rho c_d), rho = e^mean, at the
            # pixel's current direct amplitude
            rho = np.exp(m)
            with np.errstate(invalid="ignore", divide="ignore"):
                w = np.where(w > 0, w / (rho * direct_amplitude) ** 2, 0.0)
            m = rho
        kw[_PRIOR_KEYWORDS[name]] = (m, np.nan_to_num(w, nan=0.0, posinf=0.0))
    return kw


def prior_values(c: Coupling, params: dict, options: SpatialOptions) -> dict:
    """:func:`_shared_values` at ``params`` with their standard errors from the pixel's own data."""
    errs = component_errors(c.samples, params, **c.physics, hold=c.hold or None, irf=c.irf)
    return _shared_values(params, c.live, options, {k: np.asarray(v, np.float64).reshape(-1) for k, v in errs.items()})


def joint_refinement(c: Coupling, options: SpatialOptions) -> None:
    """Step 2 (module docstring): ``sweeps`` Jacobi sweeps, every decomposed pixel with a direct
    refitted with its neighbours' prior on its direct delay and (``options.material_prior``) its
    sss-to-direct amplitude ratio and sss decay rate; ``c`` updated in place."""
    rows = np.flatnonzero(c.live & np.isfinite(c.params["direct_delay_ps"]))
    c.info["spatial_pulled"] = 0
    if options.sweeps == 0 or rows.size == 0:
        return
    own = prior_values(c, c.params, options)
    stderr = {name: se for name, (_, se, _) in own.items()}
    # a material's members are found on the pixels' own answers (pulled ones agree more than
    # their data do) and stay the same in every sweep
    told_by = ("ratio",) if "sss_alpha_per_ps" in c.hold else ("ratio", "alpha")
    members = material_members(own, c.shape, options, told_by) if options.material_prior else None
    base = take_rows(c.params, rows)           # each pixel's own answer
    weights = objective_weights(c, c.params)[rows]
    noise2 = noise_variance(c)[rows]
    pulled = np.zeros(rows.size, bool)
    last = {}               # the last sweep's prior (mean, precision) on rows per name; NaN: none
    refits = 0
    for _ in range(options.sweeps):
        # the values where the last sweep left them; the errors stay the pixels' own
        current = _shared_values(c.params, c.live, options) if len(own) > 1 else own
        priors, pull, same = {}, np.zeros(rows.size, bool), np.ones(rows.size, bool)
        for name, (value, _, scale) in current.items():
            if name == "delay":
                value = np.where(c.live, c.params["direct_delay_ps"], np.nan)
            if name == "delay":
                mean, precision = neighbour_prior(value, stderr[name], c.shape, options, scale)
            elif name == "onset":
                mean, precision = onset_prior(value, stderr[name], c.shape, options,
                                              material=members.sum(axis=0) >= MATERIAL_MEMBERS_MIN)
            else:
                mean, precision = material_prior(value, c.shape, options, scale, members)
            m, p = mean[rows], precision[rows]
            on = p > 0
            pull |= on
            # a pixel refitted last sweep with (almost) this prior is where that refit left it:
            # only the pixels whose prior appeared, went or moved are refitted (or go back)
            same &= np.zeros(rows.size, bool) if name not in last else _same_prior(m, p, *last[name])
            last[name] = (np.where(on, m, np.nan), p)
            priors[name] = (m, p)
        pulled |= pull
        redo = ~same
        if not redo.any():
            break
        # a pixel without a prior this sweep is its own answer; one with a prior is refitted
        # from where the last sweep left it
        back = redo & ~pull
        for k in c.params:
            c.params[k][rows[back]] = base[k][back]
        fit = redo & pull
        if fit.any():
            r = rows[fit]
            kw = refine_priors({name: (m[fit], p[fit]) for name, (m, p) in priors.items()}, noise2[fit],
                               c.params["direct_amplitude"][r])
            fits = refit(c, r, take_rows(c.params, r), weights[fit], kw.pop("delay_prior"), kw)
            refits += int(fit.sum())
            for k in c.params:
                c.params[k][r] = fits[k]
    c.info["spatial_pulled"] = int(pulled.sum())
    c.info["spatial_refits"] = refits


#: a prior is the same as the last sweep's when its mean moved by less than this fraction of its
#: standard deviation and its precision by less than this fraction of itself
_SAME_PRIOR = 0.01


def _same_prior(mean, precision, last_mean, last_precision) -> np.ndarray:
    """(n,) bool: the prior (``mean``, ``precision``) is the last sweep's to within
    :data:`_SAME_PRIOR` (both none counts as the same; a refit from there would end where it is)."""
    none = ~(precision > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        close = ((np.abs(mean - last_mean) * np.sqrt(precision) <= _SAME_PRIOR)
                 & (np.abs(precision - last_precision) <= _SAME_PRIOR * precision))
    return np.where(none, ~(last_precision > 0), close)


def coupled_result(c: Coupling, result: DecompositionResult, options: SpatialOptions) -> DecompositionResult:
    """``result`` with ``c``'s parameters: the fit rendered again, its quality flags read again
    (the search's AMBIGUOUS kept where the neighbours did not resolve it), standard errors
    recomputed where ``result`` has them, ``info["spatial"]`` what the coupling did."""
    s = c.samples
    Y, X = c.shape
    P, L = Y * X, s.n_bins
    fit = assess_fit(s, c.params, s.noise_eff, c.opts.poor_fit, irf=c.irf)
    quality = POOR_FIT | EMPTY | AMBIGUOUS
    kept_ambiguous = c.flags & AMBIGUOUS & np.where(c.resolved, 0, AMBIGUOUS).astype(c.flags.dtype)
    flags = np.where(c.live, (c.flags & ~quality) | fit.flags | kept_ambiguous, c.flags).astype(c.flags.dtype)
    params = {k: np.array(v, copy=True) for k, v in result.params.items()}
    for k, v in c.params.items():
        params[k] = v.reshape((Y, X) + v.shape[1:])
    if "direct_delay_ps_stderr" in params:
        errs = component_errors(s, c.params, **c.physics, hold=c.hold or None, irf=c.irf)
        for k, v in errs.items():
            params[k] = np.asarray(v).reshape((Y, X) + np.shape(v)[1:])
    R = fit.interreflections.shape[1]
    info = dict(result.info)
    info["spatial"] = dict(asdict(options), coupling_reach=coupling_reach(options), **c.info)
    live = c.live[:, None]
    return DecompositionResult(
        direct=np.where(live, fit.direct, result.direct.reshape(P, L)).reshape(Y, X, L),
        sss=np.where(live, fit.sss, result.sss.reshape(P, L)).reshape(Y, X, L),
        interreflections=np.where(live[:, :, None], fit.interreflections,
                                  result.interreflections.reshape(P, R, L)).reshape(Y, X, R, L),
        params=params, residual=np.where(live, fit.residual, result.residual.reshape(P, L)).reshape(Y, X, L),
        flags=flags.reshape(Y, X), info=info)
