"""A simulated motion, `Trajectory`, and diagnostics along it: energy, motor power,
constraint residuals."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..model.dynamics import energy, power
from ..model.internal import unflatten
from ..model.kinematics import wheel_speeds
from ..model.linalg import cross
from ..model.params import RobotParams
from ..model.rotations import quat_normalize, rotmat
from ..model.state import Flat, State
from .status import RESULTS


class Trajectory(eqx.Module):
    """A simulated motion sampled at times `ts` (a pytree; batched under `vmap`).

    Fields (platform-frame components unless said otherwise): `ts` [s]; `x, y` [m] (fixed
    frame); `gamma, alpha, beta` (fixed axes seen from the platform); `omega, Omega` [1/s];
    `chi` [rad], `chi_dot` [rad/s] wheel angles and rates; `K` [N m] axle torques (the input in
    torque mode, the torques the motors must supply in wheel-speed and gait modes);
    `q, q_shell` orientation quaternions; `segment`: index of the gait or control segment of
    each sample; `status`: a `RESULTS` code, `0` (`successful`) if the solve succeeded, `1`
    (`max_steps_reached`) if the solver failed, `2` (`nonfinite`) if values became NaN or inf
    (only seen with `throw=False`; `ok` is `status == 0`; `RESULTS.message(status)` explains
    a code); `num_steps`: accepted solver steps.
    """

    ts: Float[Array, " T"]
    x: Float[Array, " T"]
    y: Float[Array, " T"]
    gamma: Float[Array, "T 3"]
    alpha: Float[Array, "T 3"]
    beta: Float[Array, "T 3"]
    omega: Float[Array, "T 3"]
    Omega: Float[Array, "T 3"]
    chi: Float[Array, "T N"]
    chi_dot: Float[Array, "T N"]
    K: Float[Array, "T N"]
    q: Float[Array, "T 4"]
    q_shell: Float[Array, "T 4"]
    segment: Int[Array, " T"]
    status: Int[Array, ""]
    num_steps: Int[Array, ""]

    @property
    def ok(self) -> Bool[Array, ""]:
        """`True` where the solve succeeded (per trial under `vmap`)."""
        return self.status == RESULTS.successful

    def state(self, i: int = -1) -> State:
        """The `State` at sample `i` (default: the last), e.g. to continue a simulation."""
        return _state_at(self, i)


@jax.jit  # one compiled program when called eagerly, not one per operation
def _state_at(traj: Trajectory, i) -> State:
    z = jnp.concatenate(
        [
            traj.q[..., i, :],
            traj.q_shell[..., i, :],
            traj.omega[..., i, :],
            traj.Omega[..., i, :],
            jnp.stack([traj.x[..., i], traj.y[..., i]], -1),
            traj.chi[..., i, :],
        ],
        axis=-1,
    )
    return unflatten(z)


def _rebuild(leaves) -> Trajectory:
    """A `Trajectory` from its leaves (in field order; for a program's runner, `jsphere._runtime.quick_compile.run_program`)."""
    return Trajectory(*leaves)


def assemble(p, d, ts, zs, omega, chi_dot, K, segment, status, num_steps) -> Trajectory:
    """Build a `Trajectory` from flat states `zs (T, 16+N)` and the mode's outputs."""
    q = quat_normalize(zs[:, Flat.q])
    R = rotmat(q)
    return Trajectory(
        ts=ts,
        x=zs[:, Flat.x],
        y=zs[:, Flat.y],
        gamma=R[:, 2],
        alpha=R[:, 0],
        beta=R[:, 1],
        omega=omega,
        Omega=zs[:, Flat.Omega],
        chi=zs[:, Flat.chi],
        chi_dot=chi_dot,
        K=K,
        q=q,
        q_shell=quat_normalize(zs[:, Flat.q_shell]),
        segment=segment,
        status=status,
        num_steps=num_steps,
    )


def raise_on_failure(traj: Trajectory, throw: bool) -> Trajectory:
    """Turn a failed solve into an error (`RESULTS.message` of its code).

    Called outside the compiled solve, so that the compiled function holds no host callback
    and can be kept in JAX's persistent compilation cache. With concrete results (an eager
    call, an eager `jax.grad`) the error is a Python `RuntimeError`; under a user's
    `jit`/`vmap` it is raised by an equinox check at run time, a host callback in the user's
    program, which JAX's persistent cache does not keep (`throw=False` adds none).
    """
    if not throw:
        return traj
    status = traj.status
    if isinstance(status, jax.core.Tracer):  # under an eager `jax.grad` its value is known
        status = jax.lax.stop_gradient(status)
    if isinstance(status, jax.core.Tracer):
        status = jnp.max(status)
        failed = eqx.branched_error_if(traj.x, status != 0, jnp.maximum(status - 1, 0), RESULTS.failure_messages())
        return eqx.tree_at(lambda t: t.x, traj, failed)
    status = int(np.max(np.asarray(status)))
    if status != RESULTS.successful:
        raise RuntimeError(RESULTS.message(status))
    return traj


# ------------------------------------------------------------------------- diagnostics


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
