"""``streaklab bench realism``: decomposition of realistic photon counts, beside the Poisson reference.

For each effect of real data (:data:`EFFECTS`: a tailed instrument response, an afterpulse, a
constant background, a weak 1 % late echo, a direct reflection truncated at the window's
start) and each photon level (expected signal photons per pixel, default 100, 300, 1,000 and
10,000), and for the echo target (``echo5sigma``: a 1 % echo 5 sigma above the noise at its
peak, the direct truncated at the window's start, at the one photon level where that holds,
:func:`five_sigma_photons`), the same synthetic scenes (:func:`decomposition.evaluation.synthetic.make_profiles` with the
effect, integer Poisson counts, bin-integrated) are decomposed by the variants

    ignored     ``decompose(counts, time_bin_ps, stderr=True)``: the defaults, the effect ignored
    modelled    ``decompose(counts, time_bin_ps, irf=<true response as the bins record it>,
                components="d,r,s,b" (",b" only where the effect is a background),
                noise="poisson", stderr=True)``: the response averaged over a bin
                (:func:`decomposition.evaluation.synthetic_effects.bin_averaged_response`), as the scenes
                are rendered and as a calibration capture on the same detector measures it
    reference   :func:`decomposition.evaluation.poisson_reference.poisson_reference_fit`: Poisson maximum
                likelihood with the true response and component set, started at the truth
    visible     the same on the components the counts leave visible (:func:`visible_truth`: an
                sss or inter-reflection whose chi2 over its samples in their Poisson variance
                is below 25 is left out), the yardstick of a method that finds every component
                the counts show and no other
    best        :func:`decomposition.evaluation.poisson_reference.best_of` the reference and the same fit
                started from the ``modelled`` answer (:func:`decomposition.evaluation.best_found.answer_start`: its values
                for the components of the true set it found, the truth's for the others),
                the lower deviance kept per pixel: the maximum likelihood as far as either
                start finds it.  Started at the truth, the reference stays in the optimum
                nearest it; where the decomposition's answer lies in a higher one, the
                reference is no longer the maximum-likelihood estimator, and a bias the
                decomposition shares with this yardstick is the estimator's, not a search's
                (needs ``modelled`` and ``reference``; ``best_start_decomposition`` is the
                fraction of pixels where the decomposition's start won)

A variant that raises (``modelled`` on a streaklab without the ``irf=`` option or the ``b``
family) is reported as an error on its rows, with the message, and no figures.

Scored per (effect, photon level, variant): the direct delay error (bias in ps and in PSF
widths, RMSE in ps) and the sss lifetime error tau = 1 / alpha (bias and RMSE relative to
the true lifetime), on the pixels where the variant reports the component; each RMSE over the
reference's; mean fidelity; the found rate of the weak echo (an inter-reflection within 2 PSF
widths of its true delay); and the calibration of the reported standard errors, median
|error| / stderr, against 0.674 (the half-normal median; printed with its own standard error,
:func:`median_z_stderr`); each RMSE ratio's target line carries its standard error over the
paired pixels (:func:`rmse_ratio_se`) and how many of them lie between it and the bar.
Beside each bias, the bias relative to the reference's on the same pixels (:func:`paired_bias`):
at 100 photons the maximum-likelihood lifetime itself is biased by a few per cent, which the
reference, started at the truth, shows.  Targets
(:data:`TARGETS`, checked for ``ignored`` and ``modelled`` at every level): bias within 1 %
(of the lifetime; of the PSF width for the delay) of zero, and for the lifetime also of the
reference's bias, RMSE within 1.1 x the reference's, median |error| / stderr within 10 % of
0.674, the echo found in >= 95 % of pixels where it is at least :data:`ECHO_SIGMA` sigma
above the noise (``echo_sigma``, its median significance, is in every echo row; a weaker
echo's found rate is printed, not judged: in the ``echo`` scenes, on an sss tail, the echo
is 0.25 sigma at 100 photons and 2.5 sigma at 10,000; 5 sigma would take 40,000).  The delay's bias beside the reference's is
printed, not checked: the reference's delay is no yardstick at few photons (started at the
truth, it stays in one of optima the counts do not tell apart: at 100 photons the
decomposition's direct lies later than the reference's by more than 0.3 ps in about 5 % of
the afterpulse pixels, most of them with a deviance as low or lower; while the reference left the sss onset free of the direct its
delay was biased by up to +0.65 ps).  Each check's line also names the reference's own
figure and verdict where the check judges a row alone, and the visible reference's on every
check; the header counts the unmet checks each of them misses too (:func:`target_records`).

Outputs in ``--out``: ``realism.csv`` (one row per effect, photon level and variant),
``summary.json`` (the settings, the rows and the targets as met / not met / not measured) and
``realism.png`` (per effect and photon level, each variant's lifetime RMSE over the reference's,
lifetime bias and direct-delay bias with their standard errors, the band each target allows
shaded; :func:`figure_series` gives its values).
"""
from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

from streaklab.cli import CommandError

from .arguments import choices, output_folder, positive_floats
from .scoring import target_entry, target_line
from .tables import write_csv

EFFECTS = ("tailed", "afterpulse", "background", "echo", "truncated", "echo5sigma")
#: effects with an echo to find
ECHO_EFFECTS = ("echo", "echo5sigma")
#: ``echo5sigma``: the echo's peak over the noise at its peak, and the direct's delay before the
#: first bin (ps; its peak outside the window, its falling edge inside)
ECHO_SIGMA = 5.0
ECHO_DIRECT_BEFORE_PS = 3.0
VARIANTS = ("ignored", "modelled", "reference", "visible", "best")
PHOTONS = (100.0, 300.0, 1000.0, 10000.0)
#: PSF core width of every scene, ps (the responses' Gaussian core)
SIGMA_PS = 4.0
HALF_NORMAL_MEDIAN = 0.6745
#: Targets, for the variants ``ignored`` and ``modelled``.
TARGETS = {"bias": 0.01, "rmse_over_reference": 1.1, "stderr_calibration": 0.10, "echo_found": 0.95,
           "min_photons": 100.0, "variants": ("ignored", "modelled")}


def effect_setup(effect: str, time_bin_ps: float) -> dict:
    """Generator options, scene kinds, the true response and whether a background is modelled.

    ``recorded_response`` is the true response averaged over a bin: what the scenes' bins
    record (they are bin-integrated) and what ``calibrate-irf`` would measure on that detector;
    the ``modelled`` variant decomposes with it.

    ``tailed``: 20 % of the response's area in a 30 ps diffusion tail; ``afterpulse``: 5 % of
    it 40 ps after the main peak; the other effects have the Gaussian response (sigma
    :data:`SIGMA_PS`) and add a background of 0.02 signal units (2-4 % of the direct's peak),
    a 1 % echo as the latest inter-reflection, or the direct 1-8 ps before the first bin;
    ``echo5sigma`` has a direct and a 1 % echo only (no sss, no background: the noise at the
    echo is its own Poisson noise), the direct :data:`ECHO_DIRECT_BEFORE_PS` before the first
    bin.
    """
    from core.irf_models import afterpulse_response, gaussian_response, tailed_response
    from decomposition.evaluation.synthetic_effects import bin_averaged_response

    tb = float(time_bin_ps)
    if effect == "tailed":
        irf = tailed_response(SIGMA_PS, 0.2, 30.0, time_step_ps=tb)
    elif effect == "afterpulse":
        irf = afterpulse_response(SIGMA_PS, 0.05, 40.0, time_step_ps=tb)
    elif effect in EFFECTS:
        irf = gaussian_response(SIGMA_PS, time_step_ps=tb)
    else:
        raise ValueError(f"unknown effect {effect!r}; choose from {', '.join(EFFECTS)}")
    options = {"response": irf}
    kinds = "d+s"
    if effect == "background":
        options["background"] = 0.02
    elif effect == "echo":
        options["echo_ratio"] = 0.01
        kinds = "d+s+r2"
    elif effect == "truncated":
        options["direct_before_window_ps"] = (1.0, 8.0)
    elif effect == "echo5sigma":
        options["echo_ratio"] = 0.01
        options["direct_before_window_ps"] = ECHO_DIRECT_BEFORE_PS
        kinds = "d+r2"
    return {"options": options, "kinds": kinds, "response": irf, "background": effect == "background",
            "recorded_response": bin_averaged_response(irf, tb)}


def five_sigma_photons(setup: dict, pixels: int, n_bins: int, time_bin_ps: float, seed: int) -> float:
    """Photons per pixel at which the echo of ``setup``'s scenes is :data:`ECHO_SIGMA` sigma.

    At N expected signal photons a pixel of in-window signal S (signal units, summed over
    the window) holds N x_i / S counts in bin i; the echo's peak e (at bin i) is ECHO_SIGMA
    sigma above the noise there when N e / S = ECHO_SIGMA sqrt(N x_i / S), i.e.
    N = ECHO_SIGMA^2 x_i S / e^2.  The scenes are those :func:`measure` counts (same seed,
    rendered bin-integrated without noise); the median over the pixels is returned (with a
    fixed truncation the pixels differ only by the bin phase of their echo).
    """
    from decomposition.evaluation.synthetic import make_profiles

    d = make_profiles(pixels, n_bins, seed=seed, kinds=setup["kinds"], time_bin_ps=time_bin_ps,
                      bin_integrated=True, **setup["options"])
    echo = np.asarray(d.components["interreflections"], np.float64)[:, -1]
    peak = np.argmax(echo, axis=1)
    rows = np.arange(echo.shape[0])
    e = echo[rows, peak]
    x = np.asarray(d.clean, np.float64)[rows, peak]
    total = np.asarray(d.clean, np.float64).sum(axis=1)
    ok = e > 0
    return float(np.median(ECHO_SIGMA ** 2 * x[ok] * total[ok] / e[ok] ** 2))


def _errors(truth: dict, est: dict, key: str):
    """Estimate minus truth on the pixels where both hold ``key`` (NaN elsewhere), (N,)."""
    t = np.asarray(truth[key], np.float64)
    e = np.asarray(est.get(key, np.full(t.shape, np.nan)), np.float64)
    return np.where(np.isfinite(t) & np.isfinite(e), e - t, np.nan)


def _rmse(x):
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


def _mean_se(x):
    x = x[np.isfinite(x)]
    if not x.size:
        return float("nan"), float("nan")
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else float("nan")


def _calibration(err, stderr):
    """Median |err| / stderr over the pixels where it is finite, and how many those are."""
    z = np.abs(err) / np.asarray(stderr, np.float64)
    z = z[np.isfinite(z)]
    return (float(np.median(z)) if z.size else float("nan")), int(z.size)


def echo_found(truth: dict, est: dict, echo: np.ndarray, n_sigma: float = 2.0) -> float:
    """Fraction of the echo pixels with an estimated inter-reflection of positive amplitude
    within ``n_sigma`` true PSF widths of the echo's true delay (the latest true one)."""
    t_ir = np.asarray(truth["ir_delay_ps"], np.float64)
    n_true = np.isfinite(t_ir).sum(axis=-1)
    last = np.take_along_axis(t_ir, np.maximum(n_true - 1, 0)[:, None], axis=1)[:, 0]
    sigma = np.asarray(truth["ir_sigma_ps"], np.float64)[:, 0]
    e_ir = np.asarray(est["ir_delay_ps"], np.float64)
    e_amp = np.asarray(est["ir_amplitude"], np.float64)
    near = np.abs(e_ir - last[:, None]) <= n_sigma * sigma[:, None]
    hit = np.any(near & (e_amp > 0), axis=1)
    return float(hit[echo].mean()) if echo.any() else float("nan")


def pixel_errors(truth: dict, est_params: dict):
    """Per-pixel errors of an estimate: the direct delay's (ps) and the relative lifetime's,
    (tau_e - tau) / tau with tau = 1 / alpha; each (N,), NaN where either side lacks it."""
    d_err = _errors(truth, est_params, "direct_delay_ps")
    alpha_t = np.asarray(truth["sss_alpha_per_ps"], np.float64)
    alpha_e = np.asarray(est_params.get("sss_alpha_per_ps", np.full(alpha_t.shape, np.nan)), np.float64)
    both = np.isfinite(alpha_t) & np.isfinite(alpha_e) & (alpha_e > 0)
    tau_rel = np.where(both, alpha_t / np.where(both, alpha_e, 1.0) - 1.0, np.nan)
    return d_err, tau_rel


def paired_bias(err, ref_err):
    """Mean of ``err - ref_err`` over the pixels where both are finite, and its standard error.

    The bias of a variant beside the reference's on the same pixels: the two share each
    pixel's noise, so the difference's error is much smaller than either bias's.
    """
    return _mean_se(np.asarray(err, np.float64) - np.asarray(ref_err, np.float64))


def rmse_ratio_se(err, ref_err) -> float:
    """Standard error of RMSE(err) / RMSE(ref_err) over the pixels where both are finite (the
    two share each pixel's counts), by the delta method on the paired squared errors a, b:
    Q = mean(a) / mean(b), var(Q) ~ (var(a) - 2 Q cov(a, b) + Q^2 var(b)) / (n mean(b)^2),
    se = sqrt(var(Q)) / (2 sqrt(Q)).  NaN with fewer than two such pixels."""
    e, r = np.asarray(err, np.float64), np.asarray(ref_err, np.float64)
    both = np.isfinite(e) & np.isfinite(r)
    a, b = np.square(e[both]), np.square(r[both])
    n = a.size
    if n < 2 or not b.mean() > 0:
        return float("nan")
    q = a.mean() / b.mean()
    c = np.cov(a, b, ddof=1)
    var_q = max(c[0, 0] - 2.0 * q * c[0, 1] + q * q * c[1, 1], 0.0) / (n * b.mean() ** 2)
    return float(math.sqrt(var_q) / (2.0 * math.sqrt(q))) if q > 0 else float("nan")


def median_z_stderr(n: int) -> float:
    """Standard error of the median of ``n`` half-normal |error| / stderr values,
    1 / (2 sqrt(n) f(m)) with f(m) = 2 phi(0.6745) = 0.636 the density at the median."""
    f = 2.0 * math.exp(-0.5 * HALF_NORMAL_MEDIAN ** 2) / math.sqrt(2.0 * math.pi)
    return 1.0 / (2.0 * math.sqrt(n) * f) if n > 0 else float("nan")


def score(data, est_params: dict, est_components, *, with_echo: bool) -> dict:
    """Figures of one estimate against the truth of ``data`` (see the module docstring)."""
    from decomposition.model.fidelity import fidelity

    truth = data.params
    d_err, tau_rel = pixel_errors(truth, est_params)
    alpha_t = np.asarray(truth["sss_alpha_per_ps"], np.float64)
    both = np.isfinite(tau_rel)
    has_d, has_s = np.isfinite(truth["direct_delay_ps"]), np.isfinite(alpha_t)
    bias_d, se_d = _mean_se(d_err)
    bias_t, se_t = _mean_se(tau_rel)
    out = {"direct_found": float(np.isfinite(d_err)[has_d].mean()) if has_d.any() else float("nan"),
           "direct_delay_bias_ps": bias_d, "direct_delay_bias_se_ps": se_d,
           "direct_delay_bias_sigma": bias_d / SIGMA_PS, "direct_delay_rmse_ps": _rmse(d_err),
           "sss_found": float(both[has_s].mean()) if has_s.any() else float("nan"),
           "lifetime_bias_rel": bias_t, "lifetime_bias_se_rel": se_t, "lifetime_rmse_rel": _rmse(tau_rel),
           "mean_fidelity": float(np.nanmean(fidelity(data.components, est_components))),
           "echo_found": echo_found(truth, est_params, data.echo) if with_echo else float("nan")}
    out["stderr_median_z_lifetime"] = out["stderr_median_z_delay"] = float("nan")
    out["stderr_median_z_lifetime_se"] = out["stderr_median_z_delay_se"] = float("nan")
    if "sss_alpha_per_ps_stderr" in est_params:
        for key, err, se in (("lifetime", _errors(truth, est_params, "sss_alpha_per_ps"),
                              est_params["sss_alpha_per_ps_stderr"]),
                             ("delay", d_err, est_params.get("direct_delay_ps_stderr", np.nan))):
            z, n = _calibration(err, se)
            out[f"stderr_median_z_{key}"], out[f"stderr_median_z_{key}_se"] = z, median_z_stderr(n)
    return out


def echo_sigma(photons: float, five_sigma: float) -> float:
    """The echo's median peak over the Poisson noise of its bin at ``photons`` per pixel, from
    the level ``five_sigma`` where it is :data:`ECHO_SIGMA` (:func:`five_sigma_photons`; the
    significance grows as the square root of the photon count).  NaN without an echo."""
    if not math.isfinite(five_sigma):
        return float("nan")
    return ECHO_SIGMA * math.sqrt(photons / five_sigma)


def echo_judged(row: dict) -> bool:
    """Whether a row's echo found rate is a target: an echo effect whose echo is at least
    :data:`ECHO_SIGMA` sigma above the noise (a weaker echo's rate is printed, not judged)."""
    return row["effect"] in ECHO_EFFECTS and row["echo_sigma"] >= ECHO_SIGMA


def visible_truth(data) -> dict:
    """The true parameters without the components the counts hide: an sss or inter-reflection
    stays where the sum over its samples of its expected counts squared over the expected
    counts there (Poisson: the variance is the mean) reaches the solver's significance_chi2
    (25; :func:`decomposition.evaluation.oracle.significant_truth` with per-sample noise)."""
    from decomposition.evaluation.oracle import significant_truth

    return significant_truth(data.params, data.components, np.sqrt(np.maximum(np.asarray(data.clean, np.float64), 0.0)))


def hides_nothing(data) -> bool:
    """Whether the counts leave every true component visible (:func:`visible_truth` equals the
    truth): the visible reference is then the reference itself, fitted once."""
    seen = visible_truth(data)
    return all(np.array_equal(seen[k], np.asarray(v, np.float64), equal_nan=True) for k, v in data.params.items())


def run_variant(variant: str, data, setup: dict, time_bin_ps: float, fits: dict | None = None):
    """One variant's estimate: (params, components).  ``best`` reads the ``reference`` and
    ``modelled`` entries of ``fits`` (variant -> (params, components))."""
    from decomposition import decompose
    from core.model import time_axis_ps
    from decomposition.evaluation.best_found import MATCH_WIDTHS, answer_start
    from decomposition.evaluation.poisson_reference import best_of, delay_window_ps, poisson_reference_fit

    background = data.background if setup["background"] else None
    if variant in ("reference", "visible"):
        truth = data.params if variant == "reference" else visible_truth(data)
        fit = poisson_reference_fit(data.noisy, truth, setup["response"], background=background,
                                    time_bin_ps=time_bin_ps, t0_ps=data.t0_ps)
        return fit.params, fit
    if variant == "best":
        fits = fits or {}
        if "reference" not in fits or "modelled" not in fits:
            raise ValueError("the best variant needs the reference and modelled variants (run before it)")
        window = delay_window_ps(setup["response"], time_axis_ps(np.shape(data.noisy)[-1], time_bin_ps, data.t0_ps))
        mod = fits["modelled"][0]
        start = answer_start(data.params, mod, delay_range_ps=window, match_ps=MATCH_WIDTHS * SIGMA_PS)
        if background is not None:
            est_bg = np.asarray(mod.get("background", np.full(np.shape(data.noisy)[:-1], np.nan)), np.float64)
            background = np.where(np.isfinite(est_bg) & (est_bg >= 0), est_bg, background)
        other = poisson_reference_fit(data.noisy, start, setup["response"], background=background,
                                      time_bin_ps=time_bin_ps, t0_ps=data.t0_ps)
        fit = best_of([fits["reference"][1], other])
        return fit.params, fit
    if variant == "ignored":
        res = decompose(data.noisy, time_bin_ps, t0_ps=data.t0_ps, stderr=True)
    elif variant == "modelled":
        comps = "d,r,s,b" if setup["background"] else "d,r,s"
        res = decompose(data.noisy, time_bin_ps, t0_ps=data.t0_ps, irf=setup["recorded_response"],
                        components=comps, noise="poisson", stderr=True)
    else:
        raise ValueError(f"unknown variant {variant!r}")
    return res.params, res


def measure(*, effects, photons, variants, pixels: int, n_bins: int, time_bin_ps: float, seed: int,
            progress=None) -> list[dict]:
    """Run the sweep; one row per (effect, photon level, variant), see :func:`score`.

    A variant that raises TypeError or ValueError gets ``status = "error: ..."`` and no figures.
    """
    from decomposition.evaluation.synthetic import make_profiles

    rows = []
    for effect in effects:
        setup = effect_setup(effect, time_bin_ps)
        seed_e = seed + 1000 * EFFECTS.index(effect)
        levels = photons
        n_5sigma = (five_sigma_photons(setup, pixels, n_bins, time_bin_ps, seed_e) if effect in ECHO_EFFECTS
                    else float("nan"))
        if effect == "echo5sigma":
            levels = [n_5sigma]
        for level in levels:
            data = make_profiles(pixels, n_bins, seed=seed_e, kinds=setup["kinds"],
                                 time_bin_ps=time_bin_ps, photons_per_pixel=float(level), **setup["options"])
            by_variant, errors, fits = {}, {}, {}
            for variant in variants:
                row = {"effect": effect, "photons_per_pixel": float(level), "variant": variant, "pixels": pixels,
                       "echo_sigma": echo_sigma(float(level), n_5sigma)}
                t_start = time.perf_counter()
                try:
                    if variant == "visible" and "reference" in fits and hides_nothing(data):
                        params, comps = fits["reference"]          # the same fit on the same set
                    else:
                        params, comps = run_variant(variant, data, setup, time_bin_ps, fits)
                    fits[variant] = (params, comps)
                except (TypeError, ValueError) as exc:
                    row["status"] = f"error: {type(exc).__name__}: {exc}"
                else:
                    row["status"] = "ok"
                    row.update(score(data, params, comps, with_echo=effect in ECHO_EFFECTS))
                    errors[variant] = pixel_errors(data.params, params)
                    if variant == "best":
                        row["best_start_decomposition"] = float(np.mean(comps.info["start"] == 1))
                row["seconds_per_pixel"] = (time.perf_counter() - t_start) / pixels
                by_variant[variant] = row
                rows.append(row)
            ref = by_variant.get("reference")
            for row in by_variant.values():
                for i, key in enumerate(("direct_delay_rmse_ps", "lifetime_rmse_rel")):
                    ratio = se = float("nan")
                    if ref is not None and ref["status"] == "ok" and row["status"] == "ok":
                        ratio = row[key] / ref[key] if ref[key] > 0 else float("nan")
                    if "reference" in errors and row["variant"] in errors:
                        se = rmse_ratio_se(errors[row["variant"]][i], errors["reference"][i])
                    name = key.replace("_ps", "").replace("_rel", "") + "_over_reference"
                    row[name], row[name + "_se"] = ratio, se
                # the bias beside the reference's on the same pixels (the estimator's own bias
                # at few photons is the reference's; a variant is judged against both)
                for i, (key, unit) in enumerate((("direct_delay", "ps"), ("lifetime", "rel"))):
                    diff = se = float("nan")
                    if "reference" in errors and row["variant"] in errors:
                        diff, se = paired_bias(errors[row["variant"]][i], errors["reference"][i])
                    row[f"{key}_bias_vs_reference_{unit}"] = diff
                    row[f"{key}_bias_vs_reference_se_{unit}"] = se
                row["direct_delay_bias_vs_reference_sigma"] = row["direct_delay_bias_vs_reference_ps"] / SIGMA_PS
                if progress:
                    progress(row)
    return rows


#: the checks that judge a row on its own (not against the reference), which the reference row
#: of the same effect and photon level is judged by too: where it misses one as well, the target
#: asks more than a maximum-likelihood fit with the true response and component set delivers
REFERENCE_JUDGED = ("lifetime bias", "direct delay bias", "lifetime stderr", "delay stderr")


def _ratio_text(row: dict, key: str) -> str:
    """'1.11 x reference' and, where the row has it, its standard error and how many of those
    lie between it and the bar ('1.11 +- 0.02 x reference, 0.5 se from the limit')."""
    ratio, se = row[key], row.get(key + "_se", float("nan"))
    if not (np.isfinite(se) and se > 1e-9 * abs(ratio)):      # none, or the reference itself
        return f"{ratio:.2f} x reference"
    return (f"{ratio:.2f} +- {se:.2f} x reference, "
            f"{abs(ratio - TARGETS['rmse_over_reference']) / se:.1f} se from the limit")


def _row_checks(row: dict) -> list[tuple[str, bool, str, str]]:
    """The target checks of one row: (name, met, measured value, the bar)."""
    with_sss = row["effect"] != "echo5sigma"          # its scenes have no sss
    checks = [
        ("lifetime bias", abs(row["lifetime_bias_rel"]) <= TARGETS["bias"],
         f"{row['lifetime_bias_rel']:+.2%} +- {row['lifetime_bias_se_rel']:.2%}", f"<= {TARGETS['bias']:.0%}"),
        ("direct delay bias", abs(row["direct_delay_bias_sigma"]) <= TARGETS["bias"],
         f"{row['direct_delay_bias_sigma']:+.3f} sigma", f"<= {TARGETS['bias']:g} sigma"),
        ("lifetime bias beside the reference's", abs(row["lifetime_bias_vs_reference_rel"]) <= TARGETS["bias"],
         f"{row['lifetime_bias_vs_reference_rel']:+.2%} +- {row['lifetime_bias_vs_reference_se_rel']:.2%}",
         f"<= {TARGETS['bias']:.0%}"),
        ("lifetime RMSE", row["lifetime_rmse_over_reference"] <= TARGETS["rmse_over_reference"],
         _ratio_text(row, "lifetime_rmse_over_reference"), f"<= {TARGETS['rmse_over_reference']:g}"),
        ("direct delay RMSE", row["direct_delay_rmse_over_reference"] <= TARGETS["rmse_over_reference"],
         _ratio_text(row, "direct_delay_rmse_over_reference"), f"<= {TARGETS['rmse_over_reference']:g}"),
    ]
    for key, label in (("stderr_median_z_lifetime", "lifetime stderr"), ("stderr_median_z_delay", "delay stderr")):
        z = row[key]
        checks.append((label, abs(z / HALF_NORMAL_MEDIAN - 1) <= TARGETS["stderr_calibration"],
                       f"median |e|/se {z:.3f} +- {row[key + '_se']:.3f}",
                       f"0.674 +- {TARGETS['stderr_calibration']:.0%}"))
    if not with_sss:
        checks = [c for c in checks if not c[0].startswith("lifetime")]
    if echo_judged(row):
        checks.append(("echo found", row["echo_found"] >= TARGETS["echo_found"],
                       f"{row['echo_found']:.1%} at {row['echo_sigma']:.1f} sigma", f">= {TARGETS['echo_found']:.0%}"))
    return checks


#: the yardsticks every judged check also names, where the rows hold them: the reference, and
#: the reference on the components the counts leave visible (``visible``, :func:`visible_truth`)
YARDSTICKS = (("reference", "the reference"), ("visible", "the visible reference"),
              ("best", "the best-found maximum likelihood"))


def check_targets(rows: list[dict]) -> list[tuple[str, bool | None, str]]:
    """:data:`TARGETS` on the rows: (text, True met / False not met / None not measured, detail),
    the ``text``, ``met`` and ``detail`` of :func:`target_records`."""
    return [(r["text"], r["met"], r["detail"]) for r in target_records(rows)]


def target_records(rows: list[dict]) -> list[dict]:
    """:data:`TARGETS` on the rows, one dict per check: ``text``, ``met`` (True / False / None:
    not measured), ``detail``, and per yardstick of :data:`YARDSTICKS` present at the same
    effect and photon level its own verdict on the same check (``reference_met``,
    ``visible_met``; None where absent or not comparable).

    The checks of :data:`REFERENCE_JUDGED` name the reference row's own figure and whether it
    meets the bar ("...; the reference: -2.42 % +- 0.44 %, not met"); every check names the
    visible reference's (its RMSE too is read over the full reference's): where the reference on
    the visible components misses a check as well, the check asks for what the counts hide."""
    yard = {name: {(r["effect"], r["photons_per_pixel"]): r for r in rows
                   if r["variant"] == name and r["status"] == "ok"} for name, _ in YARDSTICKS}
    out = []
    for row in rows:
        if row["variant"] not in TARGETS["variants"] or row["photons_per_pixel"] < TARGETS["min_photons"]:
            continue
        where = f"{row['variant']}, {row['effect']}, {row['photons_per_pixel']:g} photons"
        if row["status"] != "ok":
            out.append(_record(where, None, row["status"]))
            continue
        key = (row["effect"], row["photons_per_pixel"])
        checks = {name: ({} if key not in yard[name] else
                         {c: (ok, value) for c, ok, value, _ in _row_checks(yard[name][key])})
                  for name, _ in YARDSTICKS}
        for name, ok, value, bar in _row_checks(row):
            rec = _record(f"{where}: {name}", None, "not measured")
            if "nan" not in value:
                rec["met"], rec["detail"] = bool(ok), f"{value} ({bar})"
                for yname, label in YARDSTICKS:
                    judged = name in REFERENCE_JUDGED if yname == "reference" else True
                    if judged and name in checks[yname] and "nan" not in checks[yname][name][1]:
                        y_ok, y_value = checks[yname][name]
                        rec[f"{yname}_met"] = bool(y_ok)
                        rec["detail"] += f"; {label}: {y_value}, {'met' if y_ok else 'not met'}"
            out.append(rec)
    return out


def _record(text, met, detail) -> dict:
    """One target record, every yardstick's verdict not yet known (None)."""
    return {"text": text, "met": met, "detail": detail, **{f"{name}_met": None for name, _ in YARDSTICKS}}


#: the panels of ``realism.png``: (row key, its standard error's key or None, y label, the band
#: the target allows around its ideal (low, high), the ideal, the y range shown: a value beyond it
#: is drawn at its edge as an open triangle, with the value written beside it)
FIGURE_PANELS = (
    ("lifetime_rmse_over_reference", "lifetime_rmse_over_reference_se", "lifetime RMSE / reference's",
     (0.0, TARGETS["rmse_over_reference"]), 1.0, (0.5, 2.0)),
    ("lifetime_bias_rel", "lifetime_bias_se_rel", "lifetime bias (relative)", (-TARGETS["bias"], TARGETS["bias"]), 0.0,
     (-0.1, 0.1)),
    ("direct_delay_bias_sigma", None, "direct delay bias (PSF widths)", (-TARGETS["bias"], TARGETS["bias"]), 0.0,
     (-0.5, 0.5)),
)


def figure_series(rows: list[dict], key: str, se_key: str | None = None) -> dict:
    """The values of one panel of ``realism.png``: ``columns`` ("effect, N photons", in the rows'
    order) and per variant ``(value, se)`` arrays over them (NaN where a variant has no row, its
    row failed, or the figure is not finite; se NaN without ``se_key``)."""
    def column(r):
        return f"{r['effect']}, {r['photons_per_pixel']:,.0f} ph"

    cols = []
    for r in rows:
        if column(r) not in cols:
            cols.append(column(r))
    out = {"columns": cols, "variants": {}}
    for r in rows:
        v = out["variants"].setdefault(r["variant"], (np.full(len(cols), np.nan), np.full(len(cols), np.nan)))
        if r["status"] != "ok":
            continue
        j = cols.index(column(r))
        v[0][j] = r.get(key, np.nan)
        if se_key is not None:
            v[1][j] = r.get(se_key, np.nan)
    return out


#: vertical distance (points) between the value labels of off-scale points stacked at one edge of
#: one column, so that the labels of neighbouring variants never run into each other
OFF_SCALE_LABEL_STEP_PT = 8


def figure(rows: list[dict]):
    """``realism.png`` as a matplotlib Figure: per effect and photon level (columns), each variant's
    lifetime RMSE over the reference's, lifetime bias and direct-delay bias, with their standard
    errors where the rows hold them and the band each target allows shaded.  A value beyond a
    panel's range is an open triangle at its edge with the value beside it; the labels of several
    such values at one edge of one column are stacked, one line each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_cols = len({(r["effect"], r["photons_per_pixel"]) for r in rows})
    fig, axes = plt.subplots(len(FIGURE_PANELS), 1, figsize=(max(6.0, 1.0 + 0.55 * n_cols), 7.5), sharex=True)
    style = {"ignored": ("C3", "s"), "modelled": ("C0", "o"), "reference": ("0.2", "^"), "visible": ("C2", "v"),
             "best": ("C1", "D")}
    for ax, (key, se_key, label, band, ideal, view) in zip(axes, FIGURE_PANELS):
        ser = figure_series(rows, key, se_key)
        stacked = {}                     # (column, edge) -> labels already written there
        x = np.arange(len(ser["columns"]))
        names = list(ser["variants"])
        for k, name in enumerate(names):
            val, se = ser["variants"][name]
            color, marker = style.get(name, (None, "x"))
            off = (k - (len(names) - 1) / 2) * 0.12
            inside = (val >= view[0]) & (val <= view[1])
            ax.errorbar(x[inside] + off, val[inside], yerr=np.where(np.isfinite(se), se, 0.0)[inside], fmt=marker,
                        color=color, ms=4, lw=0.8, capsize=2, label=name)
            for j in np.flatnonzero(np.isfinite(val) & ~inside):
                edge, mk = (view[1], "^") if val[j] > view[1] else (view[0], "v")
                ax.plot(x[j] + off, edge, mk, mfc="none", color=color, ms=6, clip_on=False)
                n = stacked.get((j, mk), 0)
                stacked[(j, mk)] = n + 1
                dy = 6 + n * OFF_SCALE_LABEL_STEP_PT
                ax.annotate(f"{val[j]:.3g}", (x[j] + off, edge), fontsize=6, color=color, ha="center",
                            va="top" if mk == "^" else "bottom", xytext=(0, -dy if mk == "^" else dy),
                            textcoords="offset points")
        ax.axhspan(band[0], band[1], color="0.85", zorder=0)
        ax.axhline(ideal, color="0.5", lw=0.7)
        ax.set_ylim(*view)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    axes[-1].set_xticks(np.arange(len(ser["columns"])), ser["columns"], rotation=60, ha="right", fontsize=7)
    axes[0].legend(fontsize=7, ncol=4, loc="lower left")
    axes[0].set_title("photon counts with real-detector effects, beside the Poisson reference\n"
                      "(shaded: what each target allows)", fontsize=9)
    fig.tight_layout()
    return fig


def _plot(path, rows: list[dict]) -> None:
    import matplotlib.pyplot as plt

    fig = figure(rows)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def target_header(records: list[dict]) -> str:
    """The line above the target list: met / not met / not measured, and how many of the not met
    the reference misses itself, the visible reference, or (of the rest) the best-found maximum
    likelihood (records of :func:`target_records`)."""
    met = sum(r["met"] is True for r in records)
    unmet = [r for r in records if r["met"] is False]
    by_ref = sum(r["reference_met"] is False for r in unmet)
    by_vis = sum(r["visible_met"] is False and r["reference_met"] is not False for r in unmet)
    by_best = sum(r["best_met"] is False and r["reference_met"] is not False and r["visible_met"] is not False
                  for r in unmet)
    return (f"targets ({met} met, {len(unmet)} not met, {len(records) - met - len(unmet)} not measured; "
            f"{by_ref} of the not met are missed by the reference itself, {by_vis} more by the reference on "
            f"the visible components, {by_best} more by the best-found maximum likelihood):")


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="bench-output/realism", help="output folder (default bench-output/realism)")
    parser.add_argument("--pixels", type=int, default=200, help="profiles per effect and photon level (default 200)")
    parser.add_argument("--quick", action="store_true",
                        help="a few seconds: 6 pixels of 160 bins at 300 and 10,000 photons")
    parser.add_argument("--n-bins", type=int, default=256, help="time bins per profile (default 256)")
    parser.add_argument("--time-bin-ps", type=float, default=2.0, help="bin width in ps (default 2)")
    parser.add_argument("--photons", default=",".join(f"{p:g}" for p in PHOTONS),
                        help="expected signal photons per pixel, comma-separated (default 100,300,1000,10000)")
    parser.add_argument("--effects", default=",".join(EFFECTS),
                        help=f"effects, comma-separated (default all: {','.join(EFFECTS)})")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help=f"variants, comma-separated, run in the order {','.join(VARIANTS)} (default all; "
                             "best needs modelled and reference)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of scenes and counts (default 0)")


def _fmt(v, spec):
    digits = spec.strip("+").split(".")[0]
    width = int(digits) if digits else 0
    if not (isinstance(v, float) and math.isfinite(v)):
        return format("-", f">{width}s")
    if spec.endswith("%") and abs(v) >= 10:   # beyond 1000 %: keep the column
        return format((">" if v > 0 else "<-") + "999%", f">{width}s")
    return format(v, spec)


def run(args) -> int:
    effects = choices(args.effects, EFFECTS, "effects")
    chosen = choices(args.variants, VARIANTS, "variants")
    variants = [v for v in VARIANTS if v in chosen]      # best reads the fits run before it
    if "best" in variants and not {"modelled", "reference"} <= set(variants):
        raise CommandError("--variants: best needs modelled and reference as well")
    tb = float(args.time_bin_ps)
    if not (math.isfinite(tb) and tb > 0):
        raise CommandError(f"--time-bin-ps must be positive, got {args.time_bin_ps}")
    if args.quick:
        pixels, n_bins, photons = 6, 160, [300.0, 10000.0]
    else:
        pixels, n_bins, photons = int(args.pixels), int(args.n_bins), sorted(set(positive_floats(args.photons, "photons")))
    if pixels <= 0:
        raise CommandError(f"--pixels must be positive, got {pixels}")
    out = output_folder(args.out)
    if any(v != "reference" for v in variants):
        from decomposition.warmup import warm_up

        warm_up(time_bin_ps=tb, n_bins=n_bins, label="bench realism")

    def progress(r):
        print(f"  {r['effect']:10s} {r['photons_per_pixel']:>7g} photons {r['variant']:9s} "
              + (f"fidelity {r['mean_fidelity']:.3f}" if r["status"] == "ok" else r["status"]), file=sys.stderr)

    print(f"realism: {pixels} profiles x {len(photons)} photon levels x {len(effects)} effects (echo5sigma at its own "
          f"level), {n_bins} bins of "
          f"{tb:g} ps, variants {','.join(variants)}, seed {args.seed}", file=sys.stderr)
    try:
        rows = measure(effects=effects, photons=photons, variants=variants, pixels=pixels, n_bins=n_bins,
                       time_bin_ps=tb, seed=int(args.seed), progress=progress)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    targets = target_records(rows)
    csv_path, json_path, png_path = out / "realism.csv", out / "summary.json", out / "realism.png"
    write_csv(csv_path, rows)
    _plot(png_path, rows)
    summary = {"effects": effects, "variants": variants, "photons_per_pixel": photons, "pixels": pixels,
               "n_bins": n_bins, "time_bin_ps": tb, "sigma_ps": SIGMA_PS, "seed": int(args.seed),
               "quick": bool(args.quick), "targets": {k: list(v) if isinstance(v, tuple) else v
                                                      for k, v in TARGETS.items()},
               "target_checks": [target_entry(r) for r in targets], "rows": rows}
    json_path.write_text(json.dumps(summary, indent=2, default=float) + "\n")

    print("direct delay and sss lifetime errors beside the Poisson reference (true response and set, from the truth);")
    print("targets: bias within 1 % (of zero; the lifetime's also of the reference's on the same pixels, tau-ref), "
          "RMSE <= 1.1 x reference, median |e|/se within 10 % of 0.674, echo found >= 95 %")
    head = (f"  {'effect':10s} {'photons':>7s} {'variant':9s} {'d bias ps':>9s} {'d RMSE':>7s} {'x ref':>5s} "
            f"{'tau bias':>8s} {'+-':>6s} {'tau RMSE':>8s} {'x ref':>5s} {'fid':>6s} {'|e|/se tau':>10s} "
            f"{'|e|/se d':>8s} {'echo':>6s} {'d-ref ps':>8s} {'tau-ref':>8s} {'+-':>6s}")
    print(head)
    for r in rows:
        lead = f"  {r['effect']:10s} {r['photons_per_pixel']:>7g} {r['variant']:9s}"
        if r["status"] != "ok":
            print(f"{lead} {r['status']}")
            continue
        print(f"{lead} {_fmt(r['direct_delay_bias_ps'], '+9.3f')} {_fmt(r['direct_delay_rmse_ps'], '7.3f')} "
              f"{_fmt(r['direct_delay_rmse_over_reference'], '5.2f')} {_fmt(r['lifetime_bias_rel'], '+8.2%')} "
              f"{_fmt(r['lifetime_bias_se_rel'], '6.2%')} {_fmt(r['lifetime_rmse_rel'], '8.2%')} "
              f"{_fmt(r['lifetime_rmse_over_reference'], '5.2f')} {_fmt(r['mean_fidelity'], '6.3f')} "
              f"{_fmt(r['stderr_median_z_lifetime'], '10.3f')} {_fmt(r['stderr_median_z_delay'], '8.3f')} "
              f"{_fmt(r['echo_found'], '6.1%')} {_fmt(r['direct_delay_bias_vs_reference_ps'], '+8.3f')} "
              f"{_fmt(r['lifetime_bias_vs_reference_rel'], '+8.2%')} "
              f"{_fmt(r['lifetime_bias_vs_reference_se_rel'], '6.2%')}")
    weak = [r for r in rows if r["effect"] in ECHO_EFFECTS and r["status"] == "ok" and not echo_judged(r)]
    if weak:
        print(f"echo found below the target's {ECHO_SIGMA:g} sigma (printed, not judged): "
              + "; ".join(f"{r['variant']} {r['photons_per_pixel']:g} photons {_fmt(r['echo_found'], '.1%')} "
                          f"at {r['echo_sigma']:.1f} sigma" for r in weak))
    won = [r for r in rows if r["variant"] == "best" and r["status"] == "ok"]
    if won:
        print("best-found maximum likelihood: the start from the modelled answer won in "
              + "; ".join(f"{r['effect']} {r['photons_per_pixel']:g} {_fmt(r['best_start_decomposition'], '.0%')}"
                          for r in won) + " of the pixels (the rest: the reference's, from the truth)")
    for r in rows:
        if r["effect"] == "echo5sigma" and r["status"] == "ok":
            print(f"echo target ({r['variant']}): a 1 % echo {ECHO_SIGMA:g} sigma above the noise at "
                  f"{r['photons_per_pixel']:.0f} photons per pixel, the direct {ECHO_DIRECT_BEFORE_PS:g} ps "
                  f"before the first bin: found in {_fmt(r['echo_found'], '.1%')} of pixels "
                  f"(target >= {TARGETS['echo_found']:.0%})")
    if targets:
        print(target_header(targets))
        for r in targets:
            print(target_line(r))
    print(f"wrote {csv_path}, {json_path}, {png_path}")
    return 0
