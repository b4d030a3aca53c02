"""Verification of a plan with the accurate solver: the adaptive `simulate_gaits` (Dopri8,
rtol 1e-10, or as `SolverOptions` say) on the output grid, terminal errors, exact limit checks,
the correction of the search model's small RK4 bias, and the replay of an exported table
through `simulate`."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..controls import Torques, WheelSpeeds
from ..gaits.gaits import simulate_gaits
from ..model.state import State
from ..solve.options import SolverOptions, solver_options, unused
from ..solve.simulate import Trajectory, simulate
from .problem import Limits, gait_from_vector
from .result import Plan, platform_heading, tilt

#: `replay_errors`' step limit (a table sampled at the plan's rate has a kink at every sample)
REPLAY_MAX_STEPS = 65536


def verification_options(where: str, options: SolverOptions | None) -> SolverOptions | None:
    """Check the `SolverOptions` of a verification: its `rtol`, `atol`, `solver` and
    `max_steps` are used; `throw`, `adjoint` and `batch_steps` set are errors."""
    unused(
        options,
        where=where,
        throw="a verification that fails raises, as the plan cannot be checked",
        adjoint="the verification is not differentiated",
        batch_steps="the verification solves one manoeuvre at a time, unbatched",
    )
    return options


def _limit_report(params, tr: Trajectory, T_total, lim: Limits) -> dict:
    K, cd, ts = np.asarray(tr.K), np.asarray(tr.chi_dot), np.asarray(tr.ts)
    rep = {}
    if lim.max_torque is not None:
        rep["torque_N_m"] = (float(np.max(np.abs(K))), lim.max_torque)
    if lim.max_wheel_speed is not None:
        rep["wheel_speed_rad_s"] = (float(np.max(np.abs(cd))), lim.max_wheel_speed)
    if lim.max_tilt is not None:
        rep["tilt_rad"] = (float(np.max(tilt(params, tr.gamma))), lim.max_tilt)
    if lim.max_torque_rate is not None:
        dtt = np.diff(ts)
        ok = dtt > 0
        rate = np.abs(np.diff(K, axis=0)[ok] / dtt[ok, None]) if np.any(ok) else np.zeros(1)
        rep["torque_rate_N_m_s"] = (float(np.max(rate)), lim.max_torque_rate)
    rep["time_s"] = (float(T_total), float(lim.max_time))
    return {k: {"max": v, "limit": float(L), "ok": bool(v <= float(L) * (1 + 1e-9))} for k, (v, L) in rep.items()}


def exceeded(rep: dict) -> list[str]:
    """The sentences of the limits of a `_limit_report` that are exceeded, and by how much."""
    return [
        f"limit {name} exceeded: {r['max']:.5g} > {r['limit']:.5g} (by {100 * (r['max'] / r['limit'] - 1):.1f}%)"
        for name, r in rep.items()
        if not r["ok"]
    ]


def missed(o, has_heading: bool, err: dict, rep: dict) -> list[str]:
    """What keeps a plan from being feasible (its `shortfall`): missed tolerances of `o` (a
    `PlanOptions`), exceeded limits, and (if any) the limits that bind."""
    out = []
    if err["position_m"] > o.tol_position:
        out.append(
            f"final position misses by {1e3 * err['position_m']:.3f} mm (tolerance {1e3 * o.tol_position:.3f} mm)"
        )
    if err["speed_m_s"] > o.tol_speed:
        out.append(f"final speed {1e3 * err['speed_m_s']:.3f} mm/s (tolerance {1e3 * o.tol_speed:.3f} mm/s)")
    if has_heading and err["heading_rad"] > o.tol_heading:
        out.append(f"final heading misses by {err['heading_rad']:.4f} rad (tolerance {o.tol_heading} rad)")
    out += exceeded(rep)
    binding = [n for n, r in rep.items() if r["ok"] and r["max"] > 0.95 * r["limit"]]
    if out and binding:
        out.append(f"binding limit(s): {', '.join(binding)}")
    return out


def padded_grid(T: float, rate: float, max_time: float) -> tuple[np.ndarray, int]:
    """The output grid `k / rate` for `k / rate < T`, plus the end `T`, padded with `T` to the
    fixed length `ceil(max_time * rate) + 2`, so that plans of every duration share one compiled
    solve; and the number of its samples before the padding."""
    grid = np.arange(math.ceil(max_time * rate) + 2) / rate
    n = int(np.sum(grid < T - 1e-9)) + 1
    ts = np.minimum(grid, T)
    ts[n - 1 :] = T
    return ts, n


def _accurate(params, gait, rate, max_time, options: SolverOptions | None = None):
    """`simulate_gaits` (Dopri8, rtol 1e-10, or as `options` say) from rest (`State.at_rest`),
    sampled at `k / rate` for
    `k / rate < T`, plus the end `T`. The grid is padded to a fixed length (`max_time * rate`)
    so that plans of every duration share one compiled function; the padding is cut off
    afterwards."""
    T = float(gait.T)
    ts, n = padded_grid(T, rate, max_time)
    st0 = State.at_rest(params)
    alpha0, beta0 = np.asarray(st0.alpha), np.asarray(st0.beta)
    tr = simulate_gaits(params, [gait], ts=ts, alpha0=alpha0, beta0=beta0, options=options)
    return jax.tree_util.tree_map(lambda v: v[:n] if jnp.ndim(v) >= 1 else v, tr)


def _terminal_errors(params, tr: Trajectory, target) -> dict:
    x, y = float(tr.x[-1]), float(tr.y[-1])
    O, g = np.asarray(tr.Omega[-1]), np.asarray(tr.gamma[-1])
    psi = float(platform_heading(params, tr.alpha[-1], tr.beta[-1], g))
    head = float("nan") if target[3] == 0 else abs(math.remainder(psi - target[2], 2 * math.pi))
    return {
        "position_m": math.hypot(x - target[0], y - target[1]),
        "speed_m_s": float(params.R0) * float(np.linalg.norm(np.cross(O, g))),
        "heading_rad": head,
        "spin_rad_s": float(abs(O @ g)),
        "final": [x, y, psi],
    }


def _correct_bias(params, z, J_search, target, tr, err, accurate, lim, obj, s, tol_position, tol_speed):
    """Newton steps on the accurate terminal residual with the search model's Jacobian
    `J_search` (rows 0-5 of the residual Jacobian; min-norm step), at most 3, each kept only if
    it lowers `position + speed` error. This removes the small RK4 bias of the search model
    without differentiating the accurate solver. `accurate(gait)` re-simulates a gait.
    Returns `(z, gait, trajectory, errors, number of steps tried)`."""
    gait = gait_from_vector(jnp.asarray(z), lim, s)
    # rows 0-5 of the residual Jacobian: (x, y) / position_scale, R0 Omega / speed_scale, heading
    scales = np.array([obj.position_scale] * 2 + [obj.speed_scale] * 3 + [obj.heading_scale])
    J = J_search[:6] * scales[:, None]
    rows = [0, 1, 2, 3, 5]  # position, horizontal Omega, heading (the slow shell spin is left alone)
    steps = 0
    for _ in range(3):
        if err["position_m"] <= 0.05 * tol_position and err["speed_m_s"] <= 0.05 * tol_speed:
            break
        fin = err["final"]
        Om = float(params.R0) * np.asarray(tr.Omega[-1])
        r = np.concatenate(
            [
                [fin[0] - target[0], fin[1] - target[1]],
                Om,
                [target[3] * math.remainder(fin[2] - target[2], 2 * math.pi)],
            ]
        )
        z_new = z - np.linalg.lstsq(J[rows], r[rows], rcond=None)[0]
        g_new = gait_from_vector(jnp.asarray(z_new), lim, s)
        tr_new = accurate(g_new)
        err_new = _terminal_errors(params, tr_new, target)
        steps += 1
        if err_new["position_m"] + err_new["speed_m_s"] >= err["position_m"] + err["speed_m_s"]:
            break
        z, gait, tr, err = z_new, g_new, tr_new, err_new
    return z, gait, tr, err, steps


def replay_errors(plan_: Plan, *, mode: str = "torques", options: SolverOptions | None = None) -> dict[str, Any]:
    """Re-simulate the exported table with the plain simulator (`simulate` with
    `Torques.from_samples(t, K)` or `WheelSpeeds.from_samples(t, chi_dot)`, cubic) from rest,
    and compare the end with the plan's target and with the planned path.

    `options`: a `SolverOptions` for that solve (`rtol`, `atol`, `solver`, `max_steps`;
    `max_steps` defaults to `REPLAY_MAX_STEPS` here where it is at `SolverOptions`' default);
    `throw`, `adjoint` and `batch_steps` set are errors."""
    opts = solver_options(verification_options("replay_errors", options), where="replay_errors")
    opts = opts.or_defaults(max_steps=REPLAY_MAX_STEPS)
    cols = plan_.table()
    p = plan_.params
    N = p.n_wheels
    ts = cols["t"]
    if mode == "torques":
        ctrl = Torques.from_samples(ts, np.stack([cols[f"K_{i + 1}"] for i in range(N)], 1))
    elif mode == "wheel_speeds":
        ctrl = WheelSpeeds.from_samples(ts, np.stack([cols[f"chi_dot_{i + 1}"] for i in range(N)], 1))
    else:
        raise ValueError(f"replay_errors: mode must be 'torques' or 'wheel_speeds'; got {mode!r}.")
    tr = simulate(p, State.at_rest(p), ctrl, float(ts[-1]), ts=ts, options=opts)
    x, y = float(tr.x[-1]), float(tr.y[-1])
    return {
        "final_xy": [x, y],
        "target_error_m": math.hypot(x - plan_.target[0], y - plan_.target[1]),
        "path_deviation_m": float(np.max(np.hypot(np.asarray(tr.x) - cols["x"], np.asarray(tr.y) - cols["y"]))),
        "final_speed_m_s": float(p.R0)
        * float(np.linalg.norm(np.cross(np.asarray(tr.Omega[-1]), np.asarray(tr.gamma[-1])))),
        "trajectory": tr,
    }
