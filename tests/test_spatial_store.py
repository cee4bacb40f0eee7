"""Spatial coupling in chunks: each chunk read with the coupling's halo gives one whole-image call's
answer, and an interrupted ``--spatial`` run resumes to the uninterrupted store."""
import threading

import numpy as np
import pytest
import zarr

from _cubes import TB, smooth_scene, worker_dies_at
from decomposition.image import decompose_image
from decomposition.store.chunked import chunk_tasks, run_tasks
from decomposition.store.pipeline import PipelineError, decompose_to_store
from decomposition.store.resultstore import open_result_store
from reconstruction.cubestore import write_cube
from streaklab.cli import main

SHAPES = {"direct_delay_ps": (), "direct_amplitude": (), "direct_sigma_ps": (), "sss_delay_ps": (),
          "sss_amplitude": (), "sss_alpha_per_ps": (), "sss_sigma_ps": (), "ir_delay_ps": (2,),
          "ir_amplitude": (2,), "ir_sigma_ps": (2,)}


def _chunked(cube, chunks, **kwargs):
    sunk, lock = {}, threading.Lock()

    def sink(iy, ix, result):
        with lock:
            sunk[(iy, ix)] = result

    run_tasks(chunk_tasks(cube, chunks=chunks, sink=sink, param_shapes=SHAPES, time_bin_ps=TB, n_ir=2,
                          options={"max_reflections": 2}, **kwargs), num_workers=1)
    gy, gx = max(k[0] for k in sunk) + 1, max(k[1] for k in sunk) + 1

    def whole(get):
        return np.concatenate([np.concatenate([get(sunk[(i, j)]) for j in range(gx)], axis=1) for i in range(gy)])

    return {k: whole(lambda r: r["params"][k]) for k in SHAPES} | {"flags": whole(lambda r: r["flags"])}


def test_chunks_with_the_halo_equal_one_call_on_the_whole_image():
    cube = smooth_scene(n=10, nsr=0.11, seed=4)[0]
    ref = decompose_image(cube, TB, spatial=True, max_reflections=2)
    got = _chunked(cube, (4, 4), spatial=True)
    for k in SHAPES:
        v = np.asarray(ref.params[k], np.float64)
        np.testing.assert_array_equal(np.isnan(got[k]), np.isnan(v), err_msg=k)
        np.testing.assert_allclose(got[k], v, rtol=1e-6, atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(got["flags"], ref.flags)


def test_shared_and_spatial_in_haloed_chunks_equal_one_call_on_the_whole_image():
    # the cube's shared PSF estimated once, each haloed chunk decomposed as one image holding it
    from decomposition.image.shared import image_estimate

    cube = smooth_scene(n=10, nsr=0.11, seed=4)[0]
    ref = decompose_image(cube, TB, spatial=True, shared="psf", max_reflections=2)
    estimate = image_estimate(cube, None, TB, "convscd", ("psf",), keywords={"max_reflections": 2})
    assert estimate.psf_sigma_ps == ref.info["shared"]["psf_sigma_ps"]
    got = _chunked(cube, (4, 4), spatial=True, shared=estimate)
    present = np.isfinite(got["direct_sigma_ps"])
    assert present.any() and np.all(got["direct_sigma_ps"][present] == estimate.psf_sigma_ps)
    for k in SHAPES:
        v = np.asarray(ref.params[k], np.float64)
        np.testing.assert_array_equal(np.isnan(got[k]), np.isnan(v), err_msg=k)
        np.testing.assert_allclose(got[k], v, rtol=1e-6, atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(got["flags"], ref.flags)


@pytest.fixture(scope="module")
def spatial_store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("spatial")
    write_cube(tmp / "cube.zarr", smooth_scene(n=6, nsr=0.11, seed=5)[0].astype(np.float32), time_bin_ps=TB,
               chunks=(3, 3))
    assert main(["decompose", str(tmp / "cube.zarr"), "--out", str(tmp / "full.zarr"), "--spatial", "--quiet"]) == 0
    return tmp


def test_an_interrupted_spatial_run_resumes_to_the_same_store(spatial_store, tmp_path, monkeypatch):
    revive = worker_dies_at(monkeypatch, 3)
    with pytest.raises(RuntimeError, match="worker died"):
        decompose_to_store(spatial_store / "cube.zarr", tmp_path / "part.zarr", threads=1, progress=False, spatial=True)
    revive()
    assert 0 < int(open_result_store(tmp_path / "part.zarr").done_chunks().sum()) < 4
    # the job holds the coupling: resuming without it is refused
    with pytest.raises(PipelineError):
        decompose_to_store(spatial_store / "cube.zarr", tmp_path / "part.zarr", resume=True, progress=False)
    decompose_to_store(spatial_store / "cube.zarr", tmp_path / "part.zarr", resume=True, progress=False, spatial=True)
    ga, gb = zarr.open_group(str(spatial_store / "full.zarr"), mode="r"), zarr.open_group(str(tmp_path / "part.zarr"), mode="r")
    assert sorted(ga.array_keys()) == sorted(gb.array_keys())
    for k in ga.array_keys():
        x, y = ga[k][...], gb[k][...]
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k
    # and the store is the coupled answer, not the per-pixel one
    cube = zarr.open_group(str(spatial_store / "cube.zarr"), mode="r")["cube"][...]
    ref = decompose_image(cube, TB, spatial=True, max_reflections=3)
    np.testing.assert_allclose(ga["direct_delay_ps"][...], ref.params["direct_delay_ps"], rtol=1e-6, atol=1e-9)
    # the report says the store is coupled, and how far each chunk read around itself
    from streaklab.report import summary_text

    assert "spatial coupling:" in summary_text(open_result_store(tmp_path / "part.zarr")) and "halo of 14 pixels" in \
        summary_text(open_result_store(tmp_path / "part.zarr"))


def test_bad_spatial_settings_are_refused_before_any_work(spatial_store, tmp_path):
    with pytest.raises(PipelineError, match="--spatial: spatial: unknown option"):
        decompose_to_store(spatial_store / "cube.zarr", tmp_path / "x.zarr", progress=False, spatial={"nope": 1})
    assert not (tmp_path / "x.zarr").exists()
    # a list of profiles has no neighbours to couple
    np.save(tmp_path / "list.npy", smooth_scene(n=4, nsr=0.11, seed=1)[0].reshape(16, -1))
    with pytest.raises(PipelineError, match="list of profiles .n, t. with no neighbours"):
        decompose_to_store(tmp_path / "list.npy", tmp_path / "y.zarr", time_bin_ps=TB, progress=False, spatial=True)
    assert not (tmp_path / "y.zarr").exists()


def test_the_command_couples_an_image_by_default(spatial_store, tmp_path, capsys):
    """``streaklab decompose CUBE`` with neither --spatial nor --per-pixel: the coupled answer; its
    pixels each draw their own PSF width (smooth_scene), so nothing is shared, and the command says
    why; --per-pixel: not coupled; a list of profiles has no neighbours and is decomposed per pixel."""
    cube_path = spatial_store / "cube.zarr"
    assert main(["decompose", str(cube_path), "--out", str(tmp_path / "auto.zarr")]) == 0
    assert "nothing shared: the lit pixels' own PSF widths scatter by" in capsys.readouterr().err
    job = open_result_store(tmp_path / "auto.zarr").attrs["job"]
    assert "spatial" in job and "shared" not in job
    cube = zarr.open_group(str(cube_path), mode="r")["cube"][...]
    ref = decompose_image(cube, TB, spatial=True, max_reflections=3)
    got = zarr.open_group(str(tmp_path / "auto.zarr"), mode="r")["direct_delay_ps"][...]
    np.testing.assert_allclose(got, ref.params["direct_delay_ps"], rtol=1e-6, atol=1e-9)

    assert main(["decompose", str(cube_path), "--out", str(tmp_path / "per.zarr"), "--quiet", "--per-pixel"]) == 0
    assert "spatial" not in open_result_store(tmp_path / "per.zarr").attrs["job"]

    np.save(tmp_path / "list.npy", cube.reshape(36, -1))
    assert main(["decompose", str(tmp_path / "list.npy"), "--time-bin-ps", str(TB), "--out",
                 str(tmp_path / "list.zarr"), "--quiet"]) == 0
    assert "spatial" not in open_result_store(tmp_path / "list.zarr").attrs["job"]


def test_the_default_shares_one_instruments_psf(tmp_path):
    """A cube of one PSF (bench spatial's scene, 4 ps): the default couples it and holds the shared
    width, as decompose_image(spatial=True, shared="psf") does."""
    from decomposition.evaluation.spatial_scenes import make_spatial_scene

    scene = make_spatial_scene(10, 10, 128, nsr=0.11, seed=2)
    write_cube(tmp_path / "one.zarr", scene.profiles.astype(np.float32), time_bin_ps=scene.time_bin_ps,
               t0_ps=scene.t0_ps, chunks=(5, 5))
    assert main(["decompose", str(tmp_path / "one.zarr"), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 0
    store = open_result_store(tmp_path / "r.zarr")
    assert store.attrs["job"]["shared"] == ["psf"] and "spatial" in store.attrs["job"]
    assert store.attrs["shared"]["psf_spread"] <= 0.25
    assert abs(store.attrs["shared"]["psf_sigma_ps"] - scene.sigma_ps) < 0.3


def test_a_resumed_run_keeps_the_settings_its_store_was_started_with(spatial_store, tmp_path, monkeypatch):
    """A store started per pixel (as every store before the coupled default was) resumes per pixel
    under the default command, and a coupled one coupled."""
    cube_path = spatial_store / "cube.zarr"
    for extra, name in ((["--per-pixel"], "per"), ([], "auto")):
        revive = worker_dies_at(monkeypatch, 2)
        with pytest.raises(RuntimeError, match="worker died"):
            main(["decompose", str(cube_path), "--out", str(tmp_path / f"{name}.zarr"), "--quiet", "--threads", "1",
                  *extra])
        revive()
        assert main(["decompose", str(cube_path), "--out", str(tmp_path / f"{name}.zarr"), "--quiet",
                     "--resume"]) == 0
        assert main(["decompose", str(cube_path), "--out", str(tmp_path / f"{name}-full.zarr"), "--quiet",
                     *extra]) == 0
        ga = zarr.open_group(str(tmp_path / f"{name}.zarr"), mode="r")
        gb = zarr.open_group(str(tmp_path / f"{name}-full.zarr"), mode="r")
        for k in ("direct_delay_ps", "flags", "sss_alpha_per_ps"):
            assert np.array_equal(ga[k][...], gb[k][...], equal_nan=ga[k].dtype.kind == "f"), (name, k)


def test_the_default_decomposes_a_dark_cube(tmp_path):
    """No lit pixel: the coupled default leaves every pixel empty and still writes the store."""
    write_cube(tmp_path / "dark.zarr", np.zeros((4, 4, 128), np.float32), time_bin_ps=TB, chunks=(2, 2))
    assert main(["decompose", str(tmp_path / "dark.zarr"), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 0
    store = open_result_store(tmp_path / "r.zarr")
    assert "spatial" in store.attrs["job"] and store.done_mask().all()
    assert np.isnan(store.group["direct_delay_ps"][...]).all()
