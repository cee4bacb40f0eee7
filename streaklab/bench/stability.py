"""``streaklab bench stability``: stiff and extreme inputs for ``decompose``.

Every case is a handful of synthetic pixels with known components, built from
``core.model`` (so the truth is exact), decomposed under
warnings-as-errors.  For each case the benchmark reports:

* fidelity of the decomposition against the clean components (mean over pixels),
* whether the per-pixel quality flag expected for that case was raised (or,
  for cases inside what the model explains, whether no flag was raised),
* that every output is finite, the iteration count stays within ``max_iter``
  and the coordinate-descent objective never increased.

Cases (T = time bin):

==================  ==========================================================
alpha_sigma_<x>     d + s with alpha*sigma = x, x in 1e-6 ... 100
sigma_<n>bins       a single direct component with sigma from T/4 to 20 T
outside_window      direct before the window start (tail visible), r2 past its end
same_onset          d and s with exactly the same onset
close_reflections   d + r2 closer than one sigma
dynamic_range_1e6   d + r2 + s with r2 one millionth of d
scale_<f>           d + s + r2 scaled by f, f in 1e-30 ... 1e30
float32             d + s + r2 as float32 (compared with float64)
uint16_saturated    d + s as uint16 counts with the direct peak clipped at 65535
background_offset   d + s on a constant offset of 5 % of the peak
spike               d + s plus a single-sample spike (cosmic ray / hot pixel)
==================  ==========================================================
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Case", "build_cases", "run_case", "add_arguments", "run"]


@dataclass
class Case:
    """One stability case: profiles (N, L), their clean components, what to expect."""

    name: str
    profiles: np.ndarray
    truth: dict                      # parameter dict of the clean components
    kind: str = "model"              # "model": inside the model, no flag and min_fidelity expected
                                     # "outside": every pixel flagged (expect_flag) or still >= min_fidelity
                                     # "ambiguous": not identifiable from the data; invariants only
    expect_flag: int = 0
    allowed_flags: int = 0           # flags that describe the case truthfully (e.g. OFF_WINDOW for a
                                     # tail longer than the window), never a failure
    required_flags: int = 0          # flags every pixel must carry (components built to leave the window)
    min_fidelity: float = 0.9
    options: dict = field(default_factory=dict)
    note: str = ""


def _params(n, n_ir=1):
    from core.model import empty_params

    return empty_params((n,), n_ir=n_ir)


def build_cases(n_bins: int = 256, time_bin_ps: float = 2.0, seed: int = 0, quick: bool = False) -> list[Case]:
    """The stability cases (see the module docstring)."""
    from decomposition import POOR_FIT, SATURATED, SPIKE, AT_BOUND, OFF_WINDOW, WIDE_PSF
    from decomposition.options import GridSpec
    from decomposition.constants import OFF_WINDOW_MASS
    from core.model import render_profile

    L, T = int(n_bins), float(time_bin_ps)
    rng = np.random.default_rng(seed)
    t_mid = 0.3 * L * T
    cases = []

    def add(name, p, y=None, **kw):  # noqa: E306
        y = render_profile(p, L, T) if y is None else y
        cases.append(Case(name, y, p, **kw))

    # alpha * sigma over eight decades
    sigma = 3.0
    for x in ([1e-6, 1e-2, 1.0, 100.0] if quick else [1e-6, 1e-4, 1e-2, 0.1, 1.0, 10.0, 100.0]):
        p = _params(2, 0)
        p["direct_delay_ps"][:] = t_mid + rng.uniform(0, T, 2)
        p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 1.0, sigma
        p["sss_delay_ps"][:] = p["direct_delay_ps"] + 2.0
        p["sss_alpha_per_ps"][:] = x / sigma
        p["sss_sigma_ps"][:] = sigma
        # sss peak at 0.3 of the direct's whatever alpha is: b = 0.3 / max h
        from core.model import sss_kernel
        tt = np.linspace(-5 * sigma, 5 * sigma + 5.0 / (x / sigma), 20001)
        p["sss_amplitude"][:] = 0.3 / sss_kernel(tt, sigma, x / sigma).max()
        alpha = x / sigma
        if 0.0025 <= alpha <= 0.2:            # the alpha grid 0.01-0.05 /ps widened by the bound factor 4
            # the part of the sss area after the window's last sample, exp(-alpha (t_end - onset))
            t_end = T + (L - 1) * T
            beyond = float(np.max(np.exp(-alpha * (t_end - p["sss_delay_ps"]))))
            add(f"alpha_sigma_{x:g}", p, note="alpha inside the refinement bounds",
                allowed_flags=int(OFF_WINDOW) if beyond > 0.5 * OFF_WINDOW_MASS else 0)
        elif x >= 1.0:
            add(f"alpha_sigma_{x:g}", p, kind="ambiguous",
                note="sss decay <= PSF width: indistinguishable from a reflection")
        else:
            add(f"alpha_sigma_{x:g}", p, kind="outside", expect_flag=POOR_FIT | AT_BOUND,
                note="sss decay far longer than the alpha grid allows")
    # sigma from a quarter bin to 20 bins
    for nb in ([0.25, 1.0, 20.0] if quick else [0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0]):
        p = _params(2, 0)
        p["direct_delay_ps"][:] = t_mid + rng.uniform(0, T, 2)
        p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 1.0, nb * T
        if 0.5 <= nb <= 10.0 and nb * T > GridSpec().sigma_range_ps[1]:
            # fitted (refinement goes beyond the kernel grid), and flagged as wider than it
            add(f"sigma_{nb:g}bins", p, min_fidelity=0.95, allowed_flags=int(WIDE_PSF), required_flags=int(WIDE_PSF),
                note="sigma beyond the kernel grid's largest: fitted, flagged WIDE_PSF")
        elif 0.5 <= nb <= 10.0:
            add(f"sigma_{nb:g}bins", p, min_fidelity=0.95)
        else:
            add(f"sigma_{nb:g}bins", p, kind="outside", expect_flag=SPIKE | POOR_FIT | AT_BOUND,
                note="a quarter-bin peak is a single sample" if nb < 0.5 else "sigma at the kernel bound")
    # partly outside the window
    p = _params(2, 1)
    p["direct_delay_ps"][:] = [T - 2.0, T * 3]          # peak half a sigma before the first bin; near the start
    p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 1.0, 4.0
    p["sss_delay_ps"][:] = p["direct_delay_ps"] + 3.0
    p["sss_amplitude"][:], p["sss_alpha_per_ps"][:], p["sss_sigma_ps"][:] = 0.03, 0.02, 4.0
    p["ir_delay_ps"][:, 0] = L * T + 4.0
    p["ir_amplitude"][:, 0], p["ir_sigma_ps"][:, 0] = 0.5, 4.0
    add("outside_window", p, min_fidelity=0.85, allowed_flags=int(OFF_WINDOW), required_flags=int(OFF_WINDOW),
        note="direct peak before the first bin, r2 peak after the last (d/s split less determined); "
             "flagged OFF_WINDOW")
    # d and s with the same onset
    p = _params(3, 0)
    p["direct_delay_ps"][:] = t_mid + np.arange(3) * 0.7
    p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 1.0, 3.0
    p["sss_delay_ps"][:] = p["direct_delay_ps"]
    p["sss_amplitude"][:], p["sss_alpha_per_ps"][:], p["sss_sigma_ps"][:] = 0.05, [0.015, 0.03, 0.045], 3.0
    add("same_onset", p)
    # two reflections closer than one sigma
    p = _params(2, 1)
    p["direct_delay_ps"][:] = t_mid
    p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 1.0, 4.0
    p["ir_delay_ps"][:, 0] = t_mid + np.array([2.0, 3.5])
    p["ir_amplitude"][:, 0], p["ir_sigma_ps"][:, 0] = 0.6, 4.0
    add("close_reflections", p, kind="ambiguous", note="below the resolution: reported as one component")
    # 1e6 dynamic range
    p = _params(2, 1)
    p["direct_delay_ps"][:] = t_mid
    p["direct_amplitude"][:], p["direct_sigma_ps"][:] = 1.0, 3.0
    p["sss_delay_ps"][:] = t_mid + 3.0
    p["sss_amplitude"][:], p["sss_alpha_per_ps"][:], p["sss_sigma_ps"][:] = 0.04, 0.03, 3.0
    p["ir_delay_ps"][:, 0] = t_mid + 150.0
    p["ir_amplitude"][:, 0], p["ir_sigma_ps"][:, 0] = 1e-6, 3.0
    add("dynamic_range_1e6", p, min_fidelity=0.98, note="r2 below the 5% threshold: dropped")
    # whole-profile scale
    base = _params(2, 1)
    base["direct_delay_ps"][:] = t_mid + np.array([0.0, 1.3])
    base["direct_amplitude"][:], base["direct_sigma_ps"][:] = 1.0, 3.0
    base["sss_delay_ps"][:] = base["direct_delay_ps"] + 3.0
    base["sss_amplitude"][:], base["sss_alpha_per_ps"][:], base["sss_sigma_ps"][:] = 0.04, 0.025, 3.0
    base["ir_delay_ps"][:, 0] = t_mid + 120.0
    base["ir_amplitude"][:, 0], base["ir_sigma_ps"][:, 0] = 0.4, 3.0
    y0 = render_profile(base, L, T)
    for f in ([1e-30, 1e30] if quick else [1e-30, 1e-15, 1.0, 1e15, 1e30]):
        p = {k: (v * f if k.endswith("amplitude") else v.copy()) for k, v in base.items()}
        add(f"scale_{f:g}", p, y0 * f, min_fidelity=0.98)
    add("float32", {k: v.copy() for k, v in base.items()}, y0.astype(np.float32), min_fidelity=0.98)
    # uint16 with saturated samples
    p = {k: v.copy() for k, v in base.items()}
    for k in ("direct_amplitude", "sss_amplitude", "ir_amplitude"):
        p[k] = p[k] * 90000.0
    counts = render_profile(p, L, T)
    add("uint16_saturated", p, np.minimum(np.round(counts), 65535).astype(np.uint16), kind="outside",
        expect_flag=SATURATED, min_fidelity=1.1, note="clipped samples flagged and excluded from the fit")
    # constant background offset
    add("background_offset", {k: v.copy() for k, v in base.items()}, y0 + 0.05, kind="outside",
        expect_flag=POOR_FIT | AT_BOUND, note="an offset is not in the model: flag")
    # single-sample spike
    y = y0.copy()
    y[0, int(0.7 * L)] += 0.8
    y[1, int(0.2 * L)] += 0.5
    add("spike", {k: v.copy() for k, v in base.items()}, y, kind="outside", expect_flag=SPIKE, min_fidelity=1.1,
        note="spike flagged and excluded, not reported as a reflection")
    return cases


def run_case(case: Case, time_bin_ps: float = 2.0, max_iter: int = 8, **options) -> dict:
    """Decompose one case under warnings-as-errors and check the invariants.

    Returns a dict: name, fidelity (mean), flagged (expected bit raised on every
    pixel, or no flag at all for in-model cases), finite, bounded, monotone,
    seconds, flags (per pixel), result.
    """
    from decomposition import decompose
    from decomposition.model.fidelity import fidelity
    from core.model import render_components

    opts = dict(case.options)
    opts.update(options)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):
            res = decompose(case.profiles, time_bin_ps, max_iter=max_iter, **opts)
    secs = time.perf_counter() - t0
    L = case.profiles.shape[-1]
    truth = render_components(case.truth, L, time_bin_ps)
    fid = fidelity(truth, res)
    outs = [res.direct, res.sss, res.interreflections, res.residual.astype(np.float64)]
    finite = all(np.isfinite(o).all() for o in outs)
    finite &= all(np.isfinite(v[np.isfinite(v)]).all() for v in res.params.values())
    hist = res.info["objective"]
    d = np.diff(hist, axis=-1)
    ok = np.isfinite(d)
    monotone = bool(np.all(d[ok] <= 1e-12 * np.abs(hist[..., :-1][ok])))
    bounded = bool(np.all(res.info["n_iter"] <= max_iter))
    flags = np.asarray(res.flags).ravel()
    fid = np.asarray(fid).ravel()
    good = fid >= case.min_fidelity
    if case.kind == "model":
        ok = bool(np.all((flags & ~np.uint16(case.allowed_flags)) == 0) and np.all(good))
        ok &= bool(np.all((flags & case.required_flags) == case.required_flags))
    elif case.kind == "outside":
        ok = bool(np.all(((flags & case.expect_flag) > 0) | good))
    else:
        ok = True
    return {"name": case.name, "kind": case.kind, "fidelity": float(np.nanmean(fid)),
            "n_flagged": int(np.count_nonzero(flags)), "n_pixels": int(flags.size), "expect_ok": ok,
            "finite": bool(finite), "bounded": bounded, "monotone": monotone, "seconds": secs,
            "flags": flags, "result": res, "note": case.note}


def _flag_names(bits: int) -> str:
    from decomposition import FLAG_NAMES

    names = [n for b, n in FLAG_NAMES.items() if bits & b]
    return "|".join(names) if names else "-"


def add_arguments(parser) -> None:
    parser.add_argument("--bins", type=int, default=256, help="time bins per profile (default 256)")
    parser.add_argument("--time-bin-ps", type=float, default=2.0, help="bin width in ps (default 2)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the direct delays' sub-bin offsets in the alpha*sigma and sigma sweeps (default 0)")
    parser.add_argument("--quick", action="store_true", help="fewer values per swept parameter")


def run(args) -> int:
    from decomposition.warmup import warm_up

    cases = build_cases(args.bins, args.time_bin_ps, args.seed, quick=args.quick)
    warm_up(time_bin_ps=args.time_bin_ps, n_bins=args.bins, label="bench stability")  # not in the first case's ms
    print(f"{'case':<20} {'kind':<9} {'fidelity':>8} {'flagged':>7}  {'flags raised':<26} {'finite':>6} "
          f"{'iter':>4} {'obj':>4} {'ms':>7}  note")
    n_bad = 0
    for case in cases:
        r = run_case(case, args.time_bin_ps)
        raised = int(np.bitwise_or.reduce(r["flags"])) if r["flags"].size else 0
        good = r["expect_ok"] and r["finite"] and r["bounded"] and r["monotone"]
        n_bad += not good
        print(f"{r['name']:<20} {r['kind']:<9} {r['fidelity']:8.4f} {r['n_flagged']:>3}/{r['n_pixels']:<3}  "
              f"{_flag_names(raised):<26} {str(r['finite']):>6} {'ok' if r['bounded'] else 'OVER':>4} "
              f"{'ok' if r['monotone'] else 'UP':>4} {1e3 * r['seconds']:7.1f}  {r['note']}"
              f"{'' if good else '  <-- NOT AS EXPECTED'}")
    print(f"\n{len(cases) - n_bad} of {len(cases)} cases as expected (model: no flag and fidelity >= "
          f"threshold; outside: each pixel flagged or still fitted; ambiguous: invariants only). "
          f"Every case: no NaN/inf/overflow warning, iterations <= max_iter, objective never increased.")
    return 0 if n_bad == 0 else 1
