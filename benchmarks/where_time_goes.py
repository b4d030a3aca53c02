"""Where does the time of problem 1 go? Splits one vmapped solve into its parts.

    python benchmarks/where_time_goes.py [--batches 1 64 1024] [--out benchmarks/results-where.json]

For each batch size, in one process (ratios are what matter on a noisy machine; each entry is
the *minimum* of several calls, the least disturbed by other processes):

1. `public`: problem 1 through the public API, exactly as `run.py` times it (diffrax `Dopri8`,
   PID controller, rtol 1e-8, atol 1e-10).
2. `rhs`: the right-hand side alone: 1300 evaluations of jsphere's torque-mode vector field
   per trial (about what one solve makes: ~100 steps x 13 stages) in a `fori_loop`, vmapped.
   Gives ns per trial-evaluation.
3. `diffrax_loop`: the same diffrax solver, controller and tolerances on a trivial 19-state
   field (`y' = cos(40 t)`) that forces ~180 steps: the cost of diffrax's step loop without
   the physics, in us per trial-step.
4. `lean_loop`: an experiment, not part of jsphere: a hand-written adaptive loop around the
   same field with diffrax's own `Dopri8` Butcher tableau (stages unrolled, I-controller,
   `lax.while_loop`), to see what the loop costs when it is only what this problem needs.

The prediction for `public` is `steps x (13 x rhs + loop)`; the JSON keeps both.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import diffrax as dfx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jsphere  # noqa: E402
from jsphere.model.params import derive  # noqa: E402
from jsphere.solve.batched.field_args import FieldArgs  # noqa: E402
from jsphere.solve.simulate import _torque_field  # noqa: E402

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

PH = jnp.array([0.0, 2.1, 4.2])
EVALS = 1300


def best_of(f, *args, reps=5):
    t = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t)
    return out, first, min(ts)


class Sine(jsphere.Zero.__base__):
    """`K(t) = a sin(pi t + phases)` as a Module (so the experiments compile once)."""

    a: jax.Array

    def __call__(self, t):
        return self.a * jnp.sin(jnp.pi * t + PH)


def public(p, A):
    f = jax.jit(
        jax.vmap(
            lambda a: (lambda tr: (tr.x[-1], tr.num_steps))(
                jsphere.simulate(
                    p,
                    jsphere.State.at_rest(p),
                    jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)),
                    4.0,
                    rtol=1e-8,
                    atol=1e-10,
                )
            )
        )
    )
    (x, steps), first, best = best_of(f, A)
    return {
        "s": best,
        "first_s": first,
        "steps_mean": float(steps.mean()),
        "steps_max": int(steps.max()),
        "x0": float(x[0]),
    }


def rhs_only(p, A):
    d = derive(p)
    z0 = jsphere.State.at_rest(p).flatten()

    def loop(a):
        ctrl = jsphere.Torques(Sine(a))
        return jax.lax.fori_loop(
            0, EVALS, lambda i, z: z + 1e-6 * _torque_field(i * 1e-3, z, FieldArgs(p, d, ctrl, 0.0, 4.0)), z0
        )

    _, first, best = best_of(jax.jit(jax.vmap(loop)), A)
    return {"s": best, "ns_per_trial_eval": best / EVALS / A.shape[0] * 1e9}


def diffrax_loop(A):
    def solve(a):
        term = dfx.ODETerm(lambda t, y, args: jnp.cos(40.0 * t) * jnp.ones_like(y) + 0.0 * args[0])
        sol = dfx.diffeqsolve(
            term,
            dfx.Dopri8(),
            0.0,
            4.0,
            None,
            jnp.zeros(19),
            a,
            saveat=dfx.SaveAt(t1=True),
            stepsize_controller=dfx.PIDController(rtol=1e-8, atol=1e-10),
            max_steps=16384,
            throw=False,
        )
        return sol.stats["num_accepted_steps"]

    steps, first, best = best_of(jax.jit(jax.vmap(solve)), A)
    return {"s": best, "steps": int(steps.max()), "us_per_trial_step": best / int(steps.max()) / A.shape[0] * 1e6}


def _lean_solve(f, t0, t1, y0, rtol, atol, max_steps=16384):
    tab = dfx.Dopri8.tableau
    c = [float(v) for v in tab.c]
    a_lower = [np.asarray(v, float) for v in tab.a_lower]
    b_sol, b_err = np.asarray(tab.b_sol, float), np.asarray(tab.b_error, float)

    def combo(coefs, ks):
        return sum(float(w) * k for w, k in zip(coefs, ks) if w != 0.0)

    def step(t, y, k0, h):
        ks = [k0]
        for i, a in enumerate(a_lower):
            ks.append(f(t + c[i] * h, y + h * combo(a, ks)))
        return y + h * combo(b_sol, ks), h * combo(b_err, ks), ks[-1]

    def norm(e, y, yn):
        return jnp.sqrt(jnp.mean((e / (atol + rtol * jnp.maximum(jnp.abs(y), jnp.abs(yn)))) ** 2))

    def body(carry):
        t, y, k, h, n = carry
        h = jnp.minimum(h, t1 - t)
        yn, err, kn = step(t, y, k, h)
        e = norm(err, y, yn)
        ok = e <= 1.0
        fac = jnp.clip(0.9 * jnp.maximum(e, 1e-10) ** (-1.0 / 8.0), 0.2, 10.0)
        t_new = jnp.where(ok, jnp.where(h >= t1 - t, t1, t + h), t)
        return t_new, jnp.where(ok, yn, y), jnp.where(ok, kn, k), h * fac, n + ok.astype(jnp.int32)

    k0 = f(t0, y0)
    init = (jnp.asarray(t0, y0.dtype), y0, k0, jnp.asarray(1e-3, y0.dtype), jnp.asarray(0, jnp.int32))
    t, y, _, _, n = jax.lax.while_loop(lambda c: (c[0] < t1) & (c[4] < max_steps), body, init)
    return y, n


def lean_loop(p, A):
    d = derive(p)
    z0 = jsphere.State.at_rest(p).flatten()

    def one(a):
        ctrl = jsphere.Torques(Sine(a))
        y, n = _lean_solve(lambda t, z: _torque_field(t, z, FieldArgs(p, d, ctrl, 0.0, 4.0)), 0.0, 4.0, z0, 1e-8, 1e-10)
        return y[14], n

    (x, n), first, best = best_of(jax.jit(jax.vmap(one)), A)
    return {"s": best, "first_s": first, "steps_mean": float(n.mean()), "steps_max": int(n.max()), "x0": float(x[0])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--out", type=Path, default=HERE / "results-where.json")
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    rows = []
    for B in args.batches:
        A = jnp.asarray(0.05 * (1 + 0.1 * np.random.default_rng(0).standard_normal((B, 3))))
        r = {
            "batch": B,
            "public": public(p, A),
            "rhs": rhs_only(p, A),
            "diffrax_loop": diffrax_loop(A),
            "lean_loop": lean_loop(p, A),
        }
        steps = r["public"]["steps_max"]
        rhs_s = 13 * steps * r["rhs"]["ns_per_trial_eval"] * 1e-9 * B
        r["predicted_public_s"] = rhs_s + steps * r["diffrax_loop"]["us_per_trial_step"] * 1e-6 * B
        r["rhs_share_of_public"] = rhs_s / r["public"]["s"]
        rows.append(r)
        print(
            f"B={B:>5}: public {B / r['public']['s']:8.0f} trials/s ({r['public']['steps_max']} steps) | rhs {r['rhs']['ns_per_trial_eval']:6.0f} ns/eval"
            f" | diffrax loop {r['diffrax_loop']['us_per_trial_step']:6.2f} us/trial-step | lean loop {B / r['lean_loop']['s']:8.0f} trials/s"
            f" | predicted {B / r['predicted_public_s']:8.0f} trials/s, rhs share {r['rhs_share_of_public']:.0%}",
            flush=True,
        )
    info = {
        "jax": jax.__version__,
        "diffrax": dfx.__version__ if hasattr(dfx, "__version__") else None,
        "device": str(jax.devices()[0]),
        "rows": rows,
    }
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(info, indent=2) + "\n")
    tmp.replace(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
