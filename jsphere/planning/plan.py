"""Rest-to-rest manoeuvres to a goal pose within motor limits (`plan`), and routes through
waypoints stopping at each (`plan_route`), found by gradients through the gait dynamics of
Section 4. `plan` is the one entry point: a target, a route, or a robust plan
(`RobustOptions`); `plan_many` plans many independent targets at once.

The pieces: `problem` (limits, objective, settings, decision vector), `rollout` (the RK4
search model), `residuals`, `search` (Adam then Levenberg-Marquardt over restarts x targets
under one `jit`), `verify` (the accurate re-simulation and limit checks), `many`
(`plan_many`), `robust` (`RobustOptions`, `RobustPlan`), `result`
(`Plan`). See `docs/planning.md`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.checks import real
from .._runtime.errors import InputError
from .._runtime.moved_keywords import moved_into, no_other_keywords
from ..model.params import RobotParams
from ..solve.options import SolverOptions
from ..solve.simulate import Trajectory
from .direct import DirectSettings, plan_direct
from .many import plan_batch, plan_many
from .problem import Limits, Objective, PlanOptions, PlanSettings, _check_request, check_target
from .result import Plan, PlanInfeasibleError
from .robust import RobustOptions, robust_plan
from .verify import verification_options

__all__ = [
    "DirectSettings",
    "Limits",
    "Objective",
    "Plan",
    "PlanInfeasibleError",
    "PlanOptions",
    "PlanSettings",
    "plan",
    "plan_many",
    "plan_route",
]


def plan(
    params: RobotParams,
    to: Sequence,
    *,
    heading: float | None = None,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    plan_options: PlanOptions | None = None,
    robust: RobustOptions | None = None,
    allow_infeasible: bool = False,
    progress: bool | None = None,
    options: SolverOptions | None = None,
    **kwargs,
):
    """Plan a rest-to-rest manoeuvre from rest at the origin (platform axes = fixed axes) to
    `to = (x, y)` [m], optionally ending with platform heading `heading` [rad], within `limits`;
    or a route through the waypoints `to = [(x, y), (x, y, heading), ...]`, stopping at each
    (as `plan_route`).

    **Arguments:**
    - `limits`, `objective`: see `Limits`, `Objective`.
    - `plan_options`: a `PlanOptions` (family, rate, tolerances, restarts, seed); its fields
      given as keywords (`restarts=32`) still work, with a `DeprecationWarning`. Its `family`
      picks the manoeuvre: `"direct"` (default; free torque profiles, the shortest manoeuvre
      within the limits, `jsphere.planning.direct`) or `"gait"` (the paper's tilt gaits;
      routes and robust plans always use them).
    - `settings`: the search's sizes, a `DirectSettings` (direct) or a `PlanSettings` (gaits;
      given, it asks for the gait family).
    - `robust`: a `RobustOptions` (the parameter distribution and the robust search): plan a
      manoeuvre that still lands on the robots it allows, and return a `RobustPlan`
      (`jsphere.planning.robust`; one target only).
    - `options`: a `SolverOptions` for the accurate re-simulation that verifies the plan (as in
      `plan_many`). `progress`: as for `plan_many`.

    Raises `PlanInfeasibleError` (holding the best plan in `.plan`, and saying how far it falls
    short and which limit binds) if the tolerances or limits are not met, unless
    `allow_infeasible=True` (then check `Plan.feasible`). A robust plan never raises: its
    `RobustPlan.plan.feasible` says whether it keeps the limits.

    Example:

        p = jsphere.RobotParams.paper()
        pl = jsphere.plan(p, (0.8, -0.5), heading=1.0)
        pl.to_csv("plan.csv")

    Every argument is checked before any work; a bad one (a target or heading that is not a
    finite number, `restarts < 1`, `rate <= 0`, ...) raises `InputError` naming it.
    """
    o = moved_into("plan", kwargs, plan_options, PlanOptions, "plan_options")
    no_other_keywords("plan", kwargs)
    if _is_route(to):
        if heading is not None or robust is not None:
            raise InputError("plan: a route gives each waypoint's heading as (x, y, heading), and is not robust.")
        return _route("plan", params, to, limits, objective, settings, o, allow_infeasible, progress, options)
    x, y = check_target("plan", to)
    if heading is not None:
        real("plan", "heading", heading, low=None, unit="rad; None for a free final heading")
    if robust is not None:
        return robust_plan(
            "plan",
            params,
            (x, y, heading),
            limits,
            objective,
            settings,
            o=o,
            r=robust,
            progress=progress,
            options=options,
        )
    targets = _check_request("plan", [(x, y, heading)], limits, objective, settings, o)
    if o.family == "direct" and not isinstance(settings, PlanSettings):
        pl = plan_direct(
            "plan",
            params,
            (x, y, heading),
            limits or Limits(),
            objective or Objective(),
            o,
            settings or DirectSettings(),
            progress,
            verification_options("plan", options),
        )
    else:
        pl = plan_batch("plan", params, targets, limits, objective, settings, o, progress, options)[0]
    if not pl.feasible and not allow_infeasible:
        raise PlanInfeasibleError(
            "jsphere.plan: the request cannot be met: "
            + "; ".join(pl.shortfall)
            + ". The best plan found is in `.plan`.",
            plan=pl,
        )
    return pl


def _is_route(to) -> bool:
    """Whether `to` is a list of waypoints (its first item a sequence) rather than one target."""
    return (
        isinstance(to, Sequence)
        and not isinstance(to, (str, bytes))
        and len(to) > 0
        and isinstance(to[0], (Sequence, np.ndarray))
        and not isinstance(to[0], (str, bytes))
    )


def _move(tr: Trajectory, pose, t_offset) -> Trajectory:
    """A trajectory planned in its start frame, moved to the start pose `(x0, y0, psi0)`:
    positions rotated and shifted, the platform attitude turned by `psi0` about the vertical
    (platform-frame quantities `gamma, omega, Omega, K, chi_dot` are unchanged)."""
    x0, y0, psi = pose
    c, s_ = math.cos(psi), math.sin(psi)
    x = x0 + c * tr.x - s_ * tr.y
    y = y0 + s_ * tr.x + c * tr.y
    # alpha, beta: fixed axes seen from the platform; fixed frame turned by -psi relative to the start frame
    a = c * tr.alpha - s_ * tr.beta
    b = s_ * tr.alpha + c * tr.beta
    return eqx.tree_at(lambda t: (t.x, t.y, t.alpha, t.beta, t.ts), tr, (x, y, a, b, tr.ts + t_offset))


def plan_route(
    params: RobotParams,
    waypoints: Sequence[Sequence[float]],
    *,
    limits: Limits | None = None,
    objective: Objective | None = None,
    settings: PlanSettings | None = None,
    plan_options: PlanOptions | None = None,
    allow_infeasible: bool = False,
    progress: bool | None = None,
    options: SolverOptions | None = None,
    **kwargs,
) -> Plan:
    """A route from rest at the origin through `waypoints` `(x, y)` or `(x, y, psi)` [m, rad],
    stopping at each: one rest-to-rest manoeuvre per leg; the same as `plan(params, waypoints,
    ...)`. Every leg is planned in its start frame, all legs in one vmapped search (the dynamics
    are invariant under horizontal shifts and turns about the vertical). A waypoint without a
    heading keeps the previous heading.

    Returns one `Plan` whose gaits are the legs and whose trajectory joins them (the duplicate
    rest sample at each stop dropped). `plan_options`: a `PlanOptions` (its fields given as
    keywords still work, with a `DeprecationWarning`). `options`: a `SolverOptions` for the
    accurate re-simulation of each leg (as in `plan_many`). `progress`: as for `plan_many`.
    """
    o = moved_into("plan_route", kwargs, plan_options, PlanOptions, "plan_options")
    no_other_keywords("plan_route", kwargs)
    return _route("plan_route", params, waypoints, limits, objective, settings, o, allow_infeasible, progress, options)


def _route(where, params, waypoints, limits, objective, settings, o: PlanOptions, allow_infeasible, progress, options):
    """`plan_route`'s work; `where` names the caller in messages."""
    _check_request(where, waypoints, limits, objective, settings, o, nan_free=False, noun="waypoints")
    poses, local, pose = _legs(waypoints)
    legs = plan_batch(where, params, local, limits, objective, settings, o, progress, options)
    tr, t_off, shortfall = _joined(legs, poses)
    err, rep = _route_errors(legs, poses, tr, t_off, limits or Limits())
    tx, ty, tpsi = pose
    pl = Plan(
        params=params,
        gaits=[lg.gaits[0] for lg in legs],
        legs=np.asarray(poses),
        trajectory=tr,
        rate=o.rate,
        target=np.array([tx, ty, tpsi]),
        errors=err,
        limits_report=rep,
        feasible=all(lg.feasible for lg in legs),
        shortfall=shortfall,
        iterations=legs[0].iterations,
        elapsed_s=max(lg.elapsed_s for lg in legs),
        loss=sum(lg.loss for lg in legs),
        restarts=int(o.restarts),
        at_rest=all(lg.at_rest for lg in legs),
    )
    if not pl.feasible and not allow_infeasible:
        raise PlanInfeasibleError(f"jsphere.{where}: " + "; ".join(shortfall), plan=pl)
    return pl


def _legs(waypoints):
    """Each leg's start pose `(x0, y0, psi0)` and its target in its start frame; the end pose.
    A waypoint without a heading keeps the previous heading."""
    poses, local = [], []
    pose = (0.0, 0.0, 0.0)
    for w in waypoints:
        w = list(w)
        psi = pose[2] if len(w) == 2 or w[2] is None else float(w[2])
        dx, dy = float(w[0]) - pose[0], float(w[1]) - pose[1]
        c, s_ = math.cos(pose[2]), math.sin(pose[2])
        local.append((c * dx + s_ * dy, -s_ * dx + c * dy, math.remainder(psi - pose[2], 2 * math.pi)))
        poses.append(pose)
        pose = (float(w[0]), float(w[1]), psi)
    return poses, local, pose


def _joined(legs, poses):
    """The legs' trajectories moved to their start poses and joined (the duplicate rest sample at
    each stop dropped, `segment` = leg index); the total duration; the legs' shortfalls."""
    trs, t_off, shortfall = [], 0.0, []
    for i, (lg, ps) in enumerate(zip(legs, poses)):
        tr = _move(lg.trajectory, ps, t_off)
        if i:
            tr = jax.tree_util.tree_map(lambda v: v[1:] if jnp.ndim(v) >= 1 else v, tr)
        trs.append(tr)
        t_off += float(lg.gaits[0].T)
        shortfall += [f"leg {i + 1}: {m}" for m in lg.shortfall]

    def join(*vs):
        return jnp.concatenate(vs, axis=0) if jnp.ndim(vs[0]) >= 1 else vs[0]

    tr = jax.tree_util.tree_map(join, *trs)
    seg = jnp.concatenate([jnp.full(t.ts.shape, i, jnp.int32) for i, t in enumerate(trs)])
    tr = eqx.tree_at(lambda t: t.segment, tr, seg)
    return tr, t_off, shortfall


def _route_errors(legs, poses, tr, t_off, lim: Limits):
    """The route's terminal errors (worst leg; the final pose of the last) and its limit report
    (worst leg; the total time against `max_time` per leg)."""
    last = legs[-1]
    err = {
        "position_m": max(lg.errors["position_m"] for lg in legs),
        "speed_m_s": max(lg.errors["speed_m_s"] for lg in legs),
        "heading_rad": max((lg.errors["heading_rad"] for lg in legs), default=float("nan")),
        "spin_rad_s": max(lg.errors["spin_rad_s"] for lg in legs),
        "final": [float(tr.x[-1]), float(tr.y[-1]), last.errors["final"][2] + poses[-1][2]],
    }
    rep = {}
    for name in legs[0].limits_report:
        mx = max(lg.limits_report[name]["max"] for lg in legs) if name != "time_s" else t_off
        L = legs[0].limits_report[name]["limit"] if name != "time_s" else lim.max_time * len(legs)
        rep[name] = {"max": mx, "limit": L, "ok": all(lg.limits_report[name]["ok"] for lg in legs)}
    return err, rep
