"""Gait optimisation / motion planning (issue 4): rest-to-rest manoeuvres to a goal pose
within motor limits, found by gradients through the gait dynamics of Section 4.

A manoeuvre is one `TiltGait` (`jsphere.gaits.families`) with `Smooth` profiles: tilt vector
`u(t)` (two rows of Fourier-cosine coefficients times `sin^3(pi t/T)`), spin `omega_gamma(t)`
and a free duration `T`. It starts and ends on the Proposition's stationary motion by
construction (`gamma = gamma_m`, `gamma_dot = 0`, `omega_gamma = 0`; with `sin^3` the torques
also start and end at 0). `Omega(t)` follows the control-free sum of (3.4); being at rest at
`T` (`Omega(T) = 0`) is a terminal condition, like the position and heading.

Search (everything under one `jit`, vmapped over restarts x targets): a fixed-step RK4
integration of the same vector field as `simulate_gaits` (`n_steps` steps), Adam then
L-BFGS (optax) on a least-squares objective, the best restart per target, then
Levenberg-Marquardt on the terminal conditions (forward-mode Jacobian). Verification: the
accurate adaptive `simulate_gaits` (Dopri8, rtol 1e-10) on the output grid, with exact limit
checks; a Newton step with the RK4 Jacobian corrects the small RK4 bias if needed.
See `docs/planning.md`.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from .._runtime.checks import is_number, real, whole
from .._runtime.errors import InputError
from ..gaits.families import TiltGait, smooth_gait
from ..gaits.gaits import _gait_field, _gait_outputs, simulate_gaits
from ..model.kinematics import rest_attitude
from ..model.rotations import rotation_between, rotmat
from ..model.params import RobotParams, derive
from ..solve.simulate import Trajectory
from ..model.state import State


class Limits(eqx.Module):
    """Motor and motion limits (SI). `None` switches a limit off.

    Defaults for the paper's robot (whose motors the paper does not specify): the paper's own
    gaits need at most 0.011 N m and 4.8 rad/s; a 1.4 m rest-to-rest run in 8 s needs about
    0.02 N m and 15 rad/s. The defaults leave room for that and are typical of small geared
    DC motors: `max_torque = 0.1` N m per wheel, `max_wheel_speed = 20` rad/s (191 rpm),
    `max_tilt = 0.35` rad (20 deg, platform tilt `theta = |u|`), `max_torque_rate = 1` N m/s,
    `max_time = 12` s (upper bound of the duration `T`), `min_time = 1` s.
    """

    max_torque: float | None = 0.1
    max_wheel_speed: float | None = 20.0
    max_tilt: float | None = 0.35
    max_torque_rate: float | None = 1.0
    max_time: float = 12.0
    min_time: float = 1.0

    def __check_init__(self):
        for name in ("max_torque", "max_wheel_speed", "max_tilt", "max_torque_rate"):
            v = getattr(self, name)
            if v is not None and not _traced(v) and not (is_number(v) and float(v) > 0):
                raise InputError(f"Limits.{name} must be a positive number (or None for no limit); got {v!r}.")
        for name in ("min_time", "max_time"):
            v = getattr(self, name)
            if not _traced(v) and not (is_number(v) and math.isfinite(v)):
                raise InputError(f"Limits.{name} must be a finite number of seconds; got {v!r}.")
        if not _traced(self.min_time, self.max_time) and not 0 < float(self.min_time) < float(self.max_time):
            raise InputError(f"Limits: need 0 < min_time < max_time; got {self.min_time}, {self.max_time}.")


class Objective(eqx.Module):
    """A composed least-squares objective `sum r^2` (all residuals dimensionless).

    Terminal conditions: `(x(T), y(T)) - target` / `position_scale` [m]; `R0 Omega(T)` /
    `speed_scale` [m/s] (rest); heading error / `heading_scale` [rad] when a heading is asked.
    Limits (`Limits`): squared hinge `limit_weight * mean(max(0, v/limit - (1 - margin))^2)` for
    `|K_i|`, `|chi_dot_i|`, tilt, `|dK_i/dt|`. Costs (weights >= 0, default off): `energy` per
    joule of `int sum |K_i chi_dot_i| dt` (motor energy), `time` per second of `T`, `effort`
    per `N^2 m^2 s` of `int sum K_i^2 dt`.
    """

    position_scale: float = 1e-3
    speed_scale: float = 1e-3
    heading_scale: float = 1e-3
    limit_weight: float = 1e4
    margin: float = 0.03
    energy: float = 0.0
    time: float = 1e-3
    effort: float = 0.0

    def __check_init__(self):
        for name in ("position_scale", "speed_scale", "heading_scale"):
            if not _traced(getattr(self, name)):
                real("Objective", name, getattr(self, name), strict=True)
        for name in ("limit_weight", "energy", "time", "effort"):
            if not _traced(getattr(self, name)):
                real("Objective", name, getattr(self, name))
        if not _traced(self.margin) and not (is_number(self.margin) and 0 <= self.margin < 1):
            raise InputError(f"Objective.margin must be a number in [0, 1); got {self.margin!r}.")


class PlanSettings(eqx.Module):
    """Sizes of the search (static: they fix the compiled function).

    `n_tilt`: Fourier terms per tilt axis; `n_spin`: spin terms; `n_steps`: RK4 steps of the
    search model; `adam_steps`, `lbfgs_steps`, `lm_steps`: iterations; `learning_rate`: Adam's.
    """

    n_tilt: int = eqx.field(static=True, default=5)
    n_spin: int = eqx.field(static=True, default=3)
    n_steps: int = eqx.field(static=True, default=48)
    adam_steps: int = eqx.field(static=True, default=150)
    lbfgs_steps: int = eqx.field(static=True, default=0)
    lm_steps: int = eqx.field(static=True, default=40)
    learning_rate: float = eqx.field(static=True, default=0.02)

    def __check_init__(self):
        for name in ("n_tilt", "n_spin", "n_steps"):
            whole("PlanSettings", name, getattr(self, name), 1)
        for name in ("adam_steps", "lbfgs_steps", "lm_steps"):
            whole("PlanSettings", name, getattr(self, name), 0)
        real("PlanSettings", "learning_rate", self.learning_rate, strict=True)


def _traced(*vs) -> bool:
    return any(isinstance(v, (jax.core.Tracer, jax.Array)) for v in vs)


#: the most rows a plan's table may have (`max_time * rate`): about 1 GB of trajectory
MAX_ROWS = 10_000_000


def _check_request(where: str, targets, limits, objective, settings, restarts, rate, seed, tols=(), nan_free=True) -> list:
    """Check a planning request before any work; return the targets as lists.
    Raises `InputError` naming the value: targets `(x, y)` or `(x, y, psi)` with finite
    numbers (`psi` None, or NaN with `nan_free`, for a free heading), `restarts >= 1`,
    `rate > 0`, `seed >= 0`, positive tolerances, and `Limits`, `Objective`, `PlanSettings`
    instances."""
    for name, v, cls in (("limits", limits, Limits), ("objective", objective, Objective), ("settings", settings, PlanSettings)):
        if v is not None and not isinstance(v, cls):
            raise InputError(f"{where}: {name} must be a jsphere.{cls.__name__}; got {type(v).__name__}.")
    whole(where, "restarts", restarts, 1)
    whole(where, "seed", seed, 0)
    rate = real(where, "rate", rate, strict=True, unit="Hz")
    for name, v in tols:
        real(where, name, v, strict=True)
    lim = limits or Limits()
    if lim.max_time * rate > MAX_ROWS:
        raise InputError(f"{where}: rate = {rate:g} Hz makes {lim.max_time * rate:.3g} rows over max_time = {lim.max_time:g} s "
                         f"(at most {MAX_ROWS:.0e}); lower the rate.")  # fmt: skip
    if isinstance(targets, (str, bytes)) or not isinstance(targets, Sequence) or not len(targets):
        raise InputError(f"{where}: targets must be a non-empty list of (x, y) or (x, y, heading); got {targets!r}.")
    out = []
    for k, t in enumerate(targets):
        if isinstance(t, (str, bytes)) or not isinstance(t, (Sequence, np.ndarray)) or len(t) not in (2, 3):
            raise InputError(f"{where}: target {k} must be (x, y) or (x, y, heading); got {t!r}.")
        t = list(t)
        for i, name in enumerate(("x", "y")):
            real(where, f"target {name}" if len(targets) == 1 else f"target {k} {name}", t[i], low=None, unit="m")
        if len(t) == 3 and t[2] is not None and not (nan_free and is_number(t[2]) and math.isnan(t[2])):
            real(where, "heading" if len(targets) == 1 else f"target {k} heading", t[2], low=None, unit="rad")
        out.append(t)
    return out


# ------------------------------------------------------------------ parameterisation


def _n_vars(s: PlanSettings) -> int:
    return 2 * s.n_tilt + s.n_spin + 1


def _duration(tau, lim: Limits):
    return lim.min_time + (lim.max_time - lim.min_time) * jax.nn.sigmoid(tau)


def _duration_inv(T, lim: Limits):
    f = (T - lim.min_time) / (lim.max_time - lim.min_time)
    return jnp.log(f) - jnp.log1p(-f)


def gait_from_vector(z: Float[Array, " V"], lim: Limits, s: PlanSettings) -> TiltGait:
    """The manoeuvre of the decision vector `z = (a_1 (n), a_2 (n), b (m), tau)`: tilt
    coefficients [rad], spin coefficients [rad/s], `T = min_time + (max_time - min_time)
    sigmoid(tau)` [s]."""
    n, m = s.n_tilt, s.n_spin
    T = _duration(z[-1], lim)
    return smooth_gait(z[: 2 * n].reshape(2, n), z[2 * n : 2 * n + m], T, power=3)


# ------------------------------------------------------------------ search model (RK4)


class Rollout(eqx.Module):
    """The search model's motion on `n_steps + 1` equally spaced times of `[0, T]`."""

    ts: Float[Array, " S"]
    x: Float[Array, " S"]
    y: Float[Array, " S"]
    Omega: Float[Array, "S 3"]
    chi_dot: Float[Array, "S N"]
    K: Float[Array, "S N"]
    tilt2: Float[Array, " S"]
    heading: Float[Array, ""]


def _heading(R, Qm):
    """Platform yaw `psi` [rad] from `R = Q^T` (rows `alpha, beta, gamma`): `R Q_m = Q_psi^T`."""
    M = R @ Qm
    return jnp.arctan2(M[1, 0], M[0, 0])


def rollout(params: RobotParams, gait: TiltGait, n_steps: int) -> Rollout:
    """Integrate a gait from rest with classical RK4 (`n_steps` steps of `T/n_steps`), using
    `simulate_gaits`' own vector field (control-free sum of (3.4) for `Omega`, (2.2)-(2.4)).

    With `n_steps = 96` and `T <= 12` s the final position agrees with the adaptive solver to
    about 1e-5 m (test `test_rollout_matches_simulate_gaits`); used inside the search only.
    """
    p = params
    d = derive(p)
    dt = p.R0.dtype
    Qm = rotation_between(jnp.array([0.0, 0.0, 1.0], dt), rest_attitude(p))
    T = jnp.asarray(gait.T, dt)
    h = T / n_steps
    args = (p, d, (gait, Qm), jnp.zeros((), dt), T)

    def f(t, z):
        return _gait_field(t, z, args)

    # classical RK4 written as a loop over its stages: stage i evaluates f at
    # (t + c_i h, z + c_i h k_{i-1}) and adds w_i k_i; one f in the compiled graph, not four
    c = jnp.array([0.0, 0.5, 0.5, 1.0], dt)
    w = jnp.array([1.0, 2.0, 2.0, 1.0], dt) / 6.0

    def step(z, k):
        t = k * h

        def stage(carry, cw):
            acc, k_prev = carry
            ki = f(t + cw[0] * h, z + cw[0] * h * k_prev)
            return (acc + cw[1] * ki, ki), None

        (acc, _), _ = jax.lax.scan(stage, (jnp.zeros_like(z), jnp.zeros_like(z)), jnp.stack([c, w], axis=1))
        return z + h * acc, z

    z0 = State.at_rest(p).flatten().astype(dt)
    zT, zs = jax.lax.scan(step, z0, jnp.arange(n_steps, dtype=dt))
    zs = jnp.concatenate([zs, zT[None]], axis=0)
    ts = jnp.linspace(0.0, 1.0, n_steps + 1, dtype=dt) * T
    _, chi_dot, K = jax.vmap(lambda t, z: _gait_outputs(p, d, (gait, Qm), t, z, 0.0, T))(ts, zs)
    u = jax.vmap(gait.tilt)(ts)
    return Rollout(
        ts=ts, x=zs[:, 14], y=zs[:, 15], Omega=zs[:, 11:14], chi_dot=chi_dot, K=K,
        tilt2=jnp.sum(u**2, axis=-1), heading=_heading(rotmat(zT[0:4]), Qm),
    )  # fmt: skip


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
        jnp.atleast_1d(has_psi * _wrap(ro.heading - psi_t) / obj.heading_scale),
    ]
    S = ro.ts.shape[0]
    lw = jnp.sqrt(obj.limit_weight / S)
    lims = []
    if lim.max_torque is not None:
        lims.append(_hinge(jnp.abs(ro.K), lim.max_torque, obj.margin).ravel())
    if lim.max_wheel_speed is not None:
        lims.append(_hinge(jnp.abs(ro.chi_dot), lim.max_wheel_speed, obj.margin).ravel())
    if lim.max_tilt is not None:
        lims.append(jax.nn.relu(ro.tilt2 / lim.max_tilt**2 - (1.0 - obj.margin) ** 2))
    if lim.max_torque_rate is not None:
        rate = jnp.diff(ro.K, axis=0) / (ro.ts[1] - ro.ts[0])
        lims.append(_hinge(jnp.abs(rate), lim.max_torque_rate, obj.margin).ravel())
    h = ro.ts[1] - ro.ts[0]
    energy = h * jnp.sum(_smooth_abs(ro.K * ro.chi_dot))
    effort = h * jnp.sum(ro.K**2)
    costs = jnp.stack([
        jnp.sqrt(obj.energy * energy + 1e-30), jnp.sqrt(obj.time * gait.T + 1e-30), jnp.sqrt(obj.effort * effort + 1e-30),
    ])  # fmt: skip
    return jnp.concatenate(
        [jnp.stack(term[:2]), term[2], term[3], lw * jnp.concatenate(lims) if lims else jnp.zeros(0), costs]
    )


def _loss(z, target, params, lim, obj, s):
    r = _residuals(z, target, params, lim, obj, s)
    return jnp.sum(r**2)


# ------------------------------------------------------------------ optimisers (pure JAX)


def _adam(z0, target, params, lim, obj, s):
    opt = optax.adam(s.learning_rate)
    vg = jax.value_and_grad(_loss)

    def body(carry, _):
        z, st = carry
        v, g = vg(z, target, params, lim, obj, s)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        up, st = opt.update(g, st, z)
        return (optax.apply_updates(z, up), st), v

    (z, _), hist = jax.lax.scan(body, (z0, opt.init(z0)), None, length=s.adam_steps)
    return z, hist


def _lbfgs(z0, target, params, lim, obj, s):
    def f(z):
        return _loss(z, target, params, lim, obj, s)

    opt = optax.lbfgs()
    vg = optax.value_and_grad_from_state(f)

    def body(carry, _):
        z, st = carry
        v, g = vg(z, state=st)
        up, st_new = opt.update(g, st, z, value=v, grad=g, value_fn=f)
        z_new = optax.apply_updates(z, up)
        good = jnp.all(jnp.isfinite(z_new))
        return (jnp.where(good, z_new, z), jax.tree_util.tree_map(lambda a, b: jnp.where(good, a, b), st_new, st)), v

    (z, _), hist = jax.lax.scan(body, (z0, opt.init(z0)), None, length=s.lbfgs_steps)
    return z, hist


def _residuals_and_jacobian(z, target, params, lim, obj, s):
    """`(r, dr/dz)` by forward-mode autodiff (one JVP per decision variable): cheaper than
    reverse mode through the RK4 scan (measured 7 vs 21 ms per problem on 2 CPU cores) and
    it gives LM its Jacobian for free."""

    def r(z):
        out = _residuals(z, target, params, lim, obj, s)
        return out, out

    J, res = jax.jacfwd(r, has_aux=True)(z)
    return res, J


def _search_one(z0, target, params, lim, obj, s):
    """Adam (`adam_steps`) then Levenberg-Marquardt (`lm_steps`) in one `lax.scan` whose body
    evaluates the residuals and their Jacobian once (so the model is compiled once).

    LM with delayed acceptance: each iteration evaluates the candidate of the previous one; it
    is accepted (damping / 3) if it lowers `sum r^2`, else the damping grows x 4 and a new
    step is taken from the best point. Returns the best point, its loss, its Jacobian and the
    loss history."""
    opt = optax.adam(s.learning_rate)
    V = z0.shape[0]
    eye = jnp.eye(V, dtype=z0.dtype)

    def body(c, k):
        z, zb, rb, Jb, fb, lam, st = c
        r, J = _residuals_and_jacobian(z, target, params, lim, obj, s)
        f = jnp.sum(r**2)
        ok = jnp.isfinite(f) & jnp.all(jnp.isfinite(J))
        better = ok & (f < fb)
        zb, rb, Jb, fb = (jnp.where(better, a, b) for a, b in ((z, zb), (r, rb), (J, Jb), (f, fb)))
        # Adam step from the current point
        g = jnp.where(ok, 2.0 * J.T @ r, 0.0)
        up, st_new = opt.update(g, st, z)
        z_adam = jnp.where(ok, optax.apply_updates(z, up), zb)
        # LM step from the best point
        lm_phase = k >= s.adam_steps
        grow = jnp.where(better, jnp.maximum(lam / 3.0, 1e-12), jnp.minimum(lam * 4.0, 1e12))
        lam = jnp.where(k > s.adam_steps, grow, lam)
        JtJ = Jb.T @ Jb
        step = -jnp.linalg.solve(JtJ + lam * (jnp.diag(jnp.diag(JtJ)) + 1e-9 * eye), Jb.T @ rb)
        z_lm = zb + jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
        z_next = jnp.where(lm_phase, z_lm, z_adam)
        return (z_next, zb, rb, Jb, fb, lam, st_new), f

    r0 = _residuals(z0, target, params, lim, obj, s)
    c0 = (z0, z0, jnp.zeros_like(r0), jnp.zeros((r0.shape[0], V), z0.dtype), jnp.asarray(jnp.inf, z0.dtype),
          jnp.asarray(1e-3, z0.dtype), opt.init(z0))  # fmt: skip
    c, hist = jax.lax.scan(body, c0, jnp.arange(s.adam_steps + s.lm_steps + 1))
    _, zb, _, Jb, fb, _, _ = c
    return zb, fb, Jb, hist


@eqx.filter_jit
def _search(params, targets, z0s, lim, obj, s):
    """Every (target, restart) pair in one vmap (`targets (B, 4)`, `z0s (B, R, V)`): optional
    L-BFGS warm-up (`lbfgs_steps`), Adam then LM (`_search_one`); the best restart of each
    target is kept. Returns `(z (B, V), loss (B, R), best (B,), J (B, M, V), history (B, R, I))`."""
    B, R, V = z0s.shape
    tgt = jnp.repeat(targets, R, axis=0)
    flat = z0s.reshape(B * R, V)
    if s.lbfgs_steps:
        flat, _ = jax.vmap(lambda z, t: _lbfgs(z, t, params, lim, obj, s))(flat, tgt)
    zb, fb, Jb, hist = jax.vmap(lambda z, t: _search_one(z, t, params, lim, obj, s))(flat, tgt)
    loss = jnp.where(jnp.isfinite(fb), fb, jnp.inf).reshape(B, R)
    best = jnp.argmin(loss, axis=1)
    pick = jnp.arange(B) * R + best
    return zb[pick], loss, best, Jb[pick], hist.reshape(B, R, -1)


def _distance_gain(params: RobotParams) -> float:
    """`kappa` [m/s^2 per rad] of the small-tilt estimate `x(T) ~ kappa int_0^T int_0^t theta`:
    near rest the control-free sum of (3.4) reads `(B + D) Omega_dot ~ m g R_m theta e2 - ...`,
    the `theta_ddot` term integrates out over a rest-to-rest gait, and `x_dot = R0 Omega_2`.
    For the paper's robot `kappa = 1.298`; the distance of the accelerate-brake profile
    `a sin^3(pi s) cos(pi s)` is then `kappa a T^2 3/(32 pi)` (0.03099 m for a = 0.05, T = 4 s;
    the simulation gives 0.03098 m)."""
    from ..model.dynamics import mass_blocks

    d = derive(params)
    gm = rest_attitude(params)
    Qm = np.asarray(rotation_between(jnp.array([0.0, 0.0, 1.0], params.R0.dtype), gm))
    B, D = mass_blocks(params, d, gm)
    M = Qm.T @ np.asarray(B + D) @ Qm
    R_m = float(np.linalg.norm(np.asarray(params.r_m)))
    return float(params.R0) * float(params.m) * float(params.g) * R_m / float(M[1, 1])


def _initial_guesses(params, targets, restarts, lim, s, seed):
    """Restarts: the accelerate-brake profile towards the target (amplitude from the small-tilt
    distance estimate `_distance_gain`), random durations, random extra Fourier terms and spin;
    restart 0 without noise, at the duration where its peak tilt is half the tilt limit."""
    kappa = _distance_gain(params)
    n, m = s.n_tilt, s.n_spin
    B = targets.shape[0]
    rng = np.random.default_rng(seed)
    z = np.zeros((B, restarts, _n_vars(s)))
    tmin = max(lim.min_time * 1.05, min(3.0, 0.5 * lim.max_time))
    for b in range(B):
        xt, yt, psi, has = (float(v) for v in targets[b])
        dist, ang = math.hypot(xt, yt), math.atan2(yt, xt)
        for r in range(restarts):
            if r == 0:  # the duration at which the peak tilt is half the limit (0.15 rad without one)
                a_ref = (0.5 * lim.max_tilt if lim.max_tilt is not None else 0.15) / 0.3248  # max sin^3 cos = 0.3248
                T = math.sqrt(dist / (kappa * a_ref * 3 / (32 * math.pi)))
                T = min(max(T, 1.5 * lim.min_time), 0.95 * lim.max_time)
            else:
                T = rng.uniform(tmin, lim.max_time * 0.95)
            a = dist / (kappa * T**2 * 3 / (32 * math.pi)) * (1.0 + (0.1 * rng.normal() if r else 0.0))
            ang_r = ang + (0.15 * rng.normal() if r else 0.0)
            z[b, r, 1] = a * math.cos(ang_r)
            z[b, r, n + 1] = a * math.sin(ang_r)
            if r:
                z[b, r, : 2 * n] += 0.1 * abs(a) * rng.normal(size=2 * n) + 0.003 * rng.normal(size=2 * n)
            if has:
                z[b, r, 2 * n] = psi / (T * 4 / (3 * math.pi))  # heading ~ int omega_gamma dt
            if r:
                z[b, r, 2 * n : 2 * n + m] += 0.05 * rng.normal(size=m)
            z[b, r, -1] = float(_duration_inv(T, lim))
    return jnp.asarray(z, params.R0.dtype)


# ------------------------------------------------------------------ result


class PlanInfeasibleError(RuntimeError):
    """A request that the planner could not meet within the limits. `.plan` holds the best plan
    found (or `.plans` for a batch); the message says how far it falls short and which limit binds."""

    def __init__(self, message: str, plan: Plan | None = None, plans: list[Plan] | None = None):
        super().__init__(message)
        self.plan = plan
        self.plans = plans


@dataclasses.dataclass
class Plan:
    """A rest-to-rest manoeuvre (or a route of several, stopping at each waypoint).

    - `gaits`: the `TiltGait`s executed one after the other; `legs`: per gait, its start pose
      `(x, y, psi)` in the fixed frame (each gait is planned in its start frame).
    - `trajectory`: the accurate re-simulation (`simulate_gaits`, Dopri8, rtol 1e-10) sampled at
      `rate` Hz, with fixed-frame `x, y` (routes: leg by leg, moved to the leg's start pose).
    - `target`: `(x, y, psi or nan)` of the last leg; `errors`: achieved `position_m`,
      `speed_m_s` (`R0 |Omega x gamma|` at the end), `heading_rad` (nan if free), `spin_rad_s`.
    - `limits_report`: per limit `{limit, max, ok}`; `violations`: names with the excess.
    - `feasible`: terminal tolerances met and every limit respected.
    - `iterations`: Adam, L-BFGS, LM counts; `elapsed_s`: wall time; `loss`: final objective.
    """

    params: RobotParams
    gaits: list
    legs: np.ndarray
    trajectory: Trajectory
    rate: float
    target: np.ndarray
    errors: dict
    limits_report: dict
    feasible: bool
    shortfall: list
    iterations: dict
    elapsed_s: float
    loss: float
    restarts: int = 1

    @property
    def duration(self) -> float:
        """Total time [s]."""
        return float(np.asarray(self.trajectory.ts)[-1])

    def table(self) -> dict[str, np.ndarray]:
        """The executable table: `t, K_1..K_N, chi_dot_1..chi_dot_N, x, y, gamma_1..3, heading,
        tilt` (SI: s, N m, rad/s, m, -, rad, rad); the robot is at rest at the last row."""
        tr = self.trajectory
        N = int(np.asarray(tr.K).shape[-1])
        cols: dict[str, np.ndarray] = {"t": np.asarray(tr.ts)}
        for i in range(N):
            cols[f"K_{i + 1}"] = np.asarray(tr.K[:, i])
        for i in range(N):
            cols[f"chi_dot_{i + 1}"] = np.asarray(tr.chi_dot[:, i])
        cols["x"], cols["y"] = np.asarray(tr.x), np.asarray(tr.y)
        g = np.asarray(tr.gamma)
        for i in range(3):
            cols[f"gamma_{i + 1}"] = g[:, i]
        R = np.stack([np.asarray(tr.alpha), np.asarray(tr.beta), g], axis=-2)
        Qm = np.asarray(rotation_between(jnp.array([0.0, 0.0, 1.0]), rest_attitude(self.params)))
        M = R @ Qm
        cols["heading"] = np.unwrap(np.arctan2(M[:, 1, 0], M[:, 0, 0]))
        gm = np.asarray(rest_attitude(self.params))
        cols["tilt"] = np.arccos(np.clip(g @ gm, -1.0, 1.0))
        return cols

    def to_csv(self, path) -> None:
        """Write `table()` as CSV (header line, full float64 precision), atomically."""
        from .._runtime.files import atomic_write_text

        cols = self.table()
        names = list(cols)
        data = np.stack([cols[k] for k in names], axis=1)
        lines = [",".join(names)] + [",".join(repr(float(v)) for v in row) for row in data]
        atomic_write_text(path, "\n".join(lines) + "\n")

    def summary(self) -> str:
        """A few lines for a terminal: target, errors, limits, feasibility, iterations, time."""
        e = self.errors
        out = [
            f"plan: {len(self.gaits)} manoeuvre(s), T = {self.duration:.3f} s, "
            f"target ({self.target[0]:.4f}, {self.target[1]:.4f}) m"
            + ("" if np.isnan(self.target[2]) else f", heading {self.target[2]:.4f} rad"),
            (
                f"  final position error {1e3 * e['position_m']:.4f} mm, speed {1e3 * e['speed_m_s']:.4f} mm/s, "
                f"heading error {e['heading_rad']:.2e} rad, shell spin {e['spin_rad_s']:.2e} 1/s"
            ),
        ]
        for name, r in self.limits_report.items():
            out.append(f"  {name:<16} max {r['max']:.5g} / limit {r['limit']:.5g}  {'ok' if r['ok'] else 'VIOLATED'}")
        it = self.iterations
        out.append(
            f"  {self.restarts} restarts; Adam {it['adam']}, L-BFGS {it['lbfgs']}, LM {it['lm']} iterations; "
            f"{self.elapsed_s:.1f} s; {'FEASIBLE' if self.feasible else 'NOT FEASIBLE: ' + '; '.join(self.shortfall)}"
        )
        return "\n".join(out)


def _limit_report(params, tr: Trajectory, T_total, lim: Limits) -> dict:
    K, cd, ts = np.asarray(tr.K), np.asarray(tr.chi_dot), np.asarray(tr.ts)
    g = np.asarray(tr.gamma)
    gm = np.asarray(rest_attitude(params))
    tilt = np.arccos(np.clip(g @ gm, -1.0, 1.0))
    rep = {}
    if lim.max_torque is not None:
        rep["torque_N_m"] = (float(np.max(np.abs(K))), lim.max_torque)
    if lim.max_wheel_speed is not None:
        rep["wheel_speed_rad_s"] = (float(np.max(np.abs(cd))), lim.max_wheel_speed)
    if lim.max_tilt is not None:
        rep["tilt_rad"] = (float(np.max(tilt)), lim.max_tilt)
    if lim.max_torque_rate is not None:
        dtt = np.diff(ts)
        ok = dtt > 0
        rate = np.abs(np.diff(K, axis=0)[ok] / dtt[ok, None]) if np.any(ok) else np.zeros(1)
        rep["torque_rate_N_m_s"] = (float(np.max(rate)), lim.max_torque_rate)
    rep["time_s"] = (float(T_total), float(lim.max_time))
    return {k: {"max": v, "limit": float(L), "ok": bool(v <= float(L) * (1 + 1e-9))} for k, (v, L) in rep.items()}


def _vec_targets(targets) -> np.ndarray:
    """`(B, 4)`: x, y, heading (0 if free), has_heading."""
    rows = []
    for t in targets:
        t = list(t)
        if len(t) == 2 or t[2] is None or (isinstance(t[2], float) and math.isnan(t[2])):
            rows.append([float(t[0]), float(t[1]), 0.0, 0.0])
        else:
            rows.append([float(t[0]), float(t[1]), float(t[2]), 1.0])
    return np.asarray(rows, np.float64)


def _accurate(params, gait, rate, alpha0, beta0, max_time):
    """`simulate_gaits` (Dopri8, rtol 1e-10) sampled at `k / rate` for `k / rate < T`, plus
    the end `T`. The grid is padded to a fixed length (`max_time * rate`) so that plans of
    every duration share one compiled function; the padding is cut off afterwards."""
    T = float(gait.T)
    n_max = math.ceil(max_time * rate) + 2
    grid = np.arange(n_max) / rate
    n = int(np.sum(grid < T - 1e-9)) + 1
    ts = np.minimum(grid, T)
    ts[n - 1 :] = T
    tr = simulate_gaits(params, [gait], ts=ts, alpha0=alpha0, beta0=beta0)
    return jax.tree_util.tree_map(lambda v: v[:n] if jnp.ndim(v) >= 1 else v, tr)


def _terminal_errors(params, tr: Trajectory, target) -> dict:
    x, y = float(tr.x[-1]), float(tr.y[-1])
    O, g = np.asarray(tr.Omega[-1]), np.asarray(tr.gamma[-1])
    R = np.stack([np.asarray(tr.alpha[-1]), np.asarray(tr.beta[-1]), g])
    Qm = np.asarray(rotation_between(jnp.array([0.0, 0.0, 1.0]), rest_attitude(params)))
    M = R @ Qm
    psi = math.atan2(M[1, 0], M[0, 0])
    head = float("nan") if target[3] == 0 else abs(math.remainder(psi - target[2], 2 * math.pi))
    return {
        "position_m": math.hypot(x - target[0], y - target[1]),
        "speed_m_s": float(params.R0) * float(np.linalg.norm(np.cross(O, g))),
        "heading_rad": head,
        "spin_rad_s": float(abs(O @ g)),
        "final": [x, y, psi],
    }


def plan_many(
    params: RobotParams,
    targets: Sequence[Sequence[float]],
    *,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    restarts: int = 16,
    rate: float = 1000.0,
    seed: int = 0,
    tol_position: float = 5e-4,
    tol_speed: float = 5e-4,
    tol_heading: float = 1e-3,
    verify: bool = True,
    progress: bool = False,
) -> list[Plan]:
    """Plan rest-to-rest manoeuvres from rest at the origin (heading 0) to each target, all in
    one compiled, vmapped search (`restarts x len(targets)` problems).

    **Arguments:**
    - `targets`: `(x, y)` [m] or `(x, y, psi)` (final platform heading [rad]; `None`/nan: free).
    - `limits`, `objective`, `settings`: see `Limits`, `Objective`, `PlanSettings`.
    - `restarts`: random restarts per target (the best is kept); `rate`: output rate [Hz].
    - `tol_*`: terminal tolerances for `Plan.feasible` [m, m/s, rad].
    - `verify`: re-simulate with the accurate solver (needed for the table; `False` returns
      the search model's result only, for benchmarks).

    Every argument is checked before any work; a bad one raises `InputError` naming it.

    Returns one `Plan` per target (infeasible ones have `feasible = False`; `plan` raises).
    """
    targets = _check_request("plan_many", targets, limits, objective, settings, restarts, rate, seed,
                             (("tol_position", tol_position), ("tol_speed", tol_speed), ("tol_heading", tol_heading)))  # fmt: skip
    lim = limits or Limits()
    obj = objective or Objective()
    s = settings or PlanSettings()
    # numbers as arrays: other limits and weights reuse the compiled search (None stays static)
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, params.R0.dtype), m) for m in (lim, obj))
    tg = _vec_targets(targets)
    t0 = time.perf_counter()
    z0 = _initial_guesses(params, tg, int(restarts), lim, s, seed)
    if progress:
        print(f"jsphere plan: {len(tg)} target(s) x {restarts} restarts, Adam {s.adam_steps} + L-BFGS "
              f"{s.lbfgs_steps} + LM {s.lm_steps} iterations (compiling ...)", file=sys.stderr, flush=True)  # fmt: skip
    tgj = jnp.asarray(tg, params.R0.dtype)
    zf, loss, _, Jf, _ = _search(params, tgj, z0, lim_a, obj_a, s)
    zf, Jf = np.asarray(zf), np.asarray(Jf)
    t_search = time.perf_counter() - t0
    if progress:
        print(
            f"jsphere plan: search done in {t_search:.1f} s; verifying with the accurate solver ...",
            file=sys.stderr,
            flush=True,
        )
    st0 = State.at_rest(params)
    alpha0, beta0 = np.asarray(st0.alpha), np.asarray(st0.beta)
    plans = []
    iters = {"adam": s.adam_steps, "lbfgs": s.lbfgs_steps, "lm": s.lm_steps, "newton": 0}
    for b in range(len(tg)):
        z = zf[b]
        gait = gait_from_vector(jnp.asarray(z), lim, s)
        if verify:
            tr = _accurate(params, gait, rate, alpha0, beta0, lim.max_time)
            err = _terminal_errors(params, tr, tg[b])
            # Newton correction of the RK4 bias: accurate residual, search-model Jacobian (min-norm step)
            for _ in range(3):
                if err["position_m"] <= 0.05 * tol_position and err["speed_m_s"] <= 0.05 * tol_speed:
                    break
                # rows 0-5 of the residual Jacobian: (x, y) / position_scale, R0 Omega / speed_scale, heading
                scales = np.array([obj.position_scale] * 2 + [obj.speed_scale] * 3 + [obj.heading_scale])
                J = Jf[b, :6] * scales[:, None]
                fin = err["final"]
                Om = float(params.R0) * np.asarray(tr.Omega[-1])
                r = np.concatenate([[fin[0] - tg[b, 0], fin[1] - tg[b, 1]], Om,
                                    [tg[b, 3] * math.remainder(fin[2] - tg[b, 2], 2 * math.pi)]])  # fmt: skip
                rows = [0, 1, 2, 3, 5]  # position, horizontal Omega, heading (the slow shell spin is left alone)
                z_new = z - np.linalg.lstsq(J[rows], r[rows], rcond=None)[0]
                g_new = gait_from_vector(jnp.asarray(z_new), lim, s)
                tr_new = _accurate(params, g_new, rate, alpha0, beta0, lim.max_time)
                err_new = _terminal_errors(params, tr_new, tg[b])
                iters["newton"] += 1
                if err_new["position_m"] + err_new["speed_m_s"] >= err["position_m"] + err["speed_m_s"]:
                    break
                z, gait, tr, err = z_new, g_new, tr_new, err_new
        else:
            ro = rollout(params, gait, s.n_steps)
            tr = None
            err = {"position_m": float(np.hypot(ro.x[-1] - tg[b, 0], ro.y[-1] - tg[b, 1])),
                   "speed_m_s": float(params.R0 * jnp.linalg.norm(ro.Omega[-1, :2])), "heading_rad": float("nan"),
                   "spin_rad_s": float(abs(ro.Omega[-1, 2])), "final": [float(ro.x[-1]), float(ro.y[-1]), float(ro.heading)]}  # fmt: skip
        T = float(gait.T)
        rep = _limit_report(params, tr, T, lim) if tr is not None else {}
        shortfall = []
        if err["position_m"] > tol_position:
            shortfall.append(
                f"final position misses by {1e3 * err['position_m']:.3f} mm (tolerance {1e3 * tol_position:.3f} mm)"
            )
        if err["speed_m_s"] > tol_speed:
            shortfall.append(f"final speed {1e3 * err['speed_m_s']:.3f} mm/s (tolerance {1e3 * tol_speed:.3f} mm/s)")
        if tg[b, 3] and err["heading_rad"] > tol_heading:
            shortfall.append(f"final heading misses by {err['heading_rad']:.4f} rad (tolerance {tol_heading} rad)")
        for name, r in rep.items():
            if not r["ok"]:
                shortfall.append(
                    f"limit {name} exceeded: {r['max']:.5g} > {r['limit']:.5g} (by {100 * (r['max'] / r['limit'] - 1):.1f}%)"
                )
        binding = [n for n, r in rep.items() if r["ok"] and r["max"] > 0.95 * r["limit"]]
        if shortfall and binding:
            shortfall.append(f"binding limit(s): {', '.join(binding)}")
        plans.append(Plan(
            params=params, gaits=[gait], legs=np.zeros((1, 3)), trajectory=tr, rate=rate,
            target=np.array([tg[b, 0], tg[b, 1], tg[b, 2] if tg[b, 3] else np.nan]), errors=err,
            limits_report=rep, feasible=not shortfall, shortfall=shortfall, iterations=dict(iters),
            elapsed_s=time.perf_counter() - t0, loss=float(np.min(np.asarray(loss)[b])), restarts=int(restarts),
        ))  # fmt: skip
    return plans


def plan(
    params: RobotParams,
    to: Sequence[float],
    *,
    heading: float | None = None,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    restarts: int = 16,
    rate: float = 1000.0,
    seed: int = 0,
    allow_infeasible: bool = False,
    progress: bool = False,
) -> Plan:
    """Plan a rest-to-rest manoeuvre from rest at the origin (platform axes = fixed axes) to
    `to = (x, y)` [m], optionally ending with platform heading `heading` [rad], within `limits`.

    Raises `PlanInfeasibleError` (holding the best plan in `.plan`, and saying how far it falls
    short and which limit binds) if the tolerances or limits are not met, unless
    `allow_infeasible=True` (then check `Plan.feasible`).

    Example:

        p = jsphere.RobotParams.paper()
        pl = jsphere.plan(p, (0.8, -0.5), heading=1.0)
        pl.to_csv("plan.csv")

    Every argument is checked before any work; a bad one (a target or heading that is not a
    finite number, `restarts < 1`, `rate <= 0`, ...) raises `InputError` naming it.
    """
    if isinstance(to, (str, bytes)) or not isinstance(to, (Sequence, np.ndarray)) or len(to) != 2:
        raise InputError(f"plan: to must be the target (x, y) in m; got {to!r}.")
    if heading is not None:
        real("plan", "heading", heading, low=None, unit="rad; None for a free final heading")
    _check_request("plan", [(to[0], to[1], heading)], limits, objective, settings, restarts, rate, seed)
    pl = plan_many(params, [(to[0], to[1], heading)], limits=limits, objective=objective, settings=settings,
                   restarts=restarts, rate=rate, seed=seed, progress=progress)[0]  # fmt: skip
    if not pl.feasible and not allow_infeasible:
        raise PlanInfeasibleError(
            "jsphere.plan: the request cannot be met: "
            + "; ".join(pl.shortfall)
            + ". The best plan found is in `.plan`.",
            plan=pl,
        )
    return pl


def _move(tr: Trajectory, pose, t_offset) -> Trajectory:
    """A trajectory planned in its start frame, moved to the start pose `(x0, y0, psi0)`:
    positions rotated and shifted, the platform attitude turned by `psi0` about the vertical
    (platform-frame quantities `gamma, omega, Omega, K, chi_dot` are unchanged)."""
    x0, y0, psi = pose
    c, s_ = math.cos(psi), math.sin(psi)
    x = x0 + c * tr.x - s_ * tr.y
    y = y0 + s_ * tr.x + c * tr.y
    # alpha, beta: fixed axes seen from the platform; fixed frame turned by -psi relative to the start frame
    a = c * tr.alpha - s_ * tr.beta
    b = s_ * tr.alpha + c * tr.beta
    return eqx.tree_at(lambda t: (t.x, t.y, t.alpha, t.beta, t.ts), tr, (x, y, a, b, tr.ts + t_offset))


def plan_route(
    params: RobotParams,
    waypoints: Sequence[Sequence[float]],
    *,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    restarts: int = 16,
    rate: float = 1000.0,
    seed: int = 0,
    allow_infeasible: bool = False,
    progress: bool = False,
) -> Plan:
    """A route from rest at the origin through `waypoints` `(x, y)` or `(x, y, psi)` [m, rad],
    stopping at each: one rest-to-rest manoeuvre per leg. Every leg is planned in its start
    frame, all legs in one vmapped search (the dynamics are invariant under horizontal shifts
    and turns about the vertical). A waypoint without a heading keeps the previous heading.

    Returns one `Plan` whose gaits are the legs and whose trajectory joins them (the duplicate
    rest sample at each stop dropped).
    """
    if isinstance(waypoints, (str, bytes)) or not isinstance(waypoints, Sequence) or not len(waypoints):
        raise InputError(f"plan_route: waypoints must be a non-empty list of (x, y) or (x, y, heading); got {waypoints!r}.")
    _check_request("plan_route", [tuple(w) if isinstance(w, (Sequence, np.ndarray)) else w for w in waypoints], limits,
                   objective, settings, restarts, rate, seed, nan_free=False)  # fmt: skip
    poses, local = [], []
    pose = (0.0, 0.0, 0.0)
    for w in waypoints:
        w = list(w)
        psi = pose[2] if len(w) == 2 or w[2] is None else float(w[2])
        dx, dy = float(w[0]) - pose[0], float(w[1]) - pose[1]
        c, s_ = math.cos(pose[2]), math.sin(pose[2])
        local.append((c * dx + s_ * dy, -s_ * dx + c * dy, math.remainder(psi - pose[2], 2 * math.pi)))
        poses.append(pose)
        pose = (float(w[0]), float(w[1]), psi)
    legs = plan_many(params, local, limits=limits, objective=objective, settings=settings, restarts=restarts,
                     rate=rate, seed=seed, progress=progress)  # fmt: skip
    trs, t_off, shortfall = [], 0.0, []
    for i, (lg, ps) in enumerate(zip(legs, poses)):
        tr = _move(lg.trajectory, ps, t_off)
        if i:
            tr = jax.tree_util.tree_map(lambda v: v[1:] if jnp.ndim(v) >= 1 else v, tr)
        trs.append(tr)
        t_off += float(lg.gaits[0].T)
        shortfall += [f"leg {i + 1}: {m}" for m in lg.shortfall]

    def join(*vs):
        return jnp.concatenate(vs, axis=0) if jnp.ndim(vs[0]) >= 1 else vs[0]

    tr = jax.tree_util.tree_map(join, *trs)
    seg = jnp.concatenate([jnp.full(t.ts.shape, i, jnp.int32) for i, t in enumerate(trs)])
    tr = eqx.tree_at(lambda t: t.segment, tr, seg)
    last = legs[-1]
    tx, ty, tpsi = pose
    err = {
        "position_m": max(lg.errors["position_m"] for lg in legs),
        "speed_m_s": max(lg.errors["speed_m_s"] for lg in legs),
        "heading_rad": max((lg.errors["heading_rad"] for lg in legs), default=float("nan")),
        "spin_rad_s": max(lg.errors["spin_rad_s"] for lg in legs),
        "final": [float(tr.x[-1]), float(tr.y[-1]), last.errors["final"][2] + poses[-1][2]],
    }
    lim = limits or Limits()
    rep = {}
    for name in legs[0].limits_report:
        mx = max(lg.limits_report[name]["max"] for lg in legs) if name != "time_s" else t_off
        L = legs[0].limits_report[name]["limit"] if name != "time_s" else lim.max_time * len(legs)
        rep[name] = {"max": mx, "limit": L, "ok": all(lg.limits_report[name]["ok"] for lg in legs)}
    pl = Plan(
        params=params, gaits=[lg.gaits[0] for lg in legs], legs=np.asarray(poses), trajectory=tr, rate=rate,
        target=np.array([tx, ty, tpsi]), errors=err, limits_report=rep, feasible=all(lg.feasible for lg in legs),
        shortfall=shortfall, iterations=legs[0].iterations, elapsed_s=max(lg.elapsed_s for lg in legs),
        loss=sum(lg.loss for lg in legs), restarts=int(restarts),
    )  # fmt: skip
    if not pl.feasible and not allow_infeasible:
        raise PlanInfeasibleError("jsphere.plan_route: " + "; ".join(shortfall), plan=pl)
    return pl


def replay_errors(plan_: Plan, *, mode: str = "torques") -> dict[str, Any]:
    """Re-simulate the exported table with the plain simulator (`simulate` with
    `Torques.from_samples(t, K)` or `WheelSpeeds.from_samples(t, chi_dot)`, cubic) from rest,
    and compare the end with the plan's target and with the planned path."""
    from ..controls import Torques, WheelSpeeds
    from ..solve.simulate import simulate

    cols = plan_.table()
    p = plan_.params
    N = p.n_wheels
    ts = cols["t"]
    if mode == "torques":
        ctrl = Torques.from_samples(ts, np.stack([cols[f"K_{i + 1}"] for i in range(N)], 1))
    elif mode == "wheel_speeds":
        ctrl = WheelSpeeds.from_samples(ts, np.stack([cols[f"chi_dot_{i + 1}"] for i in range(N)], 1))
    else:
        raise ValueError(f"replay_errors: mode must be 'torques' or 'wheel_speeds'; got {mode!r}.")
    tr = simulate(p, State.at_rest(p), ctrl, float(ts[-1]), ts=ts, max_steps=65536)
    x, y = float(tr.x[-1]), float(tr.y[-1])
    return {
        "final_xy": [x, y],
        "target_error_m": math.hypot(x - plan_.target[0], y - plan_.target[1]),
        "path_deviation_m": float(np.max(np.hypot(np.asarray(tr.x) - cols["x"], np.asarray(tr.y) - cols["y"]))),
        "final_speed_m_s": float(p.R0)
        * float(np.linalg.norm(np.cross(np.asarray(tr.Omega[-1]), np.asarray(tr.gamma[-1])))),
        "trajectory": tr,
    }


def optimise_gaits(
    params: RobotParams,
    build,
    x0: Float[Array, " P"],
    residual,
    *,
    steps: int = 20,
    tol: float = 1e-12,
    rtol: float = 1e-10,
    atol: float = 1e-12,
) -> tuple[np.ndarray, dict]:
    """Levenberg-Marquardt through the accurate gait simulation, for any parameterised gait
    sequence: find `x` with `residual(simulate_gaits(params, build(x), ts=[end])) = 0` (or
    least squares).

    **Arguments:**
    - `build(x) -> list[Gait]`: the gait sequence of the parameters `x` (traceable in `x`; keep
      its structure fixed).
    - `residual(traj) -> (M,)`: conditions on the end state (the trajectory holds one sample,
      the end), e.g. `lambda tr: tr.Omega[-1, :2]` ("the robot stops").
    - `steps`, `tol`: iteration budget and the residual norm that ends it.

    Returns `(x, info)` with `info = {"residual": |r|, "iterations": k, "history": [...]}`.
    Example: the braking gait that stops the paper's turn (Section 5.2, `theta_max ~ 0.1416`):

        build = lambda x: [acceleration(), turn(), braking(theta_max=x[0], phi=x[1])]
        x, info = optimise_gaits(p, build, jnp.array([0.1, pi / 4]), lambda tr: tr.Omega[-1, :2])
    """

    @eqx.filter_jit
    def r_and_J(x):
        def r(x):
            gaits = build(x)
            T = sum(jnp.asarray(g.T) for g in gaits)
            tr = simulate_gaits(params, gaits, ts=jnp.reshape(T, (1,)), rtol=rtol, atol=atol)
            return jnp.asarray(residual(tr))

        return r(x), jax.jacrev(r)(x)

    x = np.asarray(x0, np.float64)
    lam, hist = 1e-6, []
    r, J = (np.asarray(v) for v in r_and_J(jnp.asarray(x)))
    k = 0
    for k in range(1, steps + 1):
        f = float(r @ r)
        hist.append(math.sqrt(f))
        if math.sqrt(f) < tol:
            k -= 1
            break
        A = J.T @ J
        dx = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-15), J.T @ r)
        r_new, J_new = (np.asarray(v) for v in r_and_J(jnp.asarray(x + dx)))
        if np.all(np.isfinite(r_new)) and float(r_new @ r_new) < f:
            x, r, J, lam = x + dx, r_new, J_new, max(lam / 10, 1e-15)
        else:
            lam *= 10
    return x, {"residual": float(np.linalg.norm(r)), "iterations": k, "history": hist}
