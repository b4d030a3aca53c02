"""A jitted gradient of one solve with respect to few scalars: forward mode (what jsphere does
up to `TRACED_FORWARD_MAX_INPUTS` perturbed scalars, reverse mode above) against reverse mode,
in one process.

    python benchmarks/traced_gradient.py [--repeats 15] [--out benchmarks/results-traced-gradient.json]

The solve is one trial of problem 1 of `run.py` (its first amplitudes, 4 s, rtol 1e-8, atol
1e-10, the paper's robot with `R_m = 0.03`, `j = 1e-4`); the loss is the squared distance of
its end point. For the first 1, 2, 4, 6 and 8 of the robot's scalars `j, m0, I0, m, c_roll,
c_axle, g, R0` (none moves the state at rest, so these are the solve's only perturbed
inputs), `jax.jit(jax.grad(loss))` is compiled twice:
in forward mode (the threshold raised above the count) and in reverse mode (the threshold 0:
the recomputed solve's checkpointed VJP); `mode_taken` says which the package's threshold
picks. The calls alternate; each time is the median of `--repeats` calls, as is
the forward solve's. Prints a table, writes the JSON atomically.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # this checkout's jsphere first
sys.path.insert(0, str(HERE))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import run  # noqa: E402  (problem 1's amplitudes and phases, JSON writing, environment)

import jsphere  # noqa: E402
from jsphere.solve.batched import dispatch  # noqa: E402

jsphere.enable_x64()

P0 = jsphere.RobotParams.paper(R_m=0.03, j=1e-4)
#: the robot's scalars differentiated, by count (none of them moves the state at rest, so the
#: count is the solve's number of perturbed input scalars)
NAMES = ("j", "m0", "I0", "m", "c_roll", "c_axle", "g", "R0")
COUNTS = (1, 2, 4, 6, 8)


def maker(k: int):
    names = NAMES[:k]
    return lambda p, th: eqx.tree_at(lambda q: tuple(getattr(q, n) for n in names), p, tuple(th))


def loss_of(make):
    phases = jnp.asarray(run.PHASES)

    def loss(theta, a):
        p = make(P0, theta)
        tq = jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + phases))
        tr = jsphere.simulate(p, jsphere.State.at_rest(p), tq, run.T1, rtol=run.RTOL, atol=run.ATOL)
        return tr.x[-1] ** 2 + tr.y[-1] ** 2

    return loss


def compiled(fn, *args):
    return jax.jit(fn).lower(*args).compile()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", type=Path, default=HERE / "results-traced-gradient.json")
    args = ap.parse_args(argv)
    a = jnp.asarray(run.amplitudes(np.random.default_rng(0).standard_normal((1, 3)))[0])
    threshold = dispatch.TRACED_FORWARD_MAX_INPUTS
    rows = []
    for count in COUNTS:
        name = ", ".join(NAMES[:count])
        theta = jnp.stack([getattr(P0, n) for n in NAMES[:count]])
        loss = loss_of(maker(count))
        fns = {"forward_solve": compiled(loss, theta, a)}
        try:  # the mode is chosen while the gradient is traced
            for mode, limit in (("forward_mode", 10**6), ("reverse_mode", 0)):
                dispatch.TRACED_FORWARD_MAX_INPUTS = limit
                fns[mode] = compiled(jax.grad(loss), theta, a)
        finally:
            dispatch.TRACED_FORWARD_MAX_INPUTS = threshold
        g = {k: np.asarray(f(theta, a)) for k, f in fns.items()}
        times = {k: [] for k in fns}
        for _ in range(args.repeats):
            for k, f in fns.items():
                t = time.perf_counter()
                jax.block_until_ready(f(theta, a))
                times[k].append(time.perf_counter() - t)
        med = {k: statistics.median(v) for k, v in times.items()}
        scalars = count
        row = {
            "inputs": name,
            "scalars": scalars,
            "mode_taken": "forward" if scalars <= threshold else "reverse",
            "forward_solve_s": med["forward_solve"],
            "forward_mode_s": med["forward_mode"],
            "reverse_mode_s": med["reverse_mode"],
            "forward_over_reverse": med["forward_mode"] / med["reverse_mode"],
            "forward_mode_over_solve": med["forward_mode"] / med["forward_solve"],
            "reverse_mode_over_solve": med["reverse_mode"] / med["forward_solve"],
            "max_rel_diff": float(np.max(np.abs(g["forward_mode"] - g["reverse_mode"]) / np.abs(g["reverse_mode"]))),
        }
        rows.append(row)
        run.log(f"[{name}] forward {row['forward_mode_s'] * 1e3:.2f} ms, reverse {row['reverse_mode_s'] * 1e3:.2f} ms")
    hdr = f"{'inputs':<34}{'scalars':>8}{'solve ms':>10}{'fwd-mode ms':>13}{'rev-mode ms':>13}{'fwd/rev':>9}{'grad/solve':>12}{'rel diff':>10}"
    table = [hdr, "-" * len(hdr)]
    for r in rows:
        best = min(r["forward_mode_over_solve"], r["reverse_mode_over_solve"])
        table.append(
            f"{r['inputs']:<34}{r['scalars']:>8}{r['forward_solve_s'] * 1e3:>10.2f}{r['forward_mode_s'] * 1e3:>13.2f}"
            f"{r['reverse_mode_s'] * 1e3:>13.2f}{r['forward_over_reverse']:>8.2f}x{best:>11.2f}x{r['max_rel_diff']:>10.0e}"
        )
    print("\n".join(table))
    env = run.environment()
    run.write_json_atomic(
        args.out, {**env, "threshold": threshold, "repeats": args.repeats, "rows": rows, "table": table}
    )
    print(f"JSON written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
