"""Diagnostics along a simulated `Trajectory`: energy, motor power, constraint residuals."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..model.dynamics import energy, power
from ..model.kinematics import wheel_speeds
from ..model.linalg import cross
from ..model.params import RobotParams
from .simulate import Trajectory


def energy_along(params: RobotParams, traj: Trajectory) -> Float[Array, " T"]:
    """`T + U` of (3.2), (3.3) at every sample [J]."""
    return jax.vmap(lambda g, w, W: energy(params, g, w, W))(traj.gamma, traj.omega, traj.Omega)


def power_along(params: RobotParams, traj: Trajectory) -> Float[Array, " T"]:
    """Motor power `sum_i K_i chi_dot_i` at every sample [W]; equals `d(T + U)/dt`."""
    return jax.vmap(lambda w, W, K: power(params, w, W, K))(traj.omega, traj.Omega, traj.K)


def trajectory_residuals(params: RobotParams, traj: Trajectory) -> dict[str, Float[Array, ""]]:
    """Largest violations along a trajectory of the invariants the model must keep:

    - `gamma_norm`: `max | |gamma| - 1 |`;
    - `frame`: `max |(alpha, beta, gamma) orthonormal - E|` (the Poisson equations (2.2));
    - `gamma_vs_axes`: `max |alpha x beta - gamma|` (for gaits: the integrated attitude
      against the prescribed `gamma(t)`);
    - `wheels`: `max |chi_dot - (2.4)|` [rad/s].
    """
    R = jnp.stack([traj.alpha, traj.beta, traj.gamma], axis=-2)
    eye = jnp.eye(3, dtype=R.dtype)
    chi_dot = jax.vmap(lambda w, W: wheel_speeds(params, w, W))(traj.omega, traj.Omega)
    return {
        "gamma_norm": jnp.max(jnp.abs(jnp.linalg.norm(traj.gamma, axis=-1) - 1.0)),
        "frame": jnp.max(jnp.abs(R @ jnp.swapaxes(R, -1, -2) - eye)),
        "gamma_vs_axes": jnp.max(jnp.abs(cross(traj.alpha, traj.beta) - traj.gamma)),
        "wheels": jnp.max(jnp.abs(traj.chi_dot - chi_dot)),
    }
