"""Compiled response atoms (decomposition.kernels.response) against the exact interpolant of
core.irf, and their derivatives against finite differences of themselves."""
import numpy as np
import pytest

from core.irf import ResponseError, render_shifted, render_sss
from core.irf_models import gaussian_response
from decomposition.response.resolve import resolve_response
from decomposition.kernels.response import response_table, shifted_atoms, slot_rows, sss_atoms, uniform_stride
from drivers.sim.scene import simulated_response

T = 2.0
T_AXIS = T + T * np.arange(400)


def _responses():
    return {"tailed": resolve_response(simulated_response("tailed"), T, 400),
            "afterpulse": resolve_response(simulated_response("afterpulse"), T, 400),
            "gauss1": gaussian_response(2.0, time_step_ps=T),        # sigma one bin
            "gauss3": gaussian_response(6.0, time_step_ps=T)}


RESPONSES = _responses()
# on and between bins, the peak before the axis, partly after it, and wholly after it
DELAYS = np.array([2.0, 3.0, 3.37, 101.25, 250.9, 431.0, -7.3, -30.0, 790.6, 799.0, 803.1, 1500.0])
ALPHAS = np.array([1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0])


@pytest.mark.parametrize("name", sorted(RESPONSES))
def test_shifted_atoms_match_the_exact_interpolant(name):
    irf = RESPONSES[name]
    tab = response_table(irf)
    exact, d_exact = render_shifted(irf, T_AXIS, DELAYS, derivative=True)
    got, d_got = shifted_atoms(tab, T_AXIS, DELAYS, derivative=True)
    assert got.shape == exact.shape == (DELAYS.size, T_AXIS.size)
    assert np.abs(got - exact).max() < 1e-7                       # unit-peak atoms
    assert np.abs(d_got - d_exact).max() < 5e-6 * np.abs(d_exact).max()
    assert np.all(np.abs(got[exact == 0.0]) < 1e-12)                        # outside the padded window: zeros
    assert np.all(got[DELAYS == 1500.0] == 0.0)                      # wholly after the axis
    # on a non-uniform axis (every other sample) the same values
    assert np.array_equal(shifted_atoms(tab, T_AXIS[::2], DELAYS), got[:, ::2])


@pytest.mark.parametrize("name", sorted(RESPONSES))
def test_sss_atoms_match_the_exact_interpolant(name):
    irf = RESPONSES[name]
    tab = response_table(irf)
    d, a = np.meshgrid(DELAYS, ALPHAS)
    exact, dd_exact, da_exact = render_sss(irf, T_AXIS, d, a, derivatives=True)
    got, dd_got, da_got = sss_atoms(tab, T_AXIS, d, a, derivatives=True)
    # each alpha's errors relative to its largest atom (the rows hold atoms wholly inside)
    top = np.abs(exact).max(axis=(1, 2))[:, None, None]
    assert np.abs(got - exact).max(axis=(1, 2)).max() < 1e-7 * top.max()
    assert (np.abs(got - exact) / top).max() < 1e-7
    assert (np.abs(dd_got - dd_exact) / np.abs(dd_exact).max(axis=(1, 2))[:, None, None]).max() < 5e-6
    assert (np.abs(da_got - da_exact) / np.abs(da_exact).max(axis=(1, 2))[:, None, None]).max() < 1e-6
    assert np.all(np.abs(got[exact == 0.0]) < 1e-12) and np.all(got[:, DELAYS == 1500.0] == 0.0)


def test_sss_extremes_of_alpha_sigma():
    """alpha sigma from 1e-4 (the blurred step) to 6 (the atom ~ the response / alpha)."""
    irf = RESPONSES["gauss3"]                          # sigma 6 ps
    tab = response_table(irf)
    for alpha in (1e-4 / 6.0, 1.0):
        exact = render_sss(irf, T_AXIS, 200.3, alpha)
        got = sss_atoms(tab, T_AXIS, 200.3, alpha)
        assert np.abs(got - exact).max() < 1e-7 * np.abs(exact).max()


@pytest.mark.parametrize("name", ["tailed", "gauss1"])
def test_derivatives_are_those_of_the_rendered_atoms(name):
    irf = RESPONSES[name]
    tab = response_table(irf)
    d = np.array([3.37, 101.25, -7.3, 790.6])
    h = 1e-4
    a, da = shifted_atoms(tab, T_AXIS, d, derivative=True)
    fd = (shifted_atoms(tab, T_AXIS, d + h) - shifted_atoms(tab, T_AXIS, d - h)) / (2 * h)
    assert np.abs(da - fd).max() < 1e-6 * np.abs(da).max()
    for alpha in (1e-4, 0.03, 1.0):
        al = np.full(d.shape, alpha)
        s, sd, sa = sss_atoms(tab, T_AXIS, d, al, derivatives=True)
        fd_d = (sss_atoms(tab, T_AXIS, d + h, al) - sss_atoms(tab, T_AXIS, d - h, al)) / (2 * h)
        ha = 1e-6 * alpha
        fd_a = (sss_atoms(tab, T_AXIS, d, al + ha) - sss_atoms(tab, T_AXIS, d, al - ha)) / (2 * ha)
        assert np.abs(sd - fd_d).max() < 5e-6 * np.abs(sd).max()
        assert np.abs(sa - fd_a).max() < 1e-5 * np.abs(sa).max()


def test_sss_onset_derivative_lies_in_the_span_of_the_atoms():
    """d/dd of an sss atom is alpha s - c with c the shifted atom at the same delay, to rounding:
    a direct at the sss onset leaves the onset's column nothing outside the two atoms."""
    tab = response_table(RESPONSES["gauss3"])
    for delay in (173.47453292, 101.0):
        c = shifted_atoms(tab, T_AXIS, delay)
        s, sd, _ = sss_atoms(tab, T_AXIS, delay, 0.0319, derivatives=True)
        assert np.abs(sd - (0.0319 * s - c)).max() < 1e-15


def test_bad_input_is_refused_and_tables_are_kept():
    irf = RESPONSES["tailed"]
    tab = response_table(irf)
    assert response_table(irf) is tab and tab.substeps in (4, 8, 16, 32, 64)
    with pytest.raises(ResponseError, match="alpha_per_ps"):
        sss_atoms(tab, T_AXIS, 10.0, -0.1)
    with pytest.raises(ResponseError, match="delay_ps must be finite"):
        shifted_atoms(tab, T_AXIS, np.nan)
    with pytest.raises(ResponseError, match="InstrumentResponse"):
        response_table("tailed")


def test_params_profile_matches_the_exact_rendering():
    """The response path's trial models (table atoms) are core.model's exact rendering with the
    response to within the table's error: every family, NaN (absent) entries, a background."""
    from core.model import BACKGROUND_KEY, empty_params, render_components, render_profile
    from decomposition.model.atoms import params_components, params_profile

    irf = RESPONSES["tailed"]
    p = empty_params((4,), n_ir=2)
    p["direct_delay_ps"][:] = [40.0, 101.25, -7.3, np.nan]
    p["direct_amplitude"][:] = [3.0, 1.0, 2.0, 5.0]
    p["sss_delay_ps"][:] = [42.0, 103.0, np.nan, 300.5]
    p["sss_amplitude"][:] = [0.5, 2.0, 1.0, 0.7]
    p["sss_alpha_per_ps"][:] = [0.05, 1e-3, 0.1, 0.3]
    p["ir_delay_ps"][:] = [[250.9, np.nan], [431.0, 790.6], [np.nan, np.nan], [600.0, 650.0]]
    p["ir_amplitude"][:] = [[0.4, 1.0], [0.3, 0.2], [1.0, 1.0], [4.0, np.nan]]
    p[BACKGROUND_KEY] = np.array([0.1, np.nan, 0.0, 2.0])
    exact = render_components(p, T_AXIS.size, T, T, irf=irf)
    got = params_components(irf, T_AXIS, p)
    assert set(got) == set(exact)
    for key in exact:
        assert got[key].shape == exact[key].shape
        assert np.abs(got[key] - exact[key]).max() < 5 * 1e-7       # amplitudes up to 5, unit-peak atoms
    assert np.all(got["direct"][3] == 0.0) and np.all(got["interreflections"][2] == 0.0)
    assert np.all(got["background"][1] == 0.0) and np.all(got["background"][3] == 2.0)
    total = params_profile(irf, T_AXIS, p)
    assert np.abs(total - render_profile(p, T_AXIS.size, T, T, irf=irf)).max() < 2e-6


def test_sss_atoms_follow_the_one_pole_recursion_node_by_node():
    """On the table's own nodes (sample times on nodes) the sss atom and its alpha derivative are
    the one-pole recursion s_{j+1} = e s_j + g_j (r its alpha derivative) of the module
    docstring, summed one node at a time here, to 1e-12 of the largest; without derivatives the
    atom is the same bits as with them."""
    irf = RESPONSES["tailed"]
    tab = response_table(irf)
    h, c, m = tab.step_ps, tab.value, tab.slope
    t = tab.start_ps + h * np.arange(0, tab.n_steps + 1, 4, dtype=np.float64)   # every 4th node, delay 0
    for alpha in (1e-3, 0.05, 0.7):
        beta = alpha * h
        x = np.linspace(0.0, 1.0, 20001)            # E_n by quadrature (Simpson), for the weights
        wq = np.full(x.size, 2.0)
        wq[1::2], wq[0], wq[-1] = 4.0, 1.0, 1.0
        E = [float(np.sum(wq * np.exp(-beta * x) * x ** n) / (3 * (x.size - 1))) for n in range(5)]
        w = h * np.array([3 * E[2] - 2 * E[3], h * (E[2] - E[3]), E[0] - 3 * E[2] + 2 * E[3], h * (-E[1] + 2 * E[2] - E[3])])
        v = -h * h * np.array([3 * E[3] - 2 * E[4], h * (E[3] - E[4]), E[1] - 3 * E[3] + 2 * E[4],
                               h * (-E[2] + 2 * E[3] - E[4])])
        g = w[0] * c[:-1] + w[1] * m[:-1] + w[2] * c[1:] + w[3] * m[1:]
        q = v[0] * c[:-1] + v[1] * m[:-1] + v[2] * c[1:] + v[3] * m[1:]
        e = np.exp(-beta)
        s, r = np.zeros(tab.n_steps + 1), np.zeros(tab.n_steps + 1)
        for j in range(tab.n_steps):
            s[j + 1] = e * s[j] + g[j]
            r[j + 1] = e * r[j] - h * e * s[j] + q[j]
        got, _, da = sss_atoms(tab, t, 0.0, alpha, derivatives=True)
        want, want_da = s[::4] / tab.peak_per_ps, r[::4] / tab.peak_per_ps
        # (the weights above by quadrature: 1e-10 of them; the recursion itself to rounding)
        assert np.abs(got - want).max() < 1e-9 * np.abs(want).max()
        assert np.abs(da - want_da).max() < 1e-9 * np.abs(want_da).max()
        assert np.array_equal(sss_atoms(tab, t, 0.0, alpha), got)


@pytest.mark.parametrize("name", sorted(RESPONSES))
def test_uniform_axis_atoms_match_the_node_by_node_ones(name):
    """On an even axis a whole number of table steps apart the atoms are summed a stride of
    nodes at a time and read at one fraction of a step; the same axis with one sample more at
    an uneven spacing takes the node-by-node path.  Both agree to rounding (1e-11 of each
    row's largest value) for atoms on, between, before, across and after the axis, every alpha,
    with and without derivatives."""
    irf = RESPONSES[name]
    tab = response_table(irf)
    uneven = np.append(T_AXIS, T_AXIS[-1] + 0.7 * T)
    assert uniform_stride(T_AXIS, tab.step_ps) == tab.substeps
    assert uniform_stride(uneven, tab.step_ps) == 0 and uniform_stride(T_AXIS[:1], tab.step_ps) == 0
    assert uniform_stride(T_AXIS + 0.3 * tab.step_ps * np.arange(T_AXIS.size) ** 2 / T_AXIS.size ** 2,
                          tab.step_ps) == 0

    def close(a, b):
        top = np.maximum(np.abs(b).max(axis=-1, keepdims=True), 1e-300)
        return np.all(np.abs(a - b) <= 1e-11 * top) and np.array_equal(a == 0.0, b == 0.0)

    delays = np.concatenate([DELAYS, T_AXIS[0] - irf.window_start_ps + np.array([0.0, -1e-9, 1e-9, 0.5]),
                             [-1e6, 1e6, -1e300, 1e300]])
    for got, ref in zip(shifted_atoms(tab, T_AXIS, delays, derivative=True),
                        shifted_atoms(tab, uneven, delays, derivative=True)):
        assert close(got, ref[:, :-1])
    d, a = np.meshgrid(delays, ALPHAS)
    for got, ref in zip(sss_atoms(tab, T_AXIS, d, a, derivatives=True), sss_atoms(tab, uneven, d, a, derivatives=True)):
        assert close(got, ref[..., :-1])
    assert close(sss_atoms(tab, T_AXIS, d, a), sss_atoms(tab, uneven, d, a)[..., :-1])


@pytest.mark.parametrize("axis", ["even", "uneven"])
def test_slot_rows_are_the_atoms_of_each_slot(axis):
    """slot_rows renders (P, K) slot arrays in place: in each shifted slot the bits of
    shifted_atoms, in each sss slot those of sss_atoms (derivatives too; the alpha derivative 0
    in shifted slots), zeros in empty ones whatever their delay holds; a non-finite delay of an
    active slot or a negative alpha of an sss slot is refused by name."""
    from decomposition.constants import FAM_GAUSS, FAM_NONE, FAM_SSS

    tab = response_table(RESPONSES["tailed"])
    t = T_AXIS if axis == "even" else np.append(T_AXIS, T_AXIS[-1] + 0.7 * T)
    fam = np.array([[FAM_GAUSS, FAM_SSS, FAM_NONE], [FAM_NONE, FAM_SSS, FAM_GAUSS], [FAM_GAUSS, FAM_NONE, FAM_GAUSS]],
                   np.int8)
    delay = np.array([[101.25, 103.0, np.nan], [np.nan, -7.3, 431.0], [2.0, 5.0, 790.6]])
    alpha = np.array([[0.0, 0.05, np.nan], [1.0, 1e-3, 0.0], [0.0, -1.0, 0.0]])
    phi, dd, da = slot_rows(tab, t, fam, delay, alpha, derivatives=True)
    assert np.array_equal(slot_rows(tab, t, fam, delay, alpha), phi)
    for (p, k), f in np.ndenumerate(fam):
        if f == FAM_GAUSS:
            a, d = shifted_atoms(tab, t, delay[p, k], derivative=True)
            assert np.array_equal(phi[p, k], a) and np.array_equal(dd[p, k], d) and np.all(da[p, k] == 0.0)
        elif f == FAM_SSS:
            want = sss_atoms(tab, t, delay[p, k], alpha[p, k], derivatives=True)
            assert all(np.array_equal(x, y) for x, y in zip((phi[p, k], dd[p, k], da[p, k]), want))
        else:
            assert np.all(phi[p, k] == 0.0) and np.all(dd[p, k] == 0.0) and np.all(da[p, k] == 0.0)
    bad = delay.copy()
    bad[0, 1] = np.nan
    with pytest.raises(ResponseError, match="delay_ps must be finite"):
        slot_rows(tab, t, fam, bad, alpha)
    bad = alpha.copy()
    bad[1, 1] = -0.1
    with pytest.raises(ResponseError, match="alpha_per_ps"):
        slot_rows(tab, t, fam, delay, bad)
