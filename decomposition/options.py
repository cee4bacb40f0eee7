"""Options of :func:`decomposition.decompose`: frozen dataclasses, validated once where built.

:class:`GridSpec` holds the kernel grid, :class:`SolverOptions` everything else the ConvSCD
path reads.  Both are checked in ``__post_init__`` (types, ranges), so an instance is always
valid; :func:`options_from_mapping` builds them from a plain ``{name: value}`` mapping (the
keywords of ``decompose()``, the CLI's ``--option KEY=VALUE``), refusing unknown names with
an error that names the option.  ``dataclasses.asdict`` of the two feeds
``DecompositionResult.info`` and the result store's attributes.

Also here, the vocabularies every layer shares: the methods (:data:`METHODS`), the component
families (:func:`parse_components`) and the NaN policy (:data:`NAN_POLICIES`, :func:`parse_nan_policy`).
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import numbers
import textwrap
from dataclasses import dataclass, fields

import numpy as np

__all__ = [
    "METHODS",
    "GridSpec",
    "SolverOptions",
    "OptionError",
    "options_from_mapping",
    "option_names",
    "parse_components",
    "component_letters",
    "NAN_POLICIES",
    "parse_nan_policy",
    "NOISE_MODELS",
    "SIGNAL_NOISE_LAWS",
    "parse_noise_model",
]

#: the solvers ``decompose(method=...)`` runs: ConvSCD, and the GradBM baseline
METHODS = ("convscd", "gradbm")


class OptionError(ValueError):
    """An option has an unknown name, the wrong type or a value out of range."""


# --------------------------------------------------------------------------- field checks

def _number(name, v, *, lo=None, lo_open=False, integer=False, allow_none=False):
    if v is None and allow_none:
        return None
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise OptionError(f"option {name}: must be {'an integer' if integer else 'a number'}, got {v!r}")
    given = v
    if integer:
        if isinstance(v, numbers.Integral):
            v = int(v)
        elif float(v).is_integer():
            v = int(v)
        else:
            raise OptionError(f"option {name}: must be an integer, got {given!r}")
    else:
        v = float(v)
        if not math.isfinite(v):
            raise OptionError(f"option {name}: must be finite, got {given!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise OptionError(f"option {name}: must be {'>' if lo_open else '>='} {lo:g}, got {given!r}")
    return v


def _flag(name, v, allow_none=False):
    if v is None and allow_none:
        return None
    if not isinstance(v, (bool, np.bool_)):
        raise OptionError(f"option {name}: must be true or false, got {v!r}")
    return bool(v)


def _range(name, v):
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        raise OptionError(f"option {name}: expected a pair (lo, hi) of numbers, got {v!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise OptionError(f"option {name}: must be 0 < lo <= hi, got {v!r}")
    return (lo, hi)


def _set(obj, name, value):
    object.__setattr__(obj, name, value)


# --------------------------------------------------------------------------- the options

def _field_docs(cls) -> dict:
    """``{field: text}`` from the ``#:`` comments above each field of ``cls`` in its source."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    docs, pending = {}, []
    for line in lines:
        text = line.strip()
        if text.startswith("#:"):
            pending.append(text[2:].strip())
        elif pending and ":" in text:
            docs[text.split(":", 1)[0].strip()] = " ".join(pending)
            pending = []
        else:
            pending = []
    return docs


def _documented(cls):
    """Append an *Attributes* section, one entry per field from its ``#:`` comment, to the class
    docstring, so that ``help()`` and ``pydoc`` show what every option means."""
    docs = _field_docs(cls)
    entries = []
    for f in fields(cls):
        wrapped = textwrap.fill(docs.get(f.name, ""), 92, initial_indent="        ", subsequent_indent="        ")
        entries.append(f"    {f.name} : default {f.default!r}\n{wrapped}")
    cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n\n    Attributes\n    ----------\n" + "\n".join(entries) + "\n"
    cls.field_docs = docs
    return cls


@_documented
@dataclass(frozen=True)
class GridSpec:
    """Kernel-parameter grids.

    The *reference* grid (the paper's) is sigma 1-10 ps and alpha 0.01-0.05 /ps
    with 500 equi-spaced samples each; ``coarse_*`` are the numbers of grid
    values actually correlated against (a subsample of the reference range,
    log-spaced: Gaussian sigmas, sss sigmas x alphas); refined values live
    anywhere within ``bound_factor`` of the ranges (``off_grid=True``) or on the
    reference grid (``off_grid=False``).  The reference grid is searched coarse-to-fine,
    never densely.
    """

    #: Range (lo, hi) of the reference PSF-width grid, ps (the paper's 1-10 ps).
    sigma_range_ps: tuple = (1.0, 10.0)
    #: Samples of the reference PSF-width grid (equi-spaced over ``sigma_range_ps``).
    n_sigma: int = 500
    #: Range (lo, hi) of the reference sss-attenuation grid, 1/ps (the paper's 0.01-0.05 /ps).
    alpha_range_per_ps: tuple = (0.01, 0.05)
    #: Samples of the reference sss-attenuation grid (equi-spaced over ``alpha_range_per_ps``).
    n_alpha: int = 500
    #: Gaussian sigmas correlated in the detection step; small values are fast, refinement does the rest.
    coarse_sigma: int = 4
    #: sss alphas correlated in the detection step (times ``coarse_sss_sigma`` sss kernels).
    coarse_alpha: int = 3
    #: sss sigmas correlated in the detection step (times ``coarse_alpha`` sss kernels).
    coarse_sss_sigma: int = 3

    def __post_init__(self):
        _set(self, "sigma_range_ps", _range("sigma_range_ps", self.sigma_range_ps))
        _set(self, "alpha_range_per_ps", _range("alpha_range_per_ps", self.alpha_range_per_ps))
        for name in ("n_sigma", "n_alpha", "coarse_sigma", "coarse_alpha", "coarse_sss_sigma"):
            _set(self, name, _number(name, getattr(self, name), lo=1, integer=True))

    def check(self) -> "GridSpec":
        """The grid itself (validated when built; kept for callers of the older interface)."""
        return self

    def fine_sigma(self) -> np.ndarray:
        """The reference sigma grid (n_sigma,), ps."""
        return np.linspace(*self.sigma_range_ps, self.n_sigma)

    def fine_alpha(self) -> np.ndarray:
        """The reference alpha grid (n_alpha,), 1/ps."""
        return np.linspace(*self.alpha_range_per_ps, self.n_alpha)


@_documented
@dataclass(frozen=True)
class SolverOptions:
    """Everything but the grid that the ConvSCD path of ``decompose()`` reads.

    ``max_iter=None`` means ``max_components + 2``; ``stderr=None`` means the same as
    ``refine`` (:meth:`resolved` fills both in).  docs/decomposition.md describes the stages
    these options steer.
    """

    #: Keep continuous refined parameters (True) or snap them to the reference grid with
    #: integer-bin delays (False, the paper's setting).
    off_grid: bool = True
    #: Atoms per pixel in the sparse-coding step.
    max_components: int = 6
    #: R, the number of inter-reflection slots in the output (0 without the "r" family).
    max_reflections: int = 3
    #: Outer (pick + refine) iterations per pixel; None: ``max_components + 2``.
    max_iter: int | None = None
    #: Levenberg-Marquardt iterations after each pick.
    n_lm: int = 4
    #: Levenberg-Marquardt iterations of the final polish.
    n_polish: int = 30
    #: A pixel's refinement stops when a step gains less than lm_tol x its objective per sample.
    lm_tol: float = 1e-2
    #: Sparsity weight mu = sparsity * s^2, with s the pixel's noise estimate (floored at
    #: ``noise_floor`` x the pixel's peak).
    sparsity: float = 3.0
    #: eps = eps_rel * s, the log-sum penalty's scale, with s the pixel's noise estimate.
    eps_rel: float = 0.01
    #: Floor of the per-pixel noise estimate, as a fraction of the pixel's peak.
    noise_floor: float = 1e-3
    #: The paper's 5 % threshold: an atom whose peak height inside the window is at least this
    #: fraction of the pixel's largest in-window peak is kept.
    rel_threshold: float = 0.05
    #: An atom below the relative threshold is still kept when it is significant against the
    #: noise where it lies: its in-window energy sum(c_i^2) / s^2 at least this (25, the energy
    #: of a 5-sigma sample; :func:`decomposition.model.components.threshold`).  0 turns the
    #: significance rule off (the relative threshold alone).  The forward steps need it > 0.
    significance_chi2: float = 25.0
    #: A fitted background ("b") is kept when its likelihood-ratio statistic is at least this
    #: (>= 0; 0 keeps every fitted offset).  None: ln(n) for a pixel of n fitted samples, the
    #: Bayesian information criterion for one parameter (5.5 for 256 bins;
    #: :func:`decomposition.stages.background.background_threshold`).
    background_chi2: float | None = None
    #: Gaussians of one pixel closer than this (in bins) are merged.
    merge_tol_bins: float = 1.0
    #: Refined sigma and alpha stay within the grid ranges widened by this factor; AT_BOUND
    #: where one ends at a bound.
    bound_factor: float = 4.0
    #: POOR_FIT flag when the residual RMS exceeds this many times the noise estimate.
    poor_fit: float = 3.0
    #: Single-sample spikes this many noise sigmas above both neighbours, and too narrow for the
    #: narrowest kernel, are excluded and flagged SPIKE (0 = off).  Count data
    #: (``noise="poisson"``) are tested against their counting statistics instead, at a fixed
    #: false-alarm rate per profile (:func:`decomposition.stages.prepare.find_count_spikes`);
    #: there this only switches the test on (> 0) or off.
    spike_sigma: float = 8.0
    #: Where the primary (Gaussian-first) start leaves a fit above the noise, also run the
    #: unrestricted largest-decrease start and keep the lower objective
    #: (``convscd.solve_multistart``); False: the primary start only.
    multistart: bool = True
    #: One PSF width per pixel shared by all its components (eq. (2) has a single camera PSF
    #: c(t)); False lets every atom have its own width.
    shared_sigma: bool = True
    #: Keep the sss onset at or after the direct reflection (light enters the surface where it
    #: is directly reflected); removes the near-degeneracy of a direct peak and an sss rising
    #: edge at the same onset.
    sss_after_direct: bool = True
    #: Also consider, per pixel, an sss with no direct reflection (pixels that see only light
    #: scattered out of a translucent volume).  Off by default: slower, and the paper's model
    #: gives every pixel a direct (``components="s"`` handles scenes with sss only).
    sss_alone: bool = False
    #: Pixels per solver block.
    block_size: int = 512
    #: After the sparse step, refine every found component's continuous parameters by weighted
    #: least squares on the forward model (:func:`decomposition.model.refine.refine`: variable
    #: projection, never worse per pixel, component set kept).  Off by default: it gains no
    #: fidelity over the solver's own off-grid polish (``streaklab bench tradeoff``); it does
    #: help ``off_grid=False`` output.  Count data are always polished with Poisson weights by
    #: the solver's compiled LM (:mod:`decomposition.stages.countpolish`; this adds a NumPy
    #: refit).  With the background family the refinement always runs, and a pixel whose
    #: components are not significant together against its offset alone is reported EMPTY
    #: (:func:`decomposition.stages.refit.clear_unlit`).
    refine: bool = False
    #: Count data (``noise="poisson"``) on the Gaussian PSF: after the labels, refit every pixel
    #: by its Poisson likelihood and take the count forward steps there (a direct restored, an
    #: sss, an echo, each kept by its deviance), the stages a measured response's counts take,
    #: over the Gaussian PSF of each pixel's width -- held where ``hold`` gives it, else its
    #: labelled one (:func:`decomposition.response.path.hand_over`; ``info["counts_handed_over"]``).
    #: Where the width is known it gains most at a few hundred photons per pixel and fewer
    #: (docs/history.md).  Off by default: with a width fitted per pixel it gains next to nothing,
    #: and ``decompose_image(spatial=True)``'s coupling starts worse from such answers at 100
    #: photons.  No effect on float data or with ``irf``.
    likelihood_counts: bool = False
    #: Add per-pixel standard errors ``<key>_stderr`` (shapes and units of the parameters, NaN
    #: where absent or not identifiable) from the Fisher information at the solution
    #: (:func:`decomposition.model.fisher.standard_errors`; count data: the Poisson Fisher
    #: information).  None: the same as ``refine``.
    stderr: bool | None = None
    #: Noise model of the samples: "gaussian" (estimated from the data, the paper's setting),
    #: "poisson" (photon counts, variance = expected value), "auto" ("poisson" for count data,
    #: :func:`decomposition.noise.is_count_data`, else "gaussian"); ``info["noise_model"]``
    #: says which was used.
    noise: str = "auto"
    #: Structured alternative starts for the pixels whose first answer is in doubt, each
    #: polished, the lowest penalised objective kept (:mod:`decomposition.stages.search`);
    #: ``info["search_wins"]`` counts which start each searched pixel kept.  None: on for the
    #: Gaussian PSF, off with a measured response (``irf=``), where it runs over the response's
    #: atoms at about 1.4 times the call's time for next to no fidelity beside the prune stage
    #: (docs/instrument-response.md).
    search: bool | None = None
    #: Forward step after the search: a Gaussian at a significant resolved residual bump, and
    #: at the peak of an sss that peaks late, kept where the penalised objective is lower
    #: (:mod:`decomposition.stages.grow`; ``info["grown"]``, ``info["swapped"]``); count data
    #: also get an echo after the threshold kept by its Poisson deviance
    #: (``info["grown_counts"]``).  With ``irf=`` it runs over the response's atoms on float data;
    #: count data take the response path's own echo steps instead (:mod:`decomposition.response.grow`).
    grow: bool = True
    #: Backward step after the search: a Gaussian just after the direct on a pixel with an sss
    #: dropped where the penalised objective is lower (:mod:`decomposition.stages.prune`;
    #: ``info["pruned"]``).
    prune: bool = True
    #: A second pass for the pixels flagged POOR_FIT at the end, or whose data term lies beyond
    #: what their noise allows, decomposed again differently started and taken where the
    #: penalised misfit is lower by ``ambiguity_chi2`` (:mod:`decomposition.stages.rescue`;
    #: ``info["rescue_tried"]``, ``info["rescued"]``).
    rescue: bool = True
    #: Weigh the samples of pixels whose noise follows the signal (photon noise on float data)
    #: by 1 / their fitted variance law floor + gain * model in the stages after the detection
    #: (:func:`decomposition.stages.candidates.signal_weights`; ``info["signal_weighted"]``).
    #: Count data are weighted by their Poisson law either way.
    signal_noise: bool = True
    #: The variance law of float data whose noise follows the signal: "auto", one law for every
    #: pixel (the medians of the pixels' floors and gains) where most pixels show such noise,
    #: else each such pixel's own; "pixel", each pixel's own; "detector", the one law whatever
    #: the pixels show (recorded in ``info["signal_noise_law_fit"]``).
    signal_noise_law: str = "auto"
    #: Where the call's noise is judged correlated (pink), score the penalised objectives with
    #: residuals whitened by the call's noise spectrum
    #: (:func:`decomposition.stages.candidates.correlated_noise_spectrum`;
    #: ``info["correlated_noise"]``); False: in each pixel's lagged noise level.
    whiten: bool = True
    #: Weight of the parameter-count term of the search's objective (1 = BIC).
    search_penalty: float = 1.0
    #: A data term above this many times its expected value puts a pixel in doubt (search) or
    #: lets the forward step try it.
    search_doubt_chi2: float = 1.5
    #: AMBIGUOUS when another start's objective (chi2 + k ln n, a BIC) is within this of the
    #: best's (10: the evidence for the best below "very strong") and its split differs by more
    #: than ``ambiguity_split``; also the rescue's margin.
    ambiguity_chi2: float = 10.0
    #: With a measured response (``irf``): a restored direct is taken where the fit without it
    #: lies within this many chi-square standard deviations (sqrt(2 n)) of the fit with it.
    ambiguity_sigma: float = 3.0
    #: Splits that differ by more than this (1 - fidelity between them) count as different for
    #: the AMBIGUOUS flag.
    ambiguity_split: float = 0.3

    def __post_init__(self):
        for name in ("off_grid", "multistart", "shared_sigma", "sss_after_direct", "sss_alone", "refine",
                     "likelihood_counts", "grow", "prune", "rescue", "signal_noise", "whiten"):
            _set(self, name, _flag(name, getattr(self, name)))
        for name in ("stderr", "search"):
            _set(self, name, _flag(name, getattr(self, name), allow_none=True))
        for name in ("max_components", "block_size"):
            _set(self, name, _number(name, getattr(self, name), lo=1, integer=True))
        _set(self, "max_reflections", _number("max_reflections", self.max_reflections, lo=0, integer=True))
        _set(self, "max_iter", _number("max_iter", self.max_iter, lo=1, integer=True, allow_none=True))
        _set(self, "background_chi2", _number("background_chi2", self.background_chi2, lo=0, allow_none=True))
        for name in ("n_lm", "n_polish"):
            _set(self, name, _number(name, getattr(self, name), lo=0, integer=True))
        for name in ("lm_tol", "sparsity", "noise_floor", "rel_threshold", "significance_chi2", "merge_tol_bins",
                     "spike_sigma",
                     "search_penalty", "search_doubt_chi2", "ambiguity_chi2", "ambiguity_sigma", "ambiguity_split"):
            _set(self, name, _number(name, getattr(self, name), lo=0))
        for name in ("eps_rel", "poor_fit"):
            _set(self, name, _number(name, getattr(self, name), lo=0, lo_open=True))
        _set(self, "bound_factor", _number("bound_factor", self.bound_factor, lo=1))
        _set(self, "noise", parse_noise_model(self.noise))
        if not (isinstance(self.signal_noise_law, str) and self.signal_noise_law in SIGNAL_NOISE_LAWS):
            raise OptionError(f"option signal_noise_law: must be one of {', '.join(SIGNAL_NOISE_LAWS)}, "
                              f"got {self.signal_noise_law!r}")

    def resolved(self, components, response: bool = False) -> "SolverOptions":
        """Defaults that depend on other settings filled in: ``max_iter``, ``stderr``, ``search``
        (off with a measured ``response``), and ``max_reflections`` = 0 without the
        inter-reflection family."""
        return dataclasses.replace(
            self, max_iter=self.max_components + 2 if self.max_iter is None else self.max_iter,
            stderr=self.refine if self.stderr is None else self.stderr,
            search=not response if self.search is None else self.search,
            max_reflections=self.max_reflections if "r" in components else 0)


_OPTION_CLASSES = (GridSpec, SolverOptions)


def option_names() -> tuple[str, ...]:
    """Names of every option of :class:`GridSpec` and :class:`SolverOptions`."""
    return tuple(f.name for cls in _OPTION_CLASSES for f in fields(cls))


def options_from_mapping(values: dict, *, strict: bool = True):
    """``{name: value}`` -> (GridSpec, SolverOptions, the names not theirs).

    With ``strict`` an unknown name raises :class:`OptionError` naming it; otherwise the
    unknown names are returned as a third item (a dict) for the caller to hand on (the
    GradBM baseline's own options).
    """
    known = {cls: {f.name for f in fields(cls)} for cls in _OPTION_CLASSES}
    rest = {k: v for k, v in values.items() if not any(k in names for names in known.values())}
    if strict and rest:
        raise OptionError(f"unknown option(s) {sorted(rest)}; known: {sorted(option_names())}")
    grid = GridSpec(**{k: v for k, v in values.items() if k in known[GridSpec]})
    solver = SolverOptions(**{k: v for k, v in values.items() if k in known[SolverOptions]})
    return grid, solver, rest


# --------------------------------------------------------------------------- vocabularies

_FAMILY_NAMES = {"d": "d", "direct": "d", "r": "r", "ir": "r", "interreflections": "r", "s": "s", "sss": "s",
                 "b": "b", "background": "b"}


def component_letters(components) -> tuple[str, ...]:
    """Component families -> their letters, in the order given, without duplicates.

    Accepts ``"d,r,s"``, ``"d+s"``, ``"d s"``, ``"ds"`` or a sequence (``("d", "s")``, long names
    ``"direct"``, ``"ir"``, ``"sss"``, ``"background"`` too).  Inter-reflections ("r") need the
    direct family ("d"): both are Gaussians, and an inter-reflection is a Gaussian after the
    direct one.  The background ("b", a constant offset per pixel) needs a component family
    besides it: an offset alone is no decomposition.
    """
    if isinstance(components, str):
        items = components.replace(",", " ").replace("+", " ").split()
        if len(items) == 1 and items[0].lower() not in _FAMILY_NAMES:
            items = list(items[0])
    else:
        items = list(components)
    out = []
    for c in items:
        key = str(c).strip().lower()
        if key not in _FAMILY_NAMES:
            raise ValueError(f"components: unknown component family {c!r} (choose from 'd', 'r', 's', 'b'); "
                             f"got {components!r}")
        out.append(_FAMILY_NAMES[key])
    if not out:
        raise ValueError(f"components must be a non-empty selection of 'd', 'r', 's', 'b'; got {components!r}")
    if "r" in out and "d" not in out:
        raise ValueError("components: inter-reflections ('r') need the direct family ('d') too")
    if set(out) == {"b"}:
        raise ValueError(f"components: the background ('b') needs a component family besides it "
                         f"('d' or 's'); got {components!r}")
    return tuple(dict.fromkeys(out))


def parse_components(components) -> frozenset:
    """``"d,r,s"`` / ``("d", "s")`` / ``"ds"`` / ``"d,s,b"`` -> frozenset of family letters (see
    :func:`component_letters`)."""
    return frozenset(component_letters(components))


#: per-pixel handling of NaN/inf samples: "raise" refuses the input; "omit" leaves the pixel
#: undecomposed (NaN parameters, flag NONFINITE; ``valid = False`` in a result store)
NAN_POLICIES = ("raise", "omit")
_NAN_ALIASES = {"raise": "raise", "error": "raise", "omit": "omit", "mark": "omit"}


def parse_nan_policy(policy: str) -> str:
    """A NaN policy -> its name in :data:`NAN_POLICIES` (the CLI's "error"/"mark" are accepted)."""
    try:
        return _NAN_ALIASES[str(policy)]
    except KeyError:
        raise ValueError(f"nan_policy must be one of {', '.join(NAN_POLICIES)}, got {policy!r}") from None



#: noise models of the samples: "gaussian" (the noise is estimated from the data, white), "poisson"
#: (the samples are photon counts: variance = expected count), "auto" (poisson for count data,
#: see :func:`decomposition.noise.is_count_data`, else gaussian)
NOISE_MODELS = ("auto", "gaussian", "poisson")
#: Variance laws of noise that follows the signal (``signal_noise_law``): one for every pixel of a
#: call, in the data's units (one detector's read noise and conversion gain), where most pixels
#: show such noise ("auto"); each pixel's own ("pixel"); the one law whatever the pixels show
#: ("detector").
SIGNAL_NOISE_LAWS = ("auto", "pixel", "detector")


def parse_noise_model(noise) -> str:
    """A noise model -> its name in :data:`NOISE_MODELS`."""
    if isinstance(noise, str) and noise in NOISE_MODELS:
        return noise
    raise OptionError(f"option noise: must be one of {', '.join(NOISE_MODELS)}, got {noise!r}")
