"""Pooled echoes and the spatial spike test of decompose_image (decomposition.image.pooled)."""
import numpy as np
import pytest

from core.model import render_components
from decomposition.api import DecompositionResult
from decomposition.flags import SPIKE
from decomposition.image.api import IMAGE_STAGES, ImageOptions, _ImageCall
from decomposition.image.pooled import aligned_neighbours, pooled_echoes, refit_spikes, spatial_spikes
from decomposition.stages.prepare import find_count_spikes

T, L, SIGMA = 2.0, 160, 4.0


def _image(ny, nx, echo_ratio, rng):
    """Directs on a tilted plane (delays 40-60 ps) and an echo 150 ps after each."""
    y, x = np.mgrid[0:ny, 0:nx].astype(float)
    d = 40.0 + 1.3 * x + 0.7 * y
    nan = np.full((ny, nx), np.nan)
    p = {"direct_delay_ps": d, "direct_amplitude": 1.0 + 0.2 * np.cos(x / 3), "direct_sigma_ps": np.full((ny, nx), SIGMA),
         "sss_delay_ps": nan, "sss_amplitude": nan, "sss_alpha_per_ps": nan, "sss_sigma_ps": nan,
         "ir_delay_ps": (d + 150.0)[..., None], "ir_amplitude": (echo_ratio * (1.0 + 0.2 * np.cos(x / 3)))[..., None],
         "ir_sigma_ps": np.full((ny, nx, 1), SIGMA)}
    return p, render_components(p, L, T)


def _direct_only_fit(profiles, p, comps):
    """A per-pixel result that found the direct only (the truth's direct)."""
    direct = comps["direct"]
    params = {k: (v if not k.startswith("ir_") else np.full(v.shape, np.nan)) for k, v in p.items()}
    R = np.zeros(profiles.shape[:2] + (1, L))
    return DecompositionResult(direct=direct, sss=np.zeros_like(direct), interreflections=R, params=params,
                               residual=profiles - direct, flags=np.zeros(profiles.shape[:2], np.uint16), info={})


def test_aligned_neighbours_line_up_on_the_direct():
    rng = np.random.default_rng(0)
    p, comps = _image(7, 7, 0.0, rng)
    direct = comps["direct"]
    for _, valid, (moved,) in aligned_neighbours((direct,), p["direct_delay_ps"], T, 3):
        # every valid neighbour's peak lands within one bin of the centre's
        peak_c = np.argmax(direct, axis=-1)
        peak_n = np.argmax(moved, axis=-1)
        assert np.all(np.abs(peak_n - peak_c)[valid] <= 1)
    with pytest.raises(ValueError, match="odd"):
        next(aligned_neighbours((direct,), p["direct_delay_ps"], T, 4))


def test_a_one_percent_echo_no_pixel_sees_is_found_pooled():
    """1 % echo at ~1.4 sigma of one pixel's matched filter, ~7 sigma over 5 x 5: found in nearly
    every pixel, at its delay, with an amplitude of the right size; an image without it gets none."""
    rng = np.random.default_rng(1)
    ny = nx = 12
    p, comps = _image(ny, nx, 0.01, rng)
    clean = comps["direct"] + comps["interreflections"].sum(axis=-2)
    # matched-filter SNR of one pixel's echo: a sqrt(sum g^2) / sigma
    sigma_noise = 0.01 * np.sqrt(np.sqrt(np.pi) * SIGMA / T) / 1.4
    noisy = clean + sigma_noise * rng.standard_normal(clean.shape)
    res = _direct_only_fit(noisy, p, comps)
    out, found, snr = pooled_echoes(noisy, res, T)
    interior = np.zeros((ny, nx), bool)
    interior[2:-2, 2:-2] = True
    assert found[interior].mean() >= 0.9
    assert np.nanmedian(snr[interior]) > 5.0
    got = out.params["ir_delay_ps"][found, 0]
    assert np.all(np.abs(got - p["ir_delay_ps"][found, 0]) <= 0.75 * SIGMA)
    amp = out.params["ir_amplitude"][found, 0] / p["ir_amplitude"][found, 0]
    assert 0.5 < np.median(amp) < 1.5
    assert out.info["pooled_echoes"] == found.sum()
    # the residual lost the echo it now reports
    np.testing.assert_allclose(out.residual, noisy - out.direct - out.interreflections.sum(axis=-2), atol=1e-12)
    # no echo in the data: none is added
    p0, comps0 = _image(ny, nx, 0.0, rng)
    noisy0 = comps0["direct"] + sigma_noise * rng.standard_normal(clean.shape)
    _, found0, _ = pooled_echoes(noisy0, _direct_only_fit(noisy0, p0, comps0), T)
    assert not found0.any()


def _count_image(rng, ny=8, nx=8, narrow=True):
    """Count profiles ~1000 counts at the peak, a narrow true component (sigma 0.6 ps: its time
    neighbours hold under 1 % of it) 60 ps after each direct."""
    y, x = np.mgrid[0:ny, 0:nx].astype(float)
    d = 40.0 + 1.0 * x + 0.5 * y
    nan = np.full((ny, nx), np.nan)
    p = {"direct_delay_ps": d, "direct_amplitude": np.full((ny, nx), 1000.0), "direct_sigma_ps": np.full((ny, nx), 4.0),
         "sss_delay_ps": nan, "sss_amplitude": nan, "sss_alpha_per_ps": nan, "sss_sigma_ps": nan,
         "ir_delay_ps": np.rint((d + 60.0) / T)[..., None] * T if narrow else np.full((ny, nx, 1), np.nan),
         "ir_amplitude": np.full((ny, nx, 1), 400.0), "ir_sigma_ps": np.full((ny, nx, 1), 0.6)}
    c = render_components(p, L, T)
    mean = c["direct"] + c["interreflections"].sum(axis=-2)
    return rng.poisson(mean), mean, p


def test_spatial_spike_test_flags_spikes_and_keeps_a_narrow_true_component():
    rng = np.random.default_rng(2)
    x, mean, p = _count_image(rng)
    ny, nx = x.shape[:2]
    hit = np.zeros(x.shape, bool)
    for pix in rng.choice(ny * nx, 12, replace=False):      # 10 x spikes on bins of 100-400 expected counts
        yy, xx = divmod(int(pix), nx)
        i = rng.choice(np.flatnonzero((mean[yy, xx] > 100) & (mean[yy, xx] < 400)))
        hit[yy, xx, i] = True
    x = np.where(hit, np.rint(10 * mean).astype(x.dtype), x)
    spikes, predicted = spatial_spikes(x, T)
    assert np.array_equal(spikes, hit)
    # the narrow true component: in every pixel, flagged in none
    narrow = np.rint((p["ir_delay_ps"][..., 0] - T) / T).astype(int)
    assert x[np.arange(ny)[:, None], np.arange(nx)[None, :], narrow].min() > 200
    # the per-pixel count test cannot tell these spikes from a 1 ps kernel (too few counts under them)
    per_pixel = find_count_spikes(x.reshape(-1, L), np.ones((ny * nx, L), bool), T, 1.0).reshape(x.shape)
    assert (per_pixel & hit).sum() < hit.sum() / 2


def test_no_spatial_spike_on_pure_poisson_draws():
    rng = np.random.default_rng(3)
    for narrow in (True, False):
        x, _, _ = _count_image(rng, 10, 10, narrow)
        spikes, _ = spatial_spikes(x, T)
        assert not spikes.any()


def test_spike_stage_refits_and_flags_the_pixel():
    """The stage before the coupling: the spike's pixel is refitted without it and flagged SPIKE;
    a pure Poisson image passes untouched."""
    names = [s.name for s in IMAGE_STAGES]
    assert names.index("per_pixel") < names.index("spatial_spikes") < names.index("neighbour_starts") \
        < names.index("joint_refinement") < names.index("pooled_echoes")
    rng = np.random.default_rng(4)
    x, mean, _ = _count_image(rng, 6, 6, narrow=False)
    i = int(np.flatnonzero(mean[2, 3] > 150)[-1])
    x[2, 3, i] = int(10 * mean[2, 3, i])
    call = _ImageCall(cube=x, time_bin_ps=T, method="convscd", options=ImageOptions(spatial=True), regions=None,
                      keywords={"noise": "poisson", "components": "d,r"})
    stages = {s.name: s for s in IMAGE_STAGES}
    stages["per_pixel"].run(call)
    stages["spatial_spikes"].run(call)
    flagged = (call.result.flags & SPIKE) > 0
    assert flagged[2, 3] and flagged.sum() == 1
    assert call.result.info["spatial_spikes"] == 1
    # refitted without the spike: no component at it
    ir = call.result.params["ir_delay_ps"][2, 3]
    assert not np.any(np.abs(ir - (T + i * T)) < 4.0)
    clean_x, _, _ = _count_image(np.random.default_rng(5), 6, 6, narrow=False)
    out, spikes, _ = refit_spikes(clean_x, call.result, T, "convscd", {"noise": "poisson"})
    assert not spikes.any() and out.info["spatial_spikes"] == 0


def test_the_compiled_aligned_sums_are_the_offset_by_offset_sums_bit_for_bit():
    from decomposition.kernels.pool import aligned_sums

    rng = np.random.default_rng(8)
    Y, X, L = 5, 6, 40
    resid, model = rng.normal(size=(Y, X, L)), rng.uniform(0, 5, (Y, X, L))
    near, amp = rng.random((Y, X, L)) < 0.1, rng.uniform(0, 1, (Y, X))
    delay = rng.uniform(20, 60, (Y, X))
    delay[1, 2] = np.nan                                     # no direct: neither neighbour nor centre
    got = aligned_sums(resid, model, near, amp, delay, 2.0, 5)
    want = [np.zeros((Y, X, L)), np.zeros((Y, X, L)), np.zeros((Y, X, L), bool), np.zeros((Y, X)),
            np.zeros((Y, X), np.int64)]
    for _, valid, (r, m, n, a) in aligned_neighbours((resid, model, near, amp), delay, 2.0, 5):
        want[0] += r
        want[1] += m
        want[2] |= n.astype(bool)
        want[3] += a
        want[4] += valid
    for g, w in zip(got, want):
        assert np.array_equal(g, w)
    assert got[4][1, 2] == 0 and got[4][0, 0] == 8           # a corner pixel: 9 offsets less the NaN one


def test_the_pooled_significance_is_read_in_the_members_own_noise():
    """The pool's matched filter is scaled by the sum of its members' noise variances (each pixel's
    own noise estimate), not by a noise estimate of the pooled residual's few hundred samples,
    whose scatter puts pure-noise neighbourhoods over the threshold far more often than the
    threshold says: 25 members, each with the same residual A g(t - 200 ps) and a noise sigma s,
    give a peak of exactly sqrt(25) A |g| / s at 200 ps, found in the centre."""
    ny = nx = 9
    nan = np.full((ny, nx), np.nan)
    p = {"direct_delay_ps": np.full((ny, nx), 50.0), "direct_amplitude": np.ones((ny, nx)),
         "direct_sigma_ps": np.full((ny, nx), SIGMA), "sss_delay_ps": nan, "sss_amplitude": nan,
         "sss_alpha_per_ps": nan, "sss_sigma_ps": nan, "ir_delay_ps": np.full((ny, nx, 1), np.nan),
         "ir_amplitude": np.full((ny, nx, 1), np.nan), "ir_sigma_ps": np.full((ny, nx, 1), np.nan)}
    comps = render_components(p, L, T)
    t = T + T * np.arange(L)
    a, s = 0.006, 0.01
    g = np.exp(-0.5 * ((t - 200.0) / SIGMA) ** 2)
    profiles = comps["direct"] + a * g
    res = _direct_only_fit(profiles, p, comps)
    res.info["noise_sigma"] = np.full((ny, nx), s)
    out, found, snr = pooled_echoes(profiles, res, T)
    taps = np.exp(-0.5 * (np.arange(-8, 9) * T / SIGMA) ** 2)
    np.testing.assert_allclose(snr[4, 4], 5.0 * a * np.sqrt(np.sum(taps ** 2)) / s, rtol=1e-9)
    assert found[4, 4] and abs(out.params["ir_delay_ps"][4, 4, 0] - 200.0) < 1e-9
