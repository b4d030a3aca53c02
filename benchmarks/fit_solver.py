"""The fit's Runge-Kutta method: accuracy of the simulated positions at the fit's tolerances and
the time of a fit, for each solver, in the same run.

    python benchmarks/fit_solver.py                       # Tsit5 and Dopri8, 3 rounds of fits
    python benchmarks/fit_solver.py --solvers Tsit5 Dopri5 Dopri8 --rounds 1

Accuracy: random torque inputs (`jsphere.random_inputs`) of 6, 15 and 30 s from rest, the paper's
robot, sampled at 100 Hz as a capture is; the largest horizontal position error of each solver at
the fit's tolerances (`FIT_TOLERANCES`, rtol 1e-6, atol 1e-8) against `Dopri8` at rtol 1e-11.
Fit: five 6 s torque trials (`benchmarks/fit.py`'s synthetic captures and truth), free
`R_m, j, I[0,0], I[1,1], I[2,2], m0, I0`, `m` fixed, 2 starts: in one process, each solver's
first fit (compiling its own programs), then `--rounds - 1` more of each, compiled (the median
is reported); the order alternates between rounds. The table gives each solver's times over the
first solver's, from the same run. Writes JSON (`--out`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's jsphere first

import diffrax
import numpy as np

import jsphere
from jsphere._runtime.files import atomic_write_text
from jsphere.identify.fit import FIT_TOLERANCES

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit import metadata, run  # noqa: E402

FREE = "R_m,j,I[0,0],I[1,1],I[2,2],m0,I0"


def accuracy(solvers: list[str], durations=(6.0, 15.0, 30.0)) -> list[dict]:
    """Largest position error [m] of each solver at the fit's tolerances, per duration."""
    p = jsphere.RobotParams.paper()
    rows = []
    for k, t1 in enumerate(durations):
        u = jsphere.random_inputs(p, t1, kind="torques", seed=k)
        ts = np.arange(int(round(t1 * 100)) + 1) / 100.0
        s0 = jsphere.State.at_rest(p)
        ref = jsphere.simulate(p, s0, u, t1, ts=ts, rtol=1e-11, atol=1e-13, max_steps=200_000)
        row = {"duration_s": t1}
        for name in solvers:
            opts = jsphere.SolverOptions(solver=getattr(diffrax, name)(), max_steps=65536, **FIT_TOLERANCES)
            tr = jsphere.simulate(p, s0, u, t1, ts=ts, options=opts)
            err = np.hypot(np.asarray(tr.x) - np.asarray(ref.x), np.asarray(tr.y) - np.asarray(ref.y))
            row[name] = float(np.max(err))
        rows.append(row)
        print(f"  accuracy {t1:4.0f} s: " + ", ".join(f"{n} {row[n] * 1e6:.3g} um" for n in solvers), file=sys.stderr)
    return rows


def fits(solvers: list[str], rounds: int) -> dict[str, list[dict]]:
    """Each solver's five-trial fit, `rounds` times, the order alternating: the first round
    compiles each solver's programs, the later ones run them compiled."""
    out: dict[str, list[dict]] = {n: [] for n in solvers}
    for r in range(rounds):
        for name in solvers if r % 2 == 0 else solvers[::-1]:
            opts = jsphere.SolverOptions(solver=getattr(diffrax, name)())
            res, rows, elapsed, _ = run("torques", 5, (6.0, 6.0), FREE, ["m"], 0, 2, progress=False, options=opts)
            out[name].append(
                {
                    "fit_s": elapsed,
                    "compiled": r > 0,
                    "iterations": res.iterations,
                    "converged": res.converged,
                    "error_se": {r["name"]: r["error_se"] for r in rows},
                }
            )
            print(f"  fit {name:<7} round {r + 1}: {elapsed:5.1f} s, {res.iterations} iterations", file=sys.stderr)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--solvers", nargs="+", default=["Tsit5", "Dopri8"], help="diffrax solvers' names")
    ap.add_argument("--rounds", type=int, default=3, help="the first compiles; at least 2")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results-fit-solver.json"))
    args = ap.parse_args(argv)
    acc = accuracy(args.solvers)
    timed = fits(args.solvers, args.rounds)
    first = args.solvers[0]
    cold = {n: timed[n][0]["fit_s"] for n in args.solvers}
    warm = {
        n: statistics.median(f["fit_s"] for f in timed[n][1:]) if args.rounds > 1 else math.nan for n in args.solvers
    }
    head = " ".join(f"{'err %g s' % a['duration_s']:>11}" for a in acc)
    print(f"\n{'solver':<8} {head}   first fit  ratio   compiled  ratio  largest error")
    for n in args.solvers:
        errs = " ".join(f"{a[n] * 1e6:8.3g} um" for a in acc)
        worst = max(max(abs(v) for v in f["error_se"].values()) for f in timed[n])
        print(
            f"{n:<8} {errs}   {cold[n]:7.1f} s  {cold[n] / cold[first]:5.2f}  {warm[n]:7.1f} s  "
            f"{warm[n] / warm[first]:5.2f}  {worst:.2f} SE"
        )
    doc = {
        **metadata(),
        "config": {"solvers": args.solvers, "rounds": args.rounds, "tolerances": FIT_TOLERANCES, "free": FREE},
        "accuracy_m": acc,
        "fits": timed,
        "first_fit_s": cold,
        "compiled_fit_s_median": warm,
        "ratio_over_first": {
            n: {"first_fit": cold[n] / cold[first], "compiled": warm[n] / warm[first]} for n in args.solvers
        },
    }
    atomic_write_text(args.out, json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
