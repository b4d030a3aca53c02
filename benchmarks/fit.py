"""System identification on synthetic captures: time, and recovery in standard errors.

    python benchmarks/fit.py                                  # 20 trials x 601 samples, wheel speeds
    python benchmarks/fit.py --trials 5 --duration 4:8 --kind torques --free R_m,j,I[0,0],I[1,1],I[2,2],m0,I0 --fix m
    python benchmarks/fit.py ... --solver Dopri8                # another diffrax solver than the fit's Tsit5

Draws `--trials` capture-like trials (`jsphere.synthetic_trial`: `random_inputs`, 100 Hz,
1 mm position and 0.5 deg orientation noise) from a parameter set that differs from the
paper's robot (the "truth" below), fits the free names starting from the paper's values
(fixed names are set to the truth), and prints per free name the truth, the fit, its
standard error and the error in standard errors. Writes JSON with the machine and versions.
"""

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's jsphere first

import jax
import numpy as np

import jsphere
from jsphere._runtime.files import atomic_write_text
from jsphere.identify.fit import FIT_SOLVER

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

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


def metadata() -> dict:
    """Date, machine, device and versions: the head of the fit benchmarks' JSON."""
    return {
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "loadavg": os.getloadavg(),
        },
        "device": {"backend": jax.default_backend(), "kind": jax.devices()[0].device_kind, "count": jax.device_count()},
        "versions": {"jax": jax.__version__, "jsphere": jsphere.__version__, "numpy": np.__version__},
    }


def run(kind, n, durations, free, fix_names, seed=0, n_starts=2, progress=True, **kw):
    truth = truth_params()
    trials = make_trials(truth, n, durations, kind, seed)
    fix = {name: np.asarray(jsphere.get_value(truth, name)).tolist() for name in fix_names}
    t = time.perf_counter()
    res = jsphere.fit(
        trials, jsphere.RobotParams.paper(), free, fix=fix, n_starts=n_starts, seed=seed, progress=progress, **kw
    )
    elapsed = time.perf_counter() - t
    rows = []
    for name in res.free:
        tv = float(jsphere.get_value(truth, name))
        v, se = res.values[name], res.stderr[name]
        rows.append(
            {"name": name, "truth": tv, "fit": v, "stderr": se, "error_se": (v - tv) / se if se > 0 else float("nan")}
        )
    return res, rows, elapsed, trials


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kind", default="wheel_speeds", choices=["wheel_speeds", "torques"])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--duration", default="6", help="seconds, or lo:hi for a uniform draw per trial")
    ap.add_argument("--free", default="R_m,j,I[0,0],I[1,1],I[2,2],I0")
    ap.add_argument("--fix", default="m,m0", help="names set to the truth (comma-separated)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-starts", type=int, default=2)
    ap.add_argument("--solver", help="a diffrax solver's name (e.g. Dopri8); default: the fit's own (FIT_SOLVER)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results-fit.json"))
    args = ap.parse_args()
    lo, _, hi = args.duration.partition(":")
    durations = (float(lo), float(hi or lo))
    fix_names = [n for n in args.fix.split(",") if n]
    kw = {}
    if args.solver:
        import diffrax

        kw["options"] = jsphere.SolverOptions(solver=getattr(diffrax, args.solver)())
    res, rows, elapsed, trials = run(
        args.kind, args.trials, durations, args.free, fix_names, args.seed, args.n_starts, **kw
    )
    print(
        f"\n{args.trials} trials ({args.kind}), {sum(len(t.t) for t in trials)} samples; fit {elapsed:.1f} s "
        f"({res.iterations} LM iterations, {args.n_starts} starts, converged {res.converged})"
    )
    print(f"{'name':<8} {'truth':>12} {'fit':>12} {'stderr':>10} {'err/SE':>7}")
    for r in rows:
        print(f"{r['name']:<8} {r['truth']:>12.6g} {r['fit']:>12.6g} {r['stderr']:>10.3g} {r['error_se']:>7.2f}")
    print(f"sigma_pos {res.sigma_pos * 1e3:.3f} mm, sigma_rot {np.degrees(res.sigma_rot):.3f} deg")
    for w in res.identifiability["warnings"]:
        print("warning:", w)
    doc = {
        **metadata(),
        "config": {
            "kind": args.kind,
            "trials": args.trials,
            "duration_s": durations,
            "samples": sum(len(t.t) for t in trials),
            "free": args.free,
            "fix": fix_names,
            "n_starts": args.n_starts,
            "seed": args.seed,
            "solver": args.solver or type(FIT_SOLVER).__name__,
        },
        "fit_s_including_compile": elapsed,
        "iterations": res.iterations,
        "converged": res.converged,
        "sigma_pos_mm": res.sigma_pos * 1e3,
        "sigma_rot_deg": float(np.degrees(res.sigma_rot)),
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
