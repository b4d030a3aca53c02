"""`track`: time-varying feedback gains along a plan, and how well they land on robots that
are not the model (see the package's description and `docs/tracking.md`)."""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.checks import real, whole
from ..._runtime.errors import InputError, SolverFailure
from ...model.limits import Limits
from ...model.params import RobotParams
from ...model.state import ERROR_SIZE, Flat, State
from ...model.uncertainty import Uncertainty
from ..result import Plan, write_columns
from ..robust import in_batches, miss_summary
from ..rollout import yaw
from .evaluate import Conditions, run_batch
from .flow import linearise, reference
from .lqr import Weights, riccati, terminal_regulator
from .table import STATE_COLUMNS

#: the default uncertainty of the evaluation when neither a fit nor a study is given: 3 % (sd)
#: on the centre-of-mass offset, the wheels' inertia and the platform's principal inertias
DEFAULT_SPREAD = 0.03
DEFAULT_NAMES = ("r_m[2]", "j", "I[0,0]", "I[1,1]", "I[2,2]")
#: the most doublings of `r` that `track` tries to respect the torque limit
MAX_R_DOUBLINGS = 30
#: draws per compiled evaluation call
BATCH = 1000


@dataclasses.dataclass
class Tracker:
    """Feedback gains along a plan: the table a robot's controller runs (`to_csv`, `track.csv`)
    and its evaluation.

    - `ts (M,)`: row times [s] at `rate` Hz; the last row, at the plan's end, is the terminal
      regulator at the target at rest, held from then on.
    - `K_ff (M, N)`: feed-forward torques [N m]; `reference (M, 16+N)`: the reference flat states
      (`State.flatten`); `G (M, N, 11)`: gains for the error of `state_error`.
      The command is `K = K_ff - G e`, held until the next row (zero-order hold).
    - `weights`, `r_scale` (the factor on `weights.r` the torque limit needed), `params` (the
      model the gains are for), `target (2,)`, `conserved (11,)`: the conserved mode's left null
      vector at the target; `eigenvalues`: of the terminal closed loop (moduli, largest first).
    - `miss_mc`: `{"open_loop": {...}, "closed_loop": {...}, ...}` (`miss_summary` in metres and
      m/s, the largest commanded torque) or None without an evaluation; `elapsed_s`.
    """

    ts: np.ndarray
    K_ff: np.ndarray
    reference: np.ndarray
    G: np.ndarray
    rate: float
    weights: Weights
    r_scale: float
    params: RobotParams
    target: np.ndarray
    max_torque: float | None
    conserved: np.ndarray
    eigenvalues: np.ndarray
    miss_mc: dict | None = None
    elapsed_s: dict = dataclasses.field(default_factory=dict)

    def table(self) -> dict[str, np.ndarray]:
        """The columns of `track.csv` (`docs/tracking.md`, `jsphere.planning.tracking.table`)."""
        N = self.K_ff.shape[1]
        cols = {"t": np.asarray(self.ts), **{f"K_{i + 1}": self.K_ff[:, i] for i in range(N)}}
        cols.update({name: self.reference[:, k] for name, k in STATE_COLUMNS})
        cols.update({f"G_{i + 1}_{j + 1}": self.G[:, i, j] for i in range(N) for j in range(ERROR_SIZE)})
        return cols

    def to_csv(self, path) -> None:
        """Write `table()` as `track.csv`, atomically."""
        write_columns(path, self.table())

    def to_json(self) -> dict[str, Any]:
        """What `track.json` records: weights, rate, robot, terminal regulator, evaluation."""
        return {
            "rate_hz": self.rate,
            "rows": int(len(self.ts)),
            "duration_s": float(self.ts[-1]),
            "target": [float(v) for v in self.target],
            "weights": self.weights.to_json(),
            "r_scale": self.r_scale,
            "max_torque_N_m": self.max_torque,
            "params": self.params.to_dict(),
            "error": ["x", "y", "a_1", "a_2", "a_3", *(f"{w}_{i}" for w in ("omega", "Omega") for i in (1, 2, 3))],
            "control_law": "K = K_ff - G e, zero-order hold from a row's t to the next; the last row held",
            "terminal": {
                "conserved_mode": [float(v) for v in self.conserved],
                "eigenvalue_moduli": [float(v) for v in self.eigenvalues],
            },
            "miss_mc": self.miss_mc,
            "elapsed_s": dict(self.elapsed_s),
        }

    def summary(self) -> str:
        lines = [
            f"track: {len(self.ts)} rows at {self.rate:g} Hz over {self.ts[-1]:.3f} s, target "
            f"({self.target[0]:.4f}, {self.target[1]:.4f}) m; r x {self.r_scale:g} for the torque limit; "
            f"terminal closed loop |eig| <= {self.eigenvalues[1]:.4f} besides the conserved mode"
        ]
        if self.miss_mc:
            for k in ("open_loop", "closed_loop"):
                s = self.miss_mc[k]
                lines.append(
                    f"  {k:<12} miss mean {1e3 * s['mean']:.3f} mm, p95 {1e3 * s['p95']:.3f} mm, end speed p95 "
                    f"{1e3 * s['speed_p95']:.3f} mm/s, largest |K| {s['max_torque_N_m']:.4f} N m"
                )
            lines.append(f"  over {self.miss_mc['samples']} draws ({self.miss_mc['source']})")
        return "\n".join(lines)


def _plan_input(plan) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, RobotParams | None, str]:
    """`(t, K (T, N), target or None, params or None, where the params come from)` of a `Plan`
    or a plan file: the CSV of `jsphere plan` (its `K_1..N` columns; the target and the robot
    from the `.json` beside it when there is one) or that `.json` (the CSV beside it)."""
    if isinstance(plan, Plan):
        ts, K = np.asarray(plan.trajectory.ts), plan.commanded("K")  # the torques of the plan's CSV
        keep = np.concatenate([np.diff(ts) > 0, [True]])
        return ts[keep], K[keep], np.asarray(plan.target[:2], float), plan.params, "the Plan's params"
    if not isinstance(plan, (str, Path)):
        raise InputError(
            f"track: plan must be a jsphere.Plan or the path of a plan CSV or JSON; got {type(plan).__name__}."
        )
    from ..._runtime.files import read_mapping
    from ...capture.inputs import read_inputs_csv
    from ..result import planned_robot

    path = Path(plan)
    csv, js = (path.with_suffix(".csv"), path) if path.suffix.lower() == ".json" else (path, path.with_suffix(".json"))
    if not csv.exists():
        raise InputError(f"{path}: no plan table {csv} (write it with `jsphere plan --out {csv.name}`).")
    try:
        t, K, _, _ = read_inputs_csv(csv, kind="K")
    except ValueError as e:
        raise InputError(str(e)) from None
    target = None
    if js.exists():
        info = read_mapping(js)
        tg = info.get("target") if isinstance(info, dict) else None
        if isinstance(tg, list) and len(tg) >= 2 and all(isinstance(v, (int, float)) for v in tg[:2]):
            target = np.asarray(tg[:2], float)
    robot = planned_robot(js)
    return t, K, target, robot.params if robot else None, robot.describe() if robot else ""


def gains(
    t_plan, K_plan, params: RobotParams, *, rate: float, weights: Weights, target=None, max_torque: float | None = 0.1
):
    """The table of `Tracker` (without evaluation) for the torque table `(t_plan, K_plan)`:
    feed-forward at the midpoint of each interval (linear interpolation), the reference held
    row by row from rest, the Jacobians (`flow.linearise`), the terminal regulator at the
    target at rest, the Riccati recursion, `r` doubled until the gains respect `max_torque`
    under `weights.expected`. Returns a dict of the `Tracker` fields."""
    dt = params.R0.dtype
    h = 1.0 / rate
    T = float(t_plan[-1])
    n = max(1, int(math.ceil(T * rate - 1e-9)))  # plan intervals; the terminal row at n h
    mid = (np.arange(n) + 0.5) * h
    K_mid = np.stack([np.interp(mid, t_plan, K_plan[:, i], right=0.0) for i in range(K_plan.shape[1])], axis=1)
    N = K_mid.shape[1]
    if N != params.n_wheels:
        raise InputError(f"track: the plan has {N} torque columns; the robot has {params.n_wheels} wheels.")
    z0 = State.at_rest(params).flatten().astype(dt)
    zs = reference(params, z0, jnp.asarray(K_mid, dt), h)
    zs.block_until_ready()
    if not bool(jnp.all(jnp.isfinite(zs))):
        raise SolverFailure("track: the reference motion of the plan's torques is not finite on this robot.")
    psi = yaw(params, zs[-1, Flat.q])
    tg = np.asarray(zs[-1, Flat.xy]) if target is None else np.asarray(target, float)
    z_end = State.at_rest(params, x=float(tg[0]), y=float(tg[1]), psi=float(psi)).flatten().astype(dt)
    A, B = linearise(params, zs[:-1], jnp.asarray(K_mid, dt), zs[1:], h)
    A_end, B_end = linearise(params, z_end[None], jnp.zeros((1, N), dt), z_end[None], h)
    Q = weights.Q(dt)
    sigma = weights.sigma(dt)
    scale = 1.0
    K_all = jnp.concatenate([jnp.asarray(K_mid, dt), jnp.zeros((1, N), dt)])
    for _ in range(MAX_R_DOUBLINGS + 1):
        R = weights.r * scale * jnp.eye(N, dtype=dt)
        G_end, P_end, w, _ = terminal_regulator(A_end[0], B_end[0], Q, R)
        G, _ = riccati(A, B, Q, R, P_end)
        G_all = jnp.concatenate([G, G_end[None]])
        ask = jnp.abs(K_all) + jnp.linalg.norm(G_all * sigma, axis=-1)
        if not bool(jnp.all(jnp.isfinite(G_all))):
            raise SolverFailure(
                "track: the Riccati recursion gave gains that are not finite; check the plan and weights."
            )
        if max_torque is None or float(jnp.max(ask)) <= max_torque:
            break
        scale *= 2.0
    else:
        raise InputError(
            f"track: the gains ask for {float(jnp.max(ask)):.4g} N m under the expected errors {weights.expected} even "
            f"with r x {scale:g}, above the torque limit {max_torque} N m; lower Weights.expected or raise the limit, or "
            "plan with torque to spare (a lower --max-torque, or --family gait: a direct plan uses the whole limit)."
        )
    from .lqr import closed_loop_eigenvalues

    ev = np.abs(closed_loop_eigenvalues(A_end[0], B_end[0], G_end))
    return dict(
        ts=np.arange(n + 1) * h,
        K_ff=np.asarray(K_all),
        reference=np.concatenate([np.asarray(zs[:-1]), np.asarray(z_end)[None]]),
        G=np.asarray(G_all),
        rate=float(rate),
        weights=weights,
        r_scale=scale,
        params=params,
        target=np.asarray(tg, float),
        max_torque=max_torque,
        conserved=np.asarray(w),
        eigenvalues=ev,
    )


def default_uncertainty(params: RobotParams) -> Uncertainty:
    """`DEFAULT_SPREAD` (sd, relative) on `DEFAULT_NAMES` around `params`' values."""
    from ...model.names import get_value

    a = np.asarray([float(get_value(params, n)) for n in DEFAULT_NAMES])
    return Uncertainty(
        DEFAULT_NAMES,
        ("normal",) * len(a),
        a,
        DEFAULT_SPREAD * np.abs(a),
        None,
        f"default: {DEFAULT_SPREAD:.0%} sd on {', '.join(DEFAULT_NAMES)}",
    )


def evaluate(
    tracker: Tracker, samples: RobotParams, *, conditions: Conditions | None = None, seed: int = 0, source: str = ""
) -> dict:
    """`miss_mc` of a tracker: the plan open loop (feed-forward only) and closed loop on every
    robot of `samples` (stacked `RobotParams`), same draws and same noise for both (the
    conditions of `evaluate.Conditions`). Raises `SolverFailure` if any trial is not finite."""
    c = conditions or Conditions()
    dt = tracker.params.R0.dtype
    n = int(np.shape(samples.R0)[0])
    h = 1.0 / tracker.rate
    n_settle = int(math.ceil(c.settle * tracker.rate - 1e-9))
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    arrs = [jnp.asarray(v, dt) for v in (tracker.K_ff, tracker.reference, tracker.G, tracker.target)]
    out = {}
    for name, closed in (("open_loop", 0.0), ("closed_loop", 1.0)):
        closed = jnp.asarray(closed, dt)
        run = lambda part, k: run_batch(part, k, h, *arrs, c, tracker.max_torque, n_settle, closed)
        miss, speed, umax = in_batches(run, BATCH, samples, keys)
        bad = ~(np.isfinite(miss) & np.isfinite(speed))
        if bad.any():
            raise SolverFailure(
                f"track: {int(bad.sum())} of {n} {name.replace('_', ' ')} trials are not finite (first: draw "
                f"{int(np.argmax(bad))}); the integration at {tracker.rate:g} Hz fails on those robots."
            )
        out[name] = {**miss_summary({"miss_m": miss, "speed_m_s": speed}), "max_torque_N_m": float(np.max(umax))}
    out["samples"] = n
    out["source"] = source
    out["seed"] = int(seed)
    out["conditions"] = c.to_json()
    return out


def track(
    plan,
    params: RobotParams | None = None,
    *,
    rate: float = 100.0,
    weights: Weights | None = None,
    limits: Limits | None = None,
    uncertainty: Uncertainty | None = None,
    samples: int = 1000,
    conditions: Conditions | None = None,
    seed: int = 0,
) -> Tracker:
    """Time-varying linear-quadratic feedback along a plan, and its evaluation.

    **Arguments:**
    - `plan`: a `Plan`, or the path of a plan CSV (`jsphere plan --out`, its `K_1..N` columns)
      or of its `plan.json` (the CSV beside it). The target is the plan's; for a CSV without
      its JSON, the end of the reference motion.
    - `params`: the robot the plan was made for (default: the `Plan`'s, or the robot its
      `plan.json` records, else the paper's). A `params` other than the robot the plan
      records is an `InputError`: gains for one robot along a plan made for another.
    - `rate` [Hz]: the control rate, one table row per period.
    - `weights`: `Weights` (defaults there); `limits`: the torque limit `max_torque` of
      `Limits` (default 0.1 N m) bounds the gains and saturates the evaluation's commands.
    - `uncertainty`: the robots of the evaluation (`Uncertainty(names, kinds, a, b)` or `Uncertainty.from_fit`);
      default `default_uncertainty`. `samples` (0: no evaluation), `conditions`, `seed`: of
      the evaluation (`evaluate`).

    Returns a `Tracker`; `Tracker.to_csv` writes the table a robot's controller runs.

    Example:

        pl = jsphere.plan(p, (0.4, 0.2))
        tr = jsphere.track(pl, samples=1000)
        tr.to_csv("track.csv"); print(tr.miss_mc["closed_loop"]["p95"])
    """
    rate = real("track", "rate", rate, strict=True, unit="Hz")
    samples = whole("track", "samples", samples, 0)
    seed = whole("track", "seed", seed, 0)
    weights = weights or Weights()
    if not isinstance(weights, Weights):
        raise InputError(f"track: weights must be a jsphere.TrackWeights; got {type(weights).__name__}.")
    if uncertainty is not None and not isinstance(uncertainty, Uncertainty):
        raise InputError(f"track: uncertainty must be a jsphere.Uncertainty; got {type(uncertainty).__name__}.")
    if conditions is not None and not isinstance(conditions, Conditions):
        raise InputError(f"track: conditions must be a jsphere.TrackConditions; got {type(conditions).__name__}.")
    lim = limits or Limits()
    t_plan, K_plan, target, p_plan, p_from = _plan_input(plan)
    if params is not None and p_plan is not None:
        from ..result import robot_difference

        diff = robot_difference(p_plan, params)
        if diff is not None:
            raise InputError(
                f"track: params are not the robot the plan was made for, {p_from} (plan vs params: {diff}); leave params out to "
                "use the plan's robot, or plan again for this robot."
            )
    params = params or p_plan or RobotParams.paper()
    if t_plan[-1] * rate > 1e6:
        raise InputError(f"track: rate = {rate:g} Hz makes {t_plan[-1] * rate:.3g} rows; lower the rate.")
    t0 = time.perf_counter()
    fields = gains(t_plan, K_plan, params, rate=rate, weights=weights, target=target, max_torque=lim.max_torque)
    tr = Tracker(**fields)
    tr.elapsed_s["gains"] = time.perf_counter() - t0
    if samples:
        unc = uncertainty or default_uncertainty(params)
        t1 = time.perf_counter()
        _, drawn = unc.draw(params, samples, seed)
        tr.miss_mc = evaluate(tr, drawn, conditions=conditions, seed=seed, source=unc.source)
        tr.elapsed_s["evaluation"] = time.perf_counter() - t1
    return tr
