"""``streaklab bench counts``: mean fidelity of photon counts at each photon level, beside the Poisson-weighted oracle.

The paper's scenes (:func:`decomposition.evaluation.synthetic.make_profiles` with
``ranges="paper"``: a direct, inter-reflections and an sss per pixel, each pixel its own PSF width
of 1.3-9.5 ps) are drawn as integer Poisson counts, bin-integrated, at each ``--photons`` level
(expected signal photons per pixel; default 100, 300, 1,000 and 10,000), and decomposed with the
width

    free    fitted per pixel: ``decompose(counts, time_bin_ps)``;
    held    known, as from a calibration or the whole cube's shared PSF:
            ``decompose(..., hold={"sigma_ps": <each pixel's true width>})``.

``--option KEY=VALUE`` (repeatable, as ``streaklab decompose --option`` takes it) hands a solver
option to every decomposition, e.g. ``likelihood_counts=true``; ``--components`` the families it
looks for (default ``d,r,s``; ``d,r,s,b`` fits an offset too).  ``--background B`` adds a constant
offset of B to every bin of the scenes (signal units before the scaling to photons: the direct
amplitudes are 0.5-1), as dark counts or ambient light would; the oracle knows it (the Poisson
reference fits it, started at the truth).  Beside each, the oracle with the
same width: the true component set fitted from the truth, each sample weighed by 1 / its true
expected count (floored at POISSON_VARIANCE_FLOOR: the Poisson law's Fisher weights), by the
refinement's weighted least squares (:func:`decomposition.model.refine.refine`) -- what a fit
that knows which components are there reaches from the right start; the gap to it is printed.

``--irf NAME|PATH`` (a simulated response's name, or a stored response, as ``bench speed``
takes it) renders the scenes through that response instead, and decomposes them with it
averaged over a bin (``irf=``, as the bins record it and a calibration capture measures it);
the one column is then ``response`` (a response has no width to fit or hold), beside the
Poisson reference (:func:`decomposition.evaluation.poisson_reference.poisson_reference_fit`:
maximum likelihood with the true response and component set, started at the truth).

Outputs in ``--out`` (default ``bench-output/counts``): ``counts.csv`` (one row per photon level
and width), ``summary.json`` (the settings and the rows) and ``counts.png`` (mean fidelity against
photons per pixel, each width's decomposition beside its oracle: :func:`figure`).
"""
from __future__ import annotations

import sys
import time

import numpy as np

from streaklab.cli import CommandError

from .arguments import choices, output_folder, positive_floats
from .tables import write_csv, write_json

PHOTONS = (100.0, 300.0, 1000.0, 10000.0)
WIDTHS = ("free", "held")
#: the column of scenes rendered through a measured response
RESPONSE = "response"
TIME_BIN_PS = 2.0


#: the families the decomposition looks for by default (``--components``)
COMPONENTS = "d,r,s"


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="bench-output/counts", help="output folder (default bench-output/counts)")
    parser.add_argument("--pixels", type=int, default=300, help="profiles per photon level (default 300)")
    parser.add_argument("--bins", type=int, default=512, help="time bins of 2 ps per profile (default 512)")
    parser.add_argument("--photons", default=",".join(f"{p:g}" for p in PHOTONS),
                        help="expected signal photons per pixel, comma-separated (default 100,300,1000,10000)")
    parser.add_argument("--widths", default=None,
                        help="free (fitted per pixel) and/or held (at the truth), comma-separated (default both; "
                             "not with --irf)")
    parser.add_argument("--irf", default="gaussian", metavar="NAME|PATH",
                        help="the instrument: gaussian (default, the Gaussian PSF, a width per pixel), a simulated "
                             "response's name or a stored response")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes and their counts (default 0)")
    parser.add_argument("--components", default=COMPONENTS,
                        help=f"the families the decomposition looks for (default {COMPONENTS}; add b to fit an offset)")
    parser.add_argument("--background", type=float, default=0.0, metavar="B",
                        help="a constant offset in every bin of the scenes, signal units (direct amplitudes 0.5-1; "
                             "default 0)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="a solver option for every decomposition (repeatable; e.g. likelihood_counts=true)")


def true_widths(params: dict) -> np.ndarray:
    """(P,) each pixel's true PSF width, ps (its direct's, else its sss's)."""
    return np.where(np.isfinite(params["direct_sigma_ps"]), params["direct_sigma_ps"], params["sss_sigma_ps"])


def poisson_oracle(data, hold=None) -> dict:
    """The components of the oracle fit of count scenes ``data`` (see the module docstring),
    widths held at ``hold["sigma_ps"]`` where given, the scenes' offset (``data.background``)
    known."""
    from core.model import render_components
    from decomposition.constants import POISSON_VARIANCE_FLOOR
    from decomposition.model.refine import refine

    weights = 1.0 / np.maximum(data.clean, POISSON_VARIANCE_FLOOR)
    truth = dict(data.params, background=np.asarray(data.background, np.float64))
    params, _ = refine(np.asarray(data.noisy, np.float64), truth, time_bin_ps=data.time_bin_ps,
                       t0_ps=data.t0_ps, weights=weights, shared_sigma=True, sss_after_direct=True, keep_order=True,
                       bin_integrated=True, hold=hold)
    return render_components(params, data.noisy.shape[-1], data.time_bin_ps, data.t0_ps, bin_integrated=True)


def measure(photons: float, widths: str, *, pixels: int, bins: int, seed: int, options: dict,
            response=None, components: str = COMPONENTS, background: float = 0.0) -> dict:
    """One row: the decomposition's and the oracle's mean fidelity on one photon level's scenes
    (``widths`` "free", "held", or :data:`RESPONSE` with ``response`` the true instrument), with
    an offset ``background`` in the scenes and ``components`` decomposed."""
    from decomposition import decompose
    from decomposition.evaluation.poisson_reference import poisson_reference_fit
    from decomposition.evaluation.synthetic import make_profiles
    from decomposition.evaluation.synthetic_effects import bin_averaged_response
    from decomposition.model.fidelity import fidelity

    data = make_profiles(pixels, bins, seed=seed, ranges="paper", time_bin_ps=TIME_BIN_PS, photons_per_pixel=photons,
                         response=response, background=background)
    hold = {"sigma_ps": true_widths(data.params)} if widths == "held" else None
    kw = {"irf": bin_averaged_response(response, TIME_BIN_PS)} if response is not None else {"hold": hold}
    t0 = time.perf_counter()
    res = decompose(data.noisy, data.time_bin_ps, t0_ps=data.t0_ps, components=components, **kw, **options)
    seconds = time.perf_counter() - t0
    f_dec = float(np.mean(fidelity(data.components, res)))
    if response is None:
        oracle = poisson_oracle(data, hold)
    else:
        oracle = poisson_reference_fit(data.noisy, data.params, response, time_bin_ps=data.time_bin_ps,
                                       t0_ps=data.t0_ps, background=data.background if background > 0 else None)
    f_oracle = float(np.mean(fidelity(data.components, oracle)))
    return {"photons": photons, "widths": widths, "pixels": pixels, "fidelity": f_dec, "oracle": f_oracle,
            "gap": f_oracle - f_dec, "ms_per_pixel": 1e3 * seconds / pixels}


def figure(rows: list[dict], options: dict | None = None):
    """``counts.png`` as a matplotlib Figure: mean fidelity against photons per pixel (log), each
    width's decomposition (solid) beside its oracle (dashed, the same colour)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for k, w in enumerate(WIDTHS + (RESPONSE,)):
        mine = [r for r in rows if r["widths"] == w]
        if not mine:
            continue
        x = [r["photons"] for r in mine]
        name, ceiling = (w, "Poisson reference") if w == RESPONSE else (f"width {w}", f"oracle, width {w}")
        ax.plot(x, [r["fidelity"] for r in mine], "o-", color=f"C{k}", label=name)
        ax.plot(x, [r["oracle"] for r in mine], "s--", color=f"C{k}", mfc="none", label=ceiling)
    ax.set_xscale("log")
    ax.set_xlabel("expected signal photons per pixel")
    ax.set_ylabel("mean fidelity")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    title = "photon counts of the paper's scenes"
    if options:
        title += "\n" + ", ".join(f"{k}={v}" for k, v in options.items())
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def run(args) -> int:
    from .speed import bench_response

    photons = positive_floats(args.photons, "photons")
    response = bench_response(args.irf)
    if response is not None and args.widths is not None:
        raise CommandError(f"--widths: a measured response (--irf {args.irf}) has no width to fit or hold")
    widths = [RESPONSE] if response is not None else choices(args.widths or ",".join(WIDTHS), WIDTHS, "widths")
    if args.pixels <= 0:
        raise CommandError(f"--pixels must be positive, got {args.pixels}")
    if args.bins < 64:
        raise CommandError(f"--bins must be at least 64, got {args.bins}")
    if args.seed < 0:
        raise CommandError(f"--seed must be a non-negative integer, got {args.seed}")
    if not (np.isfinite(args.background) and args.background >= 0):
        raise CommandError(f"--background must be a finite offset >= 0, got {args.background:g}")
    from decomposition.options import component_letters

    try:
        components = ",".join(component_letters(args.components))
    except ValueError as exc:
        raise CommandError(f"--components: {str(exc).removeprefix('components: ')}") from None
    options = {}
    if args.option:
        from streaklab.commands.decompose import parse_solver_options

        options = parse_solver_options(args.option, "convscd", check_values=True)
    out = output_folder(args.out)
    from decomposition.warmup import warm_up

    # the kernels compiled or loaded before the first row is timed
    warm = {**options, "noise": "poisson"}
    if response is not None:
        from decomposition.evaluation.synthetic_effects import bin_averaged_response

        warm["irf"] = bin_averaged_response(response, TIME_BIN_PS)
    warm_up(time_bin_ps=TIME_BIN_PS, n_bins=args.bins, options=warm, label="bench counts")
    print(f"counts: {args.pixels} paper scenes of {args.bins} bins of {TIME_BIN_PS:g} ps per photon level, seed "
          f"{args.seed}, instrument {args.irf}, components {components}"
          + (f", offset {args.background:g}" if args.background else "") + (f", options {options}" if options else ""))
    print(f"{'photons':>8}  {'width':8} {'fidelity':>9} {'oracle':>8} {'gap':>7} {'ms/pixel':>9}")
    rows = []
    for n in photons:
        for w in widths:
            r = measure(n, w, pixels=args.pixels, bins=args.bins, seed=args.seed, options=options, response=response,
                        components=components, background=args.background)
            rows.append(r)
            print(f"{n:8g}  {w:8} {r['fidelity']:9.4f} {r['oracle']:8.4f} {r['gap']:7.4f} {r['ms_per_pixel']:9.2f}")
            sys.stdout.flush()
    write_csv(out / "counts.csv", rows)
    write_json(out / "summary.json", {"pixels": args.pixels, "bins": args.bins, "seed": args.seed, "irf": args.irf,
                                      "time_bin_ps": TIME_BIN_PS, "options": options, "components": components,
                                      "background": args.background, "rows": rows})
    import matplotlib.pyplot as plt

    fig = figure(rows, dict(options, **({"components": components} if components != COMPONENTS else {}),
                            **({"offset": args.background} if args.background else {})))
    fig.savefig(out / "counts.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out / 'counts.csv'}, {out / 'summary.json'} and {out / 'counts.png'}")
    return 0
