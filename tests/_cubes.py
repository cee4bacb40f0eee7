"""Small synthetic cubes shared by the chunked-decomposition tests."""
import numpy as np

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
