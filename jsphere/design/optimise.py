"""The search of an excitation design: Adam (optax) on the D-optimal criterion minus a penalty
for the limits the programmes do not keep by construction, every random restart under one
`vmap`.

Objective (maximised) of the coefficients `z`:

    Phi(z) - weight sum_c sum(max(0, v_c / limit_c - (1 - margin))^2)

over the wheel rates `|chi_dot_i|` (torque inputs; wheel-speed inputs keep their limit by
construction), the torque rates `|dK_i/dt|` (torque inputs) and the platform's tilt from its
rest attitude, each on the model grid of every trial (`jsphere.solve.fixed_grid.Rollout`).
The torques of torque programmes keep `max_torque` by construction (`jsphere.design.inputs`).
The gradient is `jax.grad` of `Phi` through the forward-mode Jacobian (reverse over forward).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from ..model.limits import Limits
from .information import Problem
from .inputs import coefficients, programme

#: weight of the limit penalty, and the margin below each limit where it starts
PENALTY_WEIGHT = 1e3
MARGIN = 0.03


def _hinge(v, limit):
    if limit is None:
        return jnp.zeros((), v.dtype)
    return jnp.sum(jnp.maximum(0.0, jnp.abs(v) / limit - (1.0 - MARGIN)) ** 2)


def extremes(pr: Problem, z, ro) -> tuple[Float[Array, "3"], Float[Array, "M S N"]]:
    """The largest wheel rate `|chi_dot_i|` [rad/s], platform tilt [rad] and input rate
    `|du_i/dt|` (N m/s for torques) of the programmes `z` on the model grid (`ro`: their
    rollouts, batched over trials), and the input rates `du_i/dt` themselves."""
    ts = jnp.asarray(pr.grid.times(pr.spec.duration), z.dtype)

    def rate(c):
        prog = programme(c, pr.spec)
        return jax.vmap(lambda t: jax.jvp(prog, (t,), (jnp.ones_like(t),))[1])(ts)

    du = jax.vmap(rate)(coefficients(z, pr.spec))
    return jnp.stack([jnp.max(jnp.abs(ro.chi_dot)), jnp.max(ro.tilt), jnp.max(jnp.abs(du))]), du


def penalty(pr: Problem, z, ro, lim: Limits):
    """The limit penalty (module docstring, without the weight) of the programmes `z` and their
    rollouts `ro` (batched over trials), and `extremes`."""
    ext, du = extremes(pr, z, ro)
    total = _hinge(ro.tilt, lim.max_tilt)
    if pr.spec.kind == "K":
        total = total + _hinge(ro.chi_dot, lim.max_wheel_speed) + _hinge(du, lim.max_torque_rate)
    return total, ext


def objective(z, pr: Problem, lim: Limits):
    """`(objective, (Phi, penalty, extremes))` of the coefficients `z` (module docstring)."""
    Fs, ro = pr.information(z)
    phi = jnp.linalg.slogdet(Fs)[1]
    pen, ext = penalty(pr, z, ro, lim)
    return phi - PENALTY_WEIGHT * pen, (phi, pen, ext)


@eqx.filter_jit
def _value_and_grad(zs, pr: Problem, lim: Limits):
    return jax.vmap(jax.value_and_grad(objective, has_aux=True), in_axes=(0, None, None))(zs, pr, lim)


#: `objective` of one coefficient vector `z (V,)`, compiled
evaluate = eqx.filter_jit(objective)


def maximise(
    z0s: np.ndarray,
    pr: Problem,
    lim: Limits,
    *,
    steps: int,
    learning_rate: float = 0.05,
    on_step: Callable[[int, np.ndarray, np.ndarray, np.ndarray], None] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Adam ascent of every start `z0s (R, V)` at once (`steps` steps). Returns the best point
    of each start (by objective), its objective, `Phi` and penalty; `on_step(k, objective, Phi,
    penalty)` is called after every step with those of each start's best point so far.
    Non-finite objectives (a programme whose model fails) are never kept, and their gradients
    are zeroed."""
    opt = optax.adam(learning_rate)
    z = jnp.asarray(z0s)
    state = opt.init(z)
    R = z.shape[0]
    best_z = np.array(z0s, dtype=np.float64)
    best = np.full(R, -np.inf)
    best_phi = np.full(R, np.nan)
    best_pen = np.full(R, np.nan)
    for k in range(steps + 1):
        (obj, (phi, pen, _)), g = _value_and_grad(z, pr, lim)
        obj, phi, pen = np.asarray(obj), np.asarray(phi), np.asarray(pen)
        ok = np.isfinite(obj)
        better = ok & (obj > best)
        best_z[better] = np.asarray(z)[better]
        best[better], best_phi[better], best_pen[better] = obj[better], phi[better], pen[better]
        if on_step is not None:
            on_step(k, best, best_phi, best_pen)
        if k == steps:
            break
        g = jnp.where(jnp.isfinite(g) & jnp.asarray(ok)[:, None], g, 0.0)
        upd, state = opt.update(-g, state, z)
        z = optax.apply_updates(z, upd)
    return best_z, best, best_phi, best_pen


def limit_values(pr: Problem, ext, tables, lim: Limits) -> list[tuple[str, float, float | None]]:
    """`(name, largest value, limit)` of every limit of the input kind: the input itself from the
    written `tables`, the others from `extremes` (`ext`) on the model grid."""
    u_max = max(float(np.max(np.abs(u))) for _, u in tables)
    chi, tilt, rate = (float(v) for v in ext)
    if pr.spec.kind == "K":
        entries = [
            ("torque_N_m", u_max, lim.max_torque),
            ("torque_rate_N_m_s", rate, lim.max_torque_rate),
            ("wheel_speed_rad_s", chi, lim.max_wheel_speed),
        ]
    else:
        entries = [("wheel_speed_rad_s", u_max, lim.max_wheel_speed)]
    return entries + [("tilt_rad", tilt, lim.max_tilt)]


def limits_report(entries) -> dict[str, dict[str, float | bool | None]]:
    """Per limit its largest value, the limit and whether it is kept (`limit_values`)."""
    return {
        name: {"max": v, "limit": limit, "ok": True if limit is None else bool(v <= limit * (1 + 1e-9))}
        for name, v, limit in entries
    }
