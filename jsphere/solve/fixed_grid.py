"""Classical RK4 on a fixed grid: the integrator of the search models (planner, robust planner,
excitation design), and `Rollout`, the motion it gives.

A fixed grid does the same amount of work for every problem of a `vmap`, and forward-mode
derivatives through it (`jax.jacfwd`, and `jax.grad` of those) are cheap: the searches run many
short integrations at once and re-check their answer with the adaptive solver (`simulate`).
The vector fields are the simulator's own (`jsphere.solve.fields`, `jsphere.gaits`): a field
`f(t, z)` of the flat state (`jsphere.model.state.Flat`).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..model.state import Flat

Field = Callable[[Array, Array], Array]


class Rollout(eqx.Module):
    """A motion on a fixed grid: the times `ts`, the flat states `zs` at them (`Flat`'s layout),
    the wheel rates `chi_dot` (2.4) and, where the caller evaluates them, the axle torques `K`
    (3.4) and the platform's tilt from its rest attitude `tilt` [rad]."""

    ts: Float[Array, " S"]
    zs: Float[Array, "S Z"]
    chi_dot: Float[Array, "S N"]
    K: Float[Array, "S N"] | None = None
    tilt: Float[Array, " S"] | None = None

    @property
    def x(self) -> Float[Array, " S"]:
        return self.zs[:, Flat.x]

    @property
    def y(self) -> Float[Array, " S"]:
        return self.zs[:, Flat.y]

    @property
    def q(self) -> Float[Array, "S 4"]:
        return self.zs[:, Flat.q]

    @property
    def Omega(self) -> Float[Array, "S 3"]:
        return self.zs[:, Flat.Omega]


def uniform_grid(T, n: int, dtype) -> Float[Array, " n+1"]:
    """`n + 1` equally spaced times `k T / n`, `k = 0..n`."""
    return jnp.linspace(0.0, 1.0, n + 1, dtype=dtype) * jnp.asarray(T, dtype)


def rk4_step(f: Field, t, z, h, last: float = 1.0):
    """One classical RK4 step of `h` from `(t, z)`, written as a loop over its stages (stage `i`
    evaluates `f` at `(t + c_i h, z + c_i h k_{i-1})` and adds `w_i k_i`): one `f` in the
    compiled graph, not four. `last`: the last stage's `c_4` (1; just below 1 evaluates a control
    table that ends at `t + h` inside its interval)."""
    dt = z.dtype
    cw = jnp.stack([jnp.array([0.0, 0.5, 0.5, last], dt), jnp.array([1.0, 2.0, 2.0, 1.0], dt) / 6.0], axis=1)

    def stage(carry, c):
        acc, k_prev = carry
        k = f(t + c[0] * h, z + c[0] * h * k_prev)
        return (acc + c[1] * k, k), None

    (acc, _), _ = jax.lax.scan(stage, (jnp.zeros_like(z), jnp.zeros_like(z)), cw)
    return z + h * acc


def integrate(
    f: Field,
    z0: Float[Array, " Z"],
    ts: Float[Array, " S"],
    *,
    substeps: int = 1,
    last: float = 1.0,
    project: Callable[[Array], Array] | None = None,
    save: bool = True,
):
    """Classical RK4 from `z0` at `ts[0]` over the grid `ts`, `substeps` equal steps per interval
    (`rk4_step`; `project` applied to the state after every step, e.g. to normalise a quaternion).
    Returns the states at `ts` `(S, Z)`, or only the last one if `save` is false (pure JAX: jit,
    vmap, jacfwd and grad work)."""
    ts = jnp.asarray(ts, z0.dtype)

    def interval(z, k):
        t, h = ts[k], (ts[k + 1] - ts[k]) / substeps

        def step(z, j):
            z = rk4_step(f, t + j * h, z, h, last)
            return (z if project is None else project(z)), None

        if substeps == 1:
            z, _ = step(z, 0)
        else:
            z, _ = jax.lax.scan(step, z, jnp.arange(substeps, dtype=z0.dtype))
        return z, (z if save else None)

    zT, zs = jax.lax.scan(interval, z0, jnp.arange(ts.shape[0] - 1))
    return jnp.concatenate([z0[None], zs], axis=0) if save else zT
