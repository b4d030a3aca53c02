"""What a Monte-Carlo trial draws: the robot's parameters (`jsphere.model.uncertainty`) and the
actuators' errors (`Actuators`). Trial `i` of a study with seed `s` draws varied name `j` from
`fold_in(fold_in(PRNGKey(s), i), j)` and its initial-velocity and actuator perturbations from
`fold_in(fold_in(PRNGKey(s), i), 2**20)`, so a trial is the same whatever the batch it runs in.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._runtime.checks import real
from ..controls import Sampled
from ..model.uncertainty import MAX_REDRAWS as MAX_REDRAWS
from ..model.uncertainty import REASONS as REASONS
from ..model.uncertainty import Uncertainty as Uncertainty
from ..model.uncertainty import draw_code as draw_code

#: the fold of a trial's key that seeds its initial-velocity and actuator perturbations
#: (the varied names use the folds 0, 1, ...)
PERTURBATION_FOLD = 2**20


class Actuators(eqx.Module):
    """Imperfect execution of a replayed command table (`mode="torques"` or `"wheel_speeds"`).

    Per trial and wheel a gain `1 + gain_sd z`, per trial a delay `max(0, delay_s + delay_sd z)`
    [s], per sample white noise of sd `white_sd` and band-limited noise of sd `band_sd` (through
    a first-order low-pass filter of bandwidth `band_hz`), in the command's units (N m or
    rad/s): the command is `gain * (plan(t - delay) + noise)`, zero before the delayed start.
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
