"""What the robot's own sensors read: a 6-axis IMU fixed to the platform and the wheels'
encoders, the measurement model of onboard-sensor trials.

The gyro measures the platform's angular velocity `omega`; the accelerometer the specific force
at its point `r` of the platform, the point's acceleration plus `g gamma` (a level IMU at rest
reads `+g` on its up axis); both in the IMU's own axes, `R^T` times the platform components,
where `R` (of the mounting's quaternion) maps IMU components to platform components. The
encoders read the wheel angles `chi` of the state, whose rates are (2.4).

The shell's centre `C`, the platform frame's origin, moves with `v = R0 Omega x gamma` (2.3);
seen from the rotating platform (platform components, `gamma_dot = gamma x omega`):

    a_C = R0 (Omega_dot x gamma + Omega x gamma_dot) + omega x v
    a_r = a_C + omega_dot x r + omega x (omega x r)

with `omega_dot, Omega_dot` from (3.4) (`accelerations`) or from a solved trajectory.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .dynamics import accelerations
from .kinematics import rolling_velocity
from .linalg import cross, matvec
from .params import RobotParams
from .rotations import rotmat


class Mounting(eqx.Module):
    """Where the IMU sits on the platform (a pytree: its fields may be fitted).

    - `position`: `(3,)` the IMU's point, platform components from the shell's centre [m]
      (the platform frame's origin, not the platform's mass centre).
    - `rotation`: `(4,)` scalar-first Hamilton quaternion whose matrix maps IMU components to
      platform components (the trial quaternion's convention). Need not be normalised.
    """

    position: Float[Array, "3"]
    rotation: Float[Array, "4"]

    def __init__(self, position: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0), rotation=(1.0, 0.0, 0.0, 0.0)):
        self.position = jnp.asarray(position, dtype=float)
        self.rotation = jnp.asarray(rotation, dtype=float)

    def to_imu(self, v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Platform components `v` in the IMU's axes, `R^T v`."""
        return matvec(rotmat(self.rotation).swapaxes(-1, -2), v)


def specific_force(
    params: RobotParams,
    r: Float[Array, "3"],
    gamma: Float[Array, "3"],
    omega: Float[Array, "3"],
    Omega: Float[Array, "3"],
    omega_dot: Float[Array, "3"],
    Omega_dot: Float[Array, "3"],
) -> Float[Array, "3"]:
    """The specific force at the platform point `r`, `a_r + g gamma` (module docstring),
    platform components [m/s^2]."""
    v = rolling_velocity(params, gamma, Omega)
    a_C = params.R0 * (cross(Omega_dot, gamma) + cross(Omega, cross(gamma, omega))) + cross(omega, v)
    a_r = a_C + cross(omega_dot, r) + cross(omega, cross(omega, r))
    return a_r + params.g * gamma


def imu_readings(
    params: RobotParams,
    mounting: Mounting,
    gamma: Float[ArrayLike, "*T 3"],
    omega: Float[ArrayLike, "*T 3"],
    Omega: Float[ArrayLike, "*T 3"],
    K: Float[ArrayLike, "*T N"],
) -> tuple[Float[Array, "*T 3"], Float[Array, "*T 3"]]:
    """The gyro's and the accelerometer's readings `(gyro, acc)` in the IMU's axes, without
    bias or noise, at states `(gamma, omega, Omega)` under the axle torques `K` (one sample, or
    leading time axes as a `Trajectory` holds them: `imu_readings(p, m, tr.gamma, tr.omega,
    tr.Omega, tr.K)`; a trajectory's `K` is the torque the motors supply in every mode).

    Pure JAX: works under `jit`, `vmap` and `grad` (in the parameters and the mounting).
    """
    dt = params.R0.dtype
    gamma, omega, Omega, K = (jnp.asarray(x, dt) for x in (gamma, omega, Omega, K))
    r = mounting.position.astype(dt)

    def one(gamma, omega, Omega, K):
        omega_dot, Omega_dot = accelerations(params, gamma, omega, Omega, K)
        return omega, specific_force(params, r, gamma, omega, Omega, omega_dot, Omega_dot)

    for _ in range(gamma.ndim - 1):
        one = jax.vmap(one)
    w, f = one(gamma, omega, Omega, K)
    return mounting.to_imu(w), mounting.to_imu(f)
