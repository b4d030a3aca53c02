"""`SolverOptions` (one place for the solver settings of `simulate` and `simulate_gaits`) and the
named result codes `RESULTS`."""

import diffrax as dfx
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere import RESULTS, SolverOptions
from jsphere.solve.options import solver_options


def test_defaults_and_validation():
    o = SolverOptions()
    got = (o.rtol, o.atol, o.solver, o.max_steps, o.throw, o.adjoint, o.batch_steps)
    assert got == (None, None, None, 16384, True, None, "shared")
    assert isinstance(o.solver_or_default(), dfx.Dopri8)
    assert isinstance(o.adjoint_or_default(), dfx.RecursiveCheckpointAdjoint)
    assert o.tolerances(jnp.float64) == (1e-8, 1e-10)
    with pytest.raises(ValueError, match="batch_steps"):
        SolverOptions(batch_steps="lockstep")
    with pytest.raises(ValueError, match="max_steps"):
        SolverOptions(max_steps=0)


def test_keyword_shortcuts_win_over_options():
    o = SolverOptions(rtol=1e-9, solver=dfx.Tsit5())
    m = solver_options(o, where="simulate", rtol=None, atol=1e-12, max_steps=100, batch_steps="per_trial")
    assert (m.rtol, m.atol, type(m.solver), m.max_steps, m.batch_steps) == (1e-9, 1e-12, dfx.Tsit5, 100, "per_trial")
    assert solver_options(o, where="simulate", rtol=1e-7).rtol == 1e-7  # the keyword given wins
    assert solver_options(None, where="simulate") == SolverOptions()
    with pytest.raises(ValueError, match="max_steps"):
        solver_options(o, where="simulate", max_steps=0)
    with pytest.raises(TypeError, match=r"^simulate: options must be a jsphere.SolverOptions; got dict.$"):
        solver_options({"rtol": 1e-9}, where="simulate")


def test_a_function_s_own_defaults_fill_the_fields_left_at_solver_options_defaults():
    own = {"rtol": 1e-6, "max_steps": 65536}
    assert SolverOptions().or_defaults(**own) == SolverOptions(rtol=1e-6, max_steps=65536)
    assert SolverOptions(rtol=1e-9, max_steps=50).or_defaults(**own) == SolverOptions(rtol=1e-9, max_steps=50)
    # an option set to exactly SolverOptions' default cannot be told from one not set
    assert SolverOptions(max_steps=16384).or_defaults(**own).max_steps == 65536


def test_results_codes_and_messages():
    assert [int(c) for c in RESULTS] == [0, 1, 2, -1]
    assert RESULTS.successful == 0 and RESULTS(2) is RESULTS.nonfinite and RESULTS(-1) is RESULTS.rejected
    assert len(RESULTS.failure_messages()) == 2
    assert "max_steps" in RESULTS.message(1) and "NaN" in RESULTS.message(np.int32(2))
    codes = jnp.array([0, 1, 2])
    np.testing.assert_array_equal(codes == RESULTS.successful, [True, False, False])


def test_simulate_with_options_is_simulate_with_keywords():
    p = jsphere.RobotParams.paper()
    s = jsphere.State.at_rest(p)
    u = jsphere.Torques(jsphere.Constant(jnp.array([0.02, -0.01, 0.0])))
    a = jsphere.simulate(p, s, u, 0.5, rtol=1e-9, max_steps=4096)
    b = jsphere.simulate(p, s, u, 0.5, options=SolverOptions(rtol=1e-9, max_steps=4096))
    np.testing.assert_array_equal(a.x, b.x)
    assert int(b.status) == RESULTS.successful and bool(b.ok)
    c = jsphere.simulate(p, s, u, 0.5, rtol=1e-9, options=SolverOptions(rtol=1e-3, max_steps=4096))
    np.testing.assert_array_equal(a.x, c.x)  # the keyword given wins over the option
