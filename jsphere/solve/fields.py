"""The vector fields of torque and wheel-speed mode on the flat state, their outputs, and the
torque field on scalar components (for batched solves)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..controls import WheelSpeeds
from ..model.dynamics import servo_accelerations, solve_accelerations
from ..model.linalg import cross, matvec
from ..model.params import Derived, RobotParams
from ..model.rotations import quat_rate_body, quat_rate_fixed, rotmat
from ..model.state import Flat
from .batched.components import torque_field_components, unit
from .field_args import FieldArgs


def _left_limit(b):
    """The largest float below `b`: evaluates a control on the left side of a jump at `b`."""
    return jnp.nextafter(b, jnp.asarray(-jnp.inf, dtype=jnp.result_type(b)))


def _control_time(t, t_end):
    """The time at which a control is evaluated: `t`, or the left limit at `t_end` from it on."""
    if t_end is None:
        return t
    return jnp.where(t >= t_end, _left_limit(jax.lax.stop_gradient(t_end)), t)


def _rates(p: RobotParams, d: Derived, z, R, gamma, omega, Omega, omega_dot, Omega_dot, w):
    """The flat state's rates in every mode from the accelerations and the wheels' relative
    rate `w = omega - Omega` (`chi_dot = -S_k w`, (2.4)), with `R = Q^T` computed once by the
    caller (`gamma` is its last row, or the prescribed `gamma(t)` of a gait)."""
    v = p.R0 * cross(Omega, gamma)
    vf = matvec(R, v)  # fixed-frame velocity; (x_dot, y_dot) = ((alpha, v), (beta, v))
    dq, dqs = quat_rate_body(z[Flat.q], omega), quat_rate_fixed(z[Flat.q_shell], matvec(R, Omega))
    return jnp.concatenate([dq, dqs, omega_dot, Omega_dot, vf[:2], -matvec(d.Sk, w)])


def _torque_field(t, z, args: FieldArgs):
    """(3.4), (3.5) with (2.2)-(2.4) in torque mode: the flat state's rates."""
    p, d = args.params, args.derived
    omega, Omega = z[Flat.omega], z[Flat.Omega]
    R = rotmat(z[Flat.q])
    gamma = R[2]
    K = _torque_control(t, args)
    omega_dot, Omega_dot = solve_accelerations(p, d, gamma, omega, Omega, K)
    return _rates(p, d, z, R, gamma, omega, Omega, omega_dot, Omega_dot, omega - Omega)


def _torque_control(t, args: FieldArgs):
    """The axle torques `K(t)` of a torque-mode segment (left limit at its end)."""
    return args.control(_control_time(t, args.t_end))


def _torque_field_soa(t, y, args: FieldArgs, K=None, adjoint=False):
    """`_torque_field` on a tuple of scalar components (`jsphere.solve.batched.components`), for
    batched solves; `K`: the torques as a tuple of scalars, if the caller has evaluated them
    already; `adjoint`: the form the batch loop's discrete adjoint differentiates."""
    if K is None:
        K = _torque_control(t, args)
        K = tuple(K[..., i] for i in range(K.shape[-1]))
    return torque_field_components(args.params, args.derived, K, y, unit(t), adjoint=adjoint)


def _servo_inputs(d: Derived, control: WheelSpeeds, t):
    u, u_dot = control.value_and_rate(t)
    return -matvec(d.Sk_pinv, u), -matvec(d.Sk_pinv, u_dot)


def _wheel_field(t, z, args: FieldArgs):
    """Wheel-speed mode (servo constraints): the flat state's rates."""
    p, d = args.params, args.derived
    Omega = z[Flat.Omega]
    R = rotmat(z[Flat.q])
    gamma = R[2]
    w, w_dot = _servo_inputs(d, args.control, _control_time(t, args.t_end))
    omega, omega_dot, Omega_dot, _ = servo_accelerations(p, d, gamma, Omega, w, w_dot)
    return _rates(p, d, z, R, gamma, omega, Omega, omega_dot, Omega_dot, w)


def _outputs_torque(t, z, args: FieldArgs):
    """`(omega, chi_dot, K)` at a saved state in torque mode."""
    omega, Omega = z[Flat.omega], z[Flat.Omega]
    return omega, -matvec(args.derived.Sk, omega - Omega), _torque_control(t, args)


def _outputs_wheel(t, z, args: FieldArgs):
    """`(omega, chi_dot, K)` at a saved state in wheel-speed mode."""
    p, d = args.params, args.derived
    Omega = z[Flat.Omega]
    gamma = rotmat(z[Flat.q])[2]
    w, w_dot = _servo_inputs(d, args.control, _control_time(t, args.t_end))
    omega, _, _, K = servo_accelerations(p, d, gamma, Omega, w, w_dot)
    return omega, -matvec(d.Sk, w), K
