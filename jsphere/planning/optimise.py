"""Levenberg-Marquardt through the accurate gait simulation, for any parameterised gait
sequence (`optimise_gaits`)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ..gaits.gaits import simulate_gaits
from ..model.params import RobotParams


def optimise_gaits(
    params: RobotParams,
    build,
    x0: Float[Array, " P"],
    residual,
    *,
    steps: int = 20,
    tol: float = 1e-12,
    rtol: float = 1e-10,
    atol: float = 1e-12,
) -> tuple[np.ndarray, dict]:
    """Levenberg-Marquardt (`optimistix.LevenbergMarquardt`) through the accurate gait
    simulation, for any parameterised gait sequence: find `x` with `residual(simulate_gaits(params, build(x), ts=[end])) = 0` (or
    least squares).

    **Arguments:**
    - `build(x) -> list[Gait]`: the gait sequence of the parameters `x` (traceable in `x`; keep
      its structure fixed).
    - `residual(traj) -> (M,)`: conditions on the end state (the trajectory holds one sample,
      the end), e.g. `lambda tr: tr.Omega[-1, :2]` ("the robot stops").
    - `steps`: iteration budget; `tol`: the solve ends once both the step in `x` and the change
      of `|r|^2 / 2` are below `tol` (max norm).
    - `rtol`, `atol`: the simulator's tolerances.

    Returns `(x, info)` with `info = {"residual": |r|, "iterations": k}`.
    Example: the braking gait that stops the paper's turn (Section 5.2, `theta_max ~ 0.1416`):

        build = lambda x: [acceleration(), turn(), braking(theta_max=x[0], phi=x[1])]
        x, info = optimise_gaits(p, build, jnp.array([0.1, pi / 4]), lambda tr: tr.Omega[-1, :2])
    """

    def r(x, _):
        gaits = build(x)
        T = sum(jnp.asarray(g.T) for g in gaits)
        tr = simulate_gaits(params, gaits, ts=jnp.reshape(T, (1,)), rtol=rtol, atol=atol)
        return jnp.asarray(residual(tr))

    @eqx.filter_jit
    def solve(x0):
        # reverse-mode Jacobian: the adaptive solver's checkpointed loop has no forward mode
        sol = optx.least_squares(
            r, optx.LevenbergMarquardt(rtol=0.0, atol=tol), x0, options={"jac": "bwd"}, max_steps=steps, throw=False
        )
        return sol.value, r(sol.value, None), sol.stats["num_steps"]

    x, res, k = solve(jnp.asarray(x0, jnp.float64))
    return np.asarray(x), {"residual": float(jnp.linalg.norm(res)), "iterations": int(k)}
