"""The planning problem: motor and motion limits, the least-squares objective, the sizes of
the search, the checks of a request, and the decision vector of one manoeuvre.

A manoeuvre is one `TiltGait` (`jsphere.gaits.families`) with `Smooth` profiles: tilt vector
`u(t)` (two rows of Fourier-cosine coefficients times `sin^3(pi t/T)`), spin `omega_gamma(t)`
and a free duration `T`. It starts and ends on the Proposition's stationary motion by
construction (`gamma = gamma_m`, `gamma_dot = 0`, `omega_gamma = 0`; with `sin^3` the torques
also start and end at 0). See `docs/planning.md`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._runtime.checks import is_number, real, whole
from .._runtime.checks import is_traced as _traced
from .._runtime.errors import InputError
from ..gaits.families import TiltGait, smooth_gait
from ..model.limits import Limits


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


class DirectSettings(eqx.Module):
    """Sizes of a direct plan (static: they fix the compiled functions).

    `intervals`: knots - 1; `substeps`: RK4 steps per interval; `tol`, `max_iter`: IPOPT's;
    `rounds`: solves at most, each tightening the limits and moving the target by what the
    accurate replay missed.
    """

    intervals: int = eqx.field(static=True, default=60)
    substeps: int = eqx.field(static=True, default=1)
    tol: float = eqx.field(static=True, default=1e-8)
    max_iter: int = eqx.field(static=True, default=500)
    rounds: int = eqx.field(static=True, default=4)

    def __check_init__(self):
        for name, low in (("intervals", 2), ("substeps", 1), ("max_iter", 1), ("rounds", 1)):
            whole("DirectSettings", name, getattr(self, name), low)


#: the default terminal speed tolerance of a plan [m/s] (`R0 |Omega x gamma|` at the end): a plan
#: whose end is within it ends at rest (`Plan.at_rest`)
TOL_SPEED = 5e-4


@dataclasses.dataclass(frozen=True)
class PlanOptions:
    """The request's options of `plan`, `plan_route` and `plan_many` besides the limits, the
    objective and the search's sizes.

    - `restarts`: random restarts per target (the best is kept).
    - `rate`: rows per second [Hz] of the plan's table (the accurate re-simulation's grid).
    - `seed`: of the restarts.
    - `tol_position` [m], `tol_speed` [m/s], `tol_heading` [rad]: terminal tolerances for
      `Plan.feasible`.
    - `verify`: re-simulate with the accurate solver (needed for the table; `False` returns the
      search model's result only, for benchmarks; gait plans).
    - `family`: `"direct"` (default): free torque profiles, minimum time by multiple shooting
      (`jsphere.planning.direct`); `"gait"`: the paper's tilt gaits searched with restarts
      (`PlanSettings`). Routes, `plan_many` and robust plans use the gait family.

    The values are checked by the planner, before any work.
    """

    restarts: int = 16
    rate: float = 1000.0
    seed: int = 0
    tol_position: float = 5e-4
    tol_speed: float = TOL_SPEED
    tol_heading: float = 1e-3
    verify: bool = True
    family: str = "direct"


#: the plan families of `PlanOptions.family`
FAMILIES = ("direct", "gait")
#: the most rows a plan's table may have (`max_time * rate`): about 1 GB of trajectory
MAX_ROWS = 10_000_000


def check_target(where: str, to) -> tuple:
    """`to` if it is one target `(x, y)`, else `InputError` (its numbers are checked by
    `_check_request`)."""
    if isinstance(to, (str, bytes)) or not isinstance(to, (Sequence, np.ndarray)) or len(to) != 2:
        raise InputError(f"{where}: to must be the target (x, y) in m; got {to!r}.")
    return to[0], to[1]


def _check_request(where: str, targets, limits, objective, settings, o: PlanOptions, nan_free=True, noun="targets"):
    """Check a planning request before any work; return the targets as lists (`noun`: what
    messages call them).
    Raises `InputError` naming the value: targets `(x, y)` or `(x, y, psi)` with finite
    numbers (`psi` None, or NaN with `nan_free`, for a free heading), `restarts >= 1`,
    `rate > 0`, `seed >= 0`, positive tolerances, and `Limits`, `Objective`, `PlanSettings`
    instances."""
    for name, v, cls in (
        ("limits", limits, Limits),
        ("objective", objective, Objective),
        ("settings", settings, (PlanSettings, DirectSettings)),
    ):
        if v is not None and not isinstance(v, cls):
            names = " or jsphere.".join(c.__name__ for c in (cls if isinstance(cls, tuple) else (cls,)))
            raise InputError(f"{where}: {name} must be a jsphere.{names}; got {type(v).__name__}.")
    if o.family not in FAMILIES:
        raise InputError(f"{where}: family must be one of {', '.join(FAMILIES)}; got {o.family!r}.")
    whole(where, "restarts", o.restarts, 1)
    whole(where, "seed", o.seed, 0)
    rate = real(where, "rate", o.rate, strict=True, unit="Hz")
    for name in ("tol_position", "tol_speed", "tol_heading"):
        real(where, name, getattr(o, name), strict=True)
    lim = limits or Limits()
    if lim.max_time * rate > MAX_ROWS:
        raise InputError(
            f"{where}: rate = {rate:g} Hz makes {lim.max_time * rate:.3g} rows over max_time = {lim.max_time:g} s "
            f"(at most {MAX_ROWS:.0e}); lower the rate."
        )
    if isinstance(targets, (str, bytes)) or not isinstance(targets, Sequence) or not len(targets):
        raise InputError(f"{where}: {noun} must be a non-empty list of (x, y) or (x, y, heading); got {targets!r}.")
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
