"""Throughput of problem 1 (and problems 2, 3) against scipy's DOP853 and CasADi, and start-up,
in one run; benchmarks/README.md defines the problems and every column and JSON field.

    python benchmarks/run.py [--quick] [--out benchmarks/results.json]
    python benchmarks/run.py --device gpu --batches 1024,100000,1000000 --problems 1,3 --no-casadi --no-startup
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import common  # this checkout's jsphere first on the path
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from casadi_baseline import PHASES, T1, NumpyRobot, casadi_rows, initial_state
from common import environment, finish, log, public, result_path, source_digest, table, time_call, write_json
from scipy.integrate import solve_ivp
from startup import measure as startup_measure

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

RTOL, ATOL = 1e-8, 1e-10
ACCURACY_TOL = 1e-6  # m, scipy vs jsphere final x, y
GRAD_FD_TOL = 1e-3  # relative, jax.grad vs central finite differences
#: the batch that problem 1 also runs on one device when it is split over several
ONE_DEVICE_BATCH = 1024


def amplitudes(z: np.ndarray) -> np.ndarray:
    return 0.05 * (1.0 + 0.1 * z)


def rate_row(r: dict, B: int, steps, **extra) -> dict:
    """A table row: timing of `B` trials, their solver steps, and `extra` fields."""
    steps = np.asarray(steps)
    log(f"      {B / r['median_s']:.1f} trials/s, compile {r['compile_s']:.1f} s")
    row = {"batch": B, "trials_per_s": B / r["median_s"]}
    return public(r) | row | {"steps_mean": float(steps.mean()), "steps_max": int(steps.max())} | extra


def problem1(p, rtol=RTOL, atol=ATOL, solver=None):
    """Problem 1 through the public API, exactly as a user writes it: `vmap` over the
    amplitude rows (jit it)."""
    options = jsphere.SolverOptions(rtol=rtol, atol=atol, solver=solver)
    return jax.vmap(
        lambda a: jsphere.simulate(
            p,
            jsphere.State.at_rest(p),
            jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + jnp.asarray(PHASES))),
            T1,
            options=options,
        )
    )


def final_xy(tr) -> np.ndarray:
    """The final `(x, y)` of a batch of trajectories, `(B, 2)`."""
    return np.stack([np.asarray(tr.x[:, -1]), np.asarray(tr.y[:, -1])], -1)


def problem1_jsphere(p, Z, batches, repeats):
    f = jax.jit(problem1(p))
    rows, finals = [], {}
    for B in batches:
        A = jnp.asarray(amplitudes(Z[:B]))
        runs = [split(A)]
        if B == ONE_DEVICE_BATCH and runs[0][1] > 1:  # the same batch on one device, in the same run
            runs.append((A, 1))
        for x, k in runs:
            log(f"[P1] jsphere batch {B} on {k} device(s) ...")
            r = time_call(f, x, repeats=repeats)
            tr = r["_out"]
            finals.setdefault(B, final_xy(tr))
            ok = bool(np.all(np.asarray(tr.ok)))
            rows.append(rate_row(r, B, tr.num_steps, devices=k, all_ok=ok, **device_memory()))
    return rows, finals


def split(x):
    """`(x, k)`: `x` split along its trial axis over the `k` devices of the platform it runs on
    (`jsphere.shard_trials`), or on the one device when its length is not a multiple of them."""
    devs = jax.devices(common.default_device().platform)
    if len(devs) == 1 or x.shape[0] % len(devs):
        return x, 1
    return jsphere.shard_trials(x, devs), len(devs)


def device_memory() -> dict:
    """The device's peak memory in use so far in this process (bytes), where the backend reports
    it (GPUs do, the CPU backend does not). Batches run in increasing size, so the peak read after
    a batch is that batch's."""
    stats = common.default_device().memory_stats() or {}
    return {"device_peak_bytes": stats.get("peak_bytes_in_use"), "device_bytes_limit": stats.get("bytes_limit")}


def scipy_trial(model, q0, a, rtol=RTOL, atol=ATOL):
    K = lambda t: a * np.sin(np.pi * t + PHASES)
    sol = solve_ivp(model.rhs, (0.0, T1), initial_state(q0), method="DOP853", rtol=rtol, atol=atol, args=(K,))
    if sol.status != 0:
        raise RuntimeError(f"solve_ivp failed: {sol.message}")
    return sol


def scipy_batch(model, q0, A, repeats, rtol=RTOL, atol=ATOL):
    """`repeats` serial runs of `scipy_trial` over the amplitude rows `A`: the row of their
    timings and solver steps, and the final `(x, y)` of the last run."""
    runs = [common.timed(lambda: [scipy_trial(model, q0, a, rtol, atol) for a in A]) for _ in range(repeats)]
    sols, times = runs[-1][0], [t for _, t in runs]
    med = statistics.median(times)
    row = {"repeats": repeats, "times_s": times, "median_s": med, "s_per_trial": med / len(A)}
    row |= {"trials_per_s": len(A) / med, "steps_mean": float(np.mean([len(s.t) - 1 for s in sols]))}
    return row | {"nfev_mean": float(np.mean([s.nfev for s in sols]))}, np.array([s.y[10:12, -1] for s in sols])


def problem1_scipy(p, Z, n_trials, repeats):
    model = NumpyRobot.from_params(p)
    q0 = np.asarray(jsphere.State.at_rest(p).q)  # the initial condition, as data
    A = amplitudes(Z[:n_trials])
    log(f"[P1] scipy DOP853, {n_trials} trials x {repeats} repeats ...")
    scipy_trial(model, q0, A[0])  # warm-up (imports, caches)
    row, finals = scipy_batch(model, q0, A, repeats)
    log(f"      {row['trials_per_s']:.2f} trials/s")
    return {"trials": n_trials} | row, finals, model, q0


def problem1_checks(model, q0, Z, scipy_finals, js_finals):
    """Accuracy: scipy vs jsphere; both vs a tight DOP853 reference on trial 0; vmap consistency;
    energy balance of the numpy model (an independent check of r1, r2 of (3.4)). Returns the
    checks and the reference's final `(x, y)` of trial 0."""
    n = scipy_finals.shape[0]
    B_ref = min(b for b in js_finals if b >= n) if any(b >= n for b in js_finals) else max(js_finals)
    n = min(n, B_ref)
    diff = np.abs(scipy_finals[:n] - js_finals[B_ref][:n])
    out = {
        "compared_trials": n,
        "jsphere_batch_used": B_ref,
        "max_abs_diff_xy_m": float(diff.max()),
        "tolerance_m": ACCURACY_TOL,
        "pass": bool(diff.max() < ACCURACY_TOL),
    }
    a0 = amplitudes(Z[0])
    ref = scipy_trial(model, q0, a0, rtol=1e-13, atol=1e-14).y[10:12, -1]
    out["trial0_reference"] = "DOP853 rtol 1e-13 atol 1e-14 on the numpy model"
    out["trial0_jsphere_err_m"] = float(np.abs(js_finals[B_ref][0] - ref).max())
    out["trial0_scipy_err_m"] = float(np.abs(scipy_finals[0] - ref).max())
    if 1 in js_finals:
        out["batch1_vs_batched_trial0_m"] = float(np.abs(js_finals[1][0] - js_finals[B_ref][0]).max())
    # energy balance: E(T) - E(0) = int_0^T sum_i K_i chi_dot_i dt
    K = lambda t: a0 * np.sin(np.pi * t + PHASES)
    rhs = lambda t, y: np.concatenate([model.rhs(t, y[:12], K), [model.power(y[:12], K(t))]])
    sol = solve_ivp(rhs, (0.0, T1), np.concatenate([initial_state(q0), [0.0]]), method="DOP853", rtol=1e-12, atol=1e-13)
    E0, E1, W = model.energy(sol.y[:12, 0]), model.energy(sol.y[:12, -1]), sol.y[12, -1]
    out |= {"energy_balance_residual_J": float(E1 - E0 - W), "energy_work_J": float(W)}
    return out, ref


def problem1_casadi(model, q0, Z, B, repeats, sc_row, ref):
    """CasADi baselines (`casadi_baseline.py`): compiled RK4 and CVODES, mapped over threads; their
    trial 0 error against `ref`. Skipped with a note in the table when CasADi is not installed."""
    log(f"[P1] CasADi baselines, batch {B} ...")
    try:
        rows, finals = casadi_rows(model, q0, amplitudes(Z[:B]), threads=os.cpu_count() or 2, repeats=repeats)
    except Exception as e:  # noqa: BLE001  (no CasADi, no C compiler, a CasADi without cvodes: report it)
        return [{"name": "CasADi", "error": f"{type(e).__name__}: {e}"}]
    for r, key in zip(rows, ("rk4", "cvodes")):
        r["ratio_vs_scipy"] = r["trials_per_s"] / sc_row["trials_per_s"]
        r["trial0_err_m"] = float(np.abs(finals[key][0] - ref).max())
        log(f"      {r['name']}: {r['trials_per_s']:.1f} trials/s, trial 0 error {r['trial0_err_m']:.1e} m")
    return rows


def problem2(p, batches, repeats):
    def one(th):
        tr = jsphere.simulate_gaits(
            p, [jsphere.acceleration(theta_max=th), jsphere.braking(theta_max=th)], ts=jnp.array([0.0, 4.0])
        )
        return tr.x[-1], tr.num_steps

    f = jax.jit(jax.vmap(one))
    TH = np.random.default_rng(1).uniform(0.05, 0.15, max(batches, default=0))
    rows = []
    for B in batches:
        th, k = split(jnp.asarray(TH[:B]))
        log(f"[P2] gaits batch {B} on {k} device(s) ...")
        try:
            r = time_call(f, th, repeats=repeats)
        except Exception as e:  # noqa: BLE001  (report, don't hide: e.g. vmap over theta_max failing)
            rows.append({"batch": B, "error": f"{type(e).__name__}: {e}"})
            log(f"      FAILED: {type(e).__name__}: {e}")
            continue
        x, steps = (np.asarray(v) for v in r["_out"])
        rows.append(rate_row(r, B, steps, devices=k, x_final_first=float(x[0]), theta_max_first=float(TH[0])))
    return rows


GRAD_NAMES = ["r_m[2] (= -R_m)", "j", "I[0,0]", "I[1,1]", "I[2,2]", "m0", "I0"]


def problem3(p0, Z, batches, repeats):
    def with_theta(theta):
        I = p0.I.at[jnp.diag_indices(3)].set(theta[2:5])
        return eqx.tree_at(
            lambda q: (q.r_m, q.j, q.I, q.m0, q.I0), p0, (p0.r_m.at[2].set(theta[0]), theta[1], I, theta[5], theta[6])
        )

    def loss(theta, A):
        tr = problem1(with_theta(theta))(A)
        return jnp.sum(tr.x[:, -1] ** 2 + tr.y[:, -1] ** 2)

    theta0 = jnp.stack([p0.r_m[2], p0.j, p0.I[0, 0], p0.I[1, 1], p0.I[2, 2], p0.m0, p0.I0])
    fwd, grad = jax.jit(loss), jax.jit(jax.grad(loss))
    rows, fd = [], None
    for B in batches:
        A, k = split(jnp.asarray(amplitudes(Z[:B])))
        log(f"[P3] forward batch {B} on {k} device(s) ...")
        rf = time_call(fwd, theta0, A, repeats=repeats)
        log(f"[P3] grad batch {B} ...")
        rg = time_call(grad, theta0, A, repeats=repeats)
        g = np.asarray(rg["_out"])
        rows.append(
            {
                "batch": B,
                "devices": k,
                "forward": public(rf),
                "grad": public(rg),
                "grad_over_forward": rg["median_s"] / rf["median_s"],
                "loss": float(rf["_out"]),
                "gradient": dict(zip(GRAD_NAMES, g.tolist())),
            }
        )
        log(f"      grad/forward = {rg['median_s'] / rf['median_s']:.2f}, grad compile {rg['compile_s']:.1f} s")
        if fd is None:  # central differences with the forward already compiled for this batch
            rel = []
            for k in range(theta0.shape[0]):
                h = 1e-5 * abs(float(theta0[k]))
                e = jnp.zeros_like(theta0).at[k].set(h)
                d = (float(fwd(theta0 + e, A)) - float(fwd(theta0 - e, A))) / (2 * h)
                rel.append(abs(d - g[k]) / max(abs(d), 1e-300))
            fd = {
                "batch": B,
                "step": "1e-5 relative, central",
                "max_rel_diff": float(max(rel)),
                "rel_diff": dict(zip(GRAD_NAMES, rel)),
                "tolerance": GRAD_FD_TOL,
                "pass": bool(max(rel) < GRAD_FD_TOL),
            }
    return rows, fd


# ------------------------------------------------------------------------ report


def fmt_table(res) -> str:
    sc = res["problem1"]["scipy"]
    rows = [{"problem": "P1 torques, jsphere jit+vmap"} | r for r in res["problem1"]["jsphere"]]
    rows.append({"problem": "P1 torques, scipy DOP853 (serial)", "batch": sc["trials"]} | sc | {"ratio_vs_scipy": 1.0})
    for r in res["problem1"].get("casadi", []):
        rows.append(
            {"problem": r["name"][:33], "devices": f"{r.get('threads', '-')} thr", "compile_s": r.get("build_s")} | r
        )
    rows += [{"problem": "P2 gaits, jsphere jit+vmap"} | r for r in res["problem2"]]
    steps = lambda r: f"{r['steps_mean']:.0f}/{r['steps_max']}" if "steps_max" in r else None
    cols = [("problem", "problem", ""), ("batch", "batch", ""), ("devices", "devices", "")]
    cols += [("trials/s", "trials_per_s", ".1f"), ("median s", "median_s", ".4f"), ("compile s", "compile_s", ".2f")]
    cols += [("reps", "repeats", ""), ("steps mean/max", steps, ""), ("vs scipy", "ratio_vs_scipy", ".1f")]
    L = table(cols, [r for r in rows if "error" not in r])
    L += [f"{r['problem']}: {r['error'][:70]}" for r in rows if "error" in r]
    if mem := [r for r in res["problem1"]["jsphere"] if r.get("device_peak_bytes")]:
        L.append(
            "  device memory, peak in use after the batch: "
            + ", ".join(f"{r['batch']}: {r['device_peak_bytes'] / 2**30:.2f} GiB" for r in mem)
        )
    p3 = [("P3 gradient (7 params)", lambda r: "jax.grad of sum(x^2 + y^2)", ""), ("batch", "batch", "")]
    p3 += [("devices", "devices", ""), ("grad s", lambda r: r["grad"]["median_s"], ".4f")]
    p3 += [("forward s", lambda r: r["forward"]["median_s"], ".4f"), ("grad/fwd", "grad_over_forward", ".2f")]
    L += ["", *table([*p3, ("grad compile s", lambda r: r["grad"]["compile_s"], ".2f")], res["problem3"]["rows"]), ""]
    c = res["problem1"]["checks"]
    L.append(
        f"accuracy P1: max |scipy - jsphere| final (x, y) over {c['compared_trials']} trials = {c['max_abs_diff_xy_m']:.2e} m "
        f"(< {c['tolerance_m']:.0e}: {'PASS' if c['pass'] else 'FAIL'})"
    )
    L.append(
        f"  trial 0 vs tight reference: jsphere {c['trial0_jsphere_err_m']:.1e} m, scipy {c['trial0_scipy_err_m']:.1e} m; "
        f"energy balance residual {c['energy_balance_residual_J']:.1e} J"
        + (f"; batch 1 vs batched {c['batch1_vs_batched_trial0_m']:.1e} m" if "batch1_vs_batched_trial0_m" in c else "")
    )
    if cas := [r for r in res["problem1"].get("casadi", []) if "trial0_err_m" in r]:
        L.append(
            "  CasADi trial 0 vs the same reference: "
            + ", ".join(f"{r['name'].split(',')[0]} {r['trial0_err_m']:.1e} m" for r in cas)
        )
    if fd := res["problem3"]["fd_check"]:
        L.append(
            f"gradient P3 vs central differences (batch {fd['batch']}): max rel diff {fd['max_rel_diff']:.1e} "
            f"(< {fd['tolerance']:.0e}: {'PASS' if fd['pass'] else 'FAIL'})"
        )
    if su := res.get("startup"):
        L.append(
            f"start-up, `jsphere reproduce` in new processes (figures included): first {su['first_process_s']:.1f} s "
            f"(empty cache), second {su['second_process_s']:.1f} s (median of {len(su['second_process_runs_s'])})"
        )
    return "\n".join(L)


def parse(argv):
    ap = common.parser("run.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller run (about 2 minutes on 2 CPU cores)")
    ap.add_argument("--out", type=Path, help="JSON output (default results.json; results-quick.json with --quick)")
    ap.add_argument("--no-casadi", action="store_true", help="skip the CasADi baselines (run when CasADi is installed)")
    ap.add_argument("--no-startup", action="store_true", help="skip the start-up measurement (startup.py reproduce)")
    ap.add_argument("--device", help="the JAX platform to run on (cpu, gpu, tpu; default JAX's default backend)")
    ap.add_argument("--batches", help="problem 1's batch sizes, comma separated (default 1,64,1024[,16384][,10^6])")
    ap.add_argument("--problems", default="1,2,3", help="problems to run, comma separated (1 always runs)")
    ap.add_argument("--cores", type=int, help="CPU devices, one per core (default every core; 1: one device)")
    args = ap.parse_args(argv)
    jsphere.use_cpu_cores(args.cores)  # before JAX's first operation
    if args.device is not None:
        try:
            jax.config.update("jax_default_device", jax.devices(args.device)[0])
        except RuntimeError as e:
            ap.error(f"--device {args.device}: {e}")
    args.out = result_path(args, "results-quick.json" if args.quick else "results.json")
    return args


def settings(args, gpu: bool) -> dict:
    """The run's repeats, batch sizes and problems, as the JSON records them."""
    problems = {int(k) for k in args.problems.split(",")} | {1}
    b1 = [1, 64, 1024] + ([] if args.quick else [16384]) + ([10**6] if gpu else [])
    if args.batches:
        b1 = sorted(int(float(b)) for b in args.batches.split(","))
    return {
        "repeats": 2 if args.quick else 3,
        "repeat_rule": "at least `repeats` steady-state calls, more (up to 25) while their total is under 1 s",
        "compile_s": "first call (trace + compile + one run) minus the steady-state median",
        "problem1": {
            "t1": T1,
            "rtol": RTOL,
            "atol": ATOL,
            "amplitudes": "0.05 (1 + 0.1 z), z ~ default_rng(0).standard_normal((B, 3)), rows 0..B-1",
            "phases": PHASES.tolist(),
            "batches": b1,
            "scipy_trials": 3 if args.quick else 10,
        },
        "problem2": {
            "gaits": "acceleration(theta_max=th), braking(theta_max=th)",
            "theta_max": "default_rng(1).uniform(0.05, 0.15)",
            "tolerances": "simulate_gaits defaults (rtol 1e-10, atol 1e-12)",
            "batches": [1, 64, 1024] if 2 in problems else [],
        },
        "problem3": {
            "params": GRAD_NAMES,
            "loss": "sum over batch of x_final^2 + y_final^2",
            "batches": ([64] if args.quick else [64, 1024]) if 3 in problems else [],
        },
    }


def main(argv=None) -> int:
    args = parse(argv)
    t_start = time.perf_counter()
    env = environment(source_digest())
    s = settings(args, gpu=env["jax"]["platform"] in ("gpu", "cuda", "rocm"))
    repeats, b1 = s["repeats"], s["problem1"]["batches"]
    log(
        f"jsphere benchmark ({'quick' if args.quick else 'full'}): backend {env['jax']['backend']} "
        f"({env['jax']['device_kind']}), {env['machine']['cpu_count']} CPUs"
    )
    p = jsphere.RobotParams.paper()
    Z = np.random.default_rng(0).standard_normal((max(b1), 3))

    js_rows, js_finals = problem1_jsphere(p, Z, b1, repeats)
    sc_row, sc_finals, model, q0 = problem1_scipy(p, Z, s["problem1"]["scipy_trials"], repeats)
    for r in js_rows:
        r["ratio_vs_scipy"] = r["trials_per_s"] / sc_row["trials_per_s"]
    checks, ref = problem1_checks(model, q0, Z, sc_finals, js_finals)
    cas_rows = problem1_casadi(model, q0, Z, 1024, repeats, sc_row, ref) if not args.no_casadi else []
    p2 = problem2(p, s["problem2"]["batches"], repeats)
    p3_rows, fd = problem3(p, Z, s["problem3"]["batches"], repeats)
    startup = None
    if not args.no_startup:  # last: new processes, each with the CPUs to itself
        log("[start-up] jsphere reproduce in new processes, empty cache then cached ...")
        with tempfile.TemporaryDirectory() as tmp:
            startup = startup_measure(tmp, "default", [], cached_runs=1 if args.quick else 3)
        log(f"      first {startup['first_process_s']:.1f} s, second {startup['second_process_s']:.1f} s")
    for r in p3_rows:
        if match := [j for j in js_rows if j["batch"] == r["batch"]]:
            r["problem1_forward_median_s"] = match[0]["median_s"]

    res = {
        **finish(env),
        "mode": "quick" if args.quick else "full",
        "settings": s,
        "problem1": {"jsphere": js_rows, "scipy": sc_row, "casadi": cas_rows, "checks": checks},
        "problem2": p2,
        "problem3": {"rows": p3_rows, "fd_check": fd},
        "startup": startup,
        "wall_time_s": time.perf_counter() - t_start,
    }
    table = fmt_table(res)
    res["table"] = table.splitlines()
    print(table)
    print(f"\nwall time {res['wall_time_s']:.0f} s")
    write_json(args.out, res)
    ok = checks["pass"] and (fd is None or fd["pass"]) and all("error" not in r for r in p2)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
