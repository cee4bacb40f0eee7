"""Spike detection on photon-count data: tested against the counting statistics."""
import math

import numpy as np
import pytest
from scipy.stats import poisson

from decomposition.constants import SPIKE_FALSE_ALARM
from decomposition.flags import EMPTY, SPIKE
from decomposition.noise import anscombe, count_dispersion, is_count_data
from decomposition.options import GridSpec, OptionError, SolverOptions
from decomposition.noise import resolve_noise_model
from decomposition.stages.prepare import _count_threshold, prepare_samples, time_axis
from decomposition.evaluation.synthetic import make_profiles

N_PIXELS = 3000
L = 512


def _shapes(n, time_bin_ps=2.0, seed=1):
    """Smooth unit-peak profiles: a direct Gaussian plus an sss shape (Fig. 3 kind a)."""
    d = make_profiles(n, L, noise="none", kinds=("a",), seed=seed, time_bin_ps=time_bin_ps)
    return d.clean / d.clean.max(axis=1, keepdims=True)


@pytest.mark.parametrize("peak_counts", [1, 10, 100, 1000])
def test_pure_poisson_counts_get_no_spike_flags(peak_counts):
    """No spike can exist in a Poisson resample of smooth profiles: none is flagged, no pixel
    is emptied, at every count level (the test's false-alarm rate is 1e-6 per profile)."""
    rng = np.random.default_rng(100 + peak_counts)
    x = rng.poisson(_shapes(N_PIXELS) * peak_counts)
    ax, grid = time_axis(2.0), GridSpec()
    s = prepare_samples(x, ax, grid, noise="poisson")
    s0 = prepare_samples(x, ax, grid, noise="poisson", spike_sigma=0)
    assert s.noise_model == "poisson"
    assert not np.any(s.flags & SPIKE)
    assert np.array_equal(s.fit, s0.fit)
    assert np.array_equal(s.flags & EMPTY, s0.flags & EMPTY)
    # "auto" recognises the counts, as int64 and as whole-number floats
    assert resolve_noise_model("auto", x) == resolve_noise_model("auto", x.astype(float)) == "poisson"


def test_gaussian_rule_on_counts_is_what_the_count_test_replaces():
    """The white-noise rule, applied to photon-limited counts, flags most pixels (its noise
    estimate comes from the quiet part of the window): the reason count data get their own test."""
    rng = np.random.default_rng(5)
    x = rng.poisson(_shapes(500) * 10)
    s = prepare_samples(x, time_axis(2.0), GridSpec(), noise="gaussian")
    assert np.mean(s.flags & SPIKE > 0) > 0.5


def _ten_times_spike(level, time_bin_ps, n, seed):
    """Counts with the peak sample replaced by 10 x the local level (the smooth peak's level)."""
    shape = _shapes(n, time_bin_ps)
    rng = np.random.default_rng(seed)
    x = rng.poisson(shape * level)
    i = np.argmax(shape, axis=1)
    x[np.arange(n), i] = 10 * level
    return x, i, shape


def _miss_probability(level, shape, i, time_bin_ps, sigma_min_ps=1.0):
    """P(not flagged) per pixel from the Poisson law of the two neighbours: the spike is missed
    when the larger neighbour n has a(r c) - a(n) below the threshold (the other conditions hold
    with certainty here: c = 10 level is far above any neighbour that passes this one)."""
    r = math.exp(-0.5 * (time_bin_ps / sigma_min_ps) ** 2)
    z = _count_threshold(L)
    c = 10.0 * level
    # largest neighbour count that still lets the spike through
    n_max = np.arange(0, 20 * level)
    ok = anscombe(r * c) - anscombe(n_max) > z * math.sqrt(1 + r)
    n_star = n_max[ok].max()
    rows = np.arange(shape.shape[0])
    lam_l, lam_r = shape[rows, i - 1] * level, shape[rows, i + 1] * level
    return 1.0 - poisson.cdf(n_star, lam_l) * poisson.cdf(n_star, lam_r)


@pytest.mark.parametrize("level", [10, 100, 1000])
def test_ten_times_spike_is_flagged_at_fine_sampling(level):
    """At 1 ps bins (narrowest kernel 1 ps: its neighbours are >= 61 % of its peak) a single
    sample 10 x the local level is flagged; the miss rate matches the Poisson law of the
    neighbours (mean + 4 standard deviations)."""
    n = 1000
    x, i, shape = _ten_times_spike(level, 1.0, n, seed=level)
    s = prepare_samples(x, time_axis(1.0), GridSpec(), noise="poisson")
    flagged = ~s.fit[np.arange(n), i]
    assert np.all(s.flags[flagged] & SPIKE)
    p_miss = _miss_probability(level, shape, i, 1.0)
    bound = p_miss.sum() + 4.0 * math.sqrt(np.sum(p_miss * (1 - p_miss))) + 1.0
    assert (~flagged).sum() <= bound
    assert flagged.mean() > 0.9
    # the spike is the only sample removed
    assert (~s.fit).sum() == flagged.sum()


def test_ten_times_spike_at_coarse_sampling():
    """At 2 ps bins a 1-ps kernel leaves only 13.5 % of its peak on the neighbours, so a 10 x
    sample is told from a real component only where the counts resolve 10 % from 13.5 %:
    at 1000 counts every one is flagged."""
    n = 500
    x, i, _ = _ten_times_spike(1000, 2.0, n, seed=3)
    s = prepare_samples(x, time_axis(2.0), GridSpec(), noise="poisson")
    assert np.all(~s.fit[np.arange(n), i])
    assert np.all(s.flags & SPIKE)


def test_count_threshold_is_the_false_alarm_quantile():
    z = _count_threshold(L)
    tail = 0.5 * math.erfc(z / math.sqrt(2))
    assert tail * (L - 2) == pytest.approx(SPIKE_FALSE_ALARM, rel=1e-6)


def test_dispersion_absorbs_a_gain():
    """Counts recorded with a gain of 4 units per photon: the stabilised noise is ~2, not 1,
    and no sample of a spike-free profile is flagged."""
    rng = np.random.default_rng(11)
    x = 4 * rng.poisson(_shapes(1000) * 200)
    s = prepare_samples(x, time_axis(2.0), GridSpec(), noise="poisson")
    assert not np.any(s.flags & SPIKE)
    d = count_dispersion(x.astype(float), np.ones(x.shape, bool))
    assert np.median(d) == pytest.approx(2.0, rel=0.15)


def test_count_rule():
    assert is_count_data(np.array([[0, 3, 7]], np.uint16))
    assert is_count_data(np.array([[0.0, 3.0, 7.0]]))
    assert is_count_data(np.array([[0.0, np.nan, 7.0]]))
    assert not is_count_data(np.array([[0.0, 3.5, 7.0]]))
    assert not is_count_data(np.array([[-1.0, 3.0, 7.0]]))
    assert not is_count_data(np.zeros((2, 4)))
    assert resolve_noise_model("gaussian", np.array([[1, 2]])) == "gaussian"
    assert resolve_noise_model("auto", np.array([[1.5, 2]])) == "gaussian"
    with pytest.raises(OptionError, match="noise"):
        SolverOptions(noise="shot")


def test_white_noise_data_unchanged_by_auto():
    """Float data with fractional values: "auto" is the Gaussian path, bit for bit."""
    d = make_profiles(200, L, nsr=0.05, noise="white", kinds=("a", "b"), seed=4)
    ax, grid = time_axis(2.0), GridSpec()
    a = prepare_samples(d.noisy, ax, grid, noise="auto")
    g = prepare_samples(d.noisy, ax, grid, noise="gaussian")
    assert a.noise_model == "gaussian" and a.dispersion is None
    for name in ("profiles", "scale", "fit", "noise", "noise_eff", "flags"):
        assert np.array_equal(getattr(a, name), getattr(g, name))


@pytest.mark.parametrize("response", [None, "tailed"])
def test_bench_speed_writes_a_count_cube(tmp_path, response):
    """``bench speed --photons N`` (``--irf tailed`` too, whose sampled response rings below zero
    far from its peak): whole-number Poisson counts of N photons per pixel on average, which
    ``noise="auto"`` takes as counts."""
    from drivers.sim.scene import simulated_response
    from reconstruction.cubestore import open_cube
    from streaklab.bench.speed import write_synthetic_cube

    path = tmp_path / "cube.zarr"
    irf = None if response is None else simulated_response(response)
    write_synthetic_cube(path, (4, 50, 256), nsr=0.05, seed=1, chunks=(4, 50), photons=100.0, scenes="paper",
                         response=irf)
    x = np.asarray(open_cube(path).array[:])
    assert is_count_data(x)
    totals = x.reshape(-1, 256).sum(axis=1)
    # 200 pixel totals, each Poisson(100) over the window: their mean within 4 standard errors
    assert abs(totals.mean() - 100.0) < 4.0 * math.sqrt(100.0 / totals.size)
