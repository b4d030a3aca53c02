"""The search model: a gait integrated from rest with classical RK4 on a fixed grid.

The planner's forward model. It uses `simulate_gaits`' own vector field (control-free sum of
(3.4) for `Omega`, (2.2)-(2.4)) with `n_steps` equal steps of `T / n_steps`, so that every
restart x target runs the same fixed amount of work under one `vmap`, and forward-mode
derivatives through it are cheap. The accurate re-simulation is `jsphere.planning.verify`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..gaits.families import TiltGait
from ..gaits.gaits import _gait_field, _gait_outputs
from ..model.kinematics import rest_attitude
from ..model.params import RobotParams, derive
from ..model.rotations import rotation_between, rotmat
from ..model.state import State


class Rollout(eqx.Module):
    """The search model's motion on `n_steps + 1` equally spaced times of `[0, T]`."""

    ts: Float[Array, " S"]
    x: Float[Array, " S"]
    y: Float[Array, " S"]
    Omega: Float[Array, "S 3"]
    chi_dot: Float[Array, "S N"]
    K: Float[Array, "S N"]
    tilt2: Float[Array, " S"]
    heading: Float[Array, ""]


def _heading(R, Qm):
    """Platform yaw `psi` [rad] from `R = Q^T` (rows `alpha, beta, gamma`): `R Q_m = Q_psi^T`."""
    M = R @ Qm
    return jnp.arctan2(M[1, 0], M[0, 0])


def _rest_frame(p: RobotParams):
    """`Q_m`: the rotation taking the vertical to the rest attitude `gamma_m`."""
    return rotation_between(jnp.array([0.0, 0.0, 1.0], p.R0.dtype), rest_attitude(p))


def _states(p: RobotParams, gait: TiltGait, n_steps: int) -> Float[Array, "S 16"]:
    """The flat states at `k T / n_steps`, `k = 0..n_steps`, from rest: classical RK4 with
    `simulate_gaits`' own vector field (control-free sum of (3.4) for `Omega`, (2.2)-(2.4))."""
    dt = p.R0.dtype
    T = jnp.asarray(gait.T, dt)
    h = T / n_steps
    args = (p, derive(p), (gait, _rest_frame(p)), jnp.zeros((), dt), T)

    def f(t, z):
        return _gait_field(t, z, args)

    # classical RK4 written as a loop over its stages: stage i evaluates f at
    # (t + c_i h, z + c_i h k_{i-1}) and adds w_i k_i; one f in the compiled graph, not four
    c = jnp.array([0.0, 0.5, 0.5, 1.0], dt)
    w = jnp.array([1.0, 2.0, 2.0, 1.0], dt) / 6.0

    def step(z, k):
        t = k * h

        def stage(carry, cw):
            acc, k_prev = carry
            ki = f(t + cw[0] * h, z + cw[0] * h * k_prev)
            return (acc + cw[1] * ki, ki), None

        (acc, _), _ = jax.lax.scan(stage, (jnp.zeros_like(z), jnp.zeros_like(z)), jnp.stack([c, w], axis=1))
        return z + h * acc, z

    z0 = State.at_rest(p).flatten().astype(dt)
    zT, zs = jax.lax.scan(step, z0, jnp.arange(n_steps, dtype=dt))
    return jnp.concatenate([zs, zT[None]], axis=0)


def rollout(params: RobotParams, gait: TiltGait, n_steps: int) -> Rollout:
    """Integrate a gait from rest with classical RK4 (`n_steps` steps of `T/n_steps`, `_states`)
    and evaluate its torques (3.4), wheel rates (2.4) and tilt on the same grid.

    With `n_steps = 96` and `T <= 12` s the final position agrees with the adaptive solver to
    about 1e-5 m (test `test_rollout_matches_accurate_solver`); used inside the search only.
    """
    p = params
    d = derive(p)
    dt = p.R0.dtype
    Qm = _rest_frame(p)
    T = jnp.asarray(gait.T, dt)
    zs = _states(p, gait, n_steps)
    ts = jnp.linspace(0.0, 1.0, n_steps + 1, dtype=dt) * T
    _, chi_dot, K = jax.vmap(lambda t, z: _gait_outputs(p, d, (gait, Qm), t, z, 0.0, T))(ts, zs)
    u = jax.vmap(gait.tilt)(ts)
    return Rollout(
        ts=ts,
        x=zs[:, 14],
        y=zs[:, 15],
        Omega=zs[:, 11:14],
        chi_dot=chi_dot,
        K=K,
        tilt2=jnp.sum(u**2, axis=-1),
        heading=_heading(rotmat(zs[-1, 0:4]), Qm),
    )
