"""`benchmarks/work_precision.py`'s `Vern7`, the pair it measures against Dopri8:
its transcribed coefficients make a method of order 7 with an embedded one of order 6."""

import importlib.util
import math
import sys
from pathlib import Path

import diffrax as dfx
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _vern7():
    spec = importlib.util.spec_from_file_location(
        "benchmarks_work_precision", ROOT / "benchmarks" / "work_precision.py"
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # equinox's dataclass reads the module of the class it makes
    spec.loader.exec_module(mod)
    return mod.Vern7


def test_quadrature_conditions_of_both_orders():
    """`b . c^k = 1/(k+1)` for k < 7 (solution) and k < 6 (embedded), rows summing to `c`,
    and the appended stage at `c = 1` with the solution's weights (first same as last)."""
    tab = _vern7().tableau
    c = np.concatenate([[0.0], tab.c])
    b, bh = tab.b_sol, tab.b_sol - tab.b_error
    for i, row in enumerate(tab.a_lower, 1):
        assert math.isclose(row.sum(), c[i], abs_tol=1e-14)
    for k in range(7):
        assert math.isclose(b @ c**k, 1 / (k + 1), abs_tol=1e-14), k
    for k in range(6):
        assert math.isclose(bh @ c**k, 1 / (k + 1), abs_tol=1e-14), k
    assert abs(b @ c**7 - 1 / 8) > 1e-6  # order 7, not more
    assert tab.fsal and np.array_equal(tab.a_lower[-1], b[:-1]) and b[-1] == 0.0


def test_seventh_order_convergence_on_a_nonlinear_problem():
    """Fixed steps on `y' = -y^2 + cos t`: halving the step divides the end error by ~2^7."""
    term = dfx.ODETerm(lambda t, y, a: -(y**2) + jnp.cos(t))

    def end(solver, n):
        sol = dfx.diffeqsolve(
            term, solver, 0.0, 2.0, 2.0 / n, jnp.array(1.0), stepsize_controller=dfx.ConstantStepSize()
        )
        return float(sol.ys[-1])

    exact = end(dfx.Dopri8(), 4096)
    e1, e2 = (abs(end(_vern7()(), n) - exact) for n in (8, 16))
    assert 2**6.5 < e1 / e2 < 2**7.7, e1 / e2
