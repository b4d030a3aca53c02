"""A plan: the manoeuvres found, their accurate trajectory, errors, limits and the table
that a robot executes; the record of a plan file (`plan.json`) and the robot it names."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..model.kinematics import rest_attitude
from ..model.params import RobotParams
from ..model.rotations import rotation_between
from ..solve.simulate import Trajectory


def platform_heading(params: RobotParams, alpha, beta, gamma) -> np.ndarray:
    """The platform's yaw `psi` [rad] relative to the rest attitude of the frames `alpha, beta,
    gamma (..., 3)` (the fixed axes seen from the platform): `R Q_m = Q_psi^T`."""
    R = np.stack([np.asarray(alpha), np.asarray(beta), np.asarray(gamma)], axis=-2)
    M = R @ np.asarray(rotation_between(jnp.array([0.0, 0.0, 1.0]), rest_attitude(params)))
    return np.arctan2(M[..., 1, 0], M[..., 0, 0])


def tilt(params: RobotParams, gamma) -> np.ndarray:
    """The platform's tilt [rad] from its rest attitude at the vertical axes `gamma (..., 3)`."""
    return np.arccos(np.clip(np.asarray(gamma) @ np.asarray(rest_attitude(params)), -1.0, 1.0))


def write_columns(path, cols: dict[str, np.ndarray]) -> None:
    """Write equal-length columns as CSV (a header line, full float64 precision), atomically."""
    from .._runtime.files import atomic_write_text

    data = np.stack(list(cols.values()), axis=1)
    lines = [",".join(cols)] + [",".join(repr(float(v)) for v in row) for row in data]
    atomic_write_text(path, "\n".join(lines) + "\n")


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
    - `at_rest`: every manoeuvre ends at rest (its terminal speed within the planner's
      tolerance); the commands of `table` and `commands` then end on exactly 0.
    - `family`: `"direct"` (free torque profiles; `gaits` is empty and `profile` holds the
      knots `(t (n+1,), K (n+1, N))`, linear between them) or `"gait"` (`TiltGait`s).
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
    at_rest: bool = False
    profile: tuple | None = None
    family: str = "gait"

    @property
    def duration(self) -> float:
        """Total time [s]."""
        return float(np.asarray(self.trajectory.ts)[-1])

    def commanded(self, name: str) -> np.ndarray:
        """The samples `(T, N)` of the trajectory's `K` or `chi_dot`; for a plan `at_rest`, 0 at
        the last sample of every leg, the rest each manoeuvre ends at. A manoeuvre ends on the
        stationary motion by construction (`u, u_dot, omega_gamma = 0`, so `K = 0` and the
        platform at rest); the re-simulated end sample carries the terminal speed error instead
        (`errors["speed_m_s"]`, up to the tolerance: a few 1e-3 rad/s of wheel speed) and
        rounding (`K` ~ 1e-19 N m). The command that ends a rest-to-rest manoeuvre is rest:
        exactly 0."""
        tr = self.trajectory
        vals = np.array(getattr(tr, name), dtype=float, copy=True)
        if not self.at_rest:
            return vals
        seg = np.asarray(tr.segment)
        ends = np.flatnonzero(np.append(np.diff(seg) != 0, True))
        vals[ends] = 0.0
        return vals

    def table(self) -> dict[str, np.ndarray]:
        """The executable table: `t, K_1..K_N, chi_dot_1..chi_dot_N, x, y, gamma_1..3, heading,
        tilt` (SI: s, N m, rad/s, m, -, rad, rad); the robot is at rest at the last row, whose
        commands `K_i`, `chi_dot_i` are exactly 0 for a plan `at_rest` (as at each stop of a
        route)."""
        tr = self.trajectory
        cols: dict[str, np.ndarray] = {"t": np.asarray(tr.ts)}
        for name in ("K", "chi_dot"):
            vals = self.commanded(name)
            cols.update({f"{name}_{i + 1}": vals[:, i] for i in range(vals.shape[1])})
        cols["x"], cols["y"] = np.asarray(tr.x), np.asarray(tr.y)
        g = np.asarray(tr.gamma)
        cols.update({f"gamma_{i + 1}": g[:, i] for i in range(3)})
        cols["heading"] = np.unwrap(platform_heading(self.params, tr.alpha, tr.beta, g))
        cols["tilt"] = tilt(self.params, g)
        return cols

    def to_csv(self, path) -> None:
        """Write `table()` as CSV (header line, full float64 precision), atomically."""
        write_columns(path, self.table())

    def commands(self, kind: str = "chi_dot", rate: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The commands for the robot: `(t (M,), values (M, N))`, the wheel speeds `chi_dot_i`
        [rad/s] (`kind="chi_dot"`) or the axle torques `K_i` [N m] (`kind="K"`) in the sign
        convention of `docs/capture.md` (the model's), at `rate` rows per second from `t = 0`
        to the plan's end (default: the plan's own `rate`), interpolated linearly from the
        trajectory. The robot is at rest at the last row, whose commands are exactly 0 for a
        plan `at_rest`."""
        from ..capture.inputs import input_kind

        want = input_kind(kind)
        if want is None:
            raise ValueError("Plan.commands: kind must be 'chi_dot' or 'K'.")
        rate = self.rate if rate is None else float(rate)
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"Plan.commands: rate must be a positive number of rows per second; got {rate!r}.")
        tr = self.trajectory
        ts = np.asarray(tr.ts)
        vals = self.commanded("chi_dot" if want == "wheel_speeds" else "K")
        T = float(ts[-1])
        t = np.arange(int(np.floor(T * rate + 1e-9)) + 1) / rate
        if T - t[-1] > 1e-9:
            t = np.append(t, T)
        keep = np.concatenate([np.diff(ts) > 0, [True]])  # a repeated time: its value from then on
        out = np.stack([np.interp(t, ts[keep], vals[keep, i]) for i in range(vals.shape[1])], axis=1)
        return t, out

    def write_commands(self, path, kind: str = "chi_dot", rate: float | None = None, *, comment: str = "") -> None:
        """Write `commands(kind, rate)` as an inputs table, `t, chi_dot_1..N` or `t, K_1..N`: the
        table that `read_inputs_csv` and `jsphere convert --inputs` read (atomically).
        `comment`: lines written first, each starting with `# ` (the comment lines that
        `read_inputs_csv` skips before the header)."""
        import tempfile

        from .._runtime.files import atomic_write_text
        from ..capture.inputs import input_kind, write_inputs_csv

        t, values = self.commands(kind, rate)
        if not comment:
            write_inputs_csv(path, t, values, input_kind(kind))
            return
        with tempfile.TemporaryDirectory() as tmp:
            write_inputs_csv(Path(tmp) / "commands.csv", t, values, input_kind(kind))
            table = (Path(tmp) / "commands.csv").read_text()
        lines = "".join(f"# {line}\n" for line in comment.splitlines())
        atomic_write_text(path, lines + table)

    def record(self, params_source: str) -> dict:
        """What `plan.json` holds: `feasible`, `shortfall`, `target` (a free heading as None),
        `duration_s`, `errors`, `limits` (`limits_report`), `iterations`, `elapsed_s`,
        `restarts`, `family`, `rate_hz`, and the robot the plan was made for: `params` (every field,
        `RobotParams.to_dict`; `RobotParams.load("plan.json")` reads it) and `params_source`
        (where it came from, in words: a parameter file, the paper's robot, ...)."""
        return {
            "feasible": self.feasible,
            "shortfall": self.shortfall,
            "target": [None if np.isnan(v) else float(v) for v in np.asarray(self.target).tolist()],
            "duration_s": self.duration,
            "errors": self.errors,
            "limits": self.limits_report,
            "iterations": self.iterations,
            "elapsed_s": self.elapsed_s,
            "restarts": self.restarts,
            "family": self.family,
            "rate_hz": self.rate,
            "params": self.params.to_dict(),
            "params_source": str(params_source),
        }

    def summary(self) -> str:
        """A few lines for a terminal: target, errors, limits, feasibility, iterations, time."""
        e = self.errors
        out = [
            f"plan ({self.family}): {max(len(self.gaits), 1)} manoeuvre(s), T = {self.duration:.3f} s, "
            f"target ({self.target[0]:.4f}, {self.target[1]:.4f}) m"
            + ("" if np.isnan(self.target[2]) else f", heading {self.target[2]:.4f} rad"),
            (
                f"  final position error {1e3 * e['position_m']:.4f} mm, speed {1e3 * e['speed_m_s']:.4f} mm/s, "
                + ("" if np.isnan(self.target[2]) else f"heading error {e['heading_rad']:.2e} rad, ")
                + f"shell spin {e['spin_rad_s']:.2e} 1/s"
            ),
        ]
        for name, r in self.limits_report.items():
            out.append(f"  {name:<16} max {r['max']:.5g} / limit {r['limit']:.5g}  {'ok' if r['ok'] else 'VIOLATED'}")
        it = self.iterations
        searched = (
            f"IPOPT {it['ipopt']} iterations in {it['solves']} solve(s)"
            if self.family == "direct"
            else f"{self.restarts} restarts; Adam {it['adam']}, L-BFGS {it['lbfgs']}, LM {it['lm']} iterations"
        )
        out.append(
            f"  {searched}; "
            f"{self.elapsed_s:.1f} s; {'FEASIBLE' if self.feasible else 'NOT FEASIBLE: ' + '; '.join(self.shortfall)}"
        )
        return "\n".join(out)


def manoeuvre_plan(params, gait, tr, rate, tg, err: dict, rep: dict, shortfall: list, **stats) -> Plan:
    """The `Plan` of one manoeuvre from rest at the origin: its gait, trajectory and sampling
    rate, the target `tg = (x, y, heading, has_heading)`, its terminal errors, limit report and
    shortfall (feasible when empty); `stats`: `iterations`, `elapsed_s`, `loss`, `restarts`,
    `at_rest`."""
    return Plan(
        params=params,
        gaits=[gait],
        legs=np.zeros((1, 3)),
        trajectory=tr,
        rate=rate,
        target=np.array([tg[0], tg[1], tg[2] if tg[3] else np.nan]),
        errors=err,
        limits_report=rep,
        feasible=not shortfall,
        shortfall=shortfall,
        **stats,
    )


# ----------------------------------------------------------------------------- the robot of a plan file


@dataclasses.dataclass(frozen=True)
class PlannedRobot:
    """The robot a plan file was made for: `params`, `source` (where the plan's robot came
    from, in words, e.g. the parameter file given to `jsphere plan --params`) and `record`
    (the JSON that holds it: `plan.json`, or the record beside a commands table)."""

    params: RobotParams
    source: str
    record: Path

    def describe(self) -> str:
        """`"<source> (recorded in <record>)"`, for messages."""
        return f"{self.source} (recorded in {self.record})"


def planned_robot(path) -> PlannedRobot | None:
    """The robot recorded with a plan file (`path`: a plan CSV, its `plan.json`, or a commands
    table of `jsphere plan --commands`, whose record is the `.json` beside it: `plan.csv` ->
    `plan.json`, `commands.csv` -> `commands.json`), or None when there is no
    record or the record names no robot (a table written by other means). A record of
    `jsphere plan` has `feasible` and `params` (`Plan.record`). A `params` that is not a valid
    parameter set is an `InputError` naming the record."""
    import json

    path = Path(path)
    rec = path if path.suffix.lower() == ".json" else path.with_suffix(".json")
    if not rec.is_file():
        return None
    try:
        d = json.loads(rec.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(d, dict) or "feasible" not in d or not isinstance(d.get("params"), dict):
        return None
    try:
        params = RobotParams.from_dict(d["params"])
    except ValueError as e:
        raise InputError(
            f"{rec}: params: {e} (the robot of the plan; plan again with jsphere plan --params FILE)"
        ) from None
    source = d.get("params_source")
    return PlannedRobot(params, str(source) if isinstance(source, str) and source else "an unnamed robot", rec)


def robot_difference(a: RobotParams, b: RobotParams, rtol: float = 1e-12) -> str | None:
    """None when the parameter sets `a` and `b` are the same (every field equal to `rtol`),
    else the first field that differs, in words (`"j 0.00027395 vs 0.0003"`, `"I[2,2] 0.023 vs
    0.025"`)."""
    da, db = a.to_dict(), b.to_dict()
    for name in da:
        va, vb = np.asarray(da[name], float), np.asarray(db[name], float)
        if va.shape != vb.shape:
            return f"{name} of shape {va.shape} vs {vb.shape}"
        if not np.allclose(va, vb, rtol=rtol, atol=0.0):
            if va.ndim == 0:
                return f"{name} {float(va):.6g} vs {float(vb):.6g}"
            k = np.unravel_index(np.argmax(~np.isclose(va, vb, rtol=rtol, atol=0.0)), va.shape)
            return f"{name}[{','.join(str(int(i)) for i in k)}] {float(va[k]):.6g} vs {float(vb[k]):.6g}"
    return None
