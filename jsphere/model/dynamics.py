"""Equations of motion (3.4) with (3.5), energy (3.2)-(3.3): written once, here.

With the OCR fixes of `docs/model.md`, (3.4) reads

    A w' + B W' = r1 - Sk^T K                                    (first equation)
    B^T w' + D W' = r2 + Sk^T K                                  (second equation)

with `w = omega` (platform), `W = Omega` (shell), both in platform components, and

    A = I + Jss - Jns - Jsn                                      (constant)
    B = Jns - Jss + m R0 ((gamma, r_m) E - gamma (x) r_m)
    D = I0 E + Jss + (m + m0) R0^2 (gamma^2 E - gamma (x) gamma)
    r1 = -w x I w + (Jns (W - w)) x w - m R0 r_m x (gamma x (W x w)) - m g r_m x gamma
    r2 = -(m + m0) R0^2 gamma x (gamma x (W x w)) - m R0 gamma x (w x (w x r_m)) - I0 w x W
         - c_roll W_h                                            (optional rolling resistance)
    Sk^T K = sum_i k_i s_i K_i,   K -> k_tau K - c_axle chi_dot  (torque gain, axle friction)

`W_h = W - (W, gamma) gamma`. The two damping terms are not in the paper (both 0 by default).
`K` is the commanded axle torque; the wheels get `k_tau K` (`RobotParams.k_tau`, 1 by default,
`applied_torques`), and torques the model returns (`required_torques`, wheel-speed mode) are
commanded ones, `K = K_axle / k_tau`.

The 6x6 matrix `[[A, B], [B^T, D]]` is the Hessian of the kinetic energy (3.2) with `v` and
`chi_dot` eliminated by the constraints, hence symmetric positive definite. The *sum* of the
two equations is free of the control torques (the Proposition's "first three equations").
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .kinematics import rolling_velocity, wheel_speeds
from .linalg import cross, dot, matvec, outer, solve3
from .params import Derived, RobotParams, derive


def mass_blocks(
    p: RobotParams, d: Derived, gamma: Float[Array, "3"]
) -> tuple[Float[Array, "3 3"], Float[Array, "3 3"]]:
    """The `gamma`-dependent blocks `B` (omega-Omega coupling) and `D` (Omega-Omega) of (3.4)."""
    E = jnp.eye(3, dtype=gamma.dtype)
    B = d.B0 + d.mR0 * (dot(gamma, p.r_m) * E - outer(gamma, p.r_m))
    D = d.D0 + d.MR2 * (dot(gamma, gamma) * E - outer(gamma, gamma))
    return B, D


def forces(p: RobotParams, d: Derived, gamma, omega, Omega) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Right-hand sides `r1`, `r2` of (3.4) without the control torques."""
    w, W = omega, Omega
    Wxw = cross(W, w)
    gWxw = cross(gamma, Wxw)
    r1 = (
        -cross(w, matvec(p.I, w))
        + cross(matvec(d.Jns, W - w), w)
        - d.mR0 * cross(p.r_m, gWxw)
        - d.mg * cross(p.r_m, gamma)
    )
    r2 = (
        -d.MR2 * cross(gamma, gWxw)
        - d.mR0 * cross(gamma, cross(w, cross(w, p.r_m)))
        + p.I0 * Wxw  # - I0 w x W
        - p.c_roll * (W - dot(W, gamma) * gamma)
    )
    return r1, r2


def free_forces(p: RobotParams, d: Derived, gamma, omega, Omega) -> Float[Array, "3"]:
    """`r1 + r2` of (3.4), the right-hand side of the control-free sum (`forces` added up,
    with the common factors of its cross products taken out)."""
    w, W = omega, Omega
    gWxw = cross(gamma, cross(W, w))
    spin = matvec(p.I, w) + matvec(d.Jns, W - w) + p.I0 * W  # -w x (I w) + (Jns (W-w)) x w - I0 w x W
    return (
        -cross(w, spin)
        - cross(d.mR0 * p.r_m + d.MR2 * gamma, gWxw)
        - d.mg * cross(p.r_m, gamma)
        - d.mR0 * cross(gamma, cross(w, cross(w, p.r_m)))
        - p.c_roll * (W - dot(W, gamma) * gamma)
    )


def applied_torques(p: RobotParams, K, Sk_dw):
    """The axle torques acting on the wheels, `k_tau K_i - c_axle chi_dot_i`, for the commanded
    torques `K` and `Sk_dw = Sk (omega - Omega) = -chi_dot` (arrays of `N`, or one wheel's
    scalars): the one place where the torque gain and the axle friction enter (3.4)."""
    return p.k_tau * K + p.c_axle * Sk_dw


def commanded_torques(p: RobotParams, K_axle):
    """The commanded torques `K_axle / k_tau` that give the axle torques `K_axle`."""
    return K_axle / p.k_tau


def _torques_for(p: RobotParams, d: Derived, tau, w):
    """The least-norm commanded torques of a required `Sk^T K = tau` at `omega - Omega = w`:
    the motors also overcome the axle friction `-c_axle chi_dot`."""
    return commanded_torques(p, matvec(d.Sk_T_pinv, tau) - p.c_axle * matvec(d.Sk, w))


def solve_accelerations(
    p: RobotParams, d: Derived, gamma, omega, Omega, K
) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """(3.4) solved for `(omega_dot, Omega_dot)` with the 3x3 Schur complement of the constant
    `omega` block (`A^-1` precomputed in `derive`)."""
    B, D = mass_blocks(p, d, gamma)
    r1, r2 = forces(p, d, gamma, omega, Omega)
    K = applied_torques(p, K, matvec(d.Sk, omega - Omega))  # k_tau K - c_axle chi_dot
    tau = K @ d.Sk  # sum_i k_i s_i K_i
    r1 = r1 - tau
    r2 = r2 + tau
    X = d.A_inv @ B  # A^-1 B
    S = D - B.T @ X  # Schur complement (SPD)
    a1 = matvec(d.A_inv, r1)
    Omega_dot = solve3(S, r2 - matvec(B.T, a1))
    omega_dot = a1 - matvec(X, Omega_dot)
    return omega_dot, Omega_dot


def accelerations(
    params: RobotParams,
    gamma: Float[ArrayLike, "3"],
    omega: Float[ArrayLike, "3"],
    Omega: Float[ArrayLike, "3"],
    K: Float[ArrayLike, " N"],
) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Angular accelerations `(omega_dot, Omega_dot)` of platform and shell from (3.4).

    **Arguments:** the platform-frame vertical `gamma`, platform and shell angular velocities
    `omega`, `Omega` [1/s] (platform components) and the commanded axle torques `K` [N m]
    (`+k_tau K_i n_i` acts on wheel i, `-k_tau K_i n_i` on the platform).

    Pure JAX: works under `jit`, `vmap` and `grad`.
    """
    gamma, omega, Omega, K = (jnp.asarray(x, dtype=params.R0.dtype) for x in (gamma, omega, Omega, K))
    return solve_accelerations(params, derive(params), gamma, omega, Omega, K)


def free_Omega_dot(p: RobotParams, d: Derived, gamma, omega, Omega, omega_dot) -> Float[Array, "3"]:
    """`Omega_dot` from the control-free sum of the two equations of (3.4), `omega(t)` given.

    `(B + D) Omega_dot = r1 + r2 - (A + B^T) omega_dot` (Proposition of Section 4).
    """
    B, D = mass_blocks(p, d, gamma)
    return solve3(B + D, free_forces(p, d, gamma, omega, Omega) - matvec(d.A + B.T, omega_dot))


def required_torques(
    p: RobotParams, d: Derived, gamma, omega, Omega, omega_dot, Omega_dot, *, equation: int = 2
) -> Float[Array, " N"]:
    """Axle torques realising given accelerations, from one equation of (3.4).

    `equation=2` uses `Sk^T K = B^T omega_dot + D Omega_dot - r2`; `equation=1` uses
    `Sk^T K = r1 - A omega_dot - B Omega_dot`. On a motion that satisfies the control-free
    sum, both give the same `K`. With `N > 3` wheels, `K` is the least-norm solution. `K`
    is commanded (`commanded_torques`: the axle torques over `k_tau`).
    """
    B, D = mass_blocks(p, d, gamma)
    r1, r2 = forces(p, d, gamma, omega, Omega)
    if equation == 2:
        tau = matvec(B.T, omega_dot) + matvec(D, Omega_dot) - r2
    else:
        tau = r1 - matvec(d.A, omega_dot) - matvec(B, Omega_dot)
    return _torques_for(p, d, tau, omega - Omega)


def servo_accelerations(p: RobotParams, d: Derived, gamma, Omega, w, w_dot):
    """Wheel-speed (servo-constraint) mode: `omega - Omega = w(t)` imposed by the wheels.

    The control-free sum of (3.4) with `omega = Omega + w` gives
    `(A + B + B^T + D) Omega_dot = r1 + r2 - (A + B^T) w_dot`; the torques follow from the
    second equation. Returns `(omega, omega_dot, Omega_dot, K)`, `K` commanded (over `k_tau`).
    """
    omega = Omega + w
    B, D = mass_blocks(p, d, gamma)
    r1, r2 = forces(p, d, gamma, omega, Omega)
    AB = d.A + B.T
    Omega_dot = solve3(AB + B + D, (r1 + r2) - matvec(AB, w_dot))
    omega_dot = Omega_dot + w_dot
    tau = matvec(B.T, omega_dot) + matvec(D, Omega_dot) - r2
    return omega, omega_dot, Omega_dot, _torques_for(p, d, tau, w)


def servo_jump(p: RobotParams, d: Derived, gamma, omega, Omega, w_new):
    """Velocities right after an instantaneous change of the commanded wheel speeds.

    The motor impulses are internal and cancel in the control-free sum of (3.4), so the
    momentum `p_free = (A + B^T) omega + (B + D) Omega` is continuous across the jump while
    `omega - Omega` jumps to `w_new`:
    `(A + B + B^T + D) Delta Omega = -(A + B^T) (w_new - (omega - Omega))`.
    Returns `(omega_plus, Omega_plus)`.
    """
    B, D = mass_blocks(p, d, gamma)
    AB = d.A + B.T
    dw = w_new - (omega - Omega)
    Omega_plus = Omega + solve3(AB + B + D, -matvec(AB, dw))
    return Omega_plus + w_new, Omega_plus


def free_momentum(p: RobotParams, d: Derived, gamma, omega, Omega) -> Float[Array, "3"]:
    """`(A + B^T) omega + (B + D) Omega`: the momentum of the control-free equation."""
    B, D = mass_blocks(p, d, gamma)
    return matvec(d.A + B.T, omega) + matvec(B + D, Omega)


def kinetic_energy(params: RobotParams, gamma, omega, Omega) -> Float[Array, ""]:
    """Kinetic energy (3.2) with `v` from (2.3) and `chi_dot` from (2.4) [J].

    Written term by term from (3.2), independently of the mass matrix of (3.4), so the two
    can check each other.
    """
    p, v, chi_dot = params, rolling_velocity(params, gamma, Omega), wheel_speeds(params, omega, Omega)
    return (
        0.5 * (p.m + p.m0) * dot(v, v)
        + 0.5 * p.I0 * dot(Omega, Omega)
        + 0.5 * dot(omega, matvec(p.I, omega))
        + p.m * dot(v, cross(omega, p.r_m))
        + jnp.sum(p.j * chi_dot * (p.wheel_n @ omega))
        + 0.5 * jnp.sum(p.j * chi_dot**2)
    )


def potential_energy(params: RobotParams, gamma) -> Float[Array, ""]:
    """Potential energy (3.3): `U = m g (r_m, gamma)` [J]."""
    return params.m * params.g * dot(params.r_m, gamma)


def energy(params: RobotParams, gamma, omega, Omega) -> Float[Array, ""]:
    """Total energy `T + U` of (3.2), (3.3) [J]. Conserved when `K = 0`; otherwise
    `d(T + U)/dt = k_tau sum_i K_i chi_dot_i` (see `power`)."""
    gamma, omega, Omega = (jnp.asarray(x, dtype=params.R0.dtype) for x in (gamma, omega, Omega))
    return kinetic_energy(params, gamma, omega, Omega) + potential_energy(params, gamma)


def dissipation(params: RobotParams, gamma, omega, Omega) -> Float[Array, ""]:
    """Power lost to the optional damping terms, `c_axle sum chi_dot_i^2 + c_roll |Omega_h|^2` [W];
    `d(T + U)/dt = power - dissipation`."""
    gamma, omega, Omega = (jnp.asarray(x) for x in (gamma, omega, Omega))
    chi_dot = wheel_speeds(params, omega, Omega)
    Wh = Omega - dot(Omega, gamma) * gamma
    return params.c_axle * jnp.sum(chi_dot**2) + params.c_roll * dot(Wh, Wh)


def power(params: RobotParams, omega, Omega, K) -> Float[Array, ""]:
    """Power of the wheel motors, `k_tau sum_i K_i chi_dot_i` [W] (`K` commanded)."""
    return jnp.sum(params.k_tau * jnp.asarray(K) * wheel_speeds(params, omega, Omega))
