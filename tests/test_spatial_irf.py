"""Spatial coupling with a measured instrument response (``decompose_image(spatial=True, irf=...)``):
the neighbour starts, the joint refinement with its priors, the pooled echoes and the errors read
the response's atoms (the refinement's engine with the response's table, decomposition.model.refine's
``irf``).  Known answers: images rendered through the response from known parameters."""
import threading

import numpy as np
import pytest

from _cubes import smooth_scene
from core.irf_models import tailed_response
from decomposition.image import decompose_image
from decomposition.kernels.response import response_table, shifted_atoms
from decomposition.model.atoms import params_components, params_profile
from decomposition.store.chunked import chunk_tasks, run_tasks

T = 2.0
L = 256
T_PS = T + T * np.arange(L)


@pytest.fixture(scope="module")
def irf():
    return tailed_response(4.0, 0.2, 30.0, time_step_ps=T)


def _scene(irf, n, nsr, seed):
    """An n x n image of smooth_scene's parameters (a delay ramp with a 12 ps step), rendered
    through ``irf`` on L bins, white noise ``nsr`` of each pixel's peak -> (image, truth)."""
    truth = {k: np.asarray(v, np.float64) for k, v in smooth_scene(n=n, nt=L, nsr=0.0, seed=seed)[1].items()}
    clean = params_profile(irf, T_PS, truth)
    noise = nsr * clean.max(axis=-1, keepdims=True) * np.random.default_rng(seed + 1).standard_normal(clean.shape)
    return clean + noise, truth


def _fidelity(irf, params, truth):
    got, want = params_components(irf, T_PS, params), params_components(irf, T_PS, truth)
    err = sum(((got[k] - want[k]) ** 2).sum(axis=tuple(range(2, got[k].ndim))) for k in ("direct", "sss"))
    err = err + ((got["interreflections"].sum(axis=-2) - want["interreflections"].sum(axis=-2)) ** 2).sum(-1)
    total = params_profile(irf, T_PS, truth)
    return 1.0 - err / (total ** 2).sum(-1)


@pytest.mark.parametrize("nsr", [0.11, 0.22])
def test_spatial_beats_per_pixel_with_a_measured_response(irf, nsr):
    image, truth = _scene(irf, 10, nsr, seed=3)
    per = decompose_image(image, T, irf=irf)
    spa = decompose_image(image, T, irf=irf, spatial=True, stderr=True)
    rmse = {name: np.sqrt(np.nanmean((r.params["direct_delay_ps"] - truth["direct_delay_ps"]) ** 2))
            for name, r in (("per", per), ("spatial", spa))}
    assert rmse["spatial"] < 0.9 * rmse["per"]
    assert _fidelity(irf, spa.params, truth).mean() > _fidelity(irf, per.params, truth).mean()
    # the answer is the response's: its width the response's Gaussian-equivalent one, as the
    # per-pixel path reports it; its errors finite where the pixel's data decide
    sig = np.asarray(spa.params["direct_sigma_ps"])
    assert np.allclose(sig[np.isfinite(sig)], np.nanmax(np.asarray(per.params["direct_sigma_ps"])))
    assert np.isfinite(spa.params["direct_delay_ps_stderr"]).mean() > 0.9
    assert spa.info["spatial"]["spatial_refits"] > 0


def test_chunks_with_the_halo_equal_one_call_with_a_measured_response(irf):
    image, _ = _scene(irf, 8, 0.11, seed=5)
    ref = decompose_image(image, T, irf=irf, spatial=True, max_reflections=2)
    shapes = {"direct_delay_ps": (), "direct_amplitude": (), "sss_delay_ps": (), "sss_amplitude": (),
              "sss_alpha_per_ps": (), "ir_delay_ps": (2,), "ir_amplitude": (2,), "direct_sigma_ps": (),
              "sss_sigma_ps": (), "ir_sigma_ps": (2,)}
    sunk, lock = {}, threading.Lock()

    def sink(iy, ix, result):
        with lock:
            sunk[(iy, ix)] = result

    run_tasks(chunk_tasks(image, chunks=(4, 4), sink=sink, param_shapes=shapes, time_bin_ps=T, n_ir=2,
                          options={"max_reflections": 2, "irf": irf}, spatial=True), num_workers=1)
    for k in shapes:
        got = np.concatenate([np.concatenate([np.asarray(sunk[(i, j)]["params"][k]) for j in range(2)], axis=1)
                              for i in range(2)])
        want = np.asarray(ref.params[k], np.float64)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=k)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9, err_msg=k)


def test_a_pooled_echo_is_the_shifted_response(irf):
    """A 1 % echo 60 ps after the direct, about 1.3 noise sigmas in one pixel and 5 pooled over
    5 x 5: found where the pool sees it, at its delay, as an inter-reflection of the response
    (no width)."""
    n = 9
    truth = {k: np.asarray(v, np.float64) for k, v in smooth_scene(n=n, nt=L, nsr=0.0, seed=8)[1].items()}
    for key in ("ir_delay_ps", "ir_amplitude", "ir_sigma_ps"):
        truth[key] = np.full((n, n, 1), np.nan)
    truth["sss_amplitude"][:] = np.nan
    truth["sss_delay_ps"][:] = np.nan
    truth["sss_alpha_per_ps"][:] = np.nan
    truth["direct_amplitude"][:] = 1.0
    truth["ir_delay_ps"][..., 0] = truth["direct_delay_ps"] + 60.0
    truth["ir_amplitude"][..., 0] = 0.01
    clean = params_profile(irf, T_PS, truth)
    # the echo 1.3 noise sigmas in one pixel (its matched filter's), about 6.5 in the sum of 25
    atom = shifted_atoms(response_table(irf), T_PS, np.array([100.0]))[0]
    sigma = 0.01 * np.sqrt((atom ** 2).sum()) / 1.3
    image = clean + sigma * np.random.default_rng(9).standard_normal(clean.shape)
    res = decompose_image(image, T, irf=irf, spatial=True, components="d,r")
    ir = np.asarray(res.params["ir_delay_ps"], np.float64)
    found = np.isfinite(ir).any(axis=-1)
    assert res.info["pooled_echoes"] > 0 and found[2:-2, 2:-2].mean() > 0.5
    near = np.nanmin(np.abs(ir[found] - truth["ir_delay_ps"][found]), axis=-1)
    assert near.max() < 2.0 * T
    # one pixel alone does not see it
    per = decompose_image(image, T, irf=irf, components="d,r")
    assert np.isfinite(np.asarray(per.params["ir_delay_ps"])).any(axis=-1).mean() < 0.2
    assert np.array_equal(np.isfinite(np.asarray(res.params["ir_sigma_ps"])), np.isfinite(ir))
