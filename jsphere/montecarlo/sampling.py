"""What a Monte-Carlo trial draws: the robot's parameters (`Draws`) and the actuators' errors
(`Actuators`), each from its own key, deterministic in the study's seed and the trial's index.

Trial `i` of a study with seed `s` draws varied name `j` from
`fold_in(fold_in(PRNGKey(s), i), j)` and its initial-velocity and actuator perturbations from
`fold_in(fold_in(PRNGKey(s), i), 2**20)`, so a trial is the same whatever the batch it runs in.
"""

from __future__ import annotations

from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._runtime.checks import real
from ..controls import Sampled
from ..model.names import set_value
from ..model.params import RULES, RobotParams, rule_code

#: redraws of a "truncate" distribution before a draw that is still invalid is rejected
MAX_REDRAWS = 100
#: why a draw is rejected, by `reject_code`: 0 valid, then every rule of `RobotParams`
#: (`jsphere.model.params.RULES`), then a drawn `R_m` that is not a positive distance
REASONS: tuple[str, ...] = ("valid", *(rule.reason for rule in RULES), "R_m <= 0")
#: the fold of a trial's key that seeds its initial-velocity and actuator perturbations
#: (the varied names use the folds 0, 1, ...)
PERTURBATION_FOLD = 2**20


def trial_key(seed, i) -> jax.Array:
    """The key of trial `i`: `fold_in(PRNGKey(seed), i)`."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), i)


def _sample(kinds: tuple[str, ...], ab, keys, dtype):
    """One value per varied name, from its key."""
    vals = []
    for j, kind in enumerate(kinds):
        a, b = ab[j, 0], ab[j, 1]
        if kind == "normal":
            vals.append(a + b * jax.random.normal(keys[j], dtype=dtype))
        else:
            vals.append(a + (b - a) * jax.random.uniform(keys[j], dtype=dtype))
    return jnp.stack(vals)


def with_values(params: RobotParams, names: Sequence[str], vals) -> RobotParams:
    """`params` with each of `names` set to its value in `vals`."""
    p = params
    for j, name in enumerate(names):
        p = set_value(p, name, vals[j])
    return p


def draw_code(params: RobotParams, names: Sequence[str], vals) -> Int[Array, ""]:
    """`reject_code` of a draw: 0 if the parameter set is valid, else the first broken rule
    (`REASONS`)."""
    code = rule_code(with_values(params, names, vals))
    for j, name in enumerate(names):
        if name == "R_m":
            code = jnp.where(vals[j] <= 0, len(REASONS) - 1, code)
    return code


class Draws(eqx.Module):
    """The distributions of a study's varied names (a checked `vary`, see `check_vary`).

    `names`, `kinds`: the varied names and their distributions ("normal" or "uniform");
    `ab`: per name, `(mean, sd)` or `(low, high)`; `truncate`: per name, whether it is drawn
    again while the parameter set is invalid.
    """

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    ab: Float[Array, "v 2"]
    truncate: Bool[Array, " v"]

    @classmethod
    def from_spec(cls, spec: Sequence[tuple[str, str, float, float, bool]], dtype) -> "Draws":
        """From the `[(name, kind, a, b, truncate)]` of `check_vary`."""
        names = tuple(name for name, _, _, _, _ in spec)
        kinds = tuple(kind for _, kind, _, _, _ in spec)
        ab = np.array([[a, b] for _, _, a, b, _ in spec], dtype=np.float64).reshape(len(spec), 2)
        trunc = np.array([t for *_, t in spec], dtype=bool)
        return cls(names, kinds, jnp.asarray(ab, dtype=dtype), jnp.asarray(trunc))

    def draw(self, params: RobotParams, seed, i) -> tuple[Float[Array, " v"], Int[Array, ""]]:
        """Values of every varied name for trial `i` (deterministic in `(seed, i)` only) and
        their `reject_code`. Variable `j` draws from `fold_in(fold_in(PRNGKey(seed), i), j)`;
        while the set is invalid, the "truncate" variables are redrawn from that key folded with
        the attempt number (at most `MAX_REDRAWS` times), so a study whose draws are all valid
        is the same with or without "truncate"."""
        dtype = params.R0.dtype
        key = trial_key(seed, i)
        keys = [jax.random.fold_in(key, j) for j in range(len(self.kinds))]
        if not self.kinds:
            return jnp.zeros((0,), dtype), jnp.zeros((), jnp.int32)
        vals = _sample(self.kinds, self.ab, keys, dtype)
        code = draw_code(params, self.names, vals)

        def cond(c):
            attempt, _, code = c
            return (code != 0) & jnp.any(self.truncate) & (attempt < MAX_REDRAWS)

        def body(c):
            attempt, vals, _ = c
            attempt = attempt + 1
            new = _sample(self.kinds, self.ab, [jax.random.fold_in(k, attempt) for k in keys], dtype)
            vals = jnp.where(self.truncate, new, vals)
            return attempt, vals, draw_code(params, self.names, vals)

        _, vals, code = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), vals, code))
        return vals, code

    def robot(self, params: RobotParams, vals, valid) -> RobotParams:
        """The robot of a draw, or the nominal one `params` for an invalid draw (only the varied
        leaves change), so that an invalid draw's solve is an ordinary one."""
        p = with_values(params, self.names, vals)
        if self.names:
            p = jax.tree_util.tree_map(lambda a, b: a if a is b else jnp.where(valid, a, b), p, params)
        return p


class Actuators(eqx.Module):
    """Imperfect execution of a replayed command table (`mode="torques"` or `"wheel_speeds"`).

    Per trial and wheel: a gain `1 + gain_sd z`; per trial: a delay
    `max(0, delay_s + delay_sd z)` [s]; per sample: white noise of sd `white_sd` and
    band-limited noise of sd `band_sd` (white noise through a first-order low-pass filter of
    bandwidth `band_hz`), in the command's units (N m or rad/s). The command is
    `gain * (plan(t - delay) + noise)`, held at zero before the delayed start.
    """

    gain_sd: float = 0.0
    delay_s: float = 0.0
    delay_sd: float = 0.0
    white_sd: float = 0.0
    band_sd: float = 0.0
    band_hz: float = 5.0

    def __check_init__(self):
        for name in ("gain_sd", "delay_s", "delay_sd", "white_sd", "band_sd"):
            real("Actuators", name, getattr(self, name))
        real("Actuators", "band_hz", self.band_hz, strict=True, unit="Hz")

    def table(self, key, plan_ts: Float[Array, " t"], plan_u: Float[Array, "t N"]) -> Sampled:
        """The command table `plan_u` at `plan_ts` as these actuators execute it, with the
        errors drawn from `key`."""
        dt_s = plan_ts[-1] / (plan_ts.shape[0] - 1)  # the mean sample interval
        k1, k2, k3, k4 = jax.random.split(key, 4)
        N = plan_u.shape[1]
        gain = 1.0 + self.gain_sd * jax.random.normal(k1, (N,), plan_u.dtype)
        delay = jnp.maximum(0.0, self.delay_s + self.delay_sd * jax.random.normal(k2, (), plan_u.dtype))
        u = plan_u + self.white_sd * jax.random.normal(k3, plan_u.shape, plan_u.dtype)
        if self.band_sd > 0:
            a = jnp.exp(-2.0 * jnp.pi * self.band_hz * dt_s)
            e = jax.random.normal(k4, plan_u.shape, plan_u.dtype)
            _, lp = jax.lax.scan(lambda c, x: (a * c + (1 - a) * x,) * 2, jnp.zeros(N, plan_u.dtype), e)
            u = u + self.band_sd * lp / jnp.sqrt((1 - a) / (1 + a))
        u = gain * u
        # zero until the delayed start (a duplicated time stamp encodes the jump)
        ts = jnp.concatenate([jnp.zeros((1,), plan_ts.dtype), plan_ts + delay])
        u = jnp.concatenate([jnp.zeros((1, N), u.dtype), u])
        return Sampled(ts, u, "cubic")
