"""A/B in one process: problems 1 and 2 with a step size shared by the batch, against per-trial steps.

    python benchmarks/ensemble.py [--batches 64 1024 4096] [--out benchmarks/results-ensemble.json]

Problem 2 (the paper's acceleration + braking gaits, `theta_max` per trial, `simulate_gaits`
under `vmap`) is timed in three variants: the default (shared steps, components),
`batch_steps="per_trial"` (per-trial steps in lockstep), and the flat layout with per-trial
steps in diffrax's loop (`batch_steps="diffrax"`).

Problem 1 in three variants, compiled and timed in the same process: the public API as a user
writes it (`jax.jit(jax.vmap(simulate))`, its default `batch_steps="shared"`), the public API
with `batch_steps="per_trial"`, and the reference below: one `diffeqsolve` of the whole batch
with a shared step (docs/performance.md, "Shared steps for a batch"). Under
`jax.vmap`, diffrax runs one adaptive step-size controller per trial: every step of the batched
while loop carries per-trial times, step sizes, accept/reject selects and save logic, and runs
as many iterations as the slowest trial. Here the whole batch is *one* ODE system whose state
is a tuple of `(batch,)` component vectors (the right-hand side of `jsphere.solve.batched.components`, as in the
component layout), integrated by one unbatched `diffeqsolve` with one step size for all trials.
The error norm is the largest per-trial RMS norm, so every trial meets its own tolerance (the
shared step is the smallest any trial needs). Ensemble methods of other ODE suites share a step
in the same way; the price is that trials are no longer independent: a trial that needs tiny
steps slows its whole batch, and `max_steps` is shared.

Both variants are compiled and timed in the same process (`run.time_call`: medians of 3 or more calls after the first);
the final positions are compared. Prints a table; writes JSON atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import diffrax as dfx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from run import public as timings  # noqa: E402
from run import time_call  # noqa: E402

import jsphere  # noqa: E402
from jsphere._runtime.files import atomic_write_text  # noqa: E402
from jsphere.model.params import derive  # noqa: E402
from jsphere.solve.batched.components import torque_field_components  # noqa: E402

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

PH = jnp.array([0.0, 2.1, 4.2])
RTOL, ATOL, T1 = 1e-8, 1e-10, 4.0


def ensemble_solver(p):
    """`A (B, 3) -> (x_final, y_final, accepted steps, rejected steps)` with one shared step."""
    d = derive(p)
    z0 = jsphere.State.at_rest(p).flatten()

    def field(t, y, a):
        K = tuple(a[i] * jnp.sin(jnp.pi * t + PH[i]) for i in range(3))
        return torque_field_components(p, d, K, y)

    def worst_trial_rms(err):  # err: tuple of (B,) scaled errors; the max over trials of their RMS
        return jnp.sqrt(jnp.max(sum(e * e for e in err) / len(err)))

    @jax.jit
    def solve(A):
        y0 = tuple(jnp.full((A.shape[0],), z0[i]) for i in range(z0.shape[0]))
        sol = dfx.diffeqsolve(
            dfx.ODETerm(field),
            dfx.Dopri8(),
            0.0,
            T1,
            None,
            y0,
            tuple(A[:, i] for i in range(3)),
            saveat=dfx.SaveAt(t1=True),
            stepsize_controller=dfx.PIDController(rtol=RTOL, atol=ATOL, norm=worst_trial_rms),
            max_steps=16384,
        )
        return sol.ys[14][-1], sol.ys[15][-1], sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"]

    return solve


def public_solver(p, batch_steps="shared"):
    return jax.jit(
        jax.vmap(
            lambda a: jsphere.simulate(
                p,
                jsphere.State.at_rest(p),
                jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)),
                T1,
                rtol=RTOL,
                atol=ATOL,
                batch_steps=batch_steps,
            )
        )
    )


def problem2_rows(p, batches):
    """Problem 2 (`run.problem2`) per batch: shared, per-trial (components), per-trial flat."""
    TH = np.random.default_rng(1).uniform(0.05, 0.15, max(batches))
    rows = []
    for B in batches:
        th = jnp.asarray(TH[:B])
        out = {}
        for name, steps in (("shared", "shared"), ("per_trial", "per_trial"), ("per_trial_flat", "diffrax")):
            f = jax.jit(
                jax.vmap(
                    lambda t, steps=steps: jsphere.simulate_gaits(
                        p,
                        [jsphere.acceleration(theta_max=t), jsphere.braking(theta_max=t)],
                        ts=jnp.array([0.0, 4.0]),
                        batch_steps=steps,
                    )
                )
            )
            out[name] = time_call(f, th, repeats=3)
        ref = out["per_trial_flat"]["_out"]
        row = {"batch": B}
        for name, r in out.items():
            tr = r["_out"]
            row[name] = {
                **timings(r),
                "trials_per_s": B / r["median_s"],
                "steps_max": int(jnp.max(tr.num_steps)),
                "max_abs_diff_final_xy_m": float(
                    max(jnp.max(jnp.abs(tr.x[:, -1] - ref.x[:, -1])), jnp.max(jnp.abs(tr.y[:, -1] - ref.y[:, -1])))
                ),
            }
        row["ratio_shared_vs_flat"] = out["per_trial_flat"]["median_s"] / out["shared"]["median_s"]
        rows.append(row)
    hdr = f"{'P2 batch':>9}{'flat per-trial /s':>19}{'per-trial /s':>14}{'shared /s':>11}{'ratio':>7}{'steps':>7}{'max |dxy| m':>13}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(
            f"{r['batch']:>9}{r['per_trial_flat']['trials_per_s']:>19.0f}{r['per_trial']['trials_per_s']:>14.0f}"
            f"{r['shared']['trials_per_s']:>11.0f}{r['ratio_shared_vs_flat']:>7.2f}{r['shared']['steps_max']:>7}"
            f"{r['shared']['max_abs_diff_final_xy_m']:>13.1e}"
        )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[64, 1024, 4096])
    ap.add_argument("--out", type=Path, default=HERE / "results-ensemble.json")
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    ens, pub, per = ensemble_solver(p), public_solver(p), public_solver(p, "per_trial")
    Z = np.random.default_rng(0).standard_normal((max(args.batches), 3))
    rows = []
    for B in args.batches:
        A = jnp.asarray(0.05 * (1.0 + 0.1 * Z[:B]))
        te, tp, tq = (time_call(f, A, repeats=3) for f in (ens, pub, per))
        (xe, ye, acc, rej), tr, tt = te["_out"], tp["_out"], tq["_out"]
        te, tp, tq = timings(te), timings(tp), timings(tq)

        def dxy(x, y):
            return float(max(jnp.max(jnp.abs(x - tt.x[:, -1])), jnp.max(jnp.abs(y - tt.y[:, -1]))))

        rows.append(
            {
                "batch": B,
                "ensemble": te,
                "public": tp,
                "per_trial": tq,
                "ensemble_trials_per_s": B / te["median_s"],
                "public_trials_per_s": B / tp["median_s"],
                "per_trial_trials_per_s": B / tq["median_s"],
                "ratio_public_vs_per_trial": tq["median_s"] / tp["median_s"],
                "ensemble_steps": {"accepted": int(acc), "rejected": int(rej)},
                "public_steps": int(jnp.max(tr.num_steps)),
                "per_trial_steps": {"mean": float(jnp.mean(tt.num_steps)), "max": int(jnp.max(tt.num_steps))},
                "max_abs_diff_final_xy_m": {"public": dxy(tr.x[:, -1], tr.y[:, -1]), "ensemble": dxy(xe, ye)},
            }
        )
    hdr = (
        f"{'batch':>6}{'per-trial /s':>14}{'public (shared) /s':>20}{'ratio':>7}{'one solve /s':>14}"
        f"{'steps shared':>14}{'per-trial mean/max':>20}{'max |dxy| m':>13}"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        pt = f"{r['per_trial_steps']['mean']:.0f}/{r['per_trial_steps']['max']}"
        print(
            f"{r['batch']:>6}{r['per_trial_trials_per_s']:>14.0f}{r['public_trials_per_s']:>20.0f}"
            f"{r['ratio_public_vs_per_trial']:>7.2f}{r['ensemble_trials_per_s']:>14.0f}{r['public_steps']:>14}"
            f"{pt:>20}{r['max_abs_diff_final_xy_m']['public']:>13.1e}"
        )
    rows2 = problem2_rows(p, args.batches)
    res = {
        "problem": "problem 1 of run.py (paper robot, K_i = a_i sin(pi t + 2.1 (i-1)), [0, 4] s, rtol 1e-8, atol 1e-10)",
        "variants": {
            "public": "jax.jit(jax.vmap(simulate)), default batch_steps='shared'",
            "per_trial": "the same with batch_steps='per_trial'",
            "ensemble": "reference: one diffeqsolve of the batch, shared step, max-over-trials RMS norm",
        },
        "device": str(jax.devices()[0].device_kind),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "diffrax": dfx.__version__,
        "jsphere_commit": _commit(),
        "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "rows": rows,
        "problem2": "problem 2 of run.py (acceleration + braking gaits, theta_max ~ U(0.05, 0.15), simulate_gaits defaults rtol 1e-10)",
        "problem2_rows": rows2,
    }
    atomic_write_text(args.out, json.dumps(res, indent=2) + "\n")
    return 0


def _commit():
    import subprocess

    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=HERE, capture_output=True, text=True, check=True
        ).stdout.strip()
    except Exception:  # noqa: BLE001 - not a checkout
        return None


if __name__ == "__main__":
    sys.exit(main())
