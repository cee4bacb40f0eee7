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
import math
import numbers
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

@dataclass(frozen=True)
class GridSpec:
    """Kernel-parameter grids.

    The *reference* grid (the paper's) is sigma 1-10 ps and alpha 0.01-0.05 /ps
    with 500 equi-spaced samples each; ``coarse_*`` are the numbers of grid
    values actually correlated against (a subsample of the reference range,
    log-spaced: Gaussian sigmas, sss sigmas x alphas); refined values live
    anywhere within ``bound_factor`` of the ranges (``off_grid=True``) or on the
    reference grid (``off_grid=False``).
    """

    sigma_range_ps: tuple = (1.0, 10.0)
    n_sigma: int = 500
    alpha_range_per_ps: tuple = (0.01, 0.05)
    n_alpha: int = 500
    coarse_sigma: int = 4
    coarse_alpha: int = 3
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


@dataclass(frozen=True)
class SolverOptions:
    """Everything but the grid that the ConvSCD path of ``decompose()`` reads.

    See :func:`decomposition.decompose` for the meaning of each field.  ``max_iter=None``
    means ``max_components + 2``; ``stderr=None`` means the same as ``refine``
    (:meth:`resolved` fills both in).
    """

    off_grid: bool = True
    max_components: int = 6
    max_reflections: int = 3
    max_iter: int | None = None
    n_lm: int = 4
    n_polish: int = 30
    lm_tol: float = 1e-2
    sparsity: float = 3.0
    eps_rel: float = 0.01
    noise_floor: float = 1e-3
    rel_threshold: float = 0.05
    significance_chi2: float = 25.0
    background_chi2: float | None = None
    merge_tol_bins: float = 1.0
    bound_factor: float = 4.0
    poor_fit: float = 3.0
    spike_sigma: float = 8.0
    multistart: bool = True
    shared_sigma: bool = True
    sss_after_direct: bool = True
    sss_alone: bool = False
    block_size: int = 512
    refine: bool = False
    stderr: bool | None = None
    noise: str = "auto"
    search: bool = True
    grow: bool = True
    prune: bool = True
    rescue: bool = True
    signal_noise: bool = True
    signal_noise_law: str = "auto"
    whiten: bool = True
    search_penalty: float = 1.0
    search_doubt_chi2: float = 1.5
    ambiguity_chi2: float = 10.0
    ambiguity_sigma: float = 3.0
    ambiguity_split: float = 0.3

    def __post_init__(self):
        for name in ("off_grid", "multistart", "shared_sigma", "sss_after_direct", "sss_alone", "refine", "search", "grow", "prune", "rescue",
                     "signal_noise", "whiten"):
            _set(self, name, _flag(name, getattr(self, name)))
        _set(self, "stderr", _flag("stderr", self.stderr, allow_none=True))
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

    def resolved(self, components) -> "SolverOptions":
        """Defaults that depend on other settings filled in: ``max_iter``, ``stderr``, and
        ``max_reflections`` = 0 without the inter-reflection family."""
        return dataclasses.replace(
            self, max_iter=self.max_components + 2 if self.max_iter is None else self.max_iter,
            stderr=self.refine if self.stderr is None else self.stderr,
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
