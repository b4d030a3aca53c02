"""The search model: a gait integrated from rest with classical RK4 on a fixed grid.

The planner's forward model. It uses `simulate_gaits`' own vector field (control-free sum of
(3.4) for `Omega`, (2.2)-(2.4)) with `n_steps` equal steps of `T / n_steps`
(`jsphere.solve.fixed_grid`), so that every restart x target runs the same fixed amount of work
under one `vmap`, and forward-mode derivatives through it are cheap. The accurate re-simulation
is `jsphere.planning.verify`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..gaits.families import TiltGait
from ..gaits.internal import gait_field, gait_outputs
from ..model.kinematics import rest_attitude
from ..model.params import RobotParams, derive
from ..model.rotations import rotation_between, rotmat
from ..model.state import State
from ..solve.field_args import FieldArgs
from ..solve.fixed_grid import Rollout, integrate, uniform_grid


def _rest_frame(p: RobotParams):
    """`Q_m`: the rotation taking the vertical to the rest attitude `gamma_m`."""
    return rotation_between(jnp.array([0.0, 0.0, 1.0], p.R0.dtype), rest_attitude(p))


def yaw(params: RobotParams, q) -> Float[Array, ""]:
    """Platform yaw `psi` [rad] of the attitude quaternion `q`, relative to the rest attitude:
    `R Q_m = Q_psi^T` with `R = Q^T` (rows `alpha, beta, gamma`)."""
    M = rotmat(q) @ _rest_frame(params)
    return jnp.arctan2(M[1, 0], M[0, 0])


def heading(params: RobotParams, ro: Rollout) -> Float[Array, ""]:
    """Platform yaw `psi` [rad] at the end of a rollout (`yaw`)."""
    return yaw(params, ro.q[-1])


def tilt2(gait: TiltGait, ro: Rollout) -> Float[Array, " S"]:
    """The squared tilt `|u|^2` [rad^2] that the gait prescribes at the rollout's times."""
    return jnp.sum(jax.vmap(gait.tilt)(ro.ts) ** 2, axis=-1)


def _states(p: RobotParams, gait: TiltGait, n_steps: int) -> Float[Array, "S 16"]:
    """The flat states at `k T / n_steps`, `k = 0..n_steps`, from rest: classical RK4 with
    `simulate_gaits`' own vector field (control-free sum of (3.4) for `Omega`, (2.2)-(2.4))."""
    dt = p.R0.dtype
    T = jnp.asarray(gait.T, dt)
    args = FieldArgs(params=p, derived=derive(p), control=(gait, _rest_frame(p)))
    z0 = State.at_rest(p).flatten().astype(dt)
    return integrate(lambda t, z: gait_field(t, z, args), z0, uniform_grid(T, n_steps, dt))


def rollout(params: RobotParams, gait: TiltGait, n_steps: int) -> Rollout:
    """Integrate a gait from rest with classical RK4 (`n_steps` steps of `T/n_steps`, `_states`)
    and evaluate its torques (3.4) and wheel rates (2.4) on the same grid.

    With `n_steps = 96` and `T <= 12` s the final position agrees with the adaptive solver to
    about 1e-5 m (test `test_rollout_matches_accurate_solver`); used inside the search only.
    """
    p = params
    d = derive(p)
    dt = p.R0.dtype
    T = jnp.asarray(gait.T, dt)
    zs = _states(p, gait, n_steps)
    ts = uniform_grid(T, n_steps, dt)
    args = FieldArgs(params=p, derived=d, control=(gait, _rest_frame(p)))
    _, chi_dot, K = jax.vmap(lambda t, z: gait_outputs(t, z, args))(ts, zs)
    return Rollout(ts=ts, zs=zs, chi_dot=chi_dot, K=K)
