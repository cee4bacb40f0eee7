"""``decompose_image(cube, time_bin_ps, shared=..., spatial=...)``: one image, one problem.

The image path checks its own options (:class:`ImageOptions`) and runs the declared list
:data:`IMAGE_STAGES` in order, each a small function over an :class:`_ImageCall`; the per-pixel
solver (:func:`decomposition.api.decompose`) is one of its stages.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..api import DecompositionResult, Stage
from ..options import OptionError
from . import material as mt
from . import neighbours as nb
from . import spatial as sp
from .pooled import ECHO_WINDOW, SPIKE_WINDOW, pooled_echoes, refit_spikes
from .shared import SharedEstimate, apply_held_stderr, decompose_held, image_estimate

__all__ = ["decompose_image", "ImageOptions", "IMAGE_STAGES", "SHARED_NAMES", "halo_pixels"]

#: the parameters ``shared=`` may make global: the PSF width (or a response's time scale), the
#: direct's onset, the sss decay rate
SHARED_NAMES = ("psf", "delay", "alpha")


def parse_shared(shared) -> tuple:
    """``"psf,delay"`` / ``("psf", "delay")`` / None -> a sorted tuple of :data:`SHARED_NAMES`."""
    if shared is None or shared == "" or shared == ():
        return ()
    items = shared.split(",") if isinstance(shared, str) else list(shared)
    names = []
    for item in items:
        name = str(item).strip().lower()
        if name not in SHARED_NAMES:
            raise OptionError(f"shared: unknown parameter {item!r}; choose from {', '.join(SHARED_NAMES)}")
        if name not in names:
            names.append(name)
    return tuple(sorted(names, key=SHARED_NAMES.index))


@dataclass(frozen=True)
class ImageOptions:
    """What the image path adds to the per-pixel options."""

    #: The parameters estimated once from all pixels and held fixed in every pixel's fit
    #: (a subset of :data:`SHARED_NAMES`, e.g. ``("psf", "delay")``).
    shared: tuple = ()
    #: Couple neighbouring pixels over the image axes (y, x): their answers as starts, a joint
    #: refinement with an edge-preserving prior (:mod:`decomposition.image.spatial`).  Given as
    #: true / false, a :class:`~decomposition.image.spatial.SpatialOptions` or a mapping of its
    #: fields; held as true / false, its options in ``spatial_options``.
    spatial: bool = False
    #: With ``shared`` holding "psf": the width as a quadratic surface over (y, x) (a streak
    #: camera's slit), each pixel held at its value on it, instead of one number.
    psf_map: bool = False
    #: The coupling's options (None without it).
    spatial_options: sp.SpatialOptions | None = None

    def __post_init__(self):
        object.__setattr__(self, "shared", parse_shared(self.shared))
        if not isinstance(self.psf_map, (bool, np.bool_)):
            raise OptionError(f"psf_map: must be true or false, got {self.psf_map!r}")
        object.__setattr__(self, "psf_map", bool(self.psf_map))
        if self.psf_map and "psf" not in self.shared:
            raise OptionError("psf_map: give shared='psf' too (the map is the shared PSF's)")
        given = self.spatial_options if self.spatial_options is not None else self.spatial
        options = sp.spatial_options(given)
        object.__setattr__(self, "spatial", options is not None)
        object.__setattr__(self, "spatial_options", options)


@dataclass
class _ImageCall:
    cube: np.ndarray            # (Y, X, L)
    time_bin_ps: float
    method: str
    options: ImageOptions
    regions: np.ndarray | None  # (Y, X) integer labels, or None: the whole image one region
    keywords: dict              # the per-pixel decompose() keywords (t0_ps, components, ...)
    info: dict = field(default_factory=dict)
    result: DecompositionResult | None = None
    estimate: SharedEstimate | None = None   # given (a chunk of a cube) or estimated by the shared stage
    window: tuple | None = None              # ((y0, y1), (x0, x1)): where the cube lies in the estimate's image
    hold: dict = field(default_factory=dict)         # {HOLD_KEYS: (Y, X)}: the held values, NaN free
    hold_stderr: dict = field(default_factory=dict)  # their standard errors
    coupling: sp.Coupling | None = None     # the spatial stages' state


def _check(c: _ImageCall) -> None:
    if c.cube.ndim != 3:
        raise ValueError(f"decompose_image: expected an image of profiles (y, x, t), got shape {c.cube.shape}")
    if c.regions is not None:
        if "alpha" not in c.options.shared:
            raise OptionError("regions: give shared='alpha' too (the regions are where one sss decay rate holds)")
        regions = np.asarray(c.regions)
        if regions.shape != c.cube.shape[:2] or not np.issubdtype(regions.dtype, np.integer):
            raise OptionError(f"regions: expected an integer label image of shape {c.cube.shape[:2]}, "
                              f"got {regions.dtype} {regions.shape}")
        c.regions = regions


def _shared(c: _ImageCall) -> None:
    if not c.options.shared:
        return
    if c.estimate is None:
        c.estimate = image_estimate(c.cube, c.regions, c.time_bin_ps, c.method, c.options.shared,
                                    psf_map=c.options.psf_map, keywords=c.keywords)
    c.info["shared"] = c.estimate.record()


def _per_pixel(c: _ImageCall) -> None:
    if c.estimate is not None:
        hold, stderr = c.estimate.hold(c.regions, c.window)
        lead = c.cube.shape[:2]
        c.hold = {k: np.broadcast_to(np.asarray(v, np.float64), lead) for k, v in hold.items()}
        c.hold_stderr = {k: np.broadcast_to(np.asarray(v, np.float64), lead) for k, v in stderr.items()}
    c.result = decompose_held(c.cube, c.time_bin_ps, c.method, hold=c.hold, hold_stderr=c.hold_stderr, **c.keywords)
    c.result.info.update(c.info)


def _counts(c: _ImageCall) -> bool:
    """The per-pixel pass read the image as photon counts (its noise model, in its info)."""
    return c.result.info.get("noise_model") == "poisson"


def _spatial_spikes(c: _ImageCall) -> None:
    # before the coupling: the stages after it read the image with the spikes replaced
    if c.options.spatial and _counts(c):
        c.result, _, c.cube = refit_spikes(c.cube, c.result, c.time_bin_ps, c.method, c.keywords, hold=c.hold)


def _neighbour_starts(c: _ImageCall) -> None:
    if not c.options.spatial:
        return
    c.coupling = sp.prepare_coupling(c.cube, c.result, c.time_bin_ps, c.method, c.keywords, hold=c.hold)
    nb.neighbour_starts(c.coupling, c.options.spatial_options)


def _material_starts(c: _ImageCall) -> None:
    if c.options.spatial:
        mt.material_starts(c.coupling, c.options.spatial_options)


def _joint_refinement(c: _ImageCall) -> None:
    if not c.options.spatial:
        return
    sp.joint_refinement(c.coupling, c.options.spatial_options)
    c.result = apply_held_stderr(sp.coupled_result(c.coupling, c.result, c.options.spatial_options), c.hold,
                                 c.hold_stderr)
    c.result.info["spatial"]["halo_pixels"] = halo_pixels(c.options.spatial_options)


def _pooled_echoes(c: _ImageCall) -> None:
    if c.options.spatial:
        c.result, _, _ = pooled_echoes(c.cube, c.result, c.time_bin_ps, c.keywords.get("t0_ps"), counts=_counts(c),
                                       irf=c.coupling.irf)


def halo_pixels(spatial) -> int:
    """How far (pixels, along y and x) the answer at a pixel reaches into the image with
    ``spatial`` (as :func:`decompose_image` takes it; 0 without it): the spike test's
    neighbours, then the coupling's reach (:func:`~decomposition.image.spatial.coupling_reach`),
    then the pooled echoes' neighbourhood, one after the other.  A chunk read with this halo
    around it gives its interior exactly as the whole image does."""
    options = sp.spatial_options(spatial)
    if options is None:
        return 0
    return SPIKE_WINDOW // 2 + sp.coupling_reach(options) + ECHO_WINDOW // 2


#: The stages of :func:`decompose_image`, in order.
IMAGE_STAGES = (
    Stage("check", _check, "the image's shape, the regions"),
    Stage("shared", _shared, "estimate the shared parameters once from all pixels (image.shared)"),
    Stage("per_pixel", _per_pixel, "decompose every pixel, the shared parameters held fixed"),
    Stage("spatial_spikes", _spatial_spikes,
               "count data: single-sample spikes above the pixel's own neighbours in time and its spatial "
               "neighbours' aligned samples, replaced by the neighbours' value and the pixel refitted (SPIKE)"),
    Stage("neighbour_starts", _neighbour_starts, "refit the pixels in doubt from their neighbours' answers"),
    Stage("material_starts", _material_starts,
               "refit the pixels without an sss whose neighbours are one material with an sss, with its shape"),
    Stage("joint_refinement", _joint_refinement, "sweeps with an edge-preserving prior on the direct delays"),
    Stage("pooled_echoes", _pooled_echoes,
               "weak echoes found in 5 x 5 sums of the residuals aligned on the direct, added to each pixel "
               "with its own amplitude"),
)


def decompose_image(cube, time_bin_ps: float = 2.0, method: str = "convscd", *, shared=(), regions=None,
                    spatial: bool = False, psf_map: bool = False, estimate: SharedEstimate | None = None,
                    window=None, **keywords) -> DecompositionResult:
    """Decompose an image of time profiles as one problem.

    Parameters
    ----------
    cube : array_like (Y, X, L)
        Time profiles on an image; the last axis is time.
    time_bin_ps : float
        Bin width in ps.
    method : {"convscd", "gradbm"}
        The per-pixel solver.
    shared : str or sequence, optional
        Parameters estimated once from all pixels and held fixed in each pixel's fit
        (:data:`SHARED_NAMES`; ``"psf,delay,alpha"``).
    regions : ndarray (Y, X) of int, optional
        With ``shared`` holding "alpha": one sss decay rate per label >= 0 (default one for the
        image); pixels labelled < 0 keep their own.
    spatial : bool, SpatialOptions or mapping
        Couple neighbouring pixels (:mod:`decomposition.image.spatial`): True for the defaults
        of :class:`~decomposition.image.spatial.SpatialOptions`, or those options.
    psf_map : bool
        The shared PSF as a smooth quadratic map over (y, x) (:class:`ImageOptions`).
    estimate : SharedEstimate, optional
        Shared values estimated before (a chunk of a larger image: the estimate of the whole
        one, with ``window`` ((y0, y1), (x0, x1)) where the chunk lies and ``regions`` the
        chunk's labels); default: estimated from ``cube``.
    **keywords
        Everything :func:`decomposition.decompose` takes.

    Returns
    -------
    DecompositionResult
        Arrays shaped ``(Y, X, ...)``; every held parameter equals its shared value (its
        ``_stderr`` the shared one's); ``info["shared"]`` holds the shared estimates, their
        standard errors and how many pixels each pooled (:meth:`SharedEstimate.record`).
    """
    call = _ImageCall(cube=np.asarray(cube), time_bin_ps=time_bin_ps, method=method,
                      options=ImageOptions(shared=shared, spatial=spatial, psf_map=psf_map), regions=regions,
                      keywords=keywords, estimate=estimate, window=window)
    for stage in IMAGE_STAGES:
        stage.run(call)
    return call.result
