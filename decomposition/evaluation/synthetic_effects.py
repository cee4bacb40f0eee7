"""Instrument and scene effects of synthetic profiles beyond the paper's model.

:func:`decomposition.evaluation.synthetic.make_profiles` renders the paper's model (Gaussian PSF, no
background, noise at an exact NSR) by default.  On request it adds what real streak-camera
and photon-counting data hold (the options of :class:`SyntheticEffects`):

    response               a non-Gaussian instrument response (:class:`core.irf.InstrumentResponse`,
                           e.g. :func:`core.irf_models.tailed_response` or
                           :func:`core.irf_models.afterpulse_response`); every direct and
                           inter-reflection is a shifted copy of it, the sss the response
                           convolved with its exponential (:func:`core.irf.render_shifted`,
                           :func:`core.irf.render_sss`), bin-averaged when the profiles are
    background             a constant level added to every bin (signal units; counts per bin
                           once counted)
    photons_per_pixel      true photon counting: integer counts drawn from Poisson laws whose
                           means are the bin-integrated expected counts, scaled so that the
                           expected signal photons of every pixel (background excluded) are
                           this number
    echo_ratio             the latest inter-reflection of every pixel at this fraction of the
                           direct's amplitude (a weak late echo)
    direct_before_window_ps the direct reflection placed this many ps (a value or a (lo, hi)
                           range drawn uniformly) before the first bin: only its falling edge
                           is in the window; the sss onset keeps its offset after it

Bin averages with a response: the mean of c(t - d) over a bin of width T is the response
convolved with a box of width T, sampled at the bin centre.  On the response's band-limited
interpolant that convolution is exact in the Fourier domain (each coefficient times
sinc(omega T / 2)), so :func:`bin_averaged_response` returns the box-filtered response and
the same two renderers give bin-averaged atoms of both kinds (the box commutes with the sss
exponential).  Atoms keep the peak normalisation of the unfiltered response, so an
amplitude is the peak height of the point-sampled component, as in
:func:`decomposition.evaluation.synthetic.render_bin_integrated`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

from core.irf import InstrumentResponse, render_shifted, render_sss
from core.model import time_axis_ps

__all__ = ["SyntheticEffects", "bin_averaged_response", "response_sigma_ps", "render_with_response",
           "place_direct_before_window", "set_echo", "count_photons", "MAX_PHOTONS_PER_PIXEL"]

#: Largest ``photons_per_pixel``: numpy's Poisson sampler refuses means above ~1e18 per bin.
MAX_PHOTONS_PER_PIXEL = 1e15


def _range(name, value):
    """``value`` as a (lo, hi) pair of finite non-negative floats, lo <= hi (or None)."""
    if value is None:
        return None
    v = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if v.size == 1:
        v = np.array([v[0], v[0]])
    if v.shape != (2,) or not np.all(np.isfinite(v)) or v[0] < 0 or v[0] > v[1]:
        raise ValueError(f"{name} must be a non-negative value or a (lo, hi) range with 0 <= lo <= hi, got {value!r}")
    return float(v[0]), float(v[1])


@dataclass(frozen=True)
class SyntheticEffects:
    """Validated effect options of :func:`decomposition.evaluation.synthetic.make_profiles`.

    The defaults add nothing: profiles are then exactly those of the paper's model.

    Attributes
    ----------
    response : InstrumentResponse, optional
        The instrument response every component is rendered with (None: each pixel's
        Gaussian PSF).  Its time step should be the bin width (the FFT path of
        :func:`core.irf.render_shifted`); any other step is evaluated directly, slower.
    background : float
        Constant level added to every bin, >= 0, in signal units (the units of the
        amplitudes, 0.5-1 for a direct reflection); in counts per bin once counted.
    photons_per_pixel : float, optional
        Expected signal photons of each pixel, summed over the window (background
        excluded), 0 < value <= :data:`MAX_PHOTONS_PER_PIXEL`.  None: no counting.
    echo_ratio : float, optional
        Amplitude of each pixel's latest inter-reflection over its direct's, 0 < value <= 1.
    direct_before_window_ps : (lo, hi), optional
        How far before the first bin (ps, >= 0) the direct delay is put; a single value is
        a fixed distance.
    """

    response: InstrumentResponse | None = None
    background: float = 0.0
    photons_per_pixel: float | None = None
    echo_ratio: float | None = None
    direct_before_window_ps: tuple[float, float] | None = None

    def __post_init__(self):
        if self.response is not None and not isinstance(self.response, InstrumentResponse):
            raise ValueError(f"response must be a core.irf.InstrumentResponse or None, "
                             f"got {type(self.response).__name__}")
        b = float(self.background)
        if not (math.isfinite(b) and b >= 0):
            raise ValueError(f"background must be finite and >= 0, got {self.background!r}")
        object.__setattr__(self, "background", b)
        if self.photons_per_pixel is not None:
            n = float(self.photons_per_pixel)
            if not (math.isfinite(n) and 0 < n <= MAX_PHOTONS_PER_PIXEL):
                raise ValueError(f"photons_per_pixel must be in (0, {MAX_PHOTONS_PER_PIXEL:g}], "
                                 f"got {self.photons_per_pixel!r}")
            object.__setattr__(self, "photons_per_pixel", n)
        if self.echo_ratio is not None:
            r = float(self.echo_ratio)
            if not (math.isfinite(r) and 0 < r <= 1):
                raise ValueError(f"echo_ratio must be in (0, 1], got {self.echo_ratio!r}")
            object.__setattr__(self, "echo_ratio", r)
        object.__setattr__(self, "direct_before_window_ps",
                           _range("direct_before_window_ps", self.direct_before_window_ps))

    @property
    def counting(self) -> bool:
        return self.photons_per_pixel is not None

    @property
    def any(self) -> bool:
        """Whether any effect is requested (False: the paper's model)."""
        return (self.response is not None or self.background > 0 or self.counting
                or self.echo_ratio is not None or self.direct_before_window_ps is not None)


# --------------------------------------------------------------------------- responses

def bin_averaged_response(irf: InstrumentResponse, width_ps: float) -> InstrumentResponse:
    """The response convolved with a unit-area box of width ``width_ps``: bin averages.

    ``(c * box_T)(t)`` is the mean of c over ``[t - T/2, t + T/2]``.  On the response's
    interpolant (the trigonometric polynomial of its padded window, see :mod:`core.irf`) the
    convolution multiplies each Fourier coefficient by ``sinc(omega_k T / 2)``; the result is
    sampled on the padded window (same step, same reference instant) and returned as a new
    response.  Exact for a response that has decayed to zero inside its window (the
    convolution then does not wrap), to the interpolant's own accuracy otherwise.

    Parameters
    ----------
    irf : InstrumentResponse
    width_ps : float
        Box width T in ps (> 0; the bin width), at most the response's padding on either side.

    Returns
    -------
    InstrumentResponse, unit area, samples (N,) on ``irf``'s padded window.
    """
    T = float(width_ps)
    if not (math.isfinite(T) and T > 0):
        raise ValueError(f"width_ps must be positive and finite, got {width_ps!r}")
    if T / 2 > irf.pad_samples * irf.time_step_ps:
        raise ValueError(f"a box of {T:g} ps is wider than the response's padding "
                         f"({irf.pad_samples * irf.time_step_ps:g} ps each side); record a longer response")
    w = irf.angular_frequencies()
    box = np.sinc(w * T / (2.0 * np.pi))          # numpy's sinc(x) = sin(pi x) / (pi x)
    samples = sp_fft.irfft(irf.spectrum * box, n=irf.n_padded)
    prov = dict(irf.provenance, bin_averaged_over_ps=T)
    return InstrumentResponse(samples, irf.time_step_ps, irf.window_start_ps, prov, None)


def response_sigma_ps(irf: InstrumentResponse) -> float:
    """Gaussian-equivalent core width of a response, ps: its FWHM / (2 sqrt(2 ln 2))."""
    return float(irf.fwhm_ps() / (2.0 * math.sqrt(2.0 * math.log(2.0))))


def render_with_response(params: dict, n_bins: int, time_bin_ps: float, t0_ps: float | None,
                         irf: InstrumentResponse, *, bin_integrated: bool = False) -> dict[str, np.ndarray]:
    """Components rendered with an instrument response instead of each pixel's Gaussian.

    Parameters
    ----------
    params : dict of ndarray
        Keys of :mod:`core.model`, shapes S and S + (R,); NaN = absent.  The ``*_sigma_ps``
        keys are not used.
    n_bins, time_bin_ps, t0_ps
        Time axis (see :func:`core.model.time_axis_ps`), ps.
    irf : InstrumentResponse
    bin_integrated : bool
        Each bin the mean of the continuous component over its width (else point samples).

    Returns
    -------
    dict with ``direct`` S + (L,), ``sss`` S + (L,), ``interreflections`` S + (R, L), peak-height
    amplitudes (an atom of amplitude a peaks at a when point-sampled).
    """
    t = time_axis_ps(n_bins, time_bin_ps, t0_ps)
    render_irf = bin_averaged_response(irf, time_bin_ps) if bin_integrated else irf
    scale = 1.0 / irf.peak_per_ps

    def shifted(delay, amp):
        delay, amp = np.asarray(delay, np.float64), np.asarray(amp, np.float64)
        on = np.isfinite(delay) & np.isfinite(amp)
        atoms = render_shifted(render_irf, t, np.where(on, delay, 0.0), normalization="area") * scale
        return np.where(on[..., None], np.where(on, amp, 0.0)[..., None] * atoms, 0.0)

    def sss(delay, amp, alpha):
        delay, amp, alpha = (np.asarray(v, np.float64) for v in (delay, amp, alpha))
        on = np.isfinite(delay) & np.isfinite(amp) & np.isfinite(alpha) & (alpha >= 0)
        atoms = render_sss(render_irf, t, np.where(on, delay, 0.0), np.where(on, alpha, 1.0),
                           normalization="area") * scale
        return np.where(on[..., None], np.where(on, amp, 0.0)[..., None] * atoms, 0.0)

    return {"direct": shifted(params["direct_delay_ps"], params["direct_amplitude"]),
            "sss": sss(params["sss_delay_ps"], params["sss_amplitude"], params["sss_alpha_per_ps"]),
            "interreflections": shifted(params["ir_delay_ps"], params["ir_amplitude"])}


# --------------------------------------------------------------------------- scene edits

def place_direct_before_window(params: dict, first_bin_ps: float, before_ps: tuple[float, float],
                               rng: np.random.Generator) -> dict:
    """Move every direct reflection before the window (in place); its sss follows it.

    The direct delay becomes ``first_bin_ps - u``, u uniform in ``before_ps`` (ps), drawn
    for every pixel; an sss keeps its onset after the direct.  Inter-reflections stay.

    Returns
    -------
    params (the same dict).
    """
    d = params["direct_delay_ps"]
    u = rng.uniform(before_ps[0], before_ps[1], d.shape) if before_ps[1] > before_ps[0] \
        else np.full(d.shape, before_ps[0])
    has = np.isfinite(d)
    onset = params["sss_delay_ps"] - d
    new = np.where(has, float(first_bin_ps) - u, np.nan)
    params["direct_delay_ps"] = new
    params["sss_delay_ps"] = np.where(has & np.isfinite(onset), new + onset, params["sss_delay_ps"])
    return params


def set_echo(params: dict, ratio: float) -> np.ndarray:
    """Set each pixel's latest inter-reflection to ``ratio`` x its direct amplitude (in place).

    Returns
    -------
    ndarray of bool, S: the pixels given an echo (a direct and at least one inter-reflection).

    Raises
    ------
    ValueError
        If no pixel has both a direct reflection and an inter-reflection.
    """
    ir = params["ir_delay_ps"]
    n_ir = np.isfinite(ir).sum(axis=-1)
    on = (n_ir > 0) & np.isfinite(params["direct_amplitude"])
    if not on.any():
        raise ValueError("echo_ratio needs kinds with a direct reflection and an inter-reflection "
                         "(e.g. kinds='d+s+r2')")
    last = np.maximum(n_ir - 1, 0)
    amp = params["ir_amplitude"]
    idx = np.nonzero(on)
    amp[idx + (last[on],)] = float(ratio) * params["direct_amplitude"][on]
    return on


def count_photons(clean, background: float, photons_per_pixel: float, rng: np.random.Generator):
    """Integer photon counts of profiles with a known expected signal.

    The expected counts of pixel p are ``lam_p (clean_p + background)``, with
    ``lam_p = photons_per_pixel / sum(clean_p)``; counts are drawn from independent Poisson
    laws with those means (negative values, the ringing of a sampled response far from
    it, ~1e-9 of the peak, clipped to zero first).

    Parameters
    ----------
    clean : ndarray, S + (L,)
        Expected signal (without background), signal units, non-negative.
    background : float
        Level added to every bin, signal units.
    photons_per_pixel : float
    rng : numpy.random.Generator

    Returns
    -------
    counts : ndarray of int64, S + (L,)
    lam : ndarray, S
        Counts per signal unit of each pixel.
    """
    clean = np.asarray(clean, np.float64)
    total = clean.sum(axis=-1)
    with np.errstate(divide="ignore", over="ignore"):
        lam = float(photons_per_pixel) / total
    # a far tail of ~1e-308 inside the window is no signal either: its scale would overflow
    if np.any(~(total > 0) | ~np.isfinite(lam)):
        raise ValueError("photons_per_pixel: a pixel has no signal inside the window "
                         "(e.g. a direct reflection placed too far before it)")
    mean = lam[..., None] * (np.maximum(clean, 0.0) + float(background))
    return rng.poisson(mean).astype(np.int64), lam
