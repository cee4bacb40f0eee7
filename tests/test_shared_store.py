"""``streaklab decompose --shared``: the shared parameters estimated once, before the chunks, written
to the result store and held in every chunk; a chunked run equals one whole-cube call, and a
resumed run holds the identical values."""
import json

import numpy as np
import pytest

from decomposition.evaluation.synthetic import SceneRanges, make_cube
from decomposition.image import decompose_image
from decomposition.store.resultstore import open_result_store
from streaklab.cli import main
from _cubes import worker_dies_at

TB, NT = 2.0, 96
NAMES = ("direct_delay_ps", "direct_amplitude", "direct_sigma_ps", "sss_delay_ps", "sss_amplitude",
         "sss_sigma_ps", "sss_alpha_per_ps", "direct_sigma_ps_stderr", "sss_alpha_per_ps_stderr")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = make_cube(6, 6, NT, nsr=0.08, noise="white", seed=5, kinds="d+s", time_bin_ps=TB,
                  ranges=SceneRanges(sigma_ps=(3.0, 3.0), alpha_per_ps=(0.03, 0.03), direct_position=(0.2, 0.2)))
    root = tmp_path_factory.mktemp("shared")
    cube, labels = root / "cube.npy", root / "labels.npy"
    np.save(cube, d.noisy)
    regions = np.zeros((6, 6), np.int16)
    regions[3:] = 2
    np.save(labels, regions)
    return d.noisy, regions, cube, labels


def _args(cube, out, labels, *extra):
    return ["decompose", str(cube), "--out", str(out), "--time-bin-ps", str(TB), "--chunks", "4", "4",
            "--components", "d,s", "--max-interreflections", "0", "--shared", "psf,delay,alpha",
            "--regions", str(labels), "--option", "stderr=true", "--quiet", "--per-pixel", *extra]


@pytest.fixture(scope="module")
def whole(inputs):
    cube, regions, _, _ = inputs
    return decompose_image(cube, TB, components=("d", "s"), max_reflections=0, t0_ps=TB, stderr=True,
                           shared="psf,delay,alpha", regions=regions)


def test_chunked_cli_run_equals_one_whole_cube_call(inputs, whole, tmp_path, capsys):
    cube, regions, cube_path, labels = inputs
    assert main(_args(cube_path, tmp_path / "res.zarr", labels)) == 0
    assert "shared: PSF sigma" in capsys.readouterr().out
    store = open_result_store(tmp_path / "res.zarr")
    rec = store.attrs["shared"]
    assert rec == json.loads(json.dumps(whole.info["shared"]))         # the same estimates, once
    assert store.attrs["job"]["shared"] == ["psf", "delay", "alpha"] and store.attrs["job"]["regions_sha256"]
    for key in NAMES:
        got, want = store.group[key][...], np.asarray(whole.params[key])
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=key)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12, err_msg=key)
    sigma = store.group["direct_sigma_ps"][...]
    np.testing.assert_array_equal(sigma[np.isfinite(sigma)], rec["psf_sigma_ps"])
    alpha = store.group["sss_alpha_per_ps"][...]
    for label in (0, 2):
        inside = (regions == label) & np.isfinite(alpha)
        np.testing.assert_array_equal(alpha[inside], rec["sss_alpha_per_ps"][str(label)])
    # the report says what every pixel held
    from streaklab.report import summary_text

    text = summary_text(store)
    assert f"shared: PSF sigma {rec['psf_sigma_ps']:.4g} +- " in text and "(held in every pixel)" in text
    assert "region 2" in text and "spatial coupling" not in text


def test_resume_after_an_interruption_holds_the_same_values(inputs, tmp_path, monkeypatch):
    _, _, cube_path, labels = inputs
    assert main(_args(cube_path, tmp_path / "full.zarr", labels)) == 0
    import decomposition.image.shared as shared
    revive = worker_dies_at(monkeypatch, 2)
    with pytest.raises(RuntimeError, match="worker died"):
        main(_args(cube_path, tmp_path / "part.zarr", labels, "--threads", "1"))
    revive()
    assert 0 < int(open_result_store(tmp_path / "part.zarr").done_chunks().sum()) < 4

    def no_estimate(*args, **kwargs):
        raise AssertionError("a resumed run must read the shared values back, not estimate them again")

    monkeypatch.setattr(shared, "image_estimate", no_estimate)
    assert main(_args(cube_path, tmp_path / "part.zarr", labels, "--resume")) == 0
    full, part = open_result_store(tmp_path / "full.zarr"), open_result_store(tmp_path / "part.zarr")
    assert part.attrs["shared"] == full.attrs["shared"]
    for key in NAMES + ("flags", "direct", "sss"):
        np.testing.assert_array_equal(part.group[key][...], full.group[key][...], err_msg=key)


def test_resume_with_other_shared_settings_is_refused(inputs, tmp_path, capsys):
    _, regions, cube_path, labels = inputs
    out = tmp_path / "res.zarr"
    assert main(_args(cube_path, out, labels)) == 0
    other = labels.parent / "other.npy"
    np.save(other, np.where(regions == 2, 1, 0))
    capsys.readouterr()
    assert main(_args(cube_path, out, other, "--resume")) == 2
    assert "regions_sha256" in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--shared", "psf,width"], "unknown parameter 'width'"),
    (["--shared", "psf", "--regions", "LABELS"], "give --shared alpha too"),
    (["--shared", "delay", "--psf-map"], "give --shared psf too"),
    (["--shared", "alpha", "--regions", "WRONG"], "the labels have shape (2, 2)"),
    (["--shared", "alpha", "--regions", "FLOAT"], "integer label image"),
])
def test_bad_shared_settings_are_refused_before_any_work(inputs, tmp_path, capsys, extra, message):
    _, _, cube_path, labels = inputs
    np.save(tmp_path / "wrong.npy", np.zeros((2, 2), int))
    np.save(tmp_path / "float.npy", np.zeros((6, 6)))
    swap = {"LABELS": str(labels), "WRONG": str(tmp_path / "wrong.npy"), "FLOAT": str(tmp_path / "float.npy")}
    args = ["decompose", str(cube_path), "--out", str(tmp_path / "res.zarr"), "--time-bin-ps", str(TB), "--quiet",
            *[swap.get(a, a) for a in extra]]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "res.zarr").exists()
