"""Plans to many targets from one compiled, vmapped search (`restarts x targets` problems),
each verified with the accurate solver."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.precision import warn_if_float32_by_default
from .._runtime.progress import Progress
from ..model.params import RobotParams
from ..model.state import State
from ..solve.options import SolverOptions
from .problem import Limits, Objective, PlanSettings, _check_request, _vec_targets, gait_from_vector
from .result import Plan
from .rollout import heading, rollout
from .search import _initial_guesses, _search
from .verify import _accurate, _correct_bias, _limit_report, _terminal_errors, verification_options

#: the default terminal speed tolerance of a plan [m/s] (`R0 |Omega x gamma|` at the end): a plan
#: whose end is within it ends at rest (`Plan.at_rest`)
TOL_SPEED = 5e-4


@dataclasses.dataclass
class _Batch:
    """One `plan_many` request, checked, and what the steps below share."""

    params: RobotParams
    targets: np.ndarray  # (B, 4): x, y, heading (0 if free), has_heading
    lim: Limits
    obj: Objective
    s: PlanSettings
    restarts: int
    rate: float
    tol_position: float
    tol_speed: float
    tol_heading: float
    t0: float
    iterations: dict
    options: SolverOptions | None = None  # of the accurate re-simulation


def _search_batch(b: _Batch, seed: int, progress: Progress):
    """The vmapped search; returns the best decision vector per target `(B, V)`, its residual
    Jacobian `(B, M, V)` and the loss of every restart `(B, R)`. One compiled call: the
    progress shows its time, not its iterations."""
    p, s = b.params, b.s
    # numbers as arrays: other limits and weights reuse the compiled search (None stays static)
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, p.R0.dtype), m) for m in (b.lim, b.obj))
    z0 = _initial_guesses(p, b.targets, b.restarts, b.lim, s, seed)
    progress.say(
        f"jsphere plan: {len(b.targets)} target(s) x {b.restarts} restarts, Adam {s.adam_steps} + L-BFGS "
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
    st0 = State.at_rest(p)
    alpha0, beta0 = np.asarray(st0.alpha), np.asarray(st0.beta)

    def accurate(gait):
        return _accurate(p, gait, b.rate, alpha0, beta0, lim.max_time, b.options)

    tr = accurate(gait_from_vector(jnp.asarray(z), lim, b.s))
    err = _terminal_errors(p, tr, b.targets[k])
    _, gait, tr, err, steps = _correct_bias(
        p, z, J, b.targets[k], tr, err, accurate, lim, b.obj, b.s, b.tol_position, b.tol_speed
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


def _shortfall(b: _Batch, k: int, err: dict, rep: dict) -> list[str]:
    """What keeps a plan from being feasible: missed tolerances, exceeded limits, and (if any)
    the limits that bind."""
    out = []
    if err["position_m"] > b.tol_position:
        out.append(
            f"final position misses by {1e3 * err['position_m']:.3f} mm (tolerance {1e3 * b.tol_position:.3f} mm)"
        )
    if err["speed_m_s"] > b.tol_speed:
        out.append(f"final speed {1e3 * err['speed_m_s']:.3f} mm/s (tolerance {1e3 * b.tol_speed:.3f} mm/s)")
    if b.targets[k, 3] and err["heading_rad"] > b.tol_heading:
        out.append(f"final heading misses by {err['heading_rad']:.4f} rad (tolerance {b.tol_heading} rad)")
    for name, r in rep.items():
        if not r["ok"]:
            out.append(
                f"limit {name} exceeded: {r['max']:.5g} > {r['limit']:.5g} (by {100 * (r['max'] / r['limit'] - 1):.1f}%)"
            )
    binding = [n for n, r in rep.items() if r["ok"] and r["max"] > 0.95 * r["limit"]]
    if out and binding:
        out.append(f"binding limit(s): {', '.join(binding)}")
    return out


def _plan_for(b: _Batch, k: int, z, J, loss, verify: bool) -> Plan:
    """Target `k`'s plan from its best decision vector `z` (verified if `verify`)."""
    if verify:
        gait, tr, err = _verified(b, k, z, J)
        rep = _limit_report(b.params, tr, float(gait.T), b.lim)
    else:
        gait = gait_from_vector(jnp.asarray(z), b.lim, b.s)
        tr, err, rep = None, _search_model_errors(b, k, gait), {}
    shortfall = _shortfall(b, k, err, rep)
    tg = b.targets[k]
    return Plan(
        params=b.params,
        gaits=[gait],
        legs=np.zeros((1, 3)),
        trajectory=tr,
        rate=b.rate,
        target=np.array([tg[0], tg[1], tg[2] if tg[3] else np.nan]),
        errors=err,
        limits_report=rep,
        feasible=not shortfall,
        shortfall=shortfall,
        iterations=dict(b.iterations),
        elapsed_s=time.perf_counter() - b.t0,
        loss=float(np.min(loss)),
        restarts=b.restarts,
        at_rest=verify and err["speed_m_s"] <= b.tol_speed,
    )


def plan_many(
    params: RobotParams,
    targets: Sequence[Sequence[float]],
    *,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    restarts: int = 16,
    rate: float = 1000.0,
    seed: int = 0,
    tol_position: float = 5e-4,
    tol_speed: float = TOL_SPEED,
    tol_heading: float = 1e-3,
    verify: bool = True,
    progress: bool | None = None,
    options: SolverOptions | None = None,
) -> list[Plan]:
    """Plan rest-to-rest manoeuvres from rest at the origin (heading 0) to each target, all in
    one compiled, vmapped search (`restarts x len(targets)` problems).

    **Arguments:**
    - `targets`: `(x, y)` [m] or `(x, y, psi)` (final platform heading [rad]; `None`/nan: free).
    - `limits`, `objective`, `settings`: see `Limits`, `Objective`, `PlanSettings`.
    - `restarts`: random restarts per target (the best is kept); `rate`: output rate [Hz].
    - `tol_*`: terminal tolerances for `Plan.feasible` [m, m/s, rad].
    - `verify`: re-simulate with the accurate solver (needed for the table; `False` returns
      the search model's result only, for benchmarks).
    - `options`: a `SolverOptions` for that re-simulation (`simulate_gaits`; default Dopri8,
      rtol 1e-10, atol 1e-12, max_steps 16384): its `rtol`, `atol`, `solver` and `max_steps`
      are used; `throw`, `adjoint` and `batch_steps` set are errors.
    - `progress`: `None` (default): progress bars on stderr when it is a terminal; `True`:
      bars, or lines where stderr is not a terminal; `False`: none
      (`jsphere._runtime.progress`).

    Every argument is checked before any work; a bad one raises `InputError` naming it.

    Returns one `Plan` per target (infeasible ones have `feasible = False`; `plan` raises).
    """
    targets = _check_request(
        "plan_many",
        targets,
        limits,
        objective,
        settings,
        restarts,
        rate,
        seed,
        (("tol_position", tol_position), ("tol_speed", tol_speed), ("tol_heading", tol_heading)),
    )
    options = verification_options("plan_many", options)
    warn_if_float32_by_default(params.R0.dtype, "plan_many")
    s = settings or PlanSettings()
    b = _Batch(
        params=params,
        targets=_vec_targets(targets),
        lim=limits or Limits(),
        obj=objective or Objective(),
        s=s,
        restarts=int(restarts),
        rate=rate,
        tol_position=tol_position,
        tol_speed=tol_speed,
        tol_heading=tol_heading,
        t0=time.perf_counter(),
        iterations={"adam": s.adam_steps, "lbfgs": s.lbfgs_steps, "lm": s.lm_steps, "newton": 0},
        options=options,
    )
    prog = Progress(progress)
    zf, Jf, loss = _search_batch(b, seed, prog)
    plans = []
    with prog.bar(len(b.targets), "jsphere plan: verifying", "target") as bar:
        for k in range(len(b.targets)):
            plans.append(_plan_for(b, k, zf[k], Jf[k], loss[k], verify))
            bar.update(1)
    return plans
