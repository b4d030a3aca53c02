"""Section 5 of the paper, recomputed: every number next to jsphere's value.

`reproduce(params)` runs the paper's manoeuvres and returns a `Reproduction` holding the
table rows and the trajectories for the figures (`jsphere.plots`). The CLI
`jsphere reproduce` prints the table and writes `reproduce.json` and the figures.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ..controls import kinematic_control, straight_line
from ..gaits.gaits import acceleration, braking, simulate_gaits, turn
from ..model.params import RobotParams
from ..model.state import State
from ..solve.options import SolverOptions
from ..solve.simulate import Trajectory, simulate


def to_figure_frame(x, y):
    """The paper's Fig. 3 and (5.5) use axes turned by +90 degrees: `x_fig = -y`, `y_fig = x`."""
    return -np.asarray(y), np.asarray(x)


@dataclasses.dataclass
class Row:
    """One number of Section 5: the paper's value, jsphere's (ours and in the figure frame)."""

    quantity: str
    paper: str
    ours: str
    fig: str = ""
    note: str = ""


@dataclasses.dataclass
class Reproduction:
    """What `reproduce` returns: the table's `rows`, the `values` (`reproduce.json`) and the
    `trajectories` of the figures."""

    rows: list[Row]
    values: dict[str, Any]
    trajectories: dict[str, Trajectory]

    def table(self) -> str:
        """The rows as a fixed-width text table, notes below."""
        head = ("quantity", "paper", "jsphere (x, y)", "jsphere (fig. frame)")
        cols = [[r.quantity, r.paper, r.ours, r.fig] for r in self.rows]
        w = [max(len(h), *(len(c[i]) for c in cols)) for i, h in enumerate(head)]
        line = "  ".join("-" * n for n in w)
        out = ["  ".join(h.ljust(n) for h, n in zip(head, w)), line]
        notes = []
        for r, c in zip(self.rows, cols):
            notes += [r.note] if r.note else []
            out.append("  ".join(x.ljust(n) for x, n in zip(c, w)) + (f" [{len(notes)}]" if r.note else ""))
        out.append(line)
        out += [f"[{i}] {n}" for i, n in enumerate(notes, 1)]
        return "\n".join(out)


def _mm(x, y) -> str:
    return f"({1e3 * float(x):.3f}, {1e3 * float(y):.3f}) mm"


def _point(x, y) -> tuple[str, str]:
    """A point [m] as the table shows it: in mm, in jsphere's axes and in the figure's."""
    return _mm(x, y), _mm(*to_figure_frame(x, y))


def _vec(v, digits=6) -> str:
    return "(" + ", ".join(f"{float(c):.{digits}f}" for c in np.asarray(v)) + ")"


def _horizontal_speed(params, traj, i=-1) -> float:
    O, g = np.asarray(traj.Omega[i]), np.asarray(traj.gamma[i])
    return float(params.R0) * float(np.linalg.norm(np.cross(O, g)))


def full_stop_brake(
    params: RobotParams,
    *,
    theta0: float = 0.1,
    phi0: float = math.pi / 4,
    iters: int = 8,
    tol: float = 1e-12,
    rate: float = 100.0,
    options: SolverOptions | None = None,
):
    """`(theta_max, phi, residual)` of the braking gait that stops the robot after acceleration
    (5.1) and turn (5.6), every gait starting from the previous end state (Newton on the
    horizontal `Omega` at the end, finite-difference Jacobian; one compiled function throughout).

    The finite differences reuse the forward simulation compiled for the table; an autodiff
    Jacobian (`optimistix`, as in `jsphere.optimise_gaits`) would compile a reverse-mode program
    through the adaptive solver first, which costs far more than the whole solve here
    (`benchmarks/solvers.py`). `options` go to `simulate_gaits`."""
    run = _Run(rate, options)

    def residual(x):
        tr = run.gaits(params, [acceleration(), turn(), braking(theta_max=x[0], phi=x[1])])
        return np.asarray(tr.Omega[-1, :2])

    x = np.array([theta0, phi0])
    for _ in range(iters):
        r = residual(x)
        if np.max(np.abs(r)) < tol:
            break
        h = 1e-6
        J = np.stack([(residual(x + h * e) - r) / h for e in np.eye(2)], axis=1)
        x = x - np.linalg.solve(J, r)
    return float(x[0]), float(x[1]), residual(x)


@dataclasses.dataclass(frozen=True)
class _Run:
    """How the sections below solve: output `rate` [Hz] and the `SolverOptions` of every solve."""

    rate: float = 100.0
    options: SolverOptions | None = None

    def gaits(self, p, gaits, **kwargs) -> Trajectory:
        return _host(simulate_gaits(p, gaits, rate=self.rate, options=self.options, **kwargs))


def reproduce(
    params: RobotParams | None = None,
    *,
    rate: float = 100.0,
    full_stop: bool = True,
    options: SolverOptions | None = None,
) -> Reproduction:
    """Recompute every number of Section 5 (see `docs/model.md` for the conventions).
    `options` go to every solve."""
    p = RobotParams.paper() if params is None else params
    out, run = Reproduction([], {}, {}), _Run(rate, options)
    straight, straight_reset, v_kin = _acceleration(p, run, out)
    _figure2(p, run, straight, v_kin, out)
    _straight_stop(p, straight, straight_reset, out)
    _turn_stops(p, run, out)
    if full_stop:
        _full_stop(p, run, out)
    out.values["params"] = p.to_dict()
    return out


def _acceleration(p: RobotParams, run: _Run, out: Reproduction):
    """Section 5.1: acceleration (5.1), (5.2), then braking (5.3); `Omega_1` and the speed of the
    kinematic run (5.5). Returns the straight runs (continuing, with the reset (5.4)) and that speed."""
    R0, rows, vals, trajs = float(p.R0), out.rows, out.values, out.trajectories
    straight = run.gaits(p, [acceleration(), braking()])
    straight_reset = run.gaits(p, [acceleration(), braking()], reset=True)
    trajs["straight"], trajs["straight_reset"] = straight, straight_reset
    i_acc = int(np.nonzero(np.asarray(straight.segment) == 0)[0][-1])
    Om1 = np.asarray(straight.Omega[i_acc])
    vals["Omega_after_acceleration"] = Om1.tolist()
    rows.append(Row("Omega_1 after acceleration (5.1) [1/s]", "0.864", f"{Om1[1]:.6f}", "",
                    f"full Omega at t = 2 s: {_vec(Om1)}; the e1, e3 parts come from the wheels' "
                    "inertia j and are dropped by the paper's reset (5.4)."))  # fmt: skip
    v_kin = R0 * Om1[1]
    rows.append(Row("speed of the kinematic run (5.5) [m/s]", "0.13", f"{v_kin:.4f}", "",
                    "R0 * Omega_1; the paper rounds 0.1296 to 0.13."))  # fmt: skip
    vals["kinematic_speed"] = v_kin
    return straight, straight_reset, v_kin


def _figure2(p: RobotParams, run: _Run, straight: Trajectory, v_kin: float, out: Reproduction):
    """Fig. 2: kinematic control (2.9) through the dynamic model next to gait control."""
    rows, vals, trajs = out.rows, out.values, out.trajectories
    ts8 = np.linspace(0.0, 8.0, int(8 * run.rate) + 1)
    wheels = kinematic_control(p, straight_line(v_kin), t_stop=4.0)
    kin = _host(simulate(p, State.at_rest(p), wheels, 8.0, ts=ts8, options=run.options))
    gait8 = _gaits_then_stopped(p, run, straight, wheels, ts8)
    trajs["kinematic"], trajs["gait_8s"] = kin, gait8
    sig = {}
    for name, tr in (("kinematic", kin), ("gait", gait8)):
        m = np.asarray(tr.ts) >= 4.0
        g3 = np.asarray(tr.gamma[:, 2])[m]
        sig[name] = (float(np.std(g3)), float(np.sqrt(np.mean((g3 - 1.0) ** 2))))
    vals["sigma_gamma3_t_gt_4"] = {k: {"std": v[0], "rms_from_upright": v[1]} for k, v in sig.items()}
    rows.append(Row("sigma of gamma_3, t in [4, 8] s, kinematic", "0.018 (experiment)", f"{sig['kinematic'][0]:.4f}", "",
                    "RMS deviation of gamma_3 about its mean after the wheels stop at t = 4 s; the model has no "
                    "dissipation, so the simulated oscillation does not decay (the experiment's does)."))  # fmt: skip
    rows.append(Row("sigma of gamma_3, t in [4, 8] s, gaits", "0.001 (experiment)", f"{sig['gait'][0]:.2e}", "",
                    "the gaits end on rest exactly (no reset), so the platform stays upright."))  # fmt: skip
    xk, yk = float(kin.x[int(4 * run.rate)]), float(kin.y[int(4 * run.rate)])
    vals["kinematic_position_t4_m"] = [xk, yk]
    rows.append(Row("kinematic run, position at t = 4 s", "(0, 520) mm (planned)", *_point(xk, yk),
                    "the planned path is 4 s * 0.13 m/s; the impulsive start of the wheels and the platform's "
                    "swing make the dynamic model run ahead of the kinematic plan."))  # fmt: skip


def _straight_stop(p: RobotParams, straight: Trajectory, straight_reset: Trajectory, out: Reproduction):
    """Section 5.2 (1): the stop point of the straight line."""
    R0, rows, vals = float(p.R0), out.rows, out.values
    xs, ys = float(straight.x[-1]), float(straight.y[-1])
    xr, yr = float(straight_reset.x[-1]), float(straight_reset.y[-1])
    vals["straight_stop_m"] = {"continuation": [xs, ys], "reset_5.4": [xr, yr]}
    why = ("the paper's stop does not follow from its own Omega_1: any R_m, j giving Omega_1 = 0.864 stop at "
           f"~2 s * R0 * Omega_1 = {2 * R0 * 0.864 * 1e3:.1f} mm; 344.6 mm would need Omega_1 = 1.15 1/s.")  # fmt: skip
    rows.append(Row("straight line stop, simulation", "(-0.0695, 344.6) mm", *_point(xs, ys), why))
    rows.append(Row("straight line stop, reset (5.4)", "", *_point(xr, yr),
                    f"with the reset the robot keeps {1e3 * _horizontal_speed(p, straight_reset):.2f} mm/s "
                    "(the dropped sideways part of Omega)."))  # fmt: skip
    rows.append(Row("straight line stop, experiment", "(-1.392 +- 28.9, 369.2 +- 37.7) mm", "", ""))


def _turn_stops(p: RobotParams, run: _Run, out: Reproduction):
    """Section 5.2 (2): acceleration, turn (5.6), braking at `phi = pi/4`, under the readings of (5.7)."""
    rows, vals, trajs = out.rows, out.values, out.trajectories
    gaits3 = [acceleration(), turn(), braking(phi=math.pi / 4)]
    t_reset = run.gaits(p, gaits3, reset=[True, None])
    t_cont = run.gaits(p, gaits3)
    t_sign = run.gaits(p, gaits3, reset=[True, (-0.868, 0.852, 0.0)])
    t_print = run.gaits(p, gaits3, reset=[True, (0.868, 0.852, 0.0)])
    trajs.update(turn_reset=t_reset, turn_continuation=t_cont, turn_signfixed=t_sign, turn_printed=t_print)
    i_turn = int(np.nonzero(np.asarray(t_reset.segment) == 1)[0][-1])
    Om_turn = np.asarray(t_reset.Omega[i_turn])
    vals["Omega_after_turn_reset"] = Om_turn.tolist()
    rows.append(Row("Omega after the turn [1/s]", "(0.868, 0.852, 0) (5.7)", _vec(Om_turn, 6), "",
                    "turn started from the reset (5.4); the printed (5.7) has lost the sign of its first "
                    "component (braking at phi = pi/4 needs Omega_1 < 0) and its 0.868 is not reproduced (0.864 "
                    "after the reset, 0.876 without)."))  # fmt: skip
    why = {
        "turn_printed": ": with the printed sign the 'braking' gait speeds the robot up",
        "turn_reset": "; theta_max = 0.1 at phi = pi/4 cannot cancel a speed of |(0.864, 0.852)| R0 (it removes 0.864 "
        "R0 along the diagonal); the paper's stop point is therefore not reproducible",
    }
    for name, tr, label in (
        ("turn_reset", t_reset, "turn + brake stop, reset before the turn"),
        ("turn_signfixed", t_sign, "turn + brake stop, (5.7) with its sign fixed"),
        ("turn_printed", t_print, "turn + brake stop, (5.7) as printed"),
        ("turn_continuation", t_cont, "turn + brake stop, no resets"),
    ):
        x, y = float(tr.x[-1]), float(tr.y[-1])
        vals[f"{name}_stop_m"] = [x, y]
        vals[f"{name}_residual_speed_m_s"] = _horizontal_speed(p, tr)
        note = f"still rolling at {1e3 * _horizontal_speed(p, tr):.1f} mm/s after the brake" + why.get(name, "")
        rows.append(Row(label, "(-173.2, 519.4) mm" if name == "turn_reset" else "", *_point(x, y), note))
    rows.append(Row("turn + brake stop, experiment", "(-151.3 +- 32.4, 482.4 +- 112.1) mm", "", ""))


def _full_stop(p: RobotParams, run: _Run, out: Reproduction):
    """The braking gait that stops the robot after the turn (`full_stop_brake`) and its stop point."""
    rows, vals, trajs = out.rows, out.values, out.trajectories
    th, ph, res = full_stop_brake(p, rate=run.rate, options=run.options)
    fs = run.gaits(p, [acceleration(), turn(), braking(theta_max=th, phi=ph)])
    trajs["turn_full_stop"] = fs
    vals["full_stop_brake"] = {"theta_max": th, "phi": ph, "stop_m": [float(fs.x[-1]), float(fs.y[-1])]}
    rows.append(Row("braking that stops after the turn", "-", f"theta_max = {th:.5f}, phi = {ph:.5f}", "",
                    "found by Newton on the final horizontal Omega (no resets)."))  # fmt: skip
    rows.append(Row("  ... its stop point", "-", *_point(fs.x[-1], fs.y[-1])))


def _host(tr: Trajectory) -> Trajectory:
    """`tr` with NumPy leaves: the numbers below are read from it without one small compiled
    JAX program per indexing operation (see `docs/performance.md`)."""
    return jax.device_get(tr)


def _gaits_then_stopped(p: RobotParams, run: _Run, gaits: Trajectory, wheels, ts8) -> Trajectory:
    """The gait motion `gaits` followed, until `ts8[-1]`, by the omniwheels stopped
    (`chi_dot = 0`), as after the kinematic run: "the motion of the robot lasted 4 s, after which
    the omniwheels stopped" (Section 5.1).

    `wheels` is the kinematic run's command, stopped from its `t_stop` on: starting at
    `t_end >= t_stop` it holds the wheels still throughout. Sampled on `len(ts8)` points of
    `[t_end, ts8[-1]]` and then thinned to `ts8`'s spacing, the solve has the kinematic run's
    argument shapes and so reuses its compiled program (one compilation fewer in a first run).
    """
    ts8 = np.asarray(ts8)
    t_end, t1 = float(gaits.ts[-1]), float(ts8[-1])
    n = len(ts8)
    fine = np.linspace(t_end, t1, n)
    step = (ts8[1] - ts8[0]) / (fine[1] - fine[0])
    k = int(round(step))
    if wheels.fn.t_stop is None or t_end < wheels.fn.t_stop or abs(step - k) > 1e-9 or k < 1:
        raise ValueError("_gaits_then_stopped: the gaits must end after the wheels' t_stop, on ts8's grid")
    after = _host(simulate(p, gaits.state(-1), wheels, t1, t0=t_end, ts=fine, options=run.options))
    keep = np.arange(k, n, k)  # the samples after t_end on ts8's grid, joined to the gait's
    out = jax.tree_util.tree_map(lambda u, v: np.concatenate([u, v[keep]]) if np.ndim(u) >= 1 else u, gaits, after)
    seg = np.concatenate([gaits.segment, after.segment[keep] + np.max(gaits.segment) + 1])
    status, steps = np.maximum(gaits.status, after.status), gaits.num_steps + after.num_steps
    return eqx.tree_at(lambda t: (t.segment, t.status, t.num_steps), out, (seg, status, steps))
