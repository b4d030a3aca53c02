"""A plan: the manoeuvres found, their accurate trajectory, errors, limits and the table
that a robot executes."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..model.kinematics import rest_attitude
from ..model.params import RobotParams
from ..model.rotations import rotation_between
from ..solve.simulate import Trajectory


class PlanInfeasibleError(RuntimeError):
    """A request that the planner could not meet within the limits. `.plan` holds the best plan
    found (or `.plans` for a batch); the message says how far it falls short and which limit binds."""

    def __init__(self, message: str, plan: Plan | None = None, plans: list[Plan] | None = None):
        super().__init__(message)
        self.plan = plan
        self.plans = plans


@dataclasses.dataclass
class Plan:
    """A rest-to-rest manoeuvre (or a route of several, stopping at each waypoint).

    - `gaits`: the `TiltGait`s executed one after the other; `legs`: per gait, its start pose
      `(x, y, psi)` in the fixed frame (each gait is planned in its start frame).
    - `trajectory`: the accurate re-simulation (`simulate_gaits`, Dopri8, rtol 1e-10) sampled at
      `rate` Hz, with fixed-frame `x, y` (routes: leg by leg, moved to the leg's start pose).
    - `target`: `(x, y, psi or nan)` of the last leg; `errors`: achieved `position_m`,
      `speed_m_s` (`R0 |Omega x gamma|` at the end), `heading_rad` (nan if free), `spin_rad_s`.
    - `limits_report`: per limit `{limit, max, ok}`; `violations`: names with the excess.
    - `feasible`: terminal tolerances met and every limit respected.
    - `iterations`: Adam, L-BFGS, LM counts; `elapsed_s`: wall time; `loss`: final objective.
    """

    params: RobotParams
    gaits: list
    legs: np.ndarray
    trajectory: Trajectory
    rate: float
    target: np.ndarray
    errors: dict
    limits_report: dict
    feasible: bool
    shortfall: list
    iterations: dict
    elapsed_s: float
    loss: float
    restarts: int = 1

    @property
    def duration(self) -> float:
        """Total time [s]."""
        return float(np.asarray(self.trajectory.ts)[-1])

    def table(self) -> dict[str, np.ndarray]:
        """The executable table: `t, K_1..K_N, chi_dot_1..chi_dot_N, x, y, gamma_1..3, heading,
        tilt` (SI: s, N m, rad/s, m, -, rad, rad); the robot is at rest at the last row."""
        tr = self.trajectory
        N = int(np.asarray(tr.K).shape[-1])
        cols: dict[str, np.ndarray] = {"t": np.asarray(tr.ts)}
        for i in range(N):
            cols[f"K_{i + 1}"] = np.asarray(tr.K[:, i])
        for i in range(N):
            cols[f"chi_dot_{i + 1}"] = np.asarray(tr.chi_dot[:, i])
        cols["x"], cols["y"] = np.asarray(tr.x), np.asarray(tr.y)
        g = np.asarray(tr.gamma)
        for i in range(3):
            cols[f"gamma_{i + 1}"] = g[:, i]
        R = np.stack([np.asarray(tr.alpha), np.asarray(tr.beta), g], axis=-2)
        Qm = np.asarray(rotation_between(jnp.array([0.0, 0.0, 1.0]), rest_attitude(self.params)))
        M = R @ Qm
        cols["heading"] = np.unwrap(np.arctan2(M[:, 1, 0], M[:, 0, 0]))
        gm = np.asarray(rest_attitude(self.params))
        cols["tilt"] = np.arccos(np.clip(g @ gm, -1.0, 1.0))
        return cols

    def to_csv(self, path) -> None:
        """Write `table()` as CSV (header line, full float64 precision), atomically."""
        from .._runtime.files import atomic_write_text

        cols = self.table()
        names = list(cols)
        data = np.stack([cols[k] for k in names], axis=1)
        lines = [",".join(names)] + [",".join(repr(float(v)) for v in row) for row in data]
        atomic_write_text(path, "\n".join(lines) + "\n")

    def commands(self, kind: str = "chi_dot", rate: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The commands for the robot: `(t (M,), values (M, N))`, the wheel speeds `chi_dot_i`
        [rad/s] (`kind="chi_dot"`) or the axle torques `K_i` [N m] (`kind="K"`) in the sign
        convention of `docs/capture.md` (the model's), at `rate` rows per second from `t = 0`
        to the plan's end (default: the plan's own `rate`), interpolated linearly from the
        trajectory. The robot is at rest at the last row."""
        from ..capture.inputs import input_kind

        want = input_kind(kind)
        if want is None:
            raise ValueError("Plan.commands: kind must be 'chi_dot' or 'K'.")
        rate = self.rate if rate is None else float(rate)
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"Plan.commands: rate must be a positive number of rows per second; got {rate!r}.")
        tr = self.trajectory
        ts = np.asarray(tr.ts)
        vals = np.asarray(tr.chi_dot if want == "wheel_speeds" else tr.K)
        T = float(ts[-1])
        t = np.arange(int(np.floor(T * rate + 1e-9)) + 1) / rate
        if T - t[-1] > 1e-9:
            t = np.append(t, T)
        keep = np.concatenate([np.diff(ts) > 0, [True]])  # a repeated time: its value from then on
        out = np.stack([np.interp(t, ts[keep], vals[keep, i]) for i in range(vals.shape[1])], axis=1)
        return t, out

    def write_commands(self, path, kind: str = "chi_dot", rate: float | None = None) -> None:
        """Write `commands(kind, rate)` as an inputs table, `t, chi_dot_1..N` or `t, K_1..N`: the
        table that `read_inputs_csv` and `jsphere convert --inputs` read (atomically)."""
        from ..capture.inputs import input_kind, write_inputs_csv

        t, values = self.commands(kind, rate)
        write_inputs_csv(path, t, values, input_kind(kind))

    def summary(self) -> str:
        """A few lines for a terminal: target, errors, limits, feasibility, iterations, time."""
        e = self.errors
        out = [
            f"plan: {len(self.gaits)} manoeuvre(s), T = {self.duration:.3f} s, "
            f"target ({self.target[0]:.4f}, {self.target[1]:.4f}) m"
            + ("" if np.isnan(self.target[2]) else f", heading {self.target[2]:.4f} rad"),
            (
                f"  final position error {1e3 * e['position_m']:.4f} mm, speed {1e3 * e['speed_m_s']:.4f} mm/s, "
                f"heading error {e['heading_rad']:.2e} rad, shell spin {e['spin_rad_s']:.2e} 1/s"
            ),
        ]
        for name, r in self.limits_report.items():
            out.append(f"  {name:<16} max {r['max']:.5g} / limit {r['limit']:.5g}  {'ok' if r['ok'] else 'VIOLATED'}")
        it = self.iterations
        out.append(
            f"  {self.restarts} restarts; Adam {it['adam']}, L-BFGS {it['lbfgs']}, LM {it['lm']} iterations; "
            f"{self.elapsed_s:.1f} s; {'FEASIBLE' if self.feasible else 'NOT FEASIBLE: ' + '; '.join(self.shortfall)}"
        )
        return "\n".join(out)
