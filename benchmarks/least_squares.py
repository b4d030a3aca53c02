"""`jsphere.least_squares` (a Levenberg-Marquardt loop in NumPy around jitted residuals and
Jacobian) against `optimistix.least_squares` with `optimistix.LevenbergMarquardt`, in one run.

Problems: the paper's R_m and j from its two reported numbers (`examples/fit_paper_Rm_j.py`:
two gait simulations, reverse-mode Jacobian through diffrax), and a dense curve fit (3
parameters, 400 residuals). Each solver runs twice per problem: the first call includes
compilation, the second (a new `fun` of the same structure) shows the steady cost.

    python benchmarks/least_squares.py [--quick] [--out benchmarks/results-least-squares.json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's jsphere first

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)


def with_optimistix(fun, x0, *, max_iter=50, ftol=1e-14, xtol=1e-12):
    """`optimistix.least_squares` with `optimistix.LevenbergMarquardt` (reverse-mode Jacobian),
    the step and cost tolerances of `jsphere.least_squares`."""
    solver = optx.LevenbergMarquardt(rtol=xtol, atol=ftol)
    sol = optx.least_squares(
        lambda x, _: fun(x),
        solver,
        jnp.asarray(x0, jnp.float64),
        options={"jac": "bwd"},
        max_steps=max_iter,
        throw=False,
    )
    x = np.asarray(sol.value)
    r = np.asarray(jax.jit(fun)(x))
    return x, 0.5 * float(r @ r), int(sol.stats["num_steps"]), bool(sol.result == optx.RESULTS.successful)


def paper_problem(shift: float):
    """Residuals of the paper's two reported rates (`examples/fit_paper_Rm_j.py`); `shift`
    moves the reported numbers a little so that a second call is a new function."""
    reported = np.array([0.864, 0.852]) + shift
    sd = 0.0005 / math.sqrt(3.0)
    start = jsphere.RobotParams.paper(R_m=0.025, j=1.0e-4)
    free = jsphere.FreeParams(start, "R_m,j")
    accel = [jsphere.acceleration(), jsphere.braking()]
    turned = [jsphere.acceleration(), jsphere.turn(), jsphere.braking(phi=np.pi / 4)]
    i_acc = int(np.nonzero(np.asarray(jsphere.simulate_gaits(start, accel).segment) == 0)[0][-1])
    i_turn = int(np.nonzero(np.asarray(jsphere.simulate_gaits(start, turned, reset=[True, None]).segment) == 1)[0][-1])

    def residuals(theta):
        p = free.to_params(theta)
        a = jsphere.simulate_gaits(p, accel)
        t = jsphere.simulate_gaits(p, turned, reset=[True, None])
        return (jnp.stack([a.Omega[i_acc, 1], t.Omega[i_turn, 1]]) - reported) / sd

    return residuals, free.theta0


def curve_problem(shift: float):
    t = jnp.linspace(0.0, 4.0, 400)
    y = 2.0 * jnp.exp(-1.3 * t) * jnp.cos(3.0 * t + shift) + 0.01 * jnp.sin(37.0 * t)

    def residuals(x):
        return (x[0] * jnp.exp(-x[1] * t) * jnp.cos(x[2] * t + shift) - y) / 0.01

    return residuals, np.array([1.0, 1.0, 2.8])


def run(name, make, solver):
    rows = []
    for call, shift in (("first", 0.0), ("second", 1e-4)):
        fun, x0 = make(shift)
        t0 = time.perf_counter()
        if solver == "jsphere":
            res = jsphere.least_squares(fun, x0)
            x, cost, it, conv = res.x, res.cost, res.iterations, res.converged
        else:
            x, cost, it, conv = with_optimistix(fun, x0)
        rows.append(
            {
                "problem": name,
                "solver": solver,
                "call": call,
                "seconds": time.perf_counter() - t0,
                "iterations": int(it),
                "converged": bool(conv),
                "cost": float(cost),
                "x": np.asarray(x).tolist(),
            }
        )
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the curve fit only (no simulations)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-least-squares.json")))
    args = ap.parse_args()
    rows = []
    problems = (("paper R_m, j", paper_problem), ("curve fit", curve_problem))
    for name, make in problems[1:] if args.quick else problems:
        for solver in ("jsphere", "optimistix"):
            rows += run(name, make, solver)
    print(f"{'problem':<14} {'solver':<11} {'call':<7} {'seconds':>8} {'iter':>5} {'conv':>5} {'cost':>12}")
    for r in rows:
        print(
            f"{r['problem']:<14} {r['solver']:<11} {r['call']:<7} {r['seconds']:>8.2f} {r['iterations']:>5d} "
            f"{str(r['converged']):>5} {r['cost']:>12.5e}"
        )
    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.platform(),
        "device": str(jax.devices()[0]),
        "versions": {
            "jax": jax.__version__,
            "optimistix": __import__("optimistix").__version__,
            "numpy": np.__version__,
        },
    }
    Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
