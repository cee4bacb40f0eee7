"""``streaklab simulate``: the cube plus its ground truth, self-describing, reproducible, never overwritten by accident."""
import numpy as np
import pytest
import zarr

from core.model import PARAM_KEYS, render_components
from decomposition.evaluation.synthetic import make_cube
from reconstruction.cubestore import open_cube
from streaklab.cli import main


def _simulate(out, *extra):
    return main(["simulate", "--out", str(out), "--shape", "3", "4", "96", "--nsr", "0.05", "--noise", "pink",
                 "--seed", "5", *extra])


def test_writes_cube_and_truth_layout(tmp_path):
    out = tmp_path / "sim.zarr"
    assert _simulate(out) == 0
    cube = open_cube(out)
    assert cube.shape == (3, 4, 96) and cube.time_bin_ps == 2.0 and cube.t0_ps == 2.0
    ref = make_cube(3, 4, 96, nsr=0.05, noise="pink", seed=5)
    np.testing.assert_allclose(cube.array[...], ref.noisy, rtol=1e-6, atol=1e-7)

    truth = zarr.open_group(str(out), mode="r")["truth"]
    assert truth.attrs["nsr"] == 0.05 and truth.attrs["noise"] == "pink" and truth.attrs["seed"] == 5
    assert truth.attrs["kinds"] == ["d+s", "d+s+r2", "d+s+r2+r3"]
    for key in PARAM_KEYS:
        arr = truth[key]
        dims = ("y", "x", "r") if key.startswith("ir_") else ("y", "x")
        assert tuple(arr.metadata.dimension_names) == dims
        assert arr.attrs["units"] in ("ps", "1/ps", "arbitrary")
        np.testing.assert_array_equal(arr[...], ref.params[key])
    assert truth["direct_delay_ps"].attrs["units"] == "ps"
    assert truth["sss_alpha_per_ps"].attrs["units"] == "1/ps"
    assert tuple(truth["ir"].metadata.dimension_names) == ("y", "x", "r", "t")
    assert truth["ir"].shape == (3, 4, 2, 96)
    np.testing.assert_array_equal(truth["r"][...], [2, 3])
    # Clean components re-render from the stored parameters, and add up to the clean cube.
    comps = render_components({k: truth[k][...] for k in PARAM_KEYS}, 96)
    np.testing.assert_allclose(truth["direct"][...], comps["direct"], atol=1e-6)
    np.testing.assert_allclose(truth["sss"][...], comps["sss"], atol=1e-6)
    np.testing.assert_allclose(truth["ir"][...], comps["interreflections"], atol=1e-6)
    clean = truth["direct"][...] + truth["sss"][...] + truth["ir"][...].sum(axis=2)
    nsr = np.linalg.norm(cube.array[...] - clean, axis=-1) / np.linalg.norm(clean, axis=-1)
    np.testing.assert_allclose(nsr, 0.05, rtol=1e-4)  # float32 storage
    prov = cube.attrs["provenance"]
    assert prov["producer"] == "streaklab simulate" and prov["synthetic"]["seed"] == 5


def test_xarray_opens_cube_and_truth(tmp_path):
    xr = pytest.importorskip("xarray")
    out = tmp_path / "sim.zarr"
    assert _simulate(out, "--kinds", "a,c") == 0
    ds = xr.open_zarr(out, consolidated=False)
    assert ds["cube"].dims == ("y", "x", "t")
    tr = xr.open_zarr(out, group="truth", consolidated=False)
    assert tr["ir"].dims == ("y", "x", "r", "t") and tr["direct_delay_ps"].dims == ("y", "x")
    assert tr["direct_delay_ps"].attrs["units"] == "ps"
    np.testing.assert_allclose(tr["t"].values, ds["t"].values)
    assert list(tr["r"].values) == [2, 3]


def test_refuses_to_overwrite_without_flag(tmp_path, capsys):
    out = tmp_path / "sim.zarr"
    assert _simulate(out) == 0
    before = open_cube(out).array[...]
    assert main(["simulate", "--out", str(out), "--shape", "2", "2", "64", "--seed", "9"]) == 2
    assert "already exists" in capsys.readouterr().err
    np.testing.assert_array_equal(open_cube(out).array[...], before)
    assert main(["simulate", "--out", str(out), "--shape", "2", "2", "64", "--seed", "9", "--overwrite"]) == 0
    assert open_cube(out).shape == (2, 2, 64)


def test_same_seed_same_store_and_bad_options(tmp_path, capsys):
    a, b = tmp_path / "a.zarr", tmp_path / "b.zarr"
    assert _simulate(a) == 0 and _simulate(b) == 0
    np.testing.assert_array_equal(open_cube(a).array[...], open_cube(b).array[...])
    assert main(["simulate", "--out", str(tmp_path / "x.zarr"), "--shape", "2", "2", "64", "--noise", "brown"]) == 2
    assert "unknown noise type" in capsys.readouterr().err
    assert main(["simulate", "--out", str(tmp_path / "x.zarr"), "--shape", "2", "2", "16", "--kinds", "c"]) == 2
    assert "too short" in capsys.readouterr().err
    assert main(["simulate", "--out", str(tmp_path / "x.zarr"), "--shape", "0", "2", "64"]) == 2
    assert main(["simulate", "--out", str(tmp_path / "x.zarr"), "--shape", "2", "2", "64", "--nsr", "-1"]) == 2
    assert not (tmp_path / "x.zarr").exists()  # nothing half-written


def test_paper_scenes_bin_integrated(tmp_path):
    out = tmp_path / "paper.zarr"
    assert main(["simulate", "--out", str(out), "--shape", "2", "3", "256", "--nsr", "0", "--noise", "none",
                 "--seed", "1", "--scenes", "paper", "--bin-integrated"]) == 0
    ref = make_cube(2, 3, 256, seed=1, ranges="paper", bin_integrated=True)
    np.testing.assert_allclose(open_cube(out).array[...], ref.noisy, rtol=1e-6, atol=1e-7)
    truth = zarr.open_group(str(out), mode="r")["truth"]
    assert truth.attrs["bin_integrated"] is True
    assert truth.attrs["scene_ranges"]["sigma_ps"] == [1.0, 10.0]
    assert main(["simulate", "--out", str(tmp_path / "x.zarr"), "--shape", "1", "1", "64", "--scenes", "nosuch"]) == 2
