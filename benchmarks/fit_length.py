"""Fit wall time and quality against trial length and number of trials: single against
multiple shooting, in the same run.

    python benchmarks/fit_length.py                         # lengths 6 15 30 s, 1 and 4 trials
    python benchmarks/fit_length.py --lengths 6 15 30 60 --trials 1 4
    python benchmarks/fit_length.py --lengths 6 --trials 1  # a quick look

For each (length, number of trials) the same synthetic captures (torque inputs: three sines per
wheel at 0.3-0.7 Hz, 100 Hz, 1 mm and 0.5 deg noise) of a robot 5-20 % away from the paper's are
fitted from the paper's values with seven free parameters (`r_m[2], j, I[0,0], I[1,1], I[2,2],
m0, I0`), one start, once with `shooting="single"` and once with `shooting="multiple"`. Per fit:
the wall time (compilation included: each shape compiles once), the iterations, the largest
error in standard errors, the residual sigmas; then, compiled, the time of one evaluation of
the residuals and their Jacobian (the unit of work of an iteration) and, for multiple shooting,
of the assembly and elimination of its normal equations. The table gives the ratios multiple /
single of the same run. Writes JSON (`--out`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's jsphere first

import jax
import jax.numpy as jnp
import numpy as np

import jsphere
from jsphere._runtime.files import atomic_write_text
from jsphere.identify import shooting as _shooting
from jsphere.identify.data import pack_trials
from jsphere.identify.free import FreeParams
from jsphere.identify.residuals import _functions
from jsphere.identify.starts import nuisance_guess

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit import metadata  # noqa: E402

FREE = "r_m[2],j,I[0,0],I[1,1],I[2,2],m0,I0"


def truth() -> jsphere.RobotParams:
    return jsphere.RobotParams.paper().replace(
        m0=0.85, I0=0.0105, j=3.2e-4, r_m=np.array([0.0, 0.0, -0.031]), I=np.diag([0.018, 0.0145, 0.026])
    )


def trials(robot, n: int, length: float, seed: int = 0):
    out = []
    for i in range(n):
        u = jsphere.random_inputs(robot, length, kind="torques", f_min=0.3, f_max=0.7, seed=seed * 100 + i)
        out.append(jsphere.synthetic_trial(robot, u, length, rate=100.0, seed=seed * 100 + i, name=f"t{i}"))
    return out


def best_of(f, k: int = 3) -> float:
    times = []
    for _ in range(k):
        t = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - t)
    return min(times)


def unit_costs(data, segment: float) -> dict:
    """Compiled times of one Jacobian evaluation (single and multiple shooting) and of the
    multiple-shooting assembly + elimination, at the paper's values."""
    base = jsphere.RobotParams.paper()
    free = FreeParams(base, FREE, None)
    fns = _functions(free, data.kind, 1e-6, 1e-8, 16384)
    th = jnp.asarray(free.theta0)[None]
    sig = jnp.array([1e-3, math.radians(0.5)])
    nu = jnp.asarray(nuisance_guess(data, base))[None]
    d = data.arrays()
    out = {"jacobian_single_s": best_of(lambda: fns.jacobian(base, th, nu, d, sig))}
    seg = _shooting.segment_trials(data, segment)
    nus = jnp.asarray(nuisance_guess(seg.data, base))[None]
    sd, sa = seg.data.arrays(), seg.arrays()
    scale = jnp.asarray(_shooting.defect_scale(data.kind, sig, float(base.R0), segment))
    res, ok, J, pose, e, Je = fns.segments(base, th, nus, sd, sig)
    out["jacobian_multiple_s"] = best_of(lambda: fns.segments(base, th, nus, sd, sig))

    def linalg():
        blocks, cost, _ = fns.assemble(res, J, e, Je, nus, 10.0, sa, scale)
        return fns.solve(blocks, jnp.array([1e-3]))

    out["linear_algebra_multiple_s"] = best_of(linalg)
    out["segments"] = seg.n_segments
    return out


def one(robot, n, length, method, seed):
    tr = trials(robot, n, length, seed)
    t = time.perf_counter()
    res = jsphere.fit(tr, jsphere.RobotParams.paper(), FREE, n_starts=1, shooting=method)
    wall = time.perf_counter() - t
    z = [abs((res.values[k] - float(jsphere.get_value(robot, k))) / res.stderr[k]) for k in res.free]
    return {
        "wall_s": wall,
        "iterations": res.iterations,
        "max_error_se": float(max(z)),
        "converged": res.converged,
        "status": getattr(res, "status", None),
        "sigma_pos_mm": res.sigma_pos * 1e3,
        "sigma_rot_deg": math.degrees(res.sigma_rot),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lengths", type=float, nargs="+", default=[6.0, 15.0, 30.0])
    ap.add_argument("--trials", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--segment", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results-fit-length.json"))
    args = ap.parse_args()
    robot = truth()
    rows = []
    for n in args.trials:
        for length in args.lengths:
            row = {"trials": n, "length_s": length}
            for method in ("single", "multiple"):
                print(f"{n} x {length:g} s, {method} shooting ...", file=sys.stderr, flush=True)
                row[method] = one(robot, n, length, method, args.seed)
            data = pack_trials(trials(robot, n, length, args.seed), jsphere.RobotParams.paper())
            row["unit"] = unit_costs(data, args.segment)
            rows.append(row)
    head = f"{'trials':>6} {'len s':>6} | {'single s':>9} {'max|z|':>8} {'sigma mm':>8} | {'multi s':>8} {'max|z|':>8} {'sigma mm':>8} | {'time m/s':>8} {'jac m/s':>8} {'linalg/jac':>10}"
    print(head)
    print("-" * len(head))
    for r in rows:
        s, m, u = r["single"], r["multiple"], r["unit"]
        print(
            f"{r['trials']:>6} {r['length_s']:>6g} | {s['wall_s']:>9.1f} {s['max_error_se']:>8.2f} {s['sigma_pos_mm']:>8.2f} | "
            f"{m['wall_s']:>8.1f} {m['max_error_se']:>8.2f} {m['sigma_pos_mm']:>8.2f} | {m['wall_s'] / s['wall_s']:>8.2f} "
            f"{u['jacobian_multiple_s'] / u['jacobian_single_s']:>8.2f} {u['linear_algebra_multiple_s'] / u['jacobian_multiple_s']:>10.3f}"
        )
    doc = {
        **metadata(),
        "config": {"free": FREE, "segment_s": args.segment, "seed": args.seed, "rate_hz": 100.0, "n_starts": 1},
        "rows": rows,
    }
    atomic_write_text(args.out, json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
