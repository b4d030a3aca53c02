"""Control inputs: wheel torques `K(t)` (the paper's) or commanded wheel speeds `chi_dot(t)`.

A control is a pytree holding a JAX-traceable function of time (or a sampled table), plus
the static times at which it jumps. `simulate` splits the integration at those times; in
wheel-speed mode it applies the impulsive momentum balance there (see `servo_jump`).
"""

from __future__ import annotations

from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._runtime.arrays import to_jax
from .model.kinematics import kinematic_wheel_speeds
from .model.params import RobotParams


class Sampled(eqx.Module):
    """A table `values[k]` at times `ts[k]`, interpolated piecewise linearly or by cubic Hermite
    polynomials (slopes from 3-point differences, second-order accurate; `kind="cubic"`).

    A repeated time stamp marks a jump: the first row is the value just before, the second the
    value from then on. Outside `[ts[0], ts[-1]]` the end values are held.
    """

    ts: Float[Array, " T"]
    values: Float[Array, "T N"]
    kind: str = eqx.field(static=True, default="cubic")

    def __check_init__(self):
        if self.kind not in ("linear", "cubic", "zoh"):
            raise ValueError(f"Sampled.kind must be 'linear', 'cubic' or 'zoh'; got {self.kind!r}.")
        ts, vals = self.ts, self.values
        if isinstance(ts, jax.core.Tracer) or isinstance(vals, jax.core.Tracer):
            return
        ts, vals = np.asarray(ts), np.asarray(vals)
        if vals.ndim != 2:
            raise ValueError(f"Sampled.values must be a (T, N) table, one column per wheel; got shape {vals.shape}.")
        if ts.ndim != 1 or ts.shape[0] < 2:
            raise ValueError(f"Sampled.ts must be 1-D with at least 2 times; got shape {ts.shape}.")
        if vals.shape[0] != ts.shape[0]:
            raise ValueError(
                f"Sampled.values must have one row per time: {vals.shape[0]} rows for {ts.shape[0]} times."
            )
        if not np.all(np.isfinite(ts)):
            raise ValueError("Sampled.ts contains NaN or inf.")
        bad = np.nonzero(~np.all(np.isfinite(vals.reshape(len(ts), -1)), axis=1))[0]
        if bad.size:
            raise ValueError(f"Sampled.values: row {bad[0]} (t = {ts[bad[0]]}) is not finite; controls must be finite.")
        dts = np.diff(ts)
        if np.any(dts < 0):
            k = int(np.nonzero(dts < 0)[0][0])
            raise ValueError(f"Sampled.ts must be non-decreasing; ts[{k + 1}] = {ts[k + 1]} < ts[{k}] = {ts[k]}.")
        if np.any((dts[1:] == 0) & (dts[:-1] == 0)):
            raise ValueError("Sampled.ts: a time stamp occurs more than twice (a jump needs exactly two rows).")

    @property
    def jump_ts(self) -> tuple[float, ...]:
        return _repeated(np.asarray(self.ts))

    def __call__(self, t):
        ts, ys = self.ts, self.values
        n = ts.shape[0]
        t = jnp.clip(t, ts[0], ts[-1])
        i = jnp.clip(jnp.searchsorted(ts, t, side="right") - 1, 0, n - 2)
        t0, t1 = ts[i], ts[i + 1]
        h = t1 - t0
        safe_h = jnp.where(h > 0, h, 1.0)
        s = jnp.where(h > 0, (t - t0) / safe_h, 1.0)
        y0, y1 = ys[i], ys[i + 1]
        if self.kind == "zoh":
            return jnp.where(s < 1.0, y0, y1)
        if self.kind == "linear":
            return y0 + s * (y1 - y0)
        m0, m1 = self._slope(i), self._slope(i + 1)
        s2, s3 = s * s, s * s * s
        h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
        return h00 * y0 + h10 * h * m0 + h01 * y1 + h11 * h * m1

    def _slope(self, k):
        """Second-order slope at knot k, one-sided at the ends and beside jumps."""
        ts, ys = self.ts, self.values
        n = ts.shape[0]
        km, kp = jnp.maximum(k - 1, 0), jnp.minimum(k + 1, n - 1)
        hl, hr = ts[k] - ts[km], ts[kp] - ts[k]
        dl = (ys[k] - ys[km]) / jnp.where(hl > 0, hl, 1.0)
        dr = (ys[kp] - ys[k]) / jnp.where(hr > 0, hr, 1.0)
        both = (hl > 0) & (hr > 0)
        central = (hr * dl + hl * dr) / jnp.where(both, hl + hr, 1.0)
        return jnp.where(both, central, jnp.where(hl > 0, dl, dr))


def _repeated(ts: np.ndarray) -> tuple[float, ...]:
    """The times that occur twice in a table's time stamps (its jumps)."""
    return tuple(float(t) for t in ts[1:][np.diff(ts) == 0])


def _table_jumps(ts, kind: str) -> tuple[float, ...]:
    """The jumps of a table with time stamps `ts`: its repeated times, or every inner time for
    `kind="zoh"`. Read from the host values of `ts` (a NumPy or concrete JAX array, also inside
    a `jit`); traced time stamps have no jump times to restart at, and are refused."""
    if isinstance(ts, jax.core.Tracer):
        raise ValueError(
            "from_samples: the table's time stamps are traced (an argument of jit/vmap/grad); pass them as a "
            "NumPy array or a constant, so that its jumps are known when the solve is built."
        )
    host = np.asarray(ts, dtype=float)
    return tuple(float(t) for t in host[1:-1]) if kind == "zoh" else _repeated(host)


class _Control(eqx.Module):
    """A function of time `fn(t) -> (N,)` and the static times `jump_ts` where it jumps."""

    fn: Callable
    jump_ts: tuple[float, ...] = eqx.field(static=True, default=())

    def __init__(self, fn: Callable, jump_ts: Sequence[float] = ()):
        if not callable(fn):
            name = type(self).__name__
            raise TypeError(
                f"{name} needs a function of time fn(t) -> (N,), or use {name}.from_samples(ts, values); got {type(fn).__name__}."
            )
        self.fn = fn
        self.jump_ts = tuple(sorted(float(t) for t in jump_ts))

    def __call__(self, t):
        return jnp.asarray(self.fn(t), dtype=jnp.result_type(t))


class Torques(_Control):
    """Axle torques `K(t)` [N m] (`+K_i n_i` on wheel i, `-K_i n_i` on the platform).

    `Torques(fn)` with `fn(t) -> (N,)` traceable by JAX, or `Torques.from_samples(ts, K)`.
    `jump_ts`: times where `K` jumps (the integration restarts there).
    """

    @classmethod
    def from_samples(cls, ts: Float[ArrayLike, " T"], K: Float[ArrayLike, "T N"], *, kind: str = "cubic") -> "Torques":
        """Torques from a table (repeat a time stamp to encode a jump)."""
        f = Sampled(jnp.asarray(ts), jnp.asarray(K), kind)
        return cls(f, _table_jumps(ts, kind))


class WheelSpeeds(_Control):
    """Commanded wheel rates `chi_dot(t)` [rad/s] relative to the platform (speed-controlled
    motors: servo constraints).

    The wheels then fix `omega - Omega` through (2.4), and the control-free equation of (3.4)
    gives the motion; the torques needed are an output. The command must be differentiable in
    time between its `jump_ts`; at `t0` and at each jump the velocities change impulsively
    with the momentum of the control-free equation conserved (see `docs/model.md`).
    """

    @classmethod
    def from_samples(
        cls, ts: Float[ArrayLike, " T"], chi_dot: Float[ArrayLike, "T N"], *, kind: str = "cubic"
    ) -> "WheelSpeeds":
        """Wheel rates from a table (repeat a time stamp to encode a jump)."""
        f = Sampled(jnp.asarray(ts), jnp.asarray(chi_dot), kind)
        if kind == "zoh":
            raise ValueError(
                "WheelSpeeds.from_samples: kind='zoh' would make every sample a jump; use 'linear' or 'cubic'."
            )
        return cls(f, _table_jumps(ts, kind))

    def value_and_rate(self, t):
        """`(chi_dot(t), chi_ddot(t))`, the rate by forward-mode autodiff."""
        return jax.jvp(self, (t,), (jnp.ones_like(t),))


class Zero(eqx.Module):
    """`fn(t) = 0` for `n` wheels (a Module, so repeated simulations share one compilation)."""

    n: int = eqx.field(static=True)

    def __call__(self, t):
        return jnp.zeros(self.n, dtype=jnp.result_type(t))


class _KinematicCommand(eqx.Module):
    params: RobotParams
    path: Callable
    psi: Callable
    Omega_gamma: Callable
    t_stop: float | None = eqx.field(static=True)

    def __call__(self, t):
        rdot = jax.jvp(self.path, (t,), (jnp.ones_like(t),))[1]
        ps, omega_gamma = jax.jvp(self.psi, (t,), (jnp.ones_like(t),))
        u = kinematic_wheel_speeds(self.params, rdot, Omega_gamma=self.Omega_gamma(t), omega_gamma=omega_gamma, psi=ps)
        if self.t_stop is not None:
            u = jnp.where(t < self.t_stop, u, jnp.zeros_like(u))
        return u


def kinematic_control(
    params: RobotParams,
    path: Callable,
    *,
    psi: Callable | None = None,
    Omega_gamma: Callable | None = None,
    t_stop: float | None = None,
) -> WheelSpeeds:
    """Wheel speeds of the kinematic model (2.9) that realise a planar path.

    **Arguments:**
    - `path(t) -> (2,)`: the desired position `r_c(t)` of the shell centre in the fixed frame
      [m]; its velocity is taken by autodiff.
    - `psi(t)`: precession angle of the platform (default 0; `omega_gamma = dpsi/dt`).
    - `Omega_gamma(t)`: spin of the shell about the vertical (default 0, "rubber" rolling).
    - `t_stop`: if given, the wheels are stopped (`chi_dot = 0`) from this time on, as in the
      paper's Fig. 2 experiment.
    """
    zero = Constant(0.0)
    cmd = _KinematicCommand(params, path, psi or zero, Omega_gamma or zero, None if t_stop is None else float(t_stop))
    return WheelSpeeds(cmd, () if t_stop is None else (t_stop,))


class Constant(eqx.Module):
    """A constant function of time."""

    value: Float[Array, ""] = eqx.field(converter=to_jax)

    def __call__(self, t):
        return self.value + jnp.zeros_like(t)


class StraightLine(eqx.Module):
    """`r_c(t) = speed * t * (cos heading, sin heading)`: the straight line of (5.5).

    The paper's (5.5) `x = 0, y = 0.13 t` in its figure frame is `heading = 0` here (our `x`
    is the paper's `y`; see `docs/model.md`).
    """

    speed: Float[Array, ""] = eqx.field(converter=to_jax)
    heading: Float[Array, ""] = eqx.field(converter=to_jax, default=0.0)

    def __call__(self, t):
        return self.speed * t * jnp.stack([jnp.cos(self.heading), jnp.sin(self.heading)])


def straight_line(speed: float, heading: float = 0.0) -> StraightLine:
    """The path of (5.5): see `StraightLine`."""
    return StraightLine(speed, heading)


@eqx.filter_jit
def eval_controls(controls, ts: Float[Array, " T"]) -> Float[Array, "T N"]:
    """`controls(t)` at each of `ts` (compiled once per control structure)."""
    return jax.vmap(controls)(ts)
