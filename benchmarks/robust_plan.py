"""Robust planning benchmark: `plan_robust` against the nominal `plan` of the same request, and
its replay of 1000 drawn robots (vmapped RK4 on the table's rows) against a loop of the plain
adaptive `simulate`, all in the same process.

    python benchmarks/robust_plan.py                 # samples 64, quantile 0.95, 1000 check draws
    python benchmarks/robust_plan.py --samples 128 --out /tmp/robust.json

The uncertainty is a fit-like normal distribution of `r_m[2]`, `j`, `I[2,2]`, `I0` (relative
standard deviations 3 %, 20 %, 10 %, 5 %). Prints a table and writes
`benchmarks/results-robust-plan.json` with machine information.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jsphere
from jsphere.model.names import get_value
from jsphere.planning.uncertainty import Uncertainty

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

NAMES = ("r_m[2]", "j", "I[2,2]", "I0")
REL_SD = (0.03, 0.2, 0.1, 0.05)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--to", nargs=2, type=float, default=(0.6, 0.3))
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--quantile", type=float, default=0.95)
    ap.add_argument("--check-samples", type=int, default=1000)
    ap.add_argument("--loop", type=int, default=3, help="simulate calls timed for the loop baseline")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-robust-plan.json")))
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    vals = np.array([float(get_value(p, n)) for n in NAMES])
    unc = Uncertainty(NAMES, ("normal",) * 4, vals, np.abs(vals) * np.array(REL_SD), np.eye(4), "benchmark")
    to = tuple(args.to)

    t0 = time.perf_counter()
    nominal = jsphere.plan(p, to, restarts=4, progress=False, allow_infeasible=True)
    t_nominal = time.perf_counter() - t0
    t0 = time.perf_counter()
    rp = jsphere.plan_robust(
        p,
        to,
        unc,
        samples=args.samples,
        quantile=args.quantile,
        check_samples=args.check_samples,
        nominal=nominal,
        progress=False,
    )
    t_robust = time.perf_counter() - t0

    _, fresh = unc.draw(p, args.check_samples, seed=7)
    jsphere.miss_distribution(rp.plan, jax.tree_util.tree_map(lambda v: v[:2], fresh))  # compile
    t0 = time.perf_counter()
    jsphere.miss_distribution(rp.plan, fresh)
    t_vmap = time.perf_counter() - t0
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
        ("uncertain parameters", ", ".join(NAMES)),
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
    w = max(len(a) for a, _ in rows)
    for a, b in rows:
        print(f"{a.ljust(w)}  {b}")
    info = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_count": os.cpu_count(),
            "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
            "python": platform.python_version(),
        },
        "target": list(to),
        "names": list(NAMES),
        "relative_sd": list(REL_SD),
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
    from jsphere._runtime.files import atomic_write_json

    atomic_write_json(args.out, info)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
