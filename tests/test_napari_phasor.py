"""streaklab.napari.phasor: the phasor plot's logic without Qt, and the widget once, headless."""
import os
from types import SimpleNamespace

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from decomposition.phasor import PhasorError, phasor_lifetime, semicircle, window_frequency_per_ps  # noqa: E402
from streaklab.napari.phasor import (  # noqa: E402
    SELECTION_LAYER, image_phasor, lifetime_ticks_ps, phasors_of_mask, pixels_in_circle, pixels_in_polygon,
    spatial_mask)

DT, L = 2.0, 128
F = window_frequency_per_ps(L, DT)


def decay(tau_ps, counts=1e3):
    edges = np.arange(L + 1) * DT
    return counts * np.diff(1.0 - np.exp(-edges / tau_ps))


def two_lifetime_cube():
    """(6, 8, L): columns 0-3 at 20 ps, 4-7 at 200 ps; row 5 an unfinished line (NaN)."""
    cube = np.empty((6, 8, L), dtype=np.float32)
    cube[:, :4] = decay(20.0)
    cube[:, 4:] = decay(200.0)
    cube[5] = np.nan
    return cube


def tau_point(tau_ps):
    g, s = semicircle(lifetimes_ps=tau_ps, frequency_per_ps=F)
    return float(g), float(s)


# ---------------------------------------------------------------------------------------------
# the logic, without Qt
# ---------------------------------------------------------------------------------------------
def test_image_phasor_gives_each_pixel_its_lifetime_and_nan_for_a_nan_line():
    g, s = image_phasor(two_lifetime_cube(), DT)
    assert g.shape == (6, 8)
    assert np.isnan(g[5]).all() and np.isnan(s[5]).all()
    tau, _ = phasor_lifetime(g[:5], s[:5], F)
    np.testing.assert_allclose(tau[:, :4], 20.0, rtol=0.01)
    np.testing.assert_allclose(tau[:, 4:], 200.0, rtol=0.01)
    g0, s0 = image_phasor(np.moveaxis(two_lifetime_cube(), -1, 0), DT, time_axis=0)
    np.testing.assert_array_equal(g0, g)
    np.testing.assert_array_equal(s0, s)


def test_a_circle_and_a_polygon_select_the_pixels_of_one_lifetime():
    g, s = image_phasor(two_lifetime_cube(), DT)
    expected = np.zeros((6, 8), dtype=bool)
    expected[:5, :4] = True
    np.testing.assert_array_equal(pixels_in_circle(g, s, tau_point(20.0), 0.03), expected)
    gc, sc = tau_point(20.0)
    square = [(gc - 0.02, sc - 0.02), (gc + 0.02, sc - 0.02), (gc + 0.02, sc + 0.02), (gc - 0.02, sc + 0.02)]
    np.testing.assert_array_equal(pixels_in_polygon(g, s, square), expected)
    assert not pixels_in_circle(g, s, (0.1, 0.6), 0.03).any()


def test_a_pixel_mask_gives_its_pixels_phasors():
    g, s = image_phasor(two_lifetime_cube(), DT)
    mask = np.zeros((6, 8), dtype=bool)
    mask[3:, 5:7] = True  # 6 pixels, 2 of them on the NaN line
    hg, hs = phasors_of_mask(g, s, mask)
    assert hg.shape == hs.shape == (4,)
    np.testing.assert_allclose(phasor_lifetime(hg, hs, F)[0], 200.0, rtol=0.01)


def test_a_selection_of_the_image_shape_is_reduced_over_time():
    sel = np.zeros((6, 8, L), dtype=np.int32)
    sel[2, 3, 17] = 4
    mask = spatial_mask(sel, (6, 8, L), time_axis=-1)
    assert mask.shape == (6, 8) and mask.sum() == 1 and mask[2, 3]
    assert spatial_mask(sel[..., 17], (6, 8, L)).sum() == 1
    assert spatial_mask(np.moveaxis(sel, -1, 0), (L, 6, 8), time_axis=0)[2, 3]


def test_lifetime_ticks_span_the_semicircle():
    ticks = lifetime_ticks_ps(F)
    wt = 2 * np.pi * F * ticks
    assert ticks.size >= 5 and wt.min() >= 0.1 and wt.max() <= 10
    assert 20.0 in ticks and 200.0 in ticks


@pytest.mark.parametrize("call, message", [
    (lambda g, s: pixels_in_circle(g, s, (0.5, 0.3), 0.0), "positive radius"),
    (lambda g, s: pixels_in_polygon(g, s, [(0, 0), (1, 0)]), "at least 3 finite"),
    (lambda g, s: phasors_of_mask(g, s, np.ones((8, 6), bool)), "does not match the phasor image"),
    (lambda g, s: spatial_mask(np.ones((6, 7)), (6, 8, L)), "fits neither the image"),
    (lambda g, s: image_phasor(np.ones((6, 8, L), complex), DT), "must be real numbers"),
])
def test_bad_selections_get_a_clear_error(call, message):
    g, s = image_phasor(two_lifetime_cube(), DT)
    with pytest.raises(PhasorError, match=message):
        call(g, s)


# ---------------------------------------------------------------------------------------------
# the widget, headless
# ---------------------------------------------------------------------------------------------
def test_the_widget_links_plot_and_image_both_ways():
    from napari.components import ViewerModel
    from qtpy.QtWidgets import QApplication

    from streaklab.napari.phasor import PhasorWidget

    app = QApplication.instance() or QApplication([])
    viewer = ViewerModel()
    cube = two_lifetime_cube()
    viewer.add_image(cube, name="cube", metadata={"time_bin_ps": DT})
    widget = PhasorWidget(viewer)
    assert widget.image_combo.currentText() == "cube"
    g, s = widget.compute()
    assert "40 of 48 pixels" in widget.status.text()

    # plot -> image: a circle around 200 ps marks columns 4-7 of the finite rows, in every time plane
    widget.select_region(tau_point(200.0), 0.03)
    labels = viewer.layers[SELECTION_LAYER]
    assert labels.data.shape == cube.shape
    expected = np.zeros((6, 8), dtype=bool)
    expected[:5, 4:] = True
    np.testing.assert_array_equal(labels.data[..., 0] == 1, expected)
    np.testing.assert_array_equal(labels.data[..., L - 1] == 1, expected)
    # the mouse: press at the 20 ps point, release 0.03 away
    gc, sc = tau_point(20.0)
    widget._on_press(SimpleNamespace(inaxes=widget.axes, xdata=gc, ydata=sc))
    widget._on_release(SimpleNamespace(inaxes=widget.axes, xdata=gc + 0.03, ydata=sc))
    np.testing.assert_array_equal(viewer.layers[SELECTION_LAYER].data[..., 5] == 1, ~expected & np.isfinite(g))
    assert len([ly for ly in viewer.layers if ly.name == SELECTION_LAYER]) == 1

    # image -> plot: a painted Labels layer highlights its pixels' phasors
    painted = np.zeros(cube.shape, dtype=np.uint8)
    painted[1:3, 0:2, 10] = 1
    viewer.add_labels(painted, name="painted")
    assert "painted" in [widget.selection_combo.itemText(i) for i in range(widget.selection_combo.count())]
    widget.selection_combo.setCurrentText("painted")
    hg, hs = widget.highlight_layer()
    assert hg.size == 4
    np.testing.assert_allclose(phasor_lifetime(hg, hs, F)[0], 20.0, rtol=0.01)

    # a Shapes rectangle over a (t, y, x) image, drawn in the plane t = 0
    viewer.add_image(np.moveaxis(cube, -1, 0), name="cube t-first", metadata={"time_bin_ps": DT})
    widget.time_axis.setValue(0)
    widget.image_combo.setCurrentText("cube t-first")
    widget.compute()
    shapes = viewer.add_shapes([np.array([[0, 0, 5.6], [0, 0, 7.4], [0, 4.4, 7.4], [0, 4.4, 5.6]])],
                               shape_type="rectangle", name="box")
    hg, hs = widget.highlight_layer(shapes)
    assert hg.size == 10  # rows 0-4, columns 6-7
    np.testing.assert_allclose(phasor_lifetime(hg, hs, F)[0], 200.0, rtol=0.01)
    widget.mode.setCurrentIndex(1)  # the polygon selector arms without error
    assert widget._polygon_selector is not None
    widget.close()
    app.processEvents()
