"""`SolverOptions` (one place for the solver settings of `simulate` and `simulate_gaits`) and the
named result codes `RESULTS`."""

import diffrax as dfx
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere import RESULTS, SolverOptions
from jsphere.solve.options import resolve


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


def test_merge_keywords_into_options():
    o = SolverOptions(rtol=1e-9, solver=dfx.Tsit5())
    m = resolve(
        o, where="simulate", rtol=None, atol=1e-12, solver=dfx.Tsit5(), max_steps=16384, batch_steps="per_trial"
    )
    assert (m.rtol, m.atol, type(m.solver), m.max_steps, m.batch_steps) == (1e-9, 1e-12, dfx.Tsit5, 16384, "per_trial")
    assert resolve(None, where="simulate", max_steps=100).max_steps == 100
    with pytest.raises(ValueError, match=r"simulate: rtol=1e-07 conflicts with options.rtol=1e-09"):
        resolve(o, where="simulate", rtol=1e-7)
    with pytest.raises(ValueError, match="solver"):
        resolve(o, where="simulate", solver=dfx.Dopri5())
    with pytest.raises(TypeError, match="SolverOptions"):
        resolve({"rtol": 1e-9}, where="simulate")


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
    with pytest.raises(ValueError, match="max_steps"):
        jsphere.simulate(p, s, u, 0.5, max_steps=100, options=SolverOptions(max_steps=4096))
