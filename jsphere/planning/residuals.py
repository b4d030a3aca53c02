"""The dimensionless residual vector of a manoeuvre in the search model (`Objective`):
terminal conditions, limit hinges and costs, and its Jacobian."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .problem import Limits, Objective, PlanSettings, gait_from_vector
from .rollout import heading, rollout, tilt2


def _wrap(a):
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def _smooth_abs(x, eps=1e-6):
    return jnp.sqrt(x * x + eps * eps) - eps


def _hinge(v, limit, margin):
    return jax.nn.relu(v / limit - (1.0 - margin))


def _residuals(z, target, params, lim: Limits, obj: Objective, s: PlanSettings):
    """Dimensionless residual vector: terminal conditions, limit hinges, costs (see `Objective`)."""
    gait = gait_from_vector(z, lim, s)
    ro = rollout(params, gait, s.n_steps)
    xt, yt, psi_t, has_psi = target[0], target[1], target[2], target[3]
    R0 = params.R0
    term = [
        (ro.x[-1] - xt) / obj.position_scale,
        (ro.y[-1] - yt) / obj.position_scale,
        R0 * ro.Omega[-1] / obj.speed_scale,
        jnp.atleast_1d(has_psi * _wrap(heading(params, ro) - psi_t) / obj.heading_scale),
    ]
    S = ro.ts.shape[0]
    lw = jnp.sqrt(obj.limit_weight / S)
    lims = []
    if lim.max_torque is not None:
        lims.append(_hinge(jnp.abs(ro.K), lim.max_torque, obj.margin).ravel())
    if lim.max_wheel_speed is not None:
        lims.append(_hinge(jnp.abs(ro.chi_dot), lim.max_wheel_speed, obj.margin).ravel())
    if lim.max_tilt is not None:
        lims.append(jax.nn.relu(tilt2(gait, ro) / lim.max_tilt**2 - (1.0 - obj.margin) ** 2))
    if lim.max_torque_rate is not None:
        rate = jnp.diff(ro.K, axis=0) / (ro.ts[1] - ro.ts[0])
        lims.append(_hinge(jnp.abs(rate), lim.max_torque_rate, obj.margin).ravel())
    h = ro.ts[1] - ro.ts[0]
    energy = h * jnp.sum(_smooth_abs(ro.K * ro.chi_dot))
    effort = h * jnp.sum(ro.K**2)
    costs = jnp.stack(
        [
            jnp.sqrt(obj.energy * energy + 1e-30),
            jnp.sqrt(obj.time * gait.T + 1e-30),
            jnp.sqrt(obj.effort * effort + 1e-30),
        ]
    )
    return jnp.concatenate(
        [jnp.stack(term[:2]), term[2], term[3], lw * jnp.concatenate(lims) if lims else jnp.zeros(0), costs]
    )


def _loss(z, target, params, lim, obj, s):
    r = _residuals(z, target, params, lim, obj, s)
    return jnp.sum(r**2)


def with_jacobian(f):
    """`z -> (f(z), df/dz)` by forward-mode autodiff (one JVP per decision variable): cheaper
    than reverse mode through the RK4 scan (see `docs/performance.md`); Adam's gradient is
    `2 J^T r`."""

    def rj(z):
        J, r = jax.jacfwd(lambda z: (lambda v: (v, v))(f(z)), has_aux=True)(z)
        return r, J

    return rj
