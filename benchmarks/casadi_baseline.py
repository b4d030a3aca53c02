"""CasADi baselines for problem 1 of `run.py`: the strongest alternative a control engineer
would write by hand.

Two variants, both on the numbers of the same parameter set as `numpy_model.NumpyRobot`
(nothing is imported from jsphere):

- `rk4`: the right-hand side built symbolically (CasADi SX), a fixed-step classical RK4 step,
  400 steps over [0, 4] s folded with `mapaccum`, the trial mapped over the batch with
  `map(..., "thread", n_threads)`, everything compiled to C with the system compiler (`-O3`)
  through CasADi's `jit` option.
- `cvodes`: the same right-hand side in CasADi's CVODES integrator (rtol 1e-8, atol 1e-10,
  the tolerances of problem 1), mapped over threads.

The 12-component state is that of `numpy_model` (`[q, omega, Omega, x, y]`); the 6x6 system of
(3.4) is solved symbolically (CasADi's `solve` on SX expands a QR factorisation into the
generated code).

    python benchmarks/casadi_baseline.py [--batch 1024] [--threads 2]

`run.py` imports `casadi_rows` from here when CasADi is installed (`pip install jsphere[bench]`).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

try:
    import casadi as ca
except ImportError:  # pragma: no cover - optional benchmark dependency
    ca = None

T1 = 4.0
PHASES = np.array([0.0, 2.1, 4.2])
RK4_STEPS = 400


def _cross(a, b):
    return ca.vertcat(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def symbolic_rhs(robot):
    """CasADi `Function f(y[12], t, a[3]) -> y_dot` for torques `K_i = a_i sin(pi t + phase_i)`."""
    y = ca.SX.sym("y", 12)
    t = ca.SX.sym("t")
    a = ca.SX.sym("a", 3)
    q, w, W = y[0:4], y[4:7], y[7:10]
    qn = q / ca.sqrt(ca.dot(q, q))
    qw, qx, qy, qz = qn[0], qn[1], qn[2], qn[3]
    R = ca.vertcat(
        ca.horzcat(1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)),
        ca.horzcat(2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)),
        ca.horzcat(2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)),
    )
    gamma = R[2, :].T
    p = robot
    DM = ca.DM
    I, Jns, Jss, A, Sk, r_m, E = DM(p.I), DM(p.Jns), DM(p.Jss), DM(p.A), DM(p.Sk), DM(p.r_m), DM(np.eye(3))
    B = Jns - Jss + p.m * p.R0 * (ca.dot(gamma, r_m) * E - ca.mtimes(gamma, r_m.T))
    D = p.I0 * E + Jss + (p.m + p.m0) * p.R0**2 * (ca.dot(gamma, gamma) * E - ca.mtimes(gamma, gamma.T))
    Wxw = _cross(W, w)
    r1 = (
        -_cross(w, ca.mtimes(I, w))
        + _cross(ca.mtimes(Jns, W - w), w)
        - p.m * p.R0 * _cross(r_m, _cross(gamma, Wxw))
        - p.m * p.g * _cross(r_m, gamma)
    )
    r2 = (
        -(p.m + p.m0) * p.R0**2 * _cross(gamma, _cross(gamma, Wxw))
        - p.m * p.R0 * _cross(gamma, _cross(w, _cross(w, r_m)))
        - p.I0 * _cross(w, W)
    )
    K = a * ca.sin(np.pi * t + DM(PHASES))
    tau = ca.mtimes(Sk.T, K)
    M = ca.vertcat(ca.horzcat(A, B), ca.horzcat(B.T, D))
    acc = ca.solve(M, ca.vertcat(r1 - tau, r2 + tau))
    v = p.R0 * _cross(W, gamma)
    xy_dot = ca.mtimes(R, v)[0:2]
    q_dot = 0.5 * ca.vertcat(-ca.dot(q[1:4], w), q[0] * w + _cross(q[1:4], w))
    return ca.Function("rhs", [y, t, a], [ca.vertcat(q_dot, acc, xy_dot)])


def _jit_opts():
    return {
        "jit": True,
        "compiler": "shell",
        "jit_options": {"flags": ["-O3"], "verbose": False, "cleanup": False},
        "jit_cleanup": False,
    }  # the temporary folder goes as a whole


def rk4_batch(robot, batch: int, threads: int, steps: int = RK4_STEPS):
    """Compiled `Function(y0[12 x B], a[3 x B]) -> y(T1)[12 x B]`: fixed-step RK4."""
    f = symbolic_rhs(robot)
    y = ca.SX.sym("y", 12)
    t = ca.SX.sym("t")
    a = ca.SX.sym("a", 3)
    h = T1 / steps
    k1 = f(y, t, a)
    k2 = f(y + h / 2 * k1, t + h / 2, a)
    k3 = f(y + h / 2 * k2, t + h / 2, a)
    k4 = f(y + h * k3, t + h, a)
    step = ca.Function("step", [y, t, a], [y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    roll = step.mapaccum("roll", steps)  # y accumulated; t and a mapped over the steps
    y0 = ca.MX.sym("y0", 12)
    aa = ca.MX.sym("a", 3)
    tgrid = ca.DM(np.arange(steps) * h).T
    trial = ca.Function("trial", [y0, aa], [roll(y0, tgrid, ca.repmat(aa, 1, steps))[:, -1]], _jit_opts())
    return trial.map(batch, "thread", threads)


def cvodes_batch(robot, batch: int, threads: int, rtol: float = 1e-8, atol: float = 1e-10):
    """CVODES over [0, T1] (right-hand side compiled to C), mapped over threads."""
    f = symbolic_rhs(robot)
    y = ca.SX.sym("y", 12)
    t = ca.SX.sym("t")
    a = ca.SX.sym("a", 3)
    dae = {"x": y, "t": t, "p": a, "ode": f(y, t, a)}
    integ = ca.integrator("I", "cvodes", dae, 0.0, T1, {"abstol": atol, "reltol": rtol, "max_num_steps": 100000})
    y0 = ca.MX.sym("y0", 12)
    aa = ca.MX.sym("a", 3)
    trial = ca.Function("trial", [y0, aa], [integ(x0=y0, p=aa)["xf"]])
    return trial.map(batch, "thread", threads)


def _timed(fn, *args, repeats: int):
    t = time.perf_counter()
    out = fn(*args)
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t)
    return np.asarray(out), first, float(np.median(times)), times


def casadi_rows(robot, q0, A: np.ndarray, *, threads: int = 2, repeats: int = 3, cvodes_trials: int = 64):
    """Time both CasADi variants on the amplitude rows `A (B, 3)`. Returns `(rows, finals)`,
    `finals[name]` the final `(x, y)` of the trials run (for the accuracy check)."""
    if ca is None:
        raise ImportError("CasADi is not installed: pip install 'jsphere[bench]' (or pip install casadi).")
    B = A.shape[0]
    y0 = np.tile(np.concatenate([np.asarray(q0, float), np.zeros(8)])[:, None], (1, B))
    rows, finals = [], {}
    # the shell compiler writes its sources to the current folder: keep them out of the checkout
    here = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            t = time.perf_counter()
            F = rk4_batch(robot, B, threads)
            build = time.perf_counter() - t
            out, first, med, times = _timed(F, y0, A.T, repeats=repeats)
            finals["rk4"] = out[10:12].T
            rows.append(
                {
                    "name": f"CasADi RK4 {RK4_STEPS} steps, C -O3, {threads} threads",
                    "batch": B,
                    "threads": threads,
                    "build_s": build,
                    "first_call_s": first,
                    "median_s": med,
                    "times_s": times,
                    "trials_per_s": B / med,
                }
            )
            n = min(cvodes_trials, B)
            t = time.perf_counter()
            G = cvodes_batch(robot, n, threads)
            build = time.perf_counter() - t
            out, first, med, times = _timed(G, y0[:, :n], A[:n].T, repeats=repeats)
            finals["cvodes"] = out[10:12].T
            rows.append(
                {
                    "name": f"CasADi CVODES rtol 1e-8, {threads} threads",
                    "batch": n,
                    "threads": threads,
                    "build_s": build,
                    "first_call_s": first,
                    "median_s": med,
                    "times_s": times,
                    "trials_per_s": n / med,
                }
            )
        finally:
            os.chdir(here)
    return rows, finals


def main(argv=None) -> int:
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from numpy_model import NumpyRobot

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import jsphere

    jsphere.enable_x64()  # the parameters in float64, as the CasADi model computes
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 2)
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    robot = NumpyRobot.from_params(p)
    q0 = np.asarray(jsphere.State.at_rest(p).q)
    Z = np.random.default_rng(0).standard_normal((args.batch, 3))
    A = 0.05 * (1.0 + 0.1 * Z)
    rows, finals = casadi_rows(robot, q0, A, threads=args.threads)
    for r in rows:
        print(
            f"{r['name']:<45} batch {r['batch']:>6}  {r['trials_per_s']:>10.1f} trials/s  (build {r['build_s']:.1f} s)"
        )
    print("trial 0 final (x, y):", {k: v[0].tolist() for k, v in finals.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
