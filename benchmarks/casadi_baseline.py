"""The other tools' anchors for problem 1 of `run.py` and the `plan` task of `tasks.py` (nothing here
imports jsphere).

- `NumpyRobot`: the equations of motion (3.4) in plain numpy, every derived quantity recomputed
  from the paper's formulas; the scipy baseline. State: `[q (w,x,y,z), omega, Omega, x, y]`:

      M [w'; W'] = [r1 - Sk^T K; r2 + Sk^T K],   M = [[A, B], [B^T, D]]   (numpy.linalg.solve, 6x6)
      x', y'     = (R v)[:2],  v = R0 Omega x gamma,  gamma = R[2]         (2.2), (2.3)
      q'         = q (x) (0, omega) / 2

- CasADi on the same right-hand side built symbolically (`torque_rhs`): `rk4_batch`, fixed-step
  RK4 compiled to C with `-O3`, and `cvodes_batch`, CVODES at problem 1's tolerances, both mapped
  over threads; `plan_nlp`, the plan of `jsphere plan` by multiple shooting with IPOPT.
"""

from __future__ import annotations

import contextlib
import tempfile
import time

import numpy as np
from common import timed

try:
    import casadi as ca
except ImportError:  # pragma: no cover - optional benchmark dependency
    ca = None


def _cross(a, b):
    # np.cross is slow for single 3-vectors; this is the same product written out.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _rotation_rows(w, x, y, z) -> list[list]:
    """The rows of the rotation matrix (platform -> fixed) of the unit quaternion `(w, x, y, z)`,
    of numpy or CasADi scalars."""
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


#: the `RobotParams` fields that make a `NumpyRobot`
PARAM_NAMES = ("R0", "m0", "I0", "Rw", "wheel_r", "wheel_n", "wheel_alpha", "m", "I", "r_m", "j", "g")


class NumpyRobot:
    """Parameter-only quantities of (2.4), (3.4), recomputed in numpy."""

    def __init__(self, R0, m0, I0, Rw, wheel_r, wheel_n, wheel_alpha, m, I, r_m, j, g):
        f = lambda x: np.asarray(x, dtype=np.float64)
        self.R0, self.m0, self.I0, self.Rw = float(R0), float(m0), float(I0), float(Rw)
        self.m, self.j, self.g = float(m), float(j), float(g)
        self.I, self.r_m = f(I), f(r_m)
        r, n, al = f(wheel_r), f(wheel_n), f(wheel_alpha)
        s = np.cross(r, al)  # s_i = r_i x alpha_i
        k = self.R0 / (self.Rw * np.einsum("ij,ij->i", s, n))  # k_i = R0 / (Rw (s_i, n_i))
        self.n = n
        self.Sk = k[:, None] * s  # rows k_i s_i
        jk = self.j * k
        self.Jss = np.einsum("i,ia,ib->ab", jk * k, s, s)
        self.Jsn = np.einsum("i,ia,ib->ab", jk, s, n)
        self.Jns = self.Jsn.T.copy()
        self.A = self.I + self.Jss - self.Jns - self.Jsn
        self.E = np.eye(3)

    @classmethod
    def from_params(cls, p) -> "NumpyRobot":
        """From any object with the `RobotParams` field names (values converted to numpy)."""
        return cls(**{k: np.asarray(getattr(p, k)) for k in PARAM_NAMES})

    # ------------------------------------------------------------------ model pieces
    @staticmethod
    def rotmat(q):
        """Rotation matrix (platform -> fixed) of the normalised quaternion `q = (w, x, y, z)`."""
        return np.array(_rotation_rows(*(q / np.sqrt(q @ q))))

    def mass_matrix(self, gamma):
        B = self.Jns - self.Jss + self.m * self.R0 * ((gamma @ self.r_m) * self.E - np.outer(gamma, self.r_m))
        D = (
            self.I0 * self.E
            + self.Jss
            + (self.m + self.m0) * self.R0**2 * ((gamma @ gamma) * self.E - np.outer(gamma, gamma))
        )
        return np.block([[self.A, B], [B.T, D]])

    def forces(self, gamma, w, W):
        p = self
        Wxw = _cross(W, w)
        r1 = (
            -_cross(w, p.I @ w)
            + _cross(p.Jns @ (W - w), w)
            - p.m * p.R0 * _cross(p.r_m, _cross(gamma, Wxw))
            - p.m * p.g * _cross(p.r_m, gamma)
        )
        r2 = (
            -(p.m + p.m0) * p.R0**2 * _cross(gamma, _cross(gamma, Wxw))
            - p.m * p.R0 * _cross(gamma, _cross(w, _cross(w, p.r_m)))
            - p.I0 * _cross(w, W)
        )
        return r1, r2

    def rhs(self, t, y, torque_fn):
        """`dy/dt` of the 12-component state for torques `K = torque_fn(t)`."""
        q, w, W = y[0:4], y[4:7], y[7:10]
        R = self.rotmat(q)
        gamma = R[2]
        r1, r2 = self.forces(gamma, w, W)
        tau = torque_fn(t) @ self.Sk  # Sk^T K = sum_i k_i s_i K_i
        acc = np.linalg.solve(self.mass_matrix(gamma), np.concatenate([r1 - tau, r2 + tau]))
        v = self.R0 * _cross(W, gamma)
        xy_dot = (R @ v)[:2]
        # q (x) (0, omega) / 2
        qw, qv = q[0], q[1:]
        q_dot = 0.5 * np.concatenate([[-(qv @ w)], qw * w + _cross(qv, w)])
        return np.concatenate([q_dot, acc, xy_dot])

    # ------------------------------------------------------------------ checks
    def energy(self, y):
        """Total energy (3.2) + (3.3), written from the kinetic energy term by term."""
        q, w, W = y[0:4], y[4:7], y[7:10]
        gamma = self.rotmat(q)[2]
        v = self.R0 * _cross(W, gamma)
        chi_dot = -self.Sk @ (w - W)
        T = (
            0.5 * (self.m + self.m0) * (v @ v)
            + 0.5 * self.I0 * (W @ W)
            + 0.5 * w @ self.I @ w
            + self.m * v @ _cross(w, self.r_m)
            + self.j * np.sum(chi_dot * (self.n @ w))
            + 0.5 * self.j * np.sum(chi_dot**2)
        )
        return T + self.m * self.g * (self.r_m @ gamma)

    def power(self, y, K):
        """Motor power `sum_i K_i chi_dot_i`, `chi_dot = -Sk (omega - Omega)` (2.4)."""
        return K @ (-self.Sk @ (y[4:7] - y[7:10]))


def initial_state(q0, x0=0.0, y0=0.0):
    """At rest with platform quaternion `q0`."""
    return np.concatenate([np.asarray(q0, float), np.zeros(6), [x0, y0]])


def initial_states(q0, batch: int) -> np.ndarray:
    """`initial_state(q0)` for `batch` trials, as columns (CasADi's mapped functions)."""
    return np.tile(initial_state(q0)[:, None], (1, batch))


T1 = 4.0
PHASES = np.array([0.0, 2.1, 4.2])
RK4_STEPS = 400


def _sx_cross(a, b):
    return ca.vertcat(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _symbols():
    """The symbols of the state, the time and the amplitudes: `y[12], t, a[3]`."""
    return ca.SX.sym("y", 12), ca.SX.sym("t"), ca.SX.sym("a", 3)


def _sx_rotmat(q):
    """The rotation matrix (platform -> fixed) of the quaternion `q` (normalised here); `gamma` its last row."""
    qn = q / ca.sqrt(ca.dot(q, q))
    return ca.vertcat(*(ca.horzcat(*row) for row in _rotation_rows(qn[0], qn[1], qn[2], qn[3])))


def torque_rhs(robot):
    """CasADi `Function f(y[12], K[3]) -> y_dot` of the axle torques `K`: the right-hand side that
    problem 1's sine torques and `plan_nlp`'s knot torques share."""
    y, K = ca.SX.sym("y", 12), ca.SX.sym("K", 3)
    q, w, W = y[0:4], y[4:7], y[7:10]
    R = _sx_rotmat(q)
    gamma = R[2, :].T
    p = robot
    DM = ca.DM
    I, Jns, Jss, A, Sk, r_m, E = DM(p.I), DM(p.Jns), DM(p.Jss), DM(p.A), DM(p.Sk), DM(p.r_m), DM(np.eye(3))
    B = Jns - Jss + p.m * p.R0 * (ca.dot(gamma, r_m) * E - ca.mtimes(gamma, r_m.T))
    D = p.I0 * E + Jss + (p.m + p.m0) * p.R0**2 * (ca.dot(gamma, gamma) * E - ca.mtimes(gamma, gamma.T))
    Wxw = _sx_cross(W, w)
    r1 = (
        -_sx_cross(w, ca.mtimes(I, w))
        + _sx_cross(ca.mtimes(Jns, W - w), w)
        - p.m * p.R0 * _sx_cross(r_m, _sx_cross(gamma, Wxw))
        - p.m * p.g * _sx_cross(r_m, gamma)
    )
    r2 = (
        -(p.m + p.m0) * p.R0**2 * _sx_cross(gamma, _sx_cross(gamma, Wxw))
        - p.m * p.R0 * _sx_cross(gamma, _sx_cross(w, _sx_cross(w, r_m)))
        - p.I0 * _sx_cross(w, W)
    )
    tau = ca.mtimes(Sk.T, K)
    M = ca.vertcat(ca.horzcat(A, B), ca.horzcat(B.T, D))
    acc = ca.solve(M, ca.vertcat(r1 - tau, r2 + tau))
    v = p.R0 * _sx_cross(W, gamma)
    xy_dot = ca.mtimes(R, v)[0:2]
    q_dot = 0.5 * ca.vertcat(-ca.dot(q[1:4], w), q[0] * w + _sx_cross(q[1:4], w))
    return ca.Function("rhs", [y, K], [ca.vertcat(q_dot, acc, xy_dot)])


def symbolic_rhs(robot):
    """CasADi `Function f(y[12], t, a[3]) -> y_dot` for torques `K_i = a_i sin(pi t + phase_i)`."""
    y, t, a = _symbols()
    return ca.Function("rhs", [y, t, a], [torque_rhs(robot)(y, a * ca.sin(np.pi * t + ca.DM(PHASES)))])


#: C compiled with -O3; the sources kept, since the temporary folder goes as a whole
JIT = {"jit": True, "compiler": "shell", "jit_cleanup": False}
JIT["jit_options"] = {"flags": ["-O3"], "verbose": False, "cleanup": False}


def rk4_batch(robot, batch: int, threads: int, steps: int = RK4_STEPS):
    """Compiled `Function(y0[12 x B], a[3 x B]) -> y(T1)[12 x B]`: fixed-step RK4."""
    f = symbolic_rhs(robot)
    y, t, a = _symbols()
    h = T1 / steps
    k1 = f(y, t, a)
    k2 = f(y + h / 2 * k1, t + h / 2, a)
    k3 = f(y + h / 2 * k2, t + h / 2, a)
    k4 = f(y + h * k3, t + h, a)
    step = ca.Function("step", [y, t, a], [y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    roll = step.mapaccum("roll", steps)  # y accumulated; t and a mapped over the steps
    y0, aa = ca.MX.sym("y0", 12), ca.MX.sym("a", 3)
    tgrid = ca.DM(np.arange(steps) * h).T
    trial = ca.Function("trial", [y0, aa], [roll(y0, tgrid, ca.repmat(aa, 1, steps))[:, -1]], JIT)
    return trial.map(batch, "thread", threads)


def cvodes_batch(robot, batch: int, threads: int, rtol: float = 1e-8, atol: float = 1e-10):
    """CVODES over [0, T1] (right-hand side compiled to C), mapped over threads."""
    f = symbolic_rhs(robot)
    y, t, a = _symbols()
    dae = {"x": y, "t": t, "p": a, "ode": f(y, t, a)}
    integ = ca.integrator("I", "cvodes", dae, 0.0, T1, {"abstol": atol, "reltol": rtol, "max_num_steps": 100000})
    y0, aa = ca.MX.sym("y0", 12), ca.MX.sym("a", 3)
    trial = ca.Function("trial", [y0, aa], [integ(x0=y0, p=aa)["xf"]])
    return trial.map(batch, "thread", threads)


@contextlib.contextmanager
def in_temporary_folder():
    """CasADi's shell compiler writes its sources to the current folder: keep them out of the checkout."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp):
        yield


def built_and_timed(build, y0, A: np.ndarray, *, repeats: int) -> tuple[dict, np.ndarray]:
    """`build()` (a compiled batch `Function`, timed as `build_s`), then its first call and
    `repeats` more on `(y0, A.T)`: the timings, and the final `(x, y)` of every trial."""
    F, build_s = timed(build)
    row = {"batch": A.shape[0], "build_s": build_s, "first_call_s": timed(F, y0, A.T)[1]}
    runs = [timed(F, y0, A.T) for _ in range(repeats)]
    times = [s for _, s in runs]
    med = float(np.median(times))
    row |= {"median_s": med, "repeats": repeats, "times_s": times, "trials_per_s": A.shape[0] / med}
    return row, np.asarray(runs[-1][0])[10:12].T


def casadi_rows(robot, q0, A: np.ndarray, *, threads: int = 2, repeats: int = 3, cvodes_trials: int = 64):
    """Time both CasADi variants on the amplitude rows `A (B, 3)`. Returns `(rows, finals)`,
    `finals[name]` the final `(x, y)` of the trials run (for the accuracy check)."""
    if ca is None:
        raise ImportError("CasADi is not installed: pip install 'jsphere[bench]' (or pip install casadi).")
    B, n = A.shape[0], min(cvodes_trials, A.shape[0])
    y0 = initial_states(q0, B)
    with in_temporary_folder():
        rk4, rk4_xy = built_and_timed(lambda: rk4_batch(robot, B, threads), y0, A, repeats=repeats)
        cvodes, cvodes_xy = built_and_timed(lambda: cvodes_batch(robot, n, threads), y0[:, :n], A[:n], repeats=repeats)
    rows = [
        {"name": f"CasADi RK4 {RK4_STEPS} steps, C -O3, {threads} threads", "threads": threads} | rk4,
        {"name": f"CasADi CVODES rtol 1e-8, {threads} threads", "threads": threads} | cvodes,
    ]
    return rows, {"rk4": rk4_xy, "cvodes": cvodes_xy}


#: `jsphere.Limits()`: torque [N m], wheel speed [rad/s], tilt [rad], torque rate [N m/s], duration [s]
PLAN_LIMITS = {"max_torque": 0.1, "max_wheel_speed": 20.0, "max_tilt": 0.35, "max_torque_rate": 1.0}
PLAN_LIMITS |= {"min_time": 1.0, "max_time": 12.0}


def plan_nlp(
    robot,
    q0,
    gamma_m,
    target,
    limits: dict | None = None,
    intervals: int = 60,
    smoothing: float = 1e-3,
    tol: float = 1e-8,
) -> dict:
    """The minimum-time rest-to-rest plan from rest (attitude `q0`, `gamma = gamma_m`) at the origin
    to `target = (x, y)` within `limits` (`PLAN_LIMITS`' keys): `jsphere.planning.direct`'s multiple
    shooting transcription (its module docstring) as a CasADi user writes it, for the two to solve
    one problem. IPOPT with CasADi's exact Hessian, MUMPS, the adaptive barrier. An interval's
    constraints are one SX function mapped over the intervals in an MX graph: it builds in a
    fraction of a second, where one SX graph of every interval (or `expand`) takes ~12 s to build
    to solve ~1 s faster, and C code (`jit`) compiles for longer than it saves. Returns `T`,
    IPOPT's iterations and status, the knots (`t`, `K`) and the seconds to build and to solve."""
    if ca is None:
        raise ImportError("CasADi is not installed: pip install 'jsphere[bench]' (or pip install casadi).")
    t0 = time.perf_counter()
    n, f, lim = intervals, torque_rhs(robot), PLAN_LIMITS | (limits or {})
    max_torque, max_time, min_time = lim["max_torque"], lim["max_time"], lim["min_time"]
    x, K0, xe, K1, T = ca.SX.sym("x", 12), ca.SX.sym("K0", 3), ca.SX.sym("xe", 12), ca.SX.sym("K1", 3), ca.SX.sym("T")
    h, Km, Sk, gm = T / n, (K0 + K1) / 2, ca.DM(robot.Sk), ca.DM(np.asarray(gamma_m, float))
    k1 = f(x, K0)
    k2 = f(x + h / 2 * k1, Km)
    k3 = f(x + h / 2 * k2, Km)
    k4 = f(x + h * k3, K1)
    defect = xe - (x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4))
    tilt = ca.dot(_sx_rotmat(xe[0:4])[2, :].T, gm)
    block = ca.Function(
        "block", [x, K0, xe, K1, T], [ca.vertcat(defect, (K1 - K0) / h, -Sk @ (xe[4:7] - xe[7:10]), tilt)]
    )
    Z, T = ca.MX.sym("Z", 15, n + 1), ca.MX.sym("T")  # Z's columns: (x_k, K_k)
    X, U = Z[:12, :], Z[12:, :]
    e1 = np.cross(gamma_m, [1.0, 0.0, 0.0] if abs(gamma_m[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    across = ca.DM(np.stack([e1, np.cross(gamma_m, e1)]))
    blocks = block.map(n)(X[:, :-1], U[:, :-1], X[:, 1:], U[:, 1:], ca.repmat(T, 1, n))  # one column per interval
    xn = X[:, n]
    g = [ca.vec(blocks), xn[10:12] - ca.DM(target), xn[4:10], across @ _sx_rotmat(xn[0:4])[2, :].T]
    J = T + smoothing * ca.sumsqr((U[:, 1:] - U[:, :-1]) / max_torque)
    per = np.r_[np.zeros(12), np.full(3, lim["max_torque_rate"]), np.full(3, lim["max_wheel_speed"])]
    cl = np.r_[np.tile(np.r_[-per, np.cos(lim["max_tilt"])], n), np.zeros(10)]
    cu = np.r_[np.tile(np.r_[per, np.inf], n), np.zeros(10)]
    rest = initial_state(q0)
    lb, ub = np.full((15, n + 1), -np.inf), np.full((15, n + 1), np.inf)
    lb[12:], ub[12:] = -max_torque, max_torque
    lb[:12, 0] = ub[:12, 0] = rest
    lb[12:, [0, n]] = ub[12:, [0, n]] = 0.0
    s = np.linspace(0.0, 1.0, n + 1)
    z0 = np.zeros((15, n + 1))
    z0[:12], z0[10:12] = rest[:, None], np.outer(target, 3 * s**2 - 2 * s**3)  # at rest along a smoothstep
    T0 = min(max(4.5 * np.sqrt(np.hypot(*target)), 1.2 * min_time), 0.9 * max_time)
    ipopt = {"tol": tol, "mu_strategy": "adaptive", "linear_solver": "mumps", "max_iter": 500, "sb": "yes"}
    nlp = {"x": ca.vertcat(ca.vec(Z), T), "f": J, "g": ca.vertcat(*g)}
    solver = ca.nlpsol("plan", "ipopt", nlp, {"ipopt": ipopt | {"print_level": 0}, "print_time": False})
    t1 = time.perf_counter()
    flat = lambda v, last: np.r_[v.ravel(order="F"), last]  # (x_k, K_k) by columns, then T
    sol = solver(x0=flat(z0, T0), lbx=flat(lb, min_time), ubx=flat(ub, max_time), lbg=cl, ubg=cu)
    t2 = time.perf_counter()
    z, stats = np.asarray(sol["x"]).ravel(), solver.stats()
    out = {"T": float(z[-1]), "iterations": int(stats["iter_count"]), "status": stats["return_status"]}
    out |= {"success": bool(stats["success"]), "t": np.linspace(0.0, z[-1], n + 1).tolist()}
    return out | {"K": z[:-1].reshape(n + 1, 15)[:, 12:].tolist(), "build_s": t1 - t0, "solve_s": t2 - t1}
