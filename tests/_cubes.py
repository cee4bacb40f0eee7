"""Small synthetic cubes shared by the chunked-decomposition tests."""
import numpy as np

from decomposition.evaluation.synthetic import make_profiles, render_bin_integrated
from decomposition.evaluation.synthetic_noise import add_noise

from core import model

TB = 2.0


def small_cube(ny, nx, nt=128, seed=0, nsr=0.01):
    """Profiles with a direct reflection, sss on half the pixels and an inter-reflection on a third."""
    rng = np.random.default_rng(seed)
    p = model.empty_params((ny, nx), 1)
    p["direct_delay_ps"] = rng.uniform(30, 60, (ny, nx))
    p["direct_amplitude"] = rng.uniform(0.5, 2.0, (ny, nx))
    p["direct_sigma_ps"] = rng.uniform(2.5, 4.0, (ny, nx))
    s = rng.random((ny, nx)) < 0.5
    p["sss_delay_ps"] = np.where(s, p["direct_delay_ps"], np.nan)
    p["sss_amplitude"] = np.where(s, rng.uniform(0.02, 0.05, (ny, nx)), np.nan)
    p["sss_alpha_per_ps"] = np.where(s, rng.uniform(0.01, 0.05, (ny, nx)), np.nan)
    p["sss_sigma_ps"] = np.where(s, p["direct_sigma_ps"], np.nan)
    r = rng.random((ny, nx)) < 0.33
    p["ir_delay_ps"][..., 0] = np.where(r, p["direct_delay_ps"] + rng.uniform(60, 120, (ny, nx)), np.nan)
    p["ir_amplitude"][..., 0] = np.where(r, rng.uniform(0.3, 0.8, (ny, nx)), np.nan)
    p["ir_sigma_ps"][..., 0] = np.where(r, p["direct_sigma_ps"], np.nan)
    clean = model.render_profile(p, nt, TB)
    noise = rng.standard_normal(clean.shape)
    noise *= nsr * np.linalg.norm(clean, axis=-1, keepdims=True) / np.linalg.norm(noise, axis=-1, keepdims=True)
    return (clean + noise).astype(np.float32)


def response_profiles(irf, n_bins, *, seed, delay_range_ps, echo_after_ps, noise, time_bin_ps=2.0, shape=(2, 3)):
    """Counts-scaled profiles (float32, ``shape`` + (n_bins,)) of a direct, an echo at 0.4 of it
    ``echo_after_ps`` later and a faint sss (alpha 0.03/ps), all shaped by the instrument
    response ``irf``, plus white noise of standard deviation ``noise`` (peak ~1000)
    -> (profiles, direct delays (ps) ``shape``)."""
    from core.irf import render_shifted, render_sss

    rng = np.random.default_rng(seed)
    t = time_bin_ps + time_bin_ps * np.arange(n_bins)
    d = rng.uniform(*delay_range_ps, shape)
    clean = (render_shifted(irf, t, d) + 0.4 * render_shifted(irf, t, d + echo_after_ps)
             + 0.03 * render_sss(irf, t, d, np.full(d.shape, 0.03)))
    return (1000.0 * clean + noise * rng.standard_normal(clean.shape)).astype(np.float32), d


def smooth_scene(n=12, nt=128, nsr=0.11, seed=0, step_ps=12.0):
    """An n x n image: the Fig. 3 kinds drawn per pixel, the direct delay a gentle ramp with a
    step of ``step_ps`` between columns n/2 - 1 and n/2 (every component moved with it),
    bin-integrated, white noise at ``nsr`` -> (cube, truth params, truth components, edge mask)."""
    d = make_profiles(n * n, nt, seed=seed, time_bin_ps=TB)
    p = {k: v.copy() for k, v in d.params.items()}
    yy, xx = np.mgrid[0:n, 0:n]
    shift = (60.0 + 0.6 * yy + 0.4 * xx + np.where(xx >= n // 2, step_ps, 0.0)).reshape(-1) - p["direct_delay_ps"]
    for key in ("direct_delay_ps", "sss_delay_ps"):
        p[key] = p[key] + shift
    p["ir_delay_ps"] = p["ir_delay_ps"] + shift[:, None]
    comps = render_bin_integrated(p, nt, TB, TB)
    clean = comps["direct"] + comps["sss"] + comps["interreflections"].sum(axis=-2)
    noisy = add_noise(clean, nsr, "white", rng=np.random.default_rng(seed + 100))

    def img(a):
        return a.reshape((n, n) + a.shape[1:])

    edge = (xx == n // 2) | (xx == n // 2 - 1)
    return img(noisy), {k: img(v) for k, v in p.items()}, {k: img(v) for k, v in comps.items()}, edge


def worker_dies_at(monkeypatch, call: int):
    """Make the chunked pipeline's solver raise RuntimeError("worker died") on its ``call``-th
    chunk (1-based) and on none before it, as a worker killed mid-run; returns the function that
    puts the real solver back."""
    import decomposition.store.chunked as chunked

    real, calls = chunked.solve_block, []

    def dying(*args, **kwargs):
        calls.append(1)
        if len(calls) >= call:
            raise RuntimeError("worker died")
        return real(*args, **kwargs)

    monkeypatch.setattr(chunked, "solve_block", dying)
    return lambda: monkeypatch.setattr(chunked, "solve_block", real)
