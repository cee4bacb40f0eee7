"""``streaklab decompose`` with an instrument response: a response stored in the cube is used
by default and recorded in the result store; --irf PATH and --irf gaussian choose otherwise;
bad responses stop the run before anything is written."""
import numpy as np
import pytest
import zarr

from _cubes import response_profiles
from core.irf_models import tailed_response
from core.irfstore import save_response
from decomposition import decompose
from decomposition.store.pipeline import PipelineError, decompose_to_store
from decomposition.store.resultstore import open_result_store
from reconstruction.cubestore import write_cube, write_cube_response
from streaklab.cli import main

T = 2.0
L = 512


@pytest.fixture(scope="module")
def irf():
    return tailed_response(6.0, 0.2, 40.0, time_step_ps=T)


@pytest.fixture(scope="module")
def cubes(tmp_path_factory, irf):
    tmp = tmp_path_factory.mktemp("irfcube")
    data, d = response_profiles(irf, L, seed=7, delay_range_ps=(150, 250), echo_after_ps=120.0, noise=10.0, time_bin_ps=T)
    with_irf = tmp / "with_irf.zarr"
    write_cube(with_irf, data, time_bin_ps=T, chunks=(1, 3))
    write_cube_response(str(with_irf), irf)
    plain = tmp / "plain.zarr"
    write_cube(plain, data, time_bin_ps=T, chunks=(1, 3))
    save_response(tmp / "irf.npz", irf)
    return tmp, data, d


def test_cube_response_used_by_default_and_recorded(cubes, irf, capsys):
    tmp, data, d = cubes
    out = tmp / "res_default.zarr"
    assert main(["decompose", str(tmp / "with_irf.zarr"), "--out", str(out), "--quiet", "--per-pixel"]) == 0
    said = capsys.readouterr().out
    assert "instrument response:" in said and "stored in the cube" in said
    store = open_result_store(str(out))
    rec = store.attrs["irf"]
    assert rec["kind"] == "response" and rec["fwhm_ps"] == pytest.approx(irf.fwhm_ps(), rel=1e-6)
    assert rec["model"]["name"] == irf.model["name"] and "stored in the cube" in rec["source"]
    assert store.attrs["job"]["irf_sha256"] == rec["samples_sha256"]
    p = store.params()
    ref = decompose(data.astype(np.float64), T, irf=irf).params
    assert np.allclose(p["direct_delay_ps"], ref["direct_delay_ps"], atol=1e-4)
    assert np.abs(p["direct_delay_ps"] - d).max() < 0.5
    assert np.abs(p["ir_delay_ps"][..., 0] - (d + 120.0)).max() < 0.5


def test_irf_path_and_gaussian_override(cubes, capsys):
    tmp, data, d = cubes
    out = tmp / "res_path.zarr"
    assert main(["decompose", str(tmp / "plain.zarr"), "--out", str(out), "--quiet",
                 "--irf", str(tmp / "irf.npz")]) == 0
    assert "irf.npz" in capsys.readouterr().out
    assert open_result_store(str(out)).attrs["irf"]["kind"] == "response"
    out_g = tmp / "res_gauss.zarr"
    assert main(["decompose", str(tmp / "with_irf.zarr"), "--out", str(out_g), "--quiet", "--irf", "gaussian"]) == 0
    assert "the Gaussian PSF" in capsys.readouterr().out
    store = open_result_store(str(out_g))
    assert store.attrs["irf"] == {"kind": "gaussian"} and "irf_sha256" not in store.attrs["job"]


def test_bad_responses_stop_before_writing(cubes, irf, tmp_path):
    tmp, _, _ = cubes
    with pytest.raises(PipelineError, match="no such file"):
        decompose_to_store(str(tmp / "plain.zarr"), str(tmp_path / "a.zarr"), irf=str(tmp_path / "none.npz"),
                           progress=False)
    short = tmp_path / "short.zarr"
    write_cube(short, np.ones((1, 1, 200), np.float32), time_bin_ps=T)
    with pytest.raises(PipelineError, match="longer than the profiles' window"):
        decompose_to_store(str(short), str(tmp_path / "b.zarr"), irf=irf, progress=False)
    assert not (tmp_path / "a.zarr").exists() and not (tmp_path / "b.zarr").exists()


def test_the_pipeline_warms_up_the_response_path_with_its_response(cubes, irf, tmp_path, monkeypatch):
    """The kernels are loaded before the first chunk with the response the run uses."""
    import decomposition.warmup as warmup

    calls = []
    monkeypatch.setattr(warmup, "warm_up", lambda **kw: calls.append(kw) or 0.0)
    tmp, data, d = cubes
    decompose_to_store(str(tmp / "with_irf.zarr"), str(tmp_path / "w.zarr"), progress=False)
    assert len(calls) == 1
    used = calls[0]["options"]["irf"]
    assert used.fwhm_ps() == pytest.approx(irf.fwhm_ps(), rel=1e-6)
    assert calls[0]["n_bins"] == L and calls[0]["time_bin_ps"] == T
    # the kernels of the run's kind of data only: these are floats with Gaussian noise, their
    # integer rounding photon counts
    assert calls[0]["options"]["noise"] == "gaussian"
    counts = tmp_path / "counts.zarr"
    write_cube(counts, np.rint(np.maximum(data, 0.0)).astype(np.uint16), time_bin_ps=T, chunks=(1, 3))
    write_cube_response(str(counts), irf)
    decompose_to_store(str(counts), str(tmp_path / "c.zarr"), progress=False)
    assert calls[1]["options"]["noise"] == "poisson" and calls[1]["options"]["irf"].fwhm_ps() == used.fwhm_ps()


def test_warm_up_with_a_response_decomposes_its_profiles_as_floats_and_counts(irf, monkeypatch):
    import decomposition.warmup as warmup
    from decomposition.noise import is_count_data

    assert warmup.warm_up(time_bin_ps=T, n_bins=L, options={"irf": irf}, quiet=True) >= 0.0   # the real run
    calls, rendered = [], []
    monkeypatch.setattr(warmup, "decompose", lambda y, **kw: calls.append((y, kw)))
    real_render = warmup.render_profile
    monkeypatch.setattr(warmup, "render_profile", lambda *a, **kw: rendered.append(kw["irf"]) or real_render(*a, **kw))
    warmup.warm_up(time_bin_ps=T, n_bins=L, options={"irf": irf}, quiet=True)
    assert [is_count_data(y) for y, _ in calls] == [False, True]
    assert all(kw["irf"] is irf for _, kw in calls)
    # every profile rendered with the response itself (on the run's step)
    assert rendered and all(r is not None and r.fwhm_ps() == pytest.approx(irf.fwhm_ps(), rel=1e-6) for r in rendered)
    counts = calls[1][0]
    assert counts.max(axis=1).min() > 150 and counts.shape[1] == L
    calls.clear()
    warmup.warm_up(time_bin_ps=T, n_bins=L, options={"irf": irf, "noise": "gaussian"}, quiet=True)
    assert [is_count_data(y) for y, _ in calls] == [False]
    calls.clear()
    warmup.warm_up(time_bin_ps=T, n_bins=L, options={"irf": irf, "noise": "poisson"}, quiet=True)
    assert [is_count_data(y) for y, _ in calls] == [True]


def test_spatial_coupling_with_the_cube_response(cubes, irf, tmp_path):
    """``--spatial`` with the response stored in the cube: the store holds decompose_image's coupled
    answer over the response's atoms (chunks of 1 x 3 read with the coupling's halo)."""
    from decomposition.image import decompose_image

    tmp, data, d = cubes
    out = tmp_path / "spatial.zarr"
    assert main(["decompose", str(tmp / "with_irf.zarr"), "--out", str(out), "--quiet", "--spatial"]) == 0
    store = open_result_store(str(out))
    assert store.attrs["irf"]["kind"] == "response" and "spatial" in store.attrs["job"]
    ref = decompose_image(data.astype(np.float64), T, irf=irf, spatial=True, max_reflections=store.params()[
        "ir_delay_ps"].shape[-1])
    np.testing.assert_allclose(store.params()["direct_delay_ps"], ref.params["direct_delay_ps"], rtol=1e-6)
    assert np.abs(store.params()["direct_delay_ps"] - d).max() < 0.5
    # the default couples the image too, with nothing shared: the measured response is the instrument
    assert main(["decompose", str(tmp / "with_irf.zarr"), "--out", str(tmp_path / "auto.zarr"), "--quiet"]) == 0
    job = open_result_store(str(tmp_path / "auto.zarr")).attrs["job"]
    assert "spatial" in job and "shared" not in job


def test_the_search_runs_with_the_cube_response_where_asked(cubes, irf):
    """``--option search=true`` reaches the response path: the store records it, and its
    parameters are those of ``decompose(..., irf=R, search=True)``."""
    tmp, data, d = cubes
    out = tmp / "res_search.zarr"
    assert main(["decompose", str(tmp / "with_irf.zarr"), "--out", str(out), "--quiet", "--per-pixel",
                 "--option", "search=true"]) == 0
    store = open_result_store(str(out))
    assert store.attrs["options"]["search"] is True
    ref = decompose(data.astype(np.float64), T, irf=irf, search=True)
    assert ref.info["search"] is True and "search_wins" in ref.info
    np.testing.assert_allclose(store.params()["direct_delay_ps"], ref.params["direct_delay_ps"], atol=1e-4)
    assert np.abs(store.params()["direct_delay_ps"] - d).max() < 0.5


def test_a_cube_of_one_detector_through_a_response_is_weighted_by_its_noise_law(tmp_path, irf):
    """A cube whose description says its noise is one detector's (``noise_law="detector"``),
    shot noise plus read noise rendered through the response: the response path takes the
    cube's law, as the Gaussian path does, and the store holds what the API gives with that law
    (one chunk: bit for bit); each pixel's own law gives another answer."""
    from decomposition.evaluation.synthetic import make_profiles
    rng = np.random.default_rng(3)
    d = make_profiles(16, L, seed=4, ranges="paper", noise="none", response=irf, time_bin_ps=T)
    clean = np.clip(d.noisy, 0.0, None).reshape(2, 8, L)
    data = rng.poisson(clean * 100.0) / 100.0 + rng.normal(0.0, 0.005, clean.shape)
    write_cube(tmp_path / "one.zarr", data, time_bin_ps=T, t0_ps=d.t0_ps, chunks=(2, 8), noise_law="detector")
    summary = decompose_to_store(tmp_path / "one.zarr", tmp_path / "res.zarr", progress=False, irf=irf)
    assert (summary["noise_law"]["signal_noise_law"], summary["noise_law"]["source"]) == ("detector", "cube")
    store = open_result_store(tmp_path / "res.zarr")
    assert store.attrs["options"]["signal_noise_law"] == "detector" and store.attrs["irf"]["kind"] == "response"
    flat = zarr.open_group(str(tmp_path / "one.zarr"), mode="r")["cube"][...].reshape(16, L)
    one = decompose(flat, T, t0_ps=d.t0_ps, irf=irf, signal_noise_law="detector", max_reflections=3)
    assert one.info["signal_weighted"] == 16 and one.info["signal_noise_law_fit"]["gain"] > 0
    for k in ("direct_delay_ps", "sss_alpha_per_ps", "ir_delay_ps"):
        v = np.asarray(one.params[k], np.float64)
        np.testing.assert_array_equal(store.group[k][...].reshape(v.shape), v, err_msg=k)
    own = decompose(flat, T, t0_ps=d.t0_ps, irf=irf, signal_noise_law="pixel", max_reflections=3)
    assert not np.array_equal(own.params["direct_delay_ps"], one.params["direct_delay_ps"])
