"""The planner's search model against a baseline tree's, in one process, alternating calls.

    git archive main | tar -x -C /tmp/base          # the baseline: any checkout of jsphere
    python benchmarks/fixed_grid.py --baseline /tmp/base

Compiles, for both trees, the vmapped forward-mode Jacobian of the planner's residuals
(`jsphere.planning.residuals._residuals`: RK4 rollout, outputs, limits) over 4 targets x 8
restarts, then times the two compiled programs in alternation, so that the load of a shared
machine hits both alike. Prints a table and writes `benchmarks/results-fixed-grid.json` with
the median ratio (this tree / baseline) and the largest difference of the Jacobians.
"""

from __future__ import annotations

import argparse
import importlib
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _compiled(name: str):
    J = importlib.import_module(name)
    problem = importlib.import_module(name + ".planning.problem")
    residuals = importlib.import_module(name + ".planning.residuals")
    search = importlib.import_module(name + ".planning.search")
    p, s = J.RobotParams.paper(), J.PlanSettings()
    lim, obj = J.Limits(), J.Objective()
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), m) for m in (lim, obj))
    tg = problem._vec_targets([(0.5, 0.3), (-0.4, 0.8), (1.0, -0.5), (0.2, 0.2)])
    z0 = jnp.asarray(search._initial_guesses(p, tg, 8, lim, s, 0).reshape(len(tg) * 8, -1))
    tgt = jnp.repeat(jnp.asarray(tg), 8, axis=0)

    def jac(z, t):
        return jax.jacfwd(lambda z: residuals._residuals(z, t, p, lim_a, obj_a, s))(z)

    t0 = time.perf_counter()
    c = jax.jit(jax.vmap(jac)).lower(z0, tgt).compile()
    return c, (z0, tgt), time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--baseline", required=True, help="a checkout of jsphere to compare with")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-fixed-grid.json")))
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    tmp = Path(tempfile.mkdtemp())
    shutil.copytree(Path(args.baseline) / "jsphere", tmp / "jsphere_base")
    sys.path[:0] = [str(tmp), str(ROOT)]
    trees = {name: _compiled(name) for name in ("jsphere_base", "jsphere")}
    runs = {name: [] for name in trees}
    outs = {}
    for _ in range(args.repeats):
        for name, (c, a, _) in trees.items():
            t0 = time.perf_counter()
            outs[name] = jax.block_until_ready(c(*a))
            runs[name].append(time.perf_counter() - t0)
    ratio = float(np.median(np.array(runs["jsphere"]) / np.array(runs["jsphere_base"])))
    info = {
        name: {"compile_s": trees[name][2], "run_min_s": min(r), "run_median_s": float(np.median(r))}
        for name, r in runs.items()
    }
    info["median_ratio"] = ratio
    info["max_abs_jacobian_difference"] = float(jnp.max(jnp.abs(outs["jsphere"] - outs["jsphere_base"])))
    for name in trees:
        print(f"{name:14s} compile {info[name]['compile_s']:7.1f} s   run median {info[name]['run_median_s']:.4f} s")
    print(
        f"median ratio (this tree / baseline) {ratio:.3f}; max |J difference| {info['max_abs_jacobian_difference']:.2e}"
    )
    Path(args.out).write_text(json.dumps(info, indent=2) + "\n")
    shutil.rmtree(tmp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
