"""``streaklab report`` on stores decomposed with an instrument response: the store keeps the
response (its ``irf`` group) and the report renders the fits with it; stores without one
(Gaussian, or written before stores kept it) still report, and the summary says which."""
import shutil

import numpy as np
import pytest
import zarr

from _cubes import response_profiles
from core.irf_models import tailed_response
from decomposition.store.pipeline import decompose_to_store
from decomposition.store.resultstore import RESPONSE_GROUP, ResultStoreError, open_result_store
from reconstruction.cubestore import write_cube
from streaklab.report import make_report, profiles_figure, rendered_components, summary_text

T = 2.0
L = 256


@pytest.fixture(scope="module")
def irf():
    return tailed_response(4.0, 0.2, 20.0, time_step_ps=T)


@pytest.fixture(scope="module")
def stores(tmp_path_factory, irf):
    tmp = tmp_path_factory.mktemp("report_irf")
    data, d = response_profiles(irf, L, seed=3, delay_range_ps=(100, 160), echo_after_ps=90.0, noise=5.0, time_bin_ps=T)
    write_cube(tmp / "cube.zarr", data, time_bin_ps=T, chunks=(1, 3))
    decompose_to_store(tmp / "cube.zarr", tmp / "res.zarr", irf=irf, progress=False)
    decompose_to_store(tmp / "cube.zarr", tmp / "bare.zarr", irf=irf, write_components=False, progress=False)
    return tmp


def _peak(store):
    return float(np.nanmax(np.abs(store.group["direct"][...])))


def test_store_keeps_the_response_it_was_decomposed_with(stores, irf):
    store = open_result_store(stores / "res.zarr")
    kept = store.response()
    assert kept is not None and kept.time_step_ps == T
    # the response the solver used (cropped below 1e-7 of its peak): the model's samples
    assert np.allclose(kept.evaluate(kept.time_axis_ps()), irf.evaluate(kept.time_axis_ps()),
                       atol=1e-9 * irf.peak_per_ps)
    assert kept.model["name"] == "tailed" and kept.provenance["source"] == "model"
    assert store.verify().ok
    # readable without streaklab's code: dimension names and units in the arrays' attributes
    g = zarr.open_group(str(stores / "res.zarr" / RESPONSE_GROUP), mode="r")
    assert g.attrs["streaklab_kind"] == "instrument_response" and g.attrs["time_step_ps"] == T
    assert g["response"].metadata.dimension_names == ("irf_t",) and g["response"].attrs["units"] == "1/ps"
    assert g["irf_t"].attrs["units"] == "ps"
    assert np.sum(g["response"][...]) * T == pytest.approx(1.0, abs=1e-9)


def test_report_renders_fits_with_the_stored_response(stores):
    store = open_result_store(stores / "res.zarr")
    scale = _peak(store)
    every = slice(None)
    with_irf = rendered_components(store, every, every)
    gauss = rendered_components(store, every, every, irf=None)
    for key in ("direct", "sss", "ir"):
        stored = np.asarray(store.group[key][...], np.float64)
        # the stored model is float32: the re-render matches it to its rounding
        assert np.abs(with_irf[key] - stored).max() < 1e-6 * scale, key
    # the Gaussian of the same sigma does not reproduce the tailed direct reflection
    assert np.abs(gauss["direct"] - store.group["direct"][...]).max() > 0.02 * scale
    # one time of the frames figure renders the same values as the whole profile
    it = 60
    frame = rendered_components(store, every, every, it)
    assert np.allclose(frame["direct"], with_irf["direct"][..., it], atol=1e-9 * scale)
    assert np.allclose(frame["ir"], with_irf["ir"][..., it], atol=1e-9 * scale)


def _line(ax, label):
    return next(np.asarray(line.get_ydata(), np.float64) for line in ax.get_lines() if line.get_label() == label)


def test_profiles_figure_and_summary_of_a_store_without_components_use_the_response(stores):
    """Rendered from the parameters, the figure's fit is the model the decomposition stored
    (the store with components, same cube and settings) and its residual the data minus it."""
    bare = open_result_store(stores / "bare.zarr")
    full = open_result_store(stores / "res.zarr")
    scale = _peak(full)
    fig = profiles_figure(bare, [(1, 2)])
    ax = fig.axes[0]
    stored_fit = (full.group["direct"][1, 2] + full.group["sss"][1, 2]
                  + np.asarray(full.group["ir"][1, 2]).sum(axis=0)).astype(np.float64)
    assert np.abs(_line(ax, "sum of components") - stored_fit).max() < 1e-5 * scale
    assert np.abs(_line(ax, "residual") - np.asarray(full.group["residual"][1, 2], np.float64)).max() < 1e-5 * scale
    import matplotlib.pyplot as plt

    plt.close(fig)
    summary = summary_text(bare)
    assert "the tailed model response kept in the result store" in summary
    assert "fits drawn rendered from the parameters with it" in summary
    assert "the Gaussian PSF" not in summary
    assert "fits drawn from the stored components with it" in summary_text(full)


def test_store_without_the_response_still_reports(stores, tmp_path):
    """A store of an earlier release records the response (attrs) but holds no ``irf`` group:
    the report still runs, renders with the Gaussian PSF and says so."""
    every = slice(None)
    for name in ("res.zarr", "bare.zarr"):
        old = tmp_path / name
        shutil.copytree(stores / name, old)
        shutil.rmtree(old / RESPONSE_GROUP)
        store = open_result_store(old)
        assert store.response() is None and store.attrs["irf"]["kind"] == "response"
        assert store.verify().ok
        summary = summary_text(store)
        assert "records but does not hold" in summary
        if store.write_components:
            assert "fits drawn from the stored components" in summary
        else:
            assert "Gaussian PSF" in summary
            np.testing.assert_array_equal(rendered_components(store, every, every)["direct"],
                                          rendered_components(store, every, every, irf=None)["direct"])
            rep = make_report(old, tmp_path / "figs")
            assert rep["summary"].startswith(summary)
            assert all(f.exists() for f in rep["files"])


def test_a_response_that_is_not_the_recorded_one_is_refused(stores, tmp_path):
    changed = tmp_path / "changed.zarr"
    shutil.copytree(stores / "res.zarr", changed)
    g = zarr.open_group(str(changed), mode="r+")
    rec = dict(g.attrs["irf"])
    rec["samples_sha256"] = "0" * 64
    g.attrs["irf"] = rec
    with pytest.raises(ResultStoreError, match="not the response the store recorded"):
        open_result_store(changed).response()
