"""Compiled scalar kernels (decomposition.kernels.jit) against scipy and core.model, and their disk cache."""
from pathlib import Path

import numpy as np
import pytest
from scipy import special

from decomposition.kernels import jit
from core.model import sss_kernel


def test_erfcx_matches_scipy_across_the_series_switch_and_far_tail():
    u = np.concatenate([np.linspace(0.0, 12.0, 2401), np.geomspace(12.0, 1e150, 400)])
    got = np.array([jit.erfcx(v) for v in u])
    ref = special.erfcx(u)
    np.testing.assert_allclose(got, ref, rtol=2e-14, atol=0)
    assert np.all(np.isfinite(got)) and np.all(got > 0)


def test_erfcx_table_holds_its_accuracy_on_every_interval_and_at_their_edges():
    """The table's polynomials (one per half unit of u below 10) against scipy on a dense grid,
    at every interval's ends from both sides, and at the hand-over to the series at u = 10."""
    edges = np.arange(0.0, 10.0 + 1e-9, jit._ERFCX_STEP)
    u = np.concatenate([np.linspace(0.0, 10.0, 200001), edges, np.nextafter(edges, -1.0)[1:],
                        np.nextafter(edges, 20.0), [np.nextafter(10.0, 0.0), 10.0]])
    got = np.array([jit.erfcx(v) for v in u])
    np.testing.assert_allclose(got, special.erfcx(u), rtol=1e-14, atol=0)
    assert jit.erfcx(0.0) == pytest.approx(1.0, rel=1e-15)
    assert np.isnan(jit.erfcx(np.nan))
    # negative arguments keep exp(u^2) erfc(u)
    neg = np.linspace(-5.0, -1e-3, 101)
    np.testing.assert_allclose([jit.erfcx(v) for v in neg], special.erfcx(neg), rtol=1e-13)


@pytest.mark.parametrize("sigma_ps, alpha_per_ps", [(0.5, 1e-4), (3.0, 0.02), (10.0, 0.05), (2.0, 5.0)])
def test_sss_erfc_part_is_f_erfc_on_both_sides_of_u_0(sigma_ps, alpha_per_ps):
    """g erfcx(u) (u >= 0) and 2 f - g erfcx(-u) (u < 0) are f erfc(u), f = g exp(u^2), to
    rounding, from far before the onset to where erfc(u) is 2 -- the values the compiled atoms
    and the pick's kernels take per sample."""
    x = np.linspace(-8.0 * sigma_ps, alpha_per_ps * sigma_ps ** 2 + 6.0 * sigma_ps, 2001)
    u = (alpha_per_ps * sigma_ps ** 2 - x) / (sigma_ps * np.sqrt(2.0))
    g = np.exp(-0.5 * (x / sigma_ps) ** 2)
    f = np.exp(0.5 * (alpha_per_ps * sigma_ps) ** 2 - alpha_per_ps * x)
    got = np.array([jit.sss_erfc_part(a, b, c) for a, b, c in zip(u, g, f)])
    want = np.where(u >= 0, g * special.erfcx(np.maximum(u, 0.0)), f * special.erfc(u))
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
    assert (u < 0).any() and (u > 0).any()


@pytest.mark.parametrize("sigma_ps, alpha_per_ps", [(0.5, 1e-6), (3.0, 0.02), (10.0, 0.05), (2.0, 50.0)])
def test_sss_value_matches_the_forward_model(sigma_ps, alpha_per_ps):
    x = np.linspace(-8.0 * sigma_ps, 40.0 * sigma_ps, 501)
    with np.errstate(all="raise"):
        h = np.array([jit.sss_value(v, sigma_ps, alpha_per_ps)[0] for v in x])
        g = np.array([jit.sss_value(v, sigma_ps, alpha_per_ps)[1] for v in x])
    np.testing.assert_allclose(h, sss_kernel(x, sigma_ps, alpha_per_ps), rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(g, np.exp(-0.5 * (x / sigma_ps) ** 2), rtol=1e-15, atol=0)


def test_a_kernel_without_a_cache_location_still_compiles():
    """Code with no source file (or no writable cache directory) gets no disk cache, not an error."""
    ns = {"jit": jit}
    exec("@jit.njit\ndef twice(x):\n    return 2.0 * x\n", ns)
    assert ns["twice"](1.5) == 3.0


def _run_kernel(root, repo, code=None):
    import os
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), str(repo)]))
    env.pop("NUMBA_CACHE_DIR", None)
    code = code or ("import kpkg.kern as k\n"
                    "print(k.level(), sum(k.level.stats.cache_hits.values()), sum(k.level.stats.cache_misses.values()))")
    out = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    value, hits, misses = out.stdout.split()
    return float(value), int(hits), int(misses)


def test_a_changed_constant_compiles_the_kernels_that_read_it_afresh(tmp_path):
    """numba keys its disk cache on a kernel's own file; a constant it reads from constants.py
    is frozen into the cached code.  The kernels' stamp covers the folder's constants and
    kernel modules, so a changed constant is never served from a stale cache."""
    repo = Path(jit.__file__).resolve().parents[2]
    pkg = tmp_path / "kpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "constants.py").write_text("LEVEL = 1.0\n")
    (pkg / "kern.py").write_text("from decomposition.kernels.jit import njit\nfrom .constants import LEVEL\n\n\n"
                                 "@njit\ndef level():\n    return LEVEL\n")
    assert _run_kernel(tmp_path, repo) == (1.0, 0, 1)          # compiled, written to the cache
    assert _run_kernel(tmp_path, repo) == (1.0, 1, 0)          # loaded from the cache
    digest = jit.kernel_digest(str(pkg))
    (pkg / "constants.py").write_text("LEVEL = 2.0\n")
    jit.kernel_digest.cache_clear()
    assert jit.kernel_digest(str(pkg)) != digest
    assert _run_kernel(tmp_path, repo) == (2.0, 0, 1)          # the stale entry is not used
    assert _run_kernel(tmp_path, repo) == (2.0, 1, 0)
    (pkg / "notes.py").write_text("WORDS = 'no kernel here'\n")  # a module without kernels: no new stamp
    jit.kernel_digest.cache_clear()
    assert _run_kernel(tmp_path, repo) == (2.0, 1, 0)


def test_a_changed_constant_of_the_package_compiles_a_subfolders_kernels_afresh(tmp_path):
    """Kernels in a subfolder (``decomposition/kernels/``) read the constants of the package
    above it (``decomposition/constants.py``): the stamp covers the whole package tree."""
    repo = Path(jit.__file__).resolve().parents[2]
    pkg = tmp_path / "kpkg"
    (pkg / "kern").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "constants.py").write_text("LEVEL = 1.0\n")
    (pkg / "kern" / "__init__.py").write_text("")
    (pkg / "kern" / "level.py").write_text("from decomposition.kernels.jit import njit\nfrom ..constants import LEVEL\n\n\n"
                                           "@njit\ndef level():\n    return LEVEL\n")
    code = ("import kpkg.kern.level as k\n"
            "print(k.level(), sum(k.level.stats.cache_hits.values()), sum(k.level.stats.cache_misses.values()))")
    assert _run_kernel(tmp_path, repo, code) == (1.0, 0, 1)
    assert _run_kernel(tmp_path, repo, code) == (1.0, 1, 0)
    assert jit.kernel_digest(str(pkg / "kern")) == jit.kernel_digest(str(pkg))
    (pkg / "constants.py").write_text("LEVEL = 2.0\n")
    assert _run_kernel(tmp_path, repo, code) == (2.0, 0, 1)          # the stale entry is not used


def test_the_solvers_kernels_are_cached_under_the_folders_digest():
    from decomposition.kernels import atomlm

    assert atomlm._gauss_support._cache is not None
    locator = atomlm._gauss_support._cache._impl.locator
    assert type(locator).__name__.startswith("Kernel")
    stamp = locator.get_source_stamp()
    assert stamp[1] == jit.kernel_digest(str(Path(atomlm.__file__).parent))


def test_without_a_stamped_cache_kernels_are_compiled_not_cached(tmp_path, monkeypatch):
    """Where numba's cache cannot carry the folder's digest, a kernel is compiled per process:
    nothing is written that a later, changed build could load."""
    import importlib.util

    monkeypatch.setattr(jit, "_LOCATORS", None)
    src = tmp_path / "kmod.py"
    src.write_text("from decomposition.kernels.jit import njit\nLEVEL = 3.0\n\n\n@njit\ndef level():\n    return LEVEL\n")
    spec = importlib.util.spec_from_file_location("kmod_uncached", src)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.level() == 3.0
    assert type(mod.level._cache).__name__ == "NullCache"
    assert not list(tmp_path.rglob("*.nbi"))


def test_no_call_site_hands_a_kernel_a_read_only_array():
    """numba types a read-only array (a broadcast view) as a type of its own: a kernel handed one
    where other calls hand a writable array compiled, and cached, a second time (the refine's
    loop was compiled in four signatures over the suite, the Fisher Gram product in two, the
    count fit in two).  ``kernel_array`` hands them writable C arrays; after decompositions that
    take every path of those kernels (Gaussian PSF with an offset, held widths' refits and
    standard errors; a response on floats and on counts; an image with a shared PSF), no
    signature of theirs holds a read-only array outside the instrument's frozen table."""
    from core.irf_models import tailed_response
    from decomposition import decompose
    from decomposition.evaluation.synthetic import make_cube, make_profiles
    from decomposition.image import decompose_image
    from decomposition.kernels import countlm, jit, projected, projlm

    a = np.broadcast_to(np.arange(4.0), (4,))
    assert not a.flags.writeable and jit.kernel_array(a, np.float64).flags.writeable
    b = np.arange(4.0)
    assert jit.kernel_array(b, np.float64) is b                     # nothing copied that need not be
    irf = tailed_response(4.0, 0.2, 30.0, time_step_ps=2.0)
    d = make_profiles(12, 256, nsr=0.05, seed=3)
    decompose(d.noisy, 2.0, components="d,r,s,b", refine=True, stderr=True)
    r = make_profiles(12, 512, nsr=0.05, seed=3, response=irf, ranges="paper")
    decompose(r.noisy, 2.0, irf=irf, stderr=True)
    c = make_profiles(12, 512, seed=3, response=irf, ranges="paper", photons_per_pixel=300.0)
    decompose(c.noisy, 2.0, irf=irf, components="d,r,s,b")
    decompose_image(make_cube(3, 6, 256, nsr=0.05, seed=1).noisy, 2.0, shared="psf")
    for kernel in (projlm.projected_lm, projected.fisher_gram, countlm.count_lm):
        assert kernel.signatures, kernel
        for sig in kernel.signatures:
            plain = [str(t) for t in sig if not str(t).startswith("Tuple(")]   # the instrument is frozen
            assert not any("readonly" in t for t in plain), (kernel, plain)
