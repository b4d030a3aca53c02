"""`FitOptions`: one object for every option of a fit; the keywords `fit` took before map to its
fields with a `DeprecationWarning`; `fit.json` records the options so that a fit can be replayed."""

import dataclasses
import json

import diffrax as dfx
import numpy as np
import pytest

import jsphere
from jsphere.identify.options import FIT_SOLVER, FitOptions, fit_options
from jsphere.solve.options import SolverOptions


def test_the_defaults_are_the_fits():
    o = FitOptions().checked()
    assert (o.n_starts, o.max_iter, o.adam_steps, o.loss, o.shooting) == (2, 40, 3, "cauchy", "auto")
    assert (o.rtol, o.atol, o.max_steps) == (1e-6, 1e-8, 16384)
    assert o.solver.solver == FIT_SOLVER and o.max_offset == 0.0
    assert jsphere.FitOptions is FitOptions


def test_a_keyword_warns_with_its_spelling_and_wins_over_the_options():
    with pytest.warns(DeprecationWarning, match=r"fit: loss= is deprecated; pass options=FitOptions\(loss=\.\.\.\)"):
        o = fit_options(FitOptions(loss="huber", n_starts=3), {"loss": "l2"})
    assert o == FitOptions(loss="l2", n_starts=3)
    with pytest.warns(DeprecationWarning, match=r"FitOptions\(solver=SolverOptions\(rtol=\.\.\.\)\)"):
        o = fit_options(None, {"rtol": 1e-7})
    assert o.checked().rtol == 1e-7 and o.checked().atol == 1e-8
    with pytest.warns(DeprecationWarning, match=r"options=FitOptions\(solver=SolverOptions\(\.\.\.\)\)"):
        o = fit_options(SolverOptions(max_steps=99), {})
    assert o.checked().max_steps == 99
    with pytest.raises(TypeError, match="unexpected keyword argument 'n_start'"):
        fit_options(None, {"n_start": 3})


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"n_starts": 0}, "fit: n_starts must be a whole number >= 1; got 0."),
        ({"seed": -1}, "fit: seed must be a whole number >= 0; got -1."),
        ({"segment": 0.0}, r"fit: segment must be a finite number >= 0.05 \[s\]; got 0.0."),
        ({"sigma_pos": -1.0}, r"fit: sigma_pos must be a finite number > 0 \[m\]; got -1.0."),
        ({"shooting": "double"}, "fit: shooting must be 'auto', 'single' or 'multiple'; got 'double'."),
        ({"loss": "tukey"}, "fit: loss must be one of"),
        ({"fit_time_offset": 1}, "fit: fit_time_offset must be True or False; got 1."),
    ],
)
def test_bad_options_are_named(bad, match):
    with pytest.raises(ValueError, match=match):
        FitOptions(**bad).checked()


def test_the_options_round_trip_through_json():
    o = FitOptions(n_starts=4, loss="l2", fit_time_offset=True, solver=SolverOptions(rtol=1e-7, solver=dfx.Dopri5()))
    o = o.checked()
    back = FitOptions.from_json(json.loads(json.dumps(o.to_json())))
    assert back.checked().to_json() == o.to_json()
    assert dataclasses.replace(back, solver=None) == dataclasses.replace(o, solver=None)
    assert back.checked().config(np.ones(2), True) == o.config(np.ones(2), True)
