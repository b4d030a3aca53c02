"""Work-precision of problem 1 of `run.py`: accuracy against throughput for jsphere (Dopri8, Tsit5,
`Vern7`, Dopri5), CasADi's compiled fixed-step RK4 and scipy's DOP853, all measured in one run;
benchmarks/README.md has the details. Writes the JSON and a log-log figure.

    python benchmarks/work_precision.py                  # full run (about 5 min on 2 CPU cores)
    python benchmarks/work_precision.py --quick          # fewer settings, batch 256 (about 1.5 min)
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path
from typing import ClassVar

sys.path.insert(0, str(Path(__file__).resolve().parent))  # this folder's modules (the checkout's jsphere first)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import run  # noqa: E402  (problem 1: amplitudes, phases, the scipy trial, the devices)
from casadi_baseline import NumpyRobot, built_and_timed, ca, in_temporary_folder, initial_states, rk4_batch  # noqa: E402
from common import HERE, ROOT, environment, finish, log, public, source_digest, table, time_call, timed, write_json  # noqa: E402

import jsphere  # noqa: E402

# fmt: off
_c = np.array([0.0, 0.005, 0.1088888888888888888888888888888888888889, 0.1633333333333333333333333333333333333333,
    0.4555, 0.6095094489978381317087004421486024949638, 0.884, 0.925, 1.0, 1.0])
_a = np.zeros((10, 10))
_a[1, :1] = [0.005]
_a[2, :2] = [-1.076790123456790123456790123456790123457, 1.185679012345679012345679012345679012346]
_a[3, :3] = [0.04083333333333333333333333333333333333333, 0.0, 0.1225]
_a[4, :4] = [0.6389139236255726780508121615993336109954, 0.0, -2.455672638223656809662640566430653894211,
    2.272258714598084131611828404831320283215]
_a[5, :5] = [-2.661577375018757131119259297861818119279, 0.0, 10.80451388645613769565396655365532838482,
    -8.353914657396199411968048547819291691541, 0.8204875949566569791420417341743839209619]
_a[6, :6] = [6.067741434696770992718360183877276714679, 0.0, -24.71127363591108579734203485290746001803,
    20.42751793078889394045773111748346612697, -1.906157978816647150624096784352757010879,
    1.006172249242068014790040335899474187268]
_a[7, :7] = [12.05467007625320299509109452892778311648, 0.0, -49.75478495046898932807257615331444758322,
    41.14288863860467663259698416710157354209, -4.461760149974004185641911603484815375051,
    2.042334822239174959821717077708608543738, -0.09834843665406107379530801693870224403537]
_a[8, :8] = [10.13814652288180787641845141981689030769, 0.0, -42.64113603171750214622846006736635730625,
    35.76384003992257007135021178023160054034, -4.348022840392907653340370296908245943710,
    2.009862268377035895441943593011827554771, 0.3487490460338272405953822853053145879140,
    -0.2714390051048312842371587140910297407572]
_a[9, :9] = [-45.03007203429867712435322405073769635151, 0.0, 187.3272437654588840752418206154201997384,
    -154.0288236935018690596728621034510402582, 18.56465306347536233859492332958439136765,
    -7.141809679295078854925420496823551192821, 1.308808578161378625114762706007696696508, 0.0, 0.0]
_b = np.array([0.04715561848627222170431765108838175679569, 0.0, 0.0, 0.2575056429843415189596436101037687580986,
    0.2621665397741262047713863095764527711129, 0.1521609265673855740323133199165117535523,
    0.4939969170032484246907175893227876844296, -0.2943031171403250441557244744092703429139,
    0.08131747232495109999734599440136761892478, 0.0])
_bh = np.array([0.04460860660634117628731817597479197781432, 0.0, 0.0, 0.2671640378571372680509102260943837899738,
    0.2201018300177293019979715776650753096323, 0.2188431703143156830983120833512893824578,
    0.2289871705411202883378173889763552365362, 0.0, 0.0, 0.02029518466335628222767054793810430358554])
# fmt: on


def _fsal_tableau() -> diffrax.ButcherTableau:
    """The pair's tableau with the 11th stage appended (`Vern7`)."""
    s = 11
    a = np.zeros((s, s))
    a[:10, :10] = _a
    a[10, :10] = _b
    b_sol = np.concatenate([_b, [0.0]])
    b_error = np.concatenate([_b - _bh, [0.0]])
    c = np.concatenate([_c, [1.0]])
    return diffrax.ButcherTableau(c=c[1:], b_sol=b_sol, b_error=b_error, a_lower=tuple(a[i, :i] for i in range(1, s)))


class Vern7(diffrax.AbstractERK):
    """Verner's "most efficient" 7(6) Runge-Kutta pair as a diffrax solver, for measurement, not for use.

    The coefficients are Verner's (J. H. Verner, "Numerically optimal Runge-Kutta pairs with
    interpolants", Numer. Algorithms 53 (2010) 383-396; RKV76.IIa.Efficient.00001675585.081206 at
    https://www.sfu.ca/~jverner/), to the digits published there: 10 stages, the solution of order 7
    from stages 1-9, the embedded one of order 6 from stages 1-7 and 10. An 11th stage at `c = 1`
    with the solution's weights makes the tableau first same as last (10 evaluations per step).
    Save times inside a step use a cubic Hermite interpolant; the benchmark reads only the end time.
    """

    tableau: ClassVar[diffrax.ButcherTableau] = _fsal_tableau()
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 7


REF_RTOL, REF_ATOL = 1e-13, 1e-14  # scipy DOP853 reference
JS_REF_RTOL, JS_REF_ATOL = 1e-13, 1e-15  # jsphere Dopri8, the second reference
DECADES = [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9]
SOLVERS = {"Dopri8": diffrax.Dopri8, "Tsit5": diffrax.Tsit5, "Dopri5": diffrax.Dopri5, "Vern7": Vern7}
#: the full run's tolerances: each decade from 1e-3 to 1e-11
RTOLS = [10.0**-k for k in range(3, 12)]

FULL = {
    "batch": 1024,
    "repeats": 3,
    "error_trials": 16,
    "jsphere": {"Dopri8": RTOLS, "Tsit5": RTOLS, "Dopri5": RTOLS[::2], "Vern7": RTOLS},
    "casadi_steps": [25, 50, 100, 200, 400, 800, 1600, 3200, 6400],
    "scipy_rtols": RTOLS,
}
QUICK = {
    "batch": 256,
    "repeats": 2,
    "error_trials": 4,
    "jsphere": {"Dopri8": [1e-3, 1e-6, 1e-9], "Tsit5": [1e-3, 1e-6, 1e-9], "Vern7": [1e-6]},
    "casadi_steps": [50, 200, 800],
    "scipy_rtols": [1e-3, 1e-6, 1e-9],
}


def final_error(xy: np.ndarray, ref: np.ndarray) -> float:
    """Largest distance between final positions, (n, 2) against (n, 2)."""
    return float(np.max(np.hypot(*(np.asarray(xy) - ref).T)))


# ------------------------------------------------------------------------ the rows: jsphere, CasADi, scipy


def jsphere_rows(p, A, ref, grid, repeats):
    rows, n = [], ref.shape[0]
    for name, rtols in grid.items():
        for rtol in rtols:
            log(f"[jsphere] {name} rtol {rtol:.0e}, batch {A.shape[0]} ...")
            f = jax.jit(run.problem1(p, rtol, rtol / 100, SOLVERS[name]()))
            r = time_call(f, A, repeats=repeats)
            tr = r["_out"]
            row = {
                "method": f"jsphere {name}",
                "setting": f"rtol {rtol:.0e}",
                "rtol": rtol,
                "atol": rtol / 100,
                "batch": int(A.shape[0]),
                "error_m": final_error(run.final_xy(tr)[:n], ref),
                "trials_per_s": A.shape[0] / r["median_s"],
                "steps_mean": float(np.mean(np.asarray(tr.num_steps))),
                # field evaluations per accepted step: the stages after the first (first same as last)
                "evaluations_per_step": int(len(SOLVERS[name].tableau.c) + 1 - SOLVERS[name].tableau.fsal),
                "all_ok": bool(np.all(np.asarray(tr.ok))),
                **public(r),
            }
            log(
                f"      error {row['error_m']:.1e} m, {row['trials_per_s']:.0f} trials/s, compile {r['compile_s']:.1f} s"
            )
            rows.append(row)
    return rows


def casadi_rows(model, q0, A, ref, steps_list, repeats, threads):
    if ca is None:
        return [{"method": "CasADi RK4", "error": "not run: CasADi is not installed (pip install casadi)"}]
    B, n = A.shape[0], ref.shape[0]
    y0, rows = initial_states(q0, B), []
    with in_temporary_folder():
        for steps in steps_list:
            log(f"[CasADi] RK4 {steps} steps, batch {B}, {threads} threads ...")
            r, xy = built_and_timed(lambda: rk4_batch(model, B, threads, steps), y0, A, repeats=repeats)
            err = final_error(xy[:n], ref) if np.all(np.isfinite(xy[:n])) else math.inf
            head = {"method": "CasADi RK4", "setting": f"{steps} steps", "steps": steps, "threads": threads}
            compile_s = r["build_s"] + max(r["first_call_s"] - r["median_s"], 0.0)
            rows.append(head | r | {"error_m": err, "compile_s": compile_s})
            log(f"      error {err:.1e} m, {r['trials_per_s']:.0f} trials/s, build {r['build_s']:.1f} s")
    return rows


def scipy_rows(model, q0, A, ref, rtols, repeats):
    rows = []
    run.scipy_trial(model, q0, A[0])  # warm-up (imports, caches)
    for rtol in rtols:
        log(f"[scipy] DOP853 rtol {rtol:.0e}, {A.shape[0]} trials x {repeats} ...")
        timing, finals = run.scipy_batch(model, q0, A, repeats, rtol=rtol, atol=rtol / 100)
        head = {"method": "scipy DOP853", "setting": f"rtol {rtol:.0e}", "rtol": rtol, "atol": rtol / 100}
        row = head | {"batch": int(A.shape[0]), "error_m": final_error(finals, ref), "compile_s": 0.0} | timing
        log(f"      error {row['error_m']:.1e} m, {row['trials_per_s']:.2f} trials/s")
        rows.append(row)
    return rows


# ------------------------------------------------------------------------ report

GROUPS = {"jsphere": "jsphere", "CasADi": "CasADi RK4", "scipy": "scipy DOP853"}
#: solvers measured for comparison, not among jsphere's own: left out of the decade table
#: ("jsphere (fastest solver)"), compared with Dopri8 at equal error instead (`equal_error`)
COMPARED_ONLY = ("jsphere Vern7",)
#: what the decade table keeps of a row
CROSSOVER_KEYS = ("method", "setting", "error_m", "trials_per_s", "compile_s")


def crossover(rows):
    """For each decade, the fastest measured row of each method group with error <= decade
    (jsphere's own solvers only: `COMPARED_ONLY` left out)."""
    measured = [r for r in rows if "error" not in r and r["method"] not in COMPARED_ONLY]
    out = []
    for d in DECADES:
        entry = {"accuracy_m": d}
        for g, prefix in GROUPS.items():
            ok = [r for r in measured if r["method"].startswith(prefix) and r["error_m"] <= d]
            best = max(ok, key=lambda r: r["trials_per_s"]) if ok else None
            entry[g] = {k: best[k] for k in CROSSOVER_KEYS} if best else None
        js = entry["jsphere"]
        for g in ("CasADi", "scipy"):
            other = entry[g]
            entry[f"jsphere_over_{g}"] = js["trials_per_s"] / other["trials_per_s"] if js and other else None
        out.append(entry)
    return out


def equal_error(rows, method: str, against: str = "jsphere Dopri8") -> list[dict]:
    """For each setting of `method` whose error lies within the errors measured for `against`:
    the throughput of `against` at that error, interpolated linearly in log(error) and
    log(trials/s) between its two nearest settings, and the ratio of the two throughputs; the
    same for the field evaluations per trial (accepted steps x evaluations per step), a
    measure that does not depend on the machine's speed at the time."""
    ref = sorted((r for r in rows if r.get("method") == against and "error" not in r), key=lambda r: r["error_m"])
    le = np.log10([r["error_m"] for r in ref])
    lt = np.log10([r["trials_per_s"] for r in ref])
    lw = np.log10([r["steps_mean"] * r["evaluations_per_step"] for r in ref])
    out = []
    for r in rows:
        if r.get("method") != method or "error" in r or not le.size or not le[0] <= np.log10(r["error_m"]) <= le[-1]:
            continue
        at = float(10 ** np.interp(np.log10(r["error_m"]), le, lt))
        work = float(10 ** np.interp(np.log10(r["error_m"]), le, lw))
        evaluations = r["steps_mean"] * r["evaluations_per_step"]
        row = {"method": method} | {k: r[k] for k in ("setting", "error_m", "trials_per_s")}
        row |= {"against": against, "against_trials_per_s": at, "ratio": r["trials_per_s"] / at}
        out.append(
            row | {"evaluations": evaluations, "against_evaluations": work, "evaluations_ratio": evaluations / work}
        )
    return out


def fmt_equal_error(cmp) -> list[str]:
    if not cmp:
        return []
    a, b = cmp[0]["method"].replace("jsphere ", ""), cmp[0]["against"].replace("jsphere ", "")
    cols = [("setting", "setting", ""), ("error m", "error_m", ".1e"), (f"{a} trials/s", "trials_per_s", ".1f")]
    cols += [(f"{b} trials/s", "against_trials_per_s", ".1f"), ("ratio", "ratio", ".2f")]
    cols += [(f"{a} evals", "evaluations", ".0f"), (f"{b} evals", "against_evaluations", ".0f")]
    head = f"{a} against {b} at equal error ({b} interpolated in log-log between its settings):"
    return [head, *table([*cols, ("ratio", "evaluations_ratio", ".2f")], cmp)]


def fmt_rows(rows) -> list[str]:
    cols = [("method", "method", ""), ("setting", "setting", ""), ("error m", "error_m", ".1e")]
    cols += [("trials/s", "trials_per_s", ".1f"), ("compile s", "compile_s", ".2f")]
    cols += [("steps", lambda r: r.get("steps_mean", r.get("steps")), ".0f"), ("batch", "batch", "")]
    failed = [f"{r['method']}  {r['error']}" for r in rows if "error" in r]
    return table(cols, [r for r in rows if "error" not in r]) + failed


def fmt_crossover(cross) -> list[str]:
    def cell(e):
        if e is None:
            return "not reached"
        name = e["method"].replace("jsphere ", "").replace("CasADi RK4", "RK4").replace("scipy DOP853", "DOP853")
        return f"{name} {e['setting']}: {e['trials_per_s']:.1f}"

    heads = {"jsphere": "jsphere (fastest solver)", "CasADi": "CasADi RK4", "scipy": "scipy DOP853"}
    cols = [("error <=", "accuracy_m", ".0e"), *((h, lambda e, g=g: cell(e[g]), "") for g, h in heads.items())]
    cols += [("js/CasADi", "jsphere_over_CasADi", ".1f"), ("js/scipy", "jsphere_over_scipy", ".1f")]
    title = "fastest measured setting at least this accurate (no interpolation), setting: trials/s:"
    return [title, *table(cols, cross)]


def figure(rows, path: Path, floor_m: float, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    styles = {
        "jsphere Dopri8": ("C0", "o", "-"),
        "jsphere Tsit5": ("C2", "s", "-"),
        "jsphere Dopri5": ("C4", "D", "-"),
        "jsphere Vern7": ("C5", "v", "-"),
        "CasADi RK4": ("C1", "^", "--"),
        "scipy DOP853": ("C3", "v", ":"),
    }
    fig, ax = plt.subplots(figsize=(8.0, 5.6), dpi=120)
    for method, (color, marker, ls) in styles.items():
        pts = [r for r in rows if r.get("method") == method and math.isfinite(r.get("error_m", math.inf))]
        if not pts:
            continue
        x = [max(r["error_m"], 1.05e-12) for r in pts]  # errors below the axis drawn at its edge
        y = [r["trials_per_s"] for r in pts]
        ax.plot(x, y, ls, color=color, marker=marker, label=method, lw=1.5, ms=5)
        for r, xi, yi in zip(pts, x, y):
            lab = r["setting"].replace("rtol ", "").replace(" steps", "")
            ax.annotate(lab, (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=6, color=color)
    ax.axvspan(1e-12, max(floor_m, 1e-12), color="0.85", zorder=0, label="reference agreement")
    note = "point labels: rtol (jsphere, scipy), steps over 4 s (CasADi)"
    ax.text(0.99, 0.01, note, transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.3")
    ax.set(xscale="log", yscale="log", xlim=(1e-12, 1e-1), xlabel="largest final-position error [m]")
    ax.set_ylabel("throughput [trials/s] (compilation excluded)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="major", alpha=0.4)
    ax.grid(True, which="minor", alpha=0.1)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp)
    os.replace(tmp, path)
    plt.close(fig)


# ------------------------------------------------------------------------ main


def parse(argv):
    """The arguments, and the settings of the run (`FULL` or `QUICK`, with the arguments' values)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, help="trials per jsphere and CasADi call (1024; 256 in --quick)")
    ap.add_argument("--repeats", type=int, help="steady-state calls per setting, at least (3; 2 in --quick)")
    ap.add_argument("--error-trials", type=int, help="trials the error is taken over (16; 4 in --quick)")
    ap.add_argument("--quick", action="store_true", help="fewer settings, smaller batch: a smoke run")
    ap.add_argument("--out", type=Path, help="JSON output, written atomically")
    ap.add_argument("--figure", type=Path, help="the PNG (log-log, error against trials/s)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 2, help="CasADi's map threads (CPU count)")
    ap.add_argument("--cores", type=int, help="CPU devices jsphere's batch is split over (default one per core)")
    args = ap.parse_args(argv)
    jsphere.use_cpu_cores(args.cores)  # before JAX's first operation
    cfg = dict(QUICK if args.quick else FULL)
    cfg |= {k: getattr(args, k) for k in ("batch", "repeats", "error_trials") if getattr(args, k) is not None}
    if args.out is None:
        args.out = HERE / ("results-work-precision-quick.json" if args.quick else "results-work-precision.json")
    if args.figure is None:
        args.figure = args.out.with_suffix(".png") if args.quick else ROOT / "docs" / "images" / "work-precision.png"
    if cfg["error_trials"] > cfg["batch"]:
        ap.error("--error-trials must not exceed --batch")
    return args, cfg


def references(p, model, q0, A) -> tuple[np.ndarray, dict]:
    """The final `(x, y)` of the amplitude rows `A` by scipy's DOP853 at rtol 1e-13, and its record
    with its distance from jsphere's Dopri8 at rtol 1e-13 on the same trials."""
    n = len(A)
    log(f"[reference] scipy DOP853 rtol {REF_RTOL:.0e}, atol {REF_ATOL:.0e}, {n} trials ...")
    sols, wall = timed(lambda: [run.scipy_trial(model, q0, a, rtol=REF_RTOL, atol=REF_ATOL) for a in A])
    ref = np.array([s.y[10:12, -1] for s in sols])
    log(f"[reference] jsphere Dopri8 rtol {JS_REF_RTOL:.0e}, atol {JS_REF_ATOL:.0e}, {n} trials ...")
    f = jax.jit(run.problem1(p, JS_REF_RTOL, JS_REF_ATOL, diffrax.Dopri8()))
    tr = jax.block_until_ready(f(jnp.asarray(A)))
    agree = final_error(run.final_xy(tr), ref)
    log(f"      references agree to {agree:.1e} m")
    return ref, {
        "used": f"scipy DOP853 rtol {REF_RTOL:.0e} atol {REF_ATOL:.0e} on casadi_baseline.NumpyRobot",
        "trials": n,
        "wall_s": wall,
        "steps_mean": float(np.mean([len(s.t) - 1 for s in sols])),
        "final_xy": ref.tolist(),
        "check": f"jsphere Dopri8 rtol {JS_REF_RTOL:.0e} atol {JS_REF_ATOL:.0e}, same trials (batch {n})",
        "check_all_ok": bool(np.all(np.asarray(tr.ok))),
        "max_distance_between_references_m": agree,
    }


def settings(cfg: dict, threads: int) -> dict:
    return {
        "problem": "run.py problem 1: paper robot from rest, K_i = a_i sin(pi t + 2.1 (i - 1)), [0, 4] s",
        "amplitudes": "0.05 (1 + 0.1 z), z ~ default_rng(0).standard_normal((batch, 3)), rows 0..batch-1",
        **{k: cfg[k] for k in ("batch", "repeats", "error_trials")},
        "error": "max over the first error_trials trials of the distance |(x, y) - reference| at t = 4 s [m]",
        "atol": "rtol / 100 (jsphere and scipy)",
        "jsphere": dict(cfg["jsphere"]),
        "jsphere_call": "jax.jit(jax.vmap(simulate(..., options=SolverOptions(rtol, atol, solver))))(amplitudes), "
        "default batch_steps",
        "casadi_steps": cfg["casadi_steps"],
        "casadi_threads": threads,
        "scipy_rtols": cfg["scipy_rtols"],
        "scipy_trials": cfg["error_trials"],
        "throughput": "trials per call / median steady-state wall time; compilation excluded",
        "compile_s": "jsphere: first call minus median; CasADi: construction (C compile) plus first-call excess",
        "crossover_rule": "fastest measured setting with error <= the decade, no interpolation; "
        f"jsphere's own solvers only ({', '.join(COMPARED_ONLY)} compared in equal_error)",
        "equal_error_rule": "Dopri8's trials/s (and field evaluations per trial: accepted steps x "
        "evaluations_per_step) at the same error, interpolated linearly in log-log",
    }


def main(argv=None) -> int:
    args, cfg = parse(argv)
    B, n_err, repeats = cfg["batch"], cfg["error_trials"], cfg["repeats"]
    t_start = time.perf_counter()
    env = environment(source_digest())
    env["versions"]["casadi"] = ca.__version__ if ca is not None else None
    log(
        f"work-precision ({'quick' if args.quick else 'full'}): batch {B}, error over {n_err} trials, "
        f"backend {jax.default_backend()} ({env['jax']['device']}), {os.cpu_count()} CPUs"
    )
    p = jsphere.RobotParams.paper()
    model = NumpyRobot.from_params(p)
    q0 = np.asarray(jsphere.State.at_rest(p).q)
    A = run.amplitudes(np.random.default_rng(0).standard_normal((B, 3)))
    ref, reference = references(p, model, q0, A[:n_err])

    A_split, devices = run.split(jnp.asarray(A))  # over the CPU devices, as CasADi's map over threads
    env["jsphere_devices"] = devices
    rows = jsphere_rows(p, A_split, ref, cfg["jsphere"], repeats)
    rows += casadi_rows(model, q0, A, ref, cfg["casadi_steps"], repeats, args.threads)
    rows += scipy_rows(model, q0, A[:n_err], ref, cfg["scipy_rtols"], repeats)
    cross = crossover(rows)
    compared = [c for m in COMPARED_ONLY for c in equal_error(rows, m)]

    finish(env)
    wall = time.perf_counter() - t_start
    agree = reference["max_distance_between_references_m"]
    table = fmt_rows(rows) + [""] + fmt_crossover(cross) + [""] + fmt_equal_error(compared)
    table += [
        "",
        f"error: largest |(x, y) - reference| of the final position over the first {n_err} trials; reference "
        f"{reference['used']}; the jsphere reference ({reference['check']}) is {agree:.1e} m from it",
    ]
    res = {**env, "mode": "quick" if args.quick else "full", "settings": settings(cfg, args.threads)}
    res |= {"reference": reference, "rows": rows, "crossover": cross, "equal_error": compared}
    write_json(args.out, res | {"wall_time_s": wall, "table": table})
    title = (
        f"problem 1 (4 s, batch {B}; scipy one trial at a time): {env['machine']['cpu_count']} CPUs, "
        f"JAX {jax.default_backend()}, load {env['machine']['loadavg_start'][0]:.1f}-"
        f"{env['machine']['loadavg_end'][0]:.1f}, {env['date_utc'][:10]}"
    )
    figure(rows, args.figure, agree, title)
    print("\n".join(table))
    print(f"\nwall time {wall:.0f} s; figure written to {args.figure}")
    ok = all(r.get("all_ok", True) for r in rows) and reference["check_all_ok"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
