"""Plans that still land when the robot is not the model (`plan_robust`), and the spread of a
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
from ..solve.options import SolverOptions
from .many import TOL_SPEED, plan_many
from .problem import Limits, Objective, PlanSettings, _duration_inv, _vec_targets, gait_from_vector
from .residuals import _residuals
from .result import Plan
from .rollout import rollout
from .search import SEARCH_LM
from .uncertainty import Uncertainty
from .verify import _accurate, _limit_report, _terminal_errors

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
    cols = plan_.table()
    N = plan_.params.n_wheels
    key = "chi_dot" if mode == "wheel_speeds" else "K"
    ts = cols["t"]
    table = np.stack([cols[f"{key}_{i + 1}"] for i in range(N)], axis=1)
    n = int(np.shape(samples.R0)[0])
    grid = _replay_grid(ts)
    xs, ys, vs = [], [], []
    for a in range(0, n, batch):
        part = jax.tree_util.tree_map(lambda v, a=a: v[a : a + batch], samples)
        x, y, v = _replay_batch(part, ts, table, mode, grid)
        xs.append(np.asarray(x))
        ys.append(np.asarray(y))
        vs.append(np.asarray(v))
    x, y, v = np.concatenate(xs), np.concatenate(ys), np.concatenate(vs)
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


def _robust_one(z0, target, params, samples, lim, obj, s, k: int, steps: int):
    """Levenberg-Marquardt with delayed acceptance (`jsphere.planning.search.SEARCH_LM`, the
    damping changing from the second iteration on) on `_robust_residuals`; returns the best
    point and its objective."""

    def f(z):
        out = _robust_residuals(z, target, params, samples, lim, obj, s, k)
        return out, out

    def body(c, it):
        z, pred, zb, lm = c
        J, r = jax.jacfwd(f, has_aux=True)(z)
        cost = jnp.sum(r**2)
        cost = jnp.where(jnp.isfinite(cost) & jnp.all(jnp.isfinite(J)), cost, jnp.inf)
        zb, new = SEARCH_LM.update(zb, z, lm, cost, (r, J), pred)
        lm = eqx.tree_at(lambda m: m.lam, new, jnp.where(it > 0, new.lam, lm.lam))
        z_next, pred = SEARCH_LM.propose(zb, lm)
        return (z_next, pred, zb, lm), None

    r0 = _robust_residuals(z0, target, params, samples, lim, obj, s, k)
    inf = jnp.asarray(jnp.inf, z0.dtype)
    lm0 = SEARCH_LM.init(inf, (r0, jnp.zeros((r0.shape[0], z0.shape[0]), z0.dtype)))
    (_, _, zb, lm), _ = jax.lax.scan(body, (z0, inf, z0, lm0), jnp.arange(steps + 1))
    return zb, lm.cost


@eqx.filter_jit
def _robust_search(z0s, target, params, samples, lim, obj, s, k: int, steps: int):
    """Every start of `z0s (R, V)` under one `vmap`; returns `(z (R, V), objective (R,))`."""
    zb, fb = jax.vmap(lambda z: _robust_one(z, target, params, samples, lim, obj, s, k, steps))(z0s)
    return zb, jnp.where(jnp.isfinite(fb), fb, jnp.inf)


def robust_objective(z, target, params, samples, lim, obj, s, quantile: float) -> jax.Array:
    """The robust search's objective at the decision vector `z` (sum of squares of
    `_robust_residuals`), for tests and diagnostics."""
    k = _top_k(int(np.shape(samples.R0)[0]), quantile)
    r = _robust_residuals(jnp.asarray(z), jnp.asarray(target), params, samples, lim, obj, s, k)
    return jnp.sum(r**2)


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


@dataclasses.dataclass
class RobustPlan:
    """What `plan_robust` returns. `plan`: the robust plan (verified at the nominal parameters
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


def plan_robust(
    params: RobotParams,
    to: Sequence[float],
    uncertainty: Uncertainty,
    *,
    heading: float | None = None,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    samples: int = 64,
    quantile: float = 0.95,
    restarts: int = 4,
    robust_steps: int = 40,
    check_samples: int = 1000,
    rate: float = 1000.0,
    seed: int = 0,
    progress: bool | None = None,
    options: SolverOptions | None = None,
    nominal: Plan | None = None,
) -> RobustPlan:
    """A rest-to-rest manoeuvre to `to = (x, y)` [m] whose miss stays small over the robots
    that `uncertainty` allows, executed as wheel speeds (see the module's description).

    **Arguments:** as `plan`, and
    - `uncertainty`: the parameter distribution (`Uncertainty.from_fit`, `.from_vary`); its
      normal names are set to their means in `params` for the nominal plan.
    - `samples`: parameter sets drawn for the search; `quantile` in `[0, 1)`: the search
      minimises the mean loss of the worst `ceil((1 - quantile) samples)` of them (0: all).
    - `restarts`: starts of the robust search, vmapped: the nominal plan and slower versions.
    - `robust_steps`: its Levenberg-Marquardt iterations.
    - `check_samples` (>= 1000 for the reports): the fresh draw on which `miss_mc` compares
      the nominal and the robust plan. The search's plan is kept only if its p95 miss on a
      third, independent draw of that size is at least `KEEP_MARGIN` (5 %) below the nominal
      plan's; otherwise the robust plan is the nominal plan (`RobustPlan.kept` False).
    - `seed`: of the restarts and of both draws (the check draw uses its own stream).
    - `nominal`: the nominal plan, if planned already (`plan` with the nominal parameters and
      the same request); else it is planned here.

    Returns a `RobustPlan`. Raises `InputError` for a bad argument, before any work.
    """
    whole("plan_robust", "samples", samples, 2)
    whole("plan_robust", "restarts", restarts, 1)
    whole("plan_robust", "robust_steps", robust_steps, 1)
    whole("plan_robust", "check_samples", check_samples, 2)
    whole("plan_robust", "seed", seed, 0)
    quantile = real("plan_robust", "quantile", quantile)
    if not 0.0 <= quantile < 1.0:
        raise InputError(f"plan_robust: quantile must be in [0, 1); got {quantile}.")
    if not isinstance(uncertainty, Uncertainty):
        raise InputError(f"plan_robust: uncertainty must be a jsphere.Uncertainty; got {type(uncertainty).__name__}.")
    if isinstance(to, (str, bytes)) or not isinstance(to, (Sequence, np.ndarray)) or len(to) != 2:
        raise InputError(f"plan_robust: to must be the target (x, y) in m; got {to!r}.")
    t0 = time.perf_counter()
    prog = Progress(progress)
    lim, obj, s = limits or Limits(), objective or Objective(), settings or PlanSettings()
    p_nom = uncertainty.nominal(params)
    _, draw = uncertainty.draw(params, samples, seed)
    _, check = uncertainty.draw(params, check_samples, seed + 1_000_003)
    if nominal is not None and not isinstance(nominal, Plan):
        raise InputError(f"plan_robust: nominal must be a jsphere.Plan; got {type(nominal).__name__}.")
    nominal = (
        nominal
        or plan_many(
            p_nom,
            [(to[0], to[1], heading)],
            limits=lim,
            objective=obj,
            settings=s,
            restarts=max(restarts, 2),
            rate=rate,
            seed=seed,
            progress=progress,
            options=options,
        )[0]
    )
    target = jnp.asarray(_vec_targets([(to[0], to[1], heading)])[0], p_nom.R0.dtype)
    z_nom = decision_vector(nominal.gaits[0], lim)
    z0s = jnp.asarray(_starts(z_nom, restarts, lim, seed), p_nom.R0.dtype)
    k = _top_k(samples, quantile)
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, p_nom.R0.dtype), m) for m in (lim, obj))
    prog.say(
        f"jsphere plan: robust search over {samples} drawn robots (worst {k}), {restarts} starts x {robust_steps} LM steps"
    )
    with prog.phase("jsphere plan: robust search"):
        zs, fs = _robust_search(z0s, target, p_nom, draw, lim_a, obj_a, s, k, int(robust_steps))
        zs, fs = np.asarray(zs), np.asarray(fs)
    best = int(np.argmin(fs))
    f_start = float(robust_objective(z_nom, target, p_nom, draw, lim_a, obj_a, s, quantile))
    robust = _verified_plan(p_nom, zs[best], target, lim, s, rate, options, nominal, t0)
    # the search saw only `samples` robots: keep its plan only if it also lands better on
    # another independent draw (by KEEP_MARGIN), else the nominal plan is the robust one
    _, valid = uncertainty.draw(params, check_samples, seed + 2_000_003)
    p95 = {k: miss_summary(miss_distribution(pl, valid))["p95"] for k, pl in (("n", nominal), ("r", robust))}
    kept = p95["r"] < (1.0 - KEEP_MARGIN) * p95["n"]
    robust = robust if kept else nominal
    prog.say(f"jsphere plan: replaying both plans on {check_samples} fresh draws")
    miss_mc = {
        "nominal": miss_summary(miss_distribution(nominal, check)),
        "robust": miss_summary(miss_distribution(robust, check)),
        "samples": int(check_samples),
        "mode": "wheel_speeds",
    }
    return RobustPlan(
        plan=robust,
        nominal=nominal,
        miss_mc=miss_mc,
        uncertainty=uncertainty,
        samples=int(samples),
        quantile=float(quantile),
        check_samples=int(check_samples),
        seed=int(seed),
        objective={"nominal": f_start, "robust": float(fs[best]) if kept else f_start},
        kept=bool(kept),
        elapsed_s=time.perf_counter() - t0,
    )


def _verified_plan(p, z, target, lim: Limits, s: PlanSettings, rate, options, nominal: Plan, t0: float) -> Plan:
    """The robust decision vector as a `Plan`: the accurate trajectory at the nominal
    parameters, its terminal errors there and its limits; feasible when the limits hold."""
    st0 = State.at_rest(p)
    gait = gait_from_vector(jnp.asarray(z), lim, s)
    tr = _accurate(p, gait, rate, np.asarray(st0.alpha), np.asarray(st0.beta), lim.max_time, options)
    tg = np.asarray(target)
    err = _terminal_errors(p, tr, tg)
    rep = _limit_report(p, tr, float(gait.T), lim)
    shortfall = [
        f"limit {name} exceeded: {r['max']:.5g} > {r['limit']:.5g} (by {100 * (r['max'] / r['limit'] - 1):.1f}%)"
        for name, r in rep.items()
        if not r["ok"]
    ]
    return Plan(
        params=p,
        gaits=[gait],
        legs=np.zeros((1, 3)),
        trajectory=tr,
        rate=rate,
        target=np.array([tg[0], tg[1], tg[2] if tg[3] else np.nan]),
        errors=err,
        limits_report=rep,
        feasible=not shortfall,
        shortfall=shortfall,
        iterations=dict(nominal.iterations),
        elapsed_s=time.perf_counter() - t0,
        loss=float("nan"),
        restarts=nominal.restarts,
        at_rest=err["speed_m_s"] <= TOL_SPEED,
    )
