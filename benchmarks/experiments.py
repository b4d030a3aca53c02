"""Side experiments recorded in docs/performance.md (not part of run.py; user-level knobs only,
the package is not modified).

    python benchmarks/experiments.py [--big]

Problem 1 of run.py (same trials, same tolerances), timed with:
- `solver=diffrax.Tsit5()` vs `solver=diffrax.Dopri8()` (a public argument of `simulate`),
  at batch 1 and 64, whatever the package's default is;
- batch 1024 (Tsit5) as one `vmap` vs `jax.lax.map(..., batch_size=64)` (vmap in chunks of 64).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import diffrax as dfx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jsphere  # noqa: E402

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

p = jsphere.RobotParams.paper()
PH = jnp.array([0.0, 2.1, 4.2])
A = jnp.asarray(0.05 * (1 + 0.1 * np.random.default_rng(0).standard_normal((1024, 3))))


def one(a, solver=None):  # solver=None: the package's default
    return jsphere.simulate(
        p,
        jsphere.State.at_rest(p),
        jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)),
        4.0,
        rtol=1e-8,
        atol=1e-10,
        solver=solver,
    )


def bench(f, a, n=3):
    jax.block_until_ready(f(a))
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        r = jax.block_until_ready(f(a))
        ts.append(time.perf_counter() - t)
    return statistics.median(ts), r


ref = None
print("package default solver:", type(jsphere.solve.simulate.default_solver()).__name__)
for name, solver in (("Tsit5", dfx.Tsit5()), ("Dopri8", dfx.Dopri8())):
    f = jax.jit(jax.vmap(lambda a: one(a, solver)))
    for B in (1, 64):
        t, r = bench(f, A[:B], 5 if B == 1 else 3)
        x0 = float(r.x[0, -1])
        ref = x0 if ref is None else ref
        print(
            f"{name:<16} batch {B:>5}: {B / t:8.1f} trials/s, steps mean {float(r.num_steps.mean()):.0f} "
            f"max {int(r.num_steps.max())}, x_final[0] - Tsit5's = {x0 - ref:+.1e} m"
        )


def one_tsit5(a):
    return one(a, dfx.Tsit5())


f_vmap = jax.jit(jax.vmap(one_tsit5))
f_map = jax.jit(lambda A: jax.lax.map(one_tsit5, A, batch_size=64))
for name, f in (("vmap 1024", f_vmap), ("lax.map(batch_size=64) 1024", f_map)):
    t, r = bench(f, A, 2)
    print(f"{name:<28}: {1024 / t:8.1f} trials/s")

# Gradient of problem 3 at batch 64: reverse mode (jax.grad, the package's default
# RecursiveCheckpointAdjoint) vs forward mode (jax.jacfwd with adjoint=diffrax.ForwardMode(),
# 7 tangent directions), both relative to the forward pass; package-default solver.
import equinox as eqx  # noqa: E402


def with_theta(theta):
    I = p.I.at[jnp.diag_indices(3)].set(theta[2:5])
    return eqx.tree_at(
        lambda q: (q.r_m, q.j, q.I, q.m0, q.I0), p, (p.r_m.at[2].set(theta[0]), theta[1], I, theta[5], theta[6])
    )


def loss(theta, A, adjoint=None):
    q = with_theta(theta)
    tr = jax.vmap(
        lambda a: jsphere.simulate(
            q,
            jsphere.State.at_rest(q),
            jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)),
            4.0,
            rtol=1e-8,
            atol=1e-10,
            adjoint=adjoint,
        )
    )(A)
    return jnp.sum(tr.x[:, -1] ** 2 + tr.y[:, -1] ** 2)


theta0 = jnp.stack([p.r_m[2], p.j, p.I[0, 0], p.I[1, 1], p.I[2, 2], p.m0, p.I0])
A64 = A[:64]
t_f, _ = bench(jax.jit(lambda A: loss(theta0, A)), A64)
t_r, g_r = bench(jax.jit(lambda A: jax.grad(loss)(theta0, A)), A64)
t_j, g_j = bench(jax.jit(lambda A: jax.jacfwd(lambda th: loss(th, A, dfx.ForwardMode()))(theta0)), A64)
print(
    f"batch 64: forward {t_f:.3f} s, jax.grad {t_r:.3f} s ({t_r / t_f:.1f}x), "
    f"jacfwd+ForwardMode {t_j:.3f} s ({t_j / t_f:.1f}x), max rel diff {float(jnp.max(jnp.abs(g_j / g_r - 1))):.1e}"
)

# Optional (--big, a few minutes): batch 16384 with the package-default solver as one vmap vs
# lax.map in chunks of 1024 and of 64.
if "--big" in sys.argv:
    A16 = jnp.asarray(0.05 * (1 + 0.1 * np.random.default_rng(0).standard_normal((16384, 3))))
    for name, f in (
        ("vmap 16384", jax.jit(jax.vmap(one))),
        ("lax.map(batch_size=1024) 16384", jax.jit(lambda A: jax.lax.map(one, A, batch_size=1024))),
        ("lax.map(batch_size=64) 16384", jax.jit(lambda A: jax.lax.map(one, A, batch_size=64))),
    ):
        t, r = bench(f, A16, 1)
        print(f"{name:<32}: {16384 / t:8.1f} trials/s, steps max {int(r.num_steps.max())}")
