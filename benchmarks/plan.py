"""Planning benchmark: restarts x targets optimised in one vmapped, compiled call.

    python benchmarks/plan.py                       # measure 16 x 16, extrapolate to 256 x 16
    python benchmarks/plan.py --restarts 256        # the full 256 x 16 run (about 80 min on 2 cores)
    python benchmarks/plan.py --restarts 256 --adam 4 --lm 3 --out benchmarks/results-plan-256x16-short.json
                                                    # 256 x 16 in one call, few iterations (time per iteration)

Prints a table and writes `benchmarks/results-plan.json` with machine information. The search
cost is linear in restarts x targets x iterations (every problem runs the same fixed number of
Adam and LM iterations), so time per (problem x iteration) measured at one size extrapolates.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jsphere
from jsphere.planning.problem import _vec_targets, gait_from_vector
from jsphere.planning.rollout import rollout
from jsphere.planning.search import _initial_guesses, _search

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

PLAN_DEFAULT_ITERATIONS = jsphere.PlanSettings().adam_steps + jsphere.PlanSettings().lm_steps + 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--restarts", type=int, default=16)
    ap.add_argument("--targets", type=int, default=16, help="targets on a grid over the 2 m x 2 m square")
    ap.add_argument("--adam", type=int, default=None, help="Adam steps (default: PlanSettings' 150)")
    ap.add_argument("--lm", type=int, default=None, help="LM steps (default: PlanSettings' 40)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-plan.json")))
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    s = jsphere.PlanSettings()
    if args.adam is not None or args.lm is not None:
        s = jsphere.PlanSettings(
            adam_steps=s.adam_steps if args.adam is None else args.adam,
            lm_steps=s.lm_steps if args.lm is None else args.lm,
        )
    lim, obj = jsphere.Limits(), jsphere.Objective()
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), m) for m in (lim, obj))
    k = round(np.sqrt(args.targets))
    xs = np.linspace(-1.0, 1.0, k)
    tg = _vec_targets([(x, y) for x in xs for y in xs][: args.targets])
    B, R = len(tg), args.restarts
    z0 = _initial_guesses(p, tg, R, lim, s, 0)
    t0 = time.perf_counter()
    lowered = _search.lower(p, jnp.asarray(tg), z0, lim_a, obj_a, s)
    compiled = lowered.compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    zf, loss, _, _, _ = jax.block_until_ready(compiled(p, jnp.asarray(tg), z0, lim_a, obj_a, s))
    t_run = time.perf_counter() - t0
    iters = s.adam_steps + s.lm_steps + 1
    per = t_run / (B * R * iters)
    full = 256 * 16 * (PLAN_DEFAULT_ITERATIONS) * per
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
    w = max(len(a) for a, _ in rows)
    for a, b_ in rows:
        print(f"{a.ljust(w)}  {b_}")
    info = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_count": os.cpu_count(),
            "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
            "python": platform.python_version(),
        },
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
    }
    Path(args.out).write_text(json.dumps(info, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
