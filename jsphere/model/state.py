"""The state of the robot: orientation, angular velocities, position, wheel angles."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .kinematics import attitude_matrix
from .linalg import cross
from .params import RobotParams
from .rotations import quat_conj, quat_exp, quat_from_rotmat, quat_log, quat_mul, quat_normalize, rotmat


class Flat:
    """Where each part of the integrator's flat state `[q, q_shell, omega, Omega, x, y, chi]`
    (`State.flatten`, `(16+N,)`) lies: index with these on the last axis, e.g. `z[Flat.Omega]`
    or `zs[:, Flat.x]`. Plain slices and integers, so that they index a tuple of scalar
    components (`jsphere.solve.batched.components`) as well as an array."""

    q = slice(0, 4)
    q_shell = slice(4, 8)
    quats = slice(0, 8)  # q and q_shell
    omega = slice(8, 11)
    Omega = slice(11, 14)
    x = 14
    y = 15
    xy = slice(14, 16)
    chi = slice(16, None)
    #: the number of components before the wheel angles
    size = 16

    @staticmethod
    def replace(z, *, q=None, q_shell=None, omega=None, Omega=None):
        """The 1-D flat state `z` with the parts given replaced."""
        parts = (("q", q), ("q_shell", q_shell), ("omega", omega), ("Omega", Omega))
        return jnp.concatenate([z[getattr(Flat, name)] if v is None else v for name, v in parts] + [z[Flat.x :]])


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


class State(eqx.Module):
    """State of the robot (a pytree; stack states to vmap over initial conditions).

    - `q`: `(4,)` unit quaternion `(w, x, y, z)` of the platform, rotating platform components
      into fixed ones (its rotation matrix is `Q^T` of (2.1), with rows `alpha, beta, gamma`).
    - `q_shell`: `(4,)` unit quaternion of the shell, shell -> fixed components.
    - `omega`, `Omega`: `(3,)` angular velocities of platform and shell, platform components [1/s].
    - `x`, `y`: position of the shell centre in the fixed frame [m].
    - `chi`: `(N,)` wheel rotation angles [rad].

    `alpha, beta, gamma` (the fixed axes `OX, OY, OZ` seen from the platform) are properties.
    """

    q: Float[Array, "4"]
    q_shell: Float[Array, "4"]
    omega: Float[Array, "3"]
    Omega: Float[Array, "3"]
    x: Float[Array, ""]
    y: Float[Array, ""]
    chi: Float[Array, " N"]

    def __check_init__(self):
        leaves = (self.q, self.q_shell, self.omega, self.Omega, self.x, self.y, self.chi)
        if _concrete(*leaves):
            for name, v in zip(("q", "q_shell", "omega", "Omega", "x", "y", "chi"), leaves):
                if not np.all(np.isfinite(np.asarray(v))):
                    raise ValueError(f"State.{name} must be finite; got {np.asarray(v)}.")
            for name in ("q", "q_shell"):
                n = np.linalg.norm(np.asarray(getattr(self, name)), axis=-1)
                if np.any(np.abs(n - 1.0) > 1e-6):
                    raise ValueError(f"State.{name} must be a unit quaternion (w, x, y, z); got norm {n}.")

    # -------------------------------------------------------------- derived views
    @property
    def R(self) -> Float[Array, "3 3"]:
        """Platform -> fixed rotation `Q^T`; rows are `alpha, beta, gamma`."""
        return rotmat(self.q)

    @property
    def alpha(self) -> Float[Array, "3"]:
        return self.R[..., 0, :]

    @property
    def beta(self) -> Float[Array, "3"]:
        return self.R[..., 1, :]

    @property
    def gamma(self) -> Float[Array, "3"]:
        return self.R[..., 2, :]

    # -------------------------------------------------------------- constructors
    @classmethod
    def at_rest(cls, params: RobotParams, *, x=0.0, y=0.0, psi=0.0) -> "State":
        """At rest, the platform's centre of mass straight below C (`gamma = -r_m/|r_m|`), turned
        by the precession angle `psi` about the vertical; for the paper's robot and `psi = 0`,
        `alpha, beta, gamma` are the fixed axes. Shell frame aligned with the fixed frame."""
        return cls(**_rest_fields(params, x, y, psi))

    @classmethod
    def from_axes(
        cls,
        params: RobotParams,
        alpha: Float[ArrayLike, "3"] = (1.0, 0.0, 0.0),
        beta: Float[ArrayLike, "3"] = (0.0, 1.0, 0.0),
        *,
        omega: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0),
        Omega: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0),
        x=0.0,
        y=0.0,
        chi=None,
        q_shell=(1.0, 0.0, 0.0, 0.0),
    ) -> "State":
        """A state from the fixed axes `alpha, beta` seen from the platform (`gamma = alpha x beta`)."""
        dt = params.R0.dtype
        alpha, beta = jnp.asarray(alpha, dt), jnp.asarray(beta, dt)
        if _concrete(alpha, beta):
            a, b = np.asarray(alpha), np.asarray(beta)
            if abs(np.linalg.norm(a) - 1) > 1e-6 or abs(np.linalg.norm(b) - 1) > 1e-6 or abs(a @ b) > 1e-6:
                raise ValueError(f"State.from_axes: alpha and beta must be orthonormal; got {a}, {b}.")
        R = jnp.stack([alpha, beta, cross(alpha, beta)])
        chi = jnp.zeros(params.n_wheels, dt) if chi is None else jnp.asarray(chi, dt)
        return cls(
            q=quat_from_rotmat(R),
            q_shell=quat_normalize(jnp.asarray(q_shell, dt)),
            omega=jnp.asarray(omega, dt),
            Omega=jnp.asarray(Omega, dt),
            x=jnp.asarray(x, dt),
            y=jnp.asarray(y, dt),
            chi=chi,
        )

    # -------------------------------------------------------------- flat layout
    def flatten(self) -> Float[Array, " 16+N"]:
        """The integrator's flat vector `[q, q_shell, omega, Omega, x, y, chi]`."""
        return jnp.concatenate(
            [self.q, self.q_shell, self.omega, self.Omega, jnp.stack([self.x, self.y]), self.chi], axis=-1
        )

    @classmethod
    def unflatten(cls, z: Float[Array, "... 16+N"]) -> "State":
        """The state of a flat vector (`flatten`), not validated: used on traced integrator output."""
        s = object.__new__(cls)
        for name in ("q", "q_shell", "omega", "Omega", "x", "y", "chi"):
            object.__setattr__(s, name, z[..., getattr(Flat, name)])
        return s


@jax.jit  # one compiled program when called eagerly, not one per operation
def _rest_fields(params: RobotParams, x, y, psi) -> dict:
    dt = params.R0.dtype
    Q = attitude_matrix(params, psi)
    z3 = jnp.zeros(3, dt)
    return dict(
        q=quat_from_rotmat(Q.T).astype(dt),
        q_shell=jnp.array([1.0, 0.0, 0.0, 0.0], dt),
        omega=z3,
        Omega=z3,
        x=jnp.asarray(x, dt),
        y=jnp.asarray(y, dt),
        chi=jnp.zeros(params.n_wheels, dt),
    )


#: the size of `state_error`: position (2), attitude (3), `omega` (3), `Omega` (3)
ERROR_SIZE = 11


def state_error(z: Float[Array, " 16+N"], z_ref: Float[Array, " 16+N"]) -> Float[Array, " 11"]:
    """The error of the flat state `z` from the reference `z_ref`, in the tangent space of the
    motion that matters for the shell's path: `(x - x_r, y - y_r, a_1, a_2, a_3, omega - omega_r,
    Omega - Omega_r)`, where `a` is the rotation vector [rad] of `R_r^T R` (the platform's attitude
    relative to the reference's, platform components). The shell's attitude and the wheel
    angles do not enter (the dynamics (3.4), (2.2)-(2.4) do not depend on them)."""
    a = quat_log(quat_mul(quat_conj(z_ref[Flat.q]), z[Flat.q]))
    return jnp.concatenate(
        [z[Flat.xy] - z_ref[Flat.xy], a, z[Flat.omega] - z_ref[Flat.omega], z[Flat.Omega] - z_ref[Flat.Omega]]
    )


def state_plus(z_ref: Float[Array, " 16+N"], e: Float[Array, " 11"]) -> Float[Array, " 16+N"]:
    """The flat state at the error `e` (as `state_error`) from `z_ref`: `R = R_r exp(a)`, the other
    parts added; the shell's attitude and the wheel angles as in `z_ref`. The inverse of
    `state_error`: `state_error(state_plus(z_r, e), z_r) = e` for `|a| < pi`."""
    q = quat_mul(z_ref[Flat.q], quat_exp(e[2:5]))
    out = Flat.replace(z_ref, q=q, omega=z_ref[Flat.omega] + e[5:8], Omega=z_ref[Flat.Omega] + e[8:11])
    return out.at[Flat.xy].add(e[0:2])
