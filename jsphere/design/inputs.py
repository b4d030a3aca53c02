"""The input programmes of an excitation design: windowed, saturated multisines.

Each programme drives one trial of `duration` T [s]. Per wheel i

    s_i(t) = sum_j a_ij sin(2 pi f_j t) + b_ij cos(2 pi f_j t),      f_j = j f_max / F  (j = 1..F)
    u_i(t) = L tanh(w(t) s_i(t)),
    w(t)   = sin^2(pi/2 min(1, t/r)) sin^2(pi/2 min(1, (T - t)/r))     (0 outside [0, T])

with `L` the motor limit of the input kind (`max_torque` [N m] for torques `K`,
`max_wheel_speed` [rad/s] for wheel speeds `chi_dot`) and `r` the ramp time. So every
programme is smooth, starts and ends at 0 with zero slope (the robot starts from rest and the
command ends at rest), and keeps strictly within `|u_i| < L` for every coefficient vector. The
coefficients `(a, b)` are in units of `L`; all programmes of a design are one flat vector
`z (M N 2F,)` (`coefficients`).

The programmes are written as inputs tables (`t, chi_dot_1..N` or `t, K_1..N`, read by
`jsphere.read_inputs_csv`) at a row rate (`table`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

#: the input kinds of a design and their names in inputs tables / trials
KINDS = {"K": "torques", "chi_dot": "wheel_speeds"}


class Spec(eqx.Module):
    """The shape of a design (static: it fixes the compiled functions).

    `kind`: `"K"` or `"chi_dot"`; `trials` M; `wheels` N; `n_freqs` F; `duration` T [s];
    `f_max` [Hz]: the highest frequency; `ramp` [s]: the ramp time `r`; `limit` L (N m or rad/s).
    """

    kind: str = eqx.field(static=True)
    trials: int = eqx.field(static=True)
    wheels: int = eqx.field(static=True)
    n_freqs: int = eqx.field(static=True)
    duration: float = eqx.field(static=True)
    f_max: float = eqx.field(static=True)
    ramp: float = eqx.field(static=True)
    limit: float = eqx.field(static=True)

    @property
    def size(self) -> int:
        """Length of the flat coefficient vector `z`."""
        return self.trials * self.wheels * 2 * self.n_freqs

    @property
    def freqs(self) -> np.ndarray:
        return self.f_max * np.arange(1, self.n_freqs + 1) / self.n_freqs

    @property
    def trial_kind(self) -> str:
        """`"torques"` or `"wheel_speeds"`: the kind of a `Trial` driven by the programmes."""
        return KINDS[self.kind]


def window(t, T: float, r: float):
    """`w(t)` of the module docstring: 0 at and beyond both ends, 1 between the ramps (C1)."""
    a = jnp.clip(t / r, 0.0, 1.0)
    b = jnp.clip((T - t) / r, 0.0, 1.0)
    return jnp.sin(0.5 * jnp.pi * a) ** 2 * jnp.sin(0.5 * jnp.pi * b) ** 2


class Programme(eqx.Module):
    """One trial's programme `u(t) (N,)` (module docstring): `coef (N, 2F)` (`a` then `b`, in
    units of `limit`), frequencies [Hz], limit, duration and ramp. Pure JAX: a `Torques` or
    `WheelSpeeds` control takes it as its function of time."""

    coef: Float[Array, "N F2"]
    freqs: Float[Array, " F"]
    limit: float = eqx.field(static=True)
    duration: float = eqx.field(static=True)
    ramp: float = eqx.field(static=True)

    def raw(self, t):
        """`s(t) (N,)` in units of `limit`, before the window and the saturation."""
        ph = 2.0 * jnp.pi * self.freqs * t
        basis = jnp.concatenate([jnp.sin(ph), jnp.cos(ph)])
        return self.coef @ basis

    def __call__(self, t):
        w = window(t, self.duration, self.ramp)
        return self.limit * jnp.tanh(w * self.raw(t))


def coefficients(z: Float[Array, " V"], spec: Spec) -> Float[Array, "M N F2"]:
    """The flat vector `z` as `(M, N, 2F)` coefficient blocks."""
    return z.reshape(spec.trials, spec.wheels, 2 * spec.n_freqs)


def programmes(z: Float[Array, " V"], spec: Spec) -> list[Programme]:
    """The M programmes of `z`."""
    return [programme(c, spec) for c in coefficients(z, spec)]


def programme(c: Float[Array, "N F2"], spec: Spec) -> Programme:
    """The programme of one coefficient block `c (N, 2F)` (traceable; for `vmap` over trials)."""
    return Programme(c, jnp.asarray(spec.freqs, c.dtype), spec.limit, spec.duration, spec.ramp)


def sample_times(duration: float, rate: float) -> np.ndarray:
    """`0, 1/rate, ...` up to `duration`, with `duration` itself last."""
    t = np.arange(int(math.floor(duration * rate + 1e-9)) + 1) / rate
    if duration - t[-1] > 1e-9:
        t = np.append(t, duration)
    return t


_values = jax.jit(lambda prog, ts: jax.vmap(prog)(ts))


def values_at(prog: Programme, t: np.ndarray) -> np.ndarray:
    """A programme's values `(R, N)` at the times `t`."""
    return np.asarray(_values(prog, jnp.asarray(t, prog.coef.dtype)))


def table(prog: Programme, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """`(t (R,), values (R, N))`: the programme at `rate` rows per second from 0 to its duration
    (an inputs table; the first and last rows are 0)."""
    t = sample_times(prog.duration, rate)
    return t, values_at(prog, t)


def rms(values: np.ndarray) -> float:
    """The RMS amplitude of a table's values (over rows and wheels)."""
    v = np.asarray(values, float)
    return float(np.sqrt(np.mean(v * v)))


def random_start(spec: Spec, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """A random coefficient vector: Gaussian `a, b` of standard deviation `scale / sqrt(F)` (so
    `s_i(t)` has an RMS of about `scale`)."""
    return rng.normal(0.0, scale / math.sqrt(spec.n_freqs), spec.size)


def random_multisine(spec: Spec, rng: np.random.Generator) -> np.ndarray:
    """A random multisine: every frequency with the same amplitude and a uniform random phase,
    per wheel and trial (unit RMS of `s_i`, before the window and the saturation)."""
    M, N, F = spec.trials, spec.wheels, spec.n_freqs
    ph = rng.uniform(0.0, 2.0 * math.pi, (M, N, F))
    amp = math.sqrt(2.0 / F)
    return np.concatenate([amp * np.cos(ph), amp * np.sin(ph)], axis=-1).reshape(-1)


def match_rms(z_unit: np.ndarray, spec: Spec, target_rms: float, rate: float) -> tuple[np.ndarray, float]:
    """`c z_unit` with the scale `c` chosen (by bisection) so that the programmes' tables at
    `rate` have the RMS amplitude `target_rms` (over trials, rows and wheels); returns the
    coefficients and the RMS reached. A target at or beyond what the saturation allows gives the
    largest scale tried (`1e3`)."""

    def rms_of(c):
        vals = [table(p, rate)[1] for p in programmes(jnp.asarray(c * z_unit), spec)]
        return rms(np.concatenate(vals))

    lo, hi = 0.0, 1.0
    while rms_of(hi) < target_rms and hi < 1e3:
        lo, hi = hi, hi * 2.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if rms_of(mid) < target_rms:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-6 * hi:
            break
    c = 0.5 * (lo + hi)
    return c * z_unit, rms_of(c)
