"""Material starts (decomposition.image.material): known answers on a small count image."""
from dataclasses import replace

import numpy as np

from core.model import render_components
from decomposition import decompose
from decomposition.evaluation.spatial_scenes import make_spatial_scene
from decomposition.image.material import material_estimate, material_starts
from decomposition.image.spatial import SpatialOptions, objective_weights, prepare_coupling, refit, take_rows
from decomposition.model.fidelity import fidelity

TB = 2.0


def _one_material(photons, seed=3):
    # the top-left patch of the spatial scene (material 0: sss peak ratio 0.3, decay 0.05 / ps,
    # onset 2 ps after the direct), 6 x 6 pixels of it
    scene = make_spatial_scene(12, 18, 256, photons_per_pixel=photons, seed=seed)
    return scene, np.asarray(scene.profiles)[:6, :6], {k: v[:6, :6] for k, v in scene.params.items()}


def _stripped(result, y, x):
    """``result`` with the pixel (y, x) with its sss taken out."""
    params = {k: np.array(v, copy=True) for k, v in result.params.items()}
    for k in ("sss_delay_ps", "sss_amplitude", "sss_alpha_per_ps", "sss_sigma_ps"):
        params[k][y, x] = np.nan
    return replace(result, params=params)


def _bare_coupling(cube, result, kw, y, x):
    """The coupling of ``result`` with the pixel (y, x) fitted again without an sss."""
    c = prepare_coupling(cube, _stripped(result, y, x), TB, "convscd", kw)
    row = np.array([y * cube.shape[1] + x])
    fit = refit(c, row, take_rows(c.params, row), objective_weights(c, c.params)[row])
    for k in c.params:
        c.params[k][row] = fit[k]
    return c, row


def _pixel_fidelity(scene, c, row):
    y, x = divmod(int(row[0]), 6)
    truth = {k: v[y:y + 1, x] for k, v in scene.components.items()}
    return fidelity(truth, render_components(take_rows(c.params, row), scene.profiles.shape[-1], TB, scene.t0_ps))[0]


def test_a_pixel_fitted_without_its_sss_gets_its_materials_sss_from_its_neighbours():
    scene, cube, truth = _one_material(3000.0)
    kw = {"t0_ps": scene.t0_ps, "noise": "poisson"}
    alone = decompose(cube, TB, **kw)
    assert np.all(alone.params["sss_amplitude"] > 0)             # every pixel kept its sss
    c, row = _bare_coupling(cube, alone, kw, 2, 3)
    f_bare = _pixel_fidelity(scene, c, row)
    material_starts(c, SpatialOptions())
    assert c.info["spatial_material_taken"] == 1 and c.params["sss_amplitude"][row[0]] > 0
    f_new = _pixel_fidelity(scene, c, row)
    # its split is closer to the truth's than the fit without the sss
    assert f_new > f_bare + 0.05


def test_a_pixel_whose_data_show_no_sss_keeps_its_fit_without_one():
    scene, cube, _ = _one_material(3000.0)
    kw = {"t0_ps": scene.t0_ps, "noise": "poisson"}
    # the pixel (2, 3) a direct alone, as bright as it was
    rng = np.random.default_rng(5)
    direct = scene.clean[2, 3] - scene.components["sss"][2, 3]
    cube = np.array(cube, copy=True)
    cube[2, 3] = rng.poisson(direct * scene.clean[2, 3].sum() / direct.sum())
    alone = decompose(cube, TB, **kw)
    c, _ = _bare_coupling(cube, alone, kw, 2, 3)
    before = {k: v.copy() for k, v in c.params.items()}
    material_starts(c, SpatialOptions())
    assert c.info["spatial_material_starts"] >= 1 and c.info["spatial_material_taken"] == 0
    assert np.isnan(c.params["sss_amplitude"].reshape(6, 6)[2, 3])
    np.testing.assert_array_equal(c.params["direct_delay_ps"], before["direct_delay_ps"])


def test_the_material_estimate_leaves_out_the_pixel_and_needs_one_material():
    # ln ratio of a 5 x 5 image: one material at -1.2 (standard errors 0.05), the centre with no
    # sss (NaN), the right column another material (-0.2)
    rng = np.random.default_rng(2)
    v = -1.2 + 0.05 * rng.standard_normal((5, 5))
    v[:, 4] = -0.2
    v[2, 2] = np.nan
    se = np.full((5, 5), 0.05)
    values = {n: (v.reshape(-1), se.reshape(-1), 0.05) for n in ("onset", "ratio", "alpha")}
    est = material_estimate(values, (5, 5), SpatialOptions(material_radius=1))
    mean, precision = (a.reshape(5, 5) for a in est["ratio"])
    assert precision[2, 2] > 0 and abs(mean[2, 2] + 1.2) < 0.05      # the bare pixel: its neighbours'
    assert precision[2, 0] > 0 and abs(mean[2, 0] + 1.2) < 0.05
    # next to the other material (column 3: 3 of 8 neighbours at -0.2) the majority's; the
    # right column's own neighbourhood is mostly the first material: its estimate is that one's,
    # which a pixel's own answer then refuses (neighbour_prior's own test), not this estimate
    assert abs(mean[2, 3] + 1.2) < 0.05
    est_none = material_estimate(values, (5, 5), SpatialOptions(material_radius=1, homogeneity_p=0.999999))
    assert np.all(est_none["ratio"][1] == 0)                         # no neighbourhood passes
