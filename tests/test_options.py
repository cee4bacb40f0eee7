import dataclasses

import numpy as np
import pytest

from decomposition import decompose
from decomposition.options import (GridSpec, OptionError, SolverOptions, component_letters, option_names,
                                   options_from_mapping, parse_components, parse_nan_policy)
from decomposition.evaluation.synthetic import make_profiles


def test_info_records_every_option_with_its_resolved_value():
    y = make_profiles(4, 128, nsr=0.02, noise="white", seed=0).noisy
    res = decompose(y, 2.0, components="d,s", sparsity=2, max_iter=None)
    for name in option_names():
        assert name in res.info, name
    assert res.info["max_iter"] == 6 + 2 and res.info["max_reflections"] == 0   # no "r": no slots
    assert res.info["sparsity"] == 2.0 and isinstance(res.info["sparsity"], float)
    assert res.info["stderr"] is False and res.info["coarse_sss_sigma"] == 3


@pytest.mark.parametrize("values, pattern", [
    ({"sparsity": -1.0}, "option sparsity: must be >= 0"),
    ({"sparsity": "3"}, "option sparsity: must be a number"),
    ({"max_components": 2.5}, "option max_components: must be an integer"),
    ({"max_components": 0}, "option max_components: must be >= 1"),
    ({"multistart": 1}, "option multistart: must be true or false"),
    ({"eps_rel": 0.0}, "option eps_rel: must be > 0"),
    ({"sigma_range_ps": (3.0, 1.0)}, "option sigma_range_ps: must be 0 < lo <= hi"),
    ({"lm_tol": float("nan")}, "option lm_tol: must be finite"),
    ({"no_such": 1}, r"unknown option\(s\) \['no_such'\]"),
    ({"background_chi2": -1.0}, "option background_chi2: must be >= 0"),
    ({"ambiguity_chi2": -1.0}, "option ambiguity_chi2: must be >= 0"),
])
def test_bad_values_are_refused_naming_the_option(values, pattern):
    with pytest.raises(OptionError, match=pattern):
        options_from_mapping(values)


def test_options_are_frozen_and_normalised_once():
    g = GridSpec(sigma_range_ps=[1, 10], n_sigma=np.int64(50))
    assert g.sigma_range_ps == (1.0, 10.0) and type(g.n_sigma) is int and hash(g) == hash(GridSpec((1, 10), 50))
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.n_sigma = 3
    o = SolverOptions(max_iter=3.0)
    assert o.max_iter == 3 and type(o.max_iter) is int
    assert o.resolved("ds").stderr is False and SolverOptions(refine=True).resolved("drs").stderr is True
    grid, solver, rest = options_from_mapping({"n_alpha": 7, "n_lm": 2, "n_onsets": 4}, strict=False)
    assert grid.n_alpha == 7 and solver.n_lm == 2 and rest == {"n_onsets": 4}


def test_one_component_parser_for_every_caller():
    assert component_letters("d,s,r") == ("d", "s", "r")
    assert component_letters("s+d") == ("s", "d")
    assert component_letters("dsr") == ("d", "s", "r")
    assert component_letters(("direct", "sss", "ir", "d")) == ("d", "s", "r")
    assert parse_components("sss") == frozenset("s")
    for bad in ("", "d,x", "r", ("r", "s")):
        with pytest.raises(ValueError):
            component_letters(bad)


def test_one_nan_policy_vocabulary():
    assert parse_nan_policy("raise") == parse_nan_policy("error") == "raise"
    assert parse_nan_policy("omit") == parse_nan_policy("mark") == "omit"
    with pytest.raises(ValueError, match="nan_policy"):
        parse_nan_policy("ignore")


def test_every_option_is_documented_on_its_field_and_shown_by_help():
    import pydoc
    from dataclasses import fields as dc_fields
    from decomposition.options import GridSpec, SolverOptions
    for cls in (GridSpec, SolverOptions):
        undocumented = [f.name for f in dc_fields(cls) if len(cls.field_docs.get(f.name, "")) < 20]
        assert undocumented == [], f"{cls.__name__}: fields without a #: comment: {undocumented}"
        shown = pydoc.render_doc(cls, renderer=pydoc.plaintext)
        for f in dc_fields(cls):
            assert f"{f.name} : default {f.default!r}" in shown
    assert "in-window energy sum(c_i^2) / s^2" in SolverOptions.__doc__
