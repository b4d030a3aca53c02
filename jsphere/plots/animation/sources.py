"""The `Scene`s of each kind of result jsphere computes: a `Trajectory`, a `Trial`, a `Plan`, a fit
with its trials and a `MonteCarloResult` (`jsphere.animate` reads files into those results)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..._runtime.errors import InputError
from ..base import ellipse_points
from .scene import Scene, body_from_trajectory, body_from_trial

if TYPE_CHECKING:
    from ...model.params import RobotParams

#: Monte-Carlo trials whose paths are drawn
MONTECARLO_PATHS = 5


def trajectory_scene(traj, params: RobotParams, *, title: str = "", target=None) -> Scene:
    """A `Trajectory` (a simulation of `params`)."""
    return Scene([body_from_trajectory(traj, label="simulated")], params, title=title or "simulated run", target=target)


def trial_scene(trial, params: RobotParams, *, title: str = "") -> Scene:
    """A `Trial`: its measured poses."""
    return Scene([body_from_trial(params, trial)], params, title=title or f"trial {trial.name} (measured poses)")


def plan_scene(plan, *, title: str = "") -> Scene:
    """A `Plan`: its accurate trajectory and its target."""
    tgt = np.asarray(plan.target, float)
    body = body_from_trajectory(plan.trajectory, label="plan")
    head = "feasible plan" if plan.feasible else "plan (NOT feasible)"
    text = title or f"{head} to ({tgt[0]:.3f}, {tgt[1]:.3f}) m in {plan.duration:.2f} s"
    return Scene([body], plan.params, title=text, target=(float(tgt[0]), float(tgt[1])))


def fit_scenes(params: RobotParams, trials, *, worst: str | None = None, status: str = "") -> list[Scene]:
    """A fit: per trial, the capture (solid) and the fitted model `params` replaying it (`compare`:
    simulated from the trial's own initial pose, its initial velocities estimated as the fit
    estimates them) ghosted over it, with the residual on screen; the worst-fitting trial first
    (`worst`, a fit's `verdict["worst_trial"]`; else the largest RMS position residual)."""
    from ...identify.compare import compare

    trials = list(trials)
    res = compare(params, trials)
    rms = {r["name"]: float(r["rms_pos_m"]) for r in res.trials}
    order = sorted(range(len(trials)), key=lambda i: -rms.get(trials[i].name, 0.0))
    if worst is not None:
        order = sorted(order, key=lambda i: trials[i].name != worst)
    scenes = []
    for rank, i in enumerate(order):
        tr, model = trials[i], res.predicted[i]
        bodies = [body_from_trial(params, tr, label=f"{tr.name} (capture)"), body_from_trial(params, model, ghost=True)]
        bodies[1].label = "fitted model"
        which = " - worst fit" if rank == 0 and len(trials) > 1 else ""
        rms_text = f"RMS {1e3 * rms[tr.name]:.2f} mm" if tr.name in rms else ""
        head = f"{status}; " if status else ""
        title = f"{head}trial {tr.name}{which}, {rms_text}\ncapture (blue) and fitted model (orange, faint)"
        scenes.append(Scene(bodies, params, title=title, residual=True))
    return scenes


def montecarlo_scene(result, params: RobotParams, gaits, *, reset: bool = False, stats=None, title: str = "") -> Scene:
    """A Monte-Carlo study's `MonteCarloResult`: the study's `gaits` executed by the robots drawn
    for its first `MONTECARLO_PATHS` successful trials (growing together; `params`: the nominal
    robot, `reset` as the study's), and all the stop points of its successful trials with the 95 %
    ellipse of `stats` (default `result.stats()`) at the end."""
    from ...gaits.gaits import simulate_gaits
    from ...model.names import set_value

    ok = np.asarray(result.status) == 0
    index = np.flatnonzero(ok)
    cloud = np.stack([np.asarray(result.x_final)[ok], np.asarray(result.y_final)[ok]], axis=-1)
    if not len(cloud):
        raise InputError(f"{title or 'the study'}: no successful trial; nothing to animate.")
    bodies = []
    for i in index[:MONTECARLO_PATHS]:
        p = params
        for name, v in result.samples.items():  # the robot drawn for the trial
            p = set_value(p, name, v[i])
        tr = simulate_gaits(p, gaits, reset=reset)
        bodies.append(body_from_trajectory(tr, label=f"trial {i}"))
    stats = result.stats() if stats is None else stats
    ellipse = ellipse_points(stats, 100) if stats.get("ellipse") else None
    head = title or "Monte-Carlo study"
    text = f"{head}: {len(bodies)} of {len(cloud)} trials; stop points and 95 % ellipse at the end"
    return Scene(bodies, params, title=text, cloud=cloud, ellipse=ellipse)
