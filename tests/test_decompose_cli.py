"""``streaklab decompose`` over cube stores: equals the in-memory API, same store on any scheduler,
interrupted runs resume to the same store, bad input refused before any work."""
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from _cubes import TB, small_cube as _cube, worker_dies_at
from _runs import wait_for_done_chunks
from decomposition import decompose
from decomposition.store.resultstore import open_result_store
from decomposition.store.pipeline import PipelineError, decompose_to_store
from reconstruction.cubestore import create_cube, write_cube
from streaklab.cli import main

ROOT = Path(__file__).resolve().parents[1]




@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shared")
    write_cube(tmp / "cube.zarr", _cube(5, 7, seed=11), time_bin_ps=TB, chunks=(2, 3), units="photons",
               provenance={"producer": "test"})
    return tmp


@pytest.fixture
def cube_path(shared):
    return shared / "cube.zarr"


@pytest.fixture(scope="module")
def reference(shared):
    """An uninterrupted run with the cube's own (2, 3) chunks on the default threaded scheduler."""
    out = shared / "full.zarr"
    decompose_to_store(shared / "cube.zarr", out, progress=False)
    return out


@pytest.fixture(scope="module")
def reference_1x3(shared):
    """An uninterrupted run with (1, 3) chunks."""
    out = shared / "full-1x3.zarr"
    decompose_to_store(shared / "cube.zarr", out, chunks=(1, 3), progress=False)
    return out


def _assert_same_store(a, b):
    ga, gb = zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r")
    assert sorted(ga.array_keys()) == sorted(gb.array_keys())
    for k in ga.array_keys():
        x, y = ga[k][...], gb[k][...]
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k


def test_a_cube_of_one_detector_is_decomposed_with_one_noise_law(tmp_path, capsys):
    # shot noise (100 photons per unit) plus read noise, the same for every pixel: one detector
    rng = np.random.default_rng(3)
    clean = np.clip(_cube(2, 8, seed=5, nsr=0.0), 0.0, None)
    data = rng.poisson(clean * 100.0) / 100.0 + rng.normal(0.0, 0.005, clean.shape)
    write_cube(tmp_path / "one.zarr", data, time_bin_ps=TB, chunks=(2, 8), noise_law="detector")
    write_cube(tmp_path / "any.zarr", data, time_bin_ps=TB, chunks=(2, 8))
    summaries = [decompose_to_store(tmp_path / "one.zarr", tmp_path / "one-res.zarr", progress=False),
                 decompose_to_store(tmp_path / "any.zarr", tmp_path / "any-res.zarr", progress=False),
                 decompose_to_store(tmp_path / "one.zarr", tmp_path / "own-res.zarr", progress=False,
                                    options={"signal_noise_law": "pixel"})]
    assert [(s["noise_law"]["signal_noise_law"], s["noise_law"]["source"]) for s in summaries] == [
        ("detector", "cube"), ("auto", "default"), ("pixel", "option")]
    one, other, own = (open_result_store(tmp_path / f"{n}-res.zarr") for n in ("one", "any", "own"))
    # the cube's description chooses the law, recorded with the options; an explicit option wins
    assert one.attrs["options"]["signal_noise_law"] == "detector"
    assert "signal_noise_law" not in other.attrs["options"]
    assert own.attrs["options"]["signal_noise_law"] == "pixel"
    # and the store holds what the API gives with that law on the stored values (one chunk: bit
    # for bit)
    stored = zarr.open_group(str(tmp_path / "one.zarr"), mode="r")["cube"][...].reshape(16, -1)
    for law, store in (("detector", one), ("auto", other)):
        res = decompose(stored, time_bin_ps=TB, signal_noise_law=law, max_reflections=3)
        for k in ("direct_delay_ps", "sss_alpha_per_ps", "ir_delay_ps"):
            v = np.asarray(res.params[k], np.float64)
            np.testing.assert_array_equal(store.group[k][...].reshape(v.shape), v, err_msg=(law, k))
    # (each pixel's own law gives another store: the law matters here)
    assert not np.array_equal(one.group["direct_delay_ps"][...], own.group["direct_delay_ps"][...])
    # the command says so
    assert main(["decompose", str(tmp_path / "one.zarr"), "--out", str(tmp_path / "cli.zarr"), "--quiet"]) == 0
    assert "photon noise: one camera's variance law" in capsys.readouterr().out


def test_store_equals_the_in_memory_api_and_describes_itself(cube_path, tmp_path, capsys):
    out = tmp_path / "res.zarr"
    assert main(["decompose", str(cube_path), "--out", str(out), "--max-interreflections", "3", "--per-pixel"]) == 0
    captured = capsys.readouterr()
    assert "35 pixels" in captured.out and str(out) in captured.out
    assert "9/9 chunks" in captured.err  # progress on stderr
    store = open_result_store(out)
    assert store.done_mask().all() and store.group["valid"][...].all()
    cube = zarr.open_group(str(cube_path), mode="r")["cube"][...]
    # one chunk: bit for bit the API on the same pixels
    block = cube[2:4, 3:6].reshape(6, -1)
    res = decompose(block, time_bin_ps=TB, method="convscd")
    for k, v in res.params.items():
        v = np.asarray(v, np.float64)
        np.testing.assert_array_equal(store.group[k][2:4, 3:6].reshape(v.shape), v, err_msg=k)
    for name, v in (("direct", res.direct), ("sss", res.sss), ("residual", res.residual)):
        np.testing.assert_array_equal(store.group[name][2:4, 3:6].reshape(6, -1), np.asarray(v, np.float32))
    np.testing.assert_array_equal(store.group["ir"][2:4, 3:6].reshape(6, 3, -1),
                                  np.asarray(res.interreflections, np.float32))
    np.testing.assert_array_equal(store.group["flags"][2:4, 3:6].reshape(6), res.flags)
    np.testing.assert_array_equal(store.group["rms_residual"][2:4, 3:6].reshape(6),
                                  np.sqrt(np.mean(np.square(res.residual), -1)))
    # the whole cube: the API on all pixels in one batch.  The solver's batched linear algebra and
    # iteration stops depend slightly on which pixels share a batch, so: the same components and
    # flags, values equal to well within the solver's convergence (1e-6 relative)
    res = decompose(cube.reshape(35, -1), time_bin_ps=TB, method="convscd")
    for k, v in res.params.items():
        v = np.asarray(v, np.float64)
        got = store.group[k][...].reshape(v.shape)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(v), err_msg=k)
        np.testing.assert_allclose(got, v, rtol=1e-6, atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(store.group["flags"][...].reshape(35), res.flags)
    np.testing.assert_allclose(store.group["direct"][...].reshape(35, -1), res.direct, rtol=1e-6, atol=1e-6)
    a = store.attrs
    import streaklab
    assert a["method"] == "convscd" and a["components"] == ["d", "s", "r"]
    assert a["software_version"] == streaklab.__version__
    assert a["source"]["path"] == str(cube_path.resolve())
    assert a["source"]["attrs"]["provenance"] == {"producer": "test"}
    assert a["time_bin_ps"] == TB and a["t0_ps"] == TB and a["units"] == "photons"
    assert store.group["direct_amplitude"].attrs["units"] == "photons"


@pytest.mark.timeout(90)
def test_local_cluster_of_processes_gives_the_same_store(cube_path, reference, tmp_path):
    summary = decompose_to_store(cube_path, tmp_path / "cluster.zarr", workers=2, progress=False)
    assert summary["chunks_done"] == 9
    _assert_same_store(reference, tmp_path / "cluster.zarr")


def test_crash_then_resume_gives_the_uninterrupted_store(cube_path, reference, tmp_path, monkeypatch, capsys):
    revive = worker_dies_at(monkeypatch, 3)
    with pytest.raises(RuntimeError, match="worker died"):
        decompose_to_store(cube_path, tmp_path / "part.zarr", threads=1, progress=False)
    revive()
    part = open_result_store(tmp_path / "part.zarr")
    n_done = int(part.done_chunks().sum())
    assert 0 < n_done < 9
    # a plain rerun refuses to touch it; --resume computes only what is missing
    assert main(["decompose", str(cube_path), "--out", str(tmp_path / "part.zarr"), "--quiet"]) == 2
    assert "already exists" in capsys.readouterr().err
    summary = decompose_to_store(cube_path, tmp_path / "part.zarr", resume=True, progress=False)
    assert summary["chunks_done"] == 9 - n_done
    _assert_same_store(reference, tmp_path / "part.zarr")


# The subprocess runs the real command with each chunk's solve slowed down, so that it is reliably
# still running when it is killed; everything else is the production code path.
_SLOW = ("import sys, time; import decomposition.store.chunked as c; f = c.solve_block; "
         "c.solve_block = lambda *a, **k: (time.sleep(0.1), f(*a, **k))[1]; "
         "from streaklab.cli import main; sys.exit(main(sys.argv[1:]))")


def _start_slow(cube_path, out):
    return subprocess.Popen([sys.executable, "-c", _SLOW, "decompose", str(cube_path), "--out", str(out),
                             "--threads", "1", "--chunks", "1", "3", "--per-pixel"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.timeout(90)
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_killed_process_resumes_to_the_uninterrupted_store(cube_path, reference_1x3, tmp_path, sig, capsys):
    full, part = reference_1x3, tmp_path / "part.zarr"
    proc = _start_slow(cube_path, part)  # 15 chunks
    try:
        wait_for_done_chunks(part, 2, proc)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    if sig == signal.SIGINT:
        assert proc.returncode == 130 and "--resume" in err
    else:
        assert proc.returncode == -signal.SIGKILL
    n_done = int(open_result_store(part).done_chunks().sum())
    assert 2 <= n_done < 15
    assert main(["decompose", str(cube_path), "--out", str(part), "--chunks", "1", "3", "--resume", "--per-pixel"]) == 0
    assert f"{n_done}/15 chunks already done" in capsys.readouterr().err
    _assert_same_store(full, part)


def test_resume_with_other_settings_is_refused(cube_path, tmp_path):
    out = tmp_path / "res.zarr"
    decompose_to_store(cube_path, out, progress=False)
    with pytest.raises(PipelineError, match="different settings.*method"):
        decompose_to_store(cube_path, out, resume=True, method="gradbm", progress=False)
    with pytest.raises(PipelineError, match="different settings.*n_ir"):
        decompose_to_store(cube_path, out, resume=True, n_ir=4, progress=False)
    with pytest.raises(PipelineError, match="contradict"):
        decompose_to_store(cube_path, out, resume=True, overwrite=True, progress=False)


def test_bad_inputs_are_refused_before_any_work(tmp_path, cube_path, capsys):
    out = tmp_path / "res.zarr"

    def refused(argv, pattern):
        assert main(["decompose", *map(str, argv), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert pattern in err, err
        assert not out.exists()

    refused([tmp_path / "nothing.zarr"], "no such file")
    g = zarr.open_group(str(tmp_path / "run.zarr"), mode="w")
    g.attrs["streaklab_kind"] = "run"
    refused([tmp_path / "run.zarr"], "'run' store")
    g2 = zarr.open_group(str(tmp_path / "flat.zarr"), mode="w")
    g2.create_array("cube", shape=(4, 8), dtype="float32", dimension_names=["x", "t"]).attrs["time_bin_ps"] = 2.0
    refused([tmp_path / "flat.zarr"], "3-D")
    c = create_cube(tmp_path / "nobin.zarr", (2, 2, 64), time_bin_ps=2.0, t0_ps=2.0)
    del c.array.attrs["time_bin_ps"]
    refused([tmp_path / "nobin.zarr"], "time_bin_ps")
    nan = _cube(3, 3, seed=2)
    nan[1, 1, 10] = np.nan
    write_cube(tmp_path / "nan.zarr", nan, time_bin_ps=TB)
    refused([tmp_path / "nan.zarr", "--nan-policy", "error"], "1 of 9 pixels have NaN")
    np.save(tmp_path / "p.npy", _cube(1, 4, seed=3)[0])
    refused([tmp_path / "p.npy"], "--time-bin-ps")
    refused([cube_path, "--components", "d,x"], "--components")
    refused([cube_path, "--option", "novalue"], "KEY=VALUE")
    refused([cube_path, "--option", "no_such_option=1"], "the solver refuses these settings")
    refused([cube_path, "--option", 'sparsity="abc"'], "error: --option sparsity: must be a number, got 'abc'\n")
    refused([cube_path, "--components", "r,s"], "need the direct family")
    refused([cube_path, "--option", "sparsity=-1"], "--option sparsity: must be >= 0")
    refused([cube_path, "--option", "sparsity=abc"], "--option sparsity: must be a number, got 'abc'")
    refused([cube_path, "--option", "multistart=1"], "--option multistart: must be true or false")
    refused([cube_path, "--option", "noise=shot"], "--option noise: must be one of auto, gaussian, poisson")
    refused([cube_path, "--workers", "2", "--threads", "2"], "--threads")
    # the output path: never the input, never something else without --overwrite
    assert main(["decompose", str(cube_path), "--out", str(cube_path), "--overwrite", "--quiet"]) == 2
    assert "holds the input" in capsys.readouterr().err
    assert zarr.open_group(str(cube_path), mode="r")["cube"].shape == (5, 7, 128)
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["decompose", str(cube_path), "--out", str(out), "--quiet"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "keep me"
    assert main(["decompose", str(cube_path), "--out", str(out), "--overwrite", "--quiet"]) == 0
    assert open_result_store(out).done_mask().all()


def test_nan_pixels_are_marked_invalid_and_the_rest_decomposed(tmp_path):
    data = _cube(3, 4, seed=4)
    data[2, 1, 50] = np.nan
    write_cube(tmp_path / "nan.zarr", data, time_bin_ps=TB, chunks=(2, 2))
    summary = decompose_to_store(tmp_path / "nan.zarr", tmp_path / "res.zarr", progress=False)
    assert summary["invalid_pixels"] == 1
    store = open_result_store(tmp_path / "res.zarr")
    valid = store.group["valid"][...]
    assert not valid[2, 1] and valid.sum() == 11 and store.done_mask().all()
    assert np.isnan(store.group["direct_delay_ps"][2, 1]) and np.isfinite(store.group["rms_residual"][...]).sum() == 11
    assert store.attrs["nan_policy"] == "omit" and store.attrs["job"]["nan_policy"] == "omit"


def test_one_nan_policy_vocabulary_and_stores_with_the_older_words_resume(tmp_path):
    data = _cube(2, 2, nt=96, seed=6)
    data[0, 0, 5] = np.nan
    write_cube(tmp_path / "nan.zarr", data, time_bin_ps=TB, chunks=(1, 2))
    with pytest.raises(PipelineError, match="1 of 4 pixels have NaN"):
        decompose_to_store(tmp_path / "nan.zarr", tmp_path / "a.zarr", nan_policy="raise", progress=False)
    with pytest.raises(PipelineError, match="--nan-policy: nan_policy must be one of raise, omit"):
        decompose_to_store(tmp_path / "nan.zarr", tmp_path / "a.zarr", nan_policy="skip", progress=False)
    out = tmp_path / "b.zarr"
    decompose_to_store(tmp_path / "nan.zarr", out, nan_policy="mark", progress=False)   # the older word
    store = open_result_store(out, mode="r+")
    job = dict(store.attrs["job"])
    assert job["nan_policy"] == "omit"
    job["nan_policy"] = "mark"                       # as a store written before the one vocabulary
    store.group.attrs["job"] = job
    summary = decompose_to_store(tmp_path / "nan.zarr", out, resume=True, progress=False)
    assert summary["chunks_done"] == 0


def test_npy_input_without_components(tmp_path):
    profiles = _cube(1, 6, seed=5)[0]  # (n, t)
    np.save(tmp_path / "p.npy", profiles)
    assert main(["decompose", str(tmp_path / "p.npy"), "--time-bin-ps", "2", "--out", str(tmp_path / "r.zarr"),
                 "--no-components", "--quiet"]) == 0
    store = open_result_store(tmp_path / "r.zarr")
    assert store.shape == (1, 6, 128) and "direct" not in store.group
    res = decompose(profiles, time_bin_ps=TB)
    np.testing.assert_array_equal(store.group["direct_delay_ps"][0], res.params["direct_delay_ps"])


def test_the_background_family_is_stored_in_signal_units(tmp_path):
    # components d,s,b: the fitted offset is a map of the store, in the cube's units
    from decomposition.evaluation.synthetic import make_profiles

    d = make_profiles(12, 256, seed=7, kinds=["d+s"], time_bin_ps=TB, ranges="paper", photons_per_pixel=1000.0,
                      background=0.05)
    np.save(tmp_path / "c.npy", d.noisy.reshape(2, 6, 256).astype(np.float32))
    assert main(["decompose", str(tmp_path / "c.npy"), "--time-bin-ps", str(TB), "--out", str(tmp_path / "r.zarr"),
                 "--components", "d,s,b", "--no-components", "--quiet", "--per-pixel"]) == 0
    store = open_result_store(tmp_path / "r.zarr")
    b = store.group["background"]
    assert b.attrs["units"] == store.group.attrs["units"] and "offset" in b.attrs["long_name"]
    res = decompose(d.noisy.astype(np.float32), time_bin_ps=TB, components="d,s,b")
    np.testing.assert_array_equal(np.asarray(b).ravel(), res.params["background"])
    np.testing.assert_allclose(np.asarray(b).ravel(), d.background, rtol=0.3)


def test_a_cube_of_mostly_poor_fits_gets_a_note_naming_the_usual_causes(tmp_path, capsys):
    from decomposition.evaluation.synthetic import make_profiles

    d = make_profiles(16, 256, nsr=0.01, noise="white", seed=7, kinds=["d+s"], time_bin_ps=TB, ranges="paper",
                      background=0.05, bin_integrated=True)
    np.save(tmp_path / "c.npy", d.noisy.reshape(2, 8, 256).astype(np.float32))
    args = ["decompose", str(tmp_path / "c.npy"), "--time-bin-ps", str(TB), "--no-components", "--quiet",
            "--per-pixel"]
    assert main(args + ["--out", str(tmp_path / "r1.zarr")]) == 0
    out = capsys.readouterr().out
    assert "16 of 16 pixels are flagged POOR_FIT" in out and "--components d,s,r,b" in out
    # the offset modelled: good fits, no note
    assert main(args + ["--out", str(tmp_path / "r2.zarr"), "--components", "d,s,r,b"]) == 0
    assert "POOR_FIT" not in capsys.readouterr().out


def _slow_solver_in_this_worker():
    """Run inside a dask worker: slow its chunk solve down so that it can be killed mid-run."""
    import time as _time

    import decomposition.store.chunked as c

    real = c.solve_block
    c.solve_block = lambda *a, **k: (_time.sleep(0.3), real(*a, **k))[1]
    return os.getpid()


@pytest.mark.timeout(120)
def test_a_worker_killed_mid_run_loses_and_duplicates_nothing(cube_path, reference, tmp_path):
    import threading

    from distributed import Client, LocalCluster

    out = tmp_path / "res.zarr"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster, Client(cluster) as client:
        pids = client.run(_slow_solver_in_this_worker)
        result = {}
        runner = threading.Thread(target=lambda: result.update(decompose_to_store(
            cube_path, out, scheduler=cluster.scheduler_address, progress=False)))
        runner.start()
        wait_for_done_chunks(out, 2)
        done_at_kill = int(open_result_store(out).done_chunks().sum())
        os.kill(next(iter(pids.values())), signal.SIGKILL)  # one worker dies mid-run
        runner.join(90)
        assert not runner.is_alive()
    assert 2 <= done_at_kill < 9 and result["chunks_done"] == 9
    _assert_same_store(reference, out)


def test_resume_onto_a_rewritten_cube_is_refused(tmp_path):
    write_cube(tmp_path / "cube.zarr", _cube(2, 3, seed=1), time_bin_ps=TB, provenance={"created_utc": "first"})
    decompose_to_store(tmp_path / "cube.zarr", tmp_path / "res.zarr", progress=False)
    write_cube(tmp_path / "cube.zarr", _cube(2, 3, seed=2), time_bin_ps=TB, provenance={"created_utc": "second"},
               overwrite=True)
    with pytest.raises(PipelineError, match="different settings.*source_attrs_sha256"):
        decompose_to_store(tmp_path / "cube.zarr", tmp_path / "res.zarr", resume=True, progress=False)


def test_sizes_declared_by_a_small_crafted_cube_are_refused_before_any_allocation(tmp_path, capsys):
    def crafted(name, shape, chunks):
        g = zarr.open_group(str(tmp_path / name), mode="w")
        g.attrs["streaklab_kind"] = "cube"
        g.create_array("cube", shape=shape, chunks=chunks, dtype="float32", fill_value=0.0,
                       dimension_names=["y", "x", "t"]).attrs.update({"time_bin_ps": 2.0, "t0_ps": 2.0})
        return tmp_path / name

    out = tmp_path / "res.zarr"
    # a few hundred bytes of metadata: 1.25e9 bins would make even the option probe ask for 9.31 GiB
    long_t = crafted("long.zarr", (1, 1, 1_250_000_000), (1, 1, 1_250_000_000))
    assert main(["decompose", str(long_t), "--out", str(out), "--quiet"]) == 2
    assert capsys.readouterr().err == (f"streaklab decompose: error: {long_t}: t: 1250000000 time bins exceeds the "
                                       f"limit of 65536 time bins\n")
    wide = crafted("wide.zarr", (4096, 4096, 512), (4096, 4096, 512))
    assert main(["decompose", str(wide), "--out", str(out), "--quiet"]) == 2
    # 4096 x 4096 pixels of 512 bins: 16.8e6 x 512 x 64 bytes
    assert capsys.readouterr().err == (f"streaklab decompose: error: {wide}: --chunks: needs 512.00 GiB to solve a "
                                       f"4096 x 4096 pixel chunk of 512 bins (limits.MAX_CHUNK_BYTES), above the "
                                       f"limit of 2.00 GiB\n")
    assert not out.exists()
