"""A/B in one process: the flat state layout against the component layout of batched solves.

    python benchmarks/layouts.py [--batches 64 1024 4096] [--grad-batch 64] [--out benchmarks/results-layouts.json]

Problem 1 of `run.py` (paper robot, `K_i = a_i sin(pi t + 2.1 (i - 1))`, 4 s, rtol 1e-8, atol
1e-10) through the public API, `jax.jit(jax.vmap(lambda a: simulate(...)))`, once with
`batch_steps="diffrax"` (diffrax's own `vmap`: every solve carries the flat `(16+N,)` state) and
once with the default (`"shared"`: under `vmap` the state is a tuple of scalar components,
`jsphere.solve.batched.components`, in the batch loop). Both variants are compiled and timed in the
same process, alternating, so the ratio is meaningful on a noisy machine. Also: the reverse-mode
gradient of problem 3 (batch-summed squared final positions w.r.t. 7 parameters) over the
forward time, both layouts. Prints a table; writes JSON atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jsphere  # noqa: E402
from jsphere._runtime.files import atomic_write_text  # noqa: E402

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

PH = jnp.array([0.0, 2.1, 4.2])


def _steps(flag: bool) -> str:
    """`batch_steps` of a variant: the component layout (`True`) or diffrax's flat `vmap`."""
    return "shared" if flag else "diffrax"


def _p1(p, flag):
    def one(a):
        tr = jsphere.simulate(
            p,
            jsphere.State.at_rest(p),
            jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)),
            4.0,
            rtol=1e-8,
            atol=1e-10,
            batch_steps=_steps(flag),
        )
        return tr.x[-1], tr.y[-1], tr.num_steps

    return jax.jit(jax.vmap(one))


def _p3(p0, flag):
    def loss(theta, A):
        I = p0.I.at[jnp.diag_indices(3)].set(theta[2:5])
        p = eqx.tree_at(
            lambda q: (q.r_m, q.j, q.I, q.m0, q.I0), p0, (p0.r_m.at[2].set(theta[0]), theta[1], I, theta[5], theta[6])
        )
        xy = _p1_traced(p, A, flag)
        return jnp.sum(xy[0] ** 2 + xy[1] ** 2)

    theta = jnp.stack([p0.r_m[2], p0.j, p0.I[0, 0], p0.I[1, 1], p0.I[2, 2], p0.m0, p0.I0])
    return jax.jit(loss), jax.jit(jax.grad(loss)), theta


def _p1_traced(p, A, flag):
    tr = jax.vmap(
        lambda a: jsphere.simulate(
            p,
            jsphere.State.at_rest(p),
            jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)),
            4.0,
            rtol=1e-8,
            atol=1e-10,
            batch_steps=_steps(flag),
        )
    )(A)
    return tr.x[:, -1], tr.y[:, -1]


def _time(f, *args, reps=3):
    t = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t)
    return out, first, float(np.median(ts)), ts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[64, 1024, 4096])
    ap.add_argument("--grad-batch", type=int, default=64)
    ap.add_argument("--out", type=Path, default=HERE / "results-layouts.json")
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    Z = np.random.default_rng(0).standard_normal((max(args.batches + [args.grad_batch]), 3))
    rows, lines = [], []
    hdr = f"{'problem':<28}{'batch':>7}{'flat /s':>11}{'components /s':>15}{'ratio':>8}{'compile flat/comp s':>22}{'max |dx| m':>12}"
    lines += [hdr, "-" * len(hdr)]
    for B in args.batches:
        A = jnp.asarray(0.05 * (1 + 0.1 * Z[:B]))
        res = {}
        for flag in (False, True):
            res[flag] = _time(_p1(p, flag), A)
            print(
                f"[P1 batch {B}] {'components' if flag else 'flat'}: {B / res[flag][2]:.0f}/s",
                file=sys.stderr,
                flush=True,
            )
        (xf, yf, nf), cf, mf, tf = res[False]
        (xc, yc, nc), cc, mc, tc = res[True]
        dx = float(max(jnp.max(jnp.abs(xf - xc)), jnp.max(jnp.abs(yf - yc))))
        rows.append(
            {
                "problem": "P1",
                "batch": B,
                "flat": {"median_s": mf, "times_s": tf, "first_s": cf, "steps_max": int(nf.max())},
                "components": {"median_s": mc, "times_s": tc, "first_s": cc, "steps_max": int(nc.max())},
                "trials_per_s_flat": B / mf,
                "trials_per_s_components": B / mc,
                "ratio": mf / mc,
                "max_abs_diff_m": dx,
            }
        )
        lines.append(
            f"{'P1 torques, public API':<28}{B:>7}{B / mf:>11.0f}{B / mc:>15.0f}{mf / mc:>8.2f}{f'{cf - mf:.1f} / {cc - mc:.1f}':>22}{dx:>12.1e}"
        )
    B = args.grad_batch
    A = jnp.asarray(0.05 * (1 + 0.1 * Z[:B]))
    g = {}
    for flag in (False, True):

        def run():
            fwd, grad, theta = _p3(p, flag)
            return _time(fwd, theta, A), _time(grad, theta, A)

        g[flag] = run()
        print(f"[P3 batch {B}] {'components' if flag else 'flat'} done", file=sys.stderr, flush=True)
    gdiff = float(jnp.max(jnp.abs(g[False][1][0] - g[True][1][0]) / jnp.abs(g[False][1][0])))
    for flag in (False, True):
        (_, _, fm, _), (_, gc, gm, _) = g[flag]
        name = "components" if flag else "flat"
        rows.append(
            {
                "problem": "P3",
                "layout": name,
                "batch": B,
                "forward_median_s": fm,
                "grad_median_s": gm,
                "grad_over_forward": gm / fm,
                "grad_first_s": gc,
                "grad_rel_diff_between_layouts": gdiff,
            }
        )
        lines.append(
            f"{'P3 grad/forward, ' + name:<28}{B:>7}{'':>11}{gm / fm:>15.2f}{'':>8}{f'grad {gc - gm:.1f}':>22}{'':>12}"
        )
    lines.append(
        f"P3 gradients of the two layouts agree to {gdiff:.1e} (relative); P3 forward flat / components: "
        f"{g[False][0][2] / g[True][0][2]:.2f}x, grad flat / components: {g[False][1][2] / g[True][1][2]:.2f}x"
    )
    table = "\n".join(lines)
    print(table)
    out = {
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_count": os.cpu_count(),
            "loadavg": os.getloadavg(),
        },
        "jax": {
            "backend": jax.default_backend(),
            "device_kind": jax.devices()[0].device_kind,
            "x64": bool(jax.config.jax_enable_x64),
        },
        "versions": {"jax": jax.__version__, "jsphere": getattr(jsphere, "__version__", None)},
        "rows": rows,
        "table": lines,
    }
    atomic_write_text(args.out, json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
