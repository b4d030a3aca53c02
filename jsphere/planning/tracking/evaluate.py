"""The regulator tried on robots that are not the model: the plan replayed open loop and closed
loop on drawn robots, through imperfect motors, with a measured (noisy, late) state fed back,
from perturbed start poses (pure JAX, vmapped over the draws).

Per draw and control interval `k` (rate `1/h`): the controller reads the state measured `d`
intervals ago (`delay_s` rounded to whole intervals; the measurement model of `docs/lab.md`:
capture pose with noise `pos_sd`, `att_sd`, platform rate from a gyro with noise `omega_sd`,
`Omega = omega - (omega - Omega)` with the relative rate from the wheel encoders through (2.4),
noise `wheel_sd`), compares it with the reference at the measurement's time, and commands
`K = K_ff,k - G_k e`, clipped to the torque limit; the motors apply `gain * (K + noise)`
`motor_delay_s` later (the gain, delay and white noise of `jsphere.Actuators`, the delay rounded
to whole intervals); the robot moves by `flow.interval` with that torque held. The open loop is
the same with `G = 0`. The miss is taken `settle` seconds after the plan's end.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..._runtime.checks import real
from ...model.linalg import cross
from ...model.params import RobotParams, derive
from ...model.rotations import quat_exp, quat_mul, rotmat
from ...model.state import Flat, State, state_error
from .flow import interval


class Conditions(eqx.Module):
    """How the evaluation's robot differs from the plan, beside its parameters.

    - `start_sd` [m], `heading_sd` [rad]: the start pose's offset per axis and about the vertical.
    - `delay_s` [s], `pos_sd` [m], `att_sd` [rad], `omega_sd`, `wheel_sd` [rad/s]: the fed-back
      state's delay and noise (module docstring).
    - `gain_sd`, `motor_delay_s` [s], `white_sd` [N m]: the motors, as `jsphere.Actuators`' fields:
      per draw and wheel a gain `1 + gain_sd z`, the command applied `motor_delay_s` late, white
      noise on each period's command.
    - `settle` [s]: how long the robot runs past the plan's end before its miss is taken.

    Defaults: a start within a few mm, a capture at 100 Hz or faster with 0.2 mm and 2 mrad of
    noise and one period of delay, a gyro of 0.01 rad/s, motor gains off by 2.5 % (sd: up to
    5 % at two sd), 2 s of settling.
    """

    start_sd: float = 0.002
    heading_sd: float = 0.01
    delay_s: float = 0.01
    pos_sd: float = 2e-4
    att_sd: float = 2e-3
    omega_sd: float = 0.01
    wheel_sd: float = 0.01
    gain_sd: float = 0.025
    motor_delay_s: float = 0.0
    white_sd: float = 5e-4
    settle: float = 2.0

    def __check_init__(self):
        for name in FIELDS:
            real("Conditions", name, getattr(self, name))

    def to_json(self) -> dict:
        return {k: getattr(self, k) for k in FIELDS}


#: the fields of `Conditions`
FIELDS = tuple(f.name for f in dataclasses.fields(Conditions))


def _start(p: RobotParams, key, c: Conditions):
    """The start state of a draw: at rest on the drawn robot, shifted and turned."""
    k1, k2 = jax.random.split(key)
    dt = p.R0.dtype
    dxy = c.start_sd * jax.random.normal(k1, (2,), dt)
    dpsi = c.heading_sd * jax.random.normal(k2, (), dt)
    z = State.at_rest(p, x=dxy[0], y=dxy[1]).flatten().astype(dt)
    q = quat_mul(quat_exp(jnp.stack([0.0 * dpsi, 0.0 * dpsi, dpsi])), z[Flat.q])  # turned about the vertical
    return Flat.replace(z, q=q)


def run_one(
    p: RobotParams,
    key,
    ts_h,
    K_ff: Float[Array, "M N"],
    ref: Float[Array, "M S"],
    G: Float[Array, "M N 11"],
    target: Float[Array, "2"],
    c: Conditions,
    max_torque,
    n_settle: int,
    closed,
):
    """One draw: the robot `p` from a perturbed start runs the table (`K_ff`, `ref`, `G`, one row
    per interval of `ts_h` seconds, the last row held) for `M - 1 + n_settle` intervals.
    `closed`: 1 for the closed loop, 0 for the open loop (the feed-forward alone; a traced
    number, so that both loops share one compiled program).
    Returns `(miss [m], end speed [m/s], largest commanded |K| [N m], end state)`."""
    d = derive(p)
    dt = ref.dtype
    M, N = K_ff.shape
    n_meas = int(round(c.delay_s / ts_h))
    n_act = int(round(c.motor_delay_s / ts_h))
    k_start, k_gain, k_noise = jax.random.split(key, 3)
    gain = 1.0 + c.gain_sd * jax.random.normal(k_gain, (N,), dt)
    z0 = _start(p, k_start, c)
    steps = M - 1 + n_settle
    sd = jnp.asarray([c.pos_sd] * 2 + [c.att_sd] * 3 + [c.omega_sd] * 3 + [0.0] * 3, dt)
    lim = jnp.asarray(jnp.inf if max_torque is None else max_torque, dt)

    def body(carry, k):
        z, zbuf, ubuf, umax = carry
        kn = jax.random.fold_in(k_noise, k)
        k1, k2, k3 = jax.random.split(kn, 3)
        row = jnp.minimum(k, M - 1)
        seen = jnp.maximum(k - n_meas, 0)
        n = sd * jax.random.normal(k1, (11,), dt)
        n = n.at[8:11].set(n[5:8] + c.wheel_sd * jax.random.normal(k2, (3,), dt))
        e = state_error(zbuf[0], ref[jnp.minimum(seen, M - 1)]) + n
        u = K_ff[row] - closed * (G[row] @ e)
        umax = jnp.maximum(umax, jnp.max(jnp.abs(u)))
        u = jnp.clip(u, -lim, lim)
        ubuf = jnp.concatenate([ubuf[1:], u[None]], axis=0)
        applied = gain * (ubuf[0] + c.white_sd * jax.random.normal(k3, (N,), dt))
        zn = interval(p, d, z, applied, ts_h)
        zbuf = jnp.concatenate([zbuf[1:], zn[None]], axis=0)
        return (zn, zbuf, ubuf, umax), None

    zbuf = jnp.broadcast_to(z0, (n_meas + 1,) + z0.shape)
    ubuf = jnp.zeros((n_act + 1, N), dt)
    (zT, _, _, umax), _ = jax.lax.scan(body, (z0, zbuf, ubuf, jnp.zeros((), dt)), jnp.arange(steps))
    miss = jnp.hypot(zT[Flat.x] - target[0], zT[Flat.y] - target[1])
    gamma = rotmat(zT[Flat.q])[2]
    speed = p.R0 * jnp.linalg.norm(cross(zT[Flat.Omega], gamma))
    return miss, speed, umax, zT


@eqx.filter_jit
def run_batch(
    samples: RobotParams, keys, ts_h: float, K_ff, ref, G, target, c: Conditions, max_torque, n_settle: int, closed
):
    """`run_one` vmapped over the drawn robots `samples` (stacked) and their `keys`."""

    def one(p, k):
        m, v, u, _ = run_one(p, k, ts_h, K_ff, ref, G, target, c, max_torque, n_settle, closed)
        return m, v, u

    return jax.vmap(one)(samples, keys)
