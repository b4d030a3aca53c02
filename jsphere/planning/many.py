"""Plans to many targets from one compiled, vmapped search (`restarts x targets` problems),
each verified with the accurate solver."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from .._runtime.moved_keywords import moved_into, no_other_keywords
from .._runtime.precision import warn_if_float32_by_default
from .._runtime.progress import Progress
from ..model.params import RobotParams
from ..solve.options import SolverOptions
from .problem import Limits, Objective, PlanOptions, PlanSettings, _check_request, _vec_targets, gait_from_vector
from .result import Plan, manoeuvre_plan
from .rollout import heading, rollout
from .search import _initial_guesses, _search
from .verify import _accurate, _correct_bias, _limit_report, _terminal_errors, missed, verification_options


@dataclasses.dataclass
class _Batch:
    """One `plan_many` request, checked, and what the steps below share."""

    params: RobotParams
    targets: np.ndarray  # (B, 4): x, y, heading (0 if free), has_heading
    lim: Limits
    obj: Objective
    s: PlanSettings
    o: PlanOptions
    t0: float
    iterations: dict
    options: SolverOptions | None = None  # of the accurate re-simulation


def _search_batch(b: _Batch, progress: Progress):
    """The vmapped search; returns the best decision vector per target `(B, V)`, its residual
    Jacobian `(B, M, V)` and the loss of every restart `(B, R)`. One compiled call: the
    progress shows its time, not its iterations."""
    p, s = b.params, b.s
    # numbers as arrays: other limits and weights reuse the compiled search (None stays static)
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, p.R0.dtype), m) for m in (b.lim, b.obj))
    z0 = _initial_guesses(p, b.targets, b.o.restarts, b.lim, s, b.o.seed)
    progress.say(
        f"jsphere plan: {len(b.targets)} target(s) x {b.o.restarts} restarts, Adam {s.adam_steps} + L-BFGS "
        f"{s.lbfgs_steps} + LM {s.lm_steps} iterations"
    )
    limits_off = tuple(v is None for v in jax.tree_util.tree_leaves(b.lim, is_leaf=lambda v: v is None))
    program = repr((z0.shape, z0.dtype, s, limits_off, p.n_wheels))
    with progress.compiling("plan", program, "jsphere plan: search"), progress.phase("jsphere plan: search"):
        zf, loss, _, Jf, _ = _search(p, jnp.asarray(b.targets, p.R0.dtype), z0, lim_a, obj_a, s)
        zf, Jf, loss = np.asarray(zf), np.asarray(Jf), np.asarray(loss)
    progress.say(f"jsphere plan: search done in {time.perf_counter() - b.t0:.1f} s; verifying with the accurate solver")
    return zf, Jf, loss


def _verified(b: _Batch, k: int, z, J):
    """The accurate trajectory of target `k`'s manoeuvre, its RK4 bias corrected: `(gait,
    trajectory, errors)`."""
    p, lim = b.params, b.lim

    def accurate(gait):
        return _accurate(p, gait, b.o.rate, lim.max_time, b.options)

    tr = accurate(gait_from_vector(jnp.asarray(z), lim, b.s))
    err = _terminal_errors(p, tr, b.targets[k])
    _, gait, tr, err, steps = _correct_bias(
        p, z, J, b.targets[k], tr, err, accurate, lim, b.obj, b.s, b.o.tol_position, b.o.tol_speed
    )
    b.iterations["newton"] += steps
    return gait, tr, err


def _search_model_errors(b: _Batch, k: int, gait) -> dict:
    """Terminal errors in the search model (no accurate re-simulation)."""
    p, tg = b.params, b.targets[k]
    ro = rollout(p, gait, b.s.n_steps)
    return {
        "position_m": float(np.hypot(ro.x[-1] - tg[0], ro.y[-1] - tg[1])),
        "speed_m_s": float(p.R0 * jnp.linalg.norm(ro.Omega[-1, :2])),
        "heading_rad": float("nan"),
        "spin_rad_s": float(abs(ro.Omega[-1, 2])),
        "final": [float(ro.x[-1]), float(ro.y[-1]), float(heading(p, ro))],
    }


def _plan_for(b: _Batch, k: int, z, J, loss) -> Plan:
    """Target `k`'s plan from its best decision vector `z` (verified if `verify`)."""
    if b.o.verify:
        gait, tr, err = _verified(b, k, z, J)
        rep = _limit_report(b.params, tr, float(gait.T), b.lim)
    else:
        gait = gait_from_vector(jnp.asarray(z), b.lim, b.s)
        tr, err, rep = None, _search_model_errors(b, k, gait), {}
    shortfall = missed(b.o, bool(b.targets[k, 3]), err, rep)
    return manoeuvre_plan(
        b.params,
        gait,
        tr,
        b.o.rate,
        b.targets[k],
        err,
        rep,
        shortfall,
        iterations=dict(b.iterations),
        elapsed_s=time.perf_counter() - b.t0,
        loss=float(np.min(loss)),
        restarts=b.o.restarts,
        at_rest=b.o.verify and err["speed_m_s"] <= b.o.tol_speed,
    )


def plan_batch(where: str, params: RobotParams, targets, lim, obj, s, o: PlanOptions, progress, options) -> list[Plan]:
    """The plans to checked `targets` (`_check_request`) from one vmapped search; `where` names
    the caller in messages."""
    options = verification_options(where, options)
    warn_if_float32_by_default(params.R0.dtype, where)
    if s is not None and not isinstance(s, PlanSettings):
        raise InputError(f"{where}: routes and many targets are planned with gaits; settings must be a PlanSettings.")
    s = s or PlanSettings()
    b = _Batch(
        params=params,
        targets=_vec_targets(targets),
        lim=lim or Limits(),
        obj=obj or Objective(),
        s=s,
        o=dataclasses.replace(o, restarts=int(o.restarts)),
        t0=time.perf_counter(),
        iterations={"adam": s.adam_steps, "lbfgs": s.lbfgs_steps, "lm": s.lm_steps, "newton": 0},
        options=options,
    )
    prog = Progress(progress)
    zf, Jf, loss = _search_batch(b, prog)
    plans = []
    with prog.bar(len(b.targets), "jsphere plan: verifying", "target") as bar:
        for k in range(len(b.targets)):
            plans.append(_plan_for(b, k, zf[k], Jf[k], loss[k]))
            bar.update(1)
    return plans


def plan_many(
    params: RobotParams,
    targets: Sequence[Sequence[float]],
    *,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    plan_options: PlanOptions | None = None,
    progress: bool | None = None,
    options: SolverOptions | None = None,
    **kwargs,
) -> list[Plan]:
    """Plan rest-to-rest manoeuvres from rest at the origin (heading 0) to each target, all in
    one compiled, vmapped search (`restarts x len(targets)` problems).

    What `plan` cannot do: independent manoeuvres to many targets from one search, one `Plan`
    per target, never raising for an infeasible one (`Plan.feasible` says).

    **Arguments:**
    - `targets`: `(x, y)` [m] or `(x, y, psi)` (final platform heading [rad]; `None`/nan: free).
    - `limits`, `objective`, `settings`, `plan_options`: see `Limits`, `Objective`,
      `PlanSettings`, `PlanOptions` (restarts, rate, seed, tolerances, verification); the fields
      of `PlanOptions` given as keywords (`restarts=4`) still work, with a `DeprecationWarning`.
    - `options`: a `SolverOptions` for the accurate re-simulation (`simulate_gaits`; default
      Dopri8, rtol 1e-10, atol 1e-12, max_steps 16384): its `rtol`, `atol`, `solver` and
      `max_steps` are used; `throw`, `adjoint` and `batch_steps` set are errors.
    - `progress`: `None` (default): progress bars on stderr when it is a terminal; `True`:
      bars, or lines where stderr is not a terminal; `False`: none
      (`jsphere._runtime.progress`).

    Every argument is checked before any work; a bad one raises `InputError` naming it.

    Returns one `Plan` per target (infeasible ones have `feasible = False`; `plan` raises).
    """
    o = moved_into("plan_many", kwargs, plan_options, PlanOptions, "plan_options")
    no_other_keywords("plan_many", kwargs)
    targets = _check_request("plan_many", targets, limits, objective, settings, o)
    return plan_batch("plan_many", params, targets, limits, objective, settings, o, progress, options)
