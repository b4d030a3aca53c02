"""Plans that still land when the robot is not the model (`plan(..., robust=RobustOptions(...))`), and the spread of a
plan's miss over the robots an `Uncertainty` allows (`miss_distribution`).

The robot executes a plan's wheel-speed table (servo constraints, `WheelSpeeds`). With the
wheel rates fixed, (2.4) fixes `omega - Omega`, so the shell's rolling follows the command up
to the platform's own rotation `omega`, and that is the only place where the parameters enter:
a plan misses by about `R0` times the platform's attitude error at the end, and keeps rocking
with the speed of that error. Torque tables instead scale every acceleration with the
inertias (`docs/planning.md` compares both).

The robust search starts from the nominal plan (the plan for the nominal parameters) and
minimises, by Levenberg-Marquardt over the same decision vector (`gait_from_vector`), the mean
of the `k` largest per-sample losses `|(x(T), y(T)) - target|^2 / position_scale^2 +
|R0 Omega(T)|^2 / speed_scale^2` over `S` drawn parameter sets, `k = ceil((1 - quantile) S)`:
the conditional value at risk of the loss, an upper bound of its `quantile`-quantile that is
continuous in the plan (the Gauss-Newton model is the one of the `k` samples that are worst at
the point). Each sample replays the nominal wheel-speed table of the search model (`rollout`)
with classical RK4 on its grid, all samples under one `vmap`; the limits and costs are those of
`plan`, at the nominal parameters.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.checks import real, whole
from .._runtime.errors import InputError
from .._runtime.progress import Progress
from ..controls import Sampled, Torques, WheelSpeeds
from ..model.params import RobotParams, derive
from ..model.rotations import rotmat
from ..model.state import Flat, State
from ..solve.field_args import FieldArgs
from ..solve.fixed_grid import integrate
from ..solve.internal import torque_field, wheel_field
from .many import plan_batch
from .problem import (
    TOL_SPEED,
    Limits,
    Objective,
    PlanOptions,
    PlanSettings,
    _check_request,
    _duration_inv,
    _vec_targets,
    check_target,
    gait_from_vector,
)
from .residuals import _residuals, with_jacobian
from .result import Plan, manoeuvre_plan
from .rollout import rollout
from .search import lm_search
from .uncertainty import Uncertainty
from .verify import _accurate, _limit_report, _terminal_errors, exceeded

#: the relative gain in the p95 miss on a validation draw that the robust search's plan needs
#: over the nominal plan to be kept
KEEP_MARGIN = 0.05
#: the replay modes: the table column a robot executes
MODES = ("wheel_speeds", "torques")


# ----------------------------------------------------------------------------- replay


def replay_end(params: RobotParams, ts, table, mode: str = "wheel_speeds", grid=None):
    """The state at `ts[-1]` of a robot from rest (`State.at_rest`) that executes the table
    `table (T, N)` (cubic, as `WheelSpeeds.from_samples`/`Torques.from_samples` read it),
    integrated with classical RK4 (`jsphere.solve.fixed_grid`), one step per interval of `grid`
    (default: of `ts`; a grid must start at `ts[0]` and end at `ts[-1]`) (pure JAX, vmappable
    over `params`). Returns
    `(x, y, Omega (3,), gamma (3,))`."""
    d = derive(params)
    dt = params.R0.dtype
    ts = jnp.asarray(ts, dt)
    tab = Sampled(ts, jnp.asarray(table, dt), "cubic")
    control, field = (WheelSpeeds(tab, ()), wheel_field) if mode == "wheel_speeds" else (Torques(tab, ()), torque_field)
    # the end of the control lies past the table: the last stage of each step is evaluated just
    # inside its interval instead (the table's left limit, differentiable in the knot times)
    args = FieldArgs(params=params, derived=d, control=control)
    grid = ts if grid is None else jnp.asarray(grid, dt)
    z0 = State.at_rest(params).flatten().astype(dt)
    zT = integrate(lambda t, z: field(t, z, args), z0, grid, last=1.0 - 1e-12, save=False)
    return zT[Flat.x], zT[Flat.y], zT[Flat.Omega], rotmat(zT[Flat.q])[2]


#: the longest RK4 step of `miss_distribution` [s]: a table at a higher rate is integrated
#: over several rows per step (its cubic interpolant is smooth between rows)
REPLAY_STEP = 0.005


def _replay_grid(ts: np.ndarray) -> np.ndarray:
    """Every `stride`-th row of `ts` (and its last), `stride` the most rows within `REPLAY_STEP`."""
    stride = max(1, int(REPLAY_STEP / max(float(np.median(np.diff(ts))), 1e-12)))
    grid = ts[::stride]
    return grid if grid[-1] == ts[-1] else np.append(grid, ts[-1])


@eqx.filter_jit
def _replay_batch(samples: RobotParams, ts, table, mode: str, grid):
    def one(p):
        x, y, Om, g = replay_end(p, ts, table, mode, grid)
        return x, y, p.R0 * jnp.linalg.norm(jnp.cross(Om, g))

    return jax.vmap(one)(samples)


def in_batches(fn, batch: int, samples: RobotParams, *per_sample) -> list[np.ndarray]:
    """`fn(part, *parts)` on consecutive slices of `batch` parameter sets of `samples` (stacked
    `RobotParams`) and of the arrays `per_sample` (one row per set); its outputs (a tuple of
    arrays, one row per set) joined as numpy arrays."""
    n = int(np.shape(samples.R0)[0])
    outs = []
    for a in range(0, n, batch):
        cut = lambda v, a=a: v[a : a + batch]
        outs.append(fn(jax.tree_util.tree_map(cut, samples), *map(cut, per_sample)))
    return [np.concatenate([np.asarray(o[i]) for o in outs]) for i in range(len(outs[0]))]


def miss_distribution(
    plan_: Plan, samples: RobotParams, *, mode: str = "wheel_speeds", batch: int = 512
) -> dict[str, np.ndarray]:
    """Replay a plan's table (`Plan.table`, the column of `mode`) on every parameter set of
    `samples` (stacked `RobotParams`, e.g. `Uncertainty.draw`), RK4 on the table's rows
    (several rows per step for tables faster than `1 / REPLAY_STEP`).
    Returns per set `miss_m` (distance of the end from the plan's target), `speed_m_s`
    (`R0 |Omega x gamma|` at the end) and `final_xy (n, 2)`."""
    if mode not in MODES:
        raise InputError(f"miss_distribution: mode must be one of {MODES}; got {mode!r}.")
    ts = np.asarray(plan_.trajectory.ts)
    table = plan_.commanded("chi_dot" if mode == "wheel_speeds" else "K")
    grid = _replay_grid(ts)
    x, y, v = in_batches(lambda part: _replay_batch(part, ts, table, mode, grid), batch, samples)
    tg = plan_.target
    return {"miss_m": np.hypot(x - tg[0], y - tg[1]), "speed_m_s": v, "final_xy": np.stack([x, y], axis=1)}


def miss_summary(dist: dict[str, np.ndarray]) -> dict[str, float]:
    """`mean`, `p50`, `p95`, `max` of the miss [m] and `speed_mean`, `speed_p95` [m/s]."""
    m, v = dist["miss_m"], dist["speed_m_s"]
    return {
        "mean": float(np.mean(m)),
        "p50": float(np.percentile(m, 50)),
        "p95": float(np.percentile(m, 95)),
        "max": float(np.max(m)),
        "speed_mean": float(np.mean(v)),
        "speed_p95": float(np.percentile(v, 95)),
    }


# ----------------------------------------------------------------------------- the search


def _top_k(S: int, quantile: float) -> int:
    return max(1, min(S, math.ceil((1.0 - quantile) * S - 1e-9)))


def _robust_residuals(z, target, params, samples, lim, obj, s, k: int):
    """The residual vector of the robust search: the terminal residuals of the `k` samples
    whose loss is largest (each scaled by `1/sqrt(k)`; the others zero), then the heading,
    limit and cost rows of `_residuals` at the nominal parameters."""
    gait = gait_from_vector(z, lim, s)
    ro = rollout(params, gait, s.n_steps)

    def one(p):
        x, y, Om, _ = replay_end(p, ro.ts, ro.chi_dot, "wheel_speeds")
        return jnp.concatenate(
            [
                jnp.stack([(x - target[0]) / obj.position_scale, (y - target[1]) / obj.position_scale]),
                p.R0 * Om / obj.speed_scale,
            ]
        )

    r = jax.vmap(one)(samples)  # (S, 5)
    loss = jax.lax.stop_gradient(jnp.sum(r * r, axis=1))
    thr = jnp.sort(loss)[loss.shape[0] - k]
    w = (loss >= thr).astype(r.dtype) / jnp.sqrt(jnp.asarray(k, r.dtype))
    rest = _residuals(z, target, params, lim, obj, s)[5:]
    return jnp.concatenate([(r * w[:, None]).ravel(), rest])


@eqx.filter_jit
def _robust_search(z0s, target, params, samples, lim, obj, s, k: int, steps: int):
    """Every start of `z0s (R, V)` under one `vmap`; returns `(z (R, V), objective (R,))`."""

    rj = with_jacobian(lambda z: _robust_residuals(z, target, params, samples, lim, obj, s, k))
    # Levenberg-Marquardt alone (no Adam steps): the search's loop, `SEARCH_LM`
    zb, fb, _, _ = jax.vmap(lambda z: lm_search(z, rj, 0, steps, s.learning_rate))(z0s)
    return zb, jnp.where(jnp.isfinite(fb), fb, jnp.inf)


def decision_vector(gait, lim: Limits) -> np.ndarray:
    """The decision vector `z` of a `smooth_gait` manoeuvre (inverse of `gait_from_vector`)."""
    spin = gait.omega_gamma.coeffs if hasattr(gait.omega_gamma, "coeffs") else jnp.zeros(0)
    return np.concatenate(
        [np.asarray(gait.tilt.coeffs).ravel(), np.asarray(spin).ravel(), [float(_duration_inv(gait.T, lim))]]
    )


def _starts(z: np.ndarray, restarts: int, lim: Limits, seed: int) -> np.ndarray:
    """The nominal plan's vector, then copies of it stretched in time (the tilt lowered so that
    the small-tilt distance `~ a T^2` stays the same) with a little noise."""
    rng = np.random.default_rng(seed)
    out = [z]
    T = float(lim.min_time + (lim.max_time - lim.min_time) / (1.0 + math.exp(-z[-1])))
    for r in range(1, restarts):
        T_r = min(T * (1.0 + 0.5 * r / max(restarts - 1, 1)), 0.97 * lim.max_time)
        zr = z.copy()
        zr[:-1] *= (T / T_r) ** 2
        zr[:-1] += 0.02 * np.abs(zr[:-1]).max() * rng.normal(size=zr.size - 1)
        zr[-1] = float(_duration_inv(T_r, lim))
        out.append(zr)
    return np.stack(out)


# ----------------------------------------------------------------------------- the request


@dataclasses.dataclass(frozen=True)
class RobustOptions:
    """The robust plan of `plan(..., robust=RobustOptions(uncertainty, ...))` (see the module's
    description): a manoeuvre whose miss stays small over the robots that `uncertainty` allows,
    executed as wheel speeds.

    - `uncertainty`: the parameter distribution (`Uncertainty(names, kinds, a, b)` or `Uncertainty.from_fit`); its
      normal names are set to their means in `params` for the nominal plan.
    - `samples`: parameter sets drawn for the search; `quantile` in `[0, 1)`: the search
      minimises the mean loss of the worst `ceil((1 - quantile) samples)` of them (0: all).
    - `restarts`: starts of the robust search, vmapped: the nominal plan and slower versions.
    - `steps`: its Levenberg-Marquardt iterations.
    - `check_samples` (>= 1000 for the reports): the fresh draw on which `miss_mc` compares
      the nominal and the robust plan. The search's plan is kept only if its p95 miss on a
      third, independent draw of that size is at least `KEEP_MARGIN` (5 %) below the nominal
      plan's; otherwise the robust plan is the nominal plan (`RobustPlan.kept` False).
    - `nominal`: the nominal plan, if planned already (`plan` with the nominal parameters and
      the same request); else it is planned with the request's `PlanOptions`.

    The request's `PlanOptions.seed` seeds the restarts and both draws (the check draw uses its
    own stream), and its `rate` is the robust plan's. Checked by `plan`, before any work.
    """

    uncertainty: Uncertainty
    samples: int = 64
    quantile: float = 0.95
    restarts: int = 4
    steps: int = 40
    check_samples: int = 1000
    nominal: Plan | None = None


@dataclasses.dataclass
class RobustPlan:
    """What `plan` returns with `robust`. `plan`: the robust plan (verified at the nominal parameters
    with the accurate solver; `feasible` judges its limits, as its terminal errors at the
    nominal parameters are traded for the spread); `nominal`: the plan for the nominal
    parameters; `miss_mc`: `{"nominal": ..., "robust": ...}` (`miss_summary`, metres) over a
    fresh draw of `check_samples` parameter sets, independent of the `samples` sets the search
    used; `objective`: the robust objective of the start (nominal plan) and of the result;
    `kept`: whether the search's plan was kept (False: it did not land better than the nominal
    plan on a validation draw, and `plan` is the nominal plan)."""

    plan: Plan
    nominal: Plan
    miss_mc: dict[str, Any]
    uncertainty: Uncertainty
    samples: int
    quantile: float
    check_samples: int
    seed: int
    objective: dict[str, float]
    elapsed_s: float
    kept: bool = True

    def to_json(self) -> dict[str, Any]:
        """The `robust` section of plan.json (`miss_mc` is written beside it)."""
        return {
            "source": self.uncertainty.source,
            "names": list(self.uncertainty.names),
            "samples": self.samples,
            "quantile": self.quantile,
            "check_samples": self.check_samples,
            "seed": self.seed,
            "mode": "wheel_speeds",
            "objective": self.objective,
            "kept": self.kept,
            "nominal_duration_s": self.nominal.duration,
            "nominal_errors": self.nominal.errors,
            "elapsed_s": self.elapsed_s,
        }

    def summary(self) -> str:
        n, r = self.miss_mc["nominal"], self.miss_mc["robust"]
        return (
            f"robust plan over {self.samples} drawn robots (quantile {self.quantile}); on {self.check_samples} fresh "
            f"draws the miss is mean {1e3 * n['mean']:.3f} / p95 {1e3 * n['p95']:.3f} mm for the nominal plan "
            f"(T = {self.nominal.duration:.2f} s), mean {1e3 * r['mean']:.3f} / p95 {1e3 * r['p95']:.3f} mm for the "
            f"robust one (T = {self.plan.duration:.2f} s)"
            + (
                ""
                if self.kept
                else "; the search's plan did not land better on a validation draw: the nominal plan is kept"
            )
        )


def plan_robust(params: RobotParams, to: Sequence[float], uncertainty: Uncertainty, **kwargs) -> RobustPlan:
    """Deprecated: `plan(params, to, robust=RobustOptions(uncertainty, ...))`.

    The keywords of `plan` pass through; `samples`, `quantile`, `restarts`, `robust_steps`
    (`RobustOptions.steps`), `check_samples` and `nominal` go into `RobustOptions`; `rate` and
    `seed` into `PlanOptions`, whose `restarts` for the nominal plan is `max(restarts, 2)`.
    Never raises for an infeasible plan (`RobustPlan.plan.feasible` says)."""
    warnings.warn(
        "plan_robust is deprecated; call jsphere.plan(params, to, robust=jsphere.RobustOptions(uncertainty, ...))",
        DeprecationWarning,
        stacklevel=2,
    )
    fields = {k: kwargs.pop(k) for k in _ROBUST_KEYWORDS if k in kwargs}
    r = RobustOptions(uncertainty, steps=kwargs.pop("robust_steps", RobustOptions.steps), **fields)
    o = PlanOptions(restarts=max(r.restarts, 2) if isinstance(r.restarts, int) else r.restarts)
    o = dataclasses.replace(o, **{k: kwargs.pop(k) for k in ("rate", "seed") if k in kwargs})
    x, y = check_target("plan_robust", to)
    return robust_plan("plan_robust", params, (x, y, kwargs.pop("heading", None)), o=o, r=r, **kwargs)


#: the keywords of `plan_robust` that are fields of `RobustOptions` under the same name
_ROBUST_KEYWORDS = ("samples", "quantile", "restarts", "check_samples", "nominal")


def _check_robust(where: str, r: RobustOptions, o: PlanOptions) -> None:
    """`InputError` naming a bad field of `r` (or the seed of `o`), before any work."""
    whole(where, "samples", r.samples, 2)
    whole(where, "restarts", r.restarts, 1)
    whole(where, "robust_steps" if where == "plan_robust" else "steps", r.steps, 1)
    whole(where, "check_samples", r.check_samples, 2)
    whole(where, "seed", o.seed, 0)
    quantile = real(where, "quantile", r.quantile)
    if not 0.0 <= quantile < 1.0:
        raise InputError(f"{where}: quantile must be in [0, 1); got {quantile}.")
    if not isinstance(r.uncertainty, Uncertainty):
        raise InputError(f"{where}: uncertainty must be a jsphere.Uncertainty; got {type(r.uncertainty).__name__}.")
    if r.nominal is not None and not isinstance(r.nominal, Plan):
        raise InputError(f"{where}: nominal must be a jsphere.Plan; got {type(r.nominal).__name__}.")


def robust_plan(
    where: str,
    params,
    to3,
    limits=None,
    objective=None,
    settings=None,
    *,
    o: PlanOptions,
    r: RobustOptions,
    progress=None,
    options=None,
) -> RobustPlan:
    """The robust plan to `to3 = (x, y, heading or None)` (`RobustOptions`); `where` names the
    caller in messages."""
    if not isinstance(r, RobustOptions):
        raise InputError(f"{where}: robust must be a jsphere.RobustOptions; got {type(r).__name__}.")
    _check_robust(where, r, o)
    t0 = time.perf_counter()
    prog = Progress(progress)
    lim, obj, s = limits or Limits(), objective or Objective(), settings or PlanSettings()
    seed, samples = o.seed, r.samples
    p_nom = r.uncertainty.nominal(params)
    _, draw = r.uncertainty.draw(params, samples, seed)
    _, check = r.uncertainty.draw(params, r.check_samples, seed + 1_000_003)
    if r.nominal is None:
        targets = _check_request(where, [to3], lim, obj, s, o)
        nominal = plan_batch(where, p_nom, targets, lim, obj, s, o, progress, options)[0]
    elif not r.nominal.gaits:
        raise InputError(
            f"{where}: RobustOptions.nominal is a {r.nominal.family} plan; a robust plan starts from a gait plan: "
            "plan the nominal with PlanOptions(family='gait'), or leave nominal out."
        )
    else:
        nominal = r.nominal
    target = jnp.asarray(_vec_targets([to3])[0], p_nom.R0.dtype)
    z_nom = decision_vector(nominal.gaits[0], lim)
    z0s = jnp.asarray(_starts(z_nom, r.restarts, lim, seed), p_nom.R0.dtype)
    k = _top_k(samples, r.quantile)
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, p_nom.R0.dtype), m) for m in (lim, obj))
    prog.say(
        f"jsphere plan: robust search over {samples} drawn robots (worst {k}), {r.restarts} starts x {r.steps} LM steps"
    )
    with prog.phase("jsphere plan: robust search"):
        zs, fs = _robust_search(z0s, target, p_nom, draw, lim_a, obj_a, s, k, int(r.steps))
        zs, fs = np.asarray(zs), np.asarray(fs)
    best = int(np.argmin(fs))
    f_start = float(jnp.sum(_robust_residuals(jnp.asarray(z0s[0]), target, p_nom, draw, lim_a, obj_a, s, k) ** 2))
    robust = _verified_plan(p_nom, zs[best], target, lim, s, o.rate, options, nominal, t0)
    # the search saw only `samples` robots: keep its plan only if it also lands better on
    # another independent draw (by KEEP_MARGIN), else the nominal plan is the robust one
    _, valid = r.uncertainty.draw(params, r.check_samples, seed + 2_000_003)
    p95 = {k: miss_summary(miss_distribution(pl, valid))["p95"] for k, pl in (("n", nominal), ("r", robust))}
    kept = p95["r"] < (1.0 - KEEP_MARGIN) * p95["n"]
    robust = robust if kept else nominal
    prog.say(f"jsphere plan: replaying both plans on {r.check_samples} fresh draws")
    miss_mc = {
        "nominal": miss_summary(miss_distribution(nominal, check)),
        "robust": miss_summary(miss_distribution(robust, check)),
        "samples": int(r.check_samples),
        "mode": "wheel_speeds",
    }
    return RobustPlan(
        plan=robust,
        nominal=nominal,
        miss_mc=miss_mc,
        uncertainty=r.uncertainty,
        samples=int(samples),
        quantile=float(r.quantile),
        check_samples=int(r.check_samples),
        seed=int(seed),
        objective={"nominal": f_start, "robust": float(fs[best]) if kept else f_start},
        kept=bool(kept),
        elapsed_s=time.perf_counter() - t0,
    )


def _verified_plan(p, z, target, lim: Limits, s: PlanSettings, rate, options, nominal: Plan, t0: float) -> Plan:
    """The robust decision vector as a `Plan`: the accurate trajectory at the nominal
    parameters, its terminal errors there and its limits; feasible when the limits hold."""
    gait = gait_from_vector(jnp.asarray(z), lim, s)
    tr = _accurate(p, gait, rate, lim.max_time, options)
    tg = np.asarray(target)
    err = _terminal_errors(p, tr, tg)
    rep = _limit_report(p, tr, float(gait.T), lim)
    return manoeuvre_plan(
        p,
        gait,
        tr,
        rate,
        tg,
        err,
        rep,
        exceeded(rep),
        iterations=dict(nominal.iterations),
        elapsed_s=time.perf_counter() - t0,
        loss=float("nan"),
        restarts=nominal.restarts,
        at_rest=err["speed_m_s"] <= TOL_SPEED,
    )
