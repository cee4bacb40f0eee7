import numpy as np

import decomposition
from decomposition import flags as fl


def test_bit_values_are_those_of_existing_stores():
    # the on-disk format: these values are written into every result store's flags array
    want = {"EMPTY": 1, "SATURATED": 2, "POOR_FIT": 4, "SPIKE": 8, "NONFINITE": 16, "MAX_ITER": 32,
            "AT_BOUND": 64, "TRUNCATED": 128, "AMBIGUOUS": 512,
            "WIDE_PSF": 1024, "OFF_WINDOW": 2048}
    assert {f.name: int(f) for f in fl.Flag} == want
    assert fl.FLAG_NAMES == {v: k for k, v in want.items()}
    for name, v in want.items():          # the old names stay importable from the package
        assert int(getattr(decomposition, name)) == v


def test_mark_keeps_the_dtype_and_names_read_back():
    flags = np.zeros(3, fl.FLAG_DTYPE)
    fl.mark(flags, [0, 2], fl.SATURATED)
    fl.mark(flags, np.array([False, False, True]), fl.TRUNCATED)
    assert flags.dtype == np.uint16 and flags.tolist() == [2, 0, 130]
    fl.mark(flags, [1], fl.AMBIGUOUS)
    assert flags.tolist() == [2, 512, 130] and fl.flag_names(flags[1]) == ["AMBIGUOUS"]
    assert fl.flag_names(flags[2]) == ["SATURATED", "TRUNCATED"]
    assert fl.Flag(int(flags[2])) == fl.Flag.SATURATED | fl.Flag.TRUNCATED


def test_no_solver_bit_collides_with_the_result_store_bit():
    from decomposition.store.resultstore import OUT_OF_RANGE

    assert all(int(f) & OUT_OF_RANGE == 0 for f in fl.Flag)
    assert max(int(f) for f in fl.Flag) <= np.iinfo(fl.FLAG_DTYPE).max


def test_wide_psf_flags_a_width_above_the_kernel_grid_only():
    from core.model import empty_params, render_profile

    p = empty_params((2,), n_ir=1)
    p["direct_delay_ps"][:] = 200.0
    p["direct_amplitude"][:] = 1.0
    p["direct_sigma_ps"][:] = [5.0, 18.0]          # the grid spans 1-10 ps
    y = render_profile(p, 512, 2.0) + np.random.default_rng(0).normal(0, 1e-3, (2, 512))
    res = decomposition.decompose(y, 2.0, components="d")
    np.testing.assert_allclose(res.params["direct_sigma_ps"], [5.0, 18.0], rtol=0.02)
    assert [bool(f & fl.WIDE_PSF) for f in res.flags] == [False, True]
