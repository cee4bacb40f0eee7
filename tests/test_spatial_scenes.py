"""Spatially structured synthetic images (decomposition.evaluation.spatial_scenes)."""
import numpy as np
import pytest

from core.model import render_components
from decomposition.evaluation.spatial_scenes import edge_mask, make_spatial_scene
from decomposition.evaluation.synthetic import render_bin_integrated


def test_shapes_regions_and_one_instrument():
    s = make_spatial_scene(12, 16, 256, nsr=0.1, echo_ratio=0.01, seed=3)
    assert s.profiles.shape == s.clean.shape == (12, 16, 256)
    assert s.params["direct_delay_ps"].shape == (12, 16) and s.params["ir_delay_ps"].shape == (12, 16, 1)
    assert s.edges.shape == (12, 16) and s.edges.dtype == bool
    # one PSF width everywhere, the echo at 1 % of the direct, the regions disjoint
    assert np.all(s.params["direct_sigma_ps"] == 4.0)
    e = s.regions["echo"]
    assert e.any() and np.allclose(s.params["ir_amplitude"][e, 0], 0.01 * s.params["direct_amplitude"][e])
    assert not np.any(e & s.regions["corner"])
    assert np.all(np.isfinite(s.params["ir_delay_ps"][..., 0]) == (e | s.regions["corner"]))
    # the depth steps at the middle column: the far plane later by ~STEP_PS
    d = s.params["direct_delay_ps"]
    assert d[0, 8] - d[0, 7] > 30.0
    # white noise at the exact NSR of every pixel
    nsr = np.linalg.norm(s.profiles - s.clean, axis=-1) / np.linalg.norm(s.clean, axis=-1)
    assert np.allclose(nsr, 0.1)


@pytest.mark.parametrize("counts", [False, True])
def test_truth_renders_to_the_noiseless_profiles(counts):
    kw = dict(photons_per_pixel=500.0) if counts else dict(nsr=0.0, noise="none")
    s = make_spatial_scene(8, 10, 200, echo_ratio=0.02, seed=1, **kw)
    render = render_bin_integrated(s.params, 200, 2.0, s.t0_ps) if s.bin_integrated else \
        render_components(s.params, 200, 2.0, s.t0_ps)
    total = render["direct"] + render["sss"] + render["interreflections"].sum(axis=-2)
    assert s.bin_integrated == counts
    np.testing.assert_allclose(total, s.clean, rtol=1e-9, atol=1e-12 * s.clean.max())
    if counts:
        assert s.profiles.dtype == np.int64
        assert abs(s.clean.sum(axis=-1).mean() - 500.0) < 1e-6
    else:
        assert np.array_equal(s.profiles, s.clean)


def test_edge_mask_on_a_known_layout():
    depth = np.zeros((5, 6), int)
    depth[:, 3:] = 1                   # a vertical edge between columns 2 and 3
    material = np.zeros((5, 6), int)
    material[4, 0] = 2                 # one odd pixel in a corner
    m = edge_mask(depth, material)
    want = np.zeros((5, 6), bool)
    want[:, 2:4] = True
    want[3:5, 0:2] = True              # the odd pixel and its 8-neighbours
    assert np.array_equal(m, want)
    with pytest.raises(ValueError, match="label images"):
        edge_mask(depth, material[:4])


def test_scene_edges_lie_on_the_step_and_the_patches():
    s = make_spatial_scene(16, 16, 256, seed=0)
    assert np.all(s.edges[:, 7:9])                          # the depth step at column 8
    assert np.all(s.edges[7:9, :])                          # the material boundary at row 8
    assert not s.edges[2, 2] and not s.edges[12, 12]


def test_seeds_reproducible_and_bad_input_named():
    a = make_spatial_scene(8, 8, 256, nsr=0.2, seed=7)
    b = make_spatial_scene(8, 8, 256, nsr=0.2, seed=7)
    c = make_spatial_scene(8, 8, 256, nsr=0.2, seed=8)
    assert np.array_equal(a.profiles, b.profiles) and not np.array_equal(a.profiles, c.profiles)
    with pytest.raises(ValueError, match="8 x 8"):
        make_spatial_scene(4, 8)
    with pytest.raises(ValueError, match="more bins"):
        make_spatial_scene(8, 8, 60, echo_ratio=0.01)
    with pytest.raises(ValueError, match="photons_per_pixel"):
        make_spatial_scene(8, 8, 256, nsr=0.1, photons_per_pixel=100)
