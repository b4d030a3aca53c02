"""Levenberg-Marquardt through the accurate gait simulation, for any parameterised gait
sequence (`optimise_gaits`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..gaits.gaits import simulate_gaits
from ..model.params import RobotParams
from ..numerics.lm import LevenbergMarquardt

#: `optimise_gaits`' iteration: accepted decreases only; 8 rejections in a row end it
OPTIMISE_LM = LevenbergMarquardt(max_rejected=8)


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
    """Levenberg-Marquardt (`jsphere.numerics.lm`) through the accurate gait
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

    def r(x):
        gaits = build(x)
        T = sum(jnp.asarray(g.T) for g in gaits)
        tr = simulate_gaits(params, gaits, ts=jnp.reshape(T, (1,)), rtol=rtol, atol=atol)
        return jnp.asarray(residual(tr))

    def evaluate(x):
        # reverse-mode Jacobian: the adaptive solver's checkpointed loop has no forward mode
        J, res = jax.jacrev(lambda x: (lambda v: (v, v))(r(x)), has_aux=True)(x)
        return 0.5 * jnp.sum(res**2), (res, J)

    @eqx.filter_jit
    def solve(x0):
        # one evaluation in the loop's body (the model compiled once): the first evaluates `x0`
        def body(c):
            z, predicted, x, st, _ = c
            cost, ev = evaluate(z)
            x_next, new = OPTIMISE_LM.update(x, z, st, cost, ev, predicted)
            small = (jnp.max(jnp.abs(z - x)) < tol) & (jnp.abs(st.cost - cost) < tol)
            return (*OPTIMISE_LM.propose(x_next, new), x_next, new, new.converged | ((new.rejected == 0) & small))

        M = jax.eval_shape(r, x0).shape[0]
        inf = jnp.asarray(jnp.inf, x0.dtype)
        st = OPTIMISE_LM.init(inf, (jnp.zeros(M, x0.dtype), jnp.zeros((M, x0.shape[0]), x0.dtype)))
        c = jax.lax.while_loop(lambda c: (c[3].it <= steps) & ~c[4], body, (x0, inf, x0, st, jnp.asarray(False)))
        return c[2], c[3].current[0], c[3].it - 1

    x, res, k = solve(jnp.asarray(x0, jnp.float64))
    return np.asarray(x), {"residual": float(jnp.linalg.norm(res)), "iterations": int(k)}
