"""Direct plans: rest-to-rest manoeuvres over free torque profiles by multiple shooting, solved
with IPOPT (`jsphere.numerics.ipopt`); the default family of `plan` (`docs/planning.md`).

The transcription. `n` intervals of equal length `h = T/n`; the decision vector
`z = (x_0, K_0, x_1, K_1, ..., x_n, K_n, T)` of the reduced state `x = (q, omega, Omega, x, y)`
(12 numbers: the shell's attitude and the wheel angles do not enter (3.4)) and the axle torques
`K` at the knots, linear in time between them. Interval `k` gives one block of constraints on
`w_k = (x_k, K_k, x_{k+1}, K_{k+1}, T)`:

- the defect `x_{k+1} - Phi(x_k, K_k, K_{k+1}, h) = 0`, `Phi` classical RK4 (`rk4_step`,
  `substeps` steps) of (3.4), (2.2)-(2.3);
- the torque rate `(K_{k+1} - K_k) / h` within `max_torque_rate` (exact: `K` is linear);
- the wheel speeds (2.4) at `x_{k+1}` within `max_wheel_speed`, the tilt `gamma . gamma_m >=
  cos(max_tilt)` at `x_{k+1}`.

The end: position on the target, `omega = Omega = 0`, `gamma = gamma_m` (two components) and,
when asked, the heading (`sin((psi - psi_target)/2) = 0`). Bounds: `|K| <= max_torque` (exact
between knots), `x_0` at rest, `K_0 = K_n = 0`, `T` within `[min_time, max_time]`. Objective:
`T` (with `Objective.time`, `energy` and `effort` in proportion) plus a small penalty on torque
steps that keeps the profile smooth where time does not decide it.

Derivatives: each block's Jacobian with `jax.jacfwd`, vmapped over the blocks; the Hessian of the
Lagrangian by differences of each block's Lagrangian gradient (`jax.grad`, vmapped over the
blocks and their perturbations: one small program; `docs/decisions/direct-plans-with-ipopt.md`).

The plan is then replayed with the accurate solver (`simulate`, the knots' torques
interpolated linearly). Between knots the wheel speed and tilt can pass their limits slightly,
and the search model's RK4 leaves a small bias at the end: while the replay misses, the bounds
are tightened by the excess and the end (position, heading and angular velocities) moved by the
miss, and the problem solved again from the last answer (at most `DirectSettings.rounds` times).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._runtime.errors import InputError
from .._runtime.precision import HOW_TO_ENABLE
from .._runtime.progress import Progress
from .._runtime.quick_compile import eager_jit, run_program
from ..controls import Torques
from ..model.dynamics import solve_accelerations
from ..model.kinematics import rest_attitude
from ..model.linalg import cross, matvec
from ..model.params import RobotParams, derive
from ..model.rotations import quat_rate_body, rotmat
from ..model.state import State
from ..numerics import ipopt
from ..solve.fixed_grid import rk4_step
from ..solve.simulate import simulate
from .problem import DirectSettings, Limits, Objective, PlanOptions
from .result import Plan, manoeuvre_plan
from .rollout import yaw
from .verify import _limit_report, _terminal_errors, missed, padded_grid

#: the reduced state's size and its places in the flat state (`Flat`): q, omega, Omega, x, y
NX = 12
REDUCED = np.r_[np.arange(0, 4), np.arange(8, 16)]
#: the relative step of the Hessian's differences
FD_STEP = 1e-6
#: the bounds' relative back-off from the limits (IPOPT may pass a bound by its tolerance)
BACK_OFF = 1e-6
#: the weight of the torque-step penalty, per (step / max_torque)^2, relative to a second of T
SMOOTHING = 1e-3


# ----------------------------------------------------------------------------- the model


def reduced_field(p: RobotParams, d, x: Float[Array, " 12"], K: Float[Array, " N"]) -> Float[Array, " 12"]:
    """The rates of the reduced state `(q, omega, Omega, x, y)` at torques `K`: (3.4) solved as
    in `simulate`'s torque field, `q_dot = q (x) (0, omega)/2`, `(x_dot, y_dot)` of (2.2)-(2.3)."""
    q, omega, Omega = x[0:4], x[4:7], x[7:10]
    R = rotmat(q)
    gamma = R[2]
    omega_dot, Omega_dot = solve_accelerations(p, d, gamma, omega, Omega, K)
    vf = matvec(R, p.R0 * cross(Omega, gamma))
    return jnp.concatenate([quat_rate_body(q, omega), omega_dot, Omega_dot, vf[:2]])


class _Args(eqx.Module):
    """The problem's numbers (traced: another robot, target or weight reuses the programs)."""

    params: RobotParams
    derived: object
    gm: Float[Array, " 3"]  # the rest attitude gamma_m
    across: Float[Array, "2 3"]  # two unit vectors across gamma_m
    target: Float[Array, " 3"]  # x, y, heading
    rates: Float[Array, " 6"]  # omega, Omega asked at the end (0, less the replay's miss)
    weights: Float[Array, " 4"]  # time, energy, effort, smoothing (divided by the torque scale^2)


def _split(w, nx: int, nv: int):
    return w[:nx], w[nx:nv], w[nv : nv + nx], w[nv + nx : 2 * nv], w[-1]


def _block(w, a: _Args, n: int, substeps: int):
    """Interval constraints of `w = (x_k, K_k, x_{k+1}, K_{k+1}, T)`: defect (12), torque rate,
    wheel speeds and `gamma . gamma_m` at `x_{k+1}`."""
    p, d = a.params, a.derived
    nv = NX + p.n_wheels
    x0, K0, x1, K1, T = _split(w, NX, nv)
    h = T / n

    def f(t, x):
        return reduced_field(p, d, x, K0 + (K1 - K0) * (t / h))

    x = x0
    for j in range(substeps):
        x = rk4_step(f, j * h / substeps, x, h / substeps)
    chi_dot = -matvec(d.Sk, x1[4:7] - x1[7:10])
    return jnp.concatenate([x1 - x, (K1 - K0) / h, chi_dot, (rotmat(x1[0:4])[2] @ a.gm)[None]])


def _block_cost(w, a: _Args, n: int):
    """An interval's share of the objective: energy and effort by the trapezoid rule, and the
    torque-step penalty."""
    p, d = a.params, a.derived
    nv = NX + p.n_wheels
    x0, K0, x1, K1, T = _split(w, NX, nv)
    h = T / n

    def power(x, K):
        pw = K * (-matvec(d.Sk, x[4:7] - x[7:10]))
        return jnp.sum(jnp.sqrt(pw**2 + 1e-10))

    energy = 0.5 * h * (power(x0, K0) + power(x1, K1))
    effort = 0.5 * h * (jnp.sum(K0**2) + jnp.sum(K1**2))
    return a.weights[1] * energy + a.weights[2] * effort + a.weights[3] * jnp.sum((K1 - K0) ** 2)


def _terminal(x, a: _Args, heading: bool):
    """The end: position on the target, `omega = Omega = 0`, `gamma` on `gamma_m`, heading."""
    g = rotmat(x[0:4])[2]
    out = [x[10:12] - a.target[:2], x[4:10] - a.rates, a.across @ g]
    if heading:
        out.append(jnp.sin(0.5 * (yaw(a.params, x[0:4]) - a.target[2]))[None])
    return jnp.concatenate(out)


def _evaluate(W, xN, a: _Args, n: int, substeps: int, heading: bool):
    """Constraint values, their Jacobian's values (blocks, then the end), the objective's block
    sum and its gradient per block: one program."""
    block = lambda w: _block(w, a, n, substeps)
    cost = lambda w: _block_cost(w, a, n)
    c = jax.vmap(block)(W)
    Jb = jax.vmap(jax.jacfwd(block))(W)
    e = _terminal(xN, a, heading)
    Je = jax.jacfwd(lambda x: _terminal(x, a, heading))(xN)
    o, go = jax.vmap(jax.value_and_grad(cost))(W)
    return (
        jnp.concatenate([c.reshape(-1), e]),
        jnp.concatenate([Jb.reshape(-1), Je.reshape(-1)]),
        jnp.sum(o),
        go,
    )


def _second(WB, LB, sigma, xN, lt, a: _Args, n: int, substeps: int, heading: bool):
    """What the Hessian of the Lagrangian is made of: `grad_w (sigma cost + l . block)` of every
    block `WB (B, 2 nv + 1)` with its multipliers `LB`, and the end's Hessian `lt . terminal''`."""
    lagrangian = lambda w, l: sigma * _block_cost(w, a, n) + l @ _block(w, a, n, substeps)
    He = jax.hessian(lambda x: lt @ _terminal(x, a, heading))(xN)
    return jax.vmap(jax.grad(lagrangian))(WB, LB), He


#: the programs, compiled for a short first call and exported where the application keeps them
_PROGRAMS = {"direct plan: constraints": eager_jit(_evaluate), "direct plan: Hessian": eager_jit(_second)}


def _run(name: str, *args):
    return run_program(name, _PROGRAMS[name], tuple, *args)


# ----------------------------------------------------------------------------- the sparse layout


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where each block's variables and constraints lie in `z` and `g`, and the sparsity
    structures IPOPT is given."""

    n: int
    nw: int
    heading: bool

    @property
    def nv(self) -> int:
        return NX + self.nw

    @property
    def nvar(self) -> int:
        return (self.n + 1) * self.nv + 1

    @property
    def nc(self) -> int:
        return NX + 2 * self.nw + 1

    @property
    def nt(self) -> int:
        return 10 + int(self.heading)

    @functools.cached_property
    def blocks(self) -> np.ndarray:
        """`(n, 2 nv + 1)`: each block's variables' places in `z` (`T` last)."""
        nv = self.nv
        return np.array([np.r_[np.arange(k * nv, (k + 2) * nv), self.nvar - 1] for k in range(self.n)])

    @property
    def end(self) -> np.ndarray:
        return self.n * self.nv + np.arange(NX)

    @functools.cached_property
    def jacobian_structure(self):
        n, nc, lw = self.n, self.nc, self.blocks.shape[1]
        rows = np.concatenate([np.repeat(np.arange(n * nc), lw), np.repeat(n * nc + np.arange(self.nt), NX)])
        cols = np.concatenate([np.repeat(self.blocks[:, None, :], nc, 1).reshape(-1), np.tile(self.end, self.nt)])
        return rows, cols

    @functools.cached_property
    def _hessian_map(self):
        lw = self.blocks.shape[1]
        tri, tri_e = np.tril_indices(lw), np.tril_indices(NX)
        r = np.concatenate([self.blocks[:, tri[0]].reshape(-1), self.end[tri_e[0]]])
        c = np.concatenate([self.blocks[:, tri[1]].reshape(-1), self.end[tri_e[1]]])
        keys = np.maximum(r, c).astype(np.int64) * self.nvar + np.minimum(r, c)
        unique, inverse = np.unique(keys, return_inverse=True)
        return unique, inverse, tri, tri_e

    @property
    def hessian_structure(self):
        unique = self._hessian_map[0]
        return unique // self.nvar, unique % self.nvar


class _Transcription:
    """The callables of `ipopt.SparseProblem` for one request; the last point's values kept (IPOPT
    asks for the constraints, their Jacobian and the objective at the same point)."""

    def __init__(self, lay: _Layout, a: _Args, substeps: int):
        # committed to the device once: an exported program's call commits every argument
        self.lay, self.a, self.substeps = lay, jax.device_put(a, jax.devices()[0]), substeps
        self._key, self._val = None, None

    def _at(self, z):
        key = z.tobytes()
        if key != self._key:
            lay = self.lay
            out = _run("direct plan: constraints", z[lay.blocks], z[lay.end], self.a, lay.n, self.substeps, lay.heading)
            self._key, self._val = key, [np.asarray(v) for v in out]
        return self._val

    def objective(self, z):
        return float(self.a.weights[0]) * z[-1] + float(self._at(z)[2])

    def gradient(self, z):
        g = np.zeros_like(z)
        np.add.at(g, self.lay.blocks, self._at(z)[3])
        g[-1] += float(self.a.weights[0])
        return g

    def constraints(self, z):
        return self._at(z)[0]

    def jacobian(self, z):
        return self._at(z)[1]

    def hessian(self, z, lam, sigma):
        lay = self.lay
        W = z[lay.blocks]
        lw = W.shape[1]
        scale = FD_STEP * np.maximum(1.0, np.abs(W))  # (n, lw)
        pert = np.concatenate([np.zeros((lay.n, 1, lw)), scale[:, :, None] * np.eye(lw)[None]], axis=1)
        WB = (W[:, None, :] + pert).reshape(-1, lw)
        LB = np.repeat(lam[: lay.n * lay.nc].reshape(lay.n, lay.nc), lw + 1, axis=0)
        lt = lam[lay.n * lay.nc :]
        args = (WB, LB, np.asarray(sigma, float), z[lay.end], lt, self.a, lay.n, self.substeps, lay.heading)
        G, He = (np.asarray(v) for v in _run("direct plan: Hessian", *args))
        G = G.reshape(lay.n, lw + 1, lw)
        H = (G[:, 1:, :] - G[:, :1, :]) / scale[:, :, None]
        H = 0.5 * (H + np.swapaxes(H, 1, 2))
        unique, inverse, tri, tri_e = lay._hessian_map
        vals = np.concatenate([H[:, tri[0], tri[1]].reshape(-1), He[tri_e]])
        return np.bincount(inverse, weights=vals, minlength=len(unique))

    def problem(self) -> ipopt.SparseProblem:
        lay = self.lay
        return ipopt.SparseProblem(
            self.objective,
            self.gradient,
            self.constraints,
            self.jacobian,
            lay.jacobian_structure,
            self.hessian,
            lay.hessian_structure,
        )


# ----------------------------------------------------------------------------- bounds and start


def _limit(v):
    return math.inf if v is None else float(v)


def _bounds(lay: _Layout, rest: np.ndarray, lim: Limits, shrink: dict):
    """Variable and constraint bounds; `shrink`: the factors (<= 1) of the wheel-speed and tilt
    limits that the replay asks for."""
    lb, ub = np.full(lay.nvar, -math.inf), np.full(lay.nvar, math.inf)
    knots_lb, knots_ub = lb[:-1].reshape(lay.n + 1, lay.nv), ub[:-1].reshape(lay.n + 1, lay.nv)
    torque = _limit(lim.max_torque) * (1 - BACK_OFF)
    knots_lb[:, NX:], knots_ub[:, NX:] = -torque, torque
    knots_lb[0, :NX] = knots_ub[0, :NX] = rest
    knots_lb[[0, -1], NX:] = knots_ub[[0, -1], NX:] = 0.0
    lb[-1], ub[-1] = float(lim.min_time), float(lim.max_time)
    rate, speed = (
        _limit(lim.max_torque_rate) * (1 - BACK_OFF),
        _limit(lim.max_wheel_speed) * shrink["wheel_speed_rad_s"],
    )
    tilt = -1.0 if lim.max_tilt is None else math.cos(min(float(lim.max_tilt) * shrink["tilt_rad"], math.pi))
    nw = lay.nw
    cl = np.r_[np.zeros(NX), np.full(nw, -rate), np.full(nw, -speed), tilt]
    cu = np.r_[np.zeros(NX), np.full(nw, rate), np.full(nw, speed), math.inf]
    return (lb, ub), (np.r_[np.tile(cl, lay.n), np.zeros(lay.nt)], np.r_[np.tile(cu, lay.n), np.zeros(lay.nt)])


def _start(lay: _Layout, rest: np.ndarray, target, lim: Limits) -> np.ndarray:
    """The start: at rest (`rest`, the reduced state) along a smooth path to the target (turning to the heading asked),
    torques 0, `T` from the distance (`4.5 sqrt(d)` s, within the time limits)."""
    x, y, psi = target
    s = np.linspace(0.0, 1.0, lay.n + 1)
    ease = 3 * s**2 - 2 * s**3
    z = np.zeros(lay.nvar)
    knots = z[:-1].reshape(lay.n + 1, lay.nv)
    knots[:, :NX] = rest
    if lay.heading:  # turned about the vertical by psi e: q = (cos(a/2), 0, 0, sin(a/2)) (x) q_rest
        half = 0.5 * float(psi) * ease
        w, v = rest[0], rest[1:4]
        knots[:, 0] = np.cos(half) * w - np.sin(half) * v[2]
        knots[:, 1:4] = np.cos(half)[:, None] * v + np.sin(half)[:, None] * (
            w * np.array([0.0, 0.0, 1.0]) + np.cross([0.0, 0.0, 1.0], v)
        )
    knots[:, 10], knots[:, 11] = x * ease, y * ease
    T = 4.5 * math.sqrt(math.hypot(x, y))
    z[-1] = min(max(T, 1.2 * float(lim.min_time)), 0.9 * float(lim.max_time))
    return z


def _args(p: RobotParams, target, rates, obj: Objective, lim: Limits) -> _Args:
    dt = p.R0.dtype
    gm = np.asarray(rest_attitude(p))
    e1 = np.cross(gm, [1.0, 0.0, 0.0] if abs(gm[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    scale = float(obj.time) if float(obj.time) > 0 else 1.0
    kref = float(lim.max_torque) if lim.max_torque is not None else 0.1
    w = [float(obj.time) / scale, float(obj.energy) / scale, float(obj.effort) / scale, SMOOTHING / kref**2]
    return _Args(
        params=p,
        derived=derive(p),
        gm=jnp.asarray(gm, dt),
        across=jnp.asarray(np.stack([e1, np.cross(gm, e1)]), dt),
        target=jnp.asarray(target, dt),
        rates=jnp.asarray(rates, dt),
        weights=jnp.asarray(w, dt),
    )


# ----------------------------------------------------------------------------- solve and replay


def _replay(p: RobotParams, ts, K, rate: float, max_time: float, options):
    """The accurate trajectory of the knots' torques (linear between knots) from rest, sampled
    at `k / rate` and at the end; the grid padded to `max_time * rate` so that every duration
    shares one compiled solve."""
    T = float(ts[-1])
    grid, m = padded_grid(T, rate, max_time)
    ctrl = Torques.from_samples(ts, K, kind="linear")
    tr = simulate(p, State.at_rest(p), ctrl, T, ts=grid, options=options)
    return jax.tree_util.tree_map(lambda v: v[:m] if jnp.ndim(v) >= 1 else v, tr)


def _knots(lay: _Layout, z):
    knots = z[:-1].reshape(lay.n + 1, lay.nv)
    return np.linspace(0.0, z[-1], lay.n + 1), knots[:, NX:].copy()


def plan_direct(
    where: str,
    params: RobotParams,
    target,
    lim: Limits,
    obj: Objective,
    o: PlanOptions,
    ds: DirectSettings,
    progress: bool | None,
    options,
) -> Plan:
    """The direct plan from rest at the origin to `target = (x, y, heading or None)`, verified
    with the accurate solver (`options`: its `SolverOptions`); `where` names the caller."""
    t0 = time.perf_counter()
    if np.dtype(params.R0.dtype).itemsize < 8:
        raise InputError(
            f"{where}: a direct plan needs float64 parameters (its derivatives are taken by differences); "
            f"{HOW_TO_ENABLE}, or plan with family='gait'."
        )
    prog = Progress(progress)
    x, y, psi = target
    heading = psi is not None and not (isinstance(psi, float) and math.isnan(psi))
    p = params
    lay = _Layout(ds.intervals, p.n_wheels, heading)
    tg = [float(x), float(y), float(psi) if heading else 0.0]
    rest = np.asarray(State.at_rest(p).flatten())[REDUCED]
    z = _start(lay, rest, tg, lim)
    shrink = {"wheel_speed_rad_s": 1.0, "tilt_rad": 1.0}
    aim, rates = list(tg), np.zeros(6)
    iterations, rounds = 0, 0
    prog.say(f"jsphere plan: direct, {lay.n} intervals, {lay.nvar} unknowns, {lay.n * lay.nc + lay.nt} constraints")
    for rounds in range(1, ds.rounds + 1):
        tr_ = _Transcription(lay, _args(p, aim, rates, obj, lim), ds.substeps)
        bounds, cbounds = _bounds(lay, rest, lim, shrink)
        with prog.phase(f"jsphere plan: IPOPT, solve {rounds}"):
            res = ipopt.minimise(tr_.problem(), z, bounds, cbounds, tol=ds.tol, max_iter=ds.max_iter)
        iterations += res.iterations
        z = np.clip(res.z, *bounds)  # IPOPT may pass a bound by its relaxation (1e-8)
        ts, K = _knots(lay, z)
        tr = _replay(p, ts, K, o.rate, float(lim.max_time), options)
        target4 = np.array([tg[0], tg[1], tg[2], float(heading)])
        err = _terminal_errors(p, tr, target4)
        rep = _limit_report(p, tr, float(z[-1]), lim)
        prog.say(
            f"jsphere plan: solve {rounds}: {res.status} after {res.iterations} iterations, T = {z[-1]:.4f} s, "
            f"replay misses by {1e3 * err['position_m']:.3f} mm"
        )
        if not res.success or _settled(err, rep, o, heading):
            break
        for name in shrink:
            r = rep.get(name)
            if r is not None and r["max"] > r["limit"]:
                shrink[name] *= (r["limit"] / r["max"]) * (1.0 - 2e-4)
        aim[0] -= err["final"][0] - tg[0]
        aim[1] -= err["final"][1] - tg[1]
        if heading:
            aim[2] -= math.remainder(err["final"][2] - tg[2], 2 * math.pi)
        rates -= np.concatenate([np.asarray(tr.omega[-1]), np.asarray(tr.Omega[-1])])
    shortfall = missed(o, heading, err, rep)
    if not res.success:
        shortfall.insert(0, f"the direct search ended {res.status.replace('_', ' ')} after {iterations} iterations")
    plan = manoeuvre_plan(
        p,
        None,
        tr,
        o.rate,
        target4,
        err,
        rep,
        shortfall,
        iterations={"ipopt": iterations, "solves": rounds},
        elapsed_s=time.perf_counter() - t0,
        loss=float(res.objective),
        restarts=1,
        at_rest=err["speed_m_s"] <= o.tol_speed,
    )
    return dataclasses.replace(plan, gaits=[], profile=(ts, K), family="direct")


def _settled(err: dict, rep: dict, o: PlanOptions, heading: bool) -> bool:
    """The replay keeps every limit and lands well within the tolerances."""
    return (
        all(r["ok"] for r in rep.values())
        and err["position_m"] <= 0.2 * o.tol_position
        and err["speed_m_s"] <= 0.2 * o.tol_speed
        and (not heading or err["heading_rad"] <= 0.2 * o.tol_heading)
    )
