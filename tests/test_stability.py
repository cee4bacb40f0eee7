"""Stiff and extreme inputs: no NaN/inf/overflow, bounded iterations, monotone objective, flags."""
import numpy as np
import pytest

from decomposition import AT_BOUND, POOR_FIT, SATURATED, SPIKE, decompose
from streaklab.bench.stability import build_cases, run_case
from streaklab.cli import main

T = 2.0
CASES = build_cases(256, T, seed=0, quick=True)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_case_invariants_and_expectation(case):
    r = run_case(case, T, max_iter=8)      # warnings and floating-point errors raise inside
    assert r["finite"], "NaN/inf in an output"
    assert r["bounded"], "iteration count above max_iter"
    assert r["monotone"], "objective increased"
    assert r["expect_ok"], (r["name"], r["fidelity"], r["flags"])


def _case(name):
    return next(c for c in CASES if c.name == name)


def test_expected_outcomes_of_flagged_cases():
    sat = run_case(_case("uint16_saturated"), T)
    assert np.all(sat["flags"] & SATURATED)
    truth = _case("uint16_saturated").truth
    np.testing.assert_allclose(sat["result"].params["direct_amplitude"], truth["direct_amplitude"], rtol=0.02)
    spike = run_case(_case("spike"), T)
    assert np.all(spike["flags"] & SPIKE)
    ird = spike["result"].params["ir_delay_ps"]
    # exactly the true r2 (no reflection at the spike positions)
    assert np.isfinite(ird).sum(axis=1).tolist() == [1, 1]
    np.testing.assert_allclose(np.nanmax(ird, axis=1), _case("spike").truth["ir_delay_ps"][:, 0], atol=0.1)
    off = run_case(_case("background_offset"), T)
    assert np.all(off["flags"] & (POOR_FIT | AT_BOUND))
    rng = _case("dynamic_range_1e6")
    res = run_case(rng, T)["result"]
    assert np.isnan(res.params["ir_delay_ps"]).all()          # the 1e-6 reflection is below 5 %: absent, not tiny


def test_saturation_level_for_float_input_and_extreme_alpha_sigma_finite():
    c = _case("uint16_saturated")
    counts = c.profiles.astype(np.float64)
    res = decompose(counts, T, saturation_level=65535)
    assert np.all(res.flags & SATURATED)
    plain = decompose(counts, T)                      # float input: no saturation level unless given
    assert not np.any(plain.flags & SATURATED)


def test_bench_stability_command(capsys):
    assert main(["bench", "stability", "--quick", "--bins", "128"]) == 0
    out = capsys.readouterr().out
    assert "uint16_saturated" in out and "cases as expected" in out
    assert len([ln for ln in out.splitlines() if ln.startswith(("alpha_", "sigma_", "scale_"))]) >= 8


@pytest.mark.parametrize("noise", ["photon", "white"])
def test_option_variants_run_clean(noise):
    """Every documented switch, on noisy data, under warnings-as-errors and FP exceptions."""
    import warnings

    from decomposition.evaluation.synthetic import make_profiles

    data = make_profiles(20, 256, nsr=0.05, noise=noise, seed=1)
    variants = [dict(multistart=False), dict(shared_sigma=False), dict(sss_after_direct=False),
                dict(off_grid=False), dict(components="d,s"), dict(components="d,r"), dict(sss_alone=True)]
    for kw in variants:
        with warnings.catch_warnings(), np.errstate(over="raise", invalid="raise", divide="raise"):
            warnings.simplefilter("error")
            res = decompose(data.noisy, T, **kw)
        for v in (res.direct, res.sss, res.interreflections, res.residual):
            assert np.isfinite(v).all(), kw
        for k, v in res.params.items():
            assert not np.isinf(v).any(), (kw, k)


def test_a_psf_wider_than_the_kernel_grid_is_fitted_and_flagged_wide():
    from decomposition import WIDE_PSF

    case = next(c for c in build_cases(256, T, seed=0) if c.name == "sigma_10bins")   # 20 ps at 2 ps bins
    r = run_case(case, T)
    assert r["expect_ok"] and r["fidelity"] > 0.99
    assert np.all(r["flags"] & WIDE_PSF)
