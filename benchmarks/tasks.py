"""User tasks end to end, each against a same-run baseline: fits, plans, tracking, design,
animations. Each prints a table and writes its JSON (`--out`); benchmarks/README.md says what
each task measures and the file it writes.

    python benchmarks/tasks.py TASK [options]          # TASK --help lists its options
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import common
import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from common import dispatch, environment, log, parser, print_pairs, print_table, result_path, timed, write_json

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

# ---------------------------------------------------------------------- fits

#: the parameter set the fit does not know
TRUTH = {"R_m": 0.029, "j": 3.2e-4, "m0": 0.9, "I0": 0.011, "I": np.diag([0.018, 0.015, 0.025])}


def truth_params() -> jsphere.RobotParams:
    return jsphere.RobotParams.paper().replace(**TRUTH)


def make_trials(truth, n, durations, kind, seed, rate=100.0):
    """`n` synthetic trials; durations drawn uniformly from `durations = (lo, hi)` [s], or
    `durations` itself when it is a list of `n` lengths [s]."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t1 = durations[i] if isinstance(durations, list) else float(np.round(rng.uniform(*durations) * rate) / rate)
        u = jsphere.random_inputs(truth, t1, kind=kind, seed=seed * 1000 + i)
        out.append(jsphere.synthetic_trial(truth, u, t1, rate=rate, seed=seed * 1000 + i, name=f"trial{i:02d}"))
    return out


def errors_se(res, truth, names=None) -> dict:
    """Each fitted value's error against `truth`, in its standard errors (NaN where that is 0)."""
    se = lambda n: res.stderr[n] if res.stderr[n] > 0 else float("nan")
    return {n: (res.values[n] - float(jsphere.get_value(truth, n))) / se(n) for n in names or res.free}


def other_robot() -> jsphere.RobotParams:
    """A robot 5-20 % away from the paper's: the truth of `robust-fit`."""
    return jsphere.RobotParams.paper().replace(
        m0=0.85, I0=0.0105, j=3.2e-4, r_m=np.array([0.0, 0.0, -0.031]), I=np.diag([0.018, 0.0145, 0.026])
    )


def torque_trials(robot, lengths, seed: int = 0):
    """Torque trials of `lengths` [s] at 100 Hz (random inputs of 0.3-0.7 Hz)."""
    out = []
    for i, length in enumerate(lengths):
        u = jsphere.random_inputs(robot, length, kind="torques", f_min=0.3, f_max=0.7, seed=seed * 100 + i)
        out.append(jsphere.synthetic_trial(robot, u, length, rate=100.0, seed=seed * 100 + i, name=f"t{i}"))
    return out


def fit(argv) -> int:
    """System identification on synthetic captures of `TRUTH`: time, and each parameter's error in SE."""
    ap = parser("tasks.py fit", "results-fit.json")
    ap.add_argument("--kind", default="wheel_speeds", choices=["wheel_speeds", "torques"])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--duration", default="6", help="seconds, or lo:hi for a uniform draw per trial")
    ap.add_argument("--free", default="R_m,j,I[0,0],I[1,1],I[2,2],I0")
    ap.add_argument("--fix", default="m,m0", help="names set to the truth (comma-separated)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-starts", type=int, default=2)
    ap.add_argument("--solver", help="a diffrax solver's name (e.g. Dopri8); default: the fit's own (FIT_SOLVER)")
    args = ap.parse_args(argv)
    lo, _, hi = args.duration.partition(":")
    durations = (float(lo), float(hi or lo))
    fix_names = [n for n in args.fix.split(",") if n]
    solver = jsphere.SolverOptions(solver=getattr(diffrax, args.solver)()) if args.solver else None
    truth = truth_params()
    trials = make_trials(truth, args.trials, durations, args.kind, args.seed)
    fix = {name: np.asarray(jsphere.get_value(truth, name)).tolist() for name in fix_names}
    options, paper = (
        jsphere.FitOptions(n_starts=args.n_starts, seed=args.seed, solver=solver),
        jsphere.RobotParams.paper(),
    )
    res, elapsed = timed(jsphere.fit, trials, paper, args.free, fix=fix, options=options, progress=True)
    rows = [
        {"name": n, "truth": float(jsphere.get_value(truth, n)), "fit": res.values[n], "stderr": res.stderr[n]}
        | {"error_se": z}
        for n, z in errors_se(res, truth).items()
    ]
    print(
        f"\n{args.trials} trials ({args.kind}), {sum(len(t.t) for t in trials)} samples; fit {elapsed:.1f} s "
        f"({res.iterations} LM iterations, {args.n_starts} starts, converged {res.converged})"
    )
    cols = [("name", "name", ""), ("truth", "truth", ".6g"), ("fit", "fit", ".6g"), ("stderr", "stderr", ".3g")]
    print_table([*cols, ("err/SE", "error_se", ".2f")], rows)
    print(f"sigma_pos {res.sigma_pos * 1e3:.3f} mm, sigma_rot {np.degrees(res.sigma_rot):.3f} deg")
    for w in res.identifiability["warnings"]:
        print("warning:", w)
    doc = {
        **environment(),
        "config": {
            "kind": args.kind,
            "trials": args.trials,
            "duration_s": durations,
            "samples": sum(len(t.t) for t in trials),
            "free": args.free,
            "fix": fix_names,
            "n_starts": args.n_starts,
            "seed": args.seed,
            "solver": args.solver or "the fit's default (Tsit5)",
        },
        "fit_s_including_compile": elapsed,
        "iterations": res.iterations,
        "converged": res.converged,
        "sigma_pos_mm": res.sigma_pos * 1e3,
        "sigma_rot_deg": float(np.degrees(res.sigma_rot)),
        "rows": rows,
    }
    write_json(args.out, doc)
    return 0


LONG_FREE = "R_m,j,I[0,0],I[1,1],I[2,2],m0,I0"
LONG_DURATIONS = [15.0, 15.0, 15.0, 30.0]
LONG_TARGET_S = 60.0


def long_fit_child(devices: int) -> dict:
    """One fit in this process, with `devices` CPU devices (0: one per core; set before JAX's
    first operation, which `main` leaves to this)."""
    jsphere.use_cpu_cores(devices or None)
    truth = truth_params()
    trials = make_trials(truth, len(LONG_DURATIONS), LONG_DURATIONS, "torques", seed=7)
    res, elapsed = timed(jsphere.fit, trials, jsphere.RobotParams.paper(), LONG_FREE, progress=False)
    return {
        **environment(),
        "fit_s": elapsed,
        "iterations": res.iterations,
        "converged": bool(res.converged),
        "shooting": res.shooting,
        "values": res.values,
        "z": errors_se(res, truth),
    }


def fit_long(argv) -> int:
    """The long-capture fit in new processes, one CPU device per core against one device."""
    ap = parser("tasks.py fit-long", "results-fit-long.json")
    ap.add_argument("--repeat", type=int, default=1, help="pairs of processes (per core, one device)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(long_fit_child(args.child)))
        return 0
    env = common.cli_env()
    env.pop("JAX_NUM_CPU_DEVICES", None)
    runs = {"per_core": [], "one_device": []}
    for _ in range(args.repeat):
        runs["per_core"].append(common.run_child("tasks.py", ["fit-long", "--child", "0"], env))
        runs["one_device"].append(common.run_child("tasks.py", ["fit-long", "--child", "1"], env))
    med = {k: statistics.median(r["fit_s"] for r in v) for k, v in runs.items()}
    last = runs["per_core"][-1]
    res = {
        **{k: last[k] for k in ("date_utc", "machine", "jax", "versions", "jsphere_git")},
        "trials_s": LONG_DURATIONS,
        "free": LONG_FREE,
        "devices": last["jax"]["device_count"],
        "fit_s": med["per_core"],
        "fit_s_one_device": med["one_device"],
        "one_device_over_per_core": med["one_device"] / med["per_core"],
        "runs": runs,
        "targets": {"fit_s": LONG_TARGET_S},
    }
    print(f"{'long-capture fit (3 x 15 s + 30 s, 7 free)':<44} {'fit s':>7} {'|z| max':>8} {'iterations':>11}")
    for k, v in runs.items():
        r = v[-1]
        label = f"{r['jax']['device_count']} device(s)"
        print(f"{label:<44} {med[k]:7.1f} {max(abs(x) for x in r['z'].values()):8.2f} {r['iterations']:11d}")
    print(f"one device / one per core: {res['one_device_over_per_core']:.2f}; target {LONG_TARGET_S:.0f} s")
    write_json(args.out, res)
    return 0


ROBUST_FREE = "r_m[2],j,I[0,0],I[1,1],I[2,2],m0,I0"


def glitchy(clean, seed: int):
    from jsphere.capture.synthetic import add_glitches

    out, bad = [], {}
    for i, t in enumerate(clean):
        g, rows = add_glitches(t, seed=seed * 100 + i)
        out.append(g)
        bad[g.name] = set(rows.tolist())
    return out, bad


#: the columns of the robust fits' tables
ROBUST_COLUMNS = [("wall s", "wall_s", ".1f"), ("iters", "iterations", "d"), ("max|z|", "max_error_se", ".2f")]
ROBUST_COLUMNS += [("sigma mm", "sigma_pos_mm", ".3f"), ("named", "named_share", ".0%")]
ROBUST_COLUMNS += [("clean out", "clean_frames_set_aside", "d"), ("status", "status", "")]


def robust_one(robot, tr, bad, loss):
    options = jsphere.FitOptions(loss=loss)
    res, wall = timed(jsphere.fit, tr, jsphere.RobotParams.paper(), ROBUST_FREE, options=options, progress=False)
    named = {k: set(v["frames"]) for k, v in res.outliers.items()}
    injected = sum(len(b) for b in bad.values())
    return {
        "loss": loss,
        "wall_s": wall,
        "iterations": res.iterations,
        "max_error_se": float(max(map(abs, errors_se(res, robot).values()))),
        "status": res.status,
        "sigma_pos_mm": res.sigma_pos * 1e3,
        "sigma_rot_deg": math.degrees(res.sigma_rot),
        "injected": injected,
        "named_share": sum(len(bad.get(k, set()) & v) for k, v in named.items()) / injected if injected else None,
        "clean_frames_set_aside": sum(len(v - bad.get(k, set())) for k, v in named.items()),
        "values": {k: res.values[k] for k in res.free},
        "stderr": {k: res.stderr[k] for k in res.free},
    }


def long_capture(out: str) -> None:
    """The long capture with Huber's loss in the warm-up stages then Cauchy's, against Cauchy's in every stage."""
    from jsphere.identify import fit as fit_module

    robot = other_robot()
    tr = torque_trials(robot, (15.0, 15.0, 15.0, 30.0))
    rows = []
    for how, redescending in (("huber, then cauchy", fit_module.REDESCENDING), ("cauchy in every stage", ())):
        log(f"long capture, {how} ...")
        fit_module.REDESCENDING = redescending  # () : no warm stage, the fit's loss in every stage
        try:
            rows.append({"stages": how} | robust_one(robot, tr, {}, "cauchy"))
        finally:
            fit_module.REDESCENDING = ("cauchy",)
    print_table([("stages", "stages", ""), *ROBUST_COLUMNS], rows)
    config = {"free": ROBUST_FREE, "lengths_s": [15, 15, 15, 30], "rate_hz": 100.0}
    write_json(out, {**environment(), "config": config, "rows": rows})


def robust_fit(argv) -> int:
    """Glitchy torque trials against the clean ones, robust losses and `l2`; `--long`: `long_capture`."""
    ap = parser("tasks.py robust-fit")
    ap.add_argument("--losses", nargs="+", default=["cauchy", "huber", "l2"], help="the glitchy capture's losses")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--long", action="store_true", help="the long capture: Cauchy from Huber's point or in every stage")
    ap.add_argument("--out", help="result JSON (default results-robust-fit.json; results-robust-fit-long.json)")
    args = ap.parse_args(argv)
    if args.long:
        long_capture(result_path(args, "results-robust-fit-long.json"))
        return 0
    args.out = result_path(args, "results-robust-fit.json")
    robot = other_robot()
    clean = torque_trials(robot, [6.0] * 5, args.seed)
    dirty, bad = glitchy(clean, args.seed)
    log("clean capture, cauchy (compiles) ...")
    first = robust_one(robot, clean, {}, "cauchy")
    log("clean capture, cauchy, compiled ...")
    rows = [{"capture": "clean"} | robust_one(robot, clean, {}, "cauchy")]
    for loss in args.losses:
        log(f"glitchy capture, {loss} ...")
        rows.append({"capture": "glitchy"} | robust_one(robot, dirty, bad, loss))
    log("clean capture, l2 ...")
    l2 = robust_one(robot, clean, {}, "l2")
    rows.append({"capture": "clean"} | l2)
    rob = rows[0]
    # no cost on clean data: the robust fit against least squares, in the latter's standard errors
    ratios = [rob["stderr"][k] / l2["stderr"][k] for k in l2["values"]]
    clean_vs_l2 = {
        "max_value_difference_se": max(abs(rob["values"][k] - l2["values"][k]) / l2["stderr"][k] for k in l2["values"]),
        "stderr_ratio_range": [min(ratios), max(ratios)],
    }
    base = rows[0]["wall_s"]
    head = [("capture", "capture", ""), ("loss", "loss", ""), ("x clean", lambda r: r["wall_s"] / base, ".2f")]
    print_table(head + ROBUST_COLUMNS[:-2] + [("sigma deg", "sigma_rot_deg", ".3f"), *ROBUST_COLUMNS[-2:]], rows)
    print(
        f"clean capture, cauchy against l2: values within {clean_vs_l2['max_value_difference_se']:.3f} SE, standard errors "
        f"x{clean_vs_l2['stderr_ratio_range'][0]:.3f} to x{clean_vs_l2['stderr_ratio_range'][1]:.3f}"
    )
    doc = {
        **environment(),
        "config": {"free": ROBUST_FREE, "trials": 5, "length_s": 6.0, "rate_hz": 100.0, "seed": args.seed},
        "first_fit_with_compilation": first,
        "rows": rows,
        "ratio_glitchy_to_clean": {r["loss"]: r["wall_s"] / base for r in rows[1:] if r["capture"] == "glitchy"},
        "clean_cauchy_against_l2": clean_vs_l2,
    }
    write_json(args.out, doc)
    return 0


# ---------------------------------------------------------------------- planning

PLAN_DEFAULTS = jsphere.PlanSettings()
PLAN_DEFAULT_ITERATIONS = PLAN_DEFAULTS.adam_steps + PLAN_DEFAULTS.lm_steps + 1


#: the request `plan` times end to end, `jsphere plan` against CasADi, each in a new process
PLAN_TO = (0.4, 0.2)
#: the CasADi process: its arguments are this folder and the JSON of the robot, rest attitude and target
CASADI_PLAN = (
    "import json, sys; sys.path.insert(0, sys.argv[1]); import casadi_baseline as cb; a = json.loads(sys.argv[2]); "
    "print(json.dumps(cb.plan_nlp(cb.NumpyRobot(**a['robot']), a['q0'], a['gamma_m'], a['to'])))"
)


def plan_processes(p: jsphere.RobotParams) -> tuple[list[dict], dict]:
    """`jsphere plan --to 0.4 0.2 --no-plots` in a new process on an empty compilation cache, then
    in another on the cache it left, against a new process that builds and solves the same
    transcription with CasADi (`casadi_baseline.plan_nlp`), whose knot torques `simulate` replays
    to measure where it lands. Returns the rows and their ratios."""
    from casadi_baseline import PARAM_NAMES

    from jsphere.model.kinematics import rest_attitude

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["plan", "--to", *map(str, PLAN_TO), "--no-plots", "--out", os.path.join(tmp, "plan.csv")]
        for how in ("new process, empty cache", "new process, cache filled"):
            wall = common.run_cli(argv, os.path.join(tmp, "cache"))
            rec = json.loads(Path(tmp, "plan.json").read_text())
            e, status = rec["errors"], "feasible" if rec["feasible"] else "infeasible"
            row = {"name": f"jsphere plan, {how}", "wall_s": wall, "T_s": rec["duration_s"], "status": status}
            rows.append(row | {"iterations": rec["iterations"]["ipopt"], "miss_mm": 1e3 * e["position_m"]})
            rows[-1]["speed_mm_s"] = 1e3 * e["speed_m_s"]
    arg = {"robot": {k: np.asarray(getattr(p, k)).tolist() for k in PARAM_NAMES}, "to": PLAN_TO}
    arg |= {"q0": np.asarray(jsphere.State.at_rest(p).q).tolist(), "gamma_m": np.asarray(rest_attitude(p)).tolist()}
    text, wall = common.timed_run([sys.executable, "-c", CASADI_PLAN, str(common.HERE), json.dumps(arg)])
    cas = json.loads(text.strip().splitlines()[-1])
    ctrl = jsphere.Torques.from_samples(np.asarray(cas["t"]), np.asarray(cas["K"]), kind="linear")
    tr = jsphere.simulate(p, jsphere.State.at_rest(p), ctrl, cas["T"])
    miss = math.hypot(float(tr.x[-1]) - PLAN_TO[0], float(tr.y[-1]) - PLAN_TO[1])
    speed = float(p.R0) * float(np.linalg.norm(np.cross(tr.Omega[-1], tr.gamma[-1])))
    row = {"name": "CasADi + IPOPT, new process", "wall_s": wall, "T_s": cas["T"], "miss_mm": 1e3 * miss}
    rows.append(row | {"speed_mm_s": 1e3 * speed} | {k: v for k, v in cas.items() if k != "T"})
    ratios = {"wall_fresh_over_casadi": rows[0]["wall_s"] / wall, "wall_cached_over_casadi": rows[1]["wall_s"] / wall}
    return rows, ratios | {"duration_over_casadi": rows[0]["T_s"] / cas["T"]}


def plan(argv) -> int:
    """`jsphere plan` end to end against CasADi's solve of the same transcription (`plan_processes`),
    then the gait planner's search, restarts x targets in one vmapped, compiled call, extrapolated to 256 x 16."""
    from jsphere.planning.problem import _vec_targets, gait_from_vector
    from jsphere.planning.rollout import rollout
    from jsphere.planning.search import _initial_guesses, _search

    ap = parser("tasks.py plan", "results-plan.json")
    ap.add_argument("--restarts", type=int, default=16)
    ap.add_argument("--targets", type=int, default=16, help="targets on a grid over the 2 m x 2 m square")
    ap.add_argument("--adam", type=int, default=PLAN_DEFAULTS.adam_steps, help="Adam steps (default: %(default)s)")
    ap.add_argument("--lm", type=int, default=PLAN_DEFAULTS.lm_steps, help="LM steps (default: %(default)s)")
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    processes, ratios = plan_processes(p)
    cols = [("plan to (0.4, 0.2) m", "name", ""), ("wall [s]", "wall_s", ".1f"), ("T [s]", "T_s", ".4f")]
    cols += [("IPOPT iters", "iterations", "d"), ("miss [mm]", "miss_mm", ".4f"), ("at [mm/s]", "speed_mm_s", ".4f")]
    cols += [("build [s]", "build_s", ".2f"), ("solve [s]", "solve_s", ".2f"), ("status", "status", "")]
    print_table(cols, processes)
    print(", ".join(f"{k} {v:.3f}" for k, v in ratios.items()) + "\n")
    s = jsphere.PlanSettings(adam_steps=args.adam, lm_steps=args.lm)
    lim, obj = jsphere.Limits(), jsphere.Objective()
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), m) for m in (lim, obj))
    k = round(np.sqrt(args.targets))
    xs = np.linspace(-1.0, 1.0, k)
    tg = _vec_targets([(x, y) for x in xs for y in xs][: args.targets])
    B, R = len(tg), args.restarts
    z0 = _initial_guesses(p, tg, R, lim, s, 0)
    compiled, t_compile = timed(lambda: _search.lower(p, jnp.asarray(tg), z0, lim_a, obj_a, s).compile())
    (zf, loss, *_), t_run = timed(lambda: jax.block_until_ready(compiled(p, jnp.asarray(tg), z0, lim_a, obj_a, s)))
    iters = s.adam_steps + s.lm_steps + 1
    per = t_run / (B * R * iters)
    full = 256 * 16 * PLAN_DEFAULT_ITERATIONS * per
    best_loss = np.asarray(jnp.min(loss, axis=1))
    # search-model terminal errors of the best restart per target
    errs = []
    for b in range(B):
        ro = rollout(p, gait_from_vector(jnp.asarray(zf[b]), lim, s), s.n_steps)
        errs.append(float(np.hypot(ro.x[-1] - tg[b, 0], ro.y[-1] - tg[b, 1])))
    rows = [
        ("problems (targets x restarts)", f"{B} x {R} = {B * R}"),
        ("iterations per problem (Adam + LM)", f"{s.adam_steps} + {s.lm_steps + 1}"),
        ("RK4 steps per simulation", f"{s.n_steps}"),
        ("compile [s]", f"{t_compile:.1f}"),
        ("search [s]", f"{t_run:.1f}"),
        ("per problem x iteration [ms]", f"{1e3 * per:.3f}"),
        (f"256 x 16 x {PLAN_DEFAULT_ITERATIONS} default iterations, extrapolated [s]", f"{full:.0f}"),
        ("best restarts: max search-model position error [mm]", f"{1e3 * max(errs):.4f}"),
        ("best restarts: max loss", f"{float(np.max(best_loss)):.3g}"),
    ]
    print_pairs(rows)
    info = {
        **environment(),
        "targets": B,
        "restarts": R,
        "iterations": iters,
        "n_steps": s.n_steps,
        "compile_s": t_compile,
        "search_s": t_run,
        "per_problem_iteration_s": per,
        "extrapolated_256x16_s": full,
        "max_position_error_m": max(errs),
        "best_loss": best_loss.tolist(),
        "processes": processes,
        "ratios": ratios,
    }
    write_json(args.out, info)
    return 0


ROBUST_NAMES = ("r_m[2]", "j", "I[2,2]", "I0")
ROBUST_REL_SD = (0.03, 0.2, 0.1, 0.05)


def robust_plan(argv) -> int:
    """The robust plan against the nominal one, and its vmapped replay against a loop of `simulate`."""
    from jsphere.planning.uncertainty import Uncertainty

    ap = parser("tasks.py robust-plan", "results-robust-plan.json")
    ap.add_argument("--to", nargs=2, type=float, default=(0.6, 0.3))
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--quantile", type=float, default=0.95)
    ap.add_argument("--check-samples", type=int, default=1000)
    ap.add_argument("--loop", type=int, default=3, help="simulate calls timed for the loop baseline")
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    vals = np.array([float(jsphere.get_value(p, n)) for n in ROBUST_NAMES])
    sd = np.abs(vals) * np.array(ROBUST_REL_SD)
    unc = Uncertainty(ROBUST_NAMES, ("normal",) * 4, vals, sd, np.eye(4), "benchmark")
    to, four = tuple(args.to), jsphere.PlanOptions(restarts=4, family="gait")

    nominal, t_nominal = timed(jsphere.plan, p, to, plan_options=four, progress=False, allow_infeasible=True)
    t0 = time.perf_counter()
    robust = jsphere.RobustOptions(
        unc, samples=args.samples, quantile=args.quantile, check_samples=args.check_samples, nominal=nominal
    )
    rp = jsphere.plan(p, to, plan_options=four, robust=robust, progress=False)
    t_robust = time.perf_counter() - t0

    _, fresh = unc.draw(p, args.check_samples, seed=7)
    jsphere.miss_distribution(rp.plan, jax.tree_util.tree_map(lambda v: v[:2], fresh))  # compile
    _, t_vmap = timed(jsphere.miss_distribution, rp.plan, fresh)
    cols = rp.plan.table()
    ctrl = jsphere.WheelSpeeds.from_samples(cols["t"], np.stack([cols[f"chi_dot_{i}"] for i in (1, 2, 3)], 1))
    T = float(cols["t"][-1])
    one = jax.tree_util.tree_map(lambda v: v[0], fresh)
    jsphere.simulate(one, jsphere.State.at_rest(one), ctrl, T, max_steps=65536)  # compile
    t0 = time.perf_counter()
    for k in range(args.loop):
        pk = jax.tree_util.tree_map(lambda v, k=k: v[k], fresh)
        jax.block_until_ready(jsphere.simulate(pk, jsphere.State.at_rest(pk), ctrl, T, max_steps=65536).x)
    t_loop = (time.perf_counter() - t0) / args.loop * args.check_samples

    mc = rp.miss_mc
    rows = [
        ("uncertain parameters", ", ".join(ROBUST_NAMES)),
        ("nominal plan (4 restarts) [s]", f"{t_nominal:.1f}"),
        (f"robust plan ({args.samples} draws, quantile {args.quantile}, 4 starts) [s]", f"{t_robust:.1f}"),
        ("  ratio robust / nominal", f"{t_robust / t_nominal:.2f}"),
        ("duration nominal / robust [s]", f"{nominal.duration:.2f} / {rp.plan.duration:.2f}"),
        ("miss mean nominal / robust [mm]", f"{1e3 * mc['nominal']['mean']:.3f} / {1e3 * mc['robust']['mean']:.3f}"),
        ("miss p95 nominal / robust [mm]", f"{1e3 * mc['nominal']['p95']:.3f} / {1e3 * mc['robust']['p95']:.3f}"),
        (f"replay of {args.check_samples} draws, vmapped RK4 [s]", f"{t_vmap:.2f}"),
        (f"replay of {args.check_samples} draws, simulate loop (extrapolated from {args.loop}) [s]", f"{t_loop:.1f}"),
        ("  ratio loop / vmapped", f"{t_loop / t_vmap:.1f}"),
    ]
    print_pairs(rows)
    info = {
        **environment(),
        "target": list(to),
        "names": list(ROBUST_NAMES),
        "relative_sd": list(ROBUST_REL_SD),
        "samples": args.samples,
        "quantile": args.quantile,
        "check_samples": args.check_samples,
        "nominal_s": t_nominal,
        "robust_s": t_robust,
        "duration_s": {"nominal": nominal.duration, "robust": rp.plan.duration},
        "miss_mc": mc,
        "replay_vmapped_s": t_vmap,
        "replay_loop_extrapolated_s": t_loop,
    }
    write_json(args.out, info)
    return 0


def track(argv) -> int:
    """`jsphere track`'s gains and evaluation on drawn robots against the open-loop wheel-speed replay."""
    from jsphere.planning.tracking.track import default_uncertainty, evaluate, gains

    ap = parser("tasks.py track", "results-track.json")
    ap.add_argument("--to", nargs=2, type=float, default=(0.4, 0.2))
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--restarts", type=int, default=16, help="as `jsphere plan`")
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    pl, t_plan = timed(
        jsphere.plan, p, tuple(args.to), plan_options=jsphere.PlanOptions(restarts=args.restarts, family="gait")
    )
    ts, K = np.asarray(pl.trajectory.ts), np.asarray(pl.trajectory.K)
    keep = np.concatenate([np.diff(ts) > 0, [True]])
    times, weights = {}, jsphere.TrackWeights()
    for run in ("first", "second"):
        fields, times[f"gains_{run}_s"] = timed(
            gains, ts[keep], K[keep], p, rate=args.rate, weights=weights, target=pl.target[:2]
        )
    tracker = jsphere.Tracker(**fields)
    unc = default_uncertainty(p)
    _, drawn = unc.draw(p, args.samples, 0)
    miss_mc, times["evaluation_first_s"] = timed(evaluate, tracker, drawn, seed=0, source=unc.source)
    _, times["evaluation_second_s"] = timed(evaluate, tracker, drawn, seed=1, source=unc.source)
    for run in ("first", "second"):
        ws, times[f"wheel_speed_replay_{run}_s"] = timed(jsphere.miss_distribution, pl, drawn)
    o, c = miss_mc["open_loop"], miss_mc["closed_loop"]
    wheel = [float(np.mean(ws["miss_m"])), *(float(np.percentile(ws[k], 95)) for k in ("miss_m", "speed_m_s"))]
    rows = [
        ("open loop (torques)", o["mean"], o["p95"], o["speed_p95"], o["max_torque_N_m"]),
        ("closed loop", c["mean"], c["p95"], c["speed_p95"], c["max_torque_N_m"]),
        ("open loop (wheel speeds, exact)", *wheel, float("nan")),
    ]
    print(
        f"plan to {tuple(args.to)} m: T = {pl.duration:.3f} s, planned in {t_plan:.1f} s; {args.samples} draws "
        f"({unc.source}); rate {args.rate:g} Hz"
    )
    print(f"{'loop':<34}{'miss mean [mm]':>16}{'p95 [mm]':>10}{'speed p95 [mm/s]':>18}{'max |K| [N m]':>15}")
    for name, m, p95, v, u in rows:
        print(f"{name:<34}{1e3 * m:>16.3f}{1e3 * p95:>10.3f}{1e3 * v:>18.3f}{u:>15.4f}")
    ratio = {"mean": o["mean"] / c["mean"], "p95": o["p95"] / c["p95"]}
    print(f"open / closed loop miss: mean {ratio['mean']:.1f}x, p95 {ratio['p95']:.1f}x")
    for k, v in times.items():
        print(f"  {k:<30}{v:>8.2f} s")
    per_draw = times["evaluation_second_s"] / (2 * args.samples)
    print(f"  one draw, one loop ({len(tracker.ts)} rows + settling): {1e3 * per_draw:.3f} ms")
    out = {
        **environment(),
        "to": list(args.to),
        "samples": args.samples,
        "rate_hz": args.rate,
        "duration_s": pl.duration,
        "plan_s": t_plan,
        "miss_mc": miss_mc,
        "wheel_speed_open_loop": dict(zip(("mean", "p95", "speed_p95"), wheel)),
        "ratio_open_over_closed": ratio,
        "times_s": times,
    }
    write_json(args.out, out)
    return 0


# ---------------------------------------------------------------------- design

DESIGN_FREE = "r_m[2],j,I[2,2]"
#: the "true" robot of the synthetic trials: the design's values times these factors
DESIGN_TRUTH = {"r_m[2]": 1.06, "j": 0.93, "I[2,2]": 1.08}


def _fit_designs(work: Path, trials: int, duration: float, free) -> tuple[dict, dict]:
    """The design's and the baseline's tables as written, their trials on the robot `DESIGN_TRUTH`
    away from the paper's, fitted: `free`'s values and standard errors, and each fit's seconds."""
    from jsphere.controls import Sampled, Torques

    p = truth = jsphere.RobotParams.paper()
    for name, f in DESIGN_TRUTH.items():
        truth = jsphere.set_value(truth, name, jsphere.get_value(p, name) * f)
    noise = {"rate": 100.0, "pos_sd": 1e-3, "rot_sd_deg": 0.5}
    fitted, t_fit = {}, {}
    for which in ("design", "baseline"):
        paths = [work / f"{which}.csv"] if trials == 1 else [work / f"{which}_{k + 1}.csv" for k in range(trials)]
        synthetic = []
        for k, path in enumerate(paths):
            t, u = jsphere.read_inputs_csv(path)[:2]
            u = Torques(Sampled(jnp.asarray(t), jnp.asarray(u), "cubic"))
            name = f"{which}_{k + 1}"
            synthetic.append(jsphere.synthetic_trial(truth, u, duration, **noise, seed=100 + k, name=name))
        fr, t_fit[which] = timed(jsphere.fit, synthetic, p, DESIGN_FREE, progress=False)
        fitted[which] = {
            n: {"value": fr.values[n], "truth": float(jsphere.get_value(truth, n)), "stderr": fr.stderr[n]}
            for n in free
        }
        fitted[which]["status"] = fr.status
    return fitted, t_fit


#: a parameter's standard errors: the design's and the baseline's, predicted and fitted
SE_KEYS = ("se_design_predicted", "se_design_fitted", "se_baseline_predicted", "se_baseline_fitted")


def design(argv) -> int:
    """`jsphere design` end to end, then its trials and the baseline's fitted on a robot 6-8 % away."""
    ap = parser("tasks.py design", "results-design.json")
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--restarts", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="jsphere-design-"))
    out = work / "design.csv"
    cmd = [sys.executable, "-m", "jsphere.cli", "design", "--free", DESIGN_FREE, "--duration", str(args.duration)]
    cmd += f"--kind K --trials {args.trials} --restarts {args.restarts} --steps {args.steps} --seed {args.seed}".split()
    cmd += ["--out", str(out), "--baseline-out", str(work / "baseline.csv"), "--no-cache", "-q"]
    _, t_design = common.timed_run(cmd)
    doc = json.loads(out.with_suffix(".json").read_text())
    fitted, t_fit = _fit_designs(work, args.trials, args.duration, doc["free"])

    rows = [
        ("command", " ".join(["jsphere", *cmd[3:-6]])),
        ("design, end to end (cold) [s]", f"{t_design:.1f}"),
        ("fit of the design's trials [s]", f"{t_fit['design']:.1f}"),
        ("criterion design / baseline", f"{doc['criterion']['design']:.3f} / {doc['criterion']['baseline']:.3f}"),
    ]
    factors = {}
    for n in doc["free"]:
        se = [doc["stderr_predicted"][n], fitted["design"][n]["stderr"]]
        se += [doc["stderr_predicted_baseline"][n], fitted["baseline"][n]["stderr"]]
        pred, fit = se[2] / se[0], se[3] / se[1]
        factors[n] = {"predicted": pred, "fitted": fit} | dict(zip(SE_KEYS, se))
        values = f"{pred:.2f}x predicted, {fit:.2f}x fitted  ({se[0]:.3g} / {se[1]:.3g}, {se[2]:.3g} / {se[3]:.3g})"
        rows.append((f"{n}: SE design pred/fit, baseline pred/fit", values))
    print_pairs(rows)
    kept = ("criterion", "criterion_model", "rms", "baseline_equal_rms", "limits", "limits_baseline")
    info = {
        **environment(),
        "command": cmd[3:],
        "design_end_to_end_s": t_design,
        "fit_s": t_fit,
        **{k: doc[k] for k in kept},
        "truth_factors": DESIGN_TRUTH,
        "factor_baseline_over_design": factors,
        "fitted": fitted,
        "geometric_mean_factor": {
            k: math.exp(sum(math.log(v[k]) for v in factors.values()) / len(factors)) for k in ("predicted", "fitted")
        },
    }
    write_json(args.out, info)
    return 0


# ---------------------------------------------------------------------- animations


def _cpu() -> float:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def animate(argv) -> int:
    """A 10 s clip as MP4 (blitted, and every frame drawn in full: the baseline), GIF and HTML viewer."""
    args = parser("tasks.py animate", "results-animate.json").parse_args(argv)

    from jsphere.plots.animation.scene import Scene, body_from_trajectory
    from jsphere.plots.animation.video import render
    from jsphere.plots.animation.viewer import write_html

    params = jsphere.RobotParams.paper()
    traj = jsphere.simulate_gaits(params, [jsphere.acceleration(), jsphere.braking()])
    run_s = float(traj.ts[-1])
    speed, fps, size = run_s / 10.0, 30.0, (640, 480)
    scene = Scene([body_from_trajectory(traj, label="gaits")], params, title="the paper's straight line")

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        render([scene], Path(tmp) / "warm.gif", fps=2, speed=1.0, size=(160, 120), progress=False)  # imports
        video = lambda p, **kw: render([scene], p, fps=fps, speed=speed, size=size, progress=False, **kw)
        cases = [
            ("mp4", "blitted (jsphere)", video),
            ("mp4", "full redraw (matplotlib's way)", lambda p: video(p, blit=False)),
            ("gif", "blitted (jsphere)", video),
            ("html", "plotly, bundle embedded, 30 fps", lambda p: write_html([scene], p, fps=fps, speed=speed)),
            ("html", "plotly, bundle embedded, 15 fps", lambda p: write_html([scene], p, fps=15.0, speed=speed)),
        ]
        for k, (suffix, how, make) in enumerate(cases):
            path = Path(tmp) / f"clip{k}.{suffix}"
            c0, w0 = _cpu(), time.perf_counter()
            make(path)
            wall, cpu = time.perf_counter() - w0, _cpu() - c0
            rows.append({"output": suffix, "how": how, "wall_s": wall, "cpu_s": cpu, "bytes": path.stat().st_size})
            log(f"  {suffix} {how}: {wall:.1f} s")

    ratio = next(r for r in rows if r["how"].startswith("full"))["wall_s"] / rows[0]["wall_s"]
    frames = int(round(10 * fps))
    print(f"10 s clip at {fps:.0f} fps ({frames} frames, {size[0]} x {size[1]}), load {os.getloadavg()[0]:.2f}")
    cols = [("output", "output", ""), ("how", "how", ""), ("wall [s]", "wall_s", ".1f"), ("CPU [s]", "cpu_s", ".1f")]
    print_table([*cols, ("size [MB]", lambda r: r["bytes"] / 1e6, ".2f")], rows)
    print(f"blitted frames against full redraws (MP4, same run): {ratio:.1f}x faster")
    clip = {"seconds": 10.0, "fps": fps, "frames": frames, "size": list(size), "run_s": run_s}
    doc = {
        **environment(),
        "clip": clip,
        "rows": rows,
        "blit_speedup_mp4": ratio,
        "load_average_end": os.getloadavg()[0],
    }
    write_json(args.out, doc)
    return 0


ONBOARD_FREE = ["r_m[2]", "j", "I[0,0]", "I[1,1]", "I[2,2]", "m0", "I0"]


def onboard_fit(argv) -> int:
    """A fit from onboard sensors, default settings and Tsit5 at rtol 1e-6, against one at rtol 1e-10."""
    from jsphere.capture.onboard import OnboardNoise, synthetic_onboard_trial

    ap = parser("tasks.py onboard-fit", "results-onboard-fit.json")
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--duration", type=float, default=8.0)
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    mount = {"imu_position": (0.02, -0.01, -0.04), "imu_rotation": (math.cos(0.3), 0.0, math.sin(0.3), 0.0)}
    noise = OnboardNoise(0.003, 0.03, (0.01, -0.02, 0.005), (0.1, 0.0, -0.2), counts_per_turn=4096)
    trials = [
        synthetic_onboard_trial(
            p,
            jsphere.random_inputs(p, args.duration, kind="torques", seed=10 + i),
            args.duration,
            mounting=jsphere.Mounting(mount["imu_position"], mount["imu_rotation"]),
            noise=noise,
            seed=i,
            name=f"t{i}",
        )
        for i in range(args.trials)
    ]
    settings = {
        "rtol 1e-10 (baseline)": jsphere.SolverOptions(rtol=1e-10, atol=1e-12),
        "default (Dopri8, rtol 1e-8)": None,
        "Tsit5, rtol 1e-6": jsphere.SolverOptions(solver=diffrax.Tsit5(), rtol=1e-6, atol=1e-8),
    }
    fits = {}
    for label, solver in settings.items():
        options = jsphere.FitOptions(**mount, solver=solver)
        fits[label] = res, elapsed = timed(jsphere.fit, trials, p, ONBOARD_FREE, options=options, progress=False)
        log(f"{label}: {elapsed:.1f} s, {res.status}")
    base = fits["rtol 1e-10 (baseline)"][0]
    rows = []
    for label, (res, elapsed) in fits.items():
        shift = max(abs(res.values[n] - base.values[n]) / base.stderr[n] for n in ONBOARD_FREE)
        error = max(map(abs, errors_se(res, p, ONBOARD_FREE).values()))
        rows.append({"solver": label, "seconds": elapsed, "shift_se": shift, "error_se": error, "status": res.status})
    cols = [("solver", "solver", ""), ("fit [s]", "seconds", ".1f"), ("largest shift [SE]", "shift_se", ".3f")]
    print_table([*cols, ("largest error [SE]", "error_se", ".2f"), ("status", "status", "")], rows)
    config = {"trials": args.trials, "duration_s": args.duration, "free": ONBOARD_FREE, **mount}
    write_json(args.out, {**environment(), "config": config, "rows": rows})
    return 0


COMMANDS = {
    "fit": fit,
    "fit-long": fit_long,
    "robust-fit": robust_fit,
    "plan": plan,
    "robust-plan": robust_plan,
    "track": track,
    "design": design,
    "animate": animate,
    "onboard-fit": onboard_fit,
}

if __name__ == "__main__":
    raise SystemExit(dispatch(COMMANDS, None, __doc__))
