"""Sweep calibration from an etalon pulse pair: a known bowed sweep recovered, stored, applied, and refused
where it does not belong."""
import numpy as np
import pytest
from scipy.special import erf

from acquisition.config import parse_config
from acquisition.runstore import create_run
from reconstruction.align import row_edges_ps
from reconstruction.build import reconstruct
from reconstruction.sweep import (SweepError, check_sweep, fit_sweep, load_sweep, pair_rows, save_sweep)
from streaklab.cli import main

N_ROWS, NX, DARK = 256, 4, 100.0
NOMINAL_PS = [10.0, 2.0]                               # the configured (linear) sweep, ps
NOMINAL = np.polynomial.polynomial.polyval(np.arange(N_ROWS), NOMINAL_PS)
U = np.arange(N_ROWS) / (N_ROWS - 1)
BOW_PS = 0.02 * np.ptp(NOMINAL)                        # 2 % of the window: a quadratic bow, 10.2 ps
TRUE = NOMINAL + BOW_PS * 4 * U * (1 - U)
ETALON_PS, ARRIVAL_PS = 20.0, 300.0
DELAYS_PS = np.linspace(-270.0, 250.0, 30)


def pulse_counts(centre_ps, sigma_ps, total, row_times_ps=TRUE):
    e = row_edges_ps(row_times_ps)
    return total * np.diff(0.5 * (1.0 + erf((e - np.asarray(centre_ps)[..., None]) / (np.sqrt(2) * sigma_ps))))


def etalon_profiles(delays_ps=DELAYS_PS):
    """Slit-summed counts of the pair at each delay: pulses at ARRIVAL - delay and ETALON later."""
    d = np.asarray(delays_ps)
    return pulse_counts(ARRIVAL_PS - d, 2.5, 20000.0) + pulse_counts(ARRIVAL_PS + ETALON_PS - d, 2.5, 16000.0)


def residual_ps(row_times_ps):
    """Largest time error over the rows, up to the one constant an etalon cannot fix, ps."""
    err = row_times_ps - TRUE
    return float(np.max(np.abs(err - err.mean())))


def test_two_percent_bow_leaves_under_a_tenth_of_a_ps():
    rng = np.random.default_rng(4)
    prof = rng.poisson(etalon_profiles() + 4 * 20.0).astype(np.float64) - 4 * 20.0
    pairs = pair_rows(prof, ETALON_PS / 2.0)
    assert np.isfinite(pairs).all(axis=1).sum() >= 25
    cal = fit_sweep(pairs, ETALON_PS, NOMINAL, delays_ps=DELAYS_PS, degree=4, time_range=1)
    assert residual_ps(NOMINAL) > 3.0                              # the nominal sweep is off by ~3.4 ps
    assert residual_ps(cal.row_times_ps) < 0.1
    assert abs(cal.row_times_ps.mean() - NOMINAL.mean()) < 1e-9    # the constant is the nominal's
    # separations alone constrain it less tightly, but still far better than the nominal sweep
    assert residual_ps(fit_sweep(pairs, ETALON_PS, NOMINAL, degree=4).row_times_ps) < 1.5


def test_pair_finder_marks_profiles_without_a_pair():
    prof = etalon_profiles(np.array([0.0, 0.0, 0.0]))
    prof[1] = pulse_counts(ARRIVAL_PS, 2.5, 20000.0)               # the second pulse missing
    prof[2] = 0.0                                                  # no light
    pairs = pair_rows(prof + 10.0, ETALON_PS / 2.0)
    assert np.isfinite(pairs[0]).all() and np.isnan(pairs[1:]).all()
    r = np.interp([ARRIVAL_PS, ARRIVAL_PS + ETALON_PS], TRUE, np.arange(N_ROWS))
    np.testing.assert_allclose(pairs[0], r, atol=0.02)
    with pytest.raises(SweepError, match="only 1 of 3 profiles hold a clear etalon pair"):
        fit_sweep(pairs, ETALON_PS, NOMINAL, degree=4)


def test_store_round_trip_and_time_range_check(tmp_path):
    cal = fit_sweep(pair_rows(etalon_profiles(), ETALON_PS / 2.0), ETALON_PS, NOMINAL,
                    delays_ps=DELAYS_PS, time_range="1 ns")
    for name in ("sweep.npz", "sweep.zarr"):
        save_sweep(tmp_path / name, cal)
        back = load_sweep(tmp_path / name)
        np.testing.assert_array_equal(back.row_times_ps, cal.row_times_ps)
        assert back.time_range == "1 ns" and back.coefficients_ps == cal.coefficients_ps
    check_sweep(back, time_range="1 ns", n_rows=N_ROWS, where="run.zarr")
    with pytest.raises(SweepError, match=r"^run.zarr: the sweep calibration was made for time range '1 ns', "
                                         r"the run uses 2;"):
        check_sweep(back, time_range=2, n_rows=N_ROWS, where="run.zarr")
    with pytest.raises(SweepError, match="has 256 rows, the run's images 512"):
        check_sweep(back, time_range="1 ns", n_rows=512, where="run.zarr")
    (tmp_path / "junk.npz").write_bytes(b"not an npz")
    with pytest.raises(SweepError, match="is not a sweep calibration .npz file"):
        load_sweep(tmp_path / "junk.npz")


def make_run(path, line_profiles, *, time_range=1, delay_ps=0.0):
    raw = {"scan": {"angles_deg": list(np.arange(len(line_profiles), dtype=float))},
           "camera": {"frames_per_line": 2, "time_range": time_range}, "dark": {"frames": 1},
           "sync": {"trigger_delay_ps": delay_ps}, "calibration": {"time_poly_ps": NOMINAL_PS, "time_bin_ps": 2.0}}
    run = create_run(path, parse_config(raw), image_shape=(NX, N_ROWS))
    run.write_dark(np.full((1, NX, N_ROWS), DARK, dtype=np.uint16))
    rng = np.random.default_rng(6)
    for i, prof in enumerate(line_profiles):
        f = rng.poisson(np.broadcast_to(prof / NX / 2, (2, NX, N_ROWS))) + DARK
        run.write_line(i, f.astype(np.uint16), angle_deg=float(i), timestamp=1.7e9 + i)
    return run


def test_calibrate_then_reconstruct_on_a_linear_axis(tmp_path, capsys):
    make_run(tmp_path / "etalon.zarr", etalon_profiles())
    argv = ["calibrate-sweep", str(tmp_path / "etalon.zarr"), "--etalon-ps", "20", "--out", str(tmp_path / "sweep.npz"),
            "--delays-ps", *map(str, DELAYS_PS)]
    assert main(argv) == 0
    assert "wrote the sweep calibration to" in capsys.readouterr().err
    assert residual_ps(load_sweep(tmp_path / "sweep.npz").row_times_ps) < 0.1
    # a scene of two pulses 300 ps apart, seen through the bowed sweep
    scene = pulse_counts(100.0, 4.0, 40000.0) + pulse_counts(400.0, 4.0, 40000.0)
    make_run(tmp_path / "scene.zarr", [scene, scene])

    def separation_ps(cube):
        t, prof = cube.time_axis_ps(), cube.array[0].sum(axis=0).astype(np.float64)
        c = [(prof * t)[m].sum() / prof[m].sum() for m in (np.abs(t - 100) < 25, np.abs(t - 400) < 25)]
        return c[1] - c[0]

    plain = reconstruct(tmp_path / "scene.zarr", tmp_path / "plain.zarr")
    fixed = reconstruct(tmp_path / "scene.zarr", tmp_path / "cube.zarr", sweep_path=tmp_path / "sweep.npz")
    assert abs(separation_ps(plain) - 300.0) > 1.0
    assert abs(separation_ps(fixed) - 300.0) < 0.1
    assert fixed.attrs["provenance"]["time_calibration_source"] == "sweep calibration"
    np.testing.assert_array_equal(load_sweep(tmp_path / "cube.zarr").row_times_ps,
                                  load_sweep(tmp_path / "sweep.npz").row_times_ps)


def test_calibration_from_another_time_range_is_refused(tmp_path, capsys):
    make_run(tmp_path / "etalon.zarr", etalon_profiles())
    assert main(["calibrate-sweep", str(tmp_path / "etalon.zarr"), "--etalon-ps", "20",
                 "--out", str(tmp_path / "sweep.zarr")]) == 0
    make_run(tmp_path / "scene.zarr", [etalon_profiles(np.array([0.0]))[0]], time_range=2)
    capsys.readouterr()
    assert main(["reconstruct", str(tmp_path / "scene.zarr"), "--out", str(tmp_path / "cube.zarr"),
                 "--sweep", str(tmp_path / "sweep.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "made for time range 1, the run uses 2" in err[0]
    assert not (tmp_path / "cube.zarr").exists()
    assert main(["calibrate-sweep", str(tmp_path / "etalon.zarr"), "--etalon-ps", "20", "--out",
                 str(tmp_path / "s2.npz"), "--delays-ps", "1", "2"]) == 2
    assert "--delays-ps gives 2 delays, the run has 30 lines" in capsys.readouterr().err


@pytest.mark.timeout(60)
def test_an_etalon_captured_from_the_simulated_lab_calibrates_a_two_percent_bow_to_a_tenth_of_a_ps(tmp_path, capsys):
    # end to end through the camera's wire protocol: the simulated camera's sweep is bowed by
    # 2 % of its window (drivers.sim.timebase), the scene an etalon pair stepping over the rows
    from acquisition.rig import run_capture, simulated_scene
    from drivers.sim.scene import VirtualScene
    from drivers.sim.timebase import TimeBase
    from test_capture import sim_config

    n_lines = 32
    cfg = sim_config(n_lines=n_lines, n_x=8, n_t=256, camera={"frames_per_line": 4},
                     simulation={"scene": "etalon", "etalon_ps": 20.0, "sweep_nonlinearity": 0.02})
    assert run_capture(cfg, tmp_path / "etalon.zarr", simulate=True).status == "complete"
    scene = simulated_scene(cfg)
    nominal = scene.row_times_ps(0.0, cfg["camera"]["time_range"])
    arrivals = VirtualScene.etalon_arrivals_ps(n_lines, float(np.polynomial.polynomial.polyval(
        scene.n_t - 1, scene.time_calibration)), 20.0)
    assert main(["calibrate-sweep", str(tmp_path / "etalon.zarr"), "--etalon-ps", "20",
                 "--out", str(tmp_path / "sweep.zarr"), "--delays-ps", *map(str, -arrivals)]) == 0
    true = TimeBase(sweep_nonlinearity=0.02).true_row_times_ps(nominal)

    def worst_ps(times):
        err = times - true
        return float(np.max(np.abs(err - err.mean())))

    assert worst_ps(nominal) > 5.0                                     # what the bow does uncalibrated
    assert worst_ps(load_sweep(tmp_path / "sweep.zarr").row_times_ps) < 0.1
