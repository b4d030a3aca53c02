"""The model's flow over one control interval with the torques held (zero-order hold), the
reference motion it gives, and its Jacobians in the error coordinates of `state_error`.

The flow is the torque-mode vector field of (3.4), (3.5) with (2.2)-(2.4) (the one `simulate`
integrates) advanced by the search models' classical RK4 (`jsphere.solve.fixed_grid`) on the control grid; at the
control rates a robot runs (100 Hz and up, steps of at most `1 / rate`) its error against the
adaptive solver is far below the millimetre (test `test_flow_matches_simulate`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ...model.params import Derived, RobotParams, derive
from ...model.state import ERROR_SIZE, state_error, state_plus
from ...solve.field_args import FieldArgs
from ...solve.fixed_grid import rk4_step
from ...solve.internal import torque_field


def interval(p: RobotParams, d: Derived, z: Float[Array, " S"], K: Float[Array, " N"], h, substeps: int = 1):
    """The flat state after `h` seconds of the torques `K` held from the state `z`: `substeps`
    classical RK4 steps of the torque-mode field (pure JAX)."""
    args = FieldArgs(params=p, derived=d, control=lambda t: K)

    def f(z):
        return torque_field(jnp.zeros((), z.dtype), z, args)

    def step(z, _):
        return rk4_step(lambda t, z: f(z), 0.0, z, h / substeps), None

    z, _ = jax.lax.scan(step, z, None, length=substeps)
    return z


@eqx.filter_jit
def reference(p: RobotParams, z0: Float[Array, " S"], K: Float[Array, "M N"], h, substeps: int = 1):
    """The reference motion: the states `(M + 1, S)` at the row times of the feed-forward
    torques `K (M, N)` held row by row from `z0` on the robot `p`."""
    d = derive(p)

    def body(z, k):
        zn = interval(p, d, z, k, h, substeps)
        return zn, zn

    _, zs = jax.lax.scan(body, z0, K)
    return jnp.concatenate([z0[None], zs], axis=0)


@eqx.filter_jit
def linearise(
    p: RobotParams, zs: Float[Array, "M S"], K: Float[Array, "M N"], z_next: Float[Array, "M S"], h, substeps: int = 1
):
    """The Jacobians `A (M, 11, 11)`, `B (M, 11, N)` of the interval map in error coordinates:
    `e_{k+1} = state_error(interval(state_plus(z_k, e_k), K_k + du_k), z_next_k) ~ A_k e_k + B_k du_k`,
    by forward-mode differentiation through the RK4 steps (`jax.jacfwd`), vmapped over the
    intervals."""
    d = derive(p)
    N = K.shape[-1]

    def one(z, k, zn):
        def g(e, du):
            return state_error(interval(p, d, state_plus(z, e), k + du, h, substeps), zn)

        return jax.jacfwd(g, argnums=(0, 1))(jnp.zeros(ERROR_SIZE, z.dtype), jnp.zeros(N, z.dtype))

    return jax.vmap(one)(zs, K, z_next)
