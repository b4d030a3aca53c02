"""`SolverOptions` in `fit`, `plan`, `plan_route`, `plan_many`, `replay_errors` and `monte_carlo`:
each function's own defaults for the fields left at `SolverOptions`' defaults (`or_defaults`),
the fields each function uses, the errors for the ones it cannot, and the named outcomes
(`RESULTS`) of `MonteCarloResult`."""

import json
import types

import diffrax as dfx
import jax
import numpy as np
import pytest

import jsphere
from jsphere import RESULTS, SolverOptions
from jsphere.identify import fit as fit_module
from jsphere.montecarlo import run as mc_run
from jsphere.montecarlo.result import REJECTED, SUCCESS, outcome_masks
from jsphere.montecarlo.store import fingerprint
from jsphere.montecarlo.study import check_vary
from jsphere.planning import verify
from jsphere.solve.options import unused

GAITS = [jsphere.acceleration(), jsphere.braking()]
VARY = {"j": ("normal", 2.7e-4, 1e-6)}


class Stop(Exception):
    """Ends a call at the solve whose arguments a test records."""


# ------------------------------------------------------------------ fields a function cannot use


def test_unused_fields_are_refused_one_line():
    unused(None, where="fit", adjoint="never")
    unused(SolverOptions(rtol=1e-3), where="fit", adjoint="never")
    with pytest.raises(ValueError, match=r"^fit: options.adjoint=ForwardMode\(\) is not used: because\.$"):
        unused(SolverOptions(adjoint=dfx.ForwardMode()), where="fit", adjoint="because")


# ------------------------------------------------------------------ fit


@pytest.fixture(scope="module")
def trials():
    """The small problem of `test_fit.py` (2 wheel-speed trials of 1.5 s at 50 Hz): the same
    shapes, so the same compiled solves."""
    truth = jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)
    out = []
    for i in range(2):
        u = jsphere.random_inputs(truth, 1.5, kind="wheel_speeds", seed=i)
        out.append(jsphere.synthetic_trial(truth, u, 1.5, rate=50.0, seed=i, name=f"t{i}", dropout=0.05))
    return out


FIT = {"fix": {"m": 2.5}, "n_starts": 1, "adam_steps": 2, "max_iter": 15}


@pytest.mark.slow
def test_fit_with_options_is_fit_with_keywords(paper, trials):
    a = jsphere.fit(trials, paper, "R_m,j", rtol=1e-7, max_steps=8192, **FIT)
    b = jsphere.fit(trials, paper, "R_m,j", options=SolverOptions(rtol=1e-7, max_steps=8192), **FIT)
    assert a.values == b.values and a.cost == b.cost


def test_fit_passes_the_solver_options_to_its_compiled_functions(paper, trials, monkeypatch):
    """The solver settings reach the residual functions (their cache key) and the checkpoint's
    fingerprint, the same whether given as keywords or as options; without a solver named the
    fit's own (`FIT_SOLVER`) is used."""
    seen, configs = [], []

    def record(free, kind, rtol, atol, max_steps, solver=None, max_offset=0.0, split=False, measure="pose"):
        seen.append((rtol, atol, max_steps, solver))
        raise Stop

    real_setup = fit_module._setup

    def setup(data, free, params, o, *rest):
        configs.append(o.config(np.array([1e-3, 1e-2]), False))
        return real_setup(data, free, params, o, *rest)

    monkeypatch.setattr(fit_module, "_functions", record)
    monkeypatch.setattr(fit_module, "_setup", setup)
    calls = [
        {},
        {"options": SolverOptions(solver=dfx.Dopri8())},
        {"options": SolverOptions(solver=dfx.Tsit5(), atol=1e-9)},
        {"rtol": 1e-7, "max_steps": 8192},
        {"options": SolverOptions(rtol=1e-7, max_steps=8192)},
        {"rtol": 1e-7, "options": SolverOptions(rtol=1e-9, max_steps=8192)},  # the keyword wins
    ]
    for kw in calls:
        with pytest.raises(Stop):
            jsphere.fit(trials, paper, "j", **FIT, **kw)
    assert seen[0] == (1e-6, 1e-8, 16384, dfx.Tsit5())  # the fit's own solver, FIT_SOLVER
    assert seen[1] == (1e-6, 1e-8, 16384, None)  # simulate's default, Dopri8
    assert seen[2] == (1e-6, 1e-9, 16384, dfx.Tsit5())
    assert seen[3] == seen[4] == seen[5] == (1e-7, 1e-8, 8192, dfx.Tsit5())
    assert configs[0]["solver"] == repr(dfx.Tsit5()) and "solver" not in configs[1]
    assert configs[2]["solver"] == repr(dfx.Tsit5()) and configs[2]["atol"] == 1e-9
    assert configs[3] == configs[4] != configs[0]


def test_fit_option_errors(paper, trials):
    with pytest.raises(ValueError, match=r"^fit: options.adjoint=.* is not used: fit differentiates"):
        jsphere.fit(trials, paper, "j", options=SolverOptions(adjoint=dfx.ForwardMode()), **FIT)
    with pytest.raises(TypeError, match="options must be a jsphere.SolverOptions"):
        jsphere.fit(trials, paper, "j", options={"rtol": 1e-9}, **FIT)


# ------------------------------------------------------------------ plan


SMALL = jsphere.PlanSettings(n_tilt=4, n_spin=2, n_steps=32, adam_steps=60, lm_steps=30)
PLAN = {"heading": 0.8, "restarts": 2, "settings": SMALL, "rate": 200.0, "allow_infeasible": True}


@pytest.fixture(scope="module")
def planned(paper):
    return jsphere.plan(paper, (-0.5, -0.4), **PLAN)


@pytest.mark.slow
def test_plan_with_default_options_is_the_same_plan(paper, planned):
    same = jsphere.plan(paper, (-0.5, -0.4), options=SolverOptions(), **PLAN)
    np.testing.assert_array_equal(same.trajectory.x, planned.trajectory.x)
    assert same.errors == planned.errors


def _recorder(seen):
    def solve(*args, **kw):
        seen.append(kw.get("options"))
        raise Stop

    return solve


def test_plan_functions_pass_the_options_to_the_verification(paper, monkeypatch):
    """`plan_route` and `plan_many` (and `plan`, above) hand their options to the accurate
    re-simulation, and `replay_errors` to its solve with its own `max_steps` default."""
    seen = []
    monkeypatch.setattr(verify, "simulate_gaits", _recorder(seen))
    monkeypatch.setattr(verify, "simulate", _recorder(seen))
    route = {k: v for k, v in PLAN.items() if k != "heading"}
    o = SolverOptions(rtol=1e-7, atol=1e-9, solver=dfx.Tsit5(), max_steps=2000)
    with pytest.raises(Stop):
        jsphere.plan_route(paper, [(-0.5, -0.4, 0.8)], options=o, **route)
    with pytest.raises(Stop):
        jsphere.plan_many(paper, [(-0.5, -0.4, 0.8)], restarts=2, settings=SMALL, rate=200.0, options=o)
    assert seen == [o, o]
    table = {"t": np.linspace(0.0, 1.0, 5)} | {f"chi_dot_{i}": np.zeros(5) for i in (1, 2, 3)}
    dummy = types.SimpleNamespace(table=lambda: table, params=paper)
    for options, expected in ((None, SolverOptions(max_steps=65536)), (o, o)):
        with pytest.raises(Stop):
            jsphere.replay_errors(dummy, mode="wheel_speeds", options=options)
        assert seen[-1] == expected


@pytest.mark.slow
def test_plan_verification_and_replay_fail_at_max_steps(paper, planned):
    # the options reach the accurate re-simulation: two steps cannot finish the manoeuvre
    route = {k: v for k, v in PLAN.items() if k != "heading"}
    with pytest.raises(RuntimeError, match="max_steps"):
        jsphere.plan_route(paper, [(-0.5, -0.4, 0.8)], options=SolverOptions(max_steps=2), **route)
    with pytest.raises(RuntimeError, match="max_steps"):
        jsphere.replay_errors(planned, options=SolverOptions(max_steps=3))


@pytest.mark.parametrize(
    "options, match",
    [
        (SolverOptions(throw=False), r"^plan: options.throw=False is not used: a verification that fails raises"),
        (SolverOptions(adjoint=dfx.ForwardMode()), r"^plan: options.adjoint=.* is not used: the verification is not"),
        (SolverOptions(batch_steps="per_trial"), r"^plan: options.batch_steps='per_trial' is not used: the verif"),
    ],
)
def test_plan_refuses_fields_it_does_not_use(paper, options, match):
    with pytest.raises(ValueError, match=match):
        jsphere.plan(paper, (0.5, 0.0), options=options)


def test_plan_many_and_route_refuse_them_too(paper):
    with pytest.raises(ValueError, match=r"^plan_many: options.throw"):
        jsphere.plan_many(paper, [(0.5, 0.0)], options=SolverOptions(throw=False))
    with pytest.raises(ValueError, match=r"^plan_route: options.adjoint"):
        jsphere.plan_route(paper, [(0.5, 0.0)], options=SolverOptions(adjoint=dfx.ForwardMode()))
    with pytest.raises(ValueError, match=r"^replay_errors: options.batch_steps"):
        jsphere.replay_errors(None, options=SolverOptions(batch_steps="per_trial"))
    with pytest.raises(TypeError, match=r"^plan: options must be a jsphere.SolverOptions"):
        jsphere.plan(paper, (0.5, 0.0), options={"rtol": 1e-9})


# ------------------------------------------------------------------ monte_carlo


@pytest.mark.slow
def test_monte_carlo_max_steps_option_reports_the_status(paper, tmp_path):
    r = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=64, batch_size=64, progress=False, out=tmp_path, options=SolverOptions(max_steps=4)
    )
    assert np.all(r.status == RESULTS.max_steps_reached)
    assert set(r.results) == {RESULTS.max_steps_reached}
    st = r.stats()
    assert st["n_failed"] == 64 and st["failed_status"] == {"1": 64}
    assert st["outcomes"] == {"max_steps_reached": 64}
    # gait mode's step limit is part of the study's fingerprint
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert (
        manifest["fingerprint"] == _fingerprint(paper, "j", 64, 0, gait_max_steps=4) != _fingerprint(paper, "j", 64, 0)
    )


def test_monte_carlo_passes_the_options_to_its_batches(paper, monkeypatch):
    """The solver and gait mode's step limit reach the compiled batch; the replay modes' step
    limit is `max_steps` or `options.max_steps` (65536 by default)."""
    seen = []

    def record(trials, idx):
        seen.append((trials.rtol, trials.atol, trials.solver, trials.max_steps, trials.replay))
        raise Stop

    monkeypatch.setattr(mc_run, "run_batch", record)
    kw = {"vary": VARY, "n": 64, "progress": False}
    o = SolverOptions(rtol=1e-7, atol=1e-9, solver=dfx.Tsit5(), max_steps=500)
    for extra in ({}, {"options": o}, {"rtol": 1e-7, "atol": 1e-9, "options": SolverOptions(solver=dfx.Tsit5())}):
        with pytest.raises(Stop):
            jsphere.monte_carlo(paper, GAITS, **kw, **extra)
    assert seen[0] == (1e-8, 1e-10, None, 16384, None)
    assert seen[1] == (1e-7, 1e-9, dfx.Tsit5(), 500, None)
    assert seen[2] == (1e-7, 1e-9, dfx.Tsit5(), 16384, None)
    cmd = (np.array([0.0, 1.0]), np.zeros((2, 3)))
    for extra, limit in (
        ({}, 65536),
        ({"max_steps": 700}, 700),
        ({"options": SolverOptions(max_steps=800)}, 800),
        ({"max_steps": 700, "options": SolverOptions(max_steps=800)}, 700),  # the keyword wins
    ):
        with pytest.raises(Stop):
            jsphere.monte_carlo(paper, GAITS, **kw, mode="torques", commands=cmd, **extra)
        assert seen[-1][4].max_steps == limit and seen[-1][3] == 16384


def _fingerprint(paper, name, n, seed, **solver):
    vary = {name: VARY.get(name, ("normal", -0.0270146, 1e-4))}
    options = jsphere.StudyOptions(seed=seed, batch_size=n)
    solver = SolverOptions(**{"max_steps" if k == "gait_max_steps" else k: v for k, v in solver.items()})
    return mc_run.prepare(paper, GAITS, vary=vary, n=n, options=options, solver=solver).fingerprint


def test_monte_carlo_fingerprint(paper):
    """Without options (or with the defaults) a study's fingerprint is that of its settings
    alone; another solver or gait step limit changes it."""
    spec = check_vary(paper, VARY)
    B = 64 * len(jax.local_devices())
    assert _fingerprint(paper, "j", 64, 3) == fingerprint(
        paper, GAITS, spec, 3, B, (False, "gait", "()", 0.0), 1e-8, 1e-10
    )
    assert _fingerprint(paper, "j", 64, 3, solver=dfx.Dopri8()) == _fingerprint(paper, "j", 64, 3)
    variants = {
        _fingerprint(paper, "j", 64, 3),
        _fingerprint(paper, "j", 64, 3, solver=dfx.Tsit5()),
        _fingerprint(paper, "j", 64, 3, gait_max_steps=1000),
    }
    assert len(variants) == 3


@pytest.mark.parametrize("solve", ["simulate", "simulate_gaits"])
def test_a_keyword_that_is_no_solver_option_is_refused(paper, solve):
    """The solves take their `SolverOptions` fields as keywords; any other keyword is a
    `TypeError` naming it, before any work."""
    if solve == "simulate":
        call = lambda **kw: jsphere.simulate(
            paper, jsphere.State.at_rest(paper), jsphere.Torques(jsphere.Zero(3)), 1.0, **kw
        )  # noqa: E731
    else:
        call = lambda **kw: jsphere.simulate_gaits(paper, GAITS, **kw)  # noqa: E731
    with pytest.raises(TypeError, match=rf"^{solve}\(\) got an unexpected keyword argument 'rtool'"):
        call(rtool=1e-9)


def test_solver_options_hold_no_start_up_machinery():
    """How programs are compiled and kept is the application's (`jsphere.cli`), not a solve's option."""
    with pytest.raises(TypeError):
        SolverOptions(programs=print)
    assert not hasattr(jsphere, "FastStart")


def test_monte_carlo_option_errors(paper):
    with pytest.raises(ValueError, match=r"^monte_carlo: options.adjoint=.* is not used: monte_carlo does not"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=4, options=SolverOptions(adjoint=dfx.ForwardMode()))
    with pytest.raises(jsphere.InputError, match=r"monte_carlo: rtol must be a finite number > 0"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=4, options=SolverOptions(rtol=-1.0))


def test_monte_carlo_result_names_its_outcomes():
    status = np.array([0, 1, -1, 0, 2, 0], np.int32)
    r = jsphere.MonteCarloResult(
        n=6,
        seed=0,
        samples={},
        x_final=np.array([0.1, np.nan, np.nan, 0.2, np.nan, 0.3]),
        y_final=np.array([0.0, np.nan, np.nan, 0.1, np.nan, 0.0]),
        speed_final=np.zeros(6),
        status=status,
        gamma3_sd_after=np.zeros(6),
        reject_code=np.array([0, 0, 2, 0, 0, 0]),
    )
    assert r.status.dtype == np.int32
    assert list(r.results) == [RESULTS(int(c)) for c in status]
    assert r.results[2] is RESULTS.rejected and r.results[4] is RESULTS.nonfinite
    assert r.outcomes() == {"rejected": 1, "successful": 3, "max_steps_reached": 1, "nonfinite": 1}
    st = r.stats()
    assert (st["n_ok"], st["n_failed"], st["n_rejected"]) == (3, 2, 1)
    assert st["failed_status"] == {"1": 1, "2": 1} and st["outcomes"] == r.outcomes()
    # the names of the module and the class stay aliases of the members
    assert REJECTED is RESULTS.rejected == jsphere.MonteCarloResult.REJECTED == mc_run.REJECTED == -1
    assert SUCCESS is RESULTS.successful
    ok, failed, rejected = outcome_masks(status)
    np.testing.assert_array_equal(rejected, status == -1)
    assert "drawn parameters" in RESULTS.message(REJECTED)
    assert RESULTS.failure_messages() == (RESULTS.message(1), RESULTS.message(2))
