"""Solvers and integrators of the planner and of `jsphere reproduce`, each next to its
alternative, in one run (time and success):

- search: Adam then Levenberg-Marquardt per (target, restart), the package's fused
  Adam + LM scan next to an Adam scan followed by `optimistix.LevenbergMarquardt`;
- integrator: the search model's hand-written RK4 scan next to diffrax with an RK4 tableau
  and `ConstantStepSize` (forward-mode Jacobian of the residuals, as in the search);
- full stop: the braking gait of Section 5.2 by Newton with a finite-difference Jacobian
  (`full_stop_brake`, as `jsphere reproduce` runs it) next to `optimistix.GaussNewton` with
  the reverse-mode Jacobian of the accurate solver (the same derivative that an optimistix
  version of `plan_many`'s bias correction would need).

    python benchmarks/solvers.py [--only search,integrator,full_stop] [--out benchmarks/results-solvers.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jsphere
from jsphere.gaits.gaits import _gait_field, acceleration, braking, simulate_gaits, turn
from jsphere.model.kinematics import rest_attitude
from jsphere.model.params import derive
from jsphere.model.rotations import rotation_between
from jsphere.model.state import State
from jsphere.paper.reproduce import full_stop_brake
from jsphere.planning import rollout as rollout_mod
from jsphere.planning import search
from jsphere.planning.problem import Limits, Objective, PlanSettings, _vec_targets
from jsphere.planning.residuals import _residuals, _residuals_and_jacobian
from jsphere.solve.batched.field_args import FieldArgs

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

TARGETS = [(0.8, -0.5, 1.0), (-0.5, -0.4), (1.0, 1.0), (-1.0, 0.35)]


def _timed(f, *a):
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(*a))
    return out, time.perf_counter() - t0


# ------------------------------------------------------------------ search: optimistix LM


def _search_one_optimistix(z0, target, params, lim, obj, s):
    """Adam (a scan with the forward-mode Jacobian, as in the package) then at most `lm_steps`
    steps of `optimistix.LevenbergMarquardt` from the best Adam point."""
    opt = optax.adam(s.learning_rate)

    def body(c, _):
        z, zb, fb, st = c
        r, J = _residuals_and_jacobian(z, target, params, lim, obj, s)
        f = jnp.sum(r**2)
        ok = jnp.isfinite(f) & jnp.all(jnp.isfinite(J))
        better = ok & (f < fb)
        zb, fb = jnp.where(better, z, zb), jnp.where(better, f, fb)
        up, st = opt.update(jnp.where(ok, 2.0 * J.T @ r, 0.0), st, z)
        return (jnp.where(ok, optax.apply_updates(z, up), zb), zb, fb, st), f

    (_, zb, fb, _), hist = jax.lax.scan(
        body, (z0, z0, jnp.asarray(jnp.inf, z0.dtype), opt.init(z0)), None, length=s.adam_steps
    )
    sol = optx.least_squares(
        lambda z, _: _residuals(z, target, params, lim, obj, s),
        optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10),
        zb,
        max_steps=s.lm_steps,
        throw=False,
    )
    f = jnp.sum(_residuals(sol.value, target, params, lim, obj, s) ** 2)
    better = jnp.isfinite(f) & (f < fb)
    return jnp.where(better, sol.value, zb), jnp.where(better, f, fb), None, hist


def bench_search(p, restarts):
    s, lim, obj = PlanSettings(), Limits(), Objective()
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), m) for m in (lim, obj))
    tg = _vec_targets(TARGETS)
    z0 = search._initial_guesses(p, tg, restarts, lim, s, 0).reshape(-1, 2 * s.n_tilt + s.n_spin + 1)
    tgt = jnp.repeat(jnp.asarray(tg), restarts, axis=0)
    scales = np.array([obj.position_scale] * 2 + [obj.speed_scale] * 3)
    rows = {}
    for name, one in (
        ("hand-written Adam + LM scan", search._search_one),
        ("Adam + optimistix LM", _search_one_optimistix),
    ):
        f = jax.jit(jax.vmap(lambda z, t, one=one: one(z, t, p, lim_a, obj_a, s)[:2]))
        t0 = time.perf_counter()
        c = f.lower(z0, tgt).compile()
        t_compile = time.perf_counter() - t0
        (z, loss), t_run = _timed(c, z0, tgt)
        r = np.asarray(jax.vmap(lambda z, t: _residuals(z, t, p, lim_a, obj_a, s))(z, tgt))
        pos = np.hypot(r[:, 0], r[:, 1]) * scales[0]
        speed = np.linalg.norm(r[:, 2:5], axis=1) * scales[2]
        ok = (pos < 5e-4) & (speed < 5e-4)
        best = np.asarray(loss).reshape(len(tg), restarts).min(axis=1)
        rows[name] = {
            "compile_s": t_compile,
            "run_s": t_run,
            "restarts_within_0.5mm_0.5mm_s": int(ok.sum()),
            "problems": int(ok.size),
            "best_loss_per_target": best.tolist(),
        }
    return rows


# ------------------------------------------------------------------ integrator: diffrax RK4


class _RK4(diffrax.AbstractERK):
    """Classical RK4 as a diffrax tableau (no error estimate: constant steps only)."""

    tableau = diffrax.ButcherTableau(
        a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
        b_error=np.zeros(4),
        c=np.array([0.5, 0.5, 1.0]),
    )
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 4


def _states_diffrax(p, gait, n):
    dt = p.R0.dtype
    Qm = rotation_between(jnp.array([0.0, 0.0, 1.0], dt), rest_attitude(p))
    T = jnp.asarray(gait.T, dt)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_gait_field),
        _RK4(),
        0.0,
        T,
        T / n,
        State.at_rest(p).flatten().astype(dt),
        args=FieldArgs(p, derive(p), (gait, Qm), jnp.zeros((), dt), T),
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(t0=True, steps=True),
        max_steps=n,
        adjoint=diffrax.ForwardMode(),
    )
    return sol.ys


def bench_integrator(p, restarts, repeats=5):
    s, lim, obj = PlanSettings(), Limits(), Objective()
    lim_a, obj_a = (jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), m) for m in (lim, obj))
    tg = _vec_targets(TARGETS)
    z0 = search._initial_guesses(p, tg, restarts, lim, s, 0).reshape(-1, 2 * s.n_tilt + s.n_spin + 1)
    tgt = jnp.repeat(jnp.asarray(tg), restarts, axis=0)
    scan_states = rollout_mod._states

    variants = {"hand-written RK4 scan": scan_states, "diffrax RK4, ConstantStepSize": _states_diffrax}
    compiled, rows, outs = {}, {}, {}
    for name, states in variants.items():
        rollout_mod._states = states
        f = jax.jit(jax.vmap(lambda z, t: _residuals_and_jacobian(z, t, p, lim_a, obj_a, s)))
        t0 = time.perf_counter()
        compiled[name] = f.lower(z0, tgt).compile()
        rows[name] = {"compile_s": time.perf_counter() - t0, "run_s": []}
    rollout_mod._states = scan_states
    for _ in range(repeats):  # interleaved, so that the machine's load hits both alike
        for name, c in compiled.items():
            outs[name], t = _timed(c, z0, tgt)
            rows[name]["run_s"].append(t)
    a, b = outs.values()
    for name in rows:
        rows[name]["run_median_s"] = float(np.median(rows[name]["run_s"]))
    rows["max |J difference|"] = float(jnp.max(jnp.abs(a[1] - b[1])))
    rows["problems"] = int(z0.shape[0])
    return rows


# ------------------------------------------------------------------ full stop: FD Newton vs optimistix


def bench_full_stop(p):
    def fn(x, _):
        g = [acceleration(), turn(), braking(theta_max=x[0], phi=x[1])]
        T = sum(jnp.asarray(gg.T) for gg in g)
        return simulate_gaits(p, g, ts=jnp.reshape(T, (1,)), rtol=1e-10, atol=1e-12).Omega[-1, :2]

    @eqx.filter_jit
    def optimistix_newton(x0):
        sol = optx.least_squares(
            fn, optx.GaussNewton(rtol=0.0, atol=1e-12), x0, options={"jac": "bwd"}, max_steps=8, throw=False
        )
        return sol.value

    rows = {}
    full_stop_brake(p, iters=1)  # the forward program compiled, as in `jsphere reproduce` before this step
    (th, ph, res), t = _timed(full_stop_brake, p)
    rows["finite-difference Newton"] = {"s": t, "theta_max": th, "phi": ph, "residual": float(np.max(np.abs(res)))}
    x, t = _timed(optimistix_newton, jnp.array([0.1, math.pi / 4]))
    res = fn(x, None)
    rows["optimistix GaussNewton (reverse mode)"] = {
        "s": t,
        "theta_max": float(x[0]),
        "phi": float(x[1]),
        "residual": float(jnp.max(jnp.abs(res))),
    }
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default="search,integrator,full_stop")
    ap.add_argument("--restarts", type=int, default=4, help="restarts per target (4 targets)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-solvers.json")))
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    out = {
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "jax": jax.__version__,
            "optimistix": optx.__version__,
            "diffrax": diffrax.__version__,
        }
    }
    benches = {
        "search": lambda: bench_search(p, args.restarts),
        "integrator": lambda: bench_integrator(p, args.restarts),
        "full_stop": lambda: bench_full_stop(p),
    }
    for name in args.only.split(","):
        out[name] = benches[name]()
        print(f"== {name}")
        for k, v in out[name].items():
            if isinstance(v, dict):
                v = {a: (f"{b:.4g}" if isinstance(b, float) else b) for a, b in v.items() if not isinstance(b, list)}
            print(f"  {k:40s} {v}")
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
