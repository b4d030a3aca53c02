"""The search: every (target, restart) pair optimised in one compiled, vmapped call.

Per problem: optional L-BFGS warm-up, Adam (optax) on `sum r^2`, then Levenberg-Marquardt
on the residual vector of `jsphere.planning.residuals`, all through the RK4
search model; the best restart per target is kept. The restarts start from the
accelerate-brake profile towards the target with random extra terms (`_initial_guesses`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..model.dynamics import mass_blocks
from ..model.kinematics import rest_attitude
from ..model.params import RobotParams, derive
from ..model.rotations import rotation_between
from ..numerics.lm import Dense, LevenbergMarquardt
from .problem import _duration_inv, _n_vars
from .residuals import _loss, _residuals, with_jacobian


def _lbfgs(z0, target, params, lim, obj, s):
    """`lbfgs_steps` L-BFGS steps (optax) on `sum r^2`; a step to a non-finite point is dropped."""

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


#: the search's Levenberg-Marquardt: delayed acceptance, the damping / 3 on success and x 4 on failure
SEARCH_LM = LevenbergMarquardt(Dense(floor=1e-9), decrease=3.0, increase=4.0, lam_max=1e12)


def lm_search(z0, rj, adam_steps: int, lm_steps: int, learning_rate: float):
    """Adam (`adam_steps`) then Levenberg-Marquardt (`lm_steps`, `SEARCH_LM`) on the residual
    vector whose value and Jacobian `rj(z) -> (r, J)` gives, in one `lax.scan` whose body
    evaluates it once, so the model is compiled once (an `optimistix.LevenbergMarquardt` after
    an Adam scan compiles it three times: see `benchmarks/solvers.py`).

    LM with delayed acceptance: each iteration evaluates the candidate of the previous one (an
    Adam step or an LM step from the best point) and keeps it if it lowers `sum r^2`; the
    damping changes from the second LM iteration on. Returns the best point, its loss, its
    Jacobian and the loss history."""
    opt = optax.adam(learning_rate)

    def body(c, k):
        z, pred, zb, lm, st = c
        r, J = rj(z)
        f = jnp.sum(r**2)
        ok = jnp.isfinite(f) & jnp.all(jnp.isfinite(J))
        zb, new = SEARCH_LM.update(zb, z, lm, jnp.where(ok, f, jnp.inf), (r, J), pred)
        lm = eqx.tree_at(lambda m: m.lam, new, jnp.where(k > adam_steps, new.lam, lm.lam))
        # Adam step from the current point
        g = jnp.where(ok, 2.0 * J.T @ r, 0.0)
        up, st_new = opt.update(g, st, z)
        z_adam = jnp.where(ok, optax.apply_updates(z, up), zb)
        # LM step from the best point
        z_lm, pred_lm = SEARCH_LM.propose(zb, lm)
        lm_phase = k >= adam_steps
        z_next = jnp.where(lm_phase, z_lm, z_adam)
        return (z_next, jnp.where(lm_phase, pred_lm, jnp.inf), zb, lm, st_new), f

    r0 = jax.eval_shape(lambda z: rj(z)[0], z0)
    V = z0.shape[0]
    lm0 = SEARCH_LM.init(
        jnp.asarray(jnp.inf, z0.dtype), (jnp.zeros(r0.shape, z0.dtype), jnp.zeros((r0.shape[0], V), z0.dtype))
    )
    c0 = (z0, jnp.asarray(jnp.inf, z0.dtype), z0, lm0, opt.init(z0))
    c, hist = jax.lax.scan(body, c0, jnp.arange(adam_steps + lm_steps + 1))
    _, _, zb, lm, _ = c
    return zb, lm.cost, lm.current[1], hist


def _search_one(z0, target, params, lim, obj, s):
    """`lm_search` on the residuals of one (target, restart) pair."""
    rj = with_jacobian(lambda z: _residuals(z, target, params, lim, obj, s))
    return lm_search(z0, rj, s.adam_steps, s.lm_steps, s.learning_rate)


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
