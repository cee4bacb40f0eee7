"""``streaklab decompose --shared delay,alpha --irf X``: with a measured response the onset and
decay rates are estimated once, before the chunks, written to the store and held in every
chunk; a chunked run equals one whole-cube call, and a resumed run holds the identical values.
``--shared psf`` is the response's time scale there; ``--psf-map`` with a response is refused in
one line before any work."""
import json

import numpy as np
import pytest

from core.irf_models import tailed_response
from core.irfstore import save_response
from decomposition.evaluation.synthetic import SceneRanges, make_cube
from decomposition.image import decompose_image
from decomposition.store.resultstore import open_result_store
from streaklab.cli import main
from _cubes import worker_dies_at

TB, NT = 2.0, 160
IRF = tailed_response(3.0, 0.2, 20.0, time_step_ps=TB)
NAMES = ("direct_delay_ps", "direct_amplitude", "sss_delay_ps", "sss_amplitude", "sss_alpha_per_ps",
         "direct_delay_ps_stderr", "sss_alpha_per_ps_stderr", "direct_amplitude_stderr")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = make_cube(6, 6, NT, nsr=0.05, noise="white", seed=31, kinds="d+s", time_bin_ps=TB, response=IRF,
                  ranges=SceneRanges(sigma_ps=(3.0, 3.0), alpha_per_ps=(0.03, 0.03), direct_position=(0.2, 0.2)))
    root = tmp_path_factory.mktemp("shared_irf")
    cube, labels, irf = root / "cube.npy", root / "labels.npy", root / "irf.npz"
    np.save(cube, d.noisy)
    regions = np.zeros((6, 6), np.int16)
    regions[3:] = 2
    np.save(labels, regions)
    save_response(irf, IRF)
    return d, regions, cube, labels, irf


def _args(cube, out, labels, irf, *extra, shared="delay,alpha"):
    return ["decompose", str(cube), "--out", str(out), "--time-bin-ps", str(TB), "--chunks", "3", "3",
            "--components", "d,s", "--max-interreflections", "0", "--shared", shared,
            "--regions", str(labels), "--irf", str(irf), "--option", "stderr=true", "--quiet", "--per-pixel", *extra]


@pytest.mark.parametrize("shared", ["delay,alpha", "psf,delay,alpha"])
def test_chunked_cli_run_with_a_response_equals_one_whole_cube_call(inputs, tmp_path, shared):
    d, regions, cube_path, labels, irf = inputs
    whole = decompose_image(d.noisy, TB, components=("d", "s"), max_reflections=0, t0_ps=TB, stderr=True,
                            shared=shared, regions=regions, irf=IRF)
    assert main(_args(cube_path, tmp_path / "res.zarr", labels, irf, shared=shared)) == 0
    store = open_result_store(tmp_path / "res.zarr")
    rec = store.attrs["shared"]
    assert rec == json.loads(json.dumps(whole.info["shared"]))
    assert store.attrs["irf"]["kind"] == "response" and store.attrs["job"]["shared"] == shared.split(",")
    if "psf" in shared:     # rendered through the response as given: its time scale is 1
        assert abs(rec["response_stretch"] - 1.0) < 4 * rec["response_stretch_stderr"], rec
        from streaklab.report import summary_text

        assert f"response time scale {rec['response_stretch']:.4g} +- " in summary_text(store)
    truth = float(d.params["direct_delay_ps"][0, 0])
    assert abs(rec["delay_ps"] - truth) < 4 * rec["delay_ps_stderr"], rec
    assert abs(rec["sss_alpha_per_ps"]["0"] - 0.03) < 4 * rec["sss_alpha_per_ps_stderr"]["0"], rec
    for key in NAMES:
        got, want = store.group[key][...], np.asarray(whole.params[key])
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=key)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12, err_msg=key)
    delay = store.group["direct_delay_ps"][...]
    assert np.isfinite(delay).sum() == 36
    np.testing.assert_array_equal(delay, rec["delay_ps"])
    alpha = store.group["sss_alpha_per_ps"][...]
    for label in (0, 2):
        inside = (regions == label) & np.isfinite(alpha)
        np.testing.assert_array_equal(alpha[inside], rec["sss_alpha_per_ps"][str(label)])


def test_resume_with_a_response_holds_the_same_values(inputs, tmp_path, monkeypatch):
    _, _, cube_path, labels, irf = inputs
    assert main(_args(cube_path, tmp_path / "full.zarr", labels, irf)) == 0
    import decomposition.image.shared as shared
    revive = worker_dies_at(monkeypatch, 2)
    with pytest.raises(RuntimeError, match="worker died"):
        main(_args(cube_path, tmp_path / "part.zarr", labels, irf, "--threads", "1"))
    revive()
    assert 0 < int(open_result_store(tmp_path / "part.zarr").done_chunks().sum()) < 9

    def no_estimate(*args, **kwargs):
        raise AssertionError("a resumed run must read the shared values back, not estimate them again")

    monkeypatch.setattr(shared, "image_estimate", no_estimate)
    assert main(_args(cube_path, tmp_path / "part.zarr", labels, irf, "--resume")) == 0
    full, part = open_result_store(tmp_path / "full.zarr"), open_result_store(tmp_path / "part.zarr")
    assert part.attrs["shared"] == full.attrs["shared"]
    for key in NAMES + ("flags", "direct", "sss"):
        np.testing.assert_array_equal(part.group[key][...], full.group[key][...], err_msg=key)


def test_a_response_psf_map_is_refused_before_any_work(inputs, tmp_path, capsys):
    _, _, cube_path, _, irf = inputs
    args = ["decompose", str(cube_path), "--out", str(tmp_path / "res.zarr"), "--time-bin-ps", str(TB), "--quiet",
            "--shared", "psf,delay", "--psf-map", "--irf", str(irf)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "psf_map" in err and "measured response" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "res.zarr").exists()
