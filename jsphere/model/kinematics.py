"""Constraint maps of Section 2: rolling (2.3), wheels (2.4), the kinematic control (2.9).

No time integration here. All vectors are platform-frame components.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .linalg import cross, matvec
from .params import Derived, RobotParams, derive
from .rotations import rotation_between


def rolling_velocity(params: RobotParams, gamma: Float[Array, "3"], Omega: Float[Array, "3"]) -> Float[Array, "3"]:
    """Velocity of the shell centre from rolling without slipping (2.3): `v = R0 Omega x gamma`."""
    return params.R0 * cross(Omega, gamma)


def _wheel_speeds(d: Derived, omega, Omega):
    return -matvec(d.Sk, omega - Omega)


def wheel_speeds(params: RobotParams, omega: Float[ArrayLike, "3"], Omega: Float[ArrayLike, "3"]) -> Float[Array, " N"]:
    """Wheel rates relative to the platform, from the wheel constraint (2.4).

    `chi_dot_i = -k_i (omega - Omega, s_i)`, `k_i = R0/(Rw (s_i, n_i))`, `s_i = r_i x alpha_i`.
    For the paper's robot every `k_i = -53.166`.
    """
    return _wheel_speeds(derive(params), jnp.asarray(omega), jnp.asarray(Omega))


def relative_rate_from_wheel_speeds(params: RobotParams, chi_dot: Float[ArrayLike, " N"]) -> Float[Array, "3"]:
    """`omega - Omega` realised by given wheel rates: the inverse of (2.4).

    For `N > 3` wheels the least-squares solution (the commands are projected onto the
    consistent subspace; the remainder would be roller slip on a real robot).
    """
    return -matvec(derive(params).Sk_pinv, jnp.asarray(chi_dot))


def constraint_residuals(
    params: RobotParams,
    gamma: Float[ArrayLike, "3"],
    omega: Float[ArrayLike, "3"],
    Omega: Float[ArrayLike, "3"],
    v: Float[ArrayLike, "3"],
    chi_dot: Float[ArrayLike, " N"],
) -> tuple[Float[Array, "3"], Float[Array, " N"]]:
    """Residuals of the nonholonomic constraints for measured or simulated quantities.

    Returns `(F, G)` with `F = v - R0 Omega x gamma` (2.3) [m/s] and
    `G_i = chi_dot_i + k_i (omega - Omega, s_i)` (2.4) [rad/s]; both vanish on a motion
    without slipping.
    """
    gamma, omega, Omega, v, chi_dot = map(jnp.asarray, (gamma, omega, Omega, v, chi_dot))
    F = v - rolling_velocity(params, gamma, Omega)
    G = chi_dot - wheel_speeds(params, omega, Omega)
    return F, G


def rest_attitude(params: RobotParams) -> Float[Array, "3"]:
    """`gamma_m = -r_m/|r_m|`: the vertical in platform components when the robot is at rest (2.5)."""
    return -params.r_m / jnp.linalg.norm(params.r_m)


@jax.jit  # one compiled program when called eagerly
def attitude_matrix(params: RobotParams, psi: Float[ArrayLike, ""] = 0.0) -> Float[Array, "3 3"]:
    """`Q = Q_m Q_psi` of (2.6)-(2.8): fixed -> platform components for a platform at rest
    attitude (`gamma = gamma_m`) turned by the precession angle `psi` about the vertical.

    `Q_m` is the smallest rotation taking `e3` to `gamma_m` (the identity for the paper's
    robot, whose centre of mass lies on the platform's `-e3` axis).
    """
    e3 = jnp.array([0.0, 0.0, 1.0], dtype=params.r_m.dtype)
    Qm = rotation_between(e3, rest_attitude(params))
    c, s = jnp.cos(psi), jnp.sin(psi)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    Qpsi = jnp.stack([jnp.stack([c, s, z]), jnp.stack([-s, c, z]), jnp.stack([z, z, o])])
    return Qm @ Qpsi


def kinematic_wheel_speeds(
    params: RobotParams,
    rdot_c: Float[ArrayLike, "2"],
    *,
    Omega_gamma: Float[ArrayLike, ""] = 0.0,
    omega_gamma: Float[ArrayLike, ""] = 0.0,
    psi: Float[ArrayLike, ""] = 0.0,
) -> Float[Array, " N"]:
    """Wheel rates of the kinematic model (2.9) for a planar velocity `rdot_c = (x_dot, y_dot)`.

    Assumes (Section 2) that the platform keeps its rest attitude `gamma = gamma_m` and only
    turns about the vertical with rate `omega_gamma` (precession angle `psi`). Then
    `omega = omega_gamma gamma`, `Omega = Omega_gamma gamma + gamma x v / R0` with
    `v = Q rdot_c`, and (2.4) gives

        chi_dot_i = (s_i, gamma x v + R0 (Omega_gamma - omega_gamma) gamma) / (Rw (s_i, n_i)),

    which is (2.9) written in platform components. `Omega_gamma = 0` is the "rubber" rolling
    model used in the paper's experiments.
    """
    d = derive(params)
    Q = attitude_matrix(params, psi)
    rdot = jnp.asarray(rdot_c)
    v = matvec(Q, jnp.concatenate([rdot, jnp.zeros_like(rdot[..., :1])], axis=-1))
    gamma = Q[:, 2]
    omega = omega_gamma * gamma
    Omega = Omega_gamma * gamma + cross(gamma, v) / params.R0
    return _wheel_speeds(d, omega, Omega)
