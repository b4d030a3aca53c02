"""Start-up: what a new process pays before its first result, each entry in new processes;
benchmarks/README.md says what each entry measures and records.

    python benchmarks/startup.py [reproduce] [--out benchmarks/results-startup.json]
    python benchmarks/startup.py fit [--cached-runs 2] [--out benchmarks/results-fit-startup.json]
    python benchmarks/startup.py first-result [--quick] [--repeat N] [--xla-defaults] [--tasks TASK ...]

`first-result` runs each task in a child process (`startup.py first-result --child TASK`) that
times its imports, its first call (with JAX's tracing, lowering and XLA time) and a second call.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import common
from common import HERE, ROOT, cli_env, log, write_json

# ---------------------------------------------------------------------- reproduce

CONFIGS = {"default": [], "optimize": ["--optimize"], "no-plots": ["--no-plots"]}


def reproduce_argv(tmp: str, name: str, extra: list[str]) -> list[str]:
    """`jsphere reproduce` of configuration `name` (its options `extra`), writing into `tmp`."""
    return ["reproduce", "--out", os.path.join(tmp, f"out-{name}"), *extra]


def _cache_files(path: str) -> dict:
    files = [f for f in Path(path).rglob("*") if f.is_file()]
    return {"cache_files": len(files), "cache_bytes": sum(f.stat().st_size for f in files)}


def measure(tmp: str, name: str, extra: list[str], cached_runs: int = 3, command: Callable = reproduce_argv) -> dict:
    """A first process of `command(tmp, name, extra)` (its arguments) with an empty cache in
    `tmp`, then `cached_runs` processes reusing it (their median is `second_process_s`)."""
    cache, argv = os.path.join(tmp, f"cache-{name}"), command(tmp, name, extra)
    first = common.run_cli(argv, cache)
    seconds = [common.run_cli(argv, cache) for _ in range(cached_runs)]
    return {
        "args": extra,
        "first_process_s": first,
        "second_process_s": sorted(seconds)[len(seconds) // 2],
        "second_process_runs_s": seconds,
        "cache_bytes": _cache_files(cache)["cache_bytes"],
    }


def reproduce(argv) -> int:
    ap = common.parser("startup.py reproduce", "results-startup.json", description="jsphere reproduce in new processes")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for name, extra in CONFIGS.items():
            runs[name] = r = measure(tmp, name, extra)
            print(f"  {name:<9} first {r['first_process_s']:5.1f} s, second {r['second_process_s']:4.1f} s", flush=True)
        no_cache = common.run_cli(reproduce_argv(tmp, "no-cache", ["--no-cache"]), os.path.join(tmp, "unused"))
    d, b = runs["default"], runs["optimize"]
    res = {
        **common.environment_in_child(),
        "command": "python -m jsphere.cli.app reproduce",
        "runs": runs,
        "no_cache_process_s": no_cache,
        "first_default_over_optimize": d["first_process_s"] / b["first_process_s"],
        "second_default_over_optimize": d["second_process_s"] / b["second_process_s"],
        "targets": {"first_s": 20.0, "second_s": 5.0},
    }
    print(
        f"jsphere reproduce: first process {d['first_process_s']:.1f} s (empty cache), second {d['second_process_s']:.1f} s; "
        f"with --optimize {b['first_process_s']:.1f} / {b['second_process_s']:.1f} s "
        f"(ratios {res['first_default_over_optimize']:.2f} / {res['second_default_over_optimize']:.2f}); "
        f"without cache {no_cache:.1f} s"
    )
    write_json(args.out, res)
    return 0


# ---------------------------------------------------------------------- fit

FIT_FREE = "R_m,j,I[0,0],I[1,1],I[2,2],m0,I0"
FIT_TARGET_SECOND_S = 15.0


def fit_argv(tmp: str, name: str, extra: list[str]) -> list[str]:
    """`jsphere fit` of the trials in `tmp/trials`, its result in `tmp/fit-<name>.json`."""
    out = os.path.join(tmp, f"fit-{name}.json")
    return ["fit", os.path.join(tmp, "trials"), "--free", FIT_FREE, "--out", out, "--no-plots", "--quiet", *extra]


def make_trials(tmp: str) -> None:
    """Five synthetic 6 s torque trials of the truth in `tmp/trials` (`jsphere synth`)."""
    from tasks import truth_params

    truth_params().save(os.path.join(tmp, "truth.toml"))
    synth = ["synth", "--out", os.path.join(tmp, "trials"), "--trials", "5", "--kind", "torques"]
    synth += ["--duration", "6", "--params", os.path.join(tmp, "truth.toml"), "--no-cache", "--quiet"]
    common.run_cli(synth)


def fit(argv) -> int:
    ap = common.parser("startup.py fit", "results-fit-startup.json", description="`jsphere fit` in new processes")
    ap.add_argument("--cached-runs", type=int, default=2, help="processes reusing the cache")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        make_trials(tmp)
        cached = measure(tmp, "cached", [], cached_runs=args.cached_runs, command=fit_argv)
        values = {"cached": json.loads(Path(tmp, "fit-cached.json").read_text())["values"]}
        no_cache = common.run_cli(fit_argv(tmp, "no-cache", ["--no-cache"]), os.path.join(tmp, "unused"))
        values["no_cache"] = json.loads(Path(tmp, "fit-no-cache.json").read_text())["values"]
    same = values["cached"] == values["no_cache"]
    res = {
        **common.environment_in_child(),
        "command": "python -m jsphere.cli.app " + " ".join(fit_argv("TMP", "cached", [])),
        "cached": cached,
        **{k: cached[k] for k in ("first_process_s", "second_process_s")},
        "no_cache_process_s": no_cache,
        "second_over_no_cache": cached["second_process_s"] / no_cache,
        "values": values["cached"],
        "same_values": same,
        "targets": {"second_process_s": FIT_TARGET_SECOND_S},
    }
    print(f"{'jsphere fit, 5 x 6 s torque trials':<36} {'seconds':>8}")
    print(f"{'first process, empty cache':<36} {cached['first_process_s']:8.1f}")
    print(f"{'next processes, cache filled':<36} {cached['second_process_s']:8.1f}")
    print(f"{'a process without cache':<36} {no_cache:8.1f}")
    print(f"next / without cache: {res['second_over_no_cache']:.2f}; the same values in every run: {same}")
    write_json(args.out, res)
    return 0 if same else 1


# ---------------------------------------------------------------------- first result

JSPHERE_TASKS = ("gaits", "simulate", "grad", "jacfwd", "fit", "plan")
DFX_TASKS = ("dfx_solve", "dfx_grad", "dfx_jacfwd")
RATIOS = {"gaits": "dfx_solve", "simulate": "dfx_solve", "grad": "dfx_grad", "jacfwd": "dfx_jacfwd"}
QUICK_TASKS = ("gaits", "grad", "dfx_solve", "dfx_grad")
#: the environment of the comparison runs with XLA's default options (`--xla-defaults`)
XLA_DEFAULTS_ENV = {"JSPHERE_XLA_DEFAULTS": "1"}
#: targets: first simulate_gaits and first gradient at most this many times the baseline's
TARGET_RATIO = 2.5
#: target: a second process's first gradient with the cache on, and the quickstart cold [s]
TARGET_CACHED_GRAD_S, TARGET_QUICKSTART_S = 3.0, 15.0


def _enable_cache(cache_dir: str, jsphere=None) -> str:
    """Switch on a persistent compilation cache in `cache_dir`; returns how."""
    if jsphere is not None:
        jsphere.enable_compilation_cache(cache_dir)
        return "jsphere.enable_compilation_cache"
    import jax

    jax.config.update("jax_compilation_cache_dir", cache_dir)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # -1: no size threshold
    return "jax.config"


def _timed(f, *args):
    import jax

    t, c = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(f(*args))
    return out, time.perf_counter() - t, time.process_time() - c


#: JAX's duration events of a program's way to the device, by the name kept in the JSON
_PHASE_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
}


def _phases(jax) -> dict:
    """Totals, from now on, of the time JAX spends tracing, lowering and compiling programs
    (its monitoring events; nested traces overlap, so `trace_s` may exceed the wall time),
    and the number of programs compiled."""
    totals = {"trace_s": 0.0, "lower_s": 0.0, "compile_s": 0.0, "programs": 0}

    def listen(event, duration, **_):
        key = _PHASE_EVENTS.get(event)
        if key is not None:
            totals[key] += float(duration)
            totals["programs"] += key == "compile_s"

    jax.monitoring.register_event_duration_secs_listener(listen)
    return totals


def _baseline_problem():
    """A 13-state ODE of about the cost of jsphere's gait field: a quaternion, two angular
    velocities whose rates come from a 6x6 linear system with a state-dependent matrix,
    a planar position and one more angle; forcing `theta sin^2(pi t)` through trigonometric
    terms. Returns `solve(theta, ts, adjoint=None)`, the states at `ts`."""
    import diffrax as dfx
    import jax.numpy as jnp

    A0 = jnp.array([[2.0, 0.3, 0.1], [0.3, 1.5, 0.2], [0.1, 0.2, 1.8]])
    C = jnp.array([[0.2, 0.05, 0.0], [0.0, 0.15, 0.05], [0.05, 0.0, 0.25]])

    def field(t, y, theta):
        q, w, W, _xy, phi = y[0:4], y[4:7], y[7:10], y[10:12], y[12]
        g = jnp.stack(
            [2 * (q[1] * q[3] - q[0] * q[2]), 2 * (q[2] * q[3] + q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2)]
        )
        cp, sp = jnp.cos(phi), jnp.sin(phi)
        B = C * (1.0 + 0.1 * cp) + 0.05 * jnp.outer(g, g)
        M = jnp.block([[A0 + 0.1 * jnp.outer(g, g), B], [B.T, A0.T + 0.2 * jnp.eye(3) * (1.0 + 0.05 * sp)]])
        s = theta * jnp.sin(jnp.pi * t) ** 2
        force = s * jnp.stack([jnp.cos(2.0 * t), jnp.sin(3.0 * t), jnp.cos(t) * sp])
        rhs = jnp.concatenate(
            [force - jnp.cross(w, A0 @ w) - 0.1 * w, -jnp.cross(W, A0 @ W) + 0.3 * jnp.cross(g, W) - 0.05 * W]
        )
        acc = jnp.linalg.solve(M, rhs)
        qdot = 0.5 * jnp.concatenate([-(q[1:] @ w)[None], q[0] * w + jnp.cross(q[1:], w)])  # q (x) (0, w)
        xydot = 0.15 * jnp.stack([W[1] * cp + W[0] * sp, -W[0] * cp + W[1] * sp])
        return jnp.concatenate([qdot, acc, xydot, (w[2] - W[2])[None]])

    y0 = jnp.zeros(13).at[0].set(1.0)

    def solve(theta, ts, adjoint=None):
        kw = dict(stepsize_controller=dfx.PIDController(rtol=1e-10, atol=1e-12), max_steps=16384)
        kw |= dict(saveat=dfx.SaveAt(ts=ts), adjoint=adjoint or dfx.RecursiveCheckpointAdjoint())
        return dfx.diffeqsolve(dfx.ODETerm(field), dfx.Dopri8(), 0.0, 4.0, None, y0, theta, **kw).ys

    return solve


def _task(task: str, cache_dir: str | None) -> tuple[dict, Callable, contextlib.AbstractContextManager]:
    """A child's imports (timed: `import_s`), its compilation cache where asked, and the call of
    `task`: `(record, f, context)`, the first call made in `context`. The `dfx_` tasks solve the
    baseline problem (`_baseline_problem`) with diffrax alone, the others call jsphere."""
    baseline = task.startswith("dfx_")
    t = time.perf_counter()
    import diffrax as dfx
    import jax
    import jax.numpy as jnp
    import numpy as np

    if not baseline:
        import jsphere
    jax.config.update("jax_enable_x64", True)  # float64 in every task
    rec = {"import_s": time.perf_counter() - t}
    if cache_dir:
        rec["cache"] = _enable_cache(cache_dir, None if baseline else jsphere)
    kind = task.removeprefix("dfx_")
    adjoint = dfx.ForwardMode() if kind == "jacfwd" else None
    if baseline:
        solve = _baseline_problem()
        stop = lambda theta: solve(theta, jnp.array([4.0]), adjoint)[-1, 10]
    else:
        p = jsphere.RobotParams.paper()

    if task == "dfx_solve":
        f = lambda: solve(jnp.asarray(0.1), jnp.linspace(0.0, 4.0, 5))[:, 10]
    elif task == "gaits":
        f = lambda: jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.braking()]).x
    elif task == "simulate":
        ts = np.concatenate([np.linspace(0.0, 2.0, 201), np.linspace(2.0, 4.0, 201)])
        sign = np.where(np.arange(ts.size) < 201, 1.0, -1.0)
        K = 0.02 * (sign * np.sin(np.pi * ts) ** 2)[:, None] * np.array([1.0, -0.5, -0.5])
        state0 = jsphere.State.at_rest(p)
        f = lambda: jsphere.simulate(p, state0, jsphere.Torques.from_samples(ts, K), 4.0, ts=ts).x
    elif task == "fit":
        ts = np.linspace(0.0, 3.0, 301)
        K = 0.02 * (np.sin(np.pi * ts / 3.0) ** 2 * np.sin(2.0 * ts))[:, None] * np.array([1.0, -0.5, -0.5])
        truth = p.replace(R_m=1.02 * float(p.R_m))
        fit_options = jsphere.FitOptions(n_starts=1, adam_steps=0, max_iter=1)
        trial = jsphere.synthetic_trial(truth, jsphere.Torques.from_samples(ts, K), 3.0, rate=50.0, seed=1)
        f = lambda: np.asarray(jsphere.fit([trial], p, "R_m,j", options=fit_options, progress=False).params.R_m)
    elif task == "plan":
        kw = dict(settings=jsphere.PlanSettings(adam_steps=1, lm_steps=1), plan_options=jsphere.PlanOptions(restarts=2))
        f = lambda: np.asarray(jsphere.plan(p, (0.3, 0.1), **kw, allow_infeasible=True, progress=False).trajectory.x)
    elif not baseline:  # grad, jacfwd

        def stop(theta_max):
            gaits = [jsphere.acceleration(theta_max=theta_max), jsphere.braking(theta_max=theta_max)]
            return jsphere.simulate_gaits(p, gaits, ts=jnp.array([4.0]), adjoint=adjoint).x[-1]

    if kind in ("grad", "jacfwd"):
        d = jax.grad(stop) if kind == "grad" else jax.jacfwd(stop)
        f = lambda: d(0.1)
    if baseline:
        return rec, f, contextlib.nullcontext()
    from jsphere._runtime.compilation_cache import callbacks_as_nan

    # equinox's checks traced without host callbacks, so that JAX can write the solves to its cache
    return rec, f, callbacks_as_nan() if cache_dir else contextlib.nullcontext()


def child(task: str, cache_dir: str | None) -> None:
    """The record of a new process's task (`first-result --child`): its imports, its first
    call with JAX's phases of it, and its second call; printed as JSON."""
    import jax
    import numpy as np

    rec, f, context = _task(task, cache_dir)
    phases = _phases(jax)
    with context:
        out, rec["first_s"], rec["first_cpu_s"] = _timed(f)
    rec["phases"] = dict(phases)
    _, rec["second_s"], _ = _timed(f)
    rec["value"] = float(np.ravel(np.asarray(out))[-1])
    print(json.dumps(rec), flush=True)


def first_result_child(task: str, cache_dir: str | None = None, extra_env: dict | None = None) -> dict:
    argv = ["first-result", "--child", task] + (["--cache-dir", cache_dir] if cache_dir else [])
    return common.run_child("startup.py", argv, {**cli_env(), **(extra_env or {})})


def run_quickstart() -> dict:
    load = os.getloadavg()[0]
    _, wall = common.timed_run([sys.executable, str(ROOT / "examples" / "quickstart.py")], quiet=True)
    return {"wall_s": wall, "loadavg_1min_before": load}


def run_cached(task: str) -> dict:
    """The task in a process with an empty cache, then in a second process with that cache."""
    with tempfile.TemporaryDirectory(prefix="first-result-cache-") as cache:
        first = first_result_child(task, cache)
        files = _cache_files(cache)
        second = first_result_child(task, cache)
    return {**second, **files, "filling_process": first}


def _median(runs: list[dict]) -> dict:
    """Per numeric key, the median over the processes; the runs themselves are kept."""
    keys = [k for k, v in runs[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    out = {k: statistics.median(r[k] for r in runs) for k in keys}
    out.update({k: v for k, v in runs[0].items() if isinstance(v, str)})
    if "phases" in runs[0]:
        out["phases"] = {k: statistics.median(r["phases"][k] for r in runs) for k in runs[0]["phases"]}
    out["runs"] = runs
    return out


def _ratios(res: dict, key: str = "first_s") -> dict:
    return {f"{a}/{b}": res[a][key] / res[b][key] for a, b in RATIOS.items() if a in res and b in res}


def _first_result_runs(tasks, args) -> tuple[dict, dict, dict | None, dict]:
    """Each task cold (and with XLA's defaults where asked), the quickstart, each task cached:
    the medians over `args.repeat` processes."""
    cold, defaults, cached, quickstart = {}, {}, {}, None
    for task in tasks:
        cold[task] = r = _median([first_result_child(task) for _ in range(args.repeat)])
        log(
            f"  cold   {task:<11} import {r['import_s']:4.1f} s, first {r['first_s']:5.1f} s, "
            f"second {r['second_s']:6.3f} s, process {r['wall_s']:5.1f} s"
        )
        if args.xla_defaults and not task.startswith("dfx_"):
            runs = [first_result_child(task, extra_env=XLA_DEFAULTS_ENV) for _ in range(args.repeat)]
            defaults[task] = r = _median(runs)
            log(f"  cold   {task:<11} with XLA's defaults: first {r['first_s']:5.1f} s, second {r['second_s']:6.3f} s")
    if not args.quick and not args.tasks:
        quickstart = _median([run_quickstart() for _ in range(args.repeat)])
        log(f"  cold   quickstart  process {quickstart['wall_s']:5.1f} s")
    for task in () if args.no_cache else tasks:
        cached[task] = r = _median([run_cached(task) for _ in range(args.repeat)])
        log(
            f"  cached {task:<11} import {r['import_s']:4.1f} s, first {r['first_s']:5.1f} s, "
            f"process {r['wall_s']:5.1f} s, {r['cache_files']} cache files"
        )
    return cold, defaults, quickstart, cached


def _first_result_tables(tasks, cold, cached, quickstart, ratios) -> None:
    rows = [
        {"task": t, "ratio": ratios["cold"].get(f"{t}/{RATIOS.get(t)}")}
        | cold[t]
        | {f"cached_{k}": v for k, v in cached.get(t, {}).items()}
        | {"cached_ratio": ratios["cached"].get(f"{t}/{RATIOS.get(t)}")}
        for t in tasks
    ] + ([{"task": "quickstart", "wall_s": quickstart["wall_s"]}] if quickstart else [])
    cols = [("task", "task", ""), ("import", "import_s", ".2f"), ("first", "first_s", ".2f")]
    cols += [("cpu", "first_cpu_s", ".2f"), ("second", "second_s", ".3f"), ("process", "wall_s", ".2f")]
    cols += [("ratio", "ratio", ".2f"), ("cached first", "cached_first_s", ".2f")]
    cols += [("process", "cached_wall_s", ".2f"), ("ratio", "cached_ratio", ".2f")]
    print("", *common.table(cols, rows), "", sep="\n")
    cols = [("cold, first call", "task", ""), ("trace", "trace_s", ".2f"), ("lower", "lower_s", ".2f")]
    cols += [("compile", "compile_s", ".2f"), ("programs", "programs", ".0f")]
    common.print_table(cols, [{"task": t} | cold[t]["phases"] for t in tasks if cold[t].get("phases")])
    cpu = ", ".join(f"{k} {v:.2f}" for k, v in ratios["cold_cpu"].items())
    print(f"ratio: first_s over the baseline's (cpu: {cpu})")
    for t, r in ratios["options_over_xla_defaults"].items():
        print(
            f"{t}: jsphere's compiler options over XLA's defaults: first {r['first_s']:.2f}x "
            f"(cpu {r['first_cpu_s']:.2f}x), second call {r['second_s']:.2f}x"
        )
    print(
        f"targets: first gaits / grad at most {TARGET_RATIO}x the baseline; cached first grad <= {TARGET_CACHED_GRAD_S} s; "
        f"quickstart cold < {TARGET_QUICKSTART_S} s"
    )


def first_result(argv) -> int:
    ap = argparse.ArgumentParser(prog="startup.py first-result", description="a new process's first calls")
    ap.add_argument("--repeat", type=int, default=1, help="processes per entry (the median is reported)")
    ap.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK_TASKS)}; no quickstart")
    ap.add_argument("--no-cache", action="store_true", help="skip the cached part")
    ap.add_argument("--tasks", nargs="+", choices=JSPHERE_TASKS + DFX_TASKS, help="only these tasks; no quickstart")
    xla_help = "also the jsphere tasks cold with XLA's default options (JSPHERE_XLA_DEFAULTS=1), alternating"
    ap.add_argument("--xla-defaults", action="store_true", help=xla_help)
    out_help = "JSON record (default results-first-result.json; with --tasks or --quick only where --out is given)"
    ap.add_argument("--out", type=Path, help=out_help)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--cache-dir", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.cache_dir)
        return 0

    meta = common.environment_in_child()
    tasks = tuple(args.tasks) if args.tasks else QUICK_TASKS if args.quick else JSPHERE_TASKS + DFX_TASKS
    cold, defaults, quickstart, cached = _first_result_runs(tasks, args)
    ratios = {
        "cold": _ratios(cold),
        "cold_cpu": _ratios(cold, "first_cpu_s"),
        "cached": _ratios(cached) if cached else {},
        "options_over_xla_defaults": {
            t: {k: cold[t][k] / defaults[t][k] for k in ("first_s", "first_cpu_s", "second_s")} for t in defaults
        },
    }
    doc = {
        **meta,
        "config": {
            "repeat": args.repeat,
            "quick": args.quick,
            "tasks": list(tasks),
            "baseline": "13-state field, 6x6 jnp.linalg.solve, Dopri8, PIDController(1e-10, 1e-12), t in [0, 4]",
        },
        "cold": cold,
        "cold_xla_defaults": defaults,
        "cached_second_process": cached,
        "quickstart_cold": quickstart,
        "ratios": ratios,
        "targets": {
            "first_over_baseline_max": TARGET_RATIO,
            "cached_grad_first_s_max": TARGET_CACHED_GRAD_S,
            "quickstart_cold_s_max": TARGET_QUICKSTART_S,
        },
    }
    _first_result_tables(tasks, cold, cached, quickstart, ratios)
    out = args.out or (None if args.tasks or args.quick else HERE / "results-first-result.json")
    if out is None:  # the record of the full run stays whole
        print("not written: a run of some tasks writes its record only to --out")
    else:
        write_json(out, doc)
    return 0


COMMANDS = {"reproduce": reproduce, "fit": fit, "first-result": first_result}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0].startswith("--") and argv[0] not in ("-h", "--help"):
        argv = ["reproduce", *argv]
    return common.dispatch(COMMANDS, argv, __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
